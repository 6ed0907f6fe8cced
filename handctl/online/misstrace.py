"""What the tick before each late wake-up did, so that a missed tick explains itself.

A missed tick is decided in the tick before it: that tick woke, did its work and went back to
sleep on the timer, and the next wake-up came late. Where its time went is one of three
things, and the thread itself can tell them apart:

- it **ran**: thread CPU time (its stages, and the work between ticks: the collector, the
  status line, the event loop);
- it **waited, runnable**: the kernel's ``run_delay`` of the thread
  (``/proc/thread-self/schedstat``), time it was ready to run and another task had the CPU
  (the bare loop above it, or anything else the host runs there);
- it was **off the CPU**: the rest of the wall time. Blocked, if it made a voluntary context
  switch (the wait for the timer is one; handctl's tick itself never blocks); if it made
  none, it never stopped running in the kernel's view, and the time was taken from under it
  (a hypervisor's steal, or interrupts where they are accounted apart), uncounted as its CPU
  time.

``MissTrace`` keeps, for every wake-up that slept through expirations or came late by
``LATE_SHARE`` of a period, these figures over the interval from the tick before's start to
its own, with the thread's voluntary and involuntary context switches and page faults
(``getrusage(RUSAGE_THREAD)``) and what happened in that tick (``NOTE_NAMES``: a phase switch,
a change of the supervisor's state, a fault, a bus event, the status line, a collection). Per
tick it costs a read of the schedstat file and a ``getrusage`` (3.5 µs together on this
project's two-vCPU machine) and a few stores; the thread CPU time is the stage accounting's
own reading at the tick's start.
"""

from __future__ import annotations

import os
import resource
import time
from array import array
from typing import Any

#: What happened in a tick, as bits of its notes.
NOTE_PHASE = 1  # the recipe entered a phase (or its end)
NOTE_STATE = 2  # the supervisor's state changed
NOTE_FAULT = 4  # a fault was latched
NOTE_BUS_EVENT = 8  # the bus reported an event (error frame, overrun, ...)
NOTE_STATUS = 16  # the status line was written
NOTE_COLLECT = 32  # the garbage collector ran after the tick's stages
NOTE_NAMES = {
    NOTE_PHASE: "phase",
    NOTE_STATE: "state",
    NOTE_FAULT: "fault",
    NOTE_BUS_EVENT: "bus_event",
    NOTE_STATUS: "status_line",
    NOTE_COLLECT: "collection",
}
#: Share of the period: a wake-up this late has its row even if it missed nothing. On this
#: project's two-vCPU machine a run's median wake-up was 45-222 µs late, and one wake-up in 400
#: was this late (docs/timing.md).
LATE_SHARE = 0.2
#: The run_delay a tick is allowed before any of it counts as the host's holding it: this many
#: times the usual for the tick's length. The bare loop beside the run preempts the loop twice
#: a period, and one preemption costs it 20-80 µs: 103 ticks made 2-3 ms long by 2 ms of busy
#: work of their own waited 0.57-2.4 times the usual for their length (median 1.25;
#: docs/timing.md).
RUN_DELAY_FACTOR = 3.0
#: One on-time tick in this many has its run_delay kept, for the usual (``usual_run_delay_ns``).
USUAL_EVERY = 16
_SCHEDSTAT = "/proc/thread-self/schedstat"
_COLUMNS = (
    "tick",  # the late wake-up
    "missed",  # the expirations it slept through (0: late, but it missed none)
    "late_ns",  # how late it was, from the oldest of them
    "before_late_ns",  # how late the tick before woke, from its newest expiration
    "wall_ns",  # from the tick before's start to this one's (``MissTrace.woke``)
    "cpu_ns",  # thread CPU time in that interval
    "stages_ns",  # of which the tick before's stages (poll to record)
    "run_delay_ns",  # time runnable and waiting for the CPU (-1: unknown)
    "voluntary",  # context switches: the thread blocked (the wait for the timer is one)
    "involuntary",  # context switches: preempted while it could run
    "faults",  # page faults, minor and major
    "notes",  # NOTE_* of the tick before
)


