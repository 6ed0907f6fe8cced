"""The experiment bench's ``--before-manipulation``: every run stops where the recipe's first
manipulation phase would begin, known beforehand only when no phase before it has an exit."""

from __future__ import annotations

from pathlib import Path
from types import ModuleType

import pytest
import yaml

from handctl.config import HandConfig
from handctl.errors import ConfigError
from handctl.online.recipes.loader import load_recipe

from ..conftest import ROOT, load_tool

RECIPE = ROOT / "config" / "recipes" / "swap_two_cylinders.yaml"


def _bench() -> ModuleType:
    return load_tool("bench_experiment")


def test_the_runs_stop_where_the_first_manipulation_phase_begins(hand: HandConfig) -> None:
    recipe = load_recipe(RECIPE, hand)
    first = next(k for k, p in enumerate(recipe.phases) if p.name.startswith("manipulate"))
    expected = sum(p.max_s for p in recipe.phases[:first])
    assert _bench()._before_manipulation_s(RECIPE, recipe) == pytest.approx(expected)


def test_an_exit_before_the_manipulation_is_refused_naming_it(
    tmp_path: Path, hand: HandConfig
) -> None:
    data = yaml.safe_load(RECIPE.read_text())
    data["phases"][1]["exit"] = ["time > 0.5"]
    path = tmp_path / "r.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    with pytest.raises(ConfigError) as info:
        _bench()._before_manipulation_s(path, load_recipe(path, hand))
    assert info.value.key == "phases[1].exit"
