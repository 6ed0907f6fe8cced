"""The only module that imports python-can: open a bus from a spec, drain it, send on it.

Everything above this module sees ``Frame`` and ``BusEvent`` values, never python-can objects,
so the loop cannot be surprised by a python-can exception: a full transmit queue, an error frame
or a bus-off comes out as a typed event that safety can act on, and the tick goes on.

Bus specs:
- ``sim``: the simulated hand. Resolved by the caller (the CLI starts the simulated hand as a
  peer on a private virtual channel and opens ``virtual:<that channel>`` here), because the
  online plane never imports the simulation.
- ``hand``: the interface and channel written in the hand config's ``bus`` section.
- ``virtual:NAME``: python-can's in-process virtual bus (tests, lockstep runs).
- ``socketcan:can0``: a Linux SocketCAN interface. The kernel owns its bit rates; handctl checks
  that the interface exists and says how to configure it when it does not.
- ``unix:DIRECTORY``: handctl's own python-can interface over Unix datagram sockets, one per
  participant in DIRECTORY: a bus that crosses processes on one machine without a kernel CAN
  driver or any network traffic (the simulated hand in its own process, kill tests).
- ``INTERFACE:CHANNEL``: any other python-can interface, given the config's CAN-FD bit rates.

Receive times: every ``Frame`` carries the time it arrived, on the clock of whoever drains it
(``HandBus.use_clock``: the driver hands over the loop's clock), never the time it was
drained, so a frame that waited in a queue is seen as old as it is. SocketCAN stamps frames in
the kernel and the unix bus asks the kernel for the same (``SO_TIMESTAMPNS``); both are
wall-clock times, converted to the loop's clock when drained. The virtual bus stamps a frame
as it is put into the receiver's queue, on the receiver's clock itself, so a lockstep run
stays deterministic.

Identifiers: handctl speaks 11-bit identifiers only. A 29-bit (extended) frame keeps its
identity: its ``arbitration_id`` carries ``EXTENDED_ID_FLAG`` (SocketCAN's ``CAN_EFF_FLAG``),
so 0x181 sent as an extended frame is 0x80000181 and is never taken for ``Feedback_1``.

Receive budget: a real bus carries only so many frames a loop period (``frames_per_period``
in ``handctl/busload.py``: 27 on the default 1 Mbit/s CAN-FD bus at 1 kHz, 21 on classic CAN).
The virtual and unix buses carry any number, so the host holds every bus to that limit: its
drain takes at most the frames the bus could have carried since the previous drain, plus one
period's worth, and ``drain`` reports frames it had to leave in the queue as an
``RX_BACKLOG`` event, which the supervisor treats as a fault.
"""

from __future__ import annotations

import contextlib
import enum
import errno
import itertools
import os
import queue
import select
import socket
import struct
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import can
from can.interfaces import virtual as _virtual

from handctl.config import BusConfig
from handctl.errors import BusError, ConfigError
from handctl.taps import TAP_TX, TAP_TX_FAILED

#: Frames drained per call at most: a babbling node must not keep one tick busy forever.
DRAIN_LIMIT = 512
#: Set in ``Frame.arbitration_id`` (and given to ``HandBus.send``) for a 29-bit identifier, as
#: SocketCAN's ``CAN_EFF_FLAG``: an extended frame never has the id of a standard one.
EXTENDED_ID_FLAG = 0x80000000
_EXTENDED_ID_MASK = 0x1FFFFFFF
#: ``SO_TIMESTAMPNS`` (Linux, asm-generic; Python's socket module does not name it): the
#: kernel stamps each datagram as it is queued for the receiving socket.
_SO_TIMESTAMPNS = getattr(socket, "SO_TIMESTAMPNS", 35)
_TIMESPEC = struct.Struct("@qq")
#: Frames one burst holds at most on a batching transport before they go anyway (a datagram).
MAX_BURST = 32

# Linux error-frame classes (linux/can/error.h), as python-can hands them over.
_CAN_ERR_CRTL = 0x004
_CAN_ERR_BUSOFF = 0x040
_CAN_ERR_RESTARTED = 0x100
_CAN_ERR_CRTL_PASSIVE = 0x30  # rx or tx error-passive bits in data[1]


