"""A recording writer that ends while its run goes on (killed, out of memory, a crash): the
run went on driving the hand unrecorded to its end, minutes on a whole recipe, and said so
only then (found by an outside audit). It is a ramp stop now, RECORDING_LOST, within a
tenth of a second (``session._WriterWatch``)."""

from __future__ import annotations

import json
import os
import pty
import signal
import subprocess
import sys
from pathlib import Path

import psutil

from handctl import cli

from ..conftest import ROOT
from .rig import HOLD_LONG, read_until


def test_a_run_whose_writer_ends_is_stopped_and_says_why(tmp_path: Path) -> None:
    recipe = tmp_path / "hold.yaml"
    recipe.write_text(HOLD_LONG)
    log, out = tmp_path / "run.mcap", tmp_path / "out.json"
    terminal, stderr_end = pty.openpty()
    command = [sys.executable, "-m", "handctl", "run", "recipe", str(recipe), "--log", str(log)]
    proc = subprocess.Popen(
        [*command, "--summary-json", str(out), "--max-seconds", "300"],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=stderr_end,
        text=True,
    )
    os.close(stderr_end)
    try:
        shown = read_until(terminal, "running")  # the hold is under way, torque on
        assert "running" in shown, shown
        writers = [
            p
            for p in psutil.Process(proc.pid).children(recursive=True)
            if "handctl.recording.writer" in " ".join(p.cmdline())
        ]
        assert len(writers) == 1, writers
        writers[0].send_signal(signal.SIGKILL)
        proc.communicate(timeout=120)
        stderr = shown + read_until(terminal, None, timeout_s=10.0)
    finally:
        proc.kill()
        os.close(terminal)
    assert proc.returncode == cli.EXIT_SAFETY_STOP, stderr
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
