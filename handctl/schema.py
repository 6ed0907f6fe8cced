"""Strict reading of YAML documents with messages that name file, key path, expected and found.

Every loader of handctl (hand config, recipes, templates, analysis and fault scenarios, recorded
configs) reads through ``load_yaml``/``parse_yaml`` and ``Doc``, and this is the only module that
reads YAML text, so the rules are the same everywhere: a key that is not known is an error (a
typo must never silently fall back to a default), a value of the wrong type or out of range is
an error, and the message says exactly where.

What a file means cannot surprise:

- **Values follow YAML 1.2's core schema, a little stricter.** A plain (unquoted) scalar is
  ``null`` (``null``, ``Null``, ``NULL``, ``~`` or nothing); a boolean only when it is ``true``
  or ``false``; an integer when it is decimal (``-12``), octal ``0o17`` (15) or hexadecimal
  ``0x1F`` (31); a float when it is decimal with a fraction or an exponent (``1.5``, ``.5``,
  ``1e308``, ``-2.5E-3``) or ``.inf``, ``-.inf``, ``.nan``. Anything else is a string:
  ``yes``, ``on``, ``True``, ``1:00`` (YAML 1.1 read that as 60), ``1_000``, ``0b101`` and
  dates are text, which a number or boolean key then refuses by name. A decimal integer with a
  leading zero (``017``: 15 in YAML 1.1, 17 in 1.2) is refused; write ``17`` or ``0o17``.
  Quoted and block scalars are always strings. The only tags read are the core schema's
  (``!!str``, ``!!int``, ``!!float``, ``!!bool``, ``!!null``, ``!!seq``, ``!!map``, and ``!``);
  any other tag is refused, so no tag can construct an object or run code.
- **Each key once.** A key written twice in one mapping is refused, naming both lines. Merge
  keys (``<<: *anchor`` or ``<<: [*a, *b]``) supply defaults: a key the mapping writes itself
  overrides the merged one (that is what merges are for), but a key that two merged mappings
  both supply is refused, naming both lines, because which one wins is easy to get wrong.
  An anchor name is defined once per file; an alias names an anchor defined before it and
  outside the node it is in (no recursive structures).
- **Bounded work.** A file is at most ``MAX_BYTES``; a document at most ``MAX_NODES`` values
  with every alias expanded (an alias bomb is refused while it is read, before anything is
  built) and nested at most ``MAX_DEPTH`` deep; one document per file. A refused file costs
  milliseconds and a few MB, never a ``MemoryError``, and no message shows more than 80
  characters of a value.
- **Line numbers are where the mistake is.** They count from 1. A parser notices some mistakes
  only on the line after them (a missing ``:``, ``]``, ``}`` or closing quote); the message then
  names the line the unfinished thing is on, and the line where it was noticed.
"""

from __future__ import annotations

import difflib
import hashlib
import math
import os
import re
import stat
import sys
from collections.abc import Iterable, Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any, NoReturn

import yaml

# The node types of ``compose_yaml``'s tree, re-exported: this is the one module that imports yaml.
from yaml import MappingNode as MappingNode  # noqa: PLC0414 - re-exported
from yaml import Node as Node  # noqa: PLC0414 - re-exported
from yaml import ScalarNode as ScalarNode  # noqa: PLC0414 - re-exported
from yaml import SequenceNode as SequenceNode  # noqa: PLC0414 - re-exported

from handctl.errors import ConfigError, Description, absent, quoted, shown

_MISSING: Any = object()

#: How alike (difflib's ratio, 0..1) a stray key must be to an expected one to be named as
#: its likely misspelling.
DID_YOU_MEAN_CUTOFF = 0.6
#: bytes of a YAML file: 20 times the largest file handctl ships (a compiled recipe)
MAX_BYTES = 256 * 1024
#: values (scalars, lists, mappings) of one document with every alias expanded
MAX_NODES = 50_000
#: nesting of lists and mappings
MAX_DEPTH = 32
#: characters of an integer (far beyond any count or id; keeps int() conversion cheap)
MAX_INT_DIGITS = 100

# libyaml's parser when PyYAML has it (tens of times faster), PyYAML's own otherwise; only its
# events are used, and both give the same events and marks.
_EVENT_LOADER: Any = getattr(yaml, "CSafeLoader", yaml.SafeLoader)


_NOT_REGULAR = (
    (stat.S_ISDIR, "a directory"),
    (stat.S_ISFIFO, "a FIFO (named pipe)"),
    (stat.S_ISCHR, "a character device"),
    (stat.S_ISBLK, "a block device"),
    (stat.S_ISSOCK, "a socket"),
)


