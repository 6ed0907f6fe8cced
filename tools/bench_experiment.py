"""The paper's experiment over perturbed simulated hands: is the recipe robust, not lucky?

Each seed draws one model of the hand (every Coulomb coefficient ±30 %, cylinder mass ±20 %,
radius ±10 %, TDT noise ×0.5..2 and the sensor seed) and runs the recipe through the whole
stack as ``handctl run recipe`` does (bus, nodes, safety, estimator), in lockstep. A seed
succeeds when the objects were lifted and held, nothing dropped, and the pair turned at least
``--min-rotation`` degrees. Prints ``success_rate`` and ``mean_total_rotation_deg`` with the
per-seed figures; ``estimator_us_p50/p99`` is the estimator's own cost per tick on this
machine (a benchmark figure, never a test).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
DEFAULT_RECIPE = ROOT / "config" / "recipes" / "swap_two_cylinders.yaml"
DEFAULT_HAND = ROOT / "config" / "hands" / "hiroshima_hand.yaml"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--seeds", type=int, default=20, help="perturbed models to run")
    parser.add_argument("--first-seed", type=int, default=1000,
                        help="seed of the first model (models are seed, seed + 1, ...)")
    parser.add_argument("--recipe", type=Path, default=DEFAULT_RECIPE)
    parser.add_argument("--hand", type=Path, default=DEFAULT_HAND)
    parser.add_argument("--min-rotation", type=float, default=135.0,
                        help="degrees the pair must turn for a seed to count as a success")
    parser.add_argument("--nominal", action="store_true",
                        help="run the unperturbed hand once (what the CI test runs)")
    parser.add_argument("--workers", type=int,
                        help="local worker processes (default: every core)")
    parser.add_argument("--scheduler", metavar="tcp://HOST:PORT",
                        help="run the seeds on this Dask cluster (docs/scale.md)")


def _estimator_cost_us(hand: Any, recipe: Any) -> tuple[float, float]:
    """p50 and p99 of one estimator call over a stored sequence of angles (enveloping and
    open poses), on this machine."""
    from handctl.estimator import ObjectEstimator

    est = ObjectEstimator(hand, recipe.objects)
    rng = np.random.default_rng(0)
    base = np.array([0.24, 1.46, 1.53, 0.24, 1.46, 1.53, 0.47, -1.57, -1.38])
    poses = [(base + rng.normal(0.0, 0.02, 9)).tolist() for _ in range(2000)]
    poses += [[-0.55, -0.1, -0.1, -0.55, -0.1, -0.1, 0.55, 0.1, 0.1]] * 500
    times = []
    clock = time.perf_counter_ns
    for q in poses:
        t0 = clock()
        est(q)
        times.append(clock() - t0)
    p50, p99 = np.percentile(times, [50, 99])
    return float(p50) / 1e3, float(p99) / 1e3


def run(args: argparse.Namespace) -> dict[str, Any]:
    from handctl.config import load_hand
    from handctl.executor import open_pool
    from handctl.portable import portable_hand
    from handctl.progress import Progress, say
    from handctl.recipes.loader import load_recipe
    from handctl.sim.seed_run import SeedRun, run_seed

    hand = load_hand(args.hand)
    recipe = load_recipe(args.recipe, hand)
    seeds = [None] if args.nominal else list(range(args.first_seed,
                                                   args.first_seed + args.seeds))
    tasks = [SeedRun(portable_hand(hand), recipe, seed, args.min_rotation) for seed in seeds]
    with open_pool(args.workers, args.scheduler) as pool:
        say(f"experiment on {pool.where}")
        with Progress("seeds", len(tasks)) as bar:
            runs = pool.map(run_seed, tasks, bar)
    for r in runs:
        say(f"seed {r['seed']}: {'ok' if r['success'] else 'FAIL'} lifted {r['lifted']} "
            f"dropped {r['dropped']} turned {r['total_rotation_deg']} deg ({r['outcome']}, "
            f"{r['wall_s']:.1f} s)")
    rotations = [r["total_rotation_deg"] or 0.0 for r in runs]
    errors = [r["estimator_error_deg"] for r in runs if r["estimator_error_deg"] is not None]
    p50, p99 = _estimator_cost_us(hand, recipe)
    return {
        "benchmark": "experiment",
        "recipe": str(args.recipe.name),
        "seeds": len(runs),
        "min_rotation_deg": args.min_rotation,
        "success_rate": round(sum(r["success"] for r in runs) / len(runs), 3),
        "lifted_rate": round(sum(bool(r["lifted"]) for r in runs) / len(runs), 3),
        "drop_rate": round(sum(bool(r["dropped"]) for r in runs) / len(runs), 3),
        "safety_stop_rate": round(sum(r["outcome"] == "safety_stop" for r in runs) / len(runs),
                                  3),
        "mean_total_rotation_deg": round(float(np.mean(rotations)), 2),
        "min_total_rotation_deg": round(float(np.min(rotations)), 2),
        "estimator_error_deg_p95_median": (round(float(np.median(errors)), 2) if errors
                                           else None),
        "estimator_us_p50": round(p50, 2),
        "estimator_us_p99": round(p99, 2),
        "runs": runs,
    }
