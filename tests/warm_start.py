"""``python -m handctl`` without the interpreter's start-up, for the suite's many short
commands.

Most of the suite's ``handctl`` commands end within a second, and half of that second was
Python starting and importing numpy, python-can and handctl's command line: some 0.45 s
each, over the suite's hundreds of commands minutes of its wall time. So one process per
worker, started once, imports what every command imports (``handctl.cli``) and then
forks a process for each command. That process is one of its own, as a fresh one would be:
its own pid and exit (a signal's death is a negative return code, as ``subprocess``
gives), descriptors 0, 1 and 2 the command's (standard input ``/dev/null``, the output
captured), every other descriptor closed, the command's working directory, environment and
``sys.path[0]``, the signal dispositions a fresh interpreter sets, and handctl's
``__main__`` run as ``python -m`` runs it. Its uncaught exceptions, ``atexit`` handlers and
flushes are the interpreter's own, since nothing between the fork and the top of the stack
catches anything.

What it cannot be, the caller runs cold (``subprocess``, as before): a command with limits
of its own set before it starts (``preexec_fn``), or an environment that differs from this
process's where the interpreter or an imported library reads it at start-up (``PYTHON*``,
the locale, the thread pools' sizes).

The protocol, on a unix socket: the client sends a length-prefixed JSON request (argv,
cwd, env) with descriptors 0, 1 and 2 attached; a handler forked for the connection forks
the command, answers its pid, waits for it, and answers its return code. A handler per
command keeps the server free for the next one and lets the command's parent wait for it.
"""

from __future__ import annotations

import atexit
import contextlib
import gc
import importlib
import json
import os
import runpy
import selectors
import signal
import socket
import struct
import subprocess
import sys
import tempfile
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

#: What an interpreter or the libraries handctl's command line imports read from the
#: environment as they start; a command whose value differs from the server's runs cold.
#: Not MUJOCO_GL or MPLBACKEND: handctl's command line sets the one and drops the other
#: whatever the environment says, and every in-process ``cli.main`` of a test did so in the
#: worker's own environment, which then sent every later command cold
START_UP_ENV = ("PYTHON", "LC_", "LANG", "OMP_", "OPENBLAS_", "MKL_", "NUMEXPR_")
_HEADER = struct.Struct("!I")
#: What the server imports: the command line, and what loading a hand and running a recipe
#: on the simulated hand import (numpy, python-can, MuJoCo, the recorder's MCAP), and what
#: the commands that draw and plan import besides (matplotlib's figure on its Agg canvas,
#: the planner's scipy), half a second each that dozens of the suite's commands paid again
PRELOADED = (
    "orjson",  # handctl's __main__ loads it first
    "handctl.cli",
    "handctl.config",
    "handctl.online.busspec",
    "handctl.session",
    "handctl.sim.plant",
    "handctl.recording.recorder",
    "matplotlib.figure",
    "matplotlib.backends.backend_agg",
    "scipy.optimize",
)


def _started_with(key: str) -> bool:
    return key.startswith(START_UP_ENV)


# -- the server ----------------------------------------------------------------------------


def serve(path: str) -> None:
    """Import what the commands import, then fork a handler per connection until the
    parent (the suite's worker) is gone."""
    # as handctl's command line sets it before its first import of MuJoCo; a command whose
    # environment chooses otherwise starts cold (START_UP_ENV)
    os.environ.setdefault("MUJOCO_GL", "disable")
    # and as it drops matplotlib's backend (a value matplotlib does not know would end this
    # server in its import; a command that names one drops it too)
    os.environ.pop("MPLBACKEND", None)
    for name in PRELOADED:
        importlib.import_module(name)
    # what is loaded stays out of the collector's reach, so that a command's collections
    # do not write to (and so copy) every page it shares with this process
    gc.freeze()

    parent = os.getppid()
    listener = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    listener.bind(path)
    listener.listen(64)
    signal.signal(signal.SIGCHLD, signal.SIG_IGN)  # the handlers are reaped by the kernel
    selector = selectors.DefaultSelector()
    selector.register(listener, selectors.EVENT_READ)
    while os.getppid() == parent:
        if not selector.select(timeout=1.0):
            continue
        conn, _ = listener.accept()
        if os.fork() == 0:
            selector.close()
            listener.close()
            _handle(conn)  # returns only in the command's process
            return
        conn.close()


def _receive(conn: socket.socket) -> tuple[dict[str, Any], list[int]]:
    data, fds, _, _ = socket.recv_fds(conn, 1 << 16, 3)
    while len(data) < _HEADER.size:
        data += conn.recv(1 << 16)
    (size,) = _HEADER.unpack_from(data)
    body = data[_HEADER.size :]
    while len(body) < size:
        more = conn.recv(1 << 16)
        if not more:
            raise EOFError("the request was cut short")
        body += more
    return json.loads(body), fds


def _handle(conn: socket.socket) -> None:
    """The handler: fork the command, say its pid, wait for it and say how it ended. Only
    the command's process returns from here."""
    signal.signal(signal.SIGCHLD, signal.SIG_DFL)  # this process waits for its child
    request, fds = _receive(conn)
    pid = os.fork()
    if pid == 0:
        conn.close()
        _become(request, fds)
        return
    for fd in fds:
        os.close(fd)
    conn.sendall(f"{pid}\n".encode())
    _, status = os.waitpid(pid, 0)
    conn.sendall(f"{os.waitstatus_to_exitcode(status)}\n".encode())
    conn.close()
    os._exit(0)


