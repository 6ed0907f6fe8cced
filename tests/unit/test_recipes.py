"""Recipes: strict loading, limits checked against the hand before anything is sent, and the
runner's ramps, exits, time limits and aborts."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml

from handctl.config import HandConfig, load_hand
from handctl.errors import ConfigError
from handctl.online.recipes.loader import load_recipe
from handctl.online.recipes.runner import RecipeRunner, RunStatus
from handctl.online.recipes.schema import RecipeObject, estimate_names

from ..conftest import ROOT

ZERO = np.zeros(9)


def phase(name: str, value: float = 0.1, **extra: Any) -> dict[str, Any]:
    joints = ["f1_j1", "f1_j2", "f1_j3", "f2_j1", "f2_j2", "f2_j3", "f3_j1", "f3_j2", "f3_j3"]
    return {
        "name": name,
        "torques": dict.fromkeys(joints, value),
        "ramp_s": 0.1,
        "max_s": 1.0,
        **extra,
    }


def write(tmp_path: Path, data: dict[str, Any]) -> Path:
    path = tmp_path / "recipe.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def recipe_doc(*phases: dict[str, Any], **top: Any) -> dict[str, Any]:
    return {"recipe": "test", "phases": list(phases), **top}


def error(tmp_path: Path, hand: HandConfig, data: dict[str, Any]) -> ConfigError:
    path = write(tmp_path, data)
    with pytest.raises(ConfigError) as info:
        load_recipe(path, hand)
    assert str(path) in str(info.value)
    return info.value


def test_torque_over_tau_max_is_refused_naming_phase_joint_value_limit(
    tmp_path: Path, hand: HandConfig
) -> None:
    bad = phase("squeeze", 0.1)
    bad["torques"]["f1_j3"] = 0.35
    err = error(tmp_path, hand, recipe_doc(phase("a"), bad))
    assert err.key == "phases[1].torques.f1_j3"
    assert "0.3 N·m" in err.expected and "squeeze" in err.expected
    assert err.found == 0.35


def test_a_ramp_faster_than_the_rate_limit_is_refused(tmp_path: Path, hand: HandConfig) -> None:
    fast = phase("jump", -0.25, ramp_s=0.01)
    err = error(tmp_path, hand, recipe_doc(phase("a", 0.2), fast))
    assert err.key == "phases[1].ramp_s"
    assert "20 N·m/s" in err.expected and "0.45 N·m" in err.expected
    assert err.found == 0.01


def test_the_first_ramp_from_zero_and_the_end_ramp_are_checked(
    tmp_path: Path, hand: HandConfig
) -> None:
    err = error(tmp_path, hand, recipe_doc(phase("a", 0.2, ramp_s=0.0)))
    assert err.key == "phases[0].ramp_s"
    err = error(tmp_path, hand, recipe_doc(phase("a", 0.2), end_ramp_s=0.001))
    assert err.key == "end_ramp_s"


def test_compiled_recipe_for_another_hand_is_refused(tmp_path: Path, hand: HandConfig) -> None:
    err = error(
        tmp_path,
        hand,
        recipe_doc(phase("a"), compiled=True, hand_config_hash="sha256:0000000000000000"),
    )
    assert err.key == "hand_config_hash"
    assert hand.config_hash in err.expected
    err = error(tmp_path, hand, recipe_doc(phase("a"), compiled=True))
    assert err.key == "hand_config_hash"
    ok = write(tmp_path, recipe_doc(phase("a"), compiled=True, hand_config_hash=hand.config_hash))
    assert load_recipe(ok, hand).compiled


@pytest.mark.parametrize(
    ("condition", "expected"),
    [
        ("angle.f9_j1 > 1", "a joint of the hand"),
        ("speed > 1", "a condition 'SIGNAL OP NUMBER"),
        ("time = 1", "a condition"),
        ("estimate.colour > 1", "an estimate of the recipe's objects"),
        # digits the pattern admits but a float cannot hold: always or never crossed
        ("angle.f1_j1 < 1e999", "NUMBER is finite (it reads as inf)"),
        ("angle.f1_j1 > -1e999 for 0.1", "NUMBER is finite (it reads as -inf)"),
        ("time > 1 for " + "9" * 400, "held for at most 3600 s"),
        ("time > 1 for 3600.5", "held for at most 3600 s"),
        # a hold in exponent notation, as a threshold may be written: read, and bounded (it
        # was refused as no condition at all, saying nothing of why)
        ("time > 1 for 1e20", "held for at most 3600 s"),
        ("time > 1 for -2e-2", "a condition 'SIGNAL OP NUMBER [for SECONDS]'"),
        # a line break was taken and printed in the summary, a stray line after the
        # condition's; any script's digits were read as the number: ASCII digits and spaces
        # only (found by an outside audit)
        ("time > 0.4\n", "a condition 'SIGNAL OP NUMBER"),
        ("time > 0.4\r", "a condition 'SIGNAL OP NUMBER"),
        ("time\u00a0> 0.4", "a condition 'SIGNAL OP NUMBER"),
        ("time >\x0b0.4", "a condition 'SIGNAL OP NUMBER"),
        ("time > \u0660.\u0664", "a condition 'SIGNAL OP NUMBER"),
        ("time > 0.4 for \uff11", "a condition 'SIGNAL OP NUMBER"),
    ],
)
def test_bad_conditions(tmp_path: Path, hand: HandConfig, condition: str, expected: str) -> None:
    err = error(tmp_path, hand, recipe_doc(phase("a", exit=["time > 0.5", condition])))
    assert err.key == "phases[0].exit[1]"
    assert expected in err.expected


def test_a_hold_in_exponent_notation_is_read(tmp_path: Path, hand: HandConfig) -> None:
    recipe = load_recipe(
        write(tmp_path, recipe_doc(phase("a", exit=["time > 0.5 for 2e-2"]))), hand
    )
    assert recipe.phases[0].exits[0].hold_s == 0.02


def test_unknown_keys_missing_joints_and_duplicates(tmp_path: Path, hand: HandConfig) -> None:
    assert error(tmp_path, hand, recipe_doc(phase("a", ramp=0.1))).key == "phases[0].ramp"
    short = phase("a")
    del short["torques"]["f2_j2"]
    assert error(tmp_path, hand, recipe_doc(short)).key == "phases[0].torques.f2_j2"
    assert error(tmp_path, hand, recipe_doc(phase("a"), phase("a"))).key == "phases[1].name"
    no_limit = phase("a")
    del no_limit["max_s"]
    assert error(tmp_path, hand, recipe_doc(no_limit)).key == "phases[0].max_s"


def test_torques_as_a_list(tmp_path: Path, hand: HandConfig) -> None:
    p = phase("a")
    p["torques"] = [0.1] * 9
    assert load_recipe(write(tmp_path, recipe_doc(p)), hand).phases[0].torques == (0.1,) * 9
    p["torques"] = [0.1] * 8
    refused = error(tmp_path, hand, recipe_doc(p))
    assert refused.key == "phases[0].torques"
    assert "expected a list of 9 numbers, found a list of 8: [0.1, 0.1," in str(refused)


def run(
    runner: RecipeRunner,
    t_end: float,
    dt: float = 0.001,
    angle: np.ndarray = ZERO,
    est: list[float] | None = None,
) -> list[np.ndarray]:
    out = []
    t = 0.0
    while t < t_end and not runner.done:
        out.append(runner.step(t, angle, ZERO, est).copy())
        t = round(t + dt, 9)
    return out


def test_runner_ramps_exits_and_ends(tmp_path: Path, hand: HandConfig) -> None:
    data = recipe_doc(
        phase("a", 0.2, ramp_s=0.1, exit=["time >= 0.3"]),
        phase("b", -0.1, ramp_s=0.05, exit=["time >= 0.2"]),
        end_ramp_s=0.1,
    )
    recipe = load_recipe(write(tmp_path, data), hand)
    runner = RecipeRunner(recipe, 9)
    torques = run(runner, 2.0)
    assert runner.status is RunStatus.COMPLETED
    assert torques[50][0] == pytest.approx(0.1)  # halfway up the first ramp
    assert torques[200][0] == pytest.approx(0.2)
    assert torques[325][0] == pytest.approx(0.2 + (-0.3) * 0.5)  # halfway down into b
    assert [r.name for r in runner.records] == ["a", "b"]
    assert runner.records[0].exit == "time >= 0.3"
    assert runner.records[1].start_s == pytest.approx(0.3)
    assert len(torques) == pytest.approx(300 + 200 + 100, abs=2)


def test_runner_timeout_next_or_abort(tmp_path: Path, hand: HandConfig) -> None:
    data = recipe_doc(phase("a", max_s=0.2, on_timeout="next"), phase("b", max_s=0.1))
    runner = RecipeRunner(load_recipe(write(tmp_path, data), hand), 9)
    run(runner, 2.0)
    assert runner.status is RunStatus.ABORTED
    assert runner.records[0].exit == "timeout"
    assert "timeout: phase 'b'" in runner.abort_reason


def test_runner_angle_exit_must_hold(tmp_path: Path, hand: HandConfig) -> None:
    data = recipe_doc(phase("a", exit=["angle.f1_j2 > 0.5 for 0.01"]), phase("b"))
    runner = RecipeRunner(load_recipe(write(tmp_path, data), hand), 9)
    angle = np.zeros(9)
    t = 0.0
    for _ in range(100):
        runner.step(t, angle, ZERO)
        t += 0.001
    angle[1] = 0.6
    runner.step(t, angle, ZERO)
    angle[1] = 0.4  # a blip shorter than the hold time does not count
    runner.step(t + 0.001, angle, ZERO)
    angle[1] = 0.6
    for k in range(2, 30):
        runner.step(t + k * 0.001, angle, ZERO)
        if runner.phase_name == "b":
            break
    assert runner.phase_name == "b"
    assert runner.records[0].end_s == pytest.approx(t + 0.012, abs=1.5e-3)


def test_runner_abort_condition_and_estimates(tmp_path: Path, hand: HandConfig) -> None:
    data = recipe_doc(
        phase("a", exit=["estimate.cyl1_cyl2_line_angle > 0.7"], abort=["tdt.f3_j1 < -0.5"]),
        phase("b"),
        objects=[{"name": "cyl1", "radius": 0.02}, {"name": "cyl2", "radius": 0.02}],
    )
    runner = RecipeRunner(load_recipe(write(tmp_path, data), hand), 9)
    assert runner.recipe.uses_estimates
    est = [0.0] * len(
        estimate_names((RecipeObject("cyl1", 0.02), RecipeObject("cyl2", 0.02)), ((0, 1),))
    )
    run(runner, 0.1, est=est)
    assert runner.phase_name == "a"
    est[0] = 0.8
    run(runner, 0.01, est=est)
    assert runner.phase_name == "b"


def test_an_object_a_hand_config_s_scene_may_hold_a_recipe_may_name(
    tmp_path: Path, hand: HandConfig
) -> None:
    """A hand config's scene took objects of up to 1 m, a recipe only up to 0.2 m: a larger
    gripper's object could not be named, so it had no estimator and no experiment (found by
    an outside audit). One bound, ``convention.MAX_OBJECT_RADIUS``, for both."""
    from handctl.convention import MAX_OBJECT_RADIUS

    data = recipe_doc(phase("a"), objects=[{"name": "big", "radius": 0.25}])
    assert load_recipe(write(tmp_path, data), hand).objects[0].radius == 0.25
    data = recipe_doc(phase("a"), objects=[{"name": "big", "radius": MAX_OBJECT_RADIUS * 1.01}])
    with pytest.raises(ConfigError) as info:
        load_recipe(write(tmp_path, data), hand)
    assert info.value.key == "objects[0].radius"
    assert f"<= {MAX_OBJECT_RADIUS:g} m" in info.value.expected


def test_a_recipe_for_another_hand_says_so_at_its_first_joint_keyed_mapping(
    tmp_path: Path, hand: HandConfig
) -> None:
    """The swap recipe, its hash taken out, on the planar hand met its spring bands first:
    'unknown key', with no word of --hand; a per-joint damping 'did you mean left_j1?'."""
    planar = load_hand(ROOT / "config" / "hands" / "planar_2f2j.yaml")
    data = yaml.safe_load((ROOT / "config" / "recipes" / "swap_two_cylinders.yaml").read_text())
    data.pop("hand_config_hash")
    data["compiled"] = False
    for planned in data["phases"]:  # what it was planned for is said first when it is there
        planned.pop("provenance", None)
    with pytest.raises(ConfigError) as info:
        load_recipe(write(tmp_path, data), planar)
    assert info.value.key == "limit_guard_spring_bands"
    assert "written for another hand? give its config with --hand" in str(info.value)


def test_a_compiled_recipe_on_another_hand_says_it_was_compiled_for_another(
    hand: HandConfig,
) -> None:
    """On a hand whose joints are others' (the two-finger one), the recipe's hash is what is
    wrong, not the first joint it names: that said 'unknown key f2_j3, did you mean f3_j3?'
    on a two-finger hand of f1 and f3, and sent the user to rename a joint."""
    planar = load_hand(ROOT / "config" / "hands" / "planar_2f2j.yaml")
    with pytest.raises(ConfigError) as info:
        load_recipe(ROOT / "config" / "recipes" / "swap_two_cylinders.yaml", planar)
    assert info.value.key == "hand_config_hash"
    assert "compiled for another hand config" in str(info.value)
    # and how to run it as it is: on its own hand (only "recompile it" was said, which sent a
    # newcomer who forgot --hand to re-plan; found by an outside audit)
    assert "written for another hand? give its config with --hand" in str(info.value)


def test_the_torque_margin_is_held_to_tau_max_and_the_rate_limit(
    tmp_path: Path, hand: HandConfig
) -> None:
    """The runner holds the torques times the margin: the margin got around both checks, and
    the supervisor clamped what the recipe asked for."""
    over = phase("a", 0.0, torque_margin=2.0)
    over["torques"]["f1_j1"] = 0.35  # 0.7 N·m held, tau_max 0.6
    err = error(tmp_path, hand, recipe_doc(over))
    assert err.key == "phases[0].torques.f1_j1" and err.found == 0.7
    assert "torque_margin (2)" in err.expected
    fast = phase("a", 0.0, torque_margin=2.0, ramp_s=0.002)
    fast["torques"]["f1_j1"] = 0.04  # 0.08 N·m in 2 ms: 40 N·m/s, the limit 20
    assert error(tmp_path, hand, recipe_doc(fast)).key == "phases[0].ramp_s"
    fast["torques"]["f1_j1"] = 0.015  # 0.03 N·m in 2 ms: 15 N·m/s
    load_recipe(write(tmp_path, recipe_doc(fast)), hand)


@pytest.mark.parametrize("name", ["running", "end_ramp", "completed", "aborted", "-", "end_ramp "])
def test_a_phase_may_not_take_a_name_the_log_uses_for_something_else(
    tmp_path: Path, hand: HandConfig, name: str
) -> None:
    err = error(tmp_path, hand, recipe_doc(phase("a"), phase(name)))
    assert err.key == "phases[1].name" and err.found == name


def test_the_reserved_phase_names_are_what_the_log_says_where_no_phase_runs() -> None:
    from handctl.online.loop import NO_PHASE
    from handctl.online.recipes.loader import RESERVED_PHASE_NAMES

    assert {s.value for s in RunStatus} | {NO_PHASE} == RESERVED_PHASE_NAMES


@pytest.mark.parametrize(
    ("condition", "why"),
    [
        ("time >= 0 for 5", "held for 5 s from its second tick"),
        ("time > 5", "the phase times out first"),
        ("time >= 0.8 for 0.3", "the phase times out first"),
        # '>' holds a tick after its value: at the timeout's own tick it is not yet past it
        ("time > 1", "the phase times out first"),
        ("time > 0.5 for 0.5", "the phase times out first"),
        ("time < -1", "a phase's time is never below one loop period (1 ms)"),
        ("time <= 0", "a phase's time is never below one loop period"),
        ("time < 0.001", "a phase's time is never below one loop period"),
        ("angle.f1_j1 > 5", "f1_j1 past its soft limit"),
        ("angle.f1_j1 < -5", "f1_j1 past its soft limit"),
        # at the soft limit itself: '>' holds only past it
        ("angle.f1_j1 > 1.9", "f1_j1 past its soft limit 1.9 rad"),
        ("angle.f1_j1 < -1", "f1_j1 past its soft limit -1 rad"),
        # a hold starts at the phase's second tick at the earliest
        ("time >= 0 for 1", "it outlasts the phase"),
        ("angle.f1_j1 > -5 for 1", "it outlasts the phase"),
        ("tdt.f1_j1 > 1000", "never passes its device_tau_max"),
    ],
)
def test_a_condition_that_never_holds_in_its_phase_is_refused(
    tmp_path: Path, hand: HandConfig, condition: str, why: str
) -> None:
    for key in ("exit", "abort"):
        doc = recipe_doc(phase("a", max_s=1.0))
        doc["phases"][0][key] = [condition]
        err = error(tmp_path, hand, doc)
        assert err.key == f"phases[0].{key}[0]" and why in err.expected, err
    # at the edges it may hold, and loads
    load_recipe(write(tmp_path, recipe_doc(phase("a", max_s=1.0, exit=["time >= 1"]))), hand)
    for edge in ("time > 0.999", "time >= 0.5 for 0.5", "time > 0.499 for 0.5"):
        load_recipe(write(tmp_path, recipe_doc(phase("a", max_s=1.0, exit=[edge]))), hand)
    load_recipe(write(tmp_path, recipe_doc(phase("a", max_s=1.0, exit=["time <= 0.001"]))), hand)
    for at_the_limit in ("angle.f1_j1 >= 1.9", "angle.f1_j1 <= -1"):
        load_recipe(write(tmp_path, recipe_doc(phase("a", max_s=1.0, exit=[at_the_limit]))), hand)


def test_turn_from_without_a_turn_to_count_is_refused(tmp_path: Path, hand: HandConfig) -> None:
    data = recipe_doc(phase("a", max_s=0.5, on_timeout="next"), phase("b", turn_from="a"))
    err = error(tmp_path, hand, data)
    assert err.key == "phases[1].turn_from" and "reads a turn" in err.expected


def test_every_phase_is_judged_from_its_second_tick_the_first_one_too(
    tmp_path: Path, hand: HandConfig
) -> None:
    """A first phase whose exit held at once ended on the tick it began: no tick of the log
    ran it, and its holds counted one tick less than every later phase's."""
    data = recipe_doc(
        phase("a", exit=["time >= 0"]),
        phase("b", exit=["time >= 0"]),
        phase("c", exit=["time >= 0 for 0.005"]),
        phase("d", exit=["time >= 0 for 0.005"]),
        phase("e"),
    )
    runner = RecipeRunner(load_recipe(write(tmp_path, data), hand), 9)
    run(runner, 0.05)
    ticks = {r.name: round(((r.end_s or 0.0) - r.start_s) / 0.001) for r in runner.records[:4]}
    assert ticks["a"] == ticks["b"] == 1
    assert ticks["c"] == ticks["d"]


