"""The flag bits of a raw frame, shared by ``HandBus`` and the transports that exchange frames
without python-can's ``Message`` (``bus.FrameTransport``: the unix bus).

A ``Message`` costs a few µs to build and as much to take apart; a tick moves half a dozen
frames each way. The unix bus carries these very bits on its wire.
"""

from __future__ import annotations

from typing import Protocol

FD = 1  # CAN-FD frame
BRS = 2  # CAN-FD bit-rate switch
ERROR = 4  # an error frame: the id is the error class (linux/can/error.h)
ESI = 8  # CAN-FD error state indicator
EXTENDED = 16  # a 29-bit identifier
#: A remote frame (RTR): a request for the frame of its id, with no data. Without this bit it
#: was carried on as a data frame of 0 bytes, and one on id 0x000 reached the nodes as an
#: EStop of no data and the log as a data frame.
REMOTE = 32
#: Not a frame: a transport's word that what it received was malformed and dropped (the unix
#: bus: a datagram cut by its buffer, or one whose contents do not parse); the data is the
#: reason, UTF-8. Only the transport itself sets it: no frame on the wire can carry it.
RX_FAILED = 64


def message_fields(flags: int) -> dict[str, bool]:
    """The flag bits as python-can ``Message`` keyword arguments: a frame that left handctl as
    bits and meets a python-can program (a logger, another tool on the channel) becomes a
    ``Message`` in one place, whichever transport carried it."""
    return {
        "is_extended_id": bool(flags & EXTENDED),
        "is_fd": bool(flags & FD),
        "bitrate_switch": bool(flags & BRS),
        "is_error_frame": bool(flags & ERROR),
        "error_state_indicator": bool(flags & ESI),
        "is_remote_frame": bool(flags & REMOTE),
    }


class FlaggedFrame(Protocol):
    """What a python-can ``Message`` says of a frame's flags (this module needs no python-can)."""

    is_fd: bool
    bitrate_switch: bool
    is_error_frame: bool
    error_state_indicator: bool
    is_extended_id: bool
    is_remote_frame: bool


def flags_of(msg: FlaggedFrame) -> int:
    """A python-can ``Message``'s flags as these bits: ``message_fields`` the other way."""
    return (
        (FD if msg.is_fd else 0)
        | (BRS if msg.bitrate_switch else 0)
        | (ERROR if msg.is_error_frame else 0)
        | (ESI if msg.error_state_indicator else 0)
        | (EXTENDED if msg.is_extended_id else 0)
        | (REMOTE if msg.is_remote_frame else 0)
    )
