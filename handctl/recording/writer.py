"""The writer process: copies rows out of the shared rings, encodes them as JSON, writes MCAP.

Run as ``python -m handctl.recording.writer SHM_FD CTL_FD OUT_FD READY_FD`` by ``Recorder``;
never by hand. It polls the rings every ``POLL_S``, so the control process hands over nothing
but a counter per record, and it ends when the control pipe closes: on purpose (the recorder
set ``CLOSED`` first) or because the control process died. Either way it copies out what is
left in the rings and finishes the file with its summary and indexes.

Chunks hold at most ``CHUNK_NS`` of log time (or ``CHUNK_WALL_S`` of wall time, whichever comes
first) and the file is flushed after each, so even if this process is killed too, what is on
disk is a readable MCAP prefix missing no more than the chunk in progress.
"""

from __future__ import annotations

import contextlib
import errno
import io
import math
import mmap
import os
import select
import signal
import struct
import sys
import time
import traceback
from typing import IO, TYPE_CHECKING, Any

import numpy as np
import orjson

from handctl import __version__
from handctl.errors import ConfigError
from handctl.foxglove.derived import Derived
from handctl.online.taps import TAP_RX, TAP_TX
from handctl.recording import channels as ch
from handctl.recording.mcapfile import ChunkWriter
from handctl.recording.metadata import package_version
from handctl.recording.ring import (
    CLOSED,
    DROPPED_EVENTS,
    DROPPED_FRAMES,
    DROPPED_POSES,
    DROPPED_TICKS,
    E_KIND,
    E_LEN,
    E_T,
    E_TICK,
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
    I_FAULTS,
    I_NODES,
    I_PHASE,
    I_STAGES,
    I_STATE,
    LIVE_REFUSED,
    N_STAGES,
    POSE_HEAD,
    POSE_TAIL,
    RECORDED_STAGES,
    RX_FRAME_ROW,
    RX_HEAD_ROW,
    SEP,
    TICK_HEAD,
    TICK_TAIL,
    TX_FRAME_ROW,
    RingLayout,
    Rings,
)

#: share of a ring the writer may be behind by before it holds the live view back (a
#: quarter: 2 s of ticks at 1 kHz, where the rings hold 8), and the share it must be back
#: under to serve the view again (half a second of ticks)
LIVE_PAUSE_SHARE = 0.25
LIVE_RESUME_SHARE = 1 / 16


class LivePace:
    """Whether the live view is served: it is held back while the writer is behind, and
    served again once the writer has caught up.

    Why: the live view's cost is the writer's, and grows with its clients (each message is
    queued for each one); 200 local clients that never read held the writer back until the
    rings overflowed, and the log lost 2084 ticks, manipulate_4 and the stop among them, in
    a run that exited 0. The log is what the run is judged by; the view is a convenience, so
    it gives way first, long before a ring is full."""

    def __init__(self) -> None:
        self.paused = False
        self.pauses = 0  # times it was held back
        self.skipped = 0  # messages not served meanwhile

    def update(self, backlog: float) -> bool:
        """``backlog``: how far behind the writer is, as the fullest ring's share (0..1).
        True when the view is served again: the newest message of each channel, held
        meanwhile, is then to be served (``LiveServer.send_held``), or the view stays on what
        it showed before it was held back until the channel's next message."""
        if not self.paused and backlog > LIVE_PAUSE_SHARE:
            self.paused = True
            self.pauses += 1
        elif self.paused and backlog < LIVE_RESUME_SHARE:
            self.paused = False
            return True
        return False


if TYPE_CHECKING:
    from handctl.foxglove.live import LiveServer

POLL_S = 0.01
CHUNK_NS = 50_000_000
CHUNK_WALL_S = 0.05
SYNC_EVERY_S = 1.0
_LENGTH = struct.Struct("<I")
_KIND = struct.Struct("<q")  # a frame block's first word: TAP_RX, or a sent frame's direction
_RX_HEAD = struct.Struct("<" + RX_HEAD_ROW)
_BLOCK_HEAD = struct.Struct("<qqq")  # every frame block's: its kind, time and tick
_RX_FRAME = struct.Struct("<" + RX_FRAME_ROW)
_TX_FRAME = struct.Struct("<" + TX_FRAME_ROW)


