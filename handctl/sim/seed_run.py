"""One run of a recipe on one perturbed simulated hand, as a task any worker can run.

The experiment bench (``tools/bench_experiment.py``) runs a recipe through the whole stack
(bus, nodes, safety, estimator, in lockstep) on tens of perturbed hands; each is independent
of the others, so each is a task for ``handctl.executor``. The task carries the hand and the
recipe as data and the seed that draws the model, so a worker needs nothing but the installed
package and the figures do not depend on which worker ran it.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from handctl.config import HandConfig
from handctl.portable import local_hand
from handctl.recipes.schema import Recipe


@dataclass(frozen=True)
class SeedRun:
    """Run ``recipe`` on the model drawn from ``seed`` (``None``: the nominal hand)."""

    hand: HandConfig  # a ``portable_hand``
    recipe: Recipe
    seed: int | None
    min_rotation_deg: float


def run_seed(task: SeedRun) -> dict[str, Any]:
    """The seed's figures: success, outcome, what the experiment measured, the model drawn."""
    from handctl.planning.models import Spread, hand_with, perturb
    from handctl.session import RunRequest, run_recipe
    from handctl.sim.params import parse_sim

    hand = local_hand(task.hand)
    seed = task.seed
    if seed is None:
        model_hand, scales, noise = hand, {}, 1.0
        sensor_seed = 0
    else:
        rng = np.random.default_rng(seed)
        model = perturb(parse_sim(hand), rng, Spread())
        noise = float(rng.uniform(0.5, 2.0))
        model_hand = hand_with(hand, model.params, tdt_noise_scale=noise, seed=seed)
        scales = model.scales
        sensor_seed = seed
    t0 = time.monotonic()
    report = run_recipe(RunRequest(hand=model_hand, recipe=task.recipe, seed=sensor_seed))
    wall = time.monotonic() - t0
    ex = report.summary.get("experiment", {})
    ok = bool(report.summary["completed"] and ex.get("lifted") and not ex.get("dropped")
              and ex.get("total_rotation_deg", 0.0) >= task.min_rotation_deg)
    return {
        "seed": seed, "success": ok, "outcome": report.summary["outcome"],
        "lifted": ex.get("lifted"), "dropped": ex.get("dropped"),
        "total_rotation_deg": ex.get("total_rotation_deg"),
        "phase_angles_deg": ex.get("phase_angles_deg"),
        "estimator_error_deg": ex.get("estimator_error_deg"),
        "tdt_noise_scale": round(noise, 3),
        "scales": {k: round(v, 3) for k, v in scales.items()}, "wall_s": round(wall, 2)}
