"""Bringing one joint back inside its soft limits: the only way torque may flow with a joint
outside them.

Why it exists: a RAMP stop takes up to ``RAMP_BOUND_S`` to reach zero torque, and a finger that
tripped ``ANGLE_LIMIT`` at speed coasts on past its soft limit, often to its mechanical stop.
It then rests outside, and the supervisor's soft-limit check trips again as soon as any run
arms: nothing in the software could move it back, only hands on the hardware.

A recovery is asked for one joint and one direction, before the run starts (``handctl jog
JOINT --torque X --recover``; never from a recipe file, which must not loosen a limit). While
that joint is outside its soft limits the supervisor checks it against a tighter rule instead:

- it must be outside on the side the direction leads *back* from (a torque that would push it
  further out is refused at arming, as ``ANGLE_LIMIT``);
- it may never get further out than ``RECOVERY_SLACK`` beyond the farthest-in angle it has
  reached so far: a ratchet that follows the joint in and never out, so the worst it can do is
  sit where it began (encoder noise and the joint settling as torque comes on fit in the
  slack);
- once inside the soft limits the recovery is over for the rest of the run, and the normal
  check applies, so a joint that recovered and then went out again trips as any other.

Every other joint is checked as always, but one that already rests outside its soft limits
when torque is first allowed (a hand left at zero torque sags: its fingers' distal joints
sink past their limits together, and each joint's recovery was refused for the others): such
a joint is held to the same ratchet from where it rests, with no torque asked of it, so that
the joints can be brought back one at a time. The torque still passes the limiter
(``tau_max`` and the rate limit): a recovery loosens the angle check of the joints already
out, for as long as they do not go further out, once.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from handctl.online.safety.limits import JointLimits

#: rad: how far a recovering joint may go back out beyond the farthest-in angle it has reached
#: (encoder counts, a joint resting on its stop that settles as the torque comes on)
RECOVERY_SLACK = 0.02


def _ratchet(bound: float, q: float, below: bool) -> float | None:
    """The ratchet of a joint outside its limits (``below`` its lower one, else above its
    upper one), at ``q``: its bound moved in to follow it, or None if it went further out
    than ``bound``."""
    if below:
        return None if q < bound else max(bound, q - RECOVERY_SLACK)
    return None if q > bound else min(bound, q + RECOVERY_SLACK)


@dataclass
class Recovery:
    """One joint, one direction (+1: it is below its lower limit and is pushed up; −1: above
    its upper limit and pushed down). ``arm`` at the first armed tick, then ``check`` each."""

    joint: int
    direction: int
    #: rad, the angle when torque was first allowed (None before arming)
    start_angle: float | None = None
    #: the tick at which the joint was back inside its soft limits (−1: not yet)
    back_tick: int = -1
    #: rad, the farthest out it may be now (the ratchet); meaningful while active
    bound: float = 0.0
    #: whether the joint was outside its limits at arming (False: there was nothing to recover)
    needed: bool = False
    #: the other joints resting outside their limits at arming: joint -> the farthest out it
    #: may be (the ratchet, from where it rested); a joint leaves once it is back inside
    resting: dict[int, float] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.direction not in (1, -1):
            raise ValueError(f"a recovery direction is +1 or -1, found {self.direction!r}")

    @property
    def active(self) -> bool:
        """Whether the joint's angle check is still the recovery's."""
        return self.needed and self.back_tick < 0

    def arm(self, q: float, limits: JointLimits) -> str | None:
        """At the first armed tick: the reason to refuse, or None. A joint already inside its
        limits needs no recovery and is checked as usual from now on."""
        self.start_angle = q
        j = self.joint
        lo, hi, name = limits.angle_min_list[j], limits.angle_max_list[j], limits.names[j]
        if lo <= q <= hi:
            self.needed = False
            return None
        below = q < lo
        if below != (self.direction > 0):
            side, limit = ("below its lower", lo) if below else ("above its upper", hi)
            wanted = "a positive" if below else "a negative"
            return (
                f"{name} at {q:+.3f} rad, {side} limit {limit:+.3f} rad: its recovery must "
                f"push it back in ({wanted} torque), and the one asked for pushes it further out"
            )
        self.needed = True
        self.bound = q - RECOVERY_SLACK if below else q + RECOVERY_SLACK
        return None

    def rest(self, angles: list[float], limits: JointLimits) -> None:
        """At the first armed tick, after ``arm``: the other joints resting outside."""
        for k, q in enumerate(angles):
            if k == self.joint:
                continue
            if not limits.angle_min_list[k] <= q <= limits.angle_max_list[k]:
                # its ratchet as it starts: where it rests, with the slack to spare
                self.resting[k] = q + RECOVERY_SLACK * (-1 if q < limits.angle_min_list[k] else 1)

    def check_resting(self, k: int, q: float, limits: JointLimits) -> str | None:
        """A resting joint ``k`` at ``q``: None while it keeps within its ratchet (it leaves
        the resting ones once back inside its limits)."""
        lo, hi = limits.angle_min_list[k], limits.angle_max_list[k]
        bound = self.resting[k]
        if lo <= q <= hi:
            del self.resting[k]
            return None
        moved = _ratchet(bound, q, below=bound < lo)
        if moved is None:
            at, rested = _apart(q, bound)
            return (
                f"{limits.names[k]} at {at} rad, resting outside its limits "
                f"[{lo:+.3f}, {hi:+.3f}] while {limits.names[self.joint]} is recovered, and "
                f"further out than it rested ({rested} rad with {RECOVERY_SLACK:g} rad to "
                "spare)"
            )
        self.resting[k] = moved
        return None

    def check(self, q: float, tick: int, limits: JointLimits) -> str | None:
        """While active: the ratchet; None while the joint keeps within it."""
        j = self.joint
        lo, hi = limits.angle_min_list[j], limits.angle_max_list[j]
        if lo <= q <= hi:
            self.back_tick = tick
            return None
        # +1: below the lower limit, coming up
        moved = _ratchet(self.bound, q, below=self.direction > 0)
        if moved is None:
            return self._out(q, limits)
        self.bound = moved
        return None

    def _out(self, q: float, limits: JointLimits) -> str:
        j = self.joint
        at, bound = _apart(q, self.bound)
        return (
            f"{limits.names[j]} at {at} rad, further out than its recovery allows "
            f"({bound} rad, {RECOVERY_SLACK:g} rad beyond the farthest in it came; "
            f"limits [{limits.angle_min_list[j]:+.3f}, {limits.angle_max_list[j]:+.3f}])"
        )


def _apart(angle: float, bound: float) -> tuple[str, str]:
    """``angle`` and the ``bound`` it went past (rad), signed, with the fewest decimals from
    3 on (to 9) that tell them apart: at 3 a joint a fraction of a milliradian past its
    bound read "at -0.968 rad ... (-0.968 rad ...)", as if it had not gone past it (found by
    an outside audit)."""
    for decimals in range(3, 10):
        said = f"{angle:+.{decimals}f}", f"{bound:+.{decimals}f}"
        if said[0] != said[1]:
            break
    return said
