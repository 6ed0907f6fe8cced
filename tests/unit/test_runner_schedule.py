"""A phase's torque scheduled on the objects' measured size (``schedule``): the runner takes
the first entry whose ``radius_ratio`` ranges all hold for the radii the object estimator
measured, once, when the phase begins or when the radius is first measured, and ramps to
it without a step; the loader refuses a bad schedule naming the file, the key, the
expected and the actual value; a template carries it into the compiled recipe."""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml

from handctl.config import HandConfig
from handctl.errors import ConfigError
from handctl.online.estimator import ObjectEstimator
from handctl.online.recipes.loader import load_recipe
from handctl.online.recipes.runner import RecipeRunner
from handctl.online.recipes.schema import RecipeObject

from .one_turn import one_turn_template
from .test_estimator import BOX_ANGLES, OPEN_ANGLES, R, boxed_hand

JOINTS = ["f1_j1", "f1_j2", "f1_j3", "f2_j1", "f2_j2", "f2_j3", "f3_j1", "f3_j2", "f3_j3"]
OWN = [0.1, 0.1, 0.05, 0.1, 0.1, 0.05, -0.1, -0.1, -0.05]
LARGE = [0.25, 0.1, 0.05, 0.1, 0.2, 0.05, -0.1, -0.1, -0.05]
SMALL = [0.05, 0.1, 0.05, 0.1, 0.05, 0.05, -0.1, -0.1, -0.05]
DT = 0.001
RAMP = 0.1
#: the boxed hand's cages measure every cylinder as R; a recipe whose cylinder 1 is R / 1.15
#: has it measured 1.15 times the recipe's
LARGE_RATIO = 1.15


def _data(radius1: float = R / LARGE_RATIO, schedule: Any = None) -> dict[str, Any]:
    if schedule is None:
        schedule = [
            {
                "when": {"radius_ratio": {"object": "cyl1", "min": 1.07, "max": 1.3}},
                "torques": dict(zip(JOINTS, LARGE, strict=True)),
            },
            {
                "when": {"radius_ratio": [{"object": "cyl1", "max": 0.93}]},
                "torques": dict(zip(JOINTS, SMALL, strict=True)),
            },
        ]
    return {
        "recipe": "scheduled",
        "objects": [{"name": "cyl1", "radius": radius1}, {"name": "cyl2", "radius": R}],
        "phases": [
            {
                "name": "hold",
                "torques": dict(zip(JOINTS, OWN, strict=True)),
                "ramp_s": RAMP,
                "max_s": 0.5,
                "on_timeout": "next",
            },
            {
                "name": "turn",
                "torques": dict(zip(JOINTS, OWN, strict=True)),
                "ramp_s": RAMP,
                "max_s": 1.0,
                "on_timeout": "next",
                "schedule": schedule,
            },
        ],
    }


def _load(tmp_path: Path, hand: HandConfig, data: dict[str, Any]) -> Any:
    path = tmp_path / "scheduled.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return load_recipe(path, hand)


def _run(
    runner: RecipeRunner, est: ObjectEstimator, angles: list[list[float]], t0: float = 0.0
) -> tuple[float, list[np.ndarray]]:
    """One tick per entry of ``angles``, the estimator fed as the loop feeds it; returns the
    next tick's time and every proposed torque."""
    out = []
    t = t0
    for q in angles:
        a = np.array(q)
        estimates = est(a)
        out.append(runner.step(t, a, np.zeros(9), estimates).copy())
        t += DT
    return t, out


@pytest.mark.parametrize(
    ("radius1", "torques", "chosen"),
    [
        (R / LARGE_RATIO, LARGE, "cyl1 radius x1.150: schedule[0]"),
        (R / 0.9, SMALL, "cyl1 radius x0.900: schedule[1]"),
        (R, OWN, "cyl1 radius x1.000: its own torques"),
    ],
)
def test_the_torque_is_the_one_scheduled_for_the_measured_radius(
    tmp_path: Path, hand: HandConfig, radius1: float, torques: list[float], chosen: str
) -> None:
    """Measured in the hold, cylinder 1's radius chooses the turn's torque when the turn
    begins; the ramp goes from the hold's torque to it."""
    recipe = _load(tmp_path, hand, _data(radius1))
    box = boxed_hand(hand)
    est = ObjectEstimator(box, recipe.objects, recipe.pairs)
    runner = RecipeRunner(recipe, 9, sizes=est)
    t, held = _run(runner, est, [BOX_ANGLES] * 500)
    assert runner.phase_name == "hold"
    assert held[-1] == pytest.approx(OWN)
    t, turned = _run(runner, est, [BOX_ANGLES] * 300, t)
    assert turned[-1] == pytest.approx(torques)
    assert runner.records[1].schedule == chosen
    assert runner.records[0].schedule == ""  # no schedule in the hold
    steps = np.abs(np.diff(np.array(held[-1:] + turned), axis=0)).max()
    assert steps <= np.abs(np.subtract(torques, OWN)).max() * DT / RAMP + 1e-12


