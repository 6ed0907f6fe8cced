"""A node that latches FAULT after a run's stop has taken the torque out, before the disable:
the hand is safe, but the next run is refused until ``--reset-node-faults``. The run said
nothing of it (exit 0, "success"); it is said now, a warning and the summary's
``ended_in_fault``. On the simulated hand, in lockstep: its ticks are the run's."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from ..conftest import DEFAULT_RECIPE, handctl

#: an e-stop frame on the bus (identifier 0, as another host sends it) 4-5 ms after the run's
#: time budget of 0.3 s: its stop has reached zero torque (idle at 0.303 s) and the disable,
#: six ticks later, has not gone yet
ESTOP_AFTER_THE_STOP = """
faults:
  - {kind: babble, id: 0x000, per_tick: 1, length: 3, start: 0.304, stop: 0.305}
"""


def test_a_node_faulted_after_the_stop_is_said(tmp_path: Path) -> None:
    faults = tmp_path / "estop.yaml"
    faults.write_text(ESTOP_AFTER_THE_STOP)
    out = tmp_path / "summary.json"
    done = handctl(
        "run", "recipe", DEFAULT_RECIPE, "--max-seconds", "0.3",
        "--sim-faults", str(faults), "--summary-json", str(out),
    )  # fmt: skip
    assert done.returncode == 0, done.stderr  # its stop was the time budget's, whole
    summary = json.loads(out.read_text())
    assert summary["faults"] == []
    said = summary["ended_in_fault"]
    assert said.startswith("node 1 (f1, ESTOP), node 2 (f2, ESTOP), node 3 (f3, ESTOP) in FAULT")
    assert "--reset-node-faults" in said
    assert f"handctl: warning: {said}" in done.stderr
    # and where the e-stop came from: another sender (the babble's frame, not a valid one)
    heard = summary["estop_heard"]
    assert heard.startswith("an e-stop frame (id 0x000, malformed, 3 bytes: "), heard
    assert "from another sender was heard" in heard
    assert f"handctl: warning: {heard}" in done.stderr
    # without the e-stop, nothing is said
    done = handctl(
        "run", "recipe", DEFAULT_RECIPE, "--max-seconds", "0.3", "--summary-json", str(out)
    )
    assert done.returncode == 0, done.stderr
    assert "ended_in_fault" not in json.loads(out.read_text())
    assert "estop_heard" not in json.loads(out.read_text())
    assert "rebooted" not in json.loads(out.read_text())


#: another host's TorqueCommand for node 1 on the bus 8-12 ms into the run's stop, after the
#: run's disable (at 0.308 s) and while it listens for the nodes' DISABLED
COMMAND_AFTER_THE_DISABLE = """
faults:
  - {kind: babble, id: 0x101, per_tick: 1, length: 8, start: 0.308, stop: 0.312}
"""


def test_another_host_heard_after_the_disable_is_a_foreign_command(tmp_path: Path) -> None:
    """A second host that waits for this run's disable and then commands the nodes: the
    wait for the nodes' DISABLED ended on their Feedback (exit 0, nothing said but a count
    of unexpected frames), or blamed the nodes for an ENABLED that was the other host's,
    and no e-stop went until the wait was over. It is ``FOREIGN_COMMAND`` there as during
    the run, with the e-stop in the tick it is heard (exit 3), in the log as well."""
    faults = tmp_path / "foreign.yaml"
    faults.write_text(COMMAND_AFTER_THE_DISABLE)
    out = tmp_path / "summary.json"
    log = tmp_path / "run.mcap"
    done = handctl(
        "run", "recipe", DEFAULT_RECIPE, "--max-seconds", "0.3", "--sim-faults", str(faults),
        "--summary-json", str(out), "--log", str(log),
    )  # fmt: skip
    assert done.returncode == 3, done.stderr
    summary = json.loads(out.read_text())
    [fault] = summary["faults"]
    assert fault["code"] == "FOREIGN_COMMAND"
    assert fault["detail"].startswith("after this run's disable, node 1 (f1): another sender")
    dump = tmp_path / "run.log"
    assert handctl("replay", str(log), "--export", "candump", str(dump)).returncode == 0
    sent = [line.split()[2] for line in dump.read_text().splitlines() if line.endswith(" T")]
    disable = max(i for i, frame in enumerate(sent) if frame.startswith("011#"))
    foreign = [
        line.split()[2]
        for line in dump.read_text().splitlines()
        if line.endswith(" R") and line.split()[2].startswith("101#")
    ]
    assert foreign  # the other host's frame is in the log
    assert [frame for frame in sent[disable:] if frame.startswith("000#")]  # and the e-stop
    replayed = handctl("replay", str(log))
    assert "FAULT FOREIGN_COMMAND" in replayed.stdout, replayed.stdout


@pytest.mark.parametrize(
    "at",
    [
        0.305,  # in the zero ticks between the stop (idle at 0.303 s) and the disable
        0.309,  # in the wait for the nodes' DISABLED, after the disable (sent at 0.308 s)
    ],
)
def test_a_node_rebooted_in_the_run_s_stop_is_said(tmp_path: Path, at: float) -> None:
    """Node 2 reboots after the time budget's stop has taken the torque out. Its counters
    restart, so its first Heartbeat after the boot is rejected as a counter skip, and the
    run ended as if nothing had happened, exit 0, "counter_skip 3" its only trace (found by
    an outside audit). The hand is safe (a node boots DISABLED), so the exit stays 0; the
    reboot is said, a warning and the summary's ``rebooted``."""
    faults = tmp_path / "reboot.yaml"
    faults.write_text(
        f"faults:\n  - {{kind: node_reboot, node: 2, downtime: 0.0, start: {at}, stop: {at}}}\n"
    )
    out = tmp_path / "summary.json"
    done = handctl(
        "run", "recipe", DEFAULT_RECIPE, "--max-seconds", "0.3",
        "--sim-faults", str(faults), "--summary-json", str(out),
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    summary = json.loads(out.read_text())
    assert summary["outcome"] == "time_budget" and summary["faults"] == []
    assert summary["sim"]["nodes"]["f2"]["reboots"] == 1
    said = summary["rebooted"]
    assert said.startswith(
        "node 2 (f2): a Heartbeat of it with its uptime gone back to 0 ms, rejected for its "
        "counter (which a reboot restarts): rebooted after the torque was armed"
    ), said
    assert f"handctl: warning: {said}" in done.stderr
