"""The CAN protocol, compiled once from ``firmware_protocol/handctl.dbc`` into fast frame layouts.

The DBC is the one source of every frame. cantools reads it here, once, at start-up; the hot
path then packs and unpacks with precompiled ``struct`` layouts and a table CRC, because a
cantools call per frame costs tens of microseconds and a 1 kHz tick has nine joints to serve.
The rounding is the DBC's (raw = round-half-even((value - offset) / scale)), the same as cantools
and the generated C codec, so host, emulated nodes and firmware agree to the bit.

Conventions every message follows (checked when the DBC is compiled, so a DBC edit that breaks
them fails loudly instead of producing frames the receivers reject):
- byte 0 is ``Crc``, byte 1 is ``Counter``; every other signal is byte-aligned little-endian of
  8, 16 or 32 bits;
- the CRC is CRC-8/AUTOSAR (polynomial 0x2F, initial value 0xFF, final XOR 0xFF, no
  reflection) over the message's 16-bit ``DataID`` (low byte, then high byte) followed by the
  payload bytes 1..n-1; the DataID never travels, so a frame copied under another id fails;
- ``Counter`` is per message and sender, +1 per frame, wrapping 255 -> 0.
"""

from __future__ import annotations

import codecs
import enum
import logging
import math
import re
import struct
from collections.abc import Sequence
from dataclasses import dataclass
from functools import cache
from pathlib import Path
from typing import Any

from handctl.errors import ConfigError, Description, ProtocolError
from handctl.schema import read_input

# cantools warns through logging of two messages on one id; with no handler set up, Python
# printed that as a bare line before handctl's own message about the same clash
logging.getLogger("cantools").addHandler(logging.NullHandler())

DEFAULT_DBC = Path(__file__).resolve().parent.parent / "firmware_protocol" / "handctl.dbc"
#: bytes of a DBC: 17 times the largest one a hand generates (15 nodes of six joints, 58 KiB),
#: room for a hand-written one's comments. cantools holds hundreds of bytes per byte it
#: parses: a DBC padded to 10 MB took 13 s and 2.2 GB, and one of 100 MB ran out of memory,
#: which was then said as a syntax error
MAX_DBC_BYTES = 1024 * 1024

#: The largest DataID: 16 bits, low byte then high byte at the start of every CRC.
MAX_DATA_ID = 0xFFFF
CRC8_POLY = 0x2F
CRC8_INIT = 0xFF
CRC8_XOR_OUT = 0xFF


class NodeState(enum.IntEnum):
    """A node's device state, as it travels in every ``State`` signal (the DBC's value table).

    One state model for both ends: the host driver, the safety checks and the bring-up tools
    read it, the simulated nodes send it. A frame may carry a value outside it (the signal has
    eight bits) and a node not yet heard has none, so the host keeps the state as a plain int
    and names it with ``node_state_name``.
    """

    DISABLED = 0
    ENABLED = 1
    FAULT = 2


def node_state_name(value: int, unknown: str = "UNKNOWN") -> str:
    """The name of a ``State`` value, or ``unknown`` for a value the protocol does not define."""
    try:
        return NodeState(value).name
    except ValueError:
        return unknown


