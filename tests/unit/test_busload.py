"""Worst-case frame times against figures worked out by hand from the frame formats."""

from __future__ import annotations

import math
from pathlib import Path

import pytest

from handctl.busload import (
    MAX_LOAD,
    classic_frame_bits,
    fd_dlc_size,
    fd_frame_bits,
    frame_time_s,
    hand_budget,
    what_would_fit,
)
from handctl.config import HandConfig, load_hand
from handctl.hand_protocol import generate_dbc, protocol_for
from handctl.protocol import Protocol, load_protocol

from ..conftest import ROOT, handctl
from ..shapes import shaped_hand


@pytest.mark.parametrize(("n", "bits"), [(0, 55), (1, 65), (8, 135)])
def test_classic_worst_case_bits(n: int, bits: int) -> None:
    # 8n + 47 frame bits plus floor((34 + 8n - 1) / 4) stuff bits: 135 for a full frame is the
    # figure every CAN schedulability analysis quotes.
    assert classic_frame_bits(n) == bits


def test_classic_refuses_more_than_eight_bytes() -> None:
    with pytest.raises(ValueError, match="0 to 8"):
        classic_frame_bits(9)


def test_fd_dlc_sizes() -> None:
    assert [fd_dlc_size(n) for n in (0, 8, 9, 13, 16, 17, 33, 64)] == [0, 8, 12, 16, 16, 20, 48, 64]
    with pytest.raises(ValueError):
        fd_dlc_size(65)


def test_fd_frame_bits_by_hand() -> None:
    # 8 bytes: nominal 17 + 4 stuff + 13 tail = 34; data 5 + 64 + 17 dyn stuff + 4 + 17 + 6 = 113
    assert fd_frame_bits(8) == (34, 113)
    # 16 bytes: data 5 + 128 + 33 + 4 + 17 + 6 = 193
    assert fd_frame_bits(16) == (34, 193)
    # 20 bytes switch to the 21-bit CRC with 7 fixed stuff bits
    _, data = fd_frame_bits(20)
    assert data == 5 + 160 + (22 + 160 - 1) // 4 - 4 + 4 + 21 + 7


def test_frame_time() -> None:
    assert frame_time_s(8, False, 1_000_000, None) == pytest.approx(135e-6)
    assert frame_time_s(16, False, 1_000_000, None) == pytest.approx(270e-6)  # split in two
    assert frame_time_s(8, True, 1_000_000, 5_000_000) == pytest.approx(34e-6 + 113 / 5e6)
    # Without a data rate the FD frame runs entirely at the nominal rate.
    assert frame_time_s(8, True, 1_000_000, None) == pytest.approx(147e-6)


def test_default_hand_fits_and_classic_does_not(hand: HandConfig, protocol: Protocol) -> None:
    fd = hand_budget(hand, protocol)
    assert fd.ok and fd.load == pytest.approx(0.3909, abs=1e-3)
    classic = load_hand(ROOT / "config" / "hands" / "hiroshima_hand_classic.yaml")
    budget = hand_budget(classic, protocol)
    assert not budget.ok
    assert budget.load == pytest.approx(1.2257, abs=1e-3)  # Status is 12 bytes: two frames
    # What does not follow the loop (the nodes' 1 kHz Feedback in two classic frames) is
    # over the limit by itself: no loop rate fits
    fixed = sum(m.load for m in budget.messages if not m.per_loop)
    assert fixed > MAX_LOAD and budget.highest_loop_rate_hz() == 0.0
    # on CAN-FD 1/5 Mbit/s a four-by-four hand at the advertised highest rate is exactly at it
    four = load_hand(ROOT / "config" / "hands" / "four_fingers_four_joints.yaml")
    slow = hand_budget(four, protocol_for(four), data_bitrate=5_000_000)
    rate = slow.highest_loop_rate_hz()
    fixed = sum(m.load for m in slow.messages if not m.per_loop)
    assert 200 < rate < 1000
    assert fixed + rate * slow.loop_time_per_tick_s == pytest.approx(MAX_LOAD)
    one_finger = hand_budget(classic, protocol, nodes={1})
    assert one_finger.ok
    assert {m.name for m in one_finger.messages if m.name.endswith("_2")} == set()


