"""The one torque limiter, as pure functions of arrays.

Order matters and is fixed: first refuse what must never be clamped (a wrong shape, a NaN or an
infinity means the computation above is broken, and clamping would hide it), then clamp each
joint to its tau_max, then limit the change per tick to the joint's rate limit. The rate limit
is what makes every start, and every restart after a reset, a ramp from zero.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from handctl.config import HandConfig
from handctl.safety.faults import FaultCode

FloatArray = npt.NDArray[np.float64]


@dataclass(frozen=True)
class JointLimits:
    """Per-joint limits as arrays in config joint order, built once from the hand config."""

    tau_max: FloatArray  # N·m
    rate_limit: FloatArray  # N·m/s
    angle_min: FloatArray  # rad
    angle_max: FloatArray  # rad
    names: tuple[str, ...]

    @classmethod
    def from_hand(cls, hand: HandConfig) -> JointLimits:
        joints = hand.joints
        return cls(
            tau_max=np.array([j.tau_max for j in joints]),
            rate_limit=np.array([j.rate_limit for j in joints]),
            angle_min=np.array([j.angle_min for j in joints]),
            angle_max=np.array([j.angle_max for j in joints]),
            names=tuple(j.name for j in joints),
        )


def check_desired(desired: Sequence[float] | FloatArray, n_joints: int
                  ) -> tuple[FaultCode, str] | None:
    """A fault for desired torques that must not be limited but refused; None when usable."""
    try:
        arr = np.asarray(desired, dtype=np.float64)
    except (TypeError, ValueError):
        return FaultCode.WRONG_SHAPE, f"desired torques are not numbers: {desired!r:.60}"
    if arr.shape != (n_joints,):
        return FaultCode.WRONG_SHAPE, f"expected {n_joints} torques, found shape {arr.shape}"
    bad = ~np.isfinite(arr)
    if bad.any():
        joint = int(np.argmax(bad))
        return FaultCode.NON_FINITE_TORQUE, f"joint {joint}: {arr[joint]!r}"
    return None


def limit_torque(desired: FloatArray, last_applied: FloatArray, limits: JointLimits,
                 dt: float, out: FloatArray) -> int:
    """Clamp to ±tau_max, then to last ± rate·dt, into ``out``; returns how many joints were
    limited (a count for the record, not an error: limiting is the limiter's job)."""
    np.clip(desired, -limits.tau_max, limits.tau_max, out=out)
    clamped = int(np.count_nonzero(out != desired))
    step = limits.rate_limit * dt
    lo = last_applied - step
    hi = last_applied + step
    rate_limited = int(np.count_nonzero((out < lo) | (out > hi)))
    np.clip(out, lo, hi, out=out)
    return clamped + rate_limited


def angle_violations(angle: FloatArray, limits: JointLimits) -> list[int]:
    """Joints outside their soft limits."""
    outside = (angle < limits.angle_min) | (angle > limits.angle_max)
    return [int(i) for i in np.flatnonzero(outside)]


def max_rate_needed(start: FloatArray, end: FloatArray, ramp_s: float) -> FloatArray:
    """The torque rate (N·m/s) a linear ramp from ``start`` to ``end`` over ``ramp_s`` needs."""
    if ramp_s <= 0:
        return np.where(start == end, 0.0, np.inf)
    return np.abs(end - start) / ramp_s
