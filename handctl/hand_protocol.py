"""The CAN protocol of a hand: a DBC generated from its fingers, or a given DBC held against it.

The hand config describes the device (node ids, joints per node), as a CANopen object dictionary
does; the frames follow from it by the rules of ``firmware_protocol/PROTOCOL.md``, so a hand of
other fingers needs no hand-written DBC. The DBC is generated as text and read back through
``handctl.protocol.parse_protocol``, so cantools stays the one parser and the conventions it
checks hold for generated protocols too. For the default hand the text is the packaged
``firmware_protocol/handctl.dbc`` itself (``tools/gen_dbc.py --check`` and a test hold them
together), so its frames stay byte for byte what they were.

Per node n (1..15) with k joints (1..6):

- ids ``0x010+n`` NodeCommand, ``0x100+n`` TorqueCommand, ``0x180+n`` Feedback, ``0x280+n``
  Status, ``0x700+n`` Heartbeat; DataIDs ``0x1010+n`` .. ``0x1050+n`` (``EStop``: id 0, 0x0F00);
- ``TorqueCommand_n``: ``Torque1..k``; ``Feedback_n``: ``Torque1..k``, ``Angle1..k``, ``State``,
  ``FaultBits``; each payload is padded with zero bytes up to the next CAN-FD DLC size (one
  size more where an erased buffer would pass the CRC: ``frame_length``), which the CRC covers
  like any other byte.

``protocol_for`` is what every command calls: the hand's generated protocol, or a DBC given
with ``--dbc``, checked against the hand so that a firmware of other frames is named before a
frame is sent.
"""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path
from typing import TYPE_CHECKING

from handctl.busload import PROTOCOL_CYCLE_MS, PROTOCOL_SEND, fd_dlc_size
from handctl.errors import ConfigError, Description
from handctl.protocol import (
    ESTOP_REASONS,
    NODE_COMMANDS,
    STATUS_VERSION_BYTE,
    Layout,
    NodeState,
    Protocol,
    crc8,
    load_protocol,
    parse_protocol,
)
from handctl.schema import description

if TYPE_CHECKING:
    from handctl.config import HandConfig

#: The protocol version the generated DBC declares (``VERSION "handctl protocol N"``).
PROTOCOL_VERSION = 2
#: Node ids and joints per node the generated frames can carry: 4 bits of node in the ids and
#: DataIDs, and a Feedback of six joints fills a 32-byte CAN-FD frame.
NODE_IDS = range(1, 16)
MAX_JOINTS = 6
#: Per message kind: the base CAN id (plus the node id) and the base DataID (plus the node id).
ID_BASES = {
    "NodeCommand": 0x010,
    "TorqueCommand": 0x100,
    "Feedback": 0x180,
    "Status": 0x280,
    "Heartbeat": 0x700,
}
DATA_ID_BASES = {
    "NodeCommand": 0x1010,
    "TorqueCommand": 0x1020,
    "Feedback": 0x1030,
    "Status": 0x1040,
    "Heartbeat": 0x1050,
}
#: The hand config's ``can_ids`` keys, by message kind.
CAN_ID_KEYS = {
    "NodeCommand": "node_command",
    "TorqueCommand": "torque_command",
    "Feedback": "feedback",
    "Status": "status",
    "Heartbeat": "heartbeat",
}
#: The e-stop frame's identifier: the highest priority on the bus, and the one every node acts
#: on whatever the frame holds (firmware_protocol/PROTOCOL.md, *E-stop*).
ESTOP_ID = 0x000
ESTOP_DATA_ID = 0x0F00
_NUMBERS = ("one", "two", "three", "four", "five", "six")
_TORQUE = '(0.0001,0) [-3.2768|3.2767] "N.m"'
_ANGLE = '(0.0001,0) [-3.2768|3.2767] "rad"'
_BYTE = '(1,0) [0|255] ""'
_STATE_CHOICES = " ".join(f'{s.value} "{s.name}"' for s in NodeState)
_STATUS_SIGNALS = (
    ("State", '""'),
    ("FaultBits", '""'),
    ("RejectCrc", '"frames"'),
    ("RejectCounter", '"frames"'),
    ("RejectLength", '"frames"'),
    ("CommandAge", '"ms"'),
    ("ProtocolVersion", '""'),
    ("FirmwareMajor", '""'),
    ("FirmwareMinor", '""'),
    ("FirmwarePatch", '""'),
)