def test_a_radius_measured_after_the_phase_began_chooses_then_without_a_step(
    tmp_path: Path, hand: HandConfig
) -> None:
    """The turn begins before the cage has measured the cylinder (a hold too short for the
    fit): it ramps to its own torque; once the radius is measured the scheduled torque is
    ramped to from where the torque is, never a step."""
    data = _data()
    data["phases"][0]["max_s"] = data["phases"][0]["ramp_s"] = 0.05
    data["phases"][1]["ramp_s"] = 0.05  # the turn's own torque is in before the choice
    recipe = _load(tmp_path, hand, data)
    est = ObjectEstimator(boxed_hand(hand), recipe.objects, recipe.pairs)
    runner = RecipeRunner(recipe, 9, sizes=est)
    t, before = _run(runner, est, [BOX_ANGLES] * 110)
    assert runner.phase_name == "turn"
    assert est.measured_radius(0) is None
    assert before[-1] == pytest.approx(OWN)
    assert runner.records[1].schedule == ""  # not chosen yet
    t, after = _run(runner, est, [BOX_ANGLES] * 800, t)
    assert runner.phase_name == "turn"
    assert after[-1] == pytest.approx(LARGE)
    # the fit is most of the way to x1.15 when it counts as measured
    assert re.fullmatch(
        r"cyl1 radius x1\.1[0-5]\d: schedule\[0\] from 0\.\d+ s into the phase",
        runner.records[1].schedule,
    ), runner.records[1].schedule
    steps = np.abs(np.diff(np.array(before + after), axis=0)).max()
    assert steps <= np.abs(np.subtract(LARGE, OWN)).max() * DT / 0.05 + 1e-12


def test_a_radius_never_measured_keeps_the_phase_s_torque_and_says_so(
    tmp_path: Path, hand: HandConfig
) -> None:
    recipe = _load(tmp_path, hand, _data())
    est = ObjectEstimator(boxed_hand(hand), recipe.objects, recipe.pairs)
    runner = RecipeRunner(recipe, 9, sizes=est)
    _, out = _run(runner, est, [OPEN_ANGLES] * 1800)
    assert runner.done
    assert out[1400] == pytest.approx(OWN)
    assert runner.records[1].schedule == "not measured while the phase ran: its own torques"


def test_without_an_estimator_the_phase_s_own_torque_runs(tmp_path: Path, hand: HandConfig) -> None:
    recipe = _load(tmp_path, hand, _data())
    runner = RecipeRunner(recipe, 9)
    q = np.array(BOX_ANGLES)
    for k in range(900):
        out = runner.step(k * DT, q, np.zeros(9))
    assert out == pytest.approx(OWN)
    assert runner.records[1].schedule.startswith("not measured: no estimator")


def _entry(when: Any, **torques: float) -> dict[str, Any]:
    return {"when": when, "torques": {**dict(zip(JOINTS, OWN, strict=True)), **torques}}


