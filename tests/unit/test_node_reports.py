"""What one node's frames tell the host, frame by frame: the versions and times a Status
carries, and the exact words of a contradiction, which the operator reads in the fault.

The frames are encoded with the hand's own layouts and handed to ``FingerNode.receive`` one
by one, so each test says exactly what arrived and when.
"""

from __future__ import annotations

import pytest

from handctl.config import HandConfig
from handctl.online.drivers.finger import REORDERED_WITHIN_NS, FingerLayouts, FingerNode
from handctl.online.drivers.receiver import Reject
from handctl.protocol import Protocol

DISABLED, ENABLED, FAULT = 0, 1, 2
TIMEOUT, ESTOP = 0x01, 0x02


@pytest.fixture
def node(hand: HandConfig, protocol: Protocol) -> FingerNode:
    finger = hand.fingers[0]
    return FingerNode(finger, FingerLayouts.for_node(protocol, finger.node_id))


def _feedback(node: FingerNode, counter: int, state: int, bits: int) -> bytes:
    layout = node.layouts.feedback
    joints = (len(layout.signals) - 2) // 2
    return layout.encode(counter, [0.0] * (2 * joints) + [state, bits])


def _status(
    node: FingerNode,
    counter: int,
    state: int,
    bits: int,
    version: int,
    firmware: tuple[int, int, int],
) -> bytes:
    return node.layouts.status.encode(counter, (state, bits, 0, 0, 0, 7, version, *firmware))


def test_a_status_gives_the_versions_and_when_they_were_heard(node: FingerNode) -> None:
    assert node.firmware_text == "?" and "no Status" in node.version_problem()
    version = node.layouts.protocol_version
    data = _status(node, 0, DISABLED, 0, version, (4, 5, 6))
    assert node.receive(node.layouts.status.frame_id, data, 123_000) is None
    assert node.status_ns == 123_000 and node.version_ns == 123_000
    assert node.protocol_version == version
    assert node.firmware_version == (4, 5, 6) and node.firmware_text == "4.5.6"
    assert node.version_problem(since_ns=100_000) == ""
    assert node.version_problem(since_ns=123_000) == ""  # heard at that very time: current
    assert "no Status" in node.version_problem(since_ns=124_000)


def test_a_status_of_another_version_is_named(node: FingerNode) -> None:
    other = node.layouts.protocol_version + 1
    node.receive(node.layouts.status.frame_id, _status(node, 0, DISABLED, 0, other, (1, 0, 0)), 5)
    problem = node.version_problem()
    assert f"speaks handctl protocol {other}" in problem
    assert problem.endswith(
        f"this host protocol {node.layouts.protocol_version}: update the "
        "node's firmware or use the handctl of its protocol"
    )


def test_a_contradiction_names_the_frame_the_state_and_every_latched_bit(node: FingerNode) -> None:
    node.receive(node.layouts.feedback.frame_id, _feedback(node, 0, ENABLED, TIMEOUT | ESTOP), 1)
    assert node.contradiction == ("Feedback says ENABLED with latched fault bits (TIMEOUT, ESTOP)")
    assert node.contradictions == 1
    version = node.layouts.protocol_version
    node.receive(node.layouts.status.frame_id, _status(node, 0, 7, TIMEOUT, version, (1, 0, 0)), 2)
    assert node.contradictions == 2
    assert node.contradiction.startswith("Feedback")  # the first one is kept


def test_a_state_the_protocol_does_not_know_is_named_by_its_number(node: FingerNode) -> None:
    version = node.layouts.protocol_version
    node.receive(node.layouts.status.frame_id, _status(node, 0, 7, TIMEOUT, version, (1, 0, 0)), 2)
    assert node.contradiction == (
        "Status says state 7, which the protocol does not define (fault bits 0x01)"
    )
    assert node.state == -1  # never the node's state: still unknown


def _heartbeat(node: FingerNode, counter: int, state: int) -> bytes:
    return node.layouts.heartbeat.encode(counter, (state, 1000 + counter))


