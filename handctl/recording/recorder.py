"""The loop's end of a recording: copy numbers into shared memory, never wait, never encode.

``Recorder`` is the runtime's ``RecordSink`` and the bus's frame and event tap. Each call
packs a few integers and floats into a preallocated row of the shared rings (``ring.py``) and
moves a counter; a writer process (``writer.py``) turns the rows into MCAP behind it. When a
ring is full the record is dropped and counted, and the writer records the count: the loop
never blocks on the recording.

The writer is a separate interpreter (``python -m handctl.recording.writer``), started with the
ring's memory file, the output file and two pipes as inherited descriptors, in a session of its
own so that a Ctrl-C meant for the control process does not reach it. When the control process
ends, on purpose or by SIGKILL, the writer sees its control pipe close, copies out what is
left in the rings and finishes an indexed file.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import itertools
import mmap
import os
import select
import stat
import struct
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Collection, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, NamedTuple

import numpy as np
import orjson

from handctl.config import HandConfig
from handctl.errors import ConfigError, Description, HandctlError, said_by
from handctl.online.bus import MAX_BURST, BusEvent, Frame, FrameBus
from handctl.online.recipes.runner import RunStatus
from handctl.online.safety.faults import FAULTS
from handctl.online.safety.supervisor import State
from handctl.online.taps import TAP_RX
from handctl.recording import channels as ch
from handctl.recording.loglock import PARTIAL_SUFFIX, lock_log, partials_beside
from handctl.recording.mcapfile import MAGIC as MCAP_MAGIC
from handctl.recording.metadata import valid_strings, valid_text
from handctl.recording.ring import (
    CLOSED,
    CTL_WORDS,
    DROPPED_EVENTS,
    DROPPED_FRAMES,
    DROPPED_POSES,
    DROPPED_TICKS,
    EV_BUS,
    EV_FAULT,
    EV_INTERN,
    EV_PHASE,
    EV_REJECT,
    EV_REQUEST,
    EV_STATE,
    EVENT_BYTES,
    EVENT_HEAD,
    EVENT_TAIL,
    FRAME_HEAD,
    FRAME_ROW,
    FRAME_TAIL,
    I_NODES,
    LIVE_REFUSED,
    POSE_HEAD,
    POSE_TAIL,
    RX_FRAME_ROW,
    RX_HEAD_ROW,
    SEP,
    TICK_HEAD,
    TICK_TAIL,
    TX_FRAME_ROW,
    RingLayout,
    Rings,
)

if TYPE_CHECKING:
    from handctl.online.clock import Tick
    from handctl.online.drivers.hand import JointState
    from handctl.online.loop import Runtime, TickRecord
    from handctl.online.safety.supervisor import Supervisor

_TICK_HEAD = struct.Struct("<qqqqq")  # tick, scheduled, now, missed, active
_RX_HEAD = struct.Struct("<" + RX_HEAD_ROW)
_RX_FRAME = struct.Struct("<" + RX_FRAME_ROW)
_TX_FRAME = struct.Struct("<" + TX_FRAME_ROW)
#: Drains of more frames than this are written a row a call (a backlog at start-up): the
#: structs kept, one per count of frames met, stay few.
_PACKED_DRAIN = 64


_EVENT = struct.Struct("<qqqq")  # t, tick, kind, text length
#: The poses' (x, y, angle) as one run of floats, in C (bound once: no look-up a call).
_flatten = itertools.chain.from_iterable
#: Runner status names a phase column can also hold.
RUNNER_NAMES = ("-", *(status.value for status in RunStatus))
SUPERVISOR_STATE_NAMES = tuple(s.value for s in State)
#: How long ``close`` waits for the writer to finish the file, at most, and for it to move
#: at all: a writer on a slow disk gets its time, a stuck one is given up on (``close``).
CLOSE_TIMEOUT_S = 120.0
WRITER_STALL_S = 20.0
#: After how long the wait is said on stderr, and how often again; the wait's poll.
WAIT_NOTICE_S = 2.0
WAIT_NOTICE_EVERY_S = 10.0
WAIT_STEP_S = 0.25
READY_TIMEOUT_S = 30.0


class _Ring(NamedTuple):
    """Where one ring keeps what ``Recorder._ring_full`` needs: the attribute holding the
    tail this side last read, and the control words of the writer's tail and drop count."""

    tail_attribute: str
    tail_slot: int
    dropped_slot: int


_TICKS = _Ring("_tail", TICK_TAIL, DROPPED_TICKS)
_EVENTS = _Ring("_etail", EVENT_TAIL, DROPPED_EVENTS)
_POSES = _Ring("_ptail", POSE_TAIL, DROPPED_POSES)


def _view(vector: Any) -> memoryview:
    """A flat float64 view of a vector, for slice assignment into the ring's float view;
    TypeError or ValueError when it is not a contiguous float64 vector."""
    view = memoryview(vector)
    if view.format != "d" or view.ndim != 1 or not view.c_contiguous:
        raise TypeError("not a contiguous float64 vector")
    return view


def _side_by_side(first: Any, second: Any) -> memoryview | None:
    """One flat float64 view of two vectors that lie one after the other in one block of
    memory (the driver's angles and torques), for one slice assignment; None otherwise."""
    base = first.base
    if base is None or second.base is not base or not isinstance(base, np.ndarray):
        return None
    start = first.ctypes.data - base.ctypes.data
    if second.ctypes.data != first.ctypes.data + first.nbytes or not base.flags.c_contiguous:
        return None
    if start < 0 or start + first.nbytes + second.nbytes > base.nbytes:
        return None
    block = np.ndarray((first.size + second.size,), dtype=np.float64, buffer=base, offset=start)
    return _view(block)


def writer_cpus(loop_cpu: int | None, sim_cpu: int | None = None) -> list[int] | None:
    """The CPUs the writer process may run on beside a run pinned to ``loop_cpu``, with the
    simulated hand's process on ``sim_cpu`` (None: no such process): this process's CPUs but
    those two. None (anywhere) when the loop is not pinned or no CPU is left: on two CPUs
    with the simulated hand, the writer shares the loop's idle time, where the loop's
    SCHED_FIFO always comes first. Pinned beside the simulated hand alone instead, the writer
    fell seconds behind on a busy machine and the rings dropped ticks: a lost log costs more
    than the caches the writer cools on the loop's CPU."""
    if loop_cpu is None:
        return None
    rest = os.sched_getaffinity(0) - {loop_cpu, sim_cpu}
    return sorted(rest) if rest else None


#: What stands for the bytes an event's text lost from the middle of a field.
_CUT = b"..."


