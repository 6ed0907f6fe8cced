"""Progress of long work: a redrawn bar with rate and time left on a terminal, plain lines when
piped, and messages that do not break the bar."""

from __future__ import annotations

import io

import pytest

from handctl import progress
from handctl.progress import PLAIN_EVERY_S, Progress


class Clock:
    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


def test_terminal_bar_shows_rate_and_time_left_and_ends_its_line() -> None:
    out, clock = io.StringIO(), Clock()
    bar = Progress("phase lift", 40, stream=out, terminal=True, clock=clock)
    clock.now += 5.0
    bar.advance(10)  # 2 tasks/s, 30 left: 15 s
    text = out.getvalue()
    last = text.split("\r\x1b[2K")[-1]
    assert last == "[######..................] phase lift: 10/40 (25 %), 2/s, 0:15 left"
    assert "\n" not in text  # redrawn in place
    bar.close()
    assert out.getvalue().endswith("\r\x1b[2Kphase lift: 10/40 in 0:05\n")


def test_piped_progress_is_plain_lines_at_most_every_interval() -> None:
    out, clock = io.StringIO(), Clock()
    bar = Progress("cases", 100, stream=out, terminal=False, clock=clock)
    for _ in range(50):
        clock.now += 0.1
        bar.advance()
    clock.now += PLAIN_EVERY_S
    bar.advance()
    bar.close()
    lines = out.getvalue().splitlines()
    assert "\r" not in out.getvalue() and "\x1b" not in out.getvalue()
    assert lines[0] == "cases: 0/100 (0 %), 0/s, ? left"
    assert lines[1].startswith("cases: 51/100 (51 %), ")
    assert lines[-1] == "cases: 51/100 in 0:15"
    assert len(lines) == 3


def test_a_message_goes_above_the_bar_which_is_drawn_again() -> None:
    out, clock = io.StringIO(), Clock()
    bar = Progress("plan", 4, stream=out, terminal=True, clock=clock)
    bar.advance()
    bar.note("  seed analysis: score +1.000")
    text = out.getvalue()
    head, tail = text.rsplit("  seed analysis: score +1.000\n", 1)
    assert head.endswith("\r\x1b[2K")
    assert tail.startswith("\r\x1b[2K[") and "plan: 1/4" in tail
    bar.close()


def test_say_without_a_bar_is_a_plain_line(capsys: pytest.CaptureFixture[str]) -> None:
    progress.close_active()
    progress.say("planning on this process")
    assert capsys.readouterr().err == "planning on this process\n"
