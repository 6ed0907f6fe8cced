"""The soft-limit guard: a joint inside the band before a soft limit is pushed back, up to its
full tau_max at the limit; outside the band the recipe's torque passes unchanged; a recipe
turns it on with ``limit_guard_band`` and the runner proposes the guarded torque."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml
from hypothesis import given, settings
from hypothesis import strategies as st

from handctl.config import HandConfig
from handctl.errors import ConfigError
from handctl.online.recipes.guard import LimitGuard
from handctl.online.recipes.loader import load_recipe
from handctl.online.recipes.runner import RecipeRunner, RunStatus

JOINTS = ["f1_j1", "f1_j2", "f1_j3", "f2_j1", "f2_j2", "f2_j3", "f3_j1", "f3_j2", "f3_j3"]


def _recipe(tmp_path: Path, hand: HandConfig, **top: object) -> Path:
    data = {
        "recipe": "guarded",
        **top,
        "phases": [
            {
                "name": "squeeze",
                "torques": dict.fromkeys(JOINTS, 0.1),
                "ramp_s": 0.01,
                "max_s": 0.05,
                "on_timeout": "next",
            }
        ],
    }
    path = tmp_path / "guarded.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def test_outside_the_band_the_torque_is_the_recipes(hand: HandConfig) -> None:
    guard = LimitGuard.for_hand(hand, 0.15)
    mid = np.array([(j.angle_min + j.angle_max) / 2 for j in hand.joints])
    desired = np.linspace(-0.2, 0.2, 9)
    out = guard.apply(mid, desired, np.empty(9))
    assert np.array_equal(out, desired)


def test_inside_the_band_the_joint_is_pushed_back_and_at_the_limit_fully(hand: HandConfig) -> None:
    guard = LimitGuard.for_hand(hand, 0.2)
    j = 2  # f1_j3
    joint = hand.joints[j]
    angle = np.array([(x.angle_min + x.angle_max) / 2 for x in hand.joints])
    desired = np.zeros(9)
    angle[j] = joint.angle_max - 0.1  # halfway into the upper band
    out = guard.apply(angle, desired, np.empty(9))
    assert out[j] == pytest.approx(-joint.tau_max / 2)
    assert np.count_nonzero(out) == 1
    angle[j] = joint.angle_min  # at the lower limit: the whole tau_max, pushing up
    out = guard.apply(angle, desired, np.empty(9))
    assert out[j] == pytest.approx(joint.tau_max)


def test_a_joint_heading_for_a_limit_is_damped_a_band_before_the_spring(hand: HandConfig) -> None:
    band = 0.15
    guard = LimitGuard.for_hand(hand, band, lookahead_s=0.0)
    j = 4  # f2_j2
    joint = hand.joints[j]
    angle = np.array([(x.angle_min + x.angle_max) / 2 for x in hand.joints])
    desired = np.full(9, 0.05)
    velocity = np.zeros(9)
    # half a band before the spring's band, moving towards the upper limit at 2 rad/s:
    # half the damping, against the motion, and nothing on the other joints
    angle[j] = joint.angle_max - 1.5 * band
    velocity[j] = 2.0
    out = guard.apply(angle, desired, np.empty(9), velocity)
    damping = guard.damping[j]
    assert damping > 0
    assert out[j] == pytest.approx(0.05 - 0.5 * damping * 2.0)
    assert np.array_equal(np.delete(out, j), np.delete(desired, j))
    # moving away from the limit it is near: not held back
    velocity[j] = -2.0
    assert guard.apply(angle, desired, np.empty(9), velocity)[j] == 0.05
    # further from the limit than two bands: nothing, whatever the speed
    angle[j] = joint.angle_max - 2.5 * band
    velocity[j] = 5.0
    assert guard.apply(angle, desired, np.empty(9), velocity)[j] == 0.05
    # inside the spring's band towards the lower limit: spring and full damping together
    angle[j] = joint.angle_min + band / 2
    velocity[j] = -1.0
    out = guard.apply(angle, desired, np.empty(9), velocity)
    assert out[j] == pytest.approx(0.05 + guard.gain[j] * band / 2 + damping * 1.0)


def test_a_fast_joint_is_met_where_it_will_be_after_the_lag(hand: HandConfig) -> None:
    """A joint flung at a limit (a lightly damped finger in the lift) is braked from where it
    will be ``lookahead`` later: at 20 rad/s the damper reaches it well before the two bands
    where a slow joint is first damped, so that it acts through the drive's lag in time."""
    band, lookahead = 0.15, 0.03
    guard = LimitGuard.for_hand(hand, band, lookahead_s=lookahead)
    j = 5  # f2_j3, heading for its lower limit
    joint = hand.joints[j]
    angle = np.array([(x.angle_min + x.angle_max) / 2 for x in hand.joints])
    desired = np.full(9, -0.06)
    velocity = np.zeros(9)
    angle[j] = joint.angle_min + 2 * band + 0.3  # 0.3 rad before the damper's band
    velocity[j] = -0.5  # slow: 15 mrad ahead, still outside
    assert guard.apply(angle, desired, np.empty(9), velocity)[j] == -0.06
    velocity[j] = -20.0  # fast: 0.6 rad ahead, inside the spring's band
    out = guard.apply(angle, desired, np.empty(9), velocity)
    assert out[j] == pytest.approx(min(joint.tau_max, -0.06 + guard.damping[j] * 20.0))
    assert out[j] > 0.0  # braked hard, against the recipe's own torque
    assert np.array_equal(np.delete(out, j), np.delete(desired, j))
    # moving away as fast, nothing
    velocity[j] = 20.0
    assert guard.apply(angle, desired, np.empty(9), velocity)[j] == -0.06


