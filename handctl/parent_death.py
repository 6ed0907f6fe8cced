"""A helper process that must not outlive the process that started it.

The simulated hand of a real-time run is a process of its own; at SCHED_FIFO it would go on
sending frames, and holding a CPU, long after its host was killed with SIGKILL, which runs no
clean-up in the host. So the child watches for itself, on two lines, since each alone has a gap:

- the kernel's parent-death signal (Linux ``prctl(PR_SET_PDEATHSIG)``): immediate, but asked for
  by the child once it runs, so a parent that died in between is missed; and it follows the
  parent *thread* that started the child, not the whole process;
- the parent's pid against ``getppid()``: a child whose parent died is re-parented, so a check
  right after the request above, and then periodically, sees it whatever the kernel did.

The signal can come early: when the parent thread ends before the rest of its process (a
process killed with SIGKILL takes its threads down one by one), the child is signalled while
``getppid()`` still names the dying process. ``parent_ends`` waits those moments out.
"""

from __future__ import annotations

import ctypes
import json
import os
import re
import signal
import stat
import subprocess
import sys
import time
from contextlib import suppress
from pathlib import Path
from typing import Any, Self

from handctl.errors import HandctlError
from handctl.stopsignals import signal_name

_PR_SET_PDEATHSIG = 1


def die_with_parent(parent_pid: int, sig: int = signal.SIGTERM) -> bool:
    """Have ``sig`` sent to this process when its parent ends; False if it already has.

    ``sig`` should be one the process handles (SIGTERM: a clean stop that can tidy up), not
    SIGKILL, which would leave behind what only this process can remove.
    """
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(_PR_SET_PDEATHSIG, int(sig), 0, 0, 0)
    except (OSError, AttributeError):  # no prctl (not Linux): the pid check alone
        pass
    return parent_alive(parent_pid)


def parent_alive(parent_pid: int) -> bool:
    """Whether ``parent_pid`` is still this process's parent (a dead one's children move)."""
    return os.getppid() == parent_pid


def parent_ends(parent_pid: int, within_s: float) -> bool:
    """Whether ``parent_pid`` stops being this process's parent within ``within_s``."""
    deadline = time.monotonic() + within_s
    while parent_alive(parent_pid):
        if time.monotonic() >= deadline:
            return False
        time.sleep(0.01)
    return True


def remove_orphaned_bus(spec: str, summary_json: Path | None) -> None:
    """The unix bus directory of a host that died, removed by its simulated hand, which
    outlived it (a host that ends normally removes the directory itself, after the hand ended).

    Only what handctl put there goes: the bus's sockets (the dead host's too) but those of a
    process still alive, the hand's summary and its log, then the directory if nothing else is
    left in it. A directory that holds anything else was not a run's private bus, and what
    else it holds is not ours; a live peer's endpoint is its own.
    """
    interface, _, channel = spec.partition(":")
    if interface != "unix" or not channel:
        return
    directory = Path(channel).resolve()
    ours = [p for p in directory.glob("*.sock") if _is_bus_socket(p) and not _owner_alive(p)]
    if summary_json is not None:
        ours.append(summary_json)
    with suppress(OSError):
        ours.append(Path(os.readlink("/proc/self/fd/2")))  # this process's log, if a file
    for path in ours:
        if path.resolve().parent == directory:
            with suppress(OSError):
                path.unlink()
    with suppress(OSError):  # gone already, or not empty: what is left is not ours
        directory.rmdir()


def _owner_alive(path: Path) -> bool:
    """Whether the process a bus endpoint is named for (``PID-N.sock``) is alive and not
    this one (this process's own endpoints go with it)."""
    pid = int(path.name.partition("-")[0])
    return pid != os.getpid() and process_alive(pid)


