"""Switching a turn on the pair's measured position: a phase whose exit reads the turn from
an earlier phase's start (``turn_from``), so that what one phase left undone the next takes
up; a phase that ends when the pair has stopped turning (``stall``) rather than on its
timeout; and a paced ramp that, while the pair's estimate is invalid, is paced by the
joints (``blind_joint_rate``) instead of the pair's last rate."""

from __future__ import annotations

import itertools
import math
from collections.abc import Mapping
from pathlib import Path

import numpy as np
import pytest
import yaml

from handctl.config import HandConfig
from handctl.errors import ConfigError
from handctl.online.recipes.loader import load_recipe
from handctl.online.recipes.runner import RecipeRunner
from handctl.online.recipes.schema import FIRST_PAIR_TURN, Recipe, RecipeObject, estimate_names

JOINTS = ["f1_j1", "f1_j2", "f1_j3", "f2_j1", "f2_j2", "f2_j3", "f3_j1", "f3_j2", "f3_j3"]
TORQUES = [0.2, 0.1, 0.05, 0.2, 0.1, 0.05, -0.2, -0.1, -0.05]
DT = 0.001
RAMP = 0.05
MAX_S = 3.0
ESTIMATES = estimate_names((RecipeObject("a", 0.02), RecipeObject("b", 0.02)), ((0, 1),))
STALL = {"turn_deg": 1.0, "window_s": 0.3}
TURN_EXIT = "estimate.a_b_line_turn < -1"


def _recipe(tmp_path: Path, hand: HandConfig, *phases: Mapping[str, object]) -> Recipe:
    """Turn phases named ``turn_1``, ``turn_2`` ... with ``phases``' keys, then ``after``."""
    names = [f"turn_{k}" for k in range(1, len(phases) + 1)] + ["after"]
    data = {
        "recipe": "switching",
        "objects": [{"name": "a", "radius": 0.02}, {"name": "b", "radius": 0.02}],
        "phases": [
            {
                "name": name,
                "torques": dict(zip(JOINTS, TORQUES, strict=True)),
                "ramp_s": RAMP,
                "max_s": MAX_S,
                "on_timeout": "next",
                **extra,
            }
            for name, extra in zip(names, [*phases, {}], strict=True)
        ],
    }
    path = tmp_path / "switching.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return load_recipe(path, hand)


def _estimates(turn: float) -> list[float]:
    out = [math.nan] * len(ESTIMATES)
    out[FIRST_PAIR_TURN] = turn
    return out


def _run(
    runner: RecipeRunner,
    rate_deg_s: float,
    seconds: float,
    joint_speed: float = 0.0,
    valid: bool = True,
) -> dict[str, float]:
    """Feed a pair turning at ``rate_deg_s`` and joints moving at ``joint_speed`` (rad/s);
    returns when each phase began (s)."""
    starts: dict[str, float] = {}
    angle = np.zeros(9)
    turn = 0.0
    for k in range(round(seconds / DT)):
        t = k * DT
        runner.step(t, angle, np.zeros(9), _estimates(turn if valid else math.nan))
        starts.setdefault(runner.phase_name, t)
        turn += math.radians(rate_deg_s) * DT
        angle = angle + joint_speed * DT
    return starts


def test_a_stalled_phase_ends_once_its_torque_is_in_and_the_pair_rests(
    tmp_path: Path, hand: HandConfig
) -> None:
    """A pair at rest: the window starts when the ramp is done, and the phase ends one
    window later, saying why; without ``stall`` it runs to its ``max_s``."""
    runner = RecipeRunner(_recipe(tmp_path, hand, {"stall": STALL}), 9)
    starts = _run(runner, 0.0, 1.0)
    assert starts["after"] == pytest.approx(RAMP + 0.3, abs=2 * DT)
    assert runner.records[0].exit.startswith("stalled")
    runner = RecipeRunner(_recipe(tmp_path, hand, {}), 9)
    assert "after" not in _run(runner, 0.0, 1.0)


def test_a_paced_phase_is_stalled_only_with_its_pace_at_its_reach(
    tmp_path: Path, hand: HandConfig
) -> None:
    """A pair turning too fast holds a paced ramp back: the torque is not fully in, and
    nothing says the phase's own torque would not turn the pair on."""
    phase = {"stall": STALL, "paced_ramp": {"rate_deg_s": -90}}
    runner = RecipeRunner(_recipe(tmp_path, hand, phase), 9)
    # too fast the wanted way: the pace goes back, never reaches 1
    assert "after" not in _run(runner, -1000.0, 1.0)
    runner = RecipeRunner(_recipe(tmp_path, hand, phase), 9)
    assert "after" in _run(runner, 0.0, 1.0)


