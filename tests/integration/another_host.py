"""Another host on the bus: a thread that sends one command frame every tick, for the tests
that a run or a replay refuses to start beside it."""

from __future__ import annotations

import threading
from collections.abc import Iterator
from contextlib import contextmanager

from handctl.config import HandConfig
from handctl.online.bus import open_bus
from handctl.protocol import Layout


@contextmanager
def commanding(spec: str, hand: HandConfig, layout: Layout, values: list[float]) -> Iterator[None]:
    """``layout``'s frame with ``values`` sent on ``spec`` every millisecond while the block
    runs; on leaving it, a listener that was on the bus all along has heard that frame and
    nothing else (the refused tool sent nothing)."""
    other = open_bus(spec, hand.bus)
    sniffer = open_bus(spec, hand.bus)
    stop = threading.Event()

    def other_host() -> None:
        while not stop.wait(0.001):
            other.send(layout.frame_id, layout.encode(0, values))

    sender = threading.Thread(target=other_host, daemon=True)
    sender.start()
    try:
        yield
    finally:
        stop.set()
        sender.join()
    heard = sniffer.drain(limit=10**6)
    other.close()
    sniffer.close()
    assert heard and {f.arbitration_id for f in heard} == {layout.frame_id}  # the other's only
