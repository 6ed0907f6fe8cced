# mypy: disable-error-code="comparison-overlap"
# (each assert reads the supervisor's state anew after a call; mypy keeps the narrowing of the
# assert before it)
"""The supervisor's torque paths one at a time: start, the fault ramp, the stop, the reset.

The supervisor is built from the hand config and brought to RUNNING the way the runtime does
it: the host enables the simulated nodes, and ``observe`` sees every one report ENABLED. The
expected torques are derived from the config's limits (tau_max, rate limit, period) and from
``RAMP_BOUND_S``, tick by tick.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
import pytest

from handctl.config import HandConfig
from handctl.online.bus import BusEvent, BusEventKind
from handctl.online.safety.faults import (
    FAULTS,
    RAMP_BOUND_S,
    STOP_BOUND_S,
    Fault,
    FaultCode,
    StopCategory,
)
from handctl.online.safety.supervisor import Event, State, Supervisor
from handctl.protocol import Protocol

from .node_pair import Link

RAMP_CODES = [code for code, spec in FAULTS.items() if spec.category is StopCategory.RAMP]
IMMEDIATE_CODES = [code for code, spec in FAULTS.items() if spec.category is StopCategory.IMMEDIATE]


@dataclass
class Running:
    """A supervisor in RUNNING over live simulated nodes, and the tick it got there."""

    sup: Supervisor
    link: Link
    tick: int

    def observe(
        self,
        angle: np.ndarray | None = None,
        tdt: np.ndarray | None = None,
        missed: int = 0,
        events: tuple[BusEvent, ...] = (),
    ) -> list[Fault]:
        """One more tick of the nodes, and the supervisor's checks of what they said."""
        n = self.sup.n
        self.tick += 1
        now = self.link.tick()
        return self.sup.observe(
            self.tick,
            now,
            self.link.hosts,
            np.zeros(n) if angle is None else angle,
            np.zeros(n) if tdt is None else tdt,
            missed,
            events,
        )


def tau_max(hand: HandConfig) -> np.ndarray:
    return np.array([j.tau_max for j in hand.joints])


def rate_step(hand: HandConfig) -> np.ndarray:
    return np.array([j.rate_limit for j in hand.joints]) * hand.bus.period_s


def ramp_ticks(hand: HandConfig) -> int:
    """The fault ramp's length: as many whole ticks as fit in RAMP_BOUND_S, and at least one."""
    return max(1, math.floor(RAMP_BOUND_S / hand.bus.period_s + 1e-9))


def bring_up(hand: HandConfig, protocol: Protocol) -> Running:
    """A supervisor for ``hand`` brought to RUNNING over live simulated nodes."""
    sup = Supervisor(hand)
    link = Link(hand, protocol)
    link.enable()
    sup.start(0)
    assert sup.state is State.ENABLING
    assert not sup.filter(0, tau_max(hand)).any()  # nothing before the nodes confirm
    assert sup.observe(1, link.tick(), link.hosts, np.zeros(sup.n), np.zeros(sup.n), 0) == []
    assert sup.state is State.RUNNING
    assert sup.history == [
        (0, State.IDLE, Event.START, State.ENABLING),
        (1, State.ENABLING, Event.ENABLED, State.RUNNING),
    ]
    return Running(sup, link, 1)


@pytest.fixture
def running(hand: HandConfig, protocol: Protocol) -> Running:
    return bring_up(hand, protocol)


def hold(run: Running, torque: np.ndarray) -> np.ndarray:
    """Ask for ``torque`` until the rate limiter has delivered it; returns the applied torque."""
    for _ in range(1000):
        run.tick += 1
        applied = run.sup.filter(run.tick, torque).copy()
        if np.array_equal(applied, torque):
            return applied
    raise AssertionError(f"never reached {torque}")


def signed_torque(hand: HandConfig) -> np.ndarray:
    """Torques of both signs and different sizes, each within its joint's tau_max."""
    signs = np.where(np.arange(hand.n_joints) % 2 == 0, 1.0, -1.0)
    return tau_max(hand) * signs * np.linspace(0.9, 0.5, hand.n_joints)


