"""A logged message checked against its channel's JSON Schema before a reader uses it.

A recording is input like any other: a file altered by hand, or written by another program
with the mcap library, can hold a message that is not JSON, not an object, or whose fields are
missing or of another type. Every reader of a replay (the summary, the plot, the re-run, the
export, the frames onto a bus) takes its messages through ``MessageCheck``, so such a message
is a ``ConfigError`` naming the file, the channel, the message (its log time and tick), the
field, what was expected and what was found, rather than an exception from deep inside.

The checks are the channels' schemas (``channels.CHANNELS``), compiled once into a list of
``(field, required, test, expected)`` per topic, plus what the schema cannot say: a frame's id
is an 11- or 29-bit CAN id and its data hex of at most 64 bytes, and where the hand is known
the joint vectors have one entry per joint and the node vectors one per finger node. A
non-finite number is written as ``null`` (``docs/recording.md``), so every number may be null.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import orjson

from handctl.errors import ConfigError
from handctl.recording import channels as ch

#: The largest CAN id (29 bits).
MAX_CAN_ID = 0x1FFFFFFF
#: The largest standard (11-bit) CAN id.
MAX_STANDARD_ID = 0x7FF
#: Set on a 29-bit frame's id as the host holds and logs it (``online.bus.EXTENDED_ID_FLAG``,
#: SocketCAN's ``CAN_EFF_FLAG``; not imported: the bus module loads python-can)
EXTENDED_ID_FLAG = 0x80000000
#: The longest CAN-FD payload (bytes).
MAX_CAN_DATA = 64
_INT64 = 1 << 63

_Test = Callable[[Any], bool]


def _is_int(value: Any) -> bool:
    return type(value) is int and -_INT64 <= value < _INT64


def _is_number(value: Any) -> bool:
    return value is None or (type(value) is float) or _is_int(value)


def _is_str(value: Any) -> bool:
    return type(value) is str


def _is_bool(value: Any) -> bool:
    return type(value) is bool


def _is_can_id(value: Any) -> bool:
    """An 11-bit id, or a 29-bit one with ``EXTENDED_ID_FLAG``, as the host holds and logs
    every frame (a foreign 29-bit frame it received too, and a log with one was refused). An
    id above 11 bits without the flag is no frame a bus carried: a replay put 0x901 on the
    wire, which a controller that keeps 11 bits takes for 0x101, a TorqueCommand."""
    if type(value) is not int:
        return False
    if value & EXTENDED_ID_FLAG:
        return 0 <= value ^ EXTENDED_ID_FLAG <= MAX_CAN_ID
    return 0 <= value <= MAX_STANDARD_ID


def _is_hex_frame(value: Any) -> bool:
    if type(value) is not str or len(value) > 2 * MAX_CAN_DATA:
        return False
    try:
        bytes.fromhex(value)
    except ValueError:
        return False
    return True


_SCALARS: dict[str, tuple[_Test, str]] = {
    "integer": (_is_int, "an integer"),
    "number": (_is_number, "a number (or null)"),
    "string": (_is_str, "a string"),
    "boolean": (_is_bool, "true or false"),
}

#: Fields whose schema says less than a reader relies on.
_SPECIAL: dict[str, tuple[_Test, str]] = {
    "id": (
        _is_can_id,
        f"a CAN id, an integer 0..0x{MAX_STANDARD_ID:X}, or a 29-bit one 0..0x{MAX_CAN_ID:X} "
        f"with 0x{EXTENDED_ID_FLAG:X} set",
    ),
    "data": (_is_hex_frame, f"a frame's payload as hex, at most {MAX_CAN_DATA} bytes"),
}
_FRAME_TOPICS = frozenset({ch.CAN_RX, ch.CAN_TX})
#: The joint vectors and the node vectors of the per-tick channels.
_JOINT_ARRAYS = frozenset(
    {"angle_rad", "tdt_torque_nm", "feedback_age_ns", "desired_nm", "applied_nm"}
)
_NODE_ARRAYS = frozenset({"node_state", "node_fault_bits"})


def _compile(schema: dict[str, Any]) -> tuple[_Test, str]:
    """A test of a value against a (sub)schema, and what it expects in words."""
    kind = schema.get("type")
    if kind in _SCALARS:
        test, expected = _SCALARS[kind]
        if "minimum" in schema:
            low = schema["minimum"]
            scalar = test
            return (
                lambda v: scalar(v) and v is not None and v >= low,
                f"{expected.removesuffix(' (or null)')}, at least {low}",
            )
        if "enum" in schema:
            allowed = frozenset(schema["enum"])
            return (
                lambda v: type(v) is str and v in allowed,
                "one of " + ", ".join(schema["enum"]),
            )
        return test, expected
    if kind == "array":
        item, item_expected = _compile(schema.get("items", {}))
        return (
            lambda v: type(v) is list and all(item(x) for x in v),
            f"an array, each item {item_expected}",
        )
    if kind == "object":
        fields = [(k, *_compile(s)) for k, s in schema.get("properties", {}).items()]
        required = frozenset(schema.get("required", ()))

        def test(v: Any) -> bool:
            if type(v) is not dict:
                return False
            for key, t, _ in fields:
                if key in v:
                    if not t(v[key]):
                        return False
                elif key in required:
                    return False
            return True

        names = ", ".join(f"{k} ({e})" for k, _, e in fields)
        return test, f"an object with {names}" if names else "an object"
    return (lambda v: True), "anything"


_Field = tuple[str, bool, _Test, str]


def _fields(topic: str) -> list[_Field]:
    channel = next(c for c in ch.CHANNELS if c.topic == topic)
    schema = ch.schema_of(channel)
    required = set(schema.get("required", ()))
    out: list[_Field] = []
    for key, sub in schema.get("properties", {}).items():
        test, expected = (
            _SPECIAL[key] if topic in _FRAME_TOPICS and key in _SPECIAL else _compile(sub)
        )
        out.append((key, key in required, test, expected))
    return out


_FIELDS: dict[str, list[_Field]] = {c.topic: _fields(c.topic) for c in ch.CHANNELS}


class MessageCheck:
    """Checks the decoded messages of one recording; ``joints`` and ``nodes`` (when the hand
    is known) are the lengths of the joint and node vectors."""

    def __init__(self, path: str, joints: int | None = None, nodes: int | None = None) -> None:
        self.path = path
        self.joints = joints
        self.nodes = nodes

    def loads(self, topic: str, log_time: int, raw: bytes) -> dict[str, Any]:
        """A message's bytes decoded and checked."""
        try:
            value = orjson.loads(raw)
        except orjson.JSONDecodeError as exc:
            raise self._error(
                topic, log_time, None, "", f"a JSON object (json message encoding; {exc})", raw
            ) from None
        return self.check(topic, log_time, value)

    def check(self, topic: str, log_time: int, value: Any) -> dict[str, Any]:
        """``value`` itself when it is what its channel says; else a ConfigError."""
        if type(value) is not dict:
            raise self._error(topic, log_time, None, "", "a JSON object", value)
        fields = _FIELDS.get(topic)
        if fields is None:
            return value
        for key, required, test, expected in fields:
            if key in value:
                field = value[key]
                if not test(field):
                    raise self._error(topic, log_time, value, key, expected, field)
                if type(field) is list:
                    self._length(topic, log_time, value, key, field)
            elif required:
                raise self._error(topic, log_time, value, key, expected, "nothing")
        return value

    def _length(
        self, topic: str, log_time: int, msg: dict[str, Any], key: str, field: list[Any]
    ) -> None:
        want = self.joints if key in _JOINT_ARRAYS else self.nodes if key in _NODE_ARRAYS else None
        if want is not None and len(field) != want:
            what = "joint" if key in _JOINT_ARRAYS else "finger node"
            raise self._error(
                topic,
                log_time,
                msg,
                key,
                f"{want} values, one per {what} of the recorded hand",
                f"{len(field)} values",
            )

    def _error(
        self,
        topic: str,
        log_time: int,
        msg: dict[str, Any] | None,
        key: str,
        expected: str,
        found: object,
    ) -> ConfigError:
        tick = msg.get("tick") if msg is not None else None
        where = f"{topic} message at log time {log_time} ns" + (
            f" (tick {tick})" if _is_int(tick) and key != "tick" else ""
        )
        return ConfigError(self.path, f"{where}: {key}" if key else where, expected, found)
