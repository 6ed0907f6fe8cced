"""The shipped hands of other shapes, end to end through the command line as a user runs them:
the paper's planar two fingers of two joints (its analysis on its own geometry, its lift-and-turn
template planned to the committed recipe, that recipe lifting both cylinders), four fingers of
four joints closing on one cylinder and lifting it, and for every shipped hand ``handctl sim``
answering ``handctl nodes`` and a lockstep run's log re-run bit-exact. Everything goes through
``python -m handctl`` in a process of its own, on the protocol generated for each hand."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import pytest
import yaml

from handctl.analysis.model import load_scenario
from handctl.config import load_hand
from handctl.online.recipes.loader import load_recipe
from handctl.sim.params import parse_sim

from ..conftest import HAND_YAML, ROOT, handctl
from .realtime import REALTIME

HANDS = ROOT / "config" / "hands"
RECIPES = ROOT / "config" / "recipes"
PLANAR = HANDS / "planar_2f2j.yaml"
FOUR_BY_FOUR = HANDS / "four_fingers_four_joints.yaml"
PLANAR_ANALYSIS = ROOT / "config" / "analysis" / "planar_2f2j.yaml"
PLANAR_TEMPLATE = RECIPES / "planar_lift_turn.template.yaml"
PLANAR_RECIPE = RECIPES / "planar_lift_turn.yaml"
FOUR_BY_FOUR_RECIPE = RECIPES / "four_by_four_close.yaml"
#: m: how far the paper's grasp may sit from the scene's cylinders (the analysis has the pair
#: touching and enveloped, the scene has it resting on the table 1 mm apart)
GRASP_ABOVE_REST_M = 0.05


# -- the paper's planar hand: analysis and planning on its own geometry ---------------------


def test_the_planar_analysis_is_the_hand_configs_geometry() -> None:
    """The scenario's fingers and cylinders are the hand config's: bases, link lengths, radii
    and masses, the torque bound within every joint's tau_max; the cylinders are its scene's,
    enveloped a little above where they rest."""
    scenario = load_scenario(PLANAR_ANALYSIS)
    hand = load_hand(PLANAR)
    grasp = scenario.grasp
    assert [f.name for f in grasp.fingers] == [f.name for f in hand.fingers]
    for finger, configured in zip(grasp.fingers, hand.fingers, strict=True):
        assert finger.base[0] == pytest.approx(configured.base_x)
        assert finger.base[1] == pytest.approx(configured.base_y)
        assert list(finger.lengths) == pytest.approx([j.link_length for j in configured.joints])
    assert scenario.tau_max <= min(j.tau_max for j in hand.joints)
    scene = parse_sim(hand).objects
    assert [b.name for b in grasp.bodies] == [o.name for o in scene]
    for body, obj in zip(grasp.bodies, scene, strict=True):
        assert body.radius == pytest.approx(obj.radius) and body.mass == pytest.approx(obj.mass)
        assert body.position[0] == pytest.approx(obj.x, abs=0.001)
        assert 0.0 < body.position[1] - obj.y < GRASP_ABOVE_REST_M
    # the grasp is the scene's gravity's: a vertical hand, the net force on each object
    assert grasp.gravity[1] == pytest.approx(-parse_sim(hand).gravity)
    assert grasp.reading == "net"


def test_the_planar_analysis_runs_on_its_own_geometry(tmp_path: Path) -> None:
    out = tmp_path / "region.json"
    done = handctl(
        "analyze",
        "torque-set",
        str(PLANAR_ANALYSIS),
        "--k",
        "0.9",
        "0.1",
        "--json",
        str(out),
        "--plot",
        str(tmp_path / "region.png"),
    )
    assert done.returncode == 0, done.stderr
    region = json.loads(out.read_text())
    assert region["conditions"] == ["move cyl1", "move cyl2", "compression cyl1/cyl2"]
    assert region["box"]["tau11"] == pytest.approx([-0.45, 0.45])
    assert region["realisable_area"] > 0  # contact forces realise torques in that box
    # against gravity, within the hand's torques, some turn the pair as Fig. 3 asks
    assert region["region"]["area"] > 0 and region["best"]["margin"] > 0
    assert all(abs(tau) <= 0.45 for tau in region["best"]["tau"])
    assert "largest robust margin" in done.stdout
    assert (tmp_path / "region.png").stat().st_size > 0


def test_the_planar_template_plans_the_committed_recipe(tmp_path: Path) -> None:
    """``handctl plan`` of the lift-and-turn template (two worker processes) writes the recipe
    that is committed, byte for byte after its header: that recipe is what the template asks
    for on this hand, and planning it stays small enough for CI. Written over a recipe of
    another hand, it says so (a plan of twenty minutes went without a word)."""
    out = tmp_path / "planned.yaml"
    out.write_text((ROOT / "config" / "recipes" / "swap_two_cylinders.yaml").read_text())
    done = handctl(
        "plan",
        str(PLANAR_TEMPLATE.relative_to(ROOT)),
        "--hand",
        str(PLANAR.relative_to(ROOT)),
        "-o",
        str(out),
        "--workers",
        "2",
    )
    assert done.returncode == 0, done.stderr
    assert (
        f"handctl: warning: {out} held another recipe (recipe swap_two_cylinders, for another "
        "hand (sha256:"
    ) in done.stderr
    header = 2  # "compiled by" and the command, which names the output file
    planned = out.read_text().splitlines()[header:]
    committed = PLANAR_RECIPE.read_text().splitlines()[header:]
    assert planned == committed
    for phase in ("approach", "lift", "envelop", "turn"):
        assert phase in done.stdout


def test_a_one_object_template_plans_on_the_four_by_four_hand(tmp_path: Path) -> None:
    """The planner takes sixteen joints and one object: the four-by-four recipe's closing
    torques as a free phase, then a lift and a hold it plans (the smallest search)."""
    recipe = yaml.safe_load(FOUR_BY_FOUR_RECIPE.read_text())
    template = {
        "template": "close_and_lift",
        "recipe": "close_and_lift",
        "objects": recipe["objects"],
        "limit_guard_band": recipe["limit_guard_band"],
        "phases": [
            {
                "name": "close",
                "kind": "free",
                "torques": recipe["phases"][0]["torques"],
                "max_s": 1.0,
            },
            {
                "name": "lift",
                "kind": "lift",
                "move": {"cylinder": [0.0, 1.0]},
                "min_height": 0.02,
                "max_s": 1.5,
            },
            {"name": "hold", "kind": "hold", "min_height": 0.02, "max_s": 1.0},
        ],
    }
    path = tmp_path / "close_and_lift.template.yaml"
    path.write_text(yaml.safe_dump(template, sort_keys=False))
    out = tmp_path / "planned.yaml"
    done = handctl(
        "plan",
        str(path),
        "--hand",
        str(FOUR_BY_FOUR),
        "-o",
        str(out),
        "--quick",
        "--models",
        "1",
        "--workers",
        "1",
    )
    assert done.returncode == 0, done.stderr
    hand = load_hand(FOUR_BY_FOUR)
    planned = load_recipe(out, hand)
    assert planned.compiled and planned.hand_config_hash == hand.config_hash
    assert [p.name for p in planned.phases] == ["close", "lift", "hold"]
    assert all(len(p.torques) == hand.n_joints == 16 for p in planned.phases)


# -- lockstep runs of the shipped shapes, their logs re-run ---------------------------------

#: hand, recipe, the objects the run must lift and report
RUNS = {
    "planar_2f2j": (PLANAR, PLANAR_RECIPE, {"cyl1", "cyl2"}),
    "four_fingers_four_joints": (FOUR_BY_FOUR, FOUR_BY_FOUR_RECIPE, {"cylinder"}),
}


@pytest.mark.parametrize("shape", list(RUNS))
def test_the_shapes_recipe_lifts_its_objects_and_its_log_reruns_bit_exact(
    shape: str, tmp_path: Path
) -> None:
    hand_path, recipe, objects = RUNS[shape]
    hand = load_hand(hand_path)
    out = tmp_path / "out.json"
    done = handctl(
        "run",
        "recipe",
        str(recipe),
        "--hand",
        str(hand_path),
        "--lockstep",
        "--summary-json",
        str(out),
        "--log",
        "run.mcap",
        cwd=tmp_path,
    )
    assert done.returncode == 0, done.stderr
    summary = json.loads(out.read_text())
    assert summary["completed"] is True and summary["faults"] == []
    assert summary["hand"] == hand.name
    # every joint of the hand was driven over the bus, on its own node's frames
    assert list(summary["max_abs_tau_nm"]) == list(hand.joint_names)
    assert all(tau > 0 for tau in summary["max_abs_tau_nm"].values())
    ex = summary["experiment"]
    assert ex["success"] is True and ex["lifted"] is True and ex["dropped"] is False
    assert set(ex["objects"]) == objects
    for name, obj in ex["objects"].items():
        assert obj["lifted"] is True and obj["final"]["height_above_rest_m"] > 0.02, name
    # the log re-runs: the same recipe on the same simulated hand, bit-exact
    replay = tmp_path / "replay.json"
    done = handctl("replay", "run.mcap", "--rerun", "--json", str(replay), cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    assert "applied torques bit-exact" in done.stdout
    assert set(json.loads(replay.read_text())["summary"]["objects"]) == objects


def test_a_turn_phase_named_for_what_it_does_is_measured_as_a_manipulation(
    tmp_path: Path,
) -> None:
    """The summary measured the turn of the phases named ``manipulate...`` only: the planar
    recipe with its turn phase named ``turn`` said the pair turned nothing, and held for the
    whole run. Planned as a turn and ending on one, it is measured as the same phase named
    ``manipulate`` is, in the run's summary and in its log's replay."""
    text = PLANAR_RECIPE.read_text()
    assert text.count("- name: manipulate\n") == 1
    renamed = tmp_path / "renamed.yaml"
    renamed.write_text(text.replace("- name: manipulate\n", "- name: turn\n"))
    summaries = []
    for recipe in (PLANAR_RECIPE, renamed):
        out, log = tmp_path / f"{recipe.stem}.json", tmp_path / f"{recipe.stem}.mcap"
        done = handctl(
            "run", "recipe", str(recipe), "--hand", str(PLANAR), "--lockstep",
            "--summary-json", str(out), "--log", str(log),
        )  # fmt: skip
        assert done.returncode == 0, done.stderr
        summaries.append(json.loads(out.read_text())["experiment"])
    shipped, named = summaries
    assert shipped["phase_angles_deg"] and shipped["phase_angles_deg"][0] < -5
    for key in ("phase_angles_deg", "peak_turn_rate_deg_s", "objects", "success"):
        assert named[key] == shipped[key], key
    replay = tmp_path / "replay.json"
    done = handctl("replay", str(tmp_path / "renamed.mcap"), "--json", str(replay))
    assert done.returncode == 0, done.stderr
    assert json.loads(replay.read_text())["summary"]["phase_turns_deg"] == pytest.approx(
        shipped["phase_angles_deg"], abs=0.05
    )


# -- every shipped hand as `handctl sim`, answering `handctl nodes` --------------------------


@REALTIME
@pytest.mark.parametrize("hand_path", [HAND_YAML, PLANAR, FOUR_BY_FOUR], ids=lambda p: p.stem)
def test_the_shape_runs_as_handctl_sim_and_answers_as_its_nodes(
    hand_path: Path, tmp_path: Path
) -> None:
    hand = load_hand(hand_path)
    spec = f"unix:{tmp_path / 'bus'}"
    truth = tmp_path / "truth.json"
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "handctl",
            "sim",
            "--hand",
            str(hand_path),
            "--bus",
            spec,
            "--seconds",
            "60",
            "--summary-json",
            str(truth),
        ],
        cwd=ROOT,
        text=True,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
    )
    try:
        report: dict[str, Any] = {}
        # The simulated hand takes a moment to start, and a loaded machine may hold its timer
        # back for longer than a listening window: ask again rather than blame the hand.
        for _ in range(20):
            done = handctl(
                "nodes",
                "--bus",
                spec,
                "--hand",
                str(hand_path),
                "--json",
                "--seconds",
                "0.6",
                timeout=120,
            )
            report = json.loads(done.stdout) if done.stdout else {}
            if done.returncode == 0 and report.get("ok"):
                break
            time.sleep(0.5)
        assert report.get("ok"), report
        rows = {row["node_id"]: row for row in report["nodes"]}
        assert set(rows) == {f.node_id for f in hand.fingers}
        assert all(row["present"] and row["state"] == "DISABLED" for row in rows.values())
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=60)
        assert proc.returncode in (0, 130), err
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    ground = json.loads(truth.read_text())
    assert set(ground["nodes"]) == {f.name for f in hand.fingers}
    assert set(ground["objects"]) == {o.name for o in parse_sim(hand).objects}


def test_a_hand_of_two_links_runs_its_estimator_and_records_the_run(tmp_path: Path) -> None:
    """One finger of two joints around one cylinder: the object estimator meets two contacts
    at most, and raised at the first tick (ESTIMATOR_EXCEPTION, exit 3); the recording's
    writer, which runs the same estimator for its Foxglove channels, died with it and left
    the log without a chunk."""
    data = ROOT / "tests" / "data"
    log = tmp_path / "run.mcap"
    done = handctl(
        "run",
        "recipe",
        str(data / "recipes" / "close_one_finger.yaml"),
        "--hand",
        str(data / "hands" / "one_finger_two_joints.yaml"),
        "--max-seconds",
        "1",
        "--log",
        str(log),
    )
    assert done.returncode in (0, 1), done.stderr  # 1: a close alone lifts nothing
    assert "ESTIMATOR_EXCEPTION" not in done.stderr and "Traceback" not in done.stderr
    again = handctl("replay", str(log), "--rerun")
    assert again.returncode == 0, again.stderr
    assert "applied torques bit-exact" in again.stdout
