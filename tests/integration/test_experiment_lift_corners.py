"""Everything before the manipulation, on the corners of the model set the lift is least sure
of, in lockstep; the run is stopped at the end of the last phase before the first manipulation
phase (``--max-seconds``): up to there it must lift both cylinders, hold them caged, drop
nothing and stop on nothing.

- Joint damping and tendon friction at the bottom of the model set (×0.3). There the lift
  moves the distal joints three times as fast as on the nominal hand and the limit guard's
  spring, acting through the drive's lag, has little of the joint's own damping to lean on; a
  finger flung past its soft limit stopped the run in the lift (``ANGLE_LIMIT``).
- Both cylinders at the top of their mass range (×1.5), on the nominal hand and on the light
  one. With the planned torques times 1.3 the pair pushed the fingers open and a distal joint
  past its limit; the lift's margin per joint and its injected damping are for these
  (docs/experiment.md, "Torque margin").
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import yaml

from ..conftest import ROOT, handctl
from .scaled_hand import scaled_hand

RECIPE = ROOT / "config" / "recipes" / "swap_two_cylinders.yaml"
#: the simulated joints' and objects' factors at the corners of the model set
#: (``planning/models.py``)
CORNERS = {
    "light": {"damping": 0.3, "frictionloss": 0.3},
    "heavy_pair": {"mass": 1.5},
    "heavy_pair_light_hand": {"damping": 0.3, "frictionloss": 0.3, "mass": 1.5},
}
#: s, the experiment's own hold before the first manipulation (``experiment/merit.py``)
HELD_S = 2.0


def _before_manipulation() -> tuple[float, str]:
    """s from the start to the end of the last phase before a manipulation phase, and that
    phase's name: these phases end on their timeouts (none has an exit), so their ``max_s``
    add up."""
    phases = yaml.safe_load(RECIPE.read_text())["phases"]
    before = []
    for phase in phases:
        if phase["name"].startswith("manipulate"):
            break
        assert not phase.get("exit"), phase["name"]
        before.append(phase)
    assert before, "the recipe has no phase before its manipulation"
    return sum(p["max_s"] for p in before), before[-1]["name"]


@pytest.mark.parametrize("corner", sorted(CORNERS))
def test_the_lift_s_corners_lift_and_hold_the_pair(tmp_path: Path, corner: str) -> None:
    out = tmp_path / "summary.json"
    until, last = _before_manipulation()
    done = handctl(
        "run",
        "recipe",
        str(RECIPE),
        "--hand",
        str(scaled_hand(tmp_path, CORNERS[corner])),
        "--max-seconds",
        f"{until:g}",
        "--summary-json",
        str(out),
    )
    summary = json.loads(out.read_text())
    ex = summary["experiment"]
    # stopped by the time budget at the end of the hold, not by the supervisor
    assert summary["outcome"] == "time_budget", (summary["outcome"], summary["message"])
    assert not summary["faults"], summary["faults"]
    assert done.returncode == 0, done.stderr
    assert summary["phases"][-1]["name"] == last, summary["phases"]
    assert ex["lifted"] and not ex["dropped"], ex
    assert ex["held_s"] >= HELD_S, ex
