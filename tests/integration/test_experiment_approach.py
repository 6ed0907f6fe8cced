"""The approach ends in a known pose whatever the friction, in lockstep: the pose hold's
integral (``pose.integral``) pushes a finger that friction holds short of where the nominal
hand rests on, so that the lift begins with the fingertips beside the pair.

Without it, where the tips come to rest on the table depended on friction the model does not
know: on the bench's hands of `all` the tips ended 41..65 mm from the palm's centre, the
wider the more the tips' friction on the table (correlation 0.85), and every lift that
dropped the pair began with its tips 58 mm out or more (docs/experiment.md, "The approach's
integral")."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import yaml
from mcap.reader import make_reader

from handctl.config import load_hand
from handctl.online.estimator import ObjectEstimator
from handctl.online.recipes.loader import load_recipe

from ..conftest import HAND_YAML, ROOT, handctl
from .scaled_hand import scaled_hand

RECIPE = ROOT / "config" / "recipes" / "swap_two_cylinders.yaml"
#: the model set's hands that stop short without the integral: the tips' Coulomb friction
#: on the table at the top of its range (±50 %), the joints' damping at the top of its
#: (×0.3..×3)
STIFF = {
    "tips_on_the_table_x1.5": {"friction.finger_table": 1.5},
    "joint_damping_x3": {"damping": 3.0},
}
#: m: how much wider than the nominal hand's the tips may end up
WIDER = 0.001
#: m: how much wider the tips of these hands end up without the integral, at least
SHORT = 0.004


def _approach_end(tmp_path: Path, recipe: Path, factors: dict[str, float]) -> list[float]:
    """Each fingertip's distance (m) from the palm's centre line at the end of the approach:
    the run stops there (``--max-seconds``, the approach's ``max_s``)."""
    approach = yaml.safe_load(recipe.read_text())["phases"][0]
    assert approach["name"] == "approach"
    log = tmp_path / "run.mcap"
    hand_path = scaled_hand(tmp_path, factors) if factors else HAND_YAML
    done = handctl(
        "run",
        "recipe",
        str(recipe),
        "--hand",
        str(hand_path),
        "--max-seconds",
        f"{approach['max_s']:g}",
        "--log",
        str(log),
    )
    assert done.returncode == 0, done.stderr
    last = None
    with log.open("rb") as f:
        for _, _, message in make_reader(f).iter_messages(topics=["/hand/joint_state"]):
            last = json.loads(message.data)
    assert last is not None
    hand = load_hand(HAND_YAML)
    estimator = ObjectEstimator(hand, load_recipe(RECIPE, hand).objects)
    segments = estimator.segments(last["angle_rad"])
    tips = []
    link = -1
    for finger in hand.fingers:
        link += len(finger.joints)  # the finger's distal link
        x, _, ux, _, length, _ = segments[link]
        tips.append(abs(x + ux * length))
    return tips


@pytest.fixture(scope="module")
def nominal_tips(tmp_path_factory: pytest.TempPathFactory) -> list[float]:
    return _approach_end(tmp_path_factory.mktemp("nominal"), RECIPE, {})


@pytest.mark.parametrize("model", sorted(STIFF))
def test_the_approach_brings_the_tips_beside_the_pair_whatever_the_friction(
    tmp_path: Path, model: str, nominal_tips: list[float]
) -> None:
    tips = _approach_end(tmp_path, RECIPE, STIFF[model])
    assert all(t <= n + WIDER for t, n in zip(tips, nominal_tips, strict=True)), (
        tips,
        nominal_tips,
    )
    # and without the integral, the same hand stops short: what the test is about
    doc = yaml.safe_load(RECIPE.read_text())
    doc["phases"][0]["pose"].pop("integral")
    bare = tmp_path / "bare"
    bare.mkdir()
    (bare / "recipe.yaml").write_text(yaml.safe_dump(doc, sort_keys=False))
    short = _approach_end(bare, bare / "recipe.yaml", STIFF[model])
    assert all(t > n + SHORT for t, n in zip(short, nominal_tips, strict=True)), (
        short,
        nominal_tips,
    )
