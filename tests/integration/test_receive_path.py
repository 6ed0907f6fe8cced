"""The receive path against the simulated hand in lockstep, attacked by its injectors: a flood
the bus could never carry, 29-bit twins of the nodes' frames, nodes that contradict
themselves, and a replayed stream. Each is caught (or, for the twins, harmless), and the wire
carries zero within two ticks of detection."""

from __future__ import annotations

import pytest

from handctl.config import HandConfig
from handctl.online.bus import EXTENDED_ID_FLAG, open_bus
from handctl.online.loop import Outcome
from handctl.online.recipes.loader import load_recipe
from handctl.online.recipes.schema import Recipe
from handctl.online.safety.faults import FaultCode
from handctl.sim import faults as inj
from handctl.sim.hand import SimulatedHand

from .rig import CLOSE_AND_HOLD_2S, rig, stopped_at_once

INJECT_AT = 1.0  # s of simulated time: inside the hold phase
INJECT_TICK = round(INJECT_AT / 0.001)


@pytest.fixture(scope="module")
def hold(hand: HandConfig, tmp_path_factory: pytest.TempPathFactory) -> Recipe:
    path = tmp_path_factory.mktemp("recipes") / "hold.yaml"
    path.write_text(CLOSE_AND_HOLD_2S)
    return load_recipe(path, hand)


def test_a_flood_the_bus_cannot_carry_is_stopped_at_once(hand: HandConfig, hold: Recipe) -> None:
    """1000 foreign frames a tick (a CAN-FD bus carries 27): before, the host drained 512 a
    tick and judged ever older feedback as fresh."""
    with rig(hand, hold) as r:
        r.sim.faults.add(inj.Babble(id=0x050, per_tick=1000, length=8), INJECT_AT)
        result = r.run()
        tick = stopped_at_once(r, result, FaultCode.RX_BACKLOG)
        assert INJECT_TICK - 1 <= tick <= INJECT_TICK + 2


def test_feedback_held_back_is_as_old_as_it_is(hand: HandConfig, hold: Recipe) -> None:
    """Second line of defence: with the backlog check taken out (the drain takes 500 frames a
    tick and its reports are thrown away), the nodes' frames wait ever longer behind the
    flood, and their age, counted from arrival, passes the feedback limit within ticks."""
    with rig(hand, hold) as r:
        driver = r.runtime.driver
        driver.frames_per_period = 250
        driver.take_bus_events = lambda: []  # type: ignore[method-assign]
        r.sim.faults.add(inj.Babble(id=0x050, per_tick=1000, length=8), INJECT_AT)
        result = r.run()
        tick = stopped_at_once(r, result, FaultCode.FEEDBACK_TIMEOUT)
        assert tick - INJECT_TICK <= 12


def test_extended_id_twins_change_nothing_and_are_counted(hand: HandConfig, hold: Recipe) -> None:
    with rig(hand, hold) as r:
        twin = inj.ExtendedTwin(message="all")
        r.sim.faults.add(twin, 0.0)
        result = r.run()
        assert result.outcome is Outcome.COMPLETED, result.message
        assert result.node_rejects["extended_id"] == twin.sent > 1000
        assert sum(v for k, v in result.node_rejects.items() if k != "extended_id") == 0
        # The nodes did not take the host's frames' twins either: nothing reached them twice.
        assert all(n.reject_counter == 0 for n in r.sim.nodes)


def test_the_nodes_do_not_take_an_extended_id_estop(hand: HandConfig, channel: str) -> None:
    with (
        open_bus(f"virtual:{channel}", hand.bus) as host,
        open_bus(f"virtual:{channel}", hand.bus) as peer,
    ):
        sim = SimulatedHand(hand, peer)
        sim.step()
        assert host.send(EXTENDED_ID_FLAG | 0x000, bytes(3))
        assert host.send(EXTENDED_ID_FLAG | 0x011, bytes(3))
        sim.step()
        assert [n.state for n in sim.nodes] == [0, 0, 0]
        assert [n.reject_unexpected for n in sim.nodes] == [2, 2, 2]
        assert host.send(0x000, bytes(3))  # the real e-stop, malformed: honoured
        sim.step()
        assert [n.state for n in sim.nodes] == [2, 2, 2]


def test_enabled_with_fault_bits_is_stopped(hand: HandConfig, hold: Recipe) -> None:
    with rig(hand, hold) as r:
        r.sim.faults.add(inj.Contradict(node=2, report="fault_bits", bits=0x01), INJECT_AT)
        result = r.run()
        tick = stopped_at_once(r, result, FaultCode.NODE_CONTRADICTION)
        assert INJECT_TICK - 1 <= tick <= INJECT_TICK + 2
        assert "latched fault bits (TIMEOUT)" in result.faults[0].detail


def test_a_fault_hidden_behind_an_enabled_heartbeat_is_stopped(
    hand: HandConfig, hold: Recipe
) -> None:
    """Node 3 latches FAULT (its watchdog: 15 commands lost), and after each Feedback saying
    so a Heartbeat says ENABLED in the same tick. The last report used to win. The FAULT
    stops the run at once; the first ENABLED after it may be a Heartbeat the node queued
    before the fault (CAN orders frames within an identifier only), the ones that follow it
    a node's tick later are the contradiction."""
    with rig(hand, hold) as r:
        r.sim.faults.add(inj.Contradict(node=3, report="heartbeat"), INJECT_AT - 0.2)
        r.sim.faults.add(inj.DropCommands(node=3, count=15), INJECT_AT)
        result = r.run()
        tick = stopped_at_once(r, result, FaultCode.NODE_FAULT)
        assert INJECT_TICK + 5 <= tick <= INJECT_TICK + 15  # when the node faulted
        assert "node 3 (f3) in FAULT (TIMEOUT)" in result.faults[0].detail
        (contradiction,) = [f for f in result.faults if f.code is FaultCode.NODE_CONTRADICTION]
        assert "Heartbeat says ENABLED after FAULT" in contradiction.detail
        assert tick < contradiction.tick <= tick + 2


def test_a_replayed_stream_is_stopped_by_its_reject_rate(hand: HandConfig, hold: Recipe) -> None:
    """Node 2's own feedback, replayed 0.2 s late two frames a tick: the host accepts one
    replayed frame a tick and rejects two, so the angles, torques and state it hears are
    0.2 s old. Counting rejects without bound, it noticed only when node 2 latched a FAULT of
    its own (50 ms into the replay) and said so in a Status frame; the rate stops it first."""
    with rig(hand, hold) as r:
        replay = inj.ReplayFrames(node=2, message="feedback", delay=0.2)
        r.sim.faults.add(replay, INJECT_AT)
        r.sim.faults.add(inj.DropCommands(node=2, count=15), INJECT_AT + 0.25)
        result = r.run()
        tick = stopped_at_once(r, result, FaultCode.REJECT_RATE)
        replay_starts = INJECT_TICK + 200
        limit = hand.safety.max_rejects_in_window
        assert replay_starts <= tick <= replay_starts + limit // 2 + 2
        assert "node 2" in result.faults[0].detail
