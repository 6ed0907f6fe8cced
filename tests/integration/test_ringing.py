"""A feedback too stiff for a joint makes its command ring at tens of hertz while every limit
holds: the run says so (a warning, the summary's ``chatter``), on the simulated hand."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from tests.conftest import HAND_YAML, handctl

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


#: three fingers close on the pair and lift it, the guard's usual band: the guard damps the
#: distal joints of finger 3 as they near their limits
CLOSE_AND_LIFT = """
recipe: close_and_lift
limit_guard_band: 0.15
phases:
- name: close
  torques: {f1_j1: 0.10, f1_j2: 0.06, f1_j3: 0.05, f2_j1: 0.10, f2_j2: 0.06, f2_j3: 0.05,
            f3_j1: -0.20, f3_j2: -0.12, f3_j3: -0.03}
  ramp_s: 0.3
  max_s: 1.0
  on_timeout: next
- name: lift
  torques: {f1_j1: 0.15, f1_j2: 0.12, f1_j3: 0.05, f2_j1: 0.15, f2_j2: 0.12, f2_j3: 0.05,
            f3_j1: -0.30, f3_j2: -0.15, f3_j3: -0.03}
  ramp_s: 0.3
  max_s: 1.5
  on_timeout: next
"""


@pytest.mark.parametrize("rate_hz", ["250", "333", "1000"])
def test_the_guard_holds_its_joints_without_ringing_at_any_loop_rate(
    tmp_path: Path, rate_hz: str
) -> None:
    """The velocity the guard damps was a line through the last 8 ticks, 7 ms at 1 kHz and
    28 ms at 250 Hz: lagging 14 ms, the damper came too late for the spring, and finger 3's
    distal joints rang at 20 Hz for seconds at 250 and 333 Hz, where at 1 kHz they held.
    The line now spans 7 ms at every rate."""
    text = HAND_YAML.read_text()
    assert "loop_rate_hz: 1000 " in text
    hand = tmp_path / "hand.yaml"
    hand.write_text(text.replace("loop_rate_hz: 1000 ", f"loop_rate_hz: {rate_hz} "))
    recipe = tmp_path / "close_and_lift.yaml"
    recipe.write_text(CLOSE_AND_LIFT)
    out = tmp_path / "summary.json"
    done = handctl(
        "run", "recipe", str(recipe), "--hand", str(hand), "--lockstep",
        "--summary-json", str(out),
    )  # fmt: skip
    summary = json.loads(out.read_text())
    assert summary["completed"] and not summary["faults"], done.stderr
    assert "chatter" not in summary, summary["chatter"]
    assert "rang" not in done.stderr
