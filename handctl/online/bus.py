"""The bus as the loop sees it: open one from a spec, drain it, send on it.

Everything above this module sees ``Frame`` and ``BusEvent`` values, never python-can objects,
so the loop cannot be surprised by a python-can exception: a full transmit queue, an error frame
or a bus-off comes out as a typed event that safety can act on, and the tick goes on.

Bus specs (``--bus``) are parsed in ``handctl.online.busspec``; handctl's own unix bus is the
python-can interface in ``handctl.online.unixcan``; the virtual bus that stamps arrivals on the
receiver's clock is ``handctl.online.virtualcan``; log export is ``handctl.recording.canlog``.

Receive times: every ``Frame`` carries the time it arrived, on the clock of whoever drains it
(``HandBus.use_clock``: the driver hands over the loop's clock), never the time it was
drained, so a frame that waited in a queue is seen as old as it is. SocketCAN stamps frames in
the kernel and the unix bus asks the kernel for the same (``SO_TIMESTAMPNS``); both are
wall-clock times, converted to the loop's clock when drained. A stamp is only believed where
it can be true: after the last drain that emptied the queue (a frame read now was not there
then) and not after now. Outside that (an adapter stamping from its boot, pcan without
``uptime``; a wall-clock step between a frame's stamp and its drain, NTP or PTP) or with no
stamp, the frame is taken to have arrived at that last drain, the earliest it can have: never
younger than it is, so a stale frame cannot pass the feedback timeout, and older by the time
between two drains at most. A frame that came while the drain read is taken at the drain's
own time, as every frame at the latest. The virtual bus stamps a frame as it is put into the
receiver's queue, on the receiver's clock itself, so a lockstep run stays deterministic.

Identifiers: handctl speaks 11-bit identifiers only. A 29-bit (extended) frame keeps its
identity: its ``arbitration_id`` carries ``EXTENDED_ID_FLAG`` (SocketCAN's ``CAN_EFF_FLAG``),
so 0x181 sent as an extended frame is 0x80000181 and is never taken for ``Feedback_1``. A
remote frame (RTR) is no data frame: it comes out as a ``REMOTE_FRAME`` event, never a
``Frame`` of 0 bytes.

Receive budget: a real bus carries only so many frames a loop period (``frames_per_period``
in ``handctl/busload.py``: 27 on the default 1 Mbit/s CAN-FD bus at 1 kHz, 21 on classic CAN).
The virtual and unix buses carry any number, so the host holds every bus to that limit: its
drain takes at most the frames the bus could have carried since the previous drain, plus one
period's worth, and ``drain`` reports frames it had to leave in the queue as an
``RX_BACKLOG`` event, which the supervisor treats as a fault.
"""

from __future__ import annotations

import collections
import contextlib
import enum
import errno
import itertools
import os
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, NamedTuple, Protocol, runtime_checkable

import can

from handctl.config import MAX_STANDARD_ID, BusConfig
from handctl.errors import BusError, HandctlError, escaped
from handctl.hand_protocol import ESTOP_ID
from handctl.online import frameflags as ff
from handctl.online.busspec import (
    NO_SOCKETCAN,
    BusSpec,
    bus_kwargs,
    check_socketcan,
    parse_spec,
)
from handctl.online.taps import TAP_TX, TAP_TX_FAILED
from handctl.online.virtualcan import ArrivalStampedVirtualBus

#: Frames drained per call at most: a babbling node must not keep one tick busy forever.
DRAIN_LIMIT = 512
#: bytes, the longest payload of a CAN-FD frame
MAX_FRAME_DATA = 64
#: Set in ``Frame.arbitration_id`` (and given to ``HandBus.send``) for a 29-bit identifier, as
#: SocketCAN's ``CAN_EFF_FLAG``: an extended frame never has the id of a standard one.
EXTENDED_ID_FLAG = 0x80000000
EXTENDED_ID_MASK = 0x1FFFFFFF
#: Frames one burst holds at most on a batching transport before they go anyway (a datagram).
MAX_BURST = 32
#: python-can interfaces that hand a process back the frames it sent, unmarked (``is_rx``
#: True) and unasked: udp_multicast keeps multicast loopback on (its peers on the same
#: machine hear each other by it) and refuses ``receive_own_messages=False``'s meaning. Their
#: echoes are taken out by ``HandBus`` (``_EchoFilter``); the host took its own enable for a
#: second host's (FOREIGN_COMMAND) on every run.
ECHOING_INTERFACES = frozenset({"udp_multicast"})
#: python-can interfaces whose ``is_rx`` False marks a frame sent from this computer by any
#: program, not only this bus's own: SocketCAN (the kernel sets MSG_DONTROUTE on every local
#: socket's frame and MSG_CONFIRM on the sender's own; python-can reads ``is_rx`` from
#: MSG_DONTROUTE) and Kvaser's CANlib (``canMSG_LOCAL_TXACK``: sent by another handle on the
#: channel). handctl opens them with its own messages off, so what they hand over is never its
#: own: skipped, a second master, a ``cansend`` e-stop or ``handctl sim`` on the same computer
#: (every frame on a vcan) went unheard. The other interfaces mark ``is_rx`` False on the
#: echo of this bus's own frames only (gs_usb, pcan, vector, neovi, ...), which is skipped.
LOCAL_SENDER_INTERFACES = frozenset({"socketcan", "kvaser"})
#: Frames sent whose echo is still awaited, at most; and how far into them a frame received
#: is looked for (an echo the network lost is passed over when a later one comes).
ECHOES_HELD = 4096
ECHO_LOOKAHEAD = 64