def read_input(path: str | Path, expected: str, limit: int) -> bytes:
    """The first ``limit`` + 1 bytes of the input file ``path``, a regular file; anything else
    is a ``ConfigError`` (``expected`` says what it should have been). It is opened without
    blocking and looked at before it is read: a FIFO no one writes held a command in its
    open() for good, deaf to Ctrl-C and SIGTERM (the stop is handled between system calls,
    and an interrupted open is retried), and a device was read as a file."""
    name = str(path)
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | os.O_CLOEXEC)
    except FileNotFoundError:
        raise ConfigError(
            name, "", f"an existing file ({expected})", _Text(absent(Path(path)))
        ) from None
    except OSError as exc:
        raise ConfigError(name, "", expected, str(exc)) from None
    try:
        mode = os.fstat(fd).st_mode
        if not stat.S_ISREG(mode):
            kind = next((what for test, what in _NOT_REGULAR if test(mode)), "no file")
            raise ConfigError(name, "", f"a regular file ({expected})", _Text(kind))
        os.set_blocking(fd, True)
    except OSError as exc:
        os.close(fd)
        raise ConfigError(name, "", expected, str(exc)) from None
    except BaseException:
        os.close(fd)
        raise
    with os.fdopen(fd, "rb") as file:
        try:
            return file.read(limit + 1)
        except OSError as exc:
            raise ConfigError(name, "", expected, str(exc)) from None


#: handctl's kinds of YAML file, each told by top-level keys only it has, and what is done
#: with one: a file of one kind given for another was refused on a key deep inside it
#: ("phases[0].pose.angles: expected this key"), not on what the file is.
FILE_KINDS: tuple[tuple[str, frozenset[str], str], ...] = (
    (
        "recipe template",
        frozenset({"template"}),
        "compile it into a recipe with 'handctl plan TEMPLATE.yaml -o RECIPE.yaml'",
    ),
    ("recipe", frozenset({"recipe", "phases"}), "run it with 'handctl run recipe RECIPE.yaml'"),
    (
        "hand config",
        frozenset({"bus", "fingers"}),
        # not every command takes a hand (analyze does not): said where it goes
        "give it where a command takes the hand ('handctl check HAND.yaml', --hand HAND.yaml)",
    ),
    (
        "analysis scenario",
        frozenset({"dimension", "reading"}),
        "analyse it with 'handctl analyze torque-set SCENARIO.yaml'",
    ),
    (
        "fault list",
        frozenset({"faults"}),
        "give it to the simulated hand: 'handctl run recipe ... --sim-faults' or "
        "'handctl sim --faults'",
    ),
)


def file_kind(data: object) -> tuple[str, str] | None:
    """The kind of handctl file ``data`` (a YAML file's top level) is, and what is done with
    one (``FILE_KINDS``); None if it is none of them."""
    if not isinstance(data, dict):
        return None
    for kind, keys, use in FILE_KINDS:
        if keys <= data.keys():
            return kind, use
    return None


def _a(noun: str) -> str:
    return f"an {noun}" if noun[:1] in "aeiou" else f"a {noun}"


def load_yaml(path: str | Path, kind: str | None = None) -> Doc:
    """Read a YAML file whose top level is a mapping; every failure is a ``ConfigError``.
    ``kind``: the ``FILE_KINDS`` entry it must be, if it is one of them at all."""
    doc = _load_yaml(path)
    found = file_kind(doc.data) if kind is not None else None
    if kind == "recipe template" and found is not None and found[0] == "recipe":
        phases = doc.data.get("phases")
        if isinstance(phases, list) and any(isinstance(p, dict) and "kind" in p for p in phases):
            # phases of a kind each are a template's (a recipe's have none): a template
            # that lost its first line was called a recipe, to run, and the run refused
            # it on 'phases[0].kind'
            raise ConfigError(
                str(path),
                "template",
                "this key (required): the name of the template, its first key",
                _Text(
                    "nothing: the key is missing; its phases have a kind each, as a "
                    "template's do (a recipe's have none)"
                ),
            )
    if found is not None and found[0] != kind:
        raise ConfigError(str(path), "", _a(str(kind)), _Text(f"{_a(found[0])}; {found[1]}"))
    return doc


def _load_yaml(path: str | Path) -> Doc:
    name = str(path)
    data = read_input(path, "a readable UTF-8 file", MAX_BYTES)
    if len(data) > MAX_BYTES:
        raise ConfigError(
            name, "", f"a file of at most {MAX_BYTES} bytes", _Text(f"more than {MAX_BYTES} bytes")
        )
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as exc:
        # said at its line and column, as every other mistake in a YAML file is: the
        # decoder's "position 1014" was a byte offset no editor shows
        before = _LINE_BREAKS.split(data[: exc.start].decode("utf-8"))
        raise ConfigError(
            name,
            "",
            f"UTF-8 text at line {len(before)}, column {len(before[-1]) + 1}",
            _Text(f"byte 0x{data[exc.start]:02X} ({exc.reason})"),
        ) from None
    doc = parse_yaml(text, name)
    doc.sha256 = hashlib.sha256(data).hexdigest()
    return doc


