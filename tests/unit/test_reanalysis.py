"""The analysis at the configuration the hand measures (``handctl.planning.reanalysis``): the
grasp built from the measured angles, the estimator's centres and radii has the contacts the
simulation has; the answer is the same bit for bit computed on the tick or in the real-time
worker (which is what keeps a real-time run's re-run exact); and the torque nearest a given
one keeps the margin asked for and is no further from it than the largest-margin torque."""

from __future__ import annotations

import dataclasses
import os
import time
from pathlib import Path

import numpy as np
import pytest

from handctl.analysis.conditions import build_conditions
from handctl.analysis.model import AnalysisError, load_scenario
from handctl.analysis.oracle import lp_values
from handctl.analysis.planner import plan_for_conditions
from handctl.config import HandConfig
from handctl.online.recipes.loader import load_recipe
from handctl.online.recipes.schema import GraspModel, Reanalyse, Recipe
from handctl.planning.episode import Episode
from handctl.planning.grasp import grasp_of, measured_grasp
from handctl.planning.reanalysis import ReanalysisOnTick, ReanalysisWorker
from handctl.sim.params import parse_sim

ROOT = Path(__file__).resolve().parents[2]
RECIPE = ROOT / "config" / "recipes" / "swap_two_cylinders.yaml"
FIG3 = ROOT / "config" / "analysis" / "paper_fig3.yaml"
MANIPULATE_1 = 3


@dataclasses.dataclass
class Held:
    """The nominal hand where the shipped recipe's ``manipulate_1`` begins."""

    recipe: Recipe
    episode: Episode
    angles: list[float]
    estimates: tuple[float, ...]
    radii: list[float]


@pytest.fixture(scope="module")
def held(hand: HandConfig) -> Held:
    recipe = load_recipe(RECIPE, hand)
    params = parse_sim(hand)
    model = GraspModel(
        tuple(o.mass for o in params.objects),
        params.friction.finger_object,
        params.friction.object_object,
        params.gravity,
        0.001,
    )
    phases = list(recipe.phases)
    phases[MANIPULATE_1] = dataclasses.replace(
        phases[MANIPULATE_1], reanalyse=Reanalyse(-1.0, 0.1, "nearest", 0.05)
    )
    recipe = dataclasses.replace(recipe, phases=tuple(phases), grasp_model=model)
    episode = Episode(hand, params, recipe.objects, recipe.limit_guard)
    for k, phase in enumerate(recipe.phases[:MANIPULATE_1]):
        episode.run_phase(phase, lifted=k > 1)
    estimates = episode.estimator.last
    assert np.all(np.isfinite(estimates)), "the pair is caged where manipulate_1 begins"
    return Held(
        recipe,
        episode,
        episode.plant.joint_angles.tolist(),
        estimates,
        list(episode.estimator.radii),
    )


def test_the_measured_grasp_has_the_contacts_the_simulation_has(
    held: Held, hand: HandConfig
) -> None:
    model = held.recipe.grasp_model
    assert model is not None
    measured = measured_grasp(
        hand,
        held.angles,
        held.episode.estimator.positions(held.estimates),
        held.radii,
        [o.name for o in held.recipe.objects],
        model,
    )
    simulated = grasp_of(held.episode.plant, hand)
    assert measured.contacts == simulated.contacts
    for ours, theirs in zip(
        measured.grasp.finger_contacts, simulated.grasp.finger_contacts, strict=True
    ):
        # the estimate is within a millimetre or two of the true centre
        assert np.linalg.norm(ours.point - theirs.point) < 0.003


class _Radii:
    def __init__(self, radii: list[float]) -> None:
        self.radii = radii


def test_the_answer_is_the_same_on_the_tick_and_in_the_worker(held: Held, hand: HandConfig) -> None:
    on_tick = ReanalysisOnTick(hand, held.recipe, _Radii(held.radii))
    on_tick.submit(MANIPULATE_1, held.angles, held.estimates)
    here = on_tick.collect(MANIPULATE_1)
    worker = ReanalysisWorker(hand, held.recipe, _Radii(held.radii))
    try:
        worker.submit(MANIPULATE_1, held.angles, held.estimates)
        there = None
        for _ in range(600):  # a result, however loaded the machine (never a time asserted)
            there = worker.collect(MANIPULATE_1)
            if there is not None:
                break
            time.sleep(0.1)
    finally:
        worker.close()
    assert here is not None and there is not None
    assert here.torques is not None and here.note.startswith("nearest:")
    assert there == here  # bit for bit: a re-run computes the run's torque again


def test_the_nearest_torque_keeps_its_margin_and_is_nearer_than_the_best() -> None:
    sc = load_scenario(FIG3)
    cond = build_conditions(sc.grasp, sc.directions)
    best = plan_for_conditions(cond, sc.tau_max)
    assert best.found
    rng = np.random.default_rng(13)
    for _ in range(5):
        reference = rng.uniform(-1.0, 1.0, len(best.tau)) * sc.tau_max
        wanted = 0.5 * best.margin
        near = plan_for_conditions(cond, sc.tau_max, nearest=reference, min_margin=wanted)
        assert near.found
        assert near.margin >= wanted - 1e-6
        assert lp_values(cond, np.array(near.tau)).margin == pytest.approx(near.margin)
        distance = np.sum(np.abs(np.array(near.tau) - reference))
        assert distance <= np.sum(np.abs(np.array(best.tau) - reference)) + 1e-9
    inside = np.array(best.tau)
    same = plan_for_conditions(cond, sc.tau_max, nearest=inside, min_margin=0.5 * best.margin)
    np.testing.assert_allclose(same.tau, inside, atol=1e-7)
    with pytest.raises(AnalysisError, match="min_margin"):
        plan_for_conditions(cond, sc.tau_max, nearest=inside, min_margin=0.0)


@pytest.mark.skipif(len(os.sched_getaffinity(0)) < 2, reason="needs two CPUs to avoid one")
def test_the_worker_runs_at_the_ordinary_priority_off_the_loop_s_cpu(
    held: Held, hand: HandConfig
) -> None:
    loop_cpu = min(os.sched_getaffinity(0))
    worker = ReanalysisWorker(hand, held.recipe, _Radii(held.radii), frozenset({loop_cpu}))
    try:
        policy, cpus = worker.placement()
    finally:
        worker.close()
    assert policy == os.SCHED_OTHER
    assert cpus and loop_cpu not in cpus
