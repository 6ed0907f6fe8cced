"""A log whose disk fills during a run: the run goes on under the supervisor as before, the
warning says why the recording stopped and what the file holds, and the file reads up to
where the writer stopped. The disk is a 3 MiB tmpfs, a third of the default run's log; it
needs the right to mount one (root, as CI runs here), and is skipped, saying so, without."""

from __future__ import annotations

import os
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

from ..conftest import DEFAULT_RECIPE, ROOT, handctl


@pytest.fixture
def small_disk(tmp_path: Path) -> Iterator[Path]:
    yield from _tmpfs(tmp_path, "3m")


@pytest.fixture
def tiny_disk(tmp_path: Path) -> Iterator[Path]:
    """A disk too small for a log's start: its header and set-up records."""
    yield from _tmpfs(tmp_path, "16k")


def _tmpfs(tmp_path: Path, size: str) -> Iterator[Path]:
    mount = tmp_path / "disk"
    mount.mkdir()
    made = subprocess.run(
        ["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(mount)],
        capture_output=True,
        text=True,
        check=False,
    )
    if made.returncode != 0:
        pytest.skip(f"cannot mount a small tmpfs here: {made.stderr.strip() or made.returncode}")
    try:
        yield mount
    finally:
        subprocess.run(["umount", str(mount)], check=False)


def test_a_log_whose_disk_fills_says_why_and_reads_up_to_there(small_disk: Path) -> None:
    log = small_disk / "run.mcap"
    done = handctl("run", "recipe", DEFAULT_RECIPE, "--log", str(log))
    # the run stopped once its writer had ended (RECORDING_LOST, a ramp stop): it went on
    # driving the hand unrecorded to its end before; its log is incomplete
    assert done.returncode == 3, done.stdout + done.stderr
    assert "Traceback" not in done.stderr
    assert "RECORDING_LOST" in done.stderr
    assert done.stderr.strip().splitlines()[-1] == (
        f"handctl: and the run's log {log} is lost or may be incomplete (the warning above "
        "says why)"
    )
    warning = next(line for line in done.stderr.splitlines() if str(log) in line)
    assert (
        "the recording writer is gone, and the run's summary is not in it (OSError: [Errno 28] "
        "No space left on device)"
    ) in warning
    assert "the file ends where the writer stopped" in warning
    assert log.stat().st_size > 1 << 20
    replay = handctl("replay", str(log))
    assert replay.returncode == 0, replay.stdout + replay.stderr
    assert "TRUNCATED" in replay.stdout
    # its re-run repeats what the log holds, but the run's fault and stop ramp are not in
    # it: not the whole log (it said "verified", exit 0, "outcome log ended")
    rerun = handctl("replay", str(log), "--rerun")
    assert rerun.returncode == 1, rerun.stdout + rerun.stderr
    assert "bit-exact" in rerun.stdout
    assert "rerun: FAILED: not the whole log: it is TRUNCATED" in rerun.stderr


def test_a_plot_whose_recording_fills_the_disk_is_a_failed_result(
    small_disk: Path, tmp_path: Path
) -> None:
    """``--plot`` without ``--log`` draws from a recording of the run's own in the temporary
    directory; when that recording fails the plot is not written, which said a warning and
    exit 0: a file the run was told to write and did not is a failed result."""
    plot = tmp_path / "run.png"
    done = handctl(
        "run", "recipe", DEFAULT_RECIPE, "--plot", str(plot), env={"TMPDIR": str(small_disk)}
    )
    assert done.returncode == 1, done.stdout + done.stderr
    assert "Traceback" not in done.stderr
    assert "no plot written: the run's recording failed" in done.stderr
    assert done.stderr.strip().splitlines()[-1] == (
        f"handctl: failed: the run ended as asked, but no plot was written to {plot} (the "
        "run's recording failed: the warning above says why)"
    )
    assert not plot.exists() and "overview plot" not in done.stdout


def test_rings_the_host_will_not_give_are_an_error_before_the_run(tmp_path: Path) -> None:
    """A file-size limit (``ulimit -f``) below the recording's rings, which are a memory
    file: a traceback before; now the error says what and how much, and nothing was sent."""
    path = os.pathsep.join(p for p in (str(ROOT), os.environ.get("PYTHONPATH", "")) if p)
    done = subprocess.run(
        [
            "bash",
            "-c",
            'ulimit -f 1024 && exec "$0" -m handctl run recipe "$1" --log "$2"',
            sys.executable,
            DEFAULT_RECIPE,
            str(tmp_path / "run.mcap"),
        ],
        cwd=ROOT,
        env={**os.environ, "PYTHONPATH": path},
        capture_output=True,
        text=True,
        timeout=600,
        check=False,
    )
    assert done.returncode == 1, done.stdout + done.stderr
    assert "Traceback" not in done.stderr
    assert "the recording's rings (" in done.stderr and "could not be made" in done.stderr
    assert "nothing was sent" in done.stderr


def test_a_log_whose_disk_is_full_at_the_start_says_why(tiny_disk: Path) -> None:
    """A disk that fills as the log starts: the run said "the recording writer is gone" and
    no more (an outside probe, 3 runs in 3). It says the writer's own last word, the
    system's error; nothing was sent. The same words whether the writer went while its
    set-up was sent or just after it (a race)."""
    log = tiny_disk / "run.mcap"
    done = handctl("run", "recipe", DEFAULT_RECIPE, "--log", str(log), "--max-seconds", "0.5")
    assert done.returncode == 1, done.stderr
    assert (
        f"handctl: error: {log}: the recording writer did not start: OSError: [Errno 28] No "
        "space left on device; nothing was sent"
    ) in done.stderr
