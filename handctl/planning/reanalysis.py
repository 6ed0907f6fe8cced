"""The analysis at the configuration the hand measures: what a ``reanalyse`` phase applies.

The runner (online plane) asks through ``handctl.online.recipes.reanalysis.Reanalyser``; this
module answers. ``reanalysed_torque`` is the answer itself, a pure function of the recipe,
the hand config and what the hand measured on the tick of the request (joint angles, the
estimator's centres and radii), so the same request gives the same torque bit for bit,
wherever it is computed. Two ways to compute it:

- ``ReanalysisOnTick`` (lockstep, and ``handctl replay --rerun``): on the tick the answer is
  collected. A lockstep tick may take as long as it needs (the simulated hand waits for it),
  and a re-run computes it from the same logged inputs on the same tick, so both apply the
  very torque the run applied.
- ``ReanalysisWorker`` (real time): in a process of its own, started and warmed up before the
  run, so the loop's tick never waits for it nor shares an interpreter lock with it. The
  answer is taken ``delay_s`` after the request; if it is not there then (a host far slower
  than the analysis' tens of ms), the phase keeps its planned torque and its record says
  ``late``; the re-run reads that record in the log's summary and keeps the planned torque
  there too (``rerun._LateAsLogged``), so it repeats such a run as well.
"""

from __future__ import annotations

import concurrent.futures
import contextlib
import multiprocessing
import os
from collections.abc import Sequence, Set
from typing import Protocol

import numpy as np

from handctl.analysis.conditions import build_conditions
from handctl.analysis.model import AnalysisError
from handctl.analysis.planner import blend_towards, plan_for_conditions
from handctl.config import HandConfig
from handctl.online.recipes.reanalysis import ReanalysisResult
from handctl.online.recipes.schema import Recipe
from handctl.planning.grasp import measured_grasp, turn_directions
from handctl.portable import local_hand, portable_hand


class Radii(Protocol):
    """What measures the objects' radii (the estimator): read on the tick of a request."""

    radii: list[float]


def reanalysed_torque(
    hand: HandConfig,
    recipe: Recipe,
    phase: int,
    angles: Sequence[float],
    estimates: Sequence[float],
    radii: Sequence[float],
) -> ReanalysisResult:
    """The torque for phase ``phase`` at the measured configuration, or None (keep the
    planned one) with the reason: the grasp of the measured angles, centres and radii
    (``measured_grasp``), the conditions for turning the recipe's first pair the phase's
    way, the planner's torque of the largest margin, then (``use: blend``) the point
    nearest the planned torque between the two that keeps ``min_margin``, or (``use:
    nearest``) the torque nearest the planned one that keeps it."""
    spec = recipe.phases[phase]
    wanted = spec.reanalyse
    model = recipe.grasp_model
    if wanted is None or model is None:
        return ReanalysisResult(None, "not asked: the phase has no reanalyse")
    start = 2 * len(recipe.pairs)
    centres = [
        (float(estimates[start + 2 * i]), float(estimates[start + 2 * i + 1]))
        for i in range(len(recipe.objects))
    ]
    names = [o.name for o in recipe.objects]
    snap = measured_grasp(hand, angles, centres, radii, names, model)
    grasp = snap.grasp
    contacts = ", ".join(snap.contacts)
    if not grasp.finger_contacts:
        return ReanalysisResult(None, "none: no finger touches an object; the planned torque")
    planned = np.asarray(spec.torques, dtype=float) * np.asarray(spec.torque_margin)
    limits = [j.tau_max for j in hand.joints]
    try:
        conditions = build_conditions(grasp, turn_directions(grasp, wanted.turn, recipe.pairs[0]))
        plan = plan_for_conditions(conditions, limits)
    except AnalysisError as exc:
        return ReanalysisResult(None, f"none: {exc}; the planned torque ({contacts})")
    if not plan.found:
        return ReanalysisResult(None, f"none: {plan.reason}; the planned torque ({contacts})")
    if wanted.use == "analysis":
        return ReanalysisResult(plan.tau, f"analysis: margin {plan.margin:.3g} N ({contacts})")
    if wanted.use == "nearest":
        if plan.margin < wanted.min_margin:
            return ReanalysisResult(
                plan.tau,
                f"analysis: margin {plan.margin:.3g} N, less than min_margin_N ({contacts})",
            )
        near = plan_for_conditions(
            conditions, limits, nearest=planned, min_margin=wanted.min_margin
        )
        if not near.found:  # numerically at the edge: the largest margin is the safe side
            return ReanalysisResult(
                plan.tau, f"analysis: margin {plan.margin:.3g} N ({near.reason}) ({contacts})"
            )
        moved = float(np.sum(np.abs(np.asarray(near.tau) - planned)))
        return ReanalysisResult(
            near.tau,
            f"nearest: {moved:.3g} N·m from the planned torque, margin {near.margin:.3g} N "
            f"({contacts})",
        )
    fraction, blended = blend_towards(conditions, planned, plan.tau, wanted.min_margin)
    return ReanalysisResult(
        blended.tau,
        f"blend {fraction:g} of the way to the analysis' torque: margin "
        f"{blended.margin:.3g} N ({contacts})",
    )