def test_start_ramps_up_by_one_rate_step_a_tick_to_the_clamp(
    hand: HandConfig, running: Running
) -> None:
    sup, top, step = running.sup, tau_max(hand), rate_step(hand)
    expected = np.zeros(hand.n_joints)
    for k in range(1, math.ceil(float(np.max(top / step))) + 3):
        applied = sup.filter(running.tick + k, 2 * top)
        expected = np.minimum(expected + step, top)
        assert applied == pytest.approx(expected, abs=1e-12), f"tick {k}"
        assert sup.limited_joints == hand.n_joints
    assert applied.tolist() == top.tolist()


def test_holding_torque_is_not_limited(hand: HandConfig, running: Running) -> None:
    target = hold(running, signed_torque(hand))
    assert running.sup.filter(running.tick + 1, target).tolist() == target.tolist()
    assert running.sup.limited_joints == 0
    # Nothing asked (None) holds the last applied torque.
    assert running.sup.filter(running.tick + 2, None).tolist() == target.tolist()


def test_a_late_tick_repeats_the_last_command_without_a_rate_step(
    hand: HandConfig, running: Running
) -> None:
    sup = running.sup
    first = sup.filter(running.tick + 1, tau_max(hand)).copy()
    assert sup.filter(running.tick + 2, tau_max(hand), missed=1).tolist() == first.tolist()
    assert sup.filter(running.tick + 3, tau_max(hand)) == pytest.approx(2 * first)


def _slow_rated(hand: HandConfig) -> HandConfig:
    """``hand`` with every rate limit so slow that the fault ramp's line to zero at
    RAMP_BOUND_S is the faster of the two: the line shows."""
    joints = [replace(j, rate_limit=j.tau_max / (4 * RAMP_BOUND_S)) for j in hand.joints]
    it = iter(joints)
    fingers = tuple(replace(f, joints=tuple(next(it) for _ in f.joints)) for f in hand.fingers)
    return replace(hand, fingers=fingers)


@pytest.mark.parametrize("slow", [False, True], ids=["rate-limit", "line"])
@pytest.mark.parametrize("code", RAMP_CODES)
def test_a_ramp_fault_goes_to_zero_at_the_rate_limit_or_by_the_bound_whichever_is_sooner(
    hand: HandConfig, protocol: Protocol, code: FaultCode, slow: bool
) -> None:
    """A ramp fault is never slower than a controlled stop: each joint goes to zero at its
    rate limit, or along the line from where the fault began to zero at RAMP_BOUND_S where
    that is sooner. The line alone was slower than the rate limit on every shipped hand: a
    joint past its soft limit kept its outward torque 50 ms, 35 ticks longer than the stop
    the fault replaced, and went 0.35 rad past the limit (found by an outside audit)."""
    hand = _slow_rated(hand) if slow else hand
    running = bring_up(hand, protocol)
    sup = running.sup
    start = hold(running, signed_torque(hand))
    tick = running.tick + 1
    assert sup.trip(code, "test", tick) == Fault(code, "test", tick)
    assert sup.state is State.FAULT_RAMP
    assert sup.history[-1] == (tick, State.RUNNING, Event.FAULT_RAMP, State.FAULT_RAMP)
    assert sup.torque_allowed  # the nodes stay enabled through the ramp
    n = ramp_ticks(hand)
    grid = np.array(sup.limits.step_list)
    step = rate_step(hand)
    previous = start
    k = 0
    while sup.state is State.FAULT_RAMP:
        k += 1
        assert k <= n, "past the ramp bound"
        out = sup.filter(tick + k, 2 * tau_max(hand)).copy()  # what is asked no longer matters
        # the sooner of the two, on the command grid towards zero: never more than either,
        # by less than one resolution less
        soonest = np.minimum(np.abs(start) * (1 - k / n), np.abs(previous) - step)
        soonest = np.maximum(soonest, 0.0)
        short = soonest - np.abs(out)
        assert np.all((out == 0) | (np.sign(out) == np.sign(start))), f"ramp tick {k}"
        assert np.all((short > -1e-12) & (short < grid + 1e-12)), f"ramp tick {k}"
        assert np.allclose(out / grid, np.round(out / grid), atol=1e-9, rtol=0.0)
        previous = out
    assert not previous.any()
    assert sup.state is State.FAULTED
    assert sup.history[-1] == (tick + k, State.FAULT_RAMP, Event.AT_ZERO, State.FAULTED)
    # the rate limit sets the pace on the shipped hand (30 ms from tau_max), the line on a
    # slow one (every tick of the bound)
    fastest = math.ceil(float(np.max(np.abs(start) / step)) - 1e-9)
    assert k == (n if slow else fastest), (k, n, fastest)
    assert not sup.filter(tick + k + 1, tau_max(hand)).any()