def _become(request: dict[str, Any], fds: list[int]) -> None:
    """The command's process: its descriptors, directory, environment and arguments, then
    ``python -m handctl`` (whose ``SystemExit`` ends this process as the interpreter ends
    any)."""
    for target, fd in enumerate(fds):
        os.dup2(fd, target)
    os.closerange(3, os.sysconf("SC_OPEN_MAX"))
    os.chdir(request["cwd"])
    os.environ.clear()
    os.environ.update(request["env"])
    sys.path[0] = os.getcwd()
    sys.argv = [sys.executable, *request["args"]]
    runpy.run_module("handctl", run_name="__main__", alter_sys=True)


# -- the client ----------------------------------------------------------------------------


class WarmStart:
    """The server of one process of the suite (one xdist worker), started on first use."""

    def __init__(self, root: Path, env: Mapping[str, str]) -> None:
        self.env = dict(env)
        self.directory = tempfile.mkdtemp(prefix="handctl-warm-")
        self.path = os.path.join(self.directory, "s")
        self.server = subprocess.Popen(
            [sys.executable, __file__, self.path],
            cwd=root,
            env=self.env,
            stdin=subprocess.DEVNULL,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.PIPE,
        )
        atexit.register(self.close)
        deadline = time.monotonic() + 120
        while not os.path.exists(self.path):
            if self.server.poll() is not None:
                err = self.server.stderr.read().decode() if self.server.stderr else ""
                raise RuntimeError(f"the warm-start server ended at its start: {err}")
            if time.monotonic() > deadline:
                raise RuntimeError("the warm-start server did not listen within 120 s")
            time.sleep(0.02)

    def takes(self, env: Mapping[str, str]) -> bool:
        """Whether a command with this environment can start warm: the keys read at start-up
        as the server had them."""
        keys = {k for k in (*env, *self.env) if _started_with(k)}
        return all(env.get(k) == self.env.get(k) for k in keys)

    def run(
        self, argv: Sequence[str], cwd: Path, env: Mapping[str, str], timeout: float
    ) -> subprocess.CompletedProcess[str]:
        """``subprocess.run(argv, cwd=, env=, text=True, capture_output=True,
        timeout=)``, warm (``argv`` is ``python -m handctl ...``)."""
        out_r, out_w = os.pipe()
        err_r, err_w = os.pipe()
        stdin = os.open(os.devnull, os.O_RDONLY)
        conn = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        try:
            conn.connect(self.path)
            body = json.dumps({"args": list(argv[3:]), "cwd": str(cwd), "env": dict(env)}).encode()
            socket.send_fds(conn, [_HEADER.pack(len(body)) + body], [stdin, out_w, err_w])
        finally:
            for fd in (stdin, out_w, err_w):
                os.close(fd)
        answer, out, err = self._collect(conn, out_r, err_r, time.monotonic() + timeout)
        lines = answer.decode().split()
        if len(lines) < 2:  # killed at its timeout (``_collect``)
            raise subprocess.TimeoutExpired(list(argv), timeout, _text(out), _text(err))
        return subprocess.CompletedProcess(list(argv), int(lines[1]), _text(out), _text(err))

    @staticmethod
    def _collect(
        conn: socket.socket, out_r: int, err_r: int, deadline: float
    ) -> tuple[bytes, bytes, bytes]:
        """Read the command's output to its end and the handler's answers, or up to the
        deadline; a command still running then is killed, as ``subprocess.run`` kills it."""
        said = conn.fileno()
        chunks: dict[int, list[bytes]] = {out_r: [], err_r: [], said: []}
        selector = selectors.DefaultSelector()
        for fd in chunks:
            selector.register(fd, selectors.EVENT_READ)
        killed = False
        try:
            while selector.get_map():
                left = deadline - time.monotonic()
                if left <= 0 and not killed:
                    pid = b"".join(chunks[said]).split(b"\n")[0]
                    if pid:
                        os.kill(int(pid), signal.SIGKILL)
                    killed = True
                    deadline = time.monotonic() + 5  # what it left behind, briefly
                    continue
                if left <= 0:
                    break
                for key, _ in selector.select(timeout=left):
                    fd = int(key.fd)
                    data = os.read(fd, 1 << 16)
                    if data:
                        chunks[fd].append(data)
                    else:
                        selector.unregister(fd)
        finally:
            selector.close()
            conn.close()
            os.close(out_r)
            os.close(err_r)
        answer = b"".join(chunks[said])
        if killed:  # the return code of a command killed at its timeout is not its own
            answer = answer.split(b"\n")[0]
        return answer, b"".join(chunks[out_r]), b"".join(chunks[err_r])

    def close(self) -> None:
        if self.server.poll() is None:
            self.server.kill()
            self.server.wait()
        if self.server.stderr is not None:
            self.server.stderr.close()
        with contextlib.suppress(OSError):
            os.unlink(self.path)
            os.rmdir(self.directory)


def _text(data: bytes) -> str:
    """As ``subprocess`` decodes a captured stream in text mode (universal newlines)."""
    import locale

    return data.decode(locale.getpreferredencoding(False)).replace("\r\n", "\n").replace("\r", "\n")


if __name__ == "__main__":
    serve(sys.argv[1])
