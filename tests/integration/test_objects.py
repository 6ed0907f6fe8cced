"""Recipes of one, two and three objects, end to end in lockstep on the simulated hand: each
object lifted, held and reported; a recipe naming objects the simulated hand lacks is refused
before anything runs. The hands are the default one with its scene's cylinders replaced
(the two-object swap is the default recipe, ``test_experiment.py``)."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest
import yaml

from handctl import cli
from handctl.config import load_hand
from handctl.online.recipes.loader import load_recipe
from handctl.recording import channels as ch
from handctl.recording.reader import iter_decoded, open_recording
from handctl.session import RunRequest, run_recipe

from ..conftest import HAND_YAML, ROOT

RECIPES = ROOT / "tests" / "data" / "recipes"
#: the scenes: cylinders along z on the table (y = table + r), between the fingers
DRUM = [
    {
        "name": "drum",
        "radius": 0.030,
        "length": 0.080,
        "mass": 0.050,
        "x": 0.0,
        "y": -0.110,
        "angle": 0.0,
    }
]
THREE = [
    {
        "name": name,
        "radius": 0.012,
        "length": 0.080,
        "mass": 0.020,
        "x": x,
        "y": -0.128,
        "angle": 0.0,
    }
    for name, x in (("left", -0.025), ("middle", 0.0), ("right", 0.025))
]
#: m: the estimator places a single enveloped cylinder this well (p95), from the angles alone
ONE_OBJECT_ESTIMATE_M = 0.002


def hand_with(tmp_path: Path, objects: list[dict[str, Any]]) -> Path:
    """The default hand config with ``objects`` as its simulated scene's cylinders."""
    doc = yaml.safe_load(HAND_YAML.read_text())
    doc["sim"]["objects"] = objects
    path = tmp_path / f"hand_{len(objects)}_objects.yaml"
    path.write_text(yaml.safe_dump(doc, sort_keys=False))
    return path


def run(tmp_path: Path, objects: list[dict[str, Any]], recipe: str) -> dict[str, Any]:
    hand = load_hand(hand_with(tmp_path, objects))
    report = run_recipe(
        RunRequest(hand=hand, recipe=load_recipe(RECIPES / recipe, hand), plot=tmp_path / "run.png")
    )
    assert (tmp_path / "run.png").stat().st_size > 0
    return report.summary


def test_one_cylinder_is_lifted_held_and_located(tmp_path: Path) -> None:
    """Through the command line: the summary JSON, the plot, and the printed experiment, which
    gives the object's estimator error and no turn (there is no pair)."""
    out, plot = tmp_path / "out.json", tmp_path / "run.png"
    done = subprocess.run(
        [
            sys.executable,
            "-m",
            "handctl",
            "run",
            "recipe",
            str(RECIPES / "hold_one_cylinder.yaml"),
            "--hand",
            str(hand_with(tmp_path, DRUM)),
            "--summary-json",
            str(out),
            "--plot",
            str(plot),
            "--log",
            "run.mcap",
        ],
        cwd=tmp_path,
        text=True,
        capture_output=True,
        timeout=600,
        check=False,
    )
    assert done.returncode == 0, done.stderr
    summary = json.loads(out.read_text())
    assert summary["completed"] is True and summary["faults"] == []
    ex = summary["experiment"]
    assert ex["success"] is True and ex["lifted"] is True and ex["dropped"] is False
    drum = ex["objects"]["drum"]
    assert drum["held_s"] >= 2.0
    assert drum["final"]["height_above_rest_m"] > 0.01
    assert drum["estimator_error_m"] <= ONE_OBJECT_ESTIMATE_M
    assert "turn_deg" not in ex and "pairs" not in ex  # one object: no pair, no turn
    assert plot.stat().st_size > 0
    assert "estimator p95 drum " in done.stdout and "turn per phase" not in done.stdout
    # The log says the same: one object, no line to turn, a plot of the hand's one group per
    # finger, and a re-run bit-exact with the recorded pairs (none).
    replayed = tmp_path / "replay.json"
    done = subprocess.run(
        [
            sys.executable,
            "-m",
            "handctl",
            "replay",
            "run.mcap",
            "--rerun",
            "--plot",
            "replay.png",
            "--json",
            str(replayed),
        ],
        cwd=tmp_path,
        text=True,
        capture_output=True,
        timeout=600,
        check=False,
    )
    assert done.returncode == 0, done.stderr
    logged = json.loads(replayed.read_text())
    assert list(logged["summary"]["objects"]) == ["drum"]
    assert "turn_deg" not in logged["summary"] and "turn of the centre line" not in done.stdout
    assert (tmp_path / "replay.png").stat().st_size > 0


def test_three_cylinders_are_lifted_held_and_each_reported(tmp_path: Path) -> None:
    summary = run(tmp_path, THREE, "hold_three_cylinders.yaml")
    assert summary["completed"] is True and summary["faults"] == []
    ex = summary["experiment"]
    assert ex["success"] is True and ex["dropped"] is False
    assert set(ex["objects"]) == {"left", "middle", "right"}
    for name, obj in ex["objects"].items():
        assert obj["lifted"] is True and obj["held_s"] >= 2.0, name
        assert obj["final"]["height_above_rest_m"] > 0.01, name
    assert set(ex["pairs"]) == {"left/middle", "middle/right"}


