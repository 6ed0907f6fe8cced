"""The swap on hands whose cylinders are larger than the recipe says, in lockstep, with the
shipped recipe: the estimator measures the radii in the hold, and ``manipulate_3`` takes the
torque its ``schedule`` carries for those sizes. Cylinder 1 12 % larger: with the phase's
own torque finger 1's distal link does not flip over the larger pair, the pair is not swept,
and it leans on finger 2's distal joint until that reaches its limit (``ANGLE_LIMIT``) or the
pair is turned back. The run is logged and re-run bit-exact from its log, choice included:
the measured radius is the estimator's, from the logged angles. Both cylinders 15 % larger:
both the phase's own torque and cylinder 1's turn the pair the wrong way; the entry planned
on hands with both cylinders large swaps it in steps of about 45 degrees."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

from ..conftest import ROOT, handctl

RECIPE = ROOT / "config" / "recipes" / "swap_two_cylinders.yaml"
#: cylinder 1's simulated radius as a factor of the configured one (the recipe's)
RADIUS = {"cyl1": 1.12, "cyl2": 1.0}
#: both cylinders' (the first entry of manipulate_3's schedule)
BOTH = {"cyl1": 1.15, "cyl2": 1.15}
#: deg: manipulate_3 asks for 45 (the wrong way, +, with its own torque on this hand)
TURNED_DEG = -35.0
#: deg: the bench's swap (the cylinders traded places)
SWAP_DEG = 170.0


def _hand(tmp_path: Path, radius: dict[str, float] = RADIUS) -> Path:
    """The shipped hand with its cylinders resized (``tools/resize_objects.py``)."""
    path = tmp_path / "hand.yaml"
    scales = [f"--scale={name}={factor:g}" for name, factor in radius.items()]
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
    # the second entry: cylinder 1 large, cylinder 2 not (the first is for both large)
    assert phases["manipulate_3"]["schedule"].endswith(": schedule[1]"), phases
    assert summary["outcome"] == "completed", (summary["outcome"], summary["message"])
    assert run.returncode == 0, run.stdout + run.stderr
    assert ex["success"], ex
    assert ex["phase_angles_deg"][2] <= TURNED_DEG, ex
    done = handctl("replay", str(log), "--rerun")
    assert done.returncode == 0, done.stdout + done.stderr
    assert "bit-exact" in done.stdout


def test_two_large_cylinders_are_swapped_with_the_torque_planned_for_them(
    tmp_path: Path,
) -> None:
    out = tmp_path / "summary.json"
    run = handctl(
        "run", "recipe", str(RECIPE), "--hand", str(_hand(tmp_path, BOTH)),
        "--summary-json", str(out),
    )  # fmt: skip
    summary = json.loads(out.read_text())
    ex = summary["experiment"]
    phases = {p["name"]: p for p in summary["phases"]}
    assert phases["manipulate_3"]["schedule"].endswith(": schedule[0]"), phases
    assert run.returncode == 0, run.stdout + run.stderr
    assert ex["success"] and ex["total_rotation_deg"] >= SWAP_DEG, ex
    assert all(abs(abs(a) - 45.0) <= 10.0 for a in ex["phase_angles_deg"]), ex
