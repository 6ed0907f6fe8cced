"""What the recording reader makes of a file it cannot read."""

from __future__ import annotations

from pathlib import Path

import pytest

from handctl.errors import ConfigError
from handctl.recording.reader import open_recording


@pytest.mark.parametrize(
    ("path", "found"),
    [("/proc/self/mem", "Input/output error"), ("/proc/self/clear_refs", "Invalid argument")],
)
def test_a_regular_file_that_cannot_be_read_is_bad_input_named(path: str, found: str) -> None:
    """A file that says it is a regular one and fails its read (a disk's or a network file
    system's read error; these two do it on any Linux) is refused by name, as the YAML
    loaders refuse one, where ``handctl replay`` printed a traceback and exited 1."""
    if not Path(path).is_file():
        pytest.skip(f"{path}: not on this system")
    with pytest.raises(ConfigError) as info:
        open_recording(path)
    assert info.value.file == path
    assert "a readable file" in info.value.expected
    assert found in str(info.value)
