"""``handctl replay --rerun``: a bit-exact re-run of a recording through the recipe runner and
safety.

It builds a fresh ``Runtime`` (driver, recipe runner, supervisor) from the hand config and
recipe stored in the log, and drives it with the log itself: a clock that hands out the logged
ticks (time, missed ticks) and a bus that hands out, tick by tick, the very frames the original
drain returned and the bus events it reported, with the operator's stop and e-stop requests at
the ticks they took effect. Everything the original tick consumed is thus the same, so its
applied torques, and the command frames built from them, must come out bit for bit the same;
any difference is listed.
"""

from __future__ import annotations

import asyncio
import functools
import heapq
import itertools
import math
import struct
import time
from collections import deque
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from handctl.config import HandConfig
from handctl.errors import ConfigError, Description, escaped
from handctl.hand_protocol import protocol_for
from handctl.online import timebudget
from handctl.online.bus import DRAIN_LIMIT, BusEvent, BusEventKind, Frame, FrameTap, RxTap
from handctl.online.clock import Tick
from handctl.online.drivers.hand import HandDriver
from handctl.online.loop import EndOfTicks, Runtime, TickRecord
from handctl.online.recipes.reanalysis import Reanalyser, ReanalysisResult
from handctl.online.recipes.schema import Recipe
from handctl.online.safety.faults import FaultCode
from handctl.online.taps import TAP_TX, TAP_TX_FAILED
from handctl.recording import channels as ch
from handctl.recording.feedback_check import FeedbackCheck
from handctl.recording.messages import MessageCheck
from handctl.recording.metadata import (
    check_run_metadata,
    missing_record,
    recorded_hand,
    recorded_protocol,
    recorded_recipe,
)
from handctl.recording.reader import Recording, iter_chunks, require_topics
from handctl.recording.series import json_floats

MAX_LISTED = 20
#: the outcome of a re-run of a log whose run stopped before its runtime was set up, and of
#: one whose run stopped before its first tick
NOT_STARTED = "the run ended before its runtime was set up"
NO_TICK = "the run ended before its first tick"
#: how a frame the log has and the re-run did not send ends its mismatch's text
RERUN_DID_NOT_SEND = " that the re-run did not send"


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
    desired: list[float] | None = None
    joint_state: dict[str, Any] | None = None  # the logged /hand/joint_state message
    state: str | None = None  # the logged /safety/state
    faults_latched: int | None = None  # and its count of faults latched so far
    phase: str | None = None  # the logged /recipe/phase


@dataclass
class _Pending:
    rx: list[Frame] = field(default_factory=list)
    tx: list[tuple[int, bytes, bool]] = field(default_factory=list)
    bus_events: list[BusEvent] = field(default_factory=list)
    requests: list[tuple[str, str]] = field(default_factory=list)
    rejects: dict[str, int] | None = None


