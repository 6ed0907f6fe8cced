"""The bare loop's slow pieces of work (``hostprobe.WorkLog``): the usual time is the median of
the first pieces, measured in place; from then on a piece of ``factor`` times it is kept."""

from __future__ import annotations

from handctl.hostprobe import REFERENCE_WAKEUPS, WorkLog


def test_a_piece_slower_than_factor_times_the_usual_is_kept() -> None:
    log = WorkLog(factor=3.0, capacity=2)
    for k in range(REFERENCE_WAKEUPS):  # the usual pieces, and one the host held during them
        log.add(k, 0, 1_000 if k != 7 else 50_000, 900)
    assert log.reference_ns == 1_000 and log.rows() == []
    log.add(500, 10, 10 + 2_999, 2_000)  # not slow
    log.add(501, 20, 20 + 3_000, 2_800)
    log.add(502, 30, 30 + 9_000, 8_500)
    log.add(503, 40, 40 + 9_000, 8_500)  # past the capacity: counted only
    assert log.rows() == [(501, 20, 3_020, 2_800), (502, 30, 9_030, 8_500)]
    assert log.overflow == 1 and log.count == REFERENCE_WAKEUPS + 4


def test_a_switch_is_judged_by_its_cpu_time_not_its_wall_time() -> None:
    # The switch's interval runs from the deadline to the wake-up, most of it asleep: only
    # the CPU time the bare loop spent on its way through the kernel says it was slow.
    log = WorkLog(factor=3.0, by_cpu=True)
    for k in range(REFERENCE_WAKEUPS):
        log.add(k, 0, 40_000 + 500 * k, 20_000)
    assert log.reference_ns == 20_000
    log.add(500, 1_000, 1_000 + 400_000, 59_000)  # late by a long wall time, not slow
    log.add(501, 2_000, 2_000 + 40_000, 60_000)
    assert log.rows() == [(501, 2_000, 42_000, 60_000)]