@pytest.mark.parametrize(("period_ns", "ticks"), [(1_000_000, 10), (3_333_333, 3)])
def test_a_phase_s_max_s_is_as_many_ticks_wherever_the_phase_begins(
    tmp_path: Path, hand: HandConfig, period_ns: int, ticks: int
) -> None:
    """Times to the nanosecond: a bare difference of two tick times is a hair under or over
    0.01 s by where the phase began, and 64 phases of max_s 0.01 ran 10 ticks or 11."""
    data = recipe_doc(
        *(phase(f"p{k}", ramp_s=0.01, max_s=0.01, on_timeout="next") for k in range(40)),
        phase("last", exit=["time >= 0.013"]),
    )
    runner = RecipeRunner(load_recipe(write(tmp_path, data), hand), 9)
    tick = 0
    while not runner.done and tick < 2000:
        # the loop's times: integer nanoseconds from the first tick, in seconds
        runner.step(tick * period_ns * 1e-9, ZERO, ZERO)
        tick += 1
    # at 300 Hz a period of whole nanoseconds is short by a third of one: three were under
    # 0.01 s, and a phase of max_s 0.01 ran four
    lasted = [round(((r.end_s or 0.0) - r.start_s) / (period_ns * 1e-9)) for r in runner.records]
    assert lasted[:40] == [ticks] * 40


