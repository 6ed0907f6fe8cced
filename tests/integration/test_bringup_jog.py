"""``handctl jog`` end to end against the simulated hand: in lockstep on the virtual bus, and
free-running in its own process on the unix bus with Ctrl-C as its controlled stop. One joint
gets the torque, every other zero but for the guard's push-back (named); a torque over tau_max
is refused before anything is sent."""

from __future__ import annotations

import contextlib
import dataclasses
import itertools
import math
import os
import re
import signal
import subprocess
import sys
import threading
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml

from handctl import cli
from handctl.bringup.jog import jog, jog_recipe
from handctl.config import HandConfig, load_hand
from handctl.online.bus import open_bus
from handctl.online.loop import Outcome, RunResult
from handctl.online.safety.recovery import RECOVERY_SLACK, Recovery
from handctl.sim.hand import SIM_RT_PRIORITY, SimulatedHand
from handctl.sim.params import SimParams, parse_sim

from ..conftest import HAND_YAML, ROOT
from .bringup_peer import running_hand
from .realtime import ATTEMPTS_UNDER_LOAD, REALTIME, give_up, stopped_by_load, tolerant_hand
from .rig import Rig, read_until, rig


def test_one_joint_turns_its_way(hand: HandConfig, capsys: pytest.CaptureFixture[str]) -> None:
    code = cli.main(["jog", "f1_j2", "--torque", "0.05", "--seconds", "0.3"])
    out = capsys.readouterr().out
    assert code == cli.EXIT_OK, out
    assert "every other joint at zero unless the soft-limit guard pushes it back" in out
    rows = [line.split() for line in out.splitlines() if line.strip()[:1].isdigit()]
    assert len(rows) > 5 and {r[1] for r in rows} >= {"jog", "end_ramp"}
    applied = [float(r[4]) for r in rows]
    assert max(applied) == pytest.approx(0.05) and applied[-1] < 0.01
    summary = next(line for line in out.splitlines() if line.startswith("f1_j2:"))
    moved = float(summary.split("(")[1].split()[0])
    assert moved > 0.1  # counter-clockwise positive: a positive torque turns it that way
    assert "largest |applied| 0.0500 N·m" in summary