def test_enabled_after_disabled_needs_an_enable_from_this_host(node: FingerNode) -> None:
    """One DISABLED report in the same poll as the next ENABLED was overruled by it: a node
    that dropped its torque, or a forged Heartbeat, went unseen and the run ended exit 0."""
    fb, hb = node.layouts.feedback.frame_id, node.layouts.heartbeat.frame_id
    node.receive(fb, _feedback(node, 0, DISABLED, 0), 1)
    node.next_node_command("enable")
    # the node's Heartbeat sent before the enable may arrive after its Feedback sent after it
    node.receive(fb, _feedback(node, 1, ENABLED, 0), 2)
    node.receive(hb, _heartbeat(node, 0, DISABLED), 3)
    node.receive(fb, _feedback(node, 2, ENABLED, 0), 4)
    node.receive(hb, _heartbeat(node, 1, ENABLED), 5)
    assert node.contradiction == "" and node.state == ENABLED
    # every stream has said ENABLED since the enable: a DISABLED now is the node's present
    node.receive(hb, _heartbeat(node, 2, DISABLED), 6)
    node.receive(fb, _feedback(node, 3, ENABLED, 0), 7)
    assert node.contradiction == (
        "Feedback says ENABLED after DISABLED without an enable from this host"
    )
    assert node.state == DISABLED  # what the DISABLED report said stands
    node.next_node_command("enable")  # enabled again by this host: no contradiction more
    node.receive(fb, _feedback(node, 4, ENABLED, 0), 8)
    assert node.contradictions == 1 and node.state == ENABLED


def test_a_disabled_long_after_the_node_said_enabled_is_no_older_report(node: FingerNode) -> None:
    """A node that never took the enable (its Feedback says DISABLED on every tick) beside a
    Heartbeat saying ENABLED (a forgery, or firmware that reports the state asked for) was
    taken for ENABLED for a whole run: each Feedback DISABLED counted as sent before the
    enable, for as long as the Feedback stream had not said ENABLED. Frames a node queues
    together leave within its 1 ms tick, so later than that it is the node's present."""
    fb, hb = node.layouts.feedback.frame_id, node.layouts.heartbeat.frame_id
    node.receive(fb, _feedback(node, 0, DISABLED, 0), 0)
    node.next_node_command("enable")
    node.receive(hb, _heartbeat(node, 0, ENABLED), 10_000_000)
    node.receive(fb, _feedback(node, 1, DISABLED, 0), 10_000_000 + REORDERED_WITHIN_NS)
    node.receive(hb, _heartbeat(node, 1, ENABLED), 10_000_000 + REORDERED_WITHIN_NS)
    assert node.contradiction == ""  # within the tick: may be older than the enable
    assert not node.feedback_enabled  # and the torque is not armed on it (the supervisor)
    node.receive(fb, _feedback(node, 2, DISABLED, 0), 10_000_001 + REORDERED_WITHIN_NS)
    node.receive(hb, _heartbeat(node, 2, ENABLED), 10_000_002 + REORDERED_WITHIN_NS)
    assert node.contradiction == (
        "Heartbeat says ENABLED after DISABLED without an enable from this host"
    )
    assert node.state == DISABLED


def test_one_counter_with_two_contents_is_a_second_sender(node: FingerNode) -> None:
    """A forged Feedback a counter ahead of the node is accepted, and the node's own frame
    with that counter is rejected as a repeat: counted as one lost frame, a forgery one
    frame in ten was believed under the reject-rate limit for a whole run. The same frame
    heard twice is a repeat and nothing more."""
    fb = node.layouts.feedback.frame_id
    node.receive(fb, _feedback(node, 0, ENABLED, 0), 1)
    node.receive(fb, _feedback(node, 0, ENABLED, 0), 2)
    assert node.contradiction == "" and node.rejects.total == 1
    layout = node.layouts.feedback
    joints = (len(layout.signals) - 2) // 2
    forged = layout.encode(1, [0.0] * joints + [1.8] + [0.0] * (joints - 1) + [ENABLED, 0])
    assert node.receive(fb, forged, 3) is None
    node.receive(fb, _feedback(node, 1, ENABLED, 0), 4)
    assert node.contradiction == (
        f"two Feedback frames (id 0x{fb:03X}) with counter 1 and other contents: a second "
        "sender on this node's identifier (a forged frame, or two nodes set to one id), or a "
        "node whose counter does not advance"
    )


