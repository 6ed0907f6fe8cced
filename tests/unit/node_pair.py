"""A finger's emulated node and the host's ``FingerNode`` for it, talking in lockstep.

The frames are the real ones: the host's command frames go to the simulated node's firmware,
and every frame the node publishes goes through ``FingerNode.receive``, CRC and counter checks
included. There is no bus in between, so a test decides exactly at which nanosecond each frame
arrives and which frames are lost, and a safety check is seen at the tick where it must bite.
"""

from __future__ import annotations

from collections.abc import Collection, Sequence

from handctl.config import HandConfig
from handctl.online.drivers.finger import FingerLayouts, FingerNode
from handctl.online.drivers.receiver import Reject
from handctl.protocol import Protocol
from handctl.sim.firmware import EmulatedNode
from handctl.sim.params import NODE_TICK_NS, parse_sim

MS = 1_000_000  # ns


class NodePair:
    """One finger: the node's firmware on one side, the host's view of it on the other."""

    def __init__(self, hand: HandConfig, protocol: Protocol, finger: int, now_ns: int = 0) -> None:
        config = hand.fingers[finger]
        params = parse_sim(hand)
        self.node = EmulatedNode(
            config,
            protocol,
            tdt_range=params.tdt.range,
            encoder_max_step=params.encoder.max_step,
            now_ns=now_ns,
        )
        self.host = FingerNode(config, FingerLayouts.for_node(protocol, config.node_id))
        self.protocol = protocol
        self.n = len(config.joints)
        self.rejects: list[Reject] = []

    def command(self, name: str, now_ns: int) -> None:
        """The host sends a NodeCommand (enable, disable, fault_reset) and the node takes it."""
        self.node.receive(*self.host.next_node_command(name), now_ns)

    def estop(self, now_ns: int) -> None:
        """An EStop frame reaches the node (as from the host or any other sender)."""
        layout = self.protocol.layout("EStop")
        self.node.receive(layout.frame_id, layout.encode(0, (1,)), now_ns)

    def tick(
        self,
        now_ns: int,
        torques: Sequence[float] | None = None,
        tdt: Sequence[float] | None = None,
        angles: Sequence[float] | None = None,
        lose: Collection[int] = (),
    ) -> None:
        """One 1 ms tick: the host's torque command in, the node's frames out to the host,
        except those whose id is in ``lose``: they are lost on the way."""
        self.node.receive(*self.host.next_command(torques or [0.0] * self.n), now_ns)
        self.node.update(now_ns)
        out: list[tuple[int, bytes]] = []
        self.node.publish(now_ns, list(tdt or [0.0] * self.n), list(angles or [0.0] * self.n), out)
        for frame_id, data in out:
            if frame_id not in lose:
                reason = self.host.receive(frame_id, data, now_ns)
                if reason is not None:
                    self.rejects.append(reason)


class Link:
    """Every finger of a hand as node pairs, on one clock of whole node ticks."""

    def __init__(self, hand: HandConfig, protocol: Protocol) -> None:
        self.pairs = [NodePair(hand, protocol, i) for i in range(len(hand.fingers))]
        self.now_ns = 0

    @property
    def hosts(self) -> list[FingerNode]:
        return [pair.host for pair in self.pairs]

    def tick(self, lose: Collection[int] = ()) -> int:
        """Advance every pair one node tick; returns the time of that tick (ns)."""
        now = self.now_ns
        for pair in self.pairs:
            pair.tick(now, lose=lose)
        self.now_ns += NODE_TICK_NS
        return now

    def enable(self) -> int:
        """Boot, enable every node and run until the host has heard ENABLED from each."""
        self.tick()
        for pair in self.pairs:
            pair.command("enable", self.now_ns)
        return self.tick()
