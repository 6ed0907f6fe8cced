"""The files a command is told to write, asked about before the work begins: a name that does
not resolve to a place for a file is bad input naming the option, never an exception."""

from __future__ import annotations

from pathlib import Path

import pytest

from handctl.errors import ConfigError
from handctl.outfile import check_writable


def test_a_symlink_loop_is_bad_input_naming_the_option(tmp_path: Path) -> None:
    (tmp_path / "a").symlink_to(tmp_path / "b")
    (tmp_path / "b").symlink_to(tmp_path / "a")
    with pytest.raises(ConfigError, match=r"--json: expected a file name that resolves"):
        check_writable(tmp_path / "a", "--json")


def test_a_file_in_a_writable_directory_is_its_resolved_self(tmp_path: Path) -> None:
    (tmp_path / "link").symlink_to(tmp_path / "real.yaml")
    assert check_writable(tmp_path / "link", "-o") == tmp_path / "real.yaml"