# Linux error-frame classes (linux/can/error.h), as python-can hands them over.
_CAN_ERR_CRTL = 0x004
_CAN_ERR_BUSOFF = 0x040
_CAN_ERR_RESTARTED = 0x100
_CAN_ERR_CRTL_PASSIVE = 0x30  # rx or tx error-passive bits in data[1]
#: Flags of what a drain hands on as an event, not a frame.
_NOT_A_FRAME = ff.ERROR | ff.RX_FAILED


@runtime_checkable
class BurstTransport(Protocol):
    """A python-can bus that sends frames together at less cost than one by one (the unix
    bus: one datagram a burst). ``HandBus`` holds the frames sent with ``more=True`` and hands
    the burst over after the last; ``send_burst`` raises as ``send`` would if the transport
    refused the burst, and with no messages offers again what it still holds, if anything."""

    def send_burst(self, messages: Sequence[can.Message]) -> None: ...


@runtime_checkable
class FrameTransport(Protocol):
    """A python-can bus that also exchanges frames as plain tuples, without building a
    ``can.Message`` per frame (the unix bus): ``HandBus`` then sends and drains through these
    two, and uses python-can's ``send``/``recv`` for nothing else but error frames sent.
    Flags are ``handctl.online.frameflags``; ``send_frames`` is one burst, and raises as
    ``BurstTransport.send_burst`` does."""

    def send_frames(self, frames: Sequence[tuple[int, int, bytes]]) -> None: ...

    def recv_frame(self) -> tuple[float, int, int, bytes] | None: ...


@runtime_checkable
class ConnectingTransport(Protocol):
    """A python-can bus whose first send would look its receivers up (the unix bus):
    ``HandBus.prepare_send`` has it done beforehand."""

    def connect_peers(self) -> None: ...


@runtime_checkable
class CountingTransport(Protocol):
    """A python-can bus that keeps delivery counters of its own, for summaries."""

    def transport_counts(self) -> dict[str, int]: ...


class Frame(NamedTuple):
    """One CAN frame as the rest of handctl sees it. ``timestamp_ns`` is when it arrived, on
    the clock of the ``HandBus`` that drained it (see the module's "Receive times");
    ``arbitration_id`` has ``EXTENDED_ID_FLAG`` set for a 29-bit identifier. A named tuple,
    immutable and built for every frame drained: a frozen dataclass's constructor costs about
    four times as much."""

    arbitration_id: int
    data: bytes
    timestamp_ns: int = 0
    is_fd: bool = True


class BusEventKind(enum.Enum):
    ERROR_FRAME = "error_frame"
    ERROR_PASSIVE = "error_passive"
    BUS_OFF = "bus_off"
    BUS_RESTARTED = "bus_restarted"
    TX_QUEUE_FULL = "tx_queue_full"
    TX_FAILED = "tx_failed"
    RX_FAILED = "rx_failed"
    RX_BACKLOG = "rx_backlog"  # a drain reached its limit with frames still waiting
    FOREIGN_FRAME = "foreign_frame"  # counted by callers; kept here so one enum names them all
    #: a remote frame (RTR): a request for data, which handctl's protocol has none of; not a
    #: data frame, so never handed on as a ``Frame`` (``BusEvent.frame_id`` says its id)
    REMOTE_FRAME = "remote_frame"


@dataclass(frozen=True, slots=True)
class BusEvent:
    kind: BusEventKind
    detail: str
    timestamp_ns: int
    #: the id of the frame the event is of, as a ``Frame``'s (``EXTENDED_ID_FLAG``), if any:
    #: a remote frame's, which a peer that takes any frame on an id may act on (the nodes'
    #: e-stop, PROTOCOL.md)
    frame_id: int | None = None


