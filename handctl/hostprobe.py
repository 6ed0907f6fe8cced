"""The bare timer loop of the timing check, a process of its own: it only waits for its timerfd.

What it measures is what the host does to any loop of that period, priority and CPU: the same
``PeriodicTimer`` and the same ``request_realtime`` as the control loop, and no work of
handctl's, so every microsecond of lateness is the kernel's, the hypervisor's or another
process's (like cyclictest of rt-tests). A loop that only waits sees the CPU taken away only
when that happens as it is due, and cannot see a CPU that runs slower for a while: so it also
keeps its wake-ups late by less than a stall (hiccups), and on each wake-up it runs a fixed,
calibrated piece of work (``WorkLog``) and keeps the wake-ups on which that took much longer
than usual, or on which its own passage through the kernel since the last piece (asleep on
its timer, switched out and in) cost much more CPU time than usual. It is a process and not
a thread because a thread of the control process would wait for the interpreter lock
whenever the control loop holds it, and take it from the loop every period.

``python -m handctl.hostprobe --period-ns N [--seconds S] [--record-ns T] [--priority P]
[--cpu C] [--no-lock-memory] [--hiccup-ns H] [--work-ns W] [--slow-factor F]`` runs until S
seconds have passed or SIGTERM/SIGINT comes, then writes one JSON object to stdout
(``handctl.hostcheck.ProbeRecord`` reads it): the wake-up lateness as a histogram of 1 µs
bins, every stall of at least T ns with its interval, every hiccup of at least H ns, every
slow piece of work with its interval and thread CPU time, and every slow switch (the kernel
passage before a wake-up) with the wake-up's interval and that CPU time.
"""

from __future__ import annotations

import argparse
import contextlib
import ctypes
import ctypes.util
import gc
import json
import os
import signal
import sys
import time
from array import array
from collections.abc import Callable
from pathlib import Path
from typing import Any

from handctl.hostfacts import ordinary_scheduling
from handctl.online.clock import StallLog, request_realtime
from handctl.online.timerfd import PeriodicTimer
from handctl.parent_death import stop_on_signals

#: µs: the histogram's last bin collects every wake-up later than this (the maximum is exact)
HIST_RANGE_US = 20_000
#: ns: the piece of work each wake-up does by default (1 % of a CPU at two wake-ups a ms)
WORK_NS = 5_000
#: A piece of work this many times its usual wall time is slow. Pieces beside a busy control
#: loop take up to about twice the usual (a cache the loop keeps cold); a CPU the hypervisor
#: shares takes 3 to 100 times (docs/timing.md).
SLOW_FACTOR = 3.0
#: Wake-ups whose work sets the usual time (its median): 0.1 s at 2 kHz.
REFERENCE_WAKEUPS = 200
_USER_HZ = os.sysconf("SC_CLK_TCK")
_PR_SET_PDEATHSIG = 1


def steal_ms(cpus: set[int] | None = None) -> float:
    """CPU time the hypervisor gave to someone else (``steal`` in /proc/stat), in ms, summed
    over ``cpus`` (None: the whole machine); 0 where the kernel does not count it."""
    total = 0
    try:
        lines = Path("/proc/stat").read_text().splitlines()
    except OSError:
        return 0.0
    for line in lines:
        name, *fields = line.split()
        if not name.startswith("cpu"):
            break
        wanted = name == "cpu" if cpus is None else name[3:].isdigit() and int(name[3:]) in cpus
        if wanted and len(fields) > 7:
            total += int(fields[7])
    return total * 1000 / _USER_HZ


def work(iterations: int) -> int:
    """The fixed piece of work: interpreted integer arithmetic, like the control loop's own
    Python, so that what slows the loop down slows it down alike."""
    x = 0
    for i in range(iterations):
        x = (x + i * 7) & 0xFFFF
    return x


