"""What ``handctl replay`` does with a recording: a summary, a re-run through the recipe runner
and safety, the frames back onto a bus, and an export to python-can's log formats.

The re-run is the one that earns its keep. It builds a fresh ``Runtime`` (driver, recipe
runner, supervisor) from the hand config and recipe stored in the log, and drives it with the
log itself: a clock that hands out the logged ticks (time, missed ticks) and a bus that hands
out, tick by tick, the very frames the original drain returned and the bus events it reported,
with the operator's stop and e-stop requests at the ticks they took effect. Everything the
original tick consumed is thus the same, so its applied torques, and the command frames built
from them, must come out bit for bit the same; any difference is listed.
"""

from __future__ import annotations

import asyncio
import heapq
import itertools
import math
import struct
import time
from collections import deque
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt
import orjson

from handctl import timebudget
from handctl.bus import DRAIN_LIMIT, BusEvent, BusEventKind, BusSpec, Frame, HandBus
from handctl.clock import LockstepClock, Tick
from handctl.config import HandConfig, parse_hand
from handctl.convention import phase_turns_deg
from handctl.drivers.hand import HandDriver
from handctl.errors import ConfigError
from handctl.hand_protocol import protocol_for
from handctl.loop import EndOfTicks, Runtime, TickRecord
from handctl.protocol import Protocol, parse_protocol
from handctl.recipes.loader import check_against_hand, parse_recipe
from handctl.recipes.schema import Recipe
from handctl.recording import channels as ch
from handctl.recording.feedback_check import FeedbackCheck
from handctl.recording.reader import (
    Recording,
    iter_chunks,
    iter_decoded,
    iter_messages,
    require_topics,
)
from handctl.schema import parse_yaml

FloatArray = npt.NDArray[np.float64]
#: Phase names that are the runner's status rather than a phase of the recipe.
NOT_PHASES = frozenset({"-", "running", "completed", "aborted", "?"})
MAX_LISTED = 20


# -- the recording as time series -------------------------------------------------------------
class _Rows:
    """A growing 2-D float array: one row per message, without a Python list per row."""

    def __init__(self, width: int) -> None:
        self.data = np.zeros((1024, width))
        self.size = 0

    def add(self, row: list[float] | tuple[float, ...]) -> None:
        if self.size == len(self.data):
            self.data = np.resize(self.data, (2 * len(self.data), self.data.shape[1]))
        self.data[self.size] = row
        self.size += 1

    @property
    def rows(self) -> FloatArray:
        return self.data[:self.size]


@dataclass
class Series:
    """What the summary and the plot need, as arrays over ticks (times in s since tick 0's
    scheduled time, ``handctl.convention``)."""

    joints: list[str]
    t0_ns: int = 0  # tick 0's scheduled time, on the log's clock
    rest_y: list[float] = field(default_factory=list)  # m, each object's resting height
    tau_max: list[float] = field(default_factory=list)  # N·m, each joint's host limit
    timing: FloatArray = field(default_factory=lambda: np.zeros((0, 8)))
    torque: FloatArray = field(default_factory=lambda: np.zeros((0, 1)))
    joint: FloatArray = field(default_factory=lambda: np.zeros((0, 1)))
    objects: FloatArray = field(default_factory=lambda: np.zeros((0, 1)))
    object_names: list[str] = field(default_factory=list)
    phases: list[dict[str, Any]] = field(default_factory=list)
    events: list[dict[str, Any]] = field(default_factory=list)
    frames: dict[str, int] = field(default_factory=dict)
    stats: dict[str, Any] = field(default_factory=dict)


