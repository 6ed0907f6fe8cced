"""The DBC compiles into layouts that follow the protocol's conventions, and the CRC is the one
PROTOCOL.md names."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from handctl.errors import ConfigError, ProtocolError
from handctl.protocol import DEFAULT_DBC, NodeState, SignalSpec, crc8, load_protocol
from handctl.protocol import Protocol as Proto


def test_crc8_autosar_check_value() -> None:
    # The catalogued check value of CRC-8/AUTOSAR over "123456789".
    assert crc8(b"123456789") == 0xDF


def test_every_message_has_crc_counter_and_a_unique_data_id(protocol: Proto) -> None:
    assert len(protocol.layouts) == 16
    ids = {layout.data_id for layout in protocol.layouts}
    assert len(ids) == len(protocol.layouts)
    for layout in protocol.layouts:
        assert layout.length in (3, 7, 8, 12, 16)
        assert layout.send in ("event", "loop", "cyclic")


def test_estop_has_the_highest_priority(protocol: Proto) -> None:
    estop = protocol.layout("EStop")
    assert estop.frame_id == 0
    assert min(layout.frame_id for layout in protocol.layouts) == estop.frame_id


def test_crc_covers_the_data_id(protocol: Proto) -> None:
    """The same payload under another message's DataID must fail: no masquerading frames."""
    cmd1 = protocol.layout("TorqueCommand", 1)
    cmd2 = protocol.layout("TorqueCommand", 2)
    data = cmd1.encode(7, (0.1, 0.2, 0.3))
    assert cmd1.crc_ok(data)
    assert not cmd2.crc_ok(data)


def test_crc_matches_the_documented_byte_order(protocol: Proto) -> None:
    layout = protocol.layout("Feedback", 3)
    data = layout.encode(200, (0.01, -0.02, 0.03, 1.0, -1.0, 0.5, 1, 0))
    covered = bytes((layout.data_id & 0xFF, layout.data_id >> 8)) + data[1:]
    assert data[0] == crc8(covered)


def test_every_single_bit_flip_is_detected(protocol: Proto) -> None:
    layout = protocol.layout("Feedback", 1)
    data = layout.encode(3, (0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 1, 0))
    for byte in range(len(data)):
        for bit in range(8):
            flipped = bytearray(data)
            flipped[byte] ^= 1 << bit
            assert not layout.crc_ok(bytes(flipped)), (byte, bit)


def test_wrong_length_is_not_crc_ok(protocol: Proto) -> None:
    layout = protocol.layout("TorqueCommand", 1)
    data = layout.encode(0, (0.0, 0.0, 0.0))
    assert not layout.crc_ok(data[:-1])
    assert not layout.crc_ok(data + b"\x00")


def test_rounding_is_half_to_even(protocol: Proto) -> None:
    layout = protocol.layout("TorqueCommand", 1)
    # 0.00025 N·m is 2.5 raw units: ties go to the even neighbour, as in cantools and C's rint.
    _, values = layout.decode(layout.encode(0, (0.00025, 0.00035, -0.00025)))
    assert values == pytest.approx((0.0002, 0.0004, -0.0002), abs=1e-12)


@pytest.mark.parametrize("value", [3.3, -3.3, float("nan"), float("inf")])
def test_out_of_range_is_refused_not_wrapped(protocol: Proto, value: float) -> None:
    layout = protocol.layout("TorqueCommand", 2)
    with pytest.raises(ProtocolError, match=r"TorqueCommand_2\.Torque2: expected a value in"):
        layout.encode(0, (0.0, value, 0.0))


def test_a_decode_gives_no_value_beyond_the_signal_s_decoded_range(protocol: Proto) -> None:
    """A log's value beyond ``decoded_range`` was never read off the wire (a joint angle of
    1e9 rad): its ends are what the extreme raw values decode to, exactly, whatever range
    the DBC declares, since a decode clips nothing."""
    layout = protocol.layout("Feedback", 1)
    angle = layout.signals[3]
    assert angle.name == "Angle1" and angle.offset_byte == 8
    data = bytearray(layout.encode(0, (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1, 0)))
    ends = []
    for raw in (-(1 << 15), (1 << 15) - 1):
        data[8:10] = raw.to_bytes(2, "little", signed=True)
        ends.append(layout.decode(bytes(data))[1][3])
    assert tuple(ends) == angle.decoded_range() == (-3.2768, 3.2767)
    # a DBC's range narrower than the bits: what is carried within it, what decodes beyond
    narrow = SignalSpec("X", 0, 8, False, 0.5, 1.0, 0.0, 10.0, "")
    assert narrow.carried_range() == (1.0, 10.0)
    assert narrow.decoded_range() == (1.0, 128.5)