@pytest.mark.parametrize(("rate_deg_s", "valid"), [(-5.0, True), (0.0, False)])
def test_a_turning_or_unseen_pair_is_not_stalled(
    tmp_path: Path, hand: HandConfig, rate_deg_s: float, valid: bool
) -> None:
    """A pair turning slowly (5 deg/s, more than 1 deg in 0.3 s) is still being turned; a
    pair whose estimate is invalid is not known to rest."""
    runner = RecipeRunner(_recipe(tmp_path, hand, {"stall": STALL}), 9)
    assert "after" not in _run(runner, rate_deg_s, 2.0, valid=valid)


def _turns_per_phase(runner: RecipeRunner, stop_first_at_deg: float) -> dict[str, float]:
    """Turn the pair at 100 deg/s: ``stop_first_at_deg`` in ``turn_1`` (then it rests until
    the phase ends), on in every later phase; returns how far each phase turned it (deg)."""
    angle = np.zeros(9)
    turn, t = 0.0, 0.0
    starts: dict[str, float] = {}
    while runner.phase_name != "after" and t < 4 * MAX_S:
        runner.step(t, angle, np.zeros(9), _estimates(turn))
        starts.setdefault(runner.phase_name, turn)
        if runner.phase_name != "turn_1" or turn > math.radians(-stop_first_at_deg):
            turn -= math.radians(100.0) * DT
        t += DT
    names = list(starts)
    return {a: math.degrees(starts[b] - starts[a]) for a, b in itertools.pairwise(names)}


def test_an_exit_reads_the_turn_from_the_phase_turn_from_names(
    tmp_path: Path, hand: HandConfig
) -> None:
    """The first phase stalls 10 deg short of its 45; the second, exiting on 90 deg since the
    first began, turns 55 and not 45; without ``turn_from``, 45 from its own start."""
    first = {"exit": ["estimate.a_b_line_turn < -0.7854"], "stall": STALL}
    second = {"exit": ["estimate.a_b_line_turn < -1.5708"], "turn_from": "turn_1"}
    runner = RecipeRunner(_recipe(tmp_path, hand, first, second), 9)
    assert _turns_per_phase(runner, 35.0)["turn_2"] == pytest.approx(-55.0, abs=0.5)
    assert runner.records[0].exit.startswith("stalled")
    own = {"exit": ["estimate.a_b_line_turn < -0.7854"]}
    runner = RecipeRunner(_recipe(tmp_path, hand, first, own), 9)
    assert _turns_per_phase(runner, 35.0)["turn_2"] == pytest.approx(-45.0, abs=0.5)


@pytest.mark.parametrize("stop_deg", [20.0, 35.0])
def test_an_exit_share_splits_what_is_left_evenly_wherever_the_last_phase_stopped(
    tmp_path: Path, hand: HandConfig, stop_deg: float
) -> None:
    """The first phase stops short at 20 or 35 deg; the second shares what is left of 180 deg
    with the third, so both turn (180 - stop) / 2, where a fixed exit at 135 deg gave the
    second all of the first's shortfall. The record says where the shared exit was."""
    first = {"exit": ["estimate.a_b_line_turn < -0.7854"], "stall": STALL}
    last = {"exit": ["estimate.a_b_line_turn < -3.1416"], "turn_from": "turn_1"}
    shared = {**last, "exit_share": 2}
    runner = RecipeRunner(_recipe(tmp_path, hand, first, shared, last), 9)
    turns = _turns_per_phase(runner, stop_deg)
    half = (180.0 - stop_deg) / 2
    assert turns["turn_2"] == pytest.approx(-half, abs=0.5)
    assert turns["turn_3"] == pytest.approx(-half, abs=0.5)
    said, at = runner.records[1].exit.rsplit(": at ", 1)
    assert said == f"{last['exit'][0]}, 1/2 of the rest"
    assert math.degrees(float(at)) == pytest.approx(-stop_deg - half, abs=0.2)
    fixed = {**last, "exit": ["estimate.a_b_line_turn < -2.3562"]}
    runner = RecipeRunner(_recipe(tmp_path, hand, first, fixed, last), 9)
    turns = _turns_per_phase(runner, stop_deg)
    assert turns["turn_2"] == pytest.approx(-(135.0 - stop_deg), abs=0.5)
    assert runner.records[1].exit == fixed["exit"][0]


