"""Soft-limit avoidance on the online plane: a joint that nears a soft limit is pushed back.

Why: in an enveloping grasp the joints are not where the torques put them but where the
objects let them be, and contact can bend a distal joint backwards into its soft limit. The
supervisor rightly stops the hand when a limit is crossed (a ``SOFT_LIMIT`` fault), so an
open-loop torque that brushes a limit on one model of the hand stops the run on another. A
spring inside a band before each limit turns that cliff into a slope: the desired torque gets
``tau_max * depth / band`` pushing the joint back, where ``depth`` is how far the joint is
inside the band, reaching the joint's full ``tau_max`` at the limit itself. Over the band's
second half the spring also takes on, more and more, what the proposed torque asks towards
the limit (``GUARD_DEEP_FRACTION``), so at the limit the joint is pushed back with the whole
``tau_max`` even by a phase that asks its ``tau_max`` towards it; a spring that stopped at
``tau_max`` cancelled such a phase there and no more, and the contact pushed the joint over.
It only proposes torque, like the recipe runner it belongs to: the supervisor still clamps
every torque to ``tau_max`` and the rate limit and still trips at the limit.

A spring alone chatters: a joint that runs into its band at speed (a distal joint flicked by
a slipping object) is caught by the spring within a few ticks and bounced back, and the torque
it asks for swings by a tenth of a N·m in a few hundredths of a second. The guard therefore
also damps a joint heading for a limit: from a band before the spring's band on, fading in
over that band, a damping of ``gain * damping_s`` opposes the velocity towards the limit, so
the joint reaches the spring slowly. It opposes only that motion, so a joint leaving its
limit is never held back.

Two things decide whether that damper acts in time, and both are the drive's lag (5 ms,
×0.5..×2 over the model set) against the joint's own damping (×0.3..×3). A spring acting
through a lag ``tau`` is a negative damping of about ``gain * tau``; the guard's spring
(``tau_max / band``, 2 N·m/rad on a distal joint) through 5..10 ms is 0.01..0.02 N·m·s/rad,
as much as a nominal joint's own damping and several times a lightly damped one's. The damper
that makes up for it must not add much lag of its own, so it acts on a velocity of its own:
the slope of a line through the angles of the last 7 ms (8 ticks at 1 kHz,
``velocity.FittedVelocity``), which lags by 3.5 ms where the recipe's low-pass lags by 10 ms,
and moves by a sixth as much when an encoder count comes in. And a finger flung at a limit on
a lightly damped hand (the lift on a hand whose damping is ×0.3 moves the distal joints at 20
rad/s, three times the nominal's) crosses both bands in less than the lag: the damper
therefore judges where the joint will be ``lookahead`` later at its present speed
(``GUARD_LOOKAHEAD_S``), so it meets a fast joint early enough to brake it before the
spring's band, and a slow one as before. A stronger damper (0.016 s) caught the light hands
as well but made the nominal run's torques chatter (0.0068 N·m a tick at p99), so its
strength is the one the nominal was tuned with.

A light joint's spring may need a wider band than the guard's. The same spring through the
same lag is a faster ring on a lighter link: on a distal joint (6e-5 kg·m²) the 2 N·m/rad
spring rings at about 30 Hz, and on a hand whose joint damping is ×0.3 the contact that
bends the distal joint down into its lower band turns that ring into a growing one, which
ends at the soft limit (``SOFT_LIMIT``). A recipe may therefore give one side of a joint a
spring band of its own (``limit_guard_spring_bands``): the spring starts further from the
limit and still reaches ``tau_max`` at it, with a lower gain (``tau_max / spring band``).
The damper keeps the guard's band, and so does a paced ramp's ``limit_depth``: both were
measured with it, and the damper's reach is what keeps a joint off the limit.

The guard is a pure function of the measured angles (and the velocities filtered from them)
and the phase's torque, so a replay of the logged feedback computes the very same torques.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Literal

from handctl.arrays import FloatArray
from handctl.config import HandConfig

#: s, the damper against the spring (damping = gain * this): over a nominal run, half of it
#: leaves the joints' bounces off their bands, twice as much chatters through the drive's lag
GUARD_DAMPING_S = 0.008
#: s, how far ahead the damper looks: it meets a joint where the joint will be this much later
#: at its present speed. The drive's and the velocity's lag (up to 14 ms) plus the time the
#: damper needs to slow the joint, so that a joint flung at its limit on a lightly damped
#: hand is braked before the spring's band, not inside it
GUARD_LOOKAHEAD_S = 0.03
#: s, the span of the line the dampers' velocities are the slope of
#: (``velocity.FittedVelocity``): eight ticks at 1 kHz, where it lags by 3.5 ms, not the
#: recipe's low-pass's 10, and an encoder count moves it by 0.05 rad/s. Counted in ticks, it
#: lagged by 14 ms at 250 Hz, and the guard's damper came too late to hold the spring (a
#: distal joint's command rang at 20 Hz for seconds where at 500 Hz and up it held)
GUARD_VELOCITY_SPAN_S = 0.007
#: how deep into the spring's band (a fraction of it) the spring begins to take on what the
#: proposed torque asks towards the limit as well, all of it at the limit: there the push is
#: the guard's whole strength against the joint whatever the phase asks, where the spring
#: alone only cancelled a phase torque of ``tau_max`` and left the contact to push the joint
#: over (``ANGLE_LIMIT`` on a distal joint in the experiment's third turn, which asks that
#: joint's ``tau_max``). Half the band, so a joint that rests inside the band's first half,
#: as the lift's distal joints do, is pushed exactly as before; from none of it, the nominal
#: run moved
GUARD_DEEP_FRACTION = 0.5


def _deep_share(spring: float, most: float) -> float:
    """How much of the torque asked towards the limit the spring takes on where it pushes
    ``spring`` (N·m) of its ``most`` (N·m, at the limit), which is how deep into its band the
    joint is: none in the band's first ``GUARD_DEEP_FRACTION``, then growing to all of it at
    the limit."""
    if most <= 0.0:
        return 0.0
    depth = spring / most
    if depth <= GUARD_DEEP_FRACTION:
        return 0.0
    return min(1.0, (depth - GUARD_DEEP_FRACTION) / (1.0 - GUARD_DEEP_FRACTION))


def fitted_window(period_s: float) -> int:
    """The ticks of ``GUARD_VELOCITY_SPAN_S`` at a loop period of ``period_s`` (s): the
    line's span in time, whatever the rate (8 at 1 kHz, 3 at 250 Hz, 15 at 2 kHz)."""
    return max(2, round(GUARD_VELOCITY_SPAN_S / period_s) + 1)


