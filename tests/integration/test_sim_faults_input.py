"""A fault scenario for the simulated hand is input like any other, and the simulated hand of a
real-time run is a peer the start-up watches.

A scenario the simulated hand would refuse was read by the hand alone: after the run had
truncated an existing ``--log``, and in real time by the hand's own process, which ended with
exit 2 while the host listened out its 20 s start-up and said exit 3, ``startup_failed``."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time
from pathlib import Path

import psutil
import pytest

from handctl.recording.reader import MAGIC

from ..conftest import ROOT, handctl
from .realtime import REALTIME
from .rig import HOLD_LONG

BAD_NODE = "faults:\n  - {kind: drop_feedback, node: 9, start: 0.5, stop: 0.6}\n"


@pytest.mark.parametrize("mode", ["--lockstep", "--realtime"])
def test_a_fault_scenario_the_hand_refuses_is_bad_input_and_leaves_the_log_alone(
    tmp_path: Path, mode: str
) -> None:
    recipe, faults, log = tmp_path / "hold.yaml", tmp_path / "faults.yaml", tmp_path / "run.mcap"
    recipe.write_text(HOLD_LONG)
    faults.write_text(BAD_NODE)
    earlier = MAGIC + b"an earlier run's log"  # a recording, which a run may replace
    log.write_bytes(earlier)
    done = handctl(
        "run", "recipe", str(recipe), mode, "--sim-faults", str(faults),
        "--max-seconds", "1", "--log", str(log),
    )  # fmt: skip
    assert done.returncode == 2, done.stderr
    assert f"{faults}: faults[0].node: expected a node id of the hand (1, 2, 3), found 9" in (
        done.stderr
    )
    assert "Traceback" not in done.stderr
    assert log.read_bytes() == earlier
    missing = handctl(
        "run", "recipe", str(recipe), mode, "--sim-faults", str(tmp_path / "none.yaml"),
        "--max-seconds", "1",
    )  # fmt: skip
    assert missing.returncode == 2, missing.stderr
    assert "none.yaml: expected an existing file" in missing.stderr


@REALTIME
def test_a_simulated_hand_that_dies_during_start_up_is_said_at_once(tmp_path: Path) -> None:
    """Killed while the host waits for its nodes, the hand's process is said as the reason
    the start-up failed: before, the host listened on for its whole start-up timeout and said
    only that the nodes were not ready."""
    recipe = tmp_path / "hold.yaml"
    recipe.write_text(HOLD_LONG)
    out, log = tmp_path / "out.json", tmp_path / "run.mcap"
    proc = subprocess.Popen(
        [sys.executable, "-m", "handctl", "run", "recipe", str(recipe), "--realtime",
         "--max-seconds", "5", "--summary-json", str(out), "--log", str(log)],
        cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    try:
        host = psutil.Process(proc.pid)
        sim = None
        deadline = time.monotonic() + 60.0
        while sim is None and time.monotonic() < deadline and proc.poll() is None:
            for child in host.children(recursive=True):
                try:
                    if "sim" in child.cmdline()[3:5]:
                        sim = child
                except psutil.Error:
                    continue
            time.sleep(0.01)
        assert sim is not None, "no simulated hand was started"
        sim.send_signal(signal.SIGKILL)
        _, stderr = proc.communicate(timeout=120)
    finally:
        proc.kill()
    assert proc.returncode == 3, stderr
    assert "the simulated hand's process ended with exit -9" in stderr
    assert "nodes not ready within" not in stderr
    # and its log re-runs to the same end: the hand's end, an input from outside the bus,
    # was not in it, and a genuine log said MISMATCH (found by an outside audit)
    done = handctl("replay", str(log), "--rerun")
    assert done.returncode == 0, done.stdout + done.stderr
    assert "MISMATCH" not in done.stdout


def test_a_bus_off_during_start_up_enables_no_node(tmp_path: Path) -> None:
    """Heard while the nodes are listened to, a bus-off is the start-up's end: before, the run
    enabled every node on that bus and stopped on BUS_ERROR at its first tick."""
    recipe, faults = tmp_path / "hold.yaml", tmp_path / "faults.yaml"
    out, log = tmp_path / "out.json", tmp_path / "run.mcap"
    recipe.write_text(HOLD_LONG)
    faults.write_text("faults:\n  - {kind: bus_off, start: 0.0, stop: 0.001}\n")
    done = handctl(
        "run", "recipe", str(recipe), "--sim-faults", str(faults), "--max-seconds", "2",
        "--summary-json", str(out), "--log", str(log),
    )  # fmt: skip
    assert done.returncode == 3, done.stderr
    summary = json.loads(out.read_text())
    assert summary["outcome"] == "startup_failed"
    assert [f["code"] for f in summary["faults"]] == ["BUS_ERROR"]
    assert "bus-off during start-up" in summary["faults"][0]["detail"]
    assert summary["bus_events"] >= 1  # the bus-off, which the log has too
    replayed = tmp_path / "replay.json"
    assert handctl("replay", str(log), "--json", str(replayed)).returncode == 0
    assert json.loads(replayed.read_text())["summary"]["frames"]["tx"] == 0  # nothing sent
    rerun = handctl("replay", str(log), "--rerun")
    assert rerun.returncode == 0, rerun.stdout + rerun.stderr
    assert "the start-up re-run to the same end (startup_failed)" in rerun.stdout


def test_a_receive_backlog_during_start_up_enables_no_node(tmp_path: Path) -> None:
    """A backlog is an immediate stop (safety.md #41), and one heard while the nodes are
    listened to enabled them all the same: the run stopped on it at its first running tick
    (found by an outside audit). Now it is the start-up's end, as a bus-off is."""
    recipe, faults = tmp_path / "hold.yaml", tmp_path / "faults.yaml"
    out = tmp_path / "out.json"
    recipe.write_text(HOLD_LONG)
    faults.write_text("faults:\n  - {kind: babble, per_tick: 1000, start: 0.0, stop: 0.02}\n")
    done = handctl(
        "run", "recipe", str(recipe), "--sim-faults", str(faults), "--max-seconds", "2",
        "--summary-json", str(out),
    )  # fmt: skip
    assert done.returncode == 3, done.stderr
    summary = json.loads(out.read_text())
    assert summary["outcome"] == "startup_failed", summary["message"]
    assert [f["code"] for f in summary["faults"]] == ["RX_BACKLOG"]
    assert "receive backlog during start-up" in summary["faults"][0]["detail"]
    assert "no node was enabled" in summary["faults"][0]["detail"]