def test_wrong_number_of_values(protocol: Proto) -> None:
    with pytest.raises(ProtocolError, match="expected 3 values"):
        protocol.layout("TorqueCommand", 1).encode(0, (0.0, 0.0))


def test_unknown_message(protocol: Proto) -> None:
    with pytest.raises(ProtocolError, match="no message TorqueCommand_9"):
        protocol.layout("TorqueCommand", 9)


def test_dbc_breaking_the_conventions_is_refused(tmp_path: Path) -> None:
    text = DEFAULT_DBC.read_text()
    # Move Torque1 of TorqueCommand_1 off the byte grid.
    bad = text.replace("SG_ Torque1 : 16|16@1- (0.0001,0)", "SG_ Torque1 : 17|15@1- (0.0001,0)", 1)
    assert bad != text
    path = tmp_path / "bad.dbc"
    path.write_text(bad)
    with pytest.raises(ConfigError) as info:
        load_protocol(path)
    assert info.value.key == "TorqueCommand_1.Torque1"
    assert "byte-aligned" in info.value.expected


def test_a_dbc_the_parser_refuses_is_said_whole(tmp_path: Path) -> None:
    """The parser's message was cut to 80 characters in its middle, and which signals
    overlapped, at its end, went with the cut."""
    text = DEFAULT_DBC.read_text()
    bad = text.replace("SG_ Torque1 : 16|16@1- (0.0001,0)", "SG_ Torque1 : 8|16@1- (0.0001,0)", 1)
    assert bad != text
    path = tmp_path / "overlap.dbc"
    path.write_text(bad)
    with pytest.raises(ConfigError) as info:
        load_protocol(path)
    message = str(info.value)
    assert "a valid DBC" in message and "..." not in message
    assert "The signals Torque1 and Counter are overlapping in message TorqueCommand_1" in (message)


@pytest.mark.parametrize(
    "factor, says",
    [("0", "factor 0,"), ("-0.0001", "factor -0.0001,")],
)
def test_a_signal_factor_that_is_not_positive_is_refused(
    tmp_path: Path, factor: str, says: str
) -> None:
    """Zero divided by zero in the signal's range (a traceback); a negative one turned its
    range over, and a hand config's angles were then refused as out of a range that held
    them."""
    old = "SG_ Angle1 : 64|16@1- (0.0001,0)"
    err = _refused(tmp_path, old, f"SG_ Angle1 : 64|16@1- ({factor},0)")
    assert err.key == "Feedback_1.Angle1"
    assert err.expected == "a finite factor > 0 and a finite offset"
    assert says in str(err)


def test_a_signal_range_turned_over_is_refused(tmp_path: Path) -> None:
    """[3.2767|-3.2768] holds no value: jog stopped on CLOCK_EXCEPTION with a traceback."""
    text = DEFAULT_DBC.read_text()
    old = "SG_ Angle1 : 64|16@1- (0.0001,0) [-3.2768|3.2767]"
    assert old in text
    path = tmp_path / "bad.dbc"
    path.write_text(text.replace(old, "SG_ Angle1 : 64|16@1- (0.0001,0) [3.2767|-3.2768]", 1))
    with pytest.raises(ConfigError) as info:
        load_protocol(path)
    assert info.value.key == "Feedback_1.Angle1"
    assert info.value.expected == "a range [min|max] with min <= max"


def test_missing_dbc(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="no such file"):
        load_protocol(tmp_path / "none.dbc")


def test_blank_buffers_are_never_valid_frames(protocol: Proto) -> None:
    """A zeroed or erased (0xFF) buffer sent by a confused node must fail the CRC."""
    for layout in protocol.layouts:
        for fill in (0x00, 0xFF):
            assert not layout.crc_ok(bytes([fill]) * layout.length), (layout.name, fill)


def test_node_states_are_the_dbcs_value_table() -> None:
    """Host and nodes share ``NodeState``; the DBC's ``State`` value table is what the
    firmware and any CAN tool read, so the two must say the same."""
    import cantools

    db = cantools.database.load_file(str(DEFAULT_DBC))
    assert isinstance(db, cantools.database.can.Database)
    tables = [
        {int(value): str(name) for value, name in signal.choices.items()}
        for message in db.messages
        for signal in message.signals
        if signal.name == "State" and signal.choices
    ]
    assert tables, "no State signal of the DBC has a value table"
    for table in tables:
        assert table == {state.value: state.name for state in NodeState}


