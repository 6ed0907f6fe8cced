"""The files a command is told to write (a summary, a plot, a calibrated hand config): asked
whether they can be written before the work begins, and written whole or not at all.

A run or a calibration that ends only to fail writing its result has done its work for
nothing; a hand config half written by a crash or a full disk is worse than the old one.
"""

from __future__ import annotations

import contextlib
import errno
import os
import re
import stat
from collections.abc import Mapping
from pathlib import Path

from handctl.errors import ConfigError, Description
from handctl.wholefile import write_whole


def check_writable(
    path: Path,
    option: str,
    *,
    recording: bool = False,
    json_output: bool = False,
    json_kind: tuple[str, frozenset[str]] | None = None,
    export: str | None = None,
) -> Path:
    """The file ``path`` names, resolved (a symlink is written through, not replaced), if a
    new version of it can be put there: its directory exists and may be written, and the file,
    if it exists, is a file that may be written (a read-only hand config stays as it is) and,
    unless the output is a ``recording`` itself, not a recording: a calibrated hand config, a
    plan, a summary or an export written over a run's log lost the log without a word.
    ``json_kind`` (a name and the top-level keys every such file has) narrows a
    ``json_output`` to an earlier one of that kind: a layout written over a run's
    ``--summary-json`` lost the summary, exit 0.
    Otherwise a ``ConfigError`` naming ``option``; asked before a calibration starts."""
    try:
        target = path.resolve()
    except (RuntimeError, OSError) as exc:  # a symlink loop; a name too long to resolve
        raise ConfigError(
            option, "", "a file name that resolves to a file", f"{path} ({exc})"
        ) from None
    directory = target.parent
    if not directory.is_dir():
        raise ConfigError(option, "", "a file in an existing directory", path)
    found = _stat_or_none(target, path, option)
    if (target.exists() and not target.is_file()) or (
        found is not None and not stat.S_ISREG(found.st_mode) and not _standard_stream(found)
    ):
        raise ConfigError(option, "", "a regular file (not a directory, a device or a FIFO)", path)
    stream = _standard_stream(found) if found is not None else ""
    if stream:
        # ``--log /dev/stdout > run.mcap``: the summary printed over the log's start, and
        # the command said it had recorded every tick, exit 0
        raise ConfigError(
            option,
            "",
            f"a file other than this command's standard {stream} (what it prints would be "
            "written into it)",
            path,
        )
    if target.exists() and _read_only(target):
        raise ConfigError(option, "", "a file that may be written (it is read-only)", path)
    if _read_only(directory):
        raise ConfigError(
            option, "", "a file in a directory that may be written (it is read-only)", path
        )
    if not recording and _is_recording(target):
        raise ConfigError(
            option, "", "a file that is not a run's recording (it would replace the log)", path
        )
    if json_output or json_kind is not None:
        try:
            existing = _existing_json(target)
        except _NotJsonError as exc:
            # a summary written over a hand config or a recipe replaced it, exit 0
            raise ConfigError(
                option,
                "",
                "a new file, or an earlier JSON output to write again (an existing file that "
                "is not JSON, a hand config or a recipe say, is not replaced)",
                Description(f"{path}: an existing file that is not JSON{exc}"),
            ) from None
        if json_kind is not None and existing is not _NOTHING:
            kind, keys = json_kind
            if not (isinstance(existing, dict) and keys <= existing.keys()):
                raise ConfigError(
                    option,
                    "",
                    f"a new file, or an earlier {kind} to write again (an existing JSON file "
                    "of anything else, a run's --summary-json say, is not replaced)",
                    Description(f"{path}, an existing JSON file that is not a {kind}"),
                )
    if export is not None and not _export_or_nothing(target, export):
        # a frame export written over a hand config replaced it, exit 0
        raise ConfigError(
            option,
            "",
            f"a new file, or an earlier {export} export to write again (an existing file of "
            "another kind, a hand config say, is not replaced)",
            Description(f"{path}: an existing file that is not a {export} export"),
        )
    return target


def _stat_or_none(target: Path, path: Path, option: str) -> os.stat_result | None:
    """The ``os.stat`` of the file ``path`` names (``target``, resolved), or None if there is
    none yet; a ``ConfigError`` naming ``option`` for a name the system refuses."""
    try:
        return os.stat(target)
    except OSError as exc:
        if exc.errno == errno.ENAMETOOLONG:
            # said with the file's name alone, no option, once the work was set up
            raise ConfigError(
                option, "", "a file name the system takes (File name too long)", path
            ) from None
    if target == path:
        return None
    # ``/dev/stdout`` on a pipe resolves to ``/proc/PID/fd/pipe:[N]``, no file of any
    # directory, while the link itself leads to the pipe: taken as a new file there, it was
    # refused as one in a read-only directory, not as the command's own stdout (found by an
    # outside audit)
    with contextlib.suppress(OSError):
        return os.stat(path)
    return None


