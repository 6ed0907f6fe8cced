"""Every hand-config error names the file, the key path, what was expected and what was found."""

from __future__ import annotations

import copy
import math
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest
import yaml

from handctl.config import load_hand
from handctl.errors import ConfigError

ROOT = Path(__file__).resolve().parents[2]
HAND_YAML = ROOT / "config" / "hands" / "hiroshima_hand.yaml"


@pytest.fixture
def base() -> dict[str, Any]:
    data = yaml.safe_load(HAND_YAML.read_text())
    assert isinstance(data, dict)
    return data


def write(tmp_path: Path, data: dict[str, Any]) -> Path:
    path = tmp_path / "hand.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


def error_for(tmp_path: Path, data: dict[str, Any]) -> ConfigError:
    path = write(tmp_path, data)
    with pytest.raises(ConfigError) as info:
        load_hand(path)
    assert isinstance(info.value, ValueError)
    assert str(path) in str(info.value)
    return info.value


def test_default_hand_loads_as_nine_joints_on_three_nodes() -> None:
    hand = load_hand(HAND_YAML)
    assert hand.n_joints == 9
    assert [f.node_id for f in hand.fingers] == [1, 2, 3]
    assert hand.bus.fd and hand.bus.data_bitrate == 5_000_000
    assert hand.bus.loop_rate_hz == 1000
    assert all(j.tau_max <= j.device_tau_max for j in hand.joints)


def test_config_is_immutable() -> None:
    hand = load_hand(HAND_YAML)
    with pytest.raises(AttributeError):
        hand.fingers[0].joints[0].tau_max = 10.0  # type: ignore[misc]


def test_hash_ignores_comments_and_sim_but_not_limits(tmp_path: Path,
                                                      base: dict[str, Any]) -> None:
    original = load_hand(write(tmp_path, base)).config_hash
    with_sim = copy.deepcopy(base)
    with_sim["sim"] = {"anything": 1}
    assert load_hand(write(tmp_path, with_sim)).config_hash == original
    changed = copy.deepcopy(base)
    changed["fingers"][0]["joints"][0]["tau_max"] = 0.5
    assert load_hand(write(tmp_path, changed)).config_hash != original


def test_missing_tau_max_has_no_default(tmp_path: Path, base: dict[str, Any]) -> None:
    del base["fingers"][1]["joints"][2]["tau_max"]
    err = error_for(tmp_path, base)
    assert err.key == "fingers[1].joints[2].tau_max"
    assert "required" in err.expected


def test_unknown_key_is_refused(tmp_path: Path, base: dict[str, Any]) -> None:
    base["fingers"][0]["joints"][1]["tau_maxx"] = 1.0
    err = error_for(tmp_path, base)
    assert err.key == "fingers[0].joints[1].tau_maxx"
    assert "unknown key" in err.expected


def test_unknown_top_level_key(tmp_path: Path, base: dict[str, Any]) -> None:
    base["limits"] = {}
    assert error_for(tmp_path, base).key == "limits"


def key_path(path: tuple[Any, ...]) -> str:
    """The key path as handctl spells it: dots between keys, [i] for list indices."""
    out = ""
    for part in path:
        out += f"[{part}]" if isinstance(part, int) else (f".{part}" if out else part)
    return out


@pytest.mark.parametrize(("path", "value", "expected"), [
    (("fingers", 0, "joints", 0, "tau_max"), "lots", "a number"),
    (("fingers", 0, "joints", 0, "tau_max"), True, "a number"),
    (("fingers", 2, "node_id"), 1.5, "an integer"),
    (("bus", "fd"), "yes", "true or false"),
    (("fingers", 0, "base"), [0, 0], "a mapping"),
    (("fingers", 1, "joints"), {"a": 1}, "a list"),
    (("name",), None, "a non-empty string"),
])
def test_wrong_types(tmp_path: Path, base: dict[str, Any], path: tuple[Any, ...], value: Any,
                     expected: str) -> None:
    target = base
    for key in path[:-1]:
        target = target[key]
    target[path[-1]] = value
    err = error_for(tmp_path, base)
    assert err.key == key_path(path)
    assert expected in err.expected


@pytest.mark.parametrize(("path", "value"), [
    (("fingers", 0, "joints", 0, "tau_max"), -0.1),
    (("fingers", 0, "joints", 0, "tau_max"), 0.0),
    (("fingers", 0, "joints", 0, "rate_limit"), 0),
    (("fingers", 0, "joints", 0, "link_length"), 2.5),
    (("fingers", 2, "node_id"), 16),
    (("fingers", 2, "can_ids", "feedback"), 0x800),
    (("bus", "bitrate"), 2_000_000),
    (("bus", "data_bitrate"), 500_000),
    (("bus", "loop_rate_hz"), 0),
])
def test_out_of_range(tmp_path: Path, base: dict[str, Any], path: tuple[Any, ...],
                      value: Any) -> None:
    target = base
    for key in path[:-1]:
        target = target[key]
    target[path[-1]] = value
    err = error_for(tmp_path, base)
    assert err.key == key_path(path)
    assert err.found == value


