"""The driver's frames against cantools, for every shipped hand: the torques it sends, and
the joint state it builds from feedback, joint by joint in config order.

The driver keeps its per-node spans and working lists for the tick's sake (``poll`` copies a
node's feedback only when it is new; ``send`` converts the applied torques once): fingers of
different joint counts, frames wider than a finger's joints and a non-trivial TDT calibration
must all land where cantools, reading the hand's own generated DBC, says they belong.
"""

from __future__ import annotations

import dataclasses
import itertools
from typing import Any

import cantools
import numpy as np
import pytest

from handctl.config import HandConfig, load_hand
from handctl.hand_protocol import protocol_for
from handctl.online.bus import HandBus, open_bus
from handctl.online.drivers.hand import AppliedTorques, HandDriver
from handctl.protocol import crc8

from ..conftest import ROOT

HANDS = sorted((ROOT / "config" / "hands").glob("*.yaml"))
_channels = itertools.count()


def _calibrated(hand: HandConfig) -> HandConfig:
    """The hand with a TDT scale and offset of its own per joint, so that a joint's
    calibration applied to another joint's reading shows."""
    fingers = []
    for f, finger in enumerate(hand.fingers):
        joints = [
            dataclasses.replace(
                joint,
                tdt=dataclasses.replace(
                    joint.tdt, scale=1.0 + 0.01 * (f * 7 + j), offset=0.001 * (j - f)
                ),
            )
            for j, joint in enumerate(finger.joints)
        ]
        fingers.append(dataclasses.replace(finger, joints=tuple(joints)))
    return dataclasses.replace(hand, fingers=tuple(fingers))


def _oracle(hand: HandConfig) -> cantools.database.can.Database:
    db = cantools.database.load_string(protocol_for(hand).text, database_format="dbc")
    assert isinstance(db, cantools.database.can.Database)
    return db


def _feedback_frame(
    db: cantools.database.can.Database,
    node: Any,
    counter: int,
    tdt: list[float],
    angle: list[float],
) -> tuple[int, bytes]:
    """A Feedback frame of ``node`` encoded by cantools, its CRC over the DataID as the
    protocol says (cantools does not compute it)."""
    layout = node.layouts.feedback
    message = db.get_message_by_frame_id(layout.frame_id)
    width = (len(layout.signals) - 2) // 2  # joints the frame carries, padding included
    signals: dict[str, float] = {"Crc": 0, "Counter": counter, "State": 1, "FaultBits": 0}
    for j in range(width):
        signals[f"Torque{j + 1}"] = tdt[j] if j < len(tdt) else 0.0
        signals[f"Angle{j + 1}"] = angle[j] if j < len(angle) else 0.0
    data = bytearray(message.encode(signals, strict=True))
    data_id = layout.data_id
    data[0] = crc8(bytes((data_id & 0xFF, data_id >> 8)) + bytes(data[1:]))
    return layout.frame_id, bytes(data)


@pytest.fixture(params=HANDS, ids=[p.stem for p in HANDS])
def setup(request: pytest.FixtureRequest) -> Any:
    hand = _calibrated(load_hand(request.param))
    channel = f"driver-shapes-{next(_channels)}"
    host: HandBus = open_bus(f"virtual:{channel}", hand.bus)
    peer: HandBus = open_bus(f"virtual:{channel}", hand.bus)
    now = [10_000_000]  # ns, the host's clock: frames are stamped on it as they arrive
    driver = HandDriver(hand, protocol_for(hand), host, clock_ns=lambda: now[0])
    yield hand, driver, peer, _oracle(hand), now
    host.close()
    peer.close()


def test_sent_torques_reach_each_joint_of_each_node(setup: Any) -> None:
    hand, driver, peer, db, _ = setup
    rng = np.random.default_rng(7)
    tau_max = np.array([j.tau_max for j in hand.joints])
    applied = rng.uniform(-1.0, 1.0, hand.n_joints) * tau_max
    assert driver.send(AppliedTorques(applied))
    frames = {f.arbitration_id: f.data for f in peer.drain()}
    start = 0
    for node, finger in zip(driver.nodes, hand.fingers, strict=True):
        got = db.decode_message(
            node.layouts.command.frame_id, frames[node.layouts.command.frame_id]
        )
        assert isinstance(got, dict)
        k = len(finger.joints)
        message = db.get_message_by_frame_id(node.layouts.command.frame_id)
        for j in range(len(node.layouts.command.signals)):
            name = f"Torque{j + 1}"
            want = applied[start + j] if j < k else 0.0  # zeros after the finger's joints
            scale = message.get_signal_by_name(name).scale
            assert got[name] == pytest.approx(round(want / scale) * scale, abs=1e-12), name
        start += k


def test_feedback_lands_on_its_joints_calibrated_and_only_new_feedback_is_copied(
    setup: Any,
) -> None:
    hand, driver, peer, db, now = setup
    rng = np.random.default_rng(11)
    readings: dict[int, tuple[list[float], list[float]]] = {}
    for node, finger in zip(driver.nodes, hand.fingers, strict=True):
        k = len(finger.joints)
        tdt = [round(float(v), 3) for v in rng.uniform(-0.3, 0.3, k)]
        angle = [round(float(v), 3) for v in rng.uniform(-0.5, 1.0, k)]
        readings[node.node_id] = (tdt, angle)
        peer.send(*_feedback_frame(db, node, 0, tdt, angle))
    state = driver.poll(20_000_000)
    expected_angle: list[float] = []
    expected_tdt: list[float] = []
    for node, finger in zip(driver.nodes, hand.fingers, strict=True):
        tdt, angle = readings[node.node_id]
        layout = node.layouts.feedback
        decoded = db.decode_message(layout.frame_id, _feedback_frame(db, node, 0, tdt, angle)[1])
        assert isinstance(decoded, dict)
        for j, joint in enumerate(finger.joints):
            expected_angle.append(decoded[f"Angle{j + 1}"])
            raw = decoded[f"Torque{j + 1}"]
            expected_tdt.append(raw * joint.tdt.scale + joint.tdt.offset)
    assert state.angle.tolist() == pytest.approx(expected_angle, abs=1e-12)
    assert state.tdt.tolist() == pytest.approx(expected_tdt, abs=1e-12)
    assert state.feedback_ns.tolist() == [10_000_000] * hand.n_joints  # its arrival
    assert state.node_state == [1] * len(driver.nodes)

    # A new frame from the last node only: its joints change, every other joint keeps its
    # reading and its arrival time.
    last = driver.nodes[-1]
    k = len(hand.fingers[-1].joints)
    now[0] = 30_000_000
    peer.send(*_feedback_frame(db, last, 1, [0.2] * k, [0.4] * k))
    state = driver.poll(40_000_000)
    n = hand.n_joints
    assert state.angle.tolist()[: n - k] == pytest.approx(expected_angle[: n - k], abs=1e-12)
    assert state.angle.tolist()[n - k :] == pytest.approx([0.4] * k, abs=1e-12)
    assert state.tdt.tolist()[: n - k] == pytest.approx(expected_tdt[: n - k], abs=1e-12)
    assert state.feedback_ns.tolist() == [10_000_000] * (n - k) + [30_000_000] * k
