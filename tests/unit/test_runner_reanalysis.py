"""A turn phase that asks for the analysis at the measured configuration (``reanalyse``): the
runner's side of it. When it asks (the phase's first tick with a valid estimate, never
before), when it takes the answer (``delay_s`` later, on that tick, whatever the mode), what
taking it does to the torque (a new ramp from the torque proposed then: no step), and what it
does without an answer (the planned torque, said so in the phase's record). The answers here
are scripted: what the analysis computes is ``test_reanalysis.py``'s business, and the whole
path through a lockstep run and its re-run is ``tests/integration/test_reanalysis_run.py``'s."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np
import pytest
import yaml

from handctl.config import HandConfig
from handctl.errors import ConfigError
from handctl.online.recipes.loader import load_recipe
from handctl.online.recipes.reanalysis import ReanalysisResult
from handctl.online.recipes.runner import RecipeRunner
from handctl.online.recipes.schema import FIRST_PAIR_TURN, Recipe, RecipeObject, estimate_names

JOINTS = ["f1_j1", "f1_j2", "f1_j3", "f2_j1", "f2_j2", "f2_j3", "f3_j1", "f3_j2", "f3_j3"]
TORQUES = [0.2, 0.1, 0.05, 0.2, 0.1, 0.05, -0.2, -0.1, -0.05]
ANSWER = (0.1, 0.0, 0.0, 0.1, 0.0, 0.0, -0.3, -0.2, -0.1)
DT = 0.001
RAMP = 0.05
DELAY = 0.02
ESTIMATES = estimate_names((RecipeObject("a", 0.02), RecipeObject("b", 0.02)), ((0, 1),))
MODEL = {
    "masses_kg": {"a": 0.05, "b": 0.05},
    "friction": {"finger_object": 0.8, "object_object": 0.3},
}


def _recipe(
    tmp_path: Path,
    hand: HandConfig,
    reanalyse: Mapping[str, object] | None,
    model: Mapping[str, object] | None = MODEL,
) -> Recipe:
    phase: dict[str, object] = {
        "name": "turn",
        "torques": dict(zip(JOINTS, TORQUES, strict=True)),
        "ramp_s": RAMP,
        "max_s": 1.0,
        "on_timeout": "next",
    }
    if reanalyse is not None:
        phase["reanalyse"] = dict(reanalyse)
    data: dict[str, object] = {
        "recipe": "reanalysis",
        "objects": [{"name": "a", "radius": 0.02}, {"name": "b", "radius": 0.02}],
        "phases": [phase],
    }
    if model is not None:
        data["grasp_model"] = dict(model)
    path = tmp_path / "reanalysis.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return load_recipe(path, hand)


class Scripted:
    """A ``Reanalyser`` whose answer is given: it notes what it was asked and when."""

    def __init__(self, answer: ReanalysisResult | None) -> None:
        self.answer = answer
        self.asked: list[tuple[int, list[float], list[float]]] = []
        self.collected = 0

    def submit(self, phase: int, angles: Sequence[float], estimates: Sequence[float]) -> None:
        self.asked.append((phase, list(angles), list(estimates)))

    def collect(self, phase: int) -> ReanalysisResult | None:
        self.collected += 1
        return self.answer


def _estimates(valid: bool) -> list[float]:
    out = [math.nan] * len(ESTIMATES)
    if valid:
        out = [0.1 * k for k in range(len(ESTIMATES))]
        out[FIRST_PAIR_TURN] = -0.2
    return out


def _drive(runner: RecipeRunner, seconds: float, valid_from: float) -> list[np.ndarray]:
    torques = []
    for k in range(round(seconds / DT)):
        t = k * DT
        angle = np.full(9, 0.01 * k)
        torques.append(runner.step(t, angle, np.zeros(9), _estimates(t >= valid_from)).copy())
    return torques


def test_asks_on_the_first_valid_estimate_and_takes_the_answer_delay_later(
    tmp_path: Path, hand: HandConfig
) -> None:
    recipe = _recipe(tmp_path, hand, {"turn_deg": -45, "delay_s": DELAY})
    scripted = Scripted(ReanalysisResult(ANSWER, "analysis: scripted"))
    runner = RecipeRunner(recipe, 9, reanalyser=scripted)
    valid_from = 0.06  # after the planned ramp is in
    torques = _drive(runner, 0.2, valid_from)
    # asked once, on the first tick the pair was measured, with that tick's angles
    assert len(scripted.asked) == 1
    phase, angles, estimates = scripted.asked[0]
    asked_tick = round(valid_from / DT)
    assert phase == 0
    assert angles == pytest.approx([0.01 * asked_tick] * 9)
    assert estimates[FIRST_PAIR_TURN] == -0.2
    assert scripted.collected == 1
    assert runner.records[0].reanalysis == "analysis: scripted"
    taken = asked_tick + round(DELAY / DT)
    # before the answer: the planned ramp; from it on: a new ramp, with no step
    planned = np.array(TORQUES)
    np.testing.assert_allclose(torques[taken - 1], planned, atol=1e-12)
    step = np.max(np.abs(torques[taken] - torques[taken - 1]))
    assert step < np.max(np.abs(np.array(ANSWER) - planned)) * 2 * DT / RAMP
    np.testing.assert_allclose(torques[taken + round(RAMP / DT)], ANSWER, atol=1e-12)
    np.testing.assert_allclose(torques[-1], ANSWER, atol=1e-12)


@pytest.mark.parametrize(
    ("answer", "note"),
    [
        (ReanalysisResult(None, "none: no robust torque"), "none: no robust torque"),
        (None, "late: no answer 0.02 s after the request; the planned torque"),
    ],
)
def test_no_answer_keeps_the_planned_torque_and_says_why(
    tmp_path: Path, hand: HandConfig, answer: ReanalysisResult | None, note: str
) -> None:
    recipe = _recipe(tmp_path, hand, {"turn_deg": -45, "delay_s": DELAY})
    runner = RecipeRunner(recipe, 9, reanalyser=Scripted(answer))
    torques = _drive(runner, 0.2, 0.0)
    np.testing.assert_allclose(torques[-1], TORQUES, atol=1e-12)
    assert runner.records[0].reanalysis == note


def test_never_asks_while_the_pair_is_not_measured(tmp_path: Path, hand: HandConfig) -> None:
    recipe = _recipe(tmp_path, hand, {"turn_deg": -45, "delay_s": DELAY})
    scripted = Scripted(ReanalysisResult(ANSWER, "analysis: scripted"))
    runner = RecipeRunner(recipe, 9, reanalyser=scripted)
    torques = _drive(runner, 0.2, math.inf)
    assert scripted.asked == [] and scripted.collected == 0
    np.testing.assert_allclose(torques[-1], TORQUES, atol=1e-12)


def test_without_an_analysis_the_phase_runs_its_planned_torque(
    tmp_path: Path, hand: HandConfig
) -> None:
    """The planner's episodes run a recipe without the analysis: the plan's torque, said."""
    recipe = _recipe(tmp_path, hand, {"turn_deg": -45, "delay_s": DELAY})
    runner = RecipeRunner(recipe, 9)
    torques = _drive(runner, 0.2, 0.0)
    np.testing.assert_allclose(torques[-1], TORQUES, atol=1e-12)
    assert runner.records[0].reanalysis.startswith("not run")


@pytest.mark.parametrize(
    ("reanalyse", "model", "key", "expected"),
    [
        ({"turn_deg": -45}, None, "grasp_model", "the grasp model phases[0].reanalyse needs"),
        (None, MODEL, "grasp_model", "no grasp_model: no phase has reanalyse"),
        ({"turn_deg": 0}, MODEL, "turn_deg", "a turn other than 0 deg"),
        ({"turn_deg": -45, "use": "best"}, MODEL, "use", "analysis"),
        ({"turn_deg": -45, "delay_s": 5}, MODEL, "delay_s", "<= 1"),
        ({"turn_deg": -45, "min_margin_N": 0}, MODEL, "min_margin_N", "> 0"),
        ({"turn_deg": -45}, {"masses_kg": {"a": 0.05}, "friction": {}}, "masses_kg", "b"),
    ],
)
def test_bad_reanalysis_keys_are_refused_with_the_key_and_the_value(
    tmp_path: Path,
    hand: HandConfig,
    reanalyse: Mapping[str, object] | None,
    model: Mapping[str, object] | None,
    key: str,
    expected: str,
) -> None:
    with pytest.raises(ConfigError) as info:
        _recipe(tmp_path, hand, reanalyse, model)
    text = str(info.value)
    assert "reanalysis.yaml" in text and key in text and expected in text


def test_a_template_s_reanalyse_and_grasp_model_are_carried_into_the_recipe(
    tmp_path: Path, hand: HandConfig
) -> None:
    """A template's turn phase asks with its own turn as the default; ``handctl plan``
    writes ``reanalyse`` and ``grasp_model`` into the recipe it compiles, which loads back
    to the same values."""
    from handctl.planning.compile import PhasePlan, PlanResult, _compiled_phase
    from handctl.planning.template import load_template

    root = Path(__file__).resolve().parents[2] / "config" / "recipes"
    data = yaml.safe_load((root / "swap_two_cylinders.template.yaml").read_text())
    data["phases"][5]["reanalyse"] = {"use": "nearest", "delay_s": 0.3}
    data["phases"][5].pop("schedule", None)  # a phase has one or the other
    data["grasp_model"] = {
        "masses_kg": {"cyl1": 0.05, "cyl2": 0.06},
        "friction": {"finger_object": 0.8, "object_object": 0.3},
    }
    path = tmp_path / "t.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    template = load_template(path, hand)
    spec = template.phases[5]
    assert spec.reanalyse is not None
    assert spec.reanalyse.turn == pytest.approx(spec.turn)
    plans = [
        PhasePlan(s, _compiled_phase(s, tuple(TORQUES), hand), None, None, [])
        for s in template.phases
    ]
    document = PlanResult(template, hand, plans, [], "sha256:0").recipe_document()
    compiled = tmp_path / "compiled.yaml"
    compiled.write_text(yaml.safe_dump(document, sort_keys=False))
    recipe = load_recipe(compiled, hand)
    assert recipe.phases[5].reanalyse == spec.reanalyse
    assert [p.reanalyse is None for p in recipe.phases] == [k != 5 for k in range(7)]
    assert recipe.grasp_model == template.grasp_model
    assert recipe.grasp_model is not None and recipe.grasp_model.masses == (0.05, 0.06)


def test_a_reanalysis_asked_against_its_exit_s_turn_is_refused(
    tmp_path: Path, hand: HandConfig
) -> None:
    """The analysis asked for torques that turn the pair the other way from the turn the
    phase's exit waits for: refused, as a rate signed so is."""
    path = Path(_recipe(tmp_path, hand, {"turn_deg": -45}).source)  # loads, then changed
    data = yaml.safe_load(path.read_text())
    data["phases"][0]["exit"] = ["estimate.a_b_line_turn < -0.7"]
    data["phases"][0]["reanalyse"]["turn_deg"] = 45
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    with pytest.raises(ConfigError) as info:
        load_recipe(path, hand)
    assert info.value.key == "phases[0].reanalyse.turn_deg"
    assert "a turn the way the phase's exit waits for" in info.value.expected
    data["phases"][0]["reanalyse"]["turn_deg"] = -45
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    load_recipe(path, hand)