def test_the_ramp_fits_the_bound(hand: HandConfig) -> None:
    assert ramp_ticks(hand) * hand.bus.period_s <= RAMP_BOUND_S + 1e-12
    assert ramp_ticks(hand) > 1


def test_a_loop_slower_than_the_ramp_bound_ramps_in_one_tick(hand: HandConfig) -> None:
    slow = replace(hand, bus=replace(hand.bus, loop_rate_hz=0.5 / RAMP_BOUND_S))
    sup = Supervisor(slow)
    sup.start(0)
    sup.fire(Event.ENABLED, 0)
    torque = sup.filter(1, tau_max(slow)).copy()
    assert torque.all()
    sup.trip(FaultCode.ANGLE_LIMIT, "test", 2)
    assert sup.state is State.FAULT_RAMP
    assert not sup.filter(2, None).any()
    assert sup.state is State.FAULTED


def test_a_fault_during_a_stop_ramps_from_where_the_stop_had_got(
    hand: HandConfig, running: Running
) -> None:
    sup = running.sup
    hold(running, tau_max(hand))
    tick = running.tick + 1
    sup.stop(tick)
    partly = sup.filter(tick + 1, None).copy()
    assert partly == pytest.approx(tau_max(hand) - rate_step(hand))
    sup.trip(FaultCode.TDT_MISMATCH, "test", tick + 2)
    assert sup.state is State.FAULT_RAMP
    # on from there, at the rate limit (as the stop went: no slower for the fault)
    assert sup.filter(tick + 3, None) == pytest.approx(partly - rate_step(hand))
    # and from where it had got, if the line to zero at the bound is the sooner
    slow = Supervisor(_slow_rated(hand))
    slow.start(0)
    slow.fire(Event.ENABLED, 0)
    for k in range(1, 1000):
        if np.array_equal(slow.filter(k, tau_max(hand)), tau_max(hand)):
            break
    slow.stop(k + 1)
    partly = slow.filter(k + 2, None).copy()
    slow_step = np.array(slow.limits.rate_list) * slow.dt  # on the command grid, below it
    assert partly == pytest.approx(tau_max(hand) - slow_step, abs=1e-4)
    slow.trip(FaultCode.TDT_MISMATCH, "test", k + 3)
    n = ramp_ticks(hand)
    assert slow.filter(k + 4, None) == pytest.approx(partly * (1 - 1 / n), abs=1e-4)


@pytest.mark.parametrize("code", IMMEDIATE_CODES)
def test_an_immediate_fault_zeroes_the_same_tick_even_mid_ramp(
    hand: HandConfig, running: Running, code: FaultCode
) -> None:
    sup = running.sup
    hold(running, signed_torque(hand))
    tick = running.tick + 1
    sup.trip(FaultCode.ANGLE_LIMIT, "test", tick)
    assert sup.filter(tick, None).any()
    sup.trip(code, "test", tick + 1)
    assert sup.state is State.FAULTED
    assert not sup.filter(tick + 1, signed_torque(hand)).any()
    assert [f.code for f in sup.faults] == [FaultCode.ANGLE_LIMIT, code]


