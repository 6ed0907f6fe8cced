"""A recovery (``handctl jog --recover``) as the supervisor sees it: one joint allowed outside
its soft limits as long as it comes back in, over live emulated nodes.

The supervisor is armed the way the runtime arms it: the nodes are enabled and ``observe`` sees
every one report ENABLED, with the measured angles of that tick.
"""

from __future__ import annotations

import re

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from handctl.config import HandConfig
from handctl.online.safety.faults import Fault, FaultCode
from handctl.online.safety.recovery import RECOVERY_SLACK, Recovery
from handctl.online.safety.supervisor import State, Supervisor
from handctl.protocol import Protocol

from .node_pair import Link

J = 1  # f1_j2: upper limit +2.30 rad, lower −0.90 rad


class Armed:
    """A supervisor armed over live nodes with the angles of the arming tick; ``see`` is one
    more tick with these angles."""

    def __init__(
        self,
        hand: HandConfig,
        protocol: Protocol,
        angle: np.ndarray,
        recovery: Recovery | None,
    ) -> None:
        self.sup = Supervisor(hand)
        self.sup.recovery = recovery
        self.link = Link(hand, protocol)
        self.link.enable()
        self.sup.start(0)
        self.tick = 1
        self.zeros = np.zeros(hand.n_joints)
        self.at_arming = self.sup.observe(
            1, self.link.tick(), self.link.hosts, angle, self.zeros, 0
        )

    def see(self, angle: np.ndarray) -> list[Fault]:
        self.tick += 1
        return self.sup.observe(self.tick, self.link.tick(), self.link.hosts, angle, self.zeros, 0)


def at(hand: HandConfig, q: float, joint: int = J) -> np.ndarray:
    """Every joint mid-range, ``joint`` at ``q``."""
    angle = np.array([(j.angle_min + j.angle_max) / 2 for j in hand.joints])
    angle[joint] = q
    return angle


def test_outside_at_arming_trips_and_says_how_to_recover(
    hand: HandConfig, protocol: Protocol
) -> None:
    top = hand.joints[J].angle_max
    armed = Armed(hand, protocol, at(hand, top + 0.06), None)
    assert [f.code for f in armed.at_arming] == [FaultCode.ANGLE_LIMIT]
    assert "before any torque: bring it back with `handctl jog f1_j2 --torque -X --recover`" in (
        armed.at_arming[0].detail
    )
    low = hand.joints[J].angle_min
    armed = Armed(hand, protocol, at(hand, low - 0.06), None)
    assert "`handctl jog f1_j2 --torque +X --recover`" in armed.at_arming[0].detail
    # every joint outside is named, not the first alone
    angle = at(hand, top + 0.06)
    angle[5] = hand.joints[5].angle_min - 0.02
    armed = Armed(hand, protocol, angle, None)
    detail = armed.at_arming[0].detail
    assert f"({hand.joints[5].name} outside too)" in detail and "then each of the others" in detail


def test_a_joint_coming_back_in_is_let_back(hand: HandConfig, protocol: Protocol) -> None:
    top = hand.joints[J].angle_max
    recovery = Recovery(J, -1)
    armed = Armed(hand, protocol, at(hand, top + 0.06), recovery)
    assert armed.at_arming == [] and armed.sup.state is State.RUNNING
    assert recovery.needed and recovery.active and recovery.start_angle == top + 0.06
    # settling back out on its stop by less than the slack, then coming in
    for q in (top + 0.06 + RECOVERY_SLACK * 0.9, top + 0.04, top + 0.01):
        assert armed.see(at(hand, q)) == []
    assert recovery.active
    assert armed.see(at(hand, top - 0.01)) == []
    assert not recovery.active and recovery.back_tick == armed.tick
    # back inside, the normal check again: out once more is a fault
    found = armed.see(at(hand, top + 0.005))
    assert [f.code for f in found] == [FaultCode.ANGLE_LIMIT]
    assert armed.sup.state is State.FAULT_RAMP


def test_the_ratchet_follows_the_joint_in_and_never_out(
    hand: HandConfig, protocol: Protocol
) -> None:
    low = hand.joints[J].angle_min
    recovery = Recovery(J, +1)
    armed = Armed(hand, protocol, at(hand, low - 0.08), recovery)
    assert armed.at_arming == []
    assert armed.see(at(hand, low - 0.03)) == []  # 0.05 rad on its way in
    # back out by more than the slack from the farthest in it came: refused
    found = armed.see(at(hand, low - 0.03 - RECOVERY_SLACK - 0.002))
    assert [f.code for f in found] == [FaultCode.ANGLE_LIMIT]
    assert "further out than its recovery allows" in found[0].detail
    assert f"{low - 0.03 - RECOVERY_SLACK:+.3f} rad" in found[0].detail


