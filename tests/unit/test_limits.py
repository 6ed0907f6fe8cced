"""The torque limiter on its own: every expected value comes from the hand config's limits.

Each test states one clause of the contract in docs/safety.md (guarantee 6): what must be
refused rather than clamped, the clamp to ±tau_max, the rate limit in both directions, and
the soft angle limits. Inputs sit on and just past each limit, so that an off-by-one in a
comparison or a flipped sign changes a value the test checks exactly.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from handctl.config import HandConfig
from handctl.online.safety.faults import FaultCode
from handctl.online.safety.limits import JointLimits, angle_violations, check_desired, limit_torque


@pytest.fixture(scope="module")
def limits(hand: HandConfig) -> JointLimits:
    return JointLimits.from_hand(hand)


def tau_max(hand: HandConfig) -> np.ndarray:
    return np.array([j.tau_max for j in hand.joints])


def step(hand: HandConfig) -> np.ndarray:
    """The most a joint's torque may change in one tick (N·m)."""
    return np.array([j.rate_limit for j in hand.joints]) * hand.bus.period_s


def limit(
    desired: np.ndarray, last: np.ndarray, limits: JointLimits, hand: HandConfig
) -> tuple[np.ndarray, int]:
    out = np.full(hand.n_joints, np.nan)
    count = limit_torque(desired, last, limits, hand.bus.period_s, out)
    return out, count


def test_limits_are_the_hand_configs_joint_by_joint(hand: HandConfig, limits: JointLimits) -> None:
    joints = hand.joints
    assert limits.names == tuple(j.name for j in joints)
    for array, listed, key in (
        (limits.tau_max, limits.tau_max_list, "tau_max"),
        (limits.rate_limit, limits.rate_list, "rate_limit"),
        (limits.angle_min, limits.angle_min_list, "angle_min"),
        (limits.angle_max, limits.angle_max_list, "angle_max"),
    ):
        expected = [getattr(j, key) for j in joints]
        assert array.tolist() == expected, key
        assert list(listed) == expected, key


def test_above_tau_max_is_clamped_to_tau_max(hand: HandConfig, limits: JointLimits) -> None:
    top = tau_max(hand)
    out, count = limit(2 * top, top.copy(), limits, hand)
    assert out.tolist() == top.tolist()
    assert count == hand.n_joints


def test_below_minus_tau_max_is_clamped_to_minus_tau_max(
    hand: HandConfig, limits: JointLimits
) -> None:
    top = tau_max(hand)
    out, count = limit(-2 * top, -top, limits, hand)
    assert out.tolist() == (-top).tolist()
    assert count == hand.n_joints


def test_exactly_tau_max_passes_unlimited(hand: HandConfig, limits: JointLimits) -> None:
    top = tau_max(hand)
    for sign in (1.0, -1.0):
        out, count = limit(sign * top, sign * top, limits, hand)
        assert out.tolist() == (sign * top).tolist()
        assert count == 0


def test_the_rate_limit_holds_upwards_and_downwards(hand: HandConfig, limits: JointLimits) -> None:
    top, rate_step = tau_max(hand), step(hand)
    zero = np.zeros(hand.n_joints)
    up, count = limit(top, zero, limits, hand)
    assert up.tolist() == rate_step.tolist()
    assert count == hand.n_joints
    down, count = limit(-top, zero, limits, hand)
    assert down.tolist() == (-rate_step).tolist()
    assert count == hand.n_joints


def test_the_clamp_comes_before_the_rate_limit(hand: HandConfig, limits: JointLimits) -> None:
    """From tau_max, a request of -2·tau_max moves one rate step down, never more."""
    top, rate_step = tau_max(hand), step(hand)
    out, _ = limit(-2 * top, top.copy(), limits, hand)
    assert out == pytest.approx(top - rate_step, abs=1e-15)
    out, _ = limit(2 * top, -top, limits, hand)
    assert out == pytest.approx(-top + rate_step, abs=1e-15)


def test_a_change_within_both_limits_is_applied_as_asked(
    hand: HandConfig, limits: JointLimits
) -> None:
    top, rate_step = tau_max(hand), step(hand)
    last = 0.5 * top
    for desired in (last + 0.5 * rate_step, last - 0.5 * rate_step, last):
        out, count = limit(desired, last, limits, hand)
        assert out.tolist() == desired.tolist()
        assert count == 0


def test_the_count_is_the_joints_that_were_limited(hand: HandConfig, limits: JointLimits) -> None:
    top, rate_step = tau_max(hand), step(hand)
    n = hand.n_joints
    a, b, c = 1, n // 2, n - 1
    last = np.zeros(n)
    desired = np.zeros(n)
    desired[a] = top[a]  # rate-limited
    desired[b] = -0.5 * rate_step[b]  # within both limits
    desired[c] = -top[c]  # rate-limited downwards
    out, count = limit(desired, last, limits, hand)
    assert count == 2
    assert out[[a, b, c]].tolist() == [rate_step[a], desired[b], -rate_step[c]]


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_a_non_finite_torque_is_refused_naming_the_joint(hand: HandConfig, bad: float) -> None:
    desired = np.zeros(hand.n_joints)
    desired[5] = bad
    for form in (desired, desired.tolist()):
        found = check_desired(form, hand.n_joints)
        assert found is not None
        code, detail = found
        assert code is FaultCode.NON_FINITE_TORQUE
        assert detail.startswith("joint 5: ")
        assert str(bad) in detail


