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


def hand_span(hand: HandConfig) -> tuple[float, float]:
    """``(middle, half_span)`` (m, along the palm's x) of the stretch of palm the fingers
    enclose, where an object counts as in the hand.

    Between the outermost finger bases: fingers curl towards the bases' middle, so they hold
    what lies between them. A hand whose fingers are all based at one x (one finger, or two
    facing each other across the palm's thickness) has no such stretch; its fingers hold an
    object against the palm on the side a positive torque curls them to, as far as each one's
    straight length reaches. Without that, every object would have left such a hand before
    it moved.
    """
    lo, hi = _bases(hand)
    if hi - lo <= _SAME_X:
        for f in hand.fingers:
            # a counter-clockwise curl from straight moves the tip along -sin(angle) in x
            reach = -math.sin(f.base_angle) * sum(j.link_length for j in f.joints)
            lo, hi = min(lo, f.base_x + reach), max(hi, f.base_x + reach)
    return (lo + hi) / 2, (hi - lo) / 2


def flexion_sign(hand: HandConfig, finger: FingerConfig) -> float:
    """+1 when positive torque curls ``finger`` towards the middle of the finger bases (its
    tip swings towards it), -1 when negative torque does; +1 for a finger based at the
    middle."""
    lo, hi = _bases(hand)
    # z of (finger direction) x (base -> middle): positive when the middle lies
    # counter-clockwise of the finger
    towards = -math.sin(finger.base_angle) * ((lo + hi) / 2 - finger.base_x)
    return -1.0 if towards < 0 else 1.0


def _bases(hand: HandConfig) -> tuple[float, float]:
    """The outermost finger bases along the palm (m): the stretch both functions start from."""
    xs = [f.base_x for f in hand.fingers]
    return min(xs), max(xs)
