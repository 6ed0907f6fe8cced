"""Host driver and emulated node firmware for fingers of any joint count, over a virtual bus:
every joint's torque reaches its motor and every joint's reading reaches the host, in config
order, whatever the fingers' joint counts and node ids."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from handctl.config import load_hand
from handctl.hand_protocol import protocol_for
from handctl.online.bus import open_bus
from handctl.online.drivers.hand import AppliedTorques, HandDriver
from handctl.sim.firmware import EmulatedNode

from ..shapes import shaped_hand

MS = 1_000_000


def test_mixed_fingers_carry_every_joint_both_ways(tmp_path: Path, channel: str) -> None:
    hand = load_hand(shaped_hand(tmp_path, [4, 1, 6], [2, 9, 15]))
    protocol = protocol_for(hand)
    host_bus = open_bus(f"virtual:{channel}", hand.bus)
    peer_bus = open_bus(f"virtual:{channel}", hand.bus)
    try:
        now = [0]
        driver = HandDriver(hand, protocol, host_bus, clock_ns=lambda: now[0])
        nodes = [
            EmulatedNode(f, protocol, tdt_range=3.0, encoder_max_step=10.0) for f in hand.fingers
        ]

        def deliver() -> None:
            for frame in peer_bus.drain():
                for node in nodes:
                    node.receive(frame.arbitration_id, frame.data, now[0])

        driver.node_command("enable")
        deliver()
        assert [node.state for node in nodes] == [1, 1, 1]
        torques = np.linspace(-0.3, 0.3, hand.n_joints)
        driver.send(AppliedTorques(np.zeros(hand.n_joints)))  # the stream's baseline
        now[0] += MS
        driver.send(AppliedTorques(torques))
        deliver()
        applied = [value for node in nodes for value in node.applied]
        np.testing.assert_allclose(applied, torques, atol=1e-4)

        tdt = np.linspace(0.2, -0.2, hand.n_joints)
        angles = np.linspace(-0.5, 0.7, hand.n_joints)
        out: list[tuple[int, bytes]] = []
        start = 0
        for node, finger in zip(nodes, hand.fingers, strict=True):
            k = len(finger.joints)
            node.publish(
                now[0], tdt[start : start + k].tolist(), angles[start : start + k].tolist(), out
            )
            start += k
        for frame_id, data in out:
            assert peer_bus.send(frame_id, data)
        state = driver.poll()
        assert sum(node.rejects.total for node in driver.nodes) == 0
        np.testing.assert_allclose(state.angle, angles, atol=1e-4)
        np.testing.assert_allclose(state.tdt, tdt, atol=1e-4)  # tdt scale 1, offset 0
        assert (state.feedback_ns >= 0).all()
    finally:
        host_bus.close()
        peer_bus.close()