@pytest.mark.parametrize(
    ("schedule", "key", "expected", "found"),
    [
        (
            [_entry({"radius_ratio": {"object": "cyl3", "min": 1.1}})],
            "phases[1].schedule[0].when.radius_ratio.object",
            "an object of the recipe (cyl1, cyl2)",
            "cyl3",
        ),
        (
            [_entry({"radius_ratio": [{"object": "cyl1", "min": 1.2, "max": 1.1}]})],
            "phases[1].schedule[0].when.radius_ratio[0].max",
            "a ratio larger than min (1.2)",
            "1.1",
        ),
        (
            # a lone min at the top leaves no range: the min written is to blame, not a max
            [_entry({"radius_ratio": {"object": "cyl1", "min": 1.5}})],
            "phases[1].schedule[0].when.radius_ratio.min",
            "a ratio smaller than 1.5 (max, not written)",
            "1.5",
        ),
        (
            [_entry({"radius_ratio": {"object": "cyl1"}})],
            "phases[1].schedule[0].when.radius_ratio.min",
            "a bound of the range (min, max or both)",
            "neither",
        ),
        (
            [_entry({"radius_ratio": {"object": "cyl1", "min": 2.0}})],
            "phases[1].schedule[0].when.radius_ratio.min",
            "a number >= 0.5 and <= 1.5",
            "2",
        ),
        (
            [_entry({"radius": {"object": "cyl1", "min": 1.1}})],
            "phases[1].schedule[0].when.radius",
            "no such key here",
            "",
        ),
        (
            [_entry({"radius_ratio": []})],
            "phases[1].schedule[0].when.radius_ratio",
            "a non-empty list",
            "",
        ),
        (
            [_entry({"radius_ratio": {"object": "cyl1", "min": 1.1}}, f1_j1=0.7)],
            "phases[1].schedule[0].torques.f1_j1",
            "|τ| <= 0.6 N·m (tau_max of f1_j1",
            "0.7",
        ),
        ([], "phases[1].schedule", "a list of 1 to 8 mappings", "0 entries"),
        # a range past what the estimator measures (±40 %) is never met
        (
            [_entry({"radius_ratio": {"object": "cyl1", "min": 1.45}})],
            "phases[1].schedule[0].when.radius_ratio.min",
            "a range that meets 0.6..1.4",
            "1.45",
        ),
        (
            [_entry({"radius_ratio": {"object": "cyl1", "max": 0.55}})],
            "phases[1].schedule[0].when.radius_ratio.max",
            "a range that meets 0.6..1.4",
            "0.55",
        ),
    ],
)
def test_a_bad_schedule_is_refused_naming_the_key(
    tmp_path: Path, hand: HandConfig, schedule: Any, key: str, expected: str, found: str
) -> None:
    with pytest.raises(ConfigError) as err:
        _load(tmp_path, hand, _data(schedule=schedule))
    assert err.value.file.endswith("scheduled.yaml")
    assert err.value.key == key
    assert expected in err.value.expected
    assert found in str(err.value.found)


def test_a_scheduled_torque_too_far_for_the_ramp_is_refused(
    tmp_path: Path, hand: HandConfig
) -> None:
    """Either torque of a phase may follow either of the previous phase's: every ramp
    between them is checked against the joints' rate limits."""
    data = _data(schedule=[_entry({"radius_ratio": {"object": "cyl1", "min": 1.1}}, f1_j1=0.5)])
    data["phases"][1]["ramp_s"] = 0.01  # 0.4 N·m in 10 ms: 40 N·m/s, the limit is 20
    with pytest.raises(ConfigError) as err:
        _load(tmp_path, hand, data)
    assert err.value.key == "phases[1].ramp_s"
    assert "schedule[0]" in err.value.expected


def test_a_schedule_chosen_mid_phase_is_checked_from_the_phase_s_own_torque(
    tmp_path: Path, hand: HandConfig
) -> None:
    """A radius measured once the phase has begun ramps from where the phase's own ramp got
    to the entry's torque: from the previous phase's torque to the entry's is within the rate
    limit here, from the phase's own to the entry's is not (0.8 N·m in 30 ms)."""
    data = _data(schedule=[_entry({"radius_ratio": {"object": "cyl1", "min": 1.1}}, f1_j1=0.5)])
    data["phases"][1]["torques"]["f1_j1"] = -0.3
    data["phases"][1]["ramp_s"] = 0.03
    with pytest.raises(ConfigError) as err:
        _load(tmp_path, hand, data)
    assert err.value.key == "phases[1].ramp_s"
    assert "schedule[0]" in err.value.expected and "0.8 N·m" in err.value.expected
    data["phases"][1]["ramp_s"] = 0.05  # 16 N·m/s
    _load(tmp_path, hand, data)