def load_series(recording: Recording) -> Series:  # noqa: C901 - one branch per channel; bus/replay split (issue 16)
    """One pass over the recording into arrays: timing (t, tick, lateness, missed, active,
    4 stages), torques (t, desired, applied), joints (t, TDT, angle), object poses."""
    joints = _joint_names(recording)
    n = len(joints)
    timing, torque, joint = _Rows(9), _Rows(1 + 2 * n), _Rows(1 + 2 * n)
    objects: _Rows | None = None
    series = Series(joints)
    t0: int | None = None
    tick0: int | None = None  # tick 0's scheduled time (ns)
    period_ns = int(recording.meta(ch.META_RUN, "period_ns") or 1_000_000)
    scheduled = 0.0  # the latest tick's scheduled time, s from the first message
    phase_name, phase_start, phase_tick = "", 0.0, 0
    frames = {"rx": 0, "tx": 0, "tx_refused": 0}
    exits: dict[tuple[str, int], str] = {}
    last_t = 0.0
    topics = (ch.TIMING, ch.TORQUE, ch.JOINT_STATE, ch.PHASE, ch.EVENTS, ch.OBJECTS, ch.STATS)
    for topic, log_time, raw in iter_messages(recording, (*topics, ch.CAN_RX, ch.CAN_TX)):
        if topic == ch.CAN_RX:
            frames["rx"] += 1
            continue
        if topic == ch.CAN_TX:
            frames["tx"] += 1
            if b'"ok":false' in raw:
                frames["tx_refused"] += 1
            continue
        msg = _loads(raw)
        if t0 is None:
            t0 = log_time
        t = (log_time - t0) * 1e-9
        if topic == ch.TIMING:
            if tick0 is None:
                tick0 = int(msg["scheduled_ns"]) - int(msg["tick"]) * period_ns
            scheduled = (int(msg["scheduled_ns"]) - t0) * 1e-9
            stages = msg.get("stage_cpu_ns") or {}
            timing.add((t, msg["tick"], msg.get("lateness_ns", 0), msg.get("missed", 0),
                        1.0 if msg.get("active") else 0.0, stages.get("poll", 0),
                        stages.get("recipe", 0), stages.get("safety", 0),
                        stages.get("send", 0)))
            last_t = t
        elif topic == ch.TORQUE:
            torque.add([t, *_floats(msg["desired_nm"]), *_floats(msg["applied_nm"])])
        elif topic == ch.JOINT_STATE:
            joint.add([t, *_floats(msg["tdt_torque_nm"]), *_floats(msg["angle_rad"])])
        elif topic == ch.PHASE:
            name = msg["phase"]
            if name != phase_name:  # a phase starts at its first tick's scheduled time
                if phase_name:
                    series.phases.append({"name": phase_name, "start_s": phase_start,
                                          "end_s": scheduled, "tick": phase_tick})
                phase_name, phase_start, phase_tick = name, scheduled, msg["tick"]
        elif topic == ch.EVENTS:
            msg["t_s"] = t
            series.events.append(msg)
            if msg["kind"] == "phase":
                exits[(msg.get("previous", ""), msg["tick"])] = msg.get("detail", "")
        elif topic == ch.OBJECTS:
            if objects is None:
                series.object_names = [o["name"] for o in msg["objects"]]
                objects = _Rows(2 + 3 * len(series.object_names))
            values = [t, msg.get("line_angle_rad", math.nan)]
            for o in msg["objects"]:
                values += [o["x_m"], o["y_m"], o["angle_rad"]]
            objects.add(values)
        elif topic == ch.STATS:
            series.stats = msg
    if phase_name:
        series.phases.append({"name": phase_name, "start_s": phase_start, "end_s": last_t,
                              "tick": phase_tick})
    for phase in series.phases:
        phase["exit"] = next((v for (name, tick), v in exits.items()
                              if name == phase["name"] and tick > phase["tick"]), "")
    # Times were taken from the first message on; the convention's are from tick 0.
    shift = ((tick0 - t0) * 1e-9) if tick0 is not None and t0 is not None else 0.0
    series.t0_ns = tick0 if tick0 is not None else (t0 or 0)
    for rows in (timing, torque, joint, *((objects,) if objects is not None else ())):
        rows.rows[:, 0] -= shift
    for phase in series.phases:
        phase["start_s"] -= shift
        phase["end_s"] -= shift
    for event in series.events:
        event["t_s"] -= shift
    series.timing, series.torque, series.joint = timing.rows, torque.rows, joint.rows
    if objects is not None:
        series.objects = objects.rows
    series.rest_y = _rest_heights(recording, series)
    series.frames = frames
    return series


def _loads(raw: bytes) -> dict[str, Any]:
    value = orjson.loads(raw)
    if not isinstance(value, dict):
        raise ValueError("a message that is not a JSON object")
    return value


def _floats(values: list[float | None]) -> list[float]:
    """JSON has no NaN: the writer wrote a non-finite number as null."""
    return [math.nan if v is None else v for v in values]


def _joint_names(recording: Recording) -> list[str]:
    hand = _hand(recording, required=False)
    if hand is not None:
        return list(hand.joint_names)
    for _, _, msg in iter_decoded(recording, (ch.TORQUE,)):
        return [f"j{i}" for i in range(len(msg["applied_nm"]))]
    return []


