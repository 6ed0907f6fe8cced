"""A command whose stdout or stderr was closed, or cannot be written, or whose environment names
a matplotlib backend, still does its work: the log, the summary and the plot are written and
the exit code is the run's own."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path
from typing import IO

import pytest

from handctl.recording.reader import open_recording

from ..conftest import ROOT

RECIPE = str(ROOT / "config" / "recipes" / "swap_two_cylinders.yaml")


def _run(
    tmp_path: Path,
    stdout: IO[str] | int,
    close_stdout: bool = False,
    outputs: tuple[str, ...] = (),
) -> subprocess.CompletedProcess[str]:
    """A short run with stdout as given; its log and summary in ``tmp_path`` unless
    ``outputs`` names them."""
    outputs = outputs or (
        *("--log", str(tmp_path / "run.mcap")),
        *("--summary-json", str(tmp_path / "s.json")),
    )
    return subprocess.run(
        [
            *(sys.executable, "-m", "handctl", "run", "recipe", RECIPE, "--max-seconds", "0.3"),
            *outputs,
        ],
        cwd=ROOT,
        text=True,
        timeout=300,
        check=False,
        stdout=stdout,
        stderr=subprocess.PIPE,
        preexec_fn=(lambda: os.close(1)) if close_stdout else None,
    )


def _a_whole_log(path: Path) -> None:
    recording = open_recording(path)
    assert recording.complete, recording.problem
    assert recording.message_counts["/hand/joint_state"] > 100


def test_with_stdout_closed_the_log_and_the_summary_are_written(tmp_path: Path) -> None:
    """The log took descriptor 1 and ended up empty (0 bytes), no summary, exit 120."""
    result = _run(tmp_path, subprocess.PIPE, close_stdout=True)
    assert result.returncode == 0, result.stderr
    assert "Traceback" not in result.stderr
    assert (tmp_path / "s.json").stat().st_size > 0
    _a_whole_log(tmp_path / "run.mcap")


@pytest.mark.skipif(not Path("/dev/full").exists(), reason="no /dev/full here")
def test_a_stdout_that_cannot_be_written_is_said_and_the_exit_is_the_runs(tmp_path: Path) -> None:
    with open("/dev/full", "w") as full:
        result = _run(tmp_path, full)
    assert result.returncode == 0, result.stderr
    assert "warning: stdout cannot be written (No space left on device)" in result.stderr
    assert "Traceback" not in result.stderr
    _a_whole_log(tmp_path / "run.mcap")


def test_a_matplotlib_backend_it_does_not_know_does_not_stop_the_plot(tmp_path: Path) -> None:
    """handctl's plots are files on an Agg canvas: MPLBACKEND=nonsense made matplotlib's
    import raise after the run, and its summary was never printed."""
    result = subprocess.run(
        [
            *(sys.executable, "-m", "handctl", "run", "recipe", RECIPE, "--max-seconds", "0.3"),
            *("--plot", str(tmp_path / "run.png")),
        ],
        cwd=ROOT,
        text=True,
        capture_output=True,
        timeout=300,
        check=False,
        env={**os.environ, "MPLBACKEND": "nonsense"},
    )
    assert result.returncode == 0, result.stderr
    assert f"overview plot: {tmp_path / 'run.png'}" in result.stdout
    assert (tmp_path / "run.png").stat().st_size > 0


@pytest.mark.parametrize("encoding", ["ascii", "latin-1"])
def test_an_output_encoding_without_the_units_characters_still_gets_the_summary(
    tmp_path: Path, encoding: str
) -> None:
    """``N·m`` and ``τ`` have no code in ASCII (``LANG=C``) and ``τ`` none in Latin-1: the
    summary's print raised ``UnicodeEncodeError`` after the run, exit 1 with a traceback and
    no ``--summary-json``. Now such a character is written as its escape."""
    result = subprocess.run(
        [
            *(sys.executable, "-m", "handctl", "run", "recipe", RECIPE, "--max-seconds", "0.3"),
            *("--summary-json", str(tmp_path / "s.json")),
        ],
        cwd=ROOT,
        capture_output=True,
        timeout=300,
        check=False,
        env={**os.environ, "PYTHONIOENCODING": encoding},
    )
    stderr = result.stderr.decode(encoding)
    assert result.returncode == 0, stderr
    assert "Traceback" not in stderr
    assert (tmp_path / "s.json").stat().st_size > 0
    # '·' is in Latin-1 and written as itself; ASCII has it as its escape
    assert ("N·m" if encoding == "latin-1" else "N\\xb7m") in result.stdout.decode(encoding)


def test_an_output_that_is_the_commands_own_stdout_is_refused(tmp_path: Path) -> None:
    """``--log /dev/stdout > run.mcap``: the summary printed over the log's start, and the
    run said it had recorded every tick, exit 0; the log did not open."""
    out = tmp_path / "run.mcap"
    with out.open("w") as stdout:
        result = _run(tmp_path, stdout, outputs=("--log", "/dev/stdout"))
    assert result.returncode == 2, result.stderr
    assert result.stderr.startswith(
        "handctl: error: --log: expected a file other than this command's standard output"
    ), result.stderr
    assert out.stat().st_size == 0  # nothing ran, nothing printed into it


def test_a_run_without_the_experiment_says_where_its_plot_went(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A recipe of no objects (a bring-up hold) has no experiment summary: its plot was
    written, and the run did not say where (found by an outside audit)."""
    from handctl import cli

    from .rig import CLOSE_AND_HOLD_1S

    recipe = tmp_path / "hold.yaml"
    recipe.write_text(CLOSE_AND_HOLD_1S)
    plot = tmp_path / "hold.png"
    assert cli.main(["run", "recipe", str(recipe), "--plot", str(plot)]) == cli.EXIT_OK
    out = capsys.readouterr().out
    assert "experiment:" not in out
    assert f"  overview plot: {plot}" in out and plot.stat().st_size > 0


def test_a_json_output_that_is_the_commands_own_stdout_on_a_pipe_is_said_so(
    tmp_path: Path,
) -> None:
    """``calibrate tdt -o x.yaml --json /dev/stdout | cat``: /dev/stdout on a pipe resolves
    to no file of any directory, and was refused as a file in a read-only directory, not as
    the command's own standard output (found by an outside audit). Refused before it runs."""
    result = subprocess.run(
        [
            *(sys.executable, "-m", "handctl", "calibrate", "tdt"),
            *("-o", str(tmp_path / "x.yaml"), "--json", "/dev/stdout"),
        ],
        cwd=ROOT,
        text=True,
        timeout=300,
        check=False,
        capture_output=True,
    )
    assert result.returncode == 2, result.stderr
    assert result.stderr.startswith(
        "handctl: error: --json: expected a file other than this command's standard output"
    ), result.stderr
    assert result.stdout == ""
