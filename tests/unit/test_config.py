"""Every hand-config error names the file, the key path, what was expected and what was found."""

from __future__ import annotations

import copy
import math
from pathlib import Path
from typing import Any

import pytest
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from handctl.config import RESERVED_JOINT_NAMES, load_hand
from handctl.errors import ConfigError
from handctl.protocol import DEFAULT_DBC, Protocol, SignalSpec

from ..conftest import HAND_YAML, ROOT, handctl


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


def test_hash_ignores_comments_and_sim_but_not_limits(tmp_path: Path, base: dict[str, Any]) -> None:
    original = load_hand(write(tmp_path, base)).config_hash
    with_sim = copy.deepcopy(base)
    with_sim["sim"] = {"anything": 1}
    assert load_hand(write(tmp_path, with_sim)).config_hash == original
    changed = copy.deepcopy(base)
    changed["fingers"][0]["joints"][0]["tau_max"] = 0.5
    assert load_hand(write(tmp_path, changed)).config_hash != original


def test_a_real_number_spelled_whole_is_the_same_hand(tmp_path: Path) -> None:
    """``rate_limit: 20`` for ``20.0`` made every recipe compiled for the hand refuse it as
    another hand config; the shipped recipe now loads for either spelling, and one compiled
    before (the hash of the config as written) still loads for the hand it was made for."""
    from handctl.online.recipes.loader import load_recipe

    text = HAND_YAML.read_text()
    assert "rate_limit: 20.0" in text
    whole = tmp_path / "whole.yaml"
    whole.write_text(text.replace("rate_limit: 20.0", "rate_limit: 20"))
    shipped, respelled = load_hand(HAND_YAML), load_hand(whole)
    assert respelled.config_hash == shipped.config_hash
    assert respelled.legacy_hash != shipped.legacy_hash  # as written, they differ
    recipe = ROOT / "config" / "recipes" / "swap_two_cylinders.yaml"
    assert load_recipe(recipe, respelled).hand_config_hash == shipped.config_hash
    older = tmp_path / "older.yaml"
    older.write_text(recipe.read_text().replace(shipped.config_hash, shipped.legacy_hash))
    assert shipped.legacy_hash != shipped.config_hash  # loop_rate_hz: 1000 is written whole
    assert load_recipe(older, shipped).hand_config_hash == shipped.legacy_hash
    with pytest.raises(ConfigError, match="compiled for another hand config"):
        load_recipe(older, respelled)  # as written then, for the spelling of then


@pytest.mark.parametrize(
    ("value", "found"), [({}, "an empty section"), (None, "an empty section (null)")]
)
def test_an_empty_sim_section_is_said_to_be_empty(
    tmp_path: Path, base: dict[str, Any], value: Any, found: str
) -> None:
    """``sim: {}`` and ``sim:`` read as no section: check took the hand, and a run on the
    simulated hand said "the key is missing" of a key that is there."""
    base["sim"] = value
    err = error_for(tmp_path, base)
    assert err.key == "sim"
    assert "or no sim key at all for a hand that is never simulated" in err.expected
    assert str(err).endswith(f"found {found}")


def test_a_sim_section_of_another_type_is_described_not_quoted(
    tmp_path: Path, base: dict[str, Any]
) -> None:
    base["sim"] = [1, 2]
    assert str(error_for(tmp_path, base)).endswith("sim: expected a mapping, found list")


def test_a_hand_without_a_sim_section_loads(tmp_path: Path, base: dict[str, Any]) -> None:
    del base["sim"]
    assert not load_hand(write(tmp_path, base)).sim


def test_missing_tau_max_has_no_default(tmp_path: Path, base: dict[str, Any]) -> None:
    del base["fingers"][1]["joints"][2]["tau_max"]
    err = error_for(tmp_path, base)
    assert err.key == "fingers[1].joints[2].tau_max"
    assert "required" in err.expected
    # a key of its own still to be read is no misspelling of it: "'device_tau_max' is here
    # instead (a misspelling of it?)" sent the user to rename the wrong key (s42's list)
    assert str(err).endswith("found nothing: the key is missing"), str(err)


def test_a_misspelt_joint_key_is_named_with_the_key_it_means(
    tmp_path: Path, base: dict[str, Any]
) -> None:
    joint = base["fingers"][1]["joints"][2]
    joint["tau_maxx"] = joint.pop("tau_max")
    err = error_for(tmp_path, base)
    assert err.key == "fingers[1].joints[2].tau_maxx"
    assert "did you mean 'tau_max'?" in err.expected


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


@pytest.mark.parametrize(
    ("path", "value", "expected"),
    [
        (("fingers", 0, "joints", 0, "tau_max"), "lots", "a number"),
        (("fingers", 0, "joints", 0, "tau_max"), True, "a number"),
        (("fingers", 2, "node_id"), 1.5, "an integer"),
        (("bus", "fd"), "yes", "true or false"),
        (("fingers", 0, "base"), [0, 0], "a mapping"),
        (("fingers", 1, "joints"), {"a": 1}, "a list"),
        (("name",), None, "a non-empty string"),
    ],
)
def test_wrong_types(
    tmp_path: Path, base: dict[str, Any], path: tuple[Any, ...], value: Any, expected: str
) -> None:
    target = base
    for key in path[:-1]:
        target = target[key]
    target[path[-1]] = value
    err = error_for(tmp_path, base)
    assert err.key == key_path(path)
    assert expected in err.expected


