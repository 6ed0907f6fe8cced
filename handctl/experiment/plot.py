"""Pictures: each phase's torque region (``plan --plot``). The overview of a run (``run recipe
--plot``) is drawn from its recording, as its replay's is (``handctl.recording.plot``).

matplotlib is imported inside the functions and drives an Agg canvas directly (no pyplot, no
global backend switch), as in ``handctl.analysis.plot``.
"""

from __future__ import annotations

import math
import re
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from handctl.config import FingerConfig, HandConfig
from handctl.handshape import hand_span
from handctl.wholefile import save_picture


def plot_phase_region(
    path: Path,
    title: str,
    analysis: Any,
    torques: tuple[float, ...],
    hand: HandConfig,
    no_analysis: str = "no analysis for this phase (no wanted motion or no contact)",
) -> Path:
    """A phase's robust torque region, Fig. 3 style, with the chosen torque marked.

    The hand's torques are cut to a plane as eq. 25 does, keeping ratios fixed: here within
    each side of the hand, ``τ = u₁ τ°_left + u₂ τ°_right`` with ``τ°`` the analysis' torque
    (the one with the largest margin), split into the part of the fingers based left of the
    palm's middle (or on it) and the part of those based right of it. Each part
    is realisable on its own (the statics are block diagonal by finger), so the plane holds a
    true 2D region and ``τ°`` is ``(1, 1)``. The chosen torque is marked where it projects on
    the plane, with its distance from it: the search moves off the analysis' plane when the
    simulated hand asks for it. Without an analysis torque the plane is the chosen torque's
    own, and the region is empty (nothing to draw but the limits and the choice), which
    ``no_analysis`` says why."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    from matplotlib.patches import Polygon as PolygonPatch

    from handctl.analysis.conditions import build_conditions
    from handctl.analysis.exact import exact_torque_set
    from handctl.analysis.model import AnalysisError
    from handctl.analysis.polygons import intersect
    from handctl.analysis.slices import TorqueSlice

    chosen = np.asarray(torques, dtype=float)
    found = analysis is not None and analysis.found and analysis.torques is not None
    ref = np.asarray(analysis.torques, dtype=float) if found else chosen
    limits = np.asarray([j.tau_max for j in hand.joints], dtype=float)
    middle, _ = hand_span(hand)
    left_fingers = [f for f in hand.fingers if f.base_x <= middle]
    right_fingers = [f for f in hand.fingers if f.base_x > middle]
    left_joints = {j.name for f in left_fingers for j in f.joints}
    left = np.array([j.name in left_joints for j in hand.joints])
    basis = np.zeros((len(ref), 2))
    basis[left, 0] = ref[left]
    basis[~left, 1] = ref[~left]
    for col, side in ((0, left), (1, ~left)):
        if float(np.max(np.abs(basis[:, col]))) < 1e-9:
            basis[side, col] = 0.01
    # the per-joint limits in the plane: rows scaled so that |τ_j| <= tau_max_j reads |.| <= 1
    limit_slice = TorqueSlice(basis / limits[:, None], 1.0)
    limit_poly = limit_slice.limit_polygon()
    u_chosen, *_ = np.linalg.lstsq(basis, chosen, rcond=None)
    off = float(np.linalg.norm(basis @ u_chosen - chosen))
    region: list[np.ndarray] = []
    realisable: list[np.ndarray] = []
    note = ""
    if analysis is None or analysis.snapshot is None or not analysis.directions:
        note = no_analysis
    elif not found:
        note = f"the analysis has no torque: {analysis.reason}"[:110]
    else:
        try:
            conditions = build_conditions(
                analysis.snapshot.grasp, {k: np.array(v) for k, v in analysis.directions.items()}
            )
            ts = exact_torque_set(conditions, TorqueSlice(basis, float(np.max(limits))))
            # the exact set is cut by one scalar limit; cut it again by the per-joint ones
            halves = limit_slice.limit_halfplanes()
            region = [q for q in (intersect(p, halves) for p in ts.region) if len(q) >= 3]
            realisable = [q for q in (intersect(p, halves) for p in ts.realisable) if len(q) >= 3]
        except AnalysisError as exc:
            note = f"no region: {exc}"[:110]
    fig = Figure(figsize=(5.8, 5.4), dpi=110)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 1, 1)
    for poly in realisable:
        ax.add_patch(PolygonPatch(poly, closed=True, facecolor="0.92", edgecolor="none"))
    for i, poly in enumerate(region):
        ax.add_patch(
            PolygonPatch(
                poly,
                closed=True,
                facecolor="0.6",
                edgecolor="black",
                hatch="////",
                lw=0.8,
                label="robust region" if i == 0 else None,
            )
        )
    ax.add_patch(
        PolygonPatch(
            limit_poly, closed=True, fill=False, edgecolor="black", lw=1.2, label="|τ| ≤ tau_max"
        )
    )
    if found:
        ax.plot(
            [1.0],
            [1.0],
            marker="o",
            color="black",
            markersize=6,
            linestyle="none",
            label="analysis: largest margin",
        )
    ax.plot(
        [u_chosen[0]],
        [u_chosen[1]],
        marker="*",
        color="tab:red",
        markersize=13,
        linestyle="none",
        label=f"chosen torque ({off:.3f} N·m off the plane)",
    )
    lo, hi = limit_poly.min(axis=0), limit_poly.max(axis=0)
    pad = 0.08 * float(max(hi - lo))
    ax.set_xlim(float(lo[0]) - pad, float(hi[0]) + pad)
    ax.set_ylim(float(lo[1]) - pad, float(hi[1]) + pad)
    ax.axhline(0.0, color="black", lw=0.6)
    ax.axvline(0.0, color="black", lw=0.6)
    which = "analysis'" if found else "chosen"
    ax.set_xlabel(f"u₁: scale of the {which} torques of {_fingers(left_fingers)}")
    ax.set_ylabel(f"u₂: scale of the {which} torques of {_fingers(right_fingers)}")
    ax.set_title(title + (f"\n{note}" if note else ""), fontsize=8)
    ax.legend(loc="upper left", fontsize=7)
    ax.grid(True, lw=0.3)
    fig.tight_layout()
    out = Path(path)
    save_picture(fig, out)
    return out


def plot_plan(result: Any, directory: Path) -> list[Path]:
    """One region PNG per phase of a plan (``PlanResult``), in ``directory``."""
    directory.mkdir(parents=True, exist_ok=True)
    hand = result.hand
    out = []
    for k, plan in enumerate(result.phases):
        title, why = plan_plot_title(plan)
        out.append(
            plot_phase_region(
                directory / plan_plot_name(k, plan.phase.name),
                title,
                plan.analysis,
                plan.phase.torques,
                hand,
                why,
            )
        )
    return out


def plan_plot_title(plan: Any) -> tuple[str, str]:
    """The title of a plan's phase's region plot (a ``PhasePlan``), and what its plot says
    when it has no analysis. A kept phase's provenance is the base's (``kept_from``): its
    margin and score are not this plan's, and no analysis ran here to draw a region with; its
    plot said "analysis margin 1.35 N" over "no analysis for this phase"."""
    prov = plan.provenance
    score = prov.get("search", {}).get("score")
    margin = prov.get("analysis", {}).get("margin_N")
    kept = prov.get("kept_from")
    there = " there" if kept else ""
    title = (
        f"{plan.phase.name} ({plan.spec.kind})"
        + (f", kept from {kept}" if kept else "")
        + (f", analysis margin {margin} N{there}" if margin is not None else "")
        + (f", search score {score}{there}" if score is not None else "")
    )
    if plan.spec.kind == "turn":
        title += f", wanted turn {math.degrees(plan.spec.turn):+.0f} deg"
    why = (
        f"torques kept from {kept}: no analysis ran in this plan, no region drawn"
        if kept
        else "no analysis for this phase (no wanted motion or no contact)"
    )
    return title, why


def plan_plot_name(index: int, phase: str) -> str:
    """The file name of the region plot of a plan's phase ``index`` (from 0): known before
    the search, so that ``plan --plot`` can look at what it would replace before it runs."""
    return f"{index + 1:02d}_{_file_part(phase)}.png"


def _file_part(name: str) -> str:
    """A phase's name as part of a file name: what a file name cannot hold (a separator, a
    dot-dot, more than a name's length) made a plan fail only after its whole search, or wrote
    outside ``--plot``'s directory. Letters, digits, ``-`` and ``_`` are kept, anything else is
    ``_``, and the part is cut to 80 characters (the phase number before it keeps it unique)."""
    return re.sub(r"[^A-Za-z0-9_-]", "_", name)[:80] or "_"


def _fingers(fingers: Sequence[FingerConfig]) -> str:
    """'finger NAME', 'fingers NAME, NAME', or 'no finger'."""
    if not fingers:
        return "no finger"
    return ("finger " if len(fingers) == 1 else "fingers ") + ", ".join(f.name for f in fingers)
