"""A controlled stop on a hand whose joint hangs near its soft limit, held there by torque.

The stop takes the torque out at the joints' rate limits; the hanging joint sinks past its
soft limit once its torque is gone. That is the hand coming to rest, as after any run, and a
time budget or Ctrl-C is still the controlled stop it was asked for: exit 0 (or 130), the
joint said in the summary and the log, never a safety stop for the stop itself."""

from __future__ import annotations

import json
from pathlib import Path

from ..conftest import ROOT, handctl

DATA = ROOT / "tests" / "data"
HAND = DATA / "hands" / "sagging_joint_hand.yaml"
RECIPE = DATA / "recipes" / "sagging_joint.yaml"


def test_a_joint_sinking_out_as_a_time_budget_stops_the_run_is_said_not_a_safety_stop(
    tmp_path: Path,
) -> None:
    """Stopped at 0.45 s, in the middle of the stretch (0.4..0.55 s) where the stop takes
    the torque from fg0_j4 and it sinks out of its limit; later, the recipe itself runs it
    out (a fault, as it should be)."""
    out, log = tmp_path / "out.json", tmp_path / "run.mcap"
    result = handctl(
        "run", "recipe", str(RECIPE), "--hand", str(HAND), "--lockstep",
        "--max-seconds", "0.45", "--summary-json", str(out), "--log", str(log),
    )  # fmt: skip
    assert result.returncode == 0, result.stderr
    summary = json.loads(out.read_text(encoding="utf-8"))
    assert summary["outcome"] == "time_budget" and summary["faults"] == []
    (note,) = summary["left_limits_in_stop"]
    assert note.startswith("fg0_j4 at -1.0") and "not a fault" in note
    assert "fg0_j4" in result.stderr and "not a fault" in result.stderr
    # the joint did leave its limit (-1.048 rad; the note shows three decimals)
    assert float(note.split()[2]) <= -1.048
    # the re-run repeats the stop and its note, bit for bit
    rerun = handctl("replay", str(log), "--rerun")
    assert rerun.returncode == 0, rerun.stderr + rerun.stdout
    assert "bit-exact" in rerun.stderr + rerun.stdout
    assert "not repeated" not in rerun.stderr + rerun.stdout
