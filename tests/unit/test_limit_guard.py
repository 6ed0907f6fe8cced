"""The soft-limit guard: a joint inside the band before a soft limit is pushed back, up to its
full tau_max at the limit; outside the band the recipe's torque passes unchanged; a recipe
turns it on with ``limit_guard_band`` and the runner proposes the guarded torque."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml
from hypothesis import example, given, settings
from hypothesis import strategies as st

from handctl.config import HandConfig, load_hand
from handctl.errors import ConfigError
from handctl.online.recipes.guard import LimitGuard
from handctl.online.recipes.loader import load_recipe
from handctl.online.recipes.runner import RecipeRunner, RunStatus

from ..conftest import HAND_YAML

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


def test_at_the_limit_the_push_back_is_whole_whatever_the_phase_asks_towards_it(
    hand: HandConfig,
) -> None:
    """A phase that asks a joint's whole tau_max towards a limit (``manipulate_3`` on f1_j3)
    was only cancelled there by a spring reaching tau_max, and the contact pushed the joint
    over the limit (``ANGLE_LIMIT``). Deep in the band the spring takes that torque on as
    well, so the joint at the limit is pushed back with its whole tau_max; in the band's
    first half, where the lift rests its distal joints, the push is the spring's alone."""
    band = 0.2
    guard = LimitGuard.for_hand(hand, band)
    j = 2  # f1_j3
    joint = hand.joints[j]
    tau = joint.tau_max
    angle = np.array([(x.angle_min + x.angle_max) / 2 for x in hand.joints])
    desired = np.zeros(9)
    desired[j] = tau  # all of it towards the upper limit
    angle[j] = joint.angle_max
    assert guard.apply(angle, desired, np.empty(9))[j] == pytest.approx(-tau)
    # three quarters in: the spring's 3/4 and half of what the phase asks, against it
    angle[j] = joint.angle_max - band / 4
    assert guard.apply(angle, desired, np.empty(9))[j] == pytest.approx(
        tau - 0.75 * tau - 0.5 * tau
    )
    # a quarter in: the spring's quarter alone, as before
    angle[j] = joint.angle_max - 0.75 * band
    assert guard.apply(angle, desired, np.empty(9))[j] == pytest.approx(tau - 0.25 * tau)
    # a torque away from the limit is never added to: at the limit, the spring's tau_max and
    # the phase's own push away, clipped to tau_max
    desired[j] = -0.05
    angle[j] = joint.angle_max
    assert guard.apply(angle, desired, np.empty(9))[j] == pytest.approx(-tau)
    angle[j] = joint.angle_max - band / 4
    assert guard.apply(angle, desired, np.empty(9))[j] == pytest.approx(-0.05 - 0.75 * tau)
    # the lower side the same, mirrored
    desired[j] = -tau
    angle[j] = joint.angle_min
    assert guard.apply(angle, desired, np.empty(9))[j] == pytest.approx(tau)
    assert np.array_equal(np.delete(guard.apply(angle, desired, np.empty(9)), j), np.zeros(8))


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
    assert out[j] == pytest.approx(0.05 + guard.gain_lower[j] * band / 2 + damping * 1.0)


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
@example(
    angle=[0.0] * 6 + [0.515625, 0.0, 0.0],
    scale=[0.0] * 9,
    band=0.5,
    velocity=[0.0] * 6 + [-48.0, 0.0, 0.0],
)
def test_the_guard_never_proposes_more_than_tau_max(
    hand: HandConfig, angle: list[float], scale: list[float], band: float, velocity: list[float]
) -> None:
    guard = LimitGuard.for_hand(hand, band)
    tau_max = np.array([j.tau_max for j in hand.joints])
    desired = np.array(scale) * tau_max
    out = guard.apply(angle, desired, np.empty(9), velocity)
    assert np.all(np.abs(out) <= tau_max + 1e-12)
    # it never pushes a joint further towards the limit it is near, but to brake a motion
    # towards the other one: with bands as wide as 0.5 rad a joint at 48 rad/s meets the far
    # limit's damper (a band before that limit's spring band) within its lookahead, and
    # braking it is right (hypothesis found it)
    for k, joint in enumerate(hand.joints):
        ahead = angle[k] + velocity[k] * guard.lookahead
        if angle[k] > joint.angle_max - band:
            braking = velocity[k] < 0 and ahead < guard.lower[k] + band
            assert out[k] <= desired[k] or braking
        if angle[k] < joint.angle_min + band:
            braking = velocity[k] > 0 and ahead > guard.upper[k] - band
            assert out[k] >= desired[k] or braking


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
    # the whole push-back, whatever the recipe's 0.1 asks towards the limit
    assert out[8] == pytest.approx(-hand.joints[8].tau_max)
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


def test_a_side_with_a_spring_band_of_its_own_is_pushed_back_more_softly(
    tmp_path: Path, hand: HandConfig
) -> None:
    """A light distal joint's lower wall over 0.25 rad: its spring starts further out and
    reaches tau_max at the limit with 0.6 times the gain; its upper wall, every other joint
    and the damper (the guard's band) are as without it."""
    path = _recipe(
        tmp_path,
        hand,
        limit_guard_band=0.15,
        limit_guard_spring_bands={"f1_j3": {"lower": 0.25}},
    )
    recipe = load_recipe(path, hand)
    soft = recipe.limit_guard
    plain = LimitGuard.for_hand(hand, 0.15)
    assert soft is not None
    j = 2  # f1_j3
    joint = hand.joints[j]
    mid = np.array([(x.angle_min + x.angle_max) / 2 for x in hand.joints])
    desired = np.zeros(9)
    angle = mid.copy()
    angle[j] = joint.angle_min + 0.2  # inside the soft spring's band, outside the guard's
    out = soft.apply(angle, desired, np.empty(9))
    assert out[j] == pytest.approx(joint.tau_max / 0.25 * 0.05)
    assert plain.apply(angle, desired, np.empty(9))[j] == 0.0
    angle[j] = joint.angle_min + 0.1
    assert soft.apply(angle, desired, np.empty(9))[j] == pytest.approx(joint.tau_max * 0.6)
    assert plain.apply(angle, desired, np.empty(9))[j] == pytest.approx(joint.tau_max / 3)
    angle[j] = joint.angle_min
    assert soft.apply(angle, desired, np.empty(9))[j] == pytest.approx(joint.tau_max)
    # the upper wall, the other joints (f2_j3 here) and the damper are the plain guard's
    for k, q in ((j, joint.angle_max - 0.05), (5, hand.joints[5].angle_min + 0.05)):
        angle = mid.copy()
        angle[k] = q
        velocity = np.zeros(9)
        velocity[k] = 1.5 if q > mid[k] else -1.5
        assert np.array_equal(
            soft.apply(angle, desired, np.empty(9), velocity),
            plain.apply(angle, desired, np.empty(9), velocity),
        )
    assert soft.damping == plain.damping
    assert (soft.band, soft.lower, soft.upper) == (plain.band, plain.lower, plain.upper)


@pytest.mark.parametrize(
    ("top", "key", "found"),
    [
        # a spring band needs the guard it belongs to
        (
            {"limit_guard_spring_bands": {"f1_j3": {"lower": 0.25}}},
            "limit_guard_spring_bands",
            None,
        ),
        # a joint the hand does not have, beside one it has
        (
            {
                "limit_guard_band": 0.15,
                "limit_guard_spring_bands": {"f1_j3": {"lower": 0.25}, "f4_j3": {"lower": 0.25}},
            },
            "limit_guard_spring_bands.f4_j3",
            None,
        ),
        # no joint the hand has: written for another hand (the message names the hand's)
        (
            {"limit_guard_band": 0.15, "limit_guard_spring_bands": {"f4_j3": {"lower": 0.25}}},
            "limit_guard_spring_bands",
            None,
        ),
        # a side a joint does not have
        (
            {"limit_guard_band": 0.15, "limit_guard_spring_bands": {"f1_j3": {"low": 0.25}}},
            "limit_guard_spring_bands.f1_j3.low",
            None,
        ),
        # a band outside the guard's range
        (
            {"limit_guard_band": 0.15, "limit_guard_spring_bands": {"f1_j3": {"lower": 0.9}}},
            "limit_guard_spring_bands.f1_j3.lower",
            0.9,
        ),
        # empty mappings, of joints or of a joint's sides: taken, and did nothing (found by
        # an outside audit)
        (
            {"limit_guard_band": 0.15, "limit_guard_spring_bands": {}},
            "limit_guard_spring_bands",
            {},
        ),
        (
            {"limit_guard_band": 0.15, "limit_guard_spring_bands": {"f1_j3": {}}},
            "limit_guard_spring_bands.f1_j3",
            {},
        ),
    ],
)
def test_a_bad_spring_band_is_refused_naming_the_key(
    tmp_path: Path, hand: HandConfig, top: dict[str, object], key: str, found: object
) -> None:
    with pytest.raises(ConfigError) as info:
        load_recipe(_recipe(tmp_path, hand, **top), hand)
    assert info.value.key == key
    if found is not None:
        assert info.value.found == found


def test_spring_bands_that_overlap_on_a_joints_range_are_refused(
    tmp_path: Path, hand: HandConfig
) -> None:
    """On a hand whose f1_j3 moves over 0.8 rad, two springs of 0.45 rad would each start
    inside the other's band."""
    data = yaml.safe_load(HAND_YAML.read_text())
    data["fingers"][0]["joints"][2].update(angle_min=-0.2, angle_max=0.6)
    narrow_yaml = tmp_path / "narrow.yaml"
    narrow_yaml.write_text(yaml.safe_dump(data, sort_keys=False))
    narrow = load_hand(narrow_yaml)
    top = {
        "limit_guard_band": 0.15,
        "limit_guard_spring_bands": {"f1_j3": {"lower": 0.45, "upper": 0.45}},
    }
    with pytest.raises(ConfigError) as info:
        load_recipe(_recipe(tmp_path, narrow, **top), narrow)
    assert info.value.key == "limit_guard_spring_bands.f1_j3"
    assert "0.8 rad" in info.value.expected and info.value.found == "0.9 rad"
    # one side of it alone, with the guard's band on the other, leaves room
    top["limit_guard_spring_bands"] = {"f1_j3": {"lower": 0.45}}
    assert load_recipe(_recipe(tmp_path, narrow, **top), narrow).limit_guard is not None


def test_a_band_wider_than_half_a_joint_s_range_is_refused(
    tmp_path: Path, hand: HandConfig
) -> None:
    """Its two springs overlapped, every angle of the joint inside a band: a hand with a
    joint of 0.2 rad and a recipe of 0.15 rad bands each passed their checks, and every run
    stopped on ANGLE_LIMIT. Refused, naming the joint; its own spring bands make room."""
    import dataclasses

    from handctl.errors import ConfigError

    narrow = dataclasses.replace(hand.fingers[0].joints[2], angle_min=0.1, angle_max=0.3)
    finger = dataclasses.replace(hand.fingers[0], joints=(*hand.fingers[0].joints[:2], narrow))
    narrow_hand = dataclasses.replace(hand, fingers=(finger, *hand.fingers[1:]))
    with pytest.raises(ConfigError) as err:
        load_recipe(_recipe(tmp_path, narrow_hand, limit_guard_band=0.15), narrow_hand)
    assert (err.value.key, err.value.found) == ("limit_guard_band", 0.15)
    assert "below half of f1_j3's 0.2 rad" in err.value.expected
    own = {"f1_j3": {"lower": 0.05, "upper": 0.05}}
    recipe = load_recipe(
        _recipe(tmp_path, narrow_hand, limit_guard_band=0.15, limit_guard_spring_bands=own),
        narrow_hand,
    )
    assert recipe.limit_guard is not None


def test_the_band_check_names_the_narrowest_joint_and_holds_at_exactly_half(
    tmp_path: Path, hand: HandConfig
) -> None:
    """Two narrow joints: the refusal named the first in the config's order, and a band
    made narrow enough for it was refused again for the other. And a band of exactly half
    of a range written 0.35..0.45 rad (0.09999999999999998 in floating point) passed, its
    two springs meeting."""
    import dataclasses

    from handctl.errors import ConfigError

    first = dataclasses.replace(hand.fingers[0].joints[2], angle_min=0.1, angle_max=0.3)
    second = dataclasses.replace(hand.fingers[1].joints[2], angle_min=0.35, angle_max=0.45)
    f1 = dataclasses.replace(hand.fingers[0], joints=(*hand.fingers[0].joints[:2], first))
    f2 = dataclasses.replace(hand.fingers[1], joints=(*hand.fingers[1].joints[:2], second))
    narrow_hand = dataclasses.replace(hand, fingers=(f1, f2, *hand.fingers[2:]))
    with pytest.raises(ConfigError) as err:
        load_recipe(_recipe(tmp_path, narrow_hand, limit_guard_band=0.15), narrow_hand)
    assert "below half of f2_j3's 0.1 rad, the narrowest" in err.value.expected
    with pytest.raises(ConfigError) as err:
        load_recipe(_recipe(tmp_path, narrow_hand, limit_guard_band=0.05), narrow_hand)
    assert "f2_j3" in err.value.expected
    assert load_recipe(_recipe(tmp_path, narrow_hand, limit_guard_band=0.045), narrow_hand)
    # and a joint's own spring bands, meeting at exactly half of its range each
    own = {"f2_j3": {"lower": 0.05, "upper": 0.05}}
    with pytest.raises(ConfigError) as err:
        load_recipe(
            _recipe(tmp_path, narrow_hand, limit_guard_band=0.04, limit_guard_spring_bands=own),
            narrow_hand,
        )
    assert err.value.key == "limit_guard_spring_bands.f2_j3"


def test_a_joint_no_two_bands_fit_in_is_said_to_take_no_guard(
    tmp_path: Path, hand: HandConfig
) -> None:
    """A range of 0.03 rad holds no two of the narrowest bands (0.02 rad): the refusal
    offered bands of the joint's own, which were refused in their turn, whatever they were."""
    import dataclasses

    from handctl.errors import ConfigError

    tight = dataclasses.replace(hand.fingers[0].joints[2], angle_min=0.1, angle_max=0.13)
    f1 = dataclasses.replace(hand.fingers[0], joints=(*hand.fingers[0].joints[:2], tight))
    narrow_hand = dataclasses.replace(hand, fingers=(f1, *hand.fingers[1:]))
    with pytest.raises(ConfigError) as err:
        load_recipe(_recipe(tmp_path, narrow_hand, limit_guard_band=0.15), narrow_hand)
    assert "bands of its own" not in err.value.expected
    assert "no two bands of 0.02 rad fit in it: a recipe for this hand has no " in (
        err.value.expected
    )
