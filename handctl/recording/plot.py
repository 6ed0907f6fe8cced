"""The PNG of a run, drawn from its recording: ``handctl replay RUN.mcap --plot`` and ``handctl
run recipe --plot`` (which records the run, to a file of its own when not asked to) both call
``plot_log``, so the two plots of one run are the same picture from the same numbers.

One panel per finger; a joint has the same colour in every finger (proximal, middle, distal),
and the line style says what the value is: desired dashed, applied solid, measured dotted, with
thin lines of the joint's colour at ±tau_max. Phases are shaded bands named in a strip above the
first panel, never over the traces. Heights are above rest and the turn is signed
counter-clockwise positive, as ``handctl.convention`` defines them for every summary too; the
estimated turn is the object estimator's, run again on the logged joint angles of the ticks
the loop ran it (it is a function of those angles, which the re-run relies on too).
matplotlib drives an Agg canvas directly (no pyplot), as in ``handctl.analysis.plot``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from handctl.convention import HEIGHT_LABEL, TIME_LABEL, TURN_LABEL, turn_deg
from handctl.recording import channels as ch
from handctl.recording.reader import Recording
from handctl.recording.replay import NOT_PHASES
from handctl.recording.series import Series, line_angle, line_pairs, recorded_recipe_or_none

if TYPE_CHECKING:
    from handctl.online.recipes.schema import Recipe
from handctl.wholefile import save_picture

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
    """Heights above rest (m in, mm drawn) and the centre line's turn (deg, ccw +), when
    there is a panel for it."""
    for i, name in enumerate(names):
        ax_height.plot(
            t, heights[:, i] * 1e3, label=name, color=JOINT_COLOURS[(i + 3) % len(JOINT_COLOURS)]
        )
    ax_height.set_ylabel(HEIGHT_LABEL)
    ax_height.legend(**_OUTSIDE)
    if ax_turn is None:  # nothing turns (fewer than two objects)
        return
    for label, (tt, values) in turns.items():
        ax_turn.plot(tt, values, label=label, linewidth=1.0)
    ax_turn.set_ylabel(TURN_LABEL)
    ax_turn.legend(**_OUTSIDE)


def plot_log(path: Path, out: Path) -> None:
    """The plot of the recording at ``path``, titled with its replay summary."""
    from handctl.recording.reader import check_format, open_recording
    from handctl.recording.replay import summarise_recording
    from handctl.recording.series import load_series

    recording = open_recording(path)
    check_format(recording)
    series = load_series(recording)
    plot_recording(series, out, title_of(summarise_recording(recording, series)), recording)


def turns_deg(
    series: Series, recording: Recording | None = None
) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Each centre line's turn (deg, ccw +) at the logged poses, by label: the true one
    (simulation) and, for a recording whose recipe has objects, the estimator's, drawn on the
    true turn's branch (the estimate is an angle in (-pi, pi]; the gap between the two lines
    is the estimator's error). Every pair the recipe declares (``line_pairs``; each object
    with the next without one), as the replay's summary has them, not only the first."""
    ob = series.objects
    if not len(ob):
        return {}
    recipe = recorded_recipe_or_none(recording) if recording is not None else None
    pairs = line_pairs(recipe, series.object_names)
    estimated_names: list[str] = []
    estimated = np.zeros((len(ob), 0))
    if recording is not None and recipe is not None and recipe.objects and recipe.pairs:
        estimated_names = [
            ch.pair_name(recipe.objects[a].name, recipe.objects[b].name) for a, b in recipe.pairs
        ]
        estimated = _estimated_lines(recording, recipe, series, ob[:, 0])
    out: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    for name, a, b in pairs:
        true = line_angle(ob, a, b)
        turn = turn_deg(true)
        out[f"{name} true (simulation)"] = (ob[:, 0], turn)
        if name in estimated_names:
            column = estimated[:, estimated_names.index(name)]
            gap = np.degrees((column - true + np.pi) % (2 * np.pi) - np.pi)
            out[f"{name} estimated (joint angles)"] = (ob[:, 0], turn + gap)
    return out


def _estimated_lines(
    recording: Recording, recipe: Recipe, series: Series, at_s: np.ndarray
) -> np.ndarray:
    """The estimator's centre-line angles (rad), one column per pair of the recipe, as the
    loop had them at each time of ``at_s`` (s, the series' times): its estimate of the last
    tick before, NaN where it was not valid. The estimator is fed the logged angles of every
    control tick the loop ran it (the supervisor running, the recipe not done), as the
    writer's Foxglove scene does."""
    from handctl.online.estimator import ObjectEstimator
    from handctl.recording.metadata import recorded_hand
    from handctl.recording.reader import iter_decoded

    hand = recorded_hand(recording)
    assert hand is not None
    estimator = ObjectEstimator(hand, recipe.objects, recipe.pairs)
    count = len(recipe.pairs)
    times: list[int] = []
    lines: list[list[float]] = []
    angle: list[float] = []
    running = False
    topics = (ch.JOINT_STATE, ch.SAFETY, ch.PHASE)
    for topic, log_time, msg in iter_decoded(recording, topics):
        if topic == ch.JOINT_STATE:
            angle = [math.nan if v is None else v for v in msg["angle_rad"]]
        elif topic == ch.SAFETY:
            running = msg["state"] == "running"
        elif running and msg["phase"] not in ("completed", "aborted"):
            estimate = estimator(angle)
            times.append(log_time)
            # a pair's line angle is its first estimate (``PAIR_ESTIMATES``), pairs first
            valid = estimator.valid
            lines.append([estimate[2 * k] if valid else math.nan for k in range(count)])
    if not times:
        return np.full((len(at_s), count), math.nan)
    t_s = (np.asarray(times, dtype=np.int64) - series.t0_ns) * 1e-9
    # the last estimate strictly before each pose: a pose is taken at the start of its tick
    before = np.searchsorted(t_s, np.asarray(at_s) - 1e-7) - 1
    line = np.asarray(lines, dtype=float).reshape(len(times), count)[np.clip(before, 0, None)]
    result: np.ndarray = np.where((before >= 0)[:, None], line, math.nan)
    return result


def plot_recording(
    series: Series, path: Path, title: str, recording: Recording | None = None
) -> None:
    """The plot of ``series``; with its ``recording``, the estimated turn as well."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    from handctl.convention import LIFT_HEIGHT

    groups = finger_groups(series.fingers, len(series.joints))
    has_objects = len(series.objects) > 0
    turns = turns_deg(series, recording)
    rows = len(groups) + (1 if has_objects else 0) + (1 if turns else 0)
    fig = Figure(figsize=(12, 2.3 * rows + 1.0), dpi=110)
    FigureCanvasAgg(fig)
    axes = fig.subplots(rows, 1, sharex=True, squeeze=False)[:, 0]
    for ax in axes:
        ax.grid(True, lw=0.3)
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
            axes[len(groups) + 1] if turns else None,
            ob[:, 0],
            heights,
            series.object_names,
            turns,
        )
        axes[len(groups)].axhline(LIFT_HEIGHT * 1e3, color="k", lw=0.6, ls="--")
    phase_bands(list(axes), [(p["name"], p["start_s"], p["end_s"]) for p in series.phases])
    axes[-1].set_xlabel(TIME_LABEL)
    if len(series.timing):
        axes[-1].set_xlim(0.0, max(float(series.timing[-1, 0]), 1e-3))
    fig.suptitle(title, fontsize=10, y=0.995)
    fig.tight_layout(rect=(0, 0, 1, 0.97))
    save_picture(fig, Path(path))


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
