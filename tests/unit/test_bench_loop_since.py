"""The loop bench judges the host over the run proper: every kind of event the bare loop kept
(stalls, hiccups, slow pieces, slow switches) is cut at the run's start alike, so a start-up
burst of one kind cannot count while the same burst of another is left out."""

from __future__ import annotations

from handctl.hostcheck import ProbeRecord

from ..conftest import load_tool


def test_every_kind_of_event_is_cut_at_the_runs_start() -> None:
    ms = 1_000_000
    record = ProbeRecord(
        period_ns=ms,
        start_ns=0,
        end_ns=100 * ms,
        wakeups=100,
        lateness_hist_us={1: 100},
        lateness_max_ns=5 * ms,
        stalls=((3, 3 * ms, 8 * ms, 5), (60, 60 * ms, 64 * ms, 4)),
        work_reference_ns=5_000,
        slow=((4, 4 * ms, 4 * ms + 40_000, 40_000), (70, 70 * ms, 70 * ms + 50_000, 50_000)),
        hiccup_ns=200_000,
        hiccups=((5, 5 * ms, 5 * ms + 300_000), (80, 80 * ms, 80 * ms + 400_000)),
        switch_reference_ns=2_000,
        slow_switches=((6, 6 * ms, 6 * ms + 10_000, 9_000), (90, 90 * ms, 90 * ms + 1, 8_000)),
    )
    proper = load_tool("bench_loop").since(record, 50 * ms)
    assert proper.start_ns == 50 * ms
    assert [s[0] for s in proper.stalls] == [60]
    assert [s[0] for s in proper.slow] == [70]
    assert [h[0] for h in proper.hiccups] == [80]
    assert [w[0] for w in proper.slow_switches] == [90]
    assert proper.lateness_hist_us == record.lateness_hist_us
