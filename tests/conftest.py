"""Shared fixtures: the default hand, the protocol, and private virtual-bus channels."""

from __future__ import annotations

import itertools
from collections.abc import Iterator
from pathlib import Path

import pytest

from handctl.config import HandConfig, load_hand
from handctl.online.bus import HandBus, open_bus
from handctl.protocol import Protocol, load_protocol

ROOT = Path(__file__).resolve().parent.parent
HAND_YAML = ROOT / "config" / "hands" / "hiroshima_hand.yaml"
_channels = itertools.count()


@pytest.fixture(scope="session")
def hand() -> HandConfig:
    return load_hand(HAND_YAML)


@pytest.fixture(scope="session")
def protocol() -> Protocol:
    return load_protocol()


@pytest.fixture
def channel() -> str:
    """A virtual-bus channel no other test uses, so tests never hear each other."""
    return f"handctl-test-{next(_channels)}"


@pytest.fixture
def bus_pair(hand: HandConfig, channel: str) -> Iterator[tuple[HandBus, HandBus]]:
    """Two ends of one virtual bus: (host side, peer side)."""
    host = open_bus(f"virtual:{channel}", hand.bus)
    peer = open_bus(f"virtual:{channel}", hand.bus)
    yield host, peer
    host.close()
    peer.close()