def parse_yaml(text: str, name: str) -> Doc:
    """Parse YAML text (already read) as a document named ``name`` in messages."""
    if len(text) > MAX_BYTES or len(text.encode("utf-8", "surrogatepass")) > MAX_BYTES:
        raise ConfigError(
            name,
            "",
            f"a document of at most {MAX_BYTES} bytes",
            _Text(f"more than {MAX_BYTES} bytes"),
        )
    try:
        root = _compose(yaml.parse(text, Loader=_EVENT_LOADER), name)
    except yaml.MarkedYAMLError as exc:
        where, problem = _parse_error(exc, text)
        raise ConfigError(name, "", "valid YAML" + where, _Text(problem)) from None
    except yaml.reader.ReaderError as exc:  # a character YAML does not allow
        before = _LINE_BREAKS.split(text[: exc.position])
        character = chr(exc.character) if isinstance(exc.character, int) else exc.character
        raise ConfigError(
            name,
            "",
            f"valid YAML at line {len(before)}, column {len(before[-1]) + 1}",
            _Text(f"{exc.reason}: {character!r}"),
        ) from None
    except yaml.YAMLError as exc:
        raise ConfigError(name, "", "valid YAML", _Text(str(exc))) from None
    data = None if root is None else _Builder(name).build(root, "")
    if not isinstance(data, dict):
        raise ConfigError(name, "", "a mapping at the top level", _type_name(data))
    return Doc(data, name, "")


def compose_yaml(text: str) -> yaml.Node:
    """The node tree of ``text`` (positions, no values constructed), for a file that
    ``parse_yaml`` has already read within its bounds: where each value sits, so that a number
    can be edited in place without rewriting the file's comments and layout. ValueError if it
    cannot be composed."""
    try:
        node: yaml.Node | None = yaml.compose(text, Loader=yaml.SafeLoader)
    except yaml.YAMLError as exc:
        raise ValueError(str(exc)) from None
    if node is None:
        raise ValueError("an empty document")
    return node


def dump_yaml(data: Any) -> str:
    """YAML text that ``parse_yaml`` reads back as ``data`` (and YAML 1.1 readers too): a
    string that either schema would read as something else is quoted."""
    return yaml.dump(data, Dumper=_Dumper, sort_keys=False, width=100, allow_unicode=True)


#: A found value that is already a description: shown as it is, not quoted.
_Text = Description


def description(text: str) -> str:
    """What was found, told rather than quoted (``found an empty section``), for a
    ``ConfigError`` raised outside this module."""
    return _Text(text)


# -- parse errors ----------------------------------------------------------------------------------
#: What PyYAML and libyaml count as line breaks (str.splitlines counts more, e.g. form feeds).
_LINE_BREAKS = re.compile("\r\n|[\r\n\x85\u2028\u2029]")


def _parse_error(exc: yaml.MarkedYAMLError, text: str) -> tuple[str, str]:
    """Where the mistake is (1-based line and column) and the parser's complaint.

    PyYAML and libyaml notice some mistakes only on a later line than the one they are on, and
    mark where they noticed them. A key (which YAML keeps on one line) without its ':' and a
    quoted scalar without its closing quote are on the line where they start, which the parser
    gives as the context. A flow collection ('[...]', '{...}') that is not closed is noticed at
    the next line's first token: the closer is missing at the end of the last line before it.
    """
    problem = exc.problem or exc.context or "not YAML"
    # the parser's "found character ..." follows our own "found": said once
    problem = problem.removeprefix("found ")
    mark = exc.problem_mark or exc.context_mark
    if mark is None:
        return "", problem
    where = f"line {mark.line + 1}, column {mark.column + 1}"
    lines = _LINE_BREAKS.split(text)
    start = _key_without_colon(lines, mark.line, mark.column, problem)
    if start is not None:
        return (f" at line {start + 1}", f"{problem}: a key without its ':'? (noticed at {where})")
    context = exc.context_mark
    if context is None or not exc.context or context.line >= mark.line:
        if mark.line >= len(lines):
            # The end of a text without a final line break, which the parser counts as one
            # more line: the mistake is at the end of the last line there is.
            return f" at the end of line {len(lines)}", f"{problem} (at the end of the text)"
        return f" at {where}", problem
    started = f"{exc.context} that starts at line {context.line + 1}, column {context.column + 1}"
    if "simple key" in exc.context or "quoted scalar" in exc.context:
        return (
            f" at line {context.line + 1}, column {context.column + 1}",
            f"{problem} (noticed at {where}, {started})",
        )
    before = lines[mark.line][: mark.column] if mark.line < len(lines) else ""
    if "flow" in exc.context and not any(c in before for c in ":,[]{}"):
        line = mark.line - 1
        while line > context.line and _blank(lines[line]):
            line -= 1
        return f" at the end of line {line + 1}", f"{problem} (noticed at {where}, {started})"
    return f" at {where}", f"{problem} ({started})"


def _key_without_colon(lines: list[str], line: int, column: int, problem: str) -> int | None:
    """The earlier line of a key written without its ':', when that is what the parser saw.

    Such a line is a plain scalar, and the parser complains only further on: at the ':' of
    the next key when the scalar ran on into it (``name hand`` then ``bus:`` read as "name hand
    bus"), or at the next key when a comment ended the scalar. Either way the text that ran on
    has no ':' of its own, which tells it from a mistake on the line the parser names.
    """
    here = lines[line] if line < len(lines) else ""
    if "mapping values are not allowed" in problem:
        if not re.fullmatch(r"\s*[^\s:#,\[\]{}\-][^:#]*", here[:column]):
            return None
        start = None
        for i in range(line - 1, -1, -1):
            text = _uncommented(lines[i])
            if not text:
                if lines[i].strip():  # a comment line ends a plain scalar
                    break
                continue
            if ":" in text or text[0] in "[]{},":
                break
            start = i
            if text.startswith("- "):
                break
        return start
    if "expected key" in problem or "expected <block end>" in problem:
        if not re.match(r"[^\s:#,\[\]{}\-][^:#]*:(\s|$)", here[column:]):
            return None
        for i in range(line - 1, -1, -1):
            text = _uncommented(lines[i])
            if text:
                return i if ":" not in text and text[0] not in "[]{}," else None
    return None