#: the two sides of a joint's range a spring band may be given for
Side = Literal["lower", "upper"]
SIDES: tuple[Side, ...] = ("lower", "upper")


@dataclass(frozen=True)
class SpringBand:
    """One side of one joint whose spring acts over a band (rad) other than the guard's."""

    joint: str
    side: Side
    band: float  # rad


@dataclass(frozen=True)
class GuardSettings:
    """What a template or a recipe says of its guard: data, so that it travels to planner
    workers and back into the compiled recipe as it was written."""

    band: float  # rad, every joint's damper band, and its spring band unless given below
    springs: tuple[SpringBand, ...] = ()

    def guard(self, hand: HandConfig) -> LimitGuard:
        """The guard these settings describe for ``hand``."""
        return LimitGuard.for_hand(hand, self.band, springs=self.springs)

    def document(self) -> dict[str, Any]:
        """The recipe keys these settings are written as."""
        out: dict[str, Any] = {"limit_guard_band": self.band}
        if self.springs:
            bands: dict[str, dict[str, float]] = {}
            for s in self.springs:
                bands.setdefault(s.joint, {})[s.side] = s.band
            out["limit_guard_spring_bands"] = bands
        return out


@dataclass(frozen=True)
class LimitGuard:
    """The bands (rad) before each soft limit where the push-back acts, per joint."""

    band: float  # rad, the damper's band (and a paced ramp's ``limit_depth``'s)
    lower: tuple[float, ...]  # rad, where the band before the lower limit begins
    upper: tuple[float, ...]  # rad, where the band before the upper limit begins
    spring_lower: tuple[float, ...]  # rad, where the spring before the lower limit begins
    spring_upper: tuple[float, ...]  # rad, where the spring before the upper limit begins
    gain_lower: tuple[float, ...]  # N·m/rad, tau_max / the lower spring's band
    gain_upper: tuple[float, ...]  # N·m/rad, tau_max / the upper spring's band
    tau_max: tuple[float, ...]  # N·m
    damping: tuple[float, ...] = ()  # N·m·s/rad, at full strength inside the band; (): none
    lookahead: float = 0.0  # s, the damper acts on the angle this far ahead at the velocity

    @classmethod
    def for_hand(
        cls,
        hand: HandConfig,
        band: float,
        damping_s: float = GUARD_DAMPING_S,
        lookahead_s: float = GUARD_LOOKAHEAD_S,
        springs: Sequence[SpringBand] = (),
        push_max: float | None = None,
    ) -> LimitGuard:
        """The guard with ``band`` (rad) for every joint of ``hand``, from its soft limits,
        with a damping of ``damping_s`` (s) times the spring's gain, looking ``lookahead_s``
        (s) ahead; ``springs`` give a side of a joint a spring band of its own. Its spring
        reaches each joint's ``tau_max`` at the soft limit, or ``push_max`` (N·m) if that is
        less (and the damper is as much weaker), beyond what the proposed torque asks towards
        the limit (``GUARD_DEEP_FRACTION``)."""
        joints = hand.joints
        most = [j.tau_max if push_max is None else min(j.tau_max, push_max) for j in joints]
        own: Mapping[tuple[str, str], float] = {(s.joint, s.side): s.band for s in springs}
        names = {j.name for j in joints}
        for s in springs:
            if s.joint not in names:
                raise ValueError(f"spring band for {s.joint!r}, which is not a joint of the hand")
        lower_band = [own.get((j.name, "lower"), band) for j in joints]
        upper_band = [own.get((j.name, "upper"), band) for j in joints]
        return cls(
            band,
            tuple(j.angle_min + band for j in joints),
            tuple(j.angle_max - band for j in joints),
            tuple(j.angle_min + b for j, b in zip(joints, lower_band, strict=True)),
            tuple(j.angle_max - b for j, b in zip(joints, upper_band, strict=True)),
            tuple(t / b for t, b in zip(most, lower_band, strict=True)),
            tuple(t / b for t, b in zip(most, upper_band, strict=True)),
            tuple(most),
            # the damper's strength is the guard's band's spring's, whatever the spring band
            tuple(t / band * damping_s for t in most),
            lookahead_s,
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
        springs = zip(self.spring_lower, self.spring_upper, strict=True)
        for j, (q, lo, hi, (spring_lo, spring_hi)) in enumerate(
            zip(angle, self.lower, self.upper, springs, strict=True)
        ):
            push = 0.0
            if q > spring_hi:
                push = -self.gain_upper[j] * (q - spring_hi)
                push -= _deep_share(-push, self.tau_max[j]) * max(0.0, float(desired[j]))
            elif q < spring_lo:
                push = self.gain_lower[j] * (spring_lo - q)
                push += _deep_share(push, self.tau_max[j]) * max(0.0, -float(desired[j]))
            if damped:
                assert velocity is not None
                v = float(velocity[j])
                # the damper meets a joint heading for a limit a band before the spring does,
                # fading in over that band, and opposes only the motion towards the limit;
                # it judges where the joint will be ``lookahead`` later, so a fast joint is
                # met early enough for the brake to act through the lag
                ahead = q + v * self.lookahead
                if v > 0.0 and ahead > hi - band:
                    push -= self.damping[j] * min(1.0, (ahead - hi + band) / band) * v
                elif v < 0.0 and ahead < lo + band:
                    push -= self.damping[j] * min(1.0, (lo + band - ahead) / band) * v
            if push == 0.0:
                continue
            limit = self.tau_max[j]
            out[j] = max(-limit, min(limit, float(desired[j]) + push))
        return out
