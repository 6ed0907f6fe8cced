"""``handctl jog JOINT --torque X``: one joint under a small torque, to check its direction,
sign and scale before a recipe relies on them.

The jog is a recipe of one phase built in memory (the joint ramps to X N·m within its rate
limit, every other joint gets zero, then the end ramp back to zero) with the soft-limit guard,
run by the normal Runtime: every torque passes the supervisor with the hand's limits, exactly
as in a recipe run, and Ctrl-C is its controlled stop. A torque over the joint's ``tau_max`` is
refused before anything is opened or sent.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from handctl.bringup.zero_recipe import in_memory_recipe, phase
from handctl.config import HandConfig
from handctl.errors import ConfigError
from handctl.online.clock import Tick
from handctl.online.loop import TickRecord
from handctl.online.recipes.schema import Recipe
from handctl.session import RunReport, RunRequest, run_recipe

#: The shortest ramp to and from the jog torque (s), however high the rate limit.
MIN_RAMP_S = 0.2
#: rad, the soft-limit guard's band (as the default recipe's ``limit_guard_band``).
GUARD_BAND = 0.15
#: A line of the run-time table every this many ticks.
TABLE_EVERY_TICKS = 100


@dataclass(frozen=True)
class JogLine:
    """What the run-time table shows of one tick (SI units)."""

    t_s: float
    phase: str
    state: str
    desired: float  # N·m, what the jog asks of the joint (the guard's push-back included)
    applied: float  # N·m, what the supervisor let through
    angle: float  # rad
    tdt: float  # N·m


@dataclass
class JogReport:
    report: RunReport
    joint: str
    torque: float
    start_angle: float | None  # rad, when torque first flowed
    end_angle: float | None  # rad, at the end of the run
    max_abs_tdt: float  # N·m

    @property
    def moved(self) -> float | None:
        if self.start_angle is None or self.end_angle is None:
            return None
        return self.end_angle - self.start_angle


class JogSink:
    """A ``RecordSink`` that keeps the jogged joint's line every ``every`` ticks for ``show``
    and the angles a summary needs."""

    def __init__(
        self,
        index: int,
        show: Callable[[JogLine], None] | None,
        period_s: float,
        every: int = TABLE_EVERY_TICKS,
    ) -> None:
        self.index = index
        self.show = show
        self.period_s = period_s
        self.every = every
        self.start_angle: float | None = None
        self.end_angle: float | None = None
        self.max_abs_tdt = 0.0
        self._first_tick: int | None = None

    def begin_tick(self, tick: Tick) -> None:
        pass

    def note(self, kind: str, detail: str, tick: int) -> None:
        pass

    def push(self, record: TickRecord) -> None:
        j = self.index
        angle, tdt = float(record.angle[j]), float(record.tdt[j])
        if self._first_tick is None:
            self._first_tick = record.tick
            self.start_angle = angle
        self.end_angle = angle
        if np.isfinite(tdt):
            self.max_abs_tdt = max(self.max_abs_tdt, abs(tdt))
        if self.show is not None and (record.tick - self._first_tick) % self.every == 0:
            self.show(
                JogLine(
                    (record.tick - self._first_tick) * self.period_s,
                    record.phase,
                    record.state,
                    float(record.desired[j]),
                    float(record.applied[j]),
                    angle,
                    tdt,
                )
            )


def joint_index(hand: HandConfig, joint: str) -> int:
    names = hand.joint_names
    if joint not in names:
        raise ConfigError("JOINT", "", f"a joint of {hand.source} ({', '.join(names)})", joint)
    return names.index(joint)


def jog_recipe(hand: HandConfig, joint: str, torque: float, seconds: float) -> Recipe:
    """The one-phase jog; refused (``ConfigError``) over ``tau_max``, naming the limit."""
    j = joint_index(hand, joint)
    spec = hand.joints[j]
    if not abs(torque) <= spec.tau_max:  # NaN too
        raise ConfigError(
            "--torque",
            "",
            f"|τ| <= {spec.tau_max:g} N·m (tau_max of {joint} in {hand.source})",
            torque,
        )
    ramp = max(MIN_RAMP_S, abs(torque) / spec.rate_limit)
    torques = [0.0] * hand.n_joints
    torques[j] = torque
    return in_memory_recipe(
        f"jog_{joint}",
        f"{torque:+g} N·m on {joint}, zero elsewhere",
        hand,
        [phase("jog", torques, ramp, ramp + seconds)],
        ramp,
        guard_band=GUARD_BAND,
    )


def jog(
    hand: HandConfig,
    joint: str,
    torque: float,
    *,
    seconds: float = 2.0,
    bus: str = "sim",
    lockstep: bool | None = None,
    realtime_priority: bool = False,
    seed: int = 0,
    sim_faults: Path | None = None,
    reset_node_faults: bool = False,
    accept_missed_deadlines: bool = False,
    show: Callable[[JogLine], None] | None = None,
) -> JogReport:
    """Jog ``joint`` with ``torque`` N·m for ``seconds`` after the ramp, on ``bus``."""
    recipe = jog_recipe(hand, joint, torque, seconds)
    sink = JogSink(joint_index(hand, joint), show, hand.bus.period_s)
    report = run_recipe(
        RunRequest(
            hand=hand,
            recipe=recipe,
            bus=bus,
            lockstep=lockstep,
            realtime_priority=realtime_priority,
            seed=seed,
            sim_faults=sim_faults,
            reset_node_faults=reset_node_faults,
            accept_missed_deadlines=accept_missed_deadlines,
        ),
        recorder=sink,
    )
    return JogReport(report, joint, torque, sink.start_angle, sink.end_angle, sink.max_abs_tdt)