class Encoder:
    """Rings in, MCAP out: one instance per recording."""

    def __init__(
        self, rings: Rings, out: IO[bytes], setup: dict[str, Any], live: LiveServer | None = None
    ) -> None:
        self.rings = rings
        self.layout = rings.layout
        self.out = out
        self.n = self.layout.n_joints
        self.m = self.layout.n_nodes
        self.states: list[str] = list(setup["states"])
        self.phases: list[str] = list(setup["phases"])
        self.objects: list[str] = list(setup["objects"])
        #: The pairs whose centre line each pose message carries: the recipe's, by index
        #: into ``objects`` (a set-up without them: each object with the next).
        self.pairs: list[tuple[int, int]] = [
            (int(a), int(b))
            for a, b in (setup["pairs"] if "pairs" in setup else ch.pose_pairs(self.objects, ()))
        ]
        self.pair_names = [ch.pair_name(self.objects[a], self.objects[b]) for a, b in self.pairs]
        self.writer = ChunkWriter(
            out,
            ch.PROFILE,
            f"handctl {__version__} (records by mcap-python {package_version('mcap')})",
        )
        for name, data in setup["metadata"].items():
            self.writer.add_metadata(name, {k: str(v) for k, v in data.items()})
        self.writer.flush()
        schema_ids: dict[str, int] = {}
        self.channel: dict[str, int] = {}
        # each channel's metadata, the log's and the live view's alike: the live view's
        # were advertised without it, no ``joints`` to name a vector's entries by
        metadata: dict[str, dict[str, str]] = {}
        for channel in ch.CHANNELS:
            if channel.schema_name not in schema_ids:
                schema_ids[channel.schema_name] = self.writer.register_schema(
                    channel.schema_name, ch.SCHEMA_ENCODING, orjson.dumps(ch.schema_of(channel))
                )
            meta = {"handctl.format_version": str(ch.FORMAT_VERSION)}
            if channel.topic in (ch.JOINT_STATE, ch.TORQUE):
                meta["joints"] = ",".join(setup["joints"])
            if channel.topic == ch.JOINT_STATE:
                meta["nodes"] = ",".join(setup["nodes"])
            metadata[channel.topic] = meta
            self.channel[channel.topic] = self.writer.register_channel(
                channel.topic, ch.MESSAGE_ENCODING, schema_ids[channel.schema_name], meta
            )
        self.live = live
        if live is not None:
            for channel in ch.CHANNELS:
                live.add_channel(
                    channel.topic,
                    channel.schema_name,
                    ch.SCHEMA_ENCODING,
                    orjson.dumps(ch.schema_of(channel)),
                    ch.MESSAGE_ENCODING,
                    metadata[channel.topic],
                )
        self.derived: _SafeView | None = None
        try:
            self.derived = _SafeView(Derived.from_metadata(setup["metadata"], self.add_raw))
        except Exception as exc:  # a view must never cost the recording
            _note(f"handctl writer: no Foxglove channels: {exc}")
        if self.derived is not None:
            for derived in self.derived.channels:
                if derived.schema_name not in schema_ids:
                    schema_ids[derived.schema_name] = self.writer.register_schema(
                        derived.schema_name, derived.schema_encoding, derived.schema_data
                    )
                meta = {"handctl.format_version": str(ch.FORMAT_VERSION)}
                self.channel[derived.topic] = self.writer.register_channel(
                    derived.topic, derived.message_encoding, schema_ids[derived.schema_name], meta
                )
                if live is not None:
                    live.add_channel(
                        derived.topic,
                        derived.schema_name,
                        derived.schema_encoding,
                        derived.schema_data,
                        derived.message_encoding,
                        meta,
                    )
        self.sequence = dict.fromkeys(self.channel.values(), 0)
        self.ticks = self.frames = self.events = self.poses = 0
        self.messages = 0
        self.chunks = 0
        self.last_tick = -1
        self.last_log = 0
        self.chunk_log: int | None = None
        self.chunk_wall = 0.0
        self.synced = time.monotonic()
        self.can_sync = True  # until a sync says the file cannot be synced (``sync``)
        self.busy_s = 0.0
        self.dropped = [0, 0, 0, 0]
        self.live_pace = LivePace()

    def add(self, topic: str, log_time: int, payload: dict[str, Any], key: int = 0) -> None:
        self.add_raw(topic, log_time, orjson.dumps(payload), key)

    def add_raw(self, topic: str, log_time: int, data: bytes, key: int = 0) -> None:
        """One message into the file (and to the live view, which samples by ``key`` on a
        per-tick channel: a frame's id)."""
        channel = self.channel[topic]
        seq = self.sequence[channel]
        self.sequence[channel] = seq + 1
        self.writer.add_message(channel, log_time, data, seq & 0xFFFFFFFF)
        if self.live is not None:
            if self.live_pace.paused:
                self.live_pace.skipped += 1
                self.live.hold(topic, log_time, data, key)
            else:
                self.live.log(topic, log_time, data, key)
        self.messages += 1
        if self.chunk_log is None:
            self.chunk_log = log_time
            self.chunk_wall = time.monotonic()
        self.last_log = max(self.last_log, log_time)

    # -- draining -------------------------------------------------------------------------
    def drain(self) -> bool:
        """Copy out and encode everything published; True if there was anything.

        The tick head is read first: every frame and event of a published tick was published
        before it, so frames and events go out before the rows that follow them, and a reader
        that meets a tick's row has already met everything that belongs to it.

        A backlog of more than ``CHUNK_NS`` of ticks (a writer that was stopped, or held up
        by its disk, and catches up) goes out a slice of that much at a time, each slice's
        frames, events and poses before its rows and each closed as a chunk of its own: drained
        at once, it was one chunk of seconds (4 s, 19.7 MB after a 6 s SIGSTOP), which a CRC
        error or the writer's death then cost whole.
        """
        ctl = self.rings.ctl
        if self.live is not None:
            self._pace_live()
        busy = False
        while (cut := self._slice()) is not None:
            self.maybe_flush(force=True)  # the slice starts a chunk of its own
            self._drain_to(*cut)
            self.maybe_flush(force=True)
            busy = True
            # a backlog the loop keeps adding to (a lockstep run) keeps the writer here: the
            # live view gives way as it would between drains, or stalled viewers hold the
            # writer back until its rings overflow
            if self.live is not None:
                self._pace_live()
        tick_head = int(ctl[TICK_HEAD])
        heads = (int(ctl[FRAME_HEAD]), int(ctl[EVENT_HEAD]), int(ctl[POSE_HEAD]), tick_head)
        return self._drain_to(*heads) or busy

    def _pace_live(self) -> None:
        """Hold the live view back while the writer is behind, and serve it once caught up."""
        assert self.live is not None
        ctl, layout = self.rings.ctl, self.layout
        resumed = self.live_pace.update(
            max(
                (int(ctl[TICK_HEAD]) - int(ctl[TICK_TAIL])) / layout.tick_capacity,
                (int(ctl[FRAME_HEAD]) - int(ctl[FRAME_TAIL])) / layout.frame_capacity,
                (int(ctl[EVENT_HEAD]) - int(ctl[EVENT_TAIL])) / layout.event_capacity,
                (int(ctl[POSE_HEAD]) - int(ctl[POSE_TAIL])) / layout.pose_capacity,
            )
        )
        if resumed:
            self.live.send_held()

    def _drain_to(self, frame_head: int, event_head: int, pose_head: int, tick_head: int) -> bool:
        """Encode each ring up to the head given; True if there was anything."""
        ctl = self.rings.ctl
        busy = False
        if frame_head > ctl[FRAME_TAIL]:
            self._frames(int(ctl[FRAME_TAIL]), frame_head)
            busy = True
        if event_head > ctl[EVENT_TAIL]:
            self._events(int(ctl[EVENT_TAIL]), event_head)
            busy = True
        if pose_head > ctl[POSE_TAIL]:
            self._poses(int(ctl[POSE_TAIL]), pose_head)
            busy = True
        if tick_head > ctl[TICK_TAIL]:
            self._ticks(int(ctl[TICK_TAIL]), tick_head)
            busy = True
        self._drops()
        return busy

    def _slice(self) -> tuple[int, int, int, int] | None:
        """Where the first ``CHUNK_NS`` of a longer backlog of ticks ends in each ring
        (frames, events, poses, ticks), or None when the ticks published span less.

        The slice's rows end before a row that is published, so every frame and event of
        its ticks is published too (before that row); its frames, events and poses are those
        up to the last of its ticks (a row of a later tick before it goes out early, which a
        reader takes: never one of its ticks late, after a later row)."""
        rings, layout = self.rings, self.layout
        ctl = rings.ctl
        tail, head = int(ctl[TICK_TAIL]), int(ctl[TICK_HEAD])
        mask = layout.tick_capacity - 1
        # the common drain, of a few ms of ticks, reads two times and nothing more
        if (
            head - tail < 2
            or rings.tick_i[(head - 1) & mask, 2] - rings.tick_i[tail & mask, 2] < CHUNK_NS
        ):
            return None
        now = rings.tick_i[self._take(tail, head, layout.tick_capacity), 2]
        cut = tail + int(np.searchsorted(now, int(now[0]) + CHUNK_NS))
        cut = min(max(cut, tail + 1), head - 1)
        last = int(rings.tick_i[(cut - 1) & mask, 0])
        return (
            self._frames_through(last, int(ctl[FRAME_HEAD])),
            self._through(
                rings.event_i[:, E_TICK], int(ctl[EVENT_TAIL]), int(ctl[EVENT_HEAD]), last
            ),
            self._through(rings.pose_i[:, 0], int(ctl[POSE_TAIL]), int(ctl[POSE_HEAD]), last),
            cut,
        )

    def _through(self, ticks: np.ndarray, tail: int, head: int, last: int) -> int:
        """The head that takes a ring's rows up to its last one of tick ``last`` or before."""
        mine = np.flatnonzero(ticks[self._take(tail, head, len(ticks))] <= last)
        return tail + int(mine[-1]) + 1 if len(mine) else tail

    def _frames_through(self, last: int, head: int) -> int:
        """The head that takes the frame blocks up to the last of tick ``last`` or before:
        the loop stamps each block with its tick, which only grows, so the first block of a
        later tick ends them."""
        frame, mask = self.rings.frame, self.layout.frame_capacity - 1
        at = int(self.rings.ctl[FRAME_TAIL])
        while at < head:
            kind, _, tick = _BLOCK_HEAD.unpack_from(frame[at & mask])
            if tick > last:
                break
            if kind == TAP_RX:
                count = int(_RX_HEAD.unpack_from(frame[at & mask])[3])
                at += 1 + max(0, min(count, head - at - 1))
            else:
                at += 1
        return at

    def _take(self, tail: int, head: int, capacity: int) -> np.ndarray:
        return np.arange(tail, head, dtype=np.int64) & (capacity - 1)

    def _frames(self, tail: int, head: int) -> None:
        """The frame rows between ``tail`` and ``head``, block by block (``ring.py``): the
        loop publishes whole blocks, so ``tail`` is always at the start of one."""
        rings = self.rings
        index = self._take(tail, head, self.layout.frame_capacity)
        raw = rings.frame[index].tobytes()
        rings.ctl[FRAME_TAIL] = head
        rows = len(index)
        add, derived = self.add, self.derived
        i = 0
        while i < rows:
            at = i * FRAME_ROW
            kind = _KIND.unpack_from(raw, at)[0]
            if kind == TAP_RX:
                _, t_ns, tick, count = _RX_HEAD.unpack_from(raw, at)
                count = max(0, min(count, rows - i - 1))
                for j in range(i + 1, i + 1 + count):
                    frame_id, payload, bus_ns, _ = _RX_FRAME.unpack_from(raw, j * FRAME_ROW)
                    message = {"tick": tick, "id": frame_id, "data": payload.hex()}
                    message["bus_time_ns"] = bus_ns
                    add(ch.CAN_RX, t_ns, message, frame_id)
                    if derived is not None:
                        derived.frame(t_ns, tick, True, frame_id, payload)
                self.frames += count
                i += count + 1
                continue
            direction, t_ns, tick, frame_id, payload = _TX_FRAME.unpack_from(raw, at)
            add(
                ch.CAN_TX,
                t_ns,
                {"tick": tick, "id": frame_id, "data": payload.hex(), "ok": direction == TAP_TX},
                frame_id,
            )
            if derived is not None:
                derived.frame(t_ns, tick, False, frame_id, payload)
            self.frames += 1
            i += 1

    def _events(self, tail: int, head: int) -> None:
        rings = self.rings
        index = self._take(tail, head, self.layout.event_capacity)
        rows = rings.event_i[index].tolist()
        raw = rings.event_d[index].tobytes()
        rings.ctl[EVENT_TAIL] = head
        for j, row in enumerate(rows):
            text = raw[j * EVENT_BYTES : j * EVENT_BYTES + row[E_LEN]].decode(errors="replace")
            fields = text.split(SEP)
            kind, tick, t_ns = row[E_KIND], row[E_TICK], row[E_T]
            if kind == EV_INTERN:
                index_, name = int(fields[0]), fields[1]
                self.phases += [""] * (index_ + 1 - len(self.phases))
                self.phases[index_] = name
                continue
            payload = _event_payload(kind, tick, fields)
            if payload is not None:
                self.add(ch.EVENTS, t_ns, payload)
                self.events += 1
                if self.derived is not None:
                    self.derived.event(t_ns, payload)

    def _poses(self, tail: int, head: int) -> None:
        rings = self.rings
        index = self._take(tail, head, self.layout.pose_capacity)
        ints = rings.pose_i[index].tolist()
        floats = rings.pose_f[index].tolist()
        rings.ctl[POSE_TAIL] = head
        for (tick, t_ns), values in zip(ints, floats, strict=True):
            objects = [
                {
                    "name": name,
                    "x_m": values[3 * i],
                    "y_m": values[3 * i + 1],
                    "angle_rad": values[3 * i + 2],
                }
                for i, name in enumerate(self.objects)
            ]
            payload: dict[str, Any] = {"tick": tick, "objects": objects}
            pairs = [
                {
                    "name": name,
                    "line_angle_rad": math.atan2(
                        values[3 * b + 1] - values[3 * a + 1], values[3 * b] - values[3 * a]
                    ),
                }
                for (a, b), name in zip(self.pairs, self.pair_names, strict=True)
            ]
            if pairs:
                payload["line_angle_rad"] = pairs[0]["line_angle_rad"]
                payload["pairs"] = pairs
            self.add(ch.OBJECTS, t_ns, payload)
            self.poses += 1
            if self.derived is not None:
                self.derived.poses(t_ns, values)

    def _ticks(self, tail: int, head: int) -> None:
        rings = self.rings
        index = self._take(tail, head, self.layout.tick_capacity)
        ints = rings.tick_i[index].tolist()
        floats = rings.tick_f[index].tolist()
        rings.ctl[TICK_TAIL] = head
        n, m = self.n, self.m
        states, add, derived = self.states, self.add, self.derived
        node_at, feedback_at = I_NODES, self.layout.i_feedback
        for r, f in zip(ints, floats, strict=True):
            k, scheduled, now, missed, active = r[0], r[1], r[2], r[3], r[4]
            timing: dict[str, Any] = {
                "tick": k,
                "scheduled_ns": scheduled,
                "now_ns": now,
                "lateness_ns": now - scheduled,
                "missed": missed,
                "active": bool(active),
            }
            if active:
                s = I_STAGES
                timing["stage_cpu_ns"] = dict(
                    zip(RECORDED_STAGES, r[s : s + N_STAGES], strict=True)
                )
            add(ch.TIMING, now, timing)
            if active:
                feedback = r[feedback_at : feedback_at + n]
                add(
                    ch.JOINT_STATE,
                    now,
                    {
                        "tick": k,
                        "angle_rad": f[:n],
                        "tdt_torque_nm": f[n : 2 * n],
                        "feedback_age_ns": [now - x if x >= 0 else -1 for x in feedback],
                        "node_state": r[node_at : node_at + m],
                        "node_fault_bits": r[node_at + m : node_at + 2 * m],
                    },
                )
                add(
                    ch.TORQUE,
                    now,
                    {"tick": k, "desired_nm": f[2 * n : 3 * n], "applied_nm": f[3 * n :]},
                )
                state = r[I_STATE]
                state_name = states[state] if state >= 0 else "?"
                add(ch.SAFETY, now, {"tick": k, "state": state_name, "faults_latched": r[I_FAULTS]})
                phase = r[I_PHASE]
                phase_name = self.phases[phase] if 0 <= phase < len(self.phases) else "?"
                add(ch.PHASE, now, {"tick": k, "phase": phase_name})
                if derived is not None:
                    derived.tick(
                        now,
                        k,
                        f[:n],
                        f[n : 2 * n],
                        f[2 * n : 3 * n],
                        f[3 * n :],
                        state_name == "running" and phase_name not in ("completed", "aborted"),
                    )
            self.last_tick = k
        self.ticks += len(ints)

    def _drops(self) -> None:
        """Drops the loop counted become ``recording`` events as they grow."""
        ctl = self.rings.ctl
        names = ch.DROPPED_KEYS
        for i, word in enumerate((DROPPED_TICKS, DROPPED_FRAMES, DROPPED_EVENTS, DROPPED_POSES)):
            now = int(ctl[word])
            if now != self.dropped[i]:
                event = {
                    "tick": self.last_tick,
                    "kind": "recording",
                    "name": names[i],
                    "detail": "the writer fell behind: records dropped",
                    "count": now - self.dropped[i],
                }
                self.add(ch.EVENTS, self.last_log, event)
                if self.derived is not None:
                    self.derived.event(self.last_log, event)
                self.dropped[i] = now

    # -- chunks and the end ---------------------------------------------------------------
    def stats(self) -> dict[str, Any]:
        return {
            "tick": self.last_tick,
            "ticks": self.ticks,
            "frames": self.frames,
            "events": self.events,
            "dropped_ticks": self.dropped[0],
            "dropped_frames": self.dropped[1],
            "dropped_events": self.dropped[2],
            "dropped_poses": self.dropped[3],
        }

    def maybe_flush(self, force: bool = False) -> None:
        """Close the chunk once it spans ``CHUNK_NS`` of log time or ``CHUNK_WALL_S`` of wall
        time, and push it to the file, so a crash costs at most that much."""
        if self.chunk_log is None:
            return
        wall = time.monotonic()
        if (
            not force
            and self.last_log - self.chunk_log < CHUNK_NS
            and wall - self.chunk_wall < CHUNK_WALL_S
        ):
            return
        self.add(ch.STATS, self.last_log, self.stats())
        self.writer.flush()
        self.chunks += 1
        self.chunk_log = None
        if wall - self.synced >= SYNC_EVERY_S:
            self.sync()
            self.synced = wall

    def sync(self) -> None:
        """``fdatasync`` the file, if it is one that can be synced at all. A file that cannot
        (EINVAL: a device such as /dev/null, a pipe; a file system without it) has nothing to
        make durable, and the recording goes on without: the first such sync ended the
        writer with a traceback and left the log empty. Another failure (EIO) is the
        disk's, and ends the recording as a write error does."""
        if not self.can_sync:
            return
        try:
            os.fdatasync(self.out.fileno())
        except OSError as exc:
            if exc.errno not in (errno.EINVAL, errno.ENOTSUP, errno.EOPNOTSUPP):
                raise
            self.can_sync = False

    def finish(self, ended: str) -> None:
        self.maybe_flush(force=True)
        self.writer.add_metadata(
            ch.META_END,
            {
                "ended": ended,
                "ticks": str(self.ticks),
                "frames": str(self.frames),
                "events": str(self.events),
                "poses": str(self.poses),
                "messages": str(self.messages),
                "chunks": str(self.chunks),
                "dropped_ticks": str(self.dropped[0]),
                "dropped_frames": str(self.dropped[1]),
                "dropped_events": str(self.dropped[2]),
                "dropped_poses": str(self.dropped[3]),
                "writer_busy_s": f"{self.busy_s:.6f}",
                "writer_cpu_s": f"{time.process_time():.6f}",
            },
        )
        self.writer.finish()
        self.out.flush()
        self.sync()


