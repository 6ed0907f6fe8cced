"""The two clocks of the loop: real time from a timerfd, and lockstep with the simulated hand.

Both hand out ``Tick`` values with the tick number, its scheduled time and how many ticks were
missed before it, so the loop and the safety supervisor treat both alike. Missed ticks are
counted, never hidden: a real-time tick that wakes up late reports the expirations it slept
through.
"""

from __future__ import annotations

import asyncio
import contextlib
import ctypes
import ctypes.util
import gc
import os
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass

from handctl.timerfd import PeriodicTimer


@dataclass(frozen=True, slots=True)
class Tick:
    k: int  # tick number, 0 first
    scheduled_ns: int  # when it was due, on the clock's time base
    now_ns: int  # when the loop got it
    missed: int  # ticks skipped just before this one

    @property
    def lateness_ns(self) -> int:
        return self.now_ns - self.scheduled_ns


class RealtimeClock:
    """Ticks from a timerfd registered with the running asyncio loop."""

    lockstep = False

    def __init__(self, period_s: float) -> None:
        self.period_ns = round(period_s * 1e9)
        self._timer: PeriodicTimer | None = None
        self._waiter: asyncio.Future[int] | None = None
        self._pending = 0
        self._expirations = 0
        self._k = -1
        self._loop: asyncio.AbstractEventLoop | None = None

    def now_ns(self) -> int:
        return time.monotonic_ns()

    def start(self) -> None:
        self._loop = asyncio.get_running_loop()
        self._timer = PeriodicTimer(self.period_ns, nonblocking=True)
        self._loop.add_reader(self._timer.fileno(), self._on_readable)

    def _on_readable(self) -> None:
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
        if self._pending:
            n, self._pending = self._pending, 0
        else:
            self._waiter = self._loop.create_future()
            n = await self._waiter
            self._waiter = None
        self._expirations += n
        self._k += 1
        scheduled = self._timer.start_ns + self._expirations * self.period_ns
        return Tick(self._k, scheduled, time.monotonic_ns(), n - 1)

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
        self._k = -1
        self._now = 0

    def now_ns(self) -> int:
        return self._now

    async def wait_tick(self) -> Tick:
        # The peer's step ends at the new tick's time, so what it sends arrives then: the
        # clock moves first, and frames stamped on arrival (``handctl.bus``) carry that time.
        self._k += 1
        self._now = (self._k + 1) * self.period_ns
        self._step_peer()
        # Let the event loop run callbacks (signals, the recorder) between ticks.
        loop = asyncio.get_running_loop()
        done = loop.create_future()
        loop.call_soon(done.set_result, None)
        await done
        return Tick(self._k, self._now, self._now, 0)

    def close(self) -> None:
        pass


Clock = RealtimeClock | LockstepClock

_MCL_CURRENT = 1
_MCL_FUTURE = 2


@contextlib.contextmanager
def collector_paused() -> Iterator[None]:
    """No automatic garbage collection for the duration of the block (one collection first).

    Why: a full collection walks every tracked object, and after importing MuJoCo, NumPy and
    python-can that takes about 11 ms. In the simulated hand's process one such pass held the
    node timer long enough for the host's FEEDBACK_TIMEOUT, about two minutes into every soak.
    The simulated hand is a test peer that makes little cyclic garbage, so it runs without the
    collector. The control process needs no such thing: its loop allocates almost no container
    objects (six minutes of soak ran one young collection every few seconds and no full one).
    """
    gc.collect()
    gc.disable()
    try:
        yield
    finally:
        gc.enable()


def request_realtime(priority: int = 80) -> list[str]:
    """Ask for SCHED_FIFO and locked memory; returns what the system refused, in plain words."""
    refused: list[str] = []
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
    except (OSError, AttributeError) as exc:
        refused.append(f"SCHED_FIFO priority {priority} refused ({exc}); grant it with "
                       "'ulimit -r' / limits.conf rtprio, or run with CAP_SYS_NICE")
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or None, use_errno=True)
        if libc.mlockall(_MCL_CURRENT | _MCL_FUTURE) != 0:
            err = ctypes.get_errno()
            refused.append(f"locking memory refused ({os.strerror(err)}); raise 'ulimit -l' "
                           "(memlock) or run with CAP_IPC_LOCK")
    except OSError as exc:
        refused.append(f"locking memory unavailable ({exc})")
    return refused
