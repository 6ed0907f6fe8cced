"""A pose hold's integral (``pose.integral``): friction the model does not know must not hold
a finger short of the pose the nominal hand rests in. It grows only once the phase's ramp is
done, only on a joint that has stopped and only the way the phase's torque pushes the joint,
stays within its bound, starts again in each phase, and what it reached is where the next
phase's ramp starts from."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from handctl.config import HandConfig
from handctl.errors import ConfigError
from handctl.online.recipes.runner import RecipeRunner

from .test_runner_feedback import DT, JOINTS, RAMP, TORQUES, _recipe

REST = 0.1  # rad, every joint's rest pose in these tests
GAIN = 2.0  # N·m/(rad·s)
BOUND = 0.05  # N·m
STILL = 0.1  # rad/s
#: which way the phase's torque pushes each joint: the only way the integral may push it
WAY = np.sign(TORQUES)


def _pose(**integral: object) -> dict[str, object]:
    """A pose hold whose spring pulls towards 0 (the angle fed), so only the integral moves
    the torque, towards a rest pose of ``REST`` on every joint."""
    settings: dict[str, object] = {
        "rest": dict.fromkeys(JOINTS, REST),
        "gain": GAIN,
        "max": BOUND,
        "still_rate": STILL,
        **integral,
    }
    return {"pose": {"angles": dict.fromkeys(JOINTS, 0.0), "stiffness": 0.5, "integral": settings}}


def _feed(runner: RecipeRunner, angles: np.ndarray, t: float = 0.0) -> tuple[float, np.ndarray]:
    """Feed the joint angles of each row, one tick each; returns the time and the torques."""
    out = np.zeros(9)
    for row in angles:
        out = runner.step(t, row, np.zeros(9)).copy()
        t += DT
    return t, out


def _still(seconds: float) -> np.ndarray:
    return np.zeros((round(seconds / DT), 9))


def test_the_integral_grows_on_a_stopped_joint_only_once_the_ramp_is_done(
    tmp_path: Path, hand: HandConfig
) -> None:
    runner = RecipeRunner(_recipe(tmp_path, hand, _pose(), objects=False), 9)
    t, out = _feed(runner, _still(RAMP))
    # the ramp's last tick, 49 of 50 in: the torques so far and no integral yet
    assert out == pytest.approx(np.array(TORQUES) * (RAMP - DT) / RAMP, abs=1e-12)
    _, out = _feed(runner, _still(0.1), t)
    grown = out - np.array(TORQUES)
    # 0.1 s of a 0.1 rad error at 2 N·m/(rad·s): 0.02 N·m, to within the tick the ramp ends
    # on, on the joints the phase's torque pushes the same way; none on the others
    closing = WAY > 0
    assert grown[closing] == pytest.approx(GAIN * REST * 0.1, abs=GAIN * REST * 2 * DT)
    assert np.all(grown[~closing] == 0.0)


def test_the_integral_stays_within_its_bound(tmp_path: Path, hand: HandConfig) -> None:
    runner = RecipeRunner(_recipe(tmp_path, hand, _pose(), objects=False), 9)
    _, out = _feed(runner, _still(1.0))
    assert out - np.array(TORQUES) == pytest.approx(np.where(WAY > 0, BOUND, 0.0))
    # past the rest pose: back to zero on the joints pushed towards it, and on the joints
    # pushed the other way, on to the bound that way
    _, out = _feed(runner, np.full((2000, 9), 2 * REST), 1.0)
    spring = 0.5 * (0.0 - 2 * REST)
    assert out - np.array(TORQUES) == pytest.approx(spring + np.where(WAY < 0, -BOUND, 0.0))


def test_a_moving_joint_winds_up_no_integral(tmp_path: Path, hand: HandConfig) -> None:
    """A joint still on its way (faster than ``still_rate``) is not held back by friction:
    integrating its distance would only overshoot the pose."""
    runner = RecipeRunner(_recipe(tmp_path, hand, _pose(), objects=False), 9)
    speed = 4 * STILL
    ticks = round(0.5 / DT)
    angles = np.outer(np.arange(ticks) * speed * DT, np.ones(9)) - 0.1
    _, out = _feed(runner, angles)
    spring = 0.5 * (0.0 - angles[-1])
    damper = 0.0  # the pose hold has no damping here
    assert out - np.array(TORQUES) == pytest.approx(spring - damper, abs=1e-9)


def test_the_next_phase_ramps_from_the_integral_reached(tmp_path: Path, hand: HandConfig) -> None:
    """Leaving the phase is no step in torque: the next ramp starts from what was proposed,
    integral included, and the integral itself starts again from zero in the next phase."""
    runner = RecipeRunner(_recipe(tmp_path, hand, _pose(), objects=False, max_s=0.5), 9)
    t, last = _feed(runner, _still(0.5))
    assert last - np.array(TORQUES) == pytest.approx(np.where(WAY > 0, BOUND, 0.0))
    _, first = _feed(runner, _still(DT), t)
    assert runner.phase_name == "after"
    assert first == pytest.approx(last, abs=1e-3)
    _, settled = _feed(runner, _still(2 * RAMP), t + DT)
    assert settled == pytest.approx(np.array(TORQUES))


def test_the_integral_is_deterministic(tmp_path: Path, hand: HandConfig) -> None:
    recipe = _recipe(tmp_path, hand, _pose(), objects=False)
    rng = np.random.default_rng(3)
    angles = np.cumsum(rng.normal(0.0, 2e-4, (600, 9)), axis=0)
    runs = [_feed(RecipeRunner(recipe, 9), angles)[1] for _ in range(2)]
    assert np.array_equal(runs[0], runs[1])


@pytest.mark.parametrize(
    ("integral", "key"),
    [
        ({"max": 50.0}, "phases[0].pose.integral.max"),
        ({"max": 0.0}, "phases[0].pose.integral.max"),
        ({"gain": -1.0}, "phases[0].pose.integral.gain"),
        ({"still_rate": 0.0}, "phases[0].pose.integral.still_rate"),
        ({"rest": dict.fromkeys(JOINTS[1:], REST)}, f"phases[0].pose.integral.rest.{JOINTS[0]}"),
        (
            {"rest": {**dict.fromkeys(JOINTS, REST), "f2_j2": 9.0}},
            "phases[0].pose.integral.rest.f2_j2",
        ),
        ({"speed": 1.0}, "phases[0].pose.integral.speed"),
    ],
)
def test_a_bad_integral_is_refused_naming_the_key(
    tmp_path: Path, hand: HandConfig, integral: dict[str, object], key: str
) -> None:
    with pytest.raises(ConfigError) as info:
        _recipe(tmp_path, hand, _pose(**integral), objects=False)
    assert info.value.key == key


def test_a_finger_past_its_rest_pose_grows_no_integral(tmp_path: Path, hand: HandConfig) -> None:
    """A finger with a joint that went further than the rest pose (the way the phase's torque
    pushes it) is not held back by friction, whatever its other joints do: it has closed onto
    the objects. Its joints grow no integral; a finger short of the pose still does."""
    runner = RecipeRunner(_recipe(tmp_path, hand, _pose(), objects=False), 9)
    angles = _still(0.5)
    angles[:, 0] = 2 * REST  # f1_j1, pushed the + way, past its rest pose of REST
    _, out = _feed(runner, angles)
    grown = out - np.array(TORQUES) - 0.5 * (0.0 - angles[-1])
    assert np.all(grown[0:3] == 0.0)  # finger 1: none, though f1_j2 and f1_j3 are short
    assert grown[3:6] == pytest.approx(np.full(3, BOUND))  # finger 2: short, pushed on
