"""The paper's figures of merit for a run on the simulated hand, from recorded ground truth.

The run never uses ground truth: the recipe's exits read the estimator. Ground truth is
*recorded* here, every tick in lockstep, to measure what happened (did the pair leave the
table, how far did the centre line turn in each manipulation phase, did anything drop) and how
good the estimator was. Definitions:

- ``lifted``: both objects' centres ``LIFT_HEIGHT`` (10 mm) or more above where they rested on
  the table, continuously for ``HOLD_S`` (2 s) or more before the first manipulation phase
  ("lifted and held");
- ``phase_angles_deg``: for each manipulation phase (a phase whose name starts with
  ``manipulate``), the change of the true centre-line angle (unwrapped) from its start to its
  end;
- ``turn_deg``: their sum, counter-clockwise positive (``handctl.convention``, as every plot
  and summary shows it); ``total_rotation_deg`` its magnitude (the turn of the pair in the hand);
- ``dropped``: once lifted, an object came back within ``DROP_HEIGHT`` of the table or left the
  hand (more than ``HAND_HALF_SPAN`` from the palm's middle) before the last manipulation phase
  ended (the end ramp lets go of the objects on purpose);
- ``estimator_error_deg``: the 95th percentile of |estimated - true| centre-line angle over the
  ticks of the hold and manipulation phases where the estimate was valid (with the fraction of
  those ticks that had a valid estimate), and over the manipulation phases alone (where the
  exits read it; the hold includes the objects settling after the lift);
- ``peak_turn_rate_deg_s``: the largest rate of the true centre line over the manipulation
  phases, each rate taken over ``RATE_WINDOW_S`` (10 ms) so that one contact impact of a
  physics step does not count as a turn. The analysis behind a recipe is quasi-static: a
  pair that turns faster than some 180 °/s is tumbling, not being turned;
- ``success``: lifted (and so held), nothing dropped, and a total rotation of at least the
  recipe's ``min_total_turn_deg``. A run whose experiment failed is a failed run (exit 1).

Only NumPy here: ``session`` imports this module for every lockstep run.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np

from handctl.convention import POSE_EVERY_TICKS, phase_turns_deg

LIFT_HEIGHT = 0.010  # m
HOLD_S = 2.0  # s
DROP_HEIGHT = 0.005  # m
HAND_HALF_SPAN = 0.06  # m
MANIPULATE_PREFIX = "manipulate"
RATE_WINDOW_S = 0.010  # s


class _Pose(Protocol):
    @property
    def x(self) -> float: ...
    @property
    def y(self) -> float: ...


@dataclass
class Trace:
    """Per-tick samples of a run: time (s), phase, true object centres, transmitted joint
    torques, the estimator's outputs and validity."""

    rest_y: tuple[float, ...]
    palm_x: float
    joint_names: tuple[str, ...]
    t: list[float] = field(default_factory=list)
    phase: list[str] = field(default_factory=list)
    centres: list[tuple[float, float, float, float]] = field(default_factory=list)
    torques: list[tuple[float, ...]] = field(default_factory=list)
    estimate: list[tuple[float, ...]] = field(default_factory=list)
    valid: list[bool] = field(default_factory=list)
    applied: list[tuple[float, ...]] = field(default_factory=list)  # the command in force

    def add(self, t: float, phase: str, poses: Sequence[_Pose], torques: Sequence[float],
            estimate: Sequence[float] | None, valid: bool,
            applied: Sequence[float] | None = None) -> None:
        a, b = poses[0], poses[1]
        if applied is not None:
            self.applied.append(tuple(applied))
        self.t.append(t)
        self.phase.append(phase)
        self.centres.append((a.x, a.y, b.x, b.y))
        self.torques.append(tuple(torques))
        self.estimate.append(tuple(estimate) if estimate is not None else (math.nan,) * 6)
        self.valid.append(valid)

    # -- derived series ---------------------------------------------------------------------
    def arrays(self) -> dict[str, np.ndarray]:
        c = np.array(self.centres, dtype=float).reshape(-1, 4)
        est = np.array(self.estimate, dtype=float).reshape(-1, 6)
        true_angle = np.unwrap(np.arctan2(c[:, 3] - c[:, 1], c[:, 2] - c[:, 0])) \
            if len(c) else np.zeros(0)
        heights = c[:, [1, 3]] - np.array(self.rest_y[:2]) if len(c) else np.zeros((0, 2))
        return {"t": np.array(self.t), "centres": c, "true_angle": true_angle,
                "heights": heights, "estimate": est, "valid": np.array(self.valid, bool),
                "torques": np.array(self.torques, dtype=float),
                "applied": (np.array(self.applied, dtype=float)
                            if self.applied and len(self.applied) == len(self.t)
                            else np.zeros((0, len(self.joint_names))))}


