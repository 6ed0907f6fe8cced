"""Feedback inside a phase: the turn-rate loop scales the phase's torque within its range from
the estimated centre-line rate (down when the pair turns too fast, up when it stalls, held
while the estimate is invalid), a pose hold adds a joint-space spring and damper, and a
phase's ``joint_damping`` opposes every joint's velocity. All are functions of what the
runner is fed, so the same feed gives the same torques."""

from __future__ import annotations

import math
from collections.abc import Mapping
from pathlib import Path

import numpy as np
import pytest
import yaml

from handctl.config import HandConfig
from handctl.errors import ConfigError
from handctl.online.recipes.guard import GUARD_VELOCITY_SPAN_S
from handctl.online.recipes.loader import load_recipe
from handctl.online.recipes.runner import RecipeRunner
from handctl.online.recipes.schema import FIRST_PAIR_TURN, Recipe, RecipeObject, estimate_names

from .one_turn import one_turn_template

JOINTS = ["f1_j1", "f1_j2", "f1_j3", "f2_j1", "f2_j2", "f2_j3", "f3_j1", "f3_j2", "f3_j3"]
TORQUES = [0.2, 0.1, 0.05, 0.2, 0.1, 0.05, -0.2, -0.1, -0.05]
DT = 0.001
RAMP = 0.05
#: the estimates of the recipe's two objects a and b (one pair)
ESTIMATES = estimate_names((RecipeObject("a", 0.02), RecipeObject("b", 0.02)), ((0, 1),))
TURN = FIRST_PAIR_TURN


def _recipe(
    tmp_path: Path,
    hand: HandConfig,
    phase: Mapping[str, object],
    objects: bool = True,
    max_s: float = 10.0,
) -> Recipe:
    data: dict[str, object] = {
        "recipe": "feedback",
        "phases": [
            {
                "name": "turn",
                "torques": dict(zip(JOINTS, TORQUES, strict=True)),
                "ramp_s": RAMP,
                "max_s": max_s,
                "on_timeout": "next",
                **phase,
            },
            {
                "name": "after",
                "torques": dict(zip(JOINTS, TORQUES, strict=True)),
                "ramp_s": RAMP,
                "max_s": 10.0,
                "on_timeout": "next",
            },
        ],
    }
    if objects:
        data["objects"] = [{"name": "a", "radius": 0.02}, {"name": "b", "radius": 0.02}]
    path = tmp_path / "feedback.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return load_recipe(path, hand)


def _estimates(turn: float) -> list[float]:
    out = [math.nan] * len(ESTIMATES)
    out[TURN] = turn
    return out


def _drive(
    runner: RecipeRunner,
    rate_deg_s: float,
    seconds: float,
    t0: float = 0.0,
    turn0: float = 0.0,
    valid: bool = True,
) -> tuple[float, np.ndarray, float]:
    """Feed a pair turning at ``rate_deg_s``; returns the time, the last torques, the turn."""
    angle = np.zeros(9)
    out = np.zeros(9)
    t, turn = t0, turn0
    for _ in range(round(seconds / DT)):
        est = _estimates(turn if valid else math.nan)
        out = runner.step(t, angle, np.zeros(9), est).copy()
        t += DT
        turn += math.radians(rate_deg_s) * DT
    return t, out, turn


TURN_RATE: dict[str, object] = {"turn_rate": {"rate_deg_s": -45, "scale": [0.5, 1.5]}}


def test_too_fast_scales_the_torque_down_to_its_least(tmp_path: Path, hand: HandConfig) -> None:
    runner = RecipeRunner(_recipe(tmp_path, hand, TURN_RATE), 9)
    _, out, _ = _drive(runner, -400.0, 1.0)
    assert runner.scale == pytest.approx(0.5)
    assert out == pytest.approx(0.5 * np.array(TORQUES))


