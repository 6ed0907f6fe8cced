"""A recording's frames in python-can's log formats, for the CAN tools people already have."""

from __future__ import annotations

import datetime
import itertools
from collections.abc import Iterable
from pathlib import Path

import can

from handctl.errors import ConfigError
from handctl.online.bus import EXTENDED_ID_FLAG, EXTENDED_ID_MASK

#: Log formats of python-can that ``write_frames`` writes: candump -L, Vector ASC, Vector BLF.
LOG_FORMATS = ("candump", "asc", "blf")


class _ASCWriter(can.ASCWriter):
    """python-can's ASC writer, its header dated as readers read it. It wrote a header's
    milliseconds without their leading zeros (97 ms as ".97", read back as 970 ms: python-can
    4.6), and dated the file's ``date`` line at the moment of the export, not at its first
    frame (a tool that takes the frames' time of day from that line put them off by as long
    as the log had waited)."""

    def __init__(self, path: str, start_s: float) -> None:
        self._date: datetime.datetime | None = datetime.datetime.fromtimestamp(start_s)
        super().__init__(path, channel=1)

    def _format_header_datetime(self, dt: datetime.datetime) -> str:
        if self._date is not None:  # the ``date`` line, written first: the first frame's time
            dt, self._date = self._date, None
        return dt.strftime(self.FORMAT_DATE.format(f"{dt.microsecond // 1000:03d}"))


def write_frames(
    path: str | Path, fmt: str, frames: Iterable[tuple[float, int, bytes, bool, bool]]
) -> int:
    """Write ``(timestamp_s, arbitration_id, data, is_rx, is_fd)`` frames in a python-can log
    format, so the CAN tools people already have (candump/canplayer, CANalyzer, python-can's
    readers) open a handctl recording. Returns the number of frames written."""
    writer: can.io.generic.MessageWriter
    frames = iter(frames)
    first = next(frames, None)
    if first is not None:
        frames = itertools.chain((first,), frames)
    if fmt == "candump":
        writer = can.CanutilsLogWriter(str(path), channel="can0")
    elif fmt == "asc":
        writer = _ASCWriter(str(path), first[0] if first is not None else 0.0)
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
