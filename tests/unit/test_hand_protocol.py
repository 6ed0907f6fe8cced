"""The protocol follows from the hand: the default hand's generated DBC is today's packaged one,
other shapes get frames by the same rules, and a DBC given instead is held against the hand."""

from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path
from typing import Any

import cantools
import pytest

from handctl.busload import fd_dlc_size
from handctl.config import HandConfig, load_hand
from handctl.errors import ConfigError
from handctl.hand_protocol import generate_dbc, generated_protocol, protocol_for
from handctl.protocol import DEFAULT_DBC, FD_DLC_SIZES, Protocol, load_protocol

from ..conftest import ROOT, handctl
from ..shapes import shaped_hand

VECTORS = ROOT / "firmware_protocol" / "vectors.json"


def db_of(text: str) -> Any:
    return cantools.database.load_string(text, database_format="dbc", strict=True)


def test_default_hand_generates_the_packaged_dbc(hand: HandConfig) -> None:
    generated = generated_protocol(hand)
    assert generated.text == DEFAULT_DBC.read_text(encoding="cp1252")


def test_default_hand_frames_are_the_packaged_ones_message_by_message(hand: HandConfig) -> None:
    """The same through cantools, field by field, so that a harmless text change of either
    side could not hide a frame change."""
    generated = db_of(generated_protocol(hand).text)
    packaged = cantools.database.load_file(str(DEFAULT_DBC), strict=True)
    assert isinstance(packaged, cantools.database.can.Database)
    assert [m.name for m in generated.messages] == [m.name for m in packaged.messages]
    for mine, theirs in zip(generated.messages, packaged.messages, strict=True):
        assert (mine.frame_id, mine.length, mine.senders, mine.cycle_time) == (
            theirs.frame_id,
            theirs.length,
            theirs.senders,
            theirs.cycle_time,
        )
        assert mine.dbc is not None and theirs.dbc is not None
        assert mine.dbc.attributes["DataID"].value == theirs.dbc.attributes["DataID"].value
        assert [
            (
                s.name,
                s.start,
                s.length,
                s.is_signed,
                s.scale,
                s.offset,
                s.minimum,
                s.maximum,
                s.unit,
                s.receivers,
            )
            for s in mine.signals
        ] == [
            (
                s.name,
                s.start,
                s.length,
                s.is_signed,
                s.scale,
                s.offset,
                s.minimum,
                s.maximum,
                s.unit,
                s.receivers,
            )
            for s in theirs.signals
        ]


def test_default_hand_encodes_every_golden_vector_to_the_same_bytes(hand: HandConfig) -> None:
    protocol = generated_protocol(hand)
    document = json.loads(VECTORS.read_text(encoding="utf-8"))
    for vector in document["vectors"]:
        layout = protocol.by_name[vector["message"]]
        assert layout.frame_id == vector["frame_id"]
        values = [vector["signals"][name] for name in layout.signal_names]
        assert layout.encode(vector["counter"], values).hex() == vector["bytes"], vector["case"]


@pytest.mark.parametrize("shape", [[2, 2], [4, 4, 4, 4], [6], [1, 2, 3, 4, 5, 6]])
def test_other_shapes_follow_the_same_rules(shape: list[int]) -> None:
    nodes = [15 - i for i in range(len(shape))]  # the highest ids, out of order
    protocol = Protocol_of(list(zip(nodes, shape, strict=True)))
    for node, k in zip(nodes, shape, strict=True):
        command = protocol.layout("TorqueCommand", node)
        feedback = protocol.layout("Feedback", node)
        assert command.frame_id == 0x100 + node and feedback.frame_id == 0x180 + node
        assert protocol.layout("Status", node).frame_id == 0x280 + node
        assert protocol.layout("Heartbeat", node).frame_id == 0x700 + node
        assert protocol.layout("NodeCommand", node).frame_id == 0x010 + node
        assert command.signal_names == tuple(f"Torque{j + 1}" for j in range(k))
        assert feedback.signal_names == (
            *(f"Torque{j + 1}" for j in range(k)),
            *(f"Angle{j + 1}" for j in range(k)),
            "State",
            "FaultBits",
        )
        assert command.length in FD_DLC_SIZES and command.length >= 2 + 2 * k
        assert feedback.length in FD_DLC_SIZES and feedback.length >= 4 + 4 * k
        assert command.data_id == 0x1020 + node and feedback.data_id == 0x1030 + node
        # Padding travels as zeros and round-trips.
        data = command.encode(5, [0.25] * k)
        assert data[2 + 2 * k :] == bytes(command.length - 2 - 2 * k)
        assert command.decode(data) == (5, tuple([0.25] * k))


