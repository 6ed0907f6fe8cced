"""The analysis at the measured configuration in a whole run: a lockstep run of the
experiment's first phases, ``manipulate_1`` asking for the analysis (``reanalyse``), records
what the analysis answered, and ``handctl replay --rerun`` computes the same answer from the
logged angles on the same tick, so the re-run is bit-exact; a re-run without the analysis
differs, which shows the answer moved the torques."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import yaml

from handctl.recording.reader import open_recording
from handctl.recording.rerun import rerun

from ..conftest import ROOT, handctl

RECIPE = ROOT / "config" / "recipes" / "swap_two_cylinders.yaml"
HAND = ROOT / "config" / "hands" / "hiroshima_hand.yaml"


def _reanalysed(tmp_path: Path) -> Path:
    data = yaml.safe_load(RECIPE.read_text())
    sim = yaml.safe_load(HAND.read_text())["sim"]
    data["grasp_model"] = {
        "masses_kg": {o["name"]: o["mass"] for o in sim["objects"]},
        "friction": {
            "finger_object": sim["friction"]["finger_object"],
            "object_object": sim["friction"]["object_object"],
        },
        "gravity_m_s2": sim["gravity"],
        "contact_gap_m": 0.001,
    }
    phases = data["phases"][:4]
    phases[3]["max_s"] = 0.6
    phases[3]["ramp_s"] = min(phases[3]["ramp_s"], 0.6)  # a ramp within the shortened phase
    phases[3]["reanalyse"] = {"turn_deg": -45, "delay_s": 0.05, "use": "nearest"}
    # the analysis replaces the phase's torque, so its sized alternatives go (the loader
    # refuses both in one phase)
    phases[3].pop("schedule", None)
    data["phases"] = phases
    path = tmp_path / "reanalysed.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def test_a_reanalysed_run_records_its_answer_and_reruns_bit_exact(tmp_path: Path) -> None:
    log = tmp_path / "run.mcap"
    summary = tmp_path / "summary.json"
    run = handctl(
        "run",
        "recipe",
        str(_reanalysed(tmp_path)),
        "--log",
        str(log),
        "--summary-json",
        str(summary),
    )
    # the experiment is cut short, so it fails (exit 1); the hand is fine
    assert run.returncode == 1, run.stderr
    assert "completed" in run.stdout
    phase = json.loads(summary.read_text())["phases"][3]
    assert phase["name"] == "manipulate_1"
    assert phase["reanalysis"].startswith("nearest:"), phase
    assert "f1_j1/cyl1" in phase["reanalysis"]
    done = handctl("replay", str(log), "--rerun")
    assert done.returncode == 0, done.stdout + done.stderr
    assert "bit-exact" in done.stdout
    blind = rerun(open_recording(log))  # no analysis: the phase's planned torque throughout
    assert not blind.ok and blind.mismatched_ticks > 0


def test_a_run_whose_answer_came_late_reruns_bit_exact(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """In real time the answer may not be there ``delay_s`` after the request, and the phase
    keeps its planned torque ("late"); the re-run computed it on the tick and applied it,
    and a genuine log said MISMATCH (found by an outside audit). The lateness is the run's
    (a real-time run cannot be made late at will here: the run's answer is held back, in a
    lockstep run of this process); the re-run, in another process, has the real analysis."""
    from handctl import cli
    from handctl.planning import reanalysis

    monkeypatch.setattr(reanalysis.ReanalysisOnTick, "collect", lambda self, phase: None)
    log, summary = tmp_path / "run.mcap", tmp_path / "summary.json"
    recipe = str(_reanalysed(tmp_path))
    code = cli.main(["run", "recipe", recipe, "--log", str(log), "--summary-json", str(summary)])
    assert code == cli.EXIT_FAILED  # cut short: the experiment fails, the hand is fine
    monkeypatch.undo()
    phase = json.loads(summary.read_text())["phases"][3]
    assert phase["reanalysis"].startswith("late: no answer 0.05 s after the request"), phase
    done = handctl("replay", str(log), "--rerun")
    assert done.returncode == 0, done.stdout + done.stderr
    assert "bit-exact" in done.stdout
