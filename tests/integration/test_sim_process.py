"""The simulated hand as a process of its own (real-time runs): its output cannot stall it,
and a hand that dies is reported with what it said."""

from __future__ import annotations

import signal
import time
from collections.abc import Callable
from pathlib import Path

import pytest

from handctl import session
from handctl.config import HandConfig
from handctl.online.recipes.loader import load_recipe
from handctl.session import RunRequest, SimProcess

from ..conftest import ROOT


def _request(hand: HandConfig) -> RunRequest:
    recipe = load_recipe(ROOT / "config" / "recipes" / "swap_two_cylinders.yaml", hand)
    return RunRequest(hand=hand, recipe=recipe)


def _wait_for(condition: Callable[[], bool], timeout_s: float = 60.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not condition():
        assert time.monotonic() < deadline, "timed out"
        time.sleep(0.05)


def test_its_progress_goes_to_a_log_file_not_an_unread_pipe(
    hand: HandConfig, tmp_path: Path
) -> None:
    """A pipe nobody reads fills after some ten minutes of progress lines and then blocks the
    hand mid-run; a file never does."""
    with SimProcess(_request(hand), str(tmp_path)) as sim:
        assert sim.proc.stderr is None
        _wait_for(lambda: sim.log_path.exists() and "t=" in sim.log_path.read_text())
        summary = sim.finish()
    assert summary is not None
    assert sim.problem() == ""


def test_a_hand_that_dies_is_reported_with_the_end_of_its_log(
    hand: HandConfig, tmp_path: Path
) -> None:
    with SimProcess(_request(hand), str(tmp_path)) as sim:
        _wait_for(lambda: sim.log_path.exists() and "t=" in sim.log_path.read_text())
        sim.proc.send_signal(signal.SIGKILL)
        sim.proc.wait()
        assert sim.finish() is None
    problem = sim.problem()
    assert f"exit {-signal.SIGKILL}" in problem and "no summary" in problem
    assert "t=" in problem  # the last progress line it wrote


def test_it_stops_on_sigint_even_when_started_with_sigint_ignored(
    hand: HandConfig, tmp_path: Path
) -> None:
    """A host started as a background job of a script has SIGINT ignored, and its children
    inherit that; the host stops its hand with SIGINT, so the hand must listen anyway (else it
    is killed after 10 s and its summary is lost)."""
    before = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        sim = SimProcess(_request(hand), str(tmp_path))
    finally:
        signal.signal(signal.SIGINT, before)
    with sim:
        _wait_for(lambda: sim.log_path.exists() and "t=" in sim.log_path.read_text())
        summary = sim.finish()
    assert sim.proc.returncode == 0, "it did not stop on SIGINT: it was killed"
    assert summary is not None
    assert sim.problem() == ""


def test_a_hand_that_does_not_end_on_sigint_is_said_as_killed_by_the_host(
    hand: HandConfig, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A stopped hand (SIGSTOP) was killed after the wait and then said as "ended with exit
    -9", which reads as the hand's own crash (found by an outside audit)."""
    monkeypatch.setattr(session, "SIM_FINISH_S", 0.5)
    with SimProcess(_request(hand), str(tmp_path)) as sim:
        _wait_for(lambda: sim.log_path.exists() and "t=" in sim.log_path.read_text())
        sim.proc.send_signal(signal.SIGSTOP)
        assert sim.finish() is None
    assert sim.proc.returncode == -signal.SIGKILL
    problem = sim.problem()
    assert problem.startswith(
        "the simulated hand's process did not end within 0.5 s of SIGINT (stopped or hung?) "
        "and was killed (SIGKILL), with no summary"
    )
    assert "exit -9" not in problem
