"""What ``handctl replay`` says about a recording: its summary (phases, largest torques,
faults, timing, drops, objects). The recording is read as time series (``series``); the
re-run is ``rerun``, the frames onto a bus or into a file ``frames``.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any

import numpy as np

from handctl.arrays import FloatArray
from handctl.convention import phase_turns_deg
from handctl.online.tickstats import histogram_us, percentile_us
from handctl.recording import channels as ch
from handctl.recording.reader import Recording
from handctl.recording.ring import RECORDED_STAGES
from handctl.recording.series import Series, line_angle, line_pairs, recorded_recipe_or_none

if TYPE_CHECKING:
    from handctl.online.recipes.schema import Recipe

#: Phase names that are the runner's status rather than a phase of the recipe.
NOT_PHASES = frozenset({"-", "running", "completed", "aborted", "?"})


def _percentiles(values_ns: FloatArray) -> dict[str, float]:
    """As the run's summary has them (``session._percentiles_us``): from 1 µs bins."""
    if values_ns.size == 0:
        return {"p50": 0.0, "p99": 0.0, "max": 0.0}
    hist = histogram_us(values_ns)
    return {
        "p50": percentile_us(hist, 50),
        "p99": percentile_us(hist, 99),
        "max": round(float(values_ns.max()) / 1e3, 2),
    }


def summarise_recording(recording: Recording, series: Series) -> dict[str, Any]:
    """Phases and their durations, the largest torques, faults, timing, drops."""
    n = len(series.joints)
    run_summary = recording.json_meta(ch.META_SUMMARY) or {}
    drops = {
        key: recording.meta_int(ch.META_END, key, int(series.stats.get(key, 0)))
        for key in ch.DROPPED_KEYS
    }
    timing = series.timing
    active = timing[timing[:, 4] > 0] if len(timing) else timing
    largest: dict[str, dict[str, float]] = {}
    tq, js = series.torque, series.joint
    for j, name in enumerate(series.joints):
        entry: dict[str, float] = {}
        # a column with no number in it (a log whose values were nulled) has no largest:
        # its key is left out, where ``nanargmax`` raised and ``nanmax`` gave NaN, which
        # the JSON summary then wrote as the non-JSON ``NaN``
        applied = np.abs(tq[:, 1 + n + j]) if len(tq) else np.empty(0)
        if np.isfinite(applied).any():
            i = int(np.nanargmax(applied))
            entry |= {
                "applied_nm": round(float(tq[i, 1 + n + j]), 5),
                "at_s": round(float(tq[i, 0]), 3),
            }
        for key, column in (
            ("desired_nm", tq[:, 1 + j] if len(tq) else np.empty(0)),
            ("tdt_nm", js[:, 1 + j] if len(js) else np.empty(0)),
        ):
            if np.isfinite(column).any():
                entry[key] = round(float(np.nanmax(np.abs(column))), 5)
        largest[name] = entry
    phases = [
        {
            "name": p["name"],
            "start_s": round(p["start_s"], 3),
            "end_s": round(p["end_s"], 3),
            "duration_s": round(p["end_s"] - p["start_s"], 3),
            "exit": p["exit"],
        }
        for p in series.phases
        if p["name"] not in NOT_PHASES
    ]
    faults = [
        {
            "code": e["name"],
            "category": e.get("category", ""),
            "tick": e["tick"],
            "t_s": round(e["t_s"], 3),
            "detail": e["detail"],
        }
        for e in series.events
        if e["kind"] == "fault"
    ]
    rejected: dict[str, int] = {}
    for e in series.events:
        if e["kind"] == "rejected_frames":
            rejected[e["name"]] = rejected.get(e["name"], 0) + int(e.get("count", 0))
    summary: dict[str, Any] = {
        "file": str(recording.path),
        "complete": recording.complete,
        "being_written": recording.being_written,
        "damaged": recording.damaged,
        "problem": recording.problem,
        "chunks": recording.chunks,
        "recipe": recording.meta(ch.META_RECIPE, "name"),
        "hand": recording.meta(ch.META_HAND, "name"),
        "mode": recording.meta(ch.META_RUN, "mode"),
        "outcome": run_summary.get("outcome", "unknown (the log has no summary)"),
        "ended": recording.meta(ch.META_END, "ended", "the writer did not finish the file"),
        "duration_s": round(float(timing[-1, 0]), 3) if len(timing) else 0.0,
        "ticks": len(timing),
        "active_ticks": len(active),
        "phases": phases,
        "largest_torques": largest,
        "faults": faults,
        "timing": {
            "lateness_us": _percentiles(timing[:, 2] if len(timing) else timing),
            "missed_ticks": int(timing[:, 3].sum()) if len(timing) else 0,
            # over every tick, as the run's (its idle ticks' stages are zero)
            "stage_cpu_us_p99": {
                name: round(percentile_us(histogram_us(timing[:, 5 + i]), 99), 2)
                if len(timing)
                else 0.0
                for i, name in enumerate(RECORDED_STAGES)
            },
        },
        "drops": drops,
        "frames": series.frames,
        "messages_back_in_time": series.out_of_order,
        "unknown_phases": series.unknown_phases,
        "bus_events": sum(1 for e in series.events if e["kind"] == "bus"),
        "rejected_frames": rejected,
    }
    if len(series.objects):
        first, last = series.objects[0], series.objects[-1]
        summary["objects"] = {
            name: {"start": _pose(first, i, series.rest_y), "end": _pose(last, i, series.rest_y)}
            for i, name in enumerate(series.object_names)
        }
    recipe = recorded_recipe_or_none(recording) if len(series.objects) else None
    # a recipe that declares no pair (one of no objects, on a scene that has some) measures
    # none, as its run's experiment does: the replay's summary said the turn of a centre line
    # between the scene's objects that the recipe never named; a log whose recipe does not
    # read measures each logged object with the next
    declared = recipe is None or bool(recipe.pairs)
    pairs = line_pairs(recipe, series.object_names) if len(series.objects) and declared else []
    if pairs:
        summary |= _pair_figures(series, pairs, recipe)
    return summary