def _event_text(fields: Sequence[str]) -> bytes:
    """An event's fields as its row holds them: UTF-8, ``EVENT_BYTES`` at most.

    A text too long loses bytes from the middle of its longest field, at character
    boundaries: a field's ends say the most (a fault's exception type, and its place "(in
    ...)"), and the fields after it stay whole. Cut at the 480th byte, a fault whose message
    was 200 non-ASCII characters (three bytes each) ended in a broken character, its place
    gone, though its message was cut to fit (found by an outside audit). A character UTF-8
    cannot carry (a lone surrogate, a byte of a path that was not UTF-8) is written escaped:
    the event is recorded, never raised on.
    """
    text = SEP.join(fields).encode(errors="backslashreplace")
    over = len(text) - EVENT_BYTES
    if over <= 0:
        return text
    encoded = [field.encode(errors="backslashreplace") for field in fields]
    longest = max(range(len(encoded)), key=lambda i: len(encoded[i]))
    field = encoded[longest]
    keep = len(field) - over - len(_CUT)
    if keep < 2:  # the other fields alone do not fit: the beginning, whole characters
        return text[:EVENT_BYTES].decode(errors="ignore").encode()
    # a character cut at either end is left out whole (the decoder drops its bytes)
    head = field[: keep - keep // 2].decode(errors="ignore").encode()
    tail = field[len(field) - keep // 2 :].decode(errors="ignore").encode()
    encoded[longest] = head + _CUT + tail
    return SEP.encode().join(encoded)


def _say(text: str) -> None:
    """A line on stderr that cannot fail the close: a run whose stderr is gone still stops
    and finishes its log."""
    with contextlib.suppress(Exception):
        from handctl.progress import say

        say(text)


def _above_stdio(fd: int) -> int:
    """``fd`` moved above 0-2 (closing the original): a descriptor handed to the writer as 0,
    1 or 2 would be replaced there by the child's stdin, stdout or stderr. A run started with
    stdout closed had its log opened as descriptor 1, and the writer wrote the whole
    recording to /dev/null."""
    if fd > 2:
        return fd
    try:
        return fcntl.fcntl(fd, fcntl.F_DUPFD_CLOEXEC, 3)
    finally:
        os.close(fd)


def _open_log(path: Path, empty: bool = True) -> int:
    """The log opened for writing and locked for this run alone, then emptied (unless not
    ``empty``: with a live view, the writer empties it once the view's port is bound, so
    that a port taken since it was checked leaves the previous log as it was).

    Not truncated on opening: a second run given the same path while the first is still
    writing it is refused by the lock (bad input, exit 2) and leaves the first's file as it
    was; two writers used to interleave their chunks in one file and both say they were done.
    The lock (``flock``) is the open file's: the writer's copy of the descriptor holds it
    for as long as it writes, even if this process dies first, and the system drops it when
    the last copy is closed, so it never outlives the recording. A file system that has no
    such locks (some network ones) records unlocked, as before."""
    try:
        fd = _above_stdio(os.open(path, os.O_WRONLY | os.O_CREAT | os.O_CLOEXEC, 0o644))
    except OSError as exc:
        raise ConfigError(
            str(path), "", "a path where the recording can be written", exc.strerror or str(exc)
        ) from None
    try:
        # A device or a pipe is no file to lock or to empty (a lock on /dev/null would be
        # every process's): only a regular file is.
        if stat.S_ISREG(os.fstat(fd).st_mode):
            lock_log(fd, path)
            try:
                os.ftruncate(fd, 0 if empty else os.fstat(fd).st_size)  # writable, either way
            except OSError as exc:
                raise ConfigError(
                    str(path), "", "a file the recording can replace", exc.strerror or str(exc)
                ) from None
    except BaseException:
        os.close(fd)
        raise
    return fd


@dataclass
class _Beside:
    """A log written beside its path until the run begins (``Recorder.claim``): the path's
    file held and locked for the run (the previous log, or an empty one made for it), and the
    file the writer fills."""

    target: Path  # the path, its symbolic links followed: where the log goes
    held: int  # descriptor of the path's file, locked; -1 once claimed
    temp: Path
    created: bool  # the path named nothing before: the empty file there is this run's
    claimed: bool = False


def _open_beside(path: Path) -> tuple[int, _Beside] | None:
    """The log's file beside ``path`` and the path locked (``_Beside``), or None where no
    file can be made beside it (a device, a directory the run cannot write in): written in
    place then, as before."""
    target = Path(os.path.realpath(path))
    created = True
    try:
        try:
            held = os.open(target, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_CLOEXEC, 0o644)
        except FileExistsError:
            created = False
            held = os.open(target, os.O_WRONLY | os.O_CLOEXEC)
    except OSError as exc:
        raise ConfigError(
            str(path), "", "a path where the recording can be written", exc.strerror or str(exc)
        ) from None
    held = _above_stdio(held)
    if not stat.S_ISREG(os.fstat(held).st_mode):
        os.close(held)
        return None
    temp = target.with_name(f".{target.name}.{os.getpid()}{PARTIAL_SUFFIX}")
    try:
        lock_log(held, path)
        with contextlib.suppress(FileNotFoundError):
            temp.unlink()  # left by a process of this pid that was killed
        _remove_stale_partials(target)
        fd = _above_stdio(os.open(temp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_CLOEXEC, 0o644))
    except BaseException as exc:
        os.close(held)
        if created:
            with contextlib.suppress(OSError):
                target.unlink()
        if isinstance(exc, OSError):  # no file beside it: written in place
            return None
        raise
    with contextlib.suppress(OSError):
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    return fd, _Beside(target, held, temp, created)


def _remove_stale_partials(target: Path) -> None:
    """The recordings beside ``target`` that runs killed in their start-up left, removed and
    said. A run killed (SIGKILL) before it began leaves one (nothing was sent: it holds the
    start-up only), and every later run on the path went on beside it, for good (found by an
    outside audit). Called with ``target`` locked for this run: no other run starts on it
    now. One a live writer may still fill is kept (``_partial_in_use``)."""
    prefix = f".{target.name}."
    for partial in partials_beside(target):
        pid = partial.name[len(prefix) : -len(PARTIAL_SUFFIX)]
        if not pid.isdigit() or int(pid) == os.getpid():
            continue  # not a run's name; this process's own was removed already
        try:
            fd = os.open(partial, os.O_RDONLY | os.O_NOFOLLOW | os.O_CLOEXEC | os.O_NONBLOCK)
        except OSError:
            continue  # gone, a link, or not ours to open: left as it is
        try:
            if _partial_in_use(fd, partial, int(pid)):
                continue
            os.unlink(partial)
        except OSError:
            continue
        finally:
            os.close(fd)
        _say(
            f"handctl: removed {partial}: left beside this log by a run killed before it "
            f"began (process {pid}); nothing writes it any more"
        )


def _partial_in_use(fd: int, partial: Path, pid: int) -> bool:
    """Whether the recording ``partial`` (open as ``fd``) may still be written, so is not to
    be removed: by a writer, which holds the lock its run took on it for as long as it
    writes, whoever has this pid now (a pid is given again); by process ``pid`` while it is
    alive and has it open (between making it and taking that lock, or on a file system
    without locks); by anything this cannot tell (a lock refused for another reason, a
    process whose open files this one may not see). Else, this process has its lock."""
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        opened = os.fstat(fd)
        there = os.stat(partial, follow_symlinks=False)
    except OSError:
        return True  # locked by its writer (EWOULDBLOCK), or no lock to be had
    if not stat.S_ISREG(opened.st_mode) or (there.st_dev, there.st_ino) != (
        opened.st_dev,
        opened.st_ino,
    ):
        return True  # not a recording, or another file at the name since it was opened
    try:
        os.kill(pid, 0)  # whether it exists; one that ended and waits to be reaped has no files
    except ProcessLookupError:
        return False
    except (PermissionError, OverflowError):
        pass  # another user's, or no pid at all: its open files tell, or nothing does
    try:
        fds = os.listdir(f"/proc/{pid}/fd")
    except FileNotFoundError:
        return False  # ended since
    except OSError:
        return True
    for name in fds:
        with contextlib.suppress(OSError):
            held = os.stat(f"/proc/{pid}/fd/{name}")
            if (held.st_dev, held.st_ino) == (opened.st_dev, opened.st_ino):
                return True
    return False


def how_it_ended(code: int | None) -> str:
    """A process's end by its return code, as ``subprocess`` gives it: "signal 9", "exit 1"."""
    return f"signal {-code}" if code is not None and code < 0 else f"exit {code}"


def _shared_memory(size: int) -> int:
    """An anonymous memory file both processes can map: memfd where there is one. One the
    host will not give (a file-size limit below the rings, ``ulimit -f``; no memory) is an
    error before the run, naming the size, not a traceback."""
    try:
        if hasattr(os, "memfd_create"):
            fd = os.memfd_create("handctl-recording", 0)
        else:  # pragma: no cover - not Linux
            with tempfile.TemporaryFile() as handle:
                fd = os.dup(handle.fileno())
        try:
            os.ftruncate(fd, size)
        except OSError:
            os.close(fd)
            raise
    except OSError as exc:
        raise HandctlError(
            f"the recording's rings ({size / 2**20:.1f} MiB of shared memory) could not be "
            f"made: {exc.strerror or exc} (a file-size limit, ulimit -f, applies to them too);"
            " nothing was sent"
        ) from None
    return fd


class _WriterGoneError(HandctlError):
    """The writer's control pipe closed: it ended (its last word is in the message)."""


class Recorder:
    """Records one run to ``path``; see the module docstring for how."""

    # Slots, the tick's in the order it reads them: an attribute in a slot is read at a
    # fixed place in the object, where an instance dict of this many keys is a look-up in a
    # table of its own, which the simulation between two ticks has pushed out of the caches.
    # ``__dict__`` for what a bench or a test puts on an instance (a timed method).
    __slots__ = (  # noqa: RUF023 - in the order the tick reads them, not sorted
        # the taps
        "_drained",
        "_now",
        "_tick",
        "_fhead",
        "_frame_mask",
        "_sent_packs",
        "_frame_limit",
        "_buf",
        "_frame_base",
        "_drains",
        "_burst_packs",
        "_drain_packs",
        "_tx_pack",
        # push
        "_row",
        "_sup",
        "_joints",
        "_bus",
        "_last_phase",
        "_faults",
        "_history",
        "_reject_lists",
        "_reject_seen",
        "_state_name",
        "_state",
        "_phase",
        "_row_pack",
        "_tick_base",
        "_tick_stride",
        "_tk",
        "_feedback",
        "_n",
        "_tick_ints",
        "_feedback_at",
        "_ints",
        "_feedback_view",
        "_angle",
        "_tdt",
        "_desired",
        "_applied",
        "_floats",
        "_joints_view",
        "_angle_view",
        "_tdt_view",
        "_desired_view",
        "_applied_view",
        "_ctl_view",
        "_pose_list",
        "_phead",
        "_ptail",
        "_pose_mask",
        "_pose_pack",
        "_pose_base",
        "_pose_stride",
        "_head",
        # begin_tick
        "_tail",
        "_tick_mask",
        # the rest
        "_ftail",
        "_ehead",
        "_etail",
        "_event_base",
        "_event_data",
        "_event_mask",
        "_phases",
        "_states",
        "_no_faults",
        "_no_states",
        "_runtime",
        "_clock_ns",
        "_log_fd",
        "_rings",
        "_mmap",
        "_ti",
        "_tf",
        "_ctl_w",
        "_ready_r",
        "_ready",
        "_start_failed",
        "closed",
        "layout",
        "path",
        "process",
        "stats",
        "__dict__",
    )

    def __init__(
        self,
        path: str | Path,
        hand: HandConfig,
        metadata: dict[str, dict[str, str]],
        *,
        phase_names: Sequence[str] = (),
        object_names: Sequence[str] = (),
        object_pairs: Sequence[tuple[int, int]] | None = None,
        layout: RingLayout | None = None,
        live_port: int | None = None,
        cpus: Collection[int] | None = None,
        keep_previous: bool = False,
    ) -> None:
        """``keep_previous``: a log already at ``path`` stays there until the run begins
        (``claim``); a run that ends before (refused, interrupted, failed to start) leaves
        it as it was, and its own recording goes. A refused run used to empty the previous
        log, or delete it. ``cpus``: where the writer process may run (``writer_cpus``);
        None: anywhere.
        ``object_pairs``: the pairs of ``object_names`` (indices) whose centre line the pose
        messages carry, the recipe's ``pairs``; None: each object with the next."""
        self.path = Path(path)
        self.layout = layout or RingLayout(hand.n_joints, len(hand.fingers), len(object_names))
        #: The log's descriptor, kept to the end: it holds the file's lock with the writer's
        #: copy, and says at the end whether the path still names the file written.
        beside = _open_beside(self.path) if keep_previous else None
        self._beside = beside[1] if beside is not None else None
        self._log_fd = (
            beside[0] if beside is not None else _open_log(self.path, empty=live_port is None)
        )
        self._live_port = live_port
        try:
            self._start_writer(
                _above_stdio(os.dup(self._log_fd)),
                hand,
                metadata,
                phase_names,
                object_names,
                ch.pose_pairs(object_names, ()) if object_pairs is None else object_pairs,
                live_port,
                cpus,
            )
        except BaseException:
            # The writer never had its set-up, so it wrote nothing: no file, rather than an
            # empty one that no reader (``handctl replay`` included) can open. Unlinked while
            # this process still holds the lock, so no other run has started on it. A log
            # there before is left as it was.
            self._drop_beside()
            if self._beside is None or self._beside.created:
                with contextlib.suppress(OSError):
                    (self.path if self._beside is None else self._beside.target).unlink()
            os.close(self._log_fd)
            raise
        self._ready = False
        #: the writer was ended before it said it was ready (``wait_ready``): it wrote nothing
        self._start_failed = False
        self.closed = False
        self.stats: dict[str, Any] = {}
        # Loop-side cursors: the head is ours; the tail is the writer's, re-read only when the
        # ring looks full, so the common path touches no shared word but the head.
        r = self._rings
        self._n = self.layout.n_joints
        self._buf: Any = self._mmap  # Any: numpy vectors are copied in by buffer protocol
        self._ti, self._tf = r.tick_i, r.tick_f
        # Flat views of the tick rows for slice assignment from the runtime's own arrays.
        block = memoryview(self._mmap)
        at = r.offsets["tick_f"]
        self._floats = block[at : at + r.tick_f.nbytes].cast("d")
        at = r.offsets["tick_i"]
        self._ints = block[at : at + r.tick_i.nbytes].cast("q")
        block.release()
        self._tick_ints = self.layout.tick_ints
        self._angle: Any = None
        self._tdt: Any = None
        self._desired: Any = None
        self._applied: Any = None
        self._feedback: Any = None
        #: The views ``push`` copies from: the angles and torques as one (``_side_by_side``),
        #: the desired and applied torques, the feedback times.
        self._joints_view: memoryview | None = None
        self._angle_view = self._tdt_view = self._desired_view = self._applied_view = (
            self._feedback_view
        ) = memoryview(b"")
        #: The tick begun last, as the clock handed it out: the row's first four columns.
        self._tk: tuple[int, int, int, int] = (-1, 0, 0, 0)
        self._tick_stride = self.layout.tick_ints * 8
        self._tick_base = r.offsets["tick_i"]
        # The integer part of a control tick's row in one call: tick, scheduled, now, missed,
        # active, the 4 stages, state, phase, faults latched, then the node states and fault
        # bits; the feedback_ns column after them is a buffer copy.
        self._row_pack = struct.Struct(f"<{I_NODES + 2 * self.layout.n_nodes}q").pack_into
        self._no_states = [-1] * self.layout.n_nodes  # a tick without a runtime: no node seen
        self._no_faults = [0] * self.layout.n_nodes
        self._feedback_at = self.layout.i_feedback
        self._tick_mask = self.layout.tick_capacity - 1
        self._head = self._tail = 0
        self._row = -1
        self._frame_base = r.offsets["frame"]
        self._frame_mask = self.layout.frame_capacity - 1
        #: The frame rows written (the taps write them as the bus hands them over; ``push``
        #: publishes them), and the head they may reach before the writer's tail last read.
        self._fhead = self._ftail = 0
        self._frame_limit = self.layout.frame_capacity
        self._tx_pack = _TX_FRAME.pack_into
        #: The ``pack_into`` of a drain's block (its head row and its frames), by count of
        #: frames, each made when first met (``_drain_slowly``); a list, read without a call.
        self._drain_packs: list[Any] = [None] * (_PACKED_DRAIN + 1)
        self._drains = 0  # head rows written: the frames are the rows but these
        #: The frames of the last drain, not yet written: the next burst sent writes them
        #: with its own rows, in one ``pack_into`` (``_sent_packs``, by count of frames
        #: drained and sent; ``_burst_packs`` a burst's alone, by count of frames).
        self._drained: list[Frame] | None = None
        self._sent_packs: list[list[Any]] = [
            [None] * (MAX_BURST + 1) for _ in range(_PACKED_DRAIN + 1)
        ]
        self._burst_packs: list[Any] = [None] * (MAX_BURST + 1)
        self._event_base = r.offsets["event_i"]
        self._event_data = r.offsets["event_d"]
        self._event_mask = self.layout.event_capacity - 1
        self._ehead = self._etail = 0
        self._phead = self._ptail = 0
        #: The poses handed over this tick, not yet copied (``poses``).
        self._pose_list: Sequence[tuple[float, float, float]] | None = None
        self._pose_base = r.offsets["pose"]
        self._pose_stride = self.layout.pose_words * 8
        self._pose_pack = struct.Struct(f"<qq{3 * self.layout.n_objects}d").pack_into
        self._pose_mask = self.layout.pose_capacity - 1
        self._tick = -1  # frames drained before the first tick (discarded at start-up)
        self._now = 0
        #: The runtime's clock, read for what comes before the first tick (``attach``).
        self._clock_ns: Callable[[], int] | None = None
        self._runtime: Runtime | None = None
        #: What ``push`` reads every tick, kept at ``attach``: the supervisor and the driver's
        #: joint state (None: no runtime attached).
        self._sup: Supervisor | None = None
        self._joints: JointState | None = None
        #: The bus whose taps are this recorder's: what they raise it holds (``tap_error``),
        #: and ``push`` raises it, in the record stage.
        self._bus: FrameBus | None = None
        #: The last tick's supervisor state name and phase name, as the runtime handed them
        #: over (the same string objects tick after tick), and their numbers in the row.
        self._state_name = ""
        self._state = -1
        self._last_phase = ""
        self._phase = 0
        self._history = 0
        self._faults = 0
        self._reject_lists: list[list[int]] = []
        self._reject_seen: list[list[int]] = []

    def _start_writer(
        self,
        out_fd: int,
        hand: HandConfig,
        metadata: dict[str, dict[str, str]],
        phase_names: Sequence[str],
        object_names: Sequence[str],
        object_pairs: Sequence[tuple[int, int]],
        live_port: int | None,
        cpus: Collection[int] | None,
    ) -> None:
        """Map the rings, start the writer on ``out_fd`` and hand it its set-up. The set-up
        is bigger than a pipe holds (the hand, its DBC and the recipe), so the last write
        waits for the writer to have started and read it. Raises with nothing left open: no
        descriptor, no writer."""
        child_fds = [out_fd]  # the writer's; ours closed once it has them
        ctl_w = ready_r = -1
        try:
            shm_fd = _above_stdio(_shared_memory(self.layout.size))
            child_fds.append(shm_fd)
            self._mmap = mmap.mmap(shm_fd, self.layout.size)
            # Touch every page now: a page's first write is a page fault, microseconds each
            # (more in a virtual machine), which the loop would otherwise take every few ticks.
            for offset in range(0, self.layout.size, mmap.PAGESIZE):
                self._mmap[offset] = 0
            self._rings = Rings(self.layout, self._mmap)
            self._ctl_view = memoryview(self._mmap)[: CTL_WORDS * 8].cast("q")
            ctl_r, ctl_w = (_above_stdio(fd) for fd in os.pipe())
            child_fds.append(ctl_r)
            ready_r, ready_w = (_above_stdio(fd) for fd in os.pipe())
            child_fds.append(ready_w)
            package_root = str(Path(__file__).resolve().parents[2])
            env = dict(os.environ)
            env["PYTHONPATH"] = os.pathsep.join(
                p for p in (package_root, env.get("PYTHONPATH")) if p
            )
            # The writer does no linear algebra: no BLAS thread pool, whose threads would
            # start at numpy's import, before the writer places itself (``cpus``) and lowers
            # its priority.
            env["OPENBLAS_NUM_THREADS"] = env["OMP_NUM_THREADS"] = env["MKL_NUM_THREADS"] = "1"
            self.process = subprocess.Popen(
                [
                    sys.executable,
                    "-m",
                    "handctl.recording.writer",
                    str(shm_fd),
                    str(ctl_r),
                    str(out_fd),
                    str(ready_w),
                ],
                pass_fds=(shm_fd, ctl_r, out_fd, ready_w),
                stdin=subprocess.DEVNULL,
                stdout=subprocess.DEVNULL,
                stderr=subprocess.PIPE,
                env=env,
                start_new_session=True,
            )
        except BaseException as exc:
            for fd in (ctl_w, ready_r):
                if fd >= 0:
                    os.close(fd)
            if isinstance(exc, OSError) and not isinstance(exc, HandctlError):
                # a pipe, /dev/null or the process itself refused: said, not a traceback
                raise HandctlError(
                    f"the recording writer could not be started: {exc.strerror or exc}"
                    + (" (the open-files limit, ulimit -n)" if exc.errno == errno.EMFILE else "")
                    + "; nothing was sent"
                ) from None
            raise
        finally:
            for fd in child_fds:
                os.close(fd)
        self._ctl_w, self._ready_r = ctl_w, ready_r
        os.set_blocking(ctl_w, False)  # a writer that takes nothing must not hold a send
        self._states = {name: i for i, name in enumerate(SUPERVISOR_STATE_NAMES)}
        names = list(dict.fromkeys([*RUNNER_NAMES, *phase_names]))
        self._phases = {name: i for i, name in enumerate(names)}
        try:
            self._send(
                {
                    "type": "setup",
                    "layout": self.layout.as_dict(),
                    "states": SUPERVISOR_STATE_NAMES,
                    "phases": names,
                    "joints": list(hand.joint_names),
                    "nodes": [f.name for f in hand.fingers],
                    "objects": list(object_names),
                    "pairs": [list(pair) for pair in object_pairs],
                    "path": valid_text(str(self.path)),
                    "metadata": valid_strings(metadata),
                    "live_port": live_port,
                    "cpus": sorted(cpus) if cpus is not None else None,
                },
                READY_TIMEOUT_S,  # the writer reads it once its interpreter has started
            )
        except BaseException:
            self.process.kill()
            self.process.communicate()  # its stderr pipe closed too
            os.close(self._ctl_w)
            os.close(self._ready_r)
            raise

    # -- set-up ---------------------------------------------------------------------------
    def attach(self, runtime: Runtime) -> None:
        """Tap the runtime's bus and keep the runtime, whose supervisor, runner and driver the
        recorder reads when something changes (a state, a phase, a reject count)."""
        self._runtime = runtime
        self._sup = runtime.supervisor
        self._joints = runtime.driver.state
        bus = self._bus = runtime.driver.bus
        bus.tap = self._sent
        # Until the first tick begins, the drains (the start-up's discard of what queued
        # before the run) are stamped with the clock's time now, on the ticks' own time base:
        # they had 0, which beside CLOCK_MONOTONIC ticks put them the host's uptime before
        # the run (an export mixed wall-clock and uptime stamps).
        self._clock_ns = runtime.clock.now_ns
        self._now = self._clock_ns()
        bus.rx_tap = self._drain_before_start
        bus.event_tap = self._bus_event
        driver = runtime.driver
        self._reject_lists = [n.rejects.counts for n in driver.nodes]
        self._reject_lists.append(driver.unexpected.counts)
        self._reject_seen = [list(c) for c in self._reject_lists]

    def wait_ready(self, timeout_s: float = READY_TIMEOUT_S) -> None:
        """Wait until the writer has the file open and its header written.

        Called before the run starts, so a writer that cannot start is an error before any
        frame is sent, not a silent empty log.
        """
        if self._ready:
            return
        ready, _, _ = select.select([self._ready_r], [], [], timeout_s)
        answer = os.read(self._ready_r, 1) if ready else b""
        if answer != b"R":
            self._start_failed = True
            self.process.kill()
            _, err = self.process.communicate(timeout=10)
            if self.process.returncode == LIVE_REFUSED:
                from handctl.foxglove import HOST  # not ``live``: no SDK in this process

                # bad input, as a port taken when the options were checked is: nothing was
                # sent, and the previous log is as it was. Found, the writer's last line: the
                # port and the SDK's reason (its whole error, nested in this one, was cut
                # before the reason)
                said = err.decode(errors="replace").strip().splitlines()
                raise ConfigError(
                    "--live",
                    "",
                    f"a port the live view can listen on at {HOST} (it was free when the "
                    "options were checked: another program has taken it since); nothing was "
                    "sent and the log is as it was",
                    Description(said[-1] if said else str(self._live_port)),
                )
            raise HandctlError(
                f"{self.path}: the recording writer did not start: "
                f"{err.decode(errors='replace').strip() or 'no answer'}; nothing was sent"
            )
        self._ready = True

    def _send(self, message: dict[str, Any], stall_timeout_s: float = WRITER_STALL_S) -> None:
        """One message down the control pipe, given up on when the writer has taken none of
        it for ``stall_timeout_s``.

        Why bounded: the set-up (the hand config, the DBC and the recipe) and the summary
        are tens of kilobytes, more than a pipe holds, and a writer that reads nothing (a
        stalled disk, a SIGSTOP) held the send for ever: a run's start hung with no word, and
        a run's end hung before the wait for the writer that says so and gives up."""
        payload = orjson.dumps(message)
        view = memoryview(struct.pack("<I", len(payload)) + payload)
        try:
            while view:
                try:
                    view = view[os.write(self._ctl_w, view) :]
                except BlockingIOError:
                    _, room, _ = select.select([], [self._ctl_w], [], stall_timeout_s)
                    if not room:
                        raise HandctlError(
                            f"{self.path}: the recording writer took nothing of its control "
                            f"messages for {stall_timeout_s:g} s (stopped or hung)"
                        ) from None
        except BrokenPipeError:
            if not getattr(self, "_ready", False):
                # said as ``wait_ready`` says it: whether the writer went while its set-up
                # was still being sent or just after was a race (a full disk at the start)
                raise _WriterGoneError(
                    f"{self.path}: the recording writer did not start{self._why_gone()}; "
                    "nothing was sent"
                ) from None
            raise _WriterGoneError(
                f"{self.path}: the recording writer is gone{self._why_gone()}"
            ) from None

    def _why_gone(self) -> str:
        """``: `` and the last line the writer said, once it has ended (a full disk at the
        start: "OSError: [Errno 28] No space left on device"); "" if it said nothing. A
        writer that failed at the start was said as "gone" and no more."""
        try:
            _, err = self.process.communicate(timeout=5.0)  # kept: ``close`` reads it again
        except subprocess.TimeoutExpired:
            return ""
        lines = [line for line in err.decode(errors="replace").splitlines() if line.strip()]
        return f": {lines[-1].strip()}" if lines else ""

    def add_metadata(
        self, name: str, data: dict[str, str], stall_timeout_s: float = WRITER_STALL_S
    ) -> None:
        """An MCAP metadata record (string values), written as soon as the writer reads it."""
        self._send({"type": "metadata", "name": name, "data": valid_strings(data)}, stall_timeout_s)

    # -- RecordSink -----------------------------------------------------------------------
    # The hot path. The taps write each frame's row into the frame ring as the bus hands it
    # over; ``push``, after the tick's last command frame is on its way, writes the tick's row
    # with one ``struct.pack_into`` and a few buffer copies, and publishes the tick: its
    # frames, then its row (a tick without a push when the next one begins, with its frames).
    # Events go out as they happen, before the row. So a SIGKILL costs at most the tick in
    # progress. Frames sent after a tick's push (the nodes' disable after the last control
    # tick) still belong to it: they are published with the next row, before it, where
    # ``rerun.tick_inputs`` looks. In the running loop every Python-level operation here
    # costs about a microsecond and the 99th percentile grows with their number (docs/
    # recording.md, "Cost"), so the common path has as few as it can.
    def begin_tick(self, tick: Tick) -> None:
        if self._drained is not None:  # the last tick's, with no frame sent after it
            self._write_drain(self._drained)
            self._drained = None
        if self._pose_list is not None:  # the last tick's, which had no push
            self._copy_poses()
        if self._row >= 0:  # the last tick had no push (start-up, shut-down): publish it now
            self._publish_idle()
        self._tk = tick
        self._tick = tick.tick
        self._now = tick.now_ns
        head = self._head
        if head - self._tail > self._tick_mask and self._ring_full(_TICKS, head, self._tick_mask):
            self._row = -1
            return
        self._row = head & self._tick_mask

    def _publish_idle(self) -> None:
        """The row of a tick that only polled is its head alone; publish it with its frames."""
        _TICK_HEAD.pack_into(
            self._buf,
            self._tick_base + self._row * self._tick_stride,
            *self._tk,
            0,
        )
        self._publish()

    def _publish(self) -> None:
        """The tick is complete: publish its frames, then its row."""
        self._row = -1
        self._head += 1
        ctl = self._ctl_view
        ctl[FRAME_HEAD] = self._fhead
        ctl[TICK_HEAD] = self._head

    def push(self, record: TickRecord) -> None:
        row = self._row
        sup = self._sup
        joints = self._joints
        if row < 0 or sup is None or joints is None:
            self._push_rarely(record)
            self._raise_tap_error()
            return
        faults = len(sup.faults)
        phase = record.phase
        # The tick's events (and a new phase's number) before its row, so that a reader that
        # meets the row has met them. Each check is a compare that nearly always finds
        # nothing; the phase's is by identity (the runtime hands over the same name).
        if (
            phase is not self._last_phase
            or faults != self._faults
            or len(sup.history) != self._history
            or self._reject_lists != self._reject_seen
        ):
            self._sweep(sup, phase)
        state = record.state
        if state is not self._state_name:
            self._state_name, self._state = state, self._states.get(state, -1)
        s = record.stage_ns
        self._row_pack(
            self._buf,
            self._tick_base + row * self._tick_stride,
            *self._tk,
            1,
            s[0],
            s[1],
            s[2],
            s[3],
            self._state,
            self._phase,
            faults,
            *joints.node_state,
            *joints.node_faults,
        )
        # The vectors by memoryview slice assignment: no numpy call, no allocation. The
        # views of the runtime's arrays are made once (an array the runtime swaps in, the
        # zero vector for the runner's, gets its view made when first seen).
        if joints.feedback_ns is not self._feedback:
            self._new_feedback(joints.feedback_ns)
        n = self._n
        at = row * self._tick_ints + self._feedback_at
        self._ints[at : at + n] = self._feedback_view
        if (
            record.angle is not self._angle
            or record.tdt is not self._tdt
            or record.desired is not self._desired
            or record.applied is not self._applied
        ):
            self._copy_floats(row, record)
        else:
            floats = self._floats
            at = row * 4 * n
            joints_view = self._joints_view
            if joints_view is not None:
                floats[at : at + 2 * n] = joints_view
            else:  # angles and torques not side by side
                floats[at : at + n] = self._angle_view
                floats[at + n : at + 2 * n] = self._tdt_view
            floats[at + 2 * n : at + 3 * n] = self._desired_view
            floats[at + 3 * n : at + 4 * n] = self._applied_view
        ctl = self._ctl_view
        poses = self._pose_list
        if poses is not None:
            # ``_copy_poses``, inline: every tenth tick of a run of the simulated hand, where
            # the copy's code and data have gone cold since the last, a call more cost a
            # microsecond or two of the slowest ticks' (the ticks that carry poses were most of
            # the 99th percentile's).
            self._pose_list = None
            head = self._phead
            if head - self._ptail <= self._pose_mask:
                try:
                    self._pose_pack(
                        self._buf,
                        self._pose_base + (head & self._pose_mask) * self._pose_stride,
                        self._tick,
                        self._now,
                        *_flatten(poses),
                    )
                    ctl[POSE_HEAD] = self._phead = head + 1
                except struct.error:  # a pose list of another length
                    self._pose_list = poses
                    self._copy_poses()
            else:
                self._pose_list = poses
                self._copy_poses()
        if self._drained is not None:  # a tick that sent nothing after its drain
            self._write_drain(self._drained)
            self._drained = None
        ctl[FRAME_HEAD] = self._fhead
        self._row = -1
        self._head = head = self._head + 1
        ctl[TICK_HEAD] = head
        bus = self._bus
        if bus is not None and bus.tap_error is not None:
            self._raise_tap_error()

    def _raise_tap_error(self) -> None:
        """Raise what a tap of this recorder raised since the last push (the bus holds it,
        ``FrameBus.tap_error``), once the tick's row is written: the recorder's failure, in
        the record stage, where the runtime names it (RECORD_EXCEPTION). Let out where it
        came from, the bus's ``send``, it was the send stage's, and the frame that went was
        taken for one the bus refused (found by an outside audit)."""
        bus = self._bus
        if bus is not None and bus.tap_error is not None:
            failure, bus.tap_error = bus.tap_error, None
            raise failure

    def _push_rarely(self, record: TickRecord) -> None:
        """``push`` without a row (the tick ring was full) or without an attached runtime:
        the tick's events, poses and frames are still recorded, the row when there is one."""
        row = self._row
        sup = self._sup
        faults = 0
        if sup is not None:
            faults = len(sup.faults)
            if (
                record.phase != self._last_phase
                or faults != self._faults
                or len(sup.history) != self._history
                or self._reject_lists != self._reject_seen
            ):
                self._sweep(sup, record.phase)
        if row >= 0:
            phase = self._phases.get(record.phase)
            if phase is None:
                phase = self._intern(record.phase)
            s = record.stage_ns
            joints = self._joints
            node_state = joints.node_state if joints is not None else self._no_states
            node_faults = joints.node_faults if joints is not None else self._no_faults
            self._row_pack(
                self._buf,
                self._tick_base + row * self._tick_stride,
                *self._tk,
                1,
                s[0],
                s[1],
                s[2],
                s[3],
                self._states.get(record.state, -1),
                phase,
                faults,
                *node_state,
                *node_faults,
            )
            if joints is not None:
                if joints.feedback_ns is not self._feedback:
                    self._new_feedback(joints.feedback_ns)
                at = row * self._tick_ints + self._feedback_at
                self._ints[at : at + self._n] = self._feedback_view
            self._copy_floats(row, record)
        if self._pose_list is not None:
            self._copy_poses()
        if self._drained is not None:
            self._write_drain(self._drained)
            self._drained = None
        if row >= 0:
            self._publish()
        else:
            self._ctl_view[FRAME_HEAD] = self._fhead

    def _new_feedback(self, feedback_ns: Any) -> None:
        """The view of the driver's feedback times, made again when it has another array."""
        self._feedback = feedback_ns
        self._feedback_view = feedback_ns.data.cast("B").cast("q")

    def _copy_floats(self, row: int, record: TickRecord) -> None:
        """The row's four vectors when the runtime handed over an array not seen before: the
        views made anew (the angles' and torques' as one when they lie side by side), or (not
        a contiguous float64 vector of n) a numpy copy."""
        vectors = (record.angle, record.tdt, record.desired, record.applied)
        try:
            views = [_view(v) for v in vectors]
            n = self._n
            at = row * 4 * n
            for i, view in enumerate(views):
                self._floats[at + i * n : at + (i + 1) * n] = view
        except (TypeError, ValueError, BufferError):  # not a float64 vector of n
            self._angle = self._tdt = self._desired = self._applied = None
            n = self._n
            values = self._tf[row]
            for i, vector in enumerate(vectors):
                values[i * n : (i + 1) * n] = vector
            return
        self._joints_view = _side_by_side(record.angle, record.tdt)
        self._angle_view, self._tdt_view, self._desired_view, self._applied_view = views
        self._angle, self._tdt, self._desired, self._applied = vectors

    def dropped_records(self) -> int:
        """Records the rings had no room for so far (ticks, frames, events): the writer has
        not taken them in time. A few integer reads of the shared control block."""
        ctl = self._ctl_view
        return int(ctl[DROPPED_TICKS] + ctl[DROPPED_FRAMES] + ctl[DROPPED_EVENTS])

    def log_removed(self) -> bool:
        """Whether the file the writer writes has no name left: removed, or its directory,
        while the run records to it. Whatever the writer goes on writing is then lost when
        it closes, and the run drove the hand unrecorded to its end (said only then: found
        by an outside audit). One ``fstat`` of the descriptor the recorder holds, which
        stays valid whatever is done to the path; a log renamed keeps its recording."""
        try:
            held = os.fstat(self._log_fd)
        except OSError:
            return False
        return stat.S_ISREG(held.st_mode) and held.st_nlink == 0

    def note(self, kind: str, detail: str, tick: int) -> None:
        self._event(EV_REQUEST, tick, kind, detail)

    # -- taps: each frame's row written as the bus hands it over ---------------------------
    # A frame's time is its tick's (the clock stands still inside a lockstep tick; in real
    # time a tick's frames are drained or sent within its first few hundred microseconds); a
    # received frame keeps the adapter's own time stamp as well. The bus hands a burst of
    # sent frames over in one call (the tick's command frames), and a drain's block waits for
    # the tick's first burst and goes into the ring with it: in the running loop every call
    # costs about a microsecond, and a tick's first ``pack_into`` some 2 us more than the
    # others whatever it packs, so a tick's frames are two calls and one ``pack_into`` (the
    # block is written before anything that follows it: the next tick, the tick's push,
    # another drain, the end).
    def _sent(self, frames: list[tuple[int, bytes]], direction: int) -> None:
        """A burst's sent frames, a row each (direction, t, tick, arbitration id, data), after
        the last drain's block if it is not written yet: all with one ``pack_into``."""
        count = len(frames)
        drained = self._drained
        now = self._now
        tick = self._tick
        head = self._fhead
        at = head & self._frame_mask
        if drained is not None:
            self._drained = None
            rx = len(drained)
            end = head + rx + 1 + count
            try:
                pack = self._sent_packs[rx][count]
            except IndexError:  # a long drain or burst: written apart
                pack = None
            fits = end <= self._frame_limit and at + rx + count <= self._frame_mask
            if pack is not None and fits:
                args = [self._buf, self._frame_base + at * FRAME_ROW, TAP_RX, now, tick, rx]
                for frame in drained:
                    args += frame
                for arbitration_id, data in frames:
                    args += (direction, now, tick, arbitration_id, data)
                pack(*args)
                self._fhead = end
                self._drains += 1
                return
            self._write_drain(drained)
            self._new_packs(rx, count)
            head = self._fhead
            at = head & self._frame_mask
        end = head + count
        try:
            pack = self._burst_packs[count]
        except IndexError:
            pack = None
        if pack is not None and end <= self._frame_limit and at + count <= self._frame_mask + 1:
            args = [self._buf, self._frame_base + at * FRAME_ROW]
            for arbitration_id, data in frames:
                args += (direction, now, tick, arbitration_id, data)
            pack(*args)
            self._fhead = end
            return
        self._send_slowly(frames, direction)

    def _send_slowly(self, frames: list[tuple[int, bytes]], direction: int) -> None:
        """A burst's rows a call each, with a look at the writer's tail when the ring looks
        full (a frame that does not fit is dropped and counted); the struct of a burst of this
        many frames made for the next time."""
        if len(frames) <= MAX_BURST and self._burst_packs[len(frames)] is None:
            self._burst_packs[len(frames)] = struct.Struct(
                "<" + TX_FRAME_ROW * len(frames)
            ).pack_into
        for arbitration_id, data in frames:
            head = self._fhead
            if head >= self._frame_limit and self._frames_full(head + 1, 1):
                continue
            self._tx_pack(
                self._buf,
                self._frame_base + (head & self._frame_mask) * FRAME_ROW,
                direction,
                self._now,
                self._tick,
                arbitration_id,
                data,
            )
            self._fhead = head + 1

    def _new_packs(self, rx: int, count: int) -> None:
        """The struct of a drain's block of ``rx`` frames followed by ``count`` sent frames,
        made when first met, if it is one to keep (a few, met every tick)."""
        if rx <= _PACKED_DRAIN and count <= MAX_BURST and self._sent_packs[rx][count] is None:
            block = "<" + RX_HEAD_ROW + RX_FRAME_ROW * rx + TX_FRAME_ROW * count
            self._sent_packs[rx][count] = struct.Struct(block).pack_into

    def _drain_before_start(self, frames: list[Frame]) -> None:
        """``_drain`` for the drains before the first tick, stamped with the clock's time
        now; at the first drain of a tick it hands the tap over to ``_drain`` itself, so
        that the ticks' drains pay nothing for it."""
        if self._tick >= 0:
            if self._runtime is not None:
                self._runtime.driver.bus.rx_tap = self._drain
        elif self._clock_ns is not None:
            self._now = self._clock_ns()
        self._drain(frames)

    def _drain(self, frames: list[Frame]) -> None:
        """A drain's frames, kept for the next burst sent to write (``_sent``)."""
        if self._drained is not None:  # two drains with no frame sent between them
            self._write_drain(self._drained)
        self._drained = frames

    def _write_drain(self, frames: list[Frame]) -> None:
        """A drain's block: its head row (TAP_RX, t, tick, count), then its frames' rows laid
        out as the bus's own ``Frame`` tuples, with one ``pack_into`` of their fields (a
        struct per count of frames, made when first met; the arguments a list extended by
        each frame, in the running loop a little cheaper than a chain). A block that would
        wrap round the ring's end, or does not fit, or is long, goes a row a call
        (``_drain_slowly``)."""
        count = len(frames)
        head = self._fhead
        end = head + count + 1
        at = head & self._frame_mask
        pack = self._drain_packs[count] if count <= _PACKED_DRAIN else None
        if pack is None or end > self._frame_limit or at + count > self._frame_mask:
            self._drain_slowly(frames, head)
            return
        args = [self._buf, self._frame_base + at * FRAME_ROW, TAP_RX, self._now, self._tick, count]
        for frame in frames:
            args += frame
        pack(*args)
        self._fhead = end
        self._drains += 1

    def _drain_slowly(self, frames: list[Frame], head: int) -> None:
        """A drain's block a row a call, with a look at the writer's tail when the ring looks
        full: a block that does not fit is dropped whole and its frames counted. Makes the
        struct of a block of this many frames for the next time, if it is one to keep."""
        count = len(frames)
        if count <= _PACKED_DRAIN and self._drain_packs[count] is None:
            self._drain_packs[count] = struct.Struct(
                "<" + RX_HEAD_ROW + RX_FRAME_ROW * count
            ).pack_into
        end = head + count + 1
        if end > self._frame_limit and self._frames_full(end, count):
            return
        buf, base, mask = self._buf, self._frame_base, self._frame_mask
        _RX_HEAD.pack_into(
            buf, base + (head & mask) * FRAME_ROW, TAP_RX, self._now, self._tick, count
        )
        for frame in frames:
            head += 1
            _RX_FRAME.pack_into(buf, base + (head & mask) * FRAME_ROW, *frame)
        self._fhead = end
        self._drains += 1

    def _frames_full(self, end: int, records: int) -> bool:
        """The frame ring looked full up to row ``end`` by the tail this side last read: read
        the writer's tail again; if the rows still do not fit, the ``records`` about to be
        written are dropped, and counted where the writer reports them."""
        ctl = self._ctl_view
        self._ftail = tail = ctl[FRAME_TAIL]
        self._frame_limit = tail + self.layout.frame_capacity
        if end > self._frame_limit:
            ctl[DROPPED_FRAMES] += records
            return True
        return False

    def _ring_full(self, ring: _Ring, head: int, mask: int, records: int = 1) -> bool:
        """A ring looked full by the tail this side last read: read the writer's tail again
        (and keep it); if the ring is still full, the ``records`` about to be written are
        dropped, and counted where the writer reports them. The caller compares first, so
        that a ring with room costs one subtraction."""
        ctl = self._ctl_view
        tail = ctl[ring.tail_slot]
        setattr(self, ring.tail_attribute, tail)
        if head - tail > mask:
            ctl[ring.dropped_slot] += records
            return True
        return False

    def _bus_event(self, event: BusEvent) -> None:
        # one heard before the first tick is the first tick's (its poll takes it): stamped
        # tick -1, it made the whole log unreadable to every reader, whose ticks start at 0
        # (found by an outside audit: remote frames on the bus while a run started)
        tick = max(self._tick, 0)
        # and the frame id of a remote frame: the re-run hears it as the run did (a
        # foreign id, or another sender on a command id); without it the re-run counted
        # nothing, and a run stopped on FOREIGN_COMMAND re-ran as one that went on
        frame_id = "" if event.frame_id is None else str(event.frame_id)
        self._event(EV_BUS, tick, event.kind.value, event.detail, str(event.timestamp_ns), frame_id)

    def poses(self, poses: Sequence[tuple[float, float, float]]) -> None:
        """Ground truth of the simulated objects at the current tick: (x, y, angle) each.

        Kept by reference and copied into the ring with the tick's row, in ``push`` (or when
        the next tick begins, for a tick without one), with one ``pack_into``: the caller
        hands over a sequence it no longer changes. The ticks that carry poses were a third
        of the slowest 1 % of the recording's, and every C call in the running loop costs
        about a microsecond.
        """
        if self._pose_list is not None:  # two calls in one tick: both are kept, in order
            self._copy_poses()
        self._pose_list = poses

    def _copy_poses(self) -> None:
        """Copy the poses noted this tick (``poses``) into their ring."""
        poses, self._pose_list = self._pose_list, None
        assert poses is not None
        head = self._phead
        mask = self._pose_mask
        if head - self._ptail > mask and self._ring_full(_POSES, head, mask):
            return
        row = head & mask
        # One ``pack_into`` of the row, the poses flattened in C: numpy item and slice
        # assignments cost tens of microseconds here, a comprehension several times as much,
        # and in the running loop every further C call about a microsecond.
        try:
            self._pose_pack(
                self._buf,
                self._pose_base + row * self._pose_stride,
                self._tick,
                self._now,
                *_flatten(poses),
            )
        except struct.error:  # a pose list of another length: what fits, the rest NaN
            values = tuple(_flatten(poses))
            self._rings.pose_i[row] = (self._tick, self._now)
            row_values = self._rings.pose_f[row]
            row_values[:] = float("nan")
            row_values[: min(len(values), len(row_values))] = values[: len(row_values)]
        self._phead = head + 1
        self._ctl_view[POSE_HEAD] = head + 1

    # -- events (rare: strings are fine here) ---------------------------------------------
    def _event(self, kind: int, tick: int, *fields: str) -> None:
        if self.closed:
            return
        if self._tick < 0 and self._clock_ns is not None:  # before the first tick: its time
            self._now = self._clock_ns()
        head = self._ehead
        if head - self._etail > self._event_mask and self._ring_full(
            _EVENTS, head, self._event_mask
        ):
            return
        row = head & self._event_mask
        text = _event_text(fields)
        _EVENT.pack_into(self._buf, self._event_base + row * 32, self._now, tick, kind, len(text))
        start = self._event_data + row * EVENT_BYTES
        self._buf[start : start + len(text)] = text
        self._ehead = head + 1
        self._ctl_view[EVENT_HEAD] = head + 1

    def _intern(self, name: str) -> int:
        index = len(self._phases)
        self._phases[name] = index
        self._event(EV_INTERN, self._tick, str(index), name)
        return index

    def _sweep(self, sup: Supervisor, phase: str) -> None:
        """Turn what changed since the last tick into events: supervisor transitions, faults,
        the phase, reject counts; and keep the phase's number for the row. ``push`` calls it
        when one of them looks changed, which is seldom."""
        if len(sup.history) != self._history:
            if len(sup.history) < self._history:
                self._history = 0
            for tick, before, event, after in sup.history[self._history :]:
                self._event(EV_STATE, tick, after.value, before.value, event.value)
            self._history = len(sup.history)
        if len(sup.faults) != self._faults:
            if len(sup.faults) < self._faults:  # an explicit reset cleared them
                self._faults = 0
            for fault in sup.faults[self._faults :]:
                self._event(
                    EV_FAULT,
                    fault.tick,
                    fault.code.name,
                    FAULTS[fault.code].category.name.lower(),
                    fault.detail,
                )
            self._faults = len(sup.faults)
        if phase is not self._last_phase:
            if phase != self._last_phase:
                exit_reason = ""
                runner = self._runtime.runner if self._runtime is not None else None
                if runner is not None:
                    for rec in reversed(runner.records):
                        if rec.name == self._last_phase:
                            exit_reason = rec.exit
                            break
                self._event(EV_PHASE, self._tick, phase, self._last_phase, exit_reason)
            number = self._phases.get(phase)
            self._phase = self._intern(phase) if number is None else number
            self._last_phase = phase
        if self._reject_lists != self._reject_seen:
            from handctl.online.drivers.receiver import REJECT_KINDS

            for kind in REJECT_KINDS:
                count = sum(c[kind] for c in self._reject_lists)
                seen = sum(c[kind] for c in self._reject_seen)
                if count != seen:
                    self._event(EV_REJECT, self._tick, kind.name.lower(), str(count - seen))
            self._reject_seen = [list(c) for c in self._reject_lists]

    # -- the end --------------------------------------------------------------------------
    def close(
        self, summary: dict[str, Any] | None = None, stall_timeout_s: float = WRITER_STALL_S
    ) -> dict[str, Any]:
        """Publish the last row, hand over the summary, let the writer finish the file.

        Returns the recorder's accounts (ticks, frames, drops) for the run summary. A recorder
        that broke during the run (an exception in its own code, which the runtime turned into
        a stop) may break again here: the file is finished all the same, with everything the
        rings hold, and what could not be recorded is the ``HandctlError`` raised at the end.
        """
        if self.closed:
            return self.stats
        problem = ""
        try:
            if self._sup is not None:
                self._sweep(self._sup, self._last_phase)
        except Exception as exc:  # the file is still finished with what the rings hold
            problem = (
                f"the last events could not be recorded ({type(exc).__name__}: {str(exc)[:300]})"
            )
        untapped = self._detach()  # the taps come off whatever went wrong before
        problem = problem or untapped
        try:
            if self._pose_list is not None:
                self._copy_poses()
            if self._drained is not None:
                self._write_drain(self._drained)
                self._drained = None
            if self._row >= 0:
                self._publish_idle()
        except Exception as exc:  # as above: a recorder that broke in the run, broke again
            problem = problem or (
                f"the last tick could not be recorded ({type(exc).__name__}: {str(exc)[:300]})"
            )
        ctl = self._ctl_view
        ctl[FRAME_HEAD] = self._fhead
        ctl[TICK_HEAD] = self._head
        self.stats = {
            "path": str(self.path),
            "ticks": self._head,
            "frames": self._fhead - self._drains,
            "events": self._ehead,
            "dropped_ticks": ctl[DROPPED_TICKS],
            "dropped_frames": ctl[DROPPED_FRAMES],
            "dropped_events": ctl[DROPPED_EVENTS],
            "dropped_poses": ctl[DROPPED_POSES],
        }
        ctl[CLOSED] = 1
        self.closed = True
        handed = self._hand_over(summary, stall_timeout_s)  # whatever went wrong before it
        problem = problem or handed
        os.close(self._ctl_w)
        err, hung = self._wait_for_writer(stall_timeout_s)
        problem = problem or hung
        os.close(self._ready_r)
        said = err.decode(errors="replace").strip()
        if self.process.returncode != 0:
            problem = self._writer_failed(problem, said)
        elif said:
            # what the writer said of a log it did finish (no Foxglove channels, say): its
            # stderr was read only when it failed, and such a log was short of them silently
            self.stats["writer_notes"] = said
        self.stats["writer_exit"] = self.process.returncode
        lost = ""
        if not self._left_unclaimed():
            try:
                self.claim()  # a path that named nothing gets what the writer wrote
            except HandctlError as exc:
                problem = problem or str(exc).removeprefix(f"{self.path}: ")
            lost = self._lost()
        os.close(self._log_fd)
        self._release()
        if lost:
            problem = f"{lost}; {problem}" if problem else lost
        if problem:
            raise HandctlError(f"{self.path}: {problem}")
        return self.stats

    def _detach(self) -> str:
        """Take the taps off the runtime's bus; what one raised since the last push, said
        (after the last push nothing else says it), or ""."""
        if self._runtime is None:
            return ""
        bus = self._runtime.driver.bus
        bus.tap = None
        bus.rx_tap = None
        bus.event_tap = None
        failed, bus.tap_error = bus.tap_error, None
        if failed is None:
            return ""
        return (
            f"a tap of the recorder failed after the last tick's row ({type(failed).__name__}: "
            f"{said_by(failed)[:300]}): frames or bus events from then on may be missing"
        )

    def _left_unclaimed(self) -> bool:
        """Whether the run never began and its path was left as it was (the recording
        beside it removed); False: the path is the run's to claim."""
        beside = self._beside
        if beside is None or beside.claimed:
            return False
        ours = beside.created and not self._path_taken()  # the file this run put there
        if ours and not self._start_failed:
            return False  # a path that named nothing gets what the writer wrote
        # The log there before stays, and so does a file put there while the run started.
        # A path that named nothing keeps naming nothing when the writer never started (a
        # live port another program took): the empty file made to hold it was put there,
        # 0 bytes, under "the log is as it was" (found by an outside audit). Unlinked while
        # the lock is still held, as in ``__init__``.
        if ours:
            with contextlib.suppress(OSError):
                beside.target.unlink()
        self._drop_beside()
        self.stats["previous_kept"] = not beside.created
        return True

    def claim(self) -> None:
        """The run begins: from here the recording is the log at its path, whatever was
        there before (``keep_previous``). Called before the first frame is sent."""
        beside = self._beside
        if beside is None or beside.claimed:
            return
        # another file put at the path during the start-up (whose file this run held) is
        # not the run's to replace: it was, without a word (found by an outside audit)
        if self._path_taken():
            raise HandctlError(
                f"{self.path}: another file was put at this path while the run started; it "
                "is left as it is, and nothing was sent (the recording of the start-up, "
                "which sent nothing either, is not kept)"
            )
        try:
            os.rename(beside.temp, beside.target)
        except OSError as exc:
            raise HandctlError(
                f"{self.path}: the recording could not be put at this path "
                f"({exc.strerror or exc}; it was written to {beside.temp})"
            ) from None
        beside.claimed = True
        os.close(beside.held)
        beside.held = -1

    def _path_taken(self) -> bool:
        """Whether another file than the one this run holds is at the path now (put there
        while the run started); one removed is nobody's."""
        beside = self._beside
        if beside is None or beside.held < 0:
            return False
        try:
            there = os.stat(beside.target)
        except OSError:
            return False
        held = os.fstat(beside.held)
        return (there.st_dev, there.st_ino) != (held.st_dev, held.st_ino)

    def _drop_beside(self) -> None:
        """The recording beside the path removed, and the path's file let go (an empty one
        this run made is the caller's to remove)."""
        beside = self._beside
        if beside is None or beside.claimed:
            return
        with contextlib.suppress(OSError):
            beside.temp.unlink()
        if beside.held >= 0:
            os.close(beside.held)
            beside.held = -1

    def _hand_over(self, summary: dict[str, Any] | None, stall_timeout_s: float) -> str:
        """The summary to the writer; what went wrong ("" if nothing did)."""
        try:
            if summary is not None:
                self.add_metadata(
                    "handctl.summary",
                    {"json": orjson.dumps(valid_strings(summary)).decode()},
                    stall_timeout_s,
                )
        except _WriterGoneError:  # why it went, from its stderr, is said once, by ``close``
            return "the recording writer is gone, and the run's summary is not in it"
        except HandctlError as exc:
            return str(exc).removeprefix(f"{self.path}: ") + ", and the run's summary is not in it"
        return ""

    def _wait_for_writer(self, stall_timeout_s: float) -> tuple[bytes, str]:
        """Wait for the writer to finish the file: its stderr, and what went wrong if it had
        to be killed.

        The hand is stopped by now (the runtime has returned), so the wait costs the hand
        nothing, but a writer that hangs (a stalled disk, a SIGSTOP) held the run's exit with
        no word until it went on. So the wait is said on stderr after ``WAIT_NOTICE_S``, with
        what is left to write, and it ends when the writer has moved nothing (ring tails and
        file size) for ``stall_timeout_s``, or after ``CLOSE_TIMEOUT_S`` in all: a writer that
        is slow but moving gets its time, a stuck one is killed, and the file ends where it
        stopped (a truncated file, which ``handctl replay`` reads up to there)."""
        started = changed = said = time.monotonic()
        seen = self._writer_progress()
        announced = False
        while True:
            try:
                _, err = self.process.communicate(timeout=WAIT_STEP_S)
                return err, ""
            except subprocess.TimeoutExpired:
                pass
            now = time.monotonic()
            progress = self._writer_progress()
            if progress != seen:
                seen, changed = progress, now
            waited = now - started
            # Said before any giving up: a wait that is given up on was said first.
            if now - said >= (WAIT_NOTICE_S if not announced else WAIT_NOTICE_EVERY_S):
                announced, said = True, now
                _say(
                    f"handctl: the hand is stopped; waiting {waited:.0f} s so far for the "
                    f"recording writer to finish {self.path} ({self._left_to_write()} records "
                    f"left to write; given up after {stall_timeout_s:g} s without progress)"
                )
            if now - changed >= stall_timeout_s or waited >= CLOSE_TIMEOUT_S:
                self.process.kill()
                _, err = self.process.communicate()
                why = (
                    f"moved nothing for {now - changed:.1f} s (stopped or hung)"
                    if now - changed >= stall_timeout_s
                    else f"did not finish within {CLOSE_TIMEOUT_S:g} s"
                )
                return err, (
                    f"the recording writer {why} and was killed with "
                    f"{self._left_to_write()} records still to write: the log may be "
                    "incomplete (it ends where the writer stopped; handctl replay reads it up "
                    "to there)"
                )

    def _writer_progress(self) -> tuple[int, ...]:
        """What the writer has done so far: the rings' tails and the file's size."""
        ctl = self._ctl_view
        try:
            size = os.fstat(self._log_fd).st_size
        except OSError:
            size = -1
        return (ctl[TICK_TAIL], ctl[FRAME_TAIL], ctl[EVENT_TAIL], ctl[POSE_TAIL], size)

    def _left_to_write(self) -> int:
        """Records published that the writer has not yet copied out of the rings."""
        ctl = self._ctl_view
        return sum(
            max(0, ctl[head] - ctl[tail])
            for head, tail in (
                (TICK_HEAD, TICK_TAIL),
                (FRAME_HEAD, FRAME_TAIL),
                (EVENT_HEAD, EVENT_TAIL),
                (POSE_HEAD, POSE_TAIL),
            )
        )

    def _lost(self) -> str:
        """Whether the path still names the file the writer wrote: the log's directory
        removed during the run, or the log unlinked, renamed or replaced, left a run that
        said where it had recorded to and nothing (or another file) was there. Empty if it
        does."""
        try:
            written = os.fstat(self._log_fd)
        except OSError:
            return ""
        if not stat.S_ISREG(written.st_mode):
            return ""  # a device: nothing to compare
        try:
            there = os.stat(self.path)
        except FileNotFoundError:
            there = None
        except OSError as exc:
            return (
                f"the log cannot be checked at this path at the end of the run "
                f"({exc.strerror or exc}): it may not be there"
            )
        if there is not None and (there.st_dev, there.st_ino) == (written.st_dev, written.st_ino):
            return self._emptied()
        where = (
            "nothing is there now"
            if there is None
            else "another file is there now (the log was replaced)"
        )
        kept = (
            "the recording is lost (the file was removed, or its directory)"
            if written.st_nlink == 0
            else "the recording is elsewhere (the file or its directory was renamed)"
        )
        return f"expected the recording at this path at the end of the run, but {where}: {kept}"

    def _emptied(self) -> str:
        """Whether the file at the path, the one the writer wrote, no longer begins as a
        recording does: emptied in place while the run recorded to it (``: > RUN.mcap``,
        logrotate's copytruncate), the writer went on at its own offset after a hole of
        zeros, and the run said it had recorded, exit 0 (found by an outside audit). Empty if
        it begins as one."""
        try:
            fd = os.open(self.path, os.O_RDONLY | os.O_CLOEXEC)
        except OSError:
            return ""  # said by the checks of the path above, or not ours to read
        try:
            head = os.pread(fd, len(MCAP_MAGIC), 0)
        except OSError:
            return ""
        finally:
            os.close(fd)
        if head == MCAP_MAGIC:
            return ""
        return (
            "expected the recording at this path at the end of the run, but the file no "
            "longer begins as one: it was emptied or written over while the run recorded "
            "to it (': > FILE', logrotate's copytruncate): the recording is lost"
        )

    def _writer_failed(self, problem: str, said: str) -> str:
        """What to say of a writer that exited with an error (``said``, its stderr) besides
        what the recorder saw of it (``problem``): why it went (a full disk: "OSError:
        [Errno 28] No space left on device"), the last line of its traceback."""
        how = how_it_ended(self.process.returncode)
        if not problem:
            # a writer killed says nothing: "failed (exit -9): " ended on an empty reason
            return f"the writer failed ({how})" + (f": {said[-2000:]}" if said else "")
        if not said:
            return problem
        return (
            f"{problem} ({said.splitlines()[-1][:300]}); the file ends where the writer "
            "stopped (handctl replay reads it up to there)"
        )

    def _release(self) -> None:
        self._ctl_view.release()
        self._floats.release()
        self._ints.release()
        self._rings.release()
        del self._ti, self._tf
        with contextlib.suppress(BufferError):  # a view still alive: the mapping goes with it
            self._mmap.close()

    def __enter__(self) -> Recorder:
        return self

    def __exit__(self, kind: object, exc: object, tb: object) -> None:
        if self.closed:
            return
        if exc is None:
            self.close()
            return
        try:
            self.close()
        except HandctlError as error:
            # the exception in flight (a bus error, a fault) says more and keeps its exit
            # code, but a log lost with it is said too: it was said of no other exit. Not
            # when the writer never started: the exception in flight is that, and says it
            if self._ready:
                _say(
                    f"handctl: and the run's log {self.path} is lost or may be incomplete: {error}"
                )
            return
        self.say_if_previous_kept()

    def say_if_previous_kept(self) -> None:
        """One line when the run ended before it began and the log at its path was kept."""
        if self.stats.get("previous_kept"):
            _say(f"handctl: {self.path}: the run never began; the log there before is kept")