def tick_inputs(  # noqa: C901 - one branch per channel; bus/replay split (issue 16)
    recording: Recording,
    check: MessageCheck | None = None,
    faults: list[tuple[int, str]] | None = None,
) -> tuple[_Pending, Iterator[TickInput]]:
    """The frames drained before the first tick, and a stream of the logged ticks; the
    logged faults (tick, code) go into ``faults`` as the stream reads them.

    A tick is whole when the next tick's row begins: its frames and events are published
    before that row (``Recorder``), most of them before its own row, and the frames it sends
    after its push (the nodes' disable after the last control tick) between the two. So the
    stream hands out a tick only when it meets the next row, and the last row only when the
    recorder closed the file; a gap in the ticks (a damaged chunk) ends the stream before it,
    and a log whose first row is not tick 0 gives no ticks at all. Only a damaged chunk can
    explain either: in a log without one (whole, or cut short at its end) a row out of
    sequence is a ConfigError naming it.
    One pass, one branch per message: this is most of what a re-run reads.
    """
    pending: dict[int, _Pending] = {}
    kinds = {k.value: k for k in BusEventKind}
    batches = iter_chunks(recording, ch.RERUN_TOPICS, check)
    timing, torque, rx, tx, joint = ch.TIMING, ch.TORQUE, ch.CAN_RX, ch.CAN_TX, ch.JOINT_STATE
    safety, phase = ch.SAFETY, ch.PHASE
    fromhex = bytes.fromhex
    closed = recording.complete and recording.meta(ch.META_END, "ended") == ch.ENDED_CLOSED

    def inputs_of(k: int, current: TickInput | None) -> TickInput | _Pending:
        if current is not None:
            if current.tick == k:
                return current
            if k < current.tick:
                # a tick's frames and events are published before the next tick's row: one
                # of a tick already handed out was put in since. Frames of tick -1 set in the
                # middle of a log were never compared, and went onto a bus after a re-run
                # said bit-exact (found by an outside audit)
                raise _out_of_place(recording, k, current.tick)
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
                        Frame(msg["id"], fromhex(msg["data"]), msg.get("bus_time_ns", 0))
                    )
                elif topic == tx:
                    inputs_of(msg["tick"], current).tx.append(
                        (msg["id"], fromhex(msg["data"]), msg.get("ok", True))
                    )
                elif topic == timing:
                    k = msg["tick"]
                    expected = 0 if current is None else current.tick + 1
                    if k != expected:
                        if not recording.damaged or k < expected:
                            raise _out_of_sequence(recording, msg, expected)
                        return  # a gap: the ticks in a damaged chunk are not in the file
                    if current is not None:
                        yield current
                    current = TickInput(k, msg["scheduled_ns"], msg["now_ns"], msg["missed"])
                    got = pending.pop(k, None)
                    if got is not None:
                        current.rx, current.tx = got.rx, got.tx
                        current.bus_events, current.requests = got.bus_events, got.requests
                        current.rejects = got.rejects
                elif topic == torque:
                    if current is not None and current.tick == msg["tick"]:
                        current.applied = json_floats(msg["applied_nm"])
                        current.desired = json_floats(msg["desired_nm"])
                elif topic == safety:
                    if current is not None and current.tick == msg["tick"]:
                        current.state = msg["state"]
                        current.faults_latched = msg.get("faults_latched")
                elif topic == phase:
                    if current is not None and current.tick == msg["tick"]:
                        current.phase = msg["phase"]
                elif topic == joint:
                    if current is not None and current.tick == msg["tick"]:
                        current.joint_state = msg
                elif topic == ch.EVENTS and msg["kind"] in ("bus", "request", "rejected_frames"):
                    _route(msg, inputs_of(msg["tick"], current), kinds)
                elif topic == ch.EVENTS and msg["kind"] == "fault" and faults is not None:
                    faults.append((msg["tick"], msg["name"]))
        if current is not None and closed:
            yield current

    stream = ticks()
    # The frames drained before the first tick (tick -1) precede the first row.
    first = next(stream, None)
    before = pending.pop(-1, None) or _Pending()
    return before, itertools.chain(() if first is None else (first,), stream)


def _out_of_place(recording: Recording, tick: int, current: int) -> ConfigError:
    """A frame or event of tick ``tick`` logged after tick ``current``'s row: a recorder
    publishes each before the next row, so the log was altered."""
    return ConfigError(
        str(recording.path),
        f"a frame or event of tick {tick}",
        f"one logged before tick {tick + 1}'s row, as the recorder publishes them",
        Description(f"one logged after tick {current}'s row"),
    )


def _out_of_sequence(recording: Recording, msg: dict[str, Any], expected: int) -> ConfigError:
    """A logged tick row that does not follow the one before it, in a log where no damaged
    chunk can have taken the rows between: the log was altered."""
    return ConfigError(
        str(recording.path),
        f"{ch.TIMING} message: tick",
        f"tick {expected}, the row after "
        + ("the start of the log" if expected == 0 else f"tick {expected - 1}")
        + " (ticks follow one another; only a damaged chunk leaves a gap)",
        msg["tick"],
    )


