"""Generate the firmware's C codec from the DBC: ``python tools/gen_c_codec.py [--check]``.

The DBC is the one source of every frame, so the firmware must not carry a hand-written copy of
the layouts: this tool derives ``firmware_protocol/c/handctl_protocol.{h,c}`` from the same
compiled layouts the Python hot path uses (``handctl.protocol.load_protocol``), with the same
range rule (``_raw_bounds``) and the same rounding (``nearbyint`` under the default rounding
mode is round-half-even in double precision, exactly Python's ``round()`` of the same double
quotient). Constants are written with ``repr()`` so that C and Python start from the very same
doubles. ``--check`` regenerates in memory and fails when the committed files differ, so the C
codec cannot drift from the DBC unnoticed.

The output depends only on the DBC (no timestamps, no absolute paths), so regeneration is
byte-for-byte reproducible.
"""

from __future__ import annotations

import argparse
import keyword
import math
import re
import sys
import textwrap
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

from generated import DEFAULT_DBC, display_path, read_protocol, write_or_check

from handctl.protocol import (
    CRC8_INIT,
    CRC8_POLY,
    CRC8_XOR_OUT,
    Layout,
    SignalSpec,
    _raw_bounds,
)

ROOT = Path(__file__).resolve().parent.parent
DEFAULT_OUT = ROOT / "firmware_protocol" / "c"
HEADER_NAME = "handctl_protocol.h"
SOURCE_NAME = "handctl_protocol.c"
PREFIX = "handctl"

#: Raw C types by (bits, signed), with the range the type itself can hold.
_C_TYPES: dict[tuple[int, bool], tuple[str, int, int]] = {
    (8, False): ("uint8_t", 0, 0xFF),
    (8, True): ("int8_t", -0x80, 0x7F),
    (16, False): ("uint16_t", 0, 0xFFFF),
    (16, True): ("int16_t", -0x8000, 0x7FFF),
    (32, False): ("uint32_t", 0, 0xFFFF_FFFF),
    (32, True): ("int32_t", -0x8000_0000, 0x7FFF_FFFF),
}

_C_RESERVED = frozenset(
    (
        "auto",
        "break",
        "case",
        "char",
        "const",
        "continue",
        "default",
        "do",
        "double",
        "else",
        "enum",
        "extern",
        "float",
        "for",
        "goto",
        "if",
        "inline",
        "int",
        "long",
        "register",
        "restrict",
        "return",
        "short",
        "signed",
        "sizeof",
        "static",
        "struct",
        "switch",
        "typedef",
        "union",
        "unsigned",
        "void",
        "volatile",
        "while",
        "_Bool",
        "_Complex",
        "_Imaginary",
        "bool",
        "true",
        "false",
    )
)

_ERRORS = (
    ("OK", 0, "success"),
    ("ERR_ARG", -1, "NULL pointer, or wrong number of values (by-id API)"),
    ("ERR_LENGTH", -2, "encode: buffer too small; decode: frame of the wrong length"),
    ("ERR_CRC", -3, "decode: CRC does not match the message's DataID and payload"),
    ("ERR_RANGE", -4, "encode: a value outside its DBC range, or not a number"),
    ("ERR_ID", -5, "by-id API: a frame id the DBC does not define"),
)

WRAP = 96


class GenerationError(Exception):
    """The DBC holds something the C codec cannot represent faithfully."""


@dataclass(frozen=True)
class CSignal:
    spec: SignalSpec
    field: str
    raw_type: str
    type_lo: int
    type_hi: int
    raw_lo: int
    raw_hi: int

    @property
    def integer(self) -> bool:
        """Integer signals travel as exact ints in the struct, like ints on the Python side."""
        return self.spec.is_integer

    @property
    def field_type(self) -> str:
        return self.raw_type if self.integer else "double"


@dataclass(frozen=True)
class CMessage:
    layout: Layout
    ident: str
    macro: str
    senders: tuple[str, ...]
    signals: tuple[CSignal, ...]

    @property
    def struct(self) -> str:
        return f"struct {PREFIX}_{self.ident}"


