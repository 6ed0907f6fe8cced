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
    assert "the run ended as asked, but its summary lacks " in err
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
    assert "the summary itself could not be made: ForcedBugError" in said.err


def test_the_summary_in_a_failed_summary_s_place_keeps_what_a_script_reads(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """Every plain key of the run result the summary keeps is kept by the one that stands in
    for it: it lost the phases, the largest torques, and the notes a script reads to know
    whether the hand may still be enabled (found by an outside audit of the stand-in)."""
    made: list[dict[str, Any]] = []

    def made_then_raised(*args: Any, **kwargs: Any) -> None:
        made.append(real(*args, **kwargs))
        _raise()

    real = session.summarise_run
    monkeypatch.setattr(session, "summarise_run", made_then_raised)
    _, summary, _ = _run(tmp_path)
    said = capsys.readouterr()
    [whole] = made
    # what only the summary itself makes: the window's figures, the exception's place
    own = {"lateness_us", "stage_cpu_us_p99", "exception", "chatter", "asked_beyond_tau_max_nm"}
    for key in set(whole) - own:
        assert summary[key] == whole[key], key
    assert summary["phases"] and summary["max_abs_tau_nm"]
    assert "lateness p50 ? µs p99 ? µs max ? µs" in said.out
    assert "lacks the summary itself" in said.err


def test_a_jog_whose_summary_fails_is_a_failed_result_not_a_traceback(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """A bring-up run read its figures from a summary short of a part: a traceback (the
    largest torques), or exit 0 of a run whose account failed."""
    monkeypatch.setattr(session, "_host_summary", _raise)
    code = cli.main(["jog", "f1_j2", "--torque", "0.05", "--seconds", "0.2"])
    err = capsys.readouterr().err
    assert code == cli.EXIT_FAILED, err
    assert "internal error" not in err
    assert "its summary lacks the host's timing (a bug of handctl's" in err
    monkeypatch.setattr(session, "summarise_run", _raise)
    code = cli.main(["jog", "f1_j2", "--torque", "0.05", "--seconds", "0.2"])
    err = capsys.readouterr().err
    assert code == cli.EXIT_FAILED, err
    assert "internal error" not in err


def test_the_experiment_bench_raises_a_summary_short_of_a_part(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A bug in a run's account was counted by the bench as a failed manipulation, without
    a word; the bench raises it, with its traceback."""
    from handctl.config import load_hand
    from handctl.harness.seed_run import SeedRun, run_seed
    from handctl.online.recipes.loader import load_recipe
    from handctl.portable import portable_hand

    hand = load_hand(ROOT / "config/hands/hiroshima_hand.yaml")
    recipe = load_recipe(RECIPE, hand)
    monkeypatch.setattr(session, "_experiment_summary", _raise)
    with pytest.raises(RuntimeError, match="lacks the experiment's figures") as raised:
        run_seed(SeedRun(portable_hand(hand), recipe, None, "nominal", max_seconds=0.3))
    assert "ForcedBugError: forced in a part of the summary" in str(raised.value)