def parse_schedstat(raw: bytes) -> tuple[int, int, int]:
    """(CPU time on the CPU in ns, run_delay in ns, times switched in) of a schedstat line;
    (-1, -1, -1) if there is none. The CPU time is as of the thread's last switch or
    scheduler tick: the thread CPU clock is read for it instead."""
    fields = raw.split()
    if len(fields) < 3:
        return -1, -1, -1
    return int(fields[0]), int(fields[1]), int(fields[2])


def _usage() -> resource.struct_rusage:
    return resource.getrusage(resource.RUSAGE_THREAD)


class MissTrace:
    """Per late wake-up of the loop's thread (one that missed, or was ``late_floor_ns`` late),
    what the tick before it did; see the module.

    ``woke`` is called at each tick's start (start-up ticks too), in the loop's thread, with
    the tick's number, its lateness, the expirations it slept through and the thread CPU time
    then; ``done`` when its stages are done, with the CPU time then and its notes. Arrays are
    allocated once; past ``capacity`` late wake-ups are only counted.
    """

    def __init__(self, period_ns: int, capacity: int = 16384, path: str = _SCHEDSTAT) -> None:
        self.period_ns = period_ns
        #: An on-time wake-up this late has its row too: a late start that did not miss may
        #: be what the next tick missed by (``handctl.hostcheck.LoopWork.unheld_missed``).
        self.late_floor_ns = round(LATE_SHARE * period_ns)
        self.capacity = capacity
        self.columns = {name: array("q", bytes(8 * capacity)) for name in _COLUMNS}
        self.size = 0
        self.overflow = 0
        self._path = path
        self._fd = -1
        self._opened = False
        # the tick before's: number, wake-up, lateness, CPU time at its start and its stages'
        # CPU time, schedstat line and resource usage at its wake-up, notes
        self._tick = -2
        self._wake = 0
        self._late = 0
        self._cpu = 0
        self._stages = 0
        self._sched = b""
        self._usage = _usage()
        self._notes = 0
        # run_delay of on-time ticks, one in USUAL_EVERY (the newest ``capacity``)
        self._delays = array("q", bytes(8 * capacity))
        self._delay_count = 0

    def _open(self) -> None:
        """In the loop's thread (``thread-self`` is the thread that opens it)."""
        self._opened = True
        try:
            self._fd = os.open(self._path, os.O_RDONLY)
        except OSError:
            self._fd = -1

    def woke(self, tick: int, late_ns: int, missed: int, cpu_ns: int) -> None:
        """Tick ``tick`` woke ``late_ns`` after its (newest) expiration, having slept through
        ``missed`` more; ``cpu_ns`` is the thread's CPU time now.

        Every figure of an interval is read here, at the tick's start (after its hooks, where
        the stage accounting reads its first CPU time): the wall time too, not the wake-up's,
        so that the interval's wall time, CPU time, run_delay and switches cover the same
        stretch, and time the thread spent running before this point (a hook) is not taken
        for time it was off the CPU."""
        if not self._opened:
            self._open()
        now_ns = time.monotonic_ns()
        sched = os.pread(self._fd, 96, 0) if self._fd >= 0 else b""
        usage = _usage()
        if tick == self._tick + 1:
            if missed or late_ns >= self.late_floor_ns:
                self._add(tick, now_ns, late_ns, missed, cpu_ns, sched, usage)
            elif tick % USUAL_EVERY == 0 and self._fd >= 0:
                delay = parse_schedstat(sched)[1] - parse_schedstat(self._sched)[1]
                self._delays[self._delay_count % self.capacity] = delay
                self._delay_count += 1
        self._tick, self._wake, self._late, self._cpu = tick, now_ns, late_ns, cpu_ns
        self._sched, self._usage = sched, usage
        self._notes = self._stages = 0  # a start-up tick has no stages (no ``done``)

    def done(self, cpu_ns: int, notes: int) -> None:
        """The tick's stages are done; ``notes`` is what happened in it (``NOTE_*``)."""
        self._stages = cpu_ns - self._cpu
        self._notes |= notes

    def note(self, notes: int) -> None:
        """Something that happened after the tick's stages, before the next wake-up."""
        self._notes |= notes

    def _add(
        self,
        tick: int,
        now_ns: int,
        late_ns: int,
        missed: int,
        cpu_ns: int,
        sched: bytes,
        usage: resource.struct_rusage,
    ) -> None:
        n = self.size
        if n >= self.capacity:
            self.overflow += 1
            return
        before = parse_schedstat(self._sched)
        after = parse_schedstat(sched)
        known = before[0] >= 0 and after[0] >= 0
        was = self._usage
        row = (
            tick,
            missed,
            late_ns + missed * self.period_ns,
            self._late,
            now_ns - self._wake,
            cpu_ns - self._cpu,
            self._stages,
            after[1] - before[1] if known else -1,
            usage.ru_nvcsw - was.ru_nvcsw,
            usage.ru_nivcsw - was.ru_nivcsw,
            usage.ru_minflt + usage.ru_majflt - was.ru_minflt - was.ru_majflt,
            self._notes,
        )
        for column, value in zip(self.columns.values(), row, strict=True):
            column[n] = value
        self.size = n + 1

    def usual_run_delay_ns(self) -> int:
        """The median run_delay of a tick that woke on time and was followed by an on-time
        wake-up (one in ``USUAL_EVERY`` is sampled): what the loop usually waits for the CPU
        in a tick (the bare loop beside it preempts it twice a period); -1 if unknown."""
        n = min(self._delay_count, self.capacity)
        if n == 0:
            return -1
        return sorted(self._delays[:n])[n // 2]

    def rows(self) -> dict[int, dict[str, int]]:
        """Every late wake-up kept, by its tick: its columns."""
        names = list(self.columns)
        return {
            self.columns["tick"][i]: {name: self.columns[name][i] for name in names}
            for i in range(self.size)
        }

    def close(self) -> None:
        if self._fd >= 0:
            os.close(self._fd)
            self._fd = -1


def held_off_ns(row: dict[str, int], usual_delay_ns: int, period_ns: int) -> int:
    """ns of a late wake-up's interval (``MissTrace`` row) in which the loop's thread was held
    off the CPU by the kernel's own account: its run_delay beyond ``RUN_DELAY_FACTOR`` times
    the usual for as many periods (runnable, another task running), and, if it made no
    voluntary switch, the time it was neither running nor runnable (taken from under it: it
    never blocked). Never its own CPU time. 0 where the run_delay or the usual is unknown."""
    delay, wall = row["run_delay_ns"], row["wall_ns"]
    if delay < 0 or usual_delay_ns < 0:
        return 0
    held = max(0, delay - round(RUN_DELAY_FACTOR * usual_delay_ns * wall / period_ns))
    if row["voluntary"] == 0:
        held += max(0, wall - row["cpu_ns"] - delay)
    return held


def describe(row: dict[str, int], usual_ns: int, usual_delay_ns: int = -1) -> dict[str, Any]:
    """One late wake-up as the summary shows it (µs; of the tick before's wall time, what it
    ran, waited runnable and was off the CPU), beside the usual tick's CPU time and run_delay."""
    wall, cpu, delay = row["wall_ns"], row["cpu_ns"], row["run_delay_ns"]
    return {
        "tick": row["tick"],
        "missed": row["missed"],
        "late_us": round(row["late_ns"] / 1e3, 1),
        "before_woke_late_us": round(row["before_late_ns"] / 1e3, 1),
        "wall_us": round(wall / 1e3, 1),
        "cpu_us": round(cpu / 1e3, 1),
        "cpu_over_usual": round(cpu / usual_ns, 2) if usual_ns > 0 else None,
        "stages_cpu_us": round(row["stages_ns"] / 1e3, 1),
        "run_delay_us": round(delay / 1e3, 1) if delay >= 0 else None,
        "usual_run_delay_us": round(usual_delay_ns / 1e3, 1) if usual_delay_ns >= 0 else None,
        # the CPU time (getrusage) and the run_delay (schedstat) are two clocks' counts: a
        # tick that was never off the CPU came out a microsecond or so below zero
        "off_cpu_us": round(max(0, wall - cpu - delay) / 1e3, 1) if delay >= 0 else None,
        "voluntary_switches": row["voluntary"],
        "involuntary_switches": row["involuntary"],
        "page_faults": row["faults"],
        "notes": [name for bit, name in NOTE_NAMES.items() if row["notes"] & bit],
    }
