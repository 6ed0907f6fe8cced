"""handctl's one YAML reader (handctl/schema.py): each key once, bounded work, one number rule,
line numbers where the mistake is. Each finding of the attack campaign is one test here."""

from __future__ import annotations

import ast
import math
import os
import re
import tracemalloc
from pathlib import Path
from typing import Any

import pytest
import yaml
from hypothesis import example, given, settings
from hypothesis import strategies as st

from handctl.config import HandConfig, load_hand
from handctl.errors import ConfigError
from handctl.online.recipes.loader import load_recipe
from handctl.schema import MAX_BYTES, MAX_DEPTH, MAX_NODES, dump_yaml, load_yaml, parse_yaml

from ..conftest import HAND_YAML, ROOT, handctl

HAND_TEXT = HAND_YAML.read_text(encoding="utf-8")
RECIPE_YAML = ROOT / "config" / "recipes" / "swap_two_cylinders.yaml"


def error(text: str, name: str = "doc.yaml") -> ConfigError:
    with pytest.raises(ConfigError) as info:
        parse_yaml(text, name)
    assert name in str(info.value)
    return info.value


def line_of(text: str, needle: str) -> int:
    """1-based number of the first line holding ``needle``."""
    return next(i for i, line in enumerate(text.splitlines(), 1) if needle in line)


def replace_on(text: str, line: int, old: str, new: str) -> str:
    lines = text.splitlines(keepends=True)
    assert old in lines[line - 1]
    lines[line - 1] = lines[line - 1].replace(old, new, 1)
    return "".join(lines)


