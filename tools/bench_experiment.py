"""The paper's experiment over perturbed simulated hands: is the recipe robust, not lucky?

Each seed draws one model of the hand from the planner's default ``Spread``
(``handctl/planning/models.py``: contact friction, joint dynamics, the objects, their
placement, the start pose, the sensors) and runs the recipe through the whole stack as
``handctl run recipe`` does (bus, nodes, safety, estimator), in lockstep, with the seed as
the sensors' seed. By default every family is varied on its own (``--seeds`` models each),
then all of them at once; ``--family F`` runs one (``all`` for everything at once). A run
succeeds when it completed and its ``experiment.success`` holds (lifted, held, nothing
dropped, the recipe's ``min_total_turn_deg``); it is a swap when, besides, the pair turned
``--swap-deg`` (170) or more. Per group: ``success_rate``, ``swap_rate`` and the peak true
centre-line rate (deg/s, the largest and the median over the runs); the nominal hand is run
once as well. ``estimator_us_p50/p99`` is the estimator's own cost per tick on this machine
(a benchmark figure, never a test).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
DEFAULT_RECIPE = ROOT / "config" / "recipes" / "swap_two_cylinders.yaml"
DEFAULT_HAND = ROOT / "config" / "hands" / "hiroshima_hand.yaml"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--seeds", type=int, default=10, help="perturbed models per group")
    parser.add_argument("--first-seed", type=int, default=1000,
                        help="seed of the first model (models are seed, seed + 1, ...)")
    from handctl.planning.models import FAMILIES

    parser.add_argument("--family", default=None, choices=[*FAMILIES, "all"],
                        help="one family of the spread, or 'all' for all of them at once; "
                        "default: each family on its own, then all at once")
    parser.add_argument("--recipe", type=Path, default=DEFAULT_RECIPE)
    parser.add_argument("--hand", type=Path, default=DEFAULT_HAND)
    parser.add_argument("--swap-deg", type=float, default=170.0,
                        help="degrees the pair must turn for a run to count as a swap")
    parser.add_argument("--nominal", action="store_true",
                        help="run only the unperturbed hand, once")


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


def _one(hand: Any, recipe: Any, seed: int | None, model: Any, swap_deg: float
         ) -> dict[str, Any]:
    from handctl.planning.models import hand_with
    from handctl.session import RunRequest, run_recipe

    model_hand = hand if model is None else hand_with(hand, model.params, seed=seed)
    t0 = time.monotonic()
    report = run_recipe(RunRequest(hand=model_hand, recipe=recipe, seed=seed or 0))
    wall = time.monotonic() - t0
    ex = report.summary.get("experiment", {})
    ok = bool(report.summary["completed"] and ex.get("success"))
    total = ex.get("total_rotation_deg") or 0.0
    run = {
        "seed": seed, "success": ok, "swap": ok and total >= swap_deg,
        "outcome": report.summary["outcome"], "lifted": ex.get("lifted"),
        "dropped": ex.get("dropped"), "total_rotation_deg": total,
        "phase_angles_deg": ex.get("phase_angles_deg"),
        "peak_turn_rate_deg_s": ex.get("peak_turn_rate_deg_s"),
        "timed_out_phases": report.summary.get("timed_out_phases"),
        "estimator_error_deg": ex.get("estimator_error_deg"),
        "scales": {} if model is None else {k: round(v, 4) for k, v in model.scales.items()},
        "wall_s": round(wall, 2)}
    print(f"seed {seed}: {'ok' if ok else 'FAIL'} lifted {run['lifted']} dropped "
          f"{run['dropped']} turned {total} deg {run['phase_angles_deg']} peak "
          f"{run['peak_turn_rate_deg_s']} deg/s ({run['outcome']}, {wall:.1f} s)",
          file=sys.stderr, flush=True)
    return run


def _figures(runs: list[dict[str, Any]]) -> dict[str, Any]:
    n = len(runs)
    peaks = [r["peak_turn_rate_deg_s"] or 0.0 for r in runs]
    return {
        "seeds": n,
        "success_rate": round(sum(r["success"] for r in runs) / n, 3),
        "swap_rate": round(sum(r["swap"] for r in runs) / n, 3),
        "drop_rate": round(sum(bool(r["dropped"]) for r in runs) / n, 3),
        "safety_stop_rate": round(sum(r["outcome"] == "safety_stop" for r in runs) / n, 3),
        "mean_total_rotation_deg": round(float(np.mean([r["total_rotation_deg"]
                                                        for r in runs])), 2),
        "peak_turn_rate_deg_s_max": round(float(np.max(peaks)), 1),
        "peak_turn_rate_deg_s_median": round(float(np.median(peaks)), 1),
        "runs": runs,
    }


def run(args: argparse.Namespace) -> dict[str, Any]:
    from handctl.config import load_hand
    from handctl.planning.models import FAMILIES, Spread, perturb
    from handctl.recipes.loader import load_recipe
    from handctl.sim.params import parse_sim

    hand = load_hand(args.hand)
    recipe = load_recipe(args.recipe, hand)
    params = parse_sim(hand)
    out: dict[str, Any] = {"benchmark": "experiment", "recipe": str(args.recipe.name),
                           "swap_deg": args.swap_deg,
                           "min_total_turn_deg": recipe.min_total_turn_deg,
                           "spread": Spread().as_dict()}
    print("nominal:", file=sys.stderr)
    nominal = _one(hand, recipe, None, None, args.swap_deg)
    out["nominal"] = {k: nominal[k] for k in ("success", "swap", "total_rotation_deg",
                                              "phase_angles_deg", "peak_turn_rate_deg_s")}
    if not args.nominal:
        groups = [*FAMILIES, "all"] if args.family is None else [args.family]
        out["families"] = {}
        for group in groups:
            spread = Spread() if group == "all" else Spread().only(group)
            print(f"{group}:", file=sys.stderr)
            runs = []
            for seed in range(args.first_seed, args.first_seed + args.seeds):
                model = perturb(params, np.random.default_rng(seed), spread, hand)
                runs.append(_one(hand, recipe, seed, model, args.swap_deg))
            out["families"][group] = _figures(runs)
        last = out["families"]["all" if "all" in out["families"] else groups[-1]]
        out["success_rate"] = last["success_rate"]
        out["swap_rate"] = last["swap_rate"]
        out["worst_success_rate"] = min(f["success_rate"] for f in out["families"].values())
        out["peak_turn_rate_deg_s_max"] = max(f["peak_turn_rate_deg_s_max"]
                                              for f in out["families"].values())
    p50, p99 = _estimator_cost_us(hand, recipe)
    out["estimator_us_p50"] = round(p50, 2)
    out["estimator_us_p99"] = round(p99, 2)
    return out
