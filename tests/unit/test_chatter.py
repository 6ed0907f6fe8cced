"""The ring watch: a joint's command swinging back and forth at 10 Hz and more by a tenth of
its tau_max, for half a second in all, is found; ramps, stops, noise and short rings are
not."""

from __future__ import annotations

import numpy as np
import pytest

from handctl.online.safety.chatter import MIN_RING_S, ChatterWatch, Ringing

PERIOD = 0.001
TAU = np.array([0.6, 0.3])  # N·m: a proximal and a distal joint
NAMES = ("j1", "j3")


def watched(commands: np.ndarray) -> list[Ringing]:
    """``commands``: (ticks, 2) torques sent, N·m."""
    watch = ChatterWatch(NAMES, TAU, PERIOD)
    for k, row in enumerate(commands):
        watch.observe(row, k * PERIOD)
    return watch.found()


def triangle(hz: float, amplitude: float, seconds: float) -> np.ndarray:
    """A command slewing between ±amplitude at ``hz``, as the rate limit makes of a bang-bang."""
    t = np.arange(round(seconds / PERIOD)) * PERIOD
    phase = (t * hz) % 1.0
    out: np.ndarray = amplitude * (4 * np.abs(phase - 0.5) - 1)
    return out


def on_joint(values: np.ndarray, joint: int) -> np.ndarray:
    out = np.zeros((len(values), 2))
    out[:, joint] = values
    return out


def test_a_rate_limited_swing_is_found_with_its_size_and_pace() -> None:
    quiet = np.zeros((300, 2))
    ring = on_joint(0.05 + triangle(24.0, 0.15, 1.5), 1)
    found = watched(np.vstack([quiet, ring, quiet]))
    assert [r.joint for r in found] == ["j3"]
    r = found[0]
    assert r.amplitude_nm == pytest.approx(0.15, abs=0.01)
    assert r.frequency_hz == pytest.approx(24.0, abs=1.5)
    assert 1.2 <= r.seconds <= 1.5
    assert 0.3 <= r.from_s <= 0.45  # a few swings after it began
    assert "j3's command rang" in r.text() and "24 Hz" in r.text()


def test_a_smooth_ring_under_the_rate_limit_is_found_too() -> None:
    t = np.arange(2000) * PERIOD
    found = watched(on_joint(0.03 + 0.08 * np.sin(2 * np.pi * 42.0 * t), 0))
    assert [r.joint for r in found] == ["j1"]
    assert found[0].frequency_hz == pytest.approx(42.0, abs=2.0)


@pytest.mark.parametrize(
    "what",
    ["ramp up and hold", "stop ramp", "noise", "short ring", "slow swing", "small ring"],
)
def test_what_is_no_ring_is_not_said(what: str) -> None:
    rng = np.random.default_rng(3)
    t = np.arange(3000) * PERIOD
    values = {
        # a phase's ramp at the rate limit (20 N·m/s), then its torque held
        "ramp up and hold": np.minimum(t * 20.0, 0.25),
        "stop ramp": np.maximum(0.25 - t * 20.0, 0.0),
        # the TDT- and velocity-driven jitter of a feedback: far under a tenth of tau_max
        "noise": 0.1 + rng.normal(0.0, 0.004, t.size),
        # a guard catching a flung joint: a quarter of a second of ring, then it settles
        "short ring": np.where(t < MIN_RING_S / 2, triangle(17.0, 0.08, 3.0), 0.0),
        # a joint worked back and forth at 4 Hz by the recipe: a motion, not a ring
        "slow swing": triangle(4.0, 0.2, 3.0),
        # a ring of a twentieth of tau_max: under the swing a ring has to have
        "small ring": triangle(30.0, 0.006, 3.0),
    }[what]
    assert watched(on_joint(values, 1)) == []
