"""Generate the shared codec vectors: ``python tools/gen_vectors.py [--check]``.

``firmware_protocol/vectors.json`` is the contract between the host codec
(``handctl.protocol``), the generated C codec and any firmware test suite: golden bytes for
every message of the DBC, plus inputs every codec must refuse. The bytes are computed by
``handctl.protocol`` and cross-checked here against cantools, an independent implementation of
the DBC layout, so a bug in the hot-path codec cannot silently become the golden truth. The
CRC, which cantools does not know, is pinned by the CRC-8/AUTOSAR check value instead.

Vectors aim at the places codecs differ: range ends, negative values and negative zero, exact
rounding ties (``k + 0.5`` in double arithmetic, where half-even and half-away disagree for
even ``k``), a tie just outside the range that rounds back in, and counter wrap-around; plus
seeded random values. Output is deterministic, and ``--check`` fails when the committed file
differs from what the DBC yields.
"""

from __future__ import annotations

import argparse
import json
import math
import random
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from generated import DEFAULT_DBC, display_path, read_protocol, write_or_check

from handctl.errors import ProtocolError
from handctl.protocol import Layout, Protocol, SignalSpec, _raw_bounds, crc8

ROOT = Path(__file__).resolve().parent.parent
DEFAULT_OUT = ROOT / "firmware_protocol" / "vectors.json"
COMMAND = "python tools/gen_vectors.py"
SEED = 0x4A4E44  # fixed: the file must not change unless the DBC does
RANDOM_PER_MESSAGE = 4
CRC_CHECK_INPUT = b"123456789"
CRC_CHECK_VALUE = 0xDF  # CRC-8/AUTOSAR check value from the AUTOSAR CRC specification

Value = int | float


class VectorError(Exception):
    """Two codecs disagree, or a vector does not exercise what it claims to."""


def _bounds(spec: SignalSpec) -> tuple[int, int]:
    lo, hi = _raw_bounds(spec)
    return int(lo), int(hi)


def _physical(spec: SignalSpec, raw: int) -> Value:
    """The value a sender would write for ``raw``: ints stay ints, as on the Python side."""
    return raw if spec.is_integer else raw * spec.scale + spec.offset


def _zero(spec: SignalSpec) -> Value:
    """0 when the signal accepts it, else the in-range value nearest to raw 0."""
    zero: Value = 0 if spec.is_integer else 0.0
    lo, hi = _bounds(spec)
    if spec.is_integer:
        return min(max(0, lo), hi)
    if lo <= round(_quotient(spec, 0.0)) <= hi:
        return zero
    return _physical(spec, min(max(0, lo), hi))


def _quotient(spec: SignalSpec, value: float) -> float:
    return (value - spec.offset) / spec.scale


def find_tie(spec: SignalSpec, k: int) -> float | None:
    """A double v with (v - offset) / scale == k + 0.5 exactly, or None if none is near.

    Most decimal scales have such doubles for most k; a few ulps around the naive product are
    enough to find one when it exists.
    """
    target = k + 0.5
    centre = target * spec.scale + spec.offset
    below = above = centre
    for _ in range(8):
        for candidate in (below, above):
            if _quotient(spec, candidate) == target:
                return candidate
        below = math.nextafter(below, -math.inf)
        above = math.nextafter(above, math.inf)
    return None


def _tie_in(spec: SignalSpec, k_lo: int, k_hi: int, fraction: float, parity: int) -> float | None:
    """An exact tie k + 0.5 with k of the given parity in [k_lo, k_hi], near ``fraction``."""
    if k_lo > k_hi:
        return None
    centre = k_lo + int((k_hi - k_lo) * fraction)
    for distance in range(min(k_hi - k_lo + 1, 512)):
        for k in (centre + distance, centre - distance):
            if k_lo <= k <= k_hi and k % 2 == parity:
                tie = find_tie(spec, k)
                if tie is not None:
                    return tie
    return None


def _half_even(k: int) -> int:
    """Where k + 0.5 lands under round-half-even."""
    return k if k % 2 == 0 else k + 1


