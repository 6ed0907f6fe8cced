"""What ``handctl analyze torque-set`` does, as a function the CLI calls and prints the result of.

The grid in the JSON is filled from the exact method (its closed-form margins), so it agrees with
the polygons by construction; the LP oracle checks both in the tests and in
``tools/bench.py analysis``.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from handctl.analysis.conditions import build_conditions
from handctl.analysis.exact import exact_torque_set
from handctl.analysis.model import load_scenario
from handctl.analysis.planner import plan_for_conditions
from handctl.analysis.slices import ratio_slice
from handctl.errors import ConfigError, HandctlError
from handctl.wholefile import left_as_it_was, write_whole

GRID_POINTS = 121


def torque_set_report(
    scenario: Path,
    k: tuple[float, float],
    json_path: Path | None,
    plot_path: Path | None,
    progress: Callable[[str], None] | None = None,
) -> str:
    """Compute the torque set of ``scenario`` for ``τ_i2 = k_i τ_i1`` (eq. 25); write the JSON
    and the PNG if asked; return a short summary for a person.

    Raises ``ConfigError`` for a bad scenario file, and for a grasp that eq. 25 does not fit (it
    needs two fingers of two joints).
    """
    say = progress or (lambda _msg: None)
    say(f"loading {scenario}")
    sc = load_scenario(scenario)
    grasp = sc.grasp
    if len(grasp.fingers) != 2 or any(f.joints != 2 for f in grasp.fingers):
        # the scenario's shape is what is wrong (bad input), not the analysis of it
        raise ConfigError(
            str(scenario),
            "fingers",
            "two fingers of two joints each (torque-set draws the paper's eq. 25 slice, "
            "tau_i2 = k_i tau_i1; a hand of another shape is planned with handctl plan)",
            ", ".join(f"{f.name}: {f.joints} joint(s)" for f in grasp.fingers),
        )
    conditions = build_conditions(grasp, sc.directions)
    torque_slice = ratio_slice(grasp, k, sc.tau_max)
    say("computing the exact torque set")
    ts = exact_torque_set(conditions, torque_slice)
    plan = plan_for_conditions(conditions, sc.tau_max, [(1.0, k[0]), (1.0, k[1])])
    best = np.array([plan.tau[0], plan.tau[2]]) if plan.found else None

    lo, hi = torque_slice.bounds()
    xs = np.linspace(lo[0], hi[0], GRID_POINTS)
    ys = np.linspace(lo[1], hi[1], GRID_POINTS)
    gx, gy = np.meshgrid(xs, ys)
    points = np.column_stack([gx.ravel(), gy.ravel()])
    realisable = ts.realisable_mask(points).reshape(gx.shape)
    inside = ts.inside_mask(points).reshape(gx.shape)
    grid_inside: list[list[bool | None]] = [
        [bool(inside[i, j]) if realisable[i, j] else None for j in range(len(xs))]
        for i in range(len(ys))
    ]

    written: list[str] = []
    if json_path is not None:
        say(f"writing {json_path}")
        document: dict[str, Any] = {
            "scenario": str(scenario),
            "k": [float(k[0]), float(k[1])],
            "reading": grasp.reading,
            "tau_max": sc.tau_max,
            "conditions": list(conditions.labels),
            "box": {"tau11": [float(lo[0]), float(hi[0])], "tau21": [float(lo[1]), float(hi[1])]},
            "region": {"polygons": [_rounded(p) for p in ts.region], "area": ts.area},
            "realisable_area": ts.realisable_area,
            "realisable": {"polygons": [_rounded(p) for p in ts.realisable]},
            "best": (
                {
                    "tau11": plan.tau[0],
                    "tau21": plan.tau[2],
                    "tau": list(plan.tau),
                    "margin": plan.margin,
                }
                if plan.found
                else None
            ),
            "grid": {
                "tau11": [float(x) for x in xs],
                "tau21": [float(y) for y in ys],
                "inside": grid_inside,
                "layout": "inside[i][j] is the point (tau11[j], tau21[i]); null where "
                "no contact forces realise the torques",
            },
            "units": {"tau": "N·m", "area": "(N·m)²", "margin": "N"},
        }
        _write_json(json_path, document)
        written.append(str(json_path))
    if plot_path is not None:
        say(f"drawing {plot_path}")
        from handctl.analysis.plot import plot_torque_set

        plot_torque_set(
            ts,
            plot_path,
            f"{Path(scenario).name}: k1 = {k[0]:g}, k2 = {k[1]:g} ({grasp.reading} reading)",
            best,
        )
        written.append(str(plot_path))

    lines = [
        f"torque set of {scenario} for tau_i2 = k_i tau_i1, k = ({k[0]:g}, {k[1]:g}), "
        f"{grasp.reading} reading",
        f"  box: tau11 in [{lo[0]:.3g}, {hi[0]:.3g}] N·m, tau21 in [{lo[1]:.3g}, {hi[1]:.3g}] N·m",
        f"  realisable area {ts.realisable_area:.4g} (N·m)², torque-set area {ts.area:.4g} "
        f"(N·m)² in {len(ts.region)} polygon(s)",
        f"  grid: {int(inside.sum())} of {inside.size} points inside, "
        f"{int((~realisable).sum())} not realisable",
    ]
    if plan.found:
        lines.append(
            f"  largest robust margin {plan.margin:.4g} N at tau11 = {plan.tau[0]:.4g}, "
            f"tau21 = {plan.tau[2]:.4g} N·m"
        )
    else:
        margin = "none" if math.isinf(plan.margin) else f"{plan.margin:.4g} N"
        lines.append(f"  no torque moves the objects as wanted (best margin {margin})")
    if written:
        lines.append("  wrote " + ", ".join(written))
    return "\n".join(lines)


def _write_json(path: Path, document: dict[str, Any]) -> None:
    """The ``--json`` document whole or not at all (``wholefile``): written in place, a full
    disk left a cut-off file where the earlier one was, and a bare traceback. A failure is the
    command's (exit 1: the work was done, its file was not written), said as every other
    output's."""
    existed = path.exists()
    try:
        write_whole(path, (json.dumps(document, indent=1) + "\n").encode("utf-8"))
    except OSError as exc:
        raise HandctlError(
            f"--json: {path} could not be written ({exc.strerror or exc}); "
            + left_as_it_was(existed)
        ) from None


def _rounded(poly: np.ndarray[Any, Any]) -> list[list[float]]:
    return [[round(float(x), 12), round(float(y), 12)] for x, y in poly]
