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
the bus's own directory holds its participants' sockets and nothing else). A ``virtual``
bus lives inside one process and takes none. It guards one machine only: a host on another
machine on the same CAN bus is heard by the listen once it sends.
"""

from __future__ import annotations

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

    def __init__(self, fd: int | None) -> None:
        self._fd = fd

    def release(self) -> None:
        if self._fd is not None:
            fd, self._fd = self._fd, None
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
    try:
        fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o666)
    except OSError as exc:
        raise BusError(
            f"{spec}: the host lock {path} cannot be opened ({exc.strerror or exc}): it keeps "
            f"a second handctl on this machine from starting beside a first; {who} sent "
            "nothing"
        ) from None
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        holder = _holder(fd)
        os.close(fd)
        raise BusError(
            f"another handctl host holds {spec} on this machine ({holder}): stop it first, "
            f"or wait for it to end; {who} sent nothing"
        ) from None
    os.ftruncate(fd, 0)
    said = f"pid {os.getpid()}, since {time.strftime('%H:%M:%S')}: {' '.join(sys.argv)}"
    os.write(fd, said.encode(errors="replace")[:512])
    return BusLock(fd)


def _holder(fd: int) -> str:
    """What the holder wrote of itself, printable, or that it said nothing yet."""
    try:
        text = os.pread(fd, 512, 0).decode(errors="replace")
    except OSError:
        text = ""
    text = "".join(c if c.isprintable() else "?" for c in text).strip()
    return text or "a process that has not said which yet"