def _segments(phases: Sequence[str]) -> list[tuple[str, int, int]]:
    """``(name, first, last + 1)`` of each run of equal phase names, in order."""
    out: list[tuple[str, int, int]] = []
    start = 0
    for i in range(1, len(phases) + 1):
        if i == len(phases) or phases[i] != phases[start]:
            out.append((phases[start], start, i))
            start = i
    return out


def peak_rate_deg_s(t: np.ndarray, angle: np.ndarray, window_s: float = RATE_WINDOW_S) -> float:
    """The largest |d angle / dt| (deg/s) over ``window_s``-long spans of the samples."""
    if len(t) < 2:
        return 0.0
    span = max(1, int(np.searchsorted(t, t[0] + window_s - 1e-9)))
    span = min(span, len(t) - 1)
    dt = t[span:] - t[:-span]
    rate = np.abs(angle[span:] - angle[:-span]) / np.where(dt > 0, dt, np.inf)
    return float(np.degrees(rate.max())) if rate.size else 0.0


def experiment_summary(trace: Trace, min_total_turn_deg: float = 0.0) -> dict[str, Any]:
    """The ``experiment`` block of the run summary (see the module doc); the experiment
    succeeds when the pair turned ``min_total_turn_deg`` or more besides being lifted, held
    and kept."""
    a = trace.arrays()
    n = len(trace.t)
    empty: dict[str, Any] = {"success": False, "min_total_turn_deg": min_total_turn_deg,
                             "lifted": False, "held_s": 0.0, "phase_angles_deg": [],
                             "turn_deg": 0.0, "total_rotation_deg": 0.0,
                             "peak_turn_rate_deg_s": 0.0,
                             "dropped": False, "estimator_error_deg": None,
                             "estimator_error_manipulation_deg": None,
                             "estimator_valid_fraction": 0.0}
    if n == 0:
        return empty
    t, heights = a["t"], a["heights"]
    segments = _segments(trace.phase)
    manip = [s for s in segments if s[0].startswith(MANIPULATE_PREFIX)]
    first_manip = manip[0][1] if manip else n
    end_manip = manip[-1][2] if manip else n
    up = np.all(heights >= LIFT_HEIGHT, axis=1)
    # the lifted stretch that reaches the first manipulation phase (or the longest one)
    held_s = 0.0
    lift_start = None
    i = 0
    while i < first_manip:
        if up[i]:
            j = i
            while j < first_manip and up[j]:
                j += 1
            span = float(t[j - 1] - t[i]) if j > i else 0.0
            if span >= held_s:
                held_s, lift_start = span, i
            i = j
        else:
            i += 1
    lifted = held_s >= HOLD_S - 1e-9
    dropped = False
    if lift_start is not None:
        c = a["centres"]
        after = slice(lift_start, end_manip)
        low = np.any(heights[after] < DROP_HEIGHT, axis=1)
        away = np.any(np.abs(c[after][:, [0, 2]] - trace.palm_x) > HAND_HALF_SPAN, axis=1)
        dropped = bool(np.any(low | away))
    angles = a["true_angle"]
    bounds = [(name, float(t[s]), float(t[e]) if e < n else math.inf)
              for name, s, e in segments]
    # on the samples a log keeps (the convention's), so that its replay measures the same
    period = float(t[1] - t[0]) if n > 1 else 1.0
    logged = np.round(t / period).astype(np.int64) % POSE_EVERY_TICKS == 0
    phase_angles = phase_turns_deg(t[logged], angles[logged], bounds, MANIPULATE_PREFIX)
    total = abs(sum(phase_angles))
    peak_rate = (peak_rate_deg_s(t[first_manip:end_manip], angles[first_manip:end_manip])
                 if manip else 0.0)
    # estimator error over hold and manipulation (from the lifted stretch on)
    start = lift_start if lift_start is not None else first_manip
    sel = slice(start, end_manip)
    valid = a["valid"][sel]
    err = np.abs((a["estimate"][sel, 0] - np.angle(np.exp(1j * angles[sel])) + math.pi)
                 % (2 * math.pi) - math.pi)
    in_manip = np.zeros(n, dtype=bool)
    for _, s, e in manip:
        in_manip[s:e] = True
    manip_err = err[valid & np.isfinite(err) & in_manip[sel]]
    err = err[valid & np.isfinite(err)]
    return {
        "success": bool(lifted and not dropped and total >= min_total_turn_deg),
        "min_total_turn_deg": min_total_turn_deg,
        "lifted": bool(lifted),
        "held_s": round(held_s, 3),
        "phase_angles_deg": phase_angles,
        "total_rotation_deg": round(total, 2),
        "peak_turn_rate_deg_s": round(peak_rate, 1),
        "turn_deg": round(sum(phase_angles), 2),
        "dropped": dropped,
        "estimator_error_deg": (round(float(np.degrees(np.percentile(err, 95))), 2)
                                if err.size else None),
        "estimator_error_manipulation_deg": (
            round(float(np.degrees(np.percentile(manip_err, 95))), 2) if manip_err.size
            else None),
        "estimator_valid_fraction": round(float(valid.mean()) if valid.size else 0.0, 3),
    }