def Protocol_of(shape: list[tuple[int, int]]) -> Protocol:  # noqa: N802 - reads as a type
    from handctl.protocol import parse_protocol

    return parse_protocol(generate_dbc(shape), "test shape")


@pytest.mark.parametrize("joints", range(1, 7))
def test_no_erased_buffer_is_a_valid_frame_of_any_node(joints: int) -> None:
    """PROTOCOL.md's promise about the DataIDs, for every node id and joint count: all-0x00
    and all-0xFF frames of Feedback_1 of five joints would pass at 24 bytes, so it is 32."""
    protocol = Protocol_of([(n, joints) for n in range(1, 16)])
    for layout in protocol.layouts:
        for fill in (0x00, 0xFF):
            assert not layout.crc_ok(bytes([fill]) * layout.length), (layout.name, fill)
    lengths = {protocol.layout("Feedback", n).length for n in range(1, 16)}
    assert lengths == ({24, 32} if joints == 5 else {fd_dlc_size(4 + 4 * joints)})


@pytest.mark.parametrize(
    ("joints", "nodes", "key", "found"),
    [
        ([3, 7], None, "fingers[1].joints", "7 entries"),
        ([3], [16], "fingers[0].node_id", "16"),
        ([3], [0], "fingers[0].node_id", "0"),
    ],
)
def test_the_schema_refuses_shapes_the_protocol_cannot_carry(
    tmp_path: Path, joints: list[int], nodes: list[int] | None, key: str, found: str
) -> None:
    path = shaped_hand(tmp_path, joints, nodes)
    with pytest.raises(ConfigError) as err:
        load_hand(path)
    assert err.value.file == str(path)
    assert err.value.key == key
    assert found in str(err.value)


def test_can_ids_follow_the_node_and_a_wrong_one_is_named(tmp_path: Path) -> None:
    hand = load_hand(shaped_hand(tmp_path, [4, 2], [7, 9]))
    assert hand.fingers[0].can_ids.feedback == 0x187
    assert hand.fingers[1].can_ids.heartbeat == 0x709

    def wrong(doc: dict[str, Any]) -> None:
        doc["fingers"][1]["can_ids"] = {"feedback": 0x188}

    path = shaped_hand(tmp_path, [4, 2], [7, 9], wrong)
    with pytest.raises(ConfigError) as err:
        load_hand(path)
    assert err.value.key == "fingers[1].can_ids.feedback"
    # the id found written as the one expected, not quoted as a string ('0x188')
    assert "0x189" in err.value.expected and str(err.value).endswith("found 0x188")


def gen_dbc(*args: str) -> subprocess.CompletedProcess[str]:
    tool = str(ROOT / "tools" / "gen_dbc.py")
    return subprocess.run(
        [sys.executable, tool, *args],
        capture_output=True,
        text=True,
        cwd=ROOT,
        timeout=120,
        check=False,
    )


def test_an_id_of_ones_own_is_told_the_way_to_the_dbc_it_needs(tmp_path: Path) -> None:
    """A can_id off the generated rule was refused as "expected 0x189 (... in the DBC
    generated for ...)", which named no way out, and tools/gen_dbc.py --hand refused the same
    hand with the same words (found by an outside audit): the message says how to get the
    DBC such ids need, and that way is followed here to a hand that loads."""

    def own(doc: dict[str, Any]) -> None:
        doc["fingers"][1]["can_ids"] = {"feedback": 0x188}

    path = shaped_hand(tmp_path, [4, 2], [7, 9], own)
    with pytest.raises(ConfigError) as err:
        load_hand(path)
    assert err.value.key == "fingers[1].can_ids.feedback"
    expected = err.value.expected
    assert (
        "other ids need a DBC file that has them, given to handctl's commands with --dbc FILE"
        in expected
    )
    assert "a DBC writes ids in decimal, 0x181 as 385" in expected
    assert "python tools/gen_dbc.py --hand COPY.yaml --out FILE" in expected
    own_dbc = tmp_path / "own.dbc"
    refused = gen_dbc("--hand", str(path), "--out", str(own_dbc))
    assert refused.returncode == 2 and "with --dbc FILE" in refused.stderr

    # the way out: the generated DBC of a copy without can_ids, its frame's id changed there
    (tmp_path / "copy").mkdir()
    copy = shaped_hand(tmp_path / "copy", [4, 2], [7, 9])
    generated = tmp_path / "generated.dbc"
    written = gen_dbc("--hand", str(copy), "--out", str(generated))
    assert written.returncode == 0, written.stderr
    text = generated.read_text(encoding="cp1252")
    own_dbc.write_text(re.sub(rf"\b{0x189}\b", str(0x188), text), encoding="cp1252")
    assert load_hand(path, own_dbc).fingers[1].can_ids.feedback == 0x188

    # a DBC given is the one whose ids to write: no word of generating one
    with pytest.raises(ConfigError) as err:
        load_hand(path, generated)
    assert err.value.expected == f"0x189 (Feedback_9 in {generated})"


