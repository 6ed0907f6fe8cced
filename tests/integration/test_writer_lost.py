"""A recording writer that ends while its run goes on (killed, out of memory, a crash): the
run went on driving the hand unrecorded to its end, minutes on a whole recipe, and said so
only then (found by an outside audit). It is a ramp stop now, RECORDING_LOST, within a
tenth of a second (``session._WriterWatch``)."""

from __future__ import annotations

import json
import signal
import subprocess
from pathlib import Path

import psutil

from handctl import cli

from .rig import stopped_while_holding


def kill_the_writer(run: subprocess.Popen[str]) -> None:
    """SIGKILL to the run's recording writer alone, its control process left running."""
    writers = [
        p
        for p in psutil.Process(run.pid).children(recursive=True)
        if "handctl.recording.writer" in " ".join(p.cmdline())
    ]
    assert len(writers) == 1, writers
    writers[0].send_signal(signal.SIGKILL)


def test_a_run_whose_writer_ends_is_stopped_and_says_why(tmp_path: Path) -> None:
    log, out = tmp_path / "run.mcap", tmp_path / "out.json"
    options = ["--log", str(log), "--summary-json", str(out), "--max-seconds", "300"]
    code, _, stderr = stopped_while_holding(tmp_path, options, kill_the_writer)
    assert code == cli.EXIT_SAFETY_STOP, stderr
    summary = json.loads(out.read_text())
    assert summary["outcome"] == "safety_stop"
    first = summary["faults"][0]
    assert first["code"] == "RECORDING_LOST", summary["faults"]
    assert first["detail"] == (
        f"{log}: the recording writer ended (signal 9); the run was stopped rather than drive "
        "the hand unrecorded"
    )
    assert summary["ticks"] < 300_000  # stopped, not run to its budget
    assert "RECORDING_LOST" in stderr