#: What a frame tap is told about the frames sent (``HandBus.tap``): ``handctl.online.taps``.
#: ``tap(frames, direction)``: the ``(arbitration_id, data)`` of the frames ``send`` handed to
#: the bus (or could not), a burst at a time (the frames sent with ``more=True`` and the one
#: after them), in the order sent; a list the tap may keep. One call a burst rather than a
#: frame: called inside the tick, where every Python-level call costs about a microsecond, so
#: it must only copy and return.
FrameTap = Callable[[list[tuple[int, bytes]], int], None]
#: ``rx_tap(frames)``: the frames one ``drain`` returns, once per drain that returned any.
RxTap = Callable[[list[Frame]], None]


class _Message(can.Message):
    """A python-can message whose deep copy costs a constructor call, not the copy machinery.

    python-can's virtual bus deep-copies every frame for every receiver; the generic path
    (memo dict, a deep copy of the data bytearray) costs about 9 µs a frame, which is most of
    the bus time of a lockstep tick. The fields are plain values, so this copy is as deep.
    """

    __slots__ = ()

    def __deepcopy__(self, memo: dict[int, Any] | None) -> _Message:
        return _Message(
            timestamp=self.timestamp,
            arbitration_id=self.arbitration_id,
            is_extended_id=self.is_extended_id,
            is_remote_frame=self.is_remote_frame,
            is_error_frame=self.is_error_frame,
            channel=self.channel,
            dlc=self.dlc,
            data=bytearray(self.data),
            is_fd=self.is_fd,
            is_rx=self.is_rx,
            bitrate_switch=self.bitrate_switch,
            error_state_indicator=self.error_state_indicator,
        )


@runtime_checkable
class FrameBus(Protocol):
    """What the driver and the recorder ask of a bus: the frames that arrived, one frame sent,
    the events since the last call, and the recorder's taps. ``HandBus`` implements it over
    python-can; the re-run's ``ReplayBus`` over a recording. None of it raises: a failure is a
    False or an event, and what a tap raises is held in ``tap_error``."""

    tap: FrameTap | None
    rx_tap: RxTap | None
    event_tap: Callable[[BusEvent], None] | None
    #: The first exception a tap raised, held for the taps' owner to take and raise in its
    #: own stage (the recorder, in its push: a RECORD_EXCEPTION); None: none. Let out of
    #: ``send``, it made the sender take a frame that went for one that did not: its counter
    #: given back, the node rejected the next frame, the stop's zero torque (found by an
    #: outside audit).
    tap_error: BaseException | None
    #: Whether ``send(..., more=True)`` holds a frame for its burst (its True says nothing of
    #: the frame's fate, the burst's last send or ``flush`` does) rather than sending it.
    batching: bool

    def prepare_send(self) -> None:
        """Do now what the first send would (look the receivers up), while there is time."""

    def use_clock(self, clock_ns: Callable[[], int]) -> None: ...

    def drain(self, limit: int = DRAIN_LIMIT) -> list[Frame]: ...

    def send(self, arbitration_id: int, data: bytes, more: bool = False) -> bool: ...

    def flush(self) -> bool: ...

    def drop_burst(self) -> int:
        """Drop the frames ``send(..., more=True)`` holds for the burst under way, unsent and
        untapped; how many (always 0 on a bus that is not ``batching``)."""

    def events(self) -> list[BusEvent]: ...

    def close(self) -> None: ...


class _EchoFilter:
    """The frames a process sent, awaited back from a bus that echoes them
    (``ECHOING_INTERFACES``). An echo comes back in the order sent, between other senders'
    frames; one the network lost is passed over when a later one arrives. A frame of another
    sender that is byte for byte one this process sent (counter and CRC alike) is taken for
    its echo: it says nothing this process did not already say."""

    def __init__(self) -> None:
        self._sent: collections.deque[tuple[int, bytes]] = collections.deque(maxlen=ECHOES_HELD)

    def sent(self, arbitration_id: int, data: bytes) -> None:
        self._sent.append((arbitration_id, bytes(data)))

    def is_echo(self, arbitration_id: int, data: bytes) -> bool:
        sent = self._sent
        for k, frame in enumerate(itertools.islice(sent, ECHO_LOOKAHEAD)):
            if frame[0] == arbitration_id and frame[1] == data:
                for _ in range(k + 1):
                    sent.popleft()
                return True
        return False