def test_a_given_dbc_must_carry_the_hand(tmp_path: Path) -> None:
    four = load_hand(shaped_hand(tmp_path, [3, 3, 3, 3]))
    with pytest.raises(ConfigError) as err:
        protocol_for(four, DEFAULT_DBC)
    assert err.value.key == "fingers[3].node_id"
    assert "NodeCommand_4" in str(err.value) and "handctl.dbc" in str(err.value)

    short = load_hand(shaped_hand(tmp_path, [3, 2, 3]))
    with pytest.raises(ConfigError) as err:
        protocol_for(short, DEFAULT_DBC)
    assert err.value.key == "fingers[1].joints"
    assert "3 torques" in str(err.value) and "2 joints" in str(err.value)

    # The hand's own generated DBC, written to a file, is accepted as --dbc.
    dbc = tmp_path / "short.dbc"
    dbc.write_text(generate_dbc([(1, 3), (2, 2), (3, 3)]), encoding="cp1252")
    assert protocol_for(short, dbc).layout("TorqueCommand", 2).signal_names == (
        "Torque1",
        "Torque2",
    )


def test_the_packaged_dbc_as_dbc_gives_the_generated_layouts(hand: HandConfig) -> None:
    given = protocol_for(hand, DEFAULT_DBC)
    generated = protocol_for(hand)
    assert [(x.name, x.frame_id, x.length, x.data_id) for x in given.layouts] == [
        (x.name, x.frame_id, x.length, x.data_id) for x in generated.layouts
    ]
    assert load_protocol(DEFAULT_DBC).text == generated.text


def test_a_given_dbc_must_have_the_signals_host_and_nodes_read(
    hand: HandConfig, tmp_path: Path
) -> None:
    """Right counts are not enough: a Feedback with a signal more would shift State and
    FaultBits, so the signal list itself is held against the hand's."""
    text = DEFAULT_DBC.read_text(encoding="cp1252")
    line = ' SG_ FaultBits : 120|8@1+ (1,0) [0|255] "" HOST\n'
    anchor = "BO_ 386 Feedback_2: 16 FINGER2\n"
    start = text.index(anchor)
    at = text.index(line, start) + len(line)
    extra = text[:at] + ' SG_ Temperature : 128|8@1+ (1,0) [0|255] "" HOST\n' + text[at:]
    dbc = tmp_path / "extra.dbc"
    dbc.write_text(extra.replace(anchor, "BO_ 386 Feedback_2: 20 FINGER2\n"), encoding="cp1252")
    with pytest.raises(ConfigError) as err:
        protocol_for(hand, dbc)
    assert err.value.file == str(dbc) and err.value.key == "Feedback_2"
    assert "Torque1, Torque2, Torque3, Angle1, Angle2, Angle3, State, FaultBits" in (
        err.value.expected
    )
    assert str(err.value.found).endswith("FaultBits, Temperature")


@pytest.mark.parametrize(
    ("old", "new"), [('"N.m" FINGER2', '"mN.m" FINGER2'), ('"rad" HOST', '"deg" HOST')]
)
def test_a_given_dbc_whose_units_are_not_the_host_s_is_refused(
    hand: HandConfig, tmp_path: Path, old: str, new: str
) -> None:
    """A DBC whose torques said mN.m or whose angles said deg passed check, and the host read
    their values as N·m and rad all the same (found by an outside audit)."""
    text = DEFAULT_DBC.read_text(encoding="cp1252")
    assert old in text
    dbc = tmp_path / "units.dbc"
    dbc.write_text(text.replace(old, new, 1), encoding="cp1252")
    with pytest.raises(ConfigError) as err:
        protocol_for(hand, dbc)
    assert err.value.file == str(dbc)
    assert "(what the host reads it in; firmware_protocol/PROTOCOL.md)" in err.value.expected
    assert err.value.found == new.split('"')[1]


