"""PNGs of a run: ``replay --plot`` from a recording, and the panels it shares with ``run recipe
--plot`` (``handctl.experiment.plot``), so that both draw the same things the same way.

One panel per finger; a joint has the same colour in every finger (proximal, middle, distal),
and the line style says what the value is: desired dashed, applied solid, measured dotted, with
thin lines of the joint's colour at ±tau_max. Phases are shaded bands named in a strip above the
first panel, never over the traces. Heights are above rest and the turn is signed
counter-clockwise positive, as ``handctl.convention`` defines them for every summary too.
matplotlib drives an Agg canvas directly (no pyplot), as in ``handctl.analysis.plot``.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from handctl.convention import HEIGHT_LABEL, TIME_LABEL, TURN_LABEL, turn_deg
from handctl.recording.replay import NOT_PHASES
from handctl.recording.series import Series

JOINT_COLOURS = ("tab:blue", "tab:orange", "tab:green", "tab:red", "tab:purple", "tab:brown")
#: (line style, width, opacity, z-order): applied wide and pale underneath, so that the desired
#: (dashed) and measured (dotted) lines stay visible where they coincide with it.
STYLES = {
    "desired": ("--", 1.0, 1.0, 3),
    "applied": ("-", 3.0, 0.4, 2),
    "measured": (":", 1.2, 1.0, 4),
}
_OUTSIDE: dict[str, Any] = {
    "loc": "upper left",
    "bbox_to_anchor": (1.005, 1.0),
    "fontsize": 7,
    "framealpha": 0.9,
    "borderaxespad": 0.0,
}


def finger_groups(fingers: Sequence[tuple[str, int]], n_joints: int) -> list[tuple[str, list[int]]]:
    """Joint indices grouped by finger, as the recorded hand config has them (name, joint
    count); one group, "hand", when the log has no hand config."""
    if sum(count for _, count in fingers) != n_joints or not fingers:
        return [("hand", list(range(n_joints)))]
    groups, start = [], 0
    for name, count in fingers:
        groups.append((name, list(range(start, start + count))))
        start += count
    return groups


def phase_bands(axes: Sequence[Any], phases: Sequence[tuple[str, float, float]]) -> None:
    """Shade each phase in every panel and name it in a strip above the first: the names
    alternate between two rows so that short phases do not overlap each other."""
    shown = [p for p in phases if p[0] not in NOT_PHASES and p[2] > p[1]]
    for ax in axes:
        for i, (_name, start, end) in enumerate(shown):
            ax.axvspan(start, end, color="0.93" if i % 2 else "0.86", zorder=0, linewidth=0)
    top = axes[0]
    for i, (name, start, end) in enumerate(shown):
        top.text(
            (start + end) / 2,
            1.03 + 0.13 * (i % 2),
            name,
            transform=top.get_xaxis_transform(),
            ha="center",
            va="bottom",
            fontsize=7,
            clip_on=False,
        )


def torque_panel(
    ax: Any,
    finger: str,
    names: Sequence[str],
    tau_max: Sequence[float],
    series: dict[str, tuple[np.ndarray, np.ndarray]],
) -> None:
    """One finger: ``series`` maps desired/applied/measured to ``(t, values[:, joint])`` with
    the finger's joints as columns; a kind that is missing is left out."""
    for c, name in enumerate(names):
        colour = JOINT_COLOURS[c % len(JOINT_COLOURS)]
        for kind, (t, values) in series.items():
            style, width, alpha, z = STYLES[kind]
            if len(t):
                ax.plot(
                    t,
                    values[:, c],
                    color=colour,
                    linestyle=style,
                    linewidth=width,
                    alpha=alpha,
                    zorder=z,
                )
        if c < len(tau_max):
            for sign in (1.0, -1.0):
                ax.axhline(sign * tau_max[c], color=colour, linewidth=0.6, alpha=0.7)
        ax.plot([], [], color=colour, linewidth=4, label=name)
    ax.axhline(0.0, color="black", linewidth=0.5)
    ax.set_ylabel(f"{finger} torque [N·m]")
    for kind in series:
        style, width, alpha, _ = STYLES[kind]
        ax.plot([], [], color="black", linestyle=style, linewidth=width, alpha=alpha, label=kind)
    ax.plot([], [], color="0.4", linewidth=0.6, label="±tau_max")
    ax.legend(**_OUTSIDE)