class _SafeView:
    """The Foxglove channels (``Derived``), computed so that a failure ends them and never
    the recording: the writer died with an exception raised there (the estimator on a hand
    of two links, in the view), and the run's log was left without a chunk."""

    def __init__(self, view: Derived) -> None:
        self._view: Derived | None = view
        self.channels = view.channels

    def _call(self, name: str, *args: Any) -> None:
        view = self._view
        if view is None:
            return
        try:
            getattr(view, name)(*args)
        except Exception as exc:  # a view must never cost the recording
            self._view = None
            _note(f"handctl writer: Foxglove channels stopped ({type(exc).__name__}: {exc})")

    def frame(self, *args: Any) -> None:
        self._call("frame", *args)

    def tick(self, *args: Any) -> None:
        self._call("tick", *args)

    def event(self, *args: Any) -> None:
        self._call("event", *args)

    def poses(self, *args: Any) -> None:
        self._call("poses", *args)


def _event_payload(kind: int, tick: int, fields: list[str]) -> dict[str, Any] | None:
    """The JSON of one event from the fields the loop joined (see ``Recorder``)."""

    def field(i: int) -> str:
        return fields[i] if i < len(fields) else ""

    if kind == EV_FAULT:
        return {
            "tick": tick,
            "kind": "fault",
            "name": field(0),
            "category": field(1),
            "detail": field(2),
        }
    if kind == EV_STATE:
        return {
            "tick": tick,
            "kind": "state",
            "name": field(0),
            "previous": field(1),
            "cause": field(2),
            "detail": f"{field(1)} -> {field(0)} on {field(2)}",
        }
    if kind == EV_PHASE:
        return {
            "tick": tick,
            "kind": "phase",
            "name": field(0),
            "previous": field(1),
            "detail": field(2),
        }
    if kind == EV_BUS:
        bus: dict[str, Any] = {
            "tick": tick,
            "kind": "bus",
            "name": field(0),
            "detail": field(1),
            "bus_time_ns": int(field(2) or 0),
        }
        if field(3):  # the frame's id, of a remote frame
            bus["id"] = int(field(3))
        return bus
    if kind == EV_REJECT:
        return {
            "tick": tick,
            "kind": "rejected_frames",
            "name": field(0),
            "detail": f"{field(1)} {field(0)} reject(s)",
            "count": int(field(1) or 0),
        }
    if kind == EV_REQUEST:
        return {"tick": tick, "kind": "request", "name": field(0), "detail": field(1)}
    return None