def test_a_pose_of_another_hand_s_joints_says_so(tmp_path: Path) -> None:
    """It said 'left_j1: required, missing', where the torques and damping said --hand."""
    planar = load_hand(ROOT / "config" / "hands" / "planar_2f2j.yaml")
    joints = ("f1_j1", "f1_j2", "f1_j3", "f2_j1", "f2_j2", "f2_j3", "f3_j1", "f3_j2", "f3_j3")
    pose = {"angles": dict.fromkeys(joints, 0.1), "stiffness": 1.0}
    doc = recipe_doc(
        {
            "name": "a",
            "torques": dict.fromkeys(planar.joint_names, 0.0),
            "max_s": 1.0,
            "pose": pose,
        }
    )
    err = error(tmp_path, planar, doc)
    assert err.key == "phases[0].pose.angles"
    assert "written for another hand? give its config with --hand" in err.expected


def test_a_misspelt_joint_of_a_pose_is_named_not_the_one_it_stands_for(
    tmp_path: Path, hand: HandConfig
) -> None:
    """fX_j1 for f1_j1 said 'f1_j1: required, missing', and never named fX_j1."""
    angles = dict.fromkeys(hand.joint_names, 0.1)
    angles["fX_j1"] = angles.pop("f1_j1")
    doc = recipe_doc(phase("a", pose={"angles": angles, "stiffness": 1.0}))
    err = error(tmp_path, hand, doc)
    assert err.key == "phases[0].pose.angles.fX_j1"
    assert "did you mean 'f1_j1'?" in err.expected


