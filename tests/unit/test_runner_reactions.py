"""A paced ramp's reactions when the pair does not go as planned: a pair the phase's torque
turns back is not a slow pair (``turn_back_deg``: the pace holds, then goes back along the
segment), and a joint pushed deep into its soft-limit guard's band is the torque driving the
hand into its limit (``limit_depth``: the same). Without the keys the pace is as before."""

from __future__ import annotations

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
BAND = 0.15
ESTIMATES = estimate_names((RecipeObject("a", 0.02), RecipeObject("b", 0.02)), ((0, 1),))


def _recipe(
    tmp_path: Path, hand: HandConfig, paced: Mapping[str, object], guard: bool = True
) -> Recipe:
    data: dict[str, object] = {
        "recipe": "reactions",
        "objects": [{"name": "a", "radius": 0.02}, {"name": "b", "radius": 0.02}],
        "phases": [
            {
                "name": "turn",
                "torques": dict(zip(JOINTS, TORQUES, strict=True)),
                "ramp_s": RAMP,
                "max_s": 10.0,
                "on_timeout": "next",
                "paced_ramp": {"rate_deg_s": -90, **paced},
            }
        ],
    }
    if guard:
        data["limit_guard_band"] = BAND
    path = tmp_path / "reactions.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return load_recipe(path, hand)


def _estimates(turn: float) -> list[float]:
    out = [math.nan] * len(ESTIMATES)
    out[FIRST_PAIR_TURN] = turn
    return out


def _feed(
    runner: RecipeRunner,
    turns_deg: list[float],
    angle: np.ndarray | None = None,
    t0: float = 0.0,
) -> float:
    """One tick per turn (deg; NaN: no valid estimate), the joints held at ``angle``; returns
    the time of the next tick."""
    q = np.zeros(9) if angle is None else angle
    t = t0
    for turn in turns_deg:
        runner.step(t, q, np.zeros(9), _estimates(math.radians(turn)))
        t += DT
    return t


def _ramp(start: float, end: float, seconds: float) -> list[float]:
    n = round(seconds / DT)
    return [start + (end - start) * k / n for k in range(n)]


@pytest.mark.parametrize("turn_back", [None, 10.0])
def test_a_pair_turned_back_sends_the_pace_back(
    tmp_path: Path, hand: HandConfig, turn_back: float | None
) -> None:
    """The pair turns 20° the wanted way, then 30° back, slowly (a wrong-way turn reads as
    slow to the rate alone): with ``turn_back_deg`` the pace goes back towards the torque
    that held the pair, without it the ramp goes on to the phase's torque."""
    paced = {} if turn_back is None else {"turn_back_deg": turn_back}
    runner = RecipeRunner(_recipe(tmp_path, hand, paced), 9)
    t = _feed(runner, _ramp(0.0, -20.0, 0.5))
    assert runner.pace == 1.0
    t = _feed(runner, _ramp(-20.0, 10.0, 0.5), t0=t)
    _feed(runner, [10.0] * round(0.2 / DT), t0=t)
    assert runner.pace == (1.0 if turn_back is None else 0.0)


def test_a_pair_a_little_behind_its_furthest_keeps_the_pace(
    tmp_path: Path, hand: HandConfig
) -> None:
    """Less than ``turn_back_deg`` behind (the estimate's noise, a pair settling back a few
    degrees): the pace is what the rate makes it."""
    runner = RecipeRunner(_recipe(tmp_path, hand, {"turn_back_deg": 10.0}), 9)
    t = _feed(runner, _ramp(0.0, -20.0, 0.5))
    _feed(runner, _ramp(-20.0, -12.0, 0.3) + [-12.0] * 200, t0=t)
    assert runner.pace == 1.0


def test_the_pace_holds_where_the_pair_stays_turned_back_between_the_bounds(
    tmp_path: Path, hand: HandConfig
) -> None:
    """A third of the way from one ``turn_back_deg`` behind to two, the pace holds where it
    is: it neither pushes on nor lets go all the way; nearer, it goes on; further, back."""
    runner = RecipeRunner(_recipe(tmp_path, hand, {"turn_back_deg": 10.0}), 9)
    t = _feed(runner, _ramp(0.0, -20.0, 0.5))
    t = _feed(runner, _ramp(-20.0, -5.0, 0.05) + [-5.0] * 50, t0=t)  # 15° behind: back
    held = runner.pace
    assert 0.0 < held < 1.0
    t = _feed(runner, [-20.0 + 10.0 * 4 / 3] * 300, t0=t)
    assert runner.pace == pytest.approx(held, abs=1e-6)
    t = _feed(runner, [-12.0] * 50, t0=t)  # 8° behind: on
    assert runner.pace > held


def test_an_unseen_pair_keeps_the_last_seen_turn_back(tmp_path: Path, hand: HandConfig) -> None:
    """An open cage (no valid estimate) is no news that the pair came back: the pace keeps
    going back."""
    runner = RecipeRunner(_recipe(tmp_path, hand, {"turn_back_deg": 10.0}), 9)
    t = _feed(runner, _ramp(0.0, -20.0, 0.5))
    t = _feed(runner, _ramp(-20.0, 10.0, 0.05), t0=t)
    _feed(runner, [math.nan] * 300, t0=t)
    assert runner.pace == 0.0