def objects_panels(
    ax_height: Any,
    ax_turn: Any,
    t: np.ndarray,
    heights: np.ndarray,
    names: Sequence[str],
    turns: dict[str, tuple[np.ndarray, np.ndarray]],
) -> None:
    """Heights above rest (m in, mm drawn) and the centre line's turn (deg, ccw +)."""
    for i, name in enumerate(names):
        ax_height.plot(
            t, heights[:, i] * 1e3, label=name, color=JOINT_COLOURS[(i + 3) % len(JOINT_COLOURS)]
        )
    ax_height.set_ylabel(HEIGHT_LABEL)
    ax_height.legend(**_OUTSIDE)
    for label, (tt, values) in turns.items():
        ax_turn.plot(tt, values, label=label, linewidth=1.0)
    ax_turn.set_ylabel(TURN_LABEL)
    ax_turn.legend(**_OUTSIDE)


def plot_recording(series: Series, path: Path, title: str) -> None:
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    groups = finger_groups(series.fingers, len(series.joints))
    has_objects = len(series.objects) > 0
    rows = len(groups) + (2 if has_objects else 0)
    fig = Figure(figsize=(12, 2.3 * rows + 1.0), dpi=110)
    FigureCanvasAgg(fig)
    axes = fig.subplots(rows, 1, sharex=True, squeeze=False)[:, 0]
    n = len(series.joints)
    tq, js = series.torque, series.joint
    for row, (finger, group) in enumerate(groups):
        names = [series.joints[j] for j in group]
        cols = np.array(group)
        torque_panel(
            axes[row],
            finger,
            names,
            [series.tau_max[j] for j in group if j < len(series.tau_max)],
            {
                "desired": (tq[:, 0], tq[:, 1 + cols]) if len(tq) else (np.zeros(0), tq),
                "applied": (tq[:, 0], tq[:, 1 + n + cols]) if len(tq) else (np.zeros(0), tq),
                "measured": (js[:, 0], js[:, 1 + cols]) if len(js) else (np.zeros(0), js),
            },
        )
    for fault in (e for e in series.events if e["kind"] == "fault"):
        for ax in axes:
            ax.axvline(fault["t_s"], color="red", linewidth=1.0)
        axes[-1].text(
            fault["t_s"],
            0.02,
            f" {fault['name']}",
            color="red",
            fontsize=7,
            transform=axes[-1].get_xaxis_transform(),
        )
    if has_objects:
        ob = series.objects
        k = len(series.object_names)
        heights = ob[:, 3 : 3 + 3 * k : 3] - np.asarray(series.rest_y[:k], dtype=float)
        objects_panels(
            axes[len(groups)],
            axes[len(groups) + 1],
            ob[:, 0],
            heights,
            series.object_names,
            {"true (simulation)": (ob[:, 0], turn_deg(ob[:, 1]))},
        )
    phase_bands(list(axes), [(p["name"], p["start_s"], p["end_s"]) for p in series.phases])
    axes[-1].set_xlabel(TIME_LABEL)
    if len(series.timing):
        axes[-1].set_xlim(0.0, max(float(series.timing[-1, 0]), 1e-3))
    fig.suptitle(title, fontsize=10, y=0.995)
    fig.tight_layout(rect=(0, 0, 1, 0.97))
    fig.savefig(str(path))


def title_of(summary: dict[str, Any]) -> str:
    parts = [
        summary.get("recipe") or "recording",
        f"on {summary.get('hand') or '?'}",
        f"({summary.get('mode') or '?'})",
        f"— {summary.get('outcome', '')}",
    ]
    if "turn_deg" in summary:
        parts.append(f"— turned {summary['turn_deg']:+.1f} deg (ccw +)")
    if not summary.get("complete", True):
        parts.append("[damaged]" if summary.get("damaged") else "[truncated]")
    return " ".join(p for p in parts if p)
