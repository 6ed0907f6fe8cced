"""The experiment bench's seeds as tasks: a seed's figures are the same in a worker process as
here (the hand and the recipe travel as data)."""

from __future__ import annotations

from pathlib import Path

import yaml

from handctl.config import HandConfig
from handctl.executor import open_pool
from handctl.harness.seed_run import SeedRun, run_seed
from handctl.online.recipes.loader import load_recipe
from handctl.portable import portable_hand

from ..conftest import ROOT

RECIPE = ROOT / "config" / "recipes" / "swap_two_cylinders.yaml"


def test_a_seed_gives_the_same_figures_in_a_worker_as_here(
    hand: HandConfig, tmp_path: Path
) -> None:
    """On the recipe's phases up to its lift (a quarter of its run): the figures of a seed
    are the same wherever it runs whatever the recipe's length, and the lift is where the
    perturbed model first shows in them."""
    data = yaml.safe_load(RECIPE.read_text())
    names = [p["name"] for p in data["phases"]]
    data["phases"] = data["phases"][: names.index("lift") + 1]
    path = tmp_path / "lift.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    recipe = load_recipe(path, hand)
    task = SeedRun(portable_hand(hand), recipe, 1003, "all")
    here = run_seed(task)
    with open_pool(2) as pool:
        [there] = pool.map(run_seed, [task])
    assert here.pop("wall_s") > 0 and there.pop("wall_s") > 0
    assert here == there
    assert here["seed"] == 1003
    assert {"mass.1", "radius.2", "damping", "placement_m"} <= set(here["scales"])
    assert here["lifted"] is not None
    assert here["outcome"] == "completed" and here["message"] == ""
    assert here["ringing_joints"] == []


def test_a_stopped_seed_says_why(hand: HandConfig) -> None:
    """A run stopped short (here by its time budget; on the bench, mostly a safety stop
    naming the fault and the joint) carries the run's message into the seed's figures, which
    the bench prints beside a failed seed."""
    recipe = load_recipe(RECIPE, hand)
    figures = run_seed(SeedRun(portable_hand(hand), recipe, 1003, "all", max_seconds=0.3))
    assert figures["outcome"] == "time_budget"
    assert figures["message"], figures
