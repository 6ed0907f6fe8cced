"""The paper's experiment on the simulated hand, nominal model, lockstep (deterministic): the
compiled recipe lifts both cylinders and holds them, turns the pair through its manipulation
phases on exits read from the estimator, about 45° a phase, drops nothing; the estimator
follows ground truth."""

from __future__ import annotations

import json

import numpy as np
import pytest
from mcap.reader import make_reader

from handctl.config import HandConfig
from handctl.online.recipes.loader import load_recipe
from handctl.recording import channels as ch

from ..conftest import ROOT, DefaultRun

RECIPE = ROOT / "config" / "recipes" / "swap_two_cylinders.yaml"
#: deg: the issue's target for the whole manipulation. The compiled recipe turns the pair 180°
#: on the nominal model (the cylinders trade places), so this fails on a real regression, not
#: on a degree of noise
MIN_ROTATION_DEG = 135.0


#: deg: each manipulation phase turns the pair 45° within this, as the paper's steps do; a
#: phase that turns much more is the pair tumbling past where its exit could catch it
PHASE_TURN_DEG = 45.0
PHASE_TURN_TOLERANCE_DEG = 10.0


#: deg/s: the issue's most for the true centre line's rate over the manipulation: faster is
#: the pair tumbling, which the quasi-static analysis does not cover and a real hand would
#: likely drop
MAX_PEAK_TURN_RATE_DEG_S = 180.0
#: deg: the bench's swap, the cylinders traded places (180° less a little)
SWAP_DEG = 170.0


#: N·m, the most a joint's applied torque may change from one tick to the next at p99 over
#: the nominal run: more is the chatter the soft-limit guard's damping is there to remove
MAX_TORQUE_STEP_P99 = 0.005


@pytest.fixture(scope="module")
def applied(default_run: DefaultRun) -> np.ndarray:
    """The applied torques of every tick of the session's run, read back from its log with
    the mcap library (one row per tick, in tick order)."""
    rows: dict[int, list[float]] = {}
    with default_run.log.open("rb") as handle:
        for _, _, message in make_reader(handle).iter_messages(topics=[ch.TORQUE]):
            record = json.loads(message.data)
            rows[record["tick"]] = record["applied_nm"]
    return np.array([rows[k] for k in sorted(rows)], dtype=float)


@pytest.fixture(scope="module")
def summary(default_run: DefaultRun) -> dict[str, object]:
    """The session's lockstep run of this recipe (``handctl run recipe``'s summary)."""
    assert default_run.done.returncode == 0, default_run.done.stderr
    return default_run.summary


def test_no_joint_chatters(applied: np.ndarray, hand: HandConfig) -> None:
    assert len(applied) > 5_000
    steps = np.abs(np.diff(applied, axis=0))
    p99 = np.percentile(steps, 99, axis=0)
    worst = int(np.argmax(p99))
    assert p99[worst] <= MAX_TORQUE_STEP_P99, (
        f"{hand.joint_names[worst]} changes by {p99[worst]:.4f} N·m a tick at p99"
    )


def test_no_joint_rings(summary: dict[str, object]) -> None:
    """No joint's command swings back and forth for tenths of a second (``safety.chatter``),
    which the run would say as a warning and under ``chatter``."""
    assert "chatter" not in summary, summary.get("chatter")


def test_lifted_held_turned_not_dropped(summary: dict[str, object]) -> None:
    assert summary["completed"] is True and summary["faults"] == []
    ex = summary["experiment"]
    assert isinstance(ex, dict)
    assert ex["lifted"] is True and ex["held_s"] >= 2.0
    assert ex["dropped"] is False
    assert len(ex["phase_angles_deg"]) == 4
    assert ex["total_rotation_deg"] >= MIN_ROTATION_DEG
    assert ex["total_rotation_deg"] == pytest.approx(abs(sum(ex["phase_angles_deg"])), abs=0.05)


def test_each_manipulation_phase_turns_about_45_deg(summary: dict[str, object]) -> None:
    ex = summary["experiment"]
    assert isinstance(ex, dict)
    for k, angle in enumerate(ex["phase_angles_deg"], 1):
        assert abs(abs(angle) - PHASE_TURN_DEG) <= PHASE_TURN_TOLERANCE_DEG, (
            f"manipulate_{k} turned {angle}°: {ex['phase_angles_deg']}"
        )


def test_the_pair_is_turned_not_tumbled(summary: dict[str, object]) -> None:
    ex = summary["experiment"]
    assert isinstance(ex, dict)
    assert 0.0 < ex["peak_turn_rate_deg_s"] <= MAX_PEAK_TURN_RATE_DEG_S, ex["phase_angles_deg"]


def test_the_pair_is_swapped(summary: dict[str, object]) -> None:
    ex = summary["experiment"]
    assert isinstance(ex, dict)
    assert ex["total_rotation_deg"] >= SWAP_DEG, ex["phase_angles_deg"]


#: the manipulation phase in which the pair stands across the palm, where the estimator
#: cannot place it (docs/experiment.md, "What is still fragile")
ACROSS_THE_PALM = "manipulate_3"


def test_the_estimator_follows_ground_truth(summary: dict[str, object]) -> None:
    ex = summary["experiment"]
    assert isinstance(ex, dict)
    # over hold and manipulation (the objects settle, loosely caged, after the lift) ...
    assert ex["estimator_error_deg"] is not None and ex["estimator_error_deg"] < 12.0
    # ... and where the exits read it, phase by phase: a brief phase's error is not hidden
    # among the others' ticks
    by_phase = ex["estimator_error_by_phase_deg"]
    assert isinstance(by_phase, dict) and len(by_phase) == 4
    for name, error in by_phase.items():
        if name != ACROSS_THE_PALM:
            assert error is not None and error < 3.0, by_phase
    assert ex["estimator_valid_fraction"] > 0.9


@pytest.mark.xfail(
    strict=True,
    reason="in manipulate_3 the pair stands across the palm, cylinder 1 squeezed between the "
    "palm and cylinder 2: its place along the palm then follows cylinder 2's depth with a "
    "gain of cot(angle from the palm's normal), 4 at 15 deg and 11 at 5 deg, so a millimetre "
    "of slack in cylinder 2's cage moves the estimated centre line by 10..16 deg while the "
    "estimate stays valid (docs/experiment.md)",
)
def test_the_estimator_places_the_pair_standing_across_the_palm(
    summary: dict[str, object],
) -> None:
    ex = summary["experiment"]
    assert isinstance(ex, dict)
    error = ex["estimator_error_by_phase_deg"][ACROSS_THE_PALM]
    assert error is not None and error < 3.0


def test_the_compiled_recipe_is_planned_for_this_hand(hand: HandConfig) -> None:
    recipe = load_recipe(RECIPE, hand)
    assert recipe.compiled and recipe.hand_config_hash == hand.config_hash
    assert all("chosen_from" in p.provenance for p in recipe.phases)
    turns = [p for p in recipe.phases if p.name.startswith("manipulate")]
    assert len(turns) == 4
    assert all(c.text.startswith("estimate.cyl1_cyl2_line_turn") for p in turns for c in p.exits)


def test_run_recipe_plot_writes_the_overview(default_run: DefaultRun) -> None:
    """``--plot`` on the session's run."""
    done = default_run.done
    assert done.returncode == 0, done.stderr
    assert default_run.plot.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert "experiment" in default_run.summary
    assert "experiment: lifted True" in done.stdout