@dataclass(frozen=True, slots=True)
class Frame:
    """One CAN frame as the rest of handctl sees it. ``timestamp_ns`` is when it arrived, on
    the clock of the ``HandBus`` that drained it (see the module's "Receive times");
    ``arbitration_id`` has ``EXTENDED_ID_FLAG`` set for a 29-bit identifier."""

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


@dataclass(frozen=True, slots=True)
class BusEvent:
    kind: BusEventKind
    detail: str
    timestamp_ns: int


#: What a frame tap is told about each frame (``HandBus.tap``): ``handctl.taps``.
#: ``tap(arbitration_id, data, direction)``: each frame ``send`` handed to the bus (or could
#: not). Called inside the tick, so it must only copy and return.
FrameTap = Callable[[int, bytes, int], None]
#: ``rx_tap(frames)``: the frames one ``drain`` returns, once per drain that returned any.
RxTap = Callable[[list[Frame]], None]


@dataclass(frozen=True)
class BusSpec:
    interface: str
    channel: str

    def __str__(self) -> str:
        return f"{self.interface}:{self.channel}" if self.channel else self.interface


def parse_spec(spec: str, bus_config: BusConfig | None = None) -> BusSpec:
    """Split ``INTERFACE:CHANNEL``; ``hand`` takes both from the hand config."""
    if spec == "sim":
        return BusSpec("sim", "")
    if spec == "hand":
        if bus_config is None:
            raise BusError("bus spec 'hand' needs a hand config")
        return BusSpec(bus_config.interface, bus_config.channel)
    interface, sep, channel = spec.partition(":")
    if not sep or not interface or not channel:
        raise ConfigError("--bus", "", "sim, hand, or INTERFACE:CHANNEL (e.g. socketcan:can0, "
                          "virtual:test)", spec)
    if interface not in can.VALID_INTERFACES and interface != "unix":
        raise ConfigError("--bus", "interface",
                          "a python-can interface (" + ", ".join(sorted(can.VALID_INTERFACES))
                          + ")", interface)
    return BusSpec(interface, channel)


def bus_kwargs(spec: BusSpec, bus_config: BusConfig) -> dict[str, Any]:
    """The python-can constructor arguments for ``spec`` under the hand's bus settings."""
    kwargs: dict[str, Any] = {"interface": spec.interface, "channel": spec.channel}
    if spec.interface == "unix":
        kwargs["receive_own_messages"] = False
    elif spec.interface == "virtual":
        kwargs["receive_own_messages"] = False
        kwargs["protocol"] = can.CanProtocol.CAN_FD if bus_config.fd else can.CanProtocol.CAN_20
    elif spec.interface == "socketcan":
        # Bit rates of a SocketCAN interface are set with `ip link`, not by the process.
        kwargs["fd"] = bus_config.fd
    elif spec.interface == "udp_multicast":
        kwargs["fd"] = bus_config.fd
        kwargs["receive_own_messages"] = False
    else:
        kwargs["fd"] = bus_config.fd
        kwargs["bitrate"] = bus_config.bitrate
        if bus_config.fd and bus_config.data_bitrate:
            kwargs["data_bitrate"] = bus_config.data_bitrate
    return kwargs


def socketcan_setup_command(channel: str, bus_config: BusConfig) -> str:
    """The `ip link` command that brings a SocketCAN interface up with the hand's bit rates."""
    cmd = f"sudo ip link set {channel} up type can bitrate {bus_config.bitrate}"
    if bus_config.fd:
        cmd += f" dbitrate {bus_config.data_bitrate} fd on"
    return cmd


def check_socketcan(channel: str, bus_config: BusConfig, sysfs: Path = Path("/sys/class/net"),
                    ) -> None:
    """Refuse a SocketCAN channel that is missing or down, with the command that fixes it."""
    node = sysfs / channel
    hint = socketcan_setup_command(channel, bus_config)
    if not node.exists():
        raise BusError(f"socketcan:{channel}: no such network interface; load the driver and "
                       f"configure it with: {hint}")
    operstate = (node / "operstate").read_text().strip() if (node / "operstate").exists() else ""
    if operstate == "down":
        raise BusError(f"socketcan:{channel}: interface is down; bring it up with: {hint}")


