"""The experiment bench's estimator cost on any shape of hand: it ran a stored pose of the
default hand's nine joints, and on the four-by-four hand (16 joints) stopped with an
IndexError after every seed had run."""

from __future__ import annotations

import pytest

from handctl.config import HandConfig, load_hand
from handctl.online.recipes.loader import load_recipe

from ..conftest import ROOT, load_tool

SHAPES = [
    ("hiroshima_hand", "swap_two_cylinders"),
    ("four_fingers_four_joints", "four_by_four_close"),
    ("planar_2f2j", "planar_lift_turn"),
]


@pytest.mark.parametrize(("hand_name", "recipe_name"), SHAPES)
def test_the_estimator_cost_is_measured_on_poses_of_the_hand_it_runs(
    hand_name: str, recipe_name: str
) -> None:
    bench = load_tool("bench_experiment")
    hand: HandConfig = load_hand(ROOT / "config" / "hands" / f"{hand_name}.yaml")
    recipe = load_recipe(ROOT / "config" / "recipes" / f"{recipe_name}.yaml", hand)
    closed, opened = bench._cost_poses(hand, recipe)
    assert len(closed) == len(opened) == len(hand.joints)
    for q, joint in zip(opened, hand.joints, strict=True):
        assert joint.angle_min <= q <= joint.angle_max
    p50, p99 = bench._estimator_cost_us(hand, recipe)
    assert 0 < p50 <= p99
