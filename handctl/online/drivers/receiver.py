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
#: A node counts from 0 after boot: a frame of one of these first counters may be a rebooted
#: node's stream begun again, its first frames lost on the bus (``FingerNode``)
RESTART_COUNTERS = 4
#: How many values the rolling counter (one byte) takes.
COUNTER_VALUES = 256


class CounterCheck:
    """The rolling-counter rule of one message stream.

    The first frame after start (or ``reset``) is accepted with any counter; later a repeated
    counter is rejected, and any jump other than +1 is rejected and re-synchronised to, so one
    lost frame costs the frame after it and never the whole stream.

    It also remembers, for each counter value, the last frame accepted with it and when it
    arrived (``accepted``, its receiver's to call): a frame with the counter of one accepted
    shortly before and other contents is not the same frame heard twice but a second sender
    on the stream's identifier (``FingerNode``). The last accepted frame alone was compared,
    and only on a repeat: a forged frame two counters ahead made the node's own frame of the
    first counter a skip (the counter went back), and its frame of the second one was then
    accepted in sequence, beside the forged one of that counter, ten times a second under
    the reject-rate limit (found by an outside audit). One slot per counter value: the
    history is bounded by the counter's range and indexed by it, so a look-up allocates
    nothing. A node starts its counters at 0 after boot (PROTOCOL.md): a skip to 0 followed
    by 1 is a stream begun again, whose frames contradict none from before it. And a frame
    accepted many accepted frames ago may be one the counter has come round from, however
    soon: a simulated hand starved on a loaded machine catches up
    its 1 ms ticks in a burst, 256 frames within 100 ms, and every frame of the next round
    was taken for a second sender (REJECT_RATE at start-up); with its receive queue full
    too, the host lost a hundred and more of them, so the bound is the caller's
    (``FingerNode``), far below the range.
    """

    __slots__ = (
        "_accepted",
        "_after_zero",
        "_frames",
        "_frames_ns",
        "_frames_seq",
        "before",
        "last",
    )

    def __init__(self) -> None:
        self.last: int | None = None
        self.before: int | None = None  # ``last`` before the latest frame
        self._after_zero = False  # the last frame was a skip to counter 0
        self._accepted = 0  # frames accepted on the stream
        self._frames: list[bytes | None] = [None] * COUNTER_VALUES
        self._frames_ns = [0] * COUNTER_VALUES
        self._frames_seq = [0] * COUNTER_VALUES  # ``_accepted`` when each was

    def reset(self) -> None:
        self.last = None
        self._after_zero = False
        self._frames[:] = [None] * COUNTER_VALUES

    def check(self, counter: int) -> Reject | None:
        last = self.before = self.last
        self.last = counter
        if self._after_zero:
            self._after_zero = False
            if counter == 1:  # 0, 1: the stream began again (a reboot)
                self._frames[:] = [None] * COUNTER_VALUES
        if last is None or counter == (last + 1) & 0xFF:
            return None
        if counter == last:
            return Reject.COUNTER_REPEAT
        self._after_zero = counter == 0
        return Reject.COUNTER_SKIP

    def frame_of(self, counter: int) -> bytes | None:
        """The last frame accepted with ``counter``, if any."""
        return self._frames[counter]

    def begin_again(self) -> None:
        """The stream began again (a node's reboot, ``FingerNode._rebooted_stream``): no
        frame before this one is compared with those after it."""
        self._frames[:] = [None] * COUNTER_VALUES

    def accepted(self, data: bytes, arrival_ns: int) -> None:
        """Remember ``data`` (an accepted frame, counter in byte 1) as its counter's frame."""
        self._accepted += 1
        self._frames[data[1]] = data
        self._frames_ns[data[1]] = arrival_ns
        self._frames_seq[data[1]] = self._accepted

    def contradicts(self, data: bytes, arrival_ns: int, within_ns: int, within_frames: int) -> bool:
        """Whether an intact frame has the counter of a frame accepted no more than
        ``within_ns`` before it, and fewer than ``within_frames`` accepted frames ago, and
        other contents. A skip to 0 (rejected in any case) is judged by the frame
        after it: a 1 makes it a stream begun again."""
        counter = data[1]
        earlier = self._frames[counter]
        return (
            not self._after_zero
            and earlier is not None
            and earlier != data
            and arrival_ns - self._frames_ns[counter] <= within_ns
            and self._accepted - self._frames_seq[counter] < within_frames
        )


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