def _uncommented(line: str) -> str:
    """The line without its comment, stripped (a '#' after a space or at the start)."""
    stripped = line.strip()
    if stripped.startswith("#"):
        return ""
    cut = stripped.find(" #")
    return (stripped if cut < 0 else stripped[:cut]).strip()


def _blank(line: str) -> bool:
    stripped = line.strip()
    return not stripped or stripped.startswith("#")


# -- composing: events to nodes, with the bounds ---------------------------------------------------
class _Node:
    """One value of the document as the parser gave it, with where it starts (1-based)."""

    __slots__ = ("column", "done", "items", "kind", "line", "plain", "size", "tag", "text")

    def __init__(
        self, kind: str, tag: str | None, plain: bool, line: int, column: int, text: str
    ) -> None:
        self.kind = kind  # "scalar", "seq" or "map"
        self.tag = tag  # an explicit tag, or None
        self.plain = plain  # an untagged plain scalar: its type comes from the core schema
        self.line = line
        self.column = column
        self.text = text  # a scalar's text
        self.items: list[_Node] = []  # a list's items; a mapping's key, value, key, value...
        self.size = 1  # values in the node with every alias expanded
        self.done = kind == "scalar"  # read to its end (an alias inside it would recurse)


_STARTS = {
    yaml.ScalarEvent: "scalar",
    yaml.SequenceStartEvent: "seq",
    yaml.MappingStartEvent: "map",
}
_ENDS = (yaml.SequenceEndEvent, yaml.MappingEndEvent)


def _compose(events: Iterator[Any], name: str) -> _Node | None:
    """Build the node graph from the parser's events, refusing as soon as a bound is passed.

    An alias is the anchored node itself (no copy), so a bomb costs nothing here; its cost is
    counted instead: ``expanded`` grows by the whole size of each aliased node.
    """

    def fail(expected: str, found: str) -> NoReturn:
        raise ConfigError(name, "", expected, _Text(found))

    top = _Node("seq", None, False, 0, 0, "")  # holds the document's root
    stack = [top]
    anchors: dict[str, _Node] = {}
    documents = 0
    expanded = 0
    for event in events:
        kind = _STARTS.get(type(event))
        if kind is not None:
            mark = event.start_mark
            node = _Node(
                kind,
                event.tag,
                kind == "scalar" and event.tag is None and not event.style,
                mark.line + 1,
                mark.column + 1,
                event.value if kind == "scalar" else "",
            )
            anchor = event.anchor
            if anchor is not None:
                if anchor in anchors:
                    fail(
                        "each anchor name defined once",
                        f"&{anchor} at line {node.line}, "
                        f"already defined at line {anchors[anchor].line}",
                    )
                anchors[anchor] = node
            stack[-1].items.append(node)
            expanded += 1
            if kind != "scalar":
                stack.append(node)
                if len(stack) > MAX_DEPTH + 1:
                    fail(
                        f"lists and mappings nested at most {MAX_DEPTH} deep",
                        f"deeper at line {node.line}",
                    )
        elif isinstance(event, _ENDS):
            node = stack.pop()
            node.size = 1 + sum(item.size for item in node.items)
            node.done = True
        elif isinstance(event, yaml.AliasEvent):
            line = _line(event)
            target = anchors.get(event.anchor or "")
            if target is None:
                fail(
                    "an alias of an anchor defined before it",
                    f"*{event.anchor} at line {line} with no &{event.anchor} before it",
                )
            if not target.done:
                fail(
                    "an alias outside the node its anchor names (no recursive structures)",
                    f"*{event.anchor} at line {line} inside &{event.anchor} (line {target.line})",
                )
            stack[-1].items.append(target)
            expanded += target.size
        elif isinstance(event, yaml.DocumentStartEvent):
            documents += 1
            if documents > 1:
                fail("one YAML document per file", f"a second document at line {_line(event)}")
        if expanded > MAX_NODES:
            fail(
                f"at most {MAX_NODES} values with every alias expanded (a bound against alias "
                f"bombs)",
                f"more by line {_line(event)}",
            )
    return top.items[0] if top.items else None


def _line(event: yaml.Event) -> int:
    return event.start_mark.line + 1 if event.start_mark is not None else 0


# -- building: nodes to Python values ------------------------------------------------------------
_CORE = "tag:yaml.org,2002:"
_NULLS = frozenset({"", "~", "null", "Null", "NULL"})
_BOOLS = {"true": True, "false": False}
_DECIMAL = re.compile(r"[-+]?[0-9]+")
_LEADING_ZERO = re.compile(r"[-+]?0[0-9]+")
_OCTAL = re.compile(r"0o[0-7]+")
_HEX = re.compile(r"0x[0-9a-fA-F]+")
_FLOAT = re.compile(r"[-+]?(\.[0-9]+|[0-9]+(\.[0-9]*)?)([eE][-+]?[0-9]+)?")
_INF = re.compile(r"[-+]?\.(inf|Inf|INF)")
_NAN = re.compile(r"\.(nan|NaN|NAN)")


