"""A PNG of a torque set in the style of the paper's Fig. 3 (region over (τ_11, τ_21)).

matplotlib is imported inside the function and drives an Agg canvas directly (no pyplot, no
global backend switch), so importing handctl never pays for matplotlib and a caller's own
backend is left alone.
"""

from __future__ import annotations

from pathlib import Path

from handctl.analysis.exact import ExactTorqueSet
from handctl.analysis.frames import Array
from handctl.wholefile import save_picture


def plot_torque_set(
    torque_set: ExactTorqueSet, path: Path, title: str, best: Array | None = None
) -> None:
    """Write the region (hatched), the realisable torques (light) and the torque limit."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    from matplotlib.patches import Polygon as PolygonPatch

    fig = Figure(figsize=(5.2, 5.0), dpi=120)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 1, 1)
    for poly in torque_set.realisable:
        if len(poly) >= 3:
            ax.add_patch(
                PolygonPatch(
                    poly, closed=True, facecolor="0.92", edgecolor="none", label="realisable"
                )
            )
    for i, poly in enumerate(torque_set.region):
        ax.add_patch(
            PolygonPatch(
                poly,
                closed=True,
                facecolor="0.55",
                edgecolor="black",
                hatch="////",
                linewidth=1.0,
                label="torque set" if i == 0 else None,
            )
        )
    limit = torque_set.limit
    ax.add_patch(PolygonPatch(limit, closed=True, fill=False, edgecolor="black", linewidth=1.2))
    if best is not None:
        ax.plot(
            [best[0]],
            [best[1]],
            marker="o",
            color="black",
            markersize=5,
            linestyle="none",
            label="largest margin",
        )
    lo, hi = limit.min(axis=0), limit.max(axis=0)
    pad = 0.06 * float(max(hi - lo))
    ax.set_xlim(float(lo[0]) - pad, float(hi[0]) + pad)
    ax.set_ylim(float(lo[1]) - pad, float(hi[1]) + pad)
    ax.axhline(0.0, color="black", linewidth=0.6)
    ax.axvline(0.0, color="black", linewidth=0.6)
    ax.set_aspect("equal")
    ax.set_xlabel(r"$\tau_{11}$ [N·m]")
    ax.set_ylabel(r"$\tau_{21}$ [N·m]")
    ax.set_title(title, fontsize=10)
    ax.legend(loc="upper left", fontsize=8, framealpha=0.9)
    fig.tight_layout()
    save_picture(fig, Path(path))