def frame_ids(node_id: int) -> dict[str, int]:
    """The CAN id of each message of node ``node_id``, by ``can_ids`` key."""
    return {CAN_ID_KEYS[kind]: base + node_id for kind, base in ID_BASES.items()}


def node_message(frame_id: int) -> tuple[str, int] | None:
    """(message kind, node id) of a node's frame id by the id rule above, or None: how a frame
    of a node the hand does not have (whose frames its DBC therefore lacks) is still named."""
    for kind, base in ID_BASES.items():
        if frame_id - base in NODE_IDS:
            return kind, frame_id - base
    return None


def generate_dbc(shape: Iterable[tuple[int, int]]) -> str:
    """The DBC text of a hand whose nodes are ``(node_id, joints)``, in the order given."""
    nodes = list(shape)
    for node_id, joints in nodes:
        if node_id not in NODE_IDS or not 1 <= joints <= MAX_JOINTS:
            raise ValueError(
                f"a node id 1..15 with 1..{MAX_JOINTS} joints, found node {node_id} with {joints}"
            )
    fingers = [f"FINGER{n}" for n, _ in nodes]
    everyone = ",".join(fingers)
    out = [
        f'VERSION "handctl protocol {PROTOCOL_VERSION}"',
        "",
        "NS_ :",
        "\tBA_DEF_",
        "\tBA_",
        "\tVAL_",
        "\tCM_",
        "",
        "BS_:",
        "",
        f"BU_: HOST {' '.join(fingers)}",
        "",
    ]
    out += _message(ESTOP_ID, "EStop", 3, "HOST", everyone, [("Reason", 16, 8, False, _BYTE)])
    for kind in ("NodeCommand", "TorqueCommand", "Feedback", "Status", "Heartbeat"):
        for node_id, joints in nodes:
            out += _node_message(kind, node_id, joints)
    status_1 = ID_BASES["Status"] + nodes[0][0] if nodes else None
    if status_1 is not None:
        out.append(
            f'CM_ SG_ {status_1} ProtocolVersion "The protocol version the node speaks: '
            "the number in this DBC's VERSION. Stays at byte 8 of Status in every "
            'version.";'
        )
    out.append('CM_ BU_ HOST "The host computer running handctl.";')
    for node_id, joints in nodes:
        k = _NUMBERS[joints - 1]
        out.append(
            f'CM_ BU_ FINGER{node_id} "Finger {node_id} controller: {k} tendon-driven '
            f"joint{'s' if joints > 1 else ''}, {k} TDT torque sensor"
            f'{"s" if joints > 1 else ""}, {k} encoder{"s" if joints > 1 else ""}.";'
        )
    out.append(
        f'CM_ BO_ {ESTOP_ID} "Emergency stop: every node zeroes torque and latches FAULT(ESTOP). '
        'Honoured even with a bad CRC or counter.";'
    )
    comments = {
        "NodeCommand": "Node management for finger {n}: enable, disable, fault reset.",
        "TorqueCommand": "Joint torque command for finger {n}, every loop period.",
        "Feedback": "TDT joint torques, joint angles and node state of finger {n}, every 1 ms "
        "(the node's tick, whatever the host's loop rate).",
        "Status": "Node state, fault bits, receive-error counts, protocol and firmware version "
        "of finger {n}: on change and every 100 ms.",
        "Heartbeat": "Liveness of finger {n}: state and uptime, every 100 ms.",
    }
    for node_id, _ in nodes:
        for kind, text in comments.items():
            out.append(f'CM_ BO_ {ID_BASES[kind] + node_id} "{text.format(n=node_id)}";')
    out += [
        'BA_DEF_  "BusType" STRING ;',
        'BA_DEF_ BO_  "VFrameFormat" ENUM  "StandardCAN","ExtendedCAN","reserved","reserved",'
        '"reserved","reserved","reserved","reserved","reserved","reserved","reserved",'
        '"reserved","reserved","reserved","StandardCAN_FD","ExtendedCAN_FD";',
        'BA_DEF_ BO_  "GenMsgCycleTime" INT 0 10000;',
        'BA_DEF_ BO_  "DataID" INT 0 65535;',
        'BA_DEF_ BO_  "HandctlSend" ENUM  "event","loop","cyclic";',
        'BA_DEF_DEF_  "BusType" "CAN FD";',
        'BA_DEF_DEF_  "VFrameFormat" "StandardCAN_FD";',
        'BA_DEF_DEF_  "GenMsgCycleTime" 0;',
        'BA_DEF_DEF_  "DataID" 0;',
        'BA_DEF_DEF_  "HandctlSend" "event";',
        'BA_ "BusType" "CAN FD";',
        f'BA_ "DataID" BO_ {ESTOP_ID} {ESTOP_DATA_ID};',
    ]
    cycle = PROTOCOL_CYCLE_MS
    # HandctlSend: 1 "loop" (the host's loop period), 2 "cyclic" (GenMsgCycleTime). A node
    # sends its Feedback on its own 1 ms tick, whatever the loop rate: the bus budget of a
    # hand with a slower loop counted it at the loop rate, a third of what the wire carried
    send = {kind: {"loop": 1, "cyclic": 2}[how] for kind, how in PROTOCOL_SEND.items()}
    for node_id, _ in nodes:
        out += [
            f'BA_ "DataID" BO_ {ID_BASES[k] + node_id} {DATA_ID_BASES[k] + node_id};'
            for k in ID_BASES
        ]
        out += [f'BA_ "VFrameFormat" BO_ {ID_BASES[k] + node_id} 14;' for k in ID_BASES]
        out += [
            f'BA_ "GenMsgCycleTime" BO_ {ID_BASES[k] + node_id} {ms};' for k, ms in cycle.items()
        ]
    out.append(f'BA_ "VFrameFormat" BO_ {ESTOP_ID} 14;')
    for node_id, _ in nodes:
        out += [f'BA_ "HandctlSend" BO_ {ID_BASES[k] + node_id} {v};' for k, v in send.items()]
    out.append(f"VAL_ {ESTOP_ID} Reason {_choices(ESTOP_REASONS)} ;")
    for node_id, _ in nodes:
        out.append(f"VAL_ {ID_BASES['NodeCommand'] + node_id} Command {_choices(NODE_COMMANDS)} ;")
        out += [
            f"VAL_ {ID_BASES[k] + node_id} State {_STATE_CHOICES} ;"
            for k in ("Feedback", "Status", "Heartbeat")
        ]
    return "\n".join(out) + "\n"