class _Message(can.Message):
    """A python-can message whose deep copy costs a constructor call, not the copy machinery.

    python-can's virtual bus deep-copies every frame for every receiver; the generic path
    (memo dict, a deep copy of the data bytearray) costs about 9 µs a frame, which is most of
    the bus time of a lockstep tick. The fields are plain values, so this copy is as deep.
    """

    __slots__ = ()

    def __deepcopy__(self, memo: dict[int, Any] | None) -> _Message:
        return _Message(
            timestamp=self.timestamp, arbitration_id=self.arbitration_id,
            is_extended_id=self.is_extended_id, is_remote_frame=self.is_remote_frame,
            is_error_frame=self.is_error_frame, channel=self.channel, dlc=self.dlc,
            data=bytearray(self.data), is_fd=self.is_fd, is_rx=self.is_rx,
            bitrate_switch=self.bitrate_switch,
            error_state_indicator=self.error_state_indicator)


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


#: Per frame: the sender's time (s; diagnostics only: a frame is stamped on arrival by the
#: receiver's kernel), arbitration id, flags, data length; then the data.
_WIRE = struct.Struct("<dIBB")
_FD, _BRS, _ERR, _ESI, _EXT = 1, 2, 4, 8, 16
_unix_ids = itertools.count()
#: Frames per datagram at most; a burst beyond it goes out in several datagrams.
_BATCH = 32
#: Frames held at most for one receiver whose queue is full (a CAN controller's transmit
#: queue). A burst that does not fit any more is refused whole with ENOBUFS. Small on purpose:
#: a receiver's socket queue already holds ten bursts or more; this is slack for a moment,
#: and a receiver that stopped reading must still be reported within a few dozen ticks (the
#: host's BUS_ERROR after consecutive failed sends), not hidden behind a deep queue.
TX_QUEUE_FRAMES = 64
#: How long ``shutdown`` keeps offering held frames to receivers that are still reading.
_SHUTDOWN_S = 0.02


class TransmitQueueFull(can.CanOperationError):
    """A burst refused because a receiver's transmit queue is full: ``frames`` were dropped."""

    def __init__(self, frames: int, receivers: int) -> None:
        super().__init__(f"No buffer space available: {frames} frames dropped, the transmit "
                         f"queue to {receivers} receiver(s) is full", error_code=errno.ENOBUFS)
        self.frames = frames