def test_a_stop_rate_limits_to_zero_and_is_idle_exactly_when_torque_is_zero(
    hand: HandConfig, running: Running
) -> None:
    sup, step = running.sup, rate_step(hand)
    previous = hold(running, signed_torque(hand))
    tick = running.tick + 1
    sup.stop(tick)
    assert sup.state is State.STOPPING
    longest = math.ceil(float(np.max(np.abs(previous) / step))) + 1
    k = 0
    while sup.state is State.STOPPING:
        k += 1
        assert k <= longest, "the stop never ends"
        out = sup.filter(tick + k, 2 * tau_max(hand)).copy()  # a stop ignores what is asked
        expected = np.sign(previous) * np.maximum(np.abs(previous) - step, 0.0)
        assert out == pytest.approx(expected, abs=1e-12), f"stop tick {k}"
        if out.any():
            assert sup.state is State.STOPPING, f"idle with torque {out} at tick {k}"
        previous = out
    assert sup.state is State.IDLE
    assert previous.tolist() == [0.0] * hand.n_joints
    assert sup.history[-1] == (tick + k, State.STOPPING, Event.AT_ZERO, State.IDLE)
    assert not sup.torque_allowed
    assert not sup.filter(tick + k + 1, tau_max(hand)).any()


def test_a_stop_on_a_slow_rate_limit_still_lets_go_within_the_stop_bound(
    hand: HandConfig, protocol: Protocol
) -> None:
    """A rate limit of 0.6 N·m/s would take 0.9 s to bring the largest of these torques
    (0.54 N·m) to zero; the stop is done at STOP_BOUND_S, each joint no later than the line
    from where it began and never slower than its rate limit."""
    slow = replace(
        hand,
        fingers=tuple(
            replace(f, joints=tuple(replace(j, rate_limit=0.6) for j in f.joints))
            for f in hand.fingers
        ),
    )
    run = bring_up(slow, protocol)
    sup = run.sup
    start = hold(run, signed_torque(slow))
    step, grid = rate_step(slow), np.array(sup.limits.step_list)
    stop_ticks = math.floor(STOP_BOUND_S / slow.bus.period_s + 1e-9)
    assert float(np.max(np.abs(start) / step)) > 1.5 * stop_ticks  # the bound is what binds
    tick = 10_000
    sup.stop(tick)
    previous, k = start, 0
    while sup.state is State.STOPPING:
        k += 1
        assert k <= stop_ticks, "the stop outlasts its bound"
        out = sup.filter(tick + k, tau_max(slow)).copy()
        line = np.abs(start) * max(0.0, 1.0 - k / stop_ticks)
        rate_limited = np.maximum(np.abs(previous) - step, 0.0)
        assert np.all(np.sign(out) * np.sign(start) >= 0), f"stop tick {k}: past zero"
        # the nearer zero of the two, on the command grid towards zero
        assert np.abs(out) == pytest.approx(
            np.floor(np.minimum(line, rate_limited) / grid + 1e-9) * grid, abs=1e-12
        ), f"stop tick {k}"
        previous = out
    assert k == stop_ticks
    assert sup.state is State.IDLE and not previous.any()


def test_a_stop_at_zero_torque_is_idle_on_its_first_tick(
    hand: HandConfig, running: Running
) -> None:
    sup = running.sup
    sup.stop(2)
    assert sup.state is State.STOPPING
    assert not sup.filter(3, tau_max(hand)).any()
    assert sup.state is State.IDLE


def test_a_stop_while_enabling_is_idle_at_once(hand: HandConfig) -> None:
    sup = Supervisor(hand)
    sup.start(0)
    sup.stop(1)
    assert sup.state is State.IDLE
    assert sup.history == [
        (0, State.IDLE, Event.START, State.ENABLING),
        (1, State.ENABLING, Event.STOP, State.IDLE),
    ]


