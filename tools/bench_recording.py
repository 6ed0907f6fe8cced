"""Cost of recording: ``python tools/bench.py recording --json``.

One lockstep run of the recipe on the simulated hand, recorded through the real writer
process, then read back:

- ``loop_cost_us_p99``: what recording adds to a tick, 99th percentile over the control ticks.
  Two runtimes of the same recipe on two simulated hands tick in turn in one event loop, A
  recorded (recorder, its bus taps, the object poses handed to it, as ``handctl run recipe
  --log`` sets it up), B not (it computes the same poses and throws them away), A first on
  even ticks and B first on odd ones. Both run the same deterministic lockstep trajectory,
  so tick k of A and tick k of B do the same work but for the recording. Two measures:

  - *direct*: the recording's own work in each of A's ticks, timed where it runs:
    ``begin_tick`` and, every tenth tick, ``poses`` (the bench times them, with the wall
    clock: ``_WALL``) and the runtime's ``record`` stage (the refill of its record and
    ``push``, thread CPU time; the runtime times it). ``loop_cost_us_p50``,
    ``loop_cost_us_mean``.
  - *paired*: the CPU time of A's whole tick minus B's (from the moment the clock hands out
    the tick to the moment the runtime waits for the next, the simulated hands' steps
    outside; B reads the wall clock where A times ``begin_tick`` and ``poses``, so that the
    difference holds none of the bench's own readings). Its mean, ``paired_cost_us_mean``
    (with its standard error), also holds what the direct measure cannot see: the taps'
    calls during the poll and the send, and the caches the recording cools for the rest of
    the tick. Its 99th percentile,
    ``paired_cost_us_p99``, is not a usable tail: tick times vary by some ±10 µs from tick
    to tick on their own, so the difference of two ticks has a wide tail even when neither
    records. ``paired_noise_us_p99`` is that tail, from one more pair run with neither
    runtime recording.

  ``loop_cost_us_p99`` is the direct 99th percentile plus what the paired mean found beyond
  the direct mean (that indirect share, taken as the same in every tick). Target <= 28
  (``loop_target_met``; the issue's "about 14-28 us on this machine").
  The two places of a pair are not alike (``_pair``): the runs alternate them, A first in
  the first run, second in the next, and the indirect share is the average of the two
  places' (``indirect_us_mean``); a single run has the places' difference in it.
  ``tick_us_p50_unrecorded`` is B's median tick, for scale: the baseline of the same run.
  The host's floor (``noise_floor``): ``floor_us_p50`` / ``_p99`` of a ``Window`` of work as
  long as the direct median, in a pair that does not record, against
  ``loop_cost_direct_us_p99`` (``loop_cost_over_floor_us_p99``, ``loop_cost_floor_ratio_p99``);
  ``loop_cost_slow_share`` and ``floor_slow_share``, the shares of interrupted ticks
  (``slow_share``); ``tick_us_p99_recorded`` / ``_unrecorded``, ``tick_p99_added_us`` and
  ``tick_p99_ratio``, A's and B's whole ticks at the 99th percentile. The ticks that carry
  poses (every ``POSE_EVERY_TICKS``-th) are a tenth of all and the dearest, so the 99th
  percentile falls among them: ``loop_cost_posed_us_p50`` is their direct median and
  ``loop_cost_unposed_us_p99`` the direct 99th percentile of the others (``--against``:
  ``against_*_posed_us_p50``, ``against_*_unposed_us_p99``).
  ``loop_cost_share_p99`` is ``loop_cost_us_p99`` over it (and ``loop_cost_share_p50`` the
  direct median over it): on a shared machine every time swells with the load of the
  moment, the recording's and the tick's alike, and the share tells a recorder that got
  dearer from a machine that got busier.
- ``writer_rtf``: recorded seconds the writer process copies out, encodes and writes per
  second it spends doing so (its own busy time during the run). Target >= 5.
- ``replay_rtf``: recorded seconds per wall second of ``handctl replay --rerun`` (reading the
  log, re-running driver, runner, estimator and supervisor, comparing). Target >= 50. Also
  reported, per tick: ``rerun_read_us_per_tick`` (the log reading alone),
  ``rerun_runtime_us_per_tick`` (the rest) and ``rerun_estimator_us_per_tick`` (the object
  estimator alone, fed the logged angles: the part of the rest a recipe with objects needs).
- ``mb_per_min``: file size per minute of run.
- ``thread_clock_us``: what one reading of the thread CPU clock costs here and now (a system
  call; microseconds on a loaded virtual machine). The direct figure holds about one: the
  runtime's reading that ends its record stage, which the runtime makes only when it
  records, a cost of recording in every real run too.

``--profile``: instead, where the recording's time goes in the running loop. One pair as
above, every call of A's recorder (``begin_tick``, the two frame taps, ``push``,
``_sweep``, ``poses``) timed with ``perf_counter_ns`` (cheap; the thread
CPU clock is a system call) and exclusive of the timed calls it makes, summed per control
tick: ``profile_<call>_us_p50`` / ``_p99`` / ``_mean``, ``profile_recorder_own_*`` their sum,
``profile_record_stage_*`` the runtime's own record stage, ``profile_refill_and_clock_*`` that
stage less ``push`` (the refill of the runtime's record and a clock reading), against
``profile_tick_recorded_*`` and ``profile_tick_unrecorded_*`` (A's and B's whole tick, thread
CPU time) and ``profile_paired_*``. ``profile_clock_*`` say what a clock reading and a timed
empty call cost in the same run. ``--writer-paused`` stops A's writer (SIGSTOP, rings large
enough for the whole run) until the pair has run: the same figures without the writer's
competition for the CPU.

``--against REV``: instead, this tree's recorder against another's, under the same load: the
same pair, both runtimes recorded, one by this tree's ``Recorder`` and bus taps, the other by
the ``Recorder`` in ``handctl/recording/recorder.py`` at git revision ``REV`` on the ``HandBus``
of ``handctl/online/bus.py`` at ``REV`` (both imported beside this tree's, so they must work
with this tree's runtime, ring layout and writer; the rest of the runtime is this tree's), this
tree's in the first place in the first pair and in the second in the next. REV is first tried
out in a short pair (``against_problem``), and one that cannot run is refused, saying why,
before anything is measured: the bus of any revision before d7981c5 lacks ``prepare_send``,
which this tree's driver calls in start-up. ``against_this_us_p50`` / ``_p99`` / ``_mean``
and ``against_reference_*`` are the direct cost of each, and ``against_tick_us_mean`` the mean
of this tree's whole tick less the reference's, tick by tick: each over the ticks of the pairs
of one order pooled, then averaged over the two orders. Two runs of the bench minutes apart on a
shared machine differ by more than a recorder's change (the unrecorded tick's median moved from
160 to 225 us between two of them); two recorders ticking in turn do not.

Each figure is the best of ``--repeat`` runs (the machine is shared). Progress goes to stderr.
The two runtimes of a pair wait for each other every tick; one that ends or stalls
(``PARTNER_WAIT_S``) while the other waits breaks the pair off, and the bench exits 1 saying
which and how it ended, instead of waiting for ever.

``--live``: instead, what the live Foxglove view adds to the tick. The same pair, both
runtimes recorded, one's writer also serving its live view to a client process subscribed
to every channel (``live_view_cost.py``'s): A's in the first pair, B's in the second, and so
on. The two tick in turn under the same load, so that ``live_added_tick_us_p99`` (the live
side's tick p99 minus the other's, CPU time) and ``live_ratio_tick_p99`` compare like with
like, which two real-time runs one after the other on a shared machine do not;
``live_paired_us_mean`` is the mean of the live side's tick minus the other's, with its
standard error. Over the ticks of all ``--repeat`` pairs pooled (each pair's own in
``*_runs``).
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import importlib.util
import os
import signal
import subprocess
import sys
import tempfile
import time
import uuid
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from handctl.config import HandConfig, load_hand  # noqa: E402
from handctl.convention import POSE_EVERY_TICKS  # noqa: E402
from handctl.errors import HandctlError  # noqa: E402
from handctl.hand_protocol import protocol_for  # noqa: E402
from handctl.online import bus as bus_module  # noqa: E402
from handctl.online.bus import open_bus  # noqa: E402
from handctl.online.clock import LockstepClock, Tick  # noqa: E402
from handctl.online.drivers.hand import HandDriver  # noqa: E402
from handctl.online.estimator import ObjectEstimator  # noqa: E402
from handctl.online.loop import RunResult, Runtime  # noqa: E402
from handctl.online.recipes.loader import load_recipe  # noqa: E402
from handctl.online.recipes.schema import Recipe  # noqa: E402
from handctl.recording import channels as ch  # noqa: E402
from handctl.recording.metadata import (  # noqa: E402
    recorded_hand,
    recorded_recipe,
    run_metadata,
    start_metadata,
)
from handctl.recording.reader import Recording, iter_decoded, open_recording  # noqa: E402
from handctl.recording.recorder import Recorder  # noqa: E402
from handctl.recording.rerun import rerun, tick_inputs  # noqa: E402
from handctl.recording.ring import RingLayout  # noqa: E402
from handctl.sim.hand import SimulatedHand  # noqa: E402

#: One line of ``bench.py --help`` (read from the source there, without importing this).
SUMMARY = "what recording costs the tick; the writer's and replay's speed, MB per minute"

LOOP_TARGET_US = 28.0
#: CPU time of the calling thread, as the runtime's own stage accounting: time the loop was
#: preempted by another process (the machine is shared) is not the recorder's cost.
_CPU = time.thread_time_ns
#: What times ``begin_tick``: the wall clock, a read of some 50 ns without a system call. The
#: thread CPU clock is a system call (``thread_clock_us``), and two of them around each
#: ``begin_tick`` were the bench's own cost, in the direct figure and in A's tick alike, not
#: the recording's; a preemption inside a microsecond's call falls on far fewer ticks than
#: the 1 % a 99th percentile looks at.
_WALL = time.perf_counter_ns
WRITER_TARGET = 5.0
REPLAY_TARGET = 50.0


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--hand", default=str(ROOT / "config" / "hands" / "hiroshima_hand.yaml"))
    parser.add_argument(
        "--recipe", default=str(ROOT / "config" / "recipes" / "swap_two_cylinders.yaml")
    )
    parser.add_argument("--repeat", type=int, default=3, help="runs per figure (default 3)")
    parser.add_argument(
        "--live",
        action="store_true",
        help="instead: the live Foxglove view's cost on the tick, both runtimes recorded, "
        "A's writer serving a client subscribed to every channel (live_*)",
    )
    parser.add_argument(
        "--profile",
        action="store_true",
        help="instead: the recorder's own calls per tick (begin_tick, the taps, push, "
        "_sweep, poses), timed in process against the whole tick (profile_*)",
    )
    parser.add_argument(
        "--writer-paused",
        action="store_true",
        help="with --profile: the writer process stopped (SIGSTOP) while the pair runs and "
        "resumed before the recorder closes (rings large enough to hold the whole run), so "
        "that the figures lack the writer's competition for the CPU",
    )
    parser.add_argument(
        "--against",
        metavar="REV",
        help="instead: this tree's recorder against git revision REV's recorder.py and bus.py "
        "(d7981c5 or later; one that cannot run beside this tree is refused), both recording "
        "in one pair (against_*)",
    )
    parser.add_argument(
        "--breakdown",
        action="store_true",
        help="also split the direct cost: one more run in which push only publishes, "
        "the tick's row left empty (breakdown_us_p50)",
    )


#: s of wall time a runtime of the pair waits at most for the other to begin a tick: each
#: waits for the other every tick, so one that stopped or hung would hold the other (and the
#: bench) for ever. A tick takes milliseconds even on a loaded host.
PARTNER_WAIT_S = 60.0


class BrokenPairError(RuntimeError):
    """A runtime of the pair stopped or stalled while the other waited for it: the pair
    cannot go on, and ``bench.py`` says why (``run``)."""


class Turns:
    """Which of the pair runs tick k first: A on even ticks, B on odd ones. The task that
    runs first after the event loop's own work pays for caches that work cooled (measured:
    the first of the pair is the slower one in the tail), so a fixed order would bias the
    difference one way."""

    def __init__(self) -> None:
        self.done: dict[int, int] = {}  # tick -> how many of the pair have begun it
        #: side -> how its runtime ended, once it has (``_run_side``)
        self.ended: dict[str, str] = {}
        #: why the pair could not go on: the first ``BrokenPairError``'s reason, or ""
        self.broken = ""

    def first(self, k: int) -> str:
        return "a" if k % 2 == 0 else "b"

    def mine(self, side: str, k: int) -> bool:
        """Whether ``side`` may begin tick ``k`` now."""
        begun = self.done.get(k, 0)
        return (side == self.first(k)) == (begun == 0)

    def begin(self, k: int) -> None:
        self.done[k] = self.done.get(k, 0) + 1
        self.done.pop(k - 2, None)

    def wait_in_vain(self, side: str, k: int, since: float) -> None:
        """Raise ``BrokenPairError`` when ``side``, waiting since ``since`` (``time.monotonic``)
        for the other to begin tick ``k``, waits in vain: the other's runtime has ended, or
        has not moved for ``PARTNER_WAIT_S``."""
        other = "b" if side == "a" else "a"
        if other in self.ended:
            why = f"{self.ended[other]}, while the other waited for it at tick {k}"
        elif time.monotonic() - since > PARTNER_WAIT_S:
            why = f"a runtime of the pair did not begin tick {k} in {PARTNER_WAIT_S:g} s"
        else:
            return
        self.broken = self.broken or why
        raise BrokenPairError(why)

    def check(self) -> None:
        """Raise ``BrokenPairError`` if the pair broke: its runs' figures would be half a pair's."""
        if self.broken:
            raise BrokenPairError(self.broken)


class TickTimer(LockstepClock):
    """The lockstep clock, with the thread's CPU time of each tick's work noted: from when it
    hands out a tick to when the runtime next waits. Two of them in one event loop take
    turns (``Turns``), since each yields to the loop once per tick."""

    def __init__(
        self, period_s: float, step_peer: Callable[[], None], side: str, turns: Turns
    ) -> None:
        super().__init__(period_s, step_peer)
        self.side = side
        self.turns = turns
        self.work_ns: list[int] = []
        self._started: int | None = None

    async def wait_tick(self) -> Tick:
        if self._started is not None:
            self.work_ns.append(_CPU() - self._started)
        tick = await super().wait_tick()
        if not self.turns.mine(self.side, tick.tick):
            since = time.monotonic()
            while not self.turns.mine(self.side, tick.tick):
                self.turns.wait_in_vain(self.side, tick.tick, since)
                await asyncio.sleep(0)
        self.turns.begin(tick.tick)
        self._started = _CPU()
        return tick


class _Side:
    """One runtime of the pair: its simulated hand, bus, clock and (for A) recorder."""

    def __init__(
        self,
        stack: contextlib.ExitStack,
        hand: HandConfig,
        recipe: Recipe,
        out: Path | None,
        turns: Turns,
        side: str,
        push: str = "all",
        live_port: int | None = None,
        layout: RingLayout | None = None,
        recorder_type: type[Recorder] = Recorder,
        open_host: Callable[..., Any] = open_bus,
        label: str = "",
    ) -> None:
        """``open_host`` opens the runtime's own bus (the simulated hand's is this tree's);
        ``label`` names the side in what the bench says of it (default: its place)."""
        self.label = label or f"the runtime in place {side.upper()}"
        channel = f"virtual:bench-rec-{uuid.uuid4().hex[:8]}"
        peer = stack.enter_context(open_bus(channel, hand.bus))
        host = stack.enter_context(open_host(channel, hand.bus))
        self.sim = sim = SimulatedHand(hand, peer)
        self.clock = TickTimer(hand.bus.period_s, sim.step, side, turns)
        driver = HandDriver(hand, protocol_for(hand), host, clock_ns=self.clock.now_ns)
        estimator = ObjectEstimator(hand, recipe.objects, recipe.pairs) if recipe.objects else None
        self.recorder: Recorder | None = None
        if out is not None:
            self.recorder = recorder_type(
                out,
                hand,
                start_metadata(hand, recipe, ["bench"]),
                phase_names=[p.name for p in recipe.phases],
                object_names=[o.name for o in sim.params.objects],
                live_port=live_port,
                layout=layout,
            )
        self.runtime = runtime = Runtime(
            hand, driver, self.clock, recipe, recorder=self.recorder, estimator=estimator
        )
        recorder = self.recorder
        #: Time of each ``begin_tick`` (the part of the recording before the tick's poll)
        self.begin_ns: list[int] = []
        #: Time of ``poses`` (the tick's object poses handed over), by tick
        self.poses_ns: dict[int, int] = {}
        begin_ns = self.begin_ns
        if recorder is None:
            # The same timing around nothing, so that the paired difference holds none of the
            # bench's own clock readings: the wrapper below is A's, not the recording's.

            def timed_nothing(tk: Tick) -> None:
                started = _WALL()
                begin_ns.append(_WALL() - started)

            runtime.tick_hooks.append(timed_nothing)
        else:
            recorder.attach(runtime)
            begin = recorder.begin_tick

            def timed_begin(tk: Tick) -> None:
                started = _WALL()
                begin(tk)
                begin_ns.append(_WALL() - started)

            recorder.begin_tick = timed_begin  # type: ignore[method-assign, assignment]
            if push != "all":
                recorder.push = _partial_push(  # type: ignore[method-assign, assignment]
                    recorder, push
                )
            recorder.add_metadata(
                ch.META_RUN,
                run_metadata(
                    mode="lockstep",
                    bus=channel,
                    seed=0,
                    period_ns=round(hand.bus.period_s * 1e9),
                    startup_ticks=runtime.startup_ticks,
                    reset_node_faults=False,
                    estimator=estimator is not None,
                ),
            )

        poses_ns = self.poses_ns

        def poses(tk: Tick) -> None:
            if tk.tick % POSE_EVERY_TICKS == 0:
                truth = [(o.x, o.y, o.angle) for o in sim.ground_truth().objects]
                started = _WALL()  # timed on both sides, as ``begin_tick`` is
                if recorder is not None:
                    recorder.poses(truth)
                poses_ns[tk.tick] = _WALL() - started

        runtime.tick_hooks.append(poses)


async def _run_side(side: _Side) -> RunResult:
    """``side``'s run, its end noted with the pair's ``Turns``: the other runtime, waiting
    for it to begin a tick it never will, then stops instead of waiting for ever."""
    turns = side.clock.turns
    try:
        result = await side.runtime.run()
    except BaseException as exc:
        turns.ended[side.clock.side] = f"{side.label} raised {exc!r}"
        raise
    turns.ended[side.clock.side] = (
        f"{side.label} ended at tick {result.ticks}: {result.outcome.value}"
        + (f" ({result.message})" if result.message else "")
    )
    return result


def _partial_push(recorder: Recorder, part: str) -> Callable[[Any], None]:
    """A ``push`` that does only part of the work, for ``--breakdown``: ``none`` only
    publishes (the tick rows stay empty; the taps still write the frames, as they go)."""
    if part != "none":
        raise ValueError(f"bench: no partial push {part!r}")

    def push(record: Any) -> None:
        recorder._publish()

    return push


def _pair(
    hand: HandConfig,
    recipe: Recipe,
    out: Path | None,
    push: str = "all",
    live_port: int | None = None,
    b_out: Path | None = None,
    instrument: Callable[[_Side], None] | None = None,
    layout: RingLayout | None = None,
    before_close: Callable[[Recorder], None] | None = None,
    swap: bool = False,
    each: Callable[[_Side], None] | None = None,
) -> tuple[_Side, _Side, RunResult, float, dict[str, Any]]:
    """Run A (recorded to ``out``, or not when ``out`` is None; served live on ``live_port``) and B
    (recorded to ``b_out``, by default not) in turn. ``instrument`` is called with A before the
    run, ``each`` with A and with B. A is the runtime made first, gathered first and first on
    even ticks; ``swap``: B is. The two places are not alike: with both runtimes doing the same,
    the first one's ticks measured some 3-5 us more CPU time than the second's (a shared
    machine, load 4-5), which a comparison in one place only would count as the cost of what A
    does."""
    with contextlib.ExitStack() as stack:
        turns = Turns()
        # The turns' "a" is the first place, whichever runtime holds it.
        if swap:
            b = _Side(stack, hand, recipe, b_out, turns, "a")
        a = _Side(stack, hand, recipe, out, turns, "b" if swap else "a", push, live_port, layout)
        if not swap:
            b = _Side(stack, hand, recipe, b_out, turns, "b")
        if instrument is not None:
            instrument(a)
        if each is not None:
            each(a)
            each(b)
        for side in (a, b):
            if side.recorder is not None:
                side.recorder.wait_ready()

        async def both() -> tuple[RunResult, RunResult]:
            if swap:
                twin, result = await asyncio.gather(_run_side(b), _run_side(a))
                return result, twin
            return await asyncio.gather(_run_side(a), _run_side(b))

        started = time.perf_counter()
        result, twin = asyncio.run(both())
        loop_wall = time.perf_counter() - started
        if before_close is not None and a.recorder is not None:
            before_close(a.recorder)
        stats = a.recorder.close({"outcome": result.outcome.value}) if a.recorder else {}
        if b.recorder is not None:
            b.recorder.close({"outcome": twin.outcome.value})
    turns.check()
    if result.ticks != twin.ticks or result.outcome != twin.outcome:
        raise RuntimeError(
            f"bench: the twin runs differ ({result.ticks} and {twin.ticks} "
            "ticks): the paired difference would compare unlike ticks"
        )
    return a, b, result, loop_wall, stats


def _paired(a: _Side, b: _Side, control: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per control tick: A's tick minus B's tick, and B's tick (ns of thread CPU time)."""
    n = min(len(a.clock.work_ns), len(b.clock.work_ns), len(control))
    work_a = np.array(a.clock.work_ns[:n])[control[:n]]
    work_b = np.array(b.clock.work_ns[:n])[control[:n]]
    return work_a - work_b, work_b