#: The DBC's ``VERSION`` string: "handctl protocol N", N the integer every node reports in its
#: Status (``ProtocolVersion``) and the host compares with its own. ASCII digits only: ``\d``
#: took any script's digits, and ``int`` of thousands of them raised a ValueError (a traceback).
_VERSION = re.compile(r"handctl protocol ([0-9]+)")
#: The largest N: ``ProtocolVersion`` is one byte (firmware_protocol/PROTOCOL.md), so a node
#: could never report a larger one, and every run stopped on its first Status.
MAX_PROTOCOL_VERSION = 0xFF
#: What a message's ``HandctlSend`` attribute names: how it is sent (``busload.py``).
SEND_CHOICES = ("event", "loop", "cyclic")
#: the data lengths a CAN-FD frame can have (its DLC codes), bytes
FD_DLC_SIZES = (0, 1, 2, 3, 4, 5, 6, 7, 8, 12, 16, 20, 24, 32, 48, 64)
#: s, how often a node sends its Heartbeat (firmware_protocol/PROTOCOL.md): a host's heartbeat
#: watchdog must wait longer than this
HEARTBEAT_PERIOD_S = 0.1
#: s, how long an ENABLED node waits for an accepted TorqueCommand before it latches TIMEOUT
#: (firmware_protocol/PROTOCOL.md, the command watchdog)
COMMAND_WATCHDOG_S = 0.010
#: Hz, the slowest host loop a hand config may name: a tick every half of the command
#: watchdog, so that one late tick does not trip it. What a hand can run at is slower still
#: than that bound allows: see ``loop_tolerance``
MIN_LOOP_RATE_HZ = 2.0 / COMMAND_WATCHDOG_S
#: s, of the command watchdog, left to what the host's tick count does not see: a frame
#: waiting behind others on the bus, the node's own 1 ms tick on which it checks the watchdog
NODE_TIMING_MARGIN_S = 0.002
#: s, how often a node sends its Feedback, in every state and at any loop rate
#: (firmware_protocol/PROTOCOL.md): a host's feedback watchdog must wait longer than this
FEEDBACK_PERIOD_S = 0.001


def most_misses_before_watchdog(loop_rate_hz: float) -> int:
    """The most consecutive missed ticks a host at ``loop_rate_hz`` may allow before its
    LOOP_OVERRUN stop (``safety.max_consecutive_misses``) so that it stops before a node's
    command watchdog would: the command gap it then allows, that many periods and the one
    the next command is late in, with ``NODE_TIMING_MARGIN_S`` to spare, stays within the
    watchdog. 0: none; the loop is too slow. A 200 Hz hand stopped on its nodes' TIMEOUT (a
    latched fault) with no missed tick at all: a tick late by most of its 5 ms period was
    already the node's 10 ms."""
    budget = (COMMAND_WATCHDOG_S - NODE_TIMING_MARGIN_S) * loop_rate_hz
    return max(0, math.floor(budget + 1e-9) - 1)


def slowest_loop_rate_hz() -> float:
    """Hz, the slowest loop that allows one missed tick (``most_misses_before_watchdog``)."""
    return 2.0 / (COMMAND_WATCHDOG_S - NODE_TIMING_MARGIN_S)


#: ``Command`` values of NodeCommand frames.
NODE_COMMANDS = {"enable": 1, "disable": 2, "fault_reset": 3}
#: ``Reason`` values of EStop frames.
ESTOP_REASONS = {"operator": 1, "host_safety": 2, "host_shutdown": 3}


def _crc_table() -> tuple[int, ...]:
    table = []
    for byte in range(256):
        crc = byte
        for _ in range(8):
            crc = ((crc << 1) ^ CRC8_POLY) & 0xFF if crc & 0x80 else (crc << 1) & 0xFF
        table.append(crc)
    return tuple(table)


CRC8_TABLE = _crc_table()


def crc8(data: bytes, start: int = CRC8_INIT) -> int:
    """CRC-8/AUTOSAR of ``data`` continuing from register value ``start`` (final XOR applied)."""
    crc = start
    table = CRC8_TABLE
    for byte in data:
        crc = table[crc ^ byte]
    return crc ^ CRC8_XOR_OUT


def _crc_register(data: bytes) -> int:
    """The CRC register after ``data`` (no final XOR): lets a layout pre-digest its DataID."""
    crc = CRC8_INIT
    for byte in data:
        crc = CRC8_TABLE[crc ^ byte]
    return crc


