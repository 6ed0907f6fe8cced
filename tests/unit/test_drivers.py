"""The hand driver over a real virtual bus: what it sends, and what it accepts or rejects.

The far end here sends hand-made frames on purpose: these tests are about the host's receiver
rules (one bad byte, one replayed counter), which need exact control of every byte.
Conversations with the emulated finger nodes are in the integration tests.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import replace

import cantools
import numpy as np
import pytest

from handctl.config import HandConfig
from handctl.errors import ConfigError
from handctl.hand_protocol import check_protocol
from handctl.online.bus import HandBus
from handctl.online.drivers.finger import fault_names
from handctl.online.drivers.hand import ESTOP_OPERATOR, AppliedTorques, HandDriver
from handctl.protocol import Protocol

from ..dbc import decode, load_dbc


class Clock:
    def __init__(self) -> None:
        self.now = 1_000_000_000

    def __call__(self) -> int:
        return self.now


@pytest.fixture
def clock() -> Clock:
    return Clock()


@pytest.fixture
def driver(
    hand: HandConfig, protocol: Protocol, bus_pair: tuple[HandBus, HandBus], clock: Clock
) -> Iterator[HandDriver]:
    yield HandDriver(hand, protocol, bus_pair[0], clock_ns=clock)


@pytest.fixture(scope="module")
def db() -> cantools.database.can.Database:
    return load_dbc()


def feedback(
    protocol: Protocol,
    node: int,
    counter: int,
    tdt: tuple[float, float, float],
    angles: tuple[float, float, float],
    state: int = 1,
    faults: int = 0,
) -> bytes:
    return protocol.layout("Feedback", node).encode(counter, (*tdt, *angles, state, faults))


def test_sent_commands_decode_with_cantools(
    driver: HandDriver, bus_pair: tuple[HandBus, HandBus], db: cantools.database.can.Database
) -> None:
    peer = bus_pair[1]
    torques = [0.1, -0.2, 0.3, 0.01, 0.02, 0.03, -0.1, -0.2, -0.25]
    assert driver.send(AppliedTorques(np.array(torques)))
    assert driver.send(AppliedTorques(np.zeros(9)))
    frames = peer.drain()
    assert [f.arbitration_id for f in frames] == [0x101, 0x102, 0x103] * 2
    first = decode(frames[2].arbitration_id, frames[2].data)
    assert first["Counter"] == 0
    assert [first[f"Torque{k}"] for k in (1, 2, 3)] == pytest.approx([-0.1, -0.2, -0.25])
    assert decode(frames[5].arbitration_id, frames[5].data)["Counter"] == 1


def test_node_commands_and_estop(
    driver: HandDriver, bus_pair: tuple[HandBus, HandBus], db: cantools.database.can.Database
) -> None:
    peer = bus_pair[1]
    driver.node_command("enable", nodes=[2])
    driver.node_command("fault_reset")
    driver.send_estop(ESTOP_OPERATOR)
    frames = peer.drain()
    names = [db.get_message_by_frame_id(f.arbitration_id).name for f in frames]
    assert names == ["NodeCommand_2", "NodeCommand_1", "NodeCommand_2", "NodeCommand_3", "EStop"]
    assert str(decode(0x12, frames[0].data)["Command"]) == "enable"
    assert str(decode(0x12, frames[2].data)["Command"]) == "fault_reset"
    assert str(decode(0, frames[4].data)["Reason"]) == "operator"


def test_good_feedback_updates_the_joint_state(
    driver: HandDriver, protocol: Protocol, bus_pair: tuple[HandBus, HandBus], clock: Clock
) -> None:
    peer = bus_pair[1]
    peer.send(0x182, feedback(protocol, 2, 0, (0.1, 0.2, 0.3), (0.4, 0.5, 0.6)))
    state = driver.poll()
    assert state.angle[3:6] == pytest.approx([0.4, 0.5, 0.6])
    assert state.tdt[3:6] == pytest.approx([0.1, 0.2, 0.3])
    assert np.all(state.feedback_ns[3:6] == clock.now)
    assert np.all(state.feedback_ns[[0, 1, 2, 6, 7, 8]] == -1)
    clock.now += 3_000_000
    age = state.age_s(clock.now)
    assert age[4] == pytest.approx(0.003)
    assert np.isinf(age[0])
    assert state.node_state == [-1, 1, -1]


def test_tdt_calibration_is_applied_once(
    hand: HandConfig, protocol: Protocol, bus_pair: tuple[HandBus, HandBus], clock: Clock
) -> None:
    fingers = list(hand.fingers)
    joints = list(fingers[0].joints)
    joints[1] = replace(joints[1], tdt=replace(joints[1].tdt, scale=2.0, offset=0.01))
    fingers[0] = replace(fingers[0], joints=tuple(joints))
    driver = HandDriver(
        replace(hand, fingers=tuple(fingers)), protocol, bus_pair[0], clock_ns=clock
    )
    bus_pair[1].send(0x181, feedback(protocol, 1, 0, (0.1, 0.1, 0.1), (0.0, 0.0, 0.0)))
    for _ in range(3):  # polls without new frames must not compound the calibration
        state = driver.poll()
    assert state.tdt[:3] == pytest.approx([0.1, 0.21, 0.1])


@pytest.mark.parametrize(
    ("mutate", "kind"),
    [
        (lambda d: bytes((d[0] ^ 0x01,)) + d[1:], "crc"),
        (lambda d: d[:8], "length"),
        (lambda d: d + b"\x00", "length"),
        (lambda d: d[:5] + bytes((d[5] ^ 0x80,)) + d[6:], "crc"),
    ],
)
def test_corrupt_frames_are_rejected_and_never_applied(
    driver: HandDriver,
    protocol: Protocol,
    bus_pair: tuple[HandBus, HandBus],
    mutate: object,
    kind: str,
) -> None:
    peer = bus_pair[1]
    peer.send(0x181, feedback(protocol, 1, 0, (0.1, 0.1, 0.1), (0.2, 0.2, 0.2)))
    driver.poll()
    bad = mutate(feedback(protocol, 1, 1, (0.9, 0.9, 0.9), (1.0, 1.0, 1.0)))  # type: ignore[operator]
    peer.send(0x181, bad)
    state = driver.poll()
    assert state.angle[:3] == pytest.approx([0.2, 0.2, 0.2])
    assert driver.reject_counts()[kind] == 1
    assert sum(driver.reject_counts().values()) == 1


def test_counter_rules(
    driver: HandDriver, protocol: Protocol, bus_pair: tuple[HandBus, HandBus]
) -> None:
    peer = bus_pair[1]

    def send(counter: int, angle: float) -> float:
        peer.send(0x183, feedback(protocol, 3, counter, (0, 0, 0), (angle, 0, 0)))
        return float(driver.poll().angle[6])

    assert send(250, 0.1) == pytest.approx(0.1)  # first frame: any counter
    assert send(250, 0.2) == pytest.approx(0.1)  # repeated: rejected
    assert send(251, 0.3) == pytest.approx(0.3)
    assert send(253, 0.4) == pytest.approx(0.3)  # skipped: rejected, re-synchronised
    assert send(254, 0.5) == pytest.approx(0.5)  # and the stream goes on
    assert send(255, 0.6) == pytest.approx(0.6)
    assert send(0, 0.7) == pytest.approx(0.7)  # wraps
    counts = driver.reject_counts()
    assert counts["counter_repeat"] == 1
    assert counts["counter_skip"] == 1


def test_unexpected_ids_are_counted_and_dropped(
    driver: HandDriver, protocol: Protocol, bus_pair: tuple[HandBus, HandBus]
) -> None:
    peer = bus_pair[1]
    peer.send(0x555, bytes(8))
    peer.send(0x101, protocol.layout("TorqueCommand", 1).encode(0, (0.1, 0.1, 0.1)))
    peer.send(0x555, bytes(8))
    driver.poll()
    assert driver.reject_counts()["unexpected_id"] == 3
    assert driver.unexpected_ids == {0x555: 2, 0x101: 1}
    assert driver.state.node_state == [-1, -1, -1]


def test_heartbeat_going_backwards_counts_a_reboot(
    driver: HandDriver, protocol: Protocol, bus_pair: tuple[HandBus, HandBus]
) -> None:
    peer = bus_pair[1]
    hb = protocol.layout("Heartbeat", 1)
    peer.send(0x701, hb.encode(0, (1, 5000)))
    peer.send(0x701, hb.encode(1, (1, 5100)))
    driver.poll()
    assert driver.nodes[0].reboots == 0
    # The rebooted node counts from 0 again: its first frame is a skip (rejected, never
    # applied), the receiver re-synchronises, and the next one shows the uptime going back.
    peer.send(0x701, hb.encode(0, (0, 3)))
    driver.poll()
    assert driver.nodes[0].reboots == 0
    assert driver.reject_counts()["counter_skip"] == 1
    peer.send(0x701, hb.encode(1, (0, 103)))
    driver.poll()
    assert driver.nodes[0].reboots == 1
    assert driver.nodes[0].state_name == "DISABLED"


def test_status_frames_carry_faults(
    driver: HandDriver, protocol: Protocol, bus_pair: tuple[HandBus, HandBus]
) -> None:
    bus_pair[1].send(
        0x282, protocol.layout("Status", 2).encode(0, (2, 0x03, 0, 0, 0, 11, 2, 0, 2, 0))
    )
    state = driver.poll()
    assert state.node_state[1] == 2
    assert fault_names(state.node_faults[1]) == ["TIMEOUT", "ESTOP"]
    assert fault_names(0x80) == ["BIT7"]


def test_config_ids_must_match_the_dbc(hand: HandConfig, protocol: Protocol) -> None:
    check_protocol(hand, protocol)
    fingers = list(hand.fingers)
    fingers[1] = replace(fingers[1], can_ids=replace(fingers[1].can_ids, feedback=0x190))
    with pytest.raises(ConfigError) as info:
        check_protocol(replace(hand, fingers=tuple(fingers)), protocol)
    assert info.value.key == "fingers[1].can_ids.feedback"
    assert "0x182 (Feedback_2" in info.value.expected