def test_a_shared_exit_waits_for_the_pair_to_be_measured_in_its_phase(
    tmp_path: Path, hand: HandConfig
) -> None:
    """While the pair's estimate is invalid the share has no start, so the phase does not
    end on it (a guessed start would end it anywhere); from the first valid estimate the
    share is taken from there."""
    shared = {
        "exit": ["estimate.a_b_line_turn < -1.5708"],
        "turn_from": "turn_1",
        "exit_share": 2,
    }
    last = {"exit": ["estimate.a_b_line_turn < -3.1416"], "turn_from": "turn_1"}
    runner = RecipeRunner(_recipe(tmp_path, hand, {"exit": ["time > 0.1"]}, shared, last), 9)
    angle = np.zeros(9)
    for k in range(300):  # turn_1 seen at 0; turn_2 blind while the pair is far past its goal
        seen = k * DT < 0.05
        runner.step(k * DT, angle, np.zeros(9), _estimates(0.0 if seen else math.nan))
    assert runner.phase_name == "turn_2"
    t = 300 * DT
    for turn_deg in (-60.0, -60.0, -74.0, -76.0, -76.0):  # measured at 60: exits at 75
        runner.step(t, angle, np.zeros(9), _estimates(math.radians(turn_deg)))
        t += 0.01
    assert runner.phase_name == "turn_3"
    assert runner.records[1].exit.endswith(f"at {math.radians(-75.0):.4f}")


def test_a_blind_pace_goes_back_while_the_joints_run_and_the_cage_is_open(
    tmp_path: Path, hand: HandConfig
) -> None:
    """With the estimate invalid the pair's last rate says nothing; with
    ``blind_joint_rate`` the joints' speed sets the pace then (back while faster), and
    with the estimate valid the pair's rate alone, as without it."""
    blind = {"paced_ramp": {"rate_deg_s": -90, "blind_joint_rate": 2.0}}
    plain = {"paced_ramp": {"rate_deg_s": -90}}
    runner = RecipeRunner(_recipe(tmp_path, hand, blind), 9)
    _run(runner, 0.0, 4 * RAMP, joint_speed=4.0, valid=False)
    assert runner.pace == 0.0
    runner = RecipeRunner(_recipe(tmp_path, hand, plain), 9)
    _run(runner, 0.0, 4 * RAMP, joint_speed=4.0, valid=False)
    assert runner.pace == 1.0
    runner = RecipeRunner(_recipe(tmp_path, hand, blind), 9)
    _run(runner, 0.0, 4 * RAMP, joint_speed=4.0, valid=True)
    assert runner.pace == 1.0


def test_a_blind_brake_damps_while_the_joints_run_and_the_cage_is_open(
    tmp_path: Path, hand: HandConfig
) -> None:
    """With the estimate invalid, a brake with ``blind_joint_rate`` brakes on the joints'
    speed (full at twice the rate); without it, on the pair's last rate (here at rest)."""
    brake = {"rate_deg_s": 120, "joint_damping": 0.03}
    runner = RecipeRunner(_recipe(tmp_path, hand, {"brake": {**brake, "blind_joint_rate": 2.0}}), 9)
    _run(runner, 0.0, 4 * RAMP, joint_speed=4.0, valid=False)
    assert runner.damping == pytest.approx(0.03)
    runner = RecipeRunner(_recipe(tmp_path, hand, {"brake": brake}), 9)
    _run(runner, 0.0, 4 * RAMP, joint_speed=4.0, valid=False)
    assert np.all(runner.damping == 0.0)


@pytest.mark.parametrize(
    ("phases", "key"),
    [
        (({}, {"turn_from": "turn_3"}), "phases[1].turn_from"),
        (({"turn_from": "turn_2"}, {}), "phases[0].turn_from"),
        (({"stall": {"turn_deg": 0, "window_s": 0.3}},), "phases[0].stall.turn_deg"),
        (({"exit": ["time > 1"], "exit_share": 2},), "phases[0].exit_share"),
        (({"exit": ["time > 1"], "exit_share": 1},), "phases[0].exit_share"),
        (({"exit": [TURN_EXIT], "exit_share": 2},), "phases[0].exit_share"),  # none after it
        (
            ({"exit": [TURN_EXIT], "exit_share": 3}, {"exit": [TURN_EXIT], "turn_from": "turn_1"}),
            "phases[0].exit_share",  # one short
        ),
        (
            ({"exit": [TURN_EXIT], "exit_share": 2}, {"exit": [TURN_EXIT]}),
            "phases[0].exit_share",  # the next reads its turn from its own start
        ),
        (
            (
                {"exit": [TURN_EXIT], "exit_share": 2},
                {"exit": ["estimate.a_b_line_turn > 1"], "turn_from": "turn_1"},
            ),
            "phases[0].exit_share",  # the next waits for the turn the other way
        ),
        (
            (
                {"exit": [TURN_EXIT], "exit_share": 2},
                {"exit": [TURN_EXIT], "turn_from": "turn_1", "exit_share": 2},
                {"exit": [TURN_EXIT], "turn_from": "turn_1"},
            ),
            "phases[0].exit_share",  # the next shares its own
        ),
        (
            ({"exit": [TURN_EXIT]}, {"exit": [TURN_EXIT], "turn_from": "turn_1", "exit_share": 2}),
            "phases[1].exit_share",  # the last, with nothing after it to share with
        ),
        (({"exit": ["estimate.a_b_line_turn < -1"], "exit_share": 0},), "phases[0].exit_share"),
        (
            ({"exit": ["estimate.a_b_line_turn < -1"], "exit_share": True},),
            "phases[0].exit_share",
        ),
        (({"stall": {"turn_deg": 1, "window_s": -1}},), "phases[0].stall.window_s"),
        (({"stall": {"turn_deg": 1}},), "phases[0].stall.window_s"),
        (
            ({"paced_ramp": {"rate_deg_s": -90, "blind_joint_rate": -1}},),
            "phases[0].paced_ramp.blind_joint_rate",
        ),
        (
            ({"brake": {"rate_deg_s": 90, "joint_damping": 0.03, "blind_joint_rate": 500}},),
            "phases[0].brake.blind_joint_rate",
        ),
    ],
)
def test_bad_switching_is_refused_naming_the_key(
    tmp_path: Path, hand: HandConfig, phases: tuple[Mapping[str, object], ...], key: str
) -> None:
    with pytest.raises(ConfigError) as info:
        _recipe(tmp_path, hand, *phases)
    assert info.value.key == key


