"""The guarantees of docs/safety.md that no other test states on its own."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from handctl.cli import build_parser
from handctl.config import HandConfig
from handctl.errors import ConfigError
from handctl.online.busspec import BusSpec, parse_spec
from handctl.online.recipes.loader import load_recipe

from ..conftest import ROOT

RECIPE = ROOT / "config" / "recipes" / "swap_two_cylinders.yaml"


@pytest.mark.parametrize("key", ["tau_max", "rate_limit", "limits", "safety", "angle_max"])
def test_a_recipe_cannot_set_a_limit(tmp_path: Path, hand: HandConfig, key: str) -> None:
    data = yaml.safe_load(RECIPE.read_text())
    data[key] = 10.0
    path = tmp_path / "recipe.yaml"
    path.write_text(yaml.safe_dump(data))
    with pytest.raises(ConfigError) as info:
        load_recipe(path, hand)
    assert info.value.key == key
    data = yaml.safe_load(RECIPE.read_text())
    data["phases"][0][key] = 10.0
    path.write_text(yaml.safe_dump(data))
    with pytest.raises(ConfigError) as info:
        load_recipe(path, hand)
    assert info.value.key == f"phases[0].{key}"


def test_the_default_bus_is_the_simulated_hand() -> None:
    args = build_parser().parse_args(["run", "recipe", str(RECIPE)])
    assert args.bus == "sim"
    assert parse_spec(args.bus) == BusSpec("sim", "")


def test_the_configured_bus_is_used_only_when_named(hand: HandConfig) -> None:
    # The hand config names socketcan:can0; only the explicit spec "hand" reaches for it.
    assert parse_spec("hand", hand.bus) == BusSpec("socketcan", "can0")
    for spec in ("sim", "virtual:x"):
        assert parse_spec(spec, hand.bus).interface != "socketcan"