def _hand(recording: Recording, required: bool = True) -> HandConfig | None:
    text = recording.meta(ch.META_HAND, "yaml")
    if not text:
        if required:
            raise ConfigError(str(recording.path), f"metadata {ch.META_HAND}.yaml",
                              "the hand config the run used (recorded by handctl)", "nothing")
        return None
    return parse_hand(parse_yaml(text, f"{recording.path} (its recorded hand config)"),
                      _recorded_protocol(recording))


def _recorded_protocol(recording: Recording) -> Protocol | None:
    """The protocol the run spoke, as it recorded it (None in a recording from before the
    protocol was recorded: then it was the packaged DBC, which the hand generates)."""
    text = recording.meta(ch.META_HAND, "dbc")
    return parse_protocol(text, f"{recording.path} (its recorded DBC)") if text else None


def _recipe(recording: Recording, hand: HandConfig) -> Recipe:
    text = recording.meta(ch.META_RECIPE, "yaml")
    if not text:
        raise ConfigError(str(recording.path), f"metadata {ch.META_RECIPE}.yaml",
                          "the recipe the run used (recorded by handctl)", "nothing")
    recipe = parse_recipe(parse_yaml(text, f"{recording.path} (its recorded recipe)"), hand)
    check_against_hand(recipe, hand)
    return recipe


# -- summary ----------------------------------------------------------------------------------
def _percentiles(values: FloatArray, scale: float) -> dict[str, float]:
    if values.size == 0:
        return {"p50": 0.0, "p99": 0.0, "max": 0.0}
    p50, p99 = np.percentile(values, [50, 99])
    return {"p50": round(float(p50) * scale, 2), "p99": round(float(p99) * scale, 2),
            "max": round(float(values.max()) * scale, 2)}


def summarise(recording: Recording, series: Series) -> dict[str, Any]:
    """Phases and their durations, the largest torques, faults, timing, drops."""
    n = len(series.joints)
    run_summary = recording.json_meta(ch.META_SUMMARY) or {}
    end = recording.metadata.get(ch.META_END, {})
    timing = series.timing
    active = timing[timing[:, 4] > 0] if len(timing) else timing
    largest: dict[str, dict[str, float]] = {}
    tq, js = series.torque, series.joint
    for j, name in enumerate(series.joints):
        entry: dict[str, float] = {}
        if len(tq):
            i = int(np.nanargmax(np.abs(tq[:, 1 + n + j])))
            entry |= {"applied_nm": round(float(tq[i, 1 + n + j]), 5),
                      "at_s": round(float(tq[i, 0]), 3),
                      "desired_nm": round(float(np.nanmax(np.abs(tq[:, 1 + j]))), 5)}
        if len(js):
            entry["tdt_nm"] = round(float(np.nanmax(np.abs(js[:, 1 + j]))), 5)
        largest[name] = entry
    phases = [{"name": p["name"], "start_s": round(p["start_s"], 3),
               "end_s": round(p["end_s"], 3), "duration_s": round(p["end_s"] - p["start_s"], 3),
               "exit": p["exit"]}
              for p in series.phases if p["name"] not in NOT_PHASES]
    faults = [{"code": e["name"], "category": e.get("category", ""), "tick": e["tick"],
               "t_s": round(e["t_s"], 3), "detail": e["detail"]}
              for e in series.events if e["kind"] == "fault"]
    rejected: dict[str, int] = {}
    for e in series.events:
        if e["kind"] == "rejected_frames":
            rejected[e["name"]] = rejected.get(e["name"], 0) + int(e.get("count", 0))
    drops = {key: int(end.get(key, series.stats.get(key, 0))) for key in
             ("dropped_ticks", "dropped_frames", "dropped_events", "dropped_poses")}
    summary: dict[str, Any] = {
        "file": str(recording.path),
        "complete": recording.complete,
        "damaged": recording.damaged,
        "problem": recording.problem,
        "chunks": recording.chunks,
        "recipe": recording.meta(ch.META_RECIPE, "name"),
        "hand": recording.meta(ch.META_HAND, "name"),
        "mode": recording.meta(ch.META_RUN, "mode"),
        "outcome": run_summary.get("outcome", "unknown (the log has no summary)"),
        "ended": end.get("ended", "the writer did not finish the file"),
        "duration_s": round(float(timing[-1, 0]), 3) if len(timing) else 0.0,
        "ticks": len(timing),
        "active_ticks": len(active),
        "phases": phases,
        "largest_torques": largest,
        "faults": faults,
        "timing": {"lateness_us": _percentiles(timing[:, 2] if len(timing) else timing, 1e-3),
                   "missed_ticks": int(timing[:, 3].sum()) if len(timing) else 0,
                   "stage_cpu_us_p99": {
                       name: round(float(np.percentile(active[:, 5 + i], 99)) / 1e3, 2)
                       if len(active) else 0.0
                       for i, name in enumerate(("poll", "recipe", "safety", "send"))}},
        "drops": drops,
        "frames": series.frames,
        "bus_events": sum(1 for e in series.events if e["kind"] == "bus"),
        "rejected_frames": rejected,
    }
    if len(series.objects):
        first, last = series.objects[0], series.objects[-1]
        summary["objects"] = {
            name: {"start": _pose(first, i, series.rest_y), "end": _pose(last, i, series.rest_y)}
            for i, name in enumerate(series.object_names)}
        summary["objects_line_angle_rad"] = {"start": round(float(first[1]), 5),
                                             "end": round(float(last[1]), 5)}
        # a pose taken at the start of tick k belongs to the phase tick k - 1 ran, and the
        # phase channel says which phase a tick ran: the bounds move one tick later
        period = int(recording.meta(ch.META_RUN, "period_ns") or 1_000_000) * 1e-9
        turns = phase_turns_deg(series.objects[:, 0], series.objects[:, 1],
                                [(p["name"], p["start_s"] + period, p["end_s"] + period)
                                 for p in series.phases])
        summary["phase_turns_deg"] = turns
        summary["turn_deg"] = round(sum(turns), 2)
    return summary