def test_non_finite_number(tmp_path: Path, base: dict[str, Any]) -> None:
    base["fingers"][0]["joints"][0]["rate_limit"] = math.inf
    err = error_for(tmp_path, base)
    assert "finite" in err.expected


def test_tau_max_above_device_limit(tmp_path: Path, base: dict[str, Any]) -> None:
    base["fingers"][0]["joints"][0]["tau_max"] = 0.9
    err = error_for(tmp_path, base)
    assert err.key == "fingers[0].joints[0].tau_max"
    assert "device_tau_max" in err.expected


def test_angle_limits_must_be_ordered(tmp_path: Path, base: dict[str, Any]) -> None:
    base["fingers"][2]["joints"][0]["angle_max"] = -2.0
    assert error_for(tmp_path, base).key == "fingers[2].joints[0].angle_max"


def test_duplicate_node_id(tmp_path: Path, base: dict[str, Any]) -> None:
    base["fingers"][2]["node_id"] = 1
    err = error_for(tmp_path, base)
    assert err.key == "fingers[2].node_id"
    assert "fingers[0]" in err.expected


def test_duplicate_can_id(tmp_path: Path, base: dict[str, Any]) -> None:
    base["fingers"][1]["can_ids"]["status"] = base["fingers"][0]["can_ids"]["feedback"]
    err = error_for(tmp_path, base)
    assert err.key == "fingers[1].can_ids.status"
    assert "fingers[0].can_ids.feedback" in err.expected


def test_can_id_of_estop_is_reserved(tmp_path: Path, base: dict[str, Any]) -> None:
    base["fingers"][0]["can_ids"]["heartbeat"] = 0
    err = error_for(tmp_path, base)
    assert err.key == "fingers[0].can_ids.heartbeat"


def test_duplicate_joint_name(tmp_path: Path, base: dict[str, Any]) -> None:
    base["fingers"][2]["joints"][1]["name"] = "f1_j1"
    err = error_for(tmp_path, base)
    assert err.key == "fingers[2].joints[1].name"


def test_classic_bus_takes_no_data_bitrate(tmp_path: Path, base: dict[str, Any]) -> None:
    base["bus"]["fd"] = False
    err = error_for(tmp_path, base)
    assert err.key == "bus.data_bitrate"


def test_missing_file_and_bad_yaml(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="no such file"):
        load_hand(tmp_path / "nope.yaml")
    bad = tmp_path / "bad.yaml"
    bad.write_text("name: [unclosed\n")
    with pytest.raises(ConfigError, match=r"valid YAML.*line"):
        load_hand(bad)
    top = tmp_path / "list.yaml"
    top.write_text("- 1\n- 2\n")
    with pytest.raises(ConfigError, match="a mapping at the top level"):
        load_hand(top)


def test_yaml_is_loaded_safely(tmp_path: Path) -> None:
    evil = tmp_path / "evil.yaml"
    evil.write_text("name: !!python/object/apply:os.system ['echo pwned']\n")
    with pytest.raises(ConfigError, match="valid YAML"):
        load_hand(evil)


def run_cli(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "handctl", *args], cwd=ROOT,
                          capture_output=True, text=True, timeout=120, check=False)


def test_check_cli_accepts_default_hand() -> None:
    result = run_cli("check", "config/hands/hiroshima_hand.yaml")
    assert result.returncode == 0, result.stderr
    assert "total 39.1 %" in result.stdout
    assert result.stdout.rstrip().endswith("ok")


def test_check_cli_bad_config_exits_2_with_the_message(tmp_path: Path,
                                                       base: dict[str, Any]) -> None:
    del base["fingers"][0]["joints"][0]["tau_max"]
    path = write(tmp_path, base)
    result = run_cli("check", str(path))
    assert result.returncode == 2
    assert f"{path}: fingers[0].joints[0].tau_max: expected" in result.stderr
    assert "Traceback" not in result.stderr


def test_check_cli_refuses_classic_can_and_says_what_fits() -> None:
    result = run_cli("check", "config/hands/hiroshima_hand_classic.yaml")
    assert result.returncode == 2
    assert "122.6 %" in result.stderr
    assert "403 Hz" in result.stderr
    assert "one bus per finger would carry 40.9 %" in result.stderr
