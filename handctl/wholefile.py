"""A picture written whole or not at all.

Of the foundation, so that the analysis, planning and recording draw their plots with it.
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from pathlib import Path
from typing import Protocol


class Picture(Protocol):
    """What ``save_picture`` needs of a figure (matplotlib's ``Figure``), without importing
    matplotlib here."""

    def savefig(self, fname: str, *, format: str) -> None: ...  # matplotlib's


def save_picture(figure: Picture, target: Path) -> None:
    """A plot into ``target`` whole or not at all, as ``write_atomically``: matplotlib writes
    the file in place, and a full disk or a directory removed while it drew left a half
    picture, or an empty file, under the name asked for. The format is the name's suffix
    (``check_image`` checked it)."""
    target = Path(target)
    fd, tmp = tempfile.mkstemp(prefix=f".{target.name}.", suffix=".tmp", dir=target.parent)
    os.close(fd)
    try:
        figure.savefig(tmp, format=target.suffix.lower().lstrip("."))
        os.replace(tmp, target)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise
