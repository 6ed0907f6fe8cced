"""The object estimator on known poses, the recipe's ``objects`` key, and phase-relative
estimates in the runner."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml

from handctl.config import FingerConfig, HandConfig
from handctl.errors import ConfigError
from handctl.online.estimator import NAN, ObjectEstimator, advance_turn
from handctl.online.recipes.loader import load_recipe
from handctl.online.recipes.runner import RecipeRunner
from handctl.online.recipes.schema import FIRST_PAIR_TURN, RecipeObject

R = 0.0175  # m: the object that fits the square cage below exactly
H = (0.008, 0.0075, 0.007)  # m: half-thicknesses of the default hand's links


def boxed_hand(hand: HandConfig) -> HandConfig:
    """The default hand with link lengths chosen so that, at angles (0, ±π/2, ±π/2), each side
    forms a square cage under the palm that holds a cylinder of radius R exactly: proximal link
    down, middle link across, distal link up to the palm, palm on top."""
    lengths = (2 * R + H[1], 2 * R + H[0] + H[2], 2 * R + H[1])

    def fix(finger: FingerConfig) -> FingerConfig:
        joints = tuple(
            dataclasses.replace(j, link_length=length, half_thickness=h)
            for j, length, h in zip(finger.joints, lengths, H, strict=True)
        )
        return dataclasses.replace(finger, joints=joints)

    return dataclasses.replace(hand, fingers=tuple(fix(f) for f in hand.fingers))


BOX_ANGLES = [0.0, math.pi / 2, math.pi / 2] * 2 + [0.0, -math.pi / 2, -math.pi / 2]
OPEN_ANGLES = [-0.55, -0.1, -0.1] * 2 + [0.55, 0.1, 0.1]
PAIR = (RecipeObject("cyl1", R), RecipeObject("cyl2", R))


def settle(est: ObjectEstimator, angles: list[float], ticks: int = 200) -> tuple[float, ...]:
    out: tuple[float, ...] = ()
    for _ in range(ticks):
        out = est(angles)
    return out


def test_boxed_objects_are_found_exactly(hand: HandConfig) -> None:
    est = ObjectEstimator(boxed_hand(hand), PAIR)
    out = settle(est, BOX_ANGLES)
    assert est.valid
    # cage 1: x from -0.05 + h1 to -0.05 + h1 + 2R, y from -2R to 0 (palm)
    assert out[2] == pytest.approx(-0.05 + H[0] + R, abs=1e-6)
    assert out[3] == pytest.approx(-R, abs=1e-6)
    assert out[4] == pytest.approx(0.05 - H[0] - R, abs=1e-6)
    assert out[5] == pytest.approx(-R, abs=1e-6)
    assert out[0] == pytest.approx(0.0, abs=1e-6)  # the line from object 1 to object 2: +x
    assert est.clearance[0] == pytest.approx(0.0, abs=1e-6)


@pytest.mark.parametrize("factors", [(1.0, 1.0), (0.8, 1.2)])
def test_tracks_that_reach_the_cages_in_the_wrong_order_are_named_along_the_palm(
    hand: HandConfig, factors: tuple[float, float]
) -> None:
    """Before the cages close the tracks wander through the open hand, and on a hand that
    cages its objects apart each track may end in the other's cage: the names are those of
    the recipe's order along the palm once the objects are first located, not the tracks'
    (each estimate would read the other object's, a pair error of 180 degrees). Each track's
    radius goes with its name: the cage that measured it holds that object."""
    objects = tuple(RecipeObject(f"cyl{k + 1}", f * R) for k, f in enumerate(factors))
    est = ObjectEstimator(boxed_hand(hand), objects)
    first, second = (-0.05 + H[0] + R, -R), (0.05 - H[0] - R, -R)
    est.centres = [second, first]  # each track in the other object's cage
    out = settle(est, BOX_ANGLES, 1000)
    assert est.valid
    assert est.positions(out) == [
        pytest.approx(first, abs=1e-6),
        pytest.approx(second, abs=1e-6),
    ]
    assert out[0] == pytest.approx(0.0, abs=1e-6)  # the line from object 1 to object 2: +x
    assert est.radii == pytest.approx([R, R], abs=2e-5)


def test_two_tracks_stuck_in_one_cage_start_again_before_the_objects_are_located(
    hand: HandConfig,
) -> None:
    """Two tracks that ended in one cage, each inside the other, rest there while the grasp
    is held still: the ascent never takes them out, and no estimate would ever be valid. Not
    yet located, they start again from the seeds, and each finds its own cage."""
    est = ObjectEstimator(boxed_hand(hand), PAIR)
    second = (0.05 - H[0] - R, -R)
    est.centres = [second, (second[0] + 0.001, second[1])]
    out = settle(est, BOX_ANGLES, 1000)
    assert est.valid
    assert est.positions(out) == [
        pytest.approx((-0.05 + H[0] + R, -R), abs=1e-6),
        pytest.approx(second, abs=1e-6),
    ]


@pytest.mark.parametrize("factors", [(0.8, 0.8), (1.2, 1.2), (0.8, 1.2)])
def test_a_cylinder_of_another_radius_is_measured_by_its_cage(
    hand: HandConfig, factors: tuple[float, float]
) -> None:
    """The recipe's radii 20 % off, each on its own: the cage the hand closes round each
    cylinder says how large it is, and the estimate takes that radius, the centre staying
    where it is."""
    objects = tuple(RecipeObject(f"cyl{k + 1}", f * R) for k, f in enumerate(factors))
    est = ObjectEstimator(boxed_hand(hand), objects)
    out = settle(est, BOX_ANGLES, 1000)
    assert est.valid
    assert est.nominal_radii == pytest.approx([f * R for f in factors])
    assert est.measured_radii == pytest.approx([R, R], abs=2e-5)
    assert est.radii == pytest.approx([R, R], abs=2e-5)
    assert est.clearance == pytest.approx([0.0, 0.0], abs=2e-5)
    assert out[2] == pytest.approx(-0.05 + H[0] + R, abs=2e-5)
    assert out[3] == pytest.approx(-R, abs=2e-5)
    assert out[4] == pytest.approx(0.05 - H[0] - R, abs=2e-5)
    est.reset()  # a new grasp may be of other objects: the recipe's radii again
    assert est.radii == pytest.approx([f * R for f in factors])
    assert est.measured_radii == pytest.approx([f * R for f in factors])


def test_a_radius_within_the_measurement_s_uncertainty_keeps_the_recipe_s(
    hand: HandConfig,
) -> None:
    """A cylinder 0.3 mm smaller than the recipe says is measured so, but the recipe's radius
    is kept: soft contacts and a cage shared with the other cylinder make the measurement no
    better than half a millimetre."""
    objects = (RecipeObject("cyl1", R + 0.0003), RecipeObject("cyl2", R + 0.0003))
    est = ObjectEstimator(boxed_hand(hand), objects)
    settle(est, BOX_ANGLES, 1000)
    assert est.valid
    assert est.measured_radii == pytest.approx([R, R], abs=2e-5)
    assert est.radii == [R + 0.0003, R + 0.0003]


def test_the_radius_is_not_fitted_while_the_cage_moves(hand: HandConfig) -> None:
    """An object moving through the hand is not squeezed into its cage, so the cage is no
    measure of it: while the fingers swing, the radii stay; held still, they are fitted."""
    objects = (RecipeObject("cyl1", 0.9 * R), RecipeObject("cyl2", 0.9 * R))
    est = ObjectEstimator(boxed_hand(hand), objects)
    swing = np.array([1.0, 0.0, 0.0] * 2 + [-1.0, 0.0, 0.0])
    for tick in range(1000):  # 1 s at 1 kHz, the proximal joints swinging ±0.05 rad at 4 Hz
        est((np.array(BOX_ANGLES) + 0.05 * math.sin(8 * math.pi * tick / 1000) * swing).tolist())
        assert est.measured_radii == [0.9 * R, 0.9 * R]
    settle(est, BOX_ANGLES, 1000)
    assert est.measured_radii == pytest.approx([R, R], abs=2e-5)


def test_a_cage_looser_than_the_measured_object_does_not_place_it(hand: HandConfig) -> None:
    """Measured in a cage narrowed by finger 3's distal link (16.25 mm), cylinder 2 is then
    left in the square cage of 17.5 mm. While that cage moves it does not hold the cylinder:
    it lies anywhere in the slack, and the deepest point is a guess, so the estimate is
    invalid though the cage is closed round it. Held still, the cage is taken for its size."""
    est = ObjectEstimator(boxed_hand(hand), PAIR)
    settle(est, BOX_ANGLES, 1000)
    narrow = list(BOX_ANGLES)
    narrow[8] -= 0.1
    settle(est, narrow, 1000)
    assert est.measured_radii[1] == pytest.approx(R - 0.00125, abs=5e-5)
    for _ in range(50):
        est(BOX_ANGLES)
        assert not est.valid
    assert est.caged[1]
    assert est.clearance[1] + est.radii[1] - est.measured_radii[1] > 0.001
    settle(est, BOX_ANGLES, 1000)
    assert est.valid
    assert est.measured_radii[1] == pytest.approx(R, abs=2e-5)


def test_a_cage_far_larger_than_the_object_is_not_its_size(hand: HandConfig) -> None:
    """A cylinder half the size of its cage: the cage is another object's, or one the
    cylinder does not fill; the radius is not fitted to it, and the estimate is invalid."""
    objects = (RecipeObject("cyl1", 0.5 * R), RecipeObject("cyl2", 0.5 * R))
    est = ObjectEstimator(boxed_hand(hand), objects)
    settle(est, BOX_ANGLES, 1000)
    assert est.measured_radii == [0.5 * R, 0.5 * R]
    assert not est.valid


def test_the_open_hand_cages_nothing(hand: HandConfig) -> None:
    est = ObjectEstimator(hand, (RecipeObject("cyl1", 0.02), RecipeObject("cyl2", 0.02)))
    out = settle(est, OPEN_ANGLES, 500)
    assert not est.valid
    assert all(math.isnan(v) for v in out)


def test_turn_is_unwrapped_across_half_a_turn() -> None:
    """The running turn keeps counting past ±π, where the wrapped angle jumps."""
    turn, last = NAN, NAN
    turns = []
    for a in np.linspace(0.0, -1.5 * math.pi, 40):
        wrapped = math.atan2(math.sin(a), math.cos(a))
        turn = advance_turn(turn, last, wrapped)
        last = wrapped
        turns.append(turn)
    assert turns[-1] == pytest.approx(-1.5 * math.pi, abs=1e-9)
    assert np.all(np.diff(turns) < 0)


@pytest.mark.parametrize("count", [0, 5])
def test_the_estimator_tracks_one_to_four_objects(hand: HandConfig, count: int) -> None:
    with pytest.raises(ValueError, match="1 to 4 objects"):
        ObjectEstimator(hand, tuple(RecipeObject(f"c{i}", 0.02) for i in range(count)))


def row_hand(hand: HandConfig) -> tuple[HandConfig, list[float]]:
    """Four fingers in a row under the palm, ``ROW_SPACING`` apart, and the angles at which
    the first three box a cage each to their right (as ``boxed_hand``'s left side), the
    fourth hanging straight down as the last cage's wall."""
    boxed = boxed_hand(hand)
    finger = boxed.fingers[0]
    fingers = tuple(dataclasses.replace(finger, base_x=(k - 1.5) * ROW_SPACING) for k in range(4))
    angles = [0.0, math.pi / 2, math.pi / 2] * 3 + [0.0, 0.0, 0.0]
    return dataclasses.replace(boxed, fingers=fingers), angles


#: m: a finger's distal link, boxing its cage, is the next finger's proximal link
ROW_SPACING = (2 * R + H[0] + H[2]) + H[0] - H[2]


def cage_centre(k: int) -> tuple[float, float]:
    """The centre of the ``row_hand`` cage right of finger ``k``."""
    return (k - 1.5) * ROW_SPACING + H[0] + R, -R


def test_one_object_has_its_centre_and_no_pair(hand: HandConfig) -> None:
    shape, angles = row_hand(hand)
    est = ObjectEstimator(shape, (RecipeObject("ball", R),))
    assert est.estimates == ("ball_x", "ball_y")
    out = settle(est, angles)
    assert est.valid
    assert out == pytest.approx(cage_centre(1), abs=1e-6)


def test_three_objects_each_in_its_cage_with_the_pairs_asked_for(hand: HandConfig) -> None:
    shape, angles = row_hand(hand)
    objects = (RecipeObject("a", R), RecipeObject("b", R), RecipeObject("c", R))
    est = ObjectEstimator(shape, objects)
    assert est.estimates == (
        "a_b_line_angle",
        "a_b_line_turn",
        "b_c_line_angle",
        "b_c_line_turn",
        "a_x",
        "a_y",
        "b_x",
        "b_y",
        "c_x",
        "c_y",
    )
    out = settle(est, angles, 400)
    assert est.valid
    for k in range(3):
        assert est.positions(out)[k] == pytest.approx(cage_centre(k), abs=1e-6)
    assert out[0] == pytest.approx(0.0, abs=1e-6)  # a to b: +x
    assert out[2] == pytest.approx(0.0, abs=1e-6)  # b to c: +x
    # a pair the recipe names itself, the other way round: c to a points along -x
    est = ObjectEstimator(shape, objects, pairs=((2, 0),))
    assert est.estimates[:2] == ("c_a_line_angle", "c_a_line_turn")
    out = settle(est, angles, 400)
    assert abs(out[0]) == pytest.approx(math.pi, abs=1e-6)


def test_an_object_out_of_its_cage_invalidates_them_all(hand: HandConfig) -> None:
    """Every object is a wall of the others' cages: with the first cage opened, no estimate
    is given, not even of the objects still caged."""
    shape, angles = row_hand(hand)
    objects = (RecipeObject("a", R), RecipeObject("b", R), RecipeObject("c", R))
    est = ObjectEstimator(shape, objects)
    settle(est, angles, 400)
    assert est.valid
    opened = [-0.6, -0.1, -0.1, *angles[3:]]
    out = settle(est, opened, 400)
    assert not est.valid
    assert all(math.isnan(v) for v in out)


def test_half_thickness_agrees_with_the_simulated_links(hand: HandConfig) -> None:
    """The estimator's link thickness and the simulation's capsules are one fact written
    twice (the host never reads the sim section): they must not drift apart."""
    links = hand.sim["links"]
    for finger in hand.fingers:
        for k, joint in enumerate(finger.joints):
            assert joint.half_thickness == pytest.approx(links[finger.name][k]["radius"])


# -- the recipe's objects ------------------------------------------------------------------


def write(tmp_path: Path, data: dict[str, Any]) -> Path:
    path = tmp_path / "recipe.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def phase(name: str, **extra: Any) -> dict[str, Any]:
    joints = ["f1_j1", "f1_j2", "f1_j3", "f2_j1", "f2_j2", "f2_j3", "f3_j1", "f3_j2", "f3_j3"]
    return {
        "name": name,
        "torques": dict.fromkeys(joints, 0.1),
        "ramp_s": 0.1,
        "max_s": 1.0,
        **extra,
    }


OBJECTS = [{"name": "cyl1", "radius": 0.02}, {"name": "cyl2", "radius": 0.02}]


def test_objects_are_loaded_in_order(tmp_path: Path, hand: HandConfig) -> None:
    recipe = load_recipe(
        write(tmp_path, {"recipe": "r", "objects": OBJECTS, "phases": [phase("a")]}), hand
    )
    assert recipe.objects == (RecipeObject("cyl1", 0.02), RecipeObject("cyl2", 0.02))


@pytest.mark.parametrize(
    ("objects", "key", "expected"),
    [
        ([{"name": f"c{i}", "radius": 0.01} for i in range(5)], "objects", "1 to 4 mappings"),
        ([{"name": "cyl_1", "radius": 0.02}], "objects[0].name", "letters and digits"),
        # "$" let it by: a newline in a name check printed as it is
        ([{"name": "cyl1\n", "radius": 0.02}], "objects[0].name", "letters and digits"),
        ([], "objects", "1 to 4 mappings"),
        ([OBJECTS[0], OBJECTS[0]], "objects[1].name", "a name not used"),
        ([OBJECTS[0], {"name": "cyl2", "radius": -0.01}], "objects[1].radius", "> 0"),
        # accepted, and the estimator never placed it: an exit on its estimates never came
        ([{"name": "cyl1", "radius": 1e-12}], "objects[0].radius", ">= 0.005 m"),
        ([OBJECTS[0], {"name": "cyl2", "radius": 0.004}], "objects[1].radius", ">= 0.005 m"),
        ([OBJECTS[0], {"name": "cyl2", "radius": 0.02, "colour": "red"}], "objects[1]", "colour"),
        ([OBJECTS[0], {"name": "cyl2"}], "objects[1].radius", ""),
    ],
)
def test_bad_objects_are_refused_naming_the_key(
    tmp_path: Path, hand: HandConfig, objects: list[Any], key: str, expected: str
) -> None:
    path = write(tmp_path, {"recipe": "r", "objects": objects, "phases": [phase("a")]})
    with pytest.raises(ConfigError) as info:
        load_recipe(path, hand)
    assert info.value.key.startswith(key)
    assert expected in str(info.value)


@pytest.mark.parametrize(
    ("pairs", "key", "expected"),
    [
        ([["cyl1", "cyl3"]], "pairs[0]", "two names of the recipe's objects (cyl1, cyl2)"),
        ([["cyl1", "cyl1"]], "pairs[0]", "two different objects"),
        ([["cyl1", "cyl2"], ["cyl2", "cyl1"]], "pairs[1]", "a pair not listed before"),
        ([], "pairs", "a non-empty list"),
    ],
)
def test_bad_pairs_are_refused_naming_the_key(
    tmp_path: Path, hand: HandConfig, pairs: list[Any], key: str, expected: str
) -> None:
    path = write(
        tmp_path, {"recipe": "r", "objects": OBJECTS, "pairs": pairs, "phases": [phase("a")]}
    )
    with pytest.raises(ConfigError) as info:
        load_recipe(path, hand)
    assert info.value.key == key
    assert expected in info.value.expected


def test_estimates_are_named_by_the_recipe_objects(tmp_path: Path, hand: HandConfig) -> None:
    """Conditions name an object's or a pair's estimate by the recipe's own names; the
    unnamed ones of two-object recipes written before still read the same values."""
    three = [*OBJECTS, {"name": "peg", "radius": 0.01}]
    recipe = load_recipe(
        write(
            tmp_path,
            {
                "recipe": "r",
                "objects": three,
                "pairs": [["peg", "cyl1"]],
                "phases": [
                    phase("a", exit=["estimate.peg_cyl1_line_turn > 0.1", "estimate.peg_y > -0.05"])
                ],
            },
        ),
        hand,
    )
    assert recipe.estimates[:2] == ("peg_cyl1_line_angle", "peg_cyl1_line_turn")
    turn, height = recipe.phases[0].exits
    assert (turn.index, turn.relative) == (1, True)
    assert (recipe.estimates[height.index], height.relative) == ("peg_y", False)
    legacy = load_recipe(
        write(
            tmp_path,
            {
                "recipe": "r",
                "objects": OBJECTS,
                "phases": [
                    phase("a", exit=["estimate.centre_line_turn < -0.7", "estimate.object2_x > 0"])
                ],
            },
        ),
        hand,
    )
    new = ("cyl1_cyl2_line_turn", "cyl2_x")
    assert [legacy.estimates[c.index] for c in legacy.phases[0].exits] == list(new)
    assert legacy.phases[0].exits[0].relative
    with pytest.raises(ConfigError) as info:  # the old names meant two objects, one pair
        load_recipe(
            write(
                tmp_path,
                {
                    "recipe": "r",
                    "objects": three,
                    "phases": [phase("a", exit=["estimate.centre_line_turn < -0.7"])],
                },
            ),
            hand,
        )
    assert "cyl2_peg_line_turn" in info.value.expected
    # nor a pair written the other way round: its line is half a turn from what they meant
    with pytest.raises(ConfigError) as info:
        load_recipe(
            write(
                tmp_path,
                {
                    "recipe": "r",
                    "objects": OBJECTS,
                    "pairs": [["cyl2", "cyl1"]],
                    "phases": [phase("a", exit=["estimate.centre_line_angle > 3.0"])],
                },
            ),
            hand,
        )
    assert "first to second" in info.value.expected


def test_a_turn_needs_a_pair(tmp_path: Path, hand: HandConfig) -> None:
    with pytest.raises(ConfigError) as info:
        load_recipe(
            write(
                tmp_path,
                {
                    "recipe": "r",
                    "objects": OBJECTS[:1],
                    "min_total_turn_deg": 90,
                    "phases": [phase("a")],
                },
            ),
            hand,
        )
    assert info.value.key == "min_total_turn_deg"
    turning = phase("a", turn_rate={"rate_deg_s": 30, "scale": [0.5, 2.0]})
    with pytest.raises(ConfigError) as info:
        load_recipe(
            write(tmp_path, {"recipe": "r", "objects": OBJECTS[:1], "phases": [turning]}), hand
        )
    assert info.value.key == "phases[0].turn_rate"


def test_estimates_without_objects_are_refused(tmp_path: Path, hand: HandConfig) -> None:
    path = write(
        tmp_path, {"recipe": "r", "phases": [phase("a", exit=["estimate.centre_line_turn < -0.7"])]}
    )
    with pytest.raises(ConfigError) as info:
        load_recipe(path, hand)
    assert info.value.key == "phases[0].exit[0]"
    assert "the recipe declares no objects" in info.value.expected


def test_turn_exits_count_from_the_phase_start(tmp_path: Path, hand: HandConfig) -> None:
    """A pair's ``line_turn`` is a running value; a condition on it reads it relative to the
    first valid value of the phase, so each phase asks for its own 45 degrees."""
    data = {
        "recipe": "r",
        "objects": OBJECTS,
        "phases": [
            phase("a", exit=["estimate.cyl1_cyl2_line_turn < -0.5"]),
            phase("b", exit=["estimate.cyl1_cyl2_line_turn < -0.5"]),
            phase("c"),
        ],
    }
    runner = RecipeRunner(load_recipe(write(tmp_path, data), hand), 9)
    zero = np.zeros(9)
    est = [NAN] * 6  # one pair, two objects
    turn_index = FIRST_PAIR_TURN
    t = 0.0
    names = []
    for value in [NAN, NAN, 2.0, 1.8, 1.4, 1.4, 1.2, 1.0, 0.8]:
        est[turn_index] = value
        runner.step(t, zero, zero, est)
        names.append(runner.phase_name)
        t += 0.001
    # a: starts counting at 2.0 (the first valid value), leaves below 1.5 (at 1.4);
    # b: counts from 1.4 (its first tick), leaves below 0.9 (at 0.8)
    assert names == ["a", "a", "a", "a", "b", "b", "b", "b", "c"]