@settings(max_examples=300, deadline=None)
@given(
    st.lists(st.floats(-3.0, 3.0), min_size=9, max_size=9),
    st.lists(st.floats(-1.0, 1.0), min_size=9, max_size=9),
    st.floats(0.02, 0.5),
    st.lists(st.floats(-50.0, 50.0), min_size=9, max_size=9),
)
def test_the_guard_never_proposes_more_than_tau_max(
    hand: HandConfig, angle: list[float], scale: list[float], band: float, velocity: list[float]
) -> None:
    guard = LimitGuard.for_hand(hand, band)
    tau_max = np.array([j.tau_max for j in hand.joints])
    desired = np.array(scale) * tau_max
    out = guard.apply(angle, desired, np.empty(9), velocity)
    assert np.all(np.abs(out) <= tau_max + 1e-12)
    # it never pushes a joint further towards the limit it is near
    for k, joint in enumerate(hand.joints):
        if angle[k] > joint.angle_max - band:
            assert out[k] <= desired[k]
        if angle[k] < joint.angle_min + band:
            assert out[k] >= desired[k]


def test_a_recipe_turns_the_guard_on_and_the_runner_uses_it(
    tmp_path: Path, hand: HandConfig
) -> None:
    recipe = load_recipe(_recipe(tmp_path, hand, limit_guard_band=0.15), hand)
    assert recipe.limit_guard is not None and recipe.limit_guard.band == 0.15
    runner = RecipeRunner(recipe, 9)
    angle = np.array([(j.angle_min + j.angle_max) / 2 for j in hand.joints])
    angle[8] = hand.joints[8].angle_max  # f3_j3 at its upper soft limit
    runner.step(0.0, angle, np.zeros(9))
    out = runner.step(0.02, angle, np.zeros(9)).copy()  # after the ramp
    assert out[8] == pytest.approx(0.1 - hand.joints[8].tau_max)  # 0.1 plus the full push-back
    assert np.allclose(out[:8], 0.1)
    # after the recipe ends nothing is proposed, whatever the angles
    t = 0.02
    while not runner.done:
        t += 0.001
        out = runner.step(t, angle, np.zeros(9))
    assert runner.status is RunStatus.COMPLETED
    assert not np.any(out)
    unguarded = load_recipe(_recipe(tmp_path, hand), hand)
    assert unguarded.limit_guard is None


def test_a_band_out_of_range_is_refused_naming_the_key(tmp_path: Path, hand: HandConfig) -> None:
    path = _recipe(tmp_path, hand, limit_guard_band=2.0)
    with pytest.raises(ConfigError) as info:
        load_recipe(path, hand)
    assert info.value.key == "limit_guard_band"
    assert info.value.found == 2.0
