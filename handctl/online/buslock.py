"""One handctl host per bus on a machine: a lock every host takes before it listens or sends.

Why: a second run or jog listens for another host's commands before its timing check
(``otherhost``), but a first one still in its own start-up (its timing check, its listen) has
sent nothing to hear. Started within about two seconds of each other on one machine, the
second passed its listen, ran its timing check at real-time priority on the first's CPU, and
the first lost 18 to 38 ticks in a row and latched every node's TIMEOUT (found by an outside
audit). A lock is taken at once, whatever the other has sent: the second is refused before
it listens, with the first's process named.

An advisory ``flock`` on a file named for the bus: the kernel drops it when its holder ends,
however it ends, so a killed run leaves no lock behind. The files live in the temporary
directory, by interface and channel (a unix bus's by a digest of its directory's real path:
the bus's own directory holds its participants' sockets and nothing else). The holder removes
its file as it lets go, so the temporary directory does not fill with one file for every unix
bus ever used (the suite alone made 150 in a day); a killed holder leaves it, and the next
holder takes it over and removes it. Removing a lock file races with a second process that
opened it just before: that one may then lock a file no longer in the directory, so a taker
checks, once it has the lock, that the path still names the file it locked, and opens again
if not. A ``virtual``
bus lives inside one process and takes none. It guards one machine only: a host on another
machine on the same CAN bus is heard by the listen once it sends.
"""

from __future__ import annotations

import contextlib
import fcntl
import hashlib
import os
import re
import sys
import tempfile
import time
from pathlib import Path

from handctl.errors import BusError
from handctl.online.busspec import BusSpec


def lock_path(spec: BusSpec) -> Path | None:
    """Where the host lock of ``spec`` lives (None: a bus inside this process)."""
    if spec.interface in ("virtual", "sim"):
        return None
    channel = spec.channel
    if spec.interface == "unix":  # one directory, however it is written
        resolved = os.path.realpath(channel).encode(errors="surrogateescape")
        channel = hashlib.sha256(resolved).hexdigest()[:16]
    name = re.sub(r"[^A-Za-z0-9._-]", "_", f"{spec.interface}-{channel}")
    return Path(tempfile.gettempdir()) / f"handctl-bus-{name}.lock"


class BusLock:
    """This process's hold on a bus; ``release`` (or the process's end) lets it go."""

    def __init__(self, fd: int | None, path: Path | None = None) -> None:
        self._fd = fd
        self._path = path

    def release(self) -> None:
        if self._fd is not None:
            fd, self._fd = self._fd, None
            if self._path is not None:
                # removed while still held: a taker that opened it meanwhile finds its lock
                # on a file the path no longer names, and opens the path again
                with contextlib.suppress(OSError):
                    if _same_file(fd, self._path):
                        self._path.unlink()
            os.close(fd)  # the flock goes with the last descriptor

    def __enter__(self) -> BusLock:
        return self

    def __exit__(self, *_exc: object) -> None:
        self.release()


def take_bus(spec: BusSpec, who: str) -> BusLock:
    """This host's lock on ``spec``; ``BusError`` naming the holder when another handctl host
    on this machine has it. ``who`` ("this run", "this replay") has sent nothing yet."""
    path = lock_path(spec)
    if path is None:
        return BusLock(None)
    for _ in range(_OPEN_TRIES):
        fd = _open_lock(spec, path, who)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = _holder(fd)
            os.close(fd)
            raise BusError(
                f"another handctl host holds {spec} on this machine ({holder}): stop it "
                f"first, or wait for it to end; {who} sent nothing"
            ) from None
        if _same_file(fd, path):
            break
        os.close(fd)  # its holder removed it as it let go: the path's file is the lock now
    else:
        raise BusError(
            f"{spec}: the host lock {path} was removed under this process {_OPEN_TRIES} "
            f"times in a row: something else is deleting it; {who} sent nothing"
        )
    os.ftruncate(fd, 0)
    said = f"pid {os.getpid()}, since {time.strftime('%H:%M:%S')}: {' '.join(sys.argv)}"
    os.write(fd, said.encode(errors="replace")[:512])
    return BusLock(fd, path)


#: Opens of a lock file removed before it was locked, in a row, before giving up: one is a
#: holder letting go in between, several a loop of them, more something else removing it.
_OPEN_TRIES = 20


def _open_lock(spec: BusSpec, path: Path, who: str) -> int:
    try:
        return os.open(path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o666)
    except OSError as exc:
        raise BusError(
            f"{spec}: the host lock {path} cannot be opened ({exc.strerror or exc}): it keeps "
            f"a second handctl on this machine from starting beside a first; {who} sent "
            "nothing"
        ) from None


def _same_file(fd: int, path: Path) -> bool:
    """Whether ``path`` still names the file open at ``fd``."""
    try:
        named = os.stat(path)
    except FileNotFoundError:
        return False
    held = os.fstat(fd)
    return (named.st_dev, named.st_ino) == (held.st_dev, held.st_ino)


def _holder(fd: int) -> str:
    """What the holder wrote of itself, printable, or that it said nothing yet."""
    try:
        text = os.pread(fd, 512, 0).decode(errors="replace")
    except OSError:
        text = ""
    text = "".join(c if c.isprintable() else "?" for c in text).strip()
    return text or "a process that has not said which yet"