def _rest_heights(recording: Recording, series: Series) -> list[float]:
    """Where the objects rested at the start: the recorded scene's initial poses (the run
    summary's reference), or the first logged pose for a log without them. Sets the joints'
    ``tau_max`` from the recorded hand config on the way."""
    from handctl.sim.params import parse_sim

    first = [float(series.objects[0][3 + 3 * i]) if len(series.objects) else math.nan
             for i in range(len(series.object_names))] if series.object_names else []
    try:
        hand = _hand(recording, required=False)
        params = parse_sim(hand) if hand is not None and hand.sim else None
    except ConfigError:
        hand, params = None, None
    if hand is not None:
        series.tau_max = [j.tau_max for j in hand.joints]
    if params is None:
        return first
    initial = {o.name: o.y for o in params.objects}
    return [initial.get(name, first[i]) for i, name in enumerate(series.object_names)]


def _pose(row: FloatArray, i: int, rest_y: list[float]) -> dict[str, float]:
    x, y, angle = row[2 + 3 * i: 5 + 3 * i]
    pose = {"x_m": round(float(x), 5), "y_m": round(float(y), 5),
            "angle_rad": round(float(angle), 5)}
    if i < len(rest_y):
        pose["height_above_rest_m"] = round(float(y) - rest_y[i], 5)
    return pose


# -- re-run -----------------------------------------------------------------------------------
@dataclass
class TickInput:
    """Everything one logged tick consumed, and what it applied."""

    tick: int
    scheduled_ns: int
    now_ns: int
    missed: int
    rx: list[Frame] = field(default_factory=list)
    tx: list[tuple[int, bytes, bool]] = field(default_factory=list)
    bus_events: list[BusEvent] = field(default_factory=list)
    requests: list[tuple[str, str]] = field(default_factory=list)
    rejects: dict[str, int] | None = None  # the rejected_frames events of the tick, by kind
    applied: list[float] | None = None
    joint_state: dict[str, Any] | None = None  # the logged /hand/joint_state message


@dataclass
class _Pending:
    rx: list[Frame] = field(default_factory=list)
    tx: list[tuple[int, bytes, bool]] = field(default_factory=list)
    bus_events: list[BusEvent] = field(default_factory=list)
    requests: list[tuple[str, str]] = field(default_factory=list)
    rejects: dict[str, int] | None = None