def test_a_torque_pushing_it_further_out_is_refused_at_arming(
    hand: HandConfig, protocol: Protocol
) -> None:
    top = hand.joints[J].angle_max
    armed = Armed(hand, protocol, at(hand, top + 0.05), Recovery(J, +1))
    assert [f.code for f in armed.at_arming] == [FaultCode.ANGLE_LIMIT]
    assert "pushes it further out" in armed.at_arming[0].detail
    assert "(a negative torque)" in armed.at_arming[0].detail
    # tripped as it armed: a ramp from the zero torque of arming, no torque ever flowed
    assert armed.sup.state is State.FAULT_RAMP
    assert not armed.sup.filter(armed.tick, np.full(hand.n_joints, 0.1)).any()


def test_the_way_out_is_refused_from_either_side_naming_the_limit(
    hand: HandConfig, protocol: Protocol
) -> None:
    spec = hand.joints[J]
    below = Armed(hand, protocol, at(hand, spec.angle_min - 0.05), Recovery(J, -1))
    assert below.at_arming[0].detail == (
        f"f1_j2 at {spec.angle_min - 0.05:+.3f} rad, below its lower limit "
        f"{spec.angle_min:+.3f} rad: its recovery must push it back in (a positive torque), "
        "and the one asked for pushes it further out"
    )
    above = Armed(hand, protocol, at(hand, spec.angle_max + 0.05), Recovery(J, +1))
    assert f"above its upper limit {spec.angle_max:+.3f} rad" in above.at_arming[0].detail


def test_on_a_limit_is_inside(hand: HandConfig, protocol: Protocol) -> None:
    """As the soft-limit check has it: only beyond a limit is outside."""
    spec = hand.joints[J]
    for q, direction in ((spec.angle_max, -1), (spec.angle_min, +1)):
        recovery = Recovery(J, direction)
        armed = Armed(hand, protocol, at(hand, q), recovery)
        assert armed.at_arming == [] and recovery.needed is False
    for q, direction in ((spec.angle_max, -1), (spec.angle_min, +1)):
        recovery = Recovery(J, direction)
        armed = Armed(hand, protocol, at(hand, q - direction * 0.05), recovery)
        assert recovery.active
        assert armed.see(at(hand, q)) == [] and recovery.back_tick == armed.tick


@pytest.mark.parametrize("direction", [-1, +1])
def test_the_ratchet_holds_exactly_at_its_bound_and_not_beyond(
    hand: HandConfig, protocol: Protocol, direction: int
) -> None:
    spec = hand.joints[J]
    limit = spec.angle_max if direction < 0 else spec.angle_min
    out = -direction  # the way out
    farthest_in = limit + out * 0.03
    recovery = Recovery(J, direction)
    armed = Armed(hand, protocol, at(hand, limit + out * 0.08), recovery)
    assert armed.see(at(hand, farthest_in)) == []
    bound = recovery.bound
    assert bound == farthest_in + out * RECOVERY_SLACK
    assert armed.see(at(hand, bound)) == []  # on the bound: let be
    found = armed.see(at(hand, bound + out * 0.001))
    assert [f.code for f in found] == [FaultCode.ANGLE_LIMIT]
    assert found[0].detail == (
        f"f1_j2 at {bound + out * 0.001:+.3f} rad, further out than its recovery allows "
        f"({bound:+.3f} rad, {RECOVERY_SLACK:g} rad beyond the farthest in it came; "
        f"limits [{spec.angle_min:+.3f}, {spec.angle_max:+.3f}])"
    )


def test_the_other_joints_resting_outside_stay_where_they_rest(
    hand: HandConfig, protocol: Protocol
) -> None:
    """A hand left at zero torque sags several distal joints past their limits at once, and
    each one's recovery was refused for the others: a joint already resting outside when
    torque is first allowed is held to the ratchet from where it rests."""
    top = hand.joints[J].angle_max
    angle = at(hand, top + 0.05)
    other = 5
    rest = hand.joints[other].angle_max + 0.01
    angle[other] = rest
    recovery = Recovery(J, -1)
    armed = Armed(hand, protocol, angle, recovery)
    assert armed.at_arming == [] and set(recovery.resting) == {other}
    angle[other] = rest + 0.015  # within the slack
    assert armed.see(angle) == []
    angle[other] = rest + 0.03  # further out than it rested: as any joint out
    (fault,) = armed.see(angle)
    assert fault.code is FaultCode.ANGLE_LIMIT
    assert fault.detail.startswith(f"{hand.joints[other].name} at ")
    assert "further out than it rested" in fault.detail


