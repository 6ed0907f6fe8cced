"""python-can's virtual bus, stamping each frame as it arrives on the receiver's own clock, so
that a lockstep run (simulated time) stays deterministic and a frame's age is its own."""

from __future__ import annotations

import queue
import time
from collections.abc import Callable
from typing import Any

import can
from can.interfaces import virtual as _virtual

from handctl.online import frameflags as ff


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

    def send_frame(self, arbitration_id: int, flags: int, data: bytes) -> None:
        """python-can's ``send`` with a zero timeout, of one frame given as
        ``(arbitration_id, flags, data)`` (``handctl.online.frameflags``): handctl's own
        receivers on the channel are given that tuple, any other receiver a python-can
        ``Message``, as ``send`` would. A receiver with a full queue misses it; then this
        raises as ``send`` does, once every other receiver has it."""
        self._check_if_open()
        all_sent = True
        for bus_queue in self.channel:
            if bus_queue is self.queue and not self.receive_own_messages:
                continue
            item: Any = (arbitration_id, flags, data)
            if type(bus_queue) is not _ArrivalQueue:
                item = can.Message(
                    timestamp=time.time(),
                    arbitration_id=arbitration_id,
                    **ff.message_fields(flags),
                    data=data,
                    channel=self.channel_id,
                    is_rx=bus_queue is not self.queue,
                    check=False,
                )
            try:
                bus_queue.put_nowait(item)
            except queue.Full:
                all_sent = False
        if not all_sent:
            raise can.CanOperationError("Could not send message to one or more recipients")

    def take(self) -> tuple[int, can.Message | tuple[int, int, bytes]] | None:
        """The next ``(arrival_ns, message)``, or None when the queue is empty; a message from
        handctl's own sender is the ``(arbitration_id, flags, data)`` of ``send_frame``."""
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
        stamp_ns, msg = item
        if isinstance(msg, tuple):  # a frame from handctl's own sender (``send_frame``)
            arbitration_id, flags, data = msg
            msg = can.Message(
                arbitration_id=arbitration_id,
                **ff.message_fields(flags),
                data=data,
                channel=self.channel_id,
                is_rx=True,
                check=False,
            )
        msg.timestamp = stamp_ns * 1e-9
        return msg, False
