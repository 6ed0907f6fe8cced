"""The protocol version: read from the DBC, reported in every Status, and named by the host
for a node that speaks another one, even one whose Status has another length."""

from __future__ import annotations

from pathlib import Path

import pytest

from handctl.config import HandConfig
from handctl.errors import ConfigError
from handctl.hand_protocol import protocol_for
from handctl.online.bus import HandBus
from handctl.online.drivers.hand import HandDriver
from handctl.protocol import (
    DEFAULT_DBC,
    Protocol,
    crc8,
    foreign_status_version,
    load_protocol,
)


def _status(protocol: Protocol, node: int, counter: int, version: int) -> bytes:
    return protocol.layout("Status", node).encode(counter, (0, 0, 0, 0, 0, 255, version, 1, 2, 3))


def _recrc(protocol: Protocol, node: int, body: bytes) -> bytes:
    """A Status of another length with an intact CRC, as a node of another version sends it."""
    data_id = protocol.layout("Status", node).data_id
    crc = crc8(bytes((data_id & 0xFF, data_id >> 8)) + body[1:])
    return bytes((crc,)) + body[1:]


def test_the_version_is_the_dbc_s(protocol: Protocol) -> None:
    assert protocol.version == 2
    assert protocol.layout("Status", 1).signal_names[6] == "ProtocolVersion"


def test_a_dbc_without_a_version_number_is_refused(tmp_path: Path) -> None:
    text = DEFAULT_DBC.read_text().replace('VERSION "handctl protocol 2"', 'VERSION "two"')
    path = tmp_path / "bad.dbc"
    path.write_text(text)
    with pytest.raises(ConfigError) as err:
        load_protocol(path)
    assert err.value.key == "VERSION" and err.value.found == "two"


def test_a_status_of_another_length_says_its_version(protocol: Protocol) -> None:
    layout = protocol.layout("Status", 2)
    v2 = _status(protocol, 2, 7, 2)
    assert foreign_status_version(layout, v2) is None  # our own length: decoded normally
    assert foreign_status_version(layout, _recrc(protocol, 2, v2[:8])) == 1
    assert (
        foreign_status_version(layout, _recrc(protocol, 2, v2[:8] + bytes([9]) + v2[9:] + bytes(4)))
        == 9
    )
    broken = bytearray(_recrc(protocol, 2, v2[:8]))
    broken[3] ^= 1
    assert foreign_status_version(layout, bytes(broken)) is None
    # a Status of another node's DataID is not this node's
    assert foreign_status_version(layout, _recrc(protocol, 1, v2[:8])) is None


def test_the_host_names_both_versions(
    hand: HandConfig, protocol: Protocol, bus_pair: tuple[HandBus, HandBus]
) -> None:
    driver = HandDriver(hand, protocol, bus_pair[0])
    peer = bus_pair[1]
    peer.send(0x281, _status(protocol, 1, 0, 2))
    peer.send(0x282, _status(protocol, 2, 0, 3))
    peer.send(0x283, _recrc(protocol, 3, _status(protocol, 3, 0, 2)[:8]))
    driver.poll()
    one, two, three = driver.nodes
    assert one.version_problem() == "" and one.firmware_text == "1.2.3"
    assert "node 2 (f2) speaks handctl protocol 3, this host protocol 2" in two.version_problem()
    assert "node 3 (f3) speaks handctl protocol 1, this host protocol 2" in three.version_problem()
    assert three.rejects.as_dict()["length"] == 1  # named, and still never applied
    assert three.status is None


@pytest.mark.parametrize(
    ("signal", "found"),
    [
        ("64|8@1- (1,0) [-128|127]", "byte 8, 8 bits signed, scale 1, offset 0"),
        ("64|8@1+ (1,1) [1|256]", "byte 8, 8 bits unsigned, scale 1, offset 1"),
    ],
)
def test_a_dbc_whose_status_carries_its_version_otherwise_is_refused(
    tmp_path: Path, hand: HandConfig, signal: str, found: str
) -> None:
    """The host reads a node's version as byte 8 of any Status: a DBC that claimed version 2
    with ProtocolVersion scaled or signed had the nodes built from it say another
    version than the one they speak."""
    line = ' SG_ ProtocolVersion : 64|8@1+ (1,0) [0|255] "" HOST'
    text = DEFAULT_DBC.read_text(encoding="cp1252")
    assert text.count(line) == 3
    path = tmp_path / "moved.dbc"
    # Status_2's only: the first two occurrences are Status_1's and Status_2's
    first = text.index(line) + len(line)
    second = text.index(line, first)
    text = (
        text[:second] + line.replace("64|8@1+ (1,0) [0|255]", signal) + text[second + len(line) :]
    )
    path.write_text(text, encoding="cp1252")
    with pytest.raises(ConfigError) as err:
        protocol_for(hand, path)
    assert err.value.key == "Status_2.ProtocolVersion"
    assert err.value.found == found
    assert "byte 8 of Status, 8 bits unsigned, scale 1, offset 0" in err.value.expected


def test_a_dbc_of_version_1_with_a_version_in_its_status_is_refused(
    tmp_path: Path, hand: HandConfig
) -> None:
    path = tmp_path / "one.dbc"
    text = DEFAULT_DBC.read_text(encoding="cp1252")
    path.write_text(text.replace("handctl protocol 2", "handctl protocol 1"), encoding="cp1252")
    with pytest.raises(ConfigError) as err:
        protocol_for(hand, path)
    assert (err.value.key, err.value.found) == ("VERSION", 1)
    assert protocol_for(hand, DEFAULT_DBC).version == 2