def _choices(values: dict[str, int]) -> str:
    return " ".join(f'{value} "{name}"' for name, value in values.items())


Signal = tuple[str, int, int, bool, str]  # name, start bit, bits, signed, "(scale,offset) ..."


def _node_message(kind: str, n: int, joints: int) -> list[str]:
    """One message of node ``n`` with ``joints`` joints."""
    sender, receiver = (
        ("HOST", f"FINGER{n}")
        if kind in ("NodeCommand", "TorqueCommand")
        else (f"FINGER{n}", "HOST")
    )
    signals = _node_signals(kind, joints)
    used = max(start + bits for _, start, bits, _, _ in signals) // 8
    return _message(
        ID_BASES[kind] + n,
        f"{kind}_{n}",
        frame_length(DATA_ID_BASES[kind] + n, used),
        sender,
        receiver,
        signals,
    )


def frame_length(data_id: int, used: int) -> int:
    """The length of a message of ``used`` bytes: the smallest CAN-FD size that holds them and
    at which no frame of all 0x00 or all 0xFF bytes passes the CRC of ``data_id`` (so that a
    zeroed or erased buffer is never a valid frame; PROTOCOL.md). Of every message of nodes
    1..15 with 1..6 joints, only Feedback_1 of five joints needs the next size (32, not 24)."""
    size = fd_dlc_size(used)
    while _erased_buffer_passes(data_id, size):
        size = fd_dlc_size(size + 1)
    return size


def _erased_buffer_passes(data_id: int, length: int) -> bool:
    start = bytes((data_id & 0xFF, data_id >> 8))
    return any(crc8(start + bytes([fill]) * (length - 1)) == fill for fill in (0x00, 0xFF))