@dataclass(frozen=True)
class SignalSpec:
    name: str
    offset_byte: int
    size_bits: int
    signed: bool
    scale: float
    offset: float
    minimum: float  # physical, from the DBC
    maximum: float
    unit: str

    @property
    def is_integer(self) -> bool:
        """Integer signals (scale 1, offset 0) are exchanged as ints, not floats."""
        return self.scale == 1 and self.offset == 0

    def carried_range(self) -> tuple[float, float]:
        """The physical values the signal can take on the wire (low, high): the DBC's range
        within what its bits hold. A configured limit outside it can be neither sent nor
        observed, so the hand config is checked against it (``handctl/wirelimits.py``)."""
        lo, hi = _raw_bounds(self)
        ends = (lo * self.scale + self.offset, hi * self.scale + self.offset)
        return min(ends), max(ends)

    def decoded_range(self) -> tuple[float, float]:
        """The physical values a decode of the signal can give (low, high): all its bits
        hold, the DBC's range aside, since ``decode`` clips nothing. No value read off the
        wire lies outside it, so a log's value beyond it was never read (a joint angle of
        1e9 rad: ``handctl/recording/series.py``). Computed as ``decode`` scales, so its
        ends are exactly the values a decode of the extreme raw values gives."""
        lo, hi = _bit_bounds(self)
        ends = (lo * self.scale + self.offset, hi * self.scale + self.offset)
        return min(ends), max(ends)


_STRUCT_CODES = {
    (8, False): "B",
    (8, True): "b",
    (16, False): "H",
    (16, True): "h",
    (32, False): "I",
    (32, True): "i",
}