def test_a_stall_scales_the_torque_up_to_its_most(tmp_path: Path, hand: HandConfig) -> None:
    runner = RecipeRunner(_recipe(tmp_path, hand, TURN_RATE), 9)
    _, out, _ = _drive(runner, 0.0, 1.0)
    assert runner.scale == pytest.approx(1.5)
    assert out == pytest.approx(1.5 * np.array(TORQUES))


def test_the_wanted_rate_keeps_the_planned_torque(tmp_path: Path, hand: HandConfig) -> None:
    runner = RecipeRunner(_recipe(tmp_path, hand, TURN_RATE), 9)
    # the rate estimate takes a few of its time constants to settle from zero
    _drive(runner, -45.0, 1.0)
    assert runner.turn_rate == pytest.approx(math.radians(-45.0), rel=1e-3)
    assert 0.95 < runner.scale < 1.5
    # a turn the wrong way is a turn too slow the right way: more torque, not less
    runner = RecipeRunner(_recipe(tmp_path, hand, TURN_RATE), 9)
    _drive(runner, +45.0, 1.0)
    assert runner.scale == pytest.approx(1.5)


def test_the_next_phase_ramps_from_the_scaled_torque(tmp_path: Path, hand: HandConfig) -> None:
    """Leaving a phase with feedback is no step in torque: the next phase's ramp starts from
    what was proposed, not from the phase's planned torque."""
    runner = RecipeRunner(_recipe(tmp_path, hand, TURN_RATE, max_s=0.5), 9)
    t, before, turn = _drive(runner, -400.0, 0.5)
    assert runner.phase_name == "turn" and runner.scale == pytest.approx(0.5)
    _, after, _ = _drive(runner, -400.0, 2 * DT, t, turn)
    assert runner.phase_name == "after"
    assert np.max(np.abs(after - before)) < 0.01


def test_an_invalid_estimate_holds_the_scale(tmp_path: Path, hand: HandConfig) -> None:
    runner = RecipeRunner(_recipe(tmp_path, hand, TURN_RATE), 9)
    t, _, turn = _drive(runner, -400.0, 0.3)
    held = runner.scale
    assert held < 1.0
    _drive(runner, -400.0, 0.5, t, turn, valid=False)
    assert runner.scale == held


def test_the_scale_moves_within_the_ramp_without_an_integral(
    tmp_path: Path, hand: HandConfig
) -> None:
    """While the phase's torque ramps in, the pair has not begun to turn: a stall then is no
    reason to wind the integral up."""
    runner = RecipeRunner(
        _recipe(
            tmp_path,
            hand,
            {
                "turn_rate": {
                    "rate_deg_s": 45,
                    "scale": [0.5, 3.0],
                    "gain": 0.0,
                    "integral_per_s": 5.0,
                }
            },
        ),
        9,
    )
    _drive(runner, 0.0, RAMP * 0.9)
    assert runner.scale == 1.0


def test_a_pose_hold_adds_a_spring_and_a_damper(tmp_path: Path, hand: HandConfig) -> None:
    pose = {"angles": dict.fromkeys(JOINTS, 0.2), "stiffness": 0.5, "damping": 0.01}
    runner = RecipeRunner(_recipe(tmp_path, hand, {"pose": pose}, objects=False), 9)
    angle = np.zeros(9)
    t = 0.0
    out = np.zeros(9)
    for _ in range(round(2 * RAMP / DT)):  # at rest, past the ramp
        out = runner.step(t, angle, np.zeros(9)).copy()
        t += DT
    assert out == pytest.approx(np.array(TORQUES) + 0.5 * 0.2)
    # moving towards the pose at 1 rad/s: the damper takes some back
    for _ in range(200):
        angle += 1.0 * DT
        out = runner.step(t, angle, np.zeros(9)).copy()
        t += DT
    expected = np.array(TORQUES) + 0.5 * (0.2 - angle) - 0.01 * 1.0
    assert out == pytest.approx(expected, abs=1e-4)