def test_a_schedule_and_a_reanalysis_are_not_both_a_phase_s(
    tmp_path: Path, hand: HandConfig
) -> None:
    data = _data()
    data["phases"][1]["reanalyse"] = {"turn_deg": -45}
    with pytest.raises(ConfigError) as err:
        _load(tmp_path, hand, data)
    assert err.value.key == "phases[1].schedule"
    assert "no schedule in a phase with reanalyse" in err.value.expected


def test_a_template_s_schedule_is_carried_into_the_compiled_recipe(
    tmp_path: Path, hand: HandConfig
) -> None:
    """The compiled phase's document holds the schedule as written, and the loader reads it
    back to the same ranges and torques."""
    from handctl.planning.compile import PhasePlan, _compiled_phase, _phase_document

    entry = _entry({"radius_ratio": {"object": "cyl2", "min": 1.1}}, f1_j1=0.3)
    spec = one_turn_template(tmp_path, hand, OWN, {"schedule": [entry]})
    assert spec.schedule[0].when[0].object == 1
    phase = _compiled_phase(spec, tuple(OWN), hand)
    doc = _phase_document(PhasePlan(spec, phase, None, None, []), hand)
    recipe = _data()
    recipe["phases"][1]["schedule"] = doc["schedule"]
    loaded = _load(tmp_path, hand, recipe).phases[1]
    assert loaded.schedule == spec.schedule
    assert loaded.schedule[0].when[0].low == 1.1
    assert loaded.schedule[0].torques[0] == 0.3


def test_the_estimator_says_a_radius_is_measured_only_after_its_fit(hand: HandConfig) -> None:
    """What the schedule waits for: the cage fitted for ``MEASURED_TICKS``."""
    objects = (RecipeObject("cyl1", R / LARGE_RATIO), RecipeObject("cyl2", R))
    est = ObjectEstimator(boxed_hand(hand), objects)
    est(np.array(BOX_ANGLES))
    assert est.measured_radius(0) is None
    for _ in range(400):
        est(np.array(BOX_ANGLES))
    assert est.measured_radius(0) == pytest.approx(R, abs=2e-5)


@pytest.mark.parametrize(
    "second",
    [
        {"object": "cyl1", "min": 1.07, "max": 1.3},  # the same ranges
        {"object": "cyl1", "min": 1.1, "max": 1.2},  # within them
        [{"object": "cyl1", "min": 1.1, "max": 1.2}, {"object": "cyl2", "max": 0.9}],  # narrower
    ],
)
def test_an_entry_an_earlier_one_always_holds_for_is_refused(
    tmp_path: Path, hand: HandConfig, second: Any
) -> None:
    """Two entries with one 'when' and opposite torques: the second was never chosen, and the
    run was the recipe without it."""
    first = _entry({"radius_ratio": {"object": "cyl1", "min": 1.07, "max": 1.3}}, f1_j1=0.2)
    with pytest.raises(ConfigError) as info:
        _load(tmp_path, hand, _data(schedule=[first, _entry({"radius_ratio": second})]))
    assert info.value.key == "phases[1].schedule[1].when"
    assert "schedule[0] holds wherever this one does: it is never chosen" in info.value.expected
    # an entry the first does not cover may follow it
    wider = _entry({"radius_ratio": {"object": "cyl1", "min": 1.0, "max": 1.3}})
    _load(tmp_path, hand, _data(schedule=[first, wider]))


@pytest.mark.parametrize("planned", [False, True])
def test_a_template_s_entry_an_earlier_one_always_holds_for_is_refused_when_it_loads(
    tmp_path: Path, hand: HandConfig, planned: bool
) -> None:
    """A template's shadowed entry was refused only by the compiled recipe's loader, after
    the whole plan had run (minutes); the template now refuses it as the recipe does."""
    first = _entry({"radius_ratio": {"object": "cyl1", "min": 1.07, "max": 1.3}}, f1_j1=0.2)
    inner = {"radius_ratio": {"object": "cyl1", "min": 1.1, "max": 1.2}}
    second = {"when": inner, "plan": {"models": 4}} if planned else _entry(inner, f1_j1=-0.2)
    with pytest.raises(ConfigError) as info:
        one_turn_template(tmp_path, hand, OWN, {"schedule": [first, second]})
    assert info.value.key == "phases[0].schedule[1].when"
    assert "schedule[0] holds wherever this one does: it is never chosen" in info.value.expected
    assert info.value.file.endswith("t.template.yaml")