def calibrate(work_ns: int) -> int:
    """Iterations of ``work`` that take about ``work_ns`` of wall time here (the fastest of a
    few tries: a try the host interrupted would make the piece too short)."""
    iterations = 16
    while True:
        best = min(_timed(iterations) for _ in range(5))
        if best >= work_ns or iterations >= 1 << 24:
            return max(1, iterations * work_ns // max(1, best))
        iterations *= 2


def _timed(iterations: int) -> int:
    t0 = time.perf_counter_ns()
    work(iterations)
    return time.perf_counter_ns() - t0


class WorkLog:
    """The wake-ups on which a cost of the bare loop's was high: ``(index, start_ns, end_ns,
    cpu_ns)``, an interval and the thread CPU time in it.

    Two costs are kept this way: the wall time of the piece of work (``by_cpu`` False), and
    the thread CPU time of the bare loop's passage through the kernel between two pieces
    (``by_cpu`` True: going to sleep on its timer, being switched out and back in, returning
    from the read), whose interval runs from the wake-up's deadline to the wake-up.

    The usual cost (``reference_ns``) is the median of the first ``REFERENCE_WAKEUPS``,
    measured in place (at the probe's priority, on its CPU, beside what runs there), not
    before: a cache the neighbours keep cold is the usual, not a slow CPU. From then on a cost
    of at least ``factor`` times the usual is kept, in a ``StallLog`` (arrays allocated once;
    past its capacity only counted) whose fourth column holds the CPU time.
    """

    def __init__(self, factor: float, capacity: int = 1 << 16, by_cpu: bool = False) -> None:
        self.factor = factor
        self.by_cpu = by_cpu
        self.first = array("q", bytes(8 * REFERENCE_WAKEUPS))
        self.count = 0
        self.reference_ns = 0
        self.threshold_ns = 1 << 62  # nothing is slow until the usual cost is known
        self.kept = StallLog(threshold_ns=0, capacity=capacity)

    @property
    def overflow(self) -> int:
        return self.kept.overflow

    def add(self, index: int, start_ns: int, end_ns: int, cpu_ns: int) -> None:
        cost = cpu_ns if self.by_cpu else end_ns - start_ns
        count = self.count
        self.count = count + 1
        if count < REFERENCE_WAKEUPS:
            self.first[count] = cost
            if count + 1 == REFERENCE_WAKEUPS:
                self.reference_ns = sorted(self.first)[REFERENCE_WAKEUPS // 2]
                self.threshold_ns = max(1, round(self.factor * self.reference_ns))
            return
        if cost >= self.threshold_ns:
            self.kept.add(index, start_ns, end_ns, cpu_ns)

    def rows(self) -> list[tuple[int, int, int, int]]:
        return self.kept.rows()


def probe(
    period_ns: int,
    seconds: float | None,
    record_ns: int,
    stop: list[bool],
    become_realtime: Callable[[], list[str]],
    work_ns: int = WORK_NS,
    slow_factor: float = SLOW_FACTOR,
    hiccup_ns: int | None = None,
) -> dict[str, Any]:
    """The loop itself: wait, note the lateness, time the piece of work and the switch before
    it (neither if ``work_ns`` is 0), until ``seconds`` or ``stop``.

    Wake-ups late by ``hiccup_ns`` or more, but less than a stall (``record_ns``), are kept
    apart as hiccups (none if None): the CPU taken away for less than the stall threshold, many
    times in a row, holds a loop as surely as one stall does.

    Everything is allocated, and the C library found, before ``become_realtime`` raises the
    priority: at SCHED_FIFO above the control loop, every millisecond of set-up would be one
    the loop beside it could not run.
    """
    hist = [0] * (HIST_RANGE_US + 1)
    stalls = StallLog(record_ns)
    hiccups = StallLog(hiccup_ns if hiccup_ns is not None else record_ns)
    hiccup_below = record_ns if hiccup_ns is not None else 0
    late_max = 0
    wakeups = 0
    expirations = 0
    PeriodicTimer(period_ns).close()  # loads what the timer needs
    iterations = calibrate(work_ns) if work_ns > 0 else 0
    slow = WorkLog(slow_factor)
    switches = WorkLog(slow_factor, by_cpu=True)
    clock = time.monotonic_ns
    cpu_clock = time.thread_time_ns
    refused = become_realtime()
    cpus = os.sched_getaffinity(0)
    steal_before = steal_ms(cpus)
    timer = PeriodicTimer(period_ns)
    last_cpu = cpu_clock()  # where the last piece of work ended, in thread CPU time
    try:
        start = timer.start_ns
        end = None if seconds is None else start + round(seconds * 1e9)
        while not stop[0]:
            n = timer.read()
            now = time.monotonic_ns()
            expirations += n
            due = start + expirations * period_ns
            late = now - due
            b = late // 1000
            hist[b if 0 <= b < HIST_RANGE_US else (0 if b < 0 else HIST_RANGE_US)] += 1
            late_max = max(late_max, late)
            stalls.add(wakeups, due - (n - 1) * period_ns, now, n - 1)
            if n == 1 and late < hiccup_below:  # a stall's own lateness is the stall's
                hiccups.add(wakeups, due, now, 0)
            if iterations:
                c0 = cpu_clock()
                if n == 1 and late < record_ns:  # a stall's switch is the stall's
                    switches.add(wakeups, due, now, c0 - last_cpu)
                w0 = clock()
                work(iterations)
                w1 = clock()
                last_cpu = cpu_clock()
                slow.add(wakeups, w0, w1, last_cpu - c0)
            wakeups += 1
            if end is not None and now >= end:
                break
        stopped = time.monotonic_ns()
    finally:
        timer.close()
    got = scheduler()
    _step_down()  # what is left is bookkeeping, which must not hold the loop on this CPU
    return {
        "period_ns": period_ns,
        "record_ns": record_ns,
        "start_ns": start,
        "end_ns": stopped,
        "wakeups": wakeups,
        "expirations": expirations,
        "lateness_max_ns": late_max,
        "lateness_hist_us": {str(i): c for i, c in enumerate(hist) if c},
        "stalls": [list(row) for row in stalls.rows()],
        "stalls_overflow": stalls.overflow,
        "hiccup_ns": hiccup_ns or 0,
        "hiccups": [list(row[:3]) for row in hiccups.rows()],
        "hiccups_overflow": hiccups.overflow,
        "steal_ms": round(steal_ms(cpus) - steal_before, 1),
        "work": {
            "iterations": iterations,
            "pieces": slow.count,
            "reference_ns": slow.reference_ns,
            "slow_factor": slow_factor,
            "slow": [list(row) for row in slow.rows()],
            "slow_overflow": slow.overflow,
            "switch_reference_ns": switches.reference_ns,
            "slow_switches": [list(row) for row in switches.rows()],
            "slow_switches_overflow": switches.overflow,
        },
        "refused": refused,
        "scheduler": got,
    }


def _step_down() -> None:
    """Back to the ordinary scheduler once the loop ends. At SCHED_FIFO above the control
    loop, building and writing the record (milliseconds of Python) would be a stall of the
    very loop it was measuring, at the moment that loop is stopping the hand."""
    with contextlib.suppress(OSError, AttributeError):
        os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))