class UnixDatagramBus(can.BusABC):
    """A CAN bus between processes of one machine: each participant binds a datagram socket in
    the channel directory and sends every frame to all the other sockets there.

    Frames sent together (one tick's commands, one node tick's frames) travel as one datagram:
    Linux queues only ``net.unix.max_dgram_qlen`` datagrams per receiving socket (often 10),
    whatever their size and whoever sent them, and no socket buffer size lifts that. ``send``
    queues a frame and ``flush`` sends the batch; ``HandBus`` flushes after the last frame of
    a burst.

    A receiver whose queue is full does not lose what it was sent, as a CAN controller does
    not drop a frame it took for transmission but retries arbitration: the frames wait in a
    transmit queue for that receiver and go first, merged into as few datagrams as fit, at the
    next ``flush``. Only a burst that no longer fits that queue (``TX_QUEUE_FRAMES``: a
    receiver that stopped reading) is refused, whole, with ``TransmitQueueFull`` (ENOBUFS), as
    a full transmit queue refuses a frame on SocketCAN. ``queue_full`` counts the times a
    receiver's queue was found full, ``frames_dropped`` the frames refused (for one receiver
    or more). A socket whose owner died (SIGKILL) refuses delivery and is removed with what
    was held for it, so a killed peer does not wedge the bus.
    """

    def __init__(self, channel: str, receive_own_messages: bool = False,
                 rcvbuf: int = 1 << 22, **kwargs: Any) -> None:
        self.directory = Path(channel)
        self.directory.mkdir(parents=True, exist_ok=True)
        self.channel_info = f"unix:{channel}"
        self._path = self.directory / f"{os.getpid()}-{next(_unix_ids)}.sock"
        self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        with _suppress_oserror():
            self._sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, rcvbuf)
        # The kernel stamps each datagram as it arrives: the time a frame reached this
        # participant, however long it then waits to be read. (A kernel without it leaves
        # the time of reading, which makes frames look younger: Linux has it.)
        with _suppress_oserror():
            self._sock.setsockopt(socket.SOL_SOCKET, _SO_TIMESTAMPNS, 1)
        self._sock.bind(str(self._path))
        self._sock.setblocking(False)
        self._own = receive_own_messages
        self._peers: list[str] = []
        self._peers_at = 0.0
        self._pending: list[bytes] = []
        self._held: dict[str, list[bytes]] = {}  # per receiver: frames its full queue refused
        self._inbox: list[can.Message] = []
        self._can_protocol = can.CanProtocol.CAN_FD
        self.datagrams_sent = 0
        self.queue_full = 0
        self.frames_dropped = 0
        super().__init__(channel=channel, **kwargs)

    @property
    def held(self) -> int:
        """Frames waiting now for receivers whose queue was full (all receivers together)."""
        return sum(len(frames) for frames in self._held.values())

    def _refresh_peers(self) -> None:
        """Re-list the participants at most every 50 ms: joining is rare, sending is not."""
        now = time.monotonic()
        if now - self._peers_at < 0.05:
            return
        self._peers_at = now
        mine = str(self._path)
        self._peers = [str(p) for p in self.directory.glob("*.sock")
                       if self._own or str(p) != mine]
        for gone in [p for p in self._held if p not in self._peers]:
            del self._held[gone]

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        flags = ((_FD if msg.is_fd else 0) | (_BRS if msg.bitrate_switch else 0)
                 | (_ERR if msg.is_error_frame else 0)
                 | (_ESI if msg.error_state_indicator else 0)
                 | (_EXT if msg.is_extended_id else 0))
        data = bytes(msg.data)
        self._pending.append(_WIRE.pack(time.time(), msg.arbitration_id, flags, len(data))
                             + data)
        # A caller that never flushes; HandBus ends its bursts itself at MAX_BURST (no more
        # than this), so a burst's fate is always decided at its own flush.
        if len(self._pending) > TX_QUEUE_FRAMES:
            self.flush()

    def flush(self) -> None:
        """Send what is held for each receiver, then the queued frames, to every other
        participant; raise ``TransmitQueueFull`` if a receiver's transmit queue had no room."""
        frames = self._pending
        if not frames and not self._held:
            return
        self._pending = []
        self._refresh_peers()
        refused = 0
        for peer in list(self._peers):
            held = self._held.get(peer)
            if held is None:
                if frames:
                    self._deliver(peer, frames)
            elif len(held) + len(frames) > TX_QUEUE_FRAMES:
                refused += 1
                self._deliver(peer, held)
            else:
                self._deliver(peer, held + frames)
        if refused:
            self.frames_dropped += len(frames)
            raise TransmitQueueFull(len(frames), refused)

    def _deliver(self, peer: str, frames: list[bytes]) -> None:
        """Send ``frames`` to one receiver in datagrams of at most ``_BATCH`` frames; what its
        full queue refuses is held for it, in order."""
        done = 0
        total = len(frames)
        while done < total:
            chunk = frames if total <= _BATCH else frames[done:done + _BATCH]
            try:
                self._sock.sendto(b"".join(chunk), peer)
            except (ConnectionRefusedError, FileNotFoundError):
                self._forget(peer)  # its owner is gone
                return
            except (BlockingIOError, InterruptedError):
                self.queue_full += 1
                self._held[peer] = frames[done:]
                return
            self.datagrams_sent += 1
            done += len(chunk)
        self._held.pop(peer, None)

    def _forget(self, peer: str) -> None:
        self._peers.remove(peer)
        self._held.pop(peer, None)
        if peer != str(self._path):
            with _suppress_oserror():
                os.unlink(peer)

    def _read_datagram(self) -> bool:
        try:
            payload, ancillary, _, _ = self._sock.recvmsg(_BATCH * (_WIRE.size + 64),
                                                          _ANCILLARY_SIZE)
        except (BlockingIOError, InterruptedError):
            return False
        stamp = _arrival_s(ancillary)
        offset = 0
        while offset + _WIRE.size <= len(payload):
            _, frame_id, flags, length = _WIRE.unpack_from(payload, offset)
            offset += _WIRE.size
            self._inbox.append(can.Message(
                timestamp=stamp, arbitration_id=frame_id, is_extended_id=bool(flags & _EXT),
                is_fd=bool(flags & _FD), bitrate_switch=bool(flags & _BRS),
                is_error_frame=bool(flags & _ERR), error_state_indicator=bool(flags & _ESI),
                data=payload[offset:offset + length], channel=self.channel_info, is_rx=True,
                check=False))
            offset += length
        self._inbox.reverse()  # popped from the end, in arrival order
        return True

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        if not self._inbox and not self._read_datagram():
            if not timeout:
                return None, False
            ready, _, _ = select.select([self._sock], [], [], timeout)
            if not ready or not self._read_datagram():
                return None, False
        if not self._inbox:
            return None, False
        return self._inbox.pop(), False

    def fileno(self) -> int:
        return self._sock.fileno()

    def _flush_quietly(self) -> None:
        with contextlib.suppress(can.CanError, OSError):
            self.flush()

    def shutdown(self) -> None:
        if not self._is_shutdown:
            # What is held goes out while its receivers still read (a last disable command),
            # for a few milliseconds at most.
            deadline = time.monotonic() + _SHUTDOWN_S
            self._flush_quietly()
            while self._held and time.monotonic() < deadline:
                time.sleep(0.001)
                self._flush_quietly()
            self._sock.close()
            with _suppress_oserror():
                self._path.unlink()
        super().shutdown()


