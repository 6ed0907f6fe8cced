"""The loop's per-tick accounting: bounded memory however long the run, the last ticks kept one
by one in order, and the whole run's percentiles from its histograms."""

from __future__ import annotations

import numpy as np
import pytest

from handctl.online.tickstats import BLOCK, TickStats, percentile_us


def _feed(stats: TickStats, lateness_ns: np.ndarray) -> None:
    for k, late in enumerate(lateness_ns):
        stats.store(int(late), k % 7 == 0, (int(late), 1000, 2000, 3000, 4000))


def test_a_short_run_keeps_every_tick() -> None:
    stats = TickStats(5, window=4 * BLOCK)
    late = np.arange(3000) * 1000
    _feed(stats, late)
    w = stats.result()
    assert w.first_tick == 0
    assert np.array_equal(w.lateness_ns, late)
    assert int(w.missed.sum()) == len(range(0, 3000, 7))
    assert w.stage_ns.shape == (3000, 5)
    assert int(w.lateness_hist.sum()) == 3000


def test_a_long_run_keeps_the_last_window_in_order_and_memory_is_bounded() -> None:
    window = 2 * BLOCK
    stats = TickStats(5, window=window)
    rng = np.random.default_rng(3)
    late = rng.integers(0, 400_000, size=10 * window + 123)
    _feed(stats, late[: 3 * window])
    sizes = (stats._lateness.nbytes, stats._stages.nbytes, stats._late_hist.nbytes)
    assert sizes[0] == window * 8  # all of it from the start
    _feed(stats, late[3 * window :])  # carries on from tick 3 * window: the pattern shifts
    assert (stats._lateness.nbytes, stats._stages.nbytes, stats._late_hist.nbytes) == sizes
    w = stats.result()
    assert w.first_tick == late.size - window
    assert np.array_equal(w.lateness_ns, late[-window:])
    assert int(w.lateness_hist.sum()) == late.size  # the histograms cover the whole run
    assert w.lateness_max_ns == int(late.max())
    for q in (50, 99, 99.9):
        exact = float(np.percentile(late // 1000, q, method="inverted_cdf"))
        assert percentile_us(w.lateness_hist, q) == pytest.approx(exact, abs=1.0)
    assert percentile_us(w.stage_hist[1], 99) == 1.0


def test_the_result_can_be_taken_twice_and_storing_goes_on() -> None:
    stats = TickStats(5, window=BLOCK)
    _feed(stats, np.full(BLOCK // 2 + 5, 7000))
    first = stats.result()
    _feed(stats, np.full(BLOCK * 2, 9000))
    second = stats.result()
    assert int(first.lateness_hist.sum()) == BLOCK // 2 + 5
    assert int(second.lateness_hist.sum()) == BLOCK // 2 + 5 + 2 * BLOCK
    assert (
        int(second.lateness_hist[7]) == BLOCK // 2 + 5 and int(second.lateness_hist[9]) == 2 * BLOCK
    )


def test_a_window_not_made_of_blocks_is_refused() -> None:
    with pytest.raises(ValueError, match="multiple"):
        TickStats(5, window=BLOCK + 1)


def test_an_empty_histogram_has_zero_percentiles() -> None:
    assert percentile_us(np.zeros(10, dtype=np.int64), 99) == 0.0
