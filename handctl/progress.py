"""Progress of long offline work (a plan, a bench, the fault campaign) on stderr.

On a terminal a single line is redrawn in place: a bar, done/total, the rate and the time
left. Piped (a CI log, ``2> file``), redrawing would fill the log with carriage returns, so a
plain line is written when the work starts, at most every ``PLAIN_EVERY_S`` while it runs and
when it ends. Progress never goes to stdout: the commands that print JSON keep stdout to that.

The clock is injectable so that the text is testable without waiting.
"""

from __future__ import annotations

import math
import sys
import time
from collections.abc import Callable
from typing import TextIO

#: s, between plain progress lines when stderr is not a terminal
PLAIN_EVERY_S = 10.0
#: s, between redraws of the bar on a terminal (a redraw per task would cost more than it shows)
REDRAW_EVERY_S = 0.1
#: characters of the bar itself
BAR_WIDTH = 24


def _duration(seconds: float) -> str:
    if not math.isfinite(seconds):
        return "?"
    whole = round(seconds)
    hours, rest = divmod(whole, 3600)
    minutes, secs = divmod(rest, 60)
    return f"{hours}:{minutes:02d}:{secs:02d}" if hours else f"{minutes}:{secs:02d}"


class Progress:
    """Counts finished tasks out of ``total`` and shows it; ``close`` ends the line."""

    def __init__(
        self,
        label: str,
        total: int,
        *,
        stream: TextIO | None = None,
        terminal: bool | None = None,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.label = label
        self.total = max(0, total)
        self.done = 0
        self._stream = stream if stream is not None else sys.stderr
        self._terminal = (
            terminal
            if terminal is not None
            else bool(getattr(self._stream, "isatty", lambda: False)())
        )
        self._clock = clock
        self._start = clock()
        self._last_done = self._start  # when a task last ended (or the work began)
        self._shown = -math.inf
        self._closed = False
        _active[:] = [self]
        self._show(force=True)

    @property
    def rate(self) -> float:
        """Tasks per second since the start (0 before the first one ends)."""
        elapsed = self._clock() - self._start
        return self.done / elapsed if elapsed > 0 and self.done else 0.0

    def line(self) -> str:
        """What the progress says now, without the bar (a plain line); when no task has
        ended for ``PLAIN_EVERY_S`` or more, for how long (a stalled worker, a cluster with
        none: "0:04 left" stood for half a minute, and read as nearly done)."""
        rate = self.rate
        left = (self.total - self.done) / rate if rate > 0 else math.inf
        share = 100 * self.done / self.total if self.total else 100.0
        waiting = self._clock() - self._last_done
        stalled = f", none done for {_duration(waiting)}" if waiting >= PLAIN_EVERY_S else ""
        return (
            f"{self.label}: {self.done}/{self.total} ({share:.0f} %), {rate:.3g}/s, "
            f"{_duration(left)} left{stalled}"
        )

    def advance(self, count: int = 1) -> None:
        self.done = min(self.total, self.done + count)
        self._last_done = self._clock()
        self._show(force=self.done == self.total)

    def tick(self) -> None:
        """Show the progress again if it is due, though no task ended: the work waits on
        something (a plain line was written only when a task ended, and a stall of forty
        seconds wrote nothing)."""
        self._show()

    def close(self) -> None:
        """End the progress (also when the work was cancelled: the line says how far it got)."""
        if self._closed:
            return
        self._closed = True
        if _active == [self]:
            _active.clear()
        elapsed = self._clock() - self._start
        end = (
            f"{self.label}: {self.done}/{self.total} in {_duration(elapsed)}"
            if self.done == self.total
            # cancelled or failed: "15/72 in 0:03" read as a phase finished
            else f"{self.label}: stopped at {self.done}/{self.total} after {_duration(elapsed)}"
        )
        if self._terminal:
            self._stream.write("\r\x1b[2K" + end + "\n")
        else:
            self._stream.write(end + "\n")
        self._stream.flush()

    def note(self, text: str) -> None:
        """A line of text while the bar is shown: above it on a terminal."""
        if self._terminal and not self._closed:
            self._stream.write("\r\x1b[2K" + text + "\n")
            self._shown = -math.inf
            self._show(force=True)
        else:
            self._stream.write(text + "\n")
            self._stream.flush()

    def _show(self, force: bool = False) -> None:
        now = self._clock()
        every = REDRAW_EVERY_S if self._terminal else PLAIN_EVERY_S
        if self._closed or (not force and now - self._shown < every):
            return
        self._shown = now
        if self._terminal:
            filled = BAR_WIDTH * self.done // self.total if self.total else BAR_WIDTH
            bar = "#" * filled + "." * (BAR_WIDTH - filled)
            self._stream.write(f"\r\x1b[2K[{bar}] {self.line()}")
        elif self.done < self.total or self.done == 0:
            self._stream.write(self.line() + "\n")
        self._stream.flush()

    def __enter__(self) -> Progress:
        return self

    def __exit__(self, *_exc: object) -> None:
        self.close()


#: the bar being shown (at most one: stderr has one last line)
_active: list[Progress] = []


def say(text: str) -> None:
    """Print a line of text on stderr without breaking the progress bar being shown."""
    if _active:
        _active[0].note(text)
    else:
        sys.stderr.write(text + "\n")
        sys.stderr.flush()


def close_active() -> None:
    """End the bar being shown, if any (work cancelled half-way leaves none half-drawn)."""
    if _active:
        _active[0].close()
