"""The swap on a hand whose cylinder 1 is 12 % larger than the recipe says, in lockstep, with
the shipped recipe: the estimator measures the radius in the hold, and ``manipulate_3``
takes the torque its ``schedule`` carries for a large cylinder 1. With the phase's own
torque finger 1's distal link does not flip over the larger pair, the pair is not swept,
and it leans on finger 2's distal joint until that reaches its limit (``ANGLE_LIMIT``) or
the pair is turned back. The run is logged and re-run bit-exact from its log, choice
included: the measured radius is the estimator's, from the logged angles."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

from ..conftest import ROOT, handctl

RECIPE = ROOT / "config" / "recipes" / "swap_two_cylinders.yaml"
#: cylinder 1's simulated radius as a factor of the configured one (the recipe's)
RADIUS = {"cyl1": 1.12, "cyl2": 1.0}
#: deg: manipulate_3 asks for 45 (the wrong way, +, with its own torque on this hand)
TURNED_DEG = -35.0


def _hand(tmp_path: Path) -> Path:
    """The shipped hand with cylinder 1 resized (``tools/resize_objects.py``)."""
    path = tmp_path / "hand.yaml"
    scales = [f"--scale={name}={factor:g}" for name, factor in RADIUS.items()]
    done = subprocess.run(
        [sys.executable, str(ROOT / "tools" / "resize_objects.py"), *scales, "-o", str(path)],
        capture_output=True,
        text=True,
        check=False,
    )
    assert done.returncode == 0, done.stderr
    return path


def test_a_large_cylinder_1_is_swapped_with_the_torque_scheduled_for_it(tmp_path: Path) -> None:
    out, log = tmp_path / "summary.json", tmp_path / "run.mcap"
    run = handctl(
        "run",
        "recipe",
        str(RECIPE),
        "--hand",
        str(_hand(tmp_path)),
        "--summary-json",
        str(out),
        "--log",
        str(log),
    )
    summary = json.loads(out.read_text())
    ex = summary["experiment"]
    phases = {p["name"]: p for p in summary["phases"]}
    assert phases["manipulate_3"]["schedule"].startswith("cyl1 radius x1.1"), phases
    assert phases["manipulate_3"]["schedule"].endswith(": schedule[0]"), phases
    assert summary["outcome"] == "completed", (summary["outcome"], summary["message"])
    assert run.returncode == 0, run.stdout + run.stderr
    assert ex["success"], ex
    assert ex["phase_angles_deg"][2] <= TURNED_DEG, ex
    done = handctl("replay", str(log), "--rerun")
    assert done.returncode == 0, done.stdout + done.stderr
    assert "bit-exact" in done.stdout
