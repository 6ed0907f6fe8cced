"""The fault campaign aims at the hand it runs on: its first, middle and last node by id, and
a joint each node has, not at node 3 of the default hand."""

from __future__ import annotations

import dataclasses

from handctl.config import HandConfig
from handctl.harness.campaign import CASES, Targets, run_case
from handctl.sim import faults as inj


def renumbered(hand: HandConfig, ids: tuple[int, ...]) -> HandConfig:
    return dataclasses.replace(
        hand,
        fingers=tuple(
            dataclasses.replace(f, node_id=n) for f, n in zip(hand.fingers, ids, strict=True)
        ),
    )


def test_targets_are_the_hands_first_middle_and_last_node(hand: HandConfig) -> None:
    assert Targets.of(hand) == Targets(1, 2, 3)
    other = renumbered(hand, (9, 4, 7))
    targets = Targets.of(other)
    assert targets == Targets(4, 7, 9)
    aimed = {name: make(other, targets) for name, make in CASES.items()}
    nodes = {getattr(i, "node", None) for i in aimed.values()} - {None}
    assert nodes == {4, 7, 9}
    offset = aimed["tdt_offset"]
    assert isinstance(offset, inj.TdtOffset) and (offset.node, offset.joint) == (9, 2)


def test_a_node_of_one_joint_is_aimed_at_that_joint(hand: HandConfig) -> None:
    last = hand.fingers[-1]
    short = dataclasses.replace(
        hand, fingers=(*hand.fingers[:-1], dataclasses.replace(last, joints=last.joints[:1]))
    )
    offset = CASES["tdt_offset"](short, Targets.of(short))
    assert isinstance(offset, inj.TdtOffset) and (offset.node, offset.joint) == (3, 1)


def test_a_case_runs_and_reads_the_wire_by_node(hand: HandConfig) -> None:
    """One case end to end: the command frames on the wire decoded per node into the hand's
    joint order, the silenced last node caught."""
    result = run_case(hand, "node_silent", "holding")
    assert result.fault != "" and result.unsafe_frames == 0 and result.frames > 0