class _Control:
    """Length-prefixed JSON messages from the recorder on the control pipe."""

    def __init__(self, fd: int) -> None:
        self.fd = fd
        self.buffer = bytearray()
        self.eof = False
        self.pending: list[dict[str, Any]] = []

    def read(self, timeout: float | None) -> list[dict[str, Any]]:
        ready, _, _ = select.select([self.fd], [], [], timeout)
        if ready:
            chunk = os.read(self.fd, 1 << 16)
            if not chunk:
                self.eof = True
            self.buffer += chunk
        messages = []
        while len(self.buffer) >= 4:
            (size,) = _LENGTH.unpack_from(self.buffer)
            if len(self.buffer) < 4 + size:
                break
            messages.append(orjson.loads(bytes(self.buffer[4 : 4 + size])))
            del self.buffer[: 4 + size]
        return messages

    def first(self) -> dict[str, Any]:
        """The set-up message; any message that came with it stays in ``pending``."""
        while not self.eof:
            messages = self.read(None)
            if messages:
                self.pending = messages[1:]
                return messages[0]
        raise EOFError("the control pipe closed before the set-up message")


#: ``ended`` of a log whose control process died before it handed the writer its set-up
ENDED_BEFORE_SETUP = "the control process ended before it set the recording up"


def _finish_unset(out_fd: int) -> int:
    """The file of a recording whose set-up never came (the control process killed while
    it started the writer): an MCAP with nothing but its end said. The log had been emptied
    for this run, and an empty file was left: no MCAP at all, for a run that had begun."""
    with os.fdopen(out_fd, "wb") as out:
        writer = ChunkWriter(out, ch.PROFILE, f"handctl {__version__}")
        writer.add_metadata(ch.META_END, {"ended": ENDED_BEFORE_SETUP, "ticks": "0"})
        writer.finish()
        out.flush()
        os.fsync(out.fileno())
    return 1


