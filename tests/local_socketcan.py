"""python-can's SocketCAN bus as one program among others on the same computer hears them,
for the tests of a machine without SocketCAN (no ``vcan`` to open): python-can's virtual bus
underneath, and only SocketCAN's marking of the frames on top."""

from __future__ import annotations

import can


class LocalSocketcanBus(can.BusABC):
    """A test double of python-can's ``SocketcanBus``, in its marking of the frames only.

    No real peer exists for this: the kernel is what marks a frame sent by another socket on
    the same computer (``MSG_DONTROUTE``, net/can/raw.c), and python-can's socketcan backend
    turns that into ``is_rx`` False (``capture_message``). On a vcan every frame is such a
    frame; on a can0 a second program's are. Its own frames are not handed back, as with
    ``receive_own_messages`` off. The frames themselves travel on python-can's virtual bus,
    to and from any other bus on ``channel``. Stamped 0 (python-can's "no time"): the receive
    times are not what these tests are of, and a wall-clock stamp against the lockstep clock
    would make them depend on the machine's load."""

    def __init__(self, channel: str) -> None:
        self._wire = can.Bus(interface="virtual", channel=channel, receive_own_messages=False)
        super().__init__(channel=channel)
        self.channel_info = f"a local SocketCAN double on {channel}"

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        msg = self._wire.recv(timeout=timeout)
        if msg is not None:
            msg.is_rx = False  # MSG_DONTROUTE: sent from this computer
            msg.timestamp = 0.0
        return msg, False

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        self._wire.send(msg, timeout=timeout)

    def shutdown(self) -> None:
        self._wire.shutdown()
        super().shutdown()
