"""A recording as time series: what the summary and the plot of ``handctl replay`` read."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from handctl.arrays import FloatArray
from handctl.errors import ConfigError, Description
from handctl.hand_protocol import protocol_for
from handctl.recording import channels as ch
from handctl.recording.messages import MessageCheck
from handctl.recording.metadata import recorded_hand, recorded_protocol
from handctl.recording.reader import Recording, iter_decoded, iter_messages
from handctl.recording.ring import RECORDED_STAGES

if TYPE_CHECKING:
    from handctl.config import HandConfig
    from handctl.online.recipes.schema import Recipe


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
        return self.data[: self.size]


@dataclass
class Series:
    """What the summary and the plot need, as arrays over ticks (times in s since tick 0's
    scheduled time, ``handctl.convention``)."""

    joints: list[str]
    t0_ns: int = 0  # tick 0's scheduled time, on the log's clock
    rest_y: list[float] = field(default_factory=list)  # m, each object's resting height
    tau_max: list[float] = field(default_factory=list)  # N·m, each joint's host limit
    #: Each finger's name and joint count, in joint order, from the recorded hand config
    #: (empty for a log without one: then the joints are one group)
    fingers: list[tuple[str, int]] = field(default_factory=list)
    timing: FloatArray = field(default_factory=lambda: np.zeros((0, 8)))
    torque: FloatArray = field(default_factory=lambda: np.zeros((0, 1)))
    joint: FloatArray = field(default_factory=lambda: np.zeros((0, 1)))
    objects: FloatArray = field(default_factory=lambda: np.zeros((0, 1)))
    object_names: list[str] = field(default_factory=list)
    phases: list[dict[str, Any]] = field(default_factory=list)
    events: list[dict[str, Any]] = field(default_factory=list)
    frames: dict[str, int] = field(default_factory=dict)
    #: per channel, its messages whose log time is earlier than one written before them:
    #: none in a log the writer wrote (it writes each channel in time order) unless the
    #: host's clock was stepped, so a log whose times were edited after the run, which a
    #: re-run's "identical" (about the frames' content) and the summary missed
    out_of_order: dict[str, int] = field(default_factory=dict)
    #: names the phase channel gives that are neither a phase of the recorded recipe nor the
    #: runner's status, each with the first tick that says it: none in a log handctl wrote
    unknown_phases: dict[str, int] = field(default_factory=dict)
    stats: dict[str, Any] = field(default_factory=dict)


def load_series(recording: Recording) -> Series:  # noqa: C901 - one branch per channel; bus/replay split (issue 16)
    """One pass over the recording into arrays: timing (t, tick, lateness, missed, active,
    4 stages), torques (t, desired, applied), joints (t, TDT, angle), object poses."""
    joints, nodes = _joint_names(recording)
    n = len(joints)
    loads = MessageCheck(str(recording.path), n, nodes).loads
    timing, torque, joint = _Rows(9), _Rows(1 + 2 * n), _Rows(1 + 2 * n)
    objects: _Rows | None = None
    series = Series(joints)
    # None for a log without one: then no limits to hold the torques to, and no scene. One
    # that does not read, or not as its digest says, is refused (it was read as none here)
    hand = recorded_hand(recording, required=False)
    limits = (
        [j.tau_max * (1 + 1e-9) for j in hand.joints]
        if hand is not None and hand.n_joints == n
        else None
    )
    angles = _angle_ranges(recording, hand) if hand is not None and hand.n_joints == n else None
    t0: int | None = None
    tick0: int | None = None  # tick 0's scheduled time (ns)
    period_ns = recording.meta_int(ch.META_RUN, "period_ns", 1_000_000, minimum=1)
    scheduled = 0.0  # the latest tick's scheduled time, s from the first message
    phase_name, phase_start, phase_tick = "", 0.0, 0
    frames = {"rx": 0, "tx": 0, "tx_refused": 0}
    last_log_time: dict[str, int] = {}
    exits: dict[tuple[str, int], str] = {}
    #: where the phase under way ended when the run was stopped in it (a stop or a fault),
    #: and why: the run's ``phase_end`` note, which no change of phase name shows
    ended: tuple[int, str] | None = None
    ended_at: float | None = None
    last_t = 0.0
    names = _phase_names(recording)
    topics = (ch.TIMING, ch.TORQUE, ch.JOINT_STATE, ch.PHASE, ch.EVENTS, ch.OBJECTS, ch.STATS)
    for topic, log_time, raw in iter_messages(recording, (*topics, ch.CAN_RX, ch.CAN_TX)):
        # every message decoded and checked, frames too: a count read from the raw bytes
        # counted a garbled frame that held '"ok":false' as refused and a refused one written
        # with a space as sent, and passed frames the re-run then refused
        msg = loads(topic, log_time, raw)
        if log_time < last_log_time.get(topic, log_time):
            series.out_of_order[topic] = series.out_of_order.get(topic, 0) + 1
        else:
            last_log_time[topic] = log_time
        if topic == ch.CAN_RX:
            frames["rx"] += 1
            continue
        if topic == ch.CAN_TX:
            frames["tx"] += 1
            if msg.get("ok") is False:
                frames["tx_refused"] += 1
            continue
        if t0 is None:
            t0 = log_time
        t = (log_time - t0) * 1e-9
        if topic == ch.TIMING:
            tick, scheduled_ns = int(msg["tick"]), int(msg["scheduled_ns"])
            if scheduled_ns < 0:
                # no clock of a run's reads below zero (CLOCK_MONOTONIC, or simulated time
                # from 0): a time of -1e18 was refused below as a bad tick, 'tick 800'
                raise ConfigError(
                    str(recording.path),
                    f"{topic} message at log time {log_time} ns (tick {tick}): scheduled_ns",
                    "a time on the loop's clock, at least 0 (CLOCK_MONOTONIC, or simulated "
                    "time from 0)",
                    scheduled_ns,
                )
            if tick * period_ns > scheduled_ns:
                # tick 0 scheduled before the clock's zero: no run's (its ticks come a period
                # apart or more after it). A tick of 2^62 put tick 0 some 10^20 ns before
                # zero, and the plot's arrays of times overflowed: a traceback.
                raise ConfigError(
                    str(recording.path),
                    f"{topic} message at log time {log_time} ns: tick",
                    f"at most its scheduled_ns over the run's period ({scheduled_ns} ns "
                    f"/ {period_ns} ns), as a run's ticks come a period apart or more",
                    f"tick {tick}",
                )
            if tick0 is None:
                tick0 = scheduled_ns - tick * period_ns
            scheduled = (scheduled_ns - t0) * 1e-9
            if ended is not None and msg["tick"] == ended[0]:
                # the stop's tick's own scheduled time: after missed ticks (real time) it is
                # later than its number of periods, and the run's clock is the schedule's
                ended_at = scheduled
            stages = msg.get("stage_cpu_ns") or {}
            timing.add(
                (
                    t,
                    msg["tick"],
                    msg.get("lateness_ns", 0),
                    msg.get("missed", 0),
                    1.0 if msg.get("active") else 0.0,
                    *(stages.get(name, 0) for name in RECORDED_STAGES),
                )
            )
            last_t = t
        elif topic == ch.TORQUE:
            applied = json_floats(msg["applied_nm"])
            if limits is not None:
                _check_applied(recording, log_time, msg, applied, limits, joints)
            torque.add([t, *json_floats(msg["desired_nm"]), *applied])
        elif topic == ch.JOINT_STATE:
            angle = json_floats(msg["angle_rad"])
            if angles is not None:
                _check_angles(recording, log_time, msg, angle, angles, joints)
            joint.add([t, *json_floats(msg["tdt_torque_nm"]), *angle])
        elif topic == ch.PHASE:
            name = msg["phase"]
            if names is not None and name not in names:
                # one message edited to "no_such_phase" split a phase in two in the summary
                # without a word; only the re-run saw it
                series.unknown_phases.setdefault(name, msg["tick"])
            if name != phase_name:  # a phase starts at its first tick's scheduled time
                if phase_name:
                    series.phases.append(
                        {
                            "name": phase_name,
                            "start_s": phase_start,
                            "end_s": scheduled,
                            "tick": phase_tick,
                        }
                    )
                phase_name, phase_start, phase_tick = name, scheduled, msg["tick"]
        elif topic == ch.EVENTS:
            msg["t_s"] = t
            series.events.append(msg)
            if msg["kind"] == "phase":
                exits[(msg.get("previous", ""), msg["tick"])] = msg.get("detail", "")
            elif msg["kind"] == "request" and msg.get("name") == "phase_end":
                ended = (int(msg["tick"]), str(msg.get("detail", "")))
        elif topic == ch.OBJECTS:
            if objects is None:
                series.object_names = [
                    str(o.get("name", f"object{i + 1}")) for i, o in enumerate(msg["objects"])
                ]
                objects = _Rows(2 + 3 * len(series.object_names))
            if len(msg["objects"]) != len(series.object_names):
                raise ConfigError(
                    str(recording.path),
                    f"{topic} message at log time {log_time} ns (tick {msg['tick']}): objects",
                    f"the {len(series.object_names)} objects of the first such message",
                    f"{len(msg['objects'])} objects",
                )
            # null where the writer wrote a non-finite number, or none was written: NaN
            values = [t, *json_floats([msg.get("line_angle_rad")])]
            for o in msg["objects"]:
                values += json_floats([o.get("x_m"), o.get("y_m"), o.get("angle_rad")])
            objects.add(values)
        elif topic == ch.STATS:
            series.stats = msg
    _check_tick_rows(recording, timing.size, frames, torque.size + joint.size)
    if phase_name:
        series.phases.append(
            {"name": phase_name, "start_s": phase_start, "end_s": last_t, "tick": phase_tick}
        )
    stop_exit = ""
    if ended is not None and series.phases and ended[0] >= series.phases[-1]["tick"]:
        # the stop's tick, on the ticks' time base (as the run's own summary has it)
        if ended_at is not None:
            series.phases[-1]["end_s"] = ended_at
        stop_exit = ended[1]
    for phase in series.phases:
        phase["exit"] = next(
            (
                v
                for (name, tick), v in exits.items()
                if name == phase["name"] and tick > phase["tick"]
            ),
            "",
        )
    if stop_exit and not series.phases[-1]["exit"]:
        series.phases[-1]["exit"] = stop_exit
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
    series.rest_y = _rest_heights(recording, series, hand)
    series.frames = frames
    _check_drops(recording, series.stats)
    return series


def _check_tick_rows(
    recording: Recording, rows: int, frames: dict[str, int], tick_messages: int
) -> None:
    """Refuse a log of frames (or torques, joint states) and no tick row: a run logs a row
    for every tick from its first listening one on, and polls and sends only in ticks, so
    such a log is not a run's, or lost its rows (``/loop/timing`` emptied with the end
    record's count of it). It was summarised as "0 ticks, complete", exit 0, beside its
    frames and a table of torques, where ``replay --to-bus`` refused it (an outside audit).
    A log a run is still writing may hold its first tick's frames a moment before that
    tick's row (the writer puts frames out before the rows that follow them)."""
    if rows or recording.being_written or not (frames["rx"] or frames["tx"] or tick_messages):
        return
    raise ConfigError(
        str(recording.path),
        f"channel {ch.TIMING}",
        "a tick row for every tick whose frames, torques or joint states the log holds, as "
        "a run logs them (a log without them is not a run's, or lost them)",
        Description(
            f"none, beside {frames['rx']} frames received, {frames['tx']} sent and "
            f"{tick_messages} messages of {ch.TORQUE} and {ch.JOINT_STATE}"
        ),
    )