def _standard_stream(file: os.stat_result) -> str:
    """Which standard stream of this process ("output" or "error") writes to the file of
    ``file`` (its ``os.stat``); "" for none."""
    for fd, name in ((1, "output"), (2, "error")):
        try:
            stream = os.fstat(fd)
        except OSError:  # closed
            continue
        if (stream.st_dev, stream.st_ino) == (file.st_dev, file.st_ino):
            return name
    return ""


#: How each frame export (python-can's log formats) begins: what an export may replace.
EXPORT_HEADS = {
    "blf": re.compile(rb"LOGG"),
    "asc": re.compile(rb"date "),
    "candump": re.compile(rb"\(\d+\.\d+\) \S+ [0-9A-Fa-f]+#"),
}


def _export_or_nothing(target: Path, fmt: str) -> bool:
    """Whether ``target`` is absent, empty, or begins as an export in ``fmt`` does."""
    try:
        with target.open("rb") as handle:
            head = handle.read(256)
    except OSError:  # not there (yet), or not readable (said when it is written)
        return True
    return not head.strip() or EXPORT_HEADS[fmt].match(head) is not None


#: what ``_existing_json`` finds where there is no JSON to replace
_NOTHING = object()
#: bytes of an existing file read to learn whether it is an earlier JSON output: hundreds of
#: times the largest handctl writes (a run's summary, a Foxglove layout: kilobytes). The file
#: was read whole, however large, before anything was done
EXISTING_JSON_BYTES = 4 * 1024 * 1024


class _NotJsonError(Exception):
    """An existing file that is no earlier JSON output; its text, if any, says more."""


def _existing_json(target: Path) -> object:
    """The JSON at ``target``; ``_NOTHING`` where it is absent, empty or not readable (said
    when it is written). ``_NotJsonError`` where it is a file of anything else, or JSON no
    output of handctl is: larger than ``EXISTING_JSON_BYTES``, or nested deeper than the
    parser's recursion goes (a RecursionError, a traceback, exit 1)."""
    import json

    try:
        with target.open("rb") as handle:
            text = handle.read(EXISTING_JSON_BYTES + 1)
    except OSError:
        return _NOTHING
    if not text.strip():
        return _NOTHING
    if len(text) > EXISTING_JSON_BYTES:
        raise _NotJsonError(f" handctl writes (more than {EXISTING_JSON_BYTES} bytes)")
    try:
        return json.loads(text)
    except ValueError:
        raise _NotJsonError("") from None
    except RecursionError:
        raise _NotJsonError(" handctl writes (nested deeper than its reader goes)") from None


def _is_recording(target: Path) -> bool:
    """Whether ``target`` is an MCAP file (begins with its magic bytes)."""
    from handctl.recording.reader import MAGIC

    try:
        with target.open("rb") as handle:
            return handle.read(len(MAGIC)) == MAGIC
    except OSError:  # not there (yet), or not readable: nothing of a log to lose by it
        return False


def check_log_target(path: Path, option: str) -> bool:
    """``check_writable`` for a recording, which replaces what is there only if that is a
    recording too (or empty): a hand config, a recipe or a README given as ``--log`` by a
    slip of the hand, or reached through a symlink, was replaced by MCAP data without a word.
    Returns whether a recording is there, to be said when it is replaced."""
    target = check_writable(path, option, recording=True)
    if not target.exists() or target.stat().st_size == 0:
        return False
    if not _is_recording(target):
        raise ConfigError(
            option,
            "",
            "a new file, or a recording (MCAP) to replace: the file there is not one, and a "
            "recording would replace it",
            path,
        )
    _refuse_locked(target, path)
    return True


def _refuse_locked(target: Path, path: Path) -> None:
    """A recording another run is writing (it holds the file's lock, as the recorder takes
    it): said before the run, as the recorder would say it at its start. Before, the run
    first warned that it would replace the log, then refused it."""
    try:
        fd = os.open(target, os.O_RDONLY | os.O_CLOEXEC)
    except OSError:
        return  # said where the recording is opened
    from handctl.recording.loglock import lock_log

    try:
        lock_log(fd, path)
    finally:
        os.close(fd)  # and the probe's lock with it