def _move(
    runner: RecipeRunner,
    speed: float,
    seconds: float,
    t: float = 0.0,
    angle: np.ndarray | None = None,
    dt: float = DT,
) -> tuple[float, np.ndarray, np.ndarray]:
    """Feed every joint moving at ``speed`` (rad/s) every ``dt`` (s); returns the time, the
    angles, the last torques."""
    angle = np.zeros(9) if angle is None else angle
    out = np.zeros(9)
    for _ in range(round(seconds / dt)):
        out = runner.step(t, angle, np.zeros(9)).copy()
        angle = angle + speed * dt
        t += dt
    return t, angle, out


def test_injected_damping_opposes_every_joint_s_velocity(tmp_path: Path, hand: HandConfig) -> None:
    runner = RecipeRunner(_recipe(tmp_path, hand, {"joint_damping": 0.03}, objects=False), 9)
    _, _, out = _move(runner, 0.0, 2 * RAMP)
    assert out == pytest.approx(np.array(TORQUES))  # at rest: the planned torque
    _, _, out = _move(runner, 2.0, 0.2, 2 * RAMP)  # past ten of the velocity's time constants
    assert out == pytest.approx(np.array(TORQUES) - 0.03 * 2.0, abs=1e-4)
    assert np.all(runner.damping == 0.03)


@pytest.mark.parametrize("dt", [DT, 0.004])
def test_injected_damping_acts_on_a_speed_7_ms_old_at_most(
    tmp_path: Path, hand: HandConfig, dt: float
) -> None:
    """A damper acts through the drive's lag plus its velocity's own, and the most a lightly
    damped joint tolerates falls with that lag: the damping reads the line through the angles
    of the last 7 ms (``GUARD_VELOCITY_SPAN_S``), whole 7 ms after a new speed, where a 10 ms
    low-pass would still be at little more than half of it. At 250 Hz as at 1 kHz: counted in
    eight ticks, it was 28 ms long there."""
    recipe = _recipe(tmp_path, hand, {"joint_damping": 0.03}, objects=False)
    runner = RecipeRunner(recipe, 9, period_s=dt)
    t, angle, _ = _move(runner, 0.0, 2 * RAMP, dt=dt)
    ticks = round(GUARD_VELOCITY_SPAN_S / dt)
    t, angle, out = _move(runner, 2.0, ticks * dt, t, angle, dt=dt)  # the line not yet whole
    assert out != pytest.approx(np.array(TORQUES) - 0.03 * 2.0, abs=1e-6)
    _, _, out = _move(runner, 2.0, dt, t, angle, dt=dt)
    assert out == pytest.approx(np.array(TORQUES) - 0.03 * 2.0, abs=1e-6)


def test_injected_damping_per_joint_damps_only_the_joints_named(
    tmp_path: Path, hand: HandConfig
) -> None:
    """A phase that presses a distal joint into its guard's band damps that joint alone:
    the others keep the planned torque whatever their speed, so the pair's roll in the next
    phase is not slowed by damping nobody asked for."""
    damping = {name: (0.005 if name.endswith("_j3") else 0.0) for name in JOINTS}
    recipe = _recipe(tmp_path, hand, {"joint_damping": damping}, objects=False)
    assert recipe.phases[0].joint_damping == tuple(damping[n] for n in hand.joint_names)
    runner = RecipeRunner(recipe, 9)
    _, _, out = _move(runner, 2.0, 0.2 + 2 * RAMP)
    wanted = np.array(TORQUES) - 2.0 * np.array([damping[n] for n in JOINTS])
    assert out == pytest.approx(wanted, abs=1e-4)
    assert not np.allclose(out, np.array(TORQUES) - 0.005 * 2.0, atol=1e-4)


