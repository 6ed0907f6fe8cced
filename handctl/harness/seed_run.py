"""One run of a recipe on one perturbed simulated hand, as a task any worker can run.

The experiment bench (``tools/bench_experiment.py``) runs a recipe through the whole stack
(bus, nodes, safety, estimator, in lockstep) on tens of perturbed hands; each is independent
of the others, so each is a task for ``handctl.executor``. The task carries the hand and the
recipe as data, the seed that draws the model and the family of the spread it is drawn from,
so a worker needs nothing but the installed package and the figures do not depend on which
worker ran it.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from handctl.config import HandConfig
from handctl.online.recipes.schema import Recipe
from handctl.portable import local_hand


@dataclass(frozen=True)
class SeedRun:
    """Run ``recipe`` on the model drawn from ``seed`` (``None``: the nominal hand) out of the
    default spread's ``family`` (``"all"``: every family at once)."""

    hand: HandConfig  # a ``portable_hand``
    recipe: Recipe
    seed: int | None
    family: str = "all"
    swap_deg: float = 170.0
    #: s, stop the run after this long (``None``: run it to its end), as ``--max-seconds``
    max_seconds: float | None = None


def run_seed(task: SeedRun) -> dict[str, Any]:
    """The seed's figures: success (the summary's ``experiment.success``), swap, outcome, what
    the experiment measured, the model drawn."""
    from handctl.planning.models import Spread, hand_with, perturb
    from handctl.session import RunRequest, run_recipe
    from handctl.sim.params import parse_sim
    from handctl.summary_guard import require_whole

    hand = local_hand(task.hand)
    seed = task.seed
    scales: dict[str, float] = {}
    model_hand = hand
    if seed is not None:
        spread = Spread() if task.family == "all" else Spread().only(task.family)
        model = perturb(parse_sim(hand), np.random.default_rng(seed), spread, hand)
        model_hand = hand_with(hand, model.params, seed=seed)
        scales = model.scales
    t0 = time.monotonic()
    report = run_recipe(
        RunRequest(
            hand=model_hand, recipe=task.recipe, seed=seed or 0, max_seconds=task.max_seconds
        )
    )
    wall = time.monotonic() - t0
    # a bug of handctl's in the run's account is no failed manipulation: raised, as it was
    require_whole(report.summary, f"seed {seed} ({task.family})")
    ex = report.summary.get("experiment", {})
    ok = bool(report.summary["completed"] and ex.get("success"))
    total = ex.get("total_rotation_deg") or 0.0
    return {
        "seed": seed,
        "family": task.family,
        "success": ok,
        "swap": ok and total >= task.swap_deg,
        "outcome": report.summary["outcome"],
        # why a run stopped ("" for one that completed): a safety stop's fault and joint
        "message": report.summary["message"],
        "lifted": ex.get("lifted"),
        "dropped": ex.get("dropped"),
        "total_rotation_deg": total,
        # the lift's tilt, and where the pair ended against how it lay on the table
        "turn_before_manipulation_deg": ex.get("turn_before_manipulation_deg"),
        "end_from_table_deg": ex.get("end_from_table_deg"),
        "phase_angles_deg": ex.get("phase_angles_deg"),
        "peak_turn_rate_deg_s": ex.get("peak_turn_rate_deg_s"),
        "peak_turn_rate_by_phase_deg_s": ex.get("peak_turn_rate_by_phase_deg_s"),
        "timed_out_phases": report.summary.get("timed_out_phases"),
        "estimator_error_deg": ex.get("estimator_error_deg"),
        # joints whose command rang (safety.chatter): the limits held, the joint took it
        "ringing_joints": [c["joint"] for c in report.summary.get("chatter", [])],
        "scales": {k: round(v, 4) for k, v in scales.items()},
        "wall_s": round(wall, 2),
    }