def test_the_shipped_swap_exits_as_its_template_asks(hand: HandConfig) -> None:
    """The compiled recipe's manipulation exits are the template's: each on the turn since
    ``manipulate_1`` began (90 % of 45, 95 % of 90, an even share with the last of what is
    left of 180, all of 180), and none ends on a stall (docs/experiment.md: ended early, the
    pair's grasp had not settled)."""
    from handctl.planning.template import load_template

    root = Path(__file__).resolve().parents[2] / "config" / "recipes"
    template = load_template(root / "swap_two_cylinders.template.yaml", hand)
    recipe = load_recipe(root / "swap_two_cylinders.yaml", hand)
    turns = [p for p in template.phases if p.kind == "turn"]
    compiled = {p.name: p for p in recipe.phases}
    assert [p.name for p in turns] == [f"manipulate_{k}" for k in range(1, 5)]
    wanted_deg = [-45.0 * 0.9, -90.0 * 0.95, -180.0, -180.0]
    for k, (spec, wanted) in enumerate(zip(turns, wanted_deg, strict=True), 1):
        phase = compiled[spec.name]
        assert [c.text for c in phase.exits] == [spec.recipe_exit_condition()]
        assert phase.exits[0].value == pytest.approx(math.radians(wanted), abs=1e-4)
        assert phase.turn_from == spec.turn_from == ("manipulate_1" if k > 1 else "")
        assert phase.exit_share == spec.exit_share == (2 if k == 3 else 1)
        assert phase.stall is None and spec.stall is None
    assert turns[-1].exit_fraction == 1.0


def test_a_compiled_phase_carries_the_template_s_switching(hand: HandConfig) -> None:
    """``handctl plan`` writes ``turn_from`` with the exit on the turn since that phase
    began, and a ``stall`` and the blind joint rates as the template gives them; the
    planner's own episode of the phase keeps the exit on the phase's own turn."""
    from dataclasses import replace

    from handctl.online.recipes.schema import PacedRamp, TurnBrake, TurnStall
    from handctl.planning.compile import PhasePlan, _compiled_phase, _phase_document
    from handctl.planning.template import load_template

    root = Path(__file__).resolve().parents[2] / "config" / "recipes"
    template = load_template(root / "swap_two_cylinders.template.yaml", hand)
    spec = next(p for p in template.phases if p.name == "manipulate_3")
    spec = replace(
        spec,
        stall=TurnStall(math.radians(1.0), 0.3),
        paced=PacedRamp(math.radians(-90.0), 1.0, 2.0, 0.0, 4.0),
        brake=TurnBrake(math.radians(120.0), 0.03, 0.0, 3.0),
    )
    phase = _compiled_phase(spec, tuple(TORQUES), hand)
    assert [c.text for c in phase.exits] == [spec.exit_condition()]
    assert phase.exits[0].value == pytest.approx(math.radians(-45.0) * 0.95, abs=1e-4)
    doc = _phase_document(PhasePlan(spec, phase, None, None, []), hand)
    assert doc["turn_from"] == "manipulate_1"
    assert doc["exit"] == [spec.recipe_exit_condition()]
    assert "-3.1416" in doc["exit"][0]  # manipulate_4's, shared out with it
    assert doc["exit_share"] == 2
    assert doc["stall"] == {"turn_deg": 1.0, "window_s": 0.3}
    assert doc["paced_ramp"]["blind_joint_rate"] == 4.0
    assert doc["brake"]["blind_joint_rate"] == 3.0