def _route(
    msg: dict[str, Any], inputs: TickInput | _Pending, kinds: dict[str, BusEventKind]
) -> None:
    """A bus event or an operator request (inputs of their tick), or the rejects the run
    counted (what the re-run must count too)."""
    kind = msg["kind"]
    if kind == "bus":
        inputs.bus_events.append(
            BusEvent(
                kinds.get(msg["name"], BusEventKind.ERROR_FRAME),
                msg["detail"],
                msg.get("bus_time_ns", 0),
                msg.get("id"),  # a remote frame's, which the driver hears as the run did
            )
        )
    elif kind == "request":
        inputs.requests.append((msg["name"], msg["detail"]))
    else:
        rejects = inputs.rejects
        if rejects is None:
            rejects = inputs.rejects = {}
        rejects[msg["name"]] = rejects.get(msg["name"], 0) + int(msg.get("count", 0))


class ReplayBus:
    """A ``FrameBus`` with the log behind it: ``drain`` returns what the original drain
    returned in this tick, ``send`` checks the frame against the one the original sent (and
    answers as the bus did), ``events`` returns the events the original poll took. Taps are
    told what a ``HandBus`` would tell them."""

    def __init__(self) -> None:
        self.tap: FrameTap | None = None
        self.rx_tap: RxTap | None = None
        self.event_tap: Callable[[BusEvent], None] | None = None
        self.tap_error: BaseException | None = None
        #: Each frame's fate is the log's, frame by frame, a burst's too (``HandBus`` taps a
        #: failed burst's every frame as failed).
        self.batching = False
        self.sent = 0
        self.tx_failed = 0
        self.received = 0
        self.closed = False
        self.tick = -1
        self._rx: deque[Frame] = deque()
        self._tx: deque[tuple[int, bytes, bool]] = deque()
        self._events: list[BusEvent] = []
        self.frame_mismatches: list[str] = []
        self.frames_compared = 0
        #: The burst's frames sent and not yet tapped, and their direction.
        self._tapped: list[tuple[int, bytes]] = []
        self._tapped_direction = TAP_TX

    def load(self, tick: int, inputs: TickInput | _Pending) -> None:
        for frame_id, data, _ in self._tx:
            self._mismatch(
                f"tick {self.tick}: the log has frame 0x{frame_id:03X} "
                f"{data.hex()}{RERUN_DID_NOT_SEND}"
            )
        self.tick = tick
        self._rx = deque(inputs.rx)
        self._tx = deque(inputs.tx)
        self._events = list(inputs.bus_events)

    def prepare_send(self) -> None:
        """Nothing to ready: a re-run sends nowhere."""

    def use_clock(self, clock_ns: Callable[[], int]) -> None:
        """The logged frames carry the times they arrived at in the run: no clock to use."""

    def drain(self, limit: int = DRAIN_LIMIT) -> list[Frame]:
        rx = self._rx
        if len(rx) <= limit:
            frames = list(rx)
            rx.clear()
        else:
            frames = [rx.popleft() for _ in range(limit)]
        self.received += len(frames)
        if frames and self.rx_tap is not None:
            self._tap_sent()
            try:
                self.rx_tap(frames)
            except BaseException as exc:  # held, as a ``HandBus`` holds it
                self._tap_failed(exc)
        return frames

    def send(self, arbitration_id: int, data: bytes, more: bool = False) -> bool:
        self.frames_compared += 1
        if not self._tx:
            self._mismatch(
                f"tick {self.tick}: the re-run sent frame 0x{arbitration_id:03X} "
                f"{bytes(data).hex()}, the log has no more frames in this tick"
            )
            ok = True
        else:
            frame_id, logged, ok = self._tx.popleft()
            if frame_id != arbitration_id or logged != data:
                self._mismatch(
                    f"tick {self.tick}: the re-run sent 0x{arbitration_id:03X} "
                    f"{bytes(data).hex()}, the log has 0x{frame_id:03X} "
                    f"{logged.hex()}"
                )
            self.sent += ok
            self.tx_failed += not ok
        if self.tap is not None:
            # Tapped a burst at a time, as a ``HandBus`` taps them: a frame whose fate is not
            # the burst's so far ends the burst's tap before its own.
            direction = TAP_TX if ok else TAP_TX_FAILED
            if self._tapped and direction != self._tapped_direction:
                self._tap_sent()
            self._tapped.append((arbitration_id, data))
            self._tapped_direction = direction
            if not more:
                self._tap_sent()
        return ok

    def _tap_sent(self) -> None:
        tapped, self._tapped = self._tapped, []
        if self.tap is not None and tapped:
            try:
                self.tap(tapped, self._tapped_direction)
            except BaseException as exc:
                self._tap_failed(exc)

    def _tap_failed(self, exc: BaseException) -> None:
        if self.tap_error is None:
            self.tap_error = exc

    def flush(self) -> bool:
        """Sends are compared as they come: only the burst's tap is due."""
        self._tap_sent()
        return True

    def drop_burst(self) -> int:
        """Nothing is held: each frame's fate is the log's as it is sent."""
        return 0

    def events(self) -> list[BusEvent]:
        events, self._events = self._events, []
        if self.event_tap is not None:
            for event in events:
                try:
                    self.event_tap(event)
                except BaseException as exc:
                    self._tap_failed(exc)
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