def test_a_fault_latches_once_and_only_reset_leaves_faulted(
    hand: HandConfig, running: Running
) -> None:
    sup = running.sup
    hold(running, signed_torque(hand))
    assert not sup.reset(running.tick)  # nothing to reset while running
    assert sup.state is State.RUNNING
    first = sup.trip(FaultCode.NODE_STATE, "first", 10)
    assert first == Fault(FaultCode.NODE_STATE, "first", 10)
    assert sup.trip(FaultCode.NODE_STATE, "again", 11) is None
    assert sup.faults == [first]
    assert sup.active_codes == {FaultCode.NODE_STATE}
    for _ in range(3):
        sup.start(12)
        sup.stop(12)
        assert sup.state is State.FAULTED
    assert sup.reset(13)
    assert sup.state is State.IDLE
    assert sup.history[-1] == (13, State.FAULTED, Event.RESET, State.IDLE)
    assert sup.faults == [] and sup.active_codes == set()
    assert sup.applied.tolist() == [0.0] * hand.n_joints
    # The same fault can latch again after the reset.
    assert sup.trip(FaultCode.NODE_STATE, "after reset", 14) is not None


def test_after_a_reset_torque_comes_back_only_through_start_from_zero(
    hand: HandConfig, running: Running
) -> None:
    sup = running.sup
    hold(running, tau_max(hand))
    misses = hand.safety.max_consecutive_misses
    failures = hand.safety.max_consecutive_send_failures
    assert running.observe(missed=misses - 1) == []  # late ticks, one short of a fault
    for _ in range(failures):
        sup.sent(False, running.tick)  # the last of these is a BUS_ERROR
    assert sup.state is State.FAULTED
    assert sup.reset(running.tick)
    assert not sup.filter(running.tick + 1, tau_max(hand)).any()  # IDLE: nothing until START
    sup.start(running.tick + 2)
    # The counts of late ticks and failed sends start again from zero at the reset.
    assert (
        sup.observe(
            running.tick + 2,
            running.link.tick(),
            running.link.hosts,
            np.zeros(sup.n),
            np.zeros(sup.n),
            misses - 1,
        )
        == []
    )
    assert sup.state is State.RUNNING
    for _ in range(failures - 1):
        sup.sent(False, running.tick + 2)
    assert sup.state is State.RUNNING
    assert sup.filter(running.tick + 3, tau_max(hand)).tolist() == rate_step(hand).tolist()


def test_a_torque_that_must_be_refused_is_a_fault_at_its_tick(
    hand: HandConfig, running: Running
) -> None:
    sup = running.sup
    hold(running, signed_torque(hand))
    bad = signed_torque(hand)
    bad[3] = np.inf
    assert not sup.filter(running.tick + 1, bad).any()
    assert sup.state is State.FAULTED
    [fault] = sup.faults
    assert (fault.code, fault.tick) == (FaultCode.NON_FINITE_TORQUE, running.tick + 1)
    assert fault.detail.startswith(f"{hand.joint_names[3]}: ") and "inf" in fault.detail


@pytest.mark.parametrize("code", RAMP_CODES)
def test_a_ramp_fault_before_torque_flows_is_faulted_at_once(
    hand: HandConfig, code: FaultCode
) -> None:
    for started in (False, True):
        sup = Supervisor(hand)
        if started:
            sup.start(0)
        sup.trip(code, "test", 1)
        assert sup.state is State.FAULTED


@pytest.mark.parametrize("timeout", [None, 0.0], ids=["hand", "zero"])
def test_nodes_not_enabled_within_the_deadline_are_a_startup_fault(
    hand: HandConfig, protocol: Protocol, timeout: float | None
) -> None:
    if timeout is not None:
        hand = replace(hand, safety=replace(hand.safety, enable_timeout_s=timeout))
    sup = Supervisor(hand)
    link = Link(hand, protocol)  # the nodes are never told to enable
    # A deadline shorter than a tick is one tick: the nodes get one tick to answer.
    deadline = max(1, math.ceil(hand.safety.enable_timeout_s / hand.bus.period_s))
    sup.start(5)
    for tick in range(5, 5 + deadline + 1):
        assert (
            sup.observe(tick, link.tick(), link.hosts, np.zeros(sup.n), np.zeros(sup.n), 0) == []
        ), f"tick {tick}"
        assert sup.state is State.ENABLING
    found = sup.observe(6 + deadline, link.tick(), link.hosts, np.zeros(sup.n), np.zeros(sup.n), 0)
    assert [(f.code, f.tick) for f in found] == [(FaultCode.STARTUP, 6 + deadline)]
    assert found[0].detail == (
        "nodes not ENABLED in time: "
        + ", ".join(f"node {f.node_id} DISABLED" for f in hand.fingers)
    )
    assert sup.state is State.FAULTED


