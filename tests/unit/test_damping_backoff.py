"""The injected damping backs off on a joint whose command the supervisor's rate limit clips
(``online/recipes/backoff.py``): the gain falls on every clipped tick and comes back when
nothing is clipped; a joint whose damping torque follows its velocity keeps the recipe's
damping exactly; the back-off is handed from phase to phase with the limiter it mirrors."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import yaml

from handctl.config import HandConfig
from handctl.online.recipes.backoff import (
    BACKOFF_DECAY,
    BACKOFF_GAIN_MIN,
    BACKOFF_RECOVER_S,
    RateBackoff,
)
from handctl.online.recipes.loader import load_recipe
from handctl.online.recipes.runner import RecipeRunner
from handctl.online.recipes.schema import Recipe
from handctl.online.safety.limits import JointLimits, limit_torque

DT = 0.001
RATE = 20.0  # N·m/s, every joint of the shipped hand
TAU_MAX = 0.45


def _backoff(n: int = 3) -> RateBackoff:
    return RateBackoff((RATE,) * n, (TAU_MAX,) * n, DT)


def test_a_command_the_rate_limit_passes_keeps_every_gain_at_one() -> None:
    backoff = _backoff()
    for k in range(200):
        # 2 N·m/s on the first joint, a slow sine on the second, 0.01 N·m on the third (half
        # of one tick's step)
        backoff.observe(np.array([0.002 * k, 0.2 * math.sin(k * DT), 0.01]))
    assert backoff.gain.tolist() == [1.0, 1.0, 1.0]
    assert backoff.clipped_ticks == [0, 0, 0]


def test_each_clipped_tick_lowers_the_joint_s_gain_and_the_others_keep_theirs() -> None:
    backoff = _backoff()
    step = np.array([0.0, 0.4, 0.0])  # 0.4 N·m at once: 20 ticks of the rate limit
    for k in range(1, 6):
        backoff.observe(step)
        assert backoff.gain[1] == pytest.approx(BACKOFF_DECAY**k)
    assert backoff.gain[0] == backoff.gain[2] == 1.0
    for _ in range(100):
        backoff.observe(step)
    # the mirror reached 0.4 after 20 ticks: clipped on those alone, and never below the floor
    assert backoff.clipped_ticks == [0, 19, 0]
    assert backoff.gain[1] >= BACKOFF_GAIN_MIN


def test_the_gain_never_falls_below_its_floor() -> None:
    backoff = _backoff(1)
    for k in range(200):  # a square wave of ±0.45 N·m every 10 ticks: clipped throughout
        backoff.observe(np.array([TAU_MAX if (k // 10) % 2 else -TAU_MAX]))
    assert backoff.gain[0] == BACKOFF_GAIN_MIN


def test_the_gain_comes_back_over_the_recovery_time_once_nothing_is_clipped() -> None:
    backoff = _backoff(1)
    for _ in range(30):  # 0.3 N·m at once: 15 clipped ticks
        backoff.observe(np.array([0.3]))
    low = float(backoff.gain[0])
    assert low < 1.0
    ticks = math.ceil((1.0 - low) * BACKOFF_RECOVER_S / DT)
    for _ in range(ticks - 1):
        backoff.observe(np.array([0.3]))
    assert backoff.gain[0] < 1.0
    backoff.observe(np.array([0.3]))
    assert backoff.gain[0] == 1.0


def test_a_command_beyond_tau_max_is_the_clamp_s_not_the_rate_limit_s() -> None:
    """The supervisor clamps to ±tau_max before it limits the change: a proposal held above
    tau_max is clipped only while the limited torque ramps up to tau_max."""
    backoff = _backoff(1)
    for _ in range(100):
        backoff.observe(np.array([2.0]))
    assert backoff.clipped_ticks == [math.ceil(TAU_MAX / (RATE * DT)) - 1]


def test_the_mirror_clips_where_the_supervisor_s_limiter_does(hand: HandConfig) -> None:
    """The back-off reads off a mirror what the limiter does to the same proposals: the joints
    the one limits on a tick are the joints the other counts as clipped, but where the
    limiter's command grid (which the mirror leaves out) tips a change that just meets the
    rate limit. The limiter limited a joint where what it applied is further from the
    proposal than the grid's rounding takes it."""
    limits = JointLimits.from_hand(hand)
    grid = np.array(limits.step_list)
    backoff = RateBackoff.for_hand(hand, DT)
    applied = np.zeros(9)
    rng = np.random.default_rng(3)
    agree = limited_count = 0
    ticks = 1000
    for k in range(ticks):
        # 0.15 N·m at 25 Hz (up to 24 N·m/s, over the rate limit for part of each period),
        # below every joint's tau_max, so the limiter limits by the rate alone
        proposed = 0.15 * np.sin(2 * math.pi * 25.0 * k * DT + np.arange(9)) + rng.normal(
            0.0, 0.002, 9
        )
        limit_torque(proposed, applied, limits, DT, applied)
        limited = np.abs(applied - proposed) > grid
        before = list(backoff.clipped_ticks)
        backoff.observe(proposed)
        clipped = np.array(backoff.clipped_ticks) > np.array(before)
        agree += int(np.sum(limited == clipped))
        limited_count += int(np.sum(limited))
    assert 0.1 * 9 * ticks < limited_count < 0.9 * 9 * ticks
    assert agree >= 0.98 * 9 * ticks


