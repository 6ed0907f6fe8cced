"""Strict reading of YAML documents with messages that name file, key path, expected and found.

Every loader of handctl (hand config, recipes, analysis scenarios) reads through ``Doc`` so the
error discipline is the same everywhere: a key that is not known is an error (a typo must never
silently fall back to a default), a value of the wrong type or out of range is an error, and the
message says exactly where. YAML is always loaded with ``yaml.safe_load``.
"""

from __future__ import annotations

import math
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any, NoReturn

import yaml

from handctl.errors import ConfigError

_MISSING: Any = object()


def load_yaml(path: str | Path) -> Doc:
    """Read a YAML file whose top level is a mapping; every failure is a ``ConfigError``."""
    name = str(path)
    try:
        text = Path(path).read_text(encoding="utf-8")
    except FileNotFoundError:
        raise ConfigError(name, "", "an existing file", "no such file") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(name, "", "a readable UTF-8 file", str(exc)) from None
    return parse_yaml(text, name)


def parse_yaml(text: str, name: str) -> Doc:
    """Parse YAML text (already read) as a document named ``name`` in messages."""
    try:
        data = yaml.safe_load(text)
    except yaml.MarkedYAMLError as exc:
        mark = exc.problem_mark
        where = f"line {mark.line + 1}, column {mark.column + 1}" if mark else "unknown place"
        raise ConfigError(name, "", "valid YAML", f"{exc.problem} at {where}") from None
    except yaml.YAMLError as exc:
        raise ConfigError(name, "", "valid YAML", str(exc)) from None
    except RecursionError:
        raise ConfigError(name, "", "valid YAML", "nesting too deep") from None
    if not isinstance(data, dict):
        raise ConfigError(name, "", "a mapping at the top level", _type_name(data))
    return Doc(data, name, "")


def _type_name(value: object) -> str:
    if value is None:
        return "nothing (null)"
    return f"{type(value).__name__} {value!r}" if _is_scalar(value) else type(value).__name__


def _is_scalar(value: object) -> bool:
    return isinstance(value, (bool, int, float, str))


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
        self._used: set[str] = set()

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

    def _get(self, key: str, default: Any) -> Any:
        self._used.add(key)
        if key in self.data:
            return self.data[key]
        if default is _MISSING:
            self.fail(key, "this key (required)", "nothing: the key is missing")
        return default

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
        """A finite real number; bounds are inclusive unless ``min_exclusive``."""
        value = self._get(key, default)
        return self.check_number(key, value, min=min, max=max, min_exclusive=min_exclusive,
                                 unit=unit)

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
        below = min is not None and (number <= min if min_exclusive else number < min)
        above = max is not None and number > max
        if below or above:
            self.fail(key, what, value)
        return number

    def integer(self, key: str, *, default: Any = _MISSING, min: int | None = None,
                max: int | None = None) -> int:
        """An integer (YAML hex like ``0x101`` is fine); floats and booleans are refused."""
        value = self._get(key, default)
        what = "an integer" + _bounds_text(min, max, False)
        if isinstance(value, bool) or not isinstance(value, int):
            self.fail(key, what, _type_name(value))
        if (min is not None and value < min) or (max is not None and value > max):
            self.fail(key, what, value)
        return value

    def string(self, key: str, *, default: Any = _MISSING,
               choices: Sequence[str] | None = None) -> str:
        value = self._get(key, default)
        if choices is not None:
            if value not in choices:
                self.fail(key, "one of " + ", ".join(repr(c) for c in choices), value)
            return str(value)
        if not isinstance(value, str) or not value:
            self.fail(key, "a non-empty string", _type_name(value))
        return value

    def boolean(self, key: str, *, default: Any = _MISSING) -> bool:
        value = self._get(key, default)
        if not isinstance(value, bool):
            self.fail(key, "true or false", _type_name(value))
        return value

    def numbers(self, key: str, *, length: int | None = None, default: Any = _MISSING,
                min: float | None = None, max: float | None = None,
                unit: str = "") -> tuple[float, ...]:
        """A list of finite numbers, optionally of a fixed length."""
        value = self._get(key, default)
        what = f"a list of {length} numbers" if length is not None else "a list of numbers"
        if not isinstance(value, list) or (length is not None and len(value) != length):
            self.fail(key, what, value if _is_scalar(value) else _type_name(value))
        sub = Doc({}, self.file, self.key_path(key))
        return tuple(sub.check_number(i, v, min=min, max=max, unit=unit)
                     for i, v in enumerate(value))

    # -- structure ------------------------------------------------------------------------
    def mapping(self, key: str, *, default: Any = _MISSING) -> Doc:
        """A nested mapping; an absent optional one reads as empty."""
        value = self._get(key, {} if default is not _MISSING else _MISSING)
        if not isinstance(value, dict):
            self.fail(key, "a mapping", _type_name(value))
        return Doc(value, self.file, self.key_path(key))

    def mappings(self, key: str, *, min_len: int = 0, max_len: int | None = None,
                 default: Any = _MISSING) -> list[Doc]:
        """A list of mappings, e.g. ``fingers`` or ``phases``."""
        value = self._get(key, default)
        bound = f"at least {min_len}" if max_len is None else (
            f"{min_len}" if min_len == max_len else f"{min_len} to {max_len}")
        what = f"a list of {bound} mappings"
        if not isinstance(value, list):
            self.fail(key, what, _type_name(value))
        if len(value) < min_len or (max_len is not None and len(value) > max_len):
            self.fail(key, what, f"{len(value)} entries")
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
        """Refuse keys that no reader asked for: they are typos or belong elsewhere."""
        for key in self.data:
            if key not in self._used:
                self.fail(key, "no such key here (unknown key)", self.data[key])


def _bounds_text(min: float | None, max: float | None, min_exclusive: bool) -> str:
    if min is not None and max is not None:
        left = f"> {min:g}" if min_exclusive else f">= {min:g}"
        return f" {left} and <= {max:g}"
    if min is not None:
        return f" > {min:g}" if min_exclusive else f" >= {min:g}"
    if max is not None:
        return f" <= {max:g}"
    return ""