def test_injected_damping_fades_with_the_next_phase_s_ramp(
    tmp_path: Path, hand: HandConfig
) -> None:
    """Leaving a damped phase for one without is no step in torque: the coefficient follows
    the ramp down to the next phase's."""
    runner = RecipeRunner(
        _recipe(tmp_path, hand, {"joint_damping": 0.05}, objects=False, max_s=0.3), 9
    )
    t, angle, before = _move(runner, 2.0, 0.3)
    assert runner.phase_name == "turn"
    t, angle, after = _move(runner, 2.0, 2 * DT, t, angle)
    assert runner.phase_name == "after"
    assert np.max(np.abs(after - before)) < 0.01
    assert np.all((runner.damping > 0.0) & (runner.damping < 0.05))
    _, _, out = _move(runner, 2.0, RAMP, t, angle)
    assert np.all(runner.damping == 0.0)
    assert out == pytest.approx(np.array(TORQUES))


def test_injected_damping_that_does_not_fade_ends_with_its_phase(
    tmp_path: Path, hand: HandConfig
) -> None:
    """Damping meant for one phase's grasp (``joint_damping_fades: false``) is gone when the
    next phase begins, not faded over its ramp: that phase's motion is the planned one from
    its first tick. The planner's hand-over between phases says the same."""
    recipe = _recipe(
        tmp_path,
        hand,
        {"joint_damping": 0.05, "joint_damping_fades": False},
        objects=False,
        max_s=0.3,
    )
    assert recipe.phases[0].joint_damping_fades is False
    assert recipe.phases[1].joint_damping_fades is True
    runner = RecipeRunner(recipe, 9)
    t, angle, _ = _move(runner, 2.0, 0.3 - DT)
    assert runner.phase_name == "turn"
    assert np.all(runner.damping == 0.05)
    assert np.all(runner.handover().damping == 0.0)
    t, angle, out = _move(runner, 2.0, 2 * DT, t, angle)
    assert runner.phase_name == "after"
    assert np.all(runner.damping == 0.0)
    assert out == pytest.approx(np.array(TORQUES), abs=1e-4)


BRAKE: dict[str, object] = {"brake": {"rate_deg_s": 90, "joint_damping": 0.04}}


def _tumble(runner: RecipeRunner, rate_deg_s: float, speed: float, seconds: float) -> np.ndarray:
    """Feed a pair turning at ``rate_deg_s`` while every joint moves at ``speed`` (rad/s);
    returns the last torques."""
    angle, out, turn = np.zeros(9), np.zeros(9), 0.0
    for k in range(round(seconds / DT)):
        out = runner.step(k * DT, angle, np.zeros(9), _estimates(turn)).copy()
        angle = angle + speed * DT
        turn += math.radians(rate_deg_s) * DT
    return out


@pytest.mark.parametrize(
    ("rate_deg_s", "damping"),
    [(0.0, 0.0), (-60.0, 0.0), (-135.0, 0.02), (-400.0, 0.04), (400.0, 0.04)],
)
def test_the_brake_damps_the_joints_as_the_pair_turns_faster(
    tmp_path: Path, hand: HandConfig, rate_deg_s: float, damping: float
) -> None:
    """None at or below the brake's rate, its full damping from twice that rate, either way
    round: a tumble the wrong way is a tumble too."""
    runner = RecipeRunner(_recipe(tmp_path, hand, BRAKE), 9)
    out = _tumble(runner, rate_deg_s, 2.0, 0.5)
    assert runner.damping == pytest.approx(damping, abs=1e-6)
    assert out == pytest.approx(np.array(TORQUES) - damping * 2.0, abs=1e-4)


def test_the_brake_holds_no_damping_while_the_estimate_is_invalid(
    tmp_path: Path, hand: HandConfig
) -> None:
    runner = RecipeRunner(_recipe(tmp_path, hand, BRAKE), 9)
    _drive(runner, -400.0, 0.5, valid=False)
    assert np.all(runner.damping == 0.0)