class ReplayClock:
    """A ``Clock`` that hands out the logged ticks, and the operator's requests at the ticks
    they took effect. Stepped, as the lockstep clock: the log ends the run when it ends."""

    lockstep = True

    def __init__(self, inputs: Iterator[TickInput], bus: ReplayBus) -> None:
        self.inputs = inputs
        self.bus = bus
        self.runtime: Runtime | None = None
        self.current: TickInput | None = None
        self.unsupported: list[str] = []
        self.check: FeedbackCheck | None = None
        #: Bad input met in the log while the re-run ran: the runtime would take it for a
        #: failed tick and stop the hand, so the log ends there and the re-run raises it after.
        self.bad_input: ConfigError | None = None

    def now_ns(self) -> int:
        return self.current.now_ns if self.current is not None else 0

    async def wait_tick(self) -> Tick:
        try:
            current = next(self.inputs, None)
        except ConfigError as exc:
            self.bad_input = exc
            raise _EndOfLogError from None
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
                elif kind == "peer_gone":
                    # the run's peer process ended in its start-up: what it said, from here
                    runtime.peer_gone = functools.partial(str, detail)
                elif kind in ("limit", "node_reset", "phase_end", "disable_unconfirmed"):
                    pass  # the runtime's own notes (a stop's, the start-up's): said again
                else:
                    self.unsupported.append(f"tick {current.tick}: {kind}")
        return Tick(current.tick, current.scheduled_ns, current.now_ns, current.missed)

    def close(self) -> None:
        pass


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
        #: the ticks counted in ``mismatched_ticks``, and the ticks compared before ``until``
        #: (``_up_to_the_exception``: a run that ended on an exception the re-run cannot raise)
        self.bad_ticks: list[int] = []
        self.until = math.inf
        self.compared_before = 0
        #: what else the tick decided and the log says it decided: the desired torques, the
        #: supervisor's state, the phase. A log whose phase or state was rewritten re-ran
        #: "bit-exact" on its torques while replay's phase table showed the rewritten ones.
        self.decisions: list[str] = []
        #: the faults the re-run raised, (tick, code), as its supervisor latched them
        self.faults: list[tuple[int, str]] = []
        self._latched = 0

    def begin_tick(self, tick: Tick) -> None:
        return None

    def _note_faults(self) -> None:
        runtime = self.clock.runtime
        if runtime is None:
            return
        latched = runtime.supervisor.faults
        if len(latched) < self._latched:  # an explicit reset cleared them
            self._latched = 0
        self.faults += [(f.tick, f.code.name) for f in latched[self._latched :]]
        self._latched = len(latched)

    def push(self, record: TickRecord) -> None:
        self._note_faults()
        current = self.clock.current
        if current is not None:
            self.check.tick(record.tick, current.now_ns, current.joint_state, current.rx)
        logged = current.applied if current is not None else None
        rerun = record.applied
        if logged is None:
            self._mismatched(record.tick)
            self._add(
                record.tick,
                "-",
                math.nan,
                float(np.max(np.abs(rerun))),
                "the re-run ran a control step where the log has no torques",
            )
            return
        n = len(logged)
        pack = _PACK.get(n)
        if pack is None:
            pack = _PACK[n] = struct.Struct(f"<{n}d")
        self.compared += 1
        self.compared_before += record.tick < self.until
        decided = self._decisions(record, current, pack) if current is not None else True
        if len(rerun) == n and rerun.tobytes() == pack.pack(*logged):
            if not decided:
                self._mismatched(record.tick)
            return
        self._mismatched(record.tick)
        for j, (a, b) in enumerate(zip(logged, rerun.tolist(), strict=False)):
            if struct.pack("<d", a) != struct.pack("<d", b):
                name = self.joints[j] if j < len(self.joints) else str(j)
                self._add(record.tick, name, a, b, "")

    def note(self, kind: str, detail: str, tick: int) -> None:
        return None

    def _mismatched(self, tick: int) -> None:
        self.mismatched_ticks += 1
        self.bad_ticks.append(tick)

    def _decisions(self, record: TickRecord, logged: TickInput, pack: struct.Struct) -> bool:
        """Whether the tick's desired torques, safety state and phase are the log's (each
        that differs is listed in ``decisions``)."""
        same = True
        # a tick the log has no record of is no tick it shows as the re-run's (a record cut
        # out re-ran "as logged")
        if logged.state != record.state:
            self._decided(record.tick, "safety state", logged.state, record.state)
            same = False
        runtime = self.clock.runtime
        latched = len(runtime.supervisor.faults) if runtime is not None else None
        if latched is not None and logged.state is not None and logged.faults_latched != latched:
            self._decided(record.tick, "faults latched", logged.faults_latched, latched)
            same = False
        if logged.phase != record.phase:
            self._decided(record.tick, "phase", logged.phase, record.phase)
            same = False
        desired = logged.desired
        if desired is not None and (
            len(desired) != len(record.desired) or record.desired.tobytes() != pack.pack(*desired)
        ):
            for j, (a, b) in enumerate(zip(desired, record.desired.tolist(), strict=False)):
                if struct.pack("<d", a) != struct.pack("<d", b):
                    name = self.joints[j] if j < len(self.joints) else str(j)
                    self._decided(record.tick, f"desired torque of {name} (N·m)", a, b)
                    break
            same = False
        return same

    def _decided(self, tick: int, what: str, logged: object, rerun: object) -> None:
        if len(self.decisions) < 1000:
            self.decisions.append(f"tick {tick}: {what}: logged {logged!r}, re-run {rerun!r}")

    def _add(self, tick: int, joint: str, logged: float, rerun: float, detail: str) -> None:
        if len(self.mismatches) < 1000:
            self.mismatches.append(
                {
                    "tick": tick,
                    "joint": joint,
                    "logged_nm": logged,
                    "rerun_nm": rerun,
                    "detail": detail,
                }
            )


