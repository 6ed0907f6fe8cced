"""The host end the simulated-hand tests talk through: real frames on python-can's virtual bus.

Not a driver: it builds frames with the DBC's layouts, keeps one counter per message as a sender
must, and records everything it hears, tick by tick, so a test can check what went over the bus.
Decoding for assertions goes through cantools on the DBC, independently of ``handctl.protocol``.
(This module holds no tests; it shares the helper between the simulated hand's test files.)
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any

from handctl.config import HandConfig
from handctl.online.bus import BusEvent, Frame, HandBus, open_bus
from handctl.protocol import NODE_COMMANDS, Protocol, load_protocol
from handctl.sim.hand import SimulatedHand

from ..dbc import DB, decode


def crc8_autosar(data: bytes) -> int:
    """CRC-8/AUTOSAR bit by bit, written apart from handctl's table version on purpose."""
    crc = 0xFF
    for byte in data:
        crc ^= byte
        for _ in range(8):
            crc = ((crc << 1) ^ 0x2F) & 0xFF if crc & 0x80 else (crc << 1) & 0xFF
    return crc ^ 0xFF


def crc_ok(frame: Frame) -> bool:
    message = DB.get_message_by_frame_id(frame.arbitration_id)
    assert message.dbc is not None
    data_id = int(message.dbc.attributes["DataID"].value)
    return crc8_autosar(bytes((data_id & 0xFF, data_id >> 8)) + frame.data[1:]) == frame.data[0]


@dataclass(frozen=True)
class Heard:
    tick: int  # the simulated hand's tick after which the host drained the frame
    frame: Frame

    @property
    def id(self) -> int:
        return self.frame.arbitration_id

    def signals(self) -> dict[str, Any]:
        return decode(self.id, self.frame.data, choices=False)


class SimHost:
    def __init__(
        self, hand: HandConfig, bus: HandBus, sim: SimulatedHand, protocol: Protocol | None = None
    ) -> None:
        self.hand = hand
        self.bus = bus
        self.sim = sim
        self.protocol = protocol or load_protocol()
        self.counters: dict[int, int] = {}
        self.heard: list[Heard] = []
        self.events: list[BusEvent] = []

    # -- sending ----------------------------------------------------------------------------
    def send(self, kind: str, node: int | None, values: Sequence[float]) -> None:
        layout = self.protocol.layout(kind, node)
        counter = self.counters.get(layout.frame_id, 0)
        self.counters[layout.frame_id] = (counter + 1) & 0xFF
        assert self.bus.send(layout.frame_id, layout.encode(counter, values))

    def command(self, name: str, nodes: Sequence[int] | None = None) -> None:
        for node in nodes or [f.node_id for f in self.hand.fingers]:
            self.send("NodeCommand", node, (NODE_COMMANDS[name],))

    def torques(self, tau: Sequence[float]) -> None:
        """Nine torques (N·m) in config order, one TorqueCommand per finger."""
        offset = 0
        for finger in self.hand.fingers:
            n = len(finger.joints)
            values = list(tau[offset : offset + n]) + [0.0] * (3 - n)
            self.send("TorqueCommand", finger.node_id, values)
            offset += n

    # -- running ----------------------------------------------------------------------------
    def tick(self, tau: Sequence[float] | None = None) -> list[Heard]:
        """Send commands (if any), step the simulated hand once, drain what it sent."""
        if tau is not None:
            self.torques(tau)
        self.sim.step()
        return self.poll()

    def poll(self) -> list[Heard]:
        tick = self.sim.ticks
        heard = [Heard(tick, f) for f in self.bus.drain()]
        self.heard += heard
        self.events += self.bus.events()
        return heard

    def run(self, ticks: int, tau: Sequence[float] | None = None) -> list[Heard]:
        out: list[Heard] = []
        for _ in range(ticks):
            out += self.tick(tau)
        return out

    # -- reading ----------------------------------------------------------------------------
    def of(self, kind: str, node: int, heard: Sequence[Heard] | None = None) -> list[Heard]:
        frame_id = self.protocol.layout(kind, node).frame_id
        return [h for h in (self.heard if heard is None else heard) if h.id == frame_id]

    def last(self, kind: str, node: int) -> dict[str, Any]:
        return self.of(kind, node)[-1].signals()


@contextmanager
def sim_and_host(
    hand: HandConfig, channel: str, seed: int | None = None, **kwargs: Any
) -> Iterator[tuple[SimulatedHand, SimHost]]:
    """A simulated hand and a host on a fresh virtual channel, closed afterwards."""
    host_bus = open_bus(f"virtual:{channel}", hand.bus)
    peer_bus = open_bus(f"virtual:{channel}", hand.bus)
    try:
        sim = SimulatedHand(hand, peer_bus, seed=seed, **kwargs)
        yield sim, SimHost(hand, host_bus, sim)
    finally:
        host_bus.close()
        peer_bus.close()


def enable_all(host: SimHost) -> None:
    """Enable every node and hold it with zero torque until each reports ENABLED."""
    host.command("enable")
    host.run(2, [0.0] * host.hand.n_joints)
    for finger in host.hand.fingers:
        assert host.last("Feedback", finger.node_id)["State"] == 1, host.sim.status_line()
