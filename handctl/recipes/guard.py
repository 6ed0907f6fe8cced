"""Soft-limit avoidance on the online plane: a joint that nears a soft limit is pushed back.

Why: in an enveloping grasp the joints are not where the torques put them but where the
objects let them be, and contact can bend a distal joint backwards into its soft limit. The
supervisor rightly stops the hand when a limit is crossed (a ``SOFT_LIMIT`` fault), so an
open-loop torque that brushes a limit on one model of the hand stops the run on another. A
spring inside a band before each limit turns that cliff into a slope: the desired torque gets
``tau_max * depth / band`` pushing the joint back, where ``depth`` is how far the joint is
inside the band, reaching the joint's full ``tau_max`` at the limit itself. It only proposes
torque, like the recipe runner it belongs to: the supervisor still clamps every torque to
``tau_max`` and the rate limit and still trips at the limit.

The guard is a pure function of the measured angles and the phase's torque, so a replay of the
logged feedback computes the very same torques.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

from handctl.config import HandConfig
from handctl.safety.limits import FloatArray


@dataclass(frozen=True)
class LimitGuard:
    """The band (rad) before each soft limit where the push-back acts, per joint."""

    band: float  # rad
    lower: tuple[float, ...]  # rad, where the band before the lower limit begins
    upper: tuple[float, ...]  # rad, where the band before the upper limit begins
    gain: tuple[float, ...]  # N·m/rad, tau_max / band
    tau_max: tuple[float, ...]  # N·m

    @classmethod
    def for_hand(cls, hand: HandConfig, band: float) -> LimitGuard:
        """The guard with ``band`` (rad) for every joint of ``hand``, from its soft limits."""
        joints = hand.joints
        return cls(band,
                   tuple(j.angle_min + band for j in joints),
                   tuple(j.angle_max - band for j in joints),
                   tuple(j.tau_max / band for j in joints),
                   tuple(j.tau_max for j in joints))

    def apply(self, angle: Sequence[float] | FloatArray, desired: FloatArray,
              out: FloatArray) -> FloatArray:
        """``desired`` plus the push-back for ``angle`` (rad), clipped to ±tau_max, in ``out``.

        Plain floats on purpose: this runs every tick and is usually a few comparisons.
        """
        out[:] = desired
        for j, (q, lo, hi) in enumerate(zip(angle, self.lower, self.upper, strict=True)):
            if q > hi:
                push = -self.gain[j] * (q - hi)
            elif q < lo:
                push = self.gain[j] * (lo - q)
            else:
                continue
            limit = self.tau_max[j]
            out[j] = max(-limit, min(limit, float(desired[j]) + push))
        return out