class HandBus:
    """A python-can bus behind a small, never-raising interface for the loop (``FrameBus``)."""

    def __init__(
        self,
        bus: can.BusABC,
        spec: BusSpec,
        fd: bool,
        clock_ns: Callable[[], int] = time.monotonic_ns,
    ) -> None:
        self._bus = bus
        self.spec = spec
        self.fd = fd
        self._clock_ns = clock_ns
        self._events: list[BusEvent] = []
        self.sent = 0
        #: Frames that did not go: refused sends, and every frame of a burst the transport
        #: refused at its end.
        self.tx_failed = 0
        self.received = 0
        self.closed = False
        self._bursts = bus if isinstance(bus, BurstTransport) else None
        self._frames = bus if isinstance(bus, FrameTransport) else None
        self.batching = self._frames is not None or self._bursts is not None
        self._connecting = bus if isinstance(bus, ConnectingTransport) else None
        #: The flags of every frame this bus sends (``FrameTransport``).
        self._send_flags = ff.FD | ff.BRS if fd else 0
        # The burst under way on a BurstTransport, held until flush: its frames for the counts
        # and the taps, and the messages for the transport (error frames too).
        self._burst: list[tuple[int, bytes]] = []
        self._burst_messages: list[can.Message] = []
        # A virtual bus stamps arrivals on this bus's clock; the others in wall-clock time.
        self._take = bus.take if isinstance(bus, ArrivalStampedVirtualBus) else None
        #: One frame sent without a python-can Message to handctl's own receivers (the
        #: arrival-stamped virtual bus), raising as python-can's ``send`` would.
        self._send_frame = bus.send_frame if isinstance(bus, ArrivalStampedVirtualBus) else None
        if isinstance(bus, ArrivalStampedVirtualBus):
            bus.clock_ns = self._now_ns
        #: The frame a drain read past its limit, to tell whether frames were left: the
        #: first of the next drain. ``(arrival_ns, arbitration_id, flags, data)``.
        self._lookahead: tuple[int, int, int, bytes] | None = None
        #: When the last drain that emptied the queue began, on this bus's clock: every frame
        #: read since arrived after it (``_late_arrival_ns``). None before the first.
        self._emptied_ns: int | None = None
        #: The recorder's taps: every frame drained or sent, and every event as it is taken.
        self.tap: FrameTap | None = None
        #: Frames sent at once on a bus that does not batch, not yet tapped: their burst's
        #: ``send(..., more=False)``, a ``flush`` or a drain hands them to ``tap`` together.
        self._tapped: list[tuple[int, bytes]] = []
        self.rx_tap: RxTap | None = None
        self.event_tap: Callable[[BusEvent], None] | None = None
        self.tap_error: BaseException | None = None
        self._echoes = _EchoFilter() if spec.interface in ECHOING_INTERFACES else None
        #: Whether ``is_rx`` False is the echo of its own frame (``LOCAL_SENDER_INTERFACES``).
        self._skip_not_rx = spec.interface not in LOCAL_SENDER_INTERFACES

    def prepare_send(self) -> None:
        """Whatever the transport would do on its first send and can do before it (connect to
        its receivers), so that the first send costs what later ones do; never raises."""
        if self._connecting is not None:
            with contextlib.suppress(Exception):
                self._connecting.connect_peers()

    def use_clock(self, clock_ns: Callable[[], int]) -> None:
        """Stamp arrivals and events on ``clock_ns`` (the loop's clock) from now on."""
        self._clock_ns = clock_ns
        self._emptied_ns = None  # a time on the clock before

    def _now_ns(self) -> int:
        return self._clock_ns()

    def _receive(
        self, wall_to_clock_ns: int, earliest_ns: int, now_ns: int
    ) -> tuple[int, int, int, bytes] | None:
        """The next frame, ``(arrival_ns, arbitration_id, flags, data)`` with its arrival
        on this bus's clock, or None; ``earliest_ns`` and ``now_ns`` are ``_late_arrival_ns``'s."""
        if self._frames is not None:
            raw = self._frames.recv_frame()
            if raw is None:
                return None
            stamp_s, frame_id, flags, data = raw
            # the stamp believed inline where it can be true: this is every frame of a
            # real-time run
            arrival = round(stamp_s * 1e9) + wall_to_clock_ns
            if not (stamp_s > 0 and earliest_ns <= arrival <= now_ns):
                arrival = self._late_arrival_ns(stamp_s, arrival, earliest_ns, now_ns)
            return arrival, frame_id, flags, data
        if self._take is not None:
            item = self._take()
            if item is None:
                return None
            stamp, msg = item
            if isinstance(msg, tuple):  # from handctl's own sender: (id, flags, data) already
                frame_id, flags, data = msg
                return stamp, frame_id, flags, data
        else:
            received = self._bus.recv(timeout=0)
            # An adapter that echoes what this process sent (python-can marks the echo
            # ``is_rx`` False: gs_usb, neovi) hands back the host's own commands, which are
            # neither news of the hand nor another sender's. Not so on SocketCAN, where
            # ``is_rx`` False is any program's on this computer (``LOCAL_SENDER_INTERFACES``).
            while received is not None and (
                (self._skip_not_rx and not received.is_rx)
                or (self._echoes is not None and self._is_echo(received))
            ):
                received = self._bus.recv(timeout=0)
            if received is None:
                return None
            msg = received
            stamp = round(received.timestamp * 1e9) + wall_to_clock_ns
            if not (received.timestamp > 0 and earliest_ns <= stamp <= now_ns):
                stamp = self._late_arrival_ns(received.timestamp, stamp, earliest_ns, now_ns)
        return stamp, msg.arbitration_id, ff.flags_of(msg), bytes(msg.data)

    def _is_echo(self, msg: can.Message) -> bool:
        assert self._echoes is not None
        frame_id = msg.arbitration_id
        if msg.is_extended_id:
            frame_id = (frame_id & EXTENDED_ID_MASK) | EXTENDED_ID_FLAG
        return self._echoes.is_echo(frame_id, bytes(msg.data))

    def _late_arrival_ns(self, stamp_s: float, arrival: int, earliest_ns: int, now_ns: int) -> int:
        """The arrival of a frame whose stamp (s; ``arrival`` on this bus's clock) is not
        between ``earliest_ns``, when the last drain that emptied the queue began (-1 before
        the first: any time), and ``now_ns``, when this one began.

        A frame that came while this drain read the frames before it has a stamp after
        ``now_ns`` and before its reading: it arrived as the drain began, as every frame the
        drain reads is taken to at the latest (taken for the last drain's, it was a whole
        drain interval older than it is, and at 250 Hz one tick a millisecond late was a
        FEEDBACK_TIMEOUT: found by an outside audit). Any other stamp is on another clock (an
        adapter's from its boot: every frame looked seconds old and the run never started)
        or the wall clock stepped since it was taken (+0.5 s: a FEEDBACK_TIMEOUT mid-grasp;
        backwards: a stale frame taken for a fresh one), and the frame gets ``earliest_ns``
        (``now_ns`` before the first drain): older than it is by a drain interval at most,
        never younger; the time of reading would hide a wait in the queue. An interface that
        stamps nothing (0) gets the same."""
        if stamp_s > 0 and now_ns < arrival <= self._clock_ns():
            return now_ns
        return earliest_ns if earliest_ns >= 0 else now_ns

    def drain(self, limit: int = DRAIN_LIMIT) -> list[Frame]:
        """The frames that have arrived, ``limit`` at most, without waiting; error frames
        become events. Frames still waiting after ``limit`` are an ``RX_BACKLOG`` event."""
        frames: list[Frame] = []
        now = self._clock_ns()
        # Wall-clock arrival stamps (kernel, adapter) onto this bus's clock, where they can
        # be true (``_late_arrival_ns``): never later than now, so an adapter whose clock runs
        # ahead cannot make a frame look younger, nor before the last drain that emptied the
        # queue (none yet: -1, any time).
        wall_to_clock = now - time.time_ns()
        earliest = -1 if self._emptied_ns is None else self._emptied_ns
        item, self._lookahead = self._lookahead, None
        count = 0
        try:
            while True:
                if item is None:
                    item = self._receive(wall_to_clock, earliest, now)
                    if item is None:
                        self._emptied_ns = now  # whatever comes later arrived after now
                        break
                if count == limit:  # one more was waiting: keep it for the next drain
                    self._lookahead = item
                    self._event(BusEventKind.RX_BACKLOG, f"{limit} frames drained and more waiting")
                    break
                count += 1
                stamp, frame_id, flags, data = item
                item = None
                if flags & _NOT_A_FRAME:
                    if flags & ff.RX_FAILED:  # the transport dropped what it received
                        self._event(BusEventKind.RX_FAILED, data.decode("utf-8", "replace"))
                    else:
                        self._error_frame(frame_id, data)
                    continue
                if len(data) > MAX_FRAME_DATA:
                    # no CAN-FD frame is longer; an emulated bus (the unix one, python-can's
                    # virtual one) carries it all the same. Acted on, it was logged cut to 64
                    # bytes, and the log's re-run then differed from the run
                    self._event(
                        BusEventKind.RX_FAILED,
                        f"a frame of {len(data)} bytes (id 0x{frame_id:X}), longer than "
                        f"CAN-FD's {MAX_FRAME_DATA}: dropped",
                    )
                    continue
                widest = EXTENDED_ID_MASK if flags & ff.EXTENDED else MAX_STANDARD_ID
                if not 0 <= frame_id <= widest:
                    # no CAN frame carries it; an emulated bus (a peer on the unix or the
                    # virtual one) does. Logged as it came, it made the run's own log one
                    # that ``replay`` refuses; masked to fit, it would be another id's frame
                    self._event(
                        BusEventKind.RX_FAILED,
                        f"a frame with id 0x{frame_id:X}, beyond the "
                        f"{29 if flags & ff.EXTENDED else 11} bits of its format: dropped",
                    )
                    continue
                if flags & ff.EXTENDED:
                    frame_id |= EXTENDED_ID_FLAG
                if flags & ff.REMOTE:
                    # no data: handed on as a frame of 0 bytes it was a data frame, and on
                    # id 0x000 an EStop of none, logged as a data frame
                    self._events.append(
                        BusEvent(
                            BusEventKind.REMOTE_FRAME,
                            _remote_text(frame_id),
                            min(stamp, now),
                            frame_id,
                        )
                    )
                    continue
                self.received += 1
                frames.append(Frame(frame_id, data, min(stamp, now), bool(flags & ff.FD)))
        except (can.CanError, OSError, ValueError) as exc:
            self._event(BusEventKind.RX_FAILED, str(exc))
        if frames and self.rx_tap is not None:
            if self._tapped:  # sent before this drain: tapped before it, in bus order
                self._tap_sent()
            try:
                self.rx_tap(frames)
            except BaseException as exc:  # the frames were drained all the same
                self._tap_failed(exc)
        return frames

    def send(self, arbitration_id: int, data: bytes, more: bool = False) -> bool:
        """Send one frame without blocking; on failure record an event and return False.

        ``more=True`` says another frame of the same burst follows at once, so for a batching
        transport (``BurstTransport``) this one is held until the last (``more=False``) or ``flush``
        (at most ``MAX_BURST`` frames): ``send`` returns True for it, and it is counted and
        tapped when the burst goes, with the burst's fate. On other buses every frame goes at
        once, and the tap hears the burst's frames together after its last.
        """
        if self._frames is not None or self._bursts is not None:
            self._burst.append((arbitration_id, data))
            if self._frames is None:  # a BurstTransport takes python-can Messages
                self._burst_messages.append(self._message(arbitration_id, data))
            if more and len(self._burst) < MAX_BURST:
                return True
            return self.flush()
        try:
            if self._send_frame is None:
                if self._echoes is not None:
                    self._echoes.sent(arbitration_id, data)
                self._bus.send(self._message(arbitration_id, data), timeout=0)
            elif arbitration_id & EXTENDED_ID_FLAG:
                self._send_frame(
                    arbitration_id & EXTENDED_ID_MASK, self._send_flags | ff.EXTENDED, data
                )
            else:
                self._send_frame(arbitration_id, self._send_flags, data)
        except (can.CanError, OSError, ValueError) as exc:
            self._tx_error(exc)
            self.tx_failed += 1
            if self._tapped:
                self._tap_sent()
            self._tell_tap([(arbitration_id, data)], TAP_TX_FAILED)
            return False
        self.sent += 1
        if self.tap is not None:
            tapped = self._tapped
            tapped.append((arbitration_id, data))
            if not more or len(tapped) >= MAX_BURST:  # ``_tap_sent``, inline: every tick's
                self._tapped = []
                try:
                    self.tap(tapped, TAP_TX)
                except BaseException as exc:  # the frame went: its counter is used up
                    self._tap_failed(exc)
        return True

    def _tap_sent(self) -> None:
        """Hand the frames sent and not yet tapped to ``tap``."""
        tapped, self._tapped = self._tapped, []
        self._tell_tap(tapped, TAP_TX)

    def _tell_tap(self, frames: list[tuple[int, bytes]], direction: int) -> None:
        """``tap(frames, direction)``, if there is a tap; what it raises is held."""
        if self.tap is not None:
            try:
                self.tap(frames, direction)
            except BaseException as exc:
                self._tap_failed(exc)

    def _tap_failed(self, exc: BaseException) -> None:
        """Hold the first exception a tap raised for the taps' owner (``tap_error``), whatever
        it is: a SystemExit or an interrupt let out of ``send`` gave back the counter of a
        frame that went, as any exception did (found by an outside audit). The owner raises
        it at the end of the tick's record (``Recorder.push``)."""
        if self.tap_error is None:
            self.tap_error = exc

    def _message(self, arbitration_id: int, data: bytes) -> can.Message:
        """The python-can Message of a frame this bus sends (a transport that takes Messages)."""
        extended = bool(arbitration_id & EXTENDED_ID_FLAG)
        return _Message(
            arbitration_id=arbitration_id & EXTENDED_ID_MASK if extended else arbitration_id,
            data=data,
            is_extended_id=extended,
            is_fd=self.fd,
            bitrate_switch=self.fd,
            check=False,
        )

    def flush(self) -> bool:
        """End a burst: a batching transport sends the frames ``send(..., more=True)`` held
        (and offers again what receivers with a full queue were still owed).

        False, with a TX_QUEUE_FULL (or TX_FAILED) event, if the transport refused the burst:
        each of its frames is then counted in ``tx_failed`` and tapped as failed. Other buses
        send at once: only the tap of the frames sent since the last burst ended is due.
        """
        if self._bursts is None and self._frames is None:
            if self._tapped:
                self._tap_sent()
            return True
        burst, self._burst = self._burst, []
        messages, self._burst_messages = self._burst_messages, []
        ok = True
        try:
            if self._frames is not None:
                flags = self._send_flags
                self._frames.send_frames(
                    [
                        (i & EXTENDED_ID_MASK, flags | ff.EXTENDED, data)
                        if i & EXTENDED_ID_FLAG
                        else (i, flags, data)
                        for i, data in burst
                    ]
                )
            else:
                assert self._bursts is not None
                self._bursts.send_burst(messages)
        except (can.CanError, OSError, ValueError) as exc:
            self._tx_error(exc)
            ok = False
        if ok:
            self.sent += len(burst)
        else:
            self.tx_failed += len(burst)
        if burst:
            self._tell_tap(burst, TAP_TX if ok else TAP_TX_FAILED)
        return ok

    def drop_burst(self) -> int:
        """Drop the frames held for the burst under way, unsent and untapped: how many.

        For a sender whose burst broke off (``HandDriver.send``, an exception between its
        frames), which gives their counters back: held, they went with the next send, the
        stop's first zero torque, so a node got the torque of the tick that raised after the
        exception and rejected the zero that followed on the same counter (found by an
        outside audit). They never reached the bus, so nothing counts or taps them.
        """
        dropped = len(self._burst)
        self._burst = []
        self._burst_messages = []
        return dropped

    def _tx_error(self, exc: Exception) -> None:
        if isinstance(exc, can.CanOperationError):
            full = exc.error_code == errno.ENOBUFS or "No buffer space" in str(exc)
            self._event(BusEventKind.TX_QUEUE_FULL if full else BusEventKind.TX_FAILED, str(exc))
        else:
            self._event(BusEventKind.TX_FAILED, f"{type(exc).__name__}: {exc}")

    def transport_counts(self) -> dict[str, int]:
        """The transport's own delivery counters, for summaries (``CountingTransport``; the
        unix bus's datagrams, full queues and held frames). Empty for buses that keep none."""
        bus = self._bus
        return bus.transport_counts() if isinstance(bus, CountingTransport) else {}

    def send_error_frame(self, error_class: int = _CAN_ERR_CRTL, data: bytes = bytes(8)) -> bool:
        """Put an error frame on the bus (fault injection on virtual buses only).

        ``error_class`` is the Linux error class (0x004 controller, 0x040 bus-off,
        0x100 restarted), as a SocketCAN adapter would report it. On a batching transport it
        ends the burst under way.
        """
        msg = _Message(
            arbitration_id=error_class,
            is_error_frame=True,
            is_extended_id=False,
            data=data,
            check=False,
        )
        if self._frames is not None and self._burst:
            self.flush()  # the frames held go first, in order
        if self._bursts is not None and self._frames is None:
            self._burst_messages.append(msg)
            return self.flush()
        try:
            self._bus.send(msg, timeout=0)
        except (can.CanError, OSError, ValueError):
            return False
        return True

    def events(self) -> list[BusEvent]:
        """Take the events since the last call."""
        events, self._events = self._events, []
        if self.event_tap is not None:
            for event in events:
                try:
                    self.event_tap(event)
                except BaseException as exc:  # the events are the caller's all the same
                    self._tap_failed(exc)
        return events

    def close(self) -> None:
        if not self.closed:
            if self._burst_messages or self._burst:
                self.flush()
            self.closed = True
            self._bus.shutdown()

    def __enter__(self) -> HandBus:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _event(self, kind: BusEventKind, detail: str) -> None:
        self._events.append(BusEvent(kind, detail, self._clock_ns()))

    def _error_frame(self, cls: int, data: bytes) -> None:
        if cls & _CAN_ERR_BUSOFF:
            self._event(BusEventKind.BUS_OFF, f"error class 0x{cls:X}")
        elif cls & _CAN_ERR_RESTARTED:
            self._event(BusEventKind.BUS_RESTARTED, f"error class 0x{cls:X}")
        elif cls & _CAN_ERR_CRTL and len(data) > 1 and data[1] & _CAN_ERR_CRTL_PASSIVE:
            self._event(BusEventKind.ERROR_PASSIVE, f"controller 0x{data[1]:02X}")
        else:
            self._event(BusEventKind.ERROR_FRAME, f"error class 0x{cls:X}")


