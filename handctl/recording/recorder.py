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
import mmap
import os
import select
import struct
import subprocess
import sys
import tempfile
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import orjson

from handctl.bus import TAP_RX, BusEvent, Frame
from handctl.config import HandConfig
from handctl.errors import ConfigError, HandctlError
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
    FRAME_BYTES,
    FRAME_HEAD,
    FRAME_ROW,
    FRAME_TAIL,
    I_FEEDBACK,
    POSE_HEAD,
    POSE_TAIL,
    SEP,
    TICK_HEAD,
    TICK_TAIL,
    Layout,
    Rings,
)
from handctl.safety.faults import FAULTS
from handctl.safety.supervisor import State

if TYPE_CHECKING:
    from handctl.clock import Tick
    from handctl.loop import Runtime, TickRecord

_TICK_HEAD = struct.Struct("<qqqqq")  # tick, scheduled, now, missed, active
_TICK_REST = struct.Struct("<qqqqqqqq")  # active, 4 stages, state, phase, faults latched
_FRAME = struct.Struct(f"<qqqqq{FRAME_BYTES}s")  # t, tick, id, direction | size << 8, bus time
_EVENT = struct.Struct("<qqqq")  # t, tick, kind, text length
#: Runner status names a phase column can also hold.
RUNNER_NAMES = ("-", "running", "end_ramp", "completed", "aborted")
STATE_NAMES = tuple(s.value for s in State)
#: How long ``close`` waits for the writer to finish the file.
CLOSE_TIMEOUT_S = 120.0
READY_TIMEOUT_S = 30.0


def _shared_memory(size: int) -> int:
    """An anonymous memory file both processes can map: memfd where there is one."""
    if hasattr(os, "memfd_create"):
        fd = os.memfd_create("handctl-recording", 0)
    else:  # pragma: no cover - not Linux
        with tempfile.TemporaryFile() as handle:
            fd = os.dup(handle.fileno())
    os.ftruncate(fd, size)
    return fd


