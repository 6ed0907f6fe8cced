"""Joint velocities on the online plane, from the measured angles alone.

The nodes report angles, not velocities, and a 14-bit encoder read every millisecond moves in
steps of 0.38 mrad: one count in one tick is 0.38 rad/s. A raw difference is therefore a
train of spikes that any gain multiplies into torque chatter. The estimate here is the
difference of angles between ticks, divided by the time between them, through a first-order
low-pass of time constant ``time_constant`` (s): one count in one tick then moves it by
``0.38 rad/s * dt / (time_constant + dt)``, and a steady motion is followed with that lag.

It is a pure function of the sequence of (time, angles) it is fed, so a re-run of logged
feedback reproduces it exactly; it allocates nothing per tick.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from handctl.arrays import FloatArray

#: s, the default smoothing: long against one tick, short against how fast a grasp changes
VELOCITY_TIME_CONSTANT = 0.010


class JointVelocity:
    """Filtered joint velocities (rad/s), one ``update`` per tick."""

    def __init__(self, n_joints: int, time_constant: float = VELOCITY_TIME_CONSTANT) -> None:
        if time_constant < 0:
            raise ValueError(f"time_constant must be >= 0 s, got {time_constant}")
        self.time_constant = time_constant
        self.value: FloatArray = np.zeros(n_joints)
        self._previous: FloatArray = np.zeros(n_joints)
        self._t = math.nan
        self._raw: FloatArray = np.zeros(n_joints)

    def reset(self) -> None:
        """Forget the history: the next update starts from rest."""
        self.value[:] = 0.0
        self._t = math.nan

    def update(self, t: float, angle: Sequence[float] | FloatArray) -> FloatArray:
        """The estimate after the angles ``angle`` (rad) measured at ``t`` (s)."""
        dt = t - self._t
        if not dt > 0.0:  # first call (NaN), or the same tick again: no new information
            if math.isnan(self._t):
                self._previous[:] = angle
                self._t = t
            return self.value
        np.subtract(angle, self._previous, out=self._raw)
        self._raw /= dt
        alpha = dt / (self.time_constant + dt)
        self._raw -= self.value
        self._raw *= alpha
        self.value += self._raw
        self._previous[:] = angle
        self._t = t
        return self.value