def _cases(layout: Layout, rng: random.Random) -> Iterator[tuple[str, int, list[Value]]]:  # noqa: C901 - every kind of test vector; to split
    """(case, counter, values) for one message, in a fixed order."""
    specs = layout.signals
    bounds = [_bounds(s) for s in specs]
    scaled = [not s.is_integer for s in specs]

    def mid(i: int) -> Value:
        lo, hi = bounds[i]
        return _physical(specs[i], (lo + hi) // 2)

    def end(i: int, dbc_value: float, raw: int) -> Value:
        """The DBC's literal end when it encodes, else the raw end (ints stay ints)."""
        spec = specs[i]
        if spec.is_integer or not _accepts(layout, i, dbc_value):
            return _physical(spec, raw)
        return dbc_value

    yield "zero", 0, [_zero(s) for s in specs]
    minimum = [end(i, s.minimum, bounds[i][0]) for i, s in enumerate(specs)]
    maximum = [end(i, s.maximum, bounds[i][1]) for i, s in enumerate(specs)]
    yield "minimum", 1, minimum
    yield "maximum", 2, maximum
    raw_minimum = [_physical(s, lo) for s, (lo, _) in zip(specs, bounds, strict=True)]
    raw_maximum = [_physical(s, hi) for s, (_, hi) in zip(specs, bounds, strict=True)]
    if raw_minimum != minimum:
        yield "raw_minimum", 3, raw_minimum
    if raw_maximum != maximum:
        yield "raw_maximum", 4, raw_maximum

    signed = [i for i, s in enumerate(specs) if bounds[i][0] < 0]
    if signed:
        # One raw step below zero, then human-typed negatives, then deep in the range.
        picks: list[Value] = []
        for n, i in enumerate(signed):
            s, (lo, _) = specs[i], bounds[i]
            options: list[Value] = [
                _physical(s, -1),
                -1 if s.is_integer else -1.2345,
                _physical(s, lo // 3),
                _physical(s, lo + 1),
            ]
            picks.append(options[n % len(options)])
        values = [mid(i) for i in range(len(specs))]
        for i, v in zip(signed, picks, strict=True):
            values[i] = v if _accepts(layout, i, v) else _physical(specs[i], -1)
        yield "negative", 5, values
        if any(scaled[i] for i in signed):
            yield (
                "negative_zero",
                6,
                [-0.0 if scaled[i] and i in signed else mid(i) for i in range(len(specs))],
            )

    if any(scaled):
        # Ties: even k rounds down (half-away would round up), odd k rounds up; both signs.
        for case, counter, negative, parity in (
            ("tie_even", 7, False, 0),
            ("tie_odd", 8, False, 1),
            ("tie_negative_even", 9, True, 0),
            ("tie_negative_odd", 10, True, 1),
        ):
            values = [mid(i) for i in range(len(specs))]
            found = False
            for i, s in enumerate(specs):
                lo, hi = bounds[i]
                if not scaled[i]:
                    continue
                k_lo, k_hi = (lo, min(hi - 1, -1)) if negative else (max(lo, 0), hi - 1)
                tie = _tie_in(s, k_lo, k_hi, (i + 1) / (len(specs) + 1), parity)
                if tie is not None:
                    values[i] = tie
                    found = True
            if found:
                yield case, counter, values
        edge = _edge_ties(layout, accepted=True)
        if edge is not None:
            yield "tie_rounds_into_range", 11, edge

    for n in range(RANDOM_PER_MESSAGE):
        yield f"random_{n}", rng.randrange(256), _random_values(specs, bounds, rng)
    yield "counter_wrap", 255, _random_values(specs, bounds, rng)


def _random_values(
    specs: tuple[SignalSpec, ...], bounds: list[tuple[int, int]], rng: random.Random
) -> list[Value]:
    values: list[Value] = []
    for s, (lo, hi) in zip(specs, bounds, strict=True):
        if s.is_integer:
            values.append(rng.randint(lo, hi))
        else:
            values.append(rng.uniform(float(_physical(s, lo)), float(_physical(s, hi))))
    return values


def _edge_ties(layout: Layout, accepted: bool) -> list[Value] | None:
    """Values on the tie just beyond a range end, where the rounding direction decides.

    A tie at lo - 0.5 with lo even rounds back to lo (accepted; half-away would refuse it);
    with hi odd, hi + 0.5 rounds to hi + 1 (refused). ``accepted`` picks which kind; one signal
    carries the tie, the others are (nearly) zero.
    """
    values: list[Value] = []
    found = False
    for s in layout.signals:
        value = _zero(s)
        if not found and not s.is_integer:
            lo, hi = _bounds(s)
            for k in (lo - 1, hi):
                if (lo <= _half_even(k) <= hi) == accepted:
                    tie = find_tie(s, k)
                    if tie is not None:
                        value, found = tie, True
                        break
        values.append(value)
    return values if found else None


def _accepts(layout: Layout, index: int, value: Value) -> bool:
    lo, hi = _bounds(layout.signals[index])
    spec = layout.signals[index]
    if spec.is_integer and isinstance(value, int):
        return lo <= value <= hi
    return lo <= round(_quotient(spec, float(value))) <= hi


def _named(layout: Layout, values: list[Value] | tuple[Value, ...]) -> dict[str, Value]:
    return dict(zip(layout.signal_names, values, strict=True))


def _cross_check(
    db: Any, layout: Layout, counter: int, values: list[Value], data: bytes, where: str
) -> tuple[Value, ...]:
    """Bytes and decoded values must agree between handctl.protocol and cantools."""
    signals: dict[str, Value] = {"Crc": data[0], "Counter": counter, **_named(layout, values)}
    in_range = all(
        s.minimum <= v <= s.maximum or s.minimum == s.maximum == 0
        for s, v in zip(layout.signals, values, strict=True)
    )
    # cantools' strict mode checks the physical range before rounding; handctl checks the raw
    # value after it, so a value that rounds into the range is only comparable unstrict.
    theirs = db.encode_message(layout.name, signals, strict=in_range)
    if theirs != data:
        raise VectorError(f"{where}: handctl encodes {data.hex()}, cantools {theirs.hex()}")
    if not layout.crc_ok(data):
        raise VectorError(f"{where}: handctl rejects its own CRC in {data.hex()}")
    got_counter, decoded = layout.decode(data)
    decoded_cantools = db.decode_message(layout.frame_id, data, decode_choices=False)
    if got_counter != counter or decoded_cantools["Counter"] != counter:
        raise VectorError(f"{where}: counter {counter} decodes as {got_counter}")
    for name, value in zip(layout.signal_names, decoded, strict=True):
        other = decoded_cantools[name]
        if other != value or isinstance(other, float) != isinstance(value, float):
            raise VectorError(
                f"{where}: {name} decodes as {value!r} in handctl, {other!r} in cantools"
            )
    return decoded


def build(protocol: Protocol, db: Any, dbc_name: str, command: str = COMMAND) -> dict[str, Any]:
    """The whole document, as plain data."""
    if crc8(CRC_CHECK_INPUT) != CRC_CHECK_VALUE:
        raise VectorError(
            f"handctl.protocol.crc8 gives 0x{crc8(CRC_CHECK_INPUT):02X} for "
            f"'123456789', CRC-8/AUTOSAR is 0x{CRC_CHECK_VALUE:02X}"
        )
    rng = random.Random(SEED)
    vectors: list[dict[str, Any]] = []
    first_bytes: dict[str, bytes] = {}
    for layout in protocol.layouts:
        for case, counter, values in _cases(layout, rng):
            where = f"{layout.name}/{case}"
            try:
                data = layout.encode(counter, values)
            except ProtocolError as exc:
                raise VectorError(
                    f"{where}: handctl refuses a vector meant to be valid: {exc}"
                ) from None
            decoded = _cross_check(db, layout, counter, values, data, where)
            _check_ties(layout, case, values, data, where)
            first_bytes.setdefault(layout.name, data)
            vectors.append(
                {
                    "case": case,
                    "message": layout.name,
                    "frame_id": layout.frame_id,
                    "counter": counter,
                    "signals": _named(layout, values),
                    "bytes": data.hex(),
                    "decoded": _named(layout, decoded),
                }
            )
    return {
        "format": 1,
        "generated_by": command,
        "dbc": dbc_name,
        "dbc_version": db.version or "",
        "crc": "CRC-8/AUTOSAR (poly 0x2F, init 0xFF, xorout 0xFF) over DataID (low byte, high "
        "byte) then bytes 1..n-1",
        "crc_check": {"bytes": CRC_CHECK_INPUT.hex(), "crc8": CRC_CHECK_VALUE},
        "rounding": "raw = round-half-even((value - offset) / scale) in IEEE-754 double",
        "vectors": vectors,
        "encode_rejects": _encode_rejects(protocol),
        "decode_rejects": _decode_rejects(protocol, first_bytes),
    }


def _raw_at(spec: SignalSpec, data: bytes) -> int:
    start = spec.offset_byte
    return int.from_bytes(data[start : start + spec.size_bits // 8], "little", signed=spec.signed)


def _check_ties(layout: Layout, case: str, values: list[Value], data: bytes, where: str) -> None:
    """A tie vector must hold an exact tie, and the tie must land where half-even puts it."""
    if not case.startswith("tie"):
        return
    ties = 0
    for spec, value in zip(layout.signals, values, strict=True):
        if spec.is_integer:
            continue
        q = _quotient(spec, float(value))
        if q - math.floor(q) == 0.5:
            ties += 1
            want, raw = _half_even(math.floor(q)), _raw_at(spec, data)
            if raw != want:
                raise VectorError(
                    f"{where}: {spec.name}={value!r} is the tie {q!r}, "
                    f"encoded as raw {raw}, half-even gives {want}"
                )
    if ties == 0:
        raise VectorError(f"{where}: no value of the vector is an exact rounding tie")


def _encode_rejects(protocol: Protocol) -> list[dict[str, Any]]:
    """One raw step beyond each end of each signal, and the tie that rounds out of range."""
    rejects = []
    for layout in protocol.layouts:
        base = [_zero(s) for s in layout.signals]
        candidates: list[tuple[str, list[Value]]] = []
        for i, spec in enumerate(layout.signals):
            lo, hi = _bounds(spec)
            for case, raw in (("below_minimum", lo - 1), ("above_maximum", hi + 1)):
                values = list(base)
                values[i] = _physical(spec, raw)
                candidates.append((f"{spec.name}_{case}", values))
        edge = _edge_ties(layout, accepted=False)
        if edge is not None:
            candidates.append(("tie_rounds_out_of_range", edge))
        for case, values in candidates:
            try:
                data = layout.encode(0, values)
            except ProtocolError:
                rejects.append(
                    {
                        "case": case,
                        "message": layout.name,
                        "frame_id": layout.frame_id,
                        "counter": 0,
                        "signals": _named(layout, values),
                        "error": "range",
                    }
                )
                continue
            raise VectorError(f"{layout.name}/{case}: handctl accepts {values!r} as {data.hex()}")
    return rejects


def _decode_rejects(protocol: Protocol, first_bytes: dict[str, bytes]) -> list[dict[str, Any]]:
    """Frames a receiver must refuse: bad CRC, wrong length, a frame under another id."""
    rejects = []
    for layout in protocol.layouts:
        good = first_bytes[layout.name]
        frames = [
            ("crc_byte_flipped", layout, bytes((good[0] ^ 0x01,)) + good[1:], "crc"),
            ("payload_bit_flipped", layout, good[:-1] + bytes((good[-1] ^ 0x80,)), "crc"),
            ("one_byte_short", layout, good[:-1], "length"),
            ("one_byte_long", layout, good + b"\x00", "length"),
        ]
        # The DataID is in the CRC: the same bytes under another id of the same length fail.
        other = next(
            (o for o in protocol.layouts if o.length == layout.length and o is not layout), None
        )
        if other is not None and not other.crc_ok(good):
            frames.append((f"bytes_of_{layout.name}", other, good, "crc"))
        for case, target, data, error in frames:
            ok = target.crc_ok(data)
            if ok:
                raise VectorError(f"{target.name}/{case}: handctl accepts {data.hex()}")
            rejects.append(
                {
                    "case": case,
                    "message": target.name,
                    "frame_id": target.frame_id,
                    "bytes": data.hex(),
                    "error": error,
                }
            )
    return rejects


def render(document: dict[str, Any]) -> str:
    """JSON with one vector per line, so a DBC change shows up as a readable diff."""
    lines = ["{"]
    items = list(document.items())
    for n, (key, value) in enumerate(items):
        comma = "," if n < len(items) - 1 else ""
        if isinstance(value, list):
            lines.append(f"  {json.dumps(key)}: [")
            lines += [
                f"    {json.dumps(item, allow_nan=False)}{',' if m < len(value) - 1 else ''}"
                for m, item in enumerate(value)
            ]
            lines.append(f"  ]{comma}")
        else:
            lines.append(f"  {json.dumps(key)}: {json.dumps(value, allow_nan=False)}{comma}")
    lines.append("}")
    return "\n".join(lines) + "\n"


def generate(dbc: Path, hand: Path | None = None) -> str:
    """The vectors of ``dbc``, or of the protocol of ``hand``."""
    protocol, db, dbc_name, option = read_protocol(dbc, hand)
    document = build(protocol, db, dbc_name, COMMAND + option)
    text = render(document)
    if json.loads(text) != json.loads(json.dumps(document)):
        raise VectorError("the rendered JSON does not read back as the document")
    return text


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0] if __doc__ else None)
    inputs = parser.add_mutually_exclusive_group()
    inputs.add_argument("--dbc", type=Path, default=DEFAULT_DBC, help="DBC to read")
    inputs.add_argument(
        "--hand",
        type=Path,
        help="hand config (HAND.yaml) whose generated protocol to read, instead of a DBC",
    )
    parser.add_argument("--out", type=Path, default=DEFAULT_OUT, help="JSON file to write")
    parser.add_argument(
        "--check",
        action="store_true",
        help="write nothing; exit 1 if the file on disk is not up to date",
    )
    args = parser.parse_args(argv)
    try:
        text = generate(args.dbc, args.hand)
    except (VectorError, ValueError) as exc:  # ConfigError is a ValueError
        print(f"gen_vectors.py: {exc}", file=sys.stderr)
        return 2
    source = display_path(args.hand if args.hand is not None else args.dbc)
    return write_or_check("gen_vectors.py", {args.out: text}, source, COMMAND, args.check)


if __name__ == "__main__":
    sys.exit(main())
