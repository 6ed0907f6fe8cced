"""The protocol version: read from the DBC, reported in every Status, and named by the host
for a node that speaks another one, even one whose Status has another length."""

from __future__ import annotations

from pathlib import Path

import pytest

from handctl.config import HandConfig
from handctl.errors import ConfigError
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
