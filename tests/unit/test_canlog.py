"""A recording's frames written in python-can's log formats read back with python-can's own
readers, each frame at its time of day."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import can
import pytest

from handctl.recording.canlog import write_frames

#: s since 1970: a run that began 97 ms into its second
START = 1796577232.097


@pytest.mark.parametrize(
    ("fmt", "reader", "options"),
    [
        ("candump", can.CanutilsLogReader, {}),
        ("asc", can.ASCReader, {"relative_timestamp": False}),
        ("blf", can.BLFReader, {}),
    ],
)
def test_frames_read_back_at_their_time_of_day(
    tmp_path: Path, fmt: str, reader: Any, options: dict[str, Any]
) -> None:
    """The ASC header's milliseconds lost their leading zeros (97 ms as ".97", python-can
    4.6), and every frame of a run that began in the first tenth of a second read back up to
    0.9 s late (an outside audit)."""
    frames = [(START + 0.001 * k, 0x181, bytes([k]), True, True) for k in range(3)]
    path = tmp_path / f"frames.{fmt}"
    assert write_frames(path, fmt, frames) == 3
    with reader(str(path), **options) as back:
        stamps = [m.timestamp for m in back]
    assert stamps == pytest.approx([s for s, *_ in frames], abs=2e-6)
