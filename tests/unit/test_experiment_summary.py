"""The experiment's figures of merit on synthetic traces: lifted and held, turn per phase,
drops, estimator error."""

from __future__ import annotations

import math
from dataclasses import dataclass

import pytest

from handctl.planning.experiment import Trace, experiment_summary

REST = (-0.12, -0.12)
NAMES = tuple(f"j{k}" for k in range(9))


@dataclass
class Pose:
    x: float
    y: float


def trace_of(segments: list[tuple[str, float, float, float, float]],
             est_offset_deg: float = 0.0, drop_at: float | None = None) -> Trace:
    """``segments``: (phase, seconds, height (m), line angle at start, at end (deg)); 1 ms
    samples, the pair's midpoint fixed, the line turning linearly within a segment."""
    tr = Trace(REST, 0.0, NAMES)
    t = 0.0
    for phase, seconds, height, a0, a1 in segments:
        n = round(seconds / 0.001)
        for i in range(n):
            angle = math.radians(a0 + (a1 - a0) * i / max(1, n - 1))
            dx, dy = 0.02 * math.cos(angle), 0.02 * math.sin(angle)
            y = REST[0] + height
            if drop_at is not None and t >= drop_at:
                y = REST[0]
            poses = [Pose(-dx, y - dy), Pose(dx, y + dy)]
            est = angle + math.radians(est_offset_deg)
            valid = phase != "approach"
            tr.add(t, phase, poses, [0.0] * 9,
                   (math.atan2(math.sin(est), math.cos(est)), est, 0, 0, 0, 0), valid)
            t += 0.001
    return tr


EXPERIMENT = [("approach", 1.0, 0.0, 0.0, 0.0), ("lift", 0.5, 0.05, 0.0, -20.0),
              ("envelop", 2.0, 0.05, -20.0, -20.0),
              ("manipulate_1", 1.0, 0.05, -20.0, -65.0),
              ("manipulate_2", 1.0, 0.05, -65.0, -110.0),
              ("manipulate_3", 1.0, 0.05, -110.0, -155.0),
              ("manipulate_4", 1.0, 0.05, -155.0, -200.0)]


def test_a_full_swap_is_four_phases_of_45_degrees() -> None:
    ex = experiment_summary(trace_of(EXPERIMENT, est_offset_deg=1.0))
    assert ex["lifted"] is True
    assert ex["held_s"] >= 2.0
    assert ex["dropped"] is False
    # measured on the samples a log keeps (every 10th tick): the last phase ends with the
    # trace, and its last sample is 990 of its 999 ms in
    last = -45.0 * 990 / 999
    assert ex["phase_angles_deg"] == pytest.approx([-45.0] * 3 + [last], abs=0.1)
    assert ex["turn_deg"] == pytest.approx(-135.0 + last, abs=0.2)
    assert ex["total_rotation_deg"] == pytest.approx(135.0 - last, abs=0.2)
    assert ex["estimator_error_deg"] == pytest.approx(1.0, abs=1e-6)
    assert ex["estimator_error_manipulation_deg"] == pytest.approx(1.0, abs=1e-6)
    assert ex["estimator_valid_fraction"] == 1.0


def test_held_for_less_than_two_seconds_is_not_lifted() -> None:
    short = [s if s[0] != "envelop" else ("envelop", 1.0, 0.05, -20.0, -20.0)
             for s in EXPERIMENT]
    ex = experiment_summary(trace_of(short))
    assert ex["lifted"] is False
    assert 1.4 < ex["held_s"] < 2.0


def test_falling_back_to_the_table_is_a_drop() -> None:
    ex = experiment_summary(trace_of(EXPERIMENT, drop_at=5.0))
    assert ex["lifted"] is True
    assert ex["dropped"] is True


def test_an_empty_trace_has_the_keys_and_nothing_achieved() -> None:
    ex = experiment_summary(Trace(REST, 0.0, NAMES))
    assert ex["lifted"] is False and ex["phase_angles_deg"] == []
    assert ex["estimator_error_deg"] is None


def test_success_is_lifted_held_kept_and_turned_far_enough() -> None:
    ex = experiment_summary(trace_of(EXPERIMENT), min_total_turn_deg=170.0)
    assert ex["success"] is True and ex["min_total_turn_deg"] == 170.0
    # the same run asked for more turn than it made
    assert experiment_summary(trace_of(EXPERIMENT), min_total_turn_deg=190.0)["success"] is False
    # a drop is a failure whatever the turn
    assert experiment_summary(trace_of(EXPERIMENT, drop_at=5.0))["success"] is False
    # so is a pair that was never held long enough
    short = [s if s[0] != "envelop" else ("envelop", 1.0, 0.05, -20.0, -20.0)
             for s in EXPERIMENT]
    assert experiment_summary(trace_of(short))["success"] is False
    assert experiment_summary(Trace(REST, 0.0, NAMES))["success"] is False


def test_the_peak_turn_rate_is_the_fastest_stretch_of_the_manipulation() -> None:
    # 45 degrees a second in every phase but the last, which turns 45 degrees in 0.1 s
    fast = [*EXPERIMENT[:-1], ("manipulate_4", 0.1, 0.05, -155.0, -200.0)]
    ex = experiment_summary(trace_of(fast))
    assert ex["peak_turn_rate_deg_s"] == pytest.approx(45.0 / 0.099, rel=0.02)
    # the lift turns the line faster still, but it is not a manipulation phase
    assert experiment_summary(trace_of(EXPERIMENT))["peak_turn_rate_deg_s"] == pytest.approx(
        45.0 / 0.999, rel=0.02)
