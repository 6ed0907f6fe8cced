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


def _hanging_hand(tmp_path: Path) -> tuple[Path, dict[str, Any], float]:
    """The default hand whose first joint's range ends 0.1 rad above where it starts: it
    starts at -0.55 rad and hangs towards -0.3 under gravity, so the range is crossed at
    once, and the start is valid. The config's path, the joint (as loaded YAML) and its
    initial angle (rad)."""
    data: dict[str, Any] = yaml.safe_load(HAND_YAML.read_text())
    joint: dict[str, Any] = data["fingers"][0]["joints"][0]
    start: float = data["sim"]["initial_angles"][data["fingers"][0]["name"]][0]
    joint["angle_max"] = start + 0.1
    path = tmp_path / "hangs.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path, joint, start


@pytest.mark.parametrize(
    "name", ["hiroshima_hand.yaml", "planar_2f2j.yaml", "four_fingers_four_joints.yaml"]
)
def test_the_shipped_hands_stay_within_their_limits_idle(name: str) -> None:
    hand = load_hand(ROOT / "config" / "hands" / name)
    assert idle_excursions(hand, parse_sim(hand)) == []


def test_a_finger_that_hangs_past_its_limit_is_said_by_check_before_calibrate_meets_it(
    tmp_path: Path,
) -> None:
    path, joint, start = _hanging_hand(tmp_path)
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


def test_a_standalone_hand_says_when_it_has_hung_past_its_limits(tmp_path: Path) -> None:
    """``handctl sim`` waits for a host with no torque on its fingers, as long as it runs,
    and they hang where gravity takes them: the shipped hand's distal joints pass their
    limits after about 45 s, and every run then stops before any torque. The hand said
    nothing of it (found by an outside audit); it says it once, with what to do. A finger
    whose range ends 0.1 rad from where it starts, towards where it hangs, passes at once."""
    path, joint, _ = _hanging_hand(tmp_path)
    bus = tmp_path / "bus"
    bus.mkdir()
    done = handctl("sim", "--hand", str(path), "--bus", f"unix:{bus}", "--seconds", "2.5")
    assert done.returncode == 0, done.stderr
    said = [line for line in done.stderr.splitlines() if "hung past its soft limits" in line]
    assert len(said) == 1, done.stderr
    assert f"({joint['name']} at " in said[0] and "--recover" in said[0]
    # the shipped hand, as long: nothing said
    shipped = handctl("sim", "--bus", f"unix:{bus}", "--seconds", "2.5")
    assert shipped.returncode == 0, shipped.stderr
    assert "hung past" not in shipped.stderr