class Layout:
    """One message of the DBC, ready for the hot path.

    ``encode`` and ``decode`` take and give the physical values of the signals after Crc and
    Counter, in DBC start-bit order; they do no validation beyond what keeps bytes honest
    (range on encode, length and CRC on ``crc_ok``): the receiver decides what a bad frame means.
    """

    def __init__(
        self,
        name: str,
        frame_id: int,
        length: int,
        data_id: int,
        send: str,
        cycle_time_ms: int | None,
        signals: tuple[SignalSpec, ...],
        comment: str,
    ) -> None:
        self.name = name
        self.frame_id = frame_id
        self.length = length
        self.data_id = data_id
        self.send = send
        self.cycle_time_ms = cycle_time_ms
        self.signals = signals
        self.comment = comment
        kind, _, node = name.partition("_")
        self.kind = kind
        self.node = int(node) if node.isdigit() else None
        self.signal_names = tuple(s.name for s in signals)
        fmt = "<BB"
        cursor = 2
        for sig in signals:
            if sig.offset_byte > cursor:
                fmt += "x" * (sig.offset_byte - cursor)
            fmt += _STRUCT_CODES[(sig.size_bits, sig.signed)]
            cursor = sig.offset_byte + sig.size_bits // 8
        fmt += "x" * (length - cursor)
        self._struct = struct.Struct(fmt)
        self._crc_start = _crc_register(bytes((data_id & 0xFF, data_id >> 8)))

        self._compile_fast_paths()

    def __repr__(self) -> str:
        return f"Layout({self.name}, id=0x{self.frame_id:03X}, {self.length} bytes)"

    # The three hot-path methods are generated per message from the DBC, once: straight-line
    # code with the scales as literals and the CRC unrolled runs several times faster than a
    # generic loop over signal descriptions, and a 1 kHz tick codes six frames.
    def encode(self, counter: int, values: Sequence[float]) -> bytes:
        """Pack physical values into a complete frame payload with counter and CRC."""
        raise NotImplementedError  # replaced per instance by the compiled fast path

    def crc_ok(self, data: bytes) -> bool:
        """True when ``data`` has this message's length and a CRC matching its DataID."""
        raise NotImplementedError  # replaced per instance by the compiled fast path

    def decode(self, data: bytes) -> tuple[int, tuple[float, ...]]:
        """Unpack a frame of the right length into (counter, physical values)."""
        raise NotImplementedError  # replaced per instance by the compiled fast path

    def _encode_checked(self, counter: int, values: Sequence[float]) -> bytes:
        """The slow path: says exactly which value is wrong, then raises."""
        if len(values) != len(self.signals):
            raise ProtocolError(
                f"{self.name}: expected {len(self.signals)} values "
                f"({', '.join(self.signal_names)}), found {len(values)}"
            )
        for value, spec in zip(values, self.signals, strict=True):
            lo, hi = _raw_bounds(spec)
            try:
                raw = (
                    value
                    if spec.is_integer and isinstance(value, int)
                    else round((value - spec.offset) / spec.scale)
                )
                ok = lo <= raw <= hi
            except (ValueError, OverflowError, TypeError):  # NaN, infinity, not a number
                ok = False
            if not ok:
                raise ProtocolError(
                    f"{self.name}.{spec.name}: expected a value in "
                    f"[{spec.minimum:g}, {spec.maximum:g}] {spec.unit}, found {value!r}"
                )
        raise ProtocolError(f"{self.name}: cannot encode {values!r}")  # pragma: no cover

    def _compile_fast_paths(self) -> None:
        n = len(self.signals)
        vs = [f"v{i}" for i in range(n)]
        rs = [f"r{i}" for i in range(n)]
        conv = []
        checks = []
        scaled = []
        for i, spec in enumerate(self.signals):
            lo, hi = _raw_bounds(spec)
            checks.append(f"{lo!r} <= r{i} <= {hi!r}")
            if spec.is_integer:
                conv.append(f"        r{i} = v{i} if type(v{i}) is int else round(v{i})")
                scaled.append(f"a{i}")
            elif spec.offset == 0:
                conv.append(f"        r{i} = round(v{i} / {spec.scale!r})")
                scaled.append(f"a{i} * {spec.scale!r}")
            else:
                conv.append(f"        r{i} = round((v{i} - {spec.offset!r}) / {spec.scale!r})")
                scaled.append(f"a{i} * {spec.scale!r} + {spec.offset!r}")

        def crc_expr(src: str) -> str:
            expr = str(self._crc_start)
            for k in range(1, self.length):
                expr = f"T[{expr} ^ {src}[{k}]]"
            return f"({expr} ^ {CRC8_XOR_OUT})"

        unpack_names = ", ".join(["_", "c", *[f"a{i}" for i in range(n)]])
        source = "\n".join(
            [
                "def encode(counter, values):",
                "    try:",
                f"        {', '.join(vs)}{',' if n == 1 else ''} = values",
                *conv,
                "    except (ValueError, OverflowError, TypeError):",
                "        return slow(counter, values)",
                f"    if not ({' and '.join(checks) or 'True'}):",
                "        return slow(counter, values)",
                "    c = counter & 255",
                f"    body = pack(0, c, {', '.join(rs)})",
                f"    return pack({crc_expr('body')}, c, {', '.join(rs)})",
                "",
                "def crc_ok(data):",
                f"    return len(data) == {self.length} and {crc_expr('data')} == data[0]",
                "",
                "def decode(data):",
                f"    {unpack_names} = unpack(data)",
                f"    return c, ({', '.join(scaled)}{',' if n == 1 else ''})",
            ]
        )
        namespace: dict[str, Any] = {
            "T": CRC8_TABLE,
            "pack": self._struct.pack,
            "unpack": self._struct.unpack,
            "slow": self._encode_checked,
        }
        exec(compile(source, f"<layout {self.name}>", "exec"), namespace)
        # Bound straight onto the instance: one call layer less on the hot path.
        self.encode = namespace["encode"]  # type: ignore[method-assign]
        self.crc_ok = namespace["crc_ok"]  # type: ignore[method-assign]
        self.decode = namespace["decode"]  # type: ignore[method-assign]
        self.fast_source = source


def _bit_bounds(sig: SignalSpec) -> tuple[int, int]:
    """The raw range the signal's bits hold."""
    bits = sig.size_bits
    return (-(1 << (bits - 1)), (1 << (bits - 1)) - 1) if sig.signed else (0, (1 << bits) - 1)


def _raw_bounds(sig: SignalSpec) -> tuple[float, float]:
    """The raw range a value may take: the DBC's physical range within what the bits hold."""
    lo_bits, hi_bits = _bit_bounds(sig)
    if sig.minimum == sig.maximum == 0:  # no range given in the DBC: the bits decide
        return lo_bits, hi_bits
    lo = math.ceil(round((sig.minimum - sig.offset) / sig.scale, 6))
    hi = math.floor(round((sig.maximum - sig.offset) / sig.scale, 6))
    return max(lo, lo_bits), min(hi, hi_bits)


