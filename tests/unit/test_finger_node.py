"""The host's view of one finger node, fed frames encoded with the DBC's layouts.

What a frame says reaches ``FingerNode`` only if it passes every receive check, and then each
field lands where the watchdogs read it: state, fault bits, the host time of the last feedback
and heartbeat, and the reboot count that ``NodeWatch`` compares.
"""

from __future__ import annotations

import pytest

from handctl.config import HandConfig
from handctl.online.drivers.finger import (
    FAULT_BITS,
    Feedback,
    FingerLayouts,
    FingerNode,
    fault_names,
    make_command,
    make_node_command,
    parse_feedback,
)
from handctl.online.drivers.receiver import Reject
from handctl.protocol import NODE_COMMANDS, NodeState, Protocol, node_state_name

MS = 1_000_000


class Sender:
    """A node's side of its three message streams: rolling counters kept per message."""

    def __init__(self, protocol: Protocol, node_id: int) -> None:
        self.layouts = FingerLayouts.for_node(protocol, node_id)
        self.version = protocol.version
        self.counters = {"feedback": 0, "status": 0, "heartbeat": 0}

    def frame(
        self, kind: str, values: tuple[float, ...], counter: int | None = None
    ) -> tuple[int, bytes]:
        layout = getattr(self.layouts, kind)
        if counter is None:
            counter = self.counters[kind]
            self.counters[kind] = (counter + 1) & 0xFF
        return layout.frame_id, layout.encode(counter, values)

    def feedback(
        self,
        tdt: tuple[float, float, float] = (0.0, 0.0, 0.0),
        angles: tuple[float, float, float] = (0.0, 0.0, 0.0),
        state: int = 1,
        faults: int = 0,
    ) -> tuple[int, bytes]:
        return self.frame("feedback", (*tdt, *angles, state, faults))

    def heartbeat(
        self, state: int, uptime_ms: int, counter: int | None = None
    ) -> tuple[int, bytes]:
        return self.frame("heartbeat", (state, uptime_ms), counter)

    def status(
        self,
        state: int,
        faults: int,
        rejects: tuple[int, int, int] = (0, 0, 0),
        age_ms: int = 0,
        firmware: tuple[int, int, int] = (1, 0, 0),
    ) -> tuple[int, bytes]:
        """A Status of the host's own protocol version (and firmware ``firmware``)."""
        return self.frame("status", (state, faults, *rejects, age_ms, self.version, *firmware))


@pytest.fixture(params=[0, 2], ids=["f1", "f3"])
def finger(request: pytest.FixtureRequest) -> int:
    return int(request.param)


@pytest.fixture
def node(hand: HandConfig, protocol: Protocol, finger: int) -> FingerNode:
    config = hand.fingers[finger]
    return FingerNode(config, FingerLayouts.for_node(protocol, config.node_id))


@pytest.fixture
def sender(hand: HandConfig, protocol: Protocol, finger: int) -> Sender:
    return Sender(protocol, hand.fingers[finger].node_id)


def test_the_layouts_are_the_configured_ids(hand: HandConfig, protocol: Protocol) -> None:
    for finger in hand.fingers:
        layouts = FingerLayouts.for_node(protocol, finger.node_id)
        ids = finger.can_ids
        assert (
            layouts.command.frame_id,
            layouts.node_command.frame_id,
            layouts.feedback.frame_id,
            layouts.status.frame_id,
            layouts.heartbeat.frame_id,
        ) == (ids.torque_command, ids.node_command, ids.feedback, ids.status, ids.heartbeat)


def test_a_node_says_nothing_until_it_is_heard(
    node: FingerNode, hand: HandConfig, finger: int
) -> None:
    assert node.node_id == hand.fingers[finger].node_id
    assert node.finger is hand.fingers[finger]
    assert (node.state, node.state_name, node.fault_bits) == (-1, "UNKNOWN", 0)
    assert (node.feedback, node.feedback_ns, node.heartbeat_ns) == (None, None, None)
    assert (node.uptime_ms, node.reboots, node.status, node.accepted) == (None, 0, None, 0)
    assert node.rejects.total == 0
    assert set(node.streams) == {
        node.layouts.feedback.frame_id,
        node.layouts.status.frame_id,
        node.layouts.heartbeat.frame_id,
    }


def test_feedback_lands_with_the_time_it_was_received(node: FingerNode, sender: Sender) -> None:
    assert (
        node.receive(*sender.feedback((0.1, -0.2, 0.3), (0.4, -0.5, 0.6), 1, 0x10), 7 * MS) is None
    )
    assert node.feedback == Feedback((0.1, -0.2, 0.3), (0.4, -0.5, 0.6), 1, 0x10)
    assert (node.feedback_ns, node.state, node.fault_bits, node.accepted) == (7 * MS, 1, 0x10, 1)
    assert node.heartbeat_ns is None  # feedback is not a heartbeat
    assert node.receive(*sender.feedback(state=2, faults=0x02), 8 * MS) is None
    assert (node.feedback_ns, node.state_name, node.fault_bits, node.accepted) == (
        8 * MS,
        "FAULT",
        0x02,
        2,
    )


