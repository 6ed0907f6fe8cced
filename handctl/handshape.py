"""What the hand's shape implies, derived from its config alone, for code that must not
assume one hand: where the palm's middle is, how much of it the fingers enclose, and which way
each finger flexes.

The hand is planar, fingers based along the palm's face (x) and hanging from it; joint angles
and torques are counter-clockwise positive about +z (``handctl.convention``).
"""

from __future__ import annotations

import math

from handctl.config import FingerConfig, HandConfig

# m: finger bases nearer each other along the palm than this are at one x
_SAME_X = 1e-6
# rad: a finger whose joint ranges, summed, reach no further one way than the other by more
# than this has no flexion of its own to read from them
_SYMMETRIC_RAD = 0.1


def hand_span(hand: HandConfig) -> tuple[float, float]:
    """``(middle, half_span)`` (m, along the palm's x) of the stretch of palm the fingers
    enclose, where an object counts as in the hand.

    Between the outermost finger bases, where fingers curl towards each other from both
    sides: they hold what lies between them. A hand whose fingers are all based at one x (one
    finger, or two facing each other across the palm's thickness), or all curl to one side
    (a hand of fingers on one side of the palm), has no such stretch, or not all of it; its
    fingers hold an object against the palm on the side they curl to, as far as each one's
    straight length reaches, so the stretch reaches that far too. Without that, every
    object would have left such a hand before it moved (two fingers on one side, 20 mm
    apart, held a half-span of 10 mm: found by an outside audit). The side is the one the
    finger flexes to (``flexion_sign``): taken as a positive torque's whatever the finger,
    one that flexes with negative torque held its object on the other side, and a mirrored
    hand's object "left the hand" sitting still.
    """
    lo, hi = _bases(hand)
    reaches = []
    for f in hand.fingers:
        # a counter-clockwise curl from straight moves the tip along -sin(angle) in x
        length = sum(j.link_length for j in f.joints)
        reaches.append((f.base_x, -flexion_sign(hand, f) * math.sin(f.base_angle) * length))
    one_side = all(r > 0 for _, r in reaches) or all(r < 0 for _, r in reaches)
    if hi - lo <= _SAME_X or one_side:
        for base_x, reach in reaches:
            lo, hi = min(lo, base_x + reach), max(hi, base_x + reach)
    return (lo + hi) / 2, (hi - lo) / 2


def palm_ends(hand: HandConfig) -> tuple[tuple[float, float], tuple[float, float]]:
    """The two finger bases farthest apart (x, y, m), the one of the smaller x first: the
    palm's line runs from the first to the second.

    Why it is here: the object estimator lays its seeds along this line in the recipe's
    order, and its continuity keeps those names, so a recipe's objects must be listed in
    their order along it, and whoever checks that needs the same line."""
    bases = [(f.base_x, f.base_y) for f in hand.fingers]
    first, last = max(
        ((a, b) for a in bases for b in bases), key=lambda ab: math.dist(ab[0], ab[1])
    )
    if first[0] > last[0]:
        first, last = last, first
    return first, last


def order_along_palm(hand: HandConfig, positions: dict[str, tuple[float, float]]) -> list[str]:
    """The names of ``positions`` (m, x and y) in their order along the palm's line
    (``palm_ends``; along x for a hand whose fingers are all based at one point)."""
    first, last = palm_ends(hand)
    ux, uy = (last[0] - first[0], last[1] - first[1]) if first != last else (1.0, 0.0)
    return sorted(positions, key=lambda name: positions[name][0] * ux + positions[name][1] * uy)


def flexion_sign(hand: HandConfig, finger: FingerConfig) -> float:
    """+1 when positive torque flexes ``finger`` (curls it, its tip swinging towards the
    palm's side it holds things on), -1 when negative torque does.

    A finger's own joint ranges say it first: a finger flexes further than it extends, so
    the way its ranges reach further, summed over the finger, is its flexion (every shipped
    hand's fingers, by 0.5 to 4.2 rad). Only a finger whose ranges are near symmetric
    (within ``_SYMMETRIC_RAD``) is taken to curl towards the middle of the finger bases; and
    one based at that middle, with no side to curl to, +1. Why the ranges first: two like
    fingers on one side of the palm, one each side of their bases' middle, were taken to
    flex opposite ways (found by an outside audit), and a fault campaign drove one of them
    into extension; the bases' middle says nothing of a finger's construction."""
    reach = sum(j.angle_max + j.angle_min for j in finger.joints)
    if abs(reach) > _SYMMETRIC_RAD:
        return 1.0 if reach > 0 else -1.0
    lo, hi = _bases(hand)
    # z of (finger direction) x (base -> middle): positive when the middle lies
    # counter-clockwise of the finger
    offset = (lo + hi) / 2 - finger.base_x
    towards = -math.sin(finger.base_angle) * offset
    return -1.0 if towards < 0 else 1.0


def _bases(hand: HandConfig) -> tuple[float, float]:
    """The outermost finger bases along the palm (m): the stretch both functions start from."""
    xs = [f.base_x for f in hand.fingers]
    return min(xs), max(xs)