def test_a_resting_joint_back_inside_is_checked_as_any_other(
    hand: HandConfig, protocol: Protocol
) -> None:
    top = hand.joints[J].angle_max
    angle = at(hand, top + 0.05)
    other = 5
    angle[other] = hand.joints[other].angle_max + 0.01
    recovery = Recovery(J, -1)
    armed = Armed(hand, protocol, angle, recovery)
    angle[other] = hand.joints[other].angle_max - 0.01
    assert armed.see(angle) == [] and recovery.resting == {}
    angle[other] = hand.joints[other].angle_max + 0.005
    assert [f.code for f in armed.see(angle)] == [FaultCode.ANGLE_LIMIT]


def test_a_joint_inside_at_arming_may_not_go_out(hand: HandConfig, protocol: Protocol) -> None:
    top = hand.joints[J].angle_max
    angle = at(hand, top + 0.05)
    armed = Armed(hand, protocol, angle, Recovery(J, -1))
    other = 5
    angle[other] = hand.joints[other].angle_max + 0.001
    assert [f.code for f in armed.see(angle)] == [FaultCode.ANGLE_LIMIT]


def test_a_joint_inside_at_arming_needs_no_recovery(hand: HandConfig, protocol: Protocol) -> None:
    top = hand.joints[J].angle_max
    recovery = Recovery(J, -1)
    armed = Armed(hand, protocol, at(hand, top - 0.2), recovery)
    assert armed.at_arming == [] and not recovery.needed and not recovery.active
    assert [f.code for f in armed.see(at(hand, top + 0.01))] == [FaultCode.ANGLE_LIMIT]


def test_a_direction_is_up_or_down() -> None:
    with pytest.raises(ValueError, match="recovery direction"):
        Recovery(J, 0)


@settings(max_examples=200, deadline=None)
@given(st.lists(st.floats(-0.2, 0.2), min_size=1, max_size=40))
def test_no_angle_goes_unchecked_further_out_than_the_ratchet(steps: list[float]) -> None:
    """Whatever the joint does, while the supervisor lets it be outside, it never is more than
    the slack beyond the farthest in it came; inside its limits it is always let be."""
    from handctl.config import load_hand
    from handctl.protocol import load_protocol

    from ..conftest import HAND_YAML

    hand, protocol = load_hand(HAND_YAML), load_protocol()
    top = hand.joints[J].angle_max
    q = top + 0.08
    armed = Armed(hand, protocol, at(hand, q), Recovery(J, -1))
    farthest_in = q
    back = False
    for step in steps:
        q = min(q + step, top + 0.1)  # the mechanical stop
        found = armed.see(at(hand, q))
        if back:
            assert bool(found) == (q > top)
        elif q <= top:
            assert found == []
            back = True
        else:
            assert bool(found) == (q > farthest_in + RECOVERY_SLACK)
        if found:
            return
        farthest_in = min(farthest_in, q)


def _angle_and_bound(detail: str) -> tuple[str, str]:
    """The angle a fault's detail says the joint is at, and the bound it says it went past."""
    found = re.search(r" at ([-+0-9.]+) rad.*\(([-+0-9.]+) rad", detail)
    assert found is not None, detail
    return found.group(1), found.group(2)


def test_an_angle_just_past_its_bound_is_said_apart_from_it(
    hand: HandConfig, protocol: Protocol
) -> None:
    """A tenth of a milliradian past the bound, the recovered joint's angle and its bound,
    and a resting joint's, printed to 3 decimals, read the same, "at -0.968 rad ...
    (-0.968 rad ...)" (found by an outside audit)."""
    top = hand.joints[J].angle_max
    angle = at(hand, top + 0.05)
    other = 5
    angle[other] = hand.joints[other].angle_max + 0.01
    recovery = Recovery(J, -1)
    armed = Armed(hand, protocol, angle, recovery)
    angle[other] = recovery.resting[other] + 0.0001  # the resting one, just past its ratchet
    (fault,) = armed.see(angle)
    said, bound = _angle_and_bound(fault.detail)
    assert float(said) > float(bound)
    recovery = Recovery(J, -1)
    armed = Armed(hand, protocol, at(hand, top + 0.05), recovery)
    (fault,) = armed.see(at(hand, recovery.bound + 0.0001))  # the recovered one
    said, bound = _angle_and_bound(fault.detail)
    assert float(said) > float(bound)
