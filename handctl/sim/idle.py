"""Where the simulated hand goes with no torque on it: a joint gravity carries past a soft
limit.

The config's checks place the start pose inside the soft limits, and nothing asked where the
fingers go from there once every motor is at zero: under gravity a finger swings until its
mechanical stop, which lies beyond the soft limit (``stop_margin``), or until it rests on a
link, an object or the table. Every phase of zero torque (``calibrate tdt``'s settle and
measurement, a recipe that begins with a ramp from zero) then stops on ``ANGLE_LIMIT`` within
ticks, and the user learnt it from the first run. ``handctl check`` runs the hand idle
instead and says which joint leaves its range.

Only the model's answer: a real finger may hold its pose by friction the model lacks, or sag
where the model's does not.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from handctl.config import HandConfig
from handctl.sim.params import NODE_TICK_S, SimParams
from handctl.sim.plant import Plant

#: s, how long the hand is left idle: ``calibrate tdt``'s default settle and measurement
IDLE_S = 3.0


@dataclass(frozen=True)
class Excursion:
    """A joint that left its soft limits with no torque on the hand."""

    joint: int  # index in the config's order
    start: float  # rad, its initial angle
    angle: float  # rad, its first angle outside the soft limits
    limit: float  # rad, the soft limit it crossed
    time_s: float  # s, idle when it crossed


def idle_excursions(
    hand: HandConfig, params: SimParams, seconds: float = IDLE_S
) -> list[Excursion]:
    """Each joint that leaves its soft limits (once: its first crossing) while the simulated
    hand stands ``seconds`` with zero torque from its initial pose, in the config's order."""
    plant = Plant(hand, params)
    plant.set_torque_commands(np.zeros(hand.n_joints))
    lo = np.array([j.angle_min for j in hand.joints])
    hi = np.array([j.angle_max for j in hand.joints])
    start = plant.joint_angles.copy()
    found: dict[int, Excursion] = {}
    for tick in range(1, round(seconds / NODE_TICK_S) + 1):
        plant.step()
        angles = plant.joint_angles
        outside = np.flatnonzero((angles < lo) | (angles > hi))
        for j in outside:
            if int(j) not in found:
                angle = float(angles[j])
                limit = float(lo[j] if angle < lo[j] else hi[j])
                found[int(j)] = Excursion(int(j), float(start[j]), angle, limit, tick * NODE_TICK_S)
    return [found[j] for j in sorted(found)]