@pytest.mark.parametrize(("speed", "damping"), [(0.5, 0.0), (1.0, 0.0), (1.5, 0.02), (3.0, 0.04)])
def test_a_brake_with_a_joint_rate_damps_the_joints_as_they_move_faster(
    tmp_path: Path, hand: HandConfig, speed: float, damping: float
) -> None:
    """With ``joint_rate`` a pair at rest by its estimate (or a stale one: an open cage)
    does not keep the brake off while the fingers fly: none at or below that joint speed,
    the brake's full damping from twice it."""
    phase = {"brake": {"rate_deg_s": 90, "joint_damping": 0.04, "joint_rate": 1.0}}
    runner = RecipeRunner(_recipe(tmp_path, hand, phase), 9)
    out = _tumble(runner, 0.0, speed, 0.5)
    assert runner.damping == pytest.approx(damping, abs=1e-6)
    assert out == pytest.approx(np.array(TORQUES) - damping * speed, abs=1e-4)
    runner = RecipeRunner(_recipe(tmp_path, hand, BRAKE), 9)  # without: the pair's rate alone
    _tumble(runner, 0.0, speed, 0.5)
    assert np.all(runner.damping == 0.0)


PACED: dict[str, object] = {"paced_ramp": {"rate_deg_s": -90}}


def test_a_paced_ramp_advances_at_the_ramp_s_speed_while_the_pair_is_slow(
    tmp_path: Path, hand: HandConfig
) -> None:
    """A pair at rest, or turning the wrong way, is a pair the torque has not turned yet: the
    ramp goes on as the recipe's own would, to the phase's torque; a pair turning the wanted
    way, slower than wanted, slows it in proportion."""
    for rate in (0.0, +200.0, -30.0):
        runner = RecipeRunner(_recipe(tmp_path, hand, PACED), 9)
        t, _, turn = _drive(runner, rate, RAMP / 2)
        assert runner.pace == pytest.approx(0.5 if rate != -30.0 else 0.5 * 2 / 3, abs=0.1)
        _, out, _ = _drive(runner, rate, 2 * RAMP, t, turn)
        assert runner.pace == 1.0
        assert out == pytest.approx(np.array(TORQUES))


def test_a_paced_ramp_without_an_estimate_is_the_recipe_s_own_ramp(
    tmp_path: Path, hand: HandConfig
) -> None:
    """No valid estimate (the pair not caged yet): nothing says the pair runs, and the
    torque is the plain ramp's, tick for tick."""
    paced = RecipeRunner(_recipe(tmp_path, hand, PACED), 9)
    plain = RecipeRunner(_recipe(tmp_path, hand, {}), 9)
    for k in range(round(2 * RAMP / DT)):
        t = k * DT
        a = paced.step(t, np.zeros(9), np.zeros(9), _estimates(math.nan))
        b = plain.step(t, np.zeros(9), np.zeros(9), _estimates(math.nan))
        assert a == pytest.approx(b, abs=1e-12)


def test_a_paced_ramp_goes_back_while_the_pair_turns_too_fast(
    tmp_path: Path, hand: HandConfig
) -> None:
    """Too fast the wanted way: the torque goes back along its segment, towards the previous
    phase's (here none: zero), and no further."""
    runner = RecipeRunner(_recipe(tmp_path, hand, PACED), 9)
    t, _, turn = _drive(runner, 0.0, 2 * RAMP)
    assert runner.pace == 1.0
    _, out, _ = _drive(runner, -900.0, 0.2, t, turn)
    assert runner.pace == 0.0
    assert out == pytest.approx(np.zeros(9))


def test_a_paced_ramp_settles_where_the_pair_turns_at_the_wanted_rate(
    tmp_path: Path, hand: HandConfig
) -> None:
    """A pair whose rate follows the torque (here: in proportion to the fraction along the
    segment, 180°/s at the phase's torque) settles at the fraction that turns it at the
    wanted 90°/s."""
    runner = RecipeRunner(_recipe(tmp_path, hand, PACED), 9)
    t, turn = 0.0, 0.0
    for _ in range(2000):
        runner.step(t, np.zeros(9), np.zeros(9), _estimates(turn))
        turn -= math.radians(180.0) * runner.pace * DT
        t += DT
    assert runner.pace == pytest.approx(0.5, abs=0.02)
    assert runner.turn_rate == pytest.approx(math.radians(-90.0), rel=0.05)