@pytest.mark.parametrize(
    ("path", "value"),
    [
        (("fingers", 0, "joints", 0, "tau_max"), -0.1),
        (("fingers", 0, "joints", 0, "tau_max"), 0.0),
        (("fingers", 0, "joints", 0, "rate_limit"), 0),
        (("fingers", 0, "joints", 0, "link_length"), 2.5),
        # a point, not a link: MuJoCo failed to build the simulated hand (a traceback)
        (("fingers", 0, "joints", 0, "link_length"), 1e-12),
        (("fingers", 1, "joints", 2, "link_length"), 0.0005),
        (("fingers", 2, "node_id"), 16),
        (("fingers", 2, "can_ids", "feedback"), 0x800),
        (("bus", "bitrate"), 2_000_000),
        (("bus", "data_bitrate"), 500_000),
        (("bus", "loop_rate_hz"), 0),
        # a tick slower than half the nodes' 10 ms command watchdog: every run stopped on
        # the nodes' TIMEOUT at its second tick, a config check had passed
        (("bus", "loop_rate_hz"), 150),
    ],
)
def test_out_of_range(
    tmp_path: Path, base: dict[str, Any], path: tuple[Any, ...], value: Any
) -> None:
    target = base
    for key in path[:-1]:
        target = target[key]
    target[path[-1]] = value
    err = error_for(tmp_path, base)
    assert err.key == key_path(path)
    assert err.found == value


@pytest.mark.parametrize("timeout", [0.01, 0.1])
def test_a_heartbeat_watchdog_no_longer_than_the_heartbeat_period_is_refused(
    tmp_path: Path, base: dict[str, Any], timeout: float
) -> None:
    """Nodes send a heartbeat every 0.1 s: a watchdog of 0.01 s passed ``handctl check`` and
    stopped every run on HEARTBEAT_LOST within a tenth of a second."""
    base["safety"] = {"heartbeat_timeout_s": timeout}
    err = error_for(tmp_path, base)
    assert err.key == "safety.heartbeat_timeout_s" and "> 0.1" in err.expected
    base["safety"] = {"heartbeat_timeout_s": 0.15}
    assert load_hand(write(tmp_path, base)).safety.heartbeat_timeout_s == 0.15


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


def test_a_finger_given_the_next_node_s_ids_is_named_as_the_one_that_is_wrong(
    tmp_path: Path, base: dict[str, Any]
) -> None:
    """Finger 0 (node 1) given node 2's ids: the clash was said against finger 1 alone, whose
    ids are right, and the id shown as '0x12' where the config writes 0x012."""
    base["fingers"][0]["can_ids"] = dict(base["fingers"][1]["can_ids"])
    err = error_for(tmp_path, base)
    assert err.key == "fingers[1].can_ids.node_command"
    assert err.expected == (
        "a CAN id not used before (fingers[0].can_ids.node_command has it, where it is node "
        "2's by the id rule, not its node 1's)"
    )
    assert str(err.found) == "0x012"


def test_can_id_of_estop_is_reserved(tmp_path: Path, base: dict[str, Any]) -> None:
    base["fingers"][0]["can_ids"]["heartbeat"] = 0
    err = error_for(tmp_path, base)
    assert err.key == "fingers[0].can_ids.heartbeat"


def test_duplicate_joint_name(tmp_path: Path, base: dict[str, Any]) -> None:
    base["fingers"][2]["joints"][1]["name"] = "f1_j1"
    err = error_for(tmp_path, base)
    assert err.key == "fingers[2].joints[1].name"


def test_a_joint_may_not_take_a_key_of_the_log_s_joint_messages(
    tmp_path: Path, base: dict[str, Any]
) -> None:
    """A joint named tick was accepted, and overwrote the tick number in every /hand/joints
    message of its runs' logs."""
    from handctl.foxglove.derived import joints_schema

    beside = set(joints_schema(["j"])["properties"]) - {"j"}
    assert beside == set(RESERVED_JOINT_NAMES) == {"tick"}
    joint_of(base, 1, 0)["name"] = "tick"
    err = error_for(tmp_path, base)
    assert (err.key, err.found) == ("fingers[1].joints[0].name", "tick")
    assert "a name other than tick" in err.expected


@pytest.mark.parametrize("name", ["world", "palm", "table", "f1_base", "f2_base"])
def test_a_joint_may_not_take_a_name_of_the_scene_even_without_a_simulated_hand(
    tmp_path: Path, base: dict[str, Any], name: str
) -> None:
    """Only the simulated hand refused these: a hand without ``sim:`` ran with a joint named
    ``world`` or ``f1_base``, and every log of it had a Foxglove frame tree with a cycle or a
    frame of two parents (found by an outside audit)."""
    del base["sim"]
    joint_of(base, 1, 2)["name"] = name
    err = error_for(tmp_path, base)
    assert (err.key, err.found) == ("fingers[1].joints[2].name", name)
    assert err.expected.startswith(f"a name the scene does not take ({name!r} is ")


#: names check took: no recipe condition could name the first three (``angle.NAME`` is
#: ``[A-Za-z0-9_]+``), and the escape sequence and the newlines were printed raw by check,
#: nodes and a run's summary
ODD_PART_NAMES = ["f2 j1", "f2_jé", "a-b", "f.2", "f2\x1b[2Jj1", "f2\nX", "f2_j1\n", "1st"]


@pytest.mark.parametrize("name", ODD_PART_NAMES)
def test_a_joint_name_is_one_a_recipe_condition_can_name(
    tmp_path: Path, base: dict[str, Any], name: str
) -> None:
    joint_of(base, 1, 0)["name"] = name
    err = error_for(tmp_path, base)
    assert err.key == "fingers[1].joints[0].name"
    assert err.found == name
    assert "letters, digits and underscores, starting with a letter" in err.expected
    assert "angle.NAME, tdt.NAME" in err.expected


@pytest.mark.parametrize("name", ODD_PART_NAMES)
def test_a_finger_name_is_held_to_the_same_rule(
    tmp_path: Path, base: dict[str, Any], name: str
) -> None:
    base["fingers"][1]["name"] = name
    err = error_for(tmp_path, base)
    assert err.key == "fingers[1].name"
    assert "letters, digits and underscores, starting with a letter" in err.expected


def test_check_shows_a_refused_name_escaped(tmp_path: Path, base: dict[str, Any]) -> None:
    joint_of(base, 1, 0)["name"] = "f2\x1b[2Jj1"
    result = handctl("check", str(write(tmp_path, base)))
    assert result.returncode == 2
    assert "fingers[1].joints[0].name: expected a name of letters" in result.stderr
    assert "found 'f2\\x1b[2Jj1'" in result.stderr
    assert "\x1b" not in result.stdout + result.stderr


