"""The one exception tree of handctl.

Callers catch ``HandctlError`` to handle anything handctl raises on purpose; the subclasses also
derive from the standard exception a Python user would reach for first (``ValueError`` for bad
input, ``TimeoutError`` for deadlines), in the manner of python-can's exception tree, so generic
code keeps working.
"""

from __future__ import annotations

import reprlib
from pathlib import PurePath


class HandctlError(Exception):
    """Base of every error handctl raises deliberately."""


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
        where = f"{file}: {key}" if key else file
        super().__init__(f"{where}: expected {expected}, found {_show(found)}")


class ProtocolError(HandctlError, ValueError):
    """A value that cannot be put on the wire (out of the DBC range, wrong shape, unknown frame)."""


class BusError(HandctlError):
    """A bus that cannot be opened or used as asked."""


class HandctlTimeoutError(HandctlError, TimeoutError):
    """A deadline passed: a node did not answer, a tick came too late."""


#: characters of an offending value a message shows
SHOWN_CHARS = 80


def _show(found: object) -> str:
    """Render the offending value briefly: long values are cut so a message stays one line.

    ``reprlib`` bounds the work as well as the text: a value read from a hostile file (a JSON
    array nested a thousand deep) would otherwise exhaust the recursion limit while the error
    that reports it is being built."""
    if isinstance(found, PurePath):
        # a file's name is what the user must find again: whole (the system bounds it)
        return repr(str(found))
    text = _SHORT.repr(found)
    return text if len(text) <= SHOWN_CHARS else text[: SHOWN_CHARS - 3] + "..."


def _short_repr() -> reprlib.Repr:
    short = reprlib.Repr()
    short.maxlevel = 4
    short.maxstring = SHOWN_CHARS
    short.maxother = SHOWN_CHARS
    short.maxlist = short.maxtuple = short.maxdict = short.maxset = 8
    return short


_SHORT = _short_repr()