def core_type(text: str) -> str:
    """What a plain scalar is under handctl's rule: ``null``, ``bool``, ``int``, ``float`` or
    ``str`` (``int`` also for the leading-zero integers that are then refused)."""
    if text in _NULLS:
        return "null"
    if text in _BOOLS:
        return "bool"
    if _DECIMAL.fullmatch(text) or _OCTAL.fullmatch(text) or _HEX.fullmatch(text):
        return "int"
    if _FLOAT.fullmatch(text) or _INF.fullmatch(text) or _NAN.fullmatch(text):
        return "float"
    return "str"


class _Builder:
    """Python values from the node graph: each node built once (an alias shares the value, as
    in any YAML loader), with the key path of where it is for messages."""

    def __init__(self, name: str) -> None:
        self.name = name
        self.built: dict[int, Any] = {}
        self.entries_of: dict[int, dict[Any, tuple[str, Any]]] = {}

    def fail(self, path: str, expected: str, found: str) -> NoReturn:
        raise ConfigError(self.name, path, expected, _Text(found))

    def build(self, node: _Node, path: str) -> Any:
        key = id(node)
        if key in self.built:
            return self.built[key]
        value: Any
        if node.kind == "scalar":
            value = self.scalar(node, path)
        elif node.kind == "seq":
            self.check_tag(node, path, ("seq",))
            value = [self.build(item, f"{path}[{i}]") for i, item in enumerate(node.items)]
        else:
            self.check_tag(node, path, ("map",))
            value = {k: v for k, (_, v) in self.entries(node, path).items()}
        self.built[key] = value
        return value

    def check_tag(self, node: _Node, path: str, allowed: tuple[str, ...]) -> str | None:
        """The core-schema type an explicit tag asks for (None when there is no tag)."""
        if node.tag is None or node.tag == "!":
            return None
        if node.tag.startswith(_CORE) and node.tag[len(_CORE) :] in allowed:
            return node.tag[len(_CORE) :]
        shown = "!!" + node.tag[len(_CORE) :] if node.tag.startswith(_CORE) else node.tag
        self.fail(
            path,
            "a tag of YAML's core schema (here "
            + ", ".join(f"!!{t}" for t in allowed)
            + ", or none)",
            f"{shown:.60} at line {node.line}, column {node.column}",
        )

    def scalar(self, node: _Node, path: str) -> Any:
        text = node.text
        if node.plain:
            kind = core_type(text)
        else:
            kind = self.check_tag(node, path, ("str", "int", "float", "bool", "null")) or "str"
        if kind == "str":
            return text
        where = f"{text!r:.60} at line {node.line}, column {node.column}"
        if kind == "null":
            if text not in _NULLS:
                self.fail(path, "null (null, ~ or nothing) after !!null", where)
            return None
        if kind == "bool":
            if text not in _BOOLS:
                self.fail(path, "true or false after !!bool", where)
            return _BOOLS[text]
        if _LEADING_ZERO.fullmatch(text):
            self.fail(
                path,
                "a number without a leading zero (YAML 1.1 reads 017 as 15, YAML "
                "1.2 as 17): write 17 or 0o17, or quote it if it is text",
                where,
            )
        if _DECIMAL.fullmatch(text) or _OCTAL.fullmatch(text) or _HEX.fullmatch(text):
            if len(text) > MAX_INT_DIGITS:
                self.fail(
                    path,
                    f"an integer of at most {MAX_INT_DIGITS} digits",
                    f"{len(text)} characters at line {node.line}, column {node.column}",
                )
            base = 8 if text.startswith("0o") else (16 if text.startswith("0x") else 10)
            number = int(text[2:] if base != 10 else text, base)
            return float(number) if kind == "float" else number
        if kind == "int":
            self.fail(path, "an integer (decimal, 0o octal or 0x hexadecimal) after !!int", where)
        if _INF.fullmatch(text):
            return -math.inf if text.startswith("-") else math.inf
        if _NAN.fullmatch(text):
            return math.nan
        if not _FLOAT.fullmatch(text):
            self.fail(path, "a number (YAML 1.2 core schema) after !!float", where)
        return float(text)

    def entries(self, node: _Node, path: str) -> dict[Any, tuple[str, Any]]:
        """A mapping's keys with (where the key is, value), merges resolved and duplicates
        refused; kept per node so that a mapping merged in many places is resolved once."""
        cached = self.entries_of.get(id(node))
        if cached is not None:
            return cached
        own: dict[Any, tuple[str, Any]] = {}
        merged: dict[Any, tuple[str, Any]] = {}
        merge_at = ""
        for key_node, value_node in zip(node.items[0::2], node.items[1::2], strict=True):
            if key_node.kind != "scalar":
                self.fail(
                    path or "(top level)",
                    "keys that are plain values (text)",
                    f"a {'list' if key_node.kind == 'seq' else 'mapping'} as a key at "
                    f"line {key_node.line}, column {key_node.column}",
                )
            if key_node.plain and key_node.text == "<<":
                here = f"line {key_node.line}, column {key_node.column}"
                if merge_at:
                    self.fail(
                        _join(path, "<<"),
                        "each key once in a mapping",
                        f"<< at {merge_at} and again at {here}",
                    )
                merge_at = here
                self.merge(value_node, path, merged)
                continue
            key = self.build(key_node, path)
            child = _join(path, key)
            seen = own.get(key)
            here = f"line {key_node.line}, column {key_node.column}"
            if seen is not None:
                self.fail(
                    child,
                    "each key once in a mapping",
                    f"{key!r:.40} at {seen[0]} and again at {here}",
                )
            own[key] = (here, self.build(value_node, child))
        entries = {**merged, **own}
        self.entries_of[id(node)] = entries
        return entries

    def merge(self, value: _Node, path: str, merged: dict[Any, tuple[str, Any]]) -> None:
        sources = value.items if value.kind == "seq" else [value]
        for i, source in enumerate(sources):
            if source.kind != "map":
                self.fail(
                    _join(path, "<<"),
                    "a mapping or a list of mappings to merge",
                    f"a {'list' if source.kind == 'seq' else 'value'} at line "
                    f"{source.line}, column {source.column}",
                )
            if any(other is source for other in sources[:i]):
                # an alias is the anchored node itself, so its every key was said as
                # supplied "from line 5, column 8 and from line 5, column 8"
                self.fail(
                    _join(path, "<<"),
                    "each mapping merged once",
                    f"the mapping at line {source.line}, column {source.column}, twice",
                )
            for key, (line, item) in self.entries(source, path).items():
                if key in merged:
                    self.fail(
                        _join(path, key),
                        "a key that one merged mapping supplies",
                        f"{key!r:.40} from {merged[key][0]} and from {line}",
                    )
                merged[key] = (line, item)