def test_an_enable_that_never_left_the_host_is_the_bus_s_at_the_deadline(
    hand: HandConfig, protocol: Protocol
) -> None:
    """Nodes whose enable the bus refused were never asked: at the deadline it is the bus's
    refusal as the caller says it (``BUS_ERROR``), not nodes late to enable (found by an
    outside audit)."""
    sup = Supervisor(hand)
    link = Link(hand, protocol)
    deadline = sup.enable_deadline_ticks
    sup.start(5)
    sup.enable_unsent = "the bus refused the enable of node 1 (f1)"
    for tick in range(5, 5 + deadline + 1):
        assert sup.observe(tick, link.tick(), link.hosts, np.zeros(sup.n), np.zeros(sup.n), 0) == []
    found = sup.observe(6 + deadline, link.tick(), link.hosts, np.zeros(sup.n), np.zeros(sup.n), 0)
    assert [(f.code, f.detail) for f in found] == [
        (
            FaultCode.BUS_ERROR,
            "the bus refused the enable of node 1 (f1); at the deadline "
            + ", ".join(f"node {f.node_id} DISABLED" for f in hand.fingers),
        )
    ]
    assert sup.state is State.FAULTED


def test_one_node_short_of_enabled_keeps_the_supervisor_enabling(
    hand: HandConfig, protocol: Protocol
) -> None:
    sup = Supervisor(hand)
    link = Link(hand, protocol)
    link.tick()
    for pair in link.pairs[:-1]:
        pair.command("enable", link.now_ns)
    sup.start(0)
    for tick in range(1, 5):
        sup.observe(tick, link.tick(), link.hosts, np.zeros(sup.n), np.zeros(sup.n), 0)
        assert sup.state is State.ENABLING
    assert not sup.torque_allowed


def test_a_joint_past_its_soft_limit_ramps(hand: HandConfig, running: Running) -> None:
    last = hand.n_joints - 1
    angle = np.zeros(hand.n_joints)
    angle[last] = hand.joints[last].angle_max + 0.01
    found = running.observe(angle=angle)
    assert [(f.code, f.tick) for f in found] == [(FaultCode.ANGLE_LIMIT, running.tick)]
    j = hand.joints[last]
    assert found[0].detail == (
        f"{j.name} at {angle[last]:+.3f} rad, limits [{j.angle_min:+.3f}, {j.angle_max:+.3f}]"
    )
    assert running.sup.state is State.FAULT_RAMP


def test_during_a_fault_ramp_the_angle_limit_is_not_checked(
    hand: HandConfig, running: Running
) -> None:
    running.sup.trip(FaultCode.RECIPE_ABORT, "test", running.tick)
    angle = np.array([j.angle_min - 0.01 for j in hand.joints])
    assert running.observe(angle=angle) == []
    assert [f.code for f in running.sup.faults] == [FaultCode.RECIPE_ABORT]


def test_a_node_that_leaves_enabled_while_running_is_a_fault(
    hand: HandConfig, running: Running
) -> None:
    running.link.pairs[1].command("disable", running.link.now_ns)
    found = running.observe()
    assert [f.code for f in found] == [FaultCode.NODE_STATE]
    assert running.sup.state is State.FAULTED


def test_nothing_is_limited_before_anything_is_asked(hand: HandConfig) -> None:
    assert Supervisor(hand).limited_joints == 0


