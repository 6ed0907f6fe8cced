"""Joint velocities from the angles: a steady motion is followed, one encoder count in one
tick is not a spike, and the same feed gives the same values (a re-run reproduces them)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from handctl.online.recipes.velocity import JointVelocity

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