@pytest.mark.parametrize("value", [None, True, False, [1, 2], {}, 0.5, math.nan, -1, "", "  "])
def test_bus_channel_is_a_name_or_a_number(
    tmp_path: Path, base: dict[str, Any], value: Any
) -> None:
    """A channel of the wrong type was made a string ("None", "True", "[1, 2]") and opened."""
    base["bus"]["channel"] = value
    err = error_for(tmp_path, base)
    assert err.key == "bus.channel"
    assert "channel name" in err.expected


@pytest.mark.parametrize("value", ["can0", "vcan1", 0, 3])
def test_bus_channel_may_be_a_name_or_a_number(
    tmp_path: Path, base: dict[str, Any], value: Any
) -> None:
    base["bus"]["channel"] = value
    assert load_hand(write(tmp_path, base)).bus.channel == str(value)


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
    marker = tmp_path / "pwned"
    evil = tmp_path / "evil.yaml"
    evil.write_text(f"name: !!python/object/apply:os.system ['touch {marker}']\n")
    with pytest.raises(ConfigError, match=r"!!python/object/apply:os\.system at line 1"):
        load_hand(evil)
    assert not marker.exists()


def test_check_cli_accepts_default_hand() -> None:
    result = handctl("check", "config/hands/hiroshima_hand.yaml")
    assert result.returncode == 0, result.stderr
    assert "total 39.1 %" in result.stdout
    assert result.stdout.rstrip().endswith("ok")


def test_check_and_layout_take_the_hand_as_every_command_does(tmp_path: Path) -> None:
    """The README: every command takes another hand with ``--hand HAND.yaml``. ``check`` and
    ``layout`` took it only as their argument, and ``check --hand X.yaml`` was refused as an
    unrecognised option (found by an outside audit). Both spellings now, one hand at a time."""
    planar = "config/hands/planar_2f2j.yaml"
    as_argument = handctl("check", planar)
    as_option = handctl("check", "--hand", planar)
    assert as_option.returncode == 0, as_option.stderr
    assert as_option.stdout == as_argument.stdout
    two = handctl("check", planar, "--hand", "config/hands/hiroshima_hand.yaml")
    assert two.returncode == 2
    assert "--hand: expected one hand config, as HAND.yaml or as --hand" in two.stderr
    out = tmp_path / "layout.json"
    done = handctl("layout", "--hand", planar, "-o", str(out))
    assert done.returncode == 0, done.stderr
    assert "the Foxglove layout of planar_2f2j" in done.stdout
    # a file missing is said of what the user gave: --hand, not the argument it did not give
    missing = handctl("check", "--hand", str(tmp_path / "none.yaml"))
    assert missing.returncode == 2
    assert missing.stderr.startswith("handctl: error: --hand: expected an existing hand config")


def test_check_warns_of_a_rate_limit_that_starves_the_guard(
    tmp_path: Path, base: dict[str, Any], capsys: pytest.CaptureFixture[str]
) -> None:
    """At 0.1 N·m/s the guard's push-back reached 7 % of what it asked before the joint met
    its limit (an outside audit): valid, and said."""
    from handctl import cli

    joint_of(base, 0, 1).update(rate_limit=0.1)
    path = write(tmp_path, base)
    assert cli.main(["check", str(path)]) == cli.EXIT_OK
    err = capsys.readouterr().err
    name = joint_of(base, 0, 1)["name"]
    assert f"handctl: warning: {path}: {name}.rate_limit 0.1 N·m/s takes " in err
    assert err.count("handctl: warning:") == 1
    assert cli.main(["check", "config/hands/hiroshima_hand.yaml"]) == cli.EXIT_OK
    assert "warning" not in capsys.readouterr().err


def test_check_warns_of_a_scene_no_run_of_the_experiment_can_do(
    tmp_path: Path, base: dict[str, Any], capsys: pytest.CaptureFixture[str]
) -> None:
    """A joint whose range holds no two of the guard's narrowest bands, and an object with
    less room under the palm than the lift the experiment counts, passed check with "ok":
    every recipe with a guard was then refused, every run on the scene failed, each found
    out one run at a time. The config is sound (bring-up and a guardless recipe run): said."""
    from handctl import cli

    joint = joint_of(base, 0, 2)
    start = base["sim"]["initial_angles"][base["fingers"][0]["name"]][2]
    joint.update(angle_min=start - 0.015, angle_max=start + 0.015)
    # one cylinder resting on the table, its top 8 mm under the palm (one put up there, with
    # nothing under it, is refused: it falls at the first step)
    table = base["sim"]["table"]["height"]
    radius = (-0.008 - table) / 2
    base["sim"]["objects"] = [{**base["sim"]["objects"][0], "radius": radius, "x": 0.0}]
    base["sim"]["objects"][0]["y"] = table + radius
    path = write(tmp_path, base)
    assert cli.main(["check", str(path)]) == cli.EXIT_OK
    err = capsys.readouterr().err
    name, obj = joint["name"], base["sim"]["objects"][0]["name"]
    assert f"handctl: warning: {path}: {name}'s range of 0.03 rad holds no two " in err
    assert "every recipe with a limit_guard_band is refused on this hand" in err
    assert f"handctl: warning: {path}: sim.objects: {obj} can rise 8.0 mm before it " in err
    # and a range that narrow is left at once by the finger hanging idle (test_check_idle)
    assert f"with no torque on the simulated hand, {name} goes from its initial" in err
    assert err.count("handctl: warning:") == 3


def test_check_cli_bad_config_exits_2_with_the_message(
    tmp_path: Path, base: dict[str, Any]
) -> None:
    del base["fingers"][0]["joints"][0]["tau_max"]
    path = write(tmp_path, base)
    result = handctl("check", str(path))
    assert result.returncode == 2
    assert f"{path}: fingers[0].joints[0].tau_max: expected" in result.stderr
    assert "Traceback" not in result.stderr