def test_a_subnormal_number_is_refused_where_it_would_be_nothing(
    tmp_path: Path, hand: HandConfig
) -> None:
    """5e-324 deg/s passed a brake's "> 0", was 0 rad/s once converted, and the run stopped
    on a division by zero in its manipulation (RUNNER_EXCEPTION, exit 3)."""
    doc = recipe_doc(phase("a", brake={"rate_deg_s": 5e-324, "joint_damping": 0.03}))
    err = error(tmp_path, hand, doc)
    assert err.key == "phases[0].brake.rate_deg_s"
    assert "0 or at least 2.22507e-308 in size (a normal float)" in err.expected
    doc = recipe_doc(phase("a", ramp_s=-5e-324))
    assert error(tmp_path, hand, doc).key == "phases[0].ramp_s"


def test_a_pose_hold_damps_no_harder_than_injected_damping(
    tmp_path: Path, hand: HandConfig
) -> None:
    """The pose's damper is the same damper on the same velocity, through the same lag, as a
    phase's joint_damping (at most 0.2 N·m·s/rad); it took 10, and 0.5 drove a joint onto its
    limit in the approach."""
    angles = dict.fromkeys(hand.joint_names, 0.1)
    doc = recipe_doc(phase("a", pose={"angles": angles, "stiffness": 0.5, "damping": 0.5}))
    err = error(tmp_path, hand, doc)
    assert err.key == "phases[0].pose.damping"
    assert "<= 0.2 N·m·s/rad" in err.expected


