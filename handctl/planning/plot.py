"""Pictures: the overview of a run (``run recipe --plot``) and each phase's torque region
(``plan --plot``).

matplotlib is imported inside the functions and drives an Agg canvas directly (no pyplot, no
global backend switch), as in ``handctl.analysis.plot``.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np

from handctl.planning.experiment import LIFT_HEIGHT, Trace, _segments
from handctl.recipes.schema import Recipe

_PHASE_COLOURS = ("#f2f2f2", "#dde8f5")


def plot_run(trace: Trace, path: Path, recipe: Recipe,
             experiment: dict[str, Any] | None = None) -> Path:
    """One PNG: phases (shaded), transmitted joint torques, object heights above the table,
    and the centre-line angle (true and estimated)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    a = trace.arrays()
    t = a["t"]
    fig = Figure(figsize=(10.0, 9.0), dpi=110)
    FigureCanvasAgg(fig)
    axes = fig.subplots(3, 1, sharex=True)
    segments = _segments(trace.phase)
    for ax in axes:
        for k, (_name, s, e) in enumerate(segments):
            if e > s:
                ax.axvspan(t[s], t[e - 1], color=_PHASE_COLOURS[k % 2], zorder=0)
        ax.grid(True, lw=0.3)
    for name, s, e in segments:
        if e > s and name not in ("-",):
            axes[0].text((t[s] + t[e - 1]) / 2, 1.0, name, rotation=90, ha="center",
                         va="top", fontsize=7, transform=axes[0].get_xaxis_transform())
    torques = a["torques"]
    for j, name in enumerate(trace.joint_names):
        axes[0].plot(t, torques[:, j], lw=0.8, label=name,
                     linestyle=("-", "--", ":")[j // 3 % 3])
    axes[0].set_ylabel("joint torque (N·m)")
    axes[0].legend(ncol=9, fontsize=6, loc="lower left")
    heights = a["heights"] * 1e3
    axes[1].plot(t, heights[:, 0], label="object 1")
    axes[1].plot(t, heights[:, 1], label="object 2")
    axes[1].axhline(LIFT_HEIGHT * 1e3, color="k", lw=0.6, ls="--", label="10 mm")
    axes[1].set_ylabel("height above rest (mm)")
    axes[1].legend(fontsize=7, loc="upper left")
    true = np.degrees(a["true_angle"])
    # each estimate drawn on the true angle's branch (the estimate is an angle in
    # (-180, 180], the truth is unwrapped): the gap between the lines is the estimator's error
    est = np.degrees(a["estimate"][:, 0])
    gap = (est - true + 180.0) % 360.0 - 180.0
    est_valid = np.where(a["valid"] & np.isfinite(est), true + gap, np.nan)
    axes[2].plot(t, true, label="true (simulation)")
    axes[2].plot(t, est_valid, lw=0.8, label="estimated (joint angles)")
    axes[2].set_ylabel("centre-line angle (deg)")
    axes[2].set_xlabel("time (s)")
    axes[2].legend(fontsize=7, loc="lower left")
    title = f"{recipe.name}"
    if experiment:
        title += (f": lifted {experiment.get('lifted')}, turned "
                  f"{experiment.get('total_rotation_deg')} deg, dropped "
                  f"{experiment.get('dropped')}, estimator p95 "
                  f"{experiment.get('estimator_error_deg')} deg")
    fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    out = Path(path)
    fig.savefig(str(out))
    return out


def plot_phase_region(path: Path, title: str, analysis: Any, torques: tuple[float, ...],
                      tau_max: tuple[float, ...], joint_names: tuple[str, ...]) -> Path:
    """A phase's robust torque region, Fig. 3 style, with the chosen torque marked.

    The nine torques are cut to a plane as eq. 25 does, keeping ratios fixed: here within each
    side of the hand, ``τ = u₁ τ°₁₂ + u₂ τ°₃`` with ``τ°`` the analysis' torque (the one with
    the largest margin), split into its finger-1-and-2 part and its finger-3 part. Each part
    is realisable on its own (the statics are block diagonal by finger), so the plane holds a
    true 2D region and ``τ°`` is ``(1, 1)``. The chosen torque is marked where it projects on
    the plane, with its distance from it: the search moves off the analysis' plane when the
    simulated hand asks for it. Without an analysis torque the plane is the chosen torque's
    own, and the region is empty (nothing to draw but the limits and the choice)."""
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
    limits = np.asarray(tau_max, dtype=float)
    left = np.array([not name.startswith("f3") for name in joint_names])
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
        note = "no analysis for this phase (no wanted motion or no contact)"
    elif not found:
        note = f"the analysis has no torque: {analysis.reason}"[:110]
    else:
        try:
            conditions = build_conditions(analysis.snapshot.grasp,
                                          {k: np.array(v) for k, v in
                                           analysis.directions.items()})
            ts = exact_torque_set(conditions, TorqueSlice(basis, float(np.max(limits))))
            # the exact set is cut by one scalar limit; cut it again by the per-joint ones
            halves = limit_slice.limit_halfplanes()
            region = [q for q in (intersect(p, halves) for p in ts.region) if len(q) >= 3]
            realisable = [q for q in (intersect(p, halves) for p in ts.realisable)
                          if len(q) >= 3]
        except AnalysisError as exc:
            note = f"no region: {exc}"[:110]
    fig = Figure(figsize=(5.8, 5.4), dpi=110)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 1, 1)
    for poly in realisable:
        ax.add_patch(PolygonPatch(poly, closed=True, facecolor="0.92", edgecolor="none"))
    for i, poly in enumerate(region):
        ax.add_patch(PolygonPatch(poly, closed=True, facecolor="0.6", edgecolor="black",
                                  hatch="////", lw=0.8, label="robust region" if i == 0
                                  else None))
    ax.add_patch(PolygonPatch(limit_poly, closed=True, fill=False, edgecolor="black", lw=1.2,
                              label="|τ| ≤ tau_max"))
    if found:
        ax.plot([1.0], [1.0], marker="o", color="black", markersize=6, linestyle="none",
                label="analysis: largest margin")
    ax.plot([u_chosen[0]], [u_chosen[1]], marker="*", color="tab:red", markersize=13,
            linestyle="none", label=f"chosen torque ({off:.3f} N·m off the plane)")
    lo, hi = limit_poly.min(axis=0), limit_poly.max(axis=0)
    pad = 0.08 * float(max(hi - lo))
    ax.set_xlim(float(lo[0]) - pad, float(hi[0]) + pad)
    ax.set_ylim(float(lo[1]) - pad, float(hi[1]) + pad)
    ax.axhline(0.0, color="black", lw=0.6)
    ax.axvline(0.0, color="black", lw=0.6)
    which = "analysis'" if found else "chosen"
    ax.set_xlabel(f"u₁: scale of the {which} torques of fingers 1 and 2")
    ax.set_ylabel(f"u₂: scale of the {which} torques of finger 3")
    ax.set_title(title + (f"\n{note}" if note else ""), fontsize=8)
    ax.legend(loc="upper left", fontsize=7)
    ax.grid(True, lw=0.3)
    fig.tight_layout()
    out = Path(path)
    fig.savefig(str(out))
    return out


def plot_plan(result: Any, directory: Path) -> list[Path]:
    """One region PNG per phase of a plan (``PlanResult``), in ``directory``."""
    directory.mkdir(parents=True, exist_ok=True)
    hand = result.hand
    out = []
    for k, plan in enumerate(result.phases):
        prov = plan.provenance
        score = prov.get("search", {}).get("score")
        margin = prov.get("analysis", {}).get("margin_N")
        title = (f"{plan.phase.name} ({plan.spec.kind})"
                 + (f", analysis margin {margin} N" if margin is not None else "")
                 + (f", search score {score}" if score is not None else ""))
        if plan.spec.kind == "turn":
            title += f", wanted turn {math.degrees(plan.spec.turn):+.0f} deg"
        out.append(plot_phase_region(directory / f"{k + 1:02d}_{plan.phase.name}.png", title,
                                     plan.analysis, plan.phase.torques,
                                     tuple(j.tau_max for j in hand.joints), hand.joint_names))
    return out