def check_directory(path: Path, option: str) -> Path:
    """The directory ``path`` names, resolved, if files can be put in it: it is a directory
    that may be written, or it does not exist yet and its nearest existing parent is one (it
    is made when the files are written). Otherwise a ``ConfigError`` naming ``option``, asked
    before the work: ``plan --plot`` learned only after the whole search that its directory
    was a file or could not be made, with the recipe already written."""
    try:
        target = path.resolve()
    except (RuntimeError, OSError) as exc:
        raise ConfigError(option, "", "a directory name that resolves", f"{path} ({exc})") from None
    existing = target
    while not existing.exists() and existing != existing.parent:
        existing = existing.parent
    if not existing.is_dir():
        raise ConfigError(
            option,
            "",
            f"a directory, or a new one's name ({existing} is not a directory)",
            path,
        )
    if _read_only(existing):
        raise ConfigError(
            option, "", f"a directory that may be written ({existing} is read-only)", path
        )
    return target


def refuse_same_files(
    outputs: Mapping[str, Path | None], inputs: Mapping[str, Path | None]
) -> None:
    """A ``ConfigError`` naming the option when a file a command is told to write is one it
    reads (``inputs``) or one another option writes too (``outputs``; options given as None
    are left out): written at its end, it replaced the recipe or the hand config with MCAP
    data, or the log with the summary, and said nothing. Paths are compared as the files they
    name (symlinks and hard links found out) where they exist, as resolved names otherwise."""
    seen: dict[tuple[object, ...], str] = {}
    for option, path in inputs.items():
        if path is not None:
            seen.setdefault(_identity(path), option)
    for option, path in outputs.items():
        if path is None:
            continue
        key = _identity(path)
        if key in seen:
            raise ConfigError(option, "", f"another file than {seen[key]}'s (both name it)", path)
        seen[key] = option


def _identity(path: Path) -> tuple[object, ...]:
    try:
        info = path.stat()
    except (OSError, RuntimeError):  # not there yet, or a loop (refused where it is checked)
        try:
            return ("name", str(path.resolve()))
        except (OSError, RuntimeError):
            return ("name", str(path.absolute()))
    return ("file", info.st_dev, info.st_ino)


#: the picture formats a plot is written in (matplotlib's own, by file name suffix); said
#: before the work, not found out when the picture is drawn at its end
IMAGE_SUFFIXES = ("png", "pdf", "svg", "svgz", "jpg", "jpeg", "tif", "tiff", "webp", "eps", "ps")


def check_image(path: Path, option: str) -> Path:
    """``check_writable``, and a name whose suffix says a picture format the plot can be
    written in. Why here: a run's plot is drawn after the run, and matplotlib refuses an
    unknown suffix only then, with a traceback; a name without a suffix would be written
    as another file (matplotlib adds ``.png``) than the one the user named."""
    target = check_writable(path, option)
    suffix = path.suffix.lower().lstrip(".")
    if suffix not in IMAGE_SUFFIXES:
        raise ConfigError(
            option,
            "",
            "a picture file name ending in ." + ", .".join(IMAGE_SUFFIXES),
            path,
        )
    if not picture_or_nothing(target):
        # a hand config copied to a name ending in .png was replaced by the plot, exit 0
        raise ConfigError(
            option,
            "",
            "a new file, or an earlier picture to draw again (an existing file of another "
            "kind, a hand config say, is not replaced)",
            Description(f"{path}: an existing file that is not a picture"),
        )
    return target


#: How the picture formats a plot is written in begin: what a plot may replace.
PICTURE_HEADS = (
    b"\x89PNG\r\n\x1a\n",
    b"%PDF",
    b"<?xml",
    b"<svg",
    b"\x1f\x8b",  # svgz
    b"\xff\xd8\xff",
    b"II*\x00",
    b"MM\x00*",
    b"RIFF",  # webp
    b"%!PS",
    b"\xc5\xd0\xd3\xc6",  # a binary EPS
)


def picture_or_nothing(target: Path) -> bool:
    """Whether ``target`` is absent, empty, or begins as a picture does: what a plot may
    replace."""
    try:
        with target.open("rb") as handle:
            head = handle.read(16)
    except OSError:  # not there (yet), or not readable (said when it is written)
        return True
    return not head or head.startswith(PICTURE_HEADS)


def _read_only(path: Path) -> bool:
    """Not to be written by this process, or by anyone (no write bit at all: root may still
    write it, but whoever took the bits away meant it to stay)."""
    no_bits = not stat.S_IMODE(path.stat().st_mode) & (stat.S_IWUSR | stat.S_IWGRP | stat.S_IWOTH)
    return no_bits or not os.access(path, os.W_OK | (os.X_OK if path.is_dir() else 0))


def write_atomically(target: Path, text: str) -> None:
    """``text`` into ``target`` whole or not at all (``wholefile.write_whole``)."""
    write_whole(target, text.encode("utf-8"))