@pytest.mark.parametrize("length", [65, 17])
def test_a_frame_length_can_fd_has_not_is_refused(tmp_path: Path, length: int) -> None:
    """65 bytes was a traceback from the bus budget (and a C codec was generated for it); 17
    was budgeted as 17 bytes, where a CAN-FD controller sends 20."""
    err = _refused(
        tmp_path, "BO_ 385 Feedback_1: 16 FINGER1", f"BO_ 385 Feedback_1: {length} FINGER1"
    )
    assert err.key == "Feedback_1 length" and err.found == length
    assert "a CAN-FD data length" in err.expected


def _refused(tmp_path: Path, old: str, new: str) -> ConfigError:
    """The error of the default DBC with ``old`` (which it has) written as ``new``."""
    text = DEFAULT_DBC.read_text()
    assert old in text
    path = tmp_path / "bad.dbc"
    path.write_text(text.replace(old, new, 1))
    with pytest.raises(ConfigError) as info:
        load_protocol(path)
    return info.value


def test_a_message_on_an_extended_id_is_refused(tmp_path: Path) -> None:
    """handctl reads 11-bit frames only; a DBC declaring Heartbeat_1 on the 29-bit id 0x701
    passed check, nodes and the C codec's generator, and firmware built from it sends
    heartbeats the host never reads (every run a HEARTBEAT_LOST)."""
    text = DEFAULT_DBC.read_text()
    extended = 0x701 | 0x80000000  # the DBC's flag of an extended id
    assert " 1793 " in text
    path = tmp_path / "bad.dbc"
    path.write_text(text.replace(" 1793 ", f" {extended} "))
    with pytest.raises(ConfigError) as info:
        load_protocol(path)
    assert info.value.key == "Heartbeat_1 id"
    assert info.value.expected == "an 11-bit (standard) CAN id"
    assert "found the extended (29-bit) id 0x00000701" in str(info.value)


def test_two_messages_on_one_id_are_said_as_such(
    tmp_path: Path, capfd: pytest.CaptureFixture[str]
) -> None:
    """A DBC sets a message's attributes by its id, so Feedback_1 moved onto EStop's id 0 took
    EStop's DataID, and the clash was said as one of DataIDs (after a line cantools printed
    through logging)."""
    text = DEFAULT_DBC.read_text()
    path = tmp_path / "bad.dbc"
    path.write_text(text.replace(" 385 ", " 0 "))  # the message, its comment, attributes
    with pytest.raises(ConfigError) as info:
        load_protocol(path)
    err = info.value
    assert err.key == "Feedback_1 id" and err.expected == "a CAN id not used by EStop"
    assert "found 0x000, EStop's" in str(err)
    assert capfd.readouterr().err == ""


@pytest.mark.parametrize("data_id", ["99999", "-1"])
def test_a_data_id_beyond_16_bits_is_refused(tmp_path: Path, data_id: str) -> None:
    """The CRC starts with the DataID's two bytes: 99999 or -1 was a traceback there ("bytes
    must be in range(0, 256)", exit 1) (found by an outside audit)."""
    err = _refused(tmp_path, 'BA_ "DataID" BO_ 257 4129;', f'BA_ "DataID" BO_ 257 {data_id};')
    assert err.key == "TorqueCommand_1.DataID" and err.found == int(data_id)
    assert err.expected.startswith("a whole number 0..65535 ")


def test_a_dbc_with_a_utf8_byte_order_mark_is_read_as_utf8(tmp_path: Path) -> None:
    """Read as Windows-1252, the mark was three letters before VERSION and the file was refused
    as 'Invalid syntax ... ï»¿VERSION' (found by an outside audit). By the mark it is UTF-8:
    a comment's µ reads as one, and the mark is not in the text a recording keeps."""
    text = DEFAULT_DBC.read_text(encoding="cp1252").replace("every 1 ms", "every 1000 µs", 1)
    path = tmp_path / "bom.dbc"
    path.write_bytes(b"\xef\xbb\xbf" + text.encode("utf-8"))
    loaded = load_protocol(path)
    assert loaded.text == text
    assert [(x.name, x.data_id) for x in loaded.layouts] == [
        (x.name, x.data_id) for x in load_protocol(DEFAULT_DBC).layouts
    ]
    other = tmp_path / "bom_cp1252.dbc"  # the mark, and then no UTF-8
    other.write_bytes(b"\xef\xbb\xbf" + text.encode("cp1252"))
    with pytest.raises(ConfigError) as info:
        load_protocol(other)
    assert info.value.expected == "UTF-8 text (the file starts with a UTF-8 byte order mark)"
    at = 3 + text.encode("cp1252").index(b"\xb5")
    assert str(info.value).endswith(f"found byte 0xB5 at offset {at}")