def test_check_cli_refuses_classic_can_and_says_what_fits() -> None:
    result = handctl("check", "config/hands/hiroshima_hand_classic.yaml")
    assert result.returncode == 2
    assert (
        "hiroshima_hand_classic.yaml: bus.fd: expected true (CAN-FD): Feedback_1 (16 bytes)"
        in result.stderr
    )
    assert "Status_3 (12 bytes) are longer than the 8 bytes of a classic CAN frame" in (
        result.stderr
    )
    assert "(CAN-FD 1/5 Mbit/s would carry 39.1 %), found 122.6 % at 1000 Hz" in result.stderr


#: Every command that takes a hand config, HAND standing for it and DIR for a directory of
#: the test's own. The files in DIR are not there (a template, a recording) and are read
#: only after the hand, so a refusal of the hand is the only way for the command to end on
#: the hand's message.
COMMANDS_TAKING_A_HAND = [
    ["nodes", "--seconds", "0.2", "--hand", "HAND"],
    ["jog", "f1_j1", "--torque", "0.01", "--seconds", "0.2", "--hand", "HAND"],
    ["calibrate", "tdt", "-o", "DIR/out.yaml", "--seconds", "0.2", "--hand", "HAND"],
    ["monitor", "--seconds", "0.2", "--hand", "HAND"],
    ["monitor", "--log", "DIR/absent.mcap", "--hand", "HAND"],
    ["sim", "--bus", "virtual:refused", "--seconds", "0.2", "--hand", "HAND"],
    ["plan", "DIR/absent.template.yaml", "-o", "DIR/out.yaml", "--hand", "HAND"],
    ["replay", "DIR/absent.mcap", "--to-bus", "virtual:refused", "--hand", "HAND"],
    ["check", "HAND", "--timing", "--seconds", "0.01"],
]


def argv_for(command: list[str], hand: str, directory: Path) -> list[str]:
    return [hand if arg == "HAND" else arg.replace("DIR", str(directory)) for arg in command]


@pytest.mark.parametrize(
    "command", COMMANDS_TAKING_A_HAND, ids=lambda command: "-".join(command[:2])
)
def test_every_command_taking_a_hand_refuses_what_check_refuses(
    tmp_path: Path, command: list[str], capsys: pytest.CaptureFixture[str]
) -> None:
    """One config, one verdict: a classic-CAN hand that check refuses was jogged, calibrated
    and listed as fine on the simulated hand, which carries any frame; ``handctl sim`` put
    its 16-byte frames on the bus, and ``plan`` planned for it."""
    from handctl import cli

    classic = str(ROOT / "config" / "hands" / "hiroshima_hand_classic.yaml")
    assert cli.main(argv_for(command, classic, tmp_path)) == cli.EXIT_BAD_INPUT
    assert f"{classic}: bus.fd: expected true (CAN-FD)" in capsys.readouterr().err


@pytest.mark.parametrize(
    ("change", "message"),
    [
        (
            lambda d: d["bus"].update(interface="  "),
            "bus.interface: expected a python-can interface",
        ),
        (
            lambda d: d["sim"]["tdt"].update(noise=-1.0),
            "sim.tdt.noise: expected a number >= 0 and <= 1 N·m",
        ),
    ],
    ids=["interface", "sim"],
)
@pytest.mark.parametrize(
    "command", COMMANDS_TAKING_A_HAND, ids=lambda command: "-".join(command[:2])
)
def test_every_command_taking_a_hand_refuses_a_section_check_refuses(
    tmp_path: Path,
    base: dict[str, Any],
    command: list[str],
    change: Any,
    message: str,
    capsys: pytest.CaptureFixture[str],
) -> None:
    """check refuses a ``bus.interface`` python-can does not know and a mistake in the
    ``sim:`` section; a run, ``sim`` and ``plan`` on the simulated hand went ahead with the
    interface (it is only opened for ``--bus hand``), a timing check and a replay onto a
    bus with either, so the same file was good or bad by the command."""
    from handctl import cli

    change(base)
    path = str(write(tmp_path, base))
    assert cli.main(argv_for(command, path, tmp_path)) == cli.EXIT_BAD_INPUT
    assert f"{path}: {message}" in capsys.readouterr().err


def _classic(data: dict[str, Any]) -> None:
    data["bus"]["fd"] = False
    del data["bus"]["data_bitrate"]
    data["bus"]["loop_rate_hz"] = 250  # the slowest loop, with one miss before the watchdog
    data.setdefault("safety", {})["max_consecutive_misses"] = 1


@pytest.mark.parametrize(
    ("change", "key", "found"),
    [
        (lambda d: d["bus"].update(loop_rate_hz=10_000), "bus", "191.9 % at 10000 Hz"),
        (_classic, "bus.fd", "found false"),
    ],
)
def test_run_refuses_a_hand_check_refuses_before_anything_is_sent(
    tmp_path: Path, base: dict[str, Any], change: Any, key: str, found: str
) -> None:
    """A hand whose bus cannot carry it loaded for a run: at 10 kHz the run started and
    stopped at tick 10 (RX_BACKLOG, exit 3). It is bad input, as ``handctl check`` says."""
    change(base)
    path = write(tmp_path, base)
    recipe = tmp_path / "recipe.yaml"
    recipe.write_text(
        "recipe: r\nphases:\n  - {name: rest, torques: " + str([0.0] * 9) + ", max_s: 1}\n"
    )
    result = handctl("run", "recipe", str(recipe), "--hand", str(path), "--max-seconds", "0.2")
    assert result.returncode == 2, result.stderr
    assert f"{path}: {key}: expected" in result.stderr
    assert found in result.stderr
    assert "Traceback" not in result.stderr
    assert "ticks" not in result.stdout


# -- limits against the wire (handctl/wirelimits.py) ---------------------------------------------
def signal(protocol: Protocol, message: str, index: int) -> SignalSpec:
    return protocol.by_name[message].signals[index]