def test_four_fingers_of_four_joints_on_can_fd_are_refused_with_the_figures(tmp_path: Path) -> None:
    """The issue's 4 x 4 hand on CAN-FD 1/5 Mbit/s at 1 kHz, worked out from the frame sizes:
    per node a 12-byte TorqueCommand (2 + 8 bytes padded) and a 20-byte Feedback (4 + 16) each
    tick, a 12-byte Status and a 7-byte Heartbeat every 100 ms."""
    path = shaped_hand(tmp_path, [4, 4, 4, 4])
    hand = load_hand(path)
    protocol = protocol_for(hand)

    def fd_s(n_bytes: int, data_rate: float = 5e6) -> float:
        nominal, data = fd_frame_bits(n_bytes)
        return nominal / 1e6 + data / data_rate

    per_node = 1000 * (fd_s(12) + fd_s(20)) + 10 * (fd_s(12) + fd_s(7))
    budget = hand_budget(hand, protocol)
    assert budget.load == pytest.approx(4 * per_node)
    assert not budget.ok and round(budget.load * 100, 1) == 59.0
    two = hand_budget(hand, protocol, nodes={1, 2})
    assert two.load == pytest.approx(2 * per_node)
    result = handctl("check", str(path))
    assert result.returncode == 2
    assert (
        f"{path}: bus: expected a worst-case load <= 50 % ("
        f"the highest loop rate that fits is {math.floor(budget.highest_loop_rate_hz())} Hz; "
        "a data phase of 8 Mbit/s would carry "
        f"{hand_budget(hand, protocol, data_bitrate=8_000_000).load * 100:.1f} %), "
        "found 59.0 % at 1000 Hz"
    ) in result.stderr


def test_a_hand_within_the_budget_passes_check(tmp_path: Path) -> None:
    path = shaped_hand(tmp_path, [2, 2])
    result = handctl("check", str(path))
    assert result.returncode == 0, result.stderr
    assert result.stdout.splitlines()[-1] == "ok"
    assert "TorqueCommand_2   0x102     6" in result.stdout  # 2 + 2 x 2 bytes
    assert "Feedback_2        0x182    12" in result.stdout  # 2 + 4 x 2 + 2 bytes


def test_feedback_is_budgeted_at_the_nodes_tick_whatever_the_loop_rate(tmp_path: Path) -> None:
    """A node sends Feedback every 1 ms (PROTOCOL.md), at any loop rate: a 300 Hz hand's
    budget counted it at 300 Hz, a third of what the wire carried, and passed hands the bus
    cannot hold. Only the host's TorqueCommand follows the loop, so only it scales in the
    highest loop rate that fits."""

    def slow(doc: dict[str, object]) -> None:
        bus = doc["bus"]
        assert isinstance(bus, dict)
        bus["loop_rate_hz"] = 300
        doc["safety"] = {"max_consecutive_misses": 1}  # the most a 300 Hz loop may allow

    hand = load_hand(shaped_hand(tmp_path, [1] * 15, edit=slow))
    budget = hand_budget(hand, protocol_for(hand))
    rates = {m.name: m.rate_hz for m in budget.messages}
    assert rates["Feedback_15"] == 1000.0 and rates["TorqueCommand_15"] == 300.0
    assert [m.name for m in budget.messages if m.per_loop] == [
        f"TorqueCommand_{n}" for n in range(1, 16)
    ]
    fixed = sum(m.load for m in budget.messages if not m.per_loop)
    per_tick = sum(m.frame_time_us for m in budget.messages if m.per_loop) * 1e-6
    assert budget.highest_loop_rate_hz() == max(0.0, (MAX_LOAD - fixed) / per_tick)
    # the nodes' own traffic is over half this bus: no loop rate fits, and check says so
    assert fixed > MAX_LOAD and budget.highest_loop_rate_hz() == 0.0
    result = handctl("check", str(hand.source))
    assert result.returncode == 2
    assert "no loop rate of 250 Hz or more fits on one bus" in result.stderr


def test_the_highest_loop_rate_hint_names_the_misses_that_rate_allows(tmp_path: Path) -> None:
    """Six fingers of two joints fit at 333 Hz at most: a loop that slow may allow only one
    missed tick before the nodes' watchdog (``most_misses_before_watchdog``), and the hint
    that led to a config check then refused for its default three says so."""
    path = shaped_hand(tmp_path, [2] * 6)
    hand = load_hand(path)
    highest = hand_budget(hand, protocol_for(hand)).highest_loop_rate_hz()
    assert 250 < highest < 375
    result = handctl("check", str(path))
    assert result.returncode == 2
    assert (
        f"the highest loop rate that fits is {math.floor(highest)} Hz (with "
        "safety.max_consecutive_misses at most 1)"
    ) in result.stderr


