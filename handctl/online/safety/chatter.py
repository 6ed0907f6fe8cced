"""A joint whose command swings back and forth for tenths of a second: a feedback loop ringing.

Why: every torque passes the supervisor, so a feedback too stiff for a joint (a soft-limit
guard band narrower than the joint's inertia and the drive's lag allow, an injected or a pose
damper several times what a light link tolerates) never gets past tau_max or the rate
limit. It does something the limits do not see: the command slews at the rate limit one way,
then the other, tens of times a second, for as long as the phase lasts. The run completed,
exit 0, with no word of it, while a real joint and its tendon took a 25 Hz square wave of
torque for seconds. Whether a gain is too stiff depends on the joint's inertia and the drive's
lag, which a hand config does not carry, so the loader cannot refuse it; the run can see it
and say so.

What counts: the command turns back by at least ``SWING_SHARE`` of the joint's tau_max from
its last extreme (a half swing) ``MIN_SWINGS`` times within about ``WINDOW_S``: a ring of
10 Hz and more whose swing is a tenth of what the joint can do, whether the rate limit clips
it (a square wave) or not (a damper backed off to a smooth ring). A phase's ramp, a stop or a
paced ramp moves one way for tenths of a second; noise turns back by far less. The watch only
reads what was sent; a ring shorter than ``MIN_RING_S`` in all is not said.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from handctl.arrays import FloatArray

#: s, the span the watch judges over (an exponential average this long)
WINDOW_S = 0.2
#: half swings within a window that make a ring: two full periods, 10 Hz at the least
MIN_SWINGS = 4
#: a half swing turns back from the last extreme by this share of the joint's tau_max at least
SWING_SHARE = 0.1
#: s, the least time ringing that is said: a guard that catches a joint flung at its limit
#: rings for a few periods and settles (a quarter of a second on a distal joint)
MIN_RING_S = 0.5


@dataclass
class Ringing:
    """One joint's time ringing, for the summary."""

    joint: str
    from_s: float  # s, the recipe's time when it was first seen ringing
    seconds: float  # s, how long it rang in all
    amplitude_nm: float  # N·m, half the swing of the command while it rang
    frequency_hz: float  # Hz, full swings a second while it rang

    def text(self) -> str:
        return (
            f"{self.joint}'s command rang (±{self.amplitude_nm:.3g} N·m, "
            f"{self.frequency_hz:.0f} Hz) for {self.seconds:.2f} s from {self.from_s:.2f} s: "
            "a feedback too stiff for this joint (the soft-limit guard's band, an injected or "
            "a pose damping); the limits held, the joint took the swing"
        )


class ChatterWatch:
    """Per joint, whether its command rings, from the torques sent.

    The tick's work is a handful of operations on the joints' arrays; the count of half swings
    (a sum of past swings, each weighted by how long ago it was, ``WINDOW_S`` its decay time)
    is brought up to date only on a tick with a half swing, as is the time spent ringing: a
    joint rings from a half swing that brings the count to ``MIN_SWINGS`` to its last one."""

    def __init__(self, names: tuple[str, ...], tau_max: FloatArray, period_s: float) -> None:
        self.names = names
        n = len(names)
        self._turn = -np.asarray(tau_max, dtype=float) * SWING_SHARE  # N·m, back from the extreme
        self._decay = float(np.exp(-period_s / WINDOW_S))
        self._period_s = period_s
        self._extreme = np.zeros(n)  # N·m, the command's last extreme
        self._sense = np.ones(n)  # +1 while the command last went up, -1 down
        # scratch, written in place every tick: the command against its extreme (the sense's
        # way), the joints that turned back, those to take a new extreme
        self._gap = np.empty(n)
        self._turned_now = np.empty(n, dtype=bool)
        self._new_extreme = np.empty(n, dtype=bool)
        self._tick = 0
        self._count = [0.0] * n  # half swings, weighted by age, at ``_at``
        self._at = [0] * n  # the tick of each joint's last half swing
        self._rang = [False] * n  # whether the last half swing found the joint ringing
        self._ticks = [0] * n  # ticks ringing
        self._flips = [0] * n  # half swings while ringing
        self._first = [math.nan] * n
        self._low = [math.inf] * n
        self._high = [-math.inf] * n

    def observe(self, applied: FloatArray, t_s: float) -> None:
        """The torques sent in the tick at recipe time ``t_s`` (N·m)."""
        gap, turned, new = self._gap, self._turned_now, self._new_extreme
        np.subtract(applied, self._extreme, out=gap)
        gap *= self._sense
        np.less_equal(gap, self._turn, out=turned)
        if turned.any():
            self._turned(np.flatnonzero(turned), t_s)
        np.greater(gap, 0.0, out=new)
        new |= turned
        np.copyto(self._extreme, applied, where=new)
        self._tick += 1

    def _turned(self, joints: npt.NDArray[np.intp], t_s: float) -> None:
        """Joints whose command turned back by a half swing this tick (``_extreme`` still
        holds the extreme each turned back from)."""
        tick = self._tick
        for j in joints.tolist():
            self._sense[j] = -self._sense[j]
            swing_from = float(self._extreme[j])
            count = self._count[j] * self._decay ** (tick - self._at[j]) + 1.0
            ringing = count >= MIN_SWINGS
            if ringing:
                if self._rang[j]:
                    self._ticks[j] += tick - self._at[j]
                    self._flips[j] += 1
                elif math.isnan(self._first[j]):
                    self._first[j] = t_s
                self._low[j] = min(self._low[j], swing_from)
                self._high[j] = max(self._high[j], swing_from)
            self._count[j], self._at[j], self._rang[j] = count, tick, ringing

    def found(self) -> list[Ringing]:
        """Every joint seen ringing for ``MIN_RING_S`` in all, first seen first."""
        out = []
        for j, ticks in enumerate(self._ticks):
            seconds = ticks * self._period_s
            if seconds < MIN_RING_S - 1e-9:
                continue
            out.append(
                Ringing(
                    self.names[j],
                    round(self._first[j], 3),
                    round(seconds, 3),
                    round((self._high[j] - self._low[j]) / 2.0, 4),
                    round(self._flips[j] / 2.0 / seconds, 1),
                )
            )
        return sorted(out, key=lambda r: r.from_s)
