"""The CPU cost of the control tick, stage by stage, for whichever handctl is on the path.

A lockstep run of the benchmarks' hold recipe (``hold_recipe.hold_recipe``) on the
simulated hand, over the unix bus (the transport of a real-time run) or the virtual bus (that
of a lockstep run): deterministic work, the same every time, so two implementations can be laid
side by side in one benchmark run (``bench_loop.tick_cost``). It prints one JSON object: per
stage (``handctl.online.tickstats.STAGES``) and for the whole tick, p50 / p99 / mean in µs over
the ticks with the hand running.

It uses only what every handctl since the stage accounting has (hand and recipe loading,
the driver, the runtime, the simulated hand, the bus), so that ``PYTHONPATH`` can point it at
an older tree (``python tools/bench.py loop --baseline REV``); of the tools it imports only
``hold_recipe.py``, whose handctl imports are as old (``bench_loop``'s are not).
"""

from __future__ import annotations

import argparse
import asyncio
import dataclasses
import json
import sys
import tempfile
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
#: s, the feedback and heartbeat timeouts of the unix variant (see ``main``)
LIFTED_TIMEOUT_S = 10.0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument(
        "--hand", type=Path, default=HERE.parent / "config/hands/hiroshima_hand.yaml"
    )
    parser.add_argument("--seconds", type=float, default=3.0)
    parser.add_argument("--transport", choices=("unix", "virtual"), default="unix")
    args = parser.parse_args(argv)

    import handctl
    from handctl.config import load_hand
    from handctl.hand_protocol import protocol_for
    from handctl.online.bus import open_bus
    from handctl.online.busspec import BusSpec
    from handctl.online.clock import LockstepClock
    from handctl.online.drivers.hand import HandDriver
    from handctl.online.loop import Runtime
    from handctl.online.recipes.loader import load_recipe
    from handctl.online.tickstats import STAGES
    from handctl.sim.hand import SimulatedHand

    sys.path.insert(0, str(HERE))
    from hold_recipe import hold_recipe

    hand = load_hand(args.hand)
    if args.transport == "unix":
        # The unix bus stamps arrivals in wall-clock time, which a lockstep run does not keep:
        # on a loaded host a frame can look older than the feedback timeout. The stages do
        # the same work whatever the timeouts, so they are lifted here, for this figure only.
        safety = dataclasses.replace(
            hand.safety, feedback_timeout_s=LIFTED_TIMEOUT_S, heartbeat_timeout_s=LIFTED_TIMEOUT_S
        )
        hand = dataclasses.replace(hand, safety=safety)
    with tempfile.TemporaryDirectory(prefix="handctl-tick-cost-") as tmp:
        path = Path(tmp) / "hold.yaml"
        path.write_text(hold_recipe(hand, "tick_cost", args.seconds))
        recipe = load_recipe(path, hand)
        channel = str(Path(tmp) / "bus") if args.transport == "unix" else f"tick-cost-{tmp}"
        spec = BusSpec(args.transport, channel)
        with open_bus(spec, hand.bus) as peer_bus, open_bus(spec, hand.bus) as bus:
            sim = SimulatedHand(hand, peer_bus, seed=0)
            clock = LockstepClock(hand.bus.period_s, sim.step)
            driver = HandDriver(hand, protocol_for(hand), bus, clock_ns=clock.now_ns)
            runtime = Runtime(hand, driver, clock, recipe)
            result = asyncio.run(runtime.run())
    ticks = np.asarray(result.stage_ns[max(0, runtime.first_send_tick) :], dtype=np.float64) / 1e3
    figures: dict[str, object] = {
        "handctl": str(Path(handctl.__file__).resolve().parent),
        "outcome": result.outcome.value,
        "message": result.message,
        "ticks": int(ticks.shape[0]),
    }
    for name, column in [*zip(STAGES, ticks.T, strict=True), ("tick", ticks.sum(axis=1))]:
        figures[name] = {
            "p50_us": round(float(np.percentile(column, 50)), 1),
            "p99_us": round(float(np.percentile(column, 99)), 1),
            "mean_us": round(float(column.mean()), 1),
        }
    print(json.dumps(figures))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