@dataclass
class RerunReport:
    ticks: int
    compared: int
    mismatched_ticks: int
    mismatches: list[dict[str, Any]]
    frames_compared: int
    frame_mismatches: list[str]  # sent frames, and received ones the re-run read otherwise
    decision_mismatches: list[str]  # desired torques, safety state, phase
    feedback_compared: int  # ticks whose received frames were compared
    outcome: str
    logged_outcome: str
    notes: list[str]
    wall_s: float
    outcome_mismatch: str = ""  # the run ended otherwise than the log's summary says
    fault_mismatch: str = ""  # the run latched other faults than the log's events say

    @property
    def ok(self) -> bool:
        return not (
            self.mismatched_ticks
            or self.frame_mismatches
            or self.outcome_mismatch
            or self.fault_mismatch
        )

    def as_dict(self) -> dict[str, Any]:
        return {
            "ok": self.ok,
            "ticks": self.ticks,
            "compared": self.compared,
            "mismatched_ticks": self.mismatched_ticks,
            "mismatches": self.mismatches[:MAX_LISTED],
            "frames_compared": self.frames_compared,
            "frame_mismatches": self.frame_mismatches[:MAX_LISTED],
            "decision_mismatches": self.decision_mismatches[:MAX_LISTED],
            "feedback_compared": self.feedback_compared,
            "outcome": self.outcome,
            "logged_outcome": self.logged_outcome,
            "notes": self.notes,
            "wall_s": round(self.wall_s, 3),
        }


