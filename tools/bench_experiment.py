"""The paper's experiment over perturbed simulated hands: is the recipe robust, not lucky?

Each seed draws one model of the hand from the planner's default ``Spread``
(``handctl/planning/models.py``: contact friction, joint dynamics, the objects, their
placement, the start pose, the sensors) and runs the recipe through the whole stack as
``handctl run recipe`` does (bus, nodes, safety, estimator), in lockstep, with the seed as
the sensors' seed. By default every family is varied on its own (``--seeds`` models each),
then all of them at once; ``--family F`` runs one (``all`` for everything at once). A run
succeeds when it completed and its ``experiment.success`` holds (lifted, held, nothing
dropped, the recipe's ``min_total_turn_deg``); it is a swap when, besides, the pair turned
``--swap-deg`` (170) or more. Per group: ``success_rate``, ``swap_rate``, the peak true
centre-line rate (deg/s, the largest and the median over the runs) and
``before_manipulation_failures``, the runs that never lifted and held the pair;
``quasi_static_rate``, the fraction of runs whose peak stayed at or under 180°/s (what the
quasi-static analysis covers, ``MAX_TURN_RATE_DEG_S``); ``phase_band_rate``, the fraction
whose every manipulation phase turned ``--phase-deg`` (45) within ``--phase-tolerance-deg``
(10), and ``controlled_turn_rate``, those of them at or under 180°/s as well; the nominal
hand is run once as well. ``ringing_rate``: the runs with a joint whose command rang (a
feedback too stiff for it, ``handctl/online/safety/chatter.py``). ``estimator_us_p50/p99``
is the estimator's own cost per tick on this machine (a benchmark figure, never a test).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path
from typing import Any

import numpy as np

#: One line of ``bench.py --help`` (read from the source there, without importing this).
SUMMARY = "the paper's experiment over perturbed simulated hands: robust, not lucky?"

ROOT = Path(__file__).resolve().parent.parent
DEFAULT_RECIPE = ROOT / "config" / "recipes" / "swap_two_cylinders.yaml"
DEFAULT_HAND = ROOT / "config" / "hands" / "hiroshima_hand.yaml"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--seeds", type=int, default=10, help="perturbed models per group")
    parser.add_argument(
        "--first-seed",
        type=int,
        default=1000,
        help="seed of the first model (models are seed, seed + 1, ...)",
    )
    from handctl.planning.models import FAMILIES

    parser.add_argument(
        "--family",
        default=None,
        choices=[*FAMILIES, "all"],
        help="one family of the spread, or 'all' for all of them at once; "
        "default: each family on its own, then all at once",
    )
    parser.add_argument("--recipe", type=Path, default=DEFAULT_RECIPE)
    parser.add_argument("--hand", type=Path, default=DEFAULT_HAND)
    parser.add_argument(
        "--swap-deg",
        type=float,
        default=170.0,
        help="degrees the pair must turn for a run to count as a swap",
    )
    parser.add_argument(
        "--phase-deg",
        type=float,
        default=45.0,
        help="deg, what each manipulation phase should turn (the paper's steps of 45)",
    )
    parser.add_argument(
        "--phase-tolerance-deg",
        type=float,
        default=10.0,
        help="deg, how far from --phase-deg a phase's turn may be and still count",
    )
    parser.add_argument(
        "--nominal", action="store_true", help="run only the unperturbed hand, once"
    )
    parser.add_argument(
        "--before-manipulation",
        action="store_true",
        help="stop every run where the first manipulation phase would begin (the phases "
        "before it have no exits, so at the sum of their max_s): what fails in the approach, "
        "the lift and the hold, in a third of the time",
    )
    parser.add_argument("--workers", type=int, help="local worker processes (default: every core)")
    parser.add_argument(
        "--scheduler",
        metavar="tcp://HOST:PORT",
        help="run the seeds on this Dask cluster (docs/scale.md)",
    )


def _estimator_cost_us(hand: Any, recipe: Any) -> tuple[float, float]:
    """p50 and p99 of one estimator call over a stored sequence of angles (enveloping and
    open poses), on this machine."""
    from handctl.online.estimator import ObjectEstimator

    est = ObjectEstimator(hand, recipe.objects, recipe.pairs)
    rng = np.random.default_rng(0)
    closed, opened = _cost_poses(hand, recipe)
    poses = [(closed + rng.normal(0.0, 0.02, len(closed))).tolist() for _ in range(2000)]
    poses += [opened.tolist()] * 500
    times = []
    clock = time.perf_counter_ns
    for q in poses:
        t0 = clock()
        est(q)
        times.append(clock() - t0)
    p50, p99 = np.percentile(times, [50, 99])
    return float(p50) / 1e3, float(p99) / 1e3


#: The default hand's enveloping grasp in the manipulation (rad, config joint order) and its
#: open start pose: the poses the estimator's cost has been measured on since it was written.
_DEFAULT_CLOSED = (0.24, 1.46, 1.53, 0.24, 1.46, 1.53, 0.47, -1.57, -1.38)
_DEFAULT_OPEN = (-0.55, -0.1, -0.1, -0.55, -0.1, -0.1, 0.55, 0.1, 0.1)


def _cost_poses(hand: Any, recipe: Any) -> tuple[np.ndarray, np.ndarray]:
    """A closed and an open pose of ``hand`` for the estimator's cost: the default hand's
    own; for another shape, the recipe's first pose hold (where it brings the fingers round
    the objects) or the middle of every joint's range, and the simulated hand's start pose
    (or the same middle)."""
    n = len(hand.joints)
    if n == len(_DEFAULT_CLOSED) and hand.name == "hiroshima_hand":
        return np.array(_DEFAULT_CLOSED), np.array(_DEFAULT_OPEN)
    middle = np.array([(j.angle_min + j.angle_max) / 2 for j in hand.joints])
    held = next((p.pose.angles for p in recipe.phases if p.pose is not None), None)
    closed = np.array(held) if held is not None else middle
    opened = middle
    if hand.sim:
        from handctl.sim.params import parse_sim

        opened = np.array([q for finger in parse_sim(hand).initial_angles for q in finger])
    return closed, opened


def _before_manipulation_s(path: Path, recipe: Any) -> float:
    """s from the start to where the recipe's first manipulation phase begins: the sum of the
    phases' ``max_s`` before it, which must have no exits (else where it begins is not known
    beforehand)."""
    from handctl.errors import ConfigError

    total = 0.0
    for k, phase in enumerate(recipe.phases):
        if phase.manipulates:
            return total
        if phase.exits:
            raise ConfigError(
                str(path),
                f"phases[{k}].exit",
                "no exit before the first manipulation phase (for --before-manipulation)",
                [c.text for c in phase.exits],
            )
        total += phase.max_s
    raise ConfigError(
        str(path),
        "phases",
        "a manipulation phase (named manipulate*, planned as a turn, or ending on a turn)",
        [p.name for p in recipe.phases],
    )


def _say(run: dict[str, Any]) -> None:
    from handctl.progress import say

    say(
        f"{run['family']} seed {run['seed']}: {'ok' if run['success'] else 'FAIL'} lifted "
        f"{run['lifted']} dropped {run['dropped']} turned {run['total_rotation_deg']} deg "
        f"{run['phase_angles_deg']} peak {run['peak_turn_rate_deg_s']} deg/s "
        f"({run['outcome']}, {run['wall_s']:.1f} s)"
        + (f": {run['message']}" if run.get("message") else "")
    )


def in_band(run: dict[str, Any], step_deg: float, tolerance_deg: float) -> bool:
    """Whether every manipulation phase of ``run`` turned the pair ``step_deg`` (signed as
    the recipe turns, ``turn_sense``) within ``tolerance_deg``: the paper's turn in steps,
    each switched on the measured position. A phase that turned the pair back is not in the
    band, and neither is a run without its manipulation phases (stopped before them, or in
    one)."""
    angles = run["phase_angles_deg"] or []
    return len(angles) > 0 and all(abs(a - step_deg) <= tolerance_deg for a in angles)


def turn_sense(recipe: Any) -> float:
    """-1 for a recipe whose manipulation turns the pair clockwise, +1 counter-clockwise: from
    the first manipulation phase's exit on a turn (waiting for it to fall below its value is
    clockwise); +1 without one."""
    for phase in recipe.phases:
        sense = phase.turn_sense() if phase.manipulates else None
        if sense is not None:
            return float(sense)
    return 1.0


def _check_band(phase_deg: float, tolerance_deg: float) -> None:
    """A band that reaches 0 counts a phase that did not turn the pair as one that did."""
    from handctl.errors import ConfigError

    if not tolerance_deg < phase_deg:
        raise ConfigError(
            "--phase-tolerance-deg",
            "",
            f"a tolerance below --phase-deg ({phase_deg:g} deg): a band that reaches 0 "
            "counts a phase that did not turn the pair",
            tolerance_deg,
        )


def _figures(runs: list[dict[str, Any]], step_deg: float, tolerance_deg: float) -> dict[str, Any]:
    from handctl.planning.search import MAX_TURN_RATE_DEG_S

    n = len(runs)
    peaks = [r["peak_turn_rate_deg_s"] or 0.0 for r in runs]
    banded = [in_band(r, step_deg, tolerance_deg) for r in runs]
    return {
        "seeds": n,
        "success_rate": round(sum(r["success"] for r in runs) / n, 3),
        "swap_rate": round(sum(r["swap"] for r in runs) / n, 3),
        "drop_rate": round(sum(bool(r["dropped"]) for r in runs) / n, 3),
        "safety_stop_rate": round(sum(r["outcome"] == "safety_stop" for r in runs) / n, 3),
        # never lifted and held the pair: failed in the approach, the lift or the hold, before
        # any manipulation phase could do anything
        "before_manipulation_failures": sum(not r["lifted"] for r in runs),
        "mean_total_rotation_deg": round(
            float(np.mean([r["total_rotation_deg"] for r in runs])), 2
        ),
        "peak_turn_rate_deg_s_max": round(float(np.max(peaks)), 1),
        "peak_turn_rate_deg_s_median": round(float(np.median(peaks)), 1),
        # turned, not tumbled: the true centre line never faster than the quasi-static
        # analysis covers (a run stopped before the manipulation counts, having turned nothing)
        "quasi_static_rate": round(sum(p <= MAX_TURN_RATE_DEG_S for p in peaks) / n, 3),
        # each manipulation phase its step (--phase-deg, --phase-tolerance-deg), and that
        # with no tumble too: the controlled turn the paper makes
        "phase_band_rate": round(sum(banded) / n, 3),
        # runs with a joint whose command rang for half a second or more (safety.chatter)
        "ringing_rate": round(sum(bool(r.get("ringing_joints")) for r in runs) / n, 3),
        "controlled_turn_rate": round(
            sum(b and p <= MAX_TURN_RATE_DEG_S for b, p in zip(banded, peaks, strict=True)) / n,
            3,
        ),
        "runs": runs,
    }


def run(args: argparse.Namespace) -> dict[str, Any]:
    from handctl.config import load_hand
    from handctl.executor import open_pool
    from handctl.harness.seed_run import SeedRun, run_seed
    from handctl.online.recipes.loader import load_recipe
    from handctl.planning.models import FAMILIES, Spread
    from handctl.portable import portable_hand
    from handctl.progress import Progress, say

    _check_band(args.phase_deg, args.phase_tolerance_deg)
    hand = load_hand(args.hand)
    recipe = load_recipe(args.recipe, hand)
    portable = portable_hand(hand)
    out: dict[str, Any] = {
        "benchmark": "experiment",
        "recipe": str(args.recipe.name),
        "swap_deg": args.swap_deg,
        "phase_deg": args.phase_deg,
        "phase_tolerance_deg": args.phase_tolerance_deg,
        "min_total_turn_deg": recipe.min_total_turn_deg,
        "spread": Spread().as_dict(),
    }
    until = _before_manipulation_s(args.recipe, recipe) if args.before_manipulation else None
    out["before_manipulation_s"] = until
    groups = [] if args.nominal else ([*FAMILIES, "all"] if args.family is None else [args.family])
    # One pool for every run, the nominal first: results come back in this order.
    tasks = [SeedRun(portable, recipe, None, "nominal", args.swap_deg, until)]
    tasks += [
        SeedRun(portable, recipe, seed, group, args.swap_deg, until)
        for group in groups
        for seed in range(args.first_seed, args.first_seed + args.seeds)
    ]
    with open_pool(args.workers, args.scheduler) as pool:
        say(f"experiment on {pool.where}")
        with Progress("runs", len(tasks)) as bar:
            runs = pool.map(run_seed, tasks, bar)
    for r in runs:
        _say(r)
    nominal = runs[0]
    out["nominal"] = {
        k: nominal[k]
        for k in (
            "success",
            "swap",
            "total_rotation_deg",
            "phase_angles_deg",
            "peak_turn_rate_deg_s",
        )
    }
    step_deg = turn_sense(recipe) * args.phase_deg
    out["nominal"]["phases_in_band"] = in_band(nominal, step_deg, args.phase_tolerance_deg)
    if groups:
        out["families"] = {
            group: _figures(
                [r for r in runs[1:] if r["family"] == group],
                step_deg,
                args.phase_tolerance_deg,
            )
            for group in groups
        }
        last = out["families"]["all" if "all" in out["families"] else groups[-1]]
        out["success_rate"] = last["success_rate"]
        out["swap_rate"] = last["swap_rate"]
        out["quasi_static_rate"] = last["quasi_static_rate"]
        out["phase_band_rate"] = last["phase_band_rate"]
        out["controlled_turn_rate"] = last["controlled_turn_rate"]
        out["worst_success_rate"] = min(f["success_rate"] for f in out["families"].values())
        out["peak_turn_rate_deg_s_max"] = max(
            f["peak_turn_rate_deg_s_max"] for f in out["families"].values()
        )
    p50, p99 = _estimator_cost_us(hand, recipe)
    out["estimator_us_p50"] = round(p50, 2)
    out["estimator_us_p99"] = round(p99, 2)
    return out
