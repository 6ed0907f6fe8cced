"""One handctl host per bus on a machine: a lock every host takes before it listens or sends.

Why: a second run or jog listens for another host's commands before its timing check
(``otherhost``), but a first one still in its own start-up (its timing check, its listen) has
sent nothing to hear. Started within about two seconds of each other on one machine, the
second passed its listen, ran its timing check at real-time priority on the first's CPU, and
the first lost 18 to 38 ticks in a row and latched every node's TIMEOUT (found by an outside
audit). A lock is taken at once, whatever the other has sent: the second is refused before
it listens, with the first's process named.

The lock is a name in Linux's abstract unix socket namespace (``@handctl-bus-...``), bound by
the holder: the kernel refuses the name to a second socket while the first is open and frees
it when its holder ends, however it ends. A lock file in the temporary directory did the same
with ``flock``, and an outside audit found what a file brings with it: a symbolic link planted
at its predictable path was followed and the file it named emptied and overwritten (by an
``--rt`` run as root); the file removed by hand while a run started let a second host in
(the lock was on the removed file); a killed holder's file, made by one user, kept every
other user off that bus; and one file stayed behind for every unix bus ever used. A name has
no path to plant a link at, nothing to remove, no owner and nothing to leave behind. Names
are by interface and channel (a unix bus's by a digest of its directory's real path); a
``virtual`` bus lives inside one process and takes none. It guards one machine (one network
namespace) only: a host on another machine on the same CAN bus is heard by the listen once it
sends.
"""

from __future__ import annotations

import contextlib
import errno
import hashlib
import os
import re
import socket
from pathlib import Path

from handctl.errors import BusError, printable
from handctl.online.busspec import BusSpec

#: Bytes of an abstract socket's name, past the leading NUL (108 in ``sun_path``, less one).
_NAME_MAX = 107


def lock_name(spec: BusSpec) -> str | None:
    """The abstract name of the host lock of ``spec`` (None: a bus inside this process)."""
    if spec.interface in ("virtual", "sim"):
        return None
    channel = spec.channel
    if spec.interface == "unix":  # one directory, however it is written
        resolved = os.path.realpath(channel).encode(errors="surrogateescape")
        channel = hashlib.sha256(resolved).hexdigest()[:16]
    name = "handctl-bus-" + re.sub(r"[^A-Za-z0-9._-]", "_", f"{spec.interface}-{channel}")
    if len(name) > _NAME_MAX:  # a channel name longer than any interface's: by its digest
        digest = hashlib.sha256(f"{spec.interface}:{spec.channel}".encode()).hexdigest()
        name = f"handctl-bus-{spec.interface[:40]}-{digest[:32]}"
    return name


class BusLock:
    """This process's hold on a bus; ``release`` (or the process's end) lets it go."""

    def __init__(self, sock: socket.socket | None) -> None:
        self._sock = sock

    def release(self) -> None:
        if self._sock is not None:
            sock, self._sock = self._sock, None
            sock.close()  # the name is free again

    def __enter__(self) -> BusLock:
        return self

    def __exit__(self, *_exc: object) -> None:
        self.release()


def take_bus(spec: BusSpec, who: str) -> BusLock:
    """This host's lock on ``spec``; ``BusError`` naming the holder when another handctl host
    on this machine has it. ``who`` ("this run", "this replay") has sent nothing yet."""
    name = lock_name(spec)
    if name is None:
        return BusLock(None)
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM | socket.SOCK_CLOEXEC)
    try:
        sock.bind(b"\0" + name.encode())
    except OSError as exc:
        sock.close()
        if exc.errno == errno.EADDRINUSE:
            raise BusError(
                f"another handctl host holds {spec} on this machine ({_holder(name)}): stop "
                f"it first, or wait for it to end; {who} sent nothing"
            ) from None
        raise BusError(
            f"{spec}: the host lock (@{name}) cannot be taken ({exc.strerror or exc}): it "
            f"keeps a second handctl on this machine from starting beside a first; {who} sent "
            "nothing"
        ) from None
    return BusLock(sock)


def _holder(name: str) -> str:
    """Which process holds ``name``: the one with the socket bound to it open, found through
    ``/proc`` (its pid and command line), or that it cannot be seen (another user's, whose
    descriptors this process may not read)."""
    inodes = set()
    with contextlib.suppress(OSError):
        for line in Path("/proc/net/unix").read_text().splitlines()[1:]:
            fields = line.split()
            if len(fields) >= 8 and fields[7] == f"@{name}":
                inodes.add(f"socket:[{fields[6]}]")
    for pid in (p for p in os.listdir("/proc") if p.isdigit()) if inodes else ():
        with contextlib.suppress(OSError):
            fds = Path("/proc") / pid / "fd"
            if any(os.readlink(fds / fd) in inodes for fd in os.listdir(fds)):
                return f"pid {pid}: {_command(pid)}"
    return "a process this one cannot see (another user's?)"


def _command(pid: str) -> str:
    """The command line of process ``pid``, printable."""
    try:
        raw = (Path("/proc") / pid / "cmdline").read_bytes()
    except OSError:
        return "?"
    text = " ".join(a.decode(errors="replace") for a in raw.split(b"\0") if a)[:400]
    return printable(text) or "?"
