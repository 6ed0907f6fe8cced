"""``handctl check`` runs the simulated hand idle and says which joint gravity carries past
a soft limit: the first zero-torque run (``calibrate tdt``) otherwise found it out, stopped
on ANGLE_LIMIT."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest
import yaml

from handctl.config import load_hand
from handctl.sim.idle import idle_excursions
from handctl.sim.params import parse_sim

from ..conftest import HAND_YAML, ROOT, handctl


@pytest.mark.parametrize(
    "name", ["hiroshima_hand.yaml", "planar_2f2j.yaml", "four_fingers_four_joints.yaml"]
)
def test_the_shipped_hands_stay_within_their_limits_idle(name: str) -> None:
    hand = load_hand(ROOT / "config" / "hands" / name)
    assert idle_excursions(hand, parse_sim(hand)) == []


def test_a_finger_that_hangs_past_its_limit_is_said_by_check_before_calibrate_meets_it(
    tmp_path: Path,
) -> None:
    data: dict[str, Any] = yaml.safe_load(HAND_YAML.read_text())
    joint = data["fingers"][0]["joints"][0]
    start = data["sim"]["initial_angles"][data["fingers"][0]["name"]][0]
    # the finger's first joint starts at -0.55 rad and hangs towards -0.3 under gravity: a
    # range that ends 0.1 rad above the start is crossed at once, and the start is valid
    joint["angle_max"] = start + 0.1
    path = tmp_path / "hangs.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    hand = load_hand(path)
    found = idle_excursions(hand, parse_sim(hand))
    assert [e.joint for e in found] == [0]
    assert found[0].limit == pytest.approx(start + 0.1)
    assert found[0].start == pytest.approx(start) and found[0].angle > start + 0.1
    done = handctl("check", str(path))
    assert done.returncode == 0, done.stderr
    name = joint["name"]
    assert (
        f"with no torque on the simulated hand, {name} goes from its initial {start:+.3f} rad "
        f"past its soft limit {start + 0.1:+.3f} rad in {found[0].time_s:.3f} s"
    ) in done.stderr
    assert "stops on ANGLE_LIMIT" in done.stderr
    # and what it warns of is what the zero-torque run meets
    calibrated = handctl("calibrate", "tdt", "--hand", str(path), "-o", str(tmp_path / "c.yaml"))
    assert calibrated.returncode == 3, calibrated.stderr
    assert "ANGLE_LIMIT at tick" in calibrated.stderr and f"{name} at " in calibrated.stderr
    assert not (tmp_path / "c.yaml").exists()