def test_bus_off_is_a_bus_error(hand: HandConfig, running: Running) -> None:
    other = BusEvent(BusEventKind.ERROR_PASSIVE, "passive", 0)
    assert running.observe(events=(other,)) == []
    found = running.observe(events=(other, BusEvent(BusEventKind.BUS_OFF, "can0 off", 0)))
    assert [(f.code, f.detail) for f in found] == [(FaultCode.BUS_ERROR, "bus-off (can0 off)")]
    assert running.sup.state is State.FAULTED


def test_late_ticks_are_counted_through_observe(hand: HandConfig, running: Running) -> None:
    limit = hand.safety.max_consecutive_misses
    assert running.observe(missed=limit - 1) == []
    assert [f.code for f in running.observe(missed=1)] == [FaultCode.LOOP_OVERRUN]


def test_failed_sends_are_counted_through_sent(hand: HandConfig, running: Running) -> None:
    sup = running.sup
    limit = hand.safety.max_consecutive_send_failures
    for k in range(limit - 1):
        sup.sent(False, k)
    sup.sent(True, limit)
    for k in range(limit - 1):
        sup.sent(False, k)
        assert sup.state is State.RUNNING
    sup.sent(False, 99)
    assert sup.faults == [
        Fault(
            FaultCode.BUS_ERROR,
            f"{limit} consecutive ticks with command frames that could not be sent",
            99,
        )
    ]
    assert sup.state is State.FAULTED


def _corrupt_feedback(run: Running, finger: int) -> None:
    """One feedback frame with a broken CRC reaches the host's view of ``finger``."""
    host = run.link.hosts[finger]
    layout = host.layouts.feedback
    joints = (len(layout.signals) - 2) // 2
    good = layout.encode(0, [0.0] * (2 * joints) + [1, 0])
    host.receive(layout.frame_id, bytes((good[0] ^ 0xFF,)) + good[1:], run.link.now_ns)


def test_rejected_frames_at_a_rate_are_a_fault_while_torque_flows(
    hand: HandConfig, running: Running
) -> None:
    limit = hand.safety.max_rejects_in_window
    window = round(hand.safety.reject_window_s / hand.bus.period_s)
    for _ in range(limit):
        _corrupt_feedback(running, 0)
        assert running.observe() == []
    _corrupt_feedback(running, 0)
    finger = hand.fingers[0]
    assert [(f.code, f.detail) for f in running.observe()] == [
        (
            FaultCode.REJECT_RATE,
            f"node {finger.node_id} ({finger.name}): {limit + 1} frames rejected within {window} "
            f"ticks (at most {limit}; so far: crc {limit + 1})",
        )
    ]


def test_rejected_frames_before_start_are_no_fault(hand: HandConfig, protocol: Protocol) -> None:
    """An idle supervisor commands no torque, so it does not judge the frames either: a
    bring-up tool may listen to a hand whose bus is noisy."""
    sup = Supervisor(hand)
    run = Running(sup, Link(hand, protocol), 0)
    for _ in range(3 * hand.safety.max_rejects_in_window):
        _corrupt_feedback(run, 0)
        assert run.observe() == []
    assert sup.state is State.IDLE


@pytest.mark.parametrize("pushing_out", [False, True])
def test_a_joint_sinking_out_of_its_limits_in_a_controlled_stop_is_said_not_a_fault(
    hand: HandConfig, running: Running, pushing_out: bool
) -> None:
    """A stop takes the torque out, and a joint held against gravity sinks: past its soft
    limit that turned a Ctrl-C or a time budget into a safety stop, for the stop itself. A
    joint whose own torque still pushes it out is a fault as ever."""
    sup = running.sup
    j = 1
    torque = np.zeros(hand.n_joints)
    # the joint is pushed towards its lower limit when pushing out, held up against it not
    torque[j] = (-0.5 if pushing_out else 0.5) * hand.joints[j].tau_max
    hold(running, torque)
    sup.stop(running.tick)
    assert sup.state is State.STOPPING
    angle = np.zeros(hand.n_joints)
    angle[j] = hand.joints[j].angle_min - 0.01
    faults = running.observe(angle=angle)
    if pushing_out:
        assert [f.code for f in faults] == [FaultCode.ANGLE_LIMIT]
        assert sup.state is State.FAULT_RAMP
        assert sup.stop_notes == []
        return
    assert faults == [] and sup.state is State.STOPPING
    assert len(sup.stop_notes) == 1
    assert sup.stop_notes[0].startswith(f"{hand.joints[j].name} at ")
    assert "not a fault" in sup.stop_notes[0]
    running.observe(angle=angle)
    assert len(sup.stop_notes) == 1, "said once per joint"
    # the stop goes on to zero
    for _ in range(10_000):
        running.tick += 1
        sup.filter(running.tick, None)
        if sup.state is State.IDLE:
            break
    assert sup.state is State.IDLE and not sup.faults