def _errno_of(exc: BaseException) -> int | None:
    """The errno of ``exc`` or of what it was raised from (python-can wraps an OSError)."""
    while exc is not None:
        if isinstance(exc, OSError) and exc.errno is not None:
            return exc.errno
        code = getattr(exc, "error_code", None)
        if isinstance(code, int):
            return code
        exc = exc.__cause__ or exc.__context__  # type: ignore[assignment]
    return None


def open_bus(
    spec: str | BusSpec, bus_config: BusConfig, options: dict[str, Any] | None = None
) -> HandBus:
    """Open the bus named by ``spec``; every failure is a ``BusError`` that says what to do.

    ``options`` go to the python-can constructor unchanged (e.g. ``rx_queue_size`` of the
    virtual bus, or an adapter's own timing arguments).
    """
    parsed = spec if isinstance(spec, BusSpec) else parse_spec(spec, bus_config)
    if parsed.interface == "sim":
        raise BusError(
            "bus spec 'sim' is resolved by the caller: start the simulated hand and "
            "open its virtual channel"
        )
    if parsed.interface == "socketcan" and os.name == "posix":
        check_socketcan(parsed.channel, bus_config)
    kwargs = bus_kwargs(parsed, bus_config)
    kwargs.update(options or {})
    try:
        if parsed.interface == "virtual":
            del kwargs["interface"]
            bus: can.BusABC = ArrivalStampedVirtualBus(**kwargs)
        else:
            bus = can.Bus(**kwargs)
    except HandctlError:
        raise  # handctl's own (the unix bus's), already saying what is wrong
    except Exception as exc:
        # A third-party backend raises what it likes: kvaser without its library a
        # NameError, socketcand without host and port a TypeError. Each is this bus not
        # opening, said with the spec; an interrupt (not an Exception) still interrupts.
        hint = ""
        if parsed.interface == "socketcan" and _errno_of(exc) == errno.EAFNOSUPPORT:
            hint = f": {NO_SOCKETCAN}"
        raise BusError(
            f"{parsed}: cannot open the bus: {type(exc).__name__}: {escaped(str(exc))}{hint}"
        ) from None
    if bus_config.fd and _says_classic(bus):
        bus.shutdown()
        raise BusError(
            f"{parsed}: the hand config's bus is CAN FD (bus.fd: true), and this bus carries "
            "classic CAN 2.0 frames only (python-can's protocol for it: CAN_20): use an "
            f"adapter and a python-can interface that do CAN FD, not {parsed.interface}"
        )
    return HandBus(bus, parsed, bus_config.fd)


