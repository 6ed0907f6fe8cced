"""Joint velocities from the angles: a steady motion is followed, one encoder count in one
tick is not a spike, and the same feed gives the same values (a re-run reproduces them)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from handctl.online.recipes.velocity import FittedVelocity, JointVelocity

COUNT = 2 * math.pi / 16384  # rad, one count of a 14-bit encoder
DT = 0.001


def test_a_steady_motion_is_followed_and_one_count_is_not_a_spike() -> None:
    vel = JointVelocity(2, time_constant=0.01)
    for k in range(200):
        vel.update(k * DT, [0.5 * k * DT, 0.0])
    assert vel.value[0] == pytest.approx(0.5, rel=1e-3)
    assert vel.value[1] == 0.0
    vel.update(200 * DT, [0.5 * 200 * DT, COUNT])  # one count, one tick
    raw = COUNT / DT
    assert 0.0 < vel.value[1] < raw / 10


def test_the_same_feed_gives_the_same_values() -> None:
    rng = np.random.default_rng(3)
    angles = np.cumsum(rng.normal(0, 1e-3, (300, 3)), axis=0)
    runs = []
    for _ in range(2):
        vel = JointVelocity(3)
        runs.append(np.array([vel.update(k * DT, a).copy() for k, a in enumerate(angles)]))
    assert np.array_equal(runs[0], runs[1])
    assert np.all(runs[0][0] == 0.0)  # the first tick has no difference to take


def test_the_fitted_slope_follows_a_ramp_within_its_window_and_damps_a_count() -> None:
    """The guard's velocity: the slope of a line through the last ticks follows a ramp exactly
    once its window is full (a low-pass of 10 ms is still 10 % behind a step in speed after 23
    ticks), a missed tick changes nothing, and one encoder count moves it by far less than one
    tick's difference."""
    window = 8
    fit = FittedVelocity(2, window)
    low = JointVelocity(2, time_constant=0.01)
    t = 0.0
    for k in range(window):  # at rest, then 2 rad/s from here on
        t = k * DT
        fit.update(t, [0.0, 0.0])
        low.update(t, [0.0, 0.0])
    for k in range(1, window + 1):
        t += DT * (2 if k == 3 else 1)  # one tick missed: the times say so
        fit.update(t, [2.0 * (t - (window - 1) * DT), 0.0])
        low.update(t, [2.0 * (t - (window - 1) * DT), 0.0])
    assert fit.value[0] == pytest.approx(2.0, rel=1e-9)
    assert low.value[0] < 0.9 * 2.0
    before = fit.value[1]
    fit.update(t, [0.0, COUNT])  # the same tick again: no new information
    assert fit.value[1] == before
    fit.update(t + DT, [2.0 * (t + DT - (window - 1) * DT), COUNT])  # one count, one tick
    assert 0.0 < fit.value[1] < (COUNT / DT) / 4
    with pytest.raises(ValueError):
        FittedVelocity(2, 1)
