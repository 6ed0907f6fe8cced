"""handctl's unix bus: a python-can interface over Unix datagram sockets between processes of
one machine, without a kernel CAN driver or any network traffic (the simulated hand in its own
process, kill tests). ``--bus unix:DIRECTORY``: one socket per participant in DIRECTORY.

It is registered with python-can as the interface ``unix`` (the ``can.interface`` entry point
in pyproject.toml), so ``can.Bus(interface="unix", channel=DIRECTORY)`` opens it as any other
interface, and nothing in handctl names it but that entry point.
"""

from __future__ import annotations

import contextlib
import errno
import itertools
import os
import select
import socket
import stat
import struct
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import can

from handctl.online import frameflags as ff
from handctl.online.bus import MAX_FRAME_DATA

#: ``SO_TIMESTAMPNS`` (Linux, asm-generic; Python's socket module does not name it): the
#: kernel stamps each datagram as it is queued for the receiving socket.
_SO_TIMESTAMPNS = getattr(socket, "SO_TIMESTAMPNS", 35)
_TIMESPEC = struct.Struct("@qq")

#: Per frame: the sender's time (s; diagnostics only: a frame is stamped on arrival by the
#: receiver's kernel), arbitration id, flags, data length; then the data.
_WIRE = struct.Struct("<dIBB")
_unix_ids = itertools.count()
#: names tried for a participant's endpoint before the bus refuses to open (``_bind``)
_BIND_ATTEMPTS = 8
#: Frames per datagram at most; a burst beyond it goes out in several datagrams.
_BATCH = 32
#: Frames held at most for one receiver whose queue is full. A burst that does not fit any
#: more is lost for that receiver alone, and it is told so (``rx_frames_lost``): a CAN
#: listener that does not read overflows its own receive queue and never fails a sender's
#: frame. Small on purpose: a receiver's socket queue already holds ten bursts or more; this
#: is slack for a moment, and a receiver that stopped reading must learn of its loss within a
#: few dozen ticks, not have it hidden behind a deep queue.
TX_QUEUE_FRAMES = 64
#: A wire flag of the unix bus's own, beyond the CAN flags (``frameflags``): not a frame but a
#: sender's word to one receiver that it refused this many frames for it (4 bytes, little
#: endian) since its last delivery there, at this place in the stream.
_LOST_MARK = 0x80
#: The flag bits a frame on the wire may carry: the CAN ones (``frameflags``, not
#: ``RX_FAILED``, which is this transport's own word to its ``HandBus``). A wire entry with any
#: other bit is a ``_LOST_MARK`` or a malformed datagram.
_CAN_FLAGS = ff.FD | ff.BRS | ff.ERROR | ff.ESI | ff.EXTENDED | ff.REMOTE
_NOT_CAN = 0xFF & ~_CAN_FLAGS
#: bytes: the receive buffer, a full datagram of a handctl sender: ``_BATCH`` frames of the
#: longest CAN-FD payload. A longer datagram comes cut short (``MSG_TRUNC``), and is dropped
#: as malformed rather than handed on with its last frame cut.
_RECV_BYTES = _BATCH * (_WIRE.size + MAX_FRAME_DATA)
#: frames a second no participant of one machine's unix bus sends (handctl's own burst path
#: carries some hundred thousand): the frames a receiver is told it lost since it opened,
#: at this rate and a second more, bound what a ``_LOST_MARK`` may claim. A mark beyond is
#: no sender's honest word (a forged count of 2**32 - 1 a millisecond made a monitor's
#: ``frames_lost`` trillions), and its datagram is dropped as malformed.
MAX_FRAMES_PER_S = 1_000_000
#: ns: a directory modified longer ago than this is as it was at the last listing if its
#: modification time has not changed since (``_refresh_peers``).
_SETTLED_NS = 1_000_000_000
#: s: how often a sender lists the participants again (``_refresh_peers``): a socket that
#: joins is sent to from at most this long after
PEERS_EVERY_S = 0.05
#: How long ``shutdown`` keeps offering held frames to receivers that are still reading.
_SHUTDOWN_S = 0.02