def scheduler() -> dict[str, Any]:
    """What the process actually got (not what it asked for)."""
    policy = os.sched_getscheduler(0)
    names = {
        getattr(os, n): n
        for n in ("SCHED_OTHER", "SCHED_FIFO", "SCHED_RR", "SCHED_BATCH", "SCHED_IDLE")
        if hasattr(os, n)
    }
    locked_kb = 0
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmLck:"):
                locked_kb = int(line.split()[1])
    except OSError:
        pass
    return {
        "policy": names.get(policy, str(policy)),
        "priority": os.sched_getparam(0).sched_priority,
        "cpus": sorted(os.sched_getaffinity(0)),
        "memory_locked_kb": locked_kb,
    }


def _end_with_parent(parent: int) -> bool:
    """SIGTERM when the process that started this one (``parent``) dies: a bare loop at
    SCHED_FIFO must not outlive a run killed with SIGKILL. False if it is gone already."""
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or None, use_errno=True)
        libc.prctl(_PR_SET_PDEATHSIG, signal.SIGTERM)
    except (OSError, AttributeError):
        pass
    return os.getppid() == parent


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m handctl.hostprobe", description=__doc__.split("\n\n")[0]
    )
    parser.add_argument("--period-ns", type=int, required=True)
    parser.add_argument("--seconds", type=float, help="default: until SIGTERM or SIGINT")
    parser.add_argument("--record-ns", type=int, help="keep stalls this long (default: the period)")
    parser.add_argument(
        "--priority", type=int, help="SCHED_FIFO priority (default: the ordinary scheduler)"
    )
    parser.add_argument("--cpu", type=int, help="pin to this CPU")
    parser.add_argument("--no-lock-memory", action="store_true")
    parser.add_argument("--parent-pid", type=int, help="end when this process ends")
    parser.add_argument(
        "--hiccup-ns",
        type=int,
        help="also keep wake-ups this late that are no stall (default: none)",
    )
    parser.add_argument(
        "--work-ns",
        type=int,
        default=WORK_NS,
        help=f"the piece of work timed on each wake-up, ns (default {WORK_NS}; 0: none)",
    )
    parser.add_argument(
        "--slow-factor",
        type=float,
        default=SLOW_FACTOR,
        help=f"a piece this many times its usual time is slow (default {SLOW_FACTOR:g})",
    )
    args = parser.parse_args(argv)
    stop = stop_on_signals()
    if args.parent_pid is not None and not _end_with_parent(args.parent_pid):
        return 0
    # What it inherited is not what it measures: under a caller's ``chrt -f 90`` a probe
    # without --priority ran at SCHED_FIFO 90, above the loop it was to share the host with,
    # and one whose --priority was refused stayed there. The ordinary scheduler, unless
    # ``become_realtime`` gets it the priority asked for.
    ordinary_scheduling(0)
    # Before the priority is raised: a collection, like locking memory, at SCHED_FIFO would
    # hold the control loop on this CPU for milliseconds.
    gc.collect()
    gc.freeze()
    gc.disable()

    def become_realtime() -> list[str]:
        if args.priority is not None:
            return request_realtime(
                args.priority, cpu=args.cpu, lock_memory=not args.no_lock_memory
            )
        if args.cpu is not None:
            try:
                os.sched_setaffinity(0, {args.cpu})
            except (OSError, ValueError) as exc:
                return [f"pinning to CPU {args.cpu} refused ({exc})"]
        return []

    result = probe(
        args.period_ns,
        args.seconds,
        args.record_ns or args.period_ns,
        stop,
        become_realtime,
        args.work_ns,
        args.slow_factor,
        args.hiccup_ns,
    )
    json.dump(result, sys.stdout)
    sys.stdout.write("\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
