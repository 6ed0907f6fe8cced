"""The fault campaign's cases as tasks: the same results on a pool of worker processes as
here, in the campaign's order, with each case's log brought back from its worker."""

from __future__ import annotations

from pathlib import Path

import pytest

from handctl.config import HandConfig, load_hand
from handctl.executor import open_pool
from handctl.harness.campaign import PHASES, read_case_log, run_campaign, run_case

from ..conftest import ROOT


def test_cases_on_a_pool_equal_the_cases_here(hand: HandConfig, tmp_path: Path) -> None:
    injectors = ["tdt_offset"]
    here = run_campaign(hand, injectors=injectors)
    lines: list[str] = []
    with open_pool(2) as pool:
        there = run_campaign(
            hand, progress=lines.append, injectors=injectors, log_dir=tmp_path, executor=pool
        )
    assert there == here
    assert [(r.injector, r.phase) for r in there] == [(i, p) for i in injectors for p, _ in PHASES]
    assert len(lines) == len(there) and lines[0].startswith("tdt_offset")
    for r in there:
        log = read_case_log(tmp_path / f"{r.injector}-{r.phase}.mcap")
        assert r.logged
        assert log.complete and bool(log.faults) == bool(r.fault)


@pytest.mark.parametrize("name", ["planar_2f2j", "four_fingers_four_joints"])
def test_a_case_on_another_shape_of_hand_is_caught(name: str) -> None:
    """The campaign's recipe, targets and wire decoding come from the hand: on the planar
    hand and on four fingers of four joints a case runs, and its fault is caught and logged."""
    hand = load_hand(ROOT / "config" / "hands" / f"{name}.yaml")
    result = run_case(hand, "tdt_offset", "holding")
    assert result.fault == "TDT_MISMATCH" and result.unsafe_frames == 0
    assert result.logged and result.recovered
