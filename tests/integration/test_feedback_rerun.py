"""Feedback keeps a run reproducible: a lockstep run of the experiment's first phases with a
pose hold, the soft-limit guard, a turn-rate loop, brakes and a paced ramp is recorded, and
``handctl replay --rerun`` computes the very same torques from the logged angles (bit-exact),
because the feedback reads only the angles and the estimates made from them."""

from __future__ import annotations

from pathlib import Path

import yaml

from ..conftest import ROOT, handctl

RECIPE = ROOT / "config" / "recipes" / "swap_two_cylinders.yaml"
POSE = {
    "f1_j1": -0.26,
    "f1_j2": -0.58,
    "f1_j3": 1.24,
    "f2_j1": -0.26,
    "f2_j2": -0.58,
    "f2_j3": 1.24,
    "f3_j1": 0.26,
    "f3_j2": 0.58,
    "f3_j3": -1.24,
}


def _with_feedback(tmp_path: Path) -> Path:
    data = yaml.safe_load(RECIPE.read_text())
    phases = data["phases"][:5]
    phases[0]["pose"] = {"angles": POSE, "stiffness": 0.5, "damping": 0.005}
    phases[2]["max_s"] = 0.8  # envelop: long enough for the estimate to be valid
    phases[3]["max_s"] = 0.5
    # at most the phase's own torque: manipulate_1's is close to tau_max (the loader holds a
    # larger scale to it)
    phases[3]["turn_rate"] = {"rate_deg_s": -45, "scale": [0.5, 1.0]}
    phases[3]["brake"] = {"rate_deg_s": 30, "joint_damping": 0.03}
    phases[3].pop("paced_ramp", None)  # the turn-rate loop is this phase's feedback
    phases[4]["max_s"] = 0.5
    phases[4]["paced_ramp"] = {"rate_deg_s": -30, "back": 3, "joint_rate": 1.0}
    phases[4]["brake"] = {"rate_deg_s": 30, "joint_damping": 0.03, "joint_rate": 0.5}
    for phase in phases:  # a ramp within its shortened phase
        phase["ramp_s"] = min(phase.get("ramp_s", 0.1), phase["max_s"])
    data["phases"] = phases
    path = tmp_path / "feedback.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def test_a_run_with_feedback_reruns_bit_exact(tmp_path: Path) -> None:
    log = tmp_path / "run.mcap"
    run = handctl("run", "recipe", str(_with_feedback(tmp_path)), "--log", str(log))
    # the experiment is cut short, so it fails (exit 1); the hand is fine
    assert run.returncode == 1, run.stderr
    assert "completed" in run.stdout
    done = handctl("replay", str(log), "--rerun")
    assert done.returncode == 0, done.stdout + done.stderr
    assert "bit-exact" in done.stdout