class Recorder:
    """Records one run to ``path``; see the module docstring for how."""

    def __init__(self, path: str | Path, hand: HandConfig, metadata: dict[str, dict[str, str]],
                 *, phase_names: Sequence[str] = (), object_names: Sequence[str] = (),
                 layout: Layout | None = None) -> None:
        self.path = Path(path)
        self.layout = layout or Layout(hand.n_joints, len(hand.fingers), len(object_names))
        try:
            out_fd = os.open(self.path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC | os.O_CLOEXEC,
                             0o644)
        except OSError as exc:
            raise ConfigError(str(path), "", "a path where the recording can be written",
                              exc.strerror or str(exc)) from None
        shm_fd = _shared_memory(self.layout.size)
        self._mmap = mmap.mmap(shm_fd, self.layout.size)
        # Touch every page now: a page's first write is a page fault, microseconds each (more
        # in a virtual machine), which the loop would otherwise take every few ticks.
        for offset in range(0, self.layout.size, mmap.PAGESIZE):
            self._mmap[offset] = 0
        self._rings = Rings(self.layout, self._mmap)
        self._ctl_view = memoryview(self._mmap)[: CTL_WORDS * 8].cast("q")
        ctl_r, self._ctl_w = os.pipe()
        self._ready_r, ready_w = os.pipe()
        package_root = str(Path(__file__).resolve().parents[2])
        env = dict(os.environ)
        env["PYTHONPATH"] = os.pathsep.join(p for p in (package_root, env.get("PYTHONPATH"))
                                            if p)
        try:
            self.process = subprocess.Popen(
                [sys.executable, "-m", "handctl.recording.writer", str(shm_fd), str(ctl_r),
                 str(out_fd), str(ready_w)],
                pass_fds=(shm_fd, ctl_r, out_fd, ready_w), stdin=subprocess.DEVNULL,
                stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, env=env,
                start_new_session=True)
        finally:
            for fd in (shm_fd, ctl_r, out_fd, ready_w):
                os.close(fd)
        self._states = {name: i for i, name in enumerate(STATE_NAMES)}
        names = list(dict.fromkeys([*RUNNER_NAMES, *phase_names]))
        self._phases = {name: i for i, name in enumerate(names)}
        try:
            self._send({"type": "setup", "layout": self.layout.as_dict(),
                        "states": STATE_NAMES, "phases": names,
                        "joints": list(hand.joint_names),
                        "nodes": [f.name for f in hand.fingers], "objects": list(object_names),
                        "path": str(self.path), "metadata": metadata})
        except BaseException:
            self.process.kill()
            self.process.wait()
            os.close(self._ctl_w)
            os.close(self._ready_r)
            raise
        self._ready = False
        self.closed = False
        self.stats: dict[str, Any] = {}
        # Loop-side cursors: the head is ours; the tail is the writer's, re-read only when the
        # ring looks full, so the common path touches no shared word but the head.
        r = self._rings
        self._n = self.layout.n_joints
        self._buf: Any = self._mmap  # Any: numpy vectors are copied in by buffer protocol
        self._ti, self._tf = r.tick_i, r.tick_f
        self._tick_stride = self.layout.tick_ints * 8
        self._tick_base = r.offsets["tick_i"]
        self._float_base = r.offsets["tick_f"]
        self._float_stride = self.layout.tick_floats * 8
        self._vector_bytes = self._n * 8
        self._nodes_pack = struct.Struct(f"<{2 * self.layout.n_nodes}q").pack_into
        self._tick_mask = self.layout.tick_capacity - 1
        self._head = self._tail = 0
        self._row = -1
        self._frame_base = r.offsets["frame"]
        self._frame_mask = self.layout.frame_capacity - 1
        self._fhead = self._ftail = 0
        self._pending: list[list[Frame] | tuple[int, bytes, int]] = []
        self._event_base = r.offsets["event_i"]
        self._event_data = r.offsets["event_d"]
        self._event_mask = self.layout.event_capacity - 1
        self._ehead = self._etail = 0
        self._phead = self._ptail = 0
        self._tick = -1  # frames drained before the first tick (discarded at start-up)
        self._now = 0
        self._runtime: Runtime | None = None
        self._last_phase = ""
        self._history = 0
        self._faults = 0
        self._reject_lists: list[list[int]] = []
        self._reject_seen: list[list[int]] = []

    # -- set-up ---------------------------------------------------------------------------
    def attach(self, runtime: Runtime) -> None:
        """Tap the runtime's bus and keep the runtime, whose supervisor, runner and driver the
        recorder reads when something changes (a state, a phase, a reject count)."""
        self._runtime = runtime
        bus = runtime.driver.bus
        bus.tap = self._frame
        bus.rx_tap = self._rx
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
            self.process.kill()
            _, err = self.process.communicate(timeout=10)
            raise HandctlError(f"{self.path}: the recording writer did not start: "
                               f"{err.decode(errors='replace').strip() or 'no answer'}")
        self._ready = True

    def _send(self, message: dict[str, Any]) -> None:
        payload = orjson.dumps(message)
        try:
            os.write(self._ctl_w, struct.pack("<I", len(payload)))
            view = memoryview(payload)
            while view:
                view = view[os.write(self._ctl_w, view):]
        except BrokenPipeError:
            raise HandctlError(f"{self.path}: the recording writer is gone") from None

    def add_metadata(self, name: str, data: dict[str, str]) -> None:
        """An MCAP metadata record (string values), written as soon as the writer reads it."""
        self._send({"type": "metadata", "name": name, "data": data})

    # -- RecordSink -----------------------------------------------------------------------
    # The hot path. Before the commands are sent (poll, send) the taps only note references;
    # the copying into the rings happens in ``push``, after the tick's last command frame is
    # on its way, with a few ``struct.pack_into`` and buffer copies and the attributes read
    # into locals once. A tick's frames and its row are published together when the next tick
    # begins (frames first), so a SIGKILL costs the tick in progress and nothing before it.
    def begin_tick(self, tick: Tick) -> None:
        if self._pending:
            self._flush_frames()
        ctl = self._ctl_view
        if self._row >= 0:
            self._head += 1
        ctl[FRAME_HEAD] = self._fhead
        ctl[TICK_HEAD] = head = self._head
        self._tick = tick.k
        self._now = tick.now_ns
        mask = self._tick_mask
        if head - self._tail > mask:
            self._tail = ctl[TICK_TAIL]
            if head - self._tail > mask:
                ctl[DROPPED_TICKS] += 1
                self._row = -1
                return
        row = head & mask
        self._row = row
        _TICK_HEAD.pack_into(self._buf, self._tick_base + row * self._tick_stride, tick.k,
                             tick.scheduled_ns, tick.now_ns, tick.missed, 0)

    def push(self, record: TickRecord) -> None:
        if self._pending:
            self._flush_frames()
        runtime = self._runtime
        row = self._row
        if row >= 0:
            buf = self._buf
            phase = self._phases.get(record.phase)
            if phase is None:
                phase = self._intern(record.phase)
            s = record.stage_ns
            at = self._tick_base + row * self._tick_stride
            _TICK_REST.pack_into(buf, at + 32, 1, s[0], s[1], s[2], s[3],
                                 self._states.get(record.state, -1), phase,
                                 len(runtime.supervisor.faults) if runtime is not None else 0)
            size = self._vector_bytes
            at = self._float_base + row * self._float_stride
            try:
                buf[at:at + size] = record.angle
                buf[at + size:at + 2 * size] = record.tdt
                buf[at + 2 * size:at + 3 * size] = record.desired
                buf[at + 3 * size:at + 4 * size] = record.applied
            except (TypeError, ValueError, BufferError):  # not a float64 vector of n
                self._copy_floats(row, record)
            if runtime is not None:
                state = runtime.driver.state
                at = self._tick_base + row * self._tick_stride + I_FEEDBACK * 8
                buf[at:at + size] = state.feedback_ns
                self._nodes_pack(buf, at + size, *state.node_state, *state.node_faults)
        if runtime is not None:
            sup = runtime.supervisor
            if len(sup.history) != self._history or len(sup.faults) != self._faults \
                    or record.phase != self._last_phase \
                    or self._reject_lists != self._reject_seen:
                self._sweep(runtime, record.phase)

    def _copy_floats(self, row: int, record: TickRecord) -> None:
        n = self._n
        values = self._tf[row]
        values[:n] = record.angle
        values[n:2 * n] = record.tdt
        values[2 * n:3 * n] = record.desired
        values[3 * n:] = record.applied

    def note(self, kind: str, detail: str, tick: int) -> None:
        self._event(EV_REQUEST, tick, kind, detail)

    # -- taps: note now, copy in ``push`` -------------------------------------------------
    def _frame(self, arbitration_id: int, data: bytes, direction: int) -> None:
        self._pending.append((arbitration_id, data, direction))

    def _rx(self, frames: list[Frame]) -> None:
        self._pending.append(frames)

    def _flush_frames(self) -> None:
        """Copy the frames noted this tick into the ring, in the order they were on the bus.

        A frame's time is its tick's (the clock stands still inside a lockstep tick; in real
        time a tick's frames are drained or sent within its first few hundred microseconds);
        a received frame keeps the adapter's own time stamp as well.
        """
        head = self._fhead
        mask = self._frame_mask
        now, tick, buf, base = self._now, self._tick, self._buf, self._frame_base
        pack = _FRAME.pack_into
        for entry in self._pending:
            if isinstance(entry, list):
                for i, frame in enumerate(entry):
                    if head - self._ftail > mask and not self._frame_room(head, len(entry) - i):
                        break
                    data = frame.data
                    pack(buf, base + (head & mask) * FRAME_ROW, now, tick, frame.arbitration_id,
                         TAP_RX | len(data) << 8, frame.timestamp_ns, data)
                    head += 1
            else:
                if head - self._ftail > mask and not self._frame_room(head):
                    continue
                frame_id, data, direction = entry
                pack(buf, base + (head & mask) * FRAME_ROW, now, tick, frame_id,
                     direction | len(data) << 8, 0, data)
                head += 1
        self._pending.clear()
        self._fhead = head

    def _frame_room(self, head: int, frames: int = 1) -> bool:
        """The frame ring looked full: look again at the writer's tail; if it is full, the
        ``frames`` about to be written are dropped and counted."""
        ctl = self._ctl_view
        self._ftail = ctl[FRAME_TAIL]
        if head - self._ftail > self._frame_mask:
            ctl[DROPPED_FRAMES] += frames
            return False
        return True

    def _bus_event(self, event: BusEvent) -> None:
        self._event(EV_BUS, self._tick, event.kind.value, event.detail, str(event.timestamp_ns))

    def poses(self, poses: Sequence[tuple[float, float, float]]) -> None:
        """Ground truth of the simulated objects at the current tick: (x, y, angle) each."""
        head = self._phead
        mask = self.layout.pose_capacity - 1
        if head - self._ptail > mask:
            self._ptail = self._ctl_view[POSE_TAIL]
            if head - self._ptail > mask:
                self._ctl_view[DROPPED_POSES] += 1
                return
        row = head & mask
        r = self._rings
        r.pose_i[row, 0] = self._tick
        r.pose_i[row, 1] = self._now
        values = r.pose_f[row]
        for i, (x, y, angle) in enumerate(poses):
            values[3 * i:3 * i + 3] = (x, y, angle)
        self._phead = head + 1
        self._ctl_view[POSE_HEAD] = head + 1

    # -- events (rare: strings are fine here) ---------------------------------------------
    def _event(self, kind: int, tick: int, *fields: str) -> None:
        if self.closed:
            return
        head = self._ehead
        if head - self._etail > self._event_mask:
            self._etail = self._ctl_view[EVENT_TAIL]
            if head - self._etail > self._event_mask:
                self._ctl_view[DROPPED_EVENTS] += 1
                return
        row = head & self._event_mask
        text = SEP.join(fields).encode()[:EVENT_BYTES]
        _EVENT.pack_into(self._buf, self._event_base + row * 32, self._now, tick, kind,
                         len(text))
        start = self._event_data + row * EVENT_BYTES
        self._buf[start:start + len(text)] = text
        self._ehead = head + 1
        self._ctl_view[EVENT_HEAD] = head + 1

    def _intern(self, name: str) -> int:
        index = len(self._phases)
        self._phases[name] = index
        self._event(EV_INTERN, self._tick, str(index), name)
        return index

    def _sweep(self, runtime: Runtime, phase: str) -> None:
        """Turn what changed since the last tick into events: supervisor transitions, faults,
        the phase, reject counts. Each check is a length or a string compare when nothing
        changed, which is nearly always."""
        sup = runtime.supervisor
        if len(sup.history) != self._history:
            if len(sup.history) < self._history:
                self._history = 0
            for tick, before, event, after in sup.history[self._history:]:
                self._event(EV_STATE, tick, after.value, before.value, event.value)
            self._history = len(sup.history)
        if len(sup.faults) != self._faults:
            if len(sup.faults) < self._faults:  # an explicit reset cleared them
                self._faults = 0
            for fault in sup.faults[self._faults:]:
                self._event(EV_FAULT, fault.tick, fault.code.name,
                            FAULTS[fault.code].category.name.lower(), fault.detail)
            self._faults = len(sup.faults)
        if phase != self._last_phase:
            exit_reason = ""
            runner = runtime.runner
            if runner is not None:
                for rec in reversed(runner.records):
                    if rec.name == self._last_phase:
                        exit_reason = rec.exit
                        break
            self._event(EV_PHASE, self._tick, phase, self._last_phase, exit_reason)
            self._last_phase = phase
        if self._reject_lists != self._reject_seen:
            from handctl.drivers.receiver import REJECT_KINDS

            for kind in REJECT_KINDS:
                count = sum(c[kind] for c in self._reject_lists)
                seen = sum(c[kind] for c in self._reject_seen)
                if count != seen:
                    self._event(EV_REJECT, self._tick, kind.name.lower(), str(count - seen))
            self._reject_seen = [list(c) for c in self._reject_lists]

    # -- the end --------------------------------------------------------------------------
    def close(self, summary: dict[str, Any] | None = None) -> dict[str, Any]:
        """Publish the last row, hand over the summary, let the writer finish the file.

        Returns the recorder's accounts (ticks, frames, drops) for the run summary.
        """
        if self.closed:
            return self.stats
        if self._runtime is not None:
            self._sweep(self._runtime, self._last_phase)
            bus = self._runtime.driver.bus
            bus.tap = None
            bus.rx_tap = None
            bus.event_tap = None
        if self._pending:
            self._flush_frames()
        ctl = self._ctl_view
        ctl[FRAME_HEAD] = self._fhead
        if self._row >= 0:
            self._head += 1
            self._row = -1
        ctl[TICK_HEAD] = self._head
        self.stats = {"path": str(self.path), "ticks": self._head, "frames": self._fhead,
                      "events": self._ehead, "dropped_ticks": ctl[DROPPED_TICKS],
                      "dropped_frames": ctl[DROPPED_FRAMES],
                      "dropped_events": ctl[DROPPED_EVENTS],
                      "dropped_poses": ctl[DROPPED_POSES]}
        ctl[CLOSED] = 1
        self.closed = True
        problem = ""
        try:
            if summary is not None:
                self.add_metadata("handctl.summary", {"json": orjson.dumps(summary).decode()})
        except HandctlError as exc:
            problem = str(exc)
        os.close(self._ctl_w)
        try:
            _, err = self.process.communicate(timeout=CLOSE_TIMEOUT_S)
        except subprocess.TimeoutExpired:
            self.process.kill()
            _, err = self.process.communicate()
            problem = problem or f"the writer did not finish within {CLOSE_TIMEOUT_S:g} s"
        os.close(self._ready_r)
        if self.process.returncode != 0 and not problem:
            problem = (f"the writer failed (exit {self.process.returncode}): "
                       f"{err.decode(errors='replace').strip()[-2000:]}")
        self.stats["writer_exit"] = self.process.returncode
        self._release()
        if problem:
            raise HandctlError(f"{self.path}: {problem}")
        return self.stats

    def _release(self) -> None:
        self._ctl_view.release()
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
        with contextlib.suppress(HandctlError):  # the exception in flight says more
            self.close()
