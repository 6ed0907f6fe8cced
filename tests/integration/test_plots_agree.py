"""The run summary, the replay summary and both plots of one run of the default recipe say the
same thing (``handctl.convention``): phase times, the turn's sign and size, heights above
rest. Real processes, as a user runs them."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from ..conftest import DefaultRun, handctl


def test_run_and_replay_agree(default_run: DefaultRun, tmp_path: Path) -> None:
    """The session's run of the default recipe (its summary, log and plot), replayed here."""
    replay_json = tmp_path / "replay.json"
    assert default_run.done.returncode == 0, default_run.done.stderr
    rep = handctl(
        "replay",
        str(default_run.log),
        "--json",
        str(replay_json),
        "--plot",
        str(tmp_path / "replay.png"),
        cwd=tmp_path,
    )
    assert rep.returncode == 0, rep.stderr
    ran = default_run.summary
    replayed = json.loads(replay_json.read_text())["summary"]
    # phase times: the same clock, to the tick
    run_phases = [(p["name"], p["start_s"]) for p in ran["phases"]]
    # (the replay also lists the end ramp, which the run's recipe runner does not)
    replay_phases = [
        (p["name"], p["start_s"]) for p in replayed["phases"] if p["name"] != "end_ramp"
    ]
    assert [n for n, _ in replay_phases] == [n for n, _ in run_phases]
    for (_, a), (_, b) in zip(run_phases, replay_phases, strict=True):
        assert b == pytest.approx(a, abs=1e-6)
    # the turn: signed the same way; the log samples poses every 10 ticks, the run every tick
    ex = ran["experiment"]
    assert abs(ex["turn_deg"]) == pytest.approx(ex["total_rotation_deg"])
    assert abs(ex["turn_deg"]) > 90, ex
    assert replayed["turn_deg"] == pytest.approx(ex["turn_deg"], abs=1.0)
    assert replayed["phase_turns_deg"] == pytest.approx(ex["phase_angles_deg"], abs=1.0)
    # heights above rest, as the run measures lifting: 0 where they rested at the start
    for pose in replayed["objects"].values():
        assert pose["start"]["height_above_rest_m"] == pytest.approx(0.0, abs=2e-3)
    # and where the objects ended, at the last pose the log carries: the run's summary took
    # its every-tick trace's last, up to 9 ticks later in the end ramp, where the objects
    # still move (cyl1 4.34604 rad against the replay's 4.30196, 1.3 mm apart)
    assert {n: o["end"] for n, o in replayed["objects"].items()} == {
        n: o["final"] for n, o in ex["objects"].items()
    }
    assert default_run.plot.stat().st_size > 10_000
    assert (tmp_path / "replay.png").stat().st_size > 10_000
    # the two plots are one picture: the same panels, traces, legends and title, pixel for pixel
    from matplotlib.image import imread

    run_pixels, replay_pixels = imread(default_run.plot), imread(tmp_path / "replay.png")
    assert run_pixels.shape == replay_pixels.shape
    assert np.array_equal(run_pixels, replay_pixels)


def test_the_plot_draws_the_estimated_turn_beside_the_true_one(default_run: DefaultRun) -> None:
    """The estimator, run again on the logged angles, follows the true turn as the run's
    summary says it did (its p95 error), sampled where the log has poses."""
    from handctl.recording.plot import turns_deg
    from handctl.recording.reader import open_recording
    from handctl.recording.series import load_series

    recording = open_recording(default_run.log)
    turns = turns_deg(load_series(recording), recording)
    assert list(turns) == ["cyl1/cyl2 true (simulation)", "cyl1/cyl2 estimated (joint angles)"]
    (t_true, true), (t_est, estimated) = turns.values()
    assert np.array_equal(t_true, t_est)
    valid = np.isfinite(estimated)
    assert valid.sum() > 0.5 * len(estimated)  # the estimate is valid once the cage closes
    error = np.abs(estimated[valid] - true[valid])
    p95 = default_run.summary["experiment"]["estimator_error_deg"]
    assert float(np.percentile(error, 95)) <= p95 + 1.0, (np.percentile(error, 95), p95)