def _check_drops(recording: Recording, stats: dict[str, Any]) -> None:
    """The writer's running counts (``/recording/stats``) never exceed its final ones (the
    end record): a log whose stats said 3 ticks dropped and whose end said none was shown
    "drops: none" and re-run as if whole."""
    for key in ch.DROPPED_KEYS:
        said = stats.get(key)
        if said is None or not recording.meta(ch.META_END, key):
            continue
        final = recording.meta_int(ch.META_END, key, 0)
        if int(said) > final:
            raise ConfigError(
                str(recording.path),
                f"metadata {ch.META_END}.{key}",
                f"at least the {said} that {ch.STATS} counted",
                str(final),
            )


def _phase_names(recording: Recording) -> frozenset[str] | None:
    """What the phase channel may say: the recorded recipe's phases and the runner's own
    statuses; None for a log without a recipe (nothing to hold the names to)."""
    from handctl.online.recipes.runner import RunStatus
    from handctl.recording.replay import NOT_PHASES

    recipe = recorded_recipe_or_none(recording)
    if recipe is None:
        return None
    return frozenset(
        {p.name for p in recipe.phases} | {s.value for s in RunStatus} | set(NOT_PHASES)
    )


def recorded_recipe_or_none(recording: Recording) -> Recipe | None:
    """The recording's recipe, or None for a log without one (no recipe record, or no hand
    to read it for) or with one that today's rules no longer read (a log of an earlier
    handctl: its frames and its summary stay readable; the re-run, which needs the recipe,
    refuses it). One that reads but was compiled for another hand config (its digest) is
    refused as the re-run refuses it: the summary and the plot of such a log went on as for
    a log of no recipe, exit 0 (an outside audit); and refusing every recipe that did not
    read made a log of an earlier handctl unreadable (an audit of that fix)."""
    from handctl.online.recipes.loader import check_against_hand
    from handctl.recording.metadata import parse_recorded_recipe

    hand = recorded_hand(recording, required=False)
    if hand is None or not recording.meta(ch.META_RECIPE, "yaml"):
        return None
    try:
        recipe = parse_recorded_recipe(recording, hand)
    except ConfigError as exc:
        if exc.key.endswith("hand_config_hash"):
            raise  # compiled for another hand: read for that hand's digest, and refused
        return None
    check_against_hand(recipe, hand)
    return recipe


