"""Hypothesis strategies for frames of the hand's protocol, shared by the property tests and
the decoder fuzz benchmark (``tools/bench_fuzz.py``), so the benchmark's 100 000 frames are
drawn exactly as CI's few thousand are.

The frames are what a receiver can meet on a real bus: valid frames of every message the host
hears, the same with a bit flipped (a CRC that no longer matches, or a corrupted counter
byte), cut short or padded, replayed (a repeated counter), and anything at all on any 11-bit
id, the hand's own and foreign ones, or on a 29-bit id (a valid frame's twin among them).
"""

from __future__ import annotations

from hypothesis import strategies as st

from handctl.online.bus import EXTENDED_ID_FLAG
from handctl.protocol import Layout, Protocol, load_protocol

PROTOCOL = load_protocol()

Frame = tuple[int, bytes]  # (arbitration id, payload)


def raw_values(layout: Layout) -> st.SearchStrategy[tuple[int, ...]]:
    """Random raw integers inside each signal's DBC range."""
    parts = []
    for sig in layout.signals:
        lo = round((sig.minimum - sig.offset) / sig.scale)
        hi = round((sig.maximum - sig.offset) / sig.scale)
        if sig.minimum == sig.maximum == 0:
            bits = sig.size_bits
            lo, hi = (
                (-(1 << (bits - 1)), (1 << (bits - 1)) - 1) if sig.signed else (0, (1 << bits) - 1)
            )
        parts.append(st.integers(lo, hi))
    return st.tuples(*parts)


@st.composite
def message_and_values(draw: st.DrawFn) -> tuple[Layout, int, tuple[float, ...]]:
    """A message of the DBC, a counter, and physical values within its signals' ranges."""
    layout = draw(st.sampled_from(PROTOCOL.layouts))
    raws = draw(raw_values(layout))
    # Physical values: exact raw multiples, or anywhere within half a step of one.
    values: list[float] = []
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


def _host_side(protocol: Protocol) -> list[Layout]:
    return [lay for lay in protocol.layouts if lay.kind in ("Feedback", "Status", "Heartbeat")]


def _values(draw: st.DrawFn, layout: Layout) -> list[float]:
    raws = draw(raw_values(layout))
    return [
        r if s.is_integer else r * s.scale + s.offset
        for r, s in zip(raws, layout.signals, strict=True)
    ]


def frames(protocol: Protocol = PROTOCOL) -> st.SearchStrategy[Frame]:
    """One frame as a receiver may meet it: random, valid, bit-flipped, or of a wrong length."""
    host_side = _host_side(protocol)
    ids = st.one_of(
        st.sampled_from([lay.frame_id for lay in protocol.layouts]),
        st.integers(0, 0x7FF),
        st.integers(0, 0x1FFFFFFF).map(lambda i: i | EXTENDED_ID_FLAG),
    )
    random_frame = st.tuples(ids, st.binary(min_size=0, max_size=64))

    @st.composite
    def valid(draw: st.DrawFn) -> Frame:
        layout = draw(st.sampled_from(host_side))
        return layout.frame_id, layout.encode(draw(st.integers(0, 255)), _values(draw, layout))

    @st.composite
    def flipped(draw: st.DrawFn) -> Frame:
        frame_id, data = draw(valid())
        pos = draw(st.integers(0, len(data) - 1))
        bit = draw(st.integers(0, 7))
        return frame_id, data[:pos] + bytes((data[pos] ^ (1 << bit),)) + data[pos + 1 :]

    @st.composite
    def resized(draw: st.DrawFn) -> Frame:
        frame_id, data = draw(valid())
        size = draw(st.integers(0, 64).filter(lambda n: n != len(data)))
        return frame_id, (data + bytes(64))[:size]

    @st.composite
    def extended_twin(draw: st.DrawFn) -> Frame:
        frame_id, data = draw(valid())
        return frame_id | EXTENDED_ID_FLAG, data

    return st.one_of(random_frame, valid(), flipped(), resized(), extended_twin())


@st.composite
def stream(draw: st.DrawFn, protocol: Protocol = PROTOCOL) -> list[Frame]:
    """A run of valid frames of one message with consecutive counters, as a node sends them:
    after the first (which may not follow what the receiver last saw) each is acceptable."""
    layout = draw(st.sampled_from(_host_side(protocol)))
    start = draw(st.integers(0, 255))
    return [
        (layout.frame_id, layout.encode((start + k) & 0xFF, _values(draw, layout)))
        for k in range(draw(st.integers(1, 6)))
    ]


@st.composite
def frame_batches(
    draw: st.DrawFn, protocol: Protocol = PROTOCOL, min_size: int = 1, max_size: int = 40
) -> list[Frame]:
    """What one poll may drain: single frames of any kind mixed with runs of valid frames,
    some sent twice in a row (a replayed frame, whose counter repeats)."""
    parts = draw(
        st.lists(
            st.one_of(frames(protocol).map(lambda f: [f]), stream(protocol)),
            min_size=min_size,
            max_size=max_size,
        )
    )
    batch = [frame for part in parts for frame in part]
    repeats = draw(st.lists(st.integers(0, len(batch) - 1), max_size=3))
    for i in sorted(repeats, reverse=True):
        batch.insert(i + 1, batch[i])
    return batch
