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

A spring alone chatters: a joint that runs into its band at speed (a distal joint flicked by
a slipping object) is caught by the spring within a few ticks and bounced back, and the torque
it asks for swings by a tenth of a N·m in a few hundredths of a second. The guard therefore
also damps a joint heading for a limit: from a band before the spring's band on, fading in
over that band, a damping of ``gain * damping_s`` opposes the velocity towards the limit (the
velocity filtered from the angles, ``velocity.py``), so the joint reaches the spring slowly.
It opposes only that motion, so a joint leaving its limit is never held back, and it is small
against the tendon drive's lag (``GUARD_DAMPING_S``), so the damper itself stays stable.

The guard is a pure function of the measured angles (and the velocities filtered from them)
and the phase's torque, so a replay of the logged feedback computes the very same torques.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

from handctl.arrays import FloatArray
from handctl.config import HandConfig

#: s, the damper against the spring (damping = gain * this): over a nominal run, half of it
#: leaves the joints' bounces off their bands, twice as much chatters through the drive's lag
GUARD_DAMPING_S = 0.008


@dataclass(frozen=True)
class LimitGuard:
    """The band (rad) before each soft limit where the push-back acts, per joint."""

    band: float  # rad
    lower: tuple[float, ...]  # rad, where the band before the lower limit begins
    upper: tuple[float, ...]  # rad, where the band before the upper limit begins
    gain: tuple[float, ...]  # N·m/rad, tau_max / band
    tau_max: tuple[float, ...]  # N·m
    damping: tuple[float, ...] = ()  # N·m·s/rad, at full strength inside the band; (): none

    @classmethod
    def for_hand(
        cls, hand: HandConfig, band: float, damping_s: float = GUARD_DAMPING_S
    ) -> LimitGuard:
        """The guard with ``band`` (rad) for every joint of ``hand``, from its soft limits,
        with a damping of ``damping_s`` (s) times the spring's gain."""
        joints = hand.joints
        return cls(
            band,
            tuple(j.angle_min + band for j in joints),
            tuple(j.angle_max - band for j in joints),
            tuple(j.tau_max / band for j in joints),
            tuple(j.tau_max for j in joints),
            tuple(j.tau_max / band * damping_s for j in joints),
        )

    def apply(
        self,
        angle: Sequence[float] | FloatArray,
        desired: FloatArray,
        out: FloatArray,
        velocity: Sequence[float] | FloatArray | None = None,
    ) -> FloatArray:
        """``desired`` plus the push-back for ``angle`` (rad) and, given the joints'
        ``velocity`` (rad/s), the damping of a motion towards a limit, clipped to ±tau_max,
        in ``out``.

        Plain floats on purpose: this runs every tick and is usually a few comparisons.
        """
        out[:] = desired
        damped = velocity is not None and len(self.damping) > 0
        band = self.band
        for j, (q, lo, hi) in enumerate(zip(angle, self.lower, self.upper, strict=True)):
            push = 0.0
            if q > hi:
                push = -self.gain[j] * (q - hi)
            elif q < lo:
                push = self.gain[j] * (lo - q)
            if damped:
                assert velocity is not None
                v = float(velocity[j])
                # the damper meets a joint heading for a limit a band before the spring does,
                # fading in over that band, and opposes only the motion towards the limit
                if v > 0.0 and q > hi - band:
                    push -= self.damping[j] * min(1.0, (q - hi + band) / band) * v
                elif v < 0.0 and q < lo + band:
                    push -= self.damping[j] * min(1.0, (lo + band - q) / band) * v
            if push == 0.0:
                continue
            limit = self.tau_max[j]
            out[j] = max(-limit, min(limit, float(desired[j]) + push))
        return out
