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
    # closed short of its total: cancelled or failed, not a phase done
    assert out.getvalue().endswith("\r\x1b[2Kphase lift: stopped at 10/40 after 0:05\n")


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
    assert lines[-1] == "cases: stopped at 51/100 after 0:15"
    assert len(lines) == 3


def test_a_stall_is_shown_every_interval_and_says_how_long() -> None:
    """A plan whose worker was paused wrote nothing for forty seconds when piped, and its
    last line said "0:04 left" all that time (found by an outside audit): the pool's wait
    ticks the progress, which says for how long nothing has ended."""
    out, clock = io.StringIO(), Clock()
    bar = Progress("phase envelop", 4, stream=out, terminal=False, clock=clock)
    clock.now += 1.0
    bar.advance()
    for _ in range(20):  # the pool's idle checks, every 2 s, for 40 s
        clock.now += 2.0
        bar.tick()
    clock.now += 1.0
    bar.advance(3)
    bar.close()
    lines = out.getvalue().splitlines()
    stalled = [line for line in lines if "none done for" in line]
    assert len(stalled) == 4, lines  # at 10, 20, 30 and 40 s with nothing done
    assert stalled[0].startswith("phase envelop: 1/4 (25 %), ")
    assert stalled[-1].endswith(", none done for 0:40")
    assert lines[-1] == "phase envelop: 4/4 in 0:42"


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
