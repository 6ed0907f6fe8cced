"""The planner's episodes: on hands of other shapes than the default (one object is no pair),
and phase by phase exactly as a run of the whole recipe."""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence

import numpy as np
import numpy.typing as npt

from handctl.config import HandConfig, load_hand
from handctl.online.estimator import RESET_CLEARANCE, ObjectEstimator
from handctl.online.recipes.backoff import RateBackoff
from handctl.online.recipes.guard import LimitGuard
from handctl.online.recipes.runner import RecipeRunner
from handctl.online.recipes.schema import (
    PacedRamp,
    Phase,
    PoseHold,
    Recipe,
    RecipeObject,
    TimeoutAction,
    TurnBrake,
)
from handctl.online.safety.limits import JointLimits, limit_torque
from handctl.planning.episode import Episode
from handctl.sim.params import NODE_TICK_S, parse_sim

from ..conftest import ROOT

FOUR_BY_FOUR = ROOT / "config" / "hands" / "four_fingers_four_joints.yaml"


def test_a_phase_on_one_object_has_no_pair_to_block() -> None:
    """The four-by-four hand holds one cylinder: a phase ends with no pair blocked, no pair
    gap and no turn (the hold scorer asks whether a link lies between the pair's objects)."""
    hand = load_hand(FOUR_BY_FOUR)
    params = parse_sim(hand)
    (cylinder,) = params.objects
    episode = Episode(hand, params, [RecipeObject(cylinder.name, cylinder.radius)])
    phase = Phase("hold", (0.0,) * hand.n_joints, 0.0, 0.05, TimeoutAction.NEXT, (), ())
    outcome = episode.run_phase(phase)
    assert outcome.exit == "timeout"
    assert outcome.pair_blocked is False
    assert outcome.pair_gap == 0.0 and outcome.true_turn_deg == 0.0


def test_a_hold_after_a_lift_that_raised_nothing_says_so() -> None:
    """A phase entered as after a lift (``lifted``) with the object still on the table: the
    lift raised nothing, and the phase said "an object fell back to the table", as if it had
    been up (found by an outside audit: a plan whose lift ended "up 0 mm")."""
    hand = load_hand(FOUR_BY_FOUR)
    params = parse_sim(hand)
    (cylinder,) = params.objects
    episode = Episode(hand, params, [RecipeObject(cylinder.name, cylinder.radius)])
    phase = Phase("hold", (0.0,) * hand.n_joints, 0.0, 0.05, TimeoutAction.NEXT, (), ())
    outcome = episode.run_phase(phase, lifted=True)
    assert outcome.exit == "fail: an object was never lifted (the lift left it on the table)"


class CountedEstimator(ObjectEstimator):
    """The estimator, counting its steps: it takes one a call, and a run one a tick."""

    calls = 0

    def __call__(self, angle: Sequence[float] | npt.NDArray[np.float64]) -> tuple[float, ...]:
        self.calls += 1
        return super().__call__(angle)


def _counted(episode: Episode, objects: Sequence[RecipeObject]) -> Episode:
    episode.estimator = CountedEstimator(episode.hand, objects)
    return episode


def _whole_recipe(episode: Episode, recipe: Recipe) -> int:
    """Every phase of ``recipe`` in one runner on ``episode``'s plant, as a run drives them
    (measured angles, the supervisor's limiter, the bus's one tick): the tick the last phase
    is left on, with the plant where it is then."""
    hand, plant, estimator = episode.hand, episode.plant, episode.estimator
    runner = RecipeRunner(recipe, hand.n_joints, backoff=RateBackoff.for_hand(hand, NODE_TICK_S))
    limits = JointLimits.from_hand(hand)
    quantum = 2 * math.pi / episode.params.encoder.counts_per_rev
    applied = np.zeros(hand.n_joints)
    zeros = np.zeros(hand.n_joints)
    for tick in itertools.count():
        angles = [round(float(q) / quantum) * quantum for q in plant.joint_angles]
        estimates = estimator(angles)
        desired = runner.step(tick * NODE_TICK_S, np.asarray(angles), zeros, estimates)
        if runner.index >= len(recipe.phases):
            return tick
        plant.set_torque_commands(applied)
        limit_torque(desired, applied, limits, NODE_TICK_S, applied)
        plant.step()
    raise AssertionError("unreachable")


