"""A periodic Linux timerfd: the only way handctl paces 1 kHz.

``asyncio.sleep`` and ``time.sleep`` cannot pace a 1 kHz loop: the selector rounds timeouts up
to whole milliseconds and sleeps overshoot, and the error accumulates. A timerfd keeps an
absolute schedule in the kernel, becomes readable at each expiration (so the asyncio loop can
wait on it like on a socket), and a read returns how many periods have passed, so a late wake-up
shows up as missed ticks instead of silently stretching time. Python 3.13 has
``os.timerfd_create``; before that the same system calls go through ctypes.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import functools
import os
import sys
import time

_CLOCK_MONOTONIC = 1
_TFD_NONBLOCK = 0o4000
_TFD_CLOEXEC = 0o2000000
_TFD_TIMER_ABSTIME = 1


class _Timespec(ctypes.Structure):
    _fields_ = (("tv_sec", ctypes.c_long), ("tv_nsec", ctypes.c_long))


class _Itimerspec(ctypes.Structure):
    _fields_ = (("it_interval", _Timespec), ("it_value", _Timespec))


class PeriodicTimer:
    """Expires every ``period_ns`` from its creation on (CLOCK_MONOTONIC).

    ``nonblocking=True`` is for an event loop: register ``fileno()`` as a reader and call
    ``read()`` when it is readable. Blocking timers are for a plain thread (the free-running
    simulated hand).
    """

    def __init__(self, period_ns: int, *, nonblocking: bool = False) -> None:
        if period_ns <= 0:
            raise ValueError(f"timer period must be > 0 ns, found {period_ns}")
        self.period_ns = period_ns
        flags = _TFD_CLOEXEC | (_TFD_NONBLOCK if nonblocking else 0)
        create = getattr(os, "timerfd_create", None)  # Python >= 3.13
        if create is None:
            _load_libc()  # before the schedule starts: finding libc can take milliseconds
        # An absolute first expiration: expiration E is due at start_ns + E * period_ns
        # exactly, which is what lateness is measured against.
        self.start_ns = time.monotonic_ns()
        if create is not None:
            self._fd: int = create(time.CLOCK_MONOTONIC, flags=flags)
            os.timerfd_settime_ns(  # type: ignore[attr-defined,unused-ignore]
                self._fd,
                flags=_TFD_TIMER_ABSTIME,
                initial=self.start_ns + period_ns,
                interval=period_ns,
            )
        else:
            self._fd = _ctypes_timerfd(self.start_ns + period_ns, period_ns, flags)

    def fileno(self) -> int:
        return self._fd

    def read(self) -> int:
        """Expirations since the last read (>= 1); 0 if none yet on a non-blocking timer."""
        try:
            return int.from_bytes(os.read(self._fd, 8), sys.byteorder)
        except BlockingIOError:
            return 0

    def close(self) -> None:
        if self._fd >= 0:
            os.close(self._fd)
            self._fd = -1

    def __enter__(self) -> PeriodicTimer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


@functools.cache
def _load_libc() -> ctypes.CDLL:
    if not sys.platform.startswith("linux"):
        raise OSError("handctl's real-time clock needs a Linux timerfd")
    return ctypes.CDLL(ctypes.util.find_library("c") or None, use_errno=True)


def _ctypes_timerfd(first_ns: int, period_ns: int, flags: int) -> int:
    libc = _load_libc()
    fd = int(libc.timerfd_create(_CLOCK_MONOTONIC, flags))
    if fd < 0:
        err = ctypes.get_errno()
        raise OSError(err, f"timerfd_create: {os.strerror(err)}")
    period = _Timespec(*divmod(period_ns, 1_000_000_000))
    spec = _Itimerspec(period, _Timespec(*divmod(first_ns, 1_000_000_000)))
    if libc.timerfd_settime(fd, _TFD_TIMER_ABSTIME, ctypes.byref(spec), None) != 0:
        err = ctypes.get_errno()
        os.close(fd)
        raise OSError(err, f"timerfd_settime: {os.strerror(err)}")
    return fd
