"""A frame that did not go leaves its counter to the next one: the simulated nodes on the
virtual bus take the next command (and the stop's zero torque) in sequence, not as a skip."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import can
import numpy as np
import pytest

from handctl.config import HandConfig
from handctl.online.bus import HandBus, open_bus
from handctl.online.drivers.hand import AppliedTorques, HandDriver
from handctl.protocol import NodeState, Protocol
from handctl.sim.firmware import EmulatedNode

MS = 1_000_000


class Nodes:
    """Every finger's emulated node, fed what the host's driver put on the virtual bus."""

    def __init__(self, hand: HandConfig, protocol: Protocol, peer: HandBus) -> None:
        self.peer = peer
        self.nodes = [
            EmulatedNode(f, protocol, tdt_range=3.0, encoder_max_step=0.05) for f in hand.fingers
        ]
        self.now = 0

    def tick(self) -> None:
        self.now += MS
        for frame in self.peer.drain():
            for node in self.nodes:
                node.receive(frame.arbitration_id, frame.data, self.now)
        for node in self.nodes:
            node.update(self.now)

    @property
    def counter_rejects(self) -> list[int]:
        return [n.reject_counter for n in self.nodes]


@pytest.fixture(params=["virtual", "unix"])
def buses(
    request: pytest.FixtureRequest,
    hand: HandConfig,
    bus_pair: tuple[HandBus, HandBus],
    tmp_path: Path,
) -> Iterator[tuple[HandBus, HandBus]]:
    """The host's and the nodes' ends of a bus that sends each frame at once (python-can's
    virtual bus) and of one that sends a tick's frames as one burst (handctl's unix bus)."""
    if request.param == "virtual":
        yield bus_pair
        return
    with (
        open_bus(f"unix:{tmp_path / 'bus'}", hand.bus) as peer,
        open_bus(f"unix:{tmp_path / 'bus'}", hand.bus) as host,
    ):
        host.prepare_send()  # the peer is looked up now: every later send reaches it at once
        assert host.batching
        yield host, peer


@pytest.fixture
def running(
    hand: HandConfig, protocol: Protocol, buses: tuple[HandBus, HandBus]
) -> Iterator[tuple[HandDriver, Nodes]]:
    host, peer = buses
    driver = HandDriver(hand, protocol, host)
    nodes = Nodes(hand, protocol, peer)
    driver.node_command("enable")
    driver.send(AppliedTorques(np.zeros(hand.n_joints)))  # the stream's baseline
    nodes.tick()
    assert [n.state for n in nodes.nodes] == [NodeState.ENABLED] * len(nodes.nodes)
    yield driver, nodes


def _fail_next_sends(driver: HandDriver, count: int, monkeypatch: pytest.MonkeyPatch) -> None:
    """The transport under the host's ``HandBus`` refuses its next ``count`` sends (a frame on
    the virtual bus, a burst on the unix bus), as a full transmit queue does (``HandBus`` turns
    that into False and a TX_FAILED event)."""
    bus = driver.bus
    left = [count]

    def refusing(real: Callable[..., None]) -> Callable[..., None]:
        def send(*args: Any) -> None:
            if left[0] > 0:
                left[0] -= 1
                raise can.CanOperationError("transmit buffer full")
            real(*args)

        return send

    if bus._send_frame is not None:  # type: ignore[attr-defined]
        monkeypatch.setattr(bus, "_send_frame", refusing(bus._send_frame))  # type: ignore[attr-defined]
    else:
        frames = bus._frames  # type: ignore[attr-defined]
        monkeypatch.setattr(frames, "send_frames", refusing(frames.send_frames))


def test_a_command_that_did_not_go_leaves_its_counter_to_the_next(
    hand: HandConfig, running: tuple[HandDriver, Nodes], monkeypatch: pytest.MonkeyPatch
) -> None:
    driver, nodes = running
    torque = np.full(hand.n_joints, 0.01)
    driver.send(AppliedTorques(torque))
    nodes.tick()
    _fail_next_sends(driver, 1, monkeypatch)  # the first node's frame of the next tick
    assert driver.send(AppliedTorques(2 * torque)) is False
    nodes.tick()
    assert nodes.nodes[0].applied[0] == pytest.approx(0.01, abs=1e-3)  # it kept the last
    driver.send(AppliedTorques(np.zeros(hand.n_joints)))  # a stop's zero, on the next tick
    nodes.tick()
    assert nodes.counter_rejects == [0] * len(nodes.nodes)
    assert [n.applied for n in nodes.nodes] == [[0.0] * len(n.applied) for n in nodes.nodes]


def test_the_stop_after_a_failed_frame_is_taken_in_sequence(
    hand: HandConfig, running: tuple[HandDriver, Nodes], monkeypatch: pytest.MonkeyPatch
) -> None:
    driver, nodes = running
    driver.send(AppliedTorques(np.full(hand.n_joints, 0.01)))
    nodes.tick()
    _fail_next_sends(driver, 1, monkeypatch)
    driver.send(AppliedTorques(np.full(hand.n_joints, 0.02)))
    nodes.tick()
    assert driver.send_zero() is True  # the prepared frames, at each node's next counter
    nodes.tick()
    assert nodes.counter_rejects == [0] * len(nodes.nodes)
    assert all(v == 0.0 for n in nodes.nodes for v in n.applied)


def test_a_disable_that_did_not_go_is_sent_again_in_sequence(
    hand: HandConfig, running: tuple[HandDriver, Nodes], monkeypatch: pytest.MonkeyPatch
) -> None:
    driver, nodes = running
    _fail_next_sends(driver, 1, monkeypatch)
    assert driver.node_command("disable") is False
    nodes.tick()
    assert driver.node_command("disable") is True
    nodes.tick()
    assert nodes.counter_rejects == [0] * len(nodes.nodes)
    assert [n.state for n in nodes.nodes] == [NodeState.DISABLED] * len(nodes.nodes)


class _BrokenError(RuntimeError):
    """What the test forces in the middle of a tick's sends."""


def test_an_exception_between_a_tick_s_frames_sends_none_of_them_after_it(
    hand: HandConfig, running: tuple[HandDriver, Nodes], monkeypatch: pytest.MonkeyPatch
) -> None:
    """The second node's command raises in the codec: on the unix bus the first node's frame
    was held for the tick's burst, its counter given back, and it went with the stop's first
    zero, on the same counter (the node took the torque of the tick that raised and rejected
    the zero; found by an outside audit). Nothing of that tick goes after the exception, and
    the tap hears only what went."""
    driver, nodes = running
    driver.send(AppliedTorques(np.full(hand.n_joints, 0.01)))
    nodes.tick()
    heard: list[tuple[int, bytes]] = []
    driver.bus.tap = lambda frames, direction: heard.extend(frames)

    def broken(*args: Any) -> bytes:
        raise _BrokenError("forced in the codec")

    monkeypatch.setattr(driver.nodes[1].layouts.command, "encode", broken)
    with pytest.raises(_BrokenError):
        driver.send(AppliedTorques(np.full(hand.n_joints, 0.02)))
    monkeypatch.undo()
    assert driver.send_zero() is True  # as the stop after an exception does, at once
    nodes.tick()
    assert nodes.counter_rejects == [0] * len(nodes.nodes)
    assert [n.applied for n in nodes.nodes] == [[0.0] * len(n.applied) for n in nodes.nodes]
    first = hand.fingers[0].can_ids.torque_command
    sent_first = [data for frame_id, data in heard if frame_id == first]
    unix = driver.bus.batching
    assert len(sent_first) == (1 if unix else 2)  # the zero; on the virtual bus 0.02 went first