class Tracker:
    """Samples a lockstep run every tick (a runtime tick hook): ground truth from the simulated
    hand, the estimator's latest outputs. Recorded, never fed back."""

    def __init__(self, truth: Callable[[], Any], phase: Callable[[], str],
                 estimate: Callable[[], tuple[Sequence[float] | None, bool]],
                 rest_y: tuple[float, ...], palm_x: float,
                 joint_names: tuple[str, ...], period_s: float,
                 applied: Callable[[], Sequence[float]] | None = None) -> None:
        self._applied = applied
        self._truth = truth
        self._phase = phase
        self._estimate = estimate
        self._period = period_s
        self.trace = Trace(rest_y, palm_x, joint_names)

    def sample(self, tick: Any) -> None:
        truth = self._truth()
        est, valid = self._estimate()
        self.trace.add(tick.tick * self._period, self._phase(), truth.objects,
                       truth.joint_torques, est, valid,
                       self._applied() if self._applied is not None else None)


def track(runtime: Any, sim_hand: Any) -> Tracker:
    """A tracker of ``runtime`` on the lockstep ``sim_hand``, hooked into its ticks."""
    hand = runtime.hand
    estimator = runtime.estimator
    xs = [f.base_x for f in hand.fingers]

    def phase() -> str:
        return str(runtime.runner.phase_name) if runtime.runner is not None else "-"

    def estimate() -> tuple[Sequence[float] | None, bool]:
        if estimator is None:
            return None, False
        return estimator.last, bool(estimator.valid)

    tracker = Tracker(sim_hand.ground_truth, phase, estimate,
                      tuple(o.y for o in sim_hand.params.objects), (min(xs) + max(xs)) / 2,
                      hand.joint_names, hand.bus.period_s,
                      applied=lambda: runtime.supervisor.applied)
    runtime.tick_hooks.append(tracker.sample)
    return tracker
