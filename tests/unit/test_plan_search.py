"""The plan's scores: a manipulation phase that tumbles to its exit ranks below one that turns
at the pace the analysis covers."""

from __future__ import annotations

import dataclasses
import math

from handctl.planning.episode import PhaseOutcome
from handctl.planning.search import (
    MAX_TURN_RATE_DEG_S,
    TUMBLE_FAIL_FACTOR,
    Candidate,
    turn_scorer,
)

TARGET_RAD = -0.785398  # -45 deg


def outcome(exit: str, turn_deg: float, peak: float, duration_s: float = 1.0) -> PhaseOutcome:
    return PhaseOutcome(
        exit=exit,
        duration_s=duration_s,
        true_turn_deg=turn_deg,
        est_turn_deg=turn_deg,
        min_height=0.02,
        end_height=0.02,
        limit_margin=1.0,
        pair_gap=0.0,
        pair_blocked=False,
        in_hand=True,
        est_valid=True,
        est_error_deg=1.0,
        peak_rate_deg_s=peak,
    )


def test_a_turn_is_scored_on_its_peak_centre_line_rate() -> None:
    score = turn_scorer(TARGET_RAD, 3.0, max_rate_deg_s=180.0)
    paced = outcome("estimate.cyl1_cyl2_line_turn < -0.7461 for 0.02", -45.0, 150.0)
    # up to the limit the rate costs nothing
    assert score(paced) == score(dataclasses.replace(paced, peak_rate_deg_s=180.0))
    # the same turn done faster than the limit scores less, the more so the faster
    fast = [score(dataclasses.replace(paced, peak_rate_deg_s=p)) for p in (270, 400, 800)]
    assert score(paced) > fast[0] > fast[1] > fast[2]
    # a tumble to the exit, even a quick one, ranks below a slow turn that falls short
    tumble = dataclasses.replace(paced, peak_rate_deg_s=800.0, duration_s=0.3)
    short = outcome("timeout", -35.0, 90.0, 3.0)
    assert score(short) > score(tumble)
    # and above a failure: the tumble still kept the pair
    assert score(tumble) > score(outcome("fail: an object left the hand", -60.0, 900.0))
    # a timeout is judged on its rate as well
    assert score(short) > score(dataclasses.replace(short, peak_rate_deg_s=500.0))


def test_the_rate_limit_is_the_scorer_s_own() -> None:
    """A template sets it (``search.max_turn_rate_deg_s``): the same turn at 300 deg/s is
    fine under a limit of 360 and penalised under the default 180."""
    turn = outcome("estimate.cyl1_cyl2_line_turn < -0.7461 for 0.02", -45.0, 300.0)
    assert turn_scorer(TARGET_RAD, 3.0, max_rate_deg_s=360.0)(turn) > turn_scorer(TARGET_RAD, 3.0)(
        turn
    )


def test_a_candidate_that_turns_the_pair_on_most_models_beats_one_that_turns_it_on_none() -> None:
    """Doing nothing fails on no model by the old count, so it ranked first: a turn phase that
    leaves the pair short of half its wanted turn on a model has failed there too."""
    score = turn_scorer(TARGET_RAD, 3.0)
    wanted = math.degrees(TARGET_RAD)
    exit_text = "estimate.cyl1_cyl2_line_turn < -0.7461 for 0.02"

    def candidate(outcomes: list[PhaseOutcome]) -> Candidate:
        scores = [score(o) for o in outcomes]
        mean = sum(scores) / len(scores)
        return Candidate((0.0,), mean, outcomes, "", scores, wanted_turn_deg=wanted)

    idle = candidate([outcome("timeout", d, 20.0, 3.0) for d in (-3.0, 1.0, 0.0, -5.0, 2.0, -1.0)])
    turns = candidate(
        [outcome(exit_text, -45.0, 150.0)] * 5
        + [outcome("fail: an object left the hand", -60.0, 900.0)]
    )
    assert idle.failures == 6 and turns.failures == 1
    assert turns.rank() > idle.rank()
    # turning past the half of the wanted turn, the wanted way, is not a failure; the other way is
    half = candidate([outcome("timeout", 0.6 * wanted, 90.0, 3.0)])
    wrong = candidate([outcome("timeout", -0.6 * wanted, 90.0, 3.0)])
    assert (half.failures, wrong.failures) == (0, 1)
    # outside a turn phase the turn is not asked for
    hold = Candidate((0.0,), 1.0, [outcome("timeout", 0.0, 0.0, 3.0)], "", [1.0])
    assert hold.failures == 0


