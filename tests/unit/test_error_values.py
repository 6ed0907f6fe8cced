"""How an error message shows the value it names: as ``repr`` would, but never with a raw
control character, and with a byte that is not UTF-8 shown as the byte."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from handctl.config import load_hand
from handctl.errors import ConfigError, escaped

from ..conftest import HAND_YAML


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


def test_a_value_of_the_wrong_type_is_described_not_quoted(tmp_path: Path) -> None:
    """'found 'list'' read as if the value were the text "list"; a count of entries as if it
    were a string: both are descriptions of what was found."""
    from handctl.online.recipes.loader import load_recipe

    path = tmp_path / "r.yaml"
    path.write_text("recipe: x\ndescription: y\nphases: 5\n", encoding="utf-8")
    with pytest.raises(ConfigError, match=r"found int 5$"):
        load_recipe(path, load_hand(HAND_YAML))
    path.write_text("recipe: x\ndescription: y\nphases: []\n", encoding="utf-8")
    with pytest.raises(ConfigError, match=r"found 0 entries$"):
        load_recipe(path, load_hand(HAND_YAML))