def run(shm_fd: int, ctl_fd: int, out_fd: int, ready_fd: int) -> int:
    control = _Control(ctl_fd)
    try:
        setup = control.first()
    except EOFError:
        return _finish_unset(out_fd)
    layout = RingLayout.from_dict(setup["layout"])
    if setup.get("cpus"):
        # Before the live server starts its threads, which inherit the CPUs.
        try:
            os.sched_setaffinity(0, setup["cpus"])
        except OSError as exc:
            _note(f"handctl writer: runs on any CPU ({exc})")
    block = mmap.mmap(shm_fd, layout.size)
    rings = Rings(layout, block)
    live = None
    if setup.get("live_port") is not None:
        from handctl.foxglove.live import LiveServer

        live = LiveServer(int(setup["live_port"]))
    with os.fdopen(out_fd, "wb", buffering=1 << 20) as out:
        # With a live view the file is not emptied until its port is bound (the control
        # process left it as it was, ``Recorder``): what the encoder writes first is held
        # here until then, so that a port another program took since it was checked fails
        # the start with the previous log untouched (it was emptied, 0 bytes).
        head = io.BytesIO()
        encoder = Encoder(rings, head if live is not None else out, setup, live)
        if live is not None:
            # Once every channel is there, and before the ready byte: a port that cannot be
            # bound fails the start, not the run.
            try:
                live.start()
            except Exception as exc:  # foxglove's own error type: say what, not where
                # the port and why alone, the last line: the recorder makes it the found value
                # of its own refusal (the server's whole message in it was said twice)
                port = setup["live_port"]
                why = exc.found if isinstance(exc, ConfigError) else f"{port} ({exc})"
                _note(" ".join(str(why).splitlines()))
                return LIVE_REFUSED
            try:
                out.truncate(0)
                out.write(head.getvalue())
                out.flush()
            except OSError as exc:
                _note(f"{exc.strerror or exc}: the recording cannot replace the file")
                live.close()
                return 1
            encoder.out = encoder.writer.out = out
        # A control process that died since it sent the set-up cannot read this: the file
        # is still finished below, with what it had (before, the broken pipe ended the
        # writer and left the file without its end)
        with contextlib.suppress(OSError):
            os.write(ready_fd, b"R")
        os.close(ready_fd)
        messages = control.pending
        while True:
            for message in messages:
                if message.get("type") == "metadata":
                    encoder.writer.add_metadata(message["name"], message["data"])
            started = time.perf_counter()
            encoder.drain()
            encoder.maybe_flush()
            encoder.busy_s += time.perf_counter() - started
            if control.eof:
                break
            messages = control.read(POLL_S)
        # The control process closed the pipe or died: what is published is all there is.
        started = time.perf_counter()
        while encoder.drain():
            pass
        encoder.busy_s += time.perf_counter() - started
        closed = bool(rings.ctl[CLOSED])
        encoder.finish(
            ch.ENDED_CLOSED if closed else "the control process ended without closing the recorder"
        )
    if live is not None and encoder.live_pace.pauses:
        _note(
            f"the live view was held back {encoder.live_pace.pauses} time(s), "
            f"{encoder.live_pace.skipped} messages not served: the writer fell behind (its "
            "clients' queues cost it time), and the log comes first"
        )
    if live is not None and not live.close():
        # The log is whole and closed; only a viewer that stopped reading holds the server.
        # Leaving now, without the interpreter's own end (which would wait on the server's
        # threads again), is all that is left to do.
        _note("the live view's clients did not let go; the live view is left behind")
        os._exit(0)
    return 0


