"""What the hand's shape implies, derived from its config alone, for code that must not
assume one hand: where the palm's middle is, how far the fingers' bases spread, and which way
each finger flexes.

The hand is planar, fingers based along the palm's face (x) and hanging from it; joint angles
and torques are counter-clockwise positive about +z (``handctl.convention``).
"""

from __future__ import annotations

import math

from handctl.config import FingerConfig, HandConfig


def hand_span(hand: HandConfig) -> tuple[float, float]:
    """``(middle, half_span)`` (m, along the palm's x): the palm's middle between the
    outermost finger bases, and how far from it the farthest base is."""
    xs = [f.base_x for f in hand.fingers]
    middle = (min(xs) + max(xs)) / 2
    return middle, max(abs(x - middle) for x in xs)


def flexion_sign(hand: HandConfig, finger: FingerConfig) -> float:
    """+1 when positive torque curls ``finger`` towards the palm's middle (its tip swings
    towards it), -1 when negative torque does; +1 for a finger based at the middle."""
    middle, _ = hand_span(hand)
    # z of (finger direction) x (base -> middle): positive when the middle lies
    # counter-clockwise of the finger
    towards = -math.sin(finger.base_angle) * (middle - finger.base_x)
    return -1.0 if towards < 0 else 1.0