def _pair_figures(
    series: Series, pairs: list[tuple[str, int, int]], recipe: Recipe | None
) -> dict[str, Any]:
    """Each pair's centre line (the recipe's pairs, ``line_pairs``) at the start and the end
    and its turn per phase, under ``pairs`` by name as the experiment summary keys them; the
    first pair's also at the top level (``objects_line_pair`` names it), where a log of the
    default two-object recipe has always had them."""
    # The phase channel says which phase a tick ran, and a pose is taken as its tick begins:
    # the pose at a phase's first tick is where it started, the one at the next phase's
    # first tick where it ended. (Bounds a tick later ended a phase one sample late when its
    # last tick was a logged one's.)
    bounds = [(p["name"], p["start_s"], p["end_s"]) for p in series.phases]
    if bounds:
        # the last phase's turn runs to the log's last pose, as the run's summary counts it:
        # after a stop (a fault's ramp, an interrupt) the objects go on moving in that phase's
        # grasp while the torques come down, and the replay of a safety-stopped run said
        # 19° where its run had said 34° (the pair snapped on in the 55 ms of the ramp)
        name, start, _ = bounds[-1]
        bounds[-1] = (name, start, math.inf)
    # the run's own manipulation phases, as its summary counted them (a log without a recipe
    # that parses: the phases named manipulate...)
    counted = recipe.manipulation_phases if recipe is not None else None
    figures: dict[str, dict[str, Any]] = {}
    for name, a, b in pairs:
        angle = line_angle(series.objects, a, b)
        turns = phase_turns_deg(series.objects[:, 0], angle, bounds, counted)
        figures[name] = {
            "line_angle_rad": {
                "start": round(float(angle[0]), 5),
                "end": round(float(angle[-1]), 5),
            },
            "phase_turns_deg": turns,
            "turn_deg": round(sum(turns), 2),
        }
    first = pairs[0][0]
    return {
        "objects_line_pair": first,
        "objects_line_angle_rad": figures[first]["line_angle_rad"],
        "phase_turns_deg": figures[first]["phase_turns_deg"],
        "turn_deg": figures[first]["turn_deg"],
        "pairs": figures,
    }


def _pose(row: FloatArray, i: int, rest_y: list[float]) -> dict[str, float]:
    x, y, angle = row[2 + 3 * i : 5 + 3 * i]
    pose = {
        "x_m": round(float(x), 5),
        "y_m": round(float(y), 5),
        "angle_rad": round(float(angle), 5),
    }
    if i < len(rest_y):
        pose["height_above_rest_m"] = round(float(y) - rest_y[i], 5)
    return pose