def test_a_slow_arbitration_phase_is_named_as_what_to_change() -> None:
    """At 125 kbit/s arbitration no data phase carries the default hand: the only hint was a
    loop rate the nodes' watchdog refuses. It now names the arbitration rate that fits."""
    import dataclasses

    hand = load_hand(ROOT / "config" / "hands" / "hiroshima_hand.yaml")
    slow = dataclasses.replace(
        hand, bus=dataclasses.replace(hand.bus, bitrate=125_000, data_bitrate=125_000)
    )
    protocol = protocol_for(slow)
    hints = what_would_fit(slow, protocol)
    assert hints[0] == "no loop rate of 250 Hz or more fits on one bus"
    fit = hand_budget(slow, protocol, bitrate=1_000_000, data_bitrate=4_000_000)
    assert fit.ok and not hand_budget(slow, protocol, bitrate=500_000, data_bitrate=10_000_000).ok
    assert hints[1:] == [
        "an arbitration phase of 1 Mbit/s and a data phase of 4 Mbit/s would carry "
        f"{fit.load * 100:.1f} %"
    ]


@pytest.mark.parametrize(
    ("name", "attribute", "value"),
    [
        ("Feedback_1", "HandctlSend", "0"),  # an event: counted as never sent
        ("Feedback_1", "GenMsgCycleTime", "1000"),  # 1 Hz
        ("TorqueCommand_1", "HandctlSend", "0"),
        ("Status_1", "GenMsgCycleTime", "0"),
    ],
)
def test_a_dbc_cannot_count_the_protocols_traffic_as_less(
    tmp_path: Path, hand: HandConfig, name: str, attribute: str, value: str
) -> None:
    """The host sends its commands every tick and a node its reports at the protocol's
    rates, whatever a DBC's attributes say: a DBC that called the Feedback an event, or its
    cycle 1 s, had the budget count the hand at a fraction of its load, and ``check`` passed
    a hand over the 50 % limit (found by an outside audit). A DBC may count more, not less."""
    protocol = protocol_for(hand)
    text = generate_dbc((f.node_id, len(f.joints)) for f in hand.fingers)
    frame_id = protocol.by_name[name].frame_id
    line = next(
        line for line in text.splitlines() if line.startswith(f'BA_ "{attribute}" BO_ {frame_id} ')
    )
    edited = tmp_path / "edited.dbc"
    edited.write_text(text.replace(line, f'BA_ "{attribute}" BO_ {frame_id} {value};'))
    before = hand_budget(hand, protocol)
    after = hand_budget(hand, load_protocol(edited))
    assert {m.name: m.rate_hz for m in after.messages} == {
        m.name: m.rate_hz for m in before.messages
    }
    assert after.load == before.load
    assert after.highest_loop_rate_hz() == before.highest_loop_rate_hz()


def test_a_classic_hand_is_told_the_can_fd_data_phase_that_fits(tmp_path: Path) -> None:
    """Five one-joint nodes at 1 kHz on classic CAN: CAN-FD 1/5 Mbit/s would carry them at
    over 50 %, and that was the hint, a config check refuses too; the data phase that fits is
    8 Mbit/s (found by an outside audit). The hint names a rate whose budget passes."""

    def classic(doc: dict[str, object]) -> None:
        bus = doc["bus"]
        assert isinstance(bus, dict)
        bus["fd"] = False
        bus.pop("data_bitrate", None)

    hand = load_hand(shaped_hand(tmp_path, [1] * 5, edit=classic))
    protocol = protocol_for(hand)
    assert not hand_budget(hand, protocol, fd=True, bitrate=1_000_000, data_bitrate=5_000_000).ok
    [hint] = what_would_fit(hand, protocol)
    fits = hand_budget(hand, protocol, fd=True, bitrate=1_000_000, data_bitrate=8_000_000)
    assert fits.ok
    assert hint == f"CAN-FD 1/8 Mbit/s would carry {fits.load * 100:.1f} %"