#: What builds the analysis at the measured configuration for a re-run (the offline plane's
#: ``handctl.planning.reanalysis.ReanalysisOnTick``, which the command passes in: the
#: recording plane does not import the offline one): the hand, the recipe, the estimator.
ReanalysisFactory = Callable[[HandConfig, Recipe, Any], Reanalyser]


def _late_in_the_run(logged: dict[str, Any], recipe: Recipe) -> set[int]:
    """The recipe's indices of the phases whose analysis the real-time run found not there
    ``delay_s`` after asking (its summary's phase records: ``late: ...``), and so ran their
    planned torques."""
    index = {p.name: k for k, p in enumerate(recipe.phases)}
    phases = logged.get("phases")
    records = phases if isinstance(phases, list) else []
    return {
        index[p["name"]]
        for p in records
        if isinstance(p, dict)
        and p.get("name") in index
        and str(p.get("reanalysis", "")).startswith("late:")
    }


class _LateAsLogged:
    """The re-run's analysis, late where the run's was: the answer is computed on the tick in
    a re-run, so a real-time run whose answer came after ``delay_s`` (and kept the planned
    torque) re-ran with the answer and said MISMATCH on a genuine log (found by an outside
    audit)."""

    def __init__(self, inner: Reanalyser, late: set[int]) -> None:
        self.inner = inner
        self.late = late

    def submit(self, phase: int, angles: Sequence[float], estimates: Sequence[float]) -> None:
        if phase not in self.late:
            self.inner.submit(phase, angles, estimates)

    def collect(self, phase: int) -> ReanalysisResult | None:
        return None if phase in self.late else self.inner.collect(phase)