@pytest.mark.parametrize("name", ["lift ", " lift", "  "])
def test_a_phase_name_readers_cannot_tell_apart_is_refused(
    tmp_path: Path, hand: HandConfig, name: str
) -> None:
    """'lift ' beside 'lift' were two phases, a name of spaces showed as nothing, and a name
    of 10 000 characters was printed whole on the summary's line."""
    err = error(
        tmp_path, hand, recipe_doc(phase("lift", max_s=0.5, on_timeout="next"), phase(name))
    )
    assert err.key == "phases[1].name"
    # (refused by the rule of every printed name, schema's ``label``, before the phases' own)
    assert "not beginning or ending with a space" in err.expected


def test_a_recipe_name_longer_than_a_title_is_refused(tmp_path: Path, hand: HandConfig) -> None:
    """A 300-character recipe name ran off both edges of its plot's title, and a hand's
    headed every table: names printed as they are hold at most 64 characters."""
    err = error(tmp_path, hand, recipe_doc(phase("a"), recipe="r" * 65))
    assert err.key == "recipe" and "a name of at most 64 characters" in err.expected
    err = error(tmp_path, hand, recipe_doc(phase("p" * 65)))
    assert err.key == "phases[0].name" and "a name of at most 64 characters" in err.expected


def test_a_phase_shorter_than_a_loop_period_is_refused(tmp_path: Path, hand: HandConfig) -> None:
    """max_s: 1e-9 ran one tick of its phase, as if it were one that lasted a tick."""
    err = error(tmp_path, hand, recipe_doc(phase("a", max_s=1e-9)))
    assert err.key == "phases[0].max_s" and ">= 0.001" in err.expected
    load_recipe(write(tmp_path, recipe_doc(phase("a", 0.0, max_s=0.001, ramp_s=0.001))), hand)