def tick_inputs(recording: Recording) -> tuple[_Pending, Iterator[TickInput]]:  # noqa: C901 - one branch per channel; bus/replay split (issue 16)
    """The frames drained before the first tick, and a stream of the logged ticks.

    A tick is whole when the next tick's row begins: its frames and events are published
    before that row (``Recorder``), most of them before its own row, and the frames it sends
    after its push (the nodes' disable after the last control tick) between the two. So the
    stream hands out a tick only when it meets the next row, and the last row only when the
    recorder closed the file; a gap in the ticks (a damaged chunk) ends the stream before it,
    and a log whose first row is not tick 0 gives no ticks at all.
    One pass, one branch per message: this is most of what a re-run reads.
    """
    pending: dict[int, _Pending] = {}
    kinds = {k.value: k for k in BusEventKind}
    batches = iter_chunks(recording, ch.RERUN_TOPICS)
    timing, torque, rx, tx, joint = ch.TIMING, ch.TORQUE, ch.CAN_RX, ch.CAN_TX, ch.JOINT_STATE
    fromhex = bytes.fromhex
    closed = recording.complete and \
        recording.meta(ch.META_END, "ended") == ch.ENDED_CLOSED

    def inputs_of(k: int, current: TickInput | None) -> TickInput | _Pending:
        if current is not None and current.tick == k:
            return current
        got = pending.get(k)
        if got is None:
            got = pending[k] = _Pending()
        return got

    def ticks() -> Iterator[TickInput]:  # noqa: C901 - one branch per channel; bus/replay split (issue 16)
        current: TickInput | None = None
        for topics, messages in batches:
            for topic, msg in zip(topics, messages, strict=True):
                if topic == rx:
                    inputs_of(msg["tick"], current).rx.append(
                        Frame(msg["id"], fromhex(msg["data"]), msg.get("bus_time_ns", 0)))
                elif topic == tx:
                    inputs_of(msg["tick"], current).tx.append(
                        (msg["id"], fromhex(msg["data"]), msg.get("ok", True)))
                elif topic == timing:
                    k = msg["tick"]
                    if current is not None:
                        if k != current.tick + 1:
                            return  # a gap: the tick before it may lack what followed it
                        yield current
                    elif k != 0:
                        return  # the first ticks are missing: there is nothing to re-run from
                    current = TickInput(k, msg["scheduled_ns"], msg["now_ns"], msg["missed"])
                    got = pending.pop(k, None)
                    if got is not None:
                        current.rx, current.tx = got.rx, got.tx
                        current.bus_events, current.requests = got.bus_events, got.requests
                        current.rejects = got.rejects
                elif topic == torque:
                    if current is not None and current.tick == msg["tick"]:
                        current.applied = _floats(msg["applied_nm"])
                elif topic == joint:
                    if current is not None and current.tick == msg["tick"]:
                        current.joint_state = msg
                elif topic == ch.EVENTS and msg["kind"] in ("bus", "request", "rejected_frames"):
                    _route(msg, inputs_of(msg["tick"], current), kinds)
        if current is not None and closed:
            yield current

    stream = ticks()
    # The frames drained before the first tick (tick -1) precede the first row.
    first = next(stream, None)
    before = pending.pop(-1, None) or _Pending()
    return before, itertools.chain(() if first is None else (first,), stream)


def _route(msg: dict[str, Any], inputs: TickInput | _Pending,
           kinds: dict[str, BusEventKind]) -> None:
    """A bus event or an operator request (inputs of their tick), or the rejects the run
    counted (what the re-run must count too)."""
    kind = msg["kind"]
    if kind == "bus":
        inputs.bus_events.append(BusEvent(kinds.get(msg["name"], BusEventKind.ERROR_FRAME),
                                          msg["detail"], msg.get("bus_time_ns", 0)))
    elif kind == "request":
        inputs.requests.append((msg["name"], msg["detail"]))
    else:
        rejects = inputs.rejects
        if rejects is None:
            rejects = inputs.rejects = {}
        rejects[msg["name"]] = rejects.get(msg["name"], 0) + int(msg.get("count", 0))


