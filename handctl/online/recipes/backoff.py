"""The injected damping backs off on a joint whose command the rate limit clips.

Why: a damper is a damper only while its torque can follow the joint's velocity. On a lightly
damped hand (its own damping x0.3..x0.4, little tendon friction) a middle or distal joint
that loses its contact with the pair rings at about 13 Hz; the phase's injected damping
(0.03 N·m·s/rad on a middle joint) then asks for a torque that swings by a N·m in 30 ms.
The supervisor lets the command change by 20 N·m/s at most (the hand config's
``rate_limit``), so the torque that reaches the joint is a ramp that lags the velocity by a
good part of a period more than the drive's lag alone: the damper pumps energy in instead of
taking it out, and the ring grows to the joint's hard limit (``ANGLE_LIMIT``) within a few
tenths of a second. The same hands with a rate limit of 200 N·m/s do not ring, and neither
do they with half the injected damping; the nominal hand's run clips on 4 ticks of one
joint. The injected damping of a phase was chosen for the linear loop, where the rate limit
does not act; once it acts, the loop is another one.

So the runner keeps, per joint, a gain on its injected damping (the phase's
``joint_damping`` and a brake's): each tick on which the supervisor would clip the proposed
torque by the rate limit, the gain falls by ``BACKOFF_DECAY``; each tick it would not, the
gain comes back towards 1 by ``period / BACKOFF_RECOVER_S``, never below
``BACKOFF_GAIN_MIN``. Whether the supervisor would clip is read off a mirror of its limiter
(``safety.limits.limit_torque``: the clamp to ±tau_max, then the change per tick), fed the
runner's own proposals one tick late (each when the next tick begins, so a proposal the
planner drops, on the tick a phase is left, is never taken in): the runner need not be told
what the supervisor did, and a re-run of the logged feedback computes the same gains (the
mirror leaves out the limiter's last step, the command grid, whose rounding is less than a
resolution).

It only lowers a damping the recipe asked for, so it cannot ask for more torque than the
recipe would; every torque still passes the supervisor.
"""

from __future__ import annotations

import numpy as np

from handctl.arrays import FloatArray
from handctl.config import HandConfig

#: the gain's factor on each clipped tick: halved in seven ticks of clipping, a tenth of a
#: 13 Hz ring's period, so the damper backs off within the ring's first swing into the limit
BACKOFF_DECAY = 0.9
#: s, from no damping back to the recipe's, in steps of a tick, while nothing is clipped: a
#: few periods of the ring, so a damper that was clipped comes back once the ring has died
BACKOFF_RECOVER_S = 0.2
#: the least of the recipe's damping kept: the damper never leaves a joint undamped
BACKOFF_GAIN_MIN = 0.1
#: N·m, a change this much over the rate limit's step is clipped; below it, a float's rest
CLIP_SLACK = 1e-12


class RateBackoff:
    """Per-joint gains on the injected damping, from a mirror of the supervisor's limiter."""

    def __init__(self, rate_limit: tuple[float, ...], tau_max: tuple[float, ...], period_s: float):
        if len(rate_limit) != len(tau_max):
            raise ValueError(f"{len(rate_limit)} rate limits for {len(tau_max)} joints")
        if not period_s > 0.0:
            raise ValueError(f"period_s must be > 0 s, got {period_s}")
        self.steps = tuple(r * period_s for r in rate_limit)  # N·m a tick
        self.tau_max = tau_max
        self.recover = period_s / BACKOFF_RECOVER_S  # of the gain a tick
        #: the gain on each joint's injected damping, 1 until the rate limit clips it (the
        #: runner multiplies by this array; ``observe`` works on plain floats and writes the
        #: array only on a tick that changed a gain)
        self.gain: FloatArray = np.ones(len(tau_max))
        self._gains = [1.0] * len(tau_max)
        # what the supervisor would have applied last, on each joint (N·m)
        self._mirror = [0.0] * len(tau_max)
        #: ticks on which a joint's command would have been clipped
        self.clipped_ticks = [0] * len(tau_max)
        #: each joint's least gain since the runner last gave it a fresh list (a phase's
        #: record holds it: the run's summary says how far a phase's damping backed off)
        self.least = [1.0] * len(tau_max)

    @classmethod
    def for_hand(cls, hand: HandConfig, period_s: float) -> RateBackoff:
        """The back-off for ``hand``'s limits, its supervisor limiting every ``period_s``."""
        joints = hand.joints
        return cls(tuple(j.rate_limit for j in joints), tuple(j.tau_max for j in joints), period_s)

    def observe(self, proposed: FloatArray) -> None:
        """Take in a proposed torque once it was sent (the runner hands it over on the next
        tick): the joints it clipped back off, the others recover.

        Plain floats: nine of them, every tick (as ``limit_torque``)."""
        gains = self._gains
        mirror = self._mirror
        changed = False
        for j, (d, last, step, tau) in enumerate(
            zip(proposed.tolist(), mirror, self.steps, self.tau_max, strict=True)
        ):
            v = tau if d > tau else (-tau if d < -tau else d)
            if v > last + step + CLIP_SLACK or v < last - step - CLIP_SLACK:
                mirror[j] = last + step if v > last else last - step
                g = max(BACKOFF_GAIN_MIN, gains[j] * BACKOFF_DECAY)
                gains[j] = g
                self.clipped_ticks[j] += 1
                self.least[j] = min(self.least[j], g)
                changed = True
            else:
                mirror[j] = v
                if gains[j] < 1.0:
                    gains[j] = min(1.0, gains[j] + self.recover)
                    changed = True
        if changed:
            self.gain[:] = gains
