"""Exact torque set against a grid of LPs: ``python tools/bench.py analysis --json``.

Both methods classify the same 121×121 grid over the torque box of the paper's Fig. 3 scenario
(by default for both of the paper's ratio settings). ``exact_ms`` is the exact method (dual
vertices, polygons, and the closed-form classification of every grid point), the median of a
few repetitions; ``lp_grid_ms`` is one LP per condition and point (stopping at a point's first
failed condition), measured once in the same run. ``speedup`` is their ratio.
``disagreements`` counts grid points classified differently (inside / not inside, realisable /
not) whose distance to the exact boundary exceeds ``boundary_tolerance`` (N·m); points closer
than that lie on the boundary, where a strict inequality and floating point decide, not the
method.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from handctl.analysis.conditions import build_conditions  # noqa: E402
from handctl.analysis.exact import exact_torque_set  # noqa: E402
from handctl.analysis.model import load_scenario  # noqa: E402
from handctl.analysis.oracle import lp_grid  # noqa: E402
from handctl.analysis.slices import ratio_slice  # noqa: E402
from handctl.executor import check_pool_options, open_pool  # noqa: E402
from handctl.progress import Progress, say  # noqa: E402

#: One line of ``bench.py --help`` (read from the source there, without importing this).
SUMMARY = "the exact torque set against a grid of LPs, on the paper's Fig. 3 scenario"

PAPER_K = ((0.9, 0.1), (1.2, 0.5))


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--scenario", type=Path, default=ROOT / "config" / "analysis" / "paper_fig3.yaml"
    )
    parser.add_argument(
        "--k",
        type=float,
        nargs=2,
        action="append",
        default=None,
        metavar=("K1", "K2"),
        help="torque ratios (repeatable; default: the paper's two settings)",
    )
    parser.add_argument("--grid", type=int, default=121, help="points per axis")
    parser.add_argument("--repeat", type=int, default=5, help="repetitions of the exact method")
    parser.add_argument("--tolerance", type=float, default=1e-6, help="boundary tolerance, N·m")
    parser.add_argument(
        "--workers",
        type=int,
        default=1,
        help="processes for the LP grid (default 1: the speedup compares the "
        "two methods on one core)",
    )


def run(args: argparse.Namespace) -> dict[str, Any]:
    # before the first exact set is timed; no cluster to point at (no --scheduler here)
    check_pool_options(args.workers, None, offers_scheduler=False)
    scenario = load_scenario(args.scenario)
    conditions = build_conditions(scenario.grasp, scenario.directions)
    settings = [tuple(k) for k in args.k] if args.k else list(PAPER_K)
    exact_s = 0.0
    lp_s = 0.0
    disagreements = 0
    boundary_points = 0
    details: list[dict[str, Any]] = []
    for k in settings:
        torque_slice = ratio_slice(scenario.grasp, k, scenario.tau_max)
        lo, hi = torque_slice.bounds()
        xs = np.linspace(lo[0], hi[0], args.grid)
        ys = np.linspace(lo[1], hi[1], args.grid)
        gx, gy = np.meshgrid(xs, ys)
        points = np.column_stack([gx.ravel(), gy.ravel()])

        times = []
        for _ in range(max(1, args.repeat)):
            start = time.perf_counter()
            ts = exact_torque_set(conditions, torque_slice)
            exact_inside = ts.inside_mask(points)
            exact_real = ts.realisable_mask(points)
            times.append(time.perf_counter() - start)
        exact_s += statistics.median(times)

        say(f"k = {k}: {args.grid}×{args.grid} grid of LPs ...")
        start = time.perf_counter()
        with (
            open_pool(args.workers, offers_scheduler=False) as pool,
            Progress("LP grid rows", len(ys)) as bar,
        ):
            lp_real, lp_inside = lp_grid(conditions, torque_slice, xs, ys, pool, bar)
        lp_s += time.perf_counter() - start

        differ_in = lp_inside.ravel() != exact_inside
        differ_real = lp_real.ravel() != exact_real
        dist_in = ts.boundary_distance(points)
        dist_real = ts.realisable_boundary_distance(points)
        bad = (differ_in & (dist_in > args.tolerance)) | (
            differ_real & (dist_real > args.tolerance)
        )
        near = (differ_in | differ_real) & ~bad
        disagreements += int(bad.sum())
        boundary_points += int(near.sum())
        details.append(
            {
                "k": list(k),
                "area": ts.area,
                "realisable_area": ts.realisable_area,
                "inside_points": int(exact_inside.sum()),
                "disagreements": int(bad.sum()),
                "boundary_differences": int(near.sum()),
            }
        )
    return {
        "exact_ms": round(exact_s * 1e3, 3),
        "lp_grid_ms": round(lp_s * 1e3, 1),
        "speedup": round(lp_s / exact_s, 1),
        "disagreements": disagreements,
        "boundary_differences": boundary_points,
        "boundary_tolerance": args.tolerance,
        "grid": args.grid,
        "settings": details,
    }
