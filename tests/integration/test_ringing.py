"""A feedback too stiff for a joint makes its command ring at tens of hertz while every limit
holds: the run says so (a warning, the summary's ``chatter``), on the simulated hand."""

from __future__ import annotations

import json
from pathlib import Path

from tests.conftest import handctl

#: the distal joints pushed into their limits with the narrowest guard band the loader takes:
#: on the nominal hand the guard's spring (tau_max / 0.02 rad) rings through the drive's lag
NARROW_GUARD = """
recipe: narrow_guard
limit_guard_band: 0.02
phases:
- name: push
  torques: {f1_j1: 0.0, f1_j2: 0.0, f1_j3: -0.1, f2_j1: 0.0, f2_j2: 0.0, f2_j3: -0.1,
            f3_j1: 0.0, f3_j2: 0.0, f3_j3: 0.1}
  ramp_s: 0.2
  max_s: 1.5
  on_timeout: next
"""


def test_a_guard_band_too_narrow_for_the_joint_is_said_to_ring(tmp_path: Path) -> None:
    recipe = tmp_path / "narrow_guard.yaml"
    out = tmp_path / "summary.json"
    for band, rings in (("0.02", True), ("0.15", False)):
        recipe.write_text(NARROW_GUARD.replace("0.02", band))
        done = handctl("run", "recipe", str(recipe), "--summary-json", str(out))
        assert done.returncode == 0, done.stderr  # the limits held: completed
        summary = json.loads(out.read_text())
        if not rings:
            assert "chatter" not in summary and "rang" not in done.stderr, summary.get("chatter")
            continue
        chatter = {c["joint"]: c for c in summary["chatter"]}
        assert set(chatter) == {"f1_j3", "f2_j3", "f3_j3"}
        for c in chatter.values():
            assert c["frequency_hz"] >= 10.0 and c["amplitude_nm"] >= 0.03
            assert c["seconds"] >= 0.5
        assert "warning: f1_j3's command rang" in done.stderr
