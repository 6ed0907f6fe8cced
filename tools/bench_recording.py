"""Cost of recording: ``python tools/bench.py recording --json``.

One lockstep run of the recipe on the simulated hand, recorded through the real writer
process, then read back:

- ``loop_cost_us_p99``: what recording adds to a tick: the time spent in the recorder's calls
  (``begin_tick``, ``push``, ``note``, the frame and bus-event taps) during each tick of the
  run, 99th percentile over the control ticks. The time is the thread's CPU time, as in the
  runtime's own stage accounting (time the loop sat preempted by another process is not the
  recorder's), less the measured cost of the timer calls that wrap the recorder's. Target
  <= 20. ``loop_cost_before_send_us_p99`` is the part before the tick's command frames are
  sent (the taps only note references; the copying happens in ``push``, after the send).
- ``writer_rtf``: recorded seconds the writer process copies out, encodes and writes per
  second it spends doing so (its own busy time during the run). Target >= 5.
- ``replay_rtf``: recorded seconds per wall second of ``handctl replay --rerun`` (reading the
  log, re-running driver, runner and supervisor, comparing). Target >= 50. Also reported:
  ``rerun_read_us_per_tick`` (the log reading alone) and ``rerun_runtime_us_per_tick`` (the
  rest: the same Runtime tick as the live loop's, minus the bus).
- ``mb_per_min``: file size per minute of run.

Each figure is the best of ``--repeat`` runs (the machine is shared). Progress goes to stderr.
"""

from __future__ import annotations

import argparse
import asyncio
import os
import sys
import tempfile
import time
import uuid
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from handctl.bus import BusEvent, Frame, open_bus  # noqa: E402
from handctl.clock import LockstepClock, Tick  # noqa: E402
from handctl.config import load_hand  # noqa: E402
from handctl.drivers.hand import HandDriver  # noqa: E402
from handctl.loop import Runtime, TickRecord  # noqa: E402
from handctl.protocol import load_protocol  # noqa: E402
from handctl.recipes.loader import load_recipe  # noqa: E402
from handctl.recording import channels as ch  # noqa: E402
from handctl.recording.metadata import run_metadata, start_metadata  # noqa: E402
from handctl.recording.reader import open_recording  # noqa: E402
from handctl.recording.recorder import Recorder  # noqa: E402
from handctl.recording.replay import rerun, tick_inputs  # noqa: E402
from handctl.sim.hand import SimulatedHand  # noqa: E402

LOOP_TARGET_US = 20.0
#: CPU time of the calling thread, as the runtime's own stage accounting: time the loop was
#: preempted by another process (the machine is shared) is not the recorder's cost.
_CPU = time.thread_time_ns
WRITER_TARGET = 5.0
REPLAY_TARGET = 50.0


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--hand", default=str(ROOT / "config" / "hands" / "hiroshima_hand.yaml"))
    parser.add_argument("--recipe",
                        default=str(ROOT / "config" / "recipes" / "swap_two_cylinders.yaml"))
    parser.add_argument("--repeat", type=int, default=3, help="runs per figure (default 3)")


