"""How an error message shows the value it names: as ``repr`` would, but never with a raw
control character, and with a byte that is not UTF-8 shown as the byte."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from handctl.config import load_hand
from handctl.errors import DESCRIPTION_CHARS, ConfigError, Description, absent, escaped
from handctl.recording.reader import open_recording
from handctl.schema import read_input

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


def test_the_file_and_the_key_are_shown_escaped_as_the_value_is() -> None:
    """A YAML key written with a double-quoted escape ("bad\\e[2Jkey") and a file name that
    holds one were written raw: the message cleared the terminal that showed it."""
    message = str(ConfigError("d/bad\x1b[2J\udcff.yaml", "a.bad\x1b[2Jkey\n", "x", 1))
    assert message == r"d/bad\x1b[2J\xff.yaml: a.bad\x1b[2Jkey\n: expected x, found 1"
    assert str(ConfigError("ok é.yaml", "fingers[1].joints[0].tau_max", "x", 1)) == (
        "ok é.yaml: fingers[1].joints[0].tau_max: expected x, found 1"
    )


def _hand_with_key_renamed(tmp_path: Path, where: str, key: str, new: str) -> Path:
    """The shipped hand with the first finger's (``where`` "finger") or its first joint's
    (``where`` "joint") ``key`` written under ``new`` instead."""
    import yaml

    data = yaml.safe_load(HAND_YAML.read_text(encoding="utf-8"))
    finger = data["fingers"][0]
    mapping = finger if where == "finger" else finger["joints"][0]
    mapping[new] = mapping.pop(key)
    path = tmp_path / "hand.yaml"
    path.write_text(yaml.safe_dump(data), encoding="utf-8")
    return path


@pytest.mark.parametrize(
    ("where", "key", "new", "said"),
    [
        # a joint's keys are declared: an unknown one is refused at once, as the message's key
        (
            "joint",
            "tau_max",
            "tau_m\x1b",
            r"fingers[0].joints[0].tau_m\x1b: expected no such key here (unknown key; did you "
            r"mean 'tau_max'?)",
        ),
        # a finger's are not: a misspelt one beside the missing key is named in what was found
        (
            "finger",
            "node_id",
            "node_i\x1b",
            r"fingers[0].node_id: expected this key (required), found nothing: the key is "
            r"missing; 'node_i\x1b' is here instead (a misspelling of it?)",
        ),
    ],
    ids=["the key", "a suggestion"],
)
def test_a_key_of_the_file_is_escaped_where_it_is_the_key_and_where_it_is_a_suggestion(
    tmp_path: Path, where: str, key: str, new: str, said: str
) -> None:
    """An unknown key is the message's key; a misspelt one beside a missing key is named in
    what was found ("'node_i\\x1b' is here instead"): neither raw."""
    with pytest.raises(ConfigError) as info:
        load_hand(_hand_with_key_renamed(tmp_path, where, key, new))
    message = str(info.value)
    assert "\x1b" not in message
    assert said in message


def test_a_did_you_mean_suggestion_is_quoted_as_a_value_is() -> None:
    from handctl.schema import Doc

    doc = Doc({"it's": 1}, "f.yaml", "")
    with pytest.raises(ConfigError) as info:
        doc.expect(["its'"])
    assert str(info.value).endswith('(unknown key; did you mean "its\'"?), found 1')


def test_a_description_of_what_was_found_holds_no_raw_control_character() -> None:
    """What the YAML reader describes rather than quotes (``_Text``) is shown as written,
    but for a control character a description let through."""
    from handctl.schema import _Text

    assert str(ConfigError("f.yaml", "k", "x", _Text("2 entries; 'a\\\\x1b' and \x1b"))) == (
        r"f.yaml: k: expected x, found 2 entries; 'a\\x1b' and \x1b"
    )


def test_check_shows_a_file_name_escaped_in_its_own_lines(tmp_path: Path) -> None:
    """check prints the hand config's file name on stdout and its bus refusals itself, not as
    a ``ConfigError``: a file name holding an escape sequence was written raw in both. (A
    hand's own name holding one is refused: ``test_yaml_reader``.)"""
    from ..conftest import ROOT, handctl

    classic = (ROOT / "config" / "hands" / "hiroshima_hand_classic.yaml").read_text()
    path = tmp_path / "bad\x1b[2J.yaml"
    path.write_text(classic)
    result = handctl("check", str(path))
    assert result.returncode == 2
    assert "\x1b" not in result.stdout + result.stderr
    assert rf"hand hiroshima_hand_classic ({tmp_path}/bad\x1b[2J.yaml), config hash" in (
        result.stdout
    )
    assert rf"handctl: error: {tmp_path}/bad\x1b[2J.yaml: bus.fd: expected true" in (result.stderr)


def test_a_description_handctl_told_is_shown_whole_and_unquoted() -> None:
    """Cut to 80 characters in the middle, what said what was wrong was the part left out
    (``reading stopped at byte 8 after...FError: the file ends inside a record``)."""
    told = Description("reading stopped at byte 8 after " + "x" * 60 + ": the file ends there")
    assert str(ConfigError("run.mcap", "", "an MCAP file", told)).endswith(f"found {told}")
    huge = Description("a" * 600 + "b" * 600)
    text = str(ConfigError("f", "", "e", huge)).split("found ", 1)[1]
    assert len(text) == DESCRIPTION_CHARS - 1 and text.startswith("a") and text.endswith("b")
    assert "..." in text


def test_a_link_that_leads_nowhere_is_said_as_one_not_as_no_such_file(tmp_path: Path) -> None:
    """A loop of symbolic links, or a link to a name that is gone, is no file to the file
    system, and was said as "no such file" beside a name the user can list. The command
    that reads a hand config or a recording says what it is."""
    (tmp_path / "a").symlink_to(tmp_path / "b")
    (tmp_path / "b").symlink_to(tmp_path / "a")
    (tmp_path / "dangling").symlink_to(tmp_path / "gone")
    for name in ("a", "dangling"):
        assert absent(tmp_path / name).startswith("a symbolic link that leads to no file")
    assert absent(tmp_path / "never") == "no such file"
    with pytest.raises(ConfigError, match="a symbolic link that leads to no file"):
        open_recording(tmp_path / "a")


def test_a_relative_path_that_is_no_file_says_where_it_was_looked_for(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """``cd /tmp && handctl run recipe config/recipes/...`` said "found no such file" of a
    file the user could see from the repository, without saying from where it was looked
    for. A relative path now names the current directory; an absolute one needs none."""
    here = tmp_path / "elsewhere"
    here.mkdir()
    monkeypatch.chdir(here)
    where = f" (relative to {os.getcwd()})"
    assert where == f" (relative to {here.resolve()})"
    with pytest.raises(ConfigError) as caught:
        read_input(Path("config/recipes/swap.yaml"), "a recipe", 100)
    assert str(caught.value) == (
        "config/recipes/swap.yaml: expected an existing file (a recipe), found no such file" + where
    )
    with pytest.raises(ConfigError) as caught:
        open_recording("run.mcap")
    assert str(caught.value).endswith("found no such file" + where)
    (here / "dangling").symlink_to(here / "gone")
    assert absent(Path("dangling")).endswith("missing target)" + where)
    with pytest.raises(ConfigError) as caught:
        read_input(here / "swap.yaml", "a recipe", 100)
    assert str(caught.value).endswith("found no such file")


def test_a_recipe_or_template_behind_a_link_that_leads_nowhere_is_said_as_one(
    tmp_path: Path,
) -> None:
    """Every YAML input (a recipe, a template, a fault scenario) is read through one reader,
    which said "no such file" of a dangling link the user can see in a listing."""
    (tmp_path / "recipe.yaml").symlink_to(tmp_path / "gone.yaml")
    with pytest.raises(ConfigError, match="a symbolic link that leads to no file") as caught:
        read_input(tmp_path / "recipe.yaml", "a recipe", 100)
    assert "recipe.yaml" in str(caught.value)
    with pytest.raises(ConfigError, match="no such file"):
        read_input(tmp_path / "never.yaml", "a recipe", 100)