def _join(path: str, key: Any) -> str:
    return f"{path}.{key}" if path else str(key)


class _Dumper(yaml.SafeDumper):
    """PyYAML's safe dumper, quoting also the strings that handctl's rule reads as values."""

    def resolve(self, kind: Any, value: Any, implicit: Any) -> Any:
        tag = super().resolve(kind, value, implicit)  # type: ignore[no-untyped-call]
        if kind is yaml.ScalarNode and implicit[0] and tag == _CORE + "str":
            core = core_type(value)
            if core != "str":
                return _CORE + core
        return tag


def _represent_str(dumper: yaml.SafeDumper, value: str) -> yaml.ScalarNode:
    """Double quotes (which escape) for a string holding a character that a YAML 1.1 reader
    takes for a line break: in a plain or single-quoted scalar it would be folded to a space."""
    style = '"' if any(c in value for c in "\x85\u2028\u2029") else None
    return dumper.represent_scalar("tag:yaml.org,2002:str", value, style=style)


_Dumper.add_representer(str, _represent_str)


def _type_name(value: object) -> str:
    """What a value of the wrong type is, as a description (``list``, ``str 'x'``): shown as
    it is in a message, not quoted as if it were the value ("found 'list'"). The value is
    ``shown``, cut to ``SHOWN_CHARS``: its whole repr, in a description cut only at 1000
    characters, made a message of 200000 sevens 1113 characters long."""
    if value is None:
        return _Text("nothing (null)")
    text = f"{type(value).__name__} {shown(value)}" if _is_scalar(value) else type(value).__name__
    return _Text(text)


def _is_scalar(value: object) -> bool:
    return isinstance(value, (bool, int, float, str))


#: characters of a name printed as it is (a hand's, a recipe's, a phase's): it heads the
#: summary, the status line and the plots' titles
MAX_LABEL = 64


