"""Hypothesis: the hot-path codec agrees with cantools (the oracle) on every message, and the
host's receiver survives any frame, counting each one as accepted or rejected."""

from __future__ import annotations

import itertools
import os

from hypothesis import HealthCheck, given, settings

from handctl.config import HandConfig
from handctl.online.bus import open_bus
from handctl.online.drivers.hand import HandDriver
from handctl.protocol import Layout

from ..dbc import DB, decode
from ..strategies import PROTOCOL, frame_batches, message_and_values

#: The benchmark run sets this high (>= 100 000 frames); CI keeps it small.
FUZZ_EXAMPLES = int(os.environ.get("HANDCTL_FUZZ_EXAMPLES", "2000"))
_channels = itertools.count()


@settings(max_examples=400, deadline=None)
@given(message_and_values())
def test_encode_matches_cantools(case: tuple[Layout, int, tuple[float, ...]]) -> None:
    layout, counter, values = case
    ours = layout.encode(counter, values)
    signals = dict(zip(layout.signal_names, values, strict=True))
    signals.update(Crc=ours[0], Counter=counter)
    theirs = DB.encode_message(layout.frame_id, signals, strict=True)
    assert ours == theirs


@settings(max_examples=400, deadline=None)
@given(message_and_values())
def test_decode_matches_cantools(case: tuple[Layout, int, tuple[float, ...]]) -> None:
    layout, counter, values = case
    data = layout.encode(counter, values)
    got_counter, got = layout.decode(data)
    theirs = decode(layout.frame_id, data, choices=False)
    assert got_counter == theirs["Counter"] == counter
    assert list(got) == [theirs[name] for name in layout.signal_names]
    assert layout.crc_ok(data)


@settings(max_examples=200, deadline=None)
@given(message_and_values())
def test_round_trip_within_half_a_step(case: tuple[Layout, int, tuple[float, ...]]) -> None:
    layout, counter, values = case
    _, got = layout.decode(layout.encode(counter, values))
    for value, back, sig in zip(values, got, layout.signals, strict=True):
        assert abs(back - value) <= sig.scale / 2 + 1e-12


# -- decoder fuzz (tools/bench.py fuzz draws from the same strategies, 100 000 frames) ----
@settings(
    max_examples=max(1, FUZZ_EXAMPLES // 20),
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)
@given(frame_batches())
def test_decoder_fuzz_every_frame_accepted_or_rejected(
    hand: HandConfig, frames: list[tuple[int, bytes]]
) -> None:
    name = f"fuzz-{next(_channels)}"
    with (
        open_bus(f"virtual:{name}", hand.bus) as host_bus,
        open_bus(f"virtual:{name}", hand.bus) as peer,
    ):
        driver = HandDriver(hand, PROTOCOL, host_bus)
        for frame_id, data in frames:
            assert peer.send(frame_id, data)
        state = driver.poll()
        rejected = sum(driver.reject_counts().values())
        accepted = sum(node.accepted for node in driver.nodes)
        assert accepted + rejected == len(frames)
        assert all(abs(a) <= 3.2768 for a in state.angle)
