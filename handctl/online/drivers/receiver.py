"""Strict acceptance of received frames: length, CRC and rolling counter, per message stream.

A frame that fails any check is rejected and counted by kind, and never applied: a torque or an
angle from a corrupted or replayed frame is worse than no value, because the caller cannot tell
it from a good one. The rules are those of ``firmware_protocol/PROTOCOL.md``.
"""

from __future__ import annotations

import enum

from handctl.protocol import Layout


class Reject(enum.IntEnum):
    UNEXPECTED_ID = 0
    LENGTH = 1
    CRC = 2
    COUNTER_REPEAT = 3
    COUNTER_SKIP = 4
    EXTENDED_ID = 5  # a 29-bit identifier: the protocol has 11-bit ones only


REJECT_KINDS = tuple(Reject)


class CounterCheck:
    """The rolling-counter rule of one message stream.

    The first frame after start (or ``reset``) is accepted with any counter; later a repeated
    counter is rejected, and any jump other than +1 is rejected and re-synchronised to, so one
    lost frame costs the frame after it and never the whole stream.

    ``frame`` is the last accepted frame itself, and ``frame_ns`` when it arrived (both its
    receiver's to set, once the frame is accepted): a repeat with other contents soon after
    it is not the same frame heard twice but a second sender on the stream's identifier
    (``FingerNode``).
    """

    __slots__ = ("frame", "frame_ns", "last")

    def __init__(self) -> None:
        self.last: int | None = None
        self.frame: bytes | None = None
        self.frame_ns = 0

    def reset(self) -> None:
        self.last = None
        self.frame = None

    def check(self, counter: int) -> Reject | None:
        last = self.last
        self.last = counter
        if last is None or counter == (last + 1) & 0xFF:
            return None
        if counter == last:
            return Reject.COUNTER_REPEAT
        return Reject.COUNTER_SKIP


def validate(layout: Layout, data: bytes, counters: CounterCheck) -> Reject | None:
    """Run the checks in the documented order; the counter is only checked on an intact frame."""
    if len(data) != layout.length:
        return Reject.LENGTH
    if not layout.crc_ok(data):
        return Reject.CRC
    return counters.check(data[1])


class RejectCounts:
    """Rejections by kind: a fixed list indexed by ``Reject`` so counting allocates nothing;
    ``total`` is kept alongside, so a watchdog reads it every tick for nothing."""

    __slots__ = ("counts", "total")

    def __init__(self) -> None:
        self.counts = [0] * len(REJECT_KINDS)
        self.total = 0

    def add(self, kind: Reject) -> None:
        self.counts[kind] += 1
        self.total += 1

    def as_dict(self) -> dict[str, int]:
        return {kind.name.lower(): self.counts[kind] for kind in REJECT_KINDS}