class Doc:
    """One mapping of a YAML file, with the file name and key path it was found at.

    Reading a key marks it as used; ``done()`` then refuses any key that was not read, which is
    how unknown (misspelt) keys are caught without a separate list of allowed names.
    """

    def __init__(self, data: Mapping[Any, Any], file: str, path: str) -> None:
        for key in data:
            if not isinstance(key, str):
                raise ConfigError(file, path or "(top level)", "string keys", key)
        self.data = data
        self.file = file
        self.path = path
        #: the SHA-256 (hex) of the bytes this document was parsed from, for a file's top
        #: level ("" otherwise): what a record of the input names, since the file itself may
        #: have changed by the time the record is written
        self.sha256 = ""
        self._used: set[str] = set()
        self._allowed: frozenset[str] | None = None

    # -- locating -------------------------------------------------------------------------
    def key_path(self, key: str | int) -> str:
        """The dotted/indexed path of ``key`` below this mapping, as shown in messages."""
        if isinstance(key, int):
            return f"{self.path}[{key}]"
        return f"{self.path}.{key}" if self.path else key

    def fail(self, key: str | int, expected: str, found: object) -> NoReturn:
        """Raise the ``ConfigError`` for ``key`` of this mapping."""
        raise ConfigError(self.file, self.key_path(key), expected, found)

    def has(self, key: str) -> bool:
        return key in self.data

    def expect(self, keys: Iterable[str]) -> None:
        """Declare every key this mapping may hold (e.g. a hand's joint names), for mappings
        whose keys are data rather than a fixed set read one by one: an unknown key is then
        refused at once with the nearest allowed name, and a missing one names the unknown key
        beside it, rather than the first of many similar names that were simply not read yet."""
        self._allowed = frozenset(keys)
        for key in self.data:
            if key not in self._allowed:
                self.fail(
                    key,
                    "no such key here (unknown key"
                    + _did_you_mean(key, sorted(self._allowed - self.data.keys()))
                    + ")",
                    self.data[key],
                )

    def _get(self, key: str, default: Any) -> Any:
        self._used.add(key)
        if key in self.data:
            return self.data[key]
        if default is _MISSING:
            self.fail(
                key,
                "this key (required)",
                _Text("nothing: the key is missing" + self._stray_near(key)),
            )
        return default

    def _stray_near(self, key: str) -> str:
        """The key that looks like a misspelling of the missing ``key``, if one stands out.

        With declared keys (``expect``) the candidates are the unknown ones; otherwise those
        no reader has asked for yet, and only a single best match is named: of several equally
        close ones (joint names that differ in one digit) most are simply still to be read."""
        if self._allowed is not None:
            strays = [k for k in self.data if k not in self._allowed]
        else:
            strays = [k for k in self.data if k not in self._used]
        best = _closest(key, strays)
        return f"; {quoted(best)} is here instead (a misspelling of it?)" if best else ""

    # -- scalars --------------------------------------------------------------------------
    def number(
        self,
        key: str,
        *,
        default: Any = _MISSING,
        min: float | None = None,
        max: float | None = None,
        min_exclusive: bool = False,
        unit: str = "",
    ) -> float:
        """A finite real number; bounds are inclusive unless ``min_exclusive``.

        A whole number written for it (``20`` for ``20.0``) is kept in the data as the real
        number it is read as, so that what is hashed of a file (a hand config's
        ``config_hash``) is the same however the number was spelled."""
        value = self._get(key, default)
        number = self.check_number(
            key, value, min=min, max=max, min_exclusive=min_exclusive, unit=unit
        )
        if type(value) is int and isinstance(self.data, dict) and key in self.data:
            self.data[key] = number
        return number

    def check_number(
        self,
        key: str | int,
        value: Any,
        *,
        min: float | None = None,
        max: float | None = None,
        min_exclusive: bool = False,
        unit: str = "",
    ) -> float:
        """Validate an already-fetched value as a bounded finite number."""
        suffix = f" {unit}" if unit else ""
        what = "a number" + _bounds_text(min, max, min_exclusive) + suffix
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            self.fail(key, what, _type_name(value))
        number = float(value)
        if not math.isfinite(number):
            self.fail(key, "a finite number" + suffix, value)
        if number != 0.0 and abs(number) < sys.float_info.min:
            # a subnormal float (5e-324) is above zero and nothing once converted or divided
            # by: a rate of 5e-324 deg/s passed "> 0" and was 0 rad/s, and the run stopped
            # on a division by zero in its manipulation
            self.fail(
                key,
                f"{what}, and 0 or at least {sys.float_info.min:g} in size (a normal float)",
                value,
            )
        below = min is not None and (number <= min if min_exclusive else number < min)
        above = max is not None and number > max
        if below or above:
            self.fail(key, what, value)
        return number

    def integer(
        self, key: str, *, default: Any = _MISSING, min: int | None = None, max: int | None = None
    ) -> int:
        """An integer (YAML hex like ``0x101`` is fine); floats and booleans are refused."""
        value = self._get(key, default)
        what = "an integer" + _bounds_text(min, max, False)
        if isinstance(value, bool) or not isinstance(value, int):
            self.fail(key, what, _type_name(value))
        if (min is not None and value < min) or (max is not None and value > max):
            self.fail(key, what, value)
        return value

    def string(
        self, key: str, *, default: Any = _MISSING, choices: Sequence[str] | None = None
    ) -> str:
        value = self._get(key, default)
        if choices is not None:
            if value not in choices:
                self.fail(key, "one of " + ", ".join(repr(c) for c in choices), value)
            return str(value)
        if not isinstance(value, str) or not value:
            self.fail(key, "a non-empty string", _type_name(value))
        return value

    def label(self, key: str, *, default: Any = _MISSING, as_recorded: bool = False) -> str:
        """A name that is printed as it is (a hand's, a recipe's, a phase's): ``string`` of
        printable characters. An escape sequence in a hand's name retitled and cleared the
        terminal of whoever ran it or replayed its log; a newline in a phase's name forged a
        line of the summary. (Names the rest of handctl looks up, of joints and objects, have
        stricter rules of their own.)"""
        value = self.string(key, default=default)
        if not value.isprintable():
            self.fail(key, "a name of printable characters (no newline, tab or escape)", value)
        if not as_recorded and value != value.strip():
            # a hand named " " showed as nothing in check, the summary and the plot's title;
            # (``as_recorded``: a recording's hand or recipe is read as it ran)
            self.fail(key, "a name not beginning or ending with a space", value)
        if len(value) > MAX_LABEL:
            # a 300-character recipe name ran off both edges of its plot's title
            self.fail(key, f"a name of at most {MAX_LABEL} characters", value)
        return value

    def text(self, key: str, *, default: Any = _MISSING) -> str:
        """Free text such as a description: any string, empty too, but a string (a number or a
        list where text belongs is a mistake, not something to print)."""
        value = self._get(key, default)
        if not isinstance(value, str):
            self.fail(key, "text (a string)", _type_name(value))
        return value

    def boolean(self, key: str, *, default: Any = _MISSING) -> bool:
        value = self._get(key, default)
        if not isinstance(value, bool):
            self.fail(key, "true or false", _type_name(value))
        return value

    def numbers(
        self,
        key: str,
        *,
        length: int | None = None,
        default: Any = _MISSING,
        min: float | None = None,
        max: float | None = None,
        unit: str = "",
    ) -> tuple[float, ...]:
        """A list of finite numbers, optionally of a fixed length."""
        value = self._get(key, default)
        what = f"a list of {length} numbers" if length is not None else "a list of numbers"
        if not isinstance(value, list):
            self.fail(key, what, value if _is_scalar(value) else _type_name(value))
        if length is not None and len(value) != length:
            # the count is what is wrong, and the start of a long list does not show it
            self.fail(key, what, _Text(f"a list of {len(value)}: {shown(value)}"))
        sub = Doc({}, self.file, self.key_path(key))
        numbers = tuple(
            sub.check_number(i, v, min=min, max=max, unit=unit) for i, v in enumerate(value)
        )
        value[:] = numbers  # as ``number`` keeps them: read as reals, whatever the spelling
        return numbers

    # -- structure ------------------------------------------------------------------------
    def mapping(self, key: str, *, default: Any = _MISSING) -> Doc:
        """A nested mapping; an absent optional one reads as empty."""
        value = self._get(key, {} if default is not _MISSING else _MISSING)
        if not isinstance(value, dict):
            self.fail(key, "a mapping", _type_name(value))
        return Doc(value, self.file, self.key_path(key))

    def mappings(
        self, key: str, *, min_len: int = 0, max_len: int | None = None, default: Any = _MISSING
    ) -> list[Doc]:
        """A list of mappings, e.g. ``fingers`` or ``phases``."""
        value = self._get(key, default)
        bound = (
            f"at least {min_len}"
            if max_len is None
            else (f"{min_len}" if min_len == max_len else f"{min_len} to {max_len}")
        )
        what = f"a list of {bound} mappings"
        if not isinstance(value, list):
            self.fail(key, what, _type_name(value))
        if len(value) < min_len or (max_len is not None and len(value) > max_len):
            self.fail(key, what, _Text(f"{len(value)} entries"))
        sub = Doc({}, self.file, self.key_path(key))
        docs = []
        for i, item in enumerate(value):
            if not isinstance(item, dict):
                sub.fail(i, "a mapping", _type_name(item))
            docs.append(Doc(item, self.file, sub.key_path(i)))
        return docs

    def raw(self, key: str, default: Any = _MISSING) -> Any:
        """The untyped value, for callers that dispatch on its shape themselves."""
        return self._get(key, default)

    def keys(self) -> Iterator[str]:
        return iter(self.data)

    def done(self) -> None:
        """Refuse keys that no reader asked for: they are typos or belong elsewhere. The keys
        that were asked for and are absent (optional ones left at their default) are the
        likely intended spellings."""
        absent = sorted(k for k in self._used | (self._allowed or set()) if k not in self.data)
        for key in self.data:
            if key not in self._used:
                self.fail(
                    key,
                    "no such key here (unknown key" + _did_you_mean(key, absent) + ")",
                    self.data[key],
                )