def _damped_recipe(tmp_path: Path, hand: HandConfig) -> Recipe:
    names = list(hand.joint_names)
    data = {
        "recipe": "damped",
        "phases": [
            {
                "name": "damped",
                "torques": dict.fromkeys(names, 0.0),
                "joint_damping": 0.03,
                "ramp_s": 0.01,
                "max_s": 0.5,
                "on_timeout": "next",
            },
            {
                "name": "after",
                "torques": dict.fromkeys(names, 0.0),
                "joint_damping": 0.03,
                "ramp_s": 0.01,
                "max_s": 10.0,
                "on_timeout": "next",
            },
        ],
    }
    path = tmp_path / "damped.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return load_recipe(path, hand)


def _ring(runner: RecipeRunner, amplitude: float, seconds: float, t0: float = 0.0) -> list[float]:
    """f2_j2 (joint 4) swinging at 13 Hz with ``amplitude`` (rad), the others still: the
    torque proposed for it every tick."""
    out = []
    for k in range(round(seconds / DT)):
        t = t0 + k * DT
        angle = np.zeros(9)
        angle[4] = amplitude * math.sin(2 * math.pi * 13.0 * t)
        out.append(float(runner.step(t, angle, np.zeros(9))[4]))
    return out


def test_a_slow_motion_gets_the_recipe_s_damping_exactly(tmp_path: Path, hand: HandConfig) -> None:
    recipe = _damped_recipe(tmp_path, hand)
    plain = RecipeRunner(recipe, 9)
    backed = RecipeRunner(recipe, 9, backoff=RateBackoff.for_hand(hand, DT))
    # 0.01 rad at 13 Hz: 0.8 rad/s at most, a damping torque of 0.025 N·m that changes by
    # 2 N·m/s, a tenth of the rate limit
    assert _ring(backed, 0.01, 0.4) == _ring(plain, 0.01, 0.4)
    assert backed.backoff is not None and backed.backoff.gain.tolist() == [1.0] * 9


def test_a_ring_the_rate_limit_clips_is_damped_less(tmp_path: Path, hand: HandConfig) -> None:
    """0.15 rad at 13 Hz, as f2_j2 rang on a hand damped x0.3 (12 rad/s): the recipe's damper
    asks for ±0.36 N·m, changing at up to 30 N·m/s where the rate limit lets 20 through.
    Backed off, it asks for less, and the limiter clips it on fewer ticks."""
    recipe = _damped_recipe(tmp_path, hand)
    plain = RecipeRunner(recipe, 9)
    backed = RecipeRunner(recipe, 9, backoff=RateBackoff.for_hand(hand, DT))
    wild = _ring(plain, 0.15, 0.4)
    tame = _ring(backed, 0.15, 0.4)
    assert max(map(abs, wild[-100:])) > 0.3
    assert max(map(abs, tame[-100:])) < 0.75 * max(map(abs, wild[-100:]))
    # the ticks the limiter would have clipped of the plain runner's proposals
    counted = RateBackoff.for_hand(hand, DT)
    for value in wild:
        proposal = np.zeros(9)
        proposal[4] = value
        counted.observe(proposal)
    assert backed.backoff is not None
    assert backed.backoff.clipped_ticks[4] < 0.5 * counted.clipped_ticks[4]
    assert backed.backoff.gain[4] < 0.7
    assert backed.backoff.gain[3] == 1.0


def test_the_next_phase_keeps_the_back_off_it_is_handed(tmp_path: Path, hand: HandConfig) -> None:
    """The planner runs each phase on a runner of its own: a runner started from the previous
    one's handover mirrors the same limiter, so a phase starts from the gains and the last
    limited torques a run of the whole recipe would have there."""
    recipe = _damped_recipe(tmp_path, hand)
    first = RecipeRunner(recipe, 9, backoff=RateBackoff.for_hand(hand, DT))
    _ring(first, 0.15, 0.2)
    handed = first.handover()
    assert handed.backoff is first.backoff
    fresh = RateBackoff.for_hand(hand, DT)
    second = RecipeRunner(recipe, 9, handed, backoff=fresh)
    assert second.backoff is first.backoff