class UnixDatagramBus(can.BusABC):
    """A CAN bus between processes of one machine: each participant binds a datagram socket in
    the channel directory and sends every frame to all the other sockets there.

    Frames sent together (one tick's commands, one node tick's frames) travel as one datagram:
    Linux queues only ``net.unix.max_dgram_qlen`` datagrams per receiving socket (often 10),
    whatever their size and whoever sent them, and no socket buffer size lifts that. ``send``
    queues a frame and ``send_burst`` sends the batch; ``HandBus`` calls it after the last
    frame of a burst.

    A receiver whose queue is full does not lose what it was sent, as a CAN controller does
    not drop a frame it took for transmission but retries arbitration: the frames wait in a
    transmit queue for that receiver and go first, merged into as few datagrams as fit, at the
    next ``send_burst``. A burst that no longer fits that queue (``TX_QUEUE_FRAMES``: a
    receiver that stopped reading) is lost for that receiver only: the others get it, and the
    send succeeds, as on CAN, where a listener that does not read overflows its own receive
    queue and a sender never knows (a stopped ``handctl monitor`` must not stop a run).
    ``queue_full`` counts the times a receiver's queue was found full, ``frames_dropped`` the
    frames lost for one receiver or more. A socket whose owner died (SIGKILL) refuses delivery
    and is removed with what was held for it, so a killed peer does not wedge the bus.

    The receiver is told what it lost, as a SocketCAN socket is told of its receive queue's
    overflow (``SO_RXQ_OVFL``): the next delivery to it carries the number of frames refused
    for it, at the place in the stream where they were, and it counts them in
    ``rx_frames_lost``. So a listener kept from reading (a loaded machine) can tell a gap it
    caused itself from a node that skipped a counter.
    """

    def __init__(
        self, channel: str, receive_own_messages: bool = False, rcvbuf: int = 1 << 22, **kwargs: Any
    ) -> None:
        if not Path(channel).is_absolute():
            # the participants share the directory: a relative one is each process's own
            # (``handctl.online.busspec.unix_rule``)
            raise ValueError(
                f"unix bus directory {channel!r}: expected an absolute directory "
                f"(e.g. {Path(channel).absolute()})"
            )
        self.directory = Path(channel)
        if not self.directory.parent.is_dir():
            # made here, but not the directories above it: a mistyped path made a tree of
            # them, and a bus there that no other participant would ever find
            raise ValueError(
                f"unix bus directory {channel!r}: expected a directory in an existing one "
                f"({self.directory.parent} is not a directory)"
            )
        if self.directory.exists() and not self.directory.is_dir():
            raise ValueError(
                f"unix bus directory {channel!r}: expected a directory (each participant's "
                "socket is made in it), found another kind of file"
            )
        if self.directory.is_symlink() and not self.directory.exists():
            raise ValueError(
                f"unix bus directory {channel!r}: expected a directory, found a symbolic link "
                "that leads to no directory (a loop, or a link to nothing)"
            )
        #: whether this participant made the directory: the last one out takes it away again
        #: if it did (``handctl sim --bus unix:/tmp/hand`` left an empty directory behind)
        self._made_directory = not self.directory.exists()
        self.directory.mkdir(exist_ok=True)
        self.channel_info = f"unix:{channel}"
        self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        with _suppress_oserror():
            self._sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, rcvbuf)
        # The kernel stamps each datagram as it arrives: the time a frame reached this
        # participant, however long it then waits to be read. (A kernel without it leaves
        # the time of reading, which makes frames look younger: Linux has it.)
        with _suppress_oserror():
            self._sock.setsockopt(socket.SOL_SOCKET, _SO_TIMESTAMPNS, 1)
        self._path = self._bind()
        self._sock.setblocking(False)
        #: the directory this participant joined (its inode): one of that name made anew is
        #: another bus, which none of the participants of this one are on
        self._directory_ino = os.stat(self.directory).st_ino
        # Readiness asked of the kernel before a read: an empty socket answers a poll in
        # well under a µs, a read of it with an exception several µs, at the end of every drain.
        self._ready = select.poll()
        self._ready.register(self._sock, select.POLLIN)
        #: Per receiver, a socket connected to it: a send on it skips the kernel's lookup of
        #: the receiver's path, which costs as much as the send itself.
        self._links: dict[str, socket.socket] = {}
        self._directory_mtime_ns: int | None = None
        #: the directory was found removed at the last listing: nothing reaches anyone
        self._directory_gone = False
        self._own = receive_own_messages
        self._peers: list[str] = []
        self._peers_at = 0.0
        self._held: dict[str, list[bytes]] = {}  # per receiver: frames its full queue refused
        self._lost: dict[str, int] = {}  # per receiver: frames refused since the last delivery
        self._shunned: set[str] = set()  # paths in the directory that are no participant
        self._inbox: list[tuple[float, int, int, bytes]] = []  # newest first
        self._can_protocol = can.CanProtocol.CAN_FD
        self.datagrams_sent = 0
        self.queue_full = 0
        self.frames_dropped = 0
        self.rx_frames_lost = 0
        #: Datagrams received and dropped as malformed (cut by the buffer, not parsing, a
        #: lost count beyond ``MAX_FRAMES_PER_S``), each also said to ``HandBus`` as an event.
        self.rx_malformed = 0
        self._opened_s = time.time()
        super().__init__(channel=channel, **kwargs)

    @property
    def held(self) -> int:
        """Frames waiting now for receivers whose queue was full (all receivers together)."""
        return sum(len(frames) for frames in self._held.values())

    def transport_counts(self) -> dict[str, int]:
        """The datagrams sent, the times a receiver's queue was full (its frames held and
        retried), the frames refused because a receiver's transmit queue was full, and the
        frames held now; and the frames this participant lost as a receiver, as its senders
        told it."""
        return {
            "datagrams_sent": self.datagrams_sent,
            "queue_full": self.queue_full,
            "frames_dropped": self.frames_dropped,
            "frames_held": self.held,
            "rx_frames_lost": self.rx_frames_lost,
            "rx_malformed": self.rx_malformed,
        }

    def _bind(self) -> Path:
        """This participant's endpoint, under a name no entry of the directory has.

        The name is the process id and a count. An entry of that name left behind (the socket
        of a participant killed with SIGKILL whose process id came round again, or any file
        put there) made the bind fail with "Address already in use", naming neither; the
        next count is taken instead, a few times, then the bus refuses to open saying why."""
        tried = []
        for _ in range(_BIND_ATTEMPTS):
            path = self.directory / f"{os.getpid()}-{next(_unix_ids)}.sock"
            try:
                self._sock.bind(str(path))
            except OSError as exc:
                if exc.errno != errno.EADDRINUSE:
                    raise
                tried.append(path.name)
                continue
            return path
        self._sock.close()
        raise ValueError(
            f"unix bus directory {str(self.directory)!r}: expected names free for this "
            f"participant's endpoint, found {', '.join(tried)} taken (left behind by "
            "participants that were killed? remove them)"
        )

    def _refresh_peers(self, force: bool = False) -> None:
        """Re-list the participants at most every ``PEERS_EVERY_S`` (unless ``force``): joining is
        rare, sending is not.

        A listing costs tens of µs, so it is skipped while the directory is as it was at the
        last one (its modification time the same, and older than ``_SETTLED_NS``: a time
        stamp that coarse file systems may still share with a later change)."""
        now = time.monotonic()
        if not force and now - self._peers_at < PEERS_EVERY_S:
            return
        self._peers_at = now
        try:
            seen = os.stat(self.directory)
            mtime: int | None = seen.st_mtime_ns
            # removed and made again (rm -rf; mkdir): its sends went to nobody, no bus event
            self._directory_gone = seen.st_ino != self._directory_ino
        except FileNotFoundError:
            mtime = None
            self._directory_gone = True
        except OSError:
            mtime = None
        if (
            mtime is not None
            and mtime == self._directory_mtime_ns
            and time.time_ns() - mtime > _SETTLED_NS
        ):
            return
        self._directory_mtime_ns = mtime
        mine = str(self._path)
        # sockets only, and not through a link: a symlink named like one sent every
        # participant's traffic to whatever datagram socket it named (the system log's), and a
        # link to a participant doubled every frame it was sent
        listed = [str(p) for p in self.directory.glob("*.sock") if _is_socket(p)]
        self._shunned.intersection_update(listed)  # one gone and back is tried again
        self._peers = [p for p in listed if (self._own or p != mine) and p not in self._shunned]
        for gone in [p for p in self._links if p not in self._peers]:
            self._links.pop(gone).close()
        for gone in [p for p in self._held if p not in self._peers]:
            del self._held[gone]
        for gone in [p for p in self._lost if p not in self._peers]:
            del self._lost[gone]

    def connect_peers(self) -> None:
        """Look the participants up and connect a socket to each now, while there is time (a
        run's start-up ticks, which only listen), not in the first send: the first listing
        of the directory and the connects took 0.5 ms of CPU there, in the nodes' enable,
        and delayed the first running tick (docs/timing.md). Later calls cost what the
        send's own look does (``_refresh_peers``: a ``stat``).

        It looks every time, not at most every 50 ms as a send does: a run's start-up ends
        at the tick it first hears every node, and it sends the nodes' enable next. A
        simulated hand that had bound its socket within the 50 ms since the last look was
        not a receiver yet, its enable went to nobody, and the run stopped on STARTUP
        ("nodes not ENABLED in time") while the torque frames after it arrived: half the
        real-time runs on a loaded host."""
        self._refresh_peers(force=True)
        for peer in self._peers:
            if peer not in self._links:
                with _suppress_oserror():  # not there yet, or gone: a send tries again
                    self._link(peer)

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        """Send one frame now, as a burst of its own: what python-can's ``send`` promises
        any user of the interface. ``HandBus`` sends a tick's frames with ``send_burst``."""
        self.send_burst((msg,))

    def send_burst(self, messages: Sequence[can.Message]) -> None:
        """Send what is held for each receiver, then ``messages`` together, to every other
        participant (a receiver whose transmit queue has no room loses them, and is told).
        No messages: only what is held is offered again."""
        now = time.time()
        self._send_wire([_encode(msg, now) for msg in messages])

    def send_frames(self, frames: Sequence[tuple[int, int, bytes]]) -> None:
        """``send_burst`` of frames given as ``(arbitration_id, flags, data)``
        (``handctl.online.frameflags``), without python-can's ``Message``
        (``bus.FrameTransport``)."""
        now = time.time()
        pack = _WIRE.pack
        self._send_wire([pack(now, i, flags, len(data)) + data for i, flags, data in frames])

    def _send_wire(self, frames: list[bytes]) -> None:
        """Send what is held, then ``frames`` (each on the wire already), to every other
        participant, as ``send_burst`` says."""
        if not frames and not self._held:
            return
        self._refresh_peers()
        if self._directory_gone:
            # Sending to nobody would look like a bus that works: the sends fail instead, so
            # that the host's supervisor stops on its bus (BUS_ERROR) and the bus events say
            # why, rather than the nodes' silence alone (FEEDBACK_TIMEOUT, "0 bus events")
            raise OSError(
                errno.ENOENT,
                f"the unix bus directory {self.directory} is gone (removed, or removed and "
                "made again, while in use): no participant can be reached",
            )
        refused = False
        lost = self._lost
        for peer in list(self._peers):
            held = self._held.get(peer)
            if held is None:
                if frames:
                    mark = _lost_mark(lost.pop(peer)) if peer in lost else []
                    self._deliver(peer, mark + frames)
            elif len(held) + len(frames) > TX_QUEUE_FRAMES:
                refused = True
                if frames:
                    lost[peer] = lost.get(peer, 0) + len(frames)
                self._deliver(peer, held)
            elif peer in lost:
                self._deliver(peer, held + _lost_mark(lost.pop(peer)) + frames)
            else:
                self._deliver(peer, held + frames)
        if refused:
            self.frames_dropped += len(frames)

    def _deliver(self, peer: str, frames: list[bytes]) -> None:
        """Send ``frames`` to one receiver in datagrams of at most ``_BATCH`` frames; what its
        full queue refuses is held for it, in order."""
        done = 0
        total = len(frames)
        while done < total:
            chunk = frames if total <= _BATCH else frames[done : done + _BATCH]
            try:
                link = self._links.get(peer) or self._link(peer)
                link.send(b"".join(chunk))
            except (ConnectionRefusedError, FileNotFoundError):
                self._forget(peer)  # its owner is gone
                return
            except (BlockingIOError, InterruptedError):
                self.queue_full += 1
                self._held[peer] = frames[done:]
                return
            except OSError:
                # not a participant: a stream socket (EPROTOTYPE), one this process may not
                # write to (EACCES). Before, the error left the loop over the receivers, so
                # one such socket in the directory kept every participant from every frame,
                # the host's stop frames included
                self._shun(peer)
                return
            self.datagrams_sent += 1
            done += len(chunk)
        self._held.pop(peer, None)

    def _link(self, peer: str) -> socket.socket:
        """A non-blocking socket connected to ``peer``, kept for the next sends to it."""
        link = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        link.setblocking(False)
        try:
            link.connect(peer)
        except OSError:
            link.close()
            raise
        self._links[peer] = link
        return link

    def _forget(self, peer: str) -> None:
        """A receiver whose owner is gone: its socket file is removed, if it is a socket (a
        file of another kind that refuses a connection is not a participant's, nor ours)."""
        self._drop(peer)
        if peer != str(self._path):
            with _suppress_oserror():
                if stat.S_ISSOCK(os.lstat(peer).st_mode):
                    os.unlink(peer)

    def _shun(self, peer: str) -> None:
        """A path in the directory that is no participant: never sent to again while it is
        there (a socket put at that path later is tried afresh), and left as it is."""
        self._drop(peer)
        self._shunned.add(peer)

    def _drop(self, peer: str) -> None:
        self._peers.remove(peer)
        self._held.pop(peer, None)
        self._lost.pop(peer, None)
        link = self._links.pop(peer, None)
        if link is not None:
            link.close()

    def _read_datagram(self) -> bool:
        """Read one datagram into the inbox (empty: it is read only then). A malformed one
        is dropped whole, frames and lost count, and leaves one ``RX_FAILED`` entry saying
        why: a frame cut short, or a count no sender would send, is not passed on."""
        if not self._ready.poll(0):
            return False
        try:
            payload, ancillary, msg_flags, _ = self._sock.recvmsg(_RECV_BYTES, _ANCILLARY_SIZE)
        except (BlockingIOError, InterruptedError):
            return False
        stamp = _arrival_s(ancillary)
        inbox = self._inbox
        if msg_flags & socket.MSG_TRUNC:
            self._malformed(stamp, f"longer than the {_RECV_BYTES} bytes of the receive buffer")
            return True
        offset = 0
        size = _WIRE.size
        end = len(payload)
        unpack = _WIRE.unpack_from
        append = inbox.append
        lost = 0
        while offset < end:
            if offset + size > end:
                self._malformed(stamp, f"{end - offset} bytes after its last frame")
                return True
            _, frame_id, flags, length = unpack(payload, offset)
            offset += size
            if offset + length > end:
                self._malformed(stamp, f"a frame of {length} bytes with {end - offset} left")
                return True
            if flags & _NOT_CAN:
                if flags != _LOST_MARK or length != 4:
                    self._malformed(stamp, f"a wire entry of flags 0x{flags:02X}, {length} bytes")
                    return True
                lost += int.from_bytes(payload[offset : offset + 4], "little")
            else:
                append((stamp, frame_id, flags, payload[offset : offset + length]))
            offset += length
        if lost:
            bound = (stamp - self._opened_s + 1.0) * MAX_FRAMES_PER_S
            if self.rx_frames_lost + lost > bound:
                self._malformed(
                    stamp,
                    f"it says {lost} frames were lost for this participant, "
                    f"{self.rx_frames_lost} before: more than {MAX_FRAMES_PER_S} a second "
                    "since it opened",
                )
                return True
            self.rx_frames_lost += lost
        inbox.reverse()  # popped from the end, in arrival order
        return True

    def _malformed(self, stamp: float, why: str) -> None:
        """Drop the datagram being read and leave, in its place, the word that it was."""
        self.rx_malformed += 1
        self._inbox.clear()
        reason = f"unix bus: a malformed datagram ({why}): dropped"
        self._inbox.append((stamp, 0, ff.RX_FAILED, reason.encode()))

    def recv_frame(self) -> tuple[float, int, int, bytes] | None:
        """The next frame without waiting, as ``(arrival_s, arbitration_id, flags, data)``
        (``handctl.online.frameflags``), or None: what ``HandBus`` drains, without building a
        python-can ``Message`` (``bus.FrameTransport``)."""
        if not self._inbox and not self._read_datagram():
            return None
        return self._inbox.pop() if self._inbox else None

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        if not self._inbox and not self._read_datagram():
            if not timeout:
                return None, False
            ready, _, _ = select.select([self._sock], [], [], timeout)
            if not ready or not self._read_datagram():
                return None, False
        if not self._inbox:
            return None, False
        stamp, frame_id, flags, data = self._inbox.pop()
        if flags & ff.RX_FAILED:  # python-can's way of saying a receive failed
            raise can.CanOperationError(data.decode())
        msg = can.Message(
            timestamp=stamp,
            arbitration_id=frame_id,
            **ff.message_fields(flags),
            data=data,
            channel=self.channel_info,
            is_rx=True,
            check=False,
        )
        return msg, False

    def fileno(self) -> int:
        return self._sock.fileno()

    def _flush_quietly(self) -> None:
        with contextlib.suppress(can.CanError, OSError):
            self.send_burst(())

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
            for link in self._links.values():
                link.close()
            self._links.clear()
            with _suppress_oserror():
                self._path.unlink()
            if self._made_directory:
                with _suppress_oserror():  # another participant's socket still in it: kept
                    self.directory.rmdir()
        super().shutdown()