class ReanalysisOnTick:
    """The analysis computed on the tick its answer is collected (lockstep, a re-run)."""

    def __init__(self, hand: HandConfig, recipe: Recipe, radii: Radii) -> None:
        self.hand = hand
        self.recipe = recipe
        self.radii = radii
        self._asked: dict[int, tuple[list[float], tuple[float, ...], list[float]]] = {}

    def submit(self, phase: int, angles: Sequence[float], estimates: Sequence[float]) -> None:
        self._asked[phase] = (list(angles), tuple(estimates), list(self.radii.radii))

    def collect(self, phase: int) -> ReanalysisResult | None:
        asked = self._asked.pop(phase, None)
        if asked is None:
            return None
        return reanalysed_torque(self.hand, self.recipe, phase, *asked)


#: in the worker: the hand (its own, from the portable one) and the recipe, handed over once
#: when it starts, so a request carries only what was measured
_RUN: dict[str, tuple[HandConfig, Recipe]] = {}


def _answer(
    phase: int, angles: list[float], estimates: tuple[float, ...], radii: list[float]
) -> ReanalysisResult:
    """In the worker: the answer to one request."""
    hand, recipe = _RUN["run"]
    return reanalysed_torque(hand, recipe, phase, angles, estimates, radii)


class ReanalysisWorker:
    """The analysis in a process of its own (real time): ``submit`` hands the request over
    and returns; ``collect`` takes the answer if it is there. Close it when the run ends.

    The worker runs at the ordinary priority and off ``avoid_cpus`` (the loop's and the
    simulated hand's): started from a process that has already asked for SCHED_FIFO and a
    CPU of its own, it would inherit both, and a few hundred ms of analysis at the loop's
    priority on the loop's CPU would stop the loop. Start it before the loop asks."""

    def __init__(
        self, hand: HandConfig, recipe: Recipe, radii: Radii, avoid_cpus: Set[int] = frozenset()
    ) -> None:
        from handctl.executor import start_resource_tracker

        self.radii = radii
        start_resource_tracker()
        # the hand and the recipe go over once, at the start: a request is then a few
        # hundred numbers to pickle, which the executor's threads do beside the loop
        self._pool = concurrent.futures.ProcessPoolExecutor(
            max_workers=1,
            mp_context=multiprocessing.get_context("spawn"),
            initializer=_start,
            initargs=(frozenset(avoid_cpus), portable_hand(hand), recipe),
        )
        self._futures: dict[int, concurrent.futures.Future[ReanalysisResult]] = {}
        # before the run: the worker's start and its imports are not paid for in a phase
        self._pool.submit(_warm_up).result()

    def submit(self, phase: int, angles: Sequence[float], estimates: Sequence[float]) -> None:
        self._futures[phase] = self._pool.submit(
            _answer, phase, list(angles), tuple(estimates), list(self.radii.radii)
        )

    def collect(self, phase: int) -> ReanalysisResult | None:
        future = self._futures.get(phase)
        if future is None or not future.done():
            return None
        del self._futures[phase]
        return future.result()

    def placement(self) -> tuple[int, frozenset[int]]:
        """The worker's scheduling policy and CPUs, as it sees them (for a run's notes and
        the tests: it must not be the loop's)."""
        return self._pool.submit(_placement).result()

    def close(self) -> None:
        self._pool.shutdown(wait=True, cancel_futures=True)


def _start(avoid_cpus: frozenset[int], hand: HandConfig, recipe: Recipe) -> None:
    """In the worker, once: the ordinary scheduling policy, every CPU it may use but those
    to avoid (all of them if that leaves none), and the run's hand and recipe."""
    _RUN["run"] = (local_hand(hand), recipe)
    # a session of its own: Ctrl-C, Ctrl-\\ and Ctrl-Z at the terminal are the run's to
    # answer (a controlled stop), and reached this worker too, which printed a
    # KeyboardInterrupt traceback or died by the signal mid-run
    with contextlib.suppress(OSError):
        os.setsid()
    with contextlib.suppress(OSError, AttributeError):
        os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
    with contextlib.suppress(OSError, AttributeError):
        allowed = os.sched_getaffinity(0) - avoid_cpus
        if allowed:
            os.sched_setaffinity(0, allowed)


def _placement() -> tuple[int, frozenset[int]]:
    return os.sched_getscheduler(0), frozenset(os.sched_getaffinity(0))


def _warm_up() -> None:
    """Nothing: the worker has imported this module, and with it the analysis."""