def test_a_heartbeat_sets_state_uptime_and_its_time(node: FingerNode, sender: Sender) -> None:
    assert node.receive(*sender.heartbeat(0, 1234), 3 * MS) is None
    assert (node.state_name, node.uptime_ms, node.heartbeat_ns) == ("DISABLED", 1234, 3 * MS)
    assert node.feedback_ns is None and node.feedback is None  # a heartbeat is not feedback
    assert node.accepted == 1


def test_a_status_sets_state_and_fault_bits(node: FingerNode, sender: Sender) -> None:
    assert node.receive(*sender.status(2, 0x0A, (1, 2, 3), 11), 5 * MS) is None
    assert node.status == (2, 0x0A, 1, 2, 3, 11, sender.version, 1, 0, 0)
    assert (node.state, node.fault_bits) == (2, 0x0A)
    assert (node.feedback_ns, node.heartbeat_ns) == (None, None)
    assert node.receive(*sender.status(0, 0), 6 * MS) is None
    assert (node.state_name, node.fault_bits) == ("DISABLED", 0)


def test_every_reboot_is_counted(node: FingerNode, sender: Sender) -> None:
    """The uptime going back is a reboot, each time; the same uptime again is not."""

    def heartbeat(uptime: int, counter: int | None = None) -> Reject | None:
        return node.receive(*sender.heartbeat(1, uptime, counter), uptime * MS)

    assert heartbeat(5000) is None
    assert heartbeat(5100) is None
    assert heartbeat(5100) is None  # a repeated uptime (next counter) is no reboot
    assert node.reboots == 0
    # The rebooted node starts its counters at 0: the first frame is a skip, never applied.
    assert heartbeat(0, counter=0) is Reject.COUNTER_SKIP
    assert (node.reboots, node.uptime_ms) == (0, 5100)
    sender.counters["heartbeat"] = 1
    assert heartbeat(100) is None
    assert node.reboots == 1
    assert heartbeat(200) is None
    assert heartbeat(300) is None
    assert node.reboots == 1
    assert heartbeat(0, counter=0) is Reject.COUNTER_SKIP
    sender.counters["heartbeat"] = 1
    assert heartbeat(100) is None
    assert node.reboots == 2
    assert node.uptime_ms == 100


def test_an_uptime_that_wraps_is_no_reboot(node: FingerNode, sender: Sender) -> None:
    """The uptime is a uint32 of ms: 49.7 days after boot it wraps to 0, and a run then
    stopped on NODE_REBOOT (found by an outside audit). A drop that the host's clock
    accounts for, counted past 2**32, is the wrap; a drop it does not is a reboot, near the
    wrap too."""
    top = (1 << 32) - 50

    def heartbeat(uptime: int, at_ms: int, counter: int | None = None) -> Reject | None:
        return node.receive(*sender.heartbeat(1, uptime, counter), at_ms * MS)

    assert heartbeat(top, 1000) is None
    assert heartbeat(50, 1100) is None  # top + 100 ms, wrapped
    assert (node.reboots, node.uptime_ms) == (0, 50)
    assert heartbeat(150, 1200) is None
    assert heartbeat(40, 1300) is None  # back, and no wrap would give 40
    assert node.reboots == 1
    assert heartbeat(top, 1400) is None
    assert heartbeat(30_000, 1500) is None  # 30 s past the wrap, 100 ms on the host's clock
    assert node.reboots == 2


@pytest.mark.parametrize(
    ("damage", "reason"),
    [
        (lambda d: bytes((d[0] ^ 0xFF,)) + d[1:], Reject.CRC),
        (lambda d: d[:-1], Reject.LENGTH),
        (lambda d: d + b"\x00", Reject.LENGTH),
    ],
)
def test_a_damaged_frame_changes_nothing_and_is_counted(
    node: FingerNode, sender: Sender, damage: object, reason: Reject
) -> None:
    assert node.receive(*sender.feedback((0.1, 0.1, 0.1), state=1), 1 * MS) is None
    assert node.receive(*sender.heartbeat(1, 500), 1 * MS) is None
    for frame_id, data in (
        sender.feedback((0.9, 0.9, 0.9), state=2, faults=0x08),
        sender.heartbeat(0, 10),
        sender.status(2, 0x08),
    ):
        bad = damage(data)  # type: ignore[operator]
        assert node.receive(frame_id, bad, 2 * MS) is reason
    assert node.feedback is not None and node.feedback.tdt == (0.1, 0.1, 0.1)
    assert (node.state, node.fault_bits, node.feedback_ns, node.heartbeat_ns) == (
        1,
        0,
        1 * MS,
        1 * MS,
    )
    assert (node.uptime_ms, node.reboots, node.status, node.accepted) == (500, 0, None, 2)
    assert node.rejects.as_dict()[reason.name.lower()] == 3
    assert node.rejects.total == 3