def joint_of(data: dict[str, Any], finger: int, joint: int) -> dict[str, Any]:
    found: dict[str, Any] = data["fingers"][finger]["joints"][joint]
    return found


@pytest.mark.parametrize(("finger", "joint"), [(f, j) for f in range(3) for j in range(3)])
def test_tau_max_the_command_signal_cannot_carry_is_refused(
    tmp_path: Path, base: dict[str, Any], protocol: Protocol, finger: int, joint: int
) -> None:
    """The issue's tau_max: 5 on a wire of ±3.2767 N·m; every joint maps to its own signal."""
    node = base["fingers"][finger]["node_id"]
    carried = signal(protocol, f"TorqueCommand_{node}", joint)
    lo, hi = carried.carried_range()
    joint_of(base, finger, joint).update(tau_max=5.0, device_tau_max=5.0)
    err = error_for(tmp_path, base)
    assert err.key == f"fingers[{finger}].joints[{joint}].tau_max"
    assert err.found == 5.0
    assert f"TorqueCommand_{node}.{carried.name} carries ({lo:g}..{hi:g} N·m)" in err.expected
    assert "(-5..5 N·m)" in err.expected


def test_the_largest_torque_the_wire_carries_is_accepted(
    tmp_path: Path, base: dict[str, Any], protocol: Protocol
) -> None:
    lo, hi = signal(protocol, "TorqueCommand_1", 0).carried_range()
    limit = min(-lo, hi)
    joint_of(base, 0, 0).update(tau_max=limit, device_tau_max=limit)
    hand = load_hand(write(tmp_path, base))
    assert hand.joints[0].tau_max == limit


@pytest.mark.parametrize("limit", [5e-5, 1e-300])
def test_tau_max_below_the_command_signal_s_resolution_is_refused(
    tmp_path: Path, base: dict[str, Any], protocol: Protocol, limit: float
) -> None:
    """Under one step of the wire every torque the supervisor may apply goes out as zero:
    check took the joint, and it could never be driven (a jog of the same torque is
    refused)."""
    carried = signal(protocol, "TorqueCommand_1", 2)
    joint_of(base, 0, 2).update(tau_max=limit, device_tau_max=limit)
    err = error_for(tmp_path, base)
    assert err.key == "fingers[0].joints[2].tau_max"
    assert err.found == limit
    assert f"a tau_max >= {carried.scale:g} N·m, the resolution of TorqueCommand_1." in (
        err.expected
    )


def test_a_tau_max_of_one_step_of_the_wire_is_accepted(
    tmp_path: Path, base: dict[str, Any], protocol: Protocol
) -> None:
    step = signal(protocol, "TorqueCommand_1", 2).scale
    joint_of(base, 0, 2).update(tau_max=step, device_tau_max=step)
    # a joint this weak needs a TDT cross-check as fine (``_check_tdt_tolerance``)
    base.setdefault("safety", {})["tdt_tolerance"] = step / 4
    assert load_hand(write(tmp_path, base)).joints[2].tau_max == step


def test_check_shows_a_small_tau_max_and_a_long_name_as_they_are(
    tmp_path: Path, base: dict[str, Any], capsys: pytest.CaptureFixture[str]
) -> None:
    """Torques were printed to 0.001 N·m (a tau_max of 0.0004 read 0.000, bring-up step 1
    could not be done) and a name longer than 8 characters pushed its row out of the header's
    columns (found by an outside audit)."""
    from handctl import cli

    base.pop("sim", None)
    joint_of(base, 0, 2).update(tau_max=0.0004, device_tau_max=0.0004, name="distal_of_finger_one")
    base.setdefault("safety", {})["tdt_tolerance"] = 0.0001
    assert cli.main(["check", str(write(tmp_path, base))]) == cli.EXIT_OK
    lines = capsys.readouterr().out.splitlines()
    header = next(line for line in lines if line.startswith("joint "))
    row = next(line for line in lines if line.startswith("distal_of_finger_one "))
    assert "0.0004Nm" in row
    assert row.index("Nm") + 2 == header.index("tau_max") + len("tau_max")
    assert header.index("tau_max") > len("distal_of_finger_one")


def test_device_tau_max_the_command_signal_cannot_carry_is_refused(
    tmp_path: Path, base: dict[str, Any], protocol: Protocol
) -> None:
    _, hi = signal(protocol, "TorqueCommand_2", 1).carried_range()
    joint_of(base, 1, 1)["device_tau_max"] = hi + 0.01
    err = error_for(tmp_path, base)
    assert err.key == "fingers[1].joints[1].device_tau_max"
    assert "TorqueCommand_2.Torque2" in err.expected


def test_device_tau_max_whose_tdt_reading_saturates_is_refused(
    tmp_path: Path, base: dict[str, Any], protocol: Protocol
) -> None:
    """With tdt scale 0.5 a torque reads as twice its value: the feedback signal would saturate
    below the torque the node can apply, so the host could not see it."""
    lo, hi = signal(protocol, "Feedback_3", 2).carried_range()
    joint_of(base, 2, 2).update(tdt={"scale": 0.5, "offset": 0.0}, device_tau_max=hi * 0.75)
    err = error_for(tmp_path, base)
    assert err.key == "fingers[2].joints[2].device_tau_max"
    assert f"Feedback_3.Torque3 carries ({lo:g}..{hi:g} N·m)" in err.expected
    assert "tdt scale 0.5" in err.expected
    joint_of(base, 2, 2)["device_tau_max"] = hi * 0.4  # reads 0.8 * hi: carried
    load_hand(write(tmp_path, base))


def test_a_tdt_offset_moves_the_reading_out_of_the_signal(
    tmp_path: Path, base: dict[str, Any], protocol: Protocol
) -> None:
    _, hi = signal(protocol, "Feedback_1", 0).carried_range()
    joint_of(base, 0, 0).update(
        tau_max=0.5, device_tau_max=hi - 0.1, tdt={"scale": 1.0, "offset": -0.2}
    )
    err = error_for(tmp_path, base)
    assert err.key == "fingers[0].joints[0].device_tau_max"
    assert "Feedback_1.Torque1" in err.expected


