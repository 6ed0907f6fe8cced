"""What the tick before each late wake-up did, so that a missed tick explains itself.

A missed tick is decided in the tick before it: that tick woke, did its work and went back to
sleep on the timer, and the next wake-up came late. Where its time went is one of three
things, and the thread itself can tell them apart:

- it **ran**: thread CPU time (its stages, and the work between ticks: the collector, the
  status line, the event loop);
- it **waited, runnable**: the kernel's ``run_delay`` of the thread
  (``/proc/thread-self/schedstat``), time it was ready to run and another task had the CPU
  (the bare loop above it, or anything else the host runs there);
- it **slept**: the rest of the wall time, blocked (normally only the wait for the timer).

``MissTrace`` keeps, for every wake-up that slept through expirations, these figures over the
interval from the tick before's wake-up to it, with the kernel's count of the times the thread
was switched in (one per wake-up, more when it was preempted), its page faults and what
happened in that tick (``NOTE_NAMES``: a phase switch, a change of the supervisor's state, a
fault, a bus event, the status line, a collection). Per tick it costs one read of the
schedstat file (about 3 µs) and a few stores; the thread CPU time is the stage accounting's own
reading at the tick's start, and the page faults are read one tick in ``FAULTS_EVERY``.
"""

from __future__ import annotations

import os
import resource
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
#: One tick in this many reads the thread's page faults (``getrusage``, about 2 µs): a miss's
#: faults are those since the last such reading, so at most this many ticks before it.
FAULTS_EVERY = 16
_SCHEDSTAT = "/proc/thread-self/schedstat"
_COLUMNS = (
    "tick",  # the late wake-up
    "missed",  # the expirations it slept through
    "late_ns",  # how late it was, from the oldest of them
    "before_late_ns",  # how late the tick before woke (0: on time)
    "wall_ns",  # from the tick before's wake-up to this one
    "cpu_ns",  # thread CPU time in that interval
    "stages_ns",  # of which the tick before's stages (poll to record)
    "run_delay_ns",  # time runnable and waiting for the CPU (-1: unknown)
    "switches",  # times switched in (-1: unknown)
    "faults",  # page faults, minor and major, since ``faults_since``
    "faults_since",  # the tick of the reading they count from
    "notes",  # NOTE_* of the tick before
)


def parse_schedstat(raw: bytes) -> tuple[int, int, int]:
    """(CPU time on the CPU in ns, run_delay in ns, times switched in) of a schedstat line;
    (-1, -1, -1) if there is none."""
    fields = raw.split()
    if len(fields) < 3:
        return -1, -1, -1
    return int(fields[0]), int(fields[1]), int(fields[2])


def _faults() -> int:
    usage = resource.getrusage(resource.RUSAGE_THREAD)
    return usage.ru_minflt + usage.ru_majflt


class MissTrace:
    """Per late wake-up of the loop's thread, what the tick before it did; see the module.

    ``woke`` is called at each tick's start, in the loop's thread, with the tick's number, its
    wake-up time and lateness and the thread CPU time then; ``done`` when its stages are done,
    with the CPU time then and its notes. Arrays are allocated once; past ``capacity`` late
    wake-ups are only counted.
    """

    def __init__(self, period_ns: int, capacity: int = 4096, path: str = _SCHEDSTAT) -> None:
        self.period_ns = period_ns
        self.capacity = capacity
        self.columns = {name: array("q", bytes(8 * capacity)) for name in _COLUMNS}
        self.size = 0
        self.overflow = 0
        self._path = path
        self._fd = -1
        self._opened = False
        # the tick before's: wake-up, lateness, CPU time at its start and at its stages' end,
        # schedstat line at its wake-up, notes
        self._tick = -2
        self._wake = 0
        self._late = 0
        self._cpu = 0
        self._stages = 0
        self._sched = b""
        self._notes = 0
        self._fault_tick = -1
        self._fault_count = 0
        # run_delay of on-time ticks, one in FAULTS_EVERY (the newest ``capacity``)
        self._delays = array("q", bytes(8 * capacity))
        self._delay_count = 0

    def _open(self) -> None:
        """In the loop's thread (``thread-self`` is the thread that opens it)."""
        self._opened = True
        try:
            self._fd = os.open(self._path, os.O_RDONLY)
        except OSError:
            self._fd = -1

    def woke(self, tick: int, now_ns: int, late_ns: int, missed: int, cpu_ns: int) -> None:
        """Tick ``tick`` woke at ``now_ns``, ``late_ns`` after its (newest) expiration, having
        slept through ``missed`` more; ``cpu_ns`` is the thread's CPU time now."""
        if not self._opened:
            self._open()
            self._fault_tick, self._fault_count = tick, _faults()
        sched = os.pread(self._fd, 96, 0) if self._fd >= 0 else b""
        if missed and tick == self._tick + 1:
            self._add(tick, now_ns, late_ns, missed, cpu_ns, sched)
        elif tick % FAULTS_EVERY == 0:
            self._fault_tick, self._fault_count = tick, _faults()
            if not missed and tick == self._tick + 1 and self._fd >= 0:
                delay = parse_schedstat(sched)[1] - parse_schedstat(self._sched)[1]
                self._delays[self._delay_count % self.capacity] = delay
                self._delay_count += 1
        self._tick, self._wake, self._late, self._cpu, self._sched = (
            tick,
            now_ns,
            late_ns,
            cpu_ns,
            sched,
        )
        self._notes = 0

    def done(self, cpu_ns: int, notes: int) -> None:
        """The tick's stages are done; ``notes`` is what happened in it (``NOTE_*``)."""
        self._stages = cpu_ns - self._cpu
        self._notes |= notes

    def note(self, notes: int) -> None:
        """Something that happened after the tick's stages, before the next wake-up."""
        self._notes |= notes

    def _add(
        self, tick: int, now_ns: int, late_ns: int, missed: int, cpu_ns: int, sched: bytes
    ) -> None:
        n = self.size
        if n >= self.capacity:
            self.overflow += 1
            return
        before = parse_schedstat(self._sched)
        after = parse_schedstat(sched)
        known = before[0] >= 0 and after[0] >= 0
        faults = _faults()
        row = (
            tick,
            missed,
            late_ns + missed * self.period_ns,
            self._late,
            now_ns - self._wake,
            cpu_ns - self._cpu,
            self._stages,
            after[1] - before[1] if known else -1,
            after[2] - before[2] if known else -1,
            faults - self._fault_count if self._fault_tick >= 0 else -1,
            self._fault_tick,
            self._notes,
        )
        for column, value in zip(self.columns.values(), row, strict=True):
            column[n] = value
        self.size = n + 1
        self._fault_tick, self._fault_count = tick, faults

    def usual_run_delay_ns(self) -> int:
        """The median run_delay of a tick that woke on time and was followed by an on-time
        wake-up (one in ``FAULTS_EVERY`` is sampled): what the loop usually waits for the CPU
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


def describe(row: dict[str, int], usual_ns: int, usual_delay_ns: int = -1) -> dict[str, Any]:
    """One late wake-up as the summary shows it (µs; the tick before's share of its wall time
    that it ran, waited runnable and slept), beside the usual tick's CPU time and run_delay."""
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
        "slept_us": round((wall - cpu - delay) / 1e3, 1) if delay >= 0 else None,
        "switches": row["switches"] if row["switches"] >= 0 else None,
        "page_faults": row["faults"] if row["faults"] >= 0 else None,
        "page_faults_since_tick": row["faults_since"],
        "notes": [name for bit, name in NOTE_NAMES.items() if row["notes"] & bit],
    }