def line_pairs(recipe: Recipe | None, names: Sequence[str]) -> list[tuple[str, int, int]]:
    """The pairs of logged objects whose centre line a replay measures, as ``(name, a, b)``
    with ``a``, ``b`` indices into ``names`` (``Series.object_names``): the recorded
    ``recipe``'s ``pairs`` (``recorded_recipe_or_none``, read once by the caller: a tenth of
    a second each time), in its order, or each object with the next for a log whose recipe
    names none (or that has none that reads). Not simply the first two objects: a recipe of
    four objects that measures the third with the fourth was summarised by a line it never
    declared."""
    named = (
        [(recipe.objects[a].name, recipe.objects[b].name) for a, b in recipe.pairs]
        if recipe is not None
        else []
    )
    return [(ch.pair_name(names[a], names[b]), a, b) for a, b in ch.pose_pairs(names, named)]


def line_angle(objects: FloatArray, a: int, b: int) -> FloatArray:
    """rad: the angle of the line from object ``a``'s centre to ``b``'s, per row of
    ``Series.objects``."""
    angle: FloatArray = np.arctan2(
        objects[:, 3 + 3 * b] - objects[:, 3 + 3 * a],
        objects[:, 2 + 3 * b] - objects[:, 2 + 3 * a],
    )
    return angle