def _node_signals(kind: str, joints: int) -> list[Signal]:
    """The signals after Crc and Counter of a node's message ``kind``, for ``joints`` joints."""
    signals: list[Signal]
    if kind == "NodeCommand":
        signals = [("Command", 16, 8, False, _BYTE)]
    elif kind == "TorqueCommand":
        signals = [(f"Torque{k + 1}", 16 + 16 * k, 16, True, _TORQUE) for k in range(joints)]
    elif kind == "Feedback":
        signals = [(f"Torque{k + 1}", 16 + 16 * k, 16, True, _TORQUE) for k in range(joints)]
        signals += [
            (f"Angle{k + 1}", 16 + 16 * (joints + k), 16, True, _ANGLE) for k in range(joints)
        ]
        signals += [
            ("State", 16 + 32 * joints, 8, False, _BYTE),
            ("FaultBits", 24 + 32 * joints, 8, False, _BYTE),
        ]
    elif kind == "Status":
        signals = [
            (name, 16 + 8 * i, 8, False, f"(1,0) [0|255] {unit}")
            for i, (name, unit) in enumerate(_STATUS_SIGNALS)
        ]
    else:
        signals = [
            ("State", 16, 8, False, _BYTE),
            ("Uptime", 24, 32, False, '(1,0) [0|4294967295] "ms"'),
        ]
    return signals


def _message(
    frame_id: int, name: str, length: int, sender: str, receivers: str, signals: list[Signal]
) -> list[str]:
    lines = [
        f"BO_ {frame_id} {name}: {length} {sender}",
        f" SG_ Crc : 0|8@1+ {_BYTE} {receivers}",
        f" SG_ Counter : 8|8@1+ {_BYTE} {receivers}",
    ]
    lines += [
        f" SG_ {sig} : {start}|{bits}@1{'-' if signed else '+'} {rest} {receivers}"
        for sig, start, bits, signed, rest in signals
    ]
    return [*lines, ""]


def hand_shape(hand: HandConfig) -> list[tuple[int, int]]:
    """(node id, joints) of every finger, in config order."""
    return [(f.node_id, len(f.joints)) for f in hand.fingers]


def generated_protocol(hand: HandConfig) -> Protocol:
    """The protocol generated for ``hand``'s fingers (cached by its text)."""
    return parse_protocol(generate_dbc(hand_shape(hand)), _generated_source(hand))


def _generated_source(hand: HandConfig) -> str:
    return f"the DBC generated for {hand.source}"


def _other_ids_way_out(hand: HandConfig, protocol: Protocol) -> str:
    """The way out for a configured id the generated DBC does not have, said where it is
    refused: "expected 0x011 (... in the DBC generated for ...)" alone read as a rule with
    no way around it, and ``tools/gen_dbc.py --hand`` refuses the same hand with the same
    words, so the DBC such ids need was nowhere to be had. gen_dbc writes the generated ids
    only: its DBC of the hand without ``can_ids`` is the one to change (every ``BO_``,
    ``CM_``, ``BA_`` and ``VAL_`` line of a frame names its id)."""
    if protocol.source != _generated_source(hand):
        return ""  # a DBC given or recorded: its ids are the ones to write
    return (
        "; other ids need a DBC file that has them, given to handctl's commands with --dbc "
        "FILE: leave can_ids out for the generated ones, or write the generated DBC of a "
        "copy of the hand without can_ids (python tools/gen_dbc.py --hand COPY.yaml --out "
        "FILE) and change the ids of its frames there (a DBC writes ids in decimal, 0x181 "
        "as 385, on every BO_, CM_, BA_ and VAL_ line of the frame)"
    )


def protocol_for(hand: HandConfig, dbc: str | Path | None = None) -> Protocol:
    """The protocol every command of ``hand`` speaks: the DBC file ``dbc``, else the one the
    hand was loaded with (``hand.dbc``, from ``--dbc``), else the one generated from its
    fingers. A DBC file must carry every finger's frames (``check_protocol``)."""
    path = dbc if dbc is not None else hand.dbc
    protocol = generated_protocol(hand) if path is None else load_protocol(Path(path))
    check_protocol(hand, protocol)
    return protocol


