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


class FittedVelocity:
    """Joint velocities (rad/s) as the slope of a least-squares line through the angles of the
    last ``window`` ticks, one ``update`` per tick.

    Why, beside the low-pass above: a damper acting through the tendon drive's lag needs a
    velocity that adds little lag of its own, and a low-pass short enough for that passes the
    encoder's steps on (3 ms: a quarter of 0.38 rad/s for every count). A line through eight
    ticks lags by half its span (3.5 ms) and moves by about 0.38 rad/s * 6 * 3.5 / 168, i.e.
    0.05 rad/s, when a count enters it, and its noise from the counts is a sixth of one tick's
    difference. Until ``window`` angles have come in, the line is through those there are.
    """

    def __init__(self, n_joints: int, window: int) -> None:
        if window < 2:
            raise ValueError(f"window must be >= 2 ticks, got {window}")
        self.window = window
        self.value: FloatArray = np.zeros(n_joints)
        # a ring of the last ``window`` angles and their times; ``_next`` is the oldest slot
        self._angles: FloatArray = np.zeros((window, n_joints))
        self._times = [0.0] * window
        self._weights: FloatArray = np.zeros(window)
        self._next = 0
        self._count = 0

    def update(self, t: float, angle: Sequence[float] | FloatArray) -> FloatArray:
        """The estimate after the angles ``angle`` (rad) measured at ``t`` (s)."""
        last = (self._next - 1) % self.window
        if self._count and not t > self._times[last]:
            return self.value  # the same tick again: no new information
        slot = self._next
        self._angles[slot] = angle
        self._times[slot] = t
        self._next = (slot + 1) % self.window
        self._count = min(self._count + 1, self.window)
        if self._count < 2:
            return self.value
        # the slope's weights (t_k - mean) / sum (t_k - mean)^2 over the slots in use, as
        # plain floats: a handful of them is cheaper than the array calls it would take
        times = self._times
        used = [(slot - k) % self.window for k in range(self._count)]
        mean = sum(times[k] for k in used) / self._count
        spread = sum((times[k] - mean) ** 2 for k in used)
        weights = self._weights
        for k in used:
            weights[k] = (times[k] - mean) / spread
        np.dot(weights, self._angles, out=self.value)
        return self.value