@pytest.mark.parametrize(
    "condition",
    ["x > 4.0", "x >= 3.15", "x > 3.141592653589793", "x < -3.15", "x <= -3.141592653589793"],
)
def test_an_exit_on_a_line_direction_beyond_its_range_is_refused(
    tmp_path: Path, hand: HandConfig, condition: str
) -> None:
    """A line's direction lies in (-π, π]: an exit past that never came, and the phase timed
    out as if it had not been written."""
    objects = [{"name": "cyl1", "radius": 0.02}, {"name": "cyl2", "radius": 0.02}]
    text = condition.replace("x", "estimate.cyl1_cyl2_line_angle")
    err = error(tmp_path, hand, recipe_doc(phase("a", exit=[text]), objects=objects))
    assert err.key == "phases[0].exit[0]" and "a direction in (-π, π] rad" in err.expected
    assert "estimate.cyl1_cyl2_line_turn" in err.expected
    for fine in ("x > 3.1", "x >= 3.141592653589793", "x < -3.1"):
        doc = recipe_doc(
            phase("a", exit=[fine.replace("x", "estimate.cyl1_cyl2_line_angle")]), objects=objects
        )
        load_recipe(write(tmp_path, doc), hand)


def test_a_ramp_longer_than_its_phase_is_refused(tmp_path: Path, hand: HandConfig) -> None:
    """ramp_s 60 in a phase of max_s 0.5 sent 0.004 N·m of the 0.5 asked, and completed."""
    err = error(tmp_path, hand, recipe_doc(phase("a", ramp_s=60.0, max_s=0.5)))
    assert (
        err.key == "phases[0].ramp_s" and "no longer than the phase's max_s (0.5 s)" in err.expected
    )
    assert err.found == 60.0
    # unsaid, the ramp fits a short phase
    short = phase("a", 0.0, max_s=0.05)
    del short["ramp_s"]
    assert load_recipe(write(tmp_path, recipe_doc(short)), hand).phases[0].ramp_s == 0.05