def test_a_replayed_frame_changes_nothing(node: FingerNode, sender: Sender) -> None:
    old = sender.feedback((0.1, 0.2, 0.3), state=1)
    assert node.receive(*old, 1 * MS) is None
    last = sender.feedback(state=2, faults=0x01)
    assert node.receive(*last, 2 * MS) is None
    assert node.receive(*last, 3 * MS) is Reject.COUNTER_REPEAT
    assert node.receive(*old, 4 * MS) is Reject.COUNTER_SKIP
    assert node.feedback == Feedback((0.0, 0.0, 0.0), (0.0, 0.0, 0.0), 2, 0x01)
    assert (node.state, node.fault_bits, node.feedback_ns, node.accepted) == (2, 0x01, 2 * MS, 2)
    counts = node.rejects.as_dict()
    assert (counts["counter_repeat"], counts["counter_skip"], node.rejects.total) == (1, 1, 2)


def test_state_names_are_the_protocols(node: FingerNode, sender: Sender) -> None:
    for state in NodeState:
        node.receive(*sender.heartbeat(state, 1), 0)
        assert node.state_name == state.name
    assert node_state_name(9) == "UNKNOWN"


def test_a_state_the_protocol_does_not_define_is_never_the_node_s(
    node: FingerNode, sender: Sender
) -> None:
    """A Status of state 3 took a FAULT's place, and a forged Heartbeat ENABLED after it hid
    the fault for the rest of the run (found by an outside audit): the FAULT stands, and the
    undefined state is a contradiction, which the supervisor stops on."""
    node.receive(*sender.heartbeat(NodeState.FAULT, 1), 0)
    node.receive(*sender.heartbeat(3, 1), 1 * MS)
    assert node.state_name == "FAULT"
    assert node.contradiction == "Heartbeat says state 3, which the protocol does not define"
    node.receive(*sender.heartbeat(NodeState.ENABLED, 1), 2 * MS)
    assert node.state_name == "FAULT" and node.contradictions == 2


def test_command_frames_count_and_wrap(node: FingerNode, protocol: Protocol) -> None:
    layouts = node.layouts
    for expected in [*range(256), 0, 1]:
        frame_id, data = node.next_command((0.1, -0.2, 0.3))
        assert frame_id == layouts.command.frame_id
        counter, values = layouts.command.decode(data)
        assert counter == expected
        assert values == pytest.approx((0.1, -0.2, 0.3), abs=1e-4)
    for expected in [*range(256), 0]:
        frame_id, data = node.next_node_command("fault_reset")
        assert frame_id == layouts.node_command.frame_id
        assert layouts.node_command.decode(data) == (expected, (NODE_COMMANDS["fault_reset"],))
    assert node.command_counter == 2 and node.node_command_counter == 1


def test_frame_builders_are_pure(protocol: Protocol) -> None:
    layout = protocol.layout("TorqueCommand", 2)
    assert make_command(layout, 7, (0.5, 0.0, -0.5)) == (
        layout.frame_id,
        layout.encode(7, (0.5, 0.0, -0.5)),
    )
    node_layout = protocol.layout("NodeCommand", 2)
    for name, value in NODE_COMMANDS.items():
        assert make_node_command(node_layout, 3, name) == (
            node_layout.frame_id,
            node_layout.encode(3, (value,)),
        )


def test_parse_feedback_names_the_signals() -> None:
    fb = parse_feedback((0.1, 0.2, 0.3, 1.1, 1.2, 1.3, 2.0, 10.0))
    assert fb == Feedback((0.1, 0.2, 0.3), (1.1, 1.2, 1.3), 2, 10)
    assert isinstance(fb.state, int) and isinstance(fb.fault_bits, int)


def test_fault_names_of_every_bit() -> None:
    assert fault_names(0) == []
    for name, mask in FAULT_BITS.items():
        assert fault_names(mask) == [name]
    assert fault_names(0xFF) == [*FAULT_BITS, "BIT5", "BIT6", "BIT7"]
    assert fault_names(0x22) == ["ESTOP", "BIT5"]
    assert fault_names(0x100) == []  # one byte on the wire
    assert FAULT_BITS == {
        "TIMEOUT": 0x01,
        "ESTOP": 0x02,
        "RX_ERRORS": 0x04,
        "SENSOR": 0x08,
        "SATURATED": 0x10,
    }  # PROTOCOL.md's FaultBits
