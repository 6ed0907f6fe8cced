"""The one exception tree of handctl.

Callers catch ``HandctlError`` to handle anything handctl raises on purpose; the subclasses also
derive from the standard exception a Python user would reach for first (``ValueError`` for bad
input, ``TimeoutError`` for deadlines), in the manner of python-can's exception tree, so generic
code keeps working.
"""

from __future__ import annotations

import os
import reprlib
from pathlib import Path, PurePath


class HandctlError(Exception):
    """Base of every error handctl raises deliberately."""

    def __reduce__(self) -> tuple[object, ...]:
        """Pickled as its message and its attributes, whatever its ``__init__`` takes: an
        error raised in a plan's or a bench's worker process crosses back to the parent so.
        By default it is rebuilt by calling the class with its message, which a
        ``ConfigError`` (four arguments) refuses, and the pool said only that a process had
        "terminated abruptly"."""
        return (_rebuilt, (type(self), self.args, dict(self.__dict__)))


def _rebuilt(
    cls: type[HandctlError], args: tuple[object, ...], attributes: dict[str, object]
) -> HandctlError:
    """A handctl error as it was pickled (``HandctlError.__reduce__``), ``__init__`` skipped."""
    error = cls.__new__(cls, *args)
    error.args = args
    error.__dict__.update(attributes)
    return error


class ConfigError(HandctlError, ValueError):
    """Bad input in a file: names the file, the key path, what was expected and what was found.

    The four parts are kept as attributes so that a CLI, a test or a GUI can show them as it
    likes; ``str()`` gives the one-line message a user reads.
    """

    def __init__(self, file: str, key: str, expected: str, found: object) -> None:
        self.file = file
        self.key = key
        self.expected = expected
        self.found = found
        # the file and the key are the user's as much as the value: a key of a YAML file
        # ("bad\x1b[2Jkey", written with a double-quoted escape) or a file name holding an
        # escape sequence cleared the terminal that showed the message
        where = f"{escaped(file)}: {escaped(key)}" if key else escaped(file)
        super().__init__(f"{where}: expected {expected}, found {shown(found)}")


class ProtocolError(HandctlError, ValueError):
    """A value that cannot be put on the wire (out of the DBC range, wrong shape, unknown frame)."""


class BusError(HandctlError):
    """A bus that cannot be opened or used as asked."""


class HandctlTimeoutError(HandctlError, TimeoutError):
    """A deadline passed: a node did not answer, a tick came too late."""


#: characters of an offending value a message shows
SHOWN_CHARS = 80


def absent(path: Path) -> str:
    """Why ``path``, which is no file, is none: "no such file", or a symbolic link that leads
    nowhere (a loop of links, or a link to a name that does not exist), which the file system
    reports as no file either and was said as "no such file" beside a name the user can see.
    A relative path says the directory it was looked for in: a command run from elsewhere
    than the repository (``cd /tmp && handctl run recipe config/recipes/...``) said "no
    such file" of a file the user could see, from where they meant it."""
    why = (
        "a symbolic link that leads to no file (a loop of links, or a missing target)"
        if path.is_symlink()
        else "no such file"
    )
    return why + _relative_to_here(path)


def _relative_to_here(path: Path) -> str:
    """What to add to a relative ``path``'s "no such file": the directory it was looked for
    in, the current one; nothing for an absolute path."""
    if path.is_absolute():
        return ""
    try:
        here = os.getcwd()
    except OSError:  # the directory was removed under the command
        return " (relative to the current directory, which no longer exists)"
    return f" (relative to {escaped(here)})"


def escaped(text: str) -> str:
    """``text`` as a terminal can show it and a reader can tell apart, for a message that
    names a value the user gave (an argument, a file name, a value read from a file).

    A control character was written as it was: an escape sequence in an interface name
    recoloured or cleared the terminal that showed the error, a newline split the one line a
    message is. A byte that is not UTF-8 (an argument or a file name in another encoding,
    which Python holds as a lone surrogate) became ``\\udcff``, a character the user never
    typed. Now each is an escape as Python's ``repr`` writes it, the byte as ``\\xff``, and a
    backslash is doubled so that no escape is ambiguous; the rest (accented letters, any
    printable script) is left as it is."""
    if text.isprintable() and "\\" not in text:
        return text
    return "".join(_escape(char) for char in text)


