"""The two clocks of the loop: real time from a timerfd, and lockstep with the simulated hand.

The loop types against ``Clock``, the protocol both implement (as does the re-run's clock,
which hands out the ticks of a recording). Both hand out ``Tick`` values with the tick number,
its scheduled time and how many ticks were missed before it, so the loop and the safety
supervisor treat both alike. Missed ticks are counted, never hidden: a real-time tick that
wakes up late reports the expirations it slept through.
"""

from __future__ import annotations

import asyncio
import contextlib
import ctypes
import ctypes.util
import gc
import os
import time
from array import array
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import NamedTuple, Protocol

from handctl.online.timerfd import PeriodicTimer


class Tick(NamedTuple):
    """One tick as a clock hands it out. A named tuple, immutable and built every tick: a
    frozen dataclass's constructor costs about four times as much."""

    tick: int  # the tick's number, 0 first
    scheduled_ns: int  # when it was due, on the clock's time base
    now_ns: int  # when the loop got it
    missed: int  # ticks skipped just before this one

    @property
    def lateness_ns(self) -> int:
        return self.now_ns - self.scheduled_ns


class StallLog:
    """The late wake-ups of a periodic loop, each as the interval it could not run.

    A wake-up that read ``n`` expirations served its newest one late and slept through the
    ``n - 1`` before it: from the oldest of them (``due_ns``) to the wake-up (``wake_ns``) the
    loop did not run. The log keeps those intervals, not every tick, so that the loop's misses
    can be laid beside the host's (``handctl.hostcheck``): a missed tick of the control loop
    that overlaps a stall of a bare timer loop beside it was the host's doing.

    Only wake-ups at least ``threshold_ns`` late are kept, in arrays allocated once (``add``
    stores integers and allocates nothing); past ``capacity`` they are only counted.
    ``index`` is the wake-up's number in its loop, so consecutive stalls can be told apart from
    stalls with on-time wake-ups between them. With ``work=True`` each also keeps ``cpu_ns``,
    what the loop that keeps the log knows of its own work before the wake-up, or -1
    (``RealtimeClock``: the thread CPU time of the tick between two stalled wake-ups in a row).
    """

    def __init__(self, threshold_ns: int, capacity: int = 1 << 16, work: bool = False) -> None:
        self.threshold_ns = threshold_ns
        self.capacity = capacity
        self.index = array("q", bytes(8 * capacity))
        self.due_ns = array("q", bytes(8 * capacity))
        self.wake_ns = array("q", bytes(8 * capacity))
        self.missed = array("q", bytes(8 * capacity))
        self.cpu_ns = array("q", bytes(8 * capacity if work else 0))
        self.size = 0
        self.overflow = 0  # stalls seen after the log was full
        self.overflow_missed = 0  # ticks they missed

    def add(self, index: int, due_ns: int, wake_ns: int, missed: int, cpu_ns: int = -1) -> None:
        if wake_ns - due_ns < self.threshold_ns:
            return
        n = self.size
        if n >= self.capacity:
            self.overflow += 1
            self.overflow_missed += missed
            return
        self.index[n], self.due_ns[n], self.wake_ns[n], self.missed[n] = (
            index,
            due_ns,
            wake_ns,
            missed,
        )
        if self.cpu_ns:
            self.cpu_ns[n] = cpu_ns
        self.size = n + 1

    def rows(self) -> list[tuple[int, int, int, int]]:
        """(index, due_ns, wake_ns, missed) of every stall kept, in order."""
        n = self.size
        return list(
            zip(self.index[:n], self.due_ns[:n], self.wake_ns[:n], self.missed[:n], strict=True)
        )

    def work_ns(self) -> dict[int, int]:
        """``cpu_ns`` of every stall kept that has one, by wake-up index."""
        n = self.size if self.cpu_ns else 0
        return {i: c for i, c in zip(self.index[:n], self.cpu_ns[:n], strict=True) if c >= 0}


#: One tick in this many has its CPU time measured from its wake-up to the next, for the run's
#: usual (``UsualWork``): two thread CPU clock readings a sample (about 1.5 µs each on this
#: project's loaded two-vCPU machine) and a test every tick, about 0.3 µs a tick on average.
USUAL_SAMPLE_EVERY = 16


