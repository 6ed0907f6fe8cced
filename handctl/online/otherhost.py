"""Listening for another host before this one sends anything onto a hand's bus.

Why: two hosts commanding the same nodes fight tick by tick, and neither's limits hold for the
sum (the nodes take whichever torque came last). A run listened for one before its timing
check and its first frame; a ``replay --to-bus`` onto a hand a run was driving sent its
frames beside that run's. Both now listen the same way, here, and refuse with nothing sent.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence

from handctl.config import HandConfig
from handctl.errors import BusError
from handctl.online.bus import Frame, HandBus

#: s, the least a host listens for another host's commands before anything else: a host
#: sends a TorqueCommand every tick, a listener (``monitor``) none. Three of a unix bus
#: sender's re-listings of its participants (``unixcan.PEERS_EVERY_S``): a listener there
#: is sent to only once the other host has listed it, and 20 ms missed one run in two
LISTEN_FOR_HOST_S = 0.15


def refuse_another_host(
    bus: HandBus,
    hand: HandConfig,
    spec: str,
    who: str,
    seen: Callable[[Sequence[Frame]], None] | None = None,
) -> None:
    """``BusError`` when a frame on one of ``hand``'s command identifiers is heard on ``bus``
    (``spec``) within ``LISTEN_FOR_HOST_S`` (or ten periods, if longer): another host (a run,
    a jog, a replay onto the bus) is commanding the nodes, and ``who`` ("this run", "this
    replay"), which has sent nothing yet, must not start beside it. ``seen`` is given every
    frame heard (what the nodes say of themselves meanwhile)."""
    commands = {}
    for finger in hand.fingers:
        commands[finger.can_ids.torque_command] = ("TorqueCommand", finger)
        commands[finger.can_ids.node_command] = ("NodeCommand", finger)
    end = time.monotonic() + max(LISTEN_FOR_HOST_S, 10 * hand.bus.period_s)
    while True:
        frames = bus.drain()
        if seen is not None:
            seen(frames)
        for frame in frames:
            heard = commands.get(frame.arbitration_id)
            if heard is not None:
                name, finger = heard
                raise BusError(
                    f"another host is commanding this hand on {spec}: a {name} to "
                    f"node {finger.node_id} ({finger.name}), id "
                    f"0x{frame.arbitration_id:03X}, heard before {who} sent anything. "
                    "Stop the other run, jog or replay first (nothing was sent)"
                )
        if time.monotonic() >= end:
            return
        time.sleep(hand.bus.period_s / 2)