def snake(name: str) -> str:
    """CamelCase_1 -> camel_case_1: C firmware reads snake case; the DBC keeps CamelCase."""
    text = re.sub(r"(?<=[a-z0-9])(?=[A-Z])|(?<=[A-Z])(?=[A-Z][a-z])", "_", name)
    return re.sub(r"_+", "_", text).lower()


def c_double(value: float) -> str:
    """A C double literal denoting exactly the same double as ``value`` on the Python side."""
    if not math.isfinite(value):
        raise GenerationError(f"expected a finite constant, found {value!r}")
    text = repr(float(value))
    return f"({text})" if text.startswith("-") else text


def c_int(value: int, unsigned: bool) -> str:
    if unsigned:
        return f"{value}u"
    if value == -0x8000_0000:  # 2147483648 alone does not fit an int
        return "(-2147483647 - 1)"
    return str(value)


def _comment(text: str) -> str:
    """Keep DBC text from closing a C comment early."""
    return text.replace("*/", "* /").replace("/*", "/ *")


def _identifier(name: str, where: str) -> str:
    if (
        not re.fullmatch(r"[a-z_][a-z0-9_]*", name)
        or name in _C_RESERVED
        or keyword.iskeyword(name)
    ):
        raise GenerationError(f"{where}: expected a name usable as a C identifier, found {name!r}")
    return name