def _says_classic(bus: can.BusABC) -> bool:
    """Whether the backend itself said the opened bus is classic CAN 2.0 (``protocol``,
    python-can 4.x: gs_usb and slcan always, pcan or vector as they could open it). A bus
    that cannot carry the hand's CAN FD frames fails every send, and the run fails at
    start-up with the bus's errors, not saying why. Only what the backend set counts:
    python-can's default for a backend that never says is CAN_20 too (socketcand, a
    third-party interface), and that is no reason to refuse it."""
    return "_can_protocol" in vars(bus) and bus.protocol is can.CanProtocol.CAN_20


def _remote_text(frame_id: int) -> str:
    """What a remote frame is, for its event: by its id as the wire carries it."""
    if frame_id & EXTENDED_ID_FLAG:
        wire = f"0x{frame_id & EXTENDED_ID_MASK:08X} (29-bit)"
    else:
        wire = f"0x{frame_id:03X}"
    if frame_id == ESTOP_ID:
        # the nodes act on any frame on the e-stop's id, a remote one too (PROTOCOL.md): said
        # as harmless, it had e-stopped them (found by an outside audit)
        return (
            f"a remote frame (RTR) on id {wire}, the e-stop's: not taken as a data frame by "
            "the host, but every node acts on any frame on that id (PROTOCOL.md) and latches "
            "FAULT (ESTOP)"
        )
    return (
        f"a remote frame (RTR) on id {wire}: a request for data, which handctl's protocol has "
        "none of; not taken as a data frame"
    )
