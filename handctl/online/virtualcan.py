"""python-can's virtual bus, stamping each frame as it arrives on the receiver's own clock, so
that a lockstep run (simulated time) stays deterministic and a frame's age is its own."""

from __future__ import annotations

import queue
import time
from collections.abc import Callable
from typing import Any

import can
from can.interfaces import virtual as _virtual


class _ArrivalQueue(queue.Queue[Any]):
    """A virtual-bus receive queue that stamps each message as it is put, on its owner's clock.

    python-can's virtual bus stamps a message with the sender's wall clock; the receiver's
    loop runs on its own clock (simulated time in lockstep), so the stamp is taken here, at
    the moment the message is queued, as ``(stamp_ns, message)``.
    """

    def __init__(self, maxsize: int, stamp: Callable[[], int]) -> None:
        super().__init__(maxsize)
        self.stamp = stamp

    def _put(self, item: can.Message) -> None:
        self.queue.append((self.stamp(), item))


class ArrivalStampedVirtualBus(_virtual.VirtualBus):
    """python-can's virtual bus whose receive queue stamps messages on arrival (see
    ``_ArrivalQueue``); ``take`` returns them with their stamps. Other virtual buses on the
    channel, handctl's or not, send to it as to any other."""

    def __init__(self, channel: str, **kwargs: Any) -> None:
        super().__init__(channel=channel, **kwargs)
        self.clock_ns: Callable[[], int] = time.monotonic_ns
        with _virtual.channels_lock:
            old = self.queue
            stamped = _ArrivalQueue(old.maxsize, self._stamp)
            self.channel[self.channel.index(old)] = stamped
            self.queue = stamped
            while not old.empty():  # anything sent while the plain queue was registered
                stamped.put_nowait(old.get_nowait())

    def _stamp(self) -> int:
        return self.clock_ns()

    def take(self) -> tuple[int, can.Message] | None:
        """The next ``(arrival_ns, message)``, or None when the queue is empty."""
        if not self._open:
            raise can.CanOperationError("Cannot operate on a closed bus")
        if not self.queue.queue:  # empty: no lock taken and no exception raised to say so
            return None
        try:
            return self.queue.get_nowait()  # type: ignore[return-value]
        except queue.Empty:
            return None

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        self._check_if_open()
        try:
            item: Any = self.queue.get(block=True, timeout=timeout)  # (arrival_ns, message)
        except queue.Empty:
            return None, False
        item[1].timestamp = item[0] * 1e-9
        return item[1], False