class Protocol:
    """Every layout of a DBC, by name and by CAN id."""

    def __init__(
        self, layouts: Sequence[Layout], source: str, version: int = 0, text: str = ""
    ) -> None:
        self.source = source
        #: The DBC text the layouts were compiled from: what a recording keeps, so that a
        #: replay speaks the very protocol the run spoke.
        self.text = text
        #: The protocol version of the DBC (its ``VERSION``), which nodes report in Status.
        self.version = version
        self.layouts = tuple(layouts)
        self.by_name = {layout.name: layout for layout in layouts}
        self.by_id = {layout.frame_id: layout for layout in layouts}

    def layout(self, kind: str, node: int | None = None) -> Layout:
        """The layout of message ``kind`` for ``node`` (e.g. ``("Feedback", 2)``)."""
        name = kind if node is None else f"{kind}_{node}"
        try:
            return self.by_name[name]
        except KeyError:
            raise ProtocolError(f"{self.source}: no message {name} in the DBC") from None


#: The protocol version whose Status had no ``ProtocolVersion`` yet (8 bytes long).
UNVERSIONED_PROTOCOL = 1
#: Byte of Status that carries ``ProtocolVersion`` in every version since the field came.
STATUS_VERSION_BYTE = 8
_UNVERSIONED_STATUS_LENGTH = 8


def foreign_status_version(layout: Layout, data: bytes) -> int | None:
    """The protocol version a Status frame of another length than ``layout``'s announces, or
    None if it is no intact Status at all.

    Status only ever grows and keeps ``ProtocolVersion`` at byte 8 (PROTOCOL.md, "Versions"),
    and its CRC covers whatever length it has, so a host can name the version of a node that
    speaks another one instead of only counting its frames as the wrong length; an intact
    8-byte Status is a node of protocol 1, from before the field. The frame is still rejected.
    """
    if len(data) == layout.length or len(data) < _UNVERSIONED_STATUS_LENGTH:
        return None
    if crc8(data[1:], layout._crc_start) != data[0]:
        return None
    if len(data) == _UNVERSIONED_STATUS_LENGTH:
        return UNVERSIONED_PROTOCOL
    return data[STATUS_VERSION_BYTE]


@cache
def load_protocol(path: str | Path = DEFAULT_DBC) -> Protocol:
    """Compile a DBC file into layouts; cached, since the DBC does not change while we run.

    DBC files are Windows-1252 text by convention (cantools reads them so too); one that starts
    with a UTF-8 byte order mark, as some editors save, is UTF-8 by that mark. Read as
    Windows-1252 the mark was three letters before VERSION, and the file was refused as
    "Invalid syntax" at a place nothing showed wrong."""
    name = str(path)
    raw = read_input(path, "a readable DBC file", MAX_DBC_BYTES)
    _check_size(len(raw), name)
    bom = raw.startswith(codecs.BOM_UTF8)
    skip = len(codecs.BOM_UTF8) if bom else 0
    try:
        text = raw[skip:].decode("utf-8" if bom else "cp1252")
    except UnicodeDecodeError as exc:
        at = skip + exc.start
        raise ConfigError(
            name,
            "",
            "UTF-8 text (the file starts with a UTF-8 byte order mark)"
            if bom
            else "Windows-1252 text",
            Description(f"byte 0x{raw[at]:02X} at offset {at}"),
        ) from None
    return parse_protocol(text, name)


