"""The swap on hands whose cylinders are another size than the recipe says, in lockstep, with
the shipped recipe: the estimator measures the radii in the hold, and ``manipulate_3`` takes
the torque its ``schedule`` carries for those sizes.

Cylinder 1 16 % larger beside a cylinder 2 3 % larger: with the phase's own torque finger 1's
distal link does not flip over the larger pair, the pair is not swept, and it leans on finger
2's distal joint until that reaches its limit or the pair is turned back; the torque planned
for a large pair swaps it. The run is logged and re-run bit-exact from its log, choice
included: the measured radius is the estimator's, from the logged angles. Both cylinders 15 %
larger: the same entry swaps the pair in steps of about 45 degrees. Cylinder 1 15 % smaller
beside a cylinder 2 6 % larger: ``manipulate_2`` stops short (about 20 degrees) and the
phase's own torque then turns the pair back; the entry planned for such pairs turns it on.
Cylinder 1 the recipe's size beside a cylinder 2 15 % larger: the phase's own torque turns the
pair back in ``manipulate_3`` and ``manipulate_4``; the same entry, taken on the sign of
cylinder 2's measured size, turns it on as well."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

from ..conftest import ROOT, handctl

RECIPE = ROOT / "config" / "recipes" / "swap_two_cylinders.yaml"
#: the cylinders' simulated radii as factors of the configured ones (the recipe's)
RADIUS = {"cyl1": 1.16, "cyl2": 1.03}
#: both cylinders' (the first entry of manipulate_3's schedule)
BOTH = {"cyl1": 1.15, "cyl2": 1.15}
#: cylinder 1 small beside a larger cylinder 2 (the second entry)
SMALL_BESIDE_LARGE = {"cyl1": 0.85, "cyl2": 1.06}
#: cylinder 1 the recipe's size beside a larger cylinder 2 (the second entry as well)
NEAR_BESIDE_LARGE = {"cyl1": 1.0, "cyl2": 1.15}
#: deg: manipulate_3 asks for 45 (the wrong way, +, with the phase's own torque on these hands)
TURNED_DEG = -35.0
#: deg: the bench's swap (the cylinders traded places)
SWAP_DEG = 170.0


def _hand(tmp_path: Path, radius: dict[str, float]) -> Path:
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


def _run(tmp_path: Path, radius: dict[str, float], *extra: str) -> tuple[int, dict[str, Any], str]:
    """Run the shipped recipe on the hand resized by ``radius``: the exit code, the summary,
    and what ``manipulate_3``'s record says it chose."""
    out = tmp_path / "summary.json"
    run = handctl(
        "run", "recipe", str(RECIPE), "--hand", str(_hand(tmp_path, radius)),
        "--summary-json", str(out), *extra,
    )  # fmt: skip
    assert out.exists(), run.stdout + run.stderr
    summary = json.loads(out.read_text())
    phases = {p["name"]: p for p in summary["phases"]}
    return run.returncode, summary, str(phases["manipulate_3"]["schedule"])


def test_a_large_cylinder_1_is_swapped_with_the_torque_planned_for_a_large_pair(
    tmp_path: Path,
) -> None:
    log = tmp_path / "run.mcap"
    code, summary, chosen = _run(tmp_path, RADIUS, "--log", str(log))
    ex = summary["experiment"]
    assert chosen.startswith("cyl1 radius x1.1"), chosen
    # the first entry: cylinder 1 large beside a cylinder 2 not measured small
    assert chosen.endswith(": schedule[0]"), chosen
    assert summary["outcome"] == "completed", (summary["outcome"], summary["message"])
    assert code == 0, summary["message"]
    assert ex["success"], ex
    assert ex["phase_angles_deg"][2] <= TURNED_DEG, ex
    done = handctl("replay", str(log), "--rerun")
    assert done.returncode == 0, done.stdout + done.stderr
    assert "bit-exact" in done.stdout


def test_two_large_cylinders_are_swapped_with_the_torque_planned_for_them(
    tmp_path: Path,
) -> None:
    code, summary, chosen = _run(tmp_path, BOTH)
    ex = summary["experiment"]
    assert chosen.endswith(": schedule[0]"), chosen
    assert code == 0, summary["message"]
    assert ex["success"] and ex["total_rotation_deg"] >= SWAP_DEG, ex
    assert all(abs(abs(a) - 45.0) <= 10.0 for a in ex["phase_angles_deg"]), ex


@pytest.mark.parametrize(
    ("radius", "measured", "turned"),
    [
        # cylinder 1 measured smaller beside a cylinder 2 measured larger: manipulate_2's
        # own entry for a small cylinder 1 (manipulate_3's torque, sooner, finger 1's
        # lighter) turns this pair 51 deg, and manipulate_3 has the half of what is left, 34
        # deg, to turn (with finger 1's torque as manipulate_3's, 60 and 27; before the entry,
        # 23 and 39, and the last phase 81 at 235 deg/s)
        (SMALL_BESIDE_LARGE, "cyl1 radius x0.8", -20.0),
        # cylinder 1 within the estimator's tolerance reads the recipe's radius exactly
        (NEAR_BESIDE_LARGE, "cyl1 radius x1.000, cyl2 radius x1.1", TURNED_DEG),
    ],
    ids=["small-beside-large", "recipes-size-beside-large"],
)
def test_a_larger_cylinder_2_beside_a_cylinder_1_not_large_is_turned_on_by_the_second_entry(
    tmp_path: Path, radius: dict[str, float], measured: str, turned: float
) -> None:
    code, summary, chosen = _run(tmp_path, radius)
    ex = summary["experiment"]
    assert chosen.startswith(measured), chosen
    assert chosen.endswith(": schedule[1]"), chosen
    assert code == 0, summary["message"]
    assert ex["success"], ex
    assert ex["phase_angles_deg"][2] <= turned, ex  # on, not back (+) as its own torque did