class ReplayBus(HandBus):
    """A ``HandBus`` with the log behind it: ``drain`` returns what the original drain
    returned in this tick, ``send`` checks the frame against the one the original sent (and
    answers as the bus did), ``events`` returns the events the original poll took."""

    def __init__(self, fd: bool) -> None:  # no python-can bus: nothing of the parent's state
        self.spec = BusSpec("replay", "")
        self.fd = fd
        self.sent = 0
        self.tx_failed = 0
        self.received = 0
        self.closed = False
        self.tap = None
        self.rx_tap = None
        self.event_tap = None
        self.tick = -1
        self._rx: deque[Frame] = deque()
        self._tx: deque[tuple[int, bytes, bool]] = deque()
        self._events: list[BusEvent] = []
        self.frame_mismatches: list[str] = []
        self.frames_compared = 0

    def load(self, tick: int, inputs: TickInput | _Pending) -> None:
        for frame_id, data, _ in self._tx:
            self._mismatch(f"tick {self.tick}: the log has frame 0x{frame_id:03X} "
                           f"{data.hex()} that the re-run did not send")
        self.tick = tick
        self._rx = deque(inputs.rx)
        self._tx = deque(inputs.tx)
        self._events = list(inputs.bus_events)

    def drain(self, limit: int = DRAIN_LIMIT) -> list[Frame]:
        rx = self._rx
        if len(rx) <= limit:
            frames = list(rx)
            rx.clear()
        else:
            frames = [rx.popleft() for _ in range(limit)]
        self.received += len(frames)
        return frames

    def send(self, arbitration_id: int, data: bytes, more: bool = False) -> bool:
        self.frames_compared += 1
        if not self._tx:
            self._mismatch(f"tick {self.tick}: the re-run sent frame 0x{arbitration_id:03X} "
                           f"{bytes(data).hex()}, the log has no more frames in this tick")
            return True
        frame_id, logged, ok = self._tx.popleft()
        if frame_id != arbitration_id or logged != data:
            self._mismatch(f"tick {self.tick}: the re-run sent 0x{arbitration_id:03X} "
                           f"{bytes(data).hex()}, the log has 0x{frame_id:03X} {logged.hex()}")
        self.sent += ok
        self.tx_failed += not ok
        return ok

    def flush(self) -> bool:
        """Sends are compared as they come: there is no burst to end."""
        return True

    def transport_counts(self) -> dict[str, int]:
        return {}

    def events(self) -> list[BusEvent]:
        events, self._events = self._events, []
        return events

    def close(self) -> None:
        self.closed = True

    def finish(self) -> None:
        """After the last tick: a logged frame the re-run never sent is a mismatch too."""
        self.load(self.tick + 1, _Pending())

    def _mismatch(self, text: str) -> None:
        self.frame_mismatches.append(text)


class _EndOfLogError(EndOfTicks):
    """The log has no more whole ticks (a truncated or damaged recording): the re-run stops
    there."""


class ReplayClock(LockstepClock):
    """Hands out the logged ticks, and the operator's requests at the ticks they took effect."""

    def __init__(self, period_s: float, inputs: Iterator[TickInput], bus: ReplayBus) -> None:
        super().__init__(period_s, _nothing)
        self.inputs = inputs
        self.bus = bus
        self.runtime: Runtime | None = None
        self.current: TickInput | None = None
        self.unsupported: list[str] = []
        self.check: FeedbackCheck | None = None

    def now_ns(self) -> int:
        return self.current.now_ns if self.current is not None else 0

    async def wait_tick(self) -> Tick:
        current = next(self.inputs, None)
        if current is None:
            raise _EndOfLogError
        self.current = current
        self.bus.load(current.tick, current)
        if self.check is not None:
            self.check.take(current.rejects)
        runtime = self.runtime
        if runtime is not None:
            for kind, detail in current.requests:
                if kind == "stop":
                    runtime.request_stop(detail)
                elif kind == "estop":
                    runtime.request_estop(detail)
                else:
                    self.unsupported.append(f"tick {current.tick}: {kind}")
        return Tick(current.tick, current.scheduled_ns, current.now_ns, current.missed)


def _nothing() -> None:
    return None


def _no_time() -> int:
    return 0


_PACK: dict[int, struct.Struct] = {}


class _Compare:
    """The re-run's ``RecordSink``: each tick's applied torques against the logged ones."""

    def __init__(self, clock: ReplayClock, joints: list[str], check: FeedbackCheck) -> None:
        self.clock = clock
        self.joints = joints
        self.check = check
        self.compared = 0
        self.mismatches: list[dict[str, Any]] = []
        self.mismatched_ticks = 0

    def begin_tick(self, tick: Tick) -> None:
        return None

    def push(self, record: TickRecord) -> None:
        current = self.clock.current
        if current is not None:
            self.check.tick(record.tick, current.now_ns, current.joint_state, current.rx)
        logged = current.applied if current is not None else None
        rerun = record.applied
        if logged is None:
            self.mismatched_ticks += 1
            self._add(record.tick, "-", math.nan, float(np.max(np.abs(rerun))),
                      "the re-run ran a control step where the log has no torques")
            return
        n = len(logged)
        pack = _PACK.get(n)
        if pack is None:
            pack = _PACK[n] = struct.Struct(f"<{n}d")
        self.compared += 1
        if len(rerun) == n and rerun.tobytes() == pack.pack(*logged):
            return
        self.mismatched_ticks += 1
        for j, (a, b) in enumerate(zip(logged, rerun.tolist(), strict=False)):
            if struct.pack("<d", a) != struct.pack("<d", b):
                name = self.joints[j] if j < len(self.joints) else str(j)
                self._add(record.tick, name, a, b, "")

    def note(self, kind: str, detail: str, tick: int) -> None:
        return None

    def _add(self, tick: int, joint: str, logged: float, rerun: float, detail: str) -> None:
        if len(self.mismatches) < 1000:
            self.mismatches.append({"tick": tick, "joint": joint, "logged_nm": logged,
                                    "rerun_nm": rerun, "detail": detail})


