"""The garbage collector runs between ticks only (handctl/online/collector.py).

A lockstep run on the simulated hand whose tick hook leaves cyclic garbage every tick: every
collection during the run must come from the loop's own ``after_tick``, never from inside a
stage, and the garbage must still be collected. Afterwards the process's collector is as it
was.
"""

from __future__ import annotations

import asyncio
import gc
import sys
import weakref
from pathlib import Path
from typing import Any

from handctl.config import HandConfig
from handctl.online.clock import Tick
from handctl.online.collector import LoopCollector
from handctl.online.loop import Outcome
from handctl.online.recipes.loader import load_recipe

from .rig import CLOSE_AND_HOLD_1S, rig


class _Cycle:
    """An object that refers to itself: only the cyclic collector frees it."""

    def __init__(self) -> None:
        self.me = self
        self.payload = [[k] for k in range(30)]  # container objects, as a tick's garbage


def _collections_from(*codes: Any) -> tuple[list[Any], Any]:
    """A gc callback that notes, per collection, which of ``codes`` is on the stack (None
    if none is)."""
    seen: list[Any] = []

    def note(phase: str, info: dict[str, int]) -> None:
        if phase != "start":
            return
        frame = sys._getframe(1)
        while frame is not None and frame.f_code not in codes:
            frame = frame.f_back  # type: ignore[assignment]
        seen.append(None if frame is None else frame.f_code)

    return seen, note


def test_collections_happen_between_ticks_and_free_the_garbage(
    hand: HandConfig, tmp_path: Path
) -> None:
    path = tmp_path / "hold.yaml"
    path.write_text(CLOSE_AND_HOLD_1S)
    recipe = load_recipe(path, hand)
    freed: list[int] = []
    made = [0]

    def litter(tk: Tick) -> None:
        for _ in range(4):
            obj = _Cycle()
            weakref.finalize(obj, freed.append, tk.tick)
            made[0] += 1

    was_enabled = gc.isenabled()
    between = LoopCollector.after_tick.__code__
    before = LoopCollector.running.__wrapped__.__code__  # type: ignore[attr-defined]
    seen, note = _collections_from(between, before)
    with rig(hand, recipe) as r:
        r.runtime.tick_hooks.append(litter)
        gc.callbacks.append(note)
        try:
            result = asyncio.run(r.runtime.run())
        finally:
            gc.callbacks.remove(note)
    assert result.outcome is Outcome.COMPLETED
    # One full collection before the first tick, the rest between ticks. Python's own
    # collector may run once or twice before that, while asyncio sets up its loop (when is a
    # matter of how many objects the process made before this test): none is the run's.
    assert before in seen, seen
    start = seen.index(before)
    assert set(seen[:start]) <= {None}
    during = seen[start + 1 :]
    assert during, "the run's garbage was never collected"
    inside = sum(1 for code in during if code is not between)
    assert not inside, f"{inside} of {len(during)} collections inside a tick"
    assert len(freed) >= made[0] - 4 * 700  # all but what the last ticks left
    assert sum(r.runtime.collector.collections) == len(during)
    assert gc.isenabled() == was_enabled
    assert gc.get_freeze_count() == 0
