"""The safety supervisor: a state Enum, a transition table, latched faults, and ``filter``.

Every torque the runtime sends comes out of ``Supervisor.filter``; nothing else produces the
values a command frame is built from. The state machine is a table (the canopen way) so that
what can follow what is data that a test can enumerate, not control flow hidden in methods:

- IDLE: zero torque, nodes disabled. START leads to ENABLING.
- ENABLING: zero torque while the nodes confirm ENABLED (ENABLED event), within a deadline.
- RUNNING: desired torques through the limiter (tau_max, rate limit).
- STOPPING: a normal stop, rate-limited to zero and there within ``STOP_BOUND_S`` whatever the
  rate limit, then IDLE.
- FAULT_RAMP: a RAMP-category fault: to zero at the rate limit, and within ``RAMP_BOUND_S``
  whatever the rate limit, then FAULTED.
- FAULTED: zero torque; faults latched. Only RESET leaves it, to IDLE, so torque can only come
  back through a new START, with the rate limiter ramping it up from zero. A recipe never
  resumes by itself: the runner is not told to go on by anything in here.

A joint outside its soft limits trips ``ANGLE_LIMIT`` in every armed state but FAULT_RAMP (in
STOPPING only while its own torque pushes it further out: ``_left_while_stopping``), with one
exception asked for before the start: a ``Recovery`` (recovery.py), which lets one
joint be outside as long as it comes back in, and the others resting outside stay where they
are, so that a finger resting past its limit can be jogged back.
"""

from __future__ import annotations

import enum
import math
from collections.abc import Sequence

import numpy as np

from handctl.arrays import BoolArray, FloatArray
from handctl.config import HandConfig
from handctl.online.bus import BusEvent, BusEventKind
from handctl.online.drivers.finger import FingerNode
from handctl.online.drivers.hand import AppliedTorques
from handctl.online.safety.faults import RAMP_BOUND_S, STOP_BOUND_S, Fault, FaultCode, StopCategory
from handctl.online.safety.limits import (
    JointLimits,
    angle_violations,
    check_desired,
    limit_torque,
    outside_text,
    toward_zero_on_grid,
)
from handctl.online.safety.recovery import Recovery
from handctl.online.safety.watchdog import (
    NodeWatch,
    ReceiveWatch,
    TdtMonitor,
    TickWatch,
    node_faults,
)
from handctl.protocol import NodeState, Protocol


class State(enum.Enum):
    # Members are singletons compared by identity: hashing them by identity too (in C)
    # spares the tick Enum's hash of the name, a Python call, at each ``in ARMED``.
    __hash__ = object.__hash__

    IDLE = "idle"
    ENABLING = "enabling"
    RUNNING = "running"
    STOPPING = "stopping"
    FAULT_RAMP = "fault_ramp"
    FAULTED = "faulted"


class Event(enum.Enum):
    __hash__ = object.__hash__  # as State's

    START = "start"
    ENABLED = "enabled"
    STOP = "stop"
    AT_ZERO = "at_zero"
    FAULT_IMMEDIATE = "fault_immediate"
    FAULT_RAMP = "fault_ramp"
    RESET = "reset"


S, E = State, Event
#: (state, event) -> next state. A pair that is not here leaves the state as it is.
TRANSITIONS: dict[tuple[State, Event], State] = {
    (S.IDLE, E.START): S.ENABLING,
    (S.IDLE, E.FAULT_IMMEDIATE): S.FAULTED,
    (S.IDLE, E.FAULT_RAMP): S.FAULTED,
    (S.ENABLING, E.ENABLED): S.RUNNING,
    (S.ENABLING, E.STOP): S.IDLE,
    (S.ENABLING, E.FAULT_IMMEDIATE): S.FAULTED,
    (S.ENABLING, E.FAULT_RAMP): S.FAULTED,  # nothing to ramp from: torque is still zero
    (S.RUNNING, E.STOP): S.STOPPING,
    (S.RUNNING, E.FAULT_IMMEDIATE): S.FAULTED,
    (S.RUNNING, E.FAULT_RAMP): S.FAULT_RAMP,
    (S.STOPPING, E.AT_ZERO): S.IDLE,
    (S.STOPPING, E.FAULT_IMMEDIATE): S.FAULTED,
    (S.STOPPING, E.FAULT_RAMP): S.FAULT_RAMP,
    (S.FAULT_RAMP, E.AT_ZERO): S.FAULTED,
    (S.FAULT_RAMP, E.FAULT_IMMEDIATE): S.FAULTED,
    (S.FAULTED, E.RESET): S.IDLE,
}

#: States in which the nodes are expected to be ENABLED and the watchdogs are armed.
ARMED = frozenset({S.RUNNING, S.STOPPING, S.FAULT_RAMP})


def next_state(state: State, event: Event) -> State:
    return TRANSITIONS.get((state, event), state)


