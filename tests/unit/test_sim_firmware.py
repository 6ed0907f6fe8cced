"""The emulated node against ``firmware_protocol/PROTOCOL.md``, frame by frame, without a bus.

Frames are built with the protocol's layouts (the DBC) and fed to the node with explicit times,
so each rule of the spec is checked at the tick where it must bite.
"""

from __future__ import annotations

import pytest

from handctl.config import HandConfig
from handctl.protocol import NODE_COMMANDS, NodeState, Protocol
from handctl.sim.firmware import EmulatedNode, FaultBits

MS = 1_000_000
WATCHDOG_NS = 10 * MS  # PROTOCOL.md: no accepted TorqueCommand for 10 ms
REJECT_LIMIT = 100  # PROTOCOL.md: the reject score latches RX_ERRORS at 100
TDT_RANGE = 3.0
MAX_STEP = 0.05


class Wire:
    """The host end of one node's messages: counters kept per message, as a sender must."""

    def __init__(self, protocol: Protocol, node: int) -> None:
        self.protocol = protocol
        self.node = node
        self.counters: dict[str, int] = {}

    def frame(
        self,
        kind: str,
        values: tuple[float, ...],
        *,
        node: int | None = None,
        counter: int | None = None,
    ) -> tuple[int, bytes]:
        layout = (
            self.protocol.layout(kind)
            if kind == "EStop"
            else self.protocol.layout(kind, node or self.node)
        )
        if counter is None:
            counter = self.counters.get(layout.name, 0)
            self.counters[layout.name] = (counter + 1) & 0xFF
        return layout.frame_id, layout.encode(counter, values)

    def command(self, name: str) -> tuple[int, bytes]:
        return self.frame("NodeCommand", (NODE_COMMANDS[name],))

    def torque(self, *tau: float, counter: int | None = None) -> tuple[int, bytes]:
        return self.frame("TorqueCommand", tau, counter=counter)


@pytest.fixture
def node(hand: HandConfig, protocol: Protocol) -> EmulatedNode:
    return EmulatedNode(hand.fingers[0], protocol, tdt_range=TDT_RANGE, encoder_max_step=MAX_STEP)


@pytest.fixture
def wire(protocol: Protocol) -> Wire:
    return Wire(protocol, 1)


def tick(
    node: EmulatedNode,
    now: int,
    *frames: tuple[int, bytes],
    angles: list[float] | None = None,
    tdt: list[float] | None = None,
) -> list[tuple[int, bytes]]:
    """One node tick at ``now`` ns, as the simulated hand runs it; returns the frames sent."""
    for fid, data in frames:
        node.receive(fid, data, now)
    node.update(now)
    out: list[tuple[int, bytes]] = []
    node.publish(now, list(tdt or [0.0, 0.0, 0.0]), list(angles or [0.0, 0.0, 0.0]), out)
    return out


def decode(
    protocol: Protocol, frames: list[tuple[int, bytes]], kind: str, node: int = 1
) -> list[tuple[int, tuple[float, ...]]]:
    layout = protocol.layout(kind, node)
    return [layout.decode(data) for fid, data in frames if fid == layout.frame_id]


def enabled(node: EmulatedNode, wire: Wire, now: int = 0) -> int:
    """Enable as a host does: the enable, then its first (zero) command, the baseline of the
    torque stream, which is never applied."""
    tick(node, now, wire.command("enable"), wire.torque(0.0, 0.0, 0.0))
    assert node.state == NodeState.ENABLED
    return now + MS


def test_boots_disabled_and_enables(node: EmulatedNode, wire: Wire, protocol: Protocol) -> None:
    out = tick(node, 0)
    assert node.state == NodeState.DISABLED
    # at boot (uptime 0) the node announces itself: Feedback, Status, Heartbeat
    assert [fid for fid, _ in out] == [0x181, 0x281, 0x701]
    out = tick(node, MS, wire.command("enable"))
    assert node.state == NodeState.ENABLED
    ((_, status),) = decode(protocol, out, "Status")
    assert status[0] == NodeState.ENABLED  # sent at once on the state change


