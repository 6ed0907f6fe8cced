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
from handctl.estimator import NAN, ObjectEstimator, advance_turn
from handctl.recipes.loader import load_recipe
from handctl.recipes.runner import RecipeRunner
from handctl.recipes.schema import ESTIMATES, RecipeObject

R = 0.0175  # m: the object that fits the square cage below exactly
H = (0.008, 0.0075, 0.007)  # m: half-thicknesses of the default hand's links


def boxed_hand(hand: HandConfig) -> HandConfig:
    """The default hand with link lengths chosen so that, at angles (0, ±π/2, ±π/2), each side
    forms a square cage under the palm that holds a cylinder of radius R exactly: proximal link
    down, middle link across, distal link up to the palm, palm on top."""
    lengths = (2 * R + H[1], 2 * R + H[0] + H[2], 2 * R + H[1])

    def fix(finger: FingerConfig) -> FingerConfig:
        joints = tuple(dataclasses.replace(j, link_length=length, half_thickness=h)
                       for j, length, h in zip(finger.joints, lengths, H, strict=True))
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


def test_a_radius_ten_percent_off_moves_the_estimate_very_little(hand: HandConfig) -> None:
    small = (RecipeObject("cyl1", 0.9 * R), RecipeObject("cyl2", 0.9 * R))
    est = ObjectEstimator(boxed_hand(hand), small)
    out = settle(est, BOX_ANGLES)
    assert est.valid
    # the clearance absorbs the radius error, the centre stays where it is
    assert est.clearance[0] == pytest.approx(0.1 * R, abs=2e-4)
    assert out[2] == pytest.approx(-0.05 + H[0] + R, abs=2e-4)
    assert out[3] == pytest.approx(-R, abs=2e-4)


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


def test_the_estimator_needs_a_pair(hand: HandConfig) -> None:
    with pytest.raises(ValueError, match="pair"):
        ObjectEstimator(hand, (RecipeObject("cyl1", 0.02),))


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
    return {"name": name, "torques": dict.fromkeys(joints, 0.1), "ramp_s": 0.1, "max_s": 1.0,
            **extra}


OBJECTS = [{"name": "cyl1", "radius": 0.02}, {"name": "cyl2", "radius": 0.02}]


def test_objects_are_loaded_in_order(tmp_path: Path, hand: HandConfig) -> None:
    recipe = load_recipe(write(tmp_path, {"recipe": "r", "objects": OBJECTS,
                                          "phases": [phase("a")]}), hand)
    assert recipe.objects == (RecipeObject("cyl1", 0.02), RecipeObject("cyl2", 0.02))


@pytest.mark.parametrize(("objects", "key", "expected"), [
    ([OBJECTS[0]], "objects", "a list of 2 mappings"),
    ([OBJECTS[0], OBJECTS[0]], "objects[1].name", "a name not used"),
    ([OBJECTS[0], {"name": "cyl2", "radius": -0.01}], "objects[1].radius", "> 0"),
    ([OBJECTS[0], {"name": "cyl2", "radius": 0.02, "colour": "red"}], "objects[1]", "colour"),
    ([OBJECTS[0], {"name": "cyl2"}], "objects[1].radius", ""),
])
def test_bad_objects_are_refused_naming_the_key(tmp_path: Path, hand: HandConfig,
                                                objects: list[Any], key: str,
                                                expected: str) -> None:
    path = write(tmp_path, {"recipe": "r", "objects": objects, "phases": [phase("a")]})
    with pytest.raises(ConfigError) as info:
        load_recipe(path, hand)
    assert info.value.key.startswith(key)
    assert expected in str(info.value)


def test_estimates_without_objects_are_refused(tmp_path: Path, hand: HandConfig) -> None:
    path = write(tmp_path, {"recipe": "r", "phases": [
        phase("a", exit=["estimate.centre_line_turn < -0.7"])]})
    with pytest.raises(ConfigError) as info:
        load_recipe(path, hand)
    assert info.value.key == "objects"
    assert "centre_line_turn" in info.value.expected


def test_turn_exits_count_from_the_phase_start(tmp_path: Path, hand: HandConfig) -> None:
    """``centre_line_turn`` is a running value; a condition on it reads it relative to the
    first valid value of the phase, so each phase asks for its own 45 degrees."""
    data = {"recipe": "r", "objects": OBJECTS, "phases": [
        phase("a", exit=["estimate.centre_line_turn < -0.5"]),
        phase("b", exit=["estimate.centre_line_turn < -0.5"]), phase("c")]}
    runner = RecipeRunner(load_recipe(write(tmp_path, data), hand), 9)
    zero = np.zeros(9)
    est = [NAN] * len(ESTIMATES)
    turn_index = ESTIMATES.index("centre_line_turn")
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