def record_once(
    hand_path: str, recipe_path: str, out: Path, push: str = "all", swap: bool = False
) -> dict[str, Any]:
    hand = load_hand(hand_path)
    recipe = load_recipe(recipe_path, hand)
    a, b, result, loop_wall, stats = _pair(hand, recipe, out, push, swap=swap)
    # Control ticks only (start-up ticks only poll): those with a stage time for the send.
    control = result.stage_ns[:, 3] > 0
    added, unrecorded = _paired(a, b, control)
    # The direct figure: the recording's own work in each control tick, timed where it runs:
    # ``begin_tick`` and ``poses`` (timed by the bench) and the runtime's record stage (the
    # refill of its record and ``push``, timed by the runtime itself). Tick k's stage row is
    # tick k.
    n = min(len(a.begin_ns), len(control))
    poses = np.array([a.poses_ns.get(k, 0) for k in range(n)])
    direct = (np.array(a.begin_ns[:n]) + poses + result.stage_ns[:n, 4])[control[:n]]
    return {
        "direct_ns": direct,
        "posed": (np.arange(n) % POSE_EVERY_TICKS == 0)[control[:n]],
        "added_ns": added,
        "unrecorded_ns": unrecorded,
        "ticks": result.ticks,
        "loop_wall_s": loop_wall,
        "stats": stats,
        "period_s": hand.bus.period_s,
    }