def test_commands_are_applied_only_when_enabled(node: EmulatedNode, wire: Wire) -> None:
    tick(node, 0, wire.torque(0.1, 0.2, 0.3))
    assert node.applied == [0.0, 0.0, 0.0]
    now = enabled(node, wire, MS)
    tick(node, now, wire.torque(0.1, 0.2, -0.3))
    assert node.applied == pytest.approx([0.1, 0.2, -0.3])
    tick(node, now + MS, wire.command("disable"))
    assert node.state == NodeState.DISABLED and node.applied == [0.0, 0.0, 0.0]


def test_watchdog_trips_at_10_ms_without_accepted_commands(node: EmulatedNode, wire: Wire) -> None:
    now = enabled(node, wire)  # armed at t = 0 by the enable
    tick(node, now, wire.torque(0.1, 0.0, 0.0))  # last accepted command at 1 ms
    last = now
    for t in range(last + MS, last + WATCHDOG_NS, MS):
        tick(node, t)
        assert node.state == NodeState.ENABLED, f"tripped early at {t / MS} ms"
    tick(node, last + WATCHDOG_NS)
    assert node.state == NodeState.FAULT
    assert node.fault_bits & FaultBits.TIMEOUT
    assert node.applied == [0.0, 0.0, 0.0]


def test_watchdog_is_armed_by_enable(node: EmulatedNode, wire: Wire) -> None:
    enabled(node, wire, 5 * MS)
    tick(node, 5 * MS + WATCHDOG_NS - MS)
    assert node.state == NodeState.ENABLED
    tick(node, 5 * MS + WATCHDOG_NS)
    assert node.fault_bits & FaultBits.TIMEOUT


def test_rejected_commands_do_not_feed_the_watchdog(node: EmulatedNode, wire: Wire) -> None:
    now = enabled(node, wire)
    fid, good = wire.torque(0.1, 0.0, 0.0)
    bad = bytes((good[0] ^ 1,)) + good[1:]
    for t in range(now, now + WATCHDOG_NS - MS, 2 * MS):  # few enough not to trip RX_ERRORS
        tick(node, t, (fid, bad))
        tick(node, t + MS)
    assert node.state == NodeState.FAULT
    assert node.fault_bits == FaultBits.TIMEOUT
    assert node.reject_crc == 5


def test_saturation_clips_and_reports(node: EmulatedNode, wire: Wire, hand: HandConfig) -> None:
    limits = [j.device_tau_max for j in hand.fingers[0].joints]
    now = enabled(node, wire)
    tick(node, now, wire.torque(limits[0] + 0.2, -(limits[1] + 0.1), 0.01))
    assert node.applied == pytest.approx([limits[0], -limits[1], 0.01])
    assert node.fault_bits & FaultBits.SATURATED
    assert node.state == NodeState.ENABLED  # saturation is not a fault
    tick(node, now + MS, wire.torque(0.1, 0.1, 0.1))
    assert not node.fault_bits & FaultBits.SATURATED


def test_receiver_checks_in_order_and_never_applies_a_rejected_frame(
    node: EmulatedNode, wire: Wire
) -> None:
    now = enabled(node, wire)  # the baseline of the torque stream: counter 0
    tick(node, now, wire.torque(0.1, 0.0, 0.0, counter=1))
    # wrong length
    fid, data = wire.torque(0.5, 0.0, 0.0, counter=2)
    tick(node, now + MS, (fid, data[:-1]))
    # bad CRC
    tick(node, now + 2 * MS, (fid, bytes((data[0] ^ 0xFF,)) + data[1:]))
    # repeated counter (1 was the last accepted)
    tick(node, now + 3 * MS, wire.torque(0.5, 0.0, 0.0, counter=1))
    assert node.applied == pytest.approx([0.1, 0.0, 0.0])
    assert (node.reject_length, node.reject_crc, node.reject_counter) == (1, 1, 1)
    # skipped counter: rejected, but the receiver re-synchronises to it...
    tick(node, now + 4 * MS, wire.torque(0.5, 0.0, 0.0, counter=20))
    assert node.applied == pytest.approx([0.1, 0.0, 0.0]) and node.reject_counter == 2
    # ...so the next consecutive frame is accepted again
    tick(node, now + 5 * MS, wire.torque(0.4, 0.0, 0.0, counter=21))
    assert node.applied == pytest.approx([0.4, 0.0, 0.0])


