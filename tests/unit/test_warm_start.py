"""The suite's warm start (``tests/warm_start.py``) gives what a cold ``python -m handctl``
gives: its output, its exit, its working directory and environment; and it is left for a
cold start where it cannot be the same."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from ..conftest import ROOT, _warm_start, handctl
from ..warm_start import WarmStart


def _both(*args: str, cwd: Path = ROOT) -> tuple[subprocess.CompletedProcess[str], ...]:
    warm = handctl(*args, cwd=cwd)
    os.environ["HANDCTL_TESTS_COLD"] = "1"
    try:
        cold = handctl(*args, cwd=cwd)
    finally:
        del os.environ["HANDCTL_TESTS_COLD"]
    return warm, cold


@pytest.mark.parametrize(
    "args",
    [
        ("--version",),
        ("check", "no-such-hand.yaml"),
        ("run", "recipe", "config/recipes/swap_two_cylinders.yaml", "--max-seconds", "-1"),
    ],
)
def test_a_warm_command_says_and_exits_as_a_cold_one(args: tuple[str, ...]) -> None:
    warm, cold = _both(*args)
    assert (warm.returncode, warm.stdout, warm.stderr) == (
        cold.returncode,
        cold.stdout,
        cold.stderr,
    )


def test_a_warm_command_runs_in_its_own_directory_and_environment(tmp_path: Path) -> None:
    """A relative path is read from the command's directory; HANDCTL_TIMING_INJECT, read as
    the command runs, is the command's."""
    (tmp_path / "hand.yaml").write_text("not: [a, hand\n")
    warm, cold = _both("check", "hand.yaml", cwd=tmp_path)
    assert warm.returncode == cold.returncode == 2
    assert warm.stderr == cold.stderr and "hand.yaml" in warm.stderr
    missing = tmp_path / "no-such-probe.json"
    done = handctl("check", "--timing", env={"HANDCTL_TIMING_INJECT": str(missing)})
    assert done.returncode != 0 and str(missing) in done.stderr


def test_an_environment_read_as_python_starts_is_a_cold_start() -> None:
    warm = _warm_start({**os.environ, "PYTHONPATH": str(ROOT)})
    assert warm.takes({**warm.env, "HANDCTL_X": "1"})
    assert not warm.takes({**warm.env, "PYTHONHASHSEED": "7"})
    assert not warm.takes({**warm.env, "LC_ALL": "C"})
    # what handctl's command line sets or drops itself, as an in-process ``cli.main`` of a
    # test does in the worker's environment: no reason for a cold start
    assert warm.takes({**warm.env, "MUJOCO_GL": "disable"})
    assert warm.takes({k: v for k, v in warm.env.items() if k != "MPLBACKEND"})
    without = {k: v for k, v in warm.env.items() if k != "PATH"}
    assert warm.takes(without)


def test_a_command_past_its_timeout_is_killed_and_said_so(tmp_path: Path) -> None:
    """As ``subprocess.run`` does: ``TimeoutExpired``, and the command gone."""
    with pytest.raises(subprocess.TimeoutExpired):
        handctl("sim", "--bus", f"unix:{tmp_path / 'bus'}", timeout=3)


def test_a_backend_matplotlib_does_not_know_does_not_end_the_server(tmp_path: Path) -> None:
    """The server imports matplotlib as it starts; a worker's MPLBACKEND of a backend
    matplotlib does not know would end it there (the suite then failed at its first command),
    where every command drops it (``handctl.cli.main``)."""
    env = {**os.environ, "PYTHONPATH": str(ROOT), "MPLBACKEND": "no-such-backend"}
    server = WarmStart(ROOT, env)
    try:
        argv = [sys.executable, "-m", "handctl", "--version"]
        warm = server.run(argv, tmp_path, env, timeout=120)
        cold = subprocess.run(
            argv, cwd=tmp_path, env=env, capture_output=True, text=True, check=False, timeout=120
        )
    finally:
        server.close()
    assert warm.returncode == cold.returncode == 0, warm.stderr + cold.stderr
    assert warm.stdout == cold.stdout
