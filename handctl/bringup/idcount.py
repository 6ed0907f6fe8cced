"""Frames counted by id, for a fixed number of ids: a listener on a bus it does not own.

Why: ``monitor`` and ``nodes`` kept every id they saw. A babbling device or a flood of random
ids (tens of thousands a second) grew their tables without end: ``monitor``'s snapshot held
89 000 ids (2.2 MB a line) after 30 s, and ``nodes`` printed 35 000 lines, burying the rows
that matter. The first ``MAX_IDS`` ids are counted one by one; the frames of any later id are
counted together.
"""

from __future__ import annotations

from collections import Counter

#: ids counted one by one (a hand of a few nodes has tens of them)
MAX_IDS = 64


class IdCounts:
    """Frames by id for the first ``MAX_IDS`` ids seen, the rest counted together."""

    def __init__(self) -> None:
        self.by_id: Counter[int] = Counter()
        #: frames of ids seen after the first ``MAX_IDS``
        self.others = 0

    def add(self, frame_id: int) -> None:
        if frame_id in self.by_id or len(self.by_id) < MAX_IDS:
            self.by_id[frame_id] += 1
        else:
            self.others += 1

    def __bool__(self) -> bool:
        return bool(self.by_id) or self.others > 0