def check_protocol(hand: HandConfig, protocol: Protocol) -> None:
    """Raise a ``ConfigError`` naming the first thing in which ``protocol`` and ``hand``
    disagree: a node without its messages, a configured CAN id, a joint count, or a message
    whose signals are not the ones host and nodes read, in that order (scales and ranges may
    differ: ``handctl/wirelimits.py`` holds the limits against them)."""
    estop = protocol.by_name.get("EStop")
    if estop is None or estop.signal_names != ("Reason",):
        raise ConfigError(
            protocol.source,
            "EStop",
            "an EStop message of one signal, Reason",
            "none" if estop is None else ", ".join(estop.signal_names),
        )
    if estop.frame_id != ESTOP_ID:
        # the host sends its e-stop on the DBC's id: on 0x7F0 it lost arbitration to every
        # frame of the hand, and nodes, which act on 0x000 only, ignored it
        raise ConfigError(
            protocol.source,
            "EStop id",
            f"0x{ESTOP_ID:03X} (the id every node acts on, the highest priority on the bus: "
            "firmware_protocol/PROTOCOL.md, E-stop)",
            Description(f"0x{estop.frame_id:03X}"),
        )
    _check_enumerated(protocol, estop)
    for i, finger in enumerate(hand.fingers):
        where = f"fingers[{i}]"
        for kind, key in CAN_ID_KEYS.items():
            name = f"{kind}_{finger.node_id}"
            layout = protocol.by_name.get(name)
            if layout is None:
                raise ConfigError(
                    hand.source,
                    f"{where}.node_id",
                    f"a node with a {name} message in {protocol.source}",
                    f"node {finger.node_id}, which it has no {name} for",
                )
            configured = getattr(finger.can_ids, key)
            if layout.frame_id != configured:
                raise ConfigError(
                    hand.source,
                    f"{where}.can_ids.{key}",
                    f"0x{layout.frame_id:03X} ({name} in {protocol.source}"
                    f"{_other_ids_way_out(hand, protocol)})",
                    description(f"0x{configured:03X}"),  # an id, written as the expected one
                )
        n = len(finger.joints)
        command = protocol.by_name[f"TorqueCommand_{finger.node_id}"]
        feedback = protocol.by_name[f"Feedback_{finger.node_id}"]
        carried = wire_joints(command.signal_names, "Torque")
        read = (
            wire_joints(feedback.signal_names, "Torque"),
            wire_joints(feedback.signal_names, "Angle"),
        )
        # messages of as many signals as n joints have are held name by name below, which
        # says a joint's signal renamed or out of place as such (not as a count of joints)
        shaped = len(command.signals) == n and len(feedback.signals) == 2 * n + 2
        if not shaped and (carried != n or read != (n, n)):
            raise ConfigError(
                hand.source,
                f"{where}.joints",
                f"as many joints as {protocol.source} carries for node "
                f"{finger.node_id} ({command.name}: {carried} torques, "
                f"{feedback.name}: {read[0]} torques and {read[1]} angles)",
                f"{n} joints",
            )
        for kind in ID_BASES:
            layout = protocol.by_name[f"{kind}_{finger.node_id}"]
            wanted = tuple(s[0] for s in _node_signals(kind, n))
            if layout.signal_names != wanted:
                raise ConfigError(
                    protocol.source,
                    layout.name,
                    f"the signals {', '.join(wanted)} after Crc and Counter, in "
                    f"that order (what host and node read; {finger.name} has "
                    f"{n} joints)",
                    ", ".join(layout.signal_names),
                )
            _check_units(protocol, layout)
            _check_enumerated(protocol, layout)
        _check_version_signal(protocol, protocol.by_name[f"Status_{finger.node_id}"])


#: The units a torque's and an angle's signal may state (PROTOCOL.md fixes N·m and rad; a DBC
#: may leave a unit out). A DBC whose torques said "mN.m" or whose angles said "deg" passed
#: check, and the host read them as N·m and rad all the same.
SIGNAL_UNITS = {"Torque": ("N.m", "N·m", "Nm", "N*m", ""), "Angle": ("rad", "")}


def _check_units(protocol: Protocol, layout: Layout) -> None:
    for sig in layout.signals:
        for prefix, units in SIGNAL_UNITS.items():
            if sig.name.startswith(prefix) and sig.unit not in units:
                raise ConfigError(
                    protocol.source,
                    f"{layout.name}.{sig.name}",
                    f"the unit {units[0]} (what the host reads it in; "
                    "firmware_protocol/PROTOCOL.md)",
                    sig.unit,
                )


