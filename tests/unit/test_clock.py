"""Clocks: the timerfd counts the ticks a stalled loop slept through; lockstep steps the peer
exactly once per tick."""

from __future__ import annotations

import asyncio
import resource
import subprocess
import sys
import time
from pathlib import Path

import pytest

from handctl.online.clock import (
    USUAL_SAMPLE_EVERY,
    LockstepClock,
    RealtimeClock,
    StallLog,
    UsualWork,
)
from handctl.online.timerfd import PeriodicTimer


async def test_realtime_ticks_are_consecutive_and_count_missed_ones() -> None:
    clock = RealtimeClock(0.001)
    try:
        first = await clock.wait_tick()
        second = await clock.wait_tick()
        assert (first.tick, second.tick) == (0, 1)
        assert second.scheduled_ns - first.scheduled_ns == (second.missed + 1) * 1_000_000
        time.sleep(0.006)  # stall the loop: at least five expirations pass unseen
        late = await clock.wait_tick()
        assert late.missed >= 4
        assert late.lateness_ns >= 0
        assert late.scheduled_ns >= second.scheduled_ns + (late.missed + 1) * 1_000_000
        # The stall is kept with the interval the loop was late for, to be laid beside the
        # host's: from the oldest deadline it slept through to the wake-up.
        tick, due, wake, missed = clock.stalls.rows()[-1]
        assert (tick, missed, wake) == (late.tick, late.missed, late.now_ns)
        assert due == late.scheduled_ns - late.missed * 1_000_000
    finally:
        clock.close()


def _burn_cpu(ns: int) -> None:
    end = time.thread_time_ns() + ns
    while time.thread_time_ns() < end:
        pass


async def test_a_stall_right_after_a_stall_carries_the_cpu_time_of_the_tick_between() -> None:
    clock = RealtimeClock(0.001)
    try:
        await clock.wait_tick()
        time.sleep(0.003)  # held, not working: at least two expirations pass unseen
        held = await clock.wait_tick()
        _burn_cpu(3_000_000)  # the tick after it works for three periods of thread CPU
        slow = await clock.wait_tick()
        assert held.missed >= 1 and slow.missed >= 1
        work = clock.stalls.work_ns()
        assert work[slow.tick] >= 3_000_000
        # The tick before ``held`` slept: whether or not its own wake-up was late, it took
        # little of the thread's CPU time.
        assert work.get(held.tick, 0) < 3_000_000
    finally:
        clock.close()


async def _sampled_run(ticks: int, slept_tick: int) -> UsualWork:
    """``ticks`` ticks of 0.2 ms of CPU time each, but tick ``slept_tick``, which sleeps
    three periods (so the wake-up after it is late)."""
    clock = RealtimeClock(0.001)
    try:
        for _ in range(ticks):
            tk = await clock.wait_tick()
            if tk.tick == slept_tick:
                time.sleep(0.003)
            else:
                _burn_cpu(200_000)
        return clock.usual
    finally:
        clock.close()


async def test_the_usual_tick_is_measured_from_one_on_time_wake_up_to_the_next() -> None:
    # Whether two sampled wake-ups in a row are on time depends on the machine's load: a
    # run with fewer than two samples is tried again.
    for _ in range(5):
        usual = await _sampled_run(6 * USUAL_SAMPLE_EVERY, 2 * USUAL_SAMPLE_EVERY)
        if usual.count >= 2:
            break
    sampled = list(usual.tick[: usual.count])
    assert usual.count >= 2
    assert all(t % USUAL_SAMPLE_EVERY == 0 for t in sampled)
    assert 2 * USUAL_SAMPLE_EVERY not in sampled  # the tick whose next wake-up was late
    assert min(usual.cpu_ns[: usual.count]) >= 200_000  # what each tick burned, at least
    assert usual.median_ns(since_tick=sampled[-1] + 1) == 0


def test_the_usual_is_the_median_of_the_newest_samples_from_a_tick_on() -> None:
    usual = UsualWork(capacity=4)
    assert usual.median_ns() == 0
    for tick, cpu in [(0, 10), (16, 900), (32, 300), (48, 200), (64, 400), (80, 100)]:
        usual.add(tick, cpu)
    # the first two are overwritten: 300, 200, 400, 100 are kept
    assert usual.median_ns() == 300
    assert usual.median_ns(since_tick=48) == 200  # of 200, 400, 100
    assert usual.median_ns(since_tick=81) == 0


def test_a_full_stall_log_counts_what_it_cannot_keep() -> None:
    log = StallLog(threshold_ns=500, capacity=2)
    log.add(1, 0, 400, 0)  # shorter than the threshold: not a stall
    log.add(2, 0, 2_000, 1)
    log.add(5, 10_000, 13_000, 2)
    log.add(9, 20_000, 24_000, 3)
    assert log.rows() == [(2, 0, 2_000, 1), (5, 10_000, 13_000, 2)]
    assert (log.overflow, log.overflow_missed) == (1, 3)
    assert log.work_ns() == {}
    log = StallLog(threshold_ns=500, work=True)
    log.add(2, 0, 2_000, 1, cpu_ns=-1)
    log.add(3, 3_000, 5_000, 1, cpu_ns=300)
    assert log.work_ns() == {3: 300}


