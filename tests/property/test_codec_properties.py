"""Hypothesis: the hot-path codec agrees with cantools (the oracle) on every message, and the
host's receiver survives any frame, counting each one as accepted or rejected."""

from __future__ import annotations

import itertools
import os

import cantools
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from handctl.bus import open_bus
from handctl.config import HandConfig
from handctl.drivers.hand import HandDriver
from handctl.protocol import DEFAULT_DBC, Layout, Protocol, load_protocol

PROTOCOL = load_protocol()
DB = cantools.database.load_file(str(DEFAULT_DBC))
#: The benchmark run sets this high (>= 100 000 frames); CI keeps it small.
FUZZ_EXAMPLES = int(os.environ.get("HANDCTL_FUZZ_EXAMPLES", "2000"))
_channels = itertools.count()


def raw_values(layout: Layout) -> st.SearchStrategy[tuple[int, ...]]:
    """Random raw integers inside each signal's DBC range."""
    parts = []
    for sig in layout.signals:
        lo = round((sig.minimum - sig.offset) / sig.scale)
        hi = round((sig.maximum - sig.offset) / sig.scale)
        if sig.minimum == sig.maximum == 0:
            bits = sig.size_bits
            lo, hi = ((-(1 << (bits - 1)), (1 << (bits - 1)) - 1) if sig.signed
                      else (0, (1 << bits) - 1))
        parts.append(st.integers(lo, hi))
    return st.tuples(*parts)


@st.composite
def message_and_values(draw: st.DrawFn) -> tuple[Layout, int, tuple[float, ...]]:
    layout = draw(st.sampled_from(PROTOCOL.layouts))
    raws = draw(raw_values(layout))
    # Physical values: exact raw multiples, or anywhere within half a step of one.
    values = []
    for raw, sig in zip(raws, layout.signals, strict=True):
        if sig.is_integer:
            values.append(raw)
        else:
            jitter = draw(st.floats(-0.49, 0.49))
            lo = (sig.minimum - sig.offset) / sig.scale
            hi = (sig.maximum - sig.offset) / sig.scale
            r = min(max(raw + jitter, lo), hi)
            values.append(r * sig.scale + sig.offset)
    return layout, draw(st.integers(0, 255)), tuple(values)


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
    theirs = DB.decode_message(layout.frame_id, data, decode_choices=False)
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


# -- decoder fuzz --------------------------------------------------------------------------------
def _frames(protocol: Protocol) -> st.SearchStrategy[tuple[int, bytes]]:
    host_side = [lay for lay in protocol.layouts if lay.kind in ("Feedback", "Status", "Heartbeat")]
    ids = st.one_of(st.sampled_from([lay.frame_id for lay in protocol.layouts]),
                    st.integers(0, 0x7FF))
    random_frame = st.tuples(ids, st.binary(min_size=0, max_size=64))

    @st.composite
    def valid(draw: st.DrawFn) -> tuple[int, bytes]:
        layout = draw(st.sampled_from(host_side))
        raws = draw(raw_values(layout))
        vals = [r if s.is_integer else r * s.scale + s.offset
                for r, s in zip(raws, layout.signals, strict=True)]
        return layout.frame_id, layout.encode(draw(st.integers(0, 255)), vals)

    @st.composite
    def flipped(draw: st.DrawFn) -> tuple[int, bytes]:
        frame_id, data = draw(valid())
        pos = draw(st.integers(0, len(data) - 1))
        bit = draw(st.integers(0, 7))
        return frame_id, data[:pos] + bytes((data[pos] ^ (1 << bit),)) + data[pos + 1:]

    return st.one_of(random_frame, valid(), flipped())


@settings(max_examples=max(1, FUZZ_EXAMPLES // 20), deadline=None,
          suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
@given(st.lists(_frames(PROTOCOL), min_size=1, max_size=40))
def test_decoder_fuzz_every_frame_accepted_or_rejected(hand: HandConfig,
                                                       frames: list[tuple[int, bytes]]) -> None:
    name = f"fuzz-{next(_channels)}"
    with open_bus(f"virtual:{name}", hand.bus) as host_bus, \
            open_bus(f"virtual:{name}", hand.bus) as peer:
        driver = HandDriver(hand, PROTOCOL, host_bus)
        for frame_id, data in frames:
            assert peer.send(frame_id, data)
        state = driver.poll()
        rejected = sum(driver.reject_counts().values())
        accepted = sum(node.accepted for node in driver.nodes)
        assert accepted + rejected == len(frames)
        assert all(abs(a) <= 3.2768 for a in state.angle)
