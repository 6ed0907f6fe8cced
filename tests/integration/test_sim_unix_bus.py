"""The simulated hand with a babbling node, on the unix datagram bus the real-time runs use.

The loop benchmark (``tools/bench.py loop --rt --babble 20``) runs the host and the simulated
hand in two processes on two 1 kHz timers; now and then the hand ticks more than once between
two reads of the host (a late timer, a catch-up of up to ``MAX_CATCH_UP`` ticks). With 20
foreign frames a tick, none of the hand's own frames may be lost for that. Here the hand is
stepped in lockstep and the host reads only every few ticks, so no wall clock is involved.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Iterator
from pathlib import Path

import pytest

from handctl.config import HandConfig
from handctl.online.bus import HandBus, open_bus
from handctl.protocol import Protocol
from handctl.sim.faults import Babble
from handctl.sim.hand import MAX_CATCH_UP, SimulatedHand

PER_TICK = 20
TICKS = 60


@pytest.fixture
def on_unix_bus(hand: HandConfig, tmp_path: Path) -> Iterator[tuple[SimulatedHand, HandBus]]:
    host = open_bus(f"unix:{tmp_path / 'bus'}", hand.bus)
    peer = open_bus(f"unix:{tmp_path / 'bus'}", hand.bus)
    try:
        yield SimulatedHand(hand, peer, seed=0), host
    finally:
        peer.close()
        host.close()


@pytest.mark.parametrize("ticks_per_read", [1, 2, MAX_CATCH_UP])
def test_no_frame_of_the_hand_is_lost_to_a_babbling_node(
    on_unix_bus: tuple[SimulatedHand, HandBus], protocol: Protocol, ticks_per_read: int
) -> None:
    sim, host = on_unix_bus
    babble = Babble(id=0x050, per_tick=PER_TICK, length=8)
    sim.activate(babble)
    heard: Counter[int] = Counter()
    for _ in range(TICKS // ticks_per_read):
        for _ in range(ticks_per_read):
            sim.step()
        heard.update(f.arbitration_id for f in host.drain())
    feedback = [protocol.layout("Feedback", f.node_id).frame_id for f in sim.hand.fingers]
    assert [heard[i] for i in feedback] == [TICKS] * len(feedback)
    assert heard[0x050] == babble.sent == PER_TICK * TICKS
    assert sim.tx_failed == 0
    # every tick's frames, the babble's with the nodes', left as one datagram
    counts = sim.ground_truth_summary()["transport"]
    assert counts == {
        "datagrams_sent": TICKS,
        "queue_full": 0,
        "frames_dropped": 0,
        "frames_held": 0,
        "rx_frames_lost": 0,
        "rx_malformed": 0,
    }