@pytest.mark.parametrize(
    ("feedback", "key"),
    [
        ({"turn_rate": {"rate_deg_s": -45, "scale": [0.5, 5.0]}}, "phases[1].turn_rate.scale"),
        ({"paced_ramp": {"rate_deg_s": -90, "reach": 3.0}}, "phases[1].paced_ramp.reach"),
        (
            {"paced_ramp": {"rate_deg_s": -90, "back": 10.0}, "ramp_s": 0.05},
            "phases[1].paced_ramp.back",
        ),
    ],
)
def test_a_feedback_that_takes_the_torque_past_the_hand_is_refused(
    tmp_path: Path, hand: HandConfig, feedback: dict[str, Any], key: str
) -> None:
    """A turn-rate loop's scale and a paced ramp's reach went past tau_max (the supervisor
    clamped each joint, bending the planned torque's direction, and nothing said so), and a
    paced ramp going back at ten times its speed past the rate limit the ramp was checked on."""
    objects = [{"name": "cyl1", "radius": 0.02}, {"name": "cyl2", "radius": 0.02}]
    turn = {**phase("turn", 0.2, exit=["estimate.cyl1_cyl2_line_turn < -0.7"]), **feedback}
    data = recipe_doc(phase("hold", -0.1, on_timeout="next"), turn, objects=objects)
    err = error(tmp_path, hand, data)
    assert err.key == key, err
    assert "tau_max" in err.expected or "rate limit" in err.expected, err
    # within the hand, the same feedback loads
    turn["torques"] = dict.fromkeys(turn["torques"], 0.05)
    data = recipe_doc(phase("hold", -0.01, on_timeout="next"), turn, objects=objects)
    load_recipe(write(tmp_path, data), hand)


def test_a_phase_planned_for_another_hand_is_refused_without_the_recipes_own_hash(
    tmp_path: Path, hand: HandConfig
) -> None:
    """Deleting a compiled recipe's `compiled` and `hand_config_hash` let it run on another
    hand config, every phase's provenance still naming the hand it was planned for."""
    planned = phase("a", provenance={"kind": "free", "hand_config_hash": "sha256:0123456789abcdef"})
    err = error(tmp_path, hand, recipe_doc(planned))
    assert err.key == "phases[0].provenance.hand_config_hash"
    assert hand.config_hash in err.expected and "planned for another hand config" in err.expected
    assert err.found == "sha256:0123456789abcdef"
    planned["provenance"]["hand_config_hash"] = hand.config_hash
    load_recipe(write(tmp_path, recipe_doc(planned)), hand)


def test_a_phase_key_indented_into_provenance_is_refused(tmp_path: Path, hand: HandConfig) -> None:
    """A `joint_damping` or an `exit` a level too deep sat in provenance, unread: the phase
    ran without it and nothing said so."""
    deep = phase("a", provenance={"kind": "free", "joint_damping": 0.05})
    err = error(tmp_path, hand, recipe_doc(deep))
    assert err.key == "phases[0].provenance.joint_damping" and "a level too deep" in err.expected
    # what handctl plan writes there loads (its own 'schedule' among it)
    deep["provenance"] = {"kind": "free", "schedule": [{"chosen_from": "x"}], "models": {}}
    load_recipe(write(tmp_path, recipe_doc(deep)), hand)


def test_a_manipulation_phase_is_told_by_its_name_its_plan_or_its_exit_on_a_turn() -> None:
    """Which phases the experiment measures the turn of (``Phase.manipulates``): named
    ``manipulate...``, planned as a turn (``provenance.kind: turn``), or ending on a pair's
    turn; the phases of the lift and the hold are none of these."""
    import dataclasses

    hand = load_hand(ROOT / "config" / "hands" / "planar_2f2j.yaml")
    recipe = load_recipe(ROOT / "config" / "recipes" / "planar_lift_turn.yaml", hand)
    turn = next(p for p in recipe.phases if p.name == "manipulate")
    assert recipe.manipulation_phases == ("manipulate",)
    named = dataclasses.replace(turn, name="turn")
    planned_only = dataclasses.replace(named, exits=())
    exit_only = dataclasses.replace(named, provenance={})
    neither = dataclasses.replace(named, exits=(), provenance={})
    name_only = dataclasses.replace(neither, name="manipulate_9")
    assert [p.manipulates for p in (named, planned_only, exit_only, neither, name_only)] == [
        True, True, True, False, True,
    ]  # fmt: skip
    swapped = dataclasses.replace(
        recipe, phases=tuple(named if p is turn else p for p in recipe.phases)
    )
    assert swapped.manipulation_phases == ("turn",)