def test_a_counter_come_round_again_after_lost_frames_is_no_second_sender(
    node: FingerNode,
) -> None:
    """A host starved in its start-up loses frames (its receive queue full): after exactly
    255 lost, the next frame has the counter of the last it took, and other contents. That
    was taken for a second sender, and a run on a loaded machine stopped on it (CI); it
    comes 256 ms after, where a forged frame and the node's own come within a tick."""
    fb = node.layouts.feedback.frame_id
    node.receive(fb, _feedback(node, 7, ENABLED, 0), 1_000_000)
    later = 1_000_000 + 256 * 1_000_000
    assert node.receive(fb, _feedback(node, 7, DISABLED, 0), later) is Reject.COUNTER_REPEAT
    assert node.contradiction == "" and node.contradictions == 0
    node.receive(fb, _feedback(node, 8, ENABLED, 0), later + 1_000_000)  # in step again
    node.receive(fb, _feedback(node, 8, DISABLED, 0), later + 1_500_000)  # within the tick
    assert node.contradiction.startswith("two Feedback frames")


def test_a_listener_hears_another_host_enable_the_node(node: FingerNode) -> None:
    """``nodes`` and ``monitor`` send nothing: an enable they did not send is no
    contradiction."""
    fb = node.layouts.feedback.frame_id
    node.receive(fb, _feedback(node, 0, DISABLED, 0), 1)
    node.receive(fb, _feedback(node, 1, ENABLED, 0), 2)
    assert node.contradiction == "" and node.state == ENABLED


def test_an_enabled_sent_before_the_fault_may_arrive_after_it(node: FingerNode) -> None:
    """A node enabled and e-stopped in one of its ticks: the Status ENABLED it queued goes out
    after the Feedback FAULT, whose identifier wins the bus. That older ENABLED was taken for
    a contradiction, and the stop said NODE_CONTRADICTION instead of the e-stop. Once the
    Status stream itself has said FAULT, an ENABLED of it is the node's present again."""
    fb, st = node.layouts.feedback.frame_id, node.layouts.status.frame_id
    version = node.layouts.protocol_version
    node.receive(fb, _feedback(node, 0, DISABLED, 0), 1)
    node.next_node_command("enable")
    node.receive(fb, _feedback(node, 1, FAULT, ESTOP), 2)
    node.receive(st, _status(node, 0, ENABLED, 0, version, (1, 0, 0)), 3)
    assert node.contradiction == ""
    assert node.state == FAULT and node.fault_bits == ESTOP  # the FAULT report stands
    node.receive(st, _status(node, 1, FAULT, ESTOP, version, (1, 0, 0)), 4)
    node.receive(st, _status(node, 2, ENABLED, 0, version, (1, 0, 0)), 5)
    assert node.contradiction == "Status says ENABLED after FAULT without a fault reset"
    assert node.state == FAULT and node.fault_bits == ESTOP
    # the Feedback stream said FAULT first: an ENABLED of its own after it is no older report
    node.receive(fb, _feedback(node, 2, ENABLED, 0), 6)
    assert node.contradictions == 2


def test_an_enabled_long_after_the_fault_is_no_older_report(node: FingerNode) -> None:
    """Frames a node queues together leave within its 1 ms tick: a stream that says ENABLED
    later than that, never having said FAULT, contradicts the FAULT (a forged Heartbeat
    hiding it), whatever it said before."""
    fb, hb = node.layouts.feedback.frame_id, node.layouts.heartbeat.frame_id
    node.receive(fb, _feedback(node, 0, DISABLED, 0), 0)
    node.next_node_command("enable")
    node.receive(fb, _feedback(node, 1, FAULT, TIMEOUT), 10_000_000)
    node.receive(hb, _heartbeat(node, 0, ENABLED), 10_000_000 + REORDERED_WITHIN_NS)
    assert node.contradiction == ""
    node.receive(hb, _heartbeat(node, 1, ENABLED), 10_000_001 + REORDERED_WITHIN_NS)
    assert node.contradiction == "Heartbeat says ENABLED after FAULT without a fault reset"
    assert node.state == FAULT and node.fault_bits == TIMEOUT
