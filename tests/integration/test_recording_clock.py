"""One time base in a recording: the frames drained before the first tick (what queued on
the bus before the run listened, discarded at start-up) are stamped on the ticks' clock, so
that an export puts every frame on one timeline from the run's wall-clock start."""

from __future__ import annotations

import time
from pathlib import Path

import can

from handctl.recording import channels as ch
from handctl.recording.reader import iter_decoded, open_recording

from ..conftest import DEFAULT_RECIPE, handctl
from .realtime import REALTIME
from .rig import sim_on_unix_bus


@REALTIME
def test_frames_before_the_first_tick_share_the_ticks_time_base(tmp_path: Path) -> None:
    """A run against a simulated hand that was already talking on a unix bus (``handctl
    sim``): the frames that queued before tick 0 had log time 0 beside CLOCK_MONOTONIC ticks,
    and the candump export put them at the wall-clock start and every later frame the host's
    uptime after it. The run may end in a safety stop on a loaded machine; its log is what is
    looked at."""
    bus = tmp_path / "bus"
    with sim_on_unix_bus(bus):
        log = tmp_path / "run.mcap"
        began = time.monotonic_ns()
        run = handctl(
            "run",
            "recipe",
            DEFAULT_RECIPE,
            "--bus",
            f"unix:{bus}",
            "--accept-missed-deadlines",
            "--max-seconds",
            "0.5",
            "--log",
            str(log),
        )
        ran_ns = time.monotonic_ns() - began
        finished_s = time.time()
    assert run.returncode in (0, 3), run.stdout + run.stderr
    recording = open_recording(log)
    frames = [(m["tick"], t) for _, t, m in iter_decoded(recording, (ch.CAN_RX, ch.CAN_TX))]
    before = [t for tick, t in frames if tick < 0]
    assert before, "no frame queued before the first tick: nothing to look at"
    first_tick = next(t for tick, t in frames if tick >= 0)
    # One clock: the start-up's drain comes before tick 0, by no more than the run took.
    assert 0 <= first_tick - max(before) <= ran_ns
    assert [t for _, t in frames] == sorted(t for _, t in frames)

    dump = tmp_path / "frames.log"
    done = handctl("replay", str(log), "--export", "candump", str(dump))
    assert done.returncode == 0, done.stdout + done.stderr
    stamps = [m.timestamp for m in can.CanutilsLogReader(str(dump))]
    assert len(stamps) == len(frames)
    started_s = int(recording.meta("handctl.command", "started_unix_ns")) * 1e-9
    assert stamps == sorted(stamps)
    # From the run's wall-clock start to no later than it ended (candump keeps microseconds).
    assert started_s - 1e-6 <= stamps[0] and stamps[-1] <= finished_s + 1e-6
