"""A recording's frames in python-can's log formats, for the CAN tools people already have."""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path

import can

from handctl.errors import ConfigError
from handctl.online.bus import EXTENDED_ID_FLAG, EXTENDED_ID_MASK

#: Log formats of python-can that ``write_frames`` writes: candump -L, Vector ASC, Vector BLF.
LOG_FORMATS = ("candump", "asc", "blf")


def write_frames(
    path: str | Path, fmt: str, frames: Iterable[tuple[float, int, bytes, bool, bool]]
) -> int:
    """Write ``(timestamp_s, arbitration_id, data, is_rx, is_fd)`` frames in a python-can log
    format, so the CAN tools people already have (candump/canplayer, CANalyzer, python-can's
    readers) open a handctl recording. Returns the number of frames written."""
    writer: can.io.generic.MessageWriter
    if fmt == "candump":
        writer = can.CanutilsLogWriter(str(path), channel="can0")
    elif fmt == "asc":
        writer = can.ASCWriter(str(path), channel=1)
    elif fmt == "blf":
        writer = can.BLFWriter(str(path), channel=1)
    else:
        raise ConfigError("--export", "format", "one of " + ", ".join(LOG_FORMATS), fmt)
    count = 0
    with writer:
        for stamp, frame_id, data, is_rx, is_fd in frames:
            fd = is_fd or len(data) > 8
            extended = bool(frame_id & EXTENDED_ID_FLAG) or frame_id > 0x7FF
            writer.on_message_received(
                can.Message(
                    timestamp=stamp,
                    arbitration_id=frame_id & EXTENDED_ID_MASK,
                    is_extended_id=extended,
                    data=data,
                    is_fd=fd,
                    bitrate_switch=fd,
                    is_rx=is_rx,
                    check=False,
                )
            )
            count += 1
    return count