def test_a_paced_ramp_goes_beyond_the_phase_s_torque_up_to_its_reach(
    tmp_path: Path, hand: HandConfig
) -> None:
    runner = RecipeRunner(
        _recipe(tmp_path, hand, {"paced_ramp": {"rate_deg_s": -90, "reach": 1.5}}), 9
    )
    _, out, _ = _drive(runner, 0.0, 4 * RAMP)
    assert runner.pace == 1.5
    assert out == pytest.approx(1.5 * np.array(TORQUES))


def test_a_paced_ramp_goes_back_when_a_joint_moves_too_fast(
    tmp_path: Path, hand: HandConfig
) -> None:
    """With ``joint_rate`` the joints count too: they are measured every tick, also while
    the pair's estimate is invalid (an open cage), and a pair turning slowly does not keep
    the torque up while a finger flies."""
    phase = {"paced_ramp": {"rate_deg_s": -90, "joint_rate": 1.0}}
    runner = RecipeRunner(_recipe(tmp_path, hand, phase), 9)
    _tumble(runner, 0.0, 0.5, 4 * RAMP)  # half the joint rate: on, at half the speed
    assert runner.pace == 1.0
    runner = RecipeRunner(_recipe(tmp_path, hand, phase), 9)
    _tumble(runner, 0.0, 3.0, 4 * RAMP)
    assert runner.pace == 0.0
    runner = RecipeRunner(_recipe(tmp_path, hand, PACED), 9)  # without: the pair alone
    _tumble(runner, 0.0, 3.0, 4 * RAMP)
    assert runner.pace == 1.0


def test_the_next_phase_ramps_from_the_paced_torque(tmp_path: Path, hand: HandConfig) -> None:
    runner = RecipeRunner(_recipe(tmp_path, hand, PACED, max_s=0.5), 9)
    t, _, turn = _drive(runner, 0.0, 0.3)
    t, before, turn = _drive(runner, -900.0, 0.02, t, turn)
    assert runner.phase_name == "turn" and 0.0 < runner.pace < 1.0
    t, _, turn = _drive(runner, -900.0, 0.5 - 0.32 - DT, t, turn)
    before = runner.feedback(t - DT, np.zeros(9), _estimates(turn)).copy()
    _, after, _ = _drive(runner, 0.0, 2 * DT, t, turn)
    assert runner.phase_name == "after"
    assert np.max(np.abs(after - before)) < 0.01


def test_a_torque_margin_multiplies_the_phase_s_torques(tmp_path: Path, hand: HandConfig) -> None:
    """The lift's and the hold's headroom for heavier objects: the runner proposes the
    phase's torques times its ``torque_margin``, ramped in as they are, and the next phase
    ramps from there."""
    runner = RecipeRunner(_recipe(tmp_path, hand, {"torque_margin": 1.3}, max_s=0.2), 9)
    angle = np.zeros(9)
    t, out = 0.0, np.zeros(9)
    while t < 0.2 - 1e-9:
        out = runner.step(t, angle, np.zeros(9)).copy()
        t = round(t + DT, 9)
    assert runner.phase_name == "turn"
    assert np.allclose(out, 1.3 * np.array(TORQUES))
    assert not np.any(np.abs(out) > np.array([j.tau_max for j in hand.joints]))
    out = runner.step(0.2, angle, np.zeros(9)).copy()  # the next phase, margin 1: from there
    assert runner.phase_name == "after"
    assert np.allclose(out, 1.3 * np.array(TORQUES), atol=0.01)
    t = 0.2 + RAMP + DT
    assert np.allclose(runner.step(t, angle, np.zeros(9)), TORQUES)