@dataclass
class RerunReport:
    ticks: int
    compared: int
    mismatched_ticks: int
    mismatches: list[dict[str, Any]]
    frames_compared: int
    frame_mismatches: list[str]  # sent frames, and received ones the re-run read otherwise
    feedback_compared: int  # ticks whose received frames were compared
    outcome: str
    logged_outcome: str
    notes: list[str]
    wall_s: float

    @property
    def ok(self) -> bool:
        return not self.mismatched_ticks and not self.frame_mismatches

    def as_dict(self) -> dict[str, Any]:
        return {"ok": self.ok, "ticks": self.ticks, "compared": self.compared,
                "mismatched_ticks": self.mismatched_ticks,
                "mismatches": self.mismatches[:MAX_LISTED],
                "frames_compared": self.frames_compared,
                "frame_mismatches": self.frame_mismatches[:MAX_LISTED],
                "feedback_compared": self.feedback_compared,
                "outcome": self.outcome, "logged_outcome": self.logged_outcome,
                "notes": self.notes, "wall_s": round(self.wall_s, 3)}


def rerun(recording: Recording) -> RerunReport:
    """Feed the logged feedback through a fresh driver, runner and supervisor; compare."""
    require_topics(recording, ch.RERUN_TOPICS, "--rerun")
    path = str(recording.path)
    run = recording.metadata.get(ch.META_RUN)
    if not run:
        raise ConfigError(path, f"metadata {ch.META_RUN}",
                          "how the runtime was set up (recorded by handctl run recipe --log)",
                          "nothing")
    end = recording.metadata.get(ch.META_END, {})
    dropped = {k: int(end.get(k, "0")) for k in ("dropped_ticks", "dropped_frames",
                                                  "dropped_events")}
    if any(dropped.values()):
        raise ConfigError(path, "", "a recording without dropped records (the re-run needs "
                          "every frame)", ", ".join(f"{k} {v}" for k, v in dropped.items()))
    hand = _hand(recording)
    assert hand is not None
    recipe = _recipe(recording, hand)
    period_s = int(run.get("period_ns", round(hand.bus.period_s * 1e9))) * 1e-9
    startup_ticks = int(run.get("startup_ticks", "500"))
    bus = ReplayBus(hand.bus.fd)
    before, inputs = tick_inputs(recording)
    bus.load(-1, before)
    clock = ReplayClock(period_s, inputs, bus)
    driver = HandDriver(hand, _recorded_protocol(recording) or protocol_for(hand), bus,
                        clock_ns=clock.now_ns)
    check = FeedbackCheck(hand, driver)
    clock.check = check
    compare = _Compare(clock, list(hand.joint_names), check)
    estimator = None
    if recipe.objects:  # as the session sets it up: the estimator is fed the same angles
        from handctl.estimator import ObjectEstimator

        estimator = ObjectEstimator(hand, recipe.objects)
    if (estimator is not None) != (run.get("estimator", "False") == "True"):
        raise ConfigError(path, f"metadata {ch.META_RUN}.estimator",
                          f"{estimator is not None} (what the recorded recipe implies)",
                          run.get("estimator", "nothing"))
    runtime = Runtime(hand, driver, clock, recipe, recorder=compare, estimator=estimator,
                      reset_node_faults=run.get("reset_node_faults") == "True",
                      startup_timeout_s=startup_ticks * period_s, max_ticks=1 << 62)
    clock.runtime = runtime
    runtime.cpu_clock = _no_time  # stage times are the run's, not the re-run's
    notes: list[str] = []
    started = time.perf_counter()
    outcome = "log ended"
    try:
        result = timebudget.outcome(asyncio.run(runtime.run()), runtime.stop_requested)
        outcome = result.outcome.value
    except _EndOfLogError:
        where = "before a damaged chunk" if recording.damaged else "where the log ends"
        notes.append(f"the re-run stops after tick {clock.current.tick if clock.current else -1}"
                     f", {where} ({recording.problem or 'no more ticks'}); compared up to there")
    wall = time.perf_counter() - started
    if clock.current is not None and outcome != "log ended":
        check.end(clock.current.tick, clock.current.rx)
    bus.finish()
    leftover = sum(1 for _ in inputs)
    if leftover and outcome != "log ended":
        notes.append(f"the log goes on for {leftover} ticks after the re-run ended")
    notes += [f"not repeated: {u}" for u in clock.unsupported]
    logged = recording.json_meta(ch.META_SUMMARY) or {}
    ticks = (clock.current.tick + 1) if clock.current else 0
    frame_mismatches = list(heapq.merge(bus.frame_mismatches, check.mismatches,
                                        key=_tick_of))
    return RerunReport(ticks, compare.compared, compare.mismatched_ticks, compare.mismatches,
                       bus.frames_compared, frame_mismatches, check.compared, outcome,
                       logged.get("outcome", ""), notes, wall)