def _check_applied(
    recording: Recording,
    log_time: int,
    msg: dict[str, Any],
    applied: list[float],
    limits: list[float],
    joints: list[str],
) -> None:
    """Refuse an applied torque over the recorded hand's ``tau_max``: the supervisor never
    applies more, so such a log was not written by a run (the summary reported a largest
    applied torque of 1e40 N·m as a fact). Nor a NaN (the writer's null): no NaN is over a
    limit, and one passed the summary while 1e9 was refused (an outside audit)."""
    for j, (value, limit) in enumerate(zip(applied, limits, strict=True)):
        if not abs(value) <= limit:
            raise ConfigError(
                str(recording.path),
                f"{ch.TORQUE} message at log time {log_time} ns (tick {msg['tick']}): "
                f"applied_nm[{j}] ({joints[j]})",
                f"a number, at most the recorded hand's tau_max, {limit / (1 + 1e-9):g} N·m, "
                "as the supervisor applies",
                Description("null (NaN), which the supervisor never applies")
                if math.isnan(value)
                else value,
            )


#: What a joint's angle is read off: the Feedback message of its node, and its signal there
AngleRange = tuple[str, float, float]


def _angle_ranges(recording: Recording, hand: HandConfig) -> list[AngleRange]:
    """Each joint's Feedback angle signal (``Feedback_n.Anglek``) and the angles a decode of
    it can give (rad), in the recorded protocol (the packaged one the hand generates for a
    log from before it was recorded). The bound of a logged angle that a run's log can never
    pass, whatever its hand or DBC: the host's angles are those decodes, a joint past its
    soft limits included (``wirelimits`` keeps the limits inside the signal's range), so
    even a broken or hostile node reads within it. A joint's limits and a margin would be
    a guess of how far a real joint can overshoot."""
    protocol = recorded_protocol(recording) or protocol_for(hand)
    ranges: list[AngleRange] = []
    for finger in hand.fingers:
        layout = protocol.layout("Feedback", finger.node_id)
        signals = {s.name: s for s in layout.signals}
        for k in range(len(finger.joints)):
            lo, hi = signals[f"Angle{k + 1}"].decoded_range()
            ranges.append((f"{layout.name}.Angle{k + 1}", lo, hi))
    return ranges