def _closest(key: str, candidates: Sequence[str]) -> str | None:
    """The one candidate nearest to ``key`` (difflib's ratio >= 0.6), or None if there is
    none or several tie for nearest."""
    scored = sorted(
        ((difflib.SequenceMatcher(None, key, c).ratio(), c) for c in candidates), reverse=True
    )
    if not scored or scored[0][0] < DID_YOU_MEAN_CUTOFF:
        return None
    if len(scored) > 1 and scored[1][0] == scored[0][0]:
        return None
    return scored[0][1]


def _did_you_mean(key: str, candidates: Sequence[str]) -> str:
    best = _closest(key, candidates)
    return f"; did you mean {quoted(best)}?" if best else ""


def _bounds_text(min: float | None, max: float | None, min_exclusive: bool) -> str:
    if min is not None and max is not None:
        left = f"> {_bound(min)}" if min_exclusive else f">= {_bound(min)}"
        return f" {left} and <= {_bound(max)}"
    if min is not None:
        return f" > {_bound(min)}" if min_exclusive else f" >= {_bound(min)}"
    if max is not None:
        return f" <= {_bound(max)}"
    return ""


def _bound(value: float) -> str:
    """A bound as it is read: a whole number in all its digits, any other as before (six
    significant digits). Six significant digits of a whole number said "<= 4.29497e+09,
    found 4294967296", a value past the bound that read as one within it."""
    whole = isinstance(value, int) or (math.isfinite(value) and value.is_integer())
    if whole and abs(value) < 1e16:
        return str(int(value))
    return f"{value:g}"
