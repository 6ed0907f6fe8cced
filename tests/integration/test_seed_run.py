"""The experiment bench's seeds as tasks: a seed's figures are the same in a worker process as
here (the hand and the recipe travel as data)."""

from __future__ import annotations

from handctl.config import HandConfig
from handctl.executor import open_pool
from handctl.harness.seed_run import SeedRun, run_seed
from handctl.online.recipes.loader import load_recipe
from handctl.portable import portable_hand

from ..conftest import ROOT

RECIPE = ROOT / "config" / "recipes" / "swap_two_cylinders.yaml"


def test_a_seed_gives_the_same_figures_in_a_worker_as_here(hand: HandConfig) -> None:
    recipe = load_recipe(RECIPE, hand)
    task = SeedRun(portable_hand(hand), recipe, 1003, "all")
    here = run_seed(task)
    with open_pool(2) as pool:
        [there] = pool.map(run_seed, [task])
    assert here.pop("wall_s") > 0 and there.pop("wall_s") > 0
    assert here == there
    assert here["seed"] == 1003
    assert {"mass.1", "radius.2", "damping", "placement_m"} <= set(here["scales"])
    assert here["lifted"] is not None