_ANCILLARY_SIZE = socket.CMSG_SPACE(_TIMESPEC.size)


def _arrival_s(ancillary: list[tuple[int, int, bytes]]) -> float:
    """The kernel's arrival time of a datagram (wall clock, s), or now if it gave none."""
    for level, kind, data in ancillary:
        if level == socket.SOL_SOCKET and kind == _SO_TIMESTAMPNS \
                and len(data) >= _TIMESPEC.size:
            sec, nsec = _TIMESPEC.unpack_from(data)
            return float(sec + nsec * 1e-9)
    return time.time()


class _suppress_oserror:  # noqa: N801 - used like contextlib.suppress(OSError), allocation-free
    def __enter__(self) -> None:
        return None

    def __exit__(self, kind: object, exc: object, tb: object) -> bool:
        return isinstance(exc, OSError)


class HandBus:
    """A python-can bus behind a small, never-raising interface for the loop."""

    def __init__(self, bus: can.BusABC, spec: BusSpec, fd: bool,
                 clock_ns: Callable[[], int] = time.monotonic_ns) -> None:
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
        self._batching = isinstance(bus, UnixDatagramBus)
        self._burst: list[tuple[int, bytes]] = []  # held by a batching transport until flush
        # A virtual bus stamps arrivals on this bus's clock; the others in wall-clock time.
        self._take = bus.take if isinstance(bus, ArrivalStampedVirtualBus) else None
        if isinstance(bus, ArrivalStampedVirtualBus):
            bus.clock_ns = self._now_ns
        #: The message a drain read past its limit, to tell whether frames were left: the
        #: first of the next drain. ``(arrival_ns, message)``.
        self._lookahead: tuple[int, can.Message] | None = None
        #: The recorder's taps: every frame drained or sent, and every event as it is taken.
        self.tap: FrameTap | None = None
        self.rx_tap: RxTap | None = None
        self.event_tap: Callable[[BusEvent], None] | None = None

    def use_clock(self, clock_ns: Callable[[], int]) -> None:
        """Stamp arrivals and events on ``clock_ns`` (the loop's clock) from now on."""
        self._clock_ns = clock_ns

    def _now_ns(self) -> int:
        return self._clock_ns()

    def _receive(self, wall_to_clock_ns: int) -> tuple[int, can.Message] | None:
        """The next message and its arrival time on this bus's clock, or None."""
        if self._take is not None:
            return self._take()
        msg = self._bus.recv(timeout=0)
        if msg is None:
            return None
        if msg.timestamp <= 0:  # an interface that stamps nothing: the time of reading
            return self._clock_ns(), msg
        return round(msg.timestamp * 1e9) + wall_to_clock_ns, msg

    def drain(self, limit: int = DRAIN_LIMIT) -> list[Frame]:
        """The frames that have arrived, ``limit`` at most, without waiting; error frames
        become events. Frames still waiting after ``limit`` are an ``RX_BACKLOG`` event."""
        frames: list[Frame] = []
        now = self._clock_ns()
        # Wall-clock arrival stamps (kernel, adapter) onto this bus's clock; never later than
        # now, so an adapter whose clock runs ahead cannot make a frame look younger.
        wall_to_clock = now - time.time_ns()
        item, self._lookahead = self._lookahead, None
        count = 0
        try:
            while True:
                if item is None:
                    item = self._receive(wall_to_clock)
                    if item is None:
                        break
                if count == limit:  # one more was waiting: keep it for the next drain
                    self._lookahead = item
                    self._event(BusEventKind.RX_BACKLOG,
                                f"{limit} frames drained and more waiting")
                    break
                count += 1
                stamp, msg = item
                item = None
                if msg.is_error_frame:
                    self._error_frame(msg)
                    continue
                self.received += 1
                frame_id = msg.arbitration_id
                if msg.is_extended_id:
                    frame_id = (frame_id & _EXTENDED_ID_MASK) | EXTENDED_ID_FLAG
                frames.append(Frame(frame_id, bytes(msg.data), min(stamp, now), msg.is_fd))
        except (can.CanError, OSError, ValueError) as exc:
            self._event(BusEventKind.RX_FAILED, str(exc))
        if frames and self.rx_tap is not None:
            self.rx_tap(frames)
        return frames

    def send(self, arbitration_id: int, data: bytes, more: bool = False) -> bool:
        """Send one frame without blocking; on failure record an event and return False.

        ``more=True`` says another frame of the same burst follows at once, so a batching
        transport (the unix bus) holds this one until the last (``more=False``) or ``flush``
        (at most ``MAX_BURST`` frames): ``send`` returns True for it, and it is counted and
        tapped when the burst goes, with the burst's fate.
        """
        extended = bool(arbitration_id & EXTENDED_ID_FLAG)
        msg = _Message(arbitration_id=arbitration_id & _EXTENDED_ID_MASK if extended
                       else arbitration_id, data=data, is_extended_id=extended,
                       is_fd=self.fd, bitrate_switch=self.fd, check=False)
        try:
            self._bus.send(msg, timeout=0)
        except (can.CanError, OSError, ValueError) as exc:
            self._tx_error(exc)
            self.tx_failed += 1
            if self.tap is not None:
                self.tap(arbitration_id, data, TAP_TX_FAILED)
            return False
        if self._batching:
            self._burst.append((arbitration_id, data))
            if more and len(self._burst) < MAX_BURST:
                return True
            return self.flush()
        self.sent += 1
        if self.tap is not None:
            self.tap(arbitration_id, data, TAP_TX)
        return True

    def flush(self) -> bool:
        """End a burst: a batching transport sends the frames ``send(..., more=True)`` held
        (and offers again what receivers with a full queue were still owed).

        False, with a TX_QUEUE_FULL (or TX_FAILED) event, if the transport refused the burst:
        each of its frames is then counted in ``tx_failed`` and tapped as failed. Other buses
        send at once, so there is nothing to do.
        """
        if not self._batching:
            return True
        burst, self._burst = self._burst, []
        ok = True
        try:
            self._bus.flush()  # type: ignore[attr-defined]
        except (can.CanError, OSError, ValueError) as exc:
            self._tx_error(exc)
            ok = False
        if ok:
            self.sent += len(burst)
        else:
            self.tx_failed += len(burst)
        if self.tap is not None:
            direction = TAP_TX if ok else TAP_TX_FAILED
            for frame_id, data in burst:
                self.tap(frame_id, data, direction)
        return ok

    def _tx_error(self, exc: Exception) -> None:
        if isinstance(exc, can.CanOperationError):
            full = exc.error_code == errno.ENOBUFS or "No buffer space" in str(exc)
            self._event(BusEventKind.TX_QUEUE_FULL if full else BusEventKind.TX_FAILED, str(exc))
        else:
            self._event(BusEventKind.TX_FAILED, f"{type(exc).__name__}: {exc}")

    def transport_counts(self) -> dict[str, int]:
        """The transport's own delivery counters, for summaries: on the unix bus the datagrams
        sent, the times a receiver's queue was full (its frames held and retried), the frames
        refused because a receiver's transmit queue was full, and the frames held now.
        Empty for buses that keep no such counts."""
        bus = self._bus
        if not isinstance(bus, UnixDatagramBus):
            return {}
        return {"datagrams_sent": bus.datagrams_sent, "queue_full": bus.queue_full,
                "frames_dropped": bus.frames_dropped, "frames_held": bus.held}

    def send_error_frame(self, error_class: int = _CAN_ERR_CRTL, data: bytes = bytes(8)) -> bool:
        """Put an error frame on the bus (fault injection on virtual buses only).

        ``error_class`` is the Linux error class (0x004 controller, 0x040 bus-off,
        0x100 restarted), as a SocketCAN adapter would report it. On a batching transport it
        ends the burst under way.
        """
        msg = _Message(arbitration_id=error_class, is_error_frame=True, is_extended_id=False,
                       data=data, check=False)
        try:
            self._bus.send(msg, timeout=0)
        except (can.CanError, OSError, ValueError):
            return False
        return self.flush()

    def events(self) -> list[BusEvent]:
        """Take the events since the last call."""
        events, self._events = self._events, []
        if self.event_tap is not None:
            for event in events:
                self.event_tap(event)
        return events

    def close(self) -> None:
        if not self.closed:
            if self._burst:
                self.flush()
            self.closed = True
            self._bus.shutdown()

    def __enter__(self) -> HandBus:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _event(self, kind: BusEventKind, detail: str) -> None:
        self._events.append(BusEvent(kind, detail, self._clock_ns()))

    def _error_frame(self, msg: can.Message) -> None:
        cls = msg.arbitration_id
        if cls & _CAN_ERR_BUSOFF:
            self._event(BusEventKind.BUS_OFF, f"error class 0x{cls:X}")
        elif cls & _CAN_ERR_RESTARTED:
            self._event(BusEventKind.BUS_RESTARTED, f"error class 0x{cls:X}")
        elif cls & _CAN_ERR_CRTL and len(msg.data) > 1 and msg.data[1] & _CAN_ERR_CRTL_PASSIVE:
            self._event(BusEventKind.ERROR_PASSIVE, f"controller 0x{msg.data[1]:02X}")
        else:
            self._event(BusEventKind.ERROR_FRAME, f"error class 0x{cls:X}")


