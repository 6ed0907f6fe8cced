"""Per-tick accounting of the loop (lateness, missed ticks, CPU time per stage) in bounded memory.

A run may last hours, at 1 kHz: keeping every tick's 52 bytes grows the control process by
about 190 MB an hour. So the last ``window`` ticks are kept tick by tick, in arrays allocated
and written once at the start (what a benchmark or a
test inspects; the MCAP log has every tick anyway), and the whole run is kept as histograms of
1 µs bins, from which the summary's percentiles come. Blocks of ``BLOCK`` ticks are folded into
the histograms as they fill, so the work per tick stays a few array stores and no tick pays for
more than one block's fold (about 30 µs).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: The stages of a control tick, in the order the loop times them (``handctl.online.loop``).
#: ``feedback`` is the recipe phase's feedback and the soft-limit guard (``runner.feedback``);
#: it comes last so that the first five keep their places in recordings and benchmarks
STAGES = ("poll", "recipe", "safety", "send", "record", "feedback")
#: ticks folded into the histograms at a time
BLOCK = 1024
#: ticks kept one by one: 65 s at 1 kHz, 3.4 MB
DEFAULT_WINDOW = 1 << 16
#: µs, the histograms' range: a value beyond it counts in the last bin (its maximum is exact)
HIST_RANGE_US = 20_000


@dataclass(frozen=True)
class TickWindow:
    """The accounting of a run: the last ticks one by one, and the whole run as histograms."""

    first_tick: int  # loop tick index of ``lateness_ns[0]``
    lateness_ns: np.ndarray
    missed: np.ndarray  # ticks missed just before each tick
    stage_ns: np.ndarray  # (ticks, stages)
    lateness_hist: np.ndarray  # counts per µs of lateness, whole run
    stage_hist: np.ndarray  # (stages, counts per µs of CPU time), whole run
    lateness_max_ns: int


class TickStats:
    """Preallocated and bounded; ``store`` is the only call on the hot path."""

    def __init__(self, stages: int, window: int = DEFAULT_WINDOW) -> None:
        if window % BLOCK or window <= 0:
            raise ValueError(f"window must be a multiple of {BLOCK} ticks, not {window}")
        self.window = window
        self.ticks = 0
        # Every page written now (``np.full``, not the lazily mapped ``np.zeros``): the
        # process's memory is what it will be for the whole run from the first tick on.
        self._lateness = np.full(window, 0, dtype=np.int64)
        self._missed = np.full(window, 0, dtype=np.int32)
        self._stages = np.full((window, stages), 0, dtype=np.int64)
        self._late_hist = np.full(HIST_RANGE_US + 1, 0, dtype=np.int64)
        self._stage_hist = np.full((stages, HIST_RANGE_US + 1), 0, dtype=np.int64)
        self._stage_offset = np.arange(stages) * (HIST_RANGE_US + 1)  # row starts, flat
        self._late_max = 0
        self._folded = 0  # ticks already in the histograms

    def store(self, lateness_ns: int, missed: int, stages: tuple[int, ...]) -> None:
        n = self.ticks
        i = n % self.window
        self._lateness[i] = lateness_ns
        self._missed[i] = missed
        self._stages[i] = stages
        self.ticks = n + 1
        if self.ticks % BLOCK == 0:
            self._fold(self.ticks)

    def _fold(self, upto: int) -> None:
        """Add ticks ``_folded .. upto`` to the histograms (they are still in the window)."""
        if upto <= self._folded:
            return
        a = self._folded % self.window
        b = a + (upto - self._folded)
        late = self._lateness[a:b]
        self._late_max = max(self._late_max, int(late.max()))
        np.add.at(self._late_hist, _bins(late), 1)
        # every stage in one call, through the flat view of the (stages, bins) histogram
        np.add.at(self._stage_hist.reshape(-1), _bins(self._stages[a:b]) + self._stage_offset, 1)
        self._folded = upto

    def result(self) -> TickWindow:
        """The window in tick order and the histograms of the whole run (copies)."""
        self._fold(self.ticks)
        n = self.ticks
        if n <= self.window:
            order = slice(0, n)
            lateness, missed, stages = (
                self._lateness[order],
                self._missed[order],
                self._stages[order],
            )
        else:
            start = n % self.window
            lateness = np.roll(self._lateness, -start)
            missed = np.roll(self._missed, -start)
            stages = np.roll(self._stages, -start, axis=0)
        return TickWindow(
            max(0, n - self.window),
            lateness.copy(),
            missed.copy(),
            stages.copy(),
            self._late_hist.copy(),
            self._stage_hist.copy(),
            self._late_max,
        )


def histogram_us(values_ns: np.ndarray) -> np.ndarray:
    """The 1 µs histogram of ``values_ns`` that a run keeps (``TickStats``): a replay's
    percentiles from it are the run's own (numpy's interpolating percentile gave a real-time
    log's lateness p99 as 282.39 µs where its run had said 297)."""
    counts: np.ndarray = np.bincount(
        _bins(np.asarray(values_ns, dtype=np.int64)), minlength=HIST_RANGE_US + 1
    )
    return counts


def _bins(values_ns: np.ndarray) -> np.ndarray:
    bins: np.ndarray = np.minimum(np.maximum(values_ns, 0) // 1000, HIST_RANGE_US)
    return bins


def percentile_us(hist: np.ndarray, q: float) -> float:
    """The ``q``-th percentile (0..100) of a 1 µs histogram, in µs (a bin's lower edge);
    0 for an empty one."""
    total = int(hist.sum())
    if total == 0:
        return 0.0
    rank = max(1, int(np.ceil(q / 100.0 * total)))
    return float(np.searchsorted(np.cumsum(hist), rank))
