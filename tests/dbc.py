"""The DBC through cantools: the oracle the tests decode the wire with, independently of
handctl's own codec, typed as the CAN database it is."""

from __future__ import annotations

from typing import Any

import cantools

from handctl.protocol import DEFAULT_DBC


def load_dbc() -> cantools.database.can.Database:
    db = cantools.database.load_file(str(DEFAULT_DBC))
    assert isinstance(db, cantools.database.can.Database)
    return db


DB = load_dbc()


def decode(frame_id: int, data: bytes, *, choices: bool = True) -> dict[str, Any]:
    """A frame's signals by name; ``choices``: named values as their names (``"enable"``)."""
    signals = DB.decode_message(frame_id, data, decode_choices=choices)
    assert isinstance(signals, dict)  # the DBC has no multiplexed message
    return signals
