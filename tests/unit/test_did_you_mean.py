"""A renamed key is reported with the stray key beside it and the name it probably meant."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest
import yaml

from handctl.config import HandConfig, load_hand
from handctl.errors import ConfigError
from handctl.online.recipes.loader import load_recipe
from handctl.schema import Doc
from tests.conftest import HAND_YAML

JOINTS = ["f1_j1", "f1_j2", "f1_j3", "f2_j1", "f2_j2", "f2_j3", "f3_j1", "f3_j2", "f3_j3"]


def recipe(**phase: Any) -> dict[str, Any]:
    base = {"name": "a", "torques": dict.fromkeys(JOINTS, 0.1), "ramp_s": 0.1, "max_s": 1.0}
    base.update(phase)
    return {"recipe": "test", "phases": [base]}


def recipe_error(tmp_path: Path, hand: HandConfig, data: dict[str, Any]) -> ConfigError:
    path = tmp_path / "recipe.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    with pytest.raises(ConfigError) as info:
        load_recipe(path, hand)
    assert info.value.file == str(path)
    return info.value


def test_a_renamed_required_key_names_the_stray_one(tmp_path: Path, hand: HandConfig) -> None:
    data = recipe()
    data["phases"][0]["max_sec"] = data["phases"][0].pop("max_s")
    err = recipe_error(tmp_path, hand, data)
    assert err.key == "phases[0].max_s"
    assert "required" in err.expected
    assert "'max_sec' is here instead" in str(err.found)


def test_a_renamed_joint_names_the_stray_one_among_similar_joints(
    tmp_path: Path, hand: HandConfig
) -> None:
    torques = dict.fromkeys(JOINTS, 0.1)
    torques["f4_j1"] = torques.pop("f1_j1")
    err = recipe_error(tmp_path, hand, recipe(torques=torques))
    assert err.key == "phases[0].torques.f4_j1"
    assert "unknown key; did you mean 'f1_j1'?" in err.expected


def test_an_unknown_optional_key_suggests_the_key_that_was_read(tmp_path: Path) -> None:
    renamed = yaml.safe_load(HAND_YAML.read_text())
    renamed["safety"] = {"feedback_timeout_ms": 0.01}
    path = tmp_path / "hand.yaml"
    path.write_text(yaml.safe_dump(renamed))
    with pytest.raises(ConfigError) as info:
        load_hand(path)
    assert info.value.key == "safety.feedback_timeout_ms"
    assert "did you mean 'feedback_timeout_s'?" in info.value.expected


def test_no_guess_when_several_keys_are_equally_close() -> None:
    doc = Doc({"f1_j2": 1, "f2_j1": 2}, "x.yaml", "torques")
    with pytest.raises(ConfigError) as info:
        doc.number("f1_j1")
    assert str(info.value.found) == "nothing: the key is missing"


def test_no_guess_for_an_unrelated_key() -> None:
    doc = Doc({"colour": "red"}, "x.yaml", "")
    doc.raw("size", None)
    with pytest.raises(ConfigError) as info:
        doc.done()
    assert info.value.expected == "no such key here (unknown key)"