async def test_lockstep_steps_the_peer_once_per_tick() -> None:
    steps: list[int] = []
    clock = LockstepClock(0.001, lambda: steps.append(len(steps)))
    ticks = [await clock.wait_tick() for _ in range(5)]
    assert len(steps) == 5
    assert [t.tick for t in ticks] == [0, 1, 2, 3, 4]
    assert [t.scheduled_ns for t in ticks] == [1_000_000 * (k + 1) for k in range(5)]
    assert all(t.missed == 0 and t.lateness_ns == 0 for t in ticks)
    assert clock.now_ns() == 5_000_000


def test_blocking_timer_reports_expirations() -> None:
    with PeriodicTimer(1_000_000) as timer:
        assert timer.read() >= 1
        time.sleep(0.0035)
        assert timer.read() >= 3


def _unprivileged() -> None:
    """In the child: no real-time priority and almost no lockable memory."""
    resource.setrlimit(resource.RLIMIT_RTPRIO, (0, 0))
    resource.setrlimit(resource.RLIMIT_MEMLOCK, (65536, 65536))


# Root ignores those limits through its capabilities: the child drops them all first (capset),
# so the refusal path is exercised whoever runs the tests.
_CHILD = """
import ctypes
class Header(ctypes.Structure):
    _fields_ = [("version", ctypes.c_uint32), ("pid", ctypes.c_int)]
class Data(ctypes.Structure):
    _fields_ = [("effective", ctypes.c_uint32), ("permitted", ctypes.c_uint32),
                ("inheritable", ctypes.c_uint32)]
libc = ctypes.CDLL(None, use_errno=True)
libc.capset(ctypes.byref(Header(0x20080522, 0)), (Data * 2)())
from handctl.online.clock import request_realtime
for line in request_realtime():
    print(line)
"""


def test_realtime_request_says_clearly_what_was_refused() -> None:
    done = subprocess.run(
        [sys.executable, "-c", _CHILD],
        capture_output=True,
        text=True,
        timeout=60,
        preexec_fn=_unprivileged,
        check=False,
        cwd=Path(__file__).resolve().parents[2],
    )
    assert done.returncode == 0, done.stderr
    lines = done.stdout.splitlines()
    assert any(
        line.startswith("SCHED_FIFO priority 80 refused") and "rtprio" in line for line in lines
    ), lines
    assert any(line.startswith("locking memory refused") and "memlock" in line for line in lines), (
        lines
    )


def test_collector_paused_turns_automatic_collection_off_and_back_on() -> None:
    import gc

    from handctl.online.clock import collector_paused

    assert gc.isenabled()
    with collector_paused():
        assert not gc.isenabled()  # no full pass can hold the simulated hand's node timer
    assert gc.isenabled()


_HYGIENE_CHILD = """
import ctypes, os, sys
from handctl.online.clock import HEAP_RESERVE, request_realtime
class Mallinfo2(ctypes.Structure):
    _fields_ = [(n, ctypes.c_size_t) for n in ("arena", "ordblks", "smblks", "hblks", "hblkhd",
                                               "usmblks", "fsmblks", "uordblks", "fordblks",
                                               "keepcost")]
libc = ctypes.CDLL(None)
libc.mallinfo2.restype = Mallinfo2
cpu = max(os.sched_getaffinity(0))
request_realtime(1, cpu=cpu, prefault_memory=sys.argv[1] == "1")
# The heap kept what the prefault touched: glibc neither trimmed it nor used mmap for it.
print(os.sched_getaffinity(0) == {cpu}, libc.mallinfo2().fordblks >= HEAP_RESERVE)
print(request_realtime(1, cpu=4096)[0])
"""


def _hygiene_child(prefault: bool) -> list[str]:
    done = subprocess.run(
        [sys.executable, "-c", _HYGIENE_CHILD, "1" if prefault else "0"],
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
        cwd=Path(__file__).resolve().parents[2],
    )
    assert done.returncode == 0, done.stderr
    return done.stdout.splitlines()


def test_realtime_pins_the_cpu_and_keeps_a_prefaulted_heap() -> None:
    granted, refusal = _hygiene_child(prefault=True)
    assert granted == "True True"  # pinned (no privilege needed), heap reserve kept
    assert refusal.startswith("pinning to CPU 4096 refused")
    assert _hygiene_child(prefault=False)[0] == "True False"


async def test_a_timer_callback_that_raises_ends_the_wait_with_its_exception() -> None:
    """The timer's callback raised: asyncio logged it and called it again at once, as the
    timer stayed readable, thousands of times a second, and the wait never ended (the run
    found the clock silent 2 s later). The wait now raises the callback's exception, and the
    callback is off the loop."""
    loop = asyncio.get_running_loop()
    logged: list[dict[str, object]] = []
    loop.set_exception_handler(lambda _loop, context: logged.append(context))
    clock = RealtimeClock(0.001)
    try:
        await clock.wait_tick()
        assert clock._timer is not None

        def broken() -> int:
            raise OSError(9, "Bad file descriptor")

        clock._timer.read = broken  # type: ignore[method-assign]
        with pytest.raises(OSError, match="Bad file descriptor"):
            await asyncio.wait_for(clock.wait_tick(), timeout=5.0)
        with pytest.raises(OSError, match="Bad file descriptor"):  # and every wait after
            await asyncio.wait_for(clock.wait_tick(), timeout=5.0)
        await asyncio.sleep(0.01)  # ten periods: a callback still on the loop would run
        assert logged == []
    finally:
        clock.close()