class UsualWork:
    """The thread CPU time of sampled ticks that woke on time and were followed by an on-time
    wake-up, each from its wake-up to the next: what a tick usually takes, measured the way a
    catch-up tick is (``StallLog.cpu_ns``), between-tick work (the collector, the event loop)
    included. The ticks' stages alone leave that out: a quarter to a third of a tick.

    Arrays allocated once; past ``capacity`` samples (about two minutes at 1 kHz) the
    oldest are overwritten, so the usual is that of the run's last minutes.
    """

    def __init__(self, capacity: int = 8192) -> None:
        self.capacity = capacity
        self.tick = array("q", bytes(8 * capacity))
        self.cpu_ns = array("q", bytes(8 * capacity))
        self.count = 0  # samples taken; the newest is at (count - 1) % capacity

    def add(self, tick: int, cpu_ns: int) -> None:
        at = self.count % self.capacity
        self.tick[at], self.cpu_ns[at] = tick, cpu_ns
        self.count += 1

    def median_ns(self, since_tick: int = 0) -> int:
        """The median over the samples of ticks from ``since_tick`` on (a run's start-up
        ticks, which only listen, are left out this way); 0 if there are none."""
        n = min(self.count, self.capacity)
        kept = sorted(
            c for t, c in zip(self.tick[:n], self.cpu_ns[:n], strict=True) if t >= since_tick
        )
        return kept[len(kept) // 2] if kept else 0


class RealtimeClock:
    """Ticks from a timerfd registered with the running asyncio loop.

    Every tick that missed expirations is also kept in ``stalls`` with the interval the loop
    was late for, to be laid beside the host's own stalls. A late wake-up serves only the
    newest expiration: the periods slept through are counted, never run back to back.

    The thread CPU time is read on stalled wake-ups (a system call, about 1 µs, that an
    on-time tick does not pay): so a stall that follows another in the very next wake-up
    carries the CPU time the tick between them took (``StallLog.cpu_ns``). That tick started
    late because of the first stall; whether it missed the next deadline by its own work or
    because it was held is what ``handctl.hostcheck.attribute`` asks of it, against the CPU
    time a tick usually takes from one wake-up to the next (``usual``), read on two
    consecutive wake-ups of one tick in ``USUAL_SAMPLE_EVERY``.
    """

    lockstep = False

    def __init__(self, period_s: float) -> None:
        self.period_ns = round(period_s * 1e9)
        self.stalls = StallLog(self.period_ns, work=True)
        self._timer: PeriodicTimer | None = None
        self._waiter: asyncio.Future[int] | None = None
        self._pending = 0
        self._expirations = 0
        self._tick = -1
        self._loop: asyncio.AbstractEventLoop | None = None
        self.usual = UsualWork()
        self._cpu_tick = -2  # the last wake-up the thread CPU time was read at, the time then,
        self._cpu_ns = 0  # and whether that wake-up was stalled
        self._cpu_stalled = False
        #: what the timer's callback raised: the next wait raises it (``_on_readable``)
        self._failure: Exception | None = None

    def now_ns(self) -> int:
        return time.monotonic_ns()

    def start(self) -> None:
        self._loop = asyncio.get_running_loop()
        self._timer = PeriodicTimer(self.period_ns, nonblocking=True)
        self._loop.add_reader(self._timer.fileno(), self._on_readable)

    def _on_readable(self) -> None:
        """The timer's callback. One that raises takes itself off the loop and hands its
        exception to the tick waiting (or the next to wait): left to asyncio, it was logged
        and swallowed, and the timer, still readable, called it again at once, thousands of
        "Exception in callback" a second for the 2 s until the run's watch found the clock
        silent (``CLOCK_SILENT_S``). The run now stops on the clock's own exception at once."""
        try:
            self._read()
        except Exception as exc:
            self._failure = exc
            if self._loop is not None and self._timer is not None:
                self._loop.remove_reader(self._timer.fileno())
            if self._waiter is not None and not self._waiter.done():
                self._waiter.set_exception(exc)

    def _read(self) -> None:
        assert self._timer is not None
        n = self._timer.read()
        if n == 0:
            return
        if self._waiter is not None and not self._waiter.done():
            self._waiter.set_result(self._pending + n)
            self._pending = 0
        else:
            self._pending += n

    async def wait_tick(self) -> Tick:
        """Wait for the next expiration; every bus wait of the tick happens after it."""
        if self._timer is None:
            self.start()
        assert self._loop is not None and self._timer is not None
        if self._failure is not None:
            raise self._failure
        if self._pending:
            n, self._pending = self._pending, 0
        else:
            self._waiter = self._loop.create_future()
            n = await self._waiter
            self._waiter = None
        self._expirations += n
        self._tick += 1
        scheduled = self._timer.start_ns + self._expirations * self.period_ns
        now = time.monotonic_ns()
        tick = self._tick
        if n > 1 or tick % USUAL_SAMPLE_EVERY < 2:
            cpu = time.thread_time_ns()
            # the tick before, from its wake-up to this one, if it was read
            work = cpu - self._cpu_ns if self._cpu_tick == tick - 1 else -1
            stalled, self._cpu_tick, self._cpu_ns = self._cpu_stalled, tick, cpu
            self._cpu_stalled = n > 1
            if n > 1:
                due = scheduled - (n - 1) * self.period_ns
                self.stalls.add(tick, due, now, n - 1, work if stalled else -1)
            elif work >= 0 and not stalled:
                self.usual.add(tick - 1, work)
        return Tick(tick, scheduled, now, n - 1)

    def close(self) -> None:
        if self._timer is not None:
            if self._loop is not None and not self._loop.is_closed():
                self._loop.remove_reader(self._timer.fileno())
            self._timer.close()
            self._timer = None


class LockstepClock:
    """Simulated time: each tick first steps the peer (the simulated hand) by one period.

    The peer thus always sees the commands of the previous tick before it advances, and the
    runtime sees the feedback of that step: deterministic, and as fast as the machine allows.
    """

    lockstep = True

    def __init__(self, period_s: float, step_peer: Callable[[], None]) -> None:
        self.period_ns = round(period_s * 1e9)
        self._step_peer = step_peer
        self._tick = -1
        self._now = 0

    def now_ns(self) -> int:
        return self._now

    async def wait_tick(self) -> Tick:
        # The peer's step ends at the new tick's time, so what it sends arrives then: the
        # clock moves first, and frames stamped on arrival (``handctl.online.bus``) carry that time.
        self._tick += 1
        self._now = (self._tick + 1) * self.period_ns
        self._step_peer()
        # Let the event loop run callbacks (signals, the recorder) between ticks.
        loop = asyncio.get_running_loop()
        done = loop.create_future()
        loop.call_soon(done.set_result, None)
        await done
        return Tick(self._tick, self._now, self._now, 0)

    def close(self) -> None:
        pass


class Clock(Protocol):
    """What the loop asks of a clock: the next tick, the time now on the clock's time base
    (which stamps frames as they arrive), and whether it is stepped with its peer rather than
    ticked by real time (a stepped clock may end a run by having no more ticks: ``EndOfTicks``).
    """

    @property
    def lockstep(self) -> bool: ...

    def now_ns(self) -> int: ...

    async def wait_tick(self) -> Tick: ...

    def close(self) -> None: ...


_MCL_CURRENT = 1
_MCL_FUTURE = 2


@contextlib.contextmanager
def collector_paused() -> Iterator[None]:
    """No automatic garbage collection for the duration of the block (one collection first).

    Why: a full collection walks every tracked object, and after importing MuJoCo, NumPy and
    python-can that takes about 11 ms. In the simulated hand's process one such pass held the
    node timer long enough for the host's FEEDBACK_TIMEOUT, about two minutes into every soak.
    The simulated hand is a test peer that makes little cyclic garbage, so it runs without the
    collector. The control loop keeps collecting, between its ticks only
    (``handctl.online.collector``).
    """
    gc.collect()
    gc.disable()
    try:
        yield
    finally:
        gc.enable()


#: SCHED_FIFO priority of the control loop with ``--rt`` (the simulated hand runs below it, a
#: host probe beside it one above).
LOOP_PRIORITY = 80
#: Bytes of stack and of heap touched once by ``prefault``: more than a tick ever uses.
STACK_RESERVE = 256 * 1024
HEAP_RESERVE = 16 * 1024 * 1024
_M_TRIM_THRESHOLD = -1
_HEAP_BLOCK = 64 * 1024  # below glibc's smallest mmap threshold (128 KiB)


@dataclass(frozen=True)
class Hygiene:
    """What ``--rt`` does for a run besides SCHED_FIFO. Each measure can be switched off alone,
    so a benchmark can show what each is worth (``tools/bench.py loop --rt --hygiene``)."""

    pin: bool = True  # on >= 2 CPUs: the loop and the simulated hand on CPUs of their own
    loop_cpu: int | None = None  # None: chosen (``handctl.hostcheck.plan_cpus``)
    sim_cpu: int | None = None
    lock_memory: bool = True  # mlockall(MCL_CURRENT | MCL_FUTURE): no page is ever paged out
    prefault: bool = True  # touch a stack and heap reserve, so no tick faults a page in


class _StackReserve(ctypes.Structure):
    _fields_ = (("data", ctypes.c_char * STACK_RESERVE),)


def _libc() -> ctypes.CDLL:
    return ctypes.CDLL(ctypes.util.find_library("c") or None, use_errno=True)


def prefault(libc: ctypes.CDLL) -> None:
    """Make the first deep call and the first allocations of a tick free of page faults.

    The heap: glibc is told never to give the top of the heap back (no trimming), then a
    reserve is allocated in blocks small enough to come from the heap (below glibc's mmap
    threshold), written and freed, so later allocations reuse resident pages. Large blocks
    still come from mmap, which with MCL_FUTURE is populated when it is mapped. The stack:
    Python cannot grow its own C stack on purpose, so a call passes a structure of
    ``STACK_RESERVE`` bytes by value; libffi copies it onto the stack, which touches every page
    of that depth. With the memory locked, both stay resident for the whole run.
    """
    libc.mallopt(_M_TRIM_THRESHOLD, -1)
    libc.malloc.restype = ctypes.c_void_p
    blocks = []
    for _ in range(HEAP_RESERVE // _HEAP_BLOCK):
        block = libc.malloc(ctypes.c_size_t(_HEAP_BLOCK))
        if not block:
            break
        ctypes.memset(block, 1, _HEAP_BLOCK)
        blocks.append(block)
    for block in blocks:
        libc.free(ctypes.c_void_p(block))
    # getpid ignores the argument; the call is only there to have the copy made.
    touch = ctypes.CFUNCTYPE(ctypes.c_int, _StackReserve)(("getpid", libc))
    touch(_StackReserve())


def request_realtime(
    priority: int = LOOP_PRIORITY,
    *,
    cpu: int | None = None,
    lock_memory: bool = True,
    prefault_memory: bool = False,
) -> list[str]:
    """Ask for SCHED_FIFO, a CPU of its own, locked and prefaulted memory for the calling
    thread (and the threads it starts); returns what the system refused, in plain words.

    Refusals are warnings, as in ros2_control: the run goes on with what it got, and the
    timing check beside it (``handctl.hostcheck``) shows what that cost.

    The memory is locked and prefaulted before the priority is raised: locking faults in every
    page of the process (tens of ms for the control process), which at SCHED_FIFO would hold
    every task of lower or equal priority on that CPU, the control loop beside a bare timer
    loop among them.
    """
    refused: list[str] = []
    if cpu is not None:
        try:
            os.sched_setaffinity(0, {cpu})
        except (OSError, ValueError) as exc:
            refused.append(
                f"pinning to CPU {cpu} refused ({exc}); the loop runs on "
                f"CPUs {sorted(os.sched_getaffinity(0))}"
            )
    try:
        libc: ctypes.CDLL | None = _libc()
    except OSError as exc:
        libc = None
        refused.append(f"locking memory unavailable ({exc})")
    if libc is not None and lock_memory and libc.mlockall(_MCL_CURRENT | _MCL_FUTURE) != 0:
        err = ctypes.get_errno()
        refused.append(
            f"locking memory refused ({os.strerror(err)}); raise 'ulimit -l' "
            "(memlock) or run with CAP_IPC_LOCK"
        )
    if libc is not None and prefault_memory:
        prefault(libc)
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
    except (OSError, AttributeError) as exc:
        refused.append(
            f"SCHED_FIFO priority {priority} refused ({exc}); grant it with "
            "'ulimit -r' / limits.conf rtprio, or run with CAP_SYS_NICE (with either, a cgroup "
            "v1 cpu group whose cpu.rt_runtime_us is 0 still refuses it)"
        )
    return refused
