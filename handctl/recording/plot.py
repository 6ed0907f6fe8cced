"""A PNG of a recording: torques over time with the recipe's phases as bands, and (simulated
runs) the objects' heights and the angle of the line through their centres.

One row of axes per finger, each joint a colour: desired dashed, applied solid, measured (TDT)
dotted, so a joint that does not follow its command stands out. matplotlib drives an Agg canvas
directly (no pyplot), as in ``handctl.analysis.plot``.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from handctl.recording.replay import NOT_PHASES, Series

_COLOURS = ("tab:blue", "tab:orange", "tab:green", "tab:red", "tab:purple", "tab:brown")
_OUTSIDE: dict[str, Any] = {"loc": "upper left", "bbox_to_anchor": (1.005, 1.0),
                            "fontsize": 7, "framealpha": 0.9, "borderaxespad": 0.0}


def _finger_groups(joints: list[str]) -> list[list[int]]:
    """Joint indices grouped by finger, from names like ``f1_j2`` (one group if unnamed)."""
    groups: dict[str, list[int]] = {}
    for i, name in enumerate(joints):
        groups.setdefault(name.split("_")[0] if "_" in name else "all", []).append(i)
    return list(groups.values())


def _bands(ax: Any, phases: list[dict[str, Any]], label: bool) -> None:
    shown = [p for p in phases if p["name"] not in NOT_PHASES]
    for i, phase in enumerate(shown):
        ax.axvspan(phase["start_s"], phase["end_s"], color="0.93" if i % 2 else "0.86",
                   zorder=0, linewidth=0)
        if label:
            ax.text((phase["start_s"] + phase["end_s"]) / 2, 1.02, phase["name"],
                    transform=ax.get_xaxis_transform(), ha="center", va="bottom",
                    fontsize=7, rotation=20 if len(shown) > 5 else 0)


def plot_recording(series: Series, path: Path, title: str) -> None:
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    groups = _finger_groups(series.joints)
    has_objects = len(series.objects) > 0
    rows = len(groups) + (2 if has_objects else 0)
    fig = Figure(figsize=(12, 2.3 * rows + 0.8), dpi=110)
    FigureCanvasAgg(fig)
    axes = fig.subplots(rows, 1, sharex=True, squeeze=False)[:, 0]
    n = len(series.joints)
    tq, js = series.torque, series.joint
    for row, group in enumerate(groups):
        ax = axes[row]
        _bands(ax, series.phases, label=row == 0)
        for c, j in enumerate(group):
            colour = _COLOURS[c % len(_COLOURS)]
            name = series.joints[j]
            if len(tq):
                ax.plot(tq[:, 0], tq[:, 1 + j], color=colour, linestyle="--", linewidth=0.8)
                ax.plot(tq[:, 0], tq[:, 1 + n + j], color=colour, linewidth=1.2, label=name)
            if len(js):
                ax.plot(js[:, 0], js[:, 1 + j], color=colour, linestyle=":", linewidth=0.8,
                        alpha=0.6)
        ax.axhline(0.0, color="black", linewidth=0.5)
        ax.set_ylabel("torque [N·m]")
        ax.legend(**_OUTSIDE)
    for fault in (e for e in series.events if e["kind"] == "fault"):
        for ax in axes:
            ax.axvline(fault["t_s"], color="red", linewidth=1.0)
        axes[0].text(fault["t_s"], 0.02, f" {fault['name']}", color="red", fontsize=7,
                     transform=axes[0].get_xaxis_transform())
    axes[0].plot([], [], color="black", linestyle="--", linewidth=0.8, label="desired")
    axes[0].plot([], [], color="black", linewidth=1.2, label="applied")
    axes[0].plot([], [], color="black", linestyle=":", linewidth=1.0, label="measured (TDT)")
    axes[0].legend(**_OUTSIDE)
    if has_objects:
        ob = series.objects
        ax = axes[len(groups)]
        _bands(ax, series.phases, label=False)
        for i, name in enumerate(series.object_names):
            ax.plot(ob[:, 0], ob[:, 3 + 3 * i] * 1e3, label=f"{name} height (y)",
                    color=_COLOURS[i % len(_COLOURS)])
        ax.set_ylabel("height [mm]")
        ax.legend(**_OUTSIDE)
        ax = axes[len(groups) + 1]
        _bands(ax, series.phases, label=False)
        angle = np.unwrap(ob[:, 1]) if not np.isnan(ob[:, 1]).all() else ob[:, 1]
        ax.plot(ob[:, 0], np.degrees(angle), color="black",
                label="line through the centres")
        ax.set_ylabel("angle [deg]")
        ax.legend(**_OUTSIDE)
    axes[-1].set_xlabel("time [s]")
    if len(series.timing):
        axes[-1].set_xlim(0.0, max(float(series.timing[-1, 0]), 1e-3))
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    fig.savefig(str(path))


def title_of(summary: dict[str, Any]) -> str:
    parts = [summary.get("recipe") or "recording", f"on {summary.get('hand') or '?'}",
             f"({summary.get('mode') or '?'})", f"— {summary.get('outcome', '')}"]
    if not summary.get("complete", True):
        parts.append("[damaged]" if summary.get("damaged") else "[truncated]")
    return " ".join(p for p in parts if p)
