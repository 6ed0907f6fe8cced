"""Hypothesis: the hand-config and recipe loaders answer any input, random or a mutation of a
good file, with a ConfigError that carries a message, or with a valid object; never with
another exception."""

from __future__ import annotations

import os
import re
from pathlib import Path
from typing import Any

import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from handctl.config import HandConfig, load_hand
from handctl.errors import ConfigError
from handctl.online.recipes.loader import load_recipe
from handctl.schema import parse_yaml

from ..conftest import HAND_YAML, ROOT

#: YAML's line breaks (str.splitlines counts more, e.g. form feeds).
YAML_LINE_BREAKS = re.compile("\r\n|[\r\n\x85\u2028\u2029]")
RECIPE_YAML = ROOT / "config" / "recipes" / "swap_two_cylinders.yaml"
EXAMPLES = int(os.environ.get("HANDCTL_FUZZ_EXAMPLES", "2000")) // 10
HAND_DATA = yaml.safe_load(HAND_YAML.read_text())
RECIPE_DATA = yaml.safe_load(RECIPE_YAML.read_text())
#: libyaml's safe dumper where PyYAML has it: the documents of ``yaml.safe_dump``, written
#: fast enough that this module runs in 21 s instead of 36 (the Python dumper was most of it)
DUMPER: Any = getattr(yaml, "CSafeDumper", yaml.SafeDumper)

scalars = st.one_of(
    st.none(),
    st.booleans(),
    st.integers(-(10**6), 10**6),
    st.floats(allow_nan=True, allow_infinity=True),
    st.text(max_size=12),
)
values = st.recursive(
    scalars,
    lambda inner: st.one_of(
        st.lists(inner, max_size=4), st.dictionaries(st.text(max_size=8), inner, max_size=4)
    ),
    max_leaves=12,
)


def paths(data: Any, prefix: tuple[Any, ...] = ()) -> list[tuple[Any, ...]]:
    """Every key path in a YAML document, for choosing what to mutate."""
    out = [prefix]
    if isinstance(data, dict):
        for key, value in data.items():
            out += paths(value, (*prefix, key))
    elif isinstance(data, list):
        for i, value in enumerate(data):
            out += paths(value, (*prefix, i))
    return out


@st.composite
def mutated(draw: st.DrawFn, original: Any) -> Any:
    import copy

    data = copy.deepcopy(original)
    for _ in range(draw(st.integers(1, 3))):
        choices = [p for p in paths(data) if p]
        if not choices:
            break
        path = draw(st.sampled_from(choices))
        parent = data
        for key in path[:-1]:
            parent = parent[key]
        action = draw(st.sampled_from(["replace", "delete", "add"]))
        if action == "replace":
            parent[path[-1]] = draw(values)
        elif action == "delete":
            del parent[path[-1]]
        elif isinstance(parent, dict):
            parent[draw(st.text(min_size=1, max_size=8))] = draw(values)
        else:
            parent.append(draw(values))
    return data


def hand_from(tmp: Path, data: Any) -> HandConfig:
    path = tmp / "hand.yaml"
    path.write_text(yaml.dump(data, Dumper=DUMPER) if not isinstance(data, str) else data)
    return load_hand(path)


def expect_config_error_or_valid(call: Any) -> None:
    try:
        call()
    except ConfigError as exc:
        assert str(exc) and exc.file
        assert "expected" in str(exc)


@settings(
    max_examples=EXAMPLES,
    deadline=None,
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
)
@given(mutated(HAND_DATA))
def test_mutated_hand_configs(tmp_path: Path, data: Any) -> None:
    expect_config_error_or_valid(lambda: hand_from(tmp_path, data))


@settings(
    max_examples=EXAMPLES,
    deadline=None,
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
)
@given(mutated(RECIPE_DATA))
def test_mutated_recipes(tmp_path: Path, hand: HandConfig, data: Any) -> None:
    path = tmp_path / "recipe.yaml"
    path.write_text(yaml.dump(data, Dumper=DUMPER))
    expect_config_error_or_valid(lambda: load_recipe(path, hand))


@settings(max_examples=EXAMPLES, deadline=None)
@given(st.text(max_size=200))
def test_random_text_as_yaml(text: str) -> None:
    """Any text is a mapping or a ConfigError of this file, and a line it names is in it."""
    try:
        doc = parse_yaml(text, "fuzz.yaml")
    except ConfigError as exc:
        assert exc.file == "fuzz.yaml" and exc.expected
        lines = len(YAML_LINE_BREAKS.split(text))
        for named in re.findall(r"line (\d+)", exc.expected):
            assert 1 <= int(named) <= lines, (exc.expected, lines)
    else:
        assert isinstance(doc.data, dict)


@settings(
    max_examples=EXAMPLES,
    deadline=None,
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
)
@given(values)
def test_random_documents_as_recipes(tmp_path: Path, hand: HandConfig, data: Any) -> None:
    path = tmp_path / "recipe.yaml"
    path.write_text(yaml.dump(data, Dumper=DUMPER))
    expect_config_error_or_valid(lambda: load_recipe(path, hand))


#: The characters YAML's syntax is made of, so that random text is mostly anchors, aliases,
#: merges, tags, flow and block collections, quotes and numbers rather than plain words.
YAML_ALPHABET = "ab<:- \n\t[]{},&*!'\"#|>%?.0123456789exo+_~"


@settings(max_examples=EXAMPLES * 5, deadline=None)
@given(st.text(alphabet=YAML_ALPHABET, max_size=120))
def test_yaml_syntax_soup_gives_a_document_or_a_config_error(text: str) -> None:
    try:
        doc = parse_yaml(text, "soup.yaml")
    except ConfigError as exc:
        assert str(exc).startswith("soup.yaml")
        assert "expected" in str(exc)
    else:
        assert isinstance(doc.data, dict)


@settings(
    max_examples=EXAMPLES,
    deadline=None,
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
)
@given(st.data())
def test_mutated_hand_config_text(tmp_path: Path, data: st.DataObject) -> None:
    """The hand config's own text (anchors, merges, flow mappings) with a line duplicated,
    dropped, or a few characters changed."""
    lines = HAND_YAML.read_text(encoding="utf-8").splitlines(keepends=True)
    for _ in range(data.draw(st.integers(1, 3))):
        i = data.draw(st.integers(0, len(lines) - 1))
        action = data.draw(st.sampled_from(["duplicate", "drop", "edit"]))
        if action == "duplicate":
            lines.insert(i, lines[i])
        elif action == "drop":
            del lines[i]
        else:
            line = lines[i]
            at = data.draw(st.integers(0, max(len(line) - 1, 0)))
            new = data.draw(st.text(alphabet=YAML_ALPHABET, max_size=3))
            lines[i] = line[:at] + new + line[at + 1 :]
    expect_config_error_or_valid(lambda: hand_from(tmp_path, "".join(lines)))