def _tick_of(text: str) -> int:
    """The tick a mismatch's text begins with (``tick N: ...``), to list both kinds in order."""
    head = text.split(":", 1)[0].split()
    return int(head[1]) if len(head) == 2 and head[1].lstrip("-").isdigit() else -1


# -- frames: back onto a bus, or out to a file ------------------------------------------------
def logged_frames(recording: Recording, direction: str = "both"
                  ) -> Iterator[tuple[int, int, bytes, bool]]:
    """``(log_time_ns, arbitration_id, data, is_rx)`` in the order they were on the wire."""
    topics = {"both": (ch.CAN_RX, ch.CAN_TX), "rx": (ch.CAN_RX,), "tx": (ch.CAN_TX,)}
    if direction not in topics:
        raise ConfigError("--direction", "", "both, rx or tx", direction)
    for topic, log_time, msg in iter_decoded(recording, topics[direction]):
        if topic == ch.CAN_TX and msg.get("ok") is False:
            continue  # the bus refused it: it never was on the wire
        yield log_time, msg["id"], bytes.fromhex(msg["data"]), topic == ch.CAN_RX


def to_bus(recording: Recording, spec: str, speed: float = 1.0, direction: str = "both",
           sleep: Callable[[float], None] = time.sleep,
           clock: Callable[[], float] = time.perf_counter) -> dict[str, Any]:
    """Send the logged frames onto the bus ``spec`` with their original spacing / ``speed``.

    Frames are paced against their due times (not slept frame to frame), so the time spent
    sending does not add up into drift."""
    from handctl.bus import open_bus

    if not speed > 0 or not math.isfinite(speed):
        raise ConfigError("--speed", "", "a speed factor > 0 (1 = as recorded)", speed)
    require_topics(recording, (ch.CAN_RX, ch.CAN_TX), "--to-bus")
    hand = _hand(recording)
    assert hand is not None
    sent = failed = 0
    worst_late = 0.0
    with open_bus(spec, hand.bus) as bus:
        start: float | None = None
        first = 0
        for log_time, frame_id, data, _ in logged_frames(recording, direction):
            if start is None:
                start, first = clock(), log_time
            due = start + (log_time - first) * 1e-9 / speed
            wait = due - clock()
            if wait > 0:
                sleep(wait)
            else:
                worst_late = max(worst_late, -wait)
            if bus.send(frame_id, data):
                sent += 1
            else:
                failed += 1
    return {"sent": sent, "failed": failed, "worst_late_ms": round(worst_late * 1e3, 3),
            "bus": spec, "speed": speed, "direction": direction}


def export(recording: Recording, fmt: str, out: str) -> int:
    """Write the logged frames in a python-can log format (candump, asc, blf)."""
    from handctl.bus import LOG_FORMATS, write_frames

    if fmt not in LOG_FORMATS:
        raise ConfigError("--export", "", "one of " + ", ".join(LOG_FORMATS), fmt)
    require_topics(recording, (ch.CAN_RX, ch.CAN_TX), "--export")
    hand = _hand(recording, required=False)
    fd = hand.bus.fd if hand is not None else True
    started = int(recording.meta("handctl.command", "started_unix_ns", "0") or 0)
    frames = logged_frames(recording)
    first: list[int] = []

    def stamped() -> Iterator[tuple[float, int, bytes, bool, bool]]:
        for log_time, frame_id, data, is_rx in frames:
            if not first:
                first.append(log_time)
            yield ((started + log_time - first[0]) * 1e-9, frame_id, data, is_rx, fd)

    try:
        return write_frames(out, fmt, stamped())
    except OSError as exc:
        raise ConfigError(out, "", "a path where the export can be written",
                          exc.strerror or str(exc)) from None