class Supervisor:
    """Turns desired torques into applied torques, and node/bus/timing news into faults."""

    def __init__(self, hand: HandConfig, protocol: Protocol | None = None) -> None:
        """``protocol``: the one the command frames are encoded with (None: the hand's,
        ``protocol_for``), whose resolution the applied torques keep to (``limit_torque``)."""
        self.hand = hand
        self.n = hand.n_joints
        self.dt = hand.bus.period_s
        self.limits = JointLimits.from_hand(hand, protocol)
        self.node_watch = NodeWatch(hand.safety)
        self.receive_watch = ReceiveWatch(hand.safety, self.dt)
        self.tdt = TdtMonitor(hand.safety, self.n, self.dt, self.limits.names)
        self.ticks = TickWatch(hand.safety)
        self.enable_deadline_ticks = max(1, math.ceil(hand.safety.enable_timeout_s / self.dt))
        self.state = State.IDLE
        self.faults: list[Fault] = []  # latched, in order of detection
        self.active_codes: set[FaultCode] = set()
        self.applied = np.zeros(self.n)
        #: ``applied`` as the tick began: what the nodes hold (``sent``)
        self._held = np.zeros(self.n)
        self._held_tick = -1  # the tick ``_held`` was taken in: only that tick's send reverts
        self.limited_joints = 0
        #: the fault of the desired torques this tick's ``filter`` refused (None: none): the
        #: caller's bookkeeping must not read a refused vector as torques
        self.refused: FaultCode | None = None
        self.history: list[tuple[int, State, Event, State]] = []
        self._ramp_from = np.zeros(self.n)
        self._ramp_ticks = max(1, math.floor(RAMP_BOUND_S / self.dt))
        self._ramp_k = 0
        self._stop_from = np.zeros(self.n)
        self._stop_ticks = max(1, math.floor(STOP_BOUND_S / self.dt))
        self._stop_k = 0
        self._enabling_since = 0
        #: The enable frames the bus refused and the host has not got out since, as the
        #: caller says them ("": every one went): nodes that never had the enable are not
        #: late to enable, and the deadline says the bus's refusal (``BUS_ERROR``), not
        #: the nodes' states as if they had ignored it (found by an outside audit).
        self.enable_unsent = ""
        self._zero = np.zeros(self.n)  # the STOPPING state's target, never written
        #: one joint allowed back in from outside its soft limits (recovery.py); None: none
        self.recovery: Recovery | None = None
        self._armed_tick = -1  # the tick the nodes were confirmed ENABLED
        #: joints that left their soft limits in a controlled stop, not pushed out by their
        #: own torque (``_left_while_stopping``): said in the summary and the log
        self.stop_notes: list[str] = []
        self._said_in_stop: set[int] = set()  # the joints of ``stop_notes``

    # -- events ---------------------------------------------------------------------------
    def fire(self, event: Event, tick: int) -> State:
        new = next_state(self.state, event)
        if new is not self.state:
            self.history.append((tick, self.state, event, new))
            if new is State.ENABLING:
                self._enabling_since = tick
            if new is State.FAULT_RAMP:
                self._ramp_from[:] = self.applied
                self._ramp_k = 0
            elif new is State.STOPPING:
                self._stop_from[:] = self.applied
                self._stop_k = 0
            self.state = new
        return new

    def start(self, tick: int) -> None:
        """Operator or runtime asks for torque: enable first, torque only once confirmed."""
        self.fire(Event.START, tick)

    def stop(self, tick: int) -> None:
        self.fire(Event.STOP, tick)

    def reset(self, tick: int) -> bool:
        """Explicit reset: clears latched faults (only from FAULTED); torque stays at zero."""
        if self.state is not State.FAULTED:
            return False
        self.fire(Event.RESET, tick)
        self.faults.clear()
        self.active_codes.clear()
        self.applied[:] = 0.0
        self.tdt.reset(self.applied)
        self.ticks.consecutive_misses = 0
        self.ticks.consecutive_send_failures = 0
        return True

    def trip(self, code: FaultCode, detail: str, tick: int) -> Fault | None:
        """Latch a fault and take its stop; a code already latched is not recorded twice."""
        if code in self.active_codes:
            return None
        fault = Fault(code, detail, tick)
        self.faults.append(fault)
        self.active_codes.add(code)
        event = (
            Event.FAULT_IMMEDIATE if fault.category is StopCategory.IMMEDIATE else Event.FAULT_RAMP
        )
        self.fire(event, tick)
        return fault

    # -- the tick -------------------------------------------------------------------------
    def observe(
        self,
        tick: int,
        now_ns: int,
        nodes: Sequence[FingerNode],
        angle: FloatArray,
        tdt: FloatArray,
        missed: int,
        bus_events: Sequence[BusEvent] = (),
    ) -> list[Fault]:
        """Checks that come from the hand: run after the drain, before ``filter``."""
        new: list[Fault] = []
        findings = self.ticks.tick(missed)
        for event in bus_events:
            if event.kind is BusEventKind.BUS_OFF:
                findings.append((FaultCode.BUS_ERROR, f"bus-off ({event.detail})"))
            elif event.kind is BusEventKind.RX_BACKLOG:
                findings.append((FaultCode.RX_BACKLOG, event.detail))
        if (
            self.state is State.ENABLING
            or self.state in ARMED
            or any(node.state == NodeState.ENABLED for node in nodes)
        ):
            # Before the nodes are believed ENABLED, all the while torque flows, and after it
            # until they say they are disabled: the zero ticks before the disable, or a fault's
            # stop. There a second sender's torque was taken by the nodes and the run said
            # completed, its command frames counted and nothing more.
            findings += self.receive_watch.check(tick, nodes)
        if self.state is State.ENABLING:
            faulted = [node for node in nodes if node.state == NodeState.FAULT]
            if faulted:
                # a node in FAULT refuses the enable until a fault reset: said at once and
                # with its bits (an e-stop as ESTOP), not as nodes late to enable at the
                # deadline
                findings += node_faults(faulted)
            elif all(node.state == NodeState.ENABLED and node.feedback_enabled for node in nodes):
                # each node's own Feedback too: any stream's ENABLED had armed the torque
                # for a node whose Feedback said DISABLED on every tick (a forged Heartbeat)
                findings += self._arm(tick, nodes, angle)
            elif tick - self._enabling_since > self.enable_deadline_ticks:
                states = ", ".join(f"node {n.node_id} {n.state_name}" for n in nodes)
                if self.enable_unsent:
                    findings.append(
                        (FaultCode.BUS_ERROR, f"{self.enable_unsent}; at the deadline {states}")
                    )
                else:
                    findings.append((FaultCode.STARTUP, f"nodes not ENABLED in time: {states}"))
        if self.state in ARMED:
            findings += self.node_watch.check(now_ns, nodes, expect_enabled=True)
            findings += self.tdt.update(self.applied, tdt)
            if self.state is not State.FAULT_RAMP:
                self._angle_findings(angle, tick, findings)
        for code, detail in findings:
            fault = self.trip(code, detail, tick)
            if fault is not None:
                new.append(fault)
        return new

    def _arm(
        self, tick: int, nodes: Sequence[FingerNode], angle: FloatArray
    ) -> list[tuple[FaultCode, str]]:
        """The nodes confirmed ENABLED: torque may flow from this tick on."""
        self.fire(Event.ENABLED, tick)
        self.node_watch.arm(nodes)
        self.tdt.reset(self.applied)
        self._armed_tick = tick
        if self.recovery is None:
            return []
        j = self.recovery.joint
        refused = self.recovery.arm(float(angle[j]), self.limits)
        if refused is None:
            self.recovery.rest(angle.tolist(), self.limits)
        return [] if refused is None else [(FaultCode.ANGLE_LIMIT, refused)]

    def _angle_findings(
        self, angle: FloatArray, tick: int, findings: list[tuple[FaultCode, str]]
    ) -> None:
        """The soft limits, and a recovering joint's ratchet instead of its own limits, added
        to ``findings`` (the tick's own list: no list of its own every tick)."""
        outside = angle_violations(angle, self.limits)
        recovery = self.recovery
        if recovery is not None and recovery.active:
            j = recovery.joint
            beyond = recovery.check(float(angle[j]), tick, self.limits)
            if j in outside:
                outside.remove(j)
            if beyond is not None:
                findings.append((FaultCode.ANGLE_LIMIT, beyond))
        if recovery is not None and recovery.resting:
            for k in list(recovery.resting):
                beyond = recovery.check_resting(k, float(angle[k]), self.limits)
                if k in outside:
                    outside.remove(k)
                if beyond is not None:
                    findings.append((FaultCode.ANGLE_LIMIT, beyond))
        stopping = self.state is State.STOPPING
        for j in outside:
            if stopping and not self._pushes_out(j, angle):
                self._left_while_stopping(j, angle, tick)
            else:
                findings.append((FaultCode.ANGLE_LIMIT, self._outside(j, angle, tick)))

    def _pushes_out(self, j: int, angle: FloatArray) -> bool:
        """Whether joint ``j``'s applied torque pushes it further out of its soft limits."""
        tau = float(self.applied[j])
        return tau > 0.0 if angle[j] > self.limits.angle_max[j] else tau < 0.0

    def _left_while_stopping(self, j: int, angle: FloatArray, tick: int) -> None:
        """A joint that leaves its soft limits while a controlled stop ramps the torques out,
        its own torque not pushing it out: said, once per joint, and not a fault.

        Why not ``ANGLE_LIMIT``: the limit is there so that torque never drives a joint into
        its hard stop, and a fault's answer is torque to zero, which the stop is already
        doing. A joint that sinks out as its torque goes (gravity, a finger it leaned on) is
        the hand coming to rest with no torque, as it would after any run; as a fault it
        turned a Ctrl-C or a time budget into a safety stop (exit 3) for the stop itself. A
        joint whose own torque still pushes it out is a fault as ever, and its faster ramp
        takes the torque out sooner."""
        if j in self._said_in_stop:
            return
        self._said_in_stop.add(j)
        self.stop_notes.append(
            f"{self._outside(j, angle, tick)} at tick {tick}, while the torques were ramped "
            "out for the stop, its own torque not pushing it out: not a fault"
        )

    def _outside(self, j: int, angle: FloatArray, tick: int) -> str:
        # outside before any torque flowed (the armed tick): the message says how to recover
        return outside_text(j, angle, self.limits, tick == self._armed_tick)

    def filter(
        self, tick: int, desired: Sequence[float] | FloatArray | None, missed: int = 0
    ) -> AppliedTorques:
        """The applied torques of this tick (a view the caller must not keep across ticks)."""
        self.refused = None
        return AppliedTorques(self._filter(tick, desired, missed))

    def _filter(
        self, tick: int, desired: Sequence[float] | FloatArray | None, missed: int
    ) -> FloatArray:
        state = self.state
        if state is State.RUNNING:
            problem = (
                check_desired(desired, self.n, self.limits.names) if desired is not None else None
            )
            if desired is None:
                target = self.applied  # nothing asked: hold
            elif problem is not None:
                self.refused = problem[0]
                self.trip(problem[0], problem[1], tick)
                return self._filter(tick, None, missed)
            else:
                target = np.asarray(desired, dtype=np.float64)
            np.copyto(self._held, self.applied)
            self._held_tick = tick
            if missed > 0:
                # A late tick repeats the last applied command once, rather than stepping the
                # rate limiter over an interval it did not see.
                return self.applied
            # Straight into ``applied``: the limiter reads the last applied torques first.
            self.limited_joints = limit_torque(
                target, self.applied, self.limits, self.dt, self.applied
            )
        elif state is State.STOPPING:
            # and no later than the line from where the stop began to zero at STOP_BOUND_S:
            # the rate limit alone may take a slow-limited hand seconds to let go
            self._stop_k += 1
            self._towards_zero(self._stop_from, self._stop_k / self._stop_ticks, tick)
        elif state is State.FAULT_RAMP:
            # as a stop goes, and no later than the line to zero at RAMP_BOUND_S. The line
            # alone was slower than the rate limit on every shipped hand: a joint past its
            # soft limit kept its outward torque 50 ms and went 0.35 rad past the limit (an
            # outside audit), where the stop the fault replaced would have let go in 15
            self._ramp_k += 1
            self._towards_zero(self._ramp_from, self._ramp_k / self._ramp_ticks, tick)
        else:
            self.applied[:] = 0.0
        return self.applied

    def _towards_zero(self, start: FloatArray, done: float, tick: int) -> None:
        """One tick of a stop or a fault's ramp: ``applied`` towards zero at the rate limit,
        and no further from it than the line from ``start`` to zero, ``done`` of the way
        along it (so it is zero by the line's end); AT_ZERO once every joint is there."""
        limit_torque(self._zero, self.applied, self.limits, self.dt, self.applied)
        line = start * max(0.0, 1.0 - done)
        np.copyto(self.applied, line, where=np.abs(line) < np.abs(self.applied))
        toward_zero_on_grid(self.applied, self.limits)
        if not self.applied.any():
            self.fire(Event.AT_ZERO, tick)

    def sent(self, ok: bool, tick: int, unsent: BoolArray | None = None) -> None:
        """Tell the supervisor whether this tick's command frames went out, and (``unsent``,
        per joint) which did not.

        A joint whose frame did not go keeps, in ``applied``, the torque its node still
        holds: the rate limit then steps the next frame from it. Before, the limiter went on
        from the torque that never left the host, and after k frames refused in a row the
        node took k + 1 rate steps in one frame (3 at the default
        ``max_consecutive_send_failures``, up to 100 where a hand config raised it; found by
        an outside audit). Only where this tick's filter ran the hand (``_held_tick``): a
        stop's or a fault's ramp goes towards zero, where a larger step is a smaller torque,
        and its end must not wait on a frame the stop sends again anyway.
        """
        if not ok and unsent is not None and self._held_tick == tick:
            np.copyto(self.applied, self._held, where=unsent)
        for code, detail in self.ticks.sent(ok):
            self.trip(code, detail, tick)

    @property
    def torque_allowed(self) -> bool:
        return self.state in ARMED
