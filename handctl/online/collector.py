"""The garbage collector during a run: never in the middle of a tick, still collecting.

CPython collects when allocations outnumber deallocations by a threshold, in whatever code
happens to allocate then: inside a tick's poll, between two command frames. A young collection
costs a few hundred µs on a busy host, an older one milliseconds, and a full one walks every
object the imports left behind (MuJoCo, NumPy, python-can: tens of ms), which alone is a
``LOOP_OVERRUN``. A lockstep run of the default recipe measured 132 young, 12 middle and one
full collection in 5,200 ticks, the full one 55 ms long.

So for the length of a run (``LoopCollector.running``):

- one full collection first, then everything alive is frozen (``gc.freeze``): the start-up
  heap is never walked again, so no later collection costs more than what the run itself
  allocated and kept;
- automatic collection is off;
- the loop calls ``after_tick`` once a tick has sent its frames and handed over its record:
  when enough container objects have accumulated (CPython's own young threshold), it collects
  there, the young generation and every tenth time the older ones too, as CPython would.

Cyclic garbage is still collected, at most a tick later than CPython would have, and only where
the tick's own work is done. Afterwards the collector is as it was (enabled or not, the
frozen objects handed back to the oldest generation).

A run at SCHED_FIFO settles its heap (``settle_heap``: the full collection and the freeze)
before it raises its priority, as docs/timing.md has all long start-up work done: the full
collection of ``running`` then walks only what was allocated since, not tens of ms of the
imports' objects at SCHED_FIFO, which alone ran past a soft ``RLIMIT_RTTIME`` of 20 ms (the
kernel's SIGXCPU, the run stopped before its first tick).
"""

from __future__ import annotations

import contextlib
import gc
from collections.abc import Iterator

#: Container objects allocated (net) before a young collection: CPython's default threshold.
YOUNG_THRESHOLD = 700
#: Young collections per collection of the middle generation, and middle per full, as CPython.
OLDER_EVERY = 10


def settle_heap() -> None:
    """One full collection, then everything alive frozen: what ``LoopCollector.running``
    does first, done before the priority is raised so that its own is short."""
    gc.collect()
    gc.freeze()


class LoopCollector:
    """Collections at the end of a tick only; see the module's docstring."""

    def __init__(self, young_threshold: int = YOUNG_THRESHOLD) -> None:
        self.young_threshold = young_threshold
        self.collections = [0, 0, 0]  # by generation, during the run
        self._young_since_middle = 0
        self._middle_since_full = 0
        self._active = False

    @contextlib.contextmanager
    def running(self) -> Iterator[LoopCollector]:
        """Automatic collection off and the start-up heap frozen, for the block."""
        was_enabled = gc.isenabled()
        gc.collect()
        gc.freeze()
        gc.disable()
        self._active = True
        try:
            yield self
        finally:
            self._active = False
            gc.unfreeze()
            if was_enabled:
                gc.enable()

    def after_tick(self) -> bool:
        """Collect now if CPython would have by now; a few integer comparisons otherwise.
        Whether it collected."""
        if not self._active or gc.get_count()[0] < self.young_threshold:
            return False
        generation = 0
        self._young_since_middle += 1
        if self._young_since_middle >= OLDER_EVERY:
            self._young_since_middle = 0
            generation = 1
            self._middle_since_full += 1
            if self._middle_since_full >= OLDER_EVERY:
                self._middle_since_full = 0
                generation = 2
        gc.collect(generation)
        self.collections[generation] += 1
        return True
