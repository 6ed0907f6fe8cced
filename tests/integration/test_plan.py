"""``handctl plan`` end to end on a short template with the smallest search: a compiled recipe
the loader accepts, provenance on every phase, the same text twice, and the plots."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path
from typing import Any

import yaml

from handctl.config import HandConfig
from handctl.online.recipes.loader import load_recipe
from handctl.planning.compile import plan_recipe, quick_budget, recipe_text
from handctl.planning.template import load_template

from ..conftest import ROOT

TEMPLATE = ROOT / "config" / "recipes" / "swap_two_cylinders.template.yaml"


def short_template(tmp_path: Path) -> Path:
    """The shipped template cut to approach, lift, a short hold and one short turn."""
    data: dict[str, Any] = yaml.safe_load(TEMPLATE.read_text())
    data["search"]["random_seeds"] = 0
    phases = data["phases"]
    phases[2]["max_s"] = 0.5
    phases[3]["max_s"] = 1.0
    phases[0]["pose"] = {"stiffness": 0.5, "damping": 0.005}
    phases[3]["turn_rate"] = {"rate_deg_s": 45, "scale": [0.6, 1.5]}
    phases[3]["brake"] = {"rate_deg_s": 90, "joint_damping": 0.03}
    data["phases"] = phases[:4]
    path = tmp_path / "short.template.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def test_plan_compiles_a_recipe_with_provenance_reproducibly(
    tmp_path: Path, hand: HandConfig
) -> None:
    template = load_template(short_template(tmp_path), hand)
    first = recipe_text(plan_recipe(template, hand, models=1, budget=quick_budget()), "cmd")
    second = recipe_text(plan_recipe(template, hand, models=1, budget=quick_budget()), "cmd")
    assert first == second
    out = tmp_path / "planned.yaml"
    out.write_text(first)
    recipe = load_recipe(out, hand)
    assert recipe.compiled and recipe.hand_config_hash == hand.config_hash
    assert [p.name for p in recipe.phases] == ["approach", "lift", "envelop", "manipulate_1"]
    assert [o.name for o in recipe.objects] == ["cyl1", "cyl2"]
    assert recipe.phases[3].exits[0].text.startswith("estimate.cyl1_cyl2_line_turn <")
    # what the template asks of the experiment and of the feedback is carried into the recipe
    assert recipe.min_total_turn_deg == template.min_total_turn_deg > 0
    loop = recipe.phases[3].turn_rate
    assert loop is not None and loop.rate < 0  # signed as the clockwise turn
    assert (loop.scale_min, loop.scale_max) == (0.6, 1.5)
    assert template.phases[3].brake is not None
    assert recipe.phases[3].brake == template.phases[3].brake
    paced = recipe.phases[3].paced
    assert paced is not None and paced == template.phases[3].paced
    assert paced.rate < 0  # signed as the turn
    pose = recipe.phases[0].pose
    assert pose is not None and pose.stiffness == 0.5
    # the pose is where the nominal hand ends the approach: the fingers flexed from the start
    start = [q for finger in hand.sim["initial_angles"].values() for q in finger]
    assert all(abs(q - q0) > 0.05 for q, q0 in zip(pose.angles, start, strict=True))
    for phase in recipe.phases:
        prov = phase.provenance
        assert prov["hand_config_hash"] == hand.config_hash
        assert {"kind", "wanted", "chosen_from", "analysis", "models"} <= set(prov)
        assert "found" in prov["analysis"]
        if prov["kind"] != "free":
            assert {"score", "evaluated", "seed_scores"} <= set(prov["search"])
    # the lift is analysed where the fingertips first touch the objects
    lift = recipe.phases[1].provenance["analysis"]
    assert lift["contacts"] and ("margin_N" in lift or "reason" in lift)


def test_plan_command_writes_the_recipe_and_the_region_plots(tmp_path: Path) -> None:
    out = tmp_path / "r.yaml"
    plots = tmp_path / "plots"
    done = subprocess.run(
        [
            sys.executable,
            "-m",
            "handctl",
            "plan",
            str(short_template(tmp_path)),
            "-o",
            str(out),
            "--quick",
            "--models",
            "1",
            "--plot",
            str(plots),
        ],
        cwd=ROOT,
        text=True,
        capture_output=True,
        timeout=300,
        check=False,
    )
    assert done.returncode == 0, done.stderr
    assert out.read_text().startswith("# Compiled by handctl plan")
    assert " s wall, " in done.stdout and " s CPU (this process and its local workers)" in (
        done.stdout
    )
    assert sorted(p.name for p in plots.glob("*.png")) == [
        "01_approach.png",
        "02_lift.png",
        "03_envelop.png",
        "04_manipulate_1.png",
    ]
    assert "manipulate_1" in done.stdout
