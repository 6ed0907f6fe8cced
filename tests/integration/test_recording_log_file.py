"""The log file against what the system around a run may do to it and to the run's own
descriptors. Each test drives a run's real writer process, never a stand-in."""

from __future__ import annotations

import json
import os
from pathlib import Path

from handctl.config import HandConfig
from handctl.recording.metadata import start_metadata
from handctl.recording.reader import open_recording
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


def test_arguments_and_paths_that_are_not_utf_8_are_recorded_shown_as_bytes(
    hand: HandConfig, tmp_path: Path
) -> None:
    """A byte that is not UTF-8 in ``--log``'s path (Python holds it as a lone surrogate)
    failed the run's start with a TypeError from the JSON encoder, and no log. Now the file
    is at the path as given, and the metadata show the byte as ``\\xff``."""
    name = os.fsdecode(b"l_\xff.mcap")
    path = tmp_path / name
    argv = ("handctl", "run", "--log", name)
    recorder = _recorder(hand, path, argv)
    recorder.add_metadata("handctl.test", {"path": str(path)})
    recorder.close({"outcome": "test", "recording": {"path": str(path)}})
    assert os.fsencode(path) in [os.fsencode(tmp_path / p) for p in os.listdir(tmp_path)]
    recording = open_recording(path)
    assert recording.complete
    shown = str(tmp_path / "l_\\xff.mcap")
    assert json.loads(recording.meta("handctl.command", "command_line")) == [
        "handctl",
        "run",
        "--log",
        "l_\\xff.mcap",
    ]
    assert recording.meta("handctl.test", "path") == shown
    summary = recording.json_meta("handctl.summary")
    assert summary is not None and summary["recording"]["path"] == shown
