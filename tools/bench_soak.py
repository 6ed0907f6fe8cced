"""Soak: the real-time loop with the simulated hand and recording, for minutes on end.

The run is what ``handctl run recipe --realtime --log RUN.mcap`` does: the simulated hand in a
process of its own on the unix datagram bus, the loop ticked by a timerfd, every tick recorded
to MCAP by the writer process. The recipe closes the hand and holds it for the whole soak.

Figures (targets from the fault, load and soak issue):

- ``missed_rate``: ticks missed per tick of the run proper (from the first command on; before
  it the peer is still importing MuJoCo on the same cores), target <= 0.001;
- ``rss_growth_mb_per_hour``: the control process's resident memory, sampled once a second
  from inside the loop's status callback, least-squares slope after the warm-up, target <= 5;
- ``records_lost``: what the recorder and writer counted as dropped, plus ticks the runtime ran
  that the file lacks (``/loop/timing`` read back and compared tick by tick), target 0;
- ``ticks``, ``mb_written``, lateness (whole run), and the RSS at start and end;
- ``missed_host``, ``missed_host_slow_cpu``, ``missed_rival``, ``missed_host_catch_up``,
  ``missed_host_off_cpu`` and ``missed_handctl``: the missed ticks of the run proper, the
  host's (the bare timer loop beside the run stalled, or its CPU was slow, at the same time), a
  real-time rival's, the host's catch-up ticks' (right after its miss, the tick between at its
  usual CPU time, or begun too late for a usual tick to meet the deadline), the host's with
  the loop's thread held off its CPU (``handctl.online.misstrace``), or handctl's (none of
  these), and
  the bare loop's own figures (``host_*``), as in ``bench.py loop``. Target: ``missed_handctl`` 0.

With ``--rt`` the simulated hand's process gets SCHED_FIFO too (just below the loop): on a
machine shared with other jobs it would otherwise fall behind real time, and the host would
stop the hand for late feedback, rightly, which is the neighbours' doing, not the loop's.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from handctl.config import load_hand  # noqa: E402
from handctl.online.loop import Outcome, StatusLine  # noqa: E402
from handctl.online.recipes.loader import load_recipe  # noqa: E402
from handctl.recording import channels as ch  # noqa: E402
from handctl.recording.reader import iter_decoded, open_recording  # noqa: E402
from handctl.session import RunRequest, run_recipe  # noqa: E402
from handctl.summary_guard import require_whole  # noqa: E402

sys.path.insert(0, str(ROOT / "tools"))
from bench_loop import RunningSince, host_figures  # noqa: E402
from hold_recipe import hold_recipe  # noqa: E402

#: One line of ``bench.py --help`` (read from the source there, without importing this).
SUMMARY = "the real-time loop with the simulated hand and recording, for minutes on end"

MISSED_TARGET = 0.001
RSS_TARGET_MB_PER_HOUR = 5.0
#: SCHED_FIFO priority of the simulated hand with ``--rt``: just below the loop's (80).
PEER_PRIORITY = 79
#: Seconds between RSS samples.
SAMPLE_S = 1.0
_PAGE = os.sysconf("SC_PAGE_SIZE")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--minutes",
        type=float,
        default=10.0,
        help="length of the soak (fractions allowed: 0.5 for a quick check)",
    )
    parser.add_argument(
        "--warmup-s",
        type=float,
        default=None,
        help="seconds of the run proper left out of the RSS slope (default: "
        "a fifth of the soak, at most 60)",
    )
    parser.add_argument("--hand", type=Path, default=ROOT / "config/hands/hiroshima_hand.yaml")
    parser.add_argument(
        "--log",
        type=Path,
        default=None,
        help="keep the recording here (default: a temporary file, removed)",
    )
    parser.add_argument(
        "--rt",
        action="store_true",
        help="ask for SCHED_FIFO and locked memory, as `handctl run --rt`, "
        "and SCHED_FIFO one step lower for the simulated hand's process",
    )


def _children() -> list[int]:
    pids: list[int] = []
    for task in Path("/proc/self/task").iterdir():
        try:
            pids += [int(p) for p in (task / "children").read_text().split()]
        except OSError:
            continue
    return pids


def prioritise_peer(priority: int) -> str:
    """Give the simulated hand's process (``handctl sim``, a child of this one) SCHED_FIFO.

    On the robot the finger nodes are microcontrollers of their own; on one shared machine
    the simulated hand must not be starved by unrelated jobs either, or the soak measures the
    neighbours (its feedback comes late and the host stops the hand, rightly). Returns what
    was refused, or "".
    """
    for pid in _children():
        try:
            argv = Path(f"/proc/{pid}/cmdline").read_bytes().split(b"\0")
        except OSError:
            continue
        if b"handctl" in argv and b"sim" in argv:
            try:  # every thread of it: the policy is per thread
                for task in Path(f"/proc/{pid}/task").iterdir():
                    os.sched_setscheduler(int(task.name), os.SCHED_FIFO, os.sched_param(priority))
            except OSError as exc:
                return f"SCHED_FIFO for the simulated hand refused ({exc})"
            return ""
    return "the simulated hand's process was not found"


def _rss_bytes() -> int:
    with open("/proc/self/statm", "rb") as handle:
        return int(handle.read().split()[1]) * _PAGE


class RssSampler:
    """RSS of this (the control) process once a second, taken from the status callback the
    loop calls every 100 ticks: no thread, and a read of /proc costs one tick in a thousand a
    few microseconds."""

    def __init__(self, on_first: Callable[[], None] | None = None) -> None:
        self.on_first = on_first
        self.t: list[float] = []
        self.rss: list[int] = []
        self.loop_t: list[float] = []  # the loop's own run time at each sample (s)
        self._next = 0.0

    def __call__(self, line: StatusLine) -> None:
        if self.on_first is not None:
            self.on_first()
            self.on_first = None
        now = time.monotonic()
        if now >= self._next:
            self._next = now + SAMPLE_S
            self.t.append(now)
            self.loop_t.append(line.t_s)
            self.rss.append(_rss_bytes())

    def slope_mb_per_hour(self, after_s: float) -> tuple[float, int]:
        """Least-squares slope of RSS over time for the samples after ``after_s`` of loop
        time, and how many samples it used."""
        t = np.array(self.t)
        rss = np.array(self.rss, dtype=np.float64)
        keep = np.array(self.loop_t) >= after_s
        if keep.sum() < 3:
            return float("nan"), int(keep.sum())
        slope, _ = np.polyfit(t[keep] - t[keep][0], rss[keep], 1)
        return float(slope) * 3600 / 1e6, int(keep.sum())


def _log_ticks(path: Path) -> tuple[int, int, int]:
    """Ticks in the file, ticks missing from 0 to the last one, and the last tick number."""
    recording = open_recording(path)
    seen: list[int] = [m["tick"] for _, _, m in iter_decoded(recording, [ch.TIMING])]
    if not seen:
        return 0, 0, -1
    last = max(seen)
    return len(seen), last + 1 - len(set(seen)), last


def run(args: argparse.Namespace) -> dict[str, Any]:
    hand = load_hand(args.hand)
    seconds = args.minutes * 60
    warmup = args.warmup_s if args.warmup_s is not None else min(60.0, seconds / 5)
    refused: list[str] = []

    def peer_priority() -> None:
        problem = prioritise_peer(PEER_PRIORITY)
        if problem:
            refused.append(problem)

    sampler = RssSampler(peer_priority if args.rt else None)
    with tempfile.TemporaryDirectory(prefix="handctl-soak-") as tmp:
        recipe_path = Path(tmp) / "soak_hold.yaml"
        recipe_path.write_text(hold_recipe(hand, "soak_hold", seconds, pose=False))
        recipe = load_recipe(recipe_path, hand)
        log = args.log or Path(tmp) / "soak.mcap"
        print(
            f"soak: real-time loop with the simulated hand, recording to {log}, "
            f"{args.minutes:g} min ...",
            file=sys.stderr,
        )
        started = time.monotonic()
        running = RunningSince()

        def status(line: StatusLine) -> None:
            sampler(line)
            running(line)

        report = run_recipe(
            RunRequest(
                hand=hand,
                recipe=recipe,
                bus="sim",
                lockstep=False,
                realtime_priority=args.rt,
                log=log,
                command_line=("bench.py", "soak"),
            ),
            status=status,
        )
        wall = time.monotonic() - started
        require_whole(report.summary, "the soak's run")
        for warning in [*report.warnings, *refused]:
            print(f"warning: {warning}", file=sys.stderr)
        print("reading the recording back ...", file=sys.stderr)
        in_file, gaps, last = _log_ticks(log)
        mb_written = log.stat().st_size / 1e6
    result = report.result
    if result.outcome is Outcome.INTERRUPTED:
        # a soak stopped by a signal measured nothing of what was asked: exit 130 as any
        # command (it printed its figures, exit 0)
        raise KeyboardInterrupt(result.message)
    stats = report.summary.get("recording", {})
    dropped = sum(
        int(stats.get(k, 0))
        for k in ("dropped_ticks", "dropped_frames", "dropped_events", "dropped_poses")
    )
    # Every tick the runtime ran must be in the file once: a tick short is a record lost.
    missing = max(0, result.ticks - in_file) + gaps
    first = max(0, report.first_send_tick)
    proper_ticks = max(0, result.ticks - first)
    startup_missed = report.startup_missed_ticks
    missed = result.missed_ticks - startup_missed
    slope, samples = sampler.slope_mb_per_hour(warmup)
    rss = sampler.rss
    return {
        "minutes": args.minutes,
        "rt": bool(args.rt and not refused and not any("refused" in w for w in report.warnings)),
        "outcome": result.outcome.value,
        "message": result.message,
        "ticks": proper_ticks,
        "missed_ticks": missed,
        "missed_rate": round(missed / max(1, proper_ticks), 6),
        "missed_rate_target": MISSED_TARGET,
        "startup_missed_ticks": startup_missed,
        "lateness_p99_us": report.summary["lateness_us"]["p99"],
        "rss_growth_mb_per_hour": round(slope, 2) if np.isfinite(slope) else None,
        "rss_growth_target": RSS_TARGET_MB_PER_HOUR,
        "rss_samples": samples,
        "rss_warmup_s": warmup,
        "rss_start_mb": round(rss[0] / 1e6, 1) if rss else None,
        "rss_end_mb": round(rss[-1] / 1e6, 1) if rss else None,
        "records_lost": dropped + missing,
        "records_dropped": dropped,
        "ticks_run": result.ticks,
        "ticks_in_file": in_file,
        "tick_gaps_in_file": gaps,
        "last_tick_in_file": last,
        "mb_written": round(mb_written, 1),
        "wall_s": round(wall, 1),
        **host_figures(report, hand, first, running.ns),
        # a soak that did not run its minutes (a safety stop after 2 s of 30) measured less
        # than was asked: said, exit 1 (bench.py)
        "failed": (
            []
            if result.outcome is Outcome.COMPLETED
            else [f"the soak ended on {result.outcome.value} after {wall:.1f} s: {result.message}"]
        ),
    }
