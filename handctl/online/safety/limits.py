"""The one torque limiter, as pure functions of arrays.

Order matters and is fixed: first refuse what must never be clamped (a wrong shape, a NaN or an
infinity means the computation above is broken, and clamping would hide it), then clamp each
joint to its tau_max, then limit the change per tick to the joint's rate limit, then put the
result on the command signal's grid (its resolution, ``step_list``): the nearest point, as the
encoder rounds, or the one towards the last applied torque where the nearest would pass a
limit. The rate limit is what makes every start, and every restart after a reset, a
ramp from zero.

Why the grid here and not only in the encoder: the frame carries a multiple of the signal's
resolution, and the encoder's rounding to the nearest one could carry up to half a resolution
more than ``tau_max`` and a step of up to one resolution more than the rate limit allows (two
neighbouring values rounded apart). Rounded towards the last applied torque, which is on the
grid itself, a value moves no further than the limiter let it, so both limits hold for what
the wire carries, and the applied torques the log records are exactly what the frames say.
Everywhere else the nearest point is what the frames carried before the grid was kept here,
so the hand is driven as it was.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from handctl.arrays import FloatArray
from handctl.config import HandConfig
from handctl.hand_protocol import protocol_for
from handctl.online.safety.faults import FaultCode
from handctl.protocol import Protocol

#: A value within this fraction of a resolution below a grid point is that point: the
#: floating-point rest of ``last + step``, not a value short of it.
GRID_SLACK = 1e-9


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
    #: N·m, the resolution of each joint's command signal: applied torques are multiples of it
    step_list: tuple[float, ...]

    @classmethod
    def from_hand(cls, hand: HandConfig, protocol: Protocol | None = None) -> JointLimits:
        """The limits of ``hand``, on the grid of ``protocol``'s command signals (None: the
        protocol the hand speaks, ``protocol_for``)."""
        if protocol is None:
            protocol = protocol_for(hand)
        steps: list[float] = []
        for finger in hand.fingers:
            signals = protocol.layout("TorqueCommand", finger.node_id).signals
            steps += [signals[k].scale for k in range(len(finger.joints))]
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
            step_list=tuple(steps),
        )


def check_desired(
    desired: Sequence[float] | FloatArray, n_joints: int, names: Sequence[str] = ()
) -> tuple[FaultCode, str] | None:
    """A fault for desired torques that must not be limited but refused; None when usable.
    ``names``: the joints', to name the one at fault (else its index)."""
    if isinstance(desired, np.ndarray) and desired.dtype == np.float64:
        arr = desired
    else:
        # real numbers only: asked as float64 at once, numeric strings ("0.1") and booleans
        # became torques and complex values lost their imaginary part with a warning (found
        # by an outside audit)
        try:
            raw = np.asarray(desired)
        except (TypeError, ValueError):  # ragged
            raw = np.asarray(None)
        if raw.dtype.kind not in "iuf":
            return FaultCode.WRONG_SHAPE, (
                f"desired torques are not real numbers ({raw.dtype} values): {desired!r:.60}"
            )
        arr = raw.astype(np.float64)
    if arr.shape != (n_joints,):
        return FaultCode.WRONG_SHAPE, f"expected {n_joints} torques, found shape {arr.shape}"
    # A NaN or an infinity makes the sum NaN or infinite; a finite sum proves every value
    # finite at a third of the cost of the elementwise test, which only a non-finite sum
    # (or a sum of huge finite values that overflowed) still needs.
    if not math.isfinite(sum(arr.tolist())) and not np.isfinite(arr).all():
        joint = int(np.argmax(~np.isfinite(arr)))
        name = names[joint] if len(names) == n_joints else f"joint {joint}"
        return FaultCode.NON_FINITE_TORQUE, f"{name}: {float(arr[joint])} N·m asked"
    return None


def limit_torque(
    desired: FloatArray, last_applied: FloatArray, limits: JointLimits, dt: float, out: FloatArray
) -> int:
    """Clamp to ±tau_max, then to last ± rate·dt, then onto the command grid (the nearest
    point within both limits), into ``out``; returns how many joints were limited (a count
    for the record, not an error: limiting is the limiter's job; the grid's rounding is not
    counted). ``last_applied`` is on the grid (every applied torque comes from here, from
    ``toward_zero_on_grid`` or is zero).

    A plain loop over the joints: for nine values it is several times cheaper than the numpy
    calls, and it runs every tick. ``out`` may be ``last_applied``: it is read before ``out``
    is written.
    """
    limited = 0
    result = []
    floor, ceil = math.floor, math.ceil
    # within GRID_SLACK of a grid point is that point (the encoder sends it), so past the
    # slack a value lies strictly between two points and floor/ceil pick the right one
    for d, last, tau, rate, grid in zip(
        desired.tolist(),
        last_applied.tolist(),
        limits.tau_max_list,
        limits.rate_list,
        limits.step_list,
        strict=True,
    ):
        v = tau if d > tau else (-tau if d < -tau else d)
        step = rate * dt
        if v > last + step:
            v = last + step
        elif v < last - step:
            v = last - step
        if v != d:
            limited += 1
        if v != last:
            k = v / grid
            n = round(k)
            if abs(k - n) > GRID_SLACK:  # on the grid already: as asked, 0.54 not 5400 * 1e-4
                q = n * grid  # the nearest, as the encoder rounds, unless past a limit
                if q > tau or q < -tau or abs(q - last) > step:
                    q = (floor(k) if v > last else ceil(k)) * grid
                v = q
        result.append(v)
    out[:] = result
    return limited


def toward_zero_on_grid(values: FloatArray, limits: JointLimits) -> None:
    """``values`` onto the command grid, each rounded towards zero (in place): a fault's
    ramp, which scales the torques down, never carries more than it asked for."""
    out = []
    for v, grid in zip(values.tolist(), limits.step_list, strict=True):
        k = v / grid
        out.append(v if abs(k - round(k)) <= GRID_SLACK else math.trunc(k) * grid)
    values[:] = out


def angle_violations(angle: FloatArray, limits: JointLimits) -> list[int]:
    """Joints outside their soft limits."""
    return [
        j
        for j, (q, lo, hi) in enumerate(
            zip(angle.tolist(), limits.angle_min_list, limits.angle_max_list, strict=True)
        )
        if q < lo or q > hi
    ]


def outside_text(j: int, angle: FloatArray, limits: JointLimits, before_torque: bool) -> str:
    """Joint ``j`` outside its soft limits, as a refusal says it: its angle and limits, and,
    ``before_torque`` (none has flowed yet), the command that brings it back. Shared by the
    run's ANGLE_LIMIT and a replay onto a bus, so that a hand resting outside is told the
    same way whichever of them found it. (An angle of NaN is no joint outside: one not heard.)

    Outside before any torque flowed, no run can arm until it is back, and this message is
    the only place the user learns how; every joint outside is named (a hand left at zero
    torque sags several at once, and one named seemed the only one)."""
    detail = (
        f"{limits.names[j]} at {angle[j]:+.3f} rad, limits "
        f"[{limits.angle_min[j]:+.3f}, {limits.angle_max[j]:+.3f}]"
    )
    if before_torque:
        sign = "-" if angle[j] > limits.angle_max[j] else "+"
        others = [limits.names[k] for k in angle_violations(angle, limits) if k != j]
        detail += (
            (f" ({', '.join(others)} outside too)" if others else "")
            + f", before any torque: bring it back with `handctl jog {limits.names[j]} "
            f"--torque {sign}X --recover`"
            + (", then each of the others" if others else "")
            + " (docs/bringup.md)"
        )
    return detail
