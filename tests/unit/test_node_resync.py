"""A node meets a new host (PROTOCOL.md, "A new host"): the host's counters start where that
host likes, yet no single stale or replayed frame may move a joint.

Each test drives one emulated node frame by frame, with the host ends of two hosts that count
independently, the way two processes run one after the other would.
"""

from __future__ import annotations

import pytest

from handctl.config import HandConfig
from handctl.online.bus import HandBus
from handctl.online.drivers.hand import HandDriver
from handctl.protocol import NodeState, Protocol
from handctl.sim.firmware import EmulatedNode, FaultBits

from .test_sim_firmware import MAX_STEP, MS, TDT_RANGE, WATCHDOG_NS, Wire, enabled, tick


@pytest.fixture
def node(hand: HandConfig, protocol: Protocol) -> EmulatedNode:
    return EmulatedNode(hand.fingers[0], protocol, tdt_range=TDT_RANGE, encoder_max_step=MAX_STEP)


@pytest.fixture
def wire(protocol: Protocol) -> Wire:
    return Wire(protocol, 1)


def _first_host_ran(node: EmulatedNode, protocol: Protocol, commands: int = 37) -> int:
    """A first host enables, commands a while and disables: its counters end mid-range."""
    first = Wire(protocol, 1)
    now = enabled(node, first)
    for _ in range(commands):
        tick(node, now, first.torque(0.1, 0.0, 0.0))
        now += MS
    tick(node, now, first.command("disable"))
    assert node.state == NodeState.DISABLED
    return now + MS


def test_a_new_host_enables_a_disabled_node_from_its_own_counters(
    node: EmulatedNode, protocol: Protocol
) -> None:
    now = _first_host_ran(node, protocol)
    rejects = (node.reject_counter, node.reject_crc, node.reject_length)
    second = Wire(protocol, 1)  # a new process: every counter from 0 again
    now = enabled(node, second, now)
    tick(node, now, second.torque(0.2, 0.0, 0.0))
    assert node.state == NodeState.ENABLED
    assert node.applied[0] == pytest.approx(0.2)
    assert (node.reject_counter, node.reject_crc, node.reject_length) == rejects


def test_the_first_command_after_enable_is_never_applied(
    node: EmulatedNode, protocol: Protocol
) -> None:
    """A stale command arriving between an enable and the host's first command (a replay of
    the previous host's stream) only sets the baseline; the host's own next command, which
    does not follow it, is rejected once; the one after applies."""
    now = _first_host_ran(node, protocol)
    stale = Wire(protocol, 1)
    stale.counters["TorqueCommand_1"] = 200
    second = Wire(protocol, 1)
    tick(node, now, second.command("enable"), stale.torque(1.0, 1.0, 1.0))
    assert node.state == NodeState.ENABLED and node.applied == [0.0, 0.0, 0.0]
    tick(node, now + MS, second.torque(0.0, 0.0, 0.0))
    assert node.applied == [0.0, 0.0, 0.0]
    tick(node, now + 2 * MS, second.torque(0.05, 0.0, 0.0))
    assert node.applied[0] == pytest.approx(0.05)


def test_a_baseline_does_not_feed_the_command_watchdog(
    node: EmulatedNode, protocol: Protocol
) -> None:
    """An enable and a single frame (a replayed pair, no host behind them): the node times out
    from the enable, with no torque at any moment."""
    now = _first_host_ran(node, protocol)
    replay = Wire(protocol, 1)
    replay.counters.update({"NodeCommand_1": 90, "TorqueCommand_1": 91})
    enable_at = now
    tick(node, now, replay.command("enable"))
    tick(node, now + 5 * MS, replay.torque(0.8, 0.0, 0.0))
    for t in range(now + 6 * MS, enable_at + WATCHDOG_NS, MS):
        tick(node, t)
        assert node.applied == [0.0, 0.0, 0.0]
    tick(node, enable_at + WATCHDOG_NS)
    assert node.state == NodeState.FAULT and node.fault_bits & FaultBits.TIMEOUT


def test_no_resync_while_enabled(node: EmulatedNode, wire: Wire) -> None:
    now = enabled(node, wire)
    tick(node, now, wire.torque(0.1, 0.0, 0.0))
    fid, data = wire.frame("NodeCommand", (2,), counter=99)  # disable, out of sequence
    tick(node, now + MS, (fid, data))
    assert node.state == NodeState.ENABLED and node.reject_counter == 1
    tick(node, now + 2 * MS, wire.torque(0.2, 0.0, 0.0, counter=40))  # out of sequence
    assert node.applied[0] == pytest.approx(0.1) and node.reject_counter == 2


def test_a_faulted_node_takes_a_new_host_only_after_the_old_one_fell_silent(
    node: EmulatedNode, protocol: Protocol
) -> None:
    """The first host dies mid-run: the watchdog latches TIMEOUT. A fault_reset out of the
    dead host's sequence is still refused while hosts were heard within the watchdog time; once
    no host frame has come for that long, a new host's fault_reset is taken."""
    first = Wire(protocol, 1)
    now = enabled(node, first)
    for _ in range(20):
        tick(node, now, first.torque(0.1, 0.0, 0.0))
        now += MS
    last_heard = now - MS
    while node.state != NodeState.FAULT:
        tick(node, now)
        now += MS
    assert node.fault_bits & FaultBits.TIMEOUT
    assert now - last_heard <= WATCHDOG_NS + MS
    # A live host (frames heard within the watchdog time) keeps its sequence checked ...
    tick(node, now, first.torque(0.0, 0.0, 0.0))
    second = Wire(protocol, 1)
    second.counters["NodeCommand_1"] = 7
    tick(node, now + MS, second.command("fault_reset"))
    assert node.state == NodeState.FAULT and node.reject_counter == 1
    # ... and once every host has been silent that long, a new one is taken.
    later = now + WATCHDOG_NS
    tick(node, later, second.command("fault_reset"))
    assert node.state == NodeState.DISABLED and node.fault_bits == 0
    enabled(node, second, later + MS)
    tick(node, later + 2 * MS, second.torque(0.1, 0.0, 0.0))
    assert node.applied[0] == pytest.approx(0.1)


def test_the_host_takes_each_nodes_counters_afresh_at_start_up(
    hand: HandConfig, protocol: Protocol, bus_pair: tuple[HandBus, HandBus]
) -> None:
    """A driver that heard a node once, then nothing while it was not running, takes the node's
    next frames with whatever counters they carry when the next run starts: the node did not
    misbehave, the host was away."""
    host, peer = bus_pair
    driver = HandDriver(hand, protocol, host)
    feedback = protocol.layout("Feedback", 1)
    values = (0.0,) * 6 + (0, 0)
    peer.send(feedback.frame_id, feedback.encode(5, values))
    driver.poll(0)
    first = driver.nodes[0].feedback_ns
    assert first is not None
    peer.send(feedback.frame_id, feedback.encode(120, values))
    driver.discard_pending()  # a new run starts: what was queued is old news
    peer.send(feedback.frame_id, feedback.encode(121, values))
    driver.poll(1)
    assert driver.reject_counts()["counter_skip"] == 0
    last = driver.nodes[0].feedback_ns  # stamped on arrival: a later frame was taken
    assert last is not None and last > first