def test_a_margin_per_joint_multiplies_each_joint_s_torque(
    tmp_path: Path, hand: HandConfig
) -> None:
    """A lift's distal joints rest in their guard's band, held by its spring: a margin given
    per joint leaves them their planned torque while the joints that carry the load get
    headroom."""
    margin = {name: (1.0 if name.endswith("_j3") else 1.5) for name in JOINTS}
    recipe = _recipe(tmp_path, hand, {"torque_margin": margin}, max_s=0.2)
    assert recipe.phases[0].torque_margin == tuple(margin[n] for n in hand.joint_names)
    runner = RecipeRunner(recipe, 9)
    t, out = 0.0, np.zeros(9)
    while t < 0.2 - 1e-9:
        out = runner.step(t, np.zeros(9), np.zeros(9)).copy()
        t = round(t + DT, 9)
    assert runner.phase_name == "turn"
    wanted = np.array([margin[n] for n in JOINTS]) * np.array(TORQUES)
    assert np.allclose(out, wanted)
    assert not np.allclose(out, 1.5 * np.array(TORQUES))


def test_a_template_s_margin_per_joint_is_carried_into_the_compiled_recipe(
    tmp_path: Path, hand: HandConfig
) -> None:
    """``handctl plan`` writes a per-joint margin as the mapping it read, and the recipe's
    loader reads it back to the same factors in the config's joint order."""
    from handctl.planning.compile import PhasePlan, _compiled_phase, _phase_document

    margin = {name: (1.0 if name.endswith("_j3") else 1.4) for name in JOINTS}
    spec = one_turn_template(tmp_path, hand, TORQUES, {"torque_margin": margin})
    assert spec.torque_margin == tuple(margin[n] for n in hand.joint_names)
    phase = _compiled_phase(spec, tuple(TORQUES), hand)
    doc = _phase_document(PhasePlan(spec, phase, None, None, []), hand)
    assert doc["torque_margin"] == margin
    loaded = _recipe(tmp_path, hand, {"torque_margin": doc["torque_margin"]}).phases[0]
    assert loaded.torque_margin == spec.torque_margin


def test_a_template_s_damping_per_joint_is_carried_into_the_compiled_recipe(
    tmp_path: Path, hand: HandConfig
) -> None:
    """``handctl plan`` writes a per-joint ``joint_damping`` as the mapping it read, and the
    recipe's loader reads it back in the config's joint order."""
    from handctl.planning.compile import PhasePlan, _compiled_phase, _phase_document

    damping = {name: (0.005 if name.endswith("_j3") else 0.0) for name in JOINTS}
    spec = one_turn_template(
        tmp_path, hand, TORQUES, {"joint_damping": damping, "joint_damping_fades": False}
    )
    assert spec.joint_damping == tuple(damping[n] for n in hand.joint_names)
    assert spec.joint_damping_fades is False
    phase = _compiled_phase(spec, tuple(TORQUES), hand)
    assert phase.joint_damping == spec.joint_damping
    doc = _phase_document(PhasePlan(spec, phase, None, None, []), hand)
    assert doc["joint_damping"] == damping
    assert doc["joint_damping_fades"] is False
    loaded = _recipe(
        tmp_path,
        hand,
        {"joint_damping": doc["joint_damping"], "joint_damping_fades": False},
    ).phases[0]
    assert loaded.joint_damping == spec.joint_damping
    assert loaded.joint_damping_fades is False


def test_the_same_feed_gives_the_same_torques(tmp_path: Path, hand: HandConfig) -> None:
    recipe = _recipe(tmp_path, hand, TURN_RATE)
    rng = np.random.default_rng(1)
    turns = np.cumsum(rng.normal(-0.001, 0.003, 800))
    runs = []
    for _ in range(2):
        runner = RecipeRunner(recipe, 9)
        runs.append(
            np.array(
                [
                    runner.step(k * DT, np.zeros(9), np.zeros(9), _estimates(float(x))).copy()
                    for k, x in enumerate(turns)
                ]
            )
        )
    assert np.array_equal(runs[0], runs[1])


