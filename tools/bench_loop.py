"""The real-time loop against the simulated hand (its own process, on the unix datagram bus),
and, in the same run, a naive asyncio.sleep loop at the same rate as the baseline.

Figures: lateness p99 of both loops and their ratio, the missed-tick rate, and the CPU time of
our own tick stages (poll, recipe, safety, send, record) at p99, the simulated hand excluded;
the simulated hand's frames that did not go and the times the host's queue was full.
"""

from __future__ import annotations

import argparse
import asyncio
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from handctl.config import load_hand
from handctl.recipes.loader import load_recipe
from handctl.session import RunRequest, run_recipe

ROOT = Path(__file__).resolve().parent.parent
HOLD = """
recipe: bench_hold
description: close the hand gently and hold, for the loop benchmark
phases:
  - name: close
    torques: [0.06, 0.05, 0.03, 0.06, 0.05, 0.03, -0.06, -0.05, -0.03]
    ramp_s: 0.3
    max_s: {seconds}
    on_timeout: next
"""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--seconds", type=float, default=60.0, help="length of each loop run")
    parser.add_argument("--hand", type=Path, default=ROOT / "config/hands/hiroshima_hand.yaml")
    parser.add_argument("--babble", type=int, default=0, metavar="FRAMES_PER_MS",
                        help="a babbling node floods foreign ids at this rate the whole run "
                             "(20 is about all a CAN-FD bus carries)")
    parser.add_argument("--rt", action="store_true",
                        help="ask for SCHED_FIFO and locked memory, as `handctl run --rt`")
    parser.add_argument("--live", action="store_true",
                        help="two recorded runs, without and with the live Foxglove server and "
                             "a subscribed client: what the live view adds to the tick")


async def _naive(period_s: float, seconds: float) -> np.ndarray:
    """The loop a first attempt writes: sleep until the next deadline with asyncio.sleep."""
    period_ns = round(period_s * 1e9)
    start = time.monotonic_ns()
    ticks = round(seconds / period_s)
    lateness = np.zeros(ticks, dtype=np.int64)
    for k in range(ticks):
        deadline = start + (k + 1) * period_ns
        await asyncio.sleep(max(0.0, (deadline - time.monotonic_ns()) / 1e9))
        lateness[k] = time.monotonic_ns() - deadline
    return lateness


def run(args: argparse.Namespace) -> dict[str, float]:
    if args.live:
        from live_view_cost import compare

        return compare(run, args)
    live_port = getattr(args, "live_port", None)
    record = getattr(args, "record", False) or live_port is not None
    hand = load_hand(args.hand)
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "hold.yaml"
        path.write_text(HOLD.format(seconds=args.seconds))
        recipe = load_recipe(path, hand)
        faults = None
        if args.babble:
            faults = Path(tmp) / "babble.yaml"
            faults.write_text("description: a babbling node for the load benchmark\nfaults:\n"
                              f"  - {{kind: babble, id: 0x050, per_tick: {args.babble}, "
                              "length: 8, start: 0.0}\n")
        print(f"real-time loop with the simulated hand, {args.seconds:g} s"
              f"{f', babble {args.babble}/ms' if args.babble else ''} ...", file=sys.stderr)
        report = run_recipe(RunRequest(hand=hand, recipe=recipe, bus="sim", lockstep=False,
                                       realtime_priority=args.rt, sim_faults=faults,
                                       log=Path(tmp) / "run.mcap" if record else None,
                                       live_port=live_port))
    for warning in report.warnings:
        print(f"warning: {warning}", file=sys.stderr)
    result = report.result
    # Ticks of the run proper: from the first command on. Before it the peer process is still
    # importing MuJoCo and building its model on the same two cores, which is start-up, not
    # the loop's steady state; the start-up misses are reported apart.
    first = max(0, report.first_send_tick)
    ours = result.lateness_ns[first:]
    missed = int(result.missed[first:].sum())
    cpu = result.stage_ns[first:].sum(axis=1)
    # What the simulated hand's frames met on the way (its own count, from its process): frames
    # that never went, and the times the host's socket queue was full so frames waited.
    sim = report.summary.get("sim") or {}
    transport = sim.get("transport") or {}
    print(f"naive asyncio.sleep loop, {args.seconds:g} s ...", file=sys.stderr)
    naive = asyncio.run(_naive(hand.bus.period_s, args.seconds))
    ours_p99 = float(np.percentile(ours, 99)) / 1e3
    naive_p99 = float(np.percentile(naive, 99)) / 1e3
    return {
        "seconds": args.seconds,
        "babble_per_ms": args.babble,
        "foreign_frames": result.node_rejects.get("unexpected_id", 0),
        "sim_tx_failed": int(sim.get("tx_failed", -1)),
        "sim_queue_full": int(transport.get("queue_full", -1)),
        "rt": bool(args.rt and not report.warnings),  # type: ignore[dict-item]
        "outcome": result.outcome.value,  # type: ignore[dict-item]
        "message": result.message,  # type: ignore[dict-item]
        "ticks": int(ours.size),
        "lateness_p99_us": round(ours_p99, 1),
        "lateness_p50_us": round(float(np.percentile(ours, 50)) / 1e3, 1),
        "naive_lateness_p99_us": round(naive_p99, 1),
        "lateness_ratio": round(ours_p99 / naive_p99, 4),
        "missed_rate": round(missed / max(1, ours.size), 6),
        "startup_missed_ticks": int(result.missed[:first].sum()),
        "tick_cpu_us_p99": round(float(np.percentile(cpu, 99)) / 1e3, 1),
        "tick_cpu_us_p50": round(float(np.percentile(cpu, 50)) / 1e3, 1),
    }
