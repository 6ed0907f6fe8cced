"""How an error message shows the value it names: as ``repr`` would, but never with a raw
control character, and with a byte that is not UTF-8 shown as the byte."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from handctl.errors import ConfigError, escaped


@pytest.mark.parametrize(
    "value",
    ["can0", "it's", 'say "x"', "é ∑ 漢", 3, 2.5, None, ["a", ("b", 1)], {"k": "v"}],
)
def test_an_ordinary_value_is_shown_as_repr_shows_it(value: object) -> None:
    assert str(ConfigError("f.yaml", "k", "x", value)).endswith(f"found {value!r}")


@pytest.mark.parametrize(
    ("value", "shown"),
    [
        ("ca\x1b[31mn", r"'ca\x1b[31mn'"),
        ("a\nb\tc\x7f\x85", r"'a\nb\tc\x7f\x85'"),
        ("\u202eevil", r"'\u202eevil'"),  # a bidirectional override reorders the line
        ("c\udcffn", r"'c\xffn'"),  # the byte 0xFF as Python holds it from argv
        ("\ud800", r"'\ud800'"),  # a surrogate no byte decodes to
        ("a\\b", r"'a\\b'"),
        (["x\udcff", {"k\x1b": 1}], r"['x\xff', {'k\x1b': 1}]"),
        (Path(os.fsdecode(b"/d/l_\xff\x1b.mcap")), r"'/d/l_\xff\x1b.mcap'"),
    ],
)
def test_control_characters_and_bytes_are_shown_escaped(value: object, shown: str) -> None:
    """A control character was written raw only where a message named a value outside a
    ``ConfigError``; every such message now uses the same rule (``escaped``), and a byte
    that is not UTF-8 was shown as ``\\udcff``, a character the user never typed."""
    assert str(ConfigError("f.yaml", "k", "x", value)).endswith(f"found {shown}")


def test_escaped_leaves_printable_text_alone_and_cuts_nothing() -> None:
    assert escaped("can0 é") == "can0 é"
    assert escaped("x\x1b" * 100) == r"x\x1b" * 100
    assert escaped("c\udcffn\x00") == r"c\xffn\x00"
