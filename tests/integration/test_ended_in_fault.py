"""A node that latches FAULT after a run's stop has taken the torque out, before the disable:
the hand is safe, but the next run is refused until ``--reset-node-faults``. The run said
nothing of it (exit 0, "success"); it is said now, a warning and the summary's
``ended_in_fault``. On the simulated hand, in lockstep: its ticks are the run's."""

from __future__ import annotations

import json
from pathlib import Path

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
    # without the e-stop, nothing is said
    done = handctl(
        "run", "recipe", DEFAULT_RECIPE, "--max-seconds", "0.3", "--summary-json", str(out)
    )
    assert done.returncode == 0, done.stderr
    assert "ended_in_fault" not in json.loads(out.read_text())