def open_bus(spec: str | BusSpec, bus_config: BusConfig,
             options: dict[str, Any] | None = None) -> HandBus:
    """Open the bus named by ``spec``; every failure is a ``BusError`` that says what to do.

    ``options`` go to the python-can constructor unchanged (e.g. ``rx_queue_size`` of the
    virtual bus, or an adapter's own timing arguments).
    """
    parsed = spec if isinstance(spec, BusSpec) else parse_spec(spec, bus_config)
    if parsed.interface == "sim":
        raise BusError("bus spec 'sim' is resolved by the caller: start the simulated hand and "
                       "open its virtual channel")
    if parsed.interface == "socketcan" and os.name == "posix":
        check_socketcan(parsed.channel, bus_config)
    kwargs = bus_kwargs(parsed, bus_config)
    kwargs.update(options or {})
    try:
        if parsed.interface == "unix":
            del kwargs["interface"]
            bus: can.BusABC = UnixDatagramBus(**kwargs)
        elif parsed.interface == "virtual":
            del kwargs["interface"]
            bus = ArrivalStampedVirtualBus(**kwargs)
        else:
            bus = can.Bus(**kwargs)
    except (can.CanError, OSError, ValueError, ImportError, NotImplementedError) as exc:
        raise BusError(f"{parsed}: cannot open the bus: {type(exc).__name__}: {exc}") from None
    return HandBus(bus, parsed, bus_config.fd)