def test_phases_run_one_by_one_move_the_hand_as_the_whole_recipe_does(
    hand: HandConfig,
) -> None:
    """The planner scores each phase on a runner of its own. Its episodes must move the hand
    exactly as one runner over the whole recipe does, or the plan scores something else than
    what runs: the second phase's ramp starts from the first's proposed torque (its pose hold
    included, not the injected damping or the guard), the damping fades from the first's,
    the velocities go on, the injected damping's back-off goes on mirroring the limiter, and
    the supervisor's limiter clamps every command."""
    params = parse_sim(hand)
    objects = [RecipeObject(o.name, o.radius) for o in params.objects]
    guard = LimitGuard.for_hand(hand, 0.15)
    start = [q for finger in params.initial_angles for q in finger]
    flex = (0.30, 0.20, 0.15, 0.30, 0.20, 0.15, -0.30, -0.20, -0.15)
    brake = TurnBrake(math.radians(120.0), 0.03, joint_rate=0.3)
    first = Phase(
        "first",
        flex,
        0.01,  # s: faster than the rate limit, which the limiter then clamps
        0.5,
        TimeoutAction.NEXT,
        (),
        (),
        pose=PoseHold(tuple(q + 0.3 for q in start), 0.5, 0.005),
        joint_damping=0.02,
        brake=brake,
    )
    second = Phase(
        "second",
        (0.2, 0.3, 0.2, 0.2, 0.3, 0.2, -0.2, -0.3, -0.2),
        0.1,
        0.12,
        TimeoutAction.NEXT,
        (),
        (),
        brake=brake,
        paced=PacedRamp(math.radians(-90.0), 1.0, 2.0, joint_rate=0.5),
        torque_margin=1.2,
    )
    whole = _counted(Episode(hand, params, objects, guard), objects)
    recipe = Recipe("whole", "<test>", "", (first, second), 1.0, None, False, limit_guard=guard)
    ticks = _whole_recipe(whole, recipe)

    by_phase = _counted(Episode(hand, params, objects, guard), objects)
    by_phase.run_phase(first)
    again = by_phase.snapshot()  # and a phase started from a snapshot starts the same
    by_phase.run_phase(second)
    assert by_phase.tick == ticks
    assert np.array_equal(by_phase.plant.data.qpos, whole.plant.data.qpos)
    # the estimator took one step a tick (it tracks the pair by now: an estimator reset to
    # its seeds would be equal whatever steps it took)
    assert by_phase.estimator.centres == whole.estimator.centres
    assert max(whole.estimator.clearance) < RESET_CLEARANCE
    assert isinstance(by_phase.estimator, CountedEstimator)
    assert isinstance(whole.estimator, CountedEstimator)
    assert by_phase.estimator.calls == whole.estimator.calls == ticks + 1
    by_phase.restore(again)
    by_phase.run_phase(second)
    assert np.array_equal(by_phase.plant.data.qpos, whole.plant.data.qpos)


def test_a_phase_reports_its_peak_centre_line_rate(hand: HandConfig) -> None:
    """The true centre line's largest rate over 10 ms, as the run summary measures it: a
    pair pushed over by one finger turns at some hundreds of deg/s, a pair left alone not."""
    params = parse_sim(hand)
    objects = [RecipeObject(o.name, o.radius) for o in params.objects]
    still = Episode(hand, params, objects)
    rest = still.run_phase(Phase("rest", (0.0,) * 9, 0.0, 0.3, TimeoutAction.NEXT, (), ()))
    assert rest.peak_rate_deg_s < 5.0
    pushed = Episode(hand, params, objects)
    sweep = (0.6, 0.45, 0.3) + (0.0,) * 6  # finger 1 alone, flexed hard into the pair
    moved = pushed.run_phase(Phase("push", sweep, 0.0, 0.6, TimeoutAction.NEXT, (), ()))
    assert moved.peak_rate_deg_s > 50.0
    assert moved.peak_rate_deg_s >= abs(moved.true_turn_deg) / 0.6


def test_an_episode_scores_the_template_s_objects_and_its_first_pair_by_name(
    hand: HandConfig,
) -> None:
    """A scene may hold objects the template does not name: every lift was scored on the
    lowest of all the scene's objects (a third rod never lifted failed every model), and
    every turn on the scene's first two, whichever pair the template named (an outside
    audit of hand shapes)."""
    params = parse_sim(hand)
    _, second = params.objects
    only = Episode(hand, params, [RecipeObject(second.name, second.radius)])
    both = Episode(hand, params, [RecipeObject(o.name, o.radius) for o in params.objects])
    poses = both.plant.object_poses()
    assert only.heights() == [poses[1].y - second.y]
    assert len(both.heights()) == 2 and only.true_angle() == 0.0 and only.pair_gap() == 0.0
    objects = [RecipeObject(o.name, o.radius) for o in params.objects]
    turned = Episode(hand, params, objects, pairs=[(1, 0)])
    angle = math.atan2(poses[0].y - poses[1].y, poses[0].x - poses[1].x)
    assert turned.true_angle() == angle
    assert both.true_angle() == math.atan2(poses[1].y - poses[0].y, poses[1].x - poses[0].x)
    assert turned.estimator.pairs == ((1, 0),) and both.estimator.pairs == ((0, 1),)


def _commands_held(hand: HandConfig) -> tuple[int, int]:
    """A phase that ramps every joint to a torque on ``hand``: how many 1 ms plant ticks it
    ran, and how many of them took another command than the tick before."""
    params = parse_sim(hand)
    episode = Episode(hand, params, [RecipeObject(o.name, o.radius) for o in params.objects])
    plant = episode.plant
    taken: list[tuple[float, ...]] = []
    step = plant.step

    def counted_step() -> None:
        taken.append(tuple(float(c) for c in plant._ctrl))
        step()

    plant.step = counted_step  # type: ignore[method-assign]
    phase = Phase("ramp", (0.05,) * hand.n_joints, 0.1, 0.1, TimeoutAction.NEXT, (), ())
    episode.run_phase(phase)
    changes = sum(1 for a, b in itertools.pairwise(taken) if a != b)
    return len(taken), changes


def test_a_plan_runs_the_host_at_the_hand_s_own_loop_rate(hand: HandConfig) -> None:
    """A hand at 250 Hz was planned as if its host ran at 1 kHz (a new command every 1 ms
    tick of the plant, the runner's ramps and the limiter at 1 ms): the recipe planned for it
    was the 1 kHz one, its scores those of a controller it does not run. Each command is held
    for the hand's period now: the nodes' first tick of it on the command before."""
    import dataclasses

    fast_ticks, fast_changes = _commands_held(hand)
    slow = dataclasses.replace(hand, bus=dataclasses.replace(hand.bus, loop_rate_hz=250.0))
    slow_ticks, slow_changes = _commands_held(slow)
    assert abs(slow_ticks - fast_ticks) <= 8  # the same 0.1 s of the plant
    assert fast_changes >= fast_ticks * 0.9  # a ramp: a new command every tick
    assert slow_changes <= slow_ticks / 4 + 1  # one a period of four