def test_counter_wraps(node: EmulatedNode, wire: Wire) -> None:
    tick(node, 0, wire.command("enable"), wire.torque(0.0, 0.0, 0.0, counter=254))
    tick(node, MS, wire.torque(0.1, 0.0, 0.0, counter=255))
    tick(node, 2 * MS, wire.torque(0.2, 0.0, 0.0, counter=0))
    assert node.applied[0] == pytest.approx(0.2) and node.reject_counter == 0


def test_other_ids_are_counted_not_applied(
    node: EmulatedNode, wire: Wire, protocol: Protocol
) -> None:
    now = enabled(node, wire)
    tick(node, now, wire.frame("TorqueCommand", (0.3, 0.3, 0.3), node=2), (0x555, b"\x00"))
    assert node.applied == [0.0, 0.0, 0.0]
    assert node.reject_unexpected == 2
    assert node.score == 0  # not addressed to this node: no effect on the reject score


def test_ten_rejects_in_a_row_latch_rx_errors(node: EmulatedNode, wire: Wire) -> None:
    now = enabled(node, wire)
    fid, data = wire.torque(0.1, 0.0, 0.0)
    bad = bytes((data[0] ^ 0x55,)) + data[1:]
    for _ in range(REJECT_LIMIT // 10 - 1):
        node.receive(fid, bad, now)
    assert node.state == NodeState.ENABLED
    node.receive(fid, bad, now)
    assert node.state == NodeState.FAULT and node.fault_bits & FaultBits.RX_ERRORS


def test_isolated_losses_never_trip(node: EmulatedNode, wire: Wire) -> None:
    now = enabled(node, wire)
    for k in range(2000):
        frame = wire.torque(0.1, 0.0, 0.0)
        if k % 20 == 5:
            continue  # one frame in twenty lost: the next one is a skip, counted, then resync
        tick(node, now + k * MS, frame)
    assert node.state == NodeState.ENABLED
    assert node.reject_counter == 100


def test_estop_is_honoured_even_malformed(node: EmulatedNode, wire: Wire) -> None:
    now = enabled(node, wire)
    tick(node, now, wire.torque(0.2, 0.2, 0.2))
    fid, data = wire.frame("EStop", (1,))
    tick(node, now + MS, (fid, bytes((data[0] ^ 0xFF,)) + data[1:]))
    assert node.state == NodeState.FAULT
    assert node.fault_bits & FaultBits.ESTOP
    assert node.applied == [0.0, 0.0, 0.0]
    assert node.reject_crc == 1  # honoured, and still counted as rejected


def test_fault_needs_reset_then_enable(node: EmulatedNode, wire: Wire, protocol: Protocol) -> None:
    now = enabled(node, wire)
    tick(node, now, wire.frame("EStop", (2,)))
    tick(node, now + MS, wire.command("enable"))
    assert node.state == NodeState.FAULT  # enable is refused in FAULT
    out = tick(node, now + 2 * MS, wire.command("fault_reset"))
    assert node.state == NodeState.DISABLED and node.fault_bits == 0
    ((_, status),) = decode(protocol, out, "Status")
    assert status[:2] == (NodeState.DISABLED, 0)
    # the receive counters restart: any counter is accepted for the first frame, which sets
    # the baseline of its stream (a torque command is applied from the next one on)
    tick(node, now + 3 * MS, wire.command("enable"))
    tick(node, now + 4 * MS, wire.torque(0.0, 0.0, 0.0, counter=77))
    tick(node, now + 5 * MS, wire.torque(0.1, 0.0, 0.0, counter=78))
    assert node.state == NodeState.ENABLED and node.applied[0] == pytest.approx(0.1)


def test_periodic_frames_and_uptime(node: EmulatedNode, protocol: Protocol) -> None:
    frames: list[tuple[int, bytes]] = []
    for k in range(1000):
        frames += tick(node, k * MS)
    feedback = decode(protocol, frames, "Feedback")
    status = decode(protocol, frames, "Status")
    heartbeat = decode(protocol, frames, "Heartbeat")
    assert len(feedback) == 1000 and len(status) == 10 and len(heartbeat) == 10
    assert [values[1] for _, values in heartbeat] == list(range(0, 1000, 100))
    for kind in (feedback, status, heartbeat):
        counters = [c for c, _ in kind]
        assert counters == [k & 0xFF for k in range(len(counters))]
    assert status[0][1][5] == 255  # CommandAge saturates when there never was a command


def test_self_check_latches_sensor(node: EmulatedNode, wire: Wire) -> None:
    now = enabled(node, wire)
    tick(node, now, angles=[MAX_STEP / 2, 0.0, 0.0])
    tick(node, now + MS, angles=[MAX_STEP, 0.0, -MAX_STEP / 2])
    assert node.state == NodeState.ENABLED
    tick(node, now + 2 * MS, angles=[MAX_STEP, 2 * MAX_STEP, -MAX_STEP / 2])
    assert node.fault_bits & FaultBits.SENSOR and node.state == NodeState.FAULT

    other = EmulatedNode(node.finger, wire.protocol, tdt_range=TDT_RANGE, encoder_max_step=MAX_STEP)
    tick(other, 0, tdt=[0.0, TDT_RANGE + 0.1, 0.0])
    assert other.fault_bits & FaultBits.SENSOR


def test_reboot_is_silent_then_fresh(node: EmulatedNode, wire: Wire, protocol: Protocol) -> None:
    now = enabled(node, wire)
    for k in range(150):
        tick(node, now + k * MS, wire.torque(0.1, 0.0, 0.0))
    t = now + 150 * MS
    node.reboot(t, 20 * MS)
    silent = [tick(node, t + k * MS, wire.torque(0.1, 0.0, 0.0)) for k in range(20)]
    assert all(out == [] for out in silent)
    assert node.applied == [0.0, 0.0, 0.0]
    out = tick(node, t + 20 * MS)
    assert node.state == NodeState.DISABLED
    assert [c for c, _ in decode(protocol, out, "Feedback")] == [0]
    ((_, hb),) = decode(protocol, out, "Heartbeat")
    assert hb[1] == 0  # uptime restarted: the host sees the reboot


def test_a_node_enabled_and_faulted_in_one_tick_reports_its_states_in_order(
    node: EmulatedNode, wire: Wire, protocol: Protocol
) -> None:
    """Its Status frames of the two changes go before the Feedback, which reports the state
    after them: sent after it, the older ENABLED came last, and a host took the node for one
    contradicting itself (ENABLED after FAULT without a fault reset)."""
    tick(node, 0)
    out = tick(node, MS, wire.command("enable"), tdt=[0.0, TDT_RANGE + 0.1, 0.0])
    assert node.state == NodeState.FAULT
    status, feedback = protocol.layout("Status", 1), protocol.layout("Feedback", 1)
    states = [
        int(layout.decode(data)[1][index])
        for fid, data in out
        for layout, index in ((status, 0), (feedback, 6))
        if fid == layout.frame_id
    ]
    assert states == [NodeState.ENABLED, NodeState.FAULT, NodeState.FAULT]
    assert [fid for fid, _ in out][:3] == [status.frame_id, status.frame_id, feedback.frame_id]