_ANCILLARY_SIZE = socket.CMSG_SPACE(_TIMESPEC.size)


def _lost_mark(frames: int) -> list[bytes]:
    """The word to a receiver that ``frames`` were refused for it (``_LOST_MARK``), as the
    one wire entry it takes in a delivery."""
    return [_WIRE.pack(time.time(), 0, _LOST_MARK, 4) + frames.to_bytes(4, "little")]


def _encode(msg: can.Message, sent_s: float) -> bytes:
    """One frame on the wire: ``_WIRE``'s header, then the data."""
    data = bytes(msg.data)
    return _WIRE.pack(sent_s, msg.arbitration_id, ff.flags_of(msg), len(data)) + data


def _arrival_s(ancillary: list[tuple[int, int, bytes]]) -> float:
    """The kernel's arrival time of a datagram (wall clock, s), or now if it gave none."""
    for level, kind, data in ancillary:
        if level == socket.SOL_SOCKET and kind == _SO_TIMESTAMPNS and len(data) >= _TIMESPEC.size:
            sec, nsec = _TIMESPEC.unpack_from(data)
            return float(sec + nsec * 1e-9)
    return time.time()


class _suppress_oserror:  # noqa: N801 - used like contextlib.suppress(OSError), allocation-free
    def __enter__(self) -> None:
        return None

    def __exit__(self, kind: object, exc: object, tb: object) -> bool:
        return isinstance(exc, OSError)


def _is_socket(path: Path) -> bool:
    """A socket itself, not a link to one, nor any other kind of file (``lstat``)."""
    try:
        return stat.S_ISSOCK(os.lstat(path).st_mode)
    except OSError:  # gone since the listing
        return False


def anyone_on(directory: Path) -> bool:
    """Whether a live participant is on the unix bus in ``directory``: one of its sockets
    takes a connection. A participant killed leaves its socket file, and a bus directory
    outlives the participants that were on it; a run onto such a directory passed the
    check that a hand was on it, ran its timing check and listened out its whole start-up
    (found by an outside audit)."""
    for path in directory.glob("*.sock"):
        if not _is_socket(path):
            continue
        probe = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        try:
            probe.connect(str(path))
        except OSError:
            continue  # a participant gone: its socket file stayed
        else:
            return True
        finally:
            probe.close()
    return False
