"""Output written from inside a tick: a line the terminal or pipe cannot take now is dropped.

A blocking write inside the control loop stops the loop, and with it every command: the
torque last sent stays on until each node's watchdog latches TIMEOUT. A terminal stopped
with Ctrl-S (XOFF), an SSH session that stalls, or a pipe into a pager left at its prompt
(``handctl jog ... | less``) each block a plain ``print`` for as long as they last, and
a stop signal cannot end the run meanwhile: Python retries the interrupted write after the
handler. The live status line and jog's table are a view of what the log keeps in full, so
a line is worth less than a tick: what the terminal or pipe cannot take at once is dropped,
and counted.

How: a terminal or a pipe is opened again, through ``/proc/self/fd``, as an open file
description of this object's own, non-blocking. Not ``O_NONBLOCK`` on the stream's own
descriptor: that flag belongs to the open file description, which the shell and every other
process on the terminal share, and a run killed before it restored the flag would leave the
user's shell with a terminal that fails its reads. Not ``poll`` before a plain write: a
terminal polls writable with any room at all, and a line longer than the room (a newline is
two characters on a terminal) blocked the write all the same (found by an outside audit:
jog's table on a terminal whose reader stalled). Not a thread: a writer thread at the
ordinary priority, preempted while it holds the GIL, would hold up a SCHED_FIFO loop.

A socket (stdout under a service manager's journal, a socketpair a supervisor hands out)
cannot be opened again; it is sent to with ``MSG_DONTWAIT``, a flag of the call alone. A
terminal or pipe that cannot be opened again (another user's: ``sudo -u robot handctl jog
... | less``, a system without ``/proc``) has no way to be written without waiting: then
nothing is written, and ``off`` says why, for the command to say before its loop begins
(writing blocking there was the failure this module exists for: found by an outside audit).

A line the descriptor took in part is finished before any other (the next call, or
``finish``), so a line is never cut by another; while part of one waits, new lines are
dropped. Anything else (a regular file, a device such as /dev/null, a test's capture) is
written through the stream as it is: it takes a line at once, and a capture cannot block.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import os
import socket
import stat
from typing import IO

#: errnos of a reader gone for good (a closed pipe, a hung-up terminal, a socket reset):
#: nothing more is written, and nothing is said (a reader leaving is normal; the stream's
#: own wrapper says the rest at the end)
_GONE = (errno.EPIPE, errno.EIO, errno.ENXIO, errno.ECONNRESET, errno.ENOTCONN)


class LossyOut:
    """``stream`` for lines that are dropped rather than waited for. Call ``finish`` once
    the lines are done, before anything else is written to the stream."""

    def __init__(self, stream: IO[str]) -> None:
        self.stream = stream
        self.written = 0
        self.dropped = 0
        self.encoding = str(getattr(stream, "encoding", None) or "utf-8")
        self._fd = -1  # this object's own non-blocking description, if it has one
        self._sock: socket.socket | None = None  # a socket, sent to without waiting
        self._pending = b""  # the part of a line the descriptor has not taken yet
        self._gone = False
        #: why nothing is written at all, if so (no way to write without waiting); "" if not
        self.off = ""
        try:
            fd = stream.fileno()
            mode = os.fstat(fd).st_mode
        except (OSError, ValueError, AttributeError):
            return  # no descriptor: an in-memory stream, which cannot block
        terminal = stat.S_ISCHR(mode) and os.isatty(fd)
        if not (stat.S_ISSOCK(mode) or stat.S_ISFIFO(mode) or terminal):
            return
        with contextlib.suppress(OSError):
            stream.flush()  # what was printed before goes first
        if stat.S_ISSOCK(mode):
            try:
                self._sock = socket.socket(fileno=os.dup(fd))
            except OSError as exc:
                self.off = f"a socket this process cannot send to ({exc.strerror or exc})"
            return
        kind = "a terminal" if terminal else "a pipe"
        try:
            self._fd = os.open(
                f"/proc/self/fd/{fd}", os.O_WRONLY | os.O_NONBLOCK | os.O_NOCTTY | os.O_CLOEXEC
            )
        except OSError as exc:
            if exc.errno == errno.ENXIO:  # a pipe whose reader is gone: nothing to wait for
                self._gone = True
            else:
                self.off = (
                    f"{kind} this process cannot open again to write without waiting "
                    f"({exc.strerror or exc}: another user's, or no /proc)"
                )

    def write(self, text: str) -> bool:
        """``text`` (one line, or a status line) written now if the descriptor takes it
        whole or in part; False if it was dropped."""
        if self._gone or self.off:
            self.dropped += 1
            return False
        if self._fd < 0 and self._sock is None:
            self.stream.write(text)
            self.stream.flush()
            self.written += 1
            return True
        if self._pending and not self._push():
            self.dropped += 1  # a line is still going out: this one is not waited for
            return False
        data = text.encode(self.encoding, "backslashreplace")
        self._pending = data
        self._push()
        if self._gone or self._pending == data:  # none of it went: dropped whole
            self._pending = b""
            self.dropped += 1
            return False
        self.written += 1
        return True

    @property
    def gone(self) -> bool:
        """Whether the reader has gone for good (a closed pipe, a hung-up terminal): what
        was dropped since is not for want of room, and a reader leaving is not said."""
        return self._gone

    def _push(self) -> bool:
        """Write what is pending without waiting; whether all of it went."""
        while self._pending:
            try:
                if self._sock is not None:
                    n = self._sock.send(self._pending, socket.MSG_DONTWAIT)
                else:
                    n = os.write(self._fd, self._pending)
            except BlockingIOError:
                return False
            except InterruptedError:
                continue
            except OSError as exc:
                if exc.errno in _GONE:
                    self._gone = True
                    self._pending = b""
                    return False
                raise
            self._pending = self._pending[n:]
        return True

    def finish(self) -> None:
        """The part of a line still pending written out, waiting for it now (the loop has
        ended), and this object's descriptor closed: what is written after goes through the
        stream in order."""
        if self._sock is not None:
            with contextlib.suppress(OSError):
                if self._pending and not self._gone:
                    self._sock.sendall(self._pending)  # blocking: the loop has ended
            self._pending = b""
            self._sock.close()
            self._sock = None
            return
        if self._fd < 0:
            return
        try:
            if self._pending and not self._gone:
                flags = fcntl.fcntl(self._fd, fcntl.F_GETFL)
                fcntl.fcntl(self._fd, fcntl.F_SETFL, flags & ~os.O_NONBLOCK)  # ours alone
                with contextlib.suppress(OSError):
                    while self._pending:
                        self._pending = self._pending[os.write(self._fd, self._pending) :]
        finally:
            self._pending = b""
            os.close(self._fd)
            self._fd = -1
