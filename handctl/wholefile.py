"""A file written whole or not at all, a JSON output or a picture alike.

Every output a command writes goes to a file beside its name, flushed to the disk, then
renamed over it: a reader (or a crash, a full disk, Ctrl-C) sees the old file or the new one,
never a half, where writing in place left a half picture or an empty file under the name asked
for. Of the foundation, so that the analysis, planning and recording draw their plots with it
as the commands write their JSON.
"""

from __future__ import annotations

import contextlib
import io
import os
import stat
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import Protocol

from handctl.errors import HandctlError


def write_whole(target: Path, data: bytes) -> None:
    """``data`` into ``target``, whole or not at all (module docstring)."""
    with whole_file(target) as out, out.open("wb") as file:
        file.write(data)


@contextlib.contextmanager
def whole_file(target: Path) -> Iterator[Path]:
    """A path beside ``target`` to write the new version to, in full, by whatever writes it
    (a python-can log writer opens its own file); on leaving without an error it is flushed to
    the disk and renamed over ``target``, on an error removed and ``target`` left as it was. A
    symbolic link is written through, not replaced; the old file's permissions are kept, a new
    file gets what ``open`` would have given it (the umask's). The file beside it has a short
    name of its own: one named after the target went past the file system's longest name for a
    name that itself fits."""
    target = Path(target).resolve()
    if target.exists():
        mode = stat.S_IMODE(target.stat().st_mode)
    else:
        umask = os.umask(0)
        os.umask(umask)
        mode = 0o666 & ~umask
    fd, tmp = tempfile.mkstemp(prefix=".handctl-", suffix=".tmp", dir=target.parent)
    os.close(fd)
    try:
        yield Path(tmp)
        fd = os.open(tmp, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)
        os.chmod(tmp, mode)
        os.replace(tmp, target)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise
    with contextlib.suppress(OSError):  # the rename itself, on a file system that needs it
        dir_fd = os.open(target.parent, os.O_RDONLY)
        try:
            os.fsync(dir_fd)
        finally:
            os.close(dir_fd)


class Picture(Protocol):
    """What ``save_picture`` needs of a figure (matplotlib's ``Figure``), without importing
    matplotlib here."""

    def savefig(self, fname: io.BytesIO, *, format: str) -> None: ...  # its name


class PictureNotWrittenError(HandctlError):
    """A picture that could not be written: its name and why (the system's words)."""

    def __init__(self, path: Path, why: str) -> None:
        super().__init__(f"{path}: no plot written ({why})")
        self.path = path
        self.why = why


def save_picture(figure: Picture, target: Path) -> None:
    """A plot into ``target`` whole or not at all (``write_whole``), in the format its name's
    suffix says (``outfile.check_image`` checked it). Drawn in memory first: a picture drawn
    to a file records that file's name (an .svgz's gzip header, an .eps's title), which was
    the temporary one. A picture that cannot be written (a full disk, its directory gone) is
    ``PictureNotWrittenError`` naming it, not an ``OSError`` naming the file beside it."""
    target = Path(target)
    drawn = io.BytesIO()
    figure.savefig(drawn, format=target.suffix.lower().lstrip("."))
    try:
        write_whole(target, drawn.getvalue())
    except OSError as exc:
        raise PictureNotWrittenError(target, exc.strerror or str(exc)) from None


def left_as_it_was(existed: bool) -> str:
    """What a failed whole-file write left at its path, for its message: the earlier file
    as it was, or nothing. "it is unchanged" was said of a file that had never been there
    (found by an outside audit)."""
    return "it is unchanged" if existed else "no file was made there"
