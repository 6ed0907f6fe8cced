"""The bring-up listeners' id table: the first MAX_IDS ids one by one, the rest together."""

from __future__ import annotations

from handctl.bringup.idcount import MAX_IDS, IdCounts


def test_ids_past_the_bound_are_counted_together_and_known_ones_go_on_counting() -> None:
    counts = IdCounts()
    assert not counts
    for fid in range(MAX_IDS + 10):
        counts.add(fid)
    counts.add(0)  # a known id keeps its own count
    counts.add(MAX_IDS + 3)  # an id past the bound stays among the others
    assert len(counts.by_id) == MAX_IDS
    assert counts.by_id[0] == 2
    assert counts.others == 11
    assert counts