@pytest.mark.parametrize("frame_id", [0x7F0, 0x005])
def test_a_given_dbc_must_keep_the_estop_on_its_fixed_id(
    hand: HandConfig, tmp_path: Path, frame_id: int
) -> None:
    """An EStop moved to 0x7F0 passed check, and the host sent its e-stop there: behind every
    frame of the hand in arbitration, and ignored by nodes that act on 0x000 (found by an
    outside audit)."""
    text = DEFAULT_DBC.read_text(encoding="cp1252")
    for old in (
        "BO_ 0 EStop:",
        "CM_ BO_ 0 ",
        'BA_ "DataID" BO_ 0 ',
        'BA_ "VFrameFormat" BO_ 0 ',
        "VAL_ 0 ",
    ):
        assert old in text
        text = text.replace(old, old.replace(" 0", f" {frame_id}", 1))
    dbc = tmp_path / "estop.dbc"
    dbc.write_text(text, encoding="cp1252")
    with pytest.raises(ConfigError) as err:
        protocol_for(hand, dbc)
    assert err.value.file == str(dbc) and err.value.key == "EStop id"
    assert err.value.expected.startswith("0x000 ")
    assert str(err.value).endswith(f"found 0x{frame_id:03X}")


_STATE = ' SG_ State : 112|8@1+ (1,0) [0|255] "" HOST'
_FAULT_BITS = ' SG_ FaultBits : 120|8@1+ (1,0) [0|255] "" HOST'


@pytest.mark.parametrize(
    ("old", "new", "key"),
    [
        # a node in FAULT (2) read as ENABLED (1)
        (_STATE, "8@1+ (1,-1) [-1|254]", "Feedback_1.State"),
        (_STATE, "8@1+ (1,0) [0|1]", "Feedback_1.State"),
        (' SG_ State : 16|8@1+ (1,0) [0|255] "" HOST', "8@1+ (2,0) [0|510]", "Status_1.State"),
        (_FAULT_BITS, "8@1+ (0.5,0) [0|127.5]", "Feedback_1.FaultBits"),
        (_FAULT_BITS, "8@1- (1,0) [-128|127]", "Feedback_1.FaultBits"),
        # a run's disable (2) could not be encoded: exit 1 in its start, no file named
        (
            ' SG_ Command : 16|8@1+ (1,0) [0|255] "" FINGER1',
            "8@1+ (1,0) [0|1]",
            "NodeCommand_1.Command",
        ),
        (' SG_ Reason : 16|8@1+ (1,0) [0|255] "" FINGER1', "8@1+ (1,0) [0|2]", "EStop.Reason"),
    ],
)
def test_a_given_dbc_must_carry_states_commands_reasons_and_fault_bits_as_they_are(
    hand: HandConfig, tmp_path: Path, old: str, new: str, key: str
) -> None:
    """These signals were never held to scale 1, offset 0 and a range of every value the
    protocol defines, as ProtocolVersion is (found by an outside audit)."""
    text = DEFAULT_DBC.read_text(encoding="cp1252")
    assert old in text
    dbc = tmp_path / "enumerated.dbc"
    dbc.write_text(text.replace(old, old.replace("8@1+ (1,0) [0|255]", new), 1), encoding="cp1252")
    with pytest.raises(ConfigError) as err:
        protocol_for(hand, dbc)
    assert err.value.file == str(dbc) and err.value.key == key
    assert err.value.expected.startswith("scale 1, offset 0 and a range that holds ")
    lo, hi = new.split("[")[1].rstrip("]").split("|")
    assert str(err.value.found).endswith(f"range {float(lo):g}..{float(hi):g}")
    result = handctl("check", "--dbc", str(dbc))
    assert result.returncode == 2 and "Traceback" not in result.stderr
    assert f"{dbc}: {key}: expected scale 1, offset 0" in result.stderr