@cache
def parse_protocol(text: str, source: str) -> Protocol:
    """Compile DBC ``text`` (named ``source`` in messages) into layouts; cached by text, so a
    hand's generated DBC is parsed once however many commands ask for it."""
    import cantools  # only here: the hot path never touches cantools

    _check_size(len(text), source)  # a recording's DBC, which no file read bounded
    try:
        db: Any = cantools.database.load_string(text, database_format="dbc", strict=True)
    except Exception as exc:  # cantools raises many kinds of parse errors
        # the parser's whole message (cut to 80 characters, which signals overlap went)
        raise ConfigError(
            source, "", "a valid DBC", Description(f"{type(exc).__name__}: {exc}")
        ) from None
    send_choices = _enum_choices(db, "HandctlSend", source)
    layouts = [_compile(message, source, send_choices) for message in db.messages]
    frame_ids: dict[int, str] = {}
    for layout in layouts:
        # before the DataIDs: a DBC names a message's attributes by its frame id, so two
        # messages on one id share them, and the clash was said as one of DataIDs
        if layout.frame_id in frame_ids:
            raise ConfigError(
                source,
                f"{layout.name} id",
                f"a CAN id not used by {frame_ids[layout.frame_id]}",
                Description(f"0x{layout.frame_id:03X}, {frame_ids[layout.frame_id]}'s"),
            )
        frame_ids[layout.frame_id] = layout.name
    data_ids: dict[int, str] = {}
    for layout in layouts:
        if layout.data_id in data_ids:
            raise ConfigError(
                source,
                f"{layout.name}.DataID",
                f"a DataID not used by {data_ids[layout.data_id]}",
                layout.data_id,
            )
        data_ids[layout.data_id] = layout.name
    return Protocol(layouts, source, _protocol_version(db.version, source), text)


def _check_size(size: int, source: str) -> None:
    """Refuse a DBC longer than ``MAX_DBC_BYTES`` (bytes, or characters of its text, which
    are no more) before cantools parses it."""
    if size > MAX_DBC_BYTES:
        raise ConfigError(
            source,
            "",
            f"a DBC of at most {MAX_DBC_BYTES} bytes (a hand's generated one is under 64 KiB)",
            Description(f"more than {MAX_DBC_BYTES} bytes"),
        )


def _protocol_version(text: str | None, source: str) -> int:
    """The N of ``VERSION "handctl protocol N"``: what nodes and host compare, so it must be
    there and be a number."""
    match = _VERSION.fullmatch(text or "")
    # the length first: ``int`` of a number of more than 4300 digits raises
    if match is None or len(match[1]) > 3 or int(match[1]) > MAX_PROTOCOL_VERSION:
        raise ConfigError(
            source,
            "VERSION",
            f'"handctl protocol N" with N a whole number 0..{MAX_PROTOCOL_VERSION} in at most '
            "three ASCII digits (what every node sends in the one byte of its Status' "
            "ProtocolVersion: "
            "firmware_protocol/PROTOCOL.md)",
            text or "nothing",
        )
    return int(match[1])


def _enum_choices(db: Any, attribute: str, source: str) -> list[str]:
    """The names of the ENUM ``attribute``'s values, by value; none if the DBC does not
    define it. An INT or STRING definition was a traceback where a message's value was looked
    up in its choices (an IndexError, a TypeError)."""
    definition = db.dbc.attribute_definitions.get(attribute) if db.dbc else None
    if definition is None:
        return []
    if definition.type_name != "ENUM" or not definition.choices:
        raise ConfigError(
            source,
            f"BA_DEF_ {attribute}",
            "an ENUM attribute: " + ",".join(f'"{choice}"' for choice in SEND_CHOICES),
            Description(f"{definition.type_name} {definition.choices or ''}".strip()),
        )
    return [str(choice) for choice in definition.choices]


