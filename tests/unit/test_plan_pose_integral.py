"""``handctl plan`` and a free phase's pose integral: the template gives the gains, the plan
computes the rest pose as where the nominal hand settles under the hold (so the integral has
nothing to make up on the nominal hand), and the compiled recipe reads back the same hold."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import yaml

from handctl.config import HandConfig
from handctl.online.recipes.loader import load_recipe
from handctl.online.recipes.schema import RecipeObject
from handctl.planning.compile import _compiled_phase, _pose_document, _pose_of, _with_rest
from handctl.planning.episode import Episode
from handctl.planning.template import Template, TemplatePhase, load_template
from handctl.sim.params import parse_sim

from ..conftest import ROOT

TEMPLATE = ROOT / "config" / "recipes" / "swap_two_cylinders.template.yaml"
RECIPE = ROOT / "config" / "recipes" / "swap_two_cylinders.yaml"
GAINS = {"gain": 3.0, "max": 0.1, "still_rate": 0.1}


def _approach(tmp_path: Path, hand: HandConfig) -> tuple[Template, TemplatePhase]:
    """The shipped template's first phase (a free phase with a pose hold), with an integral."""
    doc = yaml.safe_load(TEMPLATE.read_text())
    first = doc["phases"][0]
    assert first["kind"] == "free" and "pose" in first
    first["pose"]["integral"] = dict(GAINS)
    doc["phases"] = [first]
    path = tmp_path / "t.template.yaml"
    path.write_text(yaml.safe_dump(doc, sort_keys=False))
    template = load_template(path, hand)
    assert template.phases[0].seed is not None
    return template, template.phases[0]


def _episode(hand: HandConfig) -> Episode:
    params = parse_sim(hand)
    return Episode(hand, params, [RecipeObject(o.name, o.radius) for o in params.objects])


def test_the_rest_pose_is_where_the_nominal_hand_settles_under_the_hold(
    tmp_path: Path, hand: HandConfig
) -> None:
    _, spec = _approach(tmp_path, hand)
    shipped = load_recipe(RECIPE, hand).phases[0].pose
    assert shipped is not None
    episode = _episode(hand)
    start = episode.snapshot()
    hold = _with_rest(episode, spec, hand, replace(shipped, integral=None))
    assert hold.integral is not None
    assert (hold.integral.gain, hold.integral.max, hold.integral.still_rate) == (3.0, 0.1, 0.1)
    assert hold.angles == shipped.angles
    # the spring's pose is not where the hold leaves the hand: through the tips' friction on
    # the table the hand rests elsewhere, and that is the pose the next phase is planned from
    assert max(abs(a - b) for a, b in zip(hold.angles, hold.integral.rest, strict=True)) > 0.05
    # on the nominal hand the integral then has next to nothing to make up: it ends in the
    # rest pose, to within a mrad
    episode.restore(start)
    assert spec.seed is not None
    episode.run_phase(_compiled_phase(spec, spec.seed, hand, hold))
    settled = np.array(episode.plant.joint_angles)
    assert np.max(np.abs(settled - np.array(hold.integral.rest))) < 1e-3


def test_the_compiled_hold_reads_back_the_same(tmp_path: Path, hand: HandConfig) -> None:
    _, spec = _approach(tmp_path, hand)
    assert spec.seed is not None
    hold = _with_rest(_episode(hand), spec, hand, _pose_of(_episode(hand), spec, hand))
    recipe = {
        "recipe": "approach",
        "phases": [
            {
                "name": "approach",
                "torques": dict(zip(hand.joint_names, spec.seed, strict=True)),
                "ramp_s": spec.ramp_s,
                "max_s": spec.max_s,
                "on_timeout": "next",
                "pose": _pose_document(hold, hand),
            }
        ],
    }
    path = tmp_path / "r.yaml"
    path.write_text(yaml.safe_dump(recipe, sort_keys=False))
    assert load_recipe(path, hand).phases[0].pose == hold