def main(argv: list[str] | None = None) -> int:
    # The recorder decides when the recording ends: a terminal's Ctrl-C or a service
    # manager's SIGTERM goes to the control process, which stops the hand and then closes us.
    for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):
        signal.signal(sig, signal.SIG_IGN)
    # Behind the loop and the simulated hand when the CPUs are contended: the rings give the
    # writer seconds of slack, a late tick is a safety stop. SCHED_BATCH as well: a writer
    # waking from its poll does not preempt a running tick. Both are inherited by the live
    # server's threads.
    with contextlib.suppress(OSError):
        os.nice(5)
    with contextlib.suppress(OSError, AttributeError):
        os.sched_setscheduler(0, os.SCHED_BATCH, os.sched_param(0))
    args = sys.argv[1:] if argv is None else argv
    try:
        shm_fd, ctl_fd, out_fd, ready_fd = (int(a) for a in args[:4])
        return run(shm_fd, ctl_fd, out_fd, ready_fd)
    except OSError as exc:
        # The file or its disk refused (a full disk, an I/O error): the recorder says the
        # last line to the user beside the log's name, so one line, never a traceback.
        _note(f"{type(exc).__name__}: {exc}")
        return 1
    except Exception:
        _note(traceback.format_exc().rstrip())
        return 1


def _note(text: str) -> None:
    """A line for the recorder on stderr, which the recorder reads when the writer fails.
    Never the writer's end: a stderr that is gone (the control process died and its pipe
    with it) or invalid costs the note, not the recording."""
    try:
        sys.stderr.write(text + "\n")
        sys.stderr.flush()
    except Exception:
        # Nowhere to say it: and nothing left buffered that would fail the exit (an
        # interpreter that cannot flush stderr at exit exits 120, a failed writer).
        with contextlib.suppress(Exception):
            sys.stderr = open(os.devnull, "w")  # noqa: SIM115 - for the rest of the process


if __name__ == "__main__":
    raise SystemExit(main())
