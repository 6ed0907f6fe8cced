"""Hypothesis: the supervisor's table and limiter hold whatever the inputs and event order."""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from handctl.config import HandConfig, load_hand
from handctl.hand_protocol import protocol_for
from handctl.online.safety.faults import FaultCode
from handctl.online.safety.supervisor import TRANSITIONS, Event, State, Supervisor, next_state

from ..conftest import HAND_YAML

HAND: HandConfig = load_hand(HAND_YAML)
TAU_MAX = np.array([j.tau_max for j in HAND.joints])
STEP = np.array([j.rate_limit for j in HAND.joints]) * HAND.bus.period_s

torque = st.one_of(st.floats(-10, 10), st.sampled_from([np.nan, np.inf, -np.inf, 0.0]))
desired = st.one_of(
    st.lists(torque, min_size=9, max_size=9),
    st.lists(st.floats(-1, 1), min_size=0, max_size=12),
    st.none(),
)
action = st.one_of(
    st.tuples(st.just("tick"), desired, st.integers(0, 2)),
    st.tuples(st.just("start")),
    st.tuples(st.just("stop")),
    st.tuples(st.just("reset")),
    st.tuples(st.just("enabled")),
    st.tuples(st.just("fault"), st.sampled_from(list(FaultCode))),
)


@settings(max_examples=300, deadline=None)
@given(st.lists(action, max_size=120))
def test_supervisor_invariants(actions: list[tuple[Any, ...]]) -> None:
    sup = Supervisor(HAND)
    previous = np.zeros(9)
    for k, act in enumerate(actions):
        before = sup.state
        kind = act[0]
        if kind == "tick":
            applied = sup.filter(k, act[1], act[2]).copy()
            assert applied.shape == (9,)
            assert np.all(np.isfinite(applied))
            assert np.all(np.abs(applied) <= TAU_MAX + 1e-12)
            if before is State.RUNNING:
                assert np.all(np.abs(applied - previous) <= STEP + 1e-12)
            if before in (State.IDLE, State.ENABLING, State.FAULTED):
                assert not applied.any()
            previous = applied
        elif kind == "start":
            sup.start(k)
        elif kind == "stop":
            sup.stop(k)
        elif kind == "reset":
            sup.reset(k)
        elif kind == "enabled":
            sup.fire(Event.ENABLED, k)
        else:
            sup.trip(act[1], "injected", k)
        if before is State.FAULTED and kind != "reset":
            assert sup.state is State.FAULTED, f"left FAULTED on {act}"
        if sup.state is State.FAULTED:
            assert sup.faults, "FAULTED without a latched fault"


def test_table_only_reset_leaves_faulted() -> None:
    for event in Event:
        after = next_state(State.FAULTED, event)
        assert after is (State.IDLE if event is Event.RESET else State.FAULTED)


def test_every_state_can_reach_faulted_and_faults_never_lead_to_torque() -> None:
    for state in State:
        assert next_state(state, Event.FAULT_IMMEDIATE) is State.FAULTED or state is State.FAULTED
    torque_states = {State.RUNNING}
    for (_, event), after in TRANSITIONS.items():
        if event in (Event.FAULT_IMMEDIATE, Event.FAULT_RAMP):
            assert after not in torque_states


def running(torque: np.ndarray | None = None, ticks: int = 100) -> Supervisor:
    """A supervisor through start and enable, holding ``torque`` after ``ticks`` ticks."""
    sup = Supervisor(HAND)
    sup.start(0)
    sup.fire(Event.ENABLED, 0)
    for k in range(1, ticks):
        sup.filter(k, TAU_MAX * 0.5 if torque is None else torque)
    return sup


def test_ramp_stop_reaches_zero_within_the_bound() -> None:
    from handctl.online.safety.faults import RAMP_BOUND_S

    sup = Supervisor(HAND)
    sup.start(0)
    sup.fire(Event.ENABLED, 0)
    target = TAU_MAX * 0.9
    k = 0
    for k in range(1, 200):
        sup.filter(k, target)
    assert np.allclose(sup.applied, target)
    sup.trip(FaultCode.TDT_MISMATCH, "test", k)
    assert sup.state is State.FAULT_RAMP
    ticks = 0
    last = sup.applied.copy()
    while sup.state is State.FAULT_RAMP:
        ticks += 1
        out = sup.filter(k + ticks, target)
        assert np.all(np.abs(out) <= np.abs(last) + 1e-12)  # monotone towards zero
        last = out.copy()
    assert not sup.applied.any()
    assert ticks * HAND.bus.period_s <= RAMP_BOUND_S + 1e-9