@pytest.mark.parametrize(
    ("key", "old", "new", "carried"),
    [
        ("CommandAge", "56|8@1+ (1,0) [0|255]", "56|8@1- (1,0) [-128|127]", 255),
        ("FirmwareMajor", "72|8@1+ (1,0) [0|255]", "72|8@1+ (1,0) [300|400]", 255),
        ("RejectCrc", "32|8@1+ (1,0) [0|255]", "32|8@1+ (2,0) [0|510]", 255),
        ("Uptime", "24|32@1+ (1,0) [0|4294967295]", "24|16@1+ (1,0) [0|65535]", 4294967295),
    ],
)
def test_a_given_dbc_must_carry_what_a_node_reports(
    hand: HandConfig, tmp_path: Path, key: str, old: str, new: str, carried: int
) -> None:
    """A signed CommandAge or a FirmwareMajor of 300..400 passed check, and every run stopped
    at tick 0 on the first Status a node could not encode (exit 3); a 16-bit Uptime wraps
    after 65 s, which the host reads as a reboot (found by an outside audit)."""
    text = DEFAULT_DBC.read_text(encoding="cp1252")
    line = f" SG_ {key} : {old} "
    assert line in text  # node 1's, the first
    dbc = tmp_path / "reports.dbc"
    dbc.write_text(text.replace(line, f" SG_ {key} : {new} ", 1), encoding="cp1252")
    with pytest.raises(ConfigError) as err:
        protocol_for(hand, dbc)
    where = f"{'Heartbeat_1' if key == 'Uptime' else 'Status_1'}.{key}"
    assert err.value.file == str(dbc) and err.value.key == where
    assert err.value.expected.startswith(f"scale 1, offset 0 and a range that holds 0..{carried} ")
    result = handctl("check", "--dbc", str(dbc))
    assert result.returncode == 2 and "Traceback" not in result.stderr
    assert f"{dbc}: {where}: expected scale 1, offset 0" in result.stderr


@pytest.mark.parametrize("version_range", ["[0|1]", "[1|255]"])
def test_a_given_dbc_s_protocol_version_must_hold_every_version(
    hand: HandConfig, tmp_path: Path, version_range: str
) -> None:
    """A ProtocolVersion of [0|1] passed check, and every run stopped at tick 0 on the first
    Status a node of version 2 could not encode (found by an outside audit)."""
    old = ' SG_ ProtocolVersion : 64|8@1+ (1,0) [0|255] ""'
    text = DEFAULT_DBC.read_text(encoding="cp1252")
    assert old in text
    dbc = tmp_path / "version.dbc"
    dbc.write_text(text.replace(old, old.replace("[0|255]", version_range), 1), encoding="cp1252")
    with pytest.raises(ConfigError) as err:
        protocol_for(hand, dbc)
    assert err.value.key == "Status_1.ProtocolVersion"
    assert err.value.expected.startswith("the range 0..255 ")
    lo, hi = version_range.strip("[]").split("|")
    assert str(err.value).endswith(f"found range {lo}..{hi}")


@pytest.mark.parametrize(
    ("new", "found"),
    [
        (("Torque2", "Torque1"), "Torque2, Torque1, Torque3"),  # swapped in place
        (("Torq1", "Torque2"), "Torq1, Torque2, Torque3"),  # renamed
    ],
)
def test_a_joint_s_signal_out_of_place_is_said_as_such(
    hand: HandConfig, tmp_path: Path, new: tuple[str, str], found: str
) -> None:
    """The host reads a message's signals by place (joint k is the k-th), so two torques
    swapped are refused; but as "TorqueCommand_1: 0 torques" of a frame with three, said of
    the hand config (found by an outside audit)."""
    text = DEFAULT_DBC.read_text(encoding="cp1252")
    old = (" SG_ Torque1 : 16|16@1- ", " SG_ Torque2 : 32|16@1- ")
    assert all(line in text for line in old)  # TorqueCommand_1's, the first of each
    for line, name in zip(old, new, strict=True):
        text = text.replace(line, line.replace(line.split()[1], name), 1)
    dbc = tmp_path / "swapped.dbc"
    dbc.write_text(text, encoding="cp1252")
    with pytest.raises(ConfigError) as err:
        protocol_for(hand, dbc)
    assert err.value.file == str(dbc) and err.value.key == "TorqueCommand_1"
    assert err.value.expected.startswith("the signals Torque1, Torque2, Torque3 after Crc")
    assert err.value.found == found
