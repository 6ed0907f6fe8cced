"""A bug of handctl's in the account made after a run's hand has stopped (here forced into one
part of it) loses nothing else: the outcome, the summary file and the log's summary are
made, the part is said with its traceback, and the run exits 1 unless its own code says more.
It was a traceback, exit 1, no summary file, and a log of "no summary"."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest

from handctl import cli, session
from handctl.recording import channels as ch
from handctl.recording.reader import open_recording

from ..conftest import ROOT

RECIPE = ROOT / "config/recipes/swap_two_cylinders.yaml"


class ForcedBugError(ZeroDivisionError):
    """What the forced part raises: a bug's kind of exception."""


def _raise(*_: object, **__: object) -> None:
    raise ForcedBugError("forced in a part of the summary")


def _run(tmp_path: Path) -> tuple[int, dict[str, Any], dict[str, Any]]:
    log, out = tmp_path / "run.mcap", tmp_path / "summary.json"
    argv = ["run", "recipe", str(RECIPE), "--max-seconds", "0.3"]
    code = cli.main([*argv, "--log", str(log), "--summary-json", str(out)])
    logged = open_recording(log).json_meta(ch.META_SUMMARY) or {}
    return code, json.loads(out.read_text()), logged


@pytest.mark.parametrize("part", ["_experiment_summary", "_host_summary", "_peer_summary"])
def test_a_part_of_the_summary_that_fails_loses_nothing_else(
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
    part: str,
) -> None:
    monkeypatch.setattr(session, part, _raise)
    code, summary, logged = _run(tmp_path)
    err = capsys.readouterr().err
    assert code == cli.EXIT_FAILED
    assert summary["outcome"] == logged["outcome"] == "time_budget"
    assert summary["ticks"] == logged["ticks"] and summary["ticks"] > 0
    [error] = summary["summary_errors"]
    assert error["error"] == "ForcedBugError: forced in a part of the summary"
    assert "in _raise" in error["traceback"]
    assert logged["summary_errors"] == summary["summary_errors"]
    assert "could not be made: ForcedBugError: forced in a part of the summary" in err
    assert "the run ended as asked, but its summary lacks what could not be made" in err
    assert "internal error" not in err


def test_a_summary_that_cannot_be_made_is_replaced_by_what_the_run_holds(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.setattr(session, "summarise_run", _raise)
    code, summary, logged = _run(tmp_path)
    said = capsys.readouterr()
    assert code == cli.EXIT_FAILED
    assert summary["outcome"] == logged["outcome"] == "time_budget"
    assert summary["message"] == "time budget of 0.3 s reached"
    assert summary["hand"] == "hiroshima_hand" and summary["ticks"] > 0
    assert [e["part"] for e in summary["summary_errors"]] == ["summary"]
    assert "sim" in summary  # the simulated hand's account was made on its own
    assert "recipe swap_two_cylinders on hiroshima_hand (lockstep): time_budget" in said.out
    assert "the run's summary could not be made: ForcedBugError" in said.err
