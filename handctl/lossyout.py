"""Output written from inside a tick: a line the terminal or pipe cannot take now is dropped.

A blocking write inside the control loop stops the loop, and with it every command: the
torque last sent stays on until each node's watchdog latches TIMEOUT. A terminal stopped
with Ctrl-S (XOFF), an SSH session that stalls, or a pipe into a pager left at its prompt
(``handctl jog ... | less``) each block a plain ``print`` for as long as they last, and
a stop signal cannot end the run meanwhile: Python retries the interrupted write after the
handler. The live status line and jog's table are a view of what the log keeps in full, so
a line is worth less than a tick: it goes out only when the descriptor can take it at once
(``poll`` for ``POLLOUT`` with no timeout), and is counted as dropped otherwise.

Why ``poll`` and not a non-blocking descriptor: ``O_NONBLOCK`` is a flag of the open file
description, which the shell and every other process on the terminal share; a run killed
before it restored the flag would leave the user's shell with a terminal that fails its
reads. Why not a thread: a writer thread at the ordinary priority that holds the GIL when
it is preempted would hold up a SCHED_FIFO loop thread waiting for it.
"""

from __future__ import annotations

import io
import select
from typing import IO

#: What says the descriptor can be written, or that writing it will fail at once (a reader
#: gone, a closed descriptor): the stream's own error handling then takes over.
_WRITABLE = select.POLLOUT | select.POLLERR | select.POLLHUP | select.POLLNVAL


class LossyOut:
    """``stream`` for lines that are dropped rather than waited for.

    Each line is whole and small (a status line, a table row): a pipe that polls writable
    has a page free and a terminal has room for a line, so the write that follows does not
    block. A stream with no descriptor (a test's capture, an in-memory buffer) cannot block
    and is written as it is.
    """

    def __init__(self, stream: IO[str]) -> None:
        self.stream = stream
        self.written = 0
        self.dropped = 0
        self._poll: select.poll | None = None
        try:
            fd = stream.fileno()
        except (OSError, ValueError, io.UnsupportedOperation):
            return
        poll = select.poll()
        poll.register(fd, select.POLLOUT)
        self._poll = poll

    def ready(self) -> bool:
        """Whether a line written now would go out without waiting."""
        if self._poll is None:
            return True
        try:
            events = self._poll.poll(0)
        except OSError:  # EINTR is retried by Python; anything else: let the write say it
            return True
        return any(mask & _WRITABLE for _, mask in events)

    def write(self, text: str) -> bool:
        """``text`` written and flushed if the stream can take it now; False if dropped."""
        if not self.ready():
            self.dropped += 1
            return False
        self.stream.write(text)
        self.stream.flush()
        self.written += 1
        return True