def _compile(message: Any, source: str, send_choices: list[str]) -> Layout:
    where = message.name
    if message.is_extended_frame:
        # handctl speaks 11-bit ids only (online/bus.py) and takes a 29-bit frame for none of
        # its own: a DBC that declares one passed every check, and firmware built from it
        # sends frames the host never reads (every run a HEARTBEAT_LOST, the bus budgeted
        # for shorter frames than sent)
        raise ConfigError(
            source,
            f"{where} id",
            "an 11-bit (standard) CAN id",
            Description(f"the extended (29-bit) id 0x{message.frame_id:08X}"),
        )
    if message.length not in FD_DLC_SIZES[1:]:
        # a CAN-FD frame carries one of these lengths, 64 bytes at most: a longer one was a
        # traceback from the bus budget (and a C codec was generated for it), one between
        # them was budgeted as sent while a controller pads it to the next
        raise ConfigError(
            source,
            f"{where} length",
            "a CAN-FD data length: " + ", ".join(map(str, FD_DLC_SIZES[1:])) + " bytes",
            message.length,
        )
    signals = sorted(message.signals, key=lambda s: s.start)
    names = [s.name for s in signals[:2]]
    if names != ["Crc", "Counter"] or any(s.length != 8 for s in signals[:2]):
        raise ConfigError(source, where, "Crc (byte 0) and Counter (byte 1) of 8 bits", names)
    specs = []
    for sig in signals[2:]:
        if (
            sig.byte_order != "little_endian"
            or sig.start % 8
            or sig.length not in (8, 16, 32)
            or sig.is_float
        ):
            raise ConfigError(
                source,
                f"{where}.{sig.name}",
                "a byte-aligned little-endian integer of 8, 16 or 32 bits",
                f"start {sig.start}, {sig.length} bits, {sig.byte_order}",
            )
        scale, offset = float(sig.scale), float(sig.offset)
        if not (math.isfinite(scale) and scale > 0 and math.isfinite(offset)):
            # every range and rounding here divides by the factor and takes it to keep the
            # order of values: zero divides by zero, a negative one turns every range over
            raise ConfigError(
                source,
                f"{where}.{sig.name}",
                "a finite factor > 0 and a finite offset",
                f"factor {sig.scale}, offset {sig.offset}",
            )
        low, high = sig.minimum, sig.maximum
        if low is not None and high is not None and not low <= high:
            # a range turned over holds no value: every frame of it was refused mid-run (a
            # jog stopped on CLOCK_EXCEPTION) or the host had a limit it could not send
            raise ConfigError(
                source,
                f"{where}.{sig.name}",
                "a range [min|max] with min <= max",
                f"[{low}|{high}]",
            )
        specs.append(
            SignalSpec(
                name=sig.name,
                offset_byte=sig.start // 8,
                size_bits=sig.length,
                signed=sig.is_signed,
                scale=float(sig.scale),
                offset=float(sig.offset),
                minimum=float(sig.minimum if sig.minimum is not None else 0.0),
                maximum=float(sig.maximum if sig.maximum is not None else 0.0),
                unit=sig.unit or "",
            )
        )
    attrs = message.dbc.attributes if message.dbc else {}
    if "DataID" not in attrs:
        raise ConfigError(source, f"{where}.DataID", "a DataID attribute", "none")
    data_id = attrs["DataID"].value
    if not isinstance(data_id, int) or not 0 <= data_id <= MAX_DATA_ID:
        # the CRC starts with the DataID's two bytes: 99999 or -1 was a traceback there
        raise ConfigError(
            source,
            f"{where}.DataID",
            f"a whole number 0..{MAX_DATA_ID} (16 bits, the two bytes the CRC starts with)",
            data_id,
        )
    send_attr = attrs.get("HandctlSend")
    send = "event" if send_attr is None else _send(send_attr.value, where, source, send_choices)
    return Layout(
        message.name,
        message.frame_id,
        message.length,
        data_id,
        send,
        message.cycle_time,
        tuple(specs),
        message.comment or "",
    )


def _send(value: object, where: str, source: str, choices: list[str]) -> str:
    """The name of a message's ``HandctlSend`` value, an index into the ENUM's ``choices``.
    One past them was an IndexError (a traceback), and -1 was read as the last choice by
    Python's negative indexing, "cyclic", which the DBC never said."""
    if isinstance(value, bool) or not isinstance(value, int) or not 0 <= value < len(choices):
        raise ConfigError(
            source,
            f"{where}.HandctlSend",
            "one of the attribute's values: "
            + ", ".join(f'{i} "{choice}"' for i, choice in enumerate(choices)),
            value,
        )
    return choices[value]