def _bad_per_joint(key: str, good: float, bad: float) -> list[tuple[dict[str, object], str, bool]]:
    """The ways a per-joint mapping of ``key`` goes wrong: a value out of range, a joint
    left out, a joint the hand does not have; each refused naming the joint."""
    return [
        ({key: {**dict.fromkeys(JOINTS, good), "f2_j3": bad}}, f"phases[0].{key}.f2_j3", False),
        ({key: dict.fromkeys(JOINTS[1:], good)}, f"phases[0].{key}.{JOINTS[0]}", False),
        ({key: {**dict.fromkeys(JOINTS, good), "f9_j1": good}}, f"phases[0].{key}.f9_j1", False),
    ]


@pytest.mark.parametrize(
    ("phase", "key", "objects"),
    [
        (
            {"turn_rate": {"rate_deg_s": -45, "scale": [1.2, 2.0]}},
            "phases[0].turn_rate.scale",
            True,
        ),
        (
            {"turn_rate": {"rate_deg_s": 0, "scale": [0.5, 2.0]}},
            "phases[0].turn_rate.rate_deg_s",
            True,
        ),
        ({"turn_rate": {"rate_deg_s": -45, "scale": [0.5, 2.0]}}, "phases[0].turn_rate", False),
        (
            {"pose": {"angles": dict.fromkeys(JOINTS, 5.0), "stiffness": 1.0}},
            "phases[0].pose.angles.f1_j1",
            False,
        ),
        ({"joint_damping": -0.01}, "phases[0].joint_damping", False),
        ({"brake": {"rate_deg_s": 90, "joint_damping": 0.03}}, "phases[0].brake", False),
        ({"brake": {"rate_deg_s": 0, "joint_damping": 0.03}}, "phases[0].brake.rate_deg_s", True),
        (
            {"brake": {"rate_deg_s": 90, "joint_damping": 0.5}},
            "phases[0].brake.joint_damping",
            True,
        ),
        ({"joint_damping": 1.0}, "phases[0].joint_damping", False),
        ({"joint_damping_fades": False}, "phases[0].joint_damping_fades", False),
        (
            {"joint_damping": 0.01, "joint_damping_fades": "no"},
            "phases[0].joint_damping_fades",
            False,
        ),
        *_bad_per_joint("joint_damping", 0.005, 0.5),
        ({"paced_ramp": {"rate_deg_s": -90}}, "phases[0].paced_ramp", False),
        ({"paced_ramp": {"rate_deg_s": 0}}, "phases[0].paced_ramp.rate_deg_s", True),
        ({"paced_ramp": {"rate_deg_s": -90, "reach": 0.5}}, "phases[0].paced_ramp.reach", True),
        ({"paced_ramp": {"rate_deg_s": -90, "back": 0}}, "phases[0].paced_ramp.back", True),
        (
            {"paced_ramp": {"rate_deg_s": -90, "joint_rate": -1}},
            "phases[0].paced_ramp.joint_rate",
            True,
        ),
        ({"paced_ramp": {"rate_deg_s": -90}, "ramp_s": 0}, "phases[0].ramp_s", True),
        (
            {"brake": {"rate_deg_s": 90, "joint_damping": 0.03, "joint_rate": 500}},
            "phases[0].brake.joint_rate",
            True,
        ),
        ({"torque_margin": 0.8}, "phases[0].torque_margin", False),
        ({"torque_margin": 2.5}, "phases[0].torque_margin", False),
        *_bad_per_joint("torque_margin", 1.2, 0.9),
    ],
)
def test_bad_feedback_is_refused_naming_the_key(
    tmp_path: Path, hand: HandConfig, phase: dict[str, object], key: str, objects: bool
) -> None:
    with pytest.raises(ConfigError) as info:
        _recipe(tmp_path, hand, phase, objects=objects)
    assert info.value.key == key
