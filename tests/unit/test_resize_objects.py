"""``tools/resize_objects.py``: a copy of a hand config with its objects resized, and what
it says of bad input."""

from __future__ import annotations

from pathlib import Path

import pytest

from ..conftest import ROOT, load_tool


@pytest.mark.parametrize(
    ("argv", "says"),
    [
        (["--scale", "cyl1=0.9", "-o", "{tmp}"], "-o: expected a regular file"),
        (["--scale", "cyl1=0.9", "--hand", "{tmp}/nosuch.yaml", "-o", "{tmp}/r.yaml"], "--hand"),
        (["--scale", "cyl1=0.9", "--scale", "cyl1=1.1", "-o", "{tmp}/r.yaml"], "scaled once"),
        (["--scale", "cyl1=0.9", "--hand", "{tmp}/h.yaml", "-o", "{tmp}/h.yaml"], "another file"),
    ],
)
def test_resize_objects_says_bad_input_with_exit_2(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], argv: list[str], says: str
) -> None:
    """A directory as -o or a missing --hand was a traceback; a cylinder scaled twice kept the
    last factor without a word; -o over --hand dumped the config over itself (its comments
    and anchors lost)."""
    hand = tmp_path / "h.yaml"
    hand.write_text((ROOT / "config" / "hands" / "hiroshima_hand.yaml").read_text())
    before = hand.read_text()
    words = [w.replace("{tmp}", str(tmp_path)) for w in argv]
    assert load_tool("resize_objects").main(words) == 2
    assert says in capsys.readouterr().err
    assert hand.read_text() == before
