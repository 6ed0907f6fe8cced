"""The bus a bring-up command works on: a named bus, or for ``sim`` a simulated hand.

``nodes`` and ``monitor`` only listen, so on ``sim`` something must be talking: a simulated hand
is started in this process, free-running on its own 1 kHz timer on a private virtual channel,
as an independent peer like the real hand, and the command listens on that channel. Like
``session``, this is composition: the online plane itself never imports the simulation.
"""

from __future__ import annotations

import itertools
import os
from collections.abc import Iterator
from contextlib import ExitStack, contextmanager

from handctl.config import HandConfig
from handctl.online.bus import HandBus, open_bus
from handctl.online.busspec import BusSpec, parse_spec, require_peers

_channels = itertools.count()


@contextmanager
def listening_bus(spec_text: str, hand: HandConfig, *, waits: bool = False) -> Iterator[HandBus]:
    """Open ``spec_text`` to listen on; ``sim`` starts a simulated hand to listen to.
    ``waits``: the listener stays until a hand comes (``monitor``), and may be the first on a
    unix bus, which it then makes; a survey (``nodes``) is refused a bus nobody is on."""
    spec = parse_spec(spec_text, hand.bus, hand.source)
    with ExitStack() as stack:
        if spec.interface == "sim":
            from handctl.sim.hand import SimulatedHand

            spec = BusSpec("virtual", f"handctl-bringup-{os.getpid()}-{next(_channels)}")
            peer_bus = stack.enter_context(open_bus(spec, hand.bus))
            sim = SimulatedHand(hand, peer_bus)
            bus = stack.enter_context(open_bus(spec, hand.bus))
            sim.start()
            stack.callback(sim.stop)
        else:
            if not waits:
                require_peers(spec)
            bus = stack.enter_context(open_bus(spec, hand.bus))
        yield bus