def test_a_turn_that_snaps_over_on_a_model_has_failed_there() -> None:
    """The score charges a peak in proportion, so a torque that snaps the pair over on one
    model and reaches its exit on the others outscored one that turns slowly everywhere and
    falls short (but past half) on one: past ``tumble_deg_s`` a turn counts as failing."""
    score = turn_scorer(TARGET_RAD, 3.0)
    wanted = math.degrees(TARGET_RAD)
    exit_text = "estimate.cyl1_cyl2_line_turn < -0.7461 for 0.02"
    tumble = TUMBLE_FAIL_FACTOR * MAX_TURN_RATE_DEG_S

    def candidate(outcomes: list[PhaseOutcome]) -> Candidate:
        scores = [score(o) for o in outcomes]
        mean = sum(scores) / len(scores)
        return Candidate(
            (0.0,), mean, outcomes, "", scores, wanted_turn_deg=wanted, tumble_deg_s=tumble
        )

    fine = [outcome(exit_text, -45.0, 150.0)] * 5
    snaps = candidate([*fine, outcome(exit_text, -45.0, 400.0)])
    slow = candidate([*fine, outcome("timeout", -27.0, 90.0, 3.0)])
    assert snaps.score > slow.score  # what the score alone prefers
    assert (snaps.failures, slow.failures) == (1, 0)
    assert slow.rank() > snaps.rank()
    # at the bound itself, and without one (a hold phase), a peak is no failure
    assert candidate([outcome(exit_text, -45.0, tumble)]).failures == 0
    hold = Candidate((0.0,), 1.0, [outcome("timeout", 0.0, 900.0, 3.0)], "", [1.0])
    assert hold.failures == 0


def test_the_plans_progress_lists_a_few_models_and_counts_many() -> None:
    """Each model's outcome, whole (a failure's reason was cut at 28 characters), up to
    ``OUTCOMES_LISTED``; beyond, the exits counted and the range (48 models made a line of
    2,000 characters)."""
    from handctl.planning.compile import OUTCOMES_LISTED, _outcomes_text
    from handctl.planning.template import TemplatePhase

    turn = TemplatePhase("m", "turn", 0.3, 3.0, None, turn=math.radians(-45.0))
    few = [outcome("fail: an object left the hand", -10.0, 50.0), outcome("timeout", -30.0, 90.0)]
    assert _outcomes_text(turn, few) == (
        "fail: an object left the hand (-10 deg, peak 50 deg/s), timeout (-30 deg, peak 90 deg/s)"
    )
    many = [outcome("estimate.x < -0.7 for 0.02", -44.0 - k, 100.0 + k) for k in range(12)]
    many[0] = outcome("timeout", -20.0, 80.0)
    assert len(many) > OUTCOMES_LISTED
    assert _outcomes_text(turn, many) == (
        "12 models: exit 11, timeout 1; turn -55 to -20 deg, peak at most 111 deg/s"
    )


def test_a_hold_of_min_height_zero_is_scored_not_divided_by() -> None:
    """A template may write min_height 0 (nothing asked but that nothing sinks): a model
    that ended a little below its start was a division by zero, a traceback at the end of
    the phase's search (found by an outside audit)."""
    from handctl.planning.search import hold_scorer

    score = hold_scorer(0.0)
    sank = dataclasses.replace(outcome("timeout", 0.0, 0.0), end_height=-0.001)
    held = dataclasses.replace(outcome("timeout", 0.0, 0.0), end_height=0.0)
    assert score(sank) < score(held)