#: Log formats of python-can that ``write_frames`` writes: candump -L, Vector ASC, Vector BLF.
LOG_FORMATS = ("candump", "asc", "blf")


def write_frames(path: str | Path, fmt: str,
                 frames: Iterable[tuple[float, int, bytes, bool, bool]]) -> int:
    """Write ``(timestamp_s, arbitration_id, data, is_rx, is_fd)`` frames in a python-can log
    format, so the CAN tools people already have (candump/canplayer, CANalyzer, python-can's
    readers) open a handctl recording. Returns the number of frames written."""
    writer: can.io.generic.MessageWriter
    if fmt == "candump":
        writer = can.CanutilsLogWriter(str(path), channel="can0")
    elif fmt == "asc":
        writer = can.ASCWriter(str(path), channel=1)
    elif fmt == "blf":
        writer = can.BLFWriter(str(path), channel=1)
    else:
        raise ConfigError("--export", "format", "one of " + ", ".join(LOG_FORMATS), fmt)
    count = 0
    with writer:
        for stamp, frame_id, data, is_rx, is_fd in frames:
            fd = is_fd or len(data) > 8
            extended = bool(frame_id & EXTENDED_ID_FLAG) or frame_id > 0x7FF
            writer.on_message_received(can.Message(
                timestamp=stamp, arbitration_id=frame_id & _EXTENDED_ID_MASK,
                is_extended_id=extended,
                data=data, is_fd=fd, bitrate_switch=fd, is_rx=is_rx, check=False))
            count += 1
    return count
