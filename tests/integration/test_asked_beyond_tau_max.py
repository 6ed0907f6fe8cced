"""A recipe that asks a joint for far more than its tau_max: the supervisor clamps it, so
nothing unsafe goes out, and the run now says it (a warning, the summary's
``asked_beyond_tau_max_nm``), on the simulated hand."""

from __future__ import annotations

import json
from pathlib import Path

from tests.conftest import handctl

#: the approach's pose with a spring far too stiff for the distal joints: from the simulated
#: hand's start, f1_j3 is some 0.5 rad from its pose angle, and 5 N·m/rad asks it for N·m
STIFF_POSE = """
recipe: stiff_pose
phases:
- name: approach
  torques: {f1_j1: 0.1, f1_j2: 0.06, f1_j3: 0.05, f2_j1: 0.1, f2_j2: 0.06, f2_j3: 0.05,
            f3_j1: -0.1, f3_j2: -0.06, f3_j3: -0.05}
  pose:
    angles: {f1_j1: -0.2572, f1_j2: -0.5542, f1_j3: 1.263, f2_j1: -0.2572, f2_j2: -0.5542,
             f2_j3: 1.263, f3_j1: 0.2572, f3_j2: 0.5543, f3_j3: -1.2629}
    stiffness: STIFFNESS
  ramp_s: 0.3
  max_s: 0.4
  on_timeout: next
"""


def test_a_joint_asked_for_far_past_its_tau_max_is_said(tmp_path: Path) -> None:
    recipe = tmp_path / "stiff_pose.yaml"
    out = tmp_path / "summary.json"
    recipe.write_text(STIFF_POSE.replace("STIFFNESS", "5"))
    done = handctl("run", "recipe", str(recipe), "--summary-json", str(out))
    assert done.returncode == 0, done.stderr  # the limits held: completed
    summary = json.loads(out.read_text())
    asked = summary["asked_beyond_tau_max_nm"]
    assert asked["f1_j3"] > 0.5, asked  # tau_max 0.3 N·m
    assert all(v <= tau for v, tau in zip(summary["max_abs_tau_nm"].values(), TAU_MAX, strict=True))
    said = [line for line in done.stderr.splitlines() if "the recipe asked" in line]
    assert len(said) == 1, done.stderr  # one line, however many joints
    assert said[0].startswith("handctl: warning: the recipe asked for more than tau_max")
    assert f"f1_j3 {asked['f1_j3']:.4g} N·m (tau_max 0.3)" in said[0]
    # a spring the joints can take asks nothing past them, and nothing is said
    recipe.write_text(STIFF_POSE.replace("STIFFNESS", "0.5"))
    done = handctl("run", "recipe", str(recipe), "--summary-json", str(out))
    assert done.returncode == 0, done.stderr
    assert "asked_beyond_tau_max_nm" not in json.loads(out.read_text())
    assert "the recipe asked" not in done.stderr


#: N·m, the nominal hand's tau_max in its joint order
TAU_MAX = (0.6, 0.45, 0.3) * 3
