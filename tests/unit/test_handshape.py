"""The hand's shape read from its config: the palm's middle, the bases' spread and each
finger's flexion, for the default hand and for hands laid out otherwise."""

from __future__ import annotations

import dataclasses
import math

import pytest

from handctl.config import HandConfig
from handctl.handshape import flexion_sign, hand_span


def test_the_default_hand(hand: HandConfig) -> None:
    assert hand_span(hand) == pytest.approx((0.0, 0.05))
    # the two fingers on the left flex counter-clockwise, the one on the right clockwise
    assert [flexion_sign(hand, f) for f in hand.fingers] == [1.0, 1.0, -1.0]


def test_a_hand_moved_along_and_turned_upside_down(hand: HandConfig) -> None:
    """Bases shifted by 0.1 m and spread wider, fingers pointing up: the middle and span
    follow the bases, and every flexion sign turns over."""
    shifted = dataclasses.replace(
        hand,
        fingers=tuple(
            dataclasses.replace(f, base_x=0.1 + 2 * f.base_x, base_angle=math.pi / 2)
            for f in hand.fingers
        ),
    )
    assert hand_span(shifted) == pytest.approx((0.1, 0.1))
    assert [flexion_sign(shifted, f) for f in shifted.fingers] == [-1.0, -1.0, 1.0]