@pytest.mark.parametrize(("key", "side"), [("angle_max", 1), ("angle_min", 0)])
def test_an_angle_limit_the_feedback_signal_cannot_show_crossed_is_refused(
    tmp_path: Path, base: dict[str, Any], protocol: Protocol, key: str, side: int
) -> None:
    """A limit at the signal's end is never seen crossed: the reading saturates on it."""
    carried = signal(protocol, "Feedback_2", 3 + 2)  # Angle3 of node 2
    end = carried.carried_range()[side]
    joint_of(base, 1, 2)[key] = end
    err = error_for(tmp_path, base)
    assert err.key == f"fingers[1].joints[2].{key}"
    assert err.found == end
    lo, hi = carried.carried_range()
    assert f"Feedback_2.Angle3 carries ({lo:g}..{hi:g} rad)" in err.expected
    inside = end - carried.scale if side else end + carried.scale
    joint_of(base, 1, 2)[key] = inside
    assert getattr(load_hand(write(tmp_path, base)).fingers[1].joints[2], key) == inside


def angle_factor_dbc(tmp_path: Path, factor: float) -> Path:
    """The packaged DBC with every feedback angle in steps of ``factor`` rad (16 bits)."""
    text = DEFAULT_DBC.read_text(encoding="cp1252")
    old = '(0.0001,0) [-3.2768|3.2767] "rad"'
    assert text.count(old) == 9
    path = tmp_path / "angles.dbc"
    new = f'({factor:g},0) [{-32768 * factor:.6f}|{32767 * factor:.6f}] "rad"'
    path.write_text(text.replace(old, new), encoding="cp1252")
    return path


@pytest.mark.parametrize(("factor", "ok"), [(1.0, False), (0.0025, False), (0.002, True)])
def test_an_angle_signal_too_coarse_to_show_a_joint_past_its_limit_is_refused(
    tmp_path: Path, factor: float, ok: bool
) -> None:
    """At 1 rad a step check said ok, and a run logged f1_j3 at 2.0 rad while it was past its
    2.3 rad soft limit: no ANGLE_LIMIT came (found by an outside audit)."""
    path = angle_factor_dbc(tmp_path, factor)
    if ok:
        assert load_hand(HAND_YAML, path).fingers[0].joints[0].angle_max == 1.9
        return
    with pytest.raises(ConfigError) as info:
        load_hand(HAND_YAML, path)
    assert info.value.file == str(path) and info.value.key == "Feedback_1.Angle1"
    assert "a factor of at most 0.002 rad (f1_j1's angle)" in info.value.expected
    assert str(info.value).endswith(f"found factor {factor:g}")
    result = handctl("check", str(HAND_YAML), "--dbc", str(path))
    assert result.returncode == 2 and "Traceback" not in result.stderr
    assert f"{path}: Feedback_1.Angle1: expected a factor of at most 0.002 rad" in result.stderr


def test_the_coarsest_angle_reading_resolves_the_guard_s_narrowest_band() -> None:
    """The bound's reason (``MAX_ANGLE_RESOLUTION_RAD``), held to the numbers it is made of."""
    from handctl.online.recipes.loader import GUARD_BAND_MIN
    from handctl.sim.params import START_MARGIN
    from handctl.wirelimits import MAX_ANGLE_RESOLUTION_RAD

    assert MAX_ANGLE_RESOLUTION_RAD <= GUARD_BAND_MIN / 10
    assert MAX_ANGLE_RESOLUTION_RAD / 2 <= START_MARGIN / 10


@pytest.mark.parametrize(
    ("loop_rate_hz", "rate_limit", "ok"),
    [
        (1000, 0.1, True),  # one 0.0001 N·m step per tick: the resolution
        (1000, 0.05, False),  # half a step per tick
        (500, 0.05, True),  # the same rate at half the loop rate is one step per tick
        (1000, 6553.5, True),  # the whole span in one tick
        (1000, 7000.0, False),  # more than the span: limits nothing the wire can express
    ],
)
def test_a_rate_limit_must_be_a_step_the_command_signal_can_carry(
    tmp_path: Path,
    base: dict[str, Any],
    protocol: Protocol,
    loop_rate_hz: float,
    rate_limit: float,
    ok: bool,
) -> None:
    carried = signal(protocol, "TorqueCommand_1", 0)
    lo, hi = carried.carried_range()
    assert carried.scale == pytest.approx(1e-4) and hi - lo == pytest.approx(6.5535)
    base["bus"]["loop_rate_hz"] = loop_rate_hz
    joint_of(base, 0, 0)["rate_limit"] = rate_limit
    if ok:
        assert load_hand(write(tmp_path, base)).joints[0].rate_limit == rate_limit
        return
    err = error_for(tmp_path, base)
    assert err.key == "fingers[0].joints[0].rate_limit"
    assert "TorqueCommand_1.Torque1" in err.expected
    assert f"bus.loop_rate_hz {loop_rate_hz:g} Hz" in err.expected