def test_finite_torques_whose_sum_overflows_are_not_taken_for_non_finite(
    hand: HandConfig,
) -> None:
    """The check sums first (a finite sum proves every value finite); a sum that overflows
    is still judged value by value, so huge finite torques are left to the limiter."""
    desired = np.full(hand.n_joints, 1e308)
    assert sum(desired.tolist()) == float("inf")
    assert check_desired(desired, hand.n_joints) is None
    desired[0], desired[1] = np.inf, -np.inf  # a NaN sum, as a NaN would give
    found = check_desired(desired, hand.n_joints)
    assert found is not None and found[0] is FaultCode.NON_FINITE_TORQUE
    assert found[1] == "joint 0: inf N·m asked"
    # named where the names are known (the supervisor's): numpy's repr said np.float64(nan)
    desired[0] = np.nan
    assert check_desired(desired, hand.n_joints, hand.joint_names) == (
        FaultCode.NON_FINITE_TORQUE,
        f"{hand.joint_names[0]}: nan N·m asked",
    )


@pytest.mark.parametrize("n", [0, 8, 10])
def test_a_wrong_number_of_torques_is_refused(hand: HandConfig, n: int) -> None:
    assert check_desired(np.zeros(n), hand.n_joints) == (
        FaultCode.WRONG_SHAPE,
        f"expected {hand.n_joints} torques, found shape ({n},)",
    )


def test_a_matrix_of_the_right_size_is_refused(hand: HandConfig) -> None:
    found = check_desired(np.zeros((1, hand.n_joints)), hand.n_joints)
    assert found == (
        FaultCode.WRONG_SHAPE,
        f"expected {hand.n_joints} torques, found shape (1, {hand.n_joints})",
    )


def test_what_is_not_numbers_is_refused_as_such(hand: HandConfig) -> None:
    desired = ["a"] * hand.n_joints
    assert check_desired(desired, hand.n_joints) == (  # type: ignore[arg-type]
        FaultCode.WRONG_SHAPE,
        f"desired torques are not real numbers (<U1 values): {desired!r:.60}",
    )


@pytest.mark.parametrize("dtype", [str, object])
def test_an_array_of_what_is_not_numbers_is_refused_as_such(hand: HandConfig, dtype: type) -> None:
    desired: np.ndarray = np.array(["a"] * hand.n_joints, dtype=dtype)
    found = check_desired(desired, hand.n_joints)
    assert found is not None and found[0] is FaultCode.WRONG_SHAPE
    assert found[1].startswith("desired torques are not real numbers (")


@pytest.mark.parametrize(
    "values",
    [
        ["0.1"] * 9,  # numeric strings: they were sent as torques
        [True] * 9,  # booleans: sent as 1 N·m, clamped to tau_max
        [0.1 + 0.2j] * 9,  # complex: the imaginary part dropped, with a warning only
        np.full(9, 0.1 + 0j),
        np.ones(9, dtype=bool),
        [0.1] * 8 + [[0.1]],  # ragged
        {"f1_j1": 0.1},
    ],
    ids=["strings", "bools", "complex", "complex_array", "bool_array", "ragged", "dict"],
)
def test_only_real_numbers_are_torques(hand: HandConfig, values: object) -> None:
    """The supervisor's contract is numbers only: numeric strings, booleans and complex
    values were converted to float64 and sent (found by an outside audit)."""
    found = check_desired(values, hand.n_joints)  # type: ignore[arg-type]
    assert found is not None and found[0] is FaultCode.WRONG_SHAPE, found
    assert found[1].startswith("desired torques are not real numbers (")


@pytest.mark.parametrize(
    "values", [[0.1] * 9, [1] * 9, np.full(9, 0.1, dtype=np.float32), np.arange(9)]
)
def test_real_numbers_of_any_kind_are_torques(hand: HandConfig, values: object) -> None:
    assert check_desired(values, hand.n_joints) is None  # type: ignore[arg-type]


def test_vectors_of_another_length_are_never_truncated(
    hand: HandConfig, limits: JointLimits
) -> None:
    """The limiter and the angle check take one value per joint, or refuse to work: zipping
    a short vector would silently leave joints out."""
    n = hand.n_joints
    for desired, last in ((np.zeros(n - 1), np.zeros(n)), (np.zeros(n), np.zeros(n - 1))):
        with pytest.raises(ValueError, match="zip"):
            limit_torque(desired, last, limits, hand.bus.period_s, np.zeros(n))
    with pytest.raises(ValueError, match="zip"):
        angle_violations(np.zeros(n - 1), limits)


def test_usable_torques_pass_in_any_numeric_form(hand: HandConfig) -> None:
    top = tau_max(hand)
    forms: tuple[Any, ...] = (
        top,
        top.tolist(),
        (-top).astype(np.float32),
        np.arange(hand.n_joints),
    )
    for desired in forms:
        assert check_desired(desired, hand.n_joints) is None


def test_soft_angle_limits_include_the_limit_itself(hand: HandConfig, limits: JointLimits) -> None:
    lo = np.array([j.angle_min for j in hand.joints])
    hi = np.array([j.angle_max for j in hand.joints])
    assert angle_violations(lo, limits) == []
    assert angle_violations(hi, limits) == []
    assert angle_violations((lo + hi) / 2, limits) == []
    n = hand.n_joints
    below = lo.copy()
    below[[2, n - 2]] = np.nextafter(lo[[2, n - 2]], -np.inf)
    assert angle_violations(below, limits) == [2, n - 2]
    above = hi.copy()
    above[[0, n - 1]] = np.nextafter(hi[[0, n - 1]], np.inf)
    assert angle_violations(above, limits) == [0, n - 1]