def test_immediate_fault_zeroes_the_same_tick() -> None:
    sup = running()
    sup.trip(FaultCode.FEEDBACK_TIMEOUT, "test", 100)
    assert not sup.filter(100, TAU_MAX * 0.5).any()


def test_non_finite_desired_is_a_fault_not_a_clamp() -> None:
    sup = running(np.full(9, 0.1), ticks=2)
    bad = np.full(9, 0.1)
    bad[4] = np.nan
    out = sup.filter(2, bad)
    assert not out.any()
    assert sup.state is State.FAULTED
    assert sup.faults[0].code is FaultCode.NON_FINITE_TORQUE
    assert sup.filter(3, np.full(9, 0.1)).sum() == 0


def test_reset_restarts_from_zero_through_the_rate_limit() -> None:
    sup = running()
    sup.trip(FaultCode.ESTOP, "test", 100)
    assert sup.reset(100)
    assert sup.state is State.IDLE and not sup.faults
    assert not sup.filter(101, TAU_MAX).any()  # IDLE: nothing until START
    sup.start(102)
    sup.fire(Event.ENABLED, 102)
    out = sup.filter(103, TAU_MAX)
    assert np.allclose(out, STEP)  # the first step after reset is one rate step from zero


def test_fault_page_is_generated_from_the_table() -> None:
    import subprocess
    import sys

    from ..conftest import ROOT

    done = subprocess.run(
        [sys.executable, "tools/gen_fault_table.py", "--check"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )
    assert done.returncode == 0, done.stderr
    page = (ROOT / "docs" / "faults.md").read_text()
    for code in FaultCode:
        assert f"`{code.name}`" in page


def _with_limits(hand: HandConfig, tau_max: float, rate_limit: float) -> HandConfig:
    fingers = tuple(
        dataclasses.replace(
            f,
            joints=tuple(
                dataclasses.replace(j, tau_max=tau_max, rate_limit=rate_limit) for j in f.joints
            ),
        )
        for f in hand.fingers
    )
    return dataclasses.replace(hand, fingers=fingers)


@settings(max_examples=150, deadline=None)
@given(
    # limits that are no multiple of the command signal's 0.0001 N·m, as a config may write
    st.floats(0.01, 0.6),
    st.floats(0.1, 3.0),
    st.lists(st.lists(st.floats(-1, 1), min_size=9, max_size=9), min_size=1, max_size=40),
    st.integers(0, 40),
    st.sampled_from([None, FaultCode.TDT_MISMATCH]),
)
def test_what_the_command_frames_carry_keeps_both_limits(
    tau: float, rate: float, asked: list[list[float]], stop_at: int, fault: FaultCode | None
) -> None:
    """The frames, not only the supervisor's floats: rounded to the signal's resolution by
    the encoder, a torque must still be within tau_max and a step within the rate limit
    (a stop or a fault's ramp towards zero included), and the applied torque the log records
    must be what the frame says."""
    hand = _with_limits(HAND, tau, rate)
    protocol = protocol_for(hand)
    layouts = [protocol.layout("TorqueCommand", f.node_id) for f in hand.fingers]
    sup = Supervisor(hand, protocol)
    sup.start(0)
    sup.fire(Event.ENABLED, 0)
    step = rate * hand.bus.period_s
    previous = np.zeros(9)
    plan = asked + [asked[-1]] * 60
    for k, want in enumerate(plan, start=1):
        if k == stop_at:
            if fault is None:
                sup.stop(k)
            else:
                sup.trip(fault, "injected", k)
        applied = sup.filter(k, np.array(want))
        carried = np.concatenate(
            [
                layout.decode(layout.encode(k % 256, applied[3 * i : 3 * i + 3].tolist()))[1][:3]
                for i, layout in enumerate(layouts)
            ]
        )
        assert carried == pytest.approx(applied, abs=1e-12), "the log differs from the frame"
        assert np.all(np.abs(carried) <= tau + 1e-12)
        moved = np.abs(carried - previous)
        toward_zero = np.abs(carried) < np.abs(previous)
        if sup.state is State.RUNNING or fault is None:
            assert np.all(moved <= step + 1e-12)
        else:
            assert np.all((moved <= step + 1e-12) | toward_zero)
        previous = carried