def process_alive(pid: int) -> bool:
    """Whether process ``pid`` exists and has not ended (one that ended and waits to be
    reaped is not alive); one this process may not signal counts as alive."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except (PermissionError, OverflowError):
        return True
    return not _zombie(pid)


def _zombie(pid: int) -> bool:
    """Whether ``pid`` has ended and waits to be reaped: a host killed with SIGKILL is one
    until its parent waits for it, and its hand tidies up in that moment (the parent-death
    signal comes at once). Where /proc does not say, the process counts as alive."""
    try:
        stat_line = Path(f"/proc/{pid}/stat").read_text(encoding="ascii", errors="replace")
    except OSError:
        return False
    # "pid (comm) S ...": the state follows the last parenthesis (comm may hold any)
    return stat_line.rpartition(")")[2].split()[:1] in (["Z"], ["X"])


def _is_bus_socket(path: Path) -> bool:
    """A unix bus endpoint (``PID-N.sock``, a socket), not some other file of that name."""
    with suppress(OSError):
        return re.fullmatch(r"\d+-\d+\.sock", path.name) is not None and stat.S_ISSOCK(
            path.lstat().st_mode
        )
    return False


def stop_on_signals() -> list[bool]:
    """A flag the helper's loop polls, set by SIGTERM (its parent's stop, or the parent's
    death through ``die_with_parent``) and SIGINT: the loop then ends and writes its record."""
    stop = [False]

    def on_signal(signum: int, frame: object) -> None:
        stop[0] = True

    signal.signal(signal.SIGTERM, on_signal)
    signal.signal(signal.SIGINT, on_signal)
    return stop


class JsonHelper:
    """A helper child process (``python -m MODULE ARGS``) that runs until told to stop, or
    for a time of its own, then writes one JSON object to stdout: the timing probe, the
    real-time rivals' watcher. It gets a session of its own: a terminal's Ctrl-C (SIGINT to
    the foreground process group) is its parent's to handle; it ends when the parent says so,
    or dies with it (``die_with_parent``)."""

    def __init__(self, module: str, args: list[str], what: str) -> None:
        self.what = what
        self.started = time.monotonic()
        self.proc = subprocess.Popen(
            [sys.executable, "-m", module, *args],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            start_new_session=True,
        )

    def finish(self, timeout_s: float, terminate: bool = True) -> Any:
        """Its record: SIGTERM first if ``terminate`` and it still runs, then up to
        ``timeout_s`` for it to write, else it is killed; a helper that failed or wrote no
        JSON is an error naming it (``self.what``) and saying why it ended."""
        terminated = killed = False
        if terminate and self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            terminated = True
        try:
            out, err = self.proc.communicate(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            killed = True
            out, err = self.proc.communicate()
        if self.proc.returncode != 0 or not out.strip():
            raise HandctlError(self._why_no_record(err, terminated, killed, timeout_s))
        try:
            return json.loads(out)
        except json.JSONDecodeError as exc:
            raise HandctlError(f"{self.what} wrote no record ({exc})") from None

    def _why_no_record(self, err: str, terminated: bool, killed: bool, timeout_s: float) -> str:
        """Why the helper wrote no record, as far as its exit tells. A helper handles SIGTERM
        once it has started up (``stop_on_signals``), so an exit by SIGTERM that handctl sent
        means it was stopped while it was still starting: the run it was beside ended first
        (a short run, or one stopped early), and it measured nothing. That was shown as
        "ended with exit -15: " and nothing after the colon."""
        code = self.proc.returncode
        said = " | ".join(err.strip().splitlines()[-3:])
        tail = f": {said}" if said else ""
        if killed:
            return (
                f"{self.what} wrote no record within {timeout_s:g} s of being asked to stop, "
                f"and handctl killed it (SIGKILL){tail}"
            )
        if code is not None and code < 0:
            name = signal_name(-code)
            if terminated and -code == signal.SIGTERM:
                return (
                    f"{self.what} measured nothing: handctl stopped it (SIGTERM) when what it "
                    f"was beside ended, {time.monotonic() - self.started:.1f} s after starting "
                    f"it, before it had started up{tail}"
                )
            return f"{self.what} was ended by {name}, which handctl did not send{tail}"
        if code != 0:
            return f"{self.what} ended with exit {code}" + (tail or " and wrote nothing on stderr")
        return f"{self.what} ended (exit 0) without writing its record{tail}"

    def close(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait()

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