#: Per signal name, the values the protocol defines for a signal that carries a number as it
#: is, and what they are (firmware_protocol/PROTOCOL.md). The FaultBits' reserved bits too: a
#: node that sets one is named (``online/drivers/finger.py``).
ENUMERATED_SIGNALS = {
    "State": (int(min(NodeState)), int(max(NodeState)), "the node states"),
    "FaultBits": (0, 0xFF, "every bit of the fault bits, the reserved ones too"),
    "Command": (min(NODE_COMMANDS.values()), max(NODE_COMMANDS.values()), "the node commands"),
    "Reason": (min(ESTOP_REASONS.values()), max(ESTOP_REASONS.values()), "the e-stop reasons"),
    # what a node counts and reports in Status and Heartbeat: a DBC whose CommandAge was
    # signed (-128..127) or whose FirmwareMajor was 300..400 passed check, and every run
    # stopped on the first Status a node could not encode. A 16-bit Uptime wrapped after 65 s,
    # which the host reads as a reboot
    "RejectCrc": (0, 0xFF, "the rejected frames, a count saturating at 255"),
    "RejectCounter": (0, 0xFF, "the rejected frames, a count saturating at 255"),
    "RejectLength": (0, 0xFF, "the rejected frames, a count saturating at 255"),
    "CommandAge": (0, 0xFF, "ms since the last accepted command, saturating at 255"),
    "FirmwareMajor": (0, 0xFF, "a firmware release number, one byte"),
    "FirmwareMinor": (0, 0xFF, "a firmware release number, one byte"),
    "FirmwarePatch": (0, 0xFF, "a firmware release number, one byte"),
    "Uptime": (0, 0xFFFFFFFF, "ms since boot, 32 bits: a smaller value is a reboot"),
}


def _check_enumerated(protocol: Protocol, layout: Layout) -> None:
    """A state, a command, a reason, fault bits or a count a node reports travel as the
    number they are: scale 1, offset 0, and a range that holds every value the protocol
    defines. A State of offset -1 read a node in FAULT (2) as ENABLED (1); a Command of range
    0..1 stopped a run in its start, unable to encode a disable (2), with no file named."""
    for sig in layout.signals:
        if sig.name not in ENUMERATED_SIGNALS:
            continue
        low, high, what = ENUMERATED_SIGNALS[sig.name]
        carried = sig.carried_range()
        if sig.scale == 1 and sig.offset == 0 and carried[0] <= low and high <= carried[1]:
            continue
        raise ConfigError(
            protocol.source,
            f"{layout.name}.{sig.name}",
            f"scale 1, offset 0 and a range that holds {low}..{high} ({what}: "
            "firmware_protocol/PROTOCOL.md)",
            Description(
                f"scale {sig.scale:g}, offset {sig.offset:g}, range {carried[0]:g}..{carried[1]:g}"
            ),
        )


def _check_version_signal(protocol: Protocol, status: Layout) -> None:
    """``ProtocolVersion`` where every version keeps it (PROTOCOL.md, *Versions*): byte 8 of
    Status, a whole byte. The host reads a node's version there in frames of any length, and a
    DBC that claimed the host's version with it elsewhere (or scaled) had nodes of this
    version named as speaking another, and a node of another one as speaking this."""
    sig = next(s for s in status.signals if s.name == "ProtocolVersion")
    found = (sig.offset_byte, sig.size_bits, sig.signed, sig.scale, sig.offset)
    if found != (STATUS_VERSION_BYTE, 8, False, 1.0, 0.0):
        raise ConfigError(
            protocol.source,
            f"{status.name}.ProtocolVersion",
            f"byte {STATUS_VERSION_BYTE} of Status, 8 bits unsigned, scale 1, offset 0 (where "
            "every protocol version keeps it: firmware_protocol/PROTOCOL.md, Versions)",
            f"byte {sig.offset_byte}, {sig.size_bits} bits "
            f"{'signed' if sig.signed else 'unsigned'}, scale {sig.scale:g}, offset "
            f"{sig.offset:g}",
        )
    low, high = sig.carried_range()
    if (low, high) != (0, 0xFF):
        # a range of [0|1] passed check, and every run stopped on the first Status a node of
        # this DBC's version could not encode; the whole byte names a node of any version
        raise ConfigError(
            protocol.source,
            f"{status.name}.ProtocolVersion",
            "the range 0..255 (the whole byte, a node of any version named by it: "
            f"firmware_protocol/PROTOCOL.md, Versions; this DBC's is {protocol.version})",
            Description(f"range {low:g}..{high:g}"),
        )
    if protocol.version < 2:
        raise ConfigError(
            protocol.source,
            "VERSION",
            '"handctl protocol N" with N at least 2 (the first version with a ProtocolVersion '
            "in Status, which this DBC's Status carries)",
            protocol.version,
        )


def wire_joints(signal_names: Iterable[str], prefix: str) -> int:
    """How many of ``prefix``1, 2, ... ``signal_names`` has, in any order: a message's joints.
    Their order is held after (``check_protocol``): counted in order, Torque2 before Torque1
    was said as a message of no torques at all."""
    names = set(signal_names)
    count = 0
    while f"{prefix}{count + 1}" in names:
        count += 1
    return count
