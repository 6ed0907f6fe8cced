"""The log file against what the system around a run may do to it and to the run's own
descriptors. Each test drives a run's real writer process, never a stand-in."""

from __future__ import annotations

import os
from pathlib import Path

from handctl.config import HandConfig
from handctl.recording.metadata import start_metadata
from handctl.recording.recorder import Recorder


def _recorder(hand: HandConfig, path: Path, argv: tuple[str, ...] = ("test",)) -> Recorder:
    """A recorder whose writer has the file open and its header written."""
    recorder = Recorder(path, hand, start_metadata(hand, None, argv))
    recorder.wait_ready()
    return recorder


def test_a_log_that_cannot_be_synced_is_no_writer_failure(hand: HandConfig) -> None:
    """``fdatasync`` of /dev/null is EINVAL: the writer ended with that traceback. A file that
    cannot be synced has nothing to make durable; the recording goes on."""
    stats = _recorder(hand, Path(os.devnull)).close({"outcome": "test"})
    assert stats["writer_exit"] == 0