@pytest.mark.parametrize("value", ["7", "-1"])
def test_a_send_attribute_outside_its_choices_is_refused(tmp_path: Path, value: str) -> None:
    """7 was an IndexError (a traceback, exit 1); -1 was read as "cyclic" by Python's negative
    indexing (found by an outside audit)."""
    old = 'BA_ "HandctlSend" BO_ 257 1;'
    err = _refused(tmp_path, old, f'BA_ "HandctlSend" BO_ 257 {value};')
    assert err.key == "TorqueCommand_1.HandctlSend" and err.found == int(value)
    assert err.expected == 'one of the attribute\'s values: 0 "event", 1 "loop", 2 "cyclic"'


@pytest.mark.parametrize(
    "definition, values",
    [("INT 0 10", ("1", "2")), ("STRING", ('"loop"', '"cyclic"'))],
)
def test_a_send_attribute_that_is_no_enum_is_refused(
    tmp_path: Path, definition: str, values: tuple[str, str]
) -> None:
    """An INT definition was an IndexError, a STRING one a TypeError: tracebacks, exit 1
    (found by an outside audit)."""
    text = DEFAULT_DBC.read_text()
    old = 'BA_DEF_ BO_  "HandctlSend" ENUM  "event","loop","cyclic";'
    assert old in text
    text = text.replace(old, f'BA_DEF_ BO_  "HandctlSend" {definition};')
    if definition.startswith("INT"):
        text = text.replace('BA_DEF_DEF_  "HandctlSend" "event";', 'BA_DEF_DEF_  "HandctlSend" 0;')
    for number, value in zip(("1;", "2;"), values, strict=True):
        text = re.sub(rf'(BA_ "HandctlSend" BO_ \d+) {number}', rf"\1 {value};", text)
    path = tmp_path / "bad.dbc"
    path.write_text(text)
    with pytest.raises(ConfigError) as info:
        load_protocol(path)
    assert info.value.key == "BA_DEF_ HandctlSend"
    assert info.value.expected == 'an ENUM attribute: "event","loop","cyclic"'
    assert str(info.value).endswith(f"found {definition.split(maxsplit=1)[0]}")


@pytest.mark.parametrize(
    "number", ["9" * 5000, "300", "\u0662"], ids=["5000 digits", "300", "arabic-indic"]
)
def test_a_version_number_a_status_cannot_carry_is_refused(tmp_path: Path, number: str) -> None:
    """5000 digits were a ValueError from ``int`` (a traceback, exit 1); 300 passed check and
    stopped every run on its first Status (ProtocolVersion is one byte); an Arabic-Indic 2 was
    read as 2 (found by an outside audit)."""
    text = DEFAULT_DBC.read_text().replace("handctl protocol 2", f"handctl protocol {number}")
    path = tmp_path / "bad.dbc"
    path.write_bytes(b"\xef\xbb\xbf" + text.encode("utf-8"))
    with pytest.raises(ConfigError) as info:
        load_protocol(path)
    assert info.value.key == "VERSION"
    assert info.value.expected.startswith('"handctl protocol N" with N a whole number 0..255 ')
    assert len(str(info.value)) < 400


def test_a_dbc_beyond_its_size_limit_is_refused_before_it_is_parsed(tmp_path: Path) -> None:
    """A DBC padded to 10 MB with a comment took 13 s and 2.2 GB in cantools; one of 100 MB
    ran out of memory, which was said as a syntax error (found by an outside audit)."""
    from handctl.protocol import MAX_DBC_BYTES, parse_protocol

    text = DEFAULT_DBC.read_text(encoding="cp1252")
    padded = text + 'CM_ "' + "x" * (MAX_DBC_BYTES - len(text)) + '";\n'
    path = tmp_path / "padded.dbc"
    path.write_text(padded, encoding="cp1252")
    with pytest.raises(ConfigError) as info:
        load_protocol(path)
    assert info.value.file == str(path)
    assert info.value.expected.startswith(f"a DBC of at most {MAX_DBC_BYTES} bytes ")
    assert str(info.value).endswith(f"found more than {MAX_DBC_BYTES} bytes")
    with pytest.raises(ConfigError) as info:  # a recording's DBC, read from no file
        parse_protocol(padded, "run.mcap (its recorded DBC)")
    assert info.value.expected.startswith(f"a DBC of at most {MAX_DBC_BYTES} bytes ")
    assert 10 * len(DEFAULT_DBC.read_bytes()) <= MAX_DBC_BYTES