def rerun(recording: Recording, reanalysis: ReanalysisFactory | None = None) -> RerunReport:
    """Feed the logged feedback through a fresh driver, runner and supervisor; compare.

    A recipe with ``reanalyse`` phases needs ``reanalysis``: the re-run computes each
    phase's analysis again from the logged inputs, on the tick the run applied it."""
    path = str(recording.path)
    run = recording.metadata.get(ch.META_RUN)
    if (
        recording.meta_int(ch.META_END, "ticks", -1) == 0
        and recording.message_counts.get(ch.TIMING, 0) == 0
    ):
        # the run stopped before its runtime was set up (a signal while it started) or
        # before its first tick (killed then), and its file was finished with no tick in it:
        # no input was refused, and nothing is there to re-run (before: exit 2, as if
        # handctl's own log were bad input, or "NOTHING COMPARED", exit 1)
        why = NOT_STARTED if not run else NO_TICK
        return RerunReport(
            ticks=0,
            compared=0,
            mismatched_ticks=0,
            mismatches=[],
            frames_compared=0,
            frame_mismatches=[],
            decision_mismatches=[],
            feedback_compared=0,
            outcome=why,
            logged_outcome="",
            notes=[],
            wall_s=0.0,
        )
    require_topics(recording, ch.RERUN_TOPICS, "--rerun")
    if not run:
        raise ConfigError(
            path,
            f"metadata {ch.META_RUN}",
            "how the runtime was set up (recorded by handctl run recipe --log)",
            missing_record(recording, ch.META_RUN),
        )
    dropped = {
        k: recording.meta_int(ch.META_END, k, 0)
        for k in ("dropped_ticks", "dropped_frames", "dropped_events")
    }
    if any(dropped.values()):
        raise ConfigError(
            path,
            "",
            "a recording without dropped records (the re-run needs every frame)",
            ", ".join(f"{k} {v}" for k, v in dropped.items()),
        )
    hand = recorded_hand(recording)
    assert hand is not None
    check_run_metadata(recording, hand)
    recipe = recorded_recipe(recording, hand)
    period_s = (
        recording.meta_int(ch.META_RUN, "period_ns", round(hand.bus.period_s * 1e9), minimum=1)
        * 1e-9
    )
    startup_ticks = recording.meta_int(ch.META_RUN, "startup_ticks", 500)
    answer_ticks = recording.meta_int(ch.META_RUN, "answer_ticks", startup_ticks)
    bus = ReplayBus()
    logged_faults: list[tuple[int, str]] = []
    before, inputs = tick_inputs(
        recording,
        MessageCheck(str(recording.path), hand.n_joints, len(hand.fingers)),
        logged_faults,
    )
    bus.load(-1, before)
    clock = ReplayClock(inputs, bus)
    driver = HandDriver(
        hand, recorded_protocol(recording) or protocol_for(hand), bus, clock_ns=clock.now_ns
    )
    check = FeedbackCheck(hand, driver)
    clock.check = check
    compare = _Compare(clock, list(hand.joint_names), check)
    estimator = None
    if recipe.objects:  # as the session sets it up: the estimator is fed the same angles
        from handctl.online.estimator import ObjectEstimator

        estimator = ObjectEstimator(hand, recipe.objects, recipe.pairs)
    if (estimator is not None) != (run.get("estimator", "False") == "True"):
        raise ConfigError(
            path,
            f"metadata {ch.META_RUN}.estimator",
            f"{estimator is not None} (what the recorded recipe implies)",
            run.get("estimator", "nothing"),
        )
    logged = recording.json_meta(ch.META_SUMMARY) or {}
    reanalyser = (
        reanalysis(hand, recipe, estimator)
        if reanalysis is not None
        and estimator is not None
        and any(p.reanalyse is not None for p in recipe.phases)
        else None
    )
    late = _late_in_the_run(logged, recipe)
    runtime = Runtime(
        hand,
        driver,
        clock,
        recipe,
        recorder=compare,
        estimator=estimator,
        reanalyser=_LateAsLogged(reanalyser, late) if reanalyser and late else reanalyser,
        reset_node_faults=run.get("reset_node_faults") == "True",
        startup_timeout_s=startup_ticks * period_s,
        answer_timeout_s=answer_ticks * period_s,
        max_ticks=1 << 62,
    )
    clock.runtime = runtime
    runtime.cpu_clock = _no_time  # stage times are the run's, not the re-run's
    notes: list[str] = []
    raised = _logged_exception(logged)
    if raised is not None:
        compare.until = raised[0]
    started = time.perf_counter()
    outcome = "log ended"
    try:
        result = timebudget.outcome(asyncio.run(runtime.run()), runtime.stop_requested)
        outcome = result.outcome.value
    except _EndOfLogError:
        where = "before a damaged chunk" if recording.damaged else "where the log ends"
        notes.append(
            f"the re-run stops after tick {clock.current.tick if clock.current else -1}"
            f", {where} ({recording.problem or 'no more ticks'}); compared up to there"
        )
    if clock.bad_input is not None:  # wherever the run met it, the stop's ticks included
        raise clock.bad_input
    wall = time.perf_counter() - started
    if clock.current is not None and outcome != "log ended":
        check.end(clock.current.tick, clock.current.rx)
    bus.finish()
    leftover = sum(1 for _ in inputs)
    if leftover and outcome != "log ended":
        notes.append(f"the log goes on for {leftover} ticks after the re-run ended")
    notes += [f"not repeated: {u}" for u in clock.unsupported]
    ticks = (clock.current.tick + 1) if clock.current else 0
    frame_mismatches = list(heapq.merge(bus.frame_mismatches, check.mismatches, key=_tick_of))
    logged_outcome = str(logged.get("outcome", ""))
    outcome_mismatch = ""
    if logged_outcome and outcome not in ("log ended", logged_outcome):
        # the run, fed the same frames to its end, ended otherwise than the log's summary
        # says: a summary altered (a time budget said to have completed) passed bit-exact
        outcome_mismatch = f"outcome: logged {logged_outcome!r}, re-run {outcome!r}"
    compare._note_faults()
    fault_mismatch = _faults_differ(logged_faults, compare.faults, min(ticks, compare.until))
    report = RerunReport(
        ticks,
        compare.compared,
        compare.mismatched_ticks,
        compare.mismatches,
        bus.frames_compared,
        frame_mismatches,
        [*compare.decisions, *(m for m in (outcome_mismatch, fault_mismatch) if m)],
        check.compared,
        outcome,
        logged_outcome,
        notes,
        wall,
        outcome_mismatch,
        fault_mismatch,
    )
    if raised is not None and (runtime.exception is None or runtime.exception.tick != raised[0]):
        return _up_to_the_exception(report, compare, raised)
    return report