def test_a_joint_out_of_its_limits_while_running_is_a_fault_whatever_its_torque(
    hand: HandConfig, running: Running
) -> None:
    sup = running.sup
    angle = np.zeros(hand.n_joints)
    angle[0] = hand.joints[0].angle_max + 0.01
    assert [f.code for f in running.observe(angle=angle)] == [FaultCode.ANGLE_LIMIT]
    assert sup.stop_notes == []


def test_a_node_e_stopped_while_being_enabled_is_an_e_stop_at_once(
    hand: HandConfig, protocol: Protocol
) -> None:
    """A node in FAULT refuses the enable until a fault reset: an e-stop during the start-up
    waited for the enable's deadline and was said as nodes not ENABLED in time ("node 1
    FAULT"), never as the e-stop it was."""
    sup = Supervisor(hand)
    link = Link(hand, protocol)
    link.tick()
    sup.start(1)
    for pair in link.pairs:
        pair.command("enable", link.now_ns)
    link.pairs[0].estop(link.now_ns)
    found = sup.observe(2, link.tick(), link.hosts, np.zeros(sup.n), np.zeros(sup.n), 0)
    first = hand.fingers[0]
    assert [(f.code, f.detail) for f in found] == [
        (FaultCode.ESTOP, f"node {first.node_id} ({first.name}) in FAULT (ESTOP)")
    ]
    assert sup.state is State.FAULTED


def test_a_refused_command_leaves_its_joints_at_what_the_node_holds(
    hand: HandConfig, running: Running
) -> None:
    """The frame after k refused ones stepped k + 1 rate steps; a late tick's refused frame
    (which repeats the last command) must leave the joints at that command, not the one
    before it."""
    sup, top, step = running.sup, tau_max(hand), rate_step(hand)
    t = running.tick
    first = sup.filter(t + 1, 2 * top).copy()
    sup.sent(True, t + 1, np.zeros(sup.n, dtype=bool))
    assert first == pytest.approx(step)
    unsent = np.zeros(sup.n, dtype=bool)
    unsent[0] = True
    sup.filter(t + 2, 2 * top)
    sup.sent(False, t + 2, unsent)
    held = sup.applied.copy()
    assert held[0] == first[0]  # node 0's joint holds the first frame
    assert held[1:] == pytest.approx(2 * step[1:])  # the others' frames went
    # a late tick repeats, and every frame of it is refused: still what the nodes hold
    assert sup.filter(t + 3, 2 * top, missed=1).tolist() == held.tolist()
    sup.sent(False, t + 3, np.ones(sup.n, dtype=bool))
    assert sup.applied.tolist() == held.tolist()
    after = sup.filter(t + 4, 2 * top)
    assert after[0] == pytest.approx(2 * step[0])  # one step on from the node's torque
    assert sup.state is State.RUNNING


def test_a_stop_s_refused_frame_does_not_hold_the_ramp_back(
    hand: HandConfig, running: Running
) -> None:
    """The stop steps only towards zero: its ramp goes on whether a frame of it went."""
    sup = running.sup
    target = hold(running, signed_torque(hand))
    sup.stop(running.tick)
    ramped = sup.filter(running.tick + 1, None).copy()
    sup.sent(False, running.tick + 1, np.ones(sup.n, dtype=bool))
    assert sup.applied.tolist() == ramped.tolist()
    assert np.all(np.abs(ramped) <= np.abs(target))