class TimedRecorder(Recorder):
    """The recorder with a stopwatch around every call the loop makes into it."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.spent = 0
        self.calls = 0
        self.in_push = 0
        self.per_tick: list[tuple[int, int, int]] = []  # (ns spent, calls, ns in push)
        self.empty: list[int] = []  # ns an empty timed call took, per tick
        self.active: list[bool] = []

    def attach(self, runtime: Runtime) -> None:
        super().attach(runtime)
        bus = runtime.driver.bus
        frame, rx, event = bus.tap, bus.rx_tap, bus.event_tap
        assert frame is not None and rx is not None and event is not None
        clock = _CPU

        def timed_frame(frame_id: int, data: bytes, direction: int) -> None:
            t0 = clock()
            frame(frame_id, data, direction)
            self.spent += clock() - t0
            self.calls += 1

        def timed_rx(frames: list[Frame]) -> None:
            t0 = clock()
            rx(frames)
            self.spent += clock() - t0
            self.calls += 1

        def timed_event(ev: BusEvent) -> None:
            t0 = clock()
            event(ev)
            self.spent += clock() - t0
            self.calls += 1

        bus.tap, bus.rx_tap, bus.event_tap = timed_frame, timed_rx, timed_event

    def begin_tick(self, tick: Tick) -> None:
        self.per_tick.append((self.spent, self.calls, self.in_push))
        self.active.append(False)
        self.spent = self.calls = self.in_push = 0
        # The stopwatch's own cost where it runs (caches as cold as the recorder's): an empty
        # call timed the same way, once per tick.
        t0 = _CPU()
        _empty()
        self.empty.append(_CPU() - t0)
        t0 = _CPU()
        super().begin_tick(tick)
        self.spent += _CPU() - t0
        self.calls += 1

    def push(self, record: TickRecord) -> None:
        t0 = _CPU()
        super().push(record)
        spent = _CPU() - t0
        self.spent += spent
        self.in_push += spent
        self.calls += 1
        self.active[-1] = True

    def note(self, kind: str, detail: str, tick: int) -> None:
        t0 = _CPU()
        super().note(kind, detail, tick)
        self.spent += _CPU() - t0
        self.calls += 1


def _empty() -> None:
    return None


def timer_overhead_ns() -> float:
    """What one stopwatch pair around an empty call costs, warm: the least the stopwatch
    costs (in the run it is measured again once per tick, and the larger is subtracted)."""
    clock = _CPU

    def empty() -> None:
        return None

    best = float("inf")
    for _ in range(5):
        spent = 0
        for _ in range(20_000):
            t0 = clock()
            empty()
            spent += clock() - t0
        best = min(best, spent / 20_000)
    return best


def record_once(hand_path: str, recipe_path: str, out: Path) -> dict[str, Any]:
    hand = load_hand(hand_path)
    recipe = load_recipe(recipe_path, hand)
    channel = f"virtual:bench-rec-{uuid.uuid4().hex[:8]}"
    with open_bus(channel, hand.bus) as peer, open_bus(channel, hand.bus) as host:
        sim = SimulatedHand(hand, peer)
        clock = LockstepClock(hand.bus.period_s, sim.step)
        driver = HandDriver(hand, load_protocol(), host, clock_ns=clock.now_ns)
        recorder = TimedRecorder(out, hand, start_metadata(hand, recipe, ["bench"]),
                                 phase_names=[p.name for p in recipe.phases],
                                 object_names=[o.name for o in sim.params.objects])
        runtime = Runtime(hand, driver, clock, recipe, recorder=recorder)
        recorder.attach(runtime)
        recorder.add_metadata(ch.META_RUN, run_metadata(
            mode="lockstep", bus=channel, seed=0, period_ns=round(hand.bus.period_s * 1e9),
            startup_ticks=runtime.startup_ticks, reset_node_faults=False, estimator=False))

        def poses(tk: Tick) -> None:
            if tk.k % 10 == 0:
                recorder.poses([(o.x, o.y, o.angle) for o in sim.ground_truth().objects])

        runtime.tick_hooks.append(poses)
        recorder.wait_ready()
        started = time.perf_counter()
        result = asyncio.run(runtime.run())
        loop_wall = time.perf_counter() - started
        recorder.per_tick.append((recorder.spent, recorder.calls, recorder.in_push))
        stats = recorder.close({"outcome": result.outcome.value})
    per_tick = recorder.per_tick[1:]
    active = [pt for pt, on in zip(per_tick, recorder.active, strict=True) if on]
    return {"per_tick": active, "ticks": result.ticks, "loop_wall_s": loop_wall,
            "timer_ns": float(np.median(recorder.empty)),
            "stats": stats, "period_s": hand.bus.period_s}


def run(args: argparse.Namespace) -> dict[str, Any]:
    overhead = timer_overhead_ns()
    loop_p99, loop_p50, writer, replay, sizes = [], [], [], [], []
    read_us, runtime_us, timers, before_p99 = [], [], [], []
    with tempfile.TemporaryDirectory(prefix="handctl-bench-") as directory:
        for i in range(args.repeat):
            out = Path(directory) / f"run{i}.mcap"
            run_ = record_once(args.hand, args.recipe, out)
            timer = max(overhead, run_["timer_ns"])
            timers.append(timer)
            spent = np.array([ns - calls * timer for ns, calls, _ in run_["per_tick"]])
            before = np.array([ns - push - (calls - 1) * timer
                               for ns, calls, push in run_["per_tick"]])
            before_p99.append(float(np.percentile(before, 99)) / 1e3)
            loop_p99.append(float(np.percentile(spent, 99)) / 1e3)
            loop_p50.append(float(np.percentile(spent, 50)) / 1e3)
            recording = open_recording(out)
            end = recording.metadata[ch.META_END]
            recorded_s = run_["ticks"] * run_["period_s"]
            writer.append(recorded_s / max(float(end["writer_busy_s"]), 1e-9))
            sizes.append(os.path.getsize(out) / 1e6 / (recorded_s / 60.0))
            started = time.perf_counter()
            _, inputs = tick_inputs(recording)
            n = sum(1 for _ in inputs)
            read = time.perf_counter() - started
            started = time.perf_counter()
            report = rerun(recording)
            wall = time.perf_counter() - started
            if not report.ok:
                raise RuntimeError(f"bench: the re-run does not match: {report.as_dict()}")
            replay.append(recorded_s / wall)
            read_us.append(1e6 * read / max(n, 1))
            runtime_us.append(1e6 * (wall - read) / max(n, 1))
            print(f"bench recording: run {i + 1}/{args.repeat}: loop p99 {loop_p99[-1]:.1f} us, "
                  f"writer_rtf {writer[-1]:.1f}, replay_rtf {replay[-1]:.1f}, "
                  f"{sizes[-1]:.1f} MB/min", file=sys.stderr)
    return {
        "loop_cost_us_p99": round(min(loop_p99), 2),
        "loop_cost_us_p50": round(min(loop_p50), 2),
        "loop_cost_before_send_us_p99": round(min(before_p99), 2),
        "timer_overhead_us_per_call": round(min(timers) / 1e3, 3),
        "writer_rtf": round(max(writer), 2),
        "replay_rtf": round(max(replay), 2),
        "rerun_read_us_per_tick": round(min(read_us), 1),
        "rerun_runtime_us_per_tick": round(min(runtime_us), 1),
        "mb_per_min": round(min(sizes), 2),
        "loop_cost_runs": [round(v, 2) for v in loop_p99],
        "writer_rtf_runs": [round(v, 2) for v in writer],
        "replay_rtf_runs": [round(v, 2) for v in replay],
        "loop_target_met": min(loop_p99) <= LOOP_TARGET_US,
        "writer_target_met": max(writer) >= WRITER_TARGET,
        "replay_target_met": max(replay) >= REPLAY_TARGET,
    }
