"""Programs on the same computer as the host, on SocketCAN: the simulated hand (``handctl sim
--bus socketcan:vcan0``), a second master, an e-stop sent with ``cansend``. The kernel marks
each of their frames as sent from this computer, which python-can's socketcan backend says as
``is_rx`` False; the host took every such frame for the echo of its own and dropped it (found
by an outside audit). Both the host and the simulated hand are on a double of python-can's
SocketCAN bus in its marking only (``tests/local_socketcan.py``): this machine has no SocketCAN,
and no real peer marks frames as the kernel does."""

from __future__ import annotations

import itertools
from collections.abc import Iterator
from contextlib import contextmanager

from handctl.config import HandConfig
from handctl.hand_protocol import protocol_for
from handctl.online.bus import HandBus, open_bus
from handctl.online.busspec import BusSpec
from handctl.online.clock import LockstepClock
from handctl.online.drivers.hand import HandDriver
from handctl.online.loop import Outcome, Runtime
from handctl.online.recipes.schema import Recipe
from handctl.online.safety.faults import FaultCode
from handctl.protocol import NodeState
from handctl.sim.firmware import FaultBits
from handctl.sim.hand import SimulatedHand

from ..local_socketcan import LocalSocketcanBus
from .rig import Rig, stopped_at_once
from .test_hostile_peer import INJECT_AT, INJECT_TICK, Every, frame, hold, third_peer

__all__ = ["hold"]  # the recipe fixture, shared with the hostile peer's tests

_channels = itertools.count()


@contextmanager
def on_one_vcan(hand: HandConfig, recipe: Recipe) -> Iterator[Rig]:
    """The runtime and the simulated hand, each a program on the same computer's vcan, in
    lockstep; and a sniffer, as the rig has (it hears every frame, as an analyser would)."""
    channel = f"local-vcan-{next(_channels)}"
    spec = BusSpec("socketcan", "vcan0")
    with (
        HandBus(LocalSocketcanBus(channel), spec, hand.bus.fd) as peer,
        HandBus(LocalSocketcanBus(channel), spec, hand.bus.fd) as host,
        open_bus(f"virtual:{channel}", hand.bus) as sniffer,
    ):
        sim = SimulatedHand(hand, peer, seed=0)
        clock = LockstepClock(hand.bus.period_s, sim.step)
        driver = HandDriver(hand, protocol_for(hand), host, clock_ns=clock.now_ns)
        yield Rig(hand, sim, Runtime(hand, driver, clock, recipe, max_ticks=30_000), sniffer)


def test_a_second_master_on_the_same_computer_is_stopped_at_once(
    hand: HandConfig, hold: Recipe
) -> None:
    """The host hears the simulated hand on the vcan (the run starts and torque flows) and a
    third program's TorqueCommand_1 frames, a counter ahead of its own: ``FOREIGN_COMMAND``
    in the tick it came, as from a second master on another computer."""
    layout = protocol_for(hand).layout("TorqueCommand", 1)
    with on_one_vcan(hand, hold) as r, third_peer(r) as peer:
        host_node = r.runtime.driver.nodes[0]
        forged: list[tuple[int, bytes]] = []

        def second_master() -> None:
            data = layout.encode(host_node.command_counter, [3.0, 3.0, 3.0])
            peer.send(frame(layout.frame_id, data))
            forged.append((layout.frame_id, data))

        r.sim.faults.add(Every(send=second_master), INJECT_AT)
        result = r.run()
        for sent in forged:  # the sniffer heard them too: the host's frames are judged
            r.wire.remove(sent)
        assert stopped_at_once(r, result, FaultCode.FOREIGN_COMMAND) == INJECT_TICK
        assert "TorqueCommand id 0x101" in result.faults[0].detail


def test_an_estop_sent_from_the_same_computer_is_heard(hand: HandConfig, hold: Recipe) -> None:
    """An EStop on 0x000 from a third program on the computer (``cansend vcan0 000#...``):
    the simulated hand on the vcan latches it, and the host hears the frame and stops on
    the nodes' e-stop (``ESTOP``)."""
    estop = protocol_for(hand).layout("EStop")
    with on_one_vcan(hand, hold) as r, third_peer(r) as peer:
        sent: list[bool] = []

        def operator() -> None:
            if not sent:
                peer.send(frame(estop.frame_id, estop.encode(0, (1,))))
                sent.append(True)

        r.sim.faults.add(Every(send=operator), INJECT_AT)
        result = r.run()
        assert result.outcome is Outcome.SAFETY_STOP, result.message
        assert result.faults[0].code is FaultCode.ESTOP, [str(f) for f in result.faults]
        assert [n.state for n in r.sim.nodes] == [int(NodeState.FAULT)] * 3
        assert all(n.fault_bits & int(FaultBits.ESTOP) for n in r.sim.nodes)
        assert r.runtime.driver.unexpected_ids.get(estop.frame_id) == 1
