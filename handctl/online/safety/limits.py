"""The one torque limiter, as pure functions of arrays.

Order matters and is fixed: first refuse what must never be clamped (a wrong shape, a NaN or an
infinity means the computation above is broken, and clamping would hide it), then clamp each
joint to its tau_max, then limit the change per tick to the joint's rate limit. The rate limit
is what makes every start, and every restart after a reset, a ramp from zero.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from handctl.arrays import FloatArray
from handctl.config import HandConfig
from handctl.online.safety.faults import FaultCode


@dataclass(frozen=True)
class JointLimits:
    """Per-joint limits as arrays in config joint order, built once from the hand config."""

    tau_max: FloatArray  # N·m
    rate_limit: FloatArray  # N·m/s
    angle_min: FloatArray  # rad
    angle_max: FloatArray  # rad
    names: tuple[str, ...]
    tau_max_list: tuple[float, ...]  # the same as plain floats, for the per-tick loop
    rate_list: tuple[float, ...]
    angle_min_list: tuple[float, ...]
    angle_max_list: tuple[float, ...]

    @classmethod
    def from_hand(cls, hand: HandConfig) -> JointLimits:
        joints = hand.joints
        return cls(
            tau_max=np.array([j.tau_max for j in joints]),
            rate_limit=np.array([j.rate_limit for j in joints]),
            angle_min=np.array([j.angle_min for j in joints]),
            angle_max=np.array([j.angle_max for j in joints]),
            names=tuple(j.name for j in joints),
            tau_max_list=tuple(j.tau_max for j in joints),
            rate_list=tuple(j.rate_limit for j in joints),
            angle_min_list=tuple(j.angle_min for j in joints),
            angle_max_list=tuple(j.angle_max for j in joints),
        )


def check_desired(
    desired: Sequence[float] | FloatArray, n_joints: int
) -> tuple[FaultCode, str] | None:
    """A fault for desired torques that must not be limited but refused; None when usable."""
    if isinstance(desired, np.ndarray) and desired.dtype == np.float64:
        arr = desired
    else:
        try:
            arr = np.asarray(desired, dtype=np.float64)
        except (TypeError, ValueError):
            return FaultCode.WRONG_SHAPE, f"desired torques are not numbers: {desired!r:.60}"
    if arr.shape != (n_joints,):
        return FaultCode.WRONG_SHAPE, f"expected {n_joints} torques, found shape {arr.shape}"
    # A NaN or an infinity makes the sum NaN or infinite; a finite sum proves every value
    # finite at a third of the cost of the elementwise test, which only a non-finite sum
    # (or a sum of huge finite values that overflowed) still needs.
    if not math.isfinite(sum(arr.tolist())) and not np.isfinite(arr).all():
        joint = int(np.argmax(~np.isfinite(arr)))
        return FaultCode.NON_FINITE_TORQUE, f"joint {joint}: {arr[joint]!r}"
    return None


def limit_torque(
    desired: FloatArray, last_applied: FloatArray, limits: JointLimits, dt: float, out: FloatArray
) -> int:
    """Clamp to ±tau_max, then to last ± rate·dt, into ``out``; returns how many joints were
    limited (a count for the record, not an error: limiting is the limiter's job).

    A plain loop over the joints: for nine values it is several times cheaper than the numpy
    calls, and it runs every tick. ``out`` may be ``last_applied``: it is read before ``out``
    is written.
    """
    limited = 0
    result = []
    for d, last, tau, rate in zip(
        desired.tolist(), last_applied.tolist(), limits.tau_max_list, limits.rate_list, strict=True
    ):
        v = tau if d > tau else (-tau if d < -tau else d)
        step = rate * dt
        if v > last + step:
            v = last + step
        elif v < last - step:
            v = last - step
        if v != d:
            limited += 1
        result.append(v)
    out[:] = result
    return limited


def angle_violations(angle: FloatArray, limits: JointLimits) -> list[int]:
    """Joints outside their soft limits."""
    return [
        j
        for j, (q, lo, hi) in enumerate(
            zip(angle.tolist(), limits.angle_min_list, limits.angle_max_list, strict=True)
        )
        if q < lo or q > hi
    ]