def _deep(hand: HandConfig, joint: str, depth: float) -> np.ndarray:
    """The angles with ``joint`` ``depth`` of the band into its band before its lower limit
    (the others mid-range)."""
    q = np.array([(j.angle_min + j.angle_max) / 2 for j in hand.joints])
    k = JOINTS.index(joint)
    q[k] = hand.joints[k].angle_min + BAND * (1.0 - depth)
    return q


@pytest.mark.parametrize("depth", [0.0, 0.3])
def test_a_joint_pushed_deep_into_its_band_sends_the_pace_back(
    tmp_path: Path, hand: HandConfig, depth: float
) -> None:
    """A distal joint pushed 0.9 of the way into its guard's band while the pair does not
    turn: with ``limit_depth`` the pace goes back to the segment's start, without it the
    ramp goes on to the phase's torque."""
    paced = {"limit_depth": depth} if depth else {}
    runner = RecipeRunner(_recipe(tmp_path, hand, paced), 9)
    t = _feed(runner, [0.0] * round(4 * RAMP / DT), _deep(hand, "f2_j3", 0.0))
    assert runner.pace == 1.0
    _feed(runner, [0.0] * round(4 * RAMP / DT), _deep(hand, "f2_j3", 0.9), t0=t)
    assert runner.pace == (1.0 if depth == 0.0 else 0.0)


@pytest.mark.parametrize(("depth", "pace"), [(0.2, 1.0), (0.3 + 0.7 / 3, 1.0), (0.7, 0.0)])
def test_how_deep_a_joint_is_sets_how_far_the_pace_goes(
    tmp_path: Path, hand: HandConfig, depth: float, pace: float
) -> None:
    """Up to ``limit_depth`` the ramp is the rate's; a third of the way from there to the
    limit, it holds where it is; deeper, it goes back."""
    runner = RecipeRunner(_recipe(tmp_path, hand, {"limit_depth": 0.3}), 9)
    t = _feed(runner, [0.0] * round(4 * RAMP / DT))
    assert runner.pace == 1.0
    _feed(runner, [0.0] * round(4 * RAMP / DT), _deep(hand, "f1_j3", depth), t0=t)
    assert runner.pace == pytest.approx(pace, abs=1e-6)


def test_a_joint_the_grasp_leans_into_its_band_counts_from_where_it_was(
    tmp_path: Path, hand: HandConfig
) -> None:
    """A joint already 0.6 of its band in when the phase begins (a grasp that leans on the
    guard on purpose) is not the phase's doing: the ramp goes on while it stays there, and
    backs off only once the phase pushes it deeper (here 0.9 of the band in)."""
    runner = RecipeRunner(_recipe(tmp_path, hand, {"limit_depth": 0.3}), 9)
    t = _feed(runner, [0.0] * round(4 * RAMP / DT), _deep(hand, "f2_j3", 0.6))
    assert runner.pace == 1.0
    _feed(runner, [0.0] * round(4 * RAMP / DT), _deep(hand, "f2_j3", 0.9), t0=t)
    assert runner.pace == 0.0


@pytest.mark.parametrize(
    ("paced", "guard", "key"),
    [
        ({"limit_depth": 0.5}, False, "phases[0].paced_ramp.limit_depth"),
        ({"limit_depth": 0.95}, True, "phases[0].paced_ramp.limit_depth"),
        ({"limit_depth": -0.1}, True, "phases[0].paced_ramp.limit_depth"),
        ({"turn_back_deg": -5}, True, "phases[0].paced_ramp.turn_back_deg"),
        ({"turn_back_deg": 120}, True, "phases[0].paced_ramp.turn_back_deg"),
        ({"turn_back_deg": "far"}, True, "phases[0].paced_ramp.turn_back_deg"),
    ],
)
def test_bad_reactions_are_refused_naming_the_key(
    tmp_path: Path, hand: HandConfig, paced: dict[str, object], guard: bool, key: str
) -> None:
    with pytest.raises(ConfigError) as info:
        _recipe(tmp_path, hand, paced, guard=guard)
    assert info.value.key == key


def test_a_compiled_phase_carries_the_template_s_reactions(
    tmp_path: Path, hand: HandConfig
) -> None:
    """``handctl plan`` writes a template's ``limit_depth`` and ``turn_back_deg`` into the
    compiled phase's ``paced_ramp``, and the recipe loads them back as they were."""
    from dataclasses import replace

    from handctl.online.recipes.schema import PacedRamp
    from handctl.planning.compile import PhasePlan, _compiled_phase, _phase_document
    from handctl.planning.template import load_template

    root = Path(__file__).resolve().parents[2] / "config" / "recipes"
    template = load_template(root / "swap_two_cylinders.template.yaml", hand)
    spec = next(p for p in template.phases if p.name == "manipulate_3")
    paced = PacedRamp(math.radians(-90.0), 1.0, 2.0, limit_depth=0.25, turn_back=0.35)
    phase = _compiled_phase(replace(spec, paced=paced), tuple(TORQUES), hand)
    doc = _phase_document(PhasePlan(replace(spec, paced=paced), phase, None, None, []), hand)
    assert doc["paced_ramp"]["limit_depth"] == 0.25
    assert doc["paced_ramp"]["turn_back_deg"] == pytest.approx(math.degrees(0.35))
    keys = {k: v for k, v in doc["paced_ramp"].items() if k != "rate_deg_s"}
    loaded = _recipe(tmp_path, hand, keys)
    assert loaded.phases[0].paced is not None
    assert loaded.phases[0].paced.limit_depth == 0.25
    assert loaded.phases[0].paced.turn_back == pytest.approx(0.35)