def _escape(char: str) -> str:
    code = ord(char)
    if char == "\\":
        return "\\\\"
    if 0xDC80 <= code <= 0xDCFF:  # a byte that was not UTF-8 (``surrogateescape``)
        return f"\\x{code - 0xDC00:02x}"
    if char.isprintable():
        return char
    return repr(char)[1:-1]  # \t, \x1b, \x85, \u202e, \ud800: repr's escapes


def quoted(text: str) -> str:
    """``text`` ``escaped`` between quotes, chosen as ``repr`` chooses them, so that a
    message shows a string as it always has unless it holds what ``escaped`` escapes."""
    body = escaped(text)
    if "'" in body and '"' not in body:
        return f'"{body}"'
    return "'" + body.replace("'", "\\'") + "'"


class Description(str):
    """A found value that handctl told rather than read (``found a file that is not a blf
    export``): shown as it is, neither quoted nor cut to ``SHOWN_CHARS``. Cut, the part
    that said what was wrong was often the part left out (``reading stopped at byte 8
    after...FError: the file ends inside a record``)."""

    def __repr__(self) -> str:
        return str(self)


#: characters of a ``Description`` a message shows: whole, but bounded (it may quote a
#: library's message about a hostile file)
DESCRIPTION_CHARS = 1000


def shown(found: object) -> str:
    """Render the offending value briefly: long values are cut so a message stays one line.

    ``reprlib`` bounds the work as well as the text: a value read from a hostile file (a JSON
    array nested a thousand deep) would otherwise exhaust the recursion limit while the error
    that reports it is being built. Strings, inside containers too, are ``quoted``."""
    if isinstance(found, PurePath):
        # a file's name is what the user must find again: whole (the system bounds it)
        return quoted(str(found))
    if isinstance(found, Description):
        text = printable(str(found))
        if len(text) > DESCRIPTION_CHARS:
            half = (DESCRIPTION_CHARS - 3) // 2
            text = text[:half] + "..." + text[len(text) - half :]
        return text
    # a description rather than a value (the YAML reader's ``_Text``, shown as it is, not
    # quoted) is its writer's to escape; this catches what one let through raw
    text = printable(_SHORT.repr(found))
    return text if len(text) <= SHOWN_CHARS else text[: SHOWN_CHARS - 3] + "..."


def printable(text: str) -> str:
    """``text`` with what ``escaped`` escapes escaped, but for the backslash: for text that
    may hold values already ``escaped`` or ``quoted``, whose backslashes must stay single."""
    if text.isprintable():
        return text
    return "".join(char if char == "\\" else _escape(char) for char in text)


class _ShortRepr(reprlib.Repr):
    def repr_str(self, x: str, level: int) -> str:
        """A string ``quoted``, its middle cut as ``reprlib`` cuts one."""
        text = quoted(x)
        if len(text) > self.maxstring:
            i = max(0, (self.maxstring - 3) // 2)
            j = max(0, self.maxstring - 3 - i)
            text = text[:i] + "..." + text[len(text) - j :]
        return text


def _short_repr() -> reprlib.Repr:
    short = _ShortRepr()
    short.maxlevel = 4
    short.maxstring = SHOWN_CHARS
    short.maxother = SHOWN_CHARS
    short.maxlist = short.maxtuple = short.maxdict = short.maxset = 8
    return short


_SHORT = _short_repr()


def said_by(exc: BaseException) -> str:
    """``str(exc)``, or that it could not be made: an exception's ``__str__`` is its own
    code, and what handles the exception (a stop, its summary) must not raise in its place:
    an interrupt whose ``__str__`` raised replaced itself and lost the run's result."""
    try:
        return str(exc)
    except Exception:
        return "(its message could not be made)"
