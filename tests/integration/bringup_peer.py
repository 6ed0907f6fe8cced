"""A simulated hand free-running on a bus in the test process, for the listening commands."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from contextlib import contextmanager

from handctl.config import HandConfig
from handctl.online.bus import open_bus
from handctl.sim.hand import SimulatedHand
from handctl.sim.params import SimParams

#: Ids only a host sends: e-stop, node commands, torque commands.
HOST_IDS = frozenset({0x000, 0x011, 0x012, 0x013, 0x101, 0x102, 0x103})


@contextmanager
def running_hand(
    hand: HandConfig,
    spec: str,
    prepare: Callable[[SimulatedHand], None] | None = None,
    params: SimParams | None = None,
) -> Iterator[SimulatedHand]:
    """The simulated hand on ``spec``, ticking on its own timer until the block ends."""
    bus = open_bus(spec, hand.bus)
    try:
        sim = SimulatedHand(hand, bus, params=params)
        if prepare is not None:
            prepare(sim)
        sim.start()
        try:
            yield sim
        finally:
            sim.stop()
    finally:
        bus.close()
