"""The hand's shape read from its config: the palm's middle, the bases' spread and each
finger's flexion, for the default hand and for hands laid out otherwise."""

from __future__ import annotations

import dataclasses
import math

import pytest

from handctl.config import FingerConfig, HandConfig
from handctl.handshape import flexion_sign, hand_span


def test_the_default_hand(hand: HandConfig) -> None:
    assert hand_span(hand) == pytest.approx((0.0, 0.05))
    # the two fingers on the left flex counter-clockwise, the one on the right clockwise
    assert [flexion_sign(hand, f) for f in hand.fingers] == [1.0, 1.0, -1.0]


def _mirrored_joints(finger: FingerConfig) -> FingerConfig:
    """``finger`` built the other way round: what its joints reached at positive angles they
    reach at negative ones."""
    return dataclasses.replace(
        finger,
        joints=tuple(
            dataclasses.replace(j, angle_min=-j.angle_max, angle_max=-j.angle_min)
            for j in finger.joints
        ),
    )


def test_a_hand_moved_along_and_turned_upside_down(hand: HandConfig) -> None:
    """Bases shifted by 0.1 m and spread wider, fingers pointing up, each built mirrored so
    that it still curls towards the others: the middle and span follow the bases, and every
    flexion sign turns over."""
    shifted = dataclasses.replace(
        hand,
        fingers=tuple(
            _mirrored_joints(
                dataclasses.replace(f, base_x=0.1 + 2 * f.base_x, base_angle=math.pi / 2)
            )
            for f in hand.fingers
        ),
    )
    assert hand_span(shifted) == pytest.approx((0.1, 0.1))
    assert [flexion_sign(shifted, f) for f in shifted.fingers] == [-1.0, -1.0, 1.0]


def test_like_fingers_on_one_side_flex_alike_and_enclose_as_far_as_they_reach(
    hand: HandConfig,
) -> None:
    """Two fingers built like f1, based 20 mm apart on one side: the one right of their
    bases' middle was taken to flex the other way (a fault campaign drove it into
    extension), and the hand held a half-span of 10 mm, so an object under the palm a
    little way out had "left the hand" (found by an outside audit)."""
    f1 = hand.fingers[0]
    side = dataclasses.replace(
        hand,
        fingers=(f1, dataclasses.replace(f1, name="f1b", node_id=2, base_x=f1.base_x + 0.02)),
    )
    assert [flexion_sign(side, f) for f in side.fingers] == [1.0, 1.0]
    length = sum(j.link_length for j in f1.joints)
    middle, half = hand_span(side)
    assert (middle - half, middle + half) == pytest.approx((f1.base_x, f1.base_x + 0.02 + length))


def test_a_finger_of_near_symmetric_ranges_curls_towards_the_others(hand: HandConfig) -> None:
    """Ranges that say nothing of a flexion (each joint's symmetric): the finger is taken to
    curl towards the middle of the bases, as before."""
    symmetric = dataclasses.replace(
        hand,
        fingers=tuple(
            dataclasses.replace(
                f,
                joints=tuple(
                    dataclasses.replace(j, angle_min=-1.5, angle_max=1.5) for j in f.joints
                ),
            )
            for f in hand.fingers
        ),
    )
    assert [flexion_sign(symmetric, f) for f in symmetric.fingers] == [1.0, 1.0, -1.0]


def _one_sided(hand: HandConfig, count: int) -> HandConfig:
    """The default hand's first ``count`` fingers, every one based where f1 is."""
    first = hand.fingers[0]
    return dataclasses.replace(
        hand,
        fingers=tuple(
            dataclasses.replace(f, base_x=first.base_x, base_angle=first.base_angle)
            for f in hand.fingers[:count]
        ),
    )


@pytest.mark.parametrize("count", [1, 2])
def test_fingers_based_at_one_x_enclose_as_far_as_they_reach(hand: HandConfig, count: int) -> None:
    """With no base across from them, the fingers hold against the palm out to their
    straight length on the side they curl towards (+x for a finger hanging down that flexes
    counter-clockwise); the stretch of bases alone is a point, and everything would be out."""
    one = _one_sided(hand, count)
    base = one.fingers[0].base_x
    length = sum(j.link_length for j in one.fingers[0].joints)
    middle, half = hand_span(one)
    assert (middle - half, middle + half) == pytest.approx((base, base + length))
    assert [flexion_sign(one, f) for f in one.fingers] == [1.0] * count


def test_bases_close_together_still_bound_the_hand_by_themselves(hand: HandConfig) -> None:
    """f3 moved to -0.03 m: the bases span 2 cm, and that is the stretch, however far the
    fingers reach; only bases at one x enclose by reach."""
    f1, f2, f3 = hand.fingers
    near = dataclasses.replace(hand, fingers=(f1, f2, dataclasses.replace(f3, base_x=-0.03)))
    assert hand_span(near) == pytest.approx((-0.04, 0.01))


@pytest.mark.parametrize("count", [1, 2])
def test_fingers_based_at_one_x_that_flex_the_other_way_enclose_on_the_other_side(
    hand: HandConfig, count: int
) -> None:
    """The mirror image of the hand above: joint ranges reaching further to negative angles
    (a finger that flexes with negative torque). Its side was taken as a positive torque's,
    so an object held still against the palm was judged out of the hand."""
    one = _one_sided(hand, count)
    mirrored = dataclasses.replace(one, fingers=tuple(_mirrored_joints(f) for f in one.fingers))
    base = one.fingers[0].base_x
    length = sum(j.link_length for j in one.fingers[0].joints)
    middle, half = hand_span(mirrored)
    assert (middle - half, middle + half) == pytest.approx((base - length, base))
    assert [flexion_sign(mirrored, f) for f in mirrored.fingers] == [-1.0] * count