#: Calls of a ``Window`` in which it sets its length; the calls after them are its figures.
WINDOW_SETTLE = 3000
#: How often (calls) a settling ``Window`` sets its length again.
WINDOW_EVERY = 100
#: A tick whose recording (or window) took more than this many times its median was
#: interrupted: the share of such ticks is what a 99th percentile falls among or not.
SLOW_FACTOR = 2.0


class Window:
    """A piece of interpreted work as long (at the median) as the recording's direct cost,
    run as a tick hook of a runtime that does not record and timed as the record stage is
    (the thread CPU clock): what the host does, in the same loop, to any work of that
    length. Its length is a count of loop turns, set every ``WINDOW_EVERY`` calls so that
    their median meets ``target_ns`` (the machine's speed drifts within a run); ``ns`` is
    kept after the first ``WINDOW_SETTLE``."""

    def __init__(self, target_ns: float) -> None:
        self.target_ns = target_ns
        started = _CPU()
        for _ in range(10_000):
            pass
        self.turns = max(0, round(target_ns / max((_CPU() - started) / 10_000, 1e-3)))
        self.ns: list[int] = []
        self.every: list[int] = []  # every call's, settling ones included
        self._recent: list[int] = []
        self._calls = 0

    def kept(self) -> list[int]:
        """The figures: the calls after the settling ones, or, in a run too short to settle
        (a hold recipe of 2.5 s: the bench's percentile of nothing was a traceback), the last
        half of the calls, whose length has been set ``WINDOW_EVERY`` calls at a time."""
        return self.ns if self.ns else self.every[len(self.every) // 2 :]

    def __call__(self, tk: Tick) -> None:
        turns = self.turns
        started = _CPU()
        for _ in range(turns):
            pass
        took = _CPU() - started
        self._calls += 1
        self.every.append(took)
        if self._calls > WINDOW_SETTLE:
            self.ns.append(took)
        self._recent.append(took)
        if len(self._recent) == WINDOW_EVERY:
            median = float(np.median(self._recent))
            self.turns = max(0, round(turns * self.target_ns / max(median, 1.0)))
            self._recent.clear()


def slow_share(ns: np.ndarray) -> float:
    """The share of samples over ``SLOW_FACTOR`` times their median: the interrupted ones."""
    return float(np.mean(ns > SLOW_FACTOR * np.median(ns)))


def noise_floor(hand_path: str, recipe_path: str, window_ns: float) -> dict[str, float]:
    """The same pair with neither runtime recording, each running a ``Window`` of
    ``window_ns`` (the recording's direct median) in every tick. ``paired_noise_us_p99``: the
    paired difference's 99th percentile, what that statistic shows of the machine alone;
    ``floor_us_*``: the windows of both runtimes pooled, what a 99th percentile of work that
    long is on this host at this moment, recording or not."""
    hand = load_hand(hand_path)
    recipe = load_recipe(recipe_path, hand)
    windows: list[Window] = []

    def add_window(side: _Side) -> None:
        windows.append(Window(window_ns))
        side.runtime.tick_hooks.append(windows[-1])

    a, b, result, _, _ = _pair(hand, recipe, None, each=add_window)
    added, _ = _paired(a, b, result.stage_ns[:, 3] > 0)
    floor = np.concatenate([np.array(w.kept(), dtype=np.float64) for w in windows]) / 1e3
    if not floor.size:
        raise HandctlError(f"{recipe_path}: the recipe ran no tick to measure the noise floor in")
    return {
        "paired_noise_us_p99": float(np.percentile(added, 99)) / 1e3,
        "floor_us_p50": float(np.percentile(floor, 50)),
        "floor_us_p99": float(np.percentile(floor, 99)),
        "floor_slow_share": slow_share(floor),
    }


def estimator_us_per_tick(recording: Recording) -> float:
    """The object estimator alone, fed the logged angles once per tick as in the re-run."""
    hand = recorded_hand(recording)
    assert hand is not None
    recipe = recorded_recipe(recording, hand)
    if not recipe.objects:
        return 0.0
    angles = [np.array(m["angle_rad"]) for _, _, m in iter_decoded(recording, (ch.JOINT_STATE,))]
    estimator = ObjectEstimator(hand, recipe.objects, recipe.pairs)
    started = time.perf_counter()
    for angle in angles:
        estimator(angle)
    return 1e6 * (time.perf_counter() - started) / max(len(angles), 1)


class CallTimes:
    """The recorder's own calls, each timed with ``perf_counter_ns`` (a cheap clock; the
    thread CPU clock is a system call) and exclusive of the timed calls it makes (``push``
    calls ``_sweep``), summed per tick."""

    NAMES = ("begin_tick", "tx_tap", "rx_tap", "push", "sweep", "poses")

    def __init__(self, recorder: Recorder) -> None:
        self.recorder = recorder
        self.ticks: list[int] = []
        self.parts: list[int] = []
        self.spent: list[int] = []
        self._child = 0

    def wrap(self, name: str, call: Callable[..., Any]) -> Callable[..., Any]:
        part = self.NAMES.index(name)
        clock = time.perf_counter_ns
        recorder, ticks, parts, spent = self.recorder, self.ticks, self.parts, self.spent

        def timed(*args: Any) -> Any:
            outer = self._child
            self._child = 0
            started = clock()
            try:
                return call(*args)
            finally:
                took = clock() - started
                ticks.append(recorder._tick)
                parts.append(part)
                spent.append(took - self._child)
                self._child = outer + took

        return timed

    def install(self, runtime: Runtime) -> None:
        """Replace the recorder's methods and the bus's taps by timed ones (after ``attach``)."""
        r = self.recorder
        for name, attribute in (
            ("begin_tick", "begin_tick"),
            ("push", "push"),
            ("sweep", "_sweep"),
            ("poses", "poses"),
        ):
            bound = getattr(type(r), attribute).__get__(r)
            setattr(r, attribute, self.wrap(name, bound))
        bus = runtime.driver.bus
        bus.tap = self.wrap("tx_tap", r._sent)
        bus.rx_tap = self.wrap("rx_tap", r._drain)

    def per_tick(self, ticks: np.ndarray) -> dict[str, np.ndarray]:
        """Per component, the ns spent in each of ``ticks`` (0 where it was not called)."""
        at = {int(k): i for i, k in enumerate(ticks)}
        out = {name: np.zeros(len(ticks)) for name in self.NAMES}
        calls = {name: np.zeros(len(ticks)) for name in self.NAMES}
        for k, part, ns in zip(self.ticks, self.parts, self.spent, strict=True):
            i = at.get(k)
            if i is not None:
                out[self.NAMES[part]][i] += ns
                calls[self.NAMES[part]][i] += 1
        out.update({f"{name}_calls": c for name, c in calls.items()})
        return out


def _clock_costs() -> dict[str, float]:
    """What one reading of each clock, and one timed no-op call, cost here and now (ns,
    median of batches)."""

    def per_call(call: Callable[[], Any], n: int = 20000) -> float:
        batches = []
        for _ in range(5):
            started = time.perf_counter_ns()
            for _ in range(n):
                call()
            batches.append((time.perf_counter_ns() - started) / n)
        return float(np.median(batches))

    class _Null:
        _tick = 0

    times = CallTimes(_Null())  # type: ignore[arg-type]
    timed_noop = times.wrap("poses", lambda: None)
    return {
        "perf_counter_ns": per_call(time.perf_counter_ns),
        "thread_time_ns": per_call(time.thread_time_ns),
        "timed_noop_ns": per_call(timed_noop) - per_call(lambda: None),
    }


def profile_once(
    hand_path: str, recipe_path: str, out: Path, writer_paused: bool = False
) -> dict[str, Any]:
    """One pair as ``record_once`` runs it, A's recorder calls timed (``CallTimes``);
    ``writer_paused``: A's writer stopped until the pair has run."""
    hand = load_hand(hand_path)
    recipe = load_recipe(recipe_path, hand)
    installed: list[CallTimes] = []

    def instrument(side: _Side) -> None:
        assert side.recorder is not None
        times = CallTimes(side.recorder)
        times.install(side.runtime)
        installed.append(times)
        if writer_paused:
            side.recorder.wait_ready()
            os.kill(side.recorder.process.pid, signal.SIGSTOP)

    layout = None
    if writer_paused:  # a minute of everything: the writer copies it out afterwards
        layout = RingLayout(
            hand.n_joints,
            len(hand.fingers),
            len(recipe.objects),
            tick_capacity=1 << 16,
            frame_capacity=1 << 19,
        )
    a, b, result, _, _ = _pair(
        hand,
        recipe,
        out,
        instrument=instrument,
        layout=layout,
        before_close=(lambda side: os.kill(side.process.pid, signal.SIGCONT))
        if writer_paused
        else None,
    )
    times = installed[0]
    control = result.stage_ns[:, 3] > 0
    n = min(len(a.clock.work_ns), len(b.clock.work_ns), len(control))
    control = control[:n]
    ticks = np.flatnonzero(control)
    parts = times.per_tick(ticks)
    figures: dict[str, Any] = {"control_ticks": len(ticks)}

    def describe(name: str, ns: np.ndarray) -> None:
        us = ns / 1e3
        figures[f"{name}_us_p50"] = round(float(np.percentile(us, 50)), 2)
        figures[f"{name}_us_p99"] = round(float(np.percentile(us, 99)), 2)
        figures[f"{name}_us_mean"] = round(float(np.mean(us)), 2)

    total = np.zeros(len(ticks))
    calls = np.zeros(len(ticks))
    for name in CallTimes.NAMES:
        describe(name, parts[name])
        figures[f"{name}_calls_per_tick"] = round(float(np.mean(parts[f"{name}_calls"])), 2)
        total += parts[name]
        calls += parts[f"{name}_calls"]
    describe("recorder_own", total)
    figures["timed_calls_per_tick"] = round(float(np.mean(calls)), 2)
    stage = result.stage_ns[:n, 4][control]
    describe("record_stage", stage)
    push_inclusive = parts["push"] + parts["sweep"]
    describe("refill_and_clock", np.maximum(stage - push_inclusive, 0))
    describe("tick_recorded", np.array(a.clock.work_ns[:n])[control])
    describe("tick_unrecorded", np.array(b.clock.work_ns[:n])[control])
    describe(
        "paired", np.array(a.clock.work_ns[:n])[control] - np.array(b.clock.work_ns[:n])[control]
    )
    return figures


def run_profile(args: argparse.Namespace) -> dict[str, Any]:
    """``--profile``: ``--repeat`` pairs; each figure the median over them."""
    runs = []
    with tempfile.TemporaryDirectory(prefix="handctl-bench-") as directory:
        for i in range(args.repeat):
            runs.append(
                profile_once(
                    args.hand, args.recipe, Path(directory) / f"p{i}.mcap", args.writer_paused
                )
            )
            print(
                f"bench recording --profile: run {i + 1}/{args.repeat}: recorder's own calls "
                f"p50 {runs[-1]['recorder_own_us_p50']} us, p99 "
                f"{runs[-1]['recorder_own_us_p99']} us; tick p50 "
                f"{runs[-1]['tick_recorded_us_p50']} us",
                file=sys.stderr,
            )
    figures: dict[str, Any] = {
        f"profile_{key}": float(np.median([r[key] for r in runs])) for key in runs[0]
    }
    figures.update({f"profile_clock_{k}": round(v, 1) for k, v in _clock_costs().items()})
    return figures


def live_once(hand_path: str, recipe_path: str, directory: Path, swap: bool) -> dict[str, Any]:
    """One pair, both recorded, A served live to a client process (``live_view_cost``), in
    the pair's second place with ``swap``: per control tick, A's CPU time and B's,
    interleaved tick by tick under the same load."""
    from live_view_cost import free_port, start_client, stop_client

    hand = load_hand(hand_path)
    recipe = load_recipe(recipe_path, hand)
    port = free_port()
    client = start_client(port)
    try:
        _, _, result, _, _ = pair = _pair(
            hand,
            recipe,
            directory / "a.mcap",
            live_port=port,
            b_out=directory / "b.mcap",
            swap=swap,
        )
    finally:
        counts = stop_client(client)
    a, b = pair[0], pair[1]
    control = result.stage_ns[:, 3] > 0
    n = min(len(a.clock.work_ns), len(b.clock.work_ns), len(control))
    live = np.array(a.clock.work_ns[:n])[control[:n]] / 1e3
    recorded = np.array(b.clock.work_ns[:n])[control[:n]] / 1e3
    figures: dict[str, Any] = _live_figures(live, recorded)
    figures["live_messages_received"] = counts["messages"]
    for name in ("a", "b"):
        end = open_recording(directory / f"{name}.mcap").metadata[ch.META_END]
        side = "live" if name == "a" else "recorded"
        figures[f"{side}_dropped_ticks"] = int(end["dropped_ticks"])
        figures[f"{side}_writer_cpu_s"] = round(float(end["writer_cpu_s"]), 2)
    return figures | {"_live": live, "_recorded": recorded, "_swap": swap}


def _live_figures(live: np.ndarray, recorded: np.ndarray) -> dict[str, Any]:
    """The live side's tick CPU time against the other's (us, tick by tick alike)."""
    added = live - recorded
    figures: dict[str, Any] = {}
    for q in (50, 99):
        with_live, without = float(np.percentile(live, q)), float(np.percentile(recorded, q))
        figures[f"live_tick_us_p{q}"] = round(with_live, 2)
        figures[f"recorded_tick_us_p{q}"] = round(without, 2)
        figures[f"live_added_tick_us_p{q}"] = round(with_live - without, 2)
        figures[f"live_ratio_tick_p{q}"] = round(with_live / without, 4)
    figures["live_paired_us_mean"] = round(float(np.mean(added)), 2)
    figures["live_paired_us_sem"] = round(float(np.std(added)) / np.sqrt(len(added)), 2)
    return figures


def run_live(args: argparse.Namespace) -> dict[str, Any]:
    """``--live``: ``--repeat`` pairs, the live runtime first of the pair in the first, second
    in the next, and so on (``_pair``'s ``swap``). Each figure is taken over the ticks of the
    pairs of one order pooled (a 99th percentile of several runs' ticks, not the median of
    percentiles of a hundred-odd ticks each), then averaged over the two orders, so that
    the places' own difference cancels; each pair's own are kept in ``*_runs``."""
    runs = []
    for i in range(args.repeat):
        with tempfile.TemporaryDirectory(prefix="handctl-bench-") as directory:
            runs.append(live_once(args.hand, args.recipe, Path(directory), swap=i % 2 == 1))
        print(
            f"bench recording --live: pair {i + 1}/{args.repeat} (live runtime "
            f"{'second' if runs[-1]['_swap'] else 'first'}): tick p99 "
            f"{runs[-1]['live_tick_us_p99']} us live, {runs[-1]['recorded_tick_us_p99']} us "
            f"without; paired mean {runs[-1]['live_paired_us_mean']} +- "
            f"{runs[-1]['live_paired_us_sem']} us",
            file=sys.stderr,
        )
    by_order = [
        _live_figures(
            np.concatenate([r["_live"] for r in group]),
            np.concatenate([r["_recorded"] for r in group]),
        )
        for group in ([r for r in runs if not r["_swap"]], [r for r in runs if r["_swap"]])
        if group
    ]
    figures: dict[str, Any] = {
        key: round(float(np.mean([f[key] for f in by_order])), 4 if "ratio" in key else 2)
        for key in by_order[0]
    }
    for key in runs[0]:
        if not key.startswith("_") and key not in figures:
            figures[key] = float(np.median([r[key] for r in runs]))
    figures["live_orders"] = len(by_order)
    figures["live_added_tick_us_p99_runs"] = [r["live_added_tick_us_p99"] for r in runs]
    figures["live_paired_us_mean_runs"] = [r["live_paired_us_mean"] for r in runs]
    return figures


def _module_of(revision: str, source: str, name: str) -> Any:
    """The module ``source`` at git revision ``revision``, imported beside this tree's as
    ``name`` (its imports are this tree's modules)."""
    shown = subprocess.run(
        ["git", "-C", str(ROOT), "show", f"{revision}:{source}"],
        capture_output=True,
        text=True,
        check=False,
    )
    if shown.returncode != 0:
        raise SystemExit(
            f"bench recording --against: expected a git revision with {source}; found "
            f"{revision!r} ({shown.stderr.strip()})"
        )
    with tempfile.NamedTemporaryFile("w", suffix=".py", delete=False) as handle:
        handle.write(shown.stdout)
    try:
        spec = importlib.util.spec_from_file_location(name, handle.name)
        assert spec is not None and spec.loader is not None
        module = importlib.util.module_from_spec(spec)
        # Where this tree's module lies: a recorder's writer process is started from this tree.
        module.__file__ = str(ROOT / source)
        sys.modules[name] = module  # where its dataclasses look their module up
        spec.loader.exec_module(module)
    finally:
        os.unlink(handle.name)
    return module


def recorder_of(revision: str) -> type[Recorder]:
    """The ``Recorder`` of ``handctl/recording/recorder.py`` at git revision ``revision``."""
    recorder: type[Recorder] = _module_of(
        revision, "handctl/recording/recorder.py", "_recorder_against"
    ).Recorder
    return recorder


#: What the rest of the runtime meets of a bus module and compares by identity (the frame
#: tuple, the events and their kinds): the other revision's bus uses this tree's.
_SHARED_BUS_NAMES = ("Frame", "BusEvent", "BusEventKind")


def bus_opener_of(revision: str) -> Callable[..., Any]:
    """``open_bus`` of ``handctl/online/bus.py`` at git revision ``revision``, whose bus
    taps the frames as that revision's recorder expects (one call a frame, or a burst). The
    rest of the runtime is this tree's, and the bus hands it this tree's frames and events."""
    module = _module_of(revision, "handctl/online/bus.py", "_bus_against")
    for name in _SHARED_BUS_NAMES:
        setattr(module, name, getattr(bus_module, name))
    opener: Callable[..., Any] = module.open_bus
    return opener


def _against_pair(
    hand: HandConfig,
    recipe: Recipe,
    reference: type[Recorder],
    reference_bus: Callable[..., Any],
    directory: Path,
    swap: bool,
    revision: str,
    max_ticks: int | None = None,
) -> tuple[dict[str, _Side], dict[str, RunResult]]:
    """One pair, both recorded (to ``this.mcap`` and ``reference.mcap`` in ``directory``),
    run and closed: this tree's recorder and bus first (second with ``swap``), the
    reference's (``reference``, its bus opened by ``reference_bus``, of git revision
    ``revision``) in the other place; each run stopped after ``max_ticks`` ticks if given.
    Raises ``BrokenPairError`` when one side stopped while the other waited for it."""
    names = ["reference", "this"] if swap else ["this", "reference"]
    with contextlib.ExitStack() as stack:
        turns = Turns()
        sides: dict[str, _Side] = {}
        for place, name in zip("ab", names, strict=True):
            this = name == "this"
            sides[name] = _Side(
                stack,
                hand,
                recipe,
                directory / f"{name}.mcap",
                turns,
                place,
                recorder_type=Recorder if this else reference,
                open_host=open_bus if this else reference_bus,
                label="this tree's runtime" if this else f"the runtime with {revision}'s recorder",
            )
            if max_ticks is not None:
                sides[name].runtime.max_ticks = max_ticks
        for side in sides.values():
            assert side.recorder is not None
            side.recorder.wait_ready()

        async def both() -> list[RunResult]:
            return list(await asyncio.gather(*(_run_side(sides[name]) for name in names)))

        results = dict(zip(names, asyncio.run(both()), strict=True))
        for side in sides.values():
            assert side.recorder is not None
            side.recorder.close({})
    turns.check()
    return sides, results


def against_once(
    hand: HandConfig,
    recipe: Recipe,
    reference: type[Recorder],
    reference_bus: Callable[..., Any],
    directory: Path,
    swap: bool,
    revision: str = "REV",
) -> dict[str, dict[str, np.ndarray]]:
    """One pair (``_against_pair``). Per side and control tick: the direct cost and the
    whole tick (us)."""
    sides, results = _against_pair(
        hand, recipe, reference, reference_bus, directory, swap, revision
    )
    if results["this"].ticks != results["reference"].ticks:
        raise RuntimeError("bench: the twin runs differ: the pair would compare unlike ticks")
    out: dict[str, dict[str, np.ndarray]] = {}
    n = min(
        min(len(side.begin_ns), len(side.clock.work_ns), len(results[name].stage_ns))
        for name, side in sides.items()
    )
    for name, side in sides.items():
        result = results[name]
        control = result.stage_ns[:, 3] > 0
        poses = np.array([side.poses_ns.get(k, 0) for k in range(n)])
        direct = np.array(side.begin_ns[:n]) + poses + result.stage_ns[:n, 4]
        out[name] = {
            "direct": direct[control[:n]] / 1e3,
            "tick": np.array(side.clock.work_ns[:n])[control[:n]] / 1e3,
            "posed": (np.arange(n) % POSE_EVERY_TICKS == 0)[control[:n]],
        }
    return out


#: Ticks of the pair that tries ``--against``'s revision out before anything is measured:
#: the start-up, the enable and a few hundred recorded ticks, poses among them.
PROBE_TICKS = 400


def against_problem(
    hand: HandConfig,
    recipe: Recipe,
    reference: type[Recorder],
    reference_bus: Callable[..., Any],
    revision: str,
) -> str:
    """Why ``revision``'s recorder and bus cannot be measured beside this tree, or "".

    Only their two modules are that revision's; the runtime that calls them, the modules
    they import and the writer process that reads their rings are this tree's. A revision
    whose bus lacks what this tree's driver calls stopped its runtime at the first tick, and
    the other waited for it for ever; one that fills the rings otherwise than this tree's
    writer reads them leaves a recording unlike this tree's. So a short pair, both recorded,
    must end alike, and the two recordings must be whole, hold the same messages and re-run
    exactly (``handctl replay --rerun``)."""
    with tempfile.TemporaryDirectory(prefix="handctl-bench-") as tmp:
        try:
            _, results = _against_pair(
                hand, recipe, reference, reference_bus, Path(tmp), False, revision, PROBE_TICKS
            )
        except BrokenPairError as exc:
            return str(exc)
        except Exception as exc:
            return f"the pair raised {type(exc).__name__}: {exc}"
        ends = {name: (r.outcome.value, r.message, r.ticks) for name, r in results.items()}
        if ends["this"] != ends["reference"]:
            return f"the two runs ended unlike: this tree's {ends['this']}, {ends['reference']}"
        recordings: dict[str, Recording] = {}
        for name in results:
            try:
                recordings[name] = recording = open_recording(Path(tmp) / f"{name}.mcap")
            except Exception as exc:
                return f"the {name} recording cannot be read: {exc}"
            if not recording.complete:
                return f"the {name} recording is not whole: {recording.problem}"
        for name, recording in recordings.items():
            end = recording.metadata.get(ch.META_END, {})
            dropped = {k: v for k, v in end.items() if k.startswith("dropped_") and v != "0"}
            if dropped:
                return f"the {name} recording's writer fell behind and dropped records: {dropped}"
        # The writer's own stats close each chunk, and a chunk closes on wall time too: their
        # count is the host's, not the recorder's.
        this, ref = (
            {t: n for t, n in recordings[name].message_counts.items() if t != ch.STATS}
            for name in ("this", "reference")
        )
        unlike = sorted(t for t in this.keys() | ref.keys() if this.get(t) != ref.get(t))
        if unlike:
            return "the recordings hold different messages: " + ", ".join(
                f"{t} {this.get(t, 0)} against {ref.get(t, 0)}" for t in unlike
            )
        report = rerun(recordings["reference"])
        if not report.ok:
            return f"the reference's recording does not re-run exactly: {report.as_dict()}"
    return ""


def run_against(args: argparse.Namespace) -> dict[str, Any]:
    """``--against REV``: ``--repeat`` pairs, this tree's recorder first of the pair in the
    first, second in the next, and so on. Each figure over the ticks of the pairs of one order
    pooled, then averaged over the two orders (``run_live``'s way): the direct cost of each
    recorder (``against_this_*``, ``against_reference_*``) and the mean of this tree's whole
    tick less the reference's (``against_tick_us_mean``), tick by tick under the same load."""
    hand = load_hand(args.hand)
    recipe = load_recipe(args.recipe, hand)
    reference = recorder_of(args.against)
    reference_bus = bus_opener_of(args.against)
    print(
        f"bench recording --against {args.against}: trying it out in a pair of "
        f"{PROBE_TICKS} ticks ...",
        file=sys.stderr,
    )
    problem = against_problem(hand, recipe, reference, reference_bus, args.against)
    if problem:
        raise SystemExit(
            f"bench.py recording --against {args.against}: its recorder and bus cannot run "
            f"beside this tree: {problem}\n(--against needs a revision whose "
            "handctl/recording/recorder.py and handctl/online/bus.py work with this tree's "
            "runtime and writer; docs/recording.md says which)"
        )
    runs = []
    for i in range(args.repeat):
        with tempfile.TemporaryDirectory(prefix="handctl-bench-") as directory:
            runs.append(
                against_once(
                    hand,
                    recipe,
                    reference,
                    reference_bus,
                    Path(directory),
                    swap=i % 2 == 1,
                    revision=args.against,
                )
            )
        this, ref = runs[-1]["this"]["direct"], runs[-1]["reference"]["direct"]
        print(
            f"bench recording --against {args.against}: pair {i + 1}/{args.repeat}: direct "
            f"p50 {np.percentile(this, 50):.2f} against {np.percentile(ref, 50):.2f} us, p99 "
            f"{np.percentile(this, 99):.1f} against {np.percentile(ref, 99):.1f} us",
            file=sys.stderr,
        )
    by_order: list[dict[str, float]] = []
    for order in (0, 1):
        group = runs[order::2]
        if not group:
            continue
        pooled = {
            (name, part): np.concatenate([r[name][part] for r in group])
            for name in ("this", "reference")
            for part in ("direct", "tick", "posed")
        }
        figures: dict[str, float] = {}
        for name in ("this", "reference"):
            direct = pooled[(name, "direct")]
            for q in (50, 99):
                figures[f"against_{name}_us_p{q}"] = float(np.percentile(direct, q))
            figures[f"against_{name}_us_mean"] = float(np.mean(direct))
            posed = pooled[(name, "posed")].astype(bool)
            figures[f"against_{name}_posed_us_p50"] = float(np.percentile(direct[posed], 50))
            figures[f"against_{name}_unposed_us_p99"] = float(np.percentile(direct[~posed], 99))
        figures["against_tick_us_mean"] = float(
            np.mean(pooled[("this", "tick")] - pooled[("reference", "tick")])
        )
        by_order.append(figures)
    result: dict[str, Any] = {
        key: round(float(np.mean([f[key] for f in by_order])), 2) for key in by_order[0]
    }
    result["against"] = args.against
    result["against_orders"] = len(by_order)
    return result


def run(args: argparse.Namespace) -> dict[str, Any]:
    try:
        return _run(args)
    except BrokenPairError as exc:
        raise SystemExit(f"bench.py recording: the pair of runtimes broke off: {exc}") from None


def _run(args: argparse.Namespace) -> dict[str, Any]:
    if args.live:
        return run_live(args)
    if args.profile:
        return run_profile(args)
    if args.against:
        return run_against(args)
    loop_p99, loop_p50, loop_mean, writer, replay, sizes = [], [], [], [], [], []
    direct_p99: list[float] = []
    paired_mean, paired_sem, paired_p99, share_p99, share_p50 = [], [], [], [], []
    read_us, runtime_us, tick_p50, estimator_us = [], [], [], []
    slow, tick_p99_recorded, tick_p99_unrecorded = [], [], []
    posed_p50, unposed_p99 = [], []
    with tempfile.TemporaryDirectory(prefix="handctl-bench-") as directory:
        for i in range(args.repeat):
            out = Path(directory) / f"run{i}.mcap"
            run_ = record_once(args.hand, args.recipe, out, swap=i % 2 == 1)
            direct = run_["direct_ns"]
            added = run_["added_ns"]
            paired_mean.append(float(np.mean(added)) / 1e3)
            loop_mean.append(float(np.mean(direct)) / 1e3)
            direct_p99.append(float(np.percentile(direct, 99)) / 1e3)
            # This run's own indirect share, until the other order's runs are in.
            loop_p99.append(direct_p99[-1] + max(0.0, paired_mean[-1] - loop_mean[-1]))
            loop_p50.append(float(np.percentile(direct, 50)) / 1e3)
            paired_sem.append(float(np.std(added)) / np.sqrt(len(added)) / 1e3)
            paired_p99.append(float(np.percentile(added, 99)) / 1e3)
            tick_p50.append(float(np.percentile(run_["unrecorded_ns"], 50)) / 1e3)
            slow.append(slow_share(direct))
            posed_p50.append(float(np.percentile(direct[run_["posed"]], 50)) / 1e3)
            unposed_p99.append(float(np.percentile(direct[~run_["posed"]], 99)) / 1e3)
            tick_p99_recorded.append(float(np.percentile(run_["unrecorded_ns"] + added, 99)) / 1e3)
            tick_p99_unrecorded.append(float(np.percentile(run_["unrecorded_ns"], 99)) / 1e3)
            share_p99.append(loop_p99[-1] / tick_p50[-1])
            share_p50.append(loop_p50[-1] / tick_p50[-1])
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
            estimator_us.append(estimator_us_per_tick(recording))
            print(
                f"bench recording: run {i + 1}/{args.repeat}: loop p99 {loop_p99[-1]:.1f} us "
                f"(p50 {loop_p50[-1]:.1f}, mean {loop_mean[-1]:.1f}; paired mean "
                f"{paired_mean[-1]:.1f} +- {paired_sem[-1]:.1f}; {share_p99[-1]:.3f} of the "
                f"unrecorded tick's median {tick_p50[-1]:.1f} us), writer_rtf "
                f"{writer[-1]:.1f}, replay_rtf {replay[-1]:.1f}, {sizes[-1]:.1f} MB/min",
                file=sys.stderr,
            )
    # The indirect share (the paired mean beyond the direct mean) of the recorded runtime in
    # the pair's first place and in its second, averaged: the places' own difference cancels
    # (``_pair``). One run has one order only, and that difference in it.
    orders = [
        [paired_mean[i] - loop_mean[i] for i in range(args.repeat) if i % 2 == swapped]
        for swapped in (0, 1)
    ]
    indirect = max(0.0, float(np.mean([np.mean(o) for o in orders if o])))
    loop_p99 = [p + indirect for p in direct_p99]
    share_p99 = [p / t for p, t in zip(loop_p99, tick_p50, strict=True)]
    best = int(np.argmin(loop_p99))
    print(
        "bench recording: the same pair with neither recording, a window of work as long as "
        f"the recording's median ({loop_p50[best]:.2f} us) in every tick (the noise floor)",
        file=sys.stderr,
    )
    noise = noise_floor(args.hand, args.recipe, loop_p50[best] * 1e3)
    breakdown: dict[str, float] = {}
    if args.breakdown:
        with tempfile.TemporaryDirectory(prefix="handctl-bench-") as directory:
            print("bench recording: breakdown, push only publishing", file=sys.stderr)
            direct = record_once(args.hand, args.recipe, Path(directory) / "none.mcap", "none")[
                "direct_ns"
            ]
            publish_p50 = float(np.percentile(direct, 50)) / 1e3
        breakdown = {
            "begin_refill_publish": round(publish_p50, 2),
            "tick_row": round(loop_p50[best] - publish_p50, 2),
        }
    clocks = _clock_costs()
    return {
        **({"breakdown_us_p50": breakdown} if breakdown else {}),
        "thread_clock_us": round(clocks["thread_time_ns"] / 1e3, 2),
        "loop_cost_us_p99": round(loop_p99[best], 2),
        "loop_cost_us_p50": round(loop_p50[best], 2),
        "loop_cost_us_mean": round(loop_mean[best], 2),
        "paired_cost_us_mean": round(paired_mean[best], 2),
        "paired_cost_us_sem": round(paired_sem[best], 2),
        "paired_cost_us_p99": round(paired_p99[best], 2),
        "paired_noise_us_p99": round(noise["paired_noise_us_p99"], 2),
        "loop_cost_direct_us_p99": round(direct_p99[best], 2),
        "loop_cost_slow_share": round(slow[best], 4),
        "loop_cost_posed_us_p50": round(posed_p50[best], 2),
        "loop_cost_unposed_us_p99": round(unposed_p99[best], 2),
        "floor_us_p50": round(noise["floor_us_p50"], 2),
        "floor_us_p99": round(noise["floor_us_p99"], 2),
        "floor_slow_share": round(noise["floor_slow_share"], 4),
        "loop_cost_over_floor_us_p99": round(direct_p99[best] - noise["floor_us_p99"], 2),
        "loop_cost_floor_ratio_p99": round(direct_p99[best] / noise["floor_us_p99"], 3),
        "tick_us_p99_recorded": round(tick_p99_recorded[best], 2),
        "tick_us_p99_unrecorded": round(tick_p99_unrecorded[best], 2),
        "tick_p99_added_us": round(tick_p99_recorded[best] - tick_p99_unrecorded[best], 2),
        "tick_p99_ratio": round(tick_p99_recorded[best] / tick_p99_unrecorded[best], 4),
        "tick_us_p50_unrecorded": round(tick_p50[best], 2),
        "loop_cost_share_p99": round(share_p99[best], 4),
        "loop_cost_share_p50": round(share_p50[best], 4),
        "writer_rtf": round(max(writer), 2),
        "replay_rtf": round(max(replay), 2),
        "rerun_read_us_per_tick": round(min(read_us), 1),
        "rerun_runtime_us_per_tick": round(min(runtime_us), 1),
        "rerun_estimator_us_per_tick": round(min(estimator_us), 1),
        "mb_per_min": round(min(sizes), 2),
        "loop_cost_runs": [round(v, 2) for v in loop_p99],
        "indirect_us_mean": round(indirect, 2),
        "writer_rtf_runs": [round(v, 2) for v in writer],
        "replay_rtf_runs": [round(v, 2) for v in replay],
        "loop_target_met": min(loop_p99) <= LOOP_TARGET_US,
        "writer_target_met": max(writer) >= WRITER_TARGET,
        "replay_target_met": max(replay) >= REPLAY_TARGET,
    }