def build_messages(
    layouts: Iterable[Layout], senders: dict[str, tuple[str, ...]]
) -> list[CMessage]:
    """Turn compiled layouts into what the templates need, refusing what C cannot mirror."""
    messages = []
    seen: dict[str, str] = {}
    for layout in layouts:
        ident = _identifier(snake(layout.name), layout.name)
        if ident in seen:
            raise GenerationError(f"{layout.name}: C name {ident} already used by {seen[ident]}")
        seen[ident] = layout.name
        if not layout.signals:
            raise GenerationError(
                f"{layout.name}: expected at least one signal after Crc and "
                "Counter (a C struct cannot be empty), found none"
            )
        covered = [False] * layout.length
        covered[0] = covered[1] = True
        fields: dict[str, str] = {}
        signals = []
        for spec in layout.signals:
            where = f"{layout.name}.{spec.name}"
            field = _identifier(snake(spec.name), where)
            if field in fields:
                raise GenerationError(f"{where}: C field {field} already used by {fields[field]}")
            fields[field] = spec.name
            span = range(spec.offset_byte, spec.offset_byte + spec.size_bits // 8)
            if span.stop > layout.length or any(covered[i] for i in span):
                raise GenerationError(
                    f"{where}: expected bytes {span.start}..{span.stop - 1} "
                    f"free inside {layout.length} bytes, found them taken"
                )
            for i in span:
                covered[i] = True
            if not (math.isfinite(spec.scale) and spec.scale != 0 and math.isfinite(spec.offset)):
                raise GenerationError(
                    f"{where}: expected a finite non-zero scale and a finite "
                    f"offset, found ({spec.scale!r}, {spec.offset!r})"
                )
            raw_type, type_lo, type_hi = _C_TYPES[(spec.size_bits, spec.signed)]
            lo, hi = _raw_bounds(spec)
            if lo > hi:
                raise GenerationError(
                    f"{where}: the DBC range [{spec.minimum}, {spec.maximum}] holds no raw value"
                )
            signals.append(CSignal(spec, field, raw_type, type_lo, type_hi, int(lo), int(hi)))
        messages.append(
            CMessage(layout, ident, ident.upper(), senders.get(layout.name, ()), tuple(signals))
        )
    return messages


def _gaps(message: CMessage) -> list[int]:
    """Bytes no signal covers: encoded as zero, as the Python ``struct`` pad bytes are."""
    covered = {0, 1}
    for sig in message.signals:
        covered.update(range(sig.spec.offset_byte, sig.spec.offset_byte + sig.spec.size_bits // 8))
    return [i for i in range(message.layout.length) if i not in covered]


def _prototype(ret: str, name: str, params: list[str], end: str) -> list[str]:
    """A declaration wrapped the way a firmware engineer would wrap it by hand."""
    head = f"{ret} {name}("
    one = head + ", ".join(params) + ")" + end
    if len(one) <= WRAP:
        return [one]
    lines = [head + params[0] + ","]
    pad = " " * len(head)
    for param in params[1:-1]:
        candidate = lines[-1] + " " + param + ","
        if len(candidate) <= WRAP:
            lines[-1] = candidate
        else:
            lines.append(pad + param + ",")
    last = params[-1] + ")" + end
    if len(lines[-1]) + 1 + len(last) <= WRAP:
        lines[-1] += " " + last
    else:
        lines.append(pad + last)
    return lines


def _encode_params(m: CMessage) -> list[str]:
    return ["uint8_t *out", "size_t out_len", "uint8_t counter", f"const {m.struct} *msg"]


def _decode_params(m: CMessage) -> list[str]:
    return ["const uint8_t *in", "size_t len", "uint8_t *counter", f"{m.struct} *msg"]


def _banner(file_name: str, command: str, dbc_name: str, version: str) -> list[str]:
    return [
        f"/* {file_name}: the handctl CAN-FD protocol codec for C99 firmware.",
        " *",
        f" * GENERATED by `{command}` from {dbc_name}",
        f' * (DBC VERSION "{_comment(version)}"). Do not edit: change the DBC and regenerate;',
        f" * `{command} --check` fails while this file is stale.",
        " */",
    ]


def render_header(messages: list[CMessage], command: str, dbc_name: str, version: str) -> str:
    out = _banner(HEADER_NAME, command, dbc_name, version)
    out += [
        "",
        "/*",
        " * Frames: byte 0 Crc, byte 1 Counter (per message and sender, +1 per frame, 255 -> 0),",
        " * then byte-aligned little-endian signals. Crc is CRC-8/AUTOSAR (poly "
        f"0x{CRC8_POLY:02X}, init 0x{CRC8_INIT:02X},",
        f" * xorout 0x{CRC8_XOR_OUT:02X}) over the message's DataID (low byte, high byte), "
        "which never travels,",
        " * followed by bytes 1..n-1 of the frame.",
        " *",
        " * Encoding rounds raw = nearbyint((value - offset) / scale) in double precision under",
        " * the default rounding mode (ties to even), bit-identical to handctl.protocol on the",
        " * host. Do not change the rounding mode (fesetround) in code that calls the encoders.",
        " * A value is accepted when its raw value lies in the DBC range (clipped to what the",
        " * bits hold), so NaN and infinities are refused. Decoding gives raw * scale + offset.",
        " *",
        " * Every function is re-entrant: no global state, no allocation, no libc I/O.",
        " */",
        "",
        "#ifndef HANDCTL_PROTOCOL_H",
        "#define HANDCTL_PROTOCOL_H",
        "",
        "#include <stddef.h>",
        "#include <stdint.h>",
        "",
        "#ifdef __cplusplus",
        'extern "C" {',
        "#endif",
        "",
        f'#define HANDCTL_PROTOCOL_VERSION "{_comment(version)}"',
        "",
        "/* Return codes of every function that returns int. */",
    ]
    for name, code, text in _ERRORS:
        value = "0" if code == 0 else f"({code})"
        out.append(f"#define HANDCTL_{name} {value} /* {text} */")
    out += [
        "",
        f"#define HANDCTL_MESSAGE_COUNT {len(messages)}u",
        f"#define HANDCTL_MAX_LENGTH {max(m.layout.length for m in messages)}u",
        f"#define HANDCTL_MAX_SIGNALS {max(len(m.signals) for m in messages)}u",
        "",
        "/* CRC-8/AUTOSAR of data[0..len-1] (init and final XOR included); check value: 0xDF",
        ' * for the ASCII bytes "123456789". */',
        "uint8_t handctl_crc8(const uint8_t *data, size_t len);",
    ]
    for m in messages:
        lay = m.layout
        sent = ", ".join(m.senders) or "?"
        about = f"{lay.name} (id 0x{lay.frame_id:03X}, {lay.length} bytes, sent by {sent})"
        if lay.comment:
            about += f": {_comment(lay.comment)}"
        out += ["", *_wrap_comment(about)]
        out += [
            f"#define HANDCTL_{m.macro}_FRAME_ID 0x{lay.frame_id:03X}u",
            f"#define HANDCTL_{m.macro}_LENGTH {lay.length}u",
            f"#define HANDCTL_{m.macro}_DATA_ID 0x{lay.data_id:04X}u",
            "",
            f"{m.struct} {{",
        ]
        for sig in m.signals:
            spec = sig.spec
            unit = f"{_comment(spec.unit)}, " if spec.unit else ""
            raw_range = f"raw [{sig.raw_lo}, {sig.raw_hi}]"
            if sig.integer:
                note = f"{unit}{raw_range}"
            else:
                conv = f"{sig.raw_type} * {spec.scale!r}"
                if spec.offset != 0:
                    conv += f" + {spec.offset!r}"
                note = f"{unit}DBC [{spec.minimum!r}, {spec.maximum!r}], {raw_range}, {conv}"
            out.append(f"    {sig.field_type} {sig.field}; /* {note} */")
        out.append("};")
        out += _prototype("int", f"{PREFIX}_{m.ident}_encode", _encode_params(m), ";")
        out += _prototype("int", f"{PREFIX}_{m.ident}_decode", _decode_params(m), ";")
    out += [
        "",
        "/*",
        " * By-id access on arrays of physical values, in DBC order (the signals after Crc and",
        " * Counter, as listed in each struct), for gateways, loggers and test harnesses.",
        " * Integer signals take nearbyint(value), exactly as handctl.protocol does for floats.",
        " * handctl_frame_length and handctl_signal_count return HANDCTL_ERR_ID for an unknown id.",
        " */",
        "int handctl_frame_length(uint32_t frame_id);",
        "int handctl_signal_count(uint32_t frame_id);",
        *_prototype(
            "int",
            "handctl_encode_by_id",
            [
                "uint32_t frame_id",
                "uint8_t *out",
                "size_t out_len",
                "uint8_t counter",
                "const double *values",
                "size_t n_values",
            ],
            ";",
        ),
        *_prototype(
            "int",
            "handctl_decode_by_id",
            [
                "uint32_t frame_id",
                "const uint8_t *in",
                "size_t len",
                "uint8_t *counter",
                "double *values",
                "size_t n_values",
            ],
            ";",
        ),
        "",
        "#ifdef __cplusplus",
        "}",
        "#endif",
        "",
        "#endif /* HANDCTL_PROTOCOL_H */",
    ]
    return "\n".join(out) + "\n"


def _wrap_comment(text: str) -> list[str]:
    lines = textwrap.wrap(text, WRAP - 3)
    if len(lines) == 1:
        return [f"/* {lines[0]} */"]
    return ["/* " + lines[0], *(" * " + line for line in lines[1:]), " */"]


_HELPERS: dict[str, list[str]] = {
    "put_u16": [
        "static void put_u16(uint8_t *p, uint16_t v)",
        "{",
        "    p[0] = (uint8_t)(v & 0xFFu);",
        "    p[1] = (uint8_t)(v >> 8);",
        "}",
    ],
    "put_u32": [
        "static void put_u32(uint8_t *p, uint32_t v)",
        "{",
        "    p[0] = (uint8_t)(v & 0xFFu);",
        "    p[1] = (uint8_t)((v >> 8) & 0xFFu);",
        "    p[2] = (uint8_t)((v >> 16) & 0xFFu);",
        "    p[3] = (uint8_t)(v >> 24);",
        "}",
    ],
    "get_u16": [
        "static uint16_t get_u16(const uint8_t *p)",
        "{",
        "    return (uint16_t)((uint16_t)p[0] | (uint16_t)((uint16_t)p[1] << 8));",
        "}",
    ],
    "get_u32": [
        "static uint32_t get_u32(const uint8_t *p)",
        "{",
        "    return (uint32_t)p[0] | ((uint32_t)p[1] << 8) | ((uint32_t)p[2] << 16)",
        "        | ((uint32_t)p[3] << 24);",
        "}",
    ],
    # Two's complement by arithmetic: converting an out-of-range unsigned value to a signed
    # type is implementation-defined in C99, so the sign is taken apart explicitly.
    "get_i8": [
        "static int8_t get_i8(const uint8_t *p)",
        "{",
        "    return (int8_t)((p[0] & 0x80u) ? (int)p[0] - 0x100 : (int)p[0]);",
        "}",
    ],
    "get_i16": [
        "static int16_t get_i16(const uint8_t *p)",
        "{",
        "    uint16_t u = get_u16(p);",
        "    return (int16_t)((u & 0x8000u) ? (int32_t)u - 0x10000 : (int32_t)u);",
        "}",
    ],
    "get_i32": [
        "static int32_t get_i32(const uint8_t *p)",
        "{",
        "    uint32_t u = get_u32(p);",
        "    return (int32_t)((u & 0x80000000u) ? (int64_t)u - 0x100000000 : (int64_t)u);",
        "}",
    ],
    "whole": [
        "/* The raw value of an integer signal given as a double (by-id API): nearbyint, then",
        " * the range of the C type, so that the cast below is always defined. */",
        "static int whole(double value, double lo, double hi, double *raw)",
        "{",
        "    double r = nearbyint(value);",
        "    if (!(r >= lo && r <= hi)) {",
        "        return HANDCTL_ERR_RANGE;",
        "    }",
        "    *raw = r;",
        "    return HANDCTL_OK;",
        "}",
    ],
}
_HELPER_DEPS = {"get_i16": ("get_u16",), "get_i32": ("get_u32",)}


def _store(sig: CSignal, value: str) -> tuple[str, set[str]]:
    """The statement writing ``value`` (the raw integer, or its double) little-endian."""
    bits, at = sig.spec.size_bits, sig.spec.offset_byte
    raw = value if sig.integer else f"({sig.raw_type}){value}"
    if sig.spec.signed:  # signed -> unsigned conversion is modular, hence well defined
        raw = f"(uint{bits}_t){raw}"
    if bits == 8:
        return f"out[{at}] = {raw};", set()
    return f"put_u{bits}(out + {at}, {raw});", {f"put_u{bits}"}


def render_source(messages: list[CMessage], command: str, dbc_name: str, version: str) -> str:
    body: list[str] = []
    used: set[str] = set()
    for m in messages:
        enc, enc_used = _render_encode(m)
        dec, dec_used = _render_decode(m)
        body += ["", *enc, "", *dec]
        used |= enc_used | dec_used
    by_id, by_id_used = _render_by_id(messages)
    body += by_id
    used |= by_id_used
    for name in list(used):
        used.update(_HELPER_DEPS.get(name, ()))

    out = _banner(SOURCE_NAME, command, dbc_name, version)
    out += [
        "",
        f'#include "{HEADER_NAME}"',
        "",
        "#include <float.h>",
        "#include <math.h>",
        "",
        "/* Excess precision (x87, FLT_EVAL_METHOD 2) would round twice and break bit-identity",
        " * with the host: build for an FPU or soft-float that evaluates doubles as doubles. */",
        "#if !defined(FLT_EVAL_METHOD) || FLT_EVAL_METHOD != 0",
        '#error "handctl_protocol.c needs FLT_EVAL_METHOD == 0 (on i386: -msse2 -mfpmath=sse)"',
        "#endif",
        "/* -ffast-math (or -freciprocal-math alone) turns x / 0.0001 into x * 10000.0, which",
        " * rounds differently. */",
        "#if defined(__FAST_MATH__)",
        '#error "handctl_protocol.c must not be built with -ffast-math"',
        "#endif",
    ]
    out += [
        "",
        "static uint8_t crc8_update(uint8_t crc, const uint8_t *data, size_t len)",
        "{",
        "    size_t i;",
        "    unsigned bit;",
        "    for (i = 0u; i < len; ++i) {",
        "        crc = (uint8_t)(crc ^ data[i]);",
        "        for (bit = 0u; bit < 8u; ++bit) {",
        f"            crc = (uint8_t)((crc & 0x80u) ? ((unsigned)crc << 1) ^ 0x{CRC8_POLY:02X}u"
        " : (unsigned)crc << 1);",
        "        }",
        "    }",
        "    return crc;",
        "}",
        "",
        "uint8_t handctl_crc8(const uint8_t *data, size_t len)",
        "{",
        f"    return (uint8_t)(crc8_update(0x{CRC8_INIT:02X}u, data, len)"
        f" ^ 0x{CRC8_XOR_OUT:02X}u);",
        "}",
        "",
        "/* The DataID is digested first and never travels: a frame copied under another id",
        " * fails its CRC. */",
        "static uint8_t frame_crc(uint16_t data_id, const uint8_t *frame, size_t len)",
        "{",
        "    uint8_t id[2];",
        "    id[0] = (uint8_t)(data_id & 0xFFu);",
        "    id[1] = (uint8_t)(data_id >> 8);",
        f"    return (uint8_t)(crc8_update(crc8_update(0x{CRC8_INIT:02X}u, id, 2u), frame + 1,"
        f" len - 1u) ^ 0x{CRC8_XOR_OUT:02X}u);",
        "}",
    ]
    for name, helper in _HELPERS.items():
        if name in used:
            out += ["", *helper]
    out += body
    return "\n".join(out) + "\n"


def _render_encode(m: CMessage) -> tuple[list[str], set[str]]:
    used: set[str] = set()
    length = f"HANDCTL_{m.macro}_LENGTH"
    lines = _prototype("int", f"{PREFIX}_{m.ident}_encode", _encode_params(m), "")
    lines.append("{")
    scaled = [s for s in m.signals if not s.integer]
    lines += [f"    double raw_{s.field};" for s in scaled]
    if scaled:
        lines.append("")
    lines += [
        "    if (out == NULL || msg == NULL) {",
        "        return HANDCTL_ERR_ARG;",
        "    }",
        f"    if (out_len < {length}) {{",
        "        return HANDCTL_ERR_LENGTH;",
        "    }",
    ]
    for s in m.signals:
        unsigned = not s.spec.signed
        if s.integer:
            conds = []
            if s.raw_lo > s.type_lo:
                conds.append(f"msg->{s.field} < {c_int(s.raw_lo, unsigned)}")
            if s.raw_hi < s.type_hi:
                conds.append(f"msg->{s.field} > {c_int(s.raw_hi, unsigned)}")
            if conds:
                lines += [
                    f"    if ({' || '.join(conds)}) {{",
                    "        return HANDCTL_ERR_RANGE;",
                    "    }",
                ]
            continue
        quotient = f"msg->{s.field}"
        if s.spec.offset != 0:  # x - 0.0 == x for every double, so the host's subtraction is
            quotient = f"({quotient} - {c_double(s.spec.offset)})"  # left out when offset is 0
        lines += [
            f"    raw_{s.field} = nearbyint({quotient} / {c_double(s.spec.scale)});",
            f"    if (!(raw_{s.field} >= {c_double(float(s.raw_lo))} && raw_{s.field} <= "
            f"{c_double(float(s.raw_hi))})) {{",
            "        return HANDCTL_ERR_RANGE;",
            "    }",
        ]
    lines.append("    out[1] = counter;")
    for s in m.signals:
        stmt, helpers = _store(s, f"msg->{s.field}" if s.integer else f"raw_{s.field}")
        lines.append(f"    {stmt}")
        used |= helpers
    lines += [f"    out[{i}] = 0u;" for i in _gaps(m)]
    lines += [
        f"    out[0] = frame_crc(HANDCTL_{m.macro}_DATA_ID, out, {length});",
        "    return HANDCTL_OK;",
        "}",
    ]
    return lines, used


def _render_decode(m: CMessage) -> tuple[list[str], set[str]]:
    used: set[str] = set()
    length = f"HANDCTL_{m.macro}_LENGTH"
    lines = _prototype("int", f"{PREFIX}_{m.ident}_decode", _decode_params(m), "")
    lines.append("{")
    # raw * scale + offset must round twice, as on the host. A compiler may fuse it into one
    # FMA (GCC in GNU modes, whatever the STDC FP_CONTRACT pragma says); a volatile product
    # cannot be fused. Only signals with an offset pay for it.
    offsets = [s for s in m.signals if not s.integer and s.spec.offset != 0]
    lines += [f"    volatile double product_{s.field};" for s in offsets]
    if offsets:
        lines.append("")
    lines += [
        "    if (in == NULL || counter == NULL || msg == NULL) {",
        "        return HANDCTL_ERR_ARG;",
        "    }",
        f"    if (len != {length}) {{",
        "        return HANDCTL_ERR_LENGTH;",
        "    }",
        f"    if (frame_crc(HANDCTL_{m.macro}_DATA_ID, in, len) != in[0]) {{",
        "        return HANDCTL_ERR_CRC;",
        "    }",
        "    *counter = in[1];",
    ]
    for s in m.signals:
        bits, signed, at = s.spec.size_bits, s.spec.signed, s.spec.offset_byte
        if bits == 8 and not signed:
            raw = f"in[{at}]"
        else:
            helper = f"get_{'i' if signed else 'u'}{bits}"
            used.add(helper)
            raw = f"{helper}(in + {at})"
        if s.integer:
            lines.append(f"    msg->{s.field} = {raw};")
            continue
        product = f"(double){raw} * {c_double(s.spec.scale)}"
        if s.spec.offset == 0:
            lines.append(f"    msg->{s.field} = {product};")
        else:
            lines += [
                f"    product_{s.field} = {product};",
                f"    msg->{s.field} = product_{s.field} + {c_double(s.spec.offset)};",
            ]
    lines += ["    return HANDCTL_OK;", "}"]
    return lines, used


def _render_by_id(messages: list[CMessage]) -> tuple[list[str], set[str]]:
    used: set[str] = set()
    lines = ["", "int handctl_frame_length(uint32_t frame_id)", "{", "    switch (frame_id) {"]
    for m in messages:
        lines += [
            f"    case HANDCTL_{m.macro}_FRAME_ID:",
            f"        return (int)HANDCTL_{m.macro}_LENGTH;",
        ]
    lines += ["    default:", "        return HANDCTL_ERR_ID;", "    }", "}"]

    lines += ["", "int handctl_signal_count(uint32_t frame_id)", "{", "    switch (frame_id) {"]
    for m in messages:
        lines += [f"    case HANDCTL_{m.macro}_FRAME_ID:", f"        return {len(m.signals)};"]
    lines += ["    default:", "        return HANDCTL_ERR_ID;", "    }", "}"]

    lines += [""]
    lines += _prototype(
        "int",
        "handctl_encode_by_id",
        [
            "uint32_t frame_id",
            "uint8_t *out",
            "size_t out_len",
            "uint8_t counter",
            "const double *values",
            "size_t n_values",
        ],
        "",
    )
    lines += [
        "{",
        "    if (values == NULL) {",
        "        return HANDCTL_ERR_ARG;",
        "    }",
        "    switch (frame_id) {",
    ]
    for m in messages:
        integers = [s for s in m.signals if s.integer]
        lines += [f"    case HANDCTL_{m.macro}_FRAME_ID: {{", f"        {m.struct} msg;"]
        if integers:
            lines.append("        double raw;")
            used.add("whole")
        lines += [
            f"        if (n_values != {len(m.signals)}u) {{",
            "            return HANDCTL_ERR_ARG;",
            "        }",
        ]
        for i, s in enumerate(m.signals):
            if s.integer:
                lines += [
                    f"        if (whole(values[{i}], {c_double(float(s.type_lo))}, "
                    f"{c_double(float(s.type_hi))}, &raw) != HANDCTL_OK) {{",
                    "            return HANDCTL_ERR_RANGE;",
                    "        }",
                    f"        msg.{s.field} = ({s.raw_type})raw;",
                ]
            else:
                lines.append(f"        msg.{s.field} = values[{i}];")
        lines += [
            f"        return {PREFIX}_{m.ident}_encode(out, out_len, counter, &msg);",
            "    }",
        ]
    lines += ["    default:", "        return HANDCTL_ERR_ID;", "    }", "}"]

    lines += [""]
    lines += _prototype(
        "int",
        "handctl_decode_by_id",
        [
            "uint32_t frame_id",
            "const uint8_t *in",
            "size_t len",
            "uint8_t *counter",
            "double *values",
            "size_t n_values",
        ],
        "",
    )
    lines += [
        "{",
        "    if (values == NULL) {",
        "        return HANDCTL_ERR_ARG;",
        "    }",
        "    switch (frame_id) {",
    ]
    for m in messages:
        lines += [
            f"    case HANDCTL_{m.macro}_FRAME_ID: {{",
            f"        {m.struct} msg;",
            "        int rc;",
            f"        if (n_values < {len(m.signals)}u) {{",
            "            return HANDCTL_ERR_ARG;",
            "        }",
            f"        rc = {PREFIX}_{m.ident}_decode(in, len, counter, &msg);",
            "        if (rc != HANDCTL_OK) {",
            "            return rc;",
            "        }",
        ]
        for i, s in enumerate(m.signals):
            cast = "(double)" if s.integer else ""
            lines.append(f"        values[{i}] = {cast}msg.{s.field};")
        lines += ["        return HANDCTL_OK;", "    }"]
    lines += ["    default:", "        return HANDCTL_ERR_ID;", "    }", "}"]
    return lines, used


def generate(dbc: Path, hand: Path | None = None) -> dict[str, str]:
    """File name -> text of the C codec for ``dbc``, or for the protocol of ``hand``."""
    protocol, db, dbc_name, option = read_protocol(dbc, hand)
    senders = {msg.name: tuple(msg.senders) for msg in db.messages}
    messages = build_messages(protocol.layouts, senders)
    command = "python tools/gen_c_codec.py" + option
    version = db.version or ""
    return {
        HEADER_NAME: render_header(messages, command, dbc_name, version),
        SOURCE_NAME: render_source(messages, command, dbc_name, version),
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0] if __doc__ else None)
    inputs = parser.add_mutually_exclusive_group()
    inputs.add_argument("--dbc", type=Path, default=DEFAULT_DBC, help="DBC to read")
    inputs.add_argument(
        "--hand",
        type=Path,
        help="hand config (HAND.yaml) whose generated protocol to read, instead of a DBC",
    )
    parser.add_argument("--out", type=Path, default=DEFAULT_OUT, help="directory to write to")
    parser.add_argument(
        "--check",
        action="store_true",
        help="write nothing; exit 1 if the files on disk are not up to date",
    )
    args = parser.parse_args(argv)
    try:
        files = generate(args.dbc, args.hand)
    except (GenerationError, ValueError) as exc:  # ConfigError is a ValueError
        print(f"gen_c_codec.py: {exc}", file=sys.stderr)
        return 2
    source = display_path(args.hand if args.hand is not None else args.dbc)
    return write_or_check(
        "gen_c_codec.py",
        {args.out / name: text for name, text in files.items()},
        source,
        "python tools/gen_c_codec.py",
        args.check,
    )


if __name__ == "__main__":
    sys.exit(main())