@pytest.mark.parametrize(
    ("condition", "holds"),
    [
        ("estimate.cyl1_y > 1e300", False),
        ("estimate.cyl1_x < -2", False),
        ("estimate.cyl1_y > 0.05", True),  # a lift's height: well within the hand
        ("estimate.cyl1_x < 2", True),  # always, at once: not this check's business
    ],
)
def test_an_object_s_place_beyond_the_hand_s_reach_is_refused(
    tmp_path: Path, hand: HandConfig, condition: str, holds: bool
) -> None:
    """An object's estimated centre is where finger links cage it: an exit at 1e300 m was
    accepted and the phase timed out as if it had not been written."""
    objects = [{"name": "cyl1", "radius": 0.02}]
    doc = recipe_doc(phase("a", exit=[condition]), objects=objects)
    if holds:
        load_recipe(write(tmp_path, doc), hand)
        return
    err = error(tmp_path, hand, doc)
    assert err.key == "phases[0].exit[0]"
    assert "an object's centre in the palm's frame, never 0.2" in err.expected


@pytest.mark.parametrize("key", ["turn_rate", "paced_ramp"])
@pytest.mark.parametrize("exit_op", ["<", ">"])
def test_a_rate_signed_against_the_phase_s_exit_is_refused(
    tmp_path: Path, hand: HandConfig, key: str, exit_op: str
) -> None:
    """A rate is signed as the wanted turn; against the turn the phase's exit waits for, the
    pair's turn towards the exit read as going back, and the loop or pace did not do what
    its key said."""
    objects = [{"name": "cyl1", "radius": 0.02}, {"name": "cyl2", "radius": 0.02}]
    wanted = -1 if exit_op == "<" else 1
    feedback: dict[str, Any] = {"rate_deg_s": -60 * wanted}
    if key == "turn_rate":
        feedback["scale"] = [0.5, 1.5]
    exit_text = f"estimate.cyl1_cyl2_line_turn {exit_op} {0.7 * wanted}"
    turn = {**phase("turn", 0.05, exit=[exit_text]), key: feedback}
    err = error(tmp_path, hand, recipe_doc(turn, objects=objects))
    assert err.key == f"phases[0].{key}.rate_deg_s"
    assert f"({exit_text}: {'negative' if wanted < 0 else 'positive'})" in err.expected
    assert err.found == -60 * wanted
    feedback["rate_deg_s"] = 60 * wanted
    load_recipe(write(tmp_path, recipe_doc(turn, objects=objects)), hand)


@pytest.mark.parametrize(
    ("condition", "refused"),
    [
        ("estimate.cyl1_cyl2_line_turn > 45", True),  # 45 degrees, written as rad
        ("estimate.cyl1_cyl2_line_turn < -180", True),
        ("estimate.cyl1_cyl2_line_turn > 1000 for 0.02", True),
        ("estimate.cyl1_cyl2_line_turn < -3.1416", False),  # half a turn
        ("estimate.cyl1_cyl2_line_turn > 6.28", False),  # all but a whole one
        ("estimate.cyl1_cyl2_line_turn < 45", False),  # holds at once: not this check's
    ],
)
def test_a_turn_of_more_than_a_revolution_in_one_phase_is_refused(
    tmp_path: Path, hand: HandConfig, condition: str, refused: bool
) -> None:
    """A turn in degrees where rad are read: 'line_turn > 1000' loaded, and the phase could
    only time out and go on, while the same slip on an angle, a line's direction or a torque
    was refused (an outside probe)."""
    objects = [{"name": "cyl1", "radius": 0.02}, {"name": "cyl2", "radius": 0.02}]
    doc = recipe_doc(phase("a", exit=[condition]), objects=objects)
    if not refused:
        load_recipe(write(tmp_path, doc), hand)
        return
    err = error(tmp_path, hand, doc)
    assert err.key == "phases[0].exit[0]"
    assert "more than a whole revolution (6.283 rad) is a turn written in degrees" in err.expected
