"""A bus that hands a process back the frames it sent (python-can's udp_multicast keeps
multicast loopback on, and ``receive_own_messages=False`` does not change it): the host took
its own enable for a second host's command (FOREIGN_COMMAND) on every run, and the simulated
hand counted its own frames as received. The echoes are taken out; other senders' frames are
not, a lost echo is passed over."""

from __future__ import annotations

import random
import time

import pytest

from handctl.config import HandConfig
from handctl.errors import BusError
from handctl.online.bus import ECHO_LOOKAHEAD, HandBus, _EchoFilter, open_bus


def test_echoes_are_matched_in_order_and_a_lost_one_is_passed_over() -> None:
    echoes = _EchoFilter()
    for k in range(5):
        echoes.sent(0x101, bytes([k]) * 8)
    assert echoes.is_echo(0x101, bytes([0]) * 8)
    assert not echoes.is_echo(0x101, bytes([9]) * 8)  # another sender's
    assert not echoes.is_echo(0x102, bytes([1]) * 8)  # another id
    # echo 1 lost on the way: 2 is found, and 1 is no longer awaited
    assert echoes.is_echo(0x101, bytes([2]) * 8)
    assert not echoes.is_echo(0x101, bytes([1]) * 8)
    assert echoes.is_echo(0x101, bytes([3]) * 8) and echoes.is_echo(0x101, bytes([4]) * 8)
    assert not echoes.is_echo(0x101, bytes([4]) * 8)  # each echo once


def test_a_frame_beyond_the_lookahead_is_not_taken_for_an_echo() -> None:
    echoes = _EchoFilter()
    for k in range(ECHO_LOOKAHEAD + 1):
        echoes.sent(0x101, k.to_bytes(8, "little"))
    assert not echoes.is_echo(0x101, ECHO_LOOKAHEAD.to_bytes(8, "little"))
    assert echoes.is_echo(0x101, (ECHO_LOOKAHEAD - 1).to_bytes(8, "little"))


def _udp_pair(hand: HandConfig) -> tuple[HandBus, HandBus]:
    group = f"239.74.{random.randrange(1, 255)}.{random.randrange(1, 255)}"
    port = random.randrange(40000, 50000)
    options = {"port": port}
    try:
        first = open_bus(f"udp_multicast:{group}", hand.bus, options)
    except BusError as exc:  # no multicast route on this host: nothing to measure
        pytest.skip(f"no udp_multicast bus here: {exc}")
    return first, open_bus(f"udp_multicast:{group}", hand.bus, options)


def test_on_udp_multicast_a_process_hears_the_others_and_not_itself(hand: HandConfig) -> None:
    host, node = _udp_pair(hand)
    try:
        for k in range(5):
            assert host.send(0x101, bytes([k]) * 16)
        assert node.send(0x181, bytes(16))
        heard_host: list[tuple[int, bytes]] = []
        heard_node: list[tuple[int, bytes]] = []
        deadline = time.monotonic() + 5.0
        while (len(heard_host) < 1 or len(heard_node) < 5) and time.monotonic() < deadline:
            heard_host += [(f.arbitration_id, f.data) for f in host.drain()]
            heard_node += [(f.arbitration_id, f.data) for f in node.drain()]
            time.sleep(0.01)
        time.sleep(0.05)  # anything more would have come by now
        heard_host += [(f.arbitration_id, f.data) for f in host.drain()]
        heard_node += [(f.arbitration_id, f.data) for f in node.drain()]
    finally:
        host.close()
        node.close()
    assert heard_host == [(0x181, bytes(16))]
    assert heard_node == [(0x101, bytes([k]) * 16) for k in range(5)]