@settings(
    max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(st.floats(0.001, 100.0))
def test_a_limit_loads_exactly_when_the_wire_carries_it(
    tmp_path: Path, base: dict[str, Any], protocol: Protocol, limit: float
) -> None:
    _, hi = signal(protocol, "TorqueCommand_3", 0).carried_range()
    data = copy.deepcopy(base)
    joint_of(data, 2, 0).update(tau_max=limit, device_tau_max=limit)
    data.setdefault("safety", {})["tdt_tolerance"] = min(limit, 0.02) / 4
    path = write(tmp_path, data)
    if limit <= hi:
        load_hand(path)
    else:
        with pytest.raises(ConfigError, match=r"TorqueCommand_3\.Torque1"):
            load_hand(path)


def narrower_dbc(tmp_path: Path) -> Path:
    """The packaged DBC with TorqueCommand_1's first torque at a tenth of the range."""
    text = DEFAULT_DBC.read_text(encoding="utf-8")
    line = ' SG_ Torque1 : 16|16@1- (0.0001,0) [-3.2768|3.2767] "N.m" FINGER1\n'
    assert line in text
    path = tmp_path / "narrow.dbc"
    path.write_text(
        text.replace(
            line, line.replace("(0.0001,0) [-3.2768|3.2767]", "(0.00001,0) [-0.32768|0.32767]")
        )
    )
    return path


def test_a_command_signal_that_cannot_carry_zero_torque_is_refused(tmp_path: Path) -> None:
    """The supervisor keeps applied torques on the command signal's grid, and a stop sends
    0 N·m: a DBC whose offset puts zero between two raw values could send neither."""
    text = DEFAULT_DBC.read_text(encoding="utf-8")
    line = ' SG_ Torque1 : 16|16@1- (0.0001,0) [-3.2768|3.2767] "N.m" FINGER1\n'
    path = tmp_path / "offset.dbc"
    path.write_text(text.replace(line, line.replace("(0.0001,0)", "(0.0001,0.00005)")))
    with pytest.raises(ConfigError, match="carry 0 N·m exactly") as info:
        load_hand(HAND_YAML, path)
    assert info.value.key == "TorqueCommand_1.Torque1"
    assert "offset.dbc" in str(info.value) and "offset 5e-05" in str(info.value)


def test_the_wire_ranges_come_from_the_dbc(tmp_path: Path) -> None:
    with pytest.raises(
        ConfigError,
        match=r"TorqueCommand_1\.Torque1 carries "
        r"\(-0\.32768\.\.0\.32767 N·m\)",
    ) as info:
        load_hand(HAND_YAML, narrower_dbc(tmp_path))
    assert info.value.key == "fingers[0].joints[0].tau_max"
    assert load_hand(HAND_YAML).joints[0].tau_max == 0.6


def test_check_cli_refuses_a_limit_the_wire_cannot_carry(
    tmp_path: Path, base: dict[str, Any]
) -> None:
    joint_of(base, 0, 0).update(tau_max=5.0, device_tau_max=5.0)
    path = write(tmp_path, base)
    result = handctl("check", str(path))
    assert result.returncode == 2
    assert (
        f"{path}: fingers[0].joints[0].tau_max: expected ±tau_max (-5..5 N·m) within what "
        "TorqueCommand_1.Torque1 carries (-3.2768..3.2767 N·m), found 5.0"
    ) in result.stderr
    assert "Traceback" not in result.stderr
    narrow = handctl(
        "check", "config/hands/hiroshima_hand.yaml", "--dbc", str(narrower_dbc(tmp_path))
    )
    assert narrow.returncode == 2
    assert "TorqueCommand_1.Torque1 carries (-0.32768..0.32767 N·m)" in narrow.stderr


@pytest.mark.parametrize(
    ("rate", "misses", "key", "expected"),
    [
        (220.0, 1, "bus.loop_rate_hz", "at least 250 Hz"),
        (100.0, 1, "bus.loop_rate_hz", "at least 250 Hz"),
        # no number: the bound it is told is the one that holds (it said >= 200)
        ("1kHz", 1, "bus.loop_rate_hz", "expected a number >= 250 and <= 10000 Hz"),
        (400.0, 3, "safety.max_consecutive_misses", "at most 2 at a 400 Hz loop"),
        (1000.0, 8, "safety.max_consecutive_misses", "at most 7 at a 1000 Hz loop"),
    ],
)
def test_the_host_stops_on_missed_ticks_before_the_nodes_watchdog(
    tmp_path: Path, rate: float | str, misses: int, key: str, expected: str
) -> None:
    """A 200 Hz hand passed check, and its runs ended on the nodes' latched TIMEOUT with no
    missed tick counted: the host's overrun stop must come first, with room for the bus."""
    doc = yaml.safe_load(HAND_YAML.read_text(encoding="utf-8"))
    doc["bus"]["loop_rate_hz"] = rate
    doc.setdefault("safety", {})["max_consecutive_misses"] = misses
    path = tmp_path / "hand.yaml"
    path.write_text(yaml.safe_dump(doc), encoding="utf-8")
    with pytest.raises(ConfigError) as info:
        load_hand(path)
    assert info.value.key == key and expected in str(info.value)
    # one fewer miss (or the slowest rate allowed) loads
    if key == "bus.loop_rate_hz":
        doc["bus"]["loop_rate_hz"] = 250.0
    else:
        doc["safety"]["max_consecutive_misses"] = misses - 1
    path.write_text(yaml.safe_dump(doc), encoding="utf-8")
    assert load_hand(path).safety.max_consecutive_misses == doc["safety"]["max_consecutive_misses"]


@pytest.mark.parametrize(("rate", "default"), [(250.0, 1), (400.0, 2), (499.0, 2), (1000.0, 3)])
def test_the_default_stop_on_missed_ticks_fits_the_loop_rate(
    tmp_path: Path, rate: float, default: int
) -> None:
    """A 250-499 Hz hand without max_consecutive_misses was refused for the default 3 it never
    wrote; the default is now the most its rate allows, up to 3."""
    doc = yaml.safe_load(HAND_YAML.read_text(encoding="utf-8"))
    doc["bus"]["loop_rate_hz"] = rate
    doc.get("safety", {}).pop("max_consecutive_misses", None)
    path = tmp_path / "hand.yaml"
    path.write_text(yaml.safe_dump(doc), encoding="utf-8")
    assert load_hand(path).safety.max_consecutive_misses == default


@pytest.mark.parametrize(("rate", "failures", "most"), [(1000.0, 8, 7), (400.0, 3, 2)])
def test_the_host_stops_on_commands_that_did_not_go_before_the_nodes_watchdog(
    tmp_path: Path, rate: float, failures: int, most: int
) -> None:
    """100 consecutive ticks of command frames that did not go were accepted: the nodes
    latched TIMEOUT (a fault the next run must reset) and the host never said BUS_ERROR.
    Held to the watchdog as missed ticks are, and its default to the loop rate likewise."""
    doc = yaml.safe_load(HAND_YAML.read_text(encoding="utf-8"))
    doc["bus"]["loop_rate_hz"] = rate
    doc.setdefault("safety", {})["max_consecutive_misses"] = 1
    doc["safety"]["max_consecutive_send_failures"] = failures
    path = tmp_path / "hand.yaml"
    path.write_text(yaml.safe_dump(doc), encoding="utf-8")
    with pytest.raises(ConfigError) as info:
        load_hand(path)
    assert info.value.key == "safety.max_consecutive_send_failures"
    assert f"at most {most} at a {rate:g} Hz loop" in str(info.value)
    doc["safety"]["max_consecutive_send_failures"] = most
    path.write_text(yaml.safe_dump(doc), encoding="utf-8")
    assert load_hand(path).safety.max_consecutive_send_failures == most
    doc["safety"].pop("max_consecutive_send_failures")
    path.write_text(yaml.safe_dump(doc), encoding="utf-8")
    assert load_hand(path).safety.max_consecutive_send_failures == min(3, most)


def test_a_key_that_is_no_string_is_refused_before_anything_is_hashed(tmp_path: Path) -> None:
    """The hash of the config as written was taken before the reading refused a key that is
    no string, and its sort raised a TypeError (the loader fuzz found it)."""
    text = HAND_YAML.read_text()
    assert "\n  fd: true" in text
    path = tmp_path / "int_key.yaml"
    path.write_text(text.replace("\n  fd: true", "\n  7: 8\n  fd: true", 1))
    with pytest.raises(ConfigError) as caught:
        load_hand(path)
    assert "bus: expected string keys, found 7" in str(caught.value)


@pytest.mark.parametrize("written", [None, 0.01])
def test_a_tdt_tolerance_of_half_a_joint_s_torque_is_refused(
    tmp_path: Path, base: dict[str, Any], written: float | None
) -> None:
    """A hand of weak joints with the default tolerance (0.02 N·m, for joints of tenths of
    a N·m): a TDT reading twenty times the drive's most was within it, and no fault."""
    joint_of(base, 1, 1).update(tau_max=0.02, device_tau_max=0.02)
    if written is not None:
        base.setdefault("safety", {})["tdt_tolerance"] = written
    err = error_for(tmp_path, base)
    assert err.key == "safety.tdt_tolerance"
    name = base["fingers"][1]["joints"][1]["name"]
    assert f"({name}: 0.02 N·m, so below 0.01 N·m)" in err.expected
    assert str(err.found) == ("0.01 N·m" if written else "0.02 N·m (the default)")
    base["safety"] = {**base.get("safety", {}), "tdt_tolerance": 0.0099}
    assert load_hand(write(tmp_path, base)).safety.tdt_tolerance == 0.0099


@pytest.mark.parametrize(
    ("key", "refused", "accepted", "expected"),
    [
        # 1.5 of the expected torque: a slack tendon (TDT reading 0) was never a mismatch
        ("tdt_tolerance_rel", 0.51, 0.5, "at most 0.5 (of the expected torque)"),
        # a command cannot move twice the weakest tau_max (0.3 N·m): the check never fires
        ("tdt_stuck_min_change", 0.6, 0.59, "so below 0.6 N·m"),
        # a thousand ticks of torque commanded without hearing the joint
        ("feedback_timeout_s", 0.101, 0.1, "at most 0.1 s"),
        # 100 ticks in the default 0.1 s window: 100 rejects let every frame be rejected
        ("max_rejects_in_window", 100, 99, "fewer than the 100 ticks of reject_window_s"),
        # a slack tendon ran nine seconds unseen with a window of 10 s
        ("tdt_window_s", 0.51, 0.5, "at most 0.5 s: longer, the watchdog sees a fault"),
        ("tdt_stuck_window_s", 0.51, 0.5, "at most 0.5 s"),
        ("heartbeat_timeout_s", 1.01, 1.0, "at most 1 s"),
        # and the other way, a setting that stops every run of a hand that works: the nodes
        # send Feedback every 1 ms, and a frame 1.8 ms old stopped a run on a host with no
        # late tick
        ("feedback_timeout_s", 0.0029, 0.003, ">= 0.003"),
        # a live sensor stays on one step a few samples by chance: every run stopped at tick 3
        ("tdt_stuck_still_s", 0.001, 0.1, "0 (off) or at least 0.1 s"),
        ("tdt_stuck_still_s", 0.099, 0.0, "0 (off) or at least 0.1 s"),
    ],
)
def test_a_safety_setting_that_turns_its_own_check_off_is_refused(
    tmp_path: Path,
    base: dict[str, Any],
    key: str,
    refused: float,
    accepted: float,
    expected: str,
) -> None:
    """Each was accepted up to a bound far past where its check can still fire, or where it
    stops every run (found by outside audits): the hand passed ``check`` and its watchdog was
    off, or every run stopped."""
    base["safety"] = {**base.get("safety", {}), key: refused}
    err = error_for(tmp_path, base)
    assert err.key == f"safety.{key}"
    assert expected in err.expected, err.expected
    base["safety"][key] = accepted
    assert getattr(load_hand(write(tmp_path, base)).safety, key) == accepted


def test_a_name_longer_than_a_column_is_refused(tmp_path: Path, base: dict[str, Any]) -> None:
    """A 300-character joint name passed check, ran off the top of the run's plot and broke
    every table's columns: names are at most 32 characters."""
    joint_of(base, 0, 0)["name"] = "j" * 32
    assert load_hand(write(tmp_path, base)).joints[0].name == "j" * 32
    joint_of(base, 0, 0)["name"] = "j" * 33
    err = error_for(tmp_path, base)
    assert err.key == "fingers[0].joints[0].name"
    assert "at most 32 characters" in err.expected