@pytest.mark.parametrize("rate_hz", [250, 300])
def test_the_table_is_every_tenth_of_a_second_and_shows_the_end_ramp_at_any_loop_rate(
    rate_hz: int, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    doc = yaml.safe_load((ROOT / "config" / "hands" / "hiroshima_hand.yaml").read_text())
    doc["bus"]["loop_rate_hz"] = rate_hz
    # the most misses a loop this slow may allow before the nodes' command watchdog
    doc.setdefault("safety", {})["max_consecutive_misses"] = 1
    path = tmp_path / f"hand_{rate_hz}.yaml"
    path.write_text(yaml.safe_dump(doc))
    args = ["jog", "f1_j2", "--torque", "0.05", "--seconds", "0.5", "--hand", str(path)]
    assert cli.main(args) == cli.EXIT_OK
    rows = [line.split() for line in capsys.readouterr().out.splitlines()]
    rows = [r for r in rows if r and r[0][:1].isdigit()]
    assert {"jog", "end_ramp"} <= {r[1] for r in rows}
    times = [float(r[0]) for r in rows]
    assert max(b - a for a, b in itertools.pairwise(times)) <= 0.1 + 1e-9
    assert {round(t, 2) for t in times} >= {0.1, 0.2, 0.3, 0.4, 0.5}


def test_every_other_joint_gets_exactly_zero(hand: HandConfig) -> None:
    result = jog(hand, "f2_j3", 0.03, seconds=0.2)
    applied = result.report.summary["max_abs_tau_nm"]
    assert result.report.summary["outcome"] == "completed"
    assert applied.pop("f2_j3") == pytest.approx(0.03)
    assert set(applied.values()) == {0.0}


def test_a_joint_the_guard_pushes_is_named_with_its_torque(
    capsys: pytest.CaptureFixture[str],
) -> None:
    """A proximal joint's swing swings the middle joint onto its soft limit, and the guard
    pushes it back by the sign the hand config gives it, the sign a jog is there to check:
    the command says so, with the torque, as it does not for a distal jog."""
    assert cli.main(["jog", "f1_j1", "--torque", "0.05", "--seconds", "0.5"]) == cli.EXIT_OK
    last = capsys.readouterr().out.splitlines()[-1]
    assert last.startswith("other joints pushed back from a soft limit by the guard"), last
    pushed = dict(item.split()[:2] for item in last.split(": ", 1)[1].split(", "))
    assert "f1_j1" not in pushed and float(pushed["f1_j2"]) > 0.01
    assert cli.main(["jog", "f2_j3", "--torque", "0.03", "--seconds", "0.2"]) == cli.EXIT_OK
    assert "pushed back" not in capsys.readouterr().out


def test_the_guard_pushes_no_joint_harder_than_twice_the_jog(tmp_path: Path) -> None:
    """A joint resting inside its guard band (f2_j1, its lower limit 0.05 rad below where it
    rests) got up to its whole tau_max while another was jogged at a twelfth of it, and a
    joint of 0.1 rad (f3_j3, around its rest) was pushed onto a limit by the guard from both
    sides: the jog stopped on ANGLE_LIMIT, exit 3. The jog's guard narrows its band on such a
    joint and pushes no joint harder than twice the jog's torque."""
    doc = yaml.safe_load((ROOT / "config" / "hands" / "hiroshima_hand.yaml").read_text())
    f2_j1, f3_j3 = doc["fingers"][1]["joints"][0], doc["fingers"][2]["joints"][2]
    f2_j1["angle_min"] = doc["sim"]["initial_angles"]["f2"][0] - 0.05
    rest = doc["sim"]["initial_angles"]["f3"][2]
    f3_j3["angle_min"], f3_j3["angle_max"] = rest - 0.05, rest + 0.05
    path = tmp_path / "hand.yaml"
    path.write_text(yaml.safe_dump(doc))
    result = jog(load_hand(path), "f1_j2", 0.05, seconds=0.5)
    summary = result.report.summary
    assert summary["outcome"] == "completed", summary.get("faults")
    applied = summary["max_abs_tau_nm"]
    assert applied.pop("f1_j2") == pytest.approx(0.05)
    assert applied["f2_j1"] > 0.01  # pushed out of its band, as before, but gently
    assert max(applied.values()) <= 2 * 0.05 + 1e-9, applied


def test_a_negative_torque_turns_it_back(capsys: pytest.CaptureFixture[str]) -> None:
    assert cli.main(["jog", "f3_j1", "--torque", "-0.05", "--seconds", "0.3"]) == cli.EXIT_OK
    out = capsys.readouterr().out
    summary = next(line for line in out.splitlines() if line.startswith("f3_j1:"))
    assert float(summary.split("(")[1].split()[0]) < -0.1


def test_a_negative_torque_in_exponent_form_is_a_value(
    capsys: pytest.CaptureFixture[str],
) -> None:
    """argparse took ``-5e-2`` for an option ("--torque: expected one argument"): a torque
    had to be written ``--torque=-5e-2``."""
    assert cli.main(["jog", "f3_j1", "--torque", "-5e-2", "--seconds", "0.3"]) == cli.EXIT_OK
    out = capsys.readouterr().out
    summary = next(line for line in out.splitlines() if line.startswith("f3_j1:"))
    assert "under -0.05 N·m" in summary


@pytest.mark.parametrize(
    "args, says",
    [
        # the bound that applies, first: over tau_max, a jog was told tau_max (0.3 here) and
        # then refused at 0.3 for its own share of it (an outside audit)
        (
            ["f1_j3", "--torque", "0.31"],
            "--torque: expected |τ| <= 0.15 N·m (half of f1_j3's tau_max, 0.3 N·m in ",
        ),
        (
            ["f1_j3", "--torque", "0.31", "--recover"],
            "--torque: expected |τ| <= 0.3 N·m (tau_max of f1_j3",
        ),
        (
            ["f1_j2", "--torque", "0.45"],
            "--torque: expected |τ| <= 0.225 N·m (half of f1_j2's tau_max, 0.45 N·m in ",
        ),
        (["f1_j3", "--torque", "nan"], "--torque: expected |τ| <= 0.15 N·m"),
        (["f9_j1", "--torque", "0.01"], "JOINT: expected a joint of"),
        (["f1_j1", "--torque", "0.01", "--seconds", "-1"], "--seconds"),
        (["f1_j1", "--torque", "0.01", "--seconds", "1e9"], "--seconds: expected a time in "),
        (
            ["f2_j2", "--torque=-4e-5"],
            "--torque: expected 0 or |τ| >= 0.0001 N·m (the command signal's step: less "
            "reaches f2_j2 as zero or as one step), found -4e-05",
        ),
    ],
)
def test_bad_input_is_refused_before_anything_is_sent(
    hand: HandConfig, channel: str, capsys: pytest.CaptureFixture[str], args: list[str], says: str
) -> None:
    sniffer = open_bus(f"virtual:{channel}", hand.bus)
    try:
        code = cli.main(["jog", *args, "--bus", f"virtual:{channel}"])
        heard = sniffer.drain(limit=1000)
    finally:
        sniffer.close()
    assert code == cli.EXIT_BAD_INPUT
    assert says in capsys.readouterr().err
    assert heard == []


@pytest.mark.parametrize(
    "command", [["jog", "f1_j1", "--torque", "0.01"], ["calibrate", "tdt", "--write"]]
)
def test_a_negative_seed_is_a_usage_error_before_anything_is_sent(
    hand: HandConfig, channel: str, capsys: pytest.CaptureFixture[str], command: list[str]
) -> None:
    # numpy's generators take no negative seed: it was a ValueError traceback from the
    # simulated hand's start, after the command had begun
    sniffer = open_bus(f"virtual:{channel}", hand.bus)
    try:
        with pytest.raises(SystemExit) as stop:
            cli.main([*command, "--seed", "-5", "--bus", f"virtual:{channel}"])
        heard = sniffer.drain(limit=1000)
    finally:
        sniffer.close()
    assert stop.value.code == cli.EXIT_BAD_INPUT
    assert "argument --seed: expected an integer from 0 to 4294967295, found '-5'" in (
        capsys.readouterr().err
    )
    assert heard == []


@pytest.mark.parametrize(
    "command",
    [
        ["jog", "f1_j1", "--torque", "0.01"],
        ["calibrate", "tdt", "-o", "{tmp}/calibrated.yaml"],
        ["run", "recipe", str(ROOT / "config" / "recipes" / "swap_two_cylinders.yaml")],
    ],
)
@pytest.mark.parametrize("option", ["--seed", "--sim-faults"])
def test_an_option_of_the_simulated_hand_on_another_bus_is_refused_before_anything_is_sent(
    tmp_path: Path,
    hand: HandConfig,
    channel: str,
    capsys: pytest.CaptureFixture[str],
    command: list[str],
    option: str,
) -> None:
    """On a bus that is not the simulated hand, ``--seed`` and ``--sim-faults`` did nothing,
    without a word: a run meant to be disturbed by faults ran on a hand that had none."""
    value = "3" if option == "--seed" else str(ROOT / "config" / "sim" / "sensor_faults.yaml")
    sniffer = open_bus(f"virtual:{channel}", hand.bus)
    try:
        words = [w.replace("{tmp}", str(tmp_path)) for w in command]
        code = cli.main([*words, option, value, "--bus", f"virtual:{channel}"])
        heard = sniffer.drain(limit=1000)
    finally:
        sniffer.close()
    assert code == cli.EXIT_BAD_INPUT
    err = capsys.readouterr().err
    assert f"{option}: expected the simulated hand (--bus sim): only it takes {option}" in err
    assert heard == []


def test_sim_cpu_on_another_bus_is_refused(
    hand: HandConfig, channel: str, capsys: pytest.CaptureFixture[str]
) -> None:
    """``run --sim-cpu N --rt`` on a bus with no simulated hand placed nothing, without a
    word."""
    recipe = str(ROOT / "config" / "recipes" / "swap_two_cylinders.yaml")
    args = ["run", "recipe", recipe, "--sim-cpu", "0", "--rt", "--bus", f"virtual:{channel}"]
    assert cli.main(args) == cli.EXIT_BAD_INPUT
    assert "--sim-cpu: expected the simulated hand (--bus sim)" in capsys.readouterr().err


def test_a_missing_node_stops_it_at_start_up(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    faults = tmp_path / "faults.yaml"
    faults.write_text("faults:\n  - {kind: node_silent, node: 3, start: 0.0}\n")
    code = cli.main(["jog", "f1_j1", "--torque", "0.05", "--sim-faults", str(faults)])
    assert code == cli.EXIT_SAFETY_STOP
    assert "node 3 (f3): no feedback" in capsys.readouterr().err


def test_a_jog_whose_encoder_fails_reports_the_motion_before_it(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """An encoder that jumps far (the node latches SENSOR) left its jump in the closing line
    as motion: tens of degrees the joint never turned (an outside audit)."""
    faults = tmp_path / "faults.yaml"
    faults.write_text(
        "faults:\n  - {kind: encoder_jump, node: 1, joint: 2, counts: 4000, start: 0.3}\n"
    )
    args = ["jog", "f1_j2", "--torque", "0.05", "--seconds", "1"]
    code = cli.main([*args, "--sim-faults", str(faults)])
    captured = capsys.readouterr()
    assert code == cli.EXIT_SAFETY_STOP, captured.err
    assert "node 1 (f1) in FAULT (SENSOR" in captured.err
    line = next(x for x in captured.out.splitlines() if x.startswith("f1_j2: "))
    assert ", to the last reading before its encoder failed)" in line
    moved = float(line.split("(")[1].split(" rad")[0])
    # 4000 counts is 1.53 rad, more than the joint turns in the whole jog (0.55 rad by then)
    assert 0.0 < moved < 1.0, line
    assert cli.main([*args[:4], "--seconds", "0.3"]) == cli.EXIT_OK  # no such words unfailed
    assert "encoder failed" not in capsys.readouterr().out


@REALTIME
def test_ctrl_c_is_a_controlled_stop_on_the_unix_bus(tmp_path: Path) -> None:
    # the stop is the subject, not the deadlines: a hand ``tolerant_of_load`` stops on fewer
    hand = tolerant_hand(HAND_YAML, tmp_path)
    stopped = []
    for _attempt in range(ATTEMPTS_UNDER_LOAD):  # a run the load stopped is tried again
        proc = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "handctl",
                "jog",
                "f2_j1",
                "--torque",
                "0.05",
                "--seconds",
                "60",
                "--hand",
                str(hand),
                "--realtime",
                "--rt",
            ],
            cwd=ROOT,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        assert proc.stdout is not None
        lines = []
        for line in proc.stdout:
            lines.append(line)
            if " jog " in line:  # torque is flowing
                proc.send_signal(signal.SIGINT)
                break
        out, err = proc.communicate(timeout=60)
        if proc.returncode == cli.EXIT_INTERRUPTED:
            assert "stopped: signal SIGINT" in err
            assert "f2_j1:" in out  # the summary after the stop
            return
        assert proc.returncode == cli.EXIT_SAFETY_STOP, (proc.returncode, err, lines)
        assert stopped_by_load(err), err
        stopped.append(err)
    give_up("every attempt was stopped by the machine's load", stopped)


@REALTIME
@pytest.mark.parametrize(
    "command",
    [
        ["jog", "f2_j1", "--torque", "0.05", "--seconds", "0.3"],
        ["calibrate", "tdt", "--settle", "0.2", "--seconds", "0.3", "--max-span", "1.0"],
    ],
)
def test_on_a_real_bus_the_host_check_can_be_overridden_as_it_says(
    hand: HandConfig, tmp_path: Path, command: list[str]
) -> None:
    # On a real bus a host that fails the timing check is refused with "to run anyway, pass
    # --accept-missed-deadlines": jog and calibrate tdt did not have that option (exit 2).
    spec = f"unix:{tmp_path / 'bus'}"
    out = ["-o", str(tmp_path / "calibrated.yaml")] if command[0] == "calibrate" else []
    with running_hand(hand, spec):
        result = subprocess.run(
            [
                sys.executable,
                "-m",
                "handctl",
                *command,
                *out,
                "--bus",
                spec,
                "--accept-missed-deadlines",
            ],
            capture_output=True,
            text=True,
            cwd=ROOT,
            timeout=300,
            check=False,
        )
    # The run went onto the bus: done, or (on a loaded machine, the hand a thread of this
    # process) stopped by the load, as the option warns it may be.
    assert result.returncode == cli.EXIT_OK or (
        result.returncode == cli.EXIT_SAFETY_STOP and stopped_by_load(result.stderr)
    ), result.stderr


# -- a joint resting outside its soft limits: ``--recover`` --------------------------------------
#: f1_j3 (a distal joint) rests hyperextended 0.05 rad below its lower limit (−0.90 rad, its
#: stop at −1.00), as a finger that tripped ANGLE_LIMIT at speed and coasted on may rest: no
#: config may start a hand there, so the test builds its params
J3, OUTSIDE, PUSH = 2, -0.95, 0.03  # index, rad, N·m


def resting_outside(hand: HandConfig) -> SimParams:
    params = parse_sim(hand)
    angles = [list(finger) for finger in params.initial_angles]
    angles[0][J3] = OUTSIDE
    return dataclasses.replace(params, initial_angles=tuple(tuple(f) for f in angles))


def test_the_hand_resting_outside_stays_outside_on_its_own(hand: HandConfig, channel: str) -> None:
    """The premise of the tests below: without torque nothing brings the joint back (it
    settles by a few hundredths and stays), so a joint back inside was brought back."""
    with open_bus(f"virtual:{channel}", hand.bus) as bus:
        sim = SimulatedHand(hand, bus, params=resting_outside(hand))
        for _ in range(3000):
            sim.step()
        assert sim.plant.joint_angles[J3] < hand.joints[J3].angle_min - 0.02


def recovery_run(
    hand: HandConfig, torque: float, recovery: Recovery | None
) -> tuple[Rig, RunResult, list[float]]:
    """The jog (``recover`` with a recovery) in lockstep on the hand resting outside: the
    rig, the run's result and f1_j3's measured angle at each tick."""
    recipe = jog_recipe(hand, "f1_j3", torque, 2.0, recover=recovery is not None)
    angles: list[float] = []
    with rig(hand, recipe, params=resting_outside(hand)) as bench:
        bench.runtime.supervisor.recovery = recovery
        bench.runtime.tick_hooks.append(
            lambda _tk: angles.append(float(bench.runtime.driver.state.angle[J3]))
        )
        result = bench.run()
    return bench, result, angles


def test_a_joint_resting_outside_stops_any_run_and_says_how_to_recover(hand: HandConfig) -> None:
    bench, result, _ = recovery_run(hand, PUSH, None)
    assert result.outcome is Outcome.SAFETY_STOP
    assert result.message.startswith("ANGLE_LIMIT at tick 1: f1_j3 at -0.9")
    assert "bring it back with `handctl jog f1_j3 --torque +X --recover`" in result.message
    assert not bench.commands().any()  # not one torque went out


def test_recover_brings_it_back_inside_and_ends_there(hand: HandConfig) -> None:
    recovery = Recovery(J3, +1)
    bench, result, angles = recovery_run(hand, PUSH, recovery)
    assert result.outcome is Outcome.COMPLETED, result.message
    lower = hand.joints[J3].angle_min
    assert recovery.needed and recovery.start_angle is not None
    assert recovery.start_angle < lower - 0.02
    assert recovery.back_tick > 0
    # the phase ended on its exit (GUARD_BAND inside), long before its 2 s
    phase = result.phases[0]
    assert phase["name"] == "recover" and phase["exit"].startswith("angle.f1_j3 >")
    assert phase["end_s"] < 1.0
    assert angles[-1] > lower + 0.1
    # the ratchet held throughout: never further out than the slack beyond the farthest in
    farthest_in = angles[0]
    for q in angles:
        assert q >= farthest_in - RECOVERY_SLACK or q >= lower
        farthest_in = max(farthest_in, q)
    commands = bench.commands()
    assert set(np.flatnonzero(np.abs(commands).max(axis=0))) == {J3}  # f1_j3 alone
    assert 0 < commands[:, J3].max() <= PUSH  # no more than asked for: the guard is off


def test_a_recovery_that_comes_in_at_speed_ends_inside_the_far_limit(tmp_path: Path) -> None:
    """The phase ends 0.15 rad inside, and the end ramp after it (0.2 s at least) had no
    guard: under the torque still in it, a joint of a 0.55 rad range that came in at speed
    went on into its other soft limit, a latched ANGLE_LIMIT (exit 3; found by an outside
    audit). The guard on the side the torque pushes towards holds it inside."""
    doc = yaml.safe_load(HAND_YAML.read_text(encoding="utf-8"))
    doc["fingers"][0]["joints"][J3]["angle_max"] = -0.35
    doc["sim"]["initial_angles"]["f1"][J3] = -0.5  # inside, for the config; the run's outside
    path = tmp_path / "narrow.yaml"
    path.write_text(yaml.safe_dump(doc), encoding="utf-8")
    narrow = load_hand(path)
    spec = narrow.joints[J3]
    recovery = Recovery(J3, +1)
    _, result, angles = recovery_run(narrow, spec.tau_max, recovery)
    assert result.outcome is Outcome.COMPLETED, result.message
    assert recovery.needed and recovery.back_tick > 0
    assert result.phases[0]["exit"].startswith("angle.f1_j3 >")
    assert max(angles) < spec.angle_max, max(angles)
    assert spec.angle_min <= angles[-1] <= spec.angle_max


def test_recover_the_wrong_way_is_refused_before_any_torque(hand: HandConfig) -> None:
    bench, result, _ = recovery_run(hand, -PUSH, Recovery(J3, -1))
    assert result.outcome is Outcome.SAFETY_STOP
    assert "its recovery must push it back in (a positive torque)" in result.message
    assert not bench.commands().any()


def test_a_recovery_without_a_torque_is_bad_input(capsys: pytest.CaptureFixture[str]) -> None:
    assert cli.main(["jog", "f1_j1", "--torque", "0", "--recover"]) == cli.EXIT_BAD_INPUT
    assert "with --recover, a torque that pushes f1_j1 back in" in capsys.readouterr().err


def test_recover_says_when_there_was_nothing_to_recover(
    capsys: pytest.CaptureFixture[str],
) -> None:
    assert cli.main(["jog", "f1_j1", "--torque", "0.05", "--recover"]) == cli.EXIT_OK
    out = capsys.readouterr().out
    assert "f1_j1 was inside its soft limits [-1, +1.9] rad" in out
    # nothing was applied, and the jog's line says so (it said "under +0.05 N·m")
    assert ") with no torque applied; largest |TDT| " in out
    assert "largest |applied| 0.0000 N·m" in out
    # the guard is off in a recovery: the banner said it might push the other joints
    assert (
        "every other joint at zero (the soft-limit guard is off in a recovery, but for the "
        "limit the torque pushes f1_j1 towards)"
    ) in out


RECOVER = [sys.executable, "-m", "handctl", "jog", "f1_j3", "--torque", str(PUSH), "--recover"]


def node_priority(sim: SimulatedHand) -> None:
    """The simulated hand's timer thread at the priority ``handctl sim --rt`` gives its
    process (the nodes have a core each on the real hand): beside a jog at SCHED_FIFO, a hand
    at normal priority is the first thing a loaded machine starves. Refused: left as it is."""
    for thread in threading.enumerate():
        if thread.name == "simulated-hand" and thread.native_id is not None:
            with contextlib.suppress(PermissionError, OSError):
                os.sched_setscheduler(
                    thread.native_id, os.SCHED_FIFO, os.sched_param(SIM_RT_PRIORITY)
                )


@REALTIME
def test_recover_on_a_bus_from_the_command_line(hand: HandConfig, tmp_path: Path) -> None:
    """The option end to end: the simulated hand resting outside, free-running on the unix
    bus in this process, and ``handctl jog --recover --rt`` in a process of its own (a
    real-time run: one the load stopped is tried again, on a hand resting outside again)."""
    stopped = []
    spec = f"unix:{tmp_path / 'bus'}"
    # the recovery is the subject, not the deadlines: a host ``tolerant_of_load``
    tolerant = tolerant_hand(HAND_YAML, tmp_path)
    for _attempt in range(ATTEMPTS_UNDER_LOAD):
        with running_hand(hand, spec, params=resting_outside(hand)) as sim:
            node_priority(sim)
            result = subprocess.run(
                [
                    *RECOVER,
                    "--bus",
                    spec,
                    "--hand",
                    str(tolerant),
                    "--rt",
                    "--accept-missed-deadlines",
                ],
                capture_output=True,
                text=True,
                cwd=ROOT,
                timeout=300,
                check=False,
            )
        if result.returncode == cli.EXIT_OK:
            assert "f1_j3 back inside its soft limits: -0.9" in result.stdout, result.stdout
            return
        assert result.returncode == cli.EXIT_SAFETY_STOP, result.stderr
        assert stopped_by_load(result.stderr), result.stderr
        stopped.append(result.stderr)
    give_up("every attempt was stopped by the machine's load", stopped)


def test_a_hand_without_a_simulated_one_is_refused_before_the_table(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """On the simulated hand (the default bus), a hand config without a sim section was
    refused under the table's header, as if the jog had begun."""
    doc = yaml.safe_load(HAND_YAML.read_text(encoding="utf-8"))
    del doc["sim"]
    path = tmp_path / "nosim.yaml"
    path.write_text(yaml.safe_dump(doc), encoding="utf-8")
    assert cli.main(["jog", "f1_j1", "--torque", "0.01", "--hand", str(path)]) == 2
    captured = capsys.readouterr()
    assert captured.out == ""
    assert f"{path}: sim: expected a sim: section for --bus sim, the simulated hand" in (
        captured.err
    )


def test_the_table_ends_on_the_torque_back_at_zero_after_a_stop(
    hand: HandConfig, tmp_path: Path
) -> None:
    """A safety stop (and a Ctrl-C) ended the table on a line of the fault ramp, the torque
    still on: the operator never saw it back at zero, which the bus had."""
    faults = tmp_path / "spike.yaml"
    faults.write_text(
        "faults:\n  - {kind: tdt_spike, node: 1, joint: 1, amplitude: 5.0, start: 0.6}\n"
    )
    lines: list[Any] = []
    report = jog(hand, "f1_j1", 0.3, seconds=1.0, sim_faults=faults, show=lines.append)
    assert report.report.result.outcome is Outcome.SAFETY_STOP
    assert lines[-1].applied == 0.0 and lines[-1].state == "faulted"
    assert any(line.applied > 0.1 for line in lines)


def test_a_stop_signal_once_the_hand_has_stopped_is_said(
    capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    """A SIGTERM after the hand had stopped, before the command's end (its run's summary
    being made; in real time, the simulated hand's process ending) was dropped inside the
    run: exit 0 without a word, where ``run`` says it (found by an outside audit). The jog's
    result stands, and the signal is said."""
    from handctl import session

    original = session.summarise_run

    def signalled(*args: Any, **kwargs: Any) -> Any:
        signal.raise_signal(signal.SIGTERM)
        return original(*args, **kwargs)

    monkeypatch.setattr(session, "summarise_run", signalled)
    code = cli.main(["jog", "f1_j2", "--torque", "0.05", "--seconds", "0.2"])
    captured = capsys.readouterr()
    assert code == cli.EXIT_OK, captured.err
    assert "f1_j2: " in captured.out  # the jog's result
    assert (
        "handctl: SIGTERM came after the hand had stopped, while the jog was finished: "
        "ignored, the jog's result stands" in captured.err
    ), captured.err


@pytest.mark.parametrize(
    ("sig", "faults", "code"),
    [
        (signal.SIGINT, None, cli.EXIT_OK),
        (signal.SIGTERM, None, cli.EXIT_OK),
        (signal.SIGINT, "{kind: motor_saturation, node: 1, joint: 2, limit: 0.012, start: 0.0}", 1),
    ],
)
def test_a_stop_signal_while_the_jog_s_result_is_said_changes_no_exit(
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
    tmp_path: Path,
    sig: signal.Signals,
    faults: str | None,
    code: int,
) -> None:
    """A Ctrl-C once the hand had stopped, while the result was said (a stopped terminal
    holds that for as long as it likes), turned the jog's exit 0, or its FAILED exit 1, into
    130 "interrupted", its result lines lost (found by an outside audit). The signal comes
    here right after the jog's stop signals are put back, the hand stopped."""
    from handctl import stopsignals

    original = stopsignals.StopSignals.__exit__

    def signalled(self: stopsignals.StopSignals, *exc: Any) -> None:
        original(self, *exc)
        signal.raise_signal(sig)

    monkeypatch.setattr(stopsignals.StopSignals, "__exit__", signalled)
    args = ["jog", "f1_j2", "--torque", "0.03", "--seconds", "0.2"]
    if faults is not None:
        scenario = tmp_path / "sat.yaml"
        scenario.write_text(f"faults:\n  - {faults}\n")
        args += ["--sim-faults", str(scenario)]
    assert cli.main(args) == code
    captured = capsys.readouterr()
    assert "f1_j2: " in captured.out, captured.err  # the jog's result, said
    assert [sig.name] == stopsignals.LATE
    cli.leave(code)
    assert (
        f"handctl: {sig.name} came after the command had finished; its exit ({code}) stands"
        in capsys.readouterr().err
    )


def test_a_jog_refused_before_it_runs_prints_no_banner(
    capsys: pytest.CaptureFixture[str],
) -> None:
    """The banner and the table's header came first, then the bus error (exit 4): read from
    a log or through a pipe it looked like a jog that had started (found by an outside
    audit). Here the kernel has no SocketCAN; on one with it, no can0 is there either."""
    code = cli.main(["jog", "f1_j1", "--torque", "0.03", "--bus", "socketcan:can0"])
    assert code == cli.EXIT_BUS
    captured = capsys.readouterr()
    assert "socketcan:can0" in captured.err
    assert captured.out == ""


def test_a_jog_whose_start_up_failed_prints_no_banner(capsys: pytest.CaptureFixture[str]) -> None:
    """No node answered, the start-up failed (exit 3), and the banner and the table's header
    were printed all the same, after it: a jog that never ran looked like one that had."""
    import uuid

    argv = ["jog", "f1_j1", "--torque", "0.03", "--bus", f"virtual:nobody-{uuid.uuid4().hex}"]
    assert cli.main([*argv, "--accept-missed-deadlines"]) == cli.EXIT_SAFETY_STOP
    captured = capsys.readouterr()
    assert "no feedback" in captured.err or "not ready" in captured.err, captured.err
    assert "jog f1_j1 with" not in captured.out and "angle rad" not in captured.out


@pytest.mark.parametrize(("joint", "torque"), [("f1_j2", 0.225), ("f1_j1", 0.3), ("f1_j3", -0.15)])
def test_a_jog_at_the_most_it_may_ask_ends_inside_every_limit(
    hand: HandConfig, joint: str, torque: float
) -> None:
    """f1_j2 at its tau_max (0.45 N·m) went past its limit, the guard's push-back meeting the
    jog only there, and f1_j1 at 0.4 N·m flung f1_j2 past its own: each a latched
    ANGLE_LIMIT (an outside audit). Half of tau_max, the most a jog now asks, holds."""
    assert torque == pytest.approx(
        math.copysign(0.5, torque) * hand.joints[[j.name for j in hand.joints].index(joint)].tau_max
    )
    result = jog(hand, joint, torque, seconds=1.5)
    assert result.report.result.outcome is Outcome.COMPLETED, result.report.result.message


@pytest.mark.parametrize(
    "fault",
    [
        "{kind: motor_saturation, node: 1, joint: 1, limit: 0.005, start: 0.0}",
        "{kind: tdt_offset, node: 1, joint: 1, offset: -0.012, start: 0.0}",
    ],
    ids=["saturated", "offset"],
)
def test_a_tdt_that_does_not_follow_the_jog_fails_it(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], fault: str
) -> None:
    """The supervisor allows the TDT 0.02 N·m and 15 % off the command, as much as a jog's
    small torque: a jog at 0.02 N·m whose TDT read a quarter of it said "completed", exit 0
    (an outside probe), the bring-up step meant to find such a sensor passed it. (A stuck
    sensor, or one further off, the supervisor stops on.)"""
    faults = tmp_path / "faults.yaml"
    faults.write_text(f"faults:\n  - {fault}\n")
    args = ["jog", "f1_j1", "--torque", "0.02", "--seconds", "0.5"]
    code = cli.main([*args, "--sim-faults", str(faults)])
    err = capsys.readouterr().err
    assert code == cli.EXIT_FAILED, err
    assert "handctl: FAILED: f1_j1's TDT read " in err
    assert "was applied (expected between 0.5 and 2 times it)" in err
    assert cli.main(args) == cli.EXIT_OK  # the same jog on the sound sensor
    assert "FAILED" not in capsys.readouterr().err


def test_a_jog_whose_command_rang_does_not_blame_the_sensor(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A joint of large tau_max and a fast rate limit: the soft-limit guard's spring (tau_max
    over its band) is stiff for the links and rings against the jog, the command swinging
    between +0.5 and -1 N·m. The mean of that is no torque the joint was held at, and a
    sound TDT was said not to follow its joint (found by an outside audit)."""
    doc = yaml.safe_load(HAND_YAML.read_text())
    joint = doc["fingers"][0]["joints"][1]
    joint.update(tau_max=2.5, device_tau_max=3.2, rate_limit=6000.0)
    doc["sim"]["tdt"]["range"] = 3.27  # past the node's saturation
    motors = doc["sim"]["actuator"]["motor_tau_max"]
    motors["f1"] = [motors["f1"][0], 4.0, *motors["f1"][2:]]  # the node's saturation binds
    hand_file = tmp_path / "stiff_guard.yaml"
    hand_file.write_text(yaml.safe_dump(doc))
    code = cli.main(
        ["jog", "f1_j2", "--torque", "0.5", "--seconds", "0.5", "--hand", str(hand_file)]
    )
    err = capsys.readouterr().err
    assert "f1_j2's command rang" in err
    assert code == cli.EXIT_FAILED, err
    assert "handctl: FAILED: f1_j2's TDT cannot be judged: its command rang" in err
    assert "does not follow its joint" not in err


@pytest.mark.parametrize("torque", ["-0.06", "-0.3"])
def test_a_jog_the_guard_holds_below_its_torque_cannot_be_judged(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], torque: str
) -> None:
    """f1_j1 jogged into its lower soft limit: the guard holds the applied torque off the
    one asked for the whole jog, no tick counted as the hold, and the TDT, here reading
    0.014 N·m high (under half the torque applied at -0.3 N·m), was judged on nothing: exit
    0 without a word (found by an outside audit). It cannot be judged, and is said so."""
    faults = tmp_path / "offset.yaml"
    faults.write_text(
        "faults:\n  - {kind: tdt_offset, node: 1, joint: 1, offset: 0.014, start: 0.0}\n"
    )
    args = ["jog", "f1_j1", "--torque", torque, "--seconds", "1", "--sim-faults", str(faults)]
    code = cli.main(args)
    err = capsys.readouterr().err
    assert code == cli.EXIT_FAILED, err
    assert (
        f"handctl: FAILED: f1_j1's TDT cannot be judged: its applied torque was held off the "
        f"{float(torque):+g} N·m asked" in err
    )
    # what was applied instead, with its sign: the guard holds the joint up from its lower
    # limit, and may push it the other way (it was said "at most" a magnitude, which read
    # as a torque past the one asked in its direction)
    found = re.search(r"acting on the joint: from ([+-][0-9.]+) to ([+-][0-9.]+) N·m\)", err)
    assert found, err
    low, high = float(found[1]), float(found[2])
    assert float(torque) <= low <= high
    assert high > float(torque)


def test_a_reader_that_falls_behind_does_not_stop_the_jog(tmp_path: Path) -> None:
    """The table is written from inside the tick. Through a pipe whose reader stopped reading
    (``handctl jog ... | less`` left at its prompt), the write blocked once the pipe was
    full, and with it the loop: the jogged torque stayed on until the node's watchdog, and
    the jog's table showed no gap. A pipe of one page, never read while the jog runs, must
    not hold the jog up: it finishes and says how many lines were not shown (on stderr),
    and only its closing lines wait for the reader. Lockstep: judged on behaviour alone."""
    import fcntl

    read_end, write_end = os.pipe()
    fcntl.fcntl(write_end, 1031, 4096)  # F_SETPIPE_SZ: one page, filled within seconds
    err_read, err_write = os.pipe()
    proc = subprocess.Popen(
        [sys.executable, "-m", "handctl", "jog", "f1_j1", "--torque", "0.05", "--seconds", "6"],
        cwd=ROOT,
        stdout=write_end,
        stderr=err_write,
    )
    os.close(write_end)
    os.close(err_write)
    try:
        # the note comes before the closing lines to stdout, which wait for the reader
        said = read_until(err_read, "lines were not shown", timeout_s=60.0)
        table = b""
        while chunk := os.read(read_end, 65536):
            table += chunk
        said += read_until(err_read, None, timeout_s=10.0)
        proc.wait(timeout=60)
    finally:
        proc.kill()
        proc.wait()
        os.close(read_end)
        os.close(err_read)
    assert "lines were not shown" in said, said
    assert proc.returncode == 0, said
    shown = table.decode()
    assert shown.startswith("jog f1_j1"), shown[:200]  # the banner went out with a line
    assert "f1_j1: " in shown  # and the closing lines, once the reader read
