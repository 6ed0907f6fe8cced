"""The simulated hand as a process of its own (real-time runs): its output cannot stall it,
and a hand that dies is reported with what it said."""

from __future__ import annotations

import signal
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

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


#: ``sitecustomize`` of the simulated hand's process: it holds the hand at the first import
#: of MuJoCo (``handctl sim``'s signals already its own, before it listens), after saying so
#: in the file HANDCTL_TEST_HOLD names, until a signal ends it.
HOLD_BEFORE_LISTENING = """
import os, sys, time

held = os.environ.pop("HANDCTL_TEST_HOLD", "")
if held:

    class Hold:
        def find_spec(self, fullname, path=None, target=None):
            if fullname == "mujoco":
                sys.meta_path.remove(self)
                open(held, "w").close()
                while True:
                    time.sleep(1)
            return None

    sys.meta_path.insert(0, Hold())
"""


def test_a_run_stopped_before_its_hand_listens_does_not_blame_the_hand(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """A SIGTERM to a real-time run once its simulated hand was started, before the first
    tick: the host stops the hand with its SIGINT, the hand ends with exit 130 as it does
    before it listens, and that was said as the hand's failure ("warning: the simulated
    hand's process ended with exit 130 and no summary: handctl: interrupted") over the run's
    own "stopped: signal SIGTERM during start-up" (found by an outside audit). The hand is
    held where it does not listen yet, and the signal comes as the runtime begins."""
    import os

    from handctl import cli
    from handctl.online.loop import Runtime

    from ..conftest import DEFAULT_RECIPE

    (tmp_path / "sitecustomize.py").write_text(HOLD_BEFORE_LISTENING)
    held = tmp_path / "held"
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join(str(p) for p in (ROOT, tmp_path)))
    monkeypatch.setenv("HANDCTL_TEST_HOLD", str(held))
    original = Runtime.run

    async def signalled(self: Runtime) -> Any:
        _wait_for(held.exists)
        signal.raise_signal(signal.SIGTERM)
        return await original(self)

    monkeypatch.setattr(Runtime, "run", signalled)
    args = ["run", "recipe", str(ROOT / DEFAULT_RECIPE), "--realtime", "--max-seconds", "5"]
    code = cli.main(args)
    err = capsys.readouterr().err
    assert code == cli.EXIT_INTERRUPTED, err
    assert "stopped: signal SIGTERM during start-up, no node enabled" in err, err
    assert "simulated hand" not in err, err


def test_a_hand_ended_by_a_signal_of_its_own_is_still_said_when_the_host_stops_it(
    hand: HandConfig, tmp_path: Path
) -> None:
    """A listening hand given SIGTERM directly writes its summary and waits for its host;
    the host's SIGINT then ends it with 130. That is no stop of the host's before the hand
    listened (which is not said): the hand stopped by itself, and is said."""
    with SimProcess(_request(hand), str(tmp_path)) as sim:
        _wait_for(lambda: sim.log_path.exists() and "t=" in sim.log_path.read_text())
        sim.proc.send_signal(signal.SIGTERM)
        _wait_for(sim.summary_path.exists)
        summary = sim.finish()
    assert summary is not None
    problem = sim.problem()
    assert problem.startswith("the simulated hand's process"), problem