def hand_file(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "hand.yaml"
    path.write_text(text, encoding="utf-8")
    return path


# -- each key once ------------------------------------------------------------------------------
def test_two_tau_max_in_the_anchored_joint_are_refused_naming_both_places(tmp_path: Path) -> None:
    """The finding: a second tau_max in f1_j1 became the limit of all three first joints."""
    line = line_of(HAND_TEXT, "&flexor")
    text = replace_on(HAND_TEXT, line, "tau_max: 0.60,", "tau_max: 0.60, tau_max: 0.80,")
    with pytest.raises(ConfigError) as info:
        load_hand(hand_file(tmp_path, text))
    err = info.value
    assert err.key == "fingers[0].joints[0].tau_max"
    assert "each key once" in err.expected
    first = text.splitlines()[line - 1].index("tau_max: 0.60") + 1
    second = text.splitlines()[line - 1].index("tau_max: 0.80") + 1
    assert str(err.found) == (
        f"'tau_max' at line {line}, column {first} and again at line {line}, column {second}"
    )


def test_a_key_repeated_on_another_line_is_refused_naming_both_lines() -> None:
    err = error("bus:\n  fd: true\n  bitrate: 1\n  fd: false\n")
    assert err.key == "bus.fd"
    assert "line 2, column 3 and again at line 4, column 3" in str(err)


def test_a_merged_key_is_overridden_by_the_mapping_s_own_key() -> None:
    """Merge keys supply defaults; that is the hand config's own use of them."""
    doc = parse_yaml(HAND_TEXT, "hand.yaml")
    joints = doc.data["fingers"][0]["joints"]
    assert [j["tau_max"] for j in joints] == [0.60, 0.45, 0.30]
    assert joints[1]["rate_limit"] == joints[0]["rate_limit"] == 20.0


def test_a_key_two_merged_mappings_supply_is_refused() -> None:
    text = "a: &a {t: 1, u: 1}\nb: &b {t: 2}\nc: {<<: [*a, *b], v: 3}\n"
    err = error(text)
    assert err.key == "c.t"
    assert "line 1, column 8" in str(err) and "line 2, column 8" in str(err)


def test_a_mapping_merged_twice_is_refused_naming_it_once() -> None:
    """It was refused as a key two merged mappings supply, "from line 1, column 8 and from
    line 1, column 8" (found by an outside audit)."""
    err = error("a: &a {t: 1, u: 1}\nc: {<<: [*a, *a], v: 3}\n")
    assert err.key == "c.<<" and err.expected == "each mapping merged once"
    assert str(err).endswith("found the mapping at line 1, column 4, twice")


def test_a_merge_inside_a_merged_mapping_is_resolved_there_first() -> None:
    doc = parse_yaml("a: &a {t: 1, u: 1}\nb: &b {<<: *a, t: 2}\nc: {<<: *b, u: 3}\n", "d")
    assert doc.data["c"] == {"t": 2, "u": 3}


def test_two_merge_keys_and_merging_a_scalar_are_refused() -> None:
    assert "<<" in error("a: &a {t: 1}\nb: {<<: *a, <<: *a}\n").key
    assert "a mapping or a list of mappings" in error("a: &a 1\nb: {<<: *a}\n").expected


keys = st.text(alphabet="abcdefghij_", min_size=1, max_size=6)


@settings(max_examples=200, deadline=None)
@given(st.lists(keys, min_size=2, max_size=12, unique=True), st.data())
def test_any_key_written_twice_is_refused_with_both_lines(
    names: list[str], data: st.DataObject
) -> None:
    twice = data.draw(st.sampled_from(names))
    lines = [f"{name}: {i}" for i, name in enumerate(names)]
    at = data.draw(st.integers(0, len(lines)))
    lines.insert(at, f"{twice}: again")
    text = "\n".join(lines) + "\n"
    numbers = [i for i, line in enumerate(lines, 1) if line.split(":")[0] == twice]
    err = error(text)
    assert err.key == twice
    assert f"at line {numbers[0]}, column 1 and again at line {numbers[1]}, column 1" in str(err)
    assert parse_yaml("\n".join(lines[:at] + lines[at + 1 :]), "d").data == {
        name: i for i, name in enumerate(names)
    }


def test_anchors_are_defined_once_and_aliases_do_not_recurse() -> None:
    assert "already defined at line 1" in str(error("a: &x 1\nb: &x 2\nc: *x\n"))
    assert "no recursive" in error("a: &x [1, *x]\n").expected
    assert "*nope at line 1" in str(error("a: *nope\n"))
    assert "one YAML document" in error("a: 1\n---\nb: 2\n").expected


# -- bounded work -------------------------------------------------------------------------------
def laughs(depth: int, fan_out: int = 10, key: str = "lol") -> str:
    """A billion-laughs document: ``fan_out ** depth`` strings behind one alias."""
    text = f"{key}0: &l0 [" + ", ".join(["lol"] * fan_out) + "]\n"
    for i in range(1, depth):
        text += f"{key}{i}: &l{i} [" + ", ".join([f"*l{i - 1}"] * fan_out) + "]\n"
    return text


def refused_cheaply(load: Any) -> ConfigError:
    """Run ``load`` and return its ConfigError, having checked the cost and the message."""
    tracemalloc.start()
    try:
        with pytest.raises(ConfigError) as info:
            load()
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert peak < 20e6
    assert len(str(info.value)) < 400
    return info.value


@pytest.mark.parametrize("where", ["an unknown key", "tau_max"])
def test_an_alias_bomb_in_a_hand_config_is_refused_cheaply(tmp_path: Path, where: str) -> None:
    """The finding: 3 GB and 40 s, and a MemoryError (exit 1) in an unknown key."""
    bomb = laughs(9, key="x_")  # 10**9 strings
    if where == "an unknown key":
        path = hand_file(tmp_path, HAND_TEXT + bomb + "surprise: *l8\n")
    else:
        line = line_of(HAND_TEXT, "&flexor")
        path = hand_file(
            tmp_path, bomb + replace_on(HAND_TEXT, line, "tau_max: 0.60", "tau_max: *l8")
        )
    err = refused_cheaply(lambda: load_hand(path))
    assert f"at most {MAX_NODES} values with every alias expanded" in err.expected


@pytest.mark.parametrize("key", ["description", "recipe", "surprise", "planned_from"])
def test_an_alias_bomb_in_a_recipe_is_refused_cheaply(
    tmp_path: Path, hand: HandConfig, key: str
) -> None:
    """The finding: a bomb in ``description`` was accepted."""
    data: dict[str, Any] = yaml.safe_load(RECIPE_YAML.read_text(encoding="utf-8"))
    data.pop(key, None)
    path = tmp_path / "recipe.yaml"
    path.write_text(laughs(9, key="x_") + f"{key}: *l8\n" + dump_yaml(data), encoding="utf-8")
    err = refused_cheaply(lambda: load_recipe(path, hand))
    assert f"at most {MAX_NODES} values with every alias expanded" in err.expected


def test_a_description_is_text(tmp_path: Path, hand: HandConfig) -> None:
    data: dict[str, Any] = yaml.safe_load(RECIPE_YAML.read_text(encoding="utf-8"))
    data["description"] = ["a", "list"]
    path = tmp_path / "recipe.yaml"
    path.write_text(dump_yaml(data), encoding="utf-8")
    with pytest.raises(ConfigError, match="description: expected text"):
        load_recipe(path, hand)


def expanded_size(depth: int, fan_out: int) -> int:
    """Values of ``laughs(depth, fan_out) + 'top: *l{depth - 1}'`` with aliases expanded."""
    sizes = [1 + fan_out]
    for _ in range(1, depth):
        sizes.append(1 + fan_out * sizes[-1])
    return 1 + sum(1 + size for size in sizes) + 1 + sizes[-1]


@settings(max_examples=60, deadline=None)
@given(st.integers(1, 8), st.integers(2, 12))
def test_aliases_are_expanded_up_to_the_bound_and_refused_beyond(depth: int, fan_out: int) -> None:
    text = laughs(depth, fan_out) + f"top: *l{depth - 1}\n"
    if expanded_size(depth, fan_out) <= MAX_NODES:
        leaves = parse_yaml(text, "d").data["top"]
        for _ in range(depth - 1):
            leaves = [leaf for item in leaves for leaf in item]
        assert leaves == ["lol"] * fan_out**depth
    else:
        assert "alias" in error(text).expected


def test_nesting_is_bounded() -> None:
    assert parse_yaml("a: " + "[" * (MAX_DEPTH - 1) + "]" * (MAX_DEPTH - 1), "d")
    err = error("a: " + "[" * 200_000)
    assert f"nested at most {MAX_DEPTH} deep" in err.expected
    assert "deeper at line 1" in str(err)


def test_a_file_larger_than_the_bound_is_refused_unread(tmp_path: Path) -> None:
    path = tmp_path / "big.yaml"
    with path.open("w") as file:
        file.write("a: 1\n")
        file.write("# padding\n" * (10 * MAX_BYTES // 10))
    with pytest.raises(ConfigError, match=f"at most {MAX_BYTES} bytes"):
        load_yaml(path)
    path.write_text("a: 1\n" + "#" * (MAX_BYTES - 10) + "\n")
    assert load_yaml(path).data == {"a": 1}


def test_a_huge_integer_is_refused_not_converted() -> None:
    assert "at most 100 digits" in error("a: " + "9" * 5000 + "\n").expected


# -- one number rule ----------------------------------------------------------------------------
@pytest.mark.parametrize(
    ("text", "value"),
    [
        ("1:00", "1:00"),  # YAML 1.1: 60
        ("1e308", 1e308),  # YAML 1.1: a string
        ("-2.5E-3", -2.5e-3),
        (".5", 0.5),
        ("1.", 1.0),
        ("0o17", 15),
        ("0x1F", 31),
        ("-12", -12),
        ("+5", 5),
        ("0", 0),
        (".inf", math.inf),
        ("-.Inf", -math.inf),
        ("true", True),
        ("false", False),
        ("True", "True"),  # only true and false are booleans
        ("yes", "yes"),
        ("on", "on"),
        ("1_000", "1_000"),
        ("0b101", "0b101"),
        ("2001-12-14", "2001-12-14"),  # YAML 1.1: a date
        ("~", None),
        ("null", None),
        ("'017'", "017"),
        ("!!float 1", 1.0),
        ("!!str 1.5", "1.5"),
        ("!!int 0x10", 16),
    ],
)
def test_the_number_rule(text: str, value: object) -> None:
    assert parse_yaml(f"v: {text}\n", "d").data["v"] == value
    assert type(parse_yaml(f"v: {text}\n", "d").data["v"]) is type(value)


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        ("017", "leading zero"),  # 15 in YAML 1.1, 17 in YAML 1.2
        ("-00", "leading zero"),
        ("!!int 1.5", "an integer"),
        ("!!float x", "a number"),
        ("!!bool yes", "true or false"),
        ("!!binary aGk=", "a tag of YAML's core schema"),
        ("!!timestamp 2001-12-14", "a tag of YAML's core schema"),
        ("!!python/name:os.system", "a tag of YAML's core schema"),
        ("!custom 1", "a tag of YAML's core schema"),
    ],
)
def test_what_the_number_rule_refuses(text: str, expected: str) -> None:
    err = error(f"x:\n  v: {text}\n")
    assert err.key == "x.v"
    assert expected in err.expected
    assert "line 2, column 6" in str(err)


def test_a_sexagesimal_max_s_is_refused(tmp_path: Path, hand: HandConfig) -> None:
    """The finding: ``max_s: 1:00`` ran as a 60 s phase."""
    recipe = RECIPE_YAML.read_text(encoding="utf-8")
    path = tmp_path / "recipe.yaml"
    path.write_text(recipe.replace("max_s: 1.0\n", "max_s: 1:00\n", 1), encoding="utf-8")
    with pytest.raises(ConfigError) as info:
        load_recipe(path, hand)
    assert info.value.key == "phases[0].max_s"
    assert "a number" in info.value.expected
    assert "'1:00'" in str(info.value)


@settings(max_examples=300, deadline=None)
@given(st.floats(allow_nan=False))
def test_every_float_reads_as_itself(x: float) -> None:
    assert parse_yaml(f"v: {x!r}\n".replace("inf", ".inf"), "d").data["v"] == x
    assert parse_yaml(dump_yaml({"v": x}), "d").data["v"] == x


@settings(max_examples=300, deadline=None)
@given(st.integers(-(10**30), 10**30))
def test_every_integer_reads_as_itself_in_each_base(n: int) -> None:
    assert parse_yaml(f"v: {n}\n", "d").data["v"] == n
    if n >= 0:
        assert parse_yaml(f"v: {n:#x}\n", "d").data["v"] == n
        assert parse_yaml(f"v: {n:#o}\n", "d").data["v"] == n


@settings(max_examples=300, deadline=None)
@given(
    st.text(max_size=20)
    | st.from_regex(
        r"[-+]?[0-9]{1,3}(:[0-5][0-9]){1,2}|[0-9._eE+-]{1,8}"
        r"|0[xob][0-9a-fA-F_]{1,5}|[TtYyNnOo][a-zA-Z]{0,4}",
        fullmatch=True,
    )
)
@example("\x85")  # a line break to YAML 1.1: folded to a space unless escaped
@example("a\u2028b")
def test_a_written_string_reads_back_as_that_string(s: str) -> None:
    """What handctl plan writes, handctl and any YAML 1.1 reader read back unchanged."""
    text = dump_yaml({"v": s})
    assert parse_yaml(text, "d").data["v"] == s
    assert yaml.safe_load(text)["v"] == s


@settings(max_examples=200, deadline=None)
@given(st.from_regex(r"[0-9]{1,3}(:[0-5][0-9]){1,2}", fullmatch=True))
def test_sexagesimal_is_text(s: str) -> None:
    assert parse_yaml(f"v: {s}\n", "d").data["v"] == s


# -- line numbers -------------------------------------------------------------------------------
FLOW_LINES = [
    i
    for i, line in enumerate(HAND_TEXT.splitlines(), 1)
    if line.rstrip().endswith("}") and not line.lstrip().startswith("#")
]


@pytest.mark.parametrize("line", FLOW_LINES)
def test_a_missing_closing_brace_is_reported_on_its_line(tmp_path: Path, line: int) -> None:
    """The finding: line 18 reported for a mistake on line 17."""
    lines = HAND_TEXT.splitlines(keepends=True)
    lines[line - 1] = lines[line - 1].rstrip()[:-1] + "\n"
    with pytest.raises(ConfigError) as info:
        load_hand(hand_file(tmp_path, "".join(lines)))
    assert re.search(rf"valid YAML at (the end of line|line) {line}\b", info.value.expected), str(
        info.value
    )


# Lines "key: value" of block mappings (not inside a flow mapping), except the first key of a
# nested mapping: without its ':' that line is the parent's (valid) scalar value, not a mistake
# YAML can see.
_LINES = HAND_TEXT.splitlines()
KEY_LINES = [
    i
    for i, line in enumerate(_LINES, 1)
    if re.match(r"\s*[a-z_]+: [^{\[]", line)
    and "," not in line.split("#")[0]
    and not _LINES[i - 2].endswith(":")
]


@pytest.mark.parametrize("line", KEY_LINES)
def test_a_key_without_its_colon_is_reported_on_its_line(tmp_path: Path, line: int) -> None:
    text = replace_on(HAND_TEXT, line, ": ", " ")
    with pytest.raises(ConfigError) as info:
        load_hand(hand_file(tmp_path, text))
    assert re.search(rf"valid YAML at (the end of line|line) {line}\b", info.value.expected), str(
        info.value
    )


@settings(max_examples=200, deadline=None)
@given(st.integers(2, 30), st.data())
def test_a_mistake_on_line_n_is_reported_on_line_n(n_lines: int, data: st.DataObject) -> None:
    lines = [f"k{i}: [{i}, {i + 1}]" for i in range(n_lines)]
    bad = data.draw(st.integers(0, n_lines - 1))
    mistake = data.draw(st.sampled_from(["no colon", "no bracket", "unclosed quote"]))
    if mistake == "no colon":
        lines[bad] = lines[bad].replace(":", "", 1)
    elif mistake == "no bracket":
        lines[bad] = lines[bad][:-1]
    else:
        lines[bad] = lines[bad].replace("[", "'[", 1)
    err = error("\n".join(lines) + "\n")
    assert re.search(rf"valid YAML at (the end of line|line) {bad + 1}\b", err.expected), (
        "\n".join(lines),
        str(err),
    )


def test_a_character_yaml_forbids_is_reported_at_its_line_not_its_offset() -> None:
    err = error("a: 1\nb: x\x00y\n")
    assert "valid YAML at line 2, column 5" in err.expected
    assert "'\\x00'" in str(err)


def test_lines_and_columns_count_from_one() -> None:
    assert "valid YAML at line 1, column 5" in error("a: b: c\n").expected
    assert "valid YAML at line 3, column 3" in error("a:\n  - 1\n  b: 2\n").expected


# -- one entry point -----------------------------------------------------------------------------
def test_only_the_schema_module_imports_yaml() -> None:
    offenders = []
    for path in sorted((ROOT / "handctl").rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            names = (
                [a.name for a in node.names]
                if isinstance(node, ast.Import)
                else [node.module or ""]
                if isinstance(node, ast.ImportFrom)
                else []
            )
            if any(n == "yaml" or n.startswith("yaml.") for n in names):
                offenders.append(str(path.relative_to(ROOT)))
    assert sorted(set(offenders)) == ["handctl/schema.py"]


# -- the CLI ------------------------------------------------------------------------------------
def test_check_refuses_an_alias_bomb_with_exit_2(tmp_path: Path) -> None:
    path = hand_file(tmp_path, HAND_TEXT + laughs(9, key="x_") + "surprise: *l8\n")
    result = handctl("check", str(path))
    assert result.returncode == 2, result.stderr
    assert f"{path}: expected at most {MAX_NODES} values with every alias expanded" in result.stderr
    assert "Traceback" not in result.stderr and "MemoryError" not in result.stderr
    assert len(result.stderr) < 500


def test_check_refuses_a_duplicate_key_with_exit_2(tmp_path: Path) -> None:
    line = line_of(HAND_TEXT, "&flexor")
    path = hand_file(
        tmp_path, replace_on(HAND_TEXT, line, "tau_max: 0.60,", "tau_max: 0.60, tau_max: 0.80,")
    )
    result = handctl("check", str(path))
    assert result.returncode == 2
    assert f"{path}: fingers[0].joints[0].tau_max: expected each key once" in result.stderr
    assert f"again at line {line}" in result.stderr


@pytest.mark.parametrize(
    ("document", "old", "new", "key"),
    [
        ("hand", "name: hiroshima_hand", 'name: "hand\\e]0;pwned\\a"', "name"),
        ("recipe", "recipe: swap_two_cylinders", 'recipe: "swap\\nfake line"', "recipe"),
        ("recipe", "- name: approach", '- name: "appr\\toach"', "phases[0].name"),
    ],
)
def test_a_name_with_a_control_character_is_refused(
    tmp_path: Path, hand: HandConfig, document: str, old: str, new: str, key: str
) -> None:
    """Names are printed by every summary, status line and replay: an escape sequence in a
    hand's name retitled and cleared the terminal of whoever ran it, or replayed its log; a
    newline in a phase's name forged a line of the output."""
    source = HAND_TEXT if document == "hand" else RECIPE_YAML.read_text(encoding="utf-8")
    assert source.count(old) == 1
    path = tmp_path / f"{document}.yaml"
    path.write_text(source.replace(old, new), encoding="utf-8")
    with pytest.raises(ConfigError) as info:
        load_hand(path) if document == "hand" else load_recipe(path, hand)
    assert info.value.key == key
    assert "a name of printable characters" in info.value.expected


def test_an_input_that_is_not_a_regular_file_is_refused_without_waiting_on_it(
    tmp_path: Path,
) -> None:
    """A FIFO no one writes held ``run recipe FIFO`` in its open() for good, deaf to Ctrl-C
    and SIGTERM; a directory said only 'Is a directory'. Refused at once, the kind named (run
    in a subprocess, so that a regression is a timeout, not a hung suite)."""
    fifo = tmp_path / "recipe.yaml"
    os.mkfifo(fifo)
    cases = [
        (["run", "recipe", str(fifo)], f"{fifo}: expected a regular file", "a FIFO (named pipe)"),
        (["run", "recipe", str(tmp_path)], f"{tmp_path}: expected a regular file", "a directory"),
        (["run", "recipe", os.devnull], "expected a regular file", "a character device"),
    ]
    for args, said, kind in cases:
        done = handctl(*args, timeout=60)
        assert done.returncode == 2, (args, done.stderr)
        assert said in done.stderr and kind in done.stderr, done.stderr
        assert "Traceback" not in done.stderr
    with pytest.raises(ConfigError) as err:
        load_yaml(tmp_path)
    assert (err.value.key, err.value.found) == ("", "a directory")


@pytest.mark.parametrize(
    ("given", "load", "said"),
    [
        (
            "config/recipes/swap_two_cylinders.template.yaml",
            "recipe",
            "expected a recipe, found a recipe template; compile it into a recipe with "
            "'handctl plan TEMPLATE.yaml -o RECIPE.yaml'",
        ),
        (
            "config/hands/hiroshima_hand.yaml",
            "recipe",
            "expected a recipe, found a hand config; give it where a command takes the hand "
            "('handctl check HAND.yaml', --hand HAND.yaml)",
        ),
        (
            "config/recipes/swap_two_cylinders.yaml",
            "template",
            "expected a recipe template, found a recipe; run it with 'handctl run recipe "
            "RECIPE.yaml'",
        ),
        (
            "config/recipes/swap_two_cylinders.yaml",
            "hand",
            "expected a hand config, found a recipe",
        ),
        ("config/sim/bus_trouble.yaml", "hand", "expected a hand config, found a fault list"),
        ("config/analysis/paper_fig3.yaml", "recipe", "expected a recipe, found an analysis"),
    ],
)
def test_a_file_of_another_kind_is_named_as_what_it_is(given: str, load: str, said: str) -> None:
    """A template given to ``run`` was refused on 'phases[0].pose.angles: expected this
    key', a recipe given to ``plan`` on 'template: expected this key': true, and no help to
    someone who gave the wrong file."""
    from handctl.config import load_hand
    from handctl.online.recipes.loader import load_recipe
    from handctl.planning.template import load_template

    hand = load_hand(ROOT / "config" / "hands" / "hiroshima_hand.yaml")
    path = ROOT / given
    with pytest.raises(ConfigError) as info:
        if load == "recipe":
            load_recipe(path, hand)
        elif load == "template":
            load_template(path, hand)
        else:
            load_hand(path)
    assert said in str(info.value), str(info.value)


def test_a_template_without_its_first_key_is_not_called_a_recipe(tmp_path: Path) -> None:
    """A template that lost its ``template:`` line was called a recipe, to run with 'handctl
    run recipe', which then refused it on 'phases[0].kind: expected no such key here'."""
    from handctl.config import load_hand
    from handctl.planning.template import load_template

    hand = load_hand(ROOT / "config" / "hands" / "planar_2f2j.yaml")
    source = ROOT / "config" / "recipes" / "planar_lift_turn.template.yaml"
    lines = source.read_text().splitlines(keepends=True)
    cut = tmp_path / "no_first_key.yaml"
    cut.write_text("".join(line for line in lines if not line.startswith("template:")))
    with pytest.raises(ConfigError) as info:
        load_template(cut, hand)
    assert info.value.key == "template"
    assert "the key is missing; its phases have a kind each" in str(info.value)
    assert "run it with" not in str(info.value)


def test_the_parser_s_found_is_said_once(tmp_path: Path) -> None:
    """'expected valid YAML at line 1, column 4, found found character ...'"""
    bad = tmp_path / "bad.yaml"
    bad.write_text("a: @x\n")
    with pytest.raises(ConfigError) as info:
        load_yaml(bad)
    assert "found character that cannot start any token" in str(info.value)
    assert "found found" not in str(info.value)


@pytest.mark.parametrize("new", ['name: " "', 'name: " hiroshima_hand"', 'name: "hand "'])
def test_a_hand_name_of_spaces_or_with_spaces_at_its_ends_is_refused(
    tmp_path: Path, new: str
) -> None:
    """A hand named " " passed check (an empty name did not) and showed as nothing in check,
    the summary and the plot's title (found by an outside audit)."""
    assert HAND_TEXT.count("name: hiroshima_hand") == 1
    path = tmp_path / "hand.yaml"
    path.write_text(HAND_TEXT.replace("name: hiroshima_hand", new), encoding="utf-8")
    with pytest.raises(ConfigError) as info:
        load_hand(path)
    assert info.value.key == "name"
    assert "a name not beginning or ending with a space" in info.value.expected


def test_a_recording_s_hand_and_recipe_are_read_as_they_ran_whatever_their_names(
    tmp_path: Path, hand: HandConfig
) -> None:
    """A name with a space at one end is refused in a hand config or a recipe to run, but a
    recording made before that rule still replays (it exited 2: found by an outside review)."""
    from handctl.config import parse_hand
    from handctl.hand_protocol import protocol_for
    from handctl.online.recipes.loader import parse_recipe
    from handctl.schema import parse_yaml

    text = HAND_TEXT.replace("name: hiroshima_hand", 'name: "hiroshima_hand "')
    with pytest.raises(ConfigError):
        parse_hand(parse_yaml(text, "hand.yaml"))
    recorded = parse_hand(parse_yaml(text, "hand.yaml"), protocol_for(hand))
    assert recorded.name == "hiroshima_hand "
    recipe = RECIPE_YAML.read_text(encoding="utf-8")
    old = recipe.replace("recipe: swap_two_cylinders", 'recipe: "swap_two_cylinders "')
    with pytest.raises(ConfigError):
        parse_recipe(parse_yaml(old, "recipe.yaml"), hand)
    assert parse_recipe(parse_yaml(old, "recipe.yaml"), hand, as_recorded=True).name == (
        "swap_two_cylinders "
    )


@pytest.mark.parametrize(
    ("read", "value", "said"),
    [
        (lambda d: d.integer("n", min=0, max=2**32 - 1), 2**32, "<= 4294967295, found 4294967296"),
        (lambda d: d.integer("n", min=10_000, max=1_000_000), 1_000_001, "<= 1000000, found"),
        (lambda d: d.number("n", min=0.0, max=1e6), 1e6 + 1, "<= 1000000"),
        (lambda d: d.number("n", min=0.001, max=10.0), 20.0, ">= 0.001 and <= 10"),
    ],
)
def test_a_bound_is_said_in_all_its_digits(read: Any, value: Any, said: str) -> None:
    """Six significant digits of a whole-number bound said "<= 4.29497e+09, found
    4294967296": a value past the bound that read as one within it."""
    from handctl.errors import ConfigError
    from handctl.schema import Doc

    with pytest.raises(ConfigError) as info:
        read(Doc({"n": value}, "f.yaml", ""))
    assert said in str(info.value)


@pytest.mark.parametrize(
    ("old", "new", "key", "kind"),
    [
        (
            "  loop_rate_hz: 1000",
            '  loop_rate_hz: "' + "7" * 200_000 + '"',
            "bus.loop_rate_hz",
            "str",
        ),
        ("name: planar_2f2j", "name: " + "7" * 100, "name", "int"),
    ],
    ids=["string", "integer"],
)
def test_a_value_of_the_wrong_type_is_shown_cut_to_80_characters(
    tmp_path: Path, old: str, new: str, key: str, kind: str
) -> None:
    """A string of 200000 sevens where a number belongs was shown to 1000 characters, a
    message of 1113 (found by an outside audit); no message shows more than 80 of a value."""
    from handctl.errors import SHOWN_CHARS

    text = (ROOT / "config" / "hands" / "planar_2f2j.yaml").read_text(encoding="utf-8")
    assert f"\n{old}\n" in text
    path = tmp_path / "hand.yaml"
    path.write_text(text.replace(f"\n{old}\n", f"\n{new}\n", 1), encoding="utf-8")
    with pytest.raises(ConfigError) as info:
        load_hand(path)
    assert info.value.key == key
    found = str(info.value).split(", found ", 1)[1]
    assert found.startswith(f"{kind} ") and "777..." in found
    assert len(found) <= len(kind) + 1 + SHOWN_CHARS


def test_a_byte_that_is_not_utf8_is_said_at_its_line_and_column(tmp_path: Path) -> None:
    """It was said by the decoder's byte offset ("position 1014"), where every other mistake
    in a YAML file is said at its line and column (found by an outside audit). Columns count
    characters: the ä before the byte is one."""
    text = (ROOT / "config" / "hands" / "planar_2f2j.yaml").read_bytes()
    lines = text.split(b"\n")
    line = lines.index(b"name: planar_2f2j") + 1
    path = tmp_path / "hand.yaml"
    path.write_bytes(text.replace(b"name: planar_2f2j", "name: planär".encode() + b"\xff", 1))
    with pytest.raises(ConfigError) as info:
        load_hand(path)
    assert info.value.expected == f"UTF-8 text at line {line}, column 13"
    assert str(info.value).endswith("found byte 0xFF (invalid start byte)")