def _faults_differ(
    logged: list[tuple[int, str]], rerun: list[tuple[int, str]], before: float
) -> str:
    """What differs between the faults the log's events say the run latched and those the
    re-run latched, on the ticks before ``before`` (those compared), or "". A log whose
    events were rewritten (a fault that never happened, one taken out) re-ran "bit-exact",
    its replay printing the forged faults."""
    ours = [f for f in logged if f[0] < before]
    theirs = [f for f in rerun if f[0] < before]
    if ours == theirs:
        return ""

    def said(faults: list[tuple[int, str]]) -> str:
        listed = ", ".join(f"{escaped(code[:40])} at tick {tick}" for tick, code in faults[:4])
        more = f" and {len(faults) - 4} more" if len(faults) > 4 else ""
        return (listed + more) or "none"

    return f"faults: logged {said(ours)}; re-run {said(theirs)}"


def _logged_exception(logged: dict[str, Any]) -> tuple[int, str] | None:
    """The tick and the description of the exception the logged run stopped on, if any."""
    exc = logged.get("exception")
    if not isinstance(exc, dict) or not isinstance(exc.get("tick"), int):
        return None
    what = ": ".join(str(exc.get(k, "?")) for k in ("code", "type", "message"))
    return int(exc["tick"]), what[:200]


def _up_to_the_exception(
    report: RerunReport, compare: _Compare, raised: tuple[int, str]
) -> RerunReport:
    """The report of a re-run compared up to the tick the logged run raised in, which the
    re-run did not: an exception comes from outside the logged inputs (a bug since fixed,
    memory, the disk), so from that tick on the two runs part by design, and a re-run that
    said MISMATCH there (exit 1) read as a log tampered with."""
    tick, what = raised
    before = [m for m in report.mismatches if m["tick"] < tick]
    # a clock's exception comes before its tick begins: the stop's frames are logged in the
    # tick before, as frames the re-run, which goes on ticking, did not send (they made a
    # clock's fault re-run as MISMATCH, exit 1: an outside audit)
    stop_tick = tick - 1 if what.startswith(f"{FaultCode.CLOCK_EXCEPTION.name}:") else None

    def kept(text: str) -> bool:
        at = _tick_of(text)
        return at < tick and not (at == stop_tick and text.endswith(RERUN_DID_NOT_SEND))

    return replace(
        report,
        compared=compare.compared_before,
        mismatched_ticks=sum(t < tick for t in compare.bad_ticks),
        mismatches=before,
        frame_mismatches=[f for f in report.frame_mismatches if kept(f)],
        decision_mismatches=[d for d in report.decision_mismatches if 0 <= _tick_of(d) < tick],
        outcome_mismatch="",
        notes=[
            *report.notes,
            f"the run stopped on an exception in tick {tick} ({what}), which the re-run of "
            f"the logged inputs does not raise: compared up to tick {tick}, the stop after it "
            "is the run's own",
        ],
    )


def _tick_of(text: str) -> int:
    """The tick a mismatch's text begins with (``tick N: ...``), to list both kinds in order."""
    head = text.split(":", 1)[0].split()
    return int(head[1]) if len(head) == 2 and head[1].lstrip("-").isdigit() else -1