def _check_angles(
    recording: Recording,
    log_time: int,
    msg: dict[str, Any],
    angles: list[float],
    ranges: list[AngleRange],
    joints: list[str],
) -> None:
    """Refuse a joint angle no Feedback frame can carry (``_angle_ranges``): a garbled or
    edited log's 1e9 rad was summarised and plotted as a joint's angle. A null (NaN) is the
    writer's for a number it could not write, and passes: it claims no angle."""
    for j, (value, (signal, lo, hi)) in enumerate(zip(angles, ranges, strict=True)):
        if not lo <= value <= hi and not math.isnan(value):
            raise ConfigError(
                str(recording.path),
                f"{ch.JOINT_STATE} message at log time {log_time} ns (tick {msg['tick']}): "
                f"angle_rad[{j}] ({joints[j]})",
                f"an angle {signal} can carry, {lo:g}..{hi:g} rad (a run reads it there)",
                value,
            )


def json_floats(values: list[float | None]) -> list[float]:
    """JSON has no NaN: the writer wrote a non-finite number as null."""
    return [math.nan if v is None else v for v in values]


def _joint_names(recording: Recording) -> tuple[list[str], int | None]:
    """The joints' names and the number of finger nodes (None: not known) of the recorded
    hand; for a log without one, as many joints as its first torques have."""
    hand = recorded_hand(recording, required=False)
    if hand is not None:
        return list(hand.joint_names), len(hand.fingers)
    for _, _, msg in iter_decoded(recording, (ch.TORQUE,)):
        return [f"j{i}" for i in range(len(msg["applied_nm"]))], None
    return [], None


def _rest_heights(recording: Recording, series: Series, hand: HandConfig | None) -> list[float]:
    """Where the objects rested at the start: the recorded scene's initial poses (the run
    summary's reference), or the first logged pose for a log without them. Sets the joints'
    ``tau_max`` from the recorded hand config (``hand``) on the way."""
    from handctl.sim.params import parse_sim
    from handctl.sim.placement import rest_heights

    first = (
        [
            float(series.objects[0][3 + 3 * i]) if len(series.objects) else math.nan
            for i in range(len(series.object_names))
        ]
        if series.object_names
        else []
    )
    try:
        params = parse_sim(hand) if hand is not None and hand.sim else None
    except ConfigError:
        hand, params = None, None
    if hand is not None:
        series.tau_max = [j.tau_max for j in hand.joints]
        series.fingers = [(f.name, len(f.joints)) for f in hand.fingers]
    if params is None:
        return first
    assert hand is not None
    initial = dict(zip((o.name for o in params.objects), rest_heights(hand, params), strict=True))
    return [initial.get(name, first[i]) for i, name in enumerate(series.object_names)]