def test_the_log_and_its_replay_measure_the_pairs_the_recipe_declares(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    doc = yaml.safe_load((RECIPES / "hold_three_cylinders.yaml").read_text())
    doc["pairs"] = [["right", "left"], ["left", "middle"]]  # not the first two objects
    doc["phases"] = doc["phases"][:1]
    doc["phases"][0]["max_s"] = 0.4
    recipe = tmp_path / "pairs.yaml"
    recipe.write_text(yaml.safe_dump(doc, sort_keys=False))
    log, out = tmp_path / "run.mcap", tmp_path / "replay.json"
    hand = hand_with(tmp_path, THREE)
    cli.main(["run", "recipe", str(recipe), "--hand", str(hand), "--log", str(log)])
    assert cli.main(["replay", str(log), "--json", str(out)]) == cli.EXIT_OK
    # the one phase left is no manipulation: the lines are measured, no turn is said
    assert "turn of the centre line" not in capsys.readouterr().out
    summary = json.loads(out.read_text())["summary"]
    assert list(summary["pairs"]) == ["right/left", "left/middle"]
    assert summary["objects_line_pair"] == "right/left"
    start = summary["objects"]
    for name, (a, b) in (("right/left", ("right", "left")), ("left/middle", ("left", "middle"))):
        p, q = start[a]["start"], start[b]["start"]
        line = math.atan2(q["y_m"] - p["y_m"], q["x_m"] - p["x_m"])
        assert summary["pairs"][name]["line_angle_rad"]["start"] == pytest.approx(line, abs=1e-3)
    assert summary["objects_line_angle_rad"] == summary["pairs"]["right/left"]["line_angle_rad"]
    assert abs(summary["objects_line_angle_rad"]["start"]) > 3.0  # right to left: about pi
    recording = open_recording(log)
    poses = [msg for _, _, msg in iter_decoded(recording, (ch.OBJECTS,))]
    assert poses and all(
        [p["name"] for p in msg["pairs"]] == ["right/left", "left/middle"]
        and msg["line_angle_rad"] == msg["pairs"][0]["line_angle_rad"]
        for msg in poses
    )


def test_a_recipe_of_objects_the_simulated_hand_lacks_is_refused(tmp_path: Path) -> None:
    """The default hand's scene has cyl1 and cyl2: a recipe for 'drum' exits 2 naming the
    recipe's key and the scene's objects, before the simulated hand is started."""
    done = subprocess.run(
        [
            sys.executable,
            "-m",
            "handctl",
            "run",
            "recipe",
            str(RECIPES / "hold_one_cylinder.yaml"),
            "--summary-json",
            str(tmp_path / "out.json"),
        ],
        cwd=tmp_path,
        text=True,
        capture_output=True,
        timeout=600,
        check=False,
    )
    assert done.returncode == 2, done.stderr
    assert "hold_one_cylinder.yaml: objects[0].name" in done.stderr
    assert "cyl1, cyl2" in done.stderr and "drum" in done.stderr
    assert not (tmp_path / "out.json").exists() or "ticks" not in json.loads(
        (tmp_path / "out.json").read_text()
    )


@pytest.mark.parametrize("recipe", ["hold_one_cylinder.yaml", "hold_three_cylinders.yaml"])
def test_the_recipes_load_against_the_default_hand(recipe: str) -> None:
    """Their torques and ramps are within the default hand's limits (``check_against_hand``)."""
    loaded = load_recipe(RECIPES / recipe, load_hand(HAND_YAML))
    assert 1 <= len(loaded.objects) <= 4


def test_a_recipe_of_no_objects_has_no_centre_line_in_its_replay(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A hold written by hand, declaring no objects, on the default hand, whose scene has
    two: the replay's summary said "turn of the centre line cyl1/cyl2: per phase [] deg,
    turn +0.00 deg", a line the recipe never declared, turned in no phase. Its run measures
    no pair; nor does its replay."""
    joints = len(load_hand(HAND_YAML).joint_names)
    recipe = tmp_path / "hold.yaml"
    recipe.write_text(
        yaml.safe_dump(
            {
                "recipe": "hold_no_objects",
                "description": "a hold that declares no objects",
                "end_ramp_s": 0.1,
                "phases": [
                    {
                        "name": "hold",
                        "torques": [0.02] * joints,
                        "ramp_s": 0.1,
                        "max_s": 0.3,
                        "on_timeout": "next",
                    }
                ],
            },
            sort_keys=False,
        )
    )
    log, out = tmp_path / "run.mcap", tmp_path / "replay.json"
    assert cli.main(["run", "recipe", str(recipe), "--log", str(log)]) == cli.EXIT_OK
    capsys.readouterr()
    assert cli.main(["replay", str(log), "--json", str(out)]) == cli.EXIT_OK
    printed = capsys.readouterr().out
    summary = json.loads(out.read_text())["summary"]
    assert len(summary["objects"]) == 2  # the scene's cylinders, logged all the same
    assert "turn of the centre line" not in printed
    assert "pairs" not in summary and "turn_deg" not in summary
