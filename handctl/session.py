"""Composition of one run: open the bus (or start the simulated hand), build the runtime, run it
under signal handling, and turn the result into the summary a user and a CI job read.

This is the one place that knows both the online plane and the simulated hand: for ``--bus
sim`` it starts the simulated hand as a peer on a private virtual channel and opens that channel
like any other bus. The online plane itself never imports the simulation.
"""

from __future__ import annotations

import asyncio
import json
import os
import signal
import subprocess
import sys
import tempfile
from collections.abc import Callable
from contextlib import ExitStack
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from handctl.bus import BusSpec, HandBus, open_bus, parse_spec
from handctl.clock import Clock, LockstepClock, RealtimeClock, request_realtime
from handctl.config import HandConfig
from handctl.drivers.hand import HandDriver
from handctl.errors import ConfigError
from handctl.loop import Outcome, RecordSink, RunResult, Runtime, StatusLine
from handctl.protocol import load_protocol
from handctl.recipes.schema import Recipe
from handctl.safety.faults import FAULTS


@dataclass
class RunRequest:
    hand: HandConfig
    recipe: Recipe
    bus: str = "sim"
    lockstep: bool | None = None  # None: lockstep on the simulated hand, real time elsewhere
    realtime_priority: bool = False
    seed: int = 0
    reset_node_faults: bool = False
    sim_faults: Path | None = None
    max_seconds: float | None = None


@dataclass
class RunReport:
    result: RunResult
    summary: dict[str, Any]
    warnings: list[str]
    first_send_tick: int = -1  # the tick of the first torque command


def _percentiles_us(values_ns: np.ndarray) -> dict[str, float]:
    if values_ns.size == 0:
        return {"p50": 0.0, "p99": 0.0, "max": 0.0}
    p50, p99 = np.percentile(values_ns, [50, 99])
    return {"p50": round(float(p50) / 1e3, 2), "p99": round(float(p99) / 1e3, 2),
            "max": round(float(values_ns.max()) / 1e3, 2)}


def summarise(result: RunResult, hand: HandConfig, recipe: Recipe, lockstep: bool,
              sim: dict[str, Any] | None) -> dict[str, Any]:
    """The summary JSON: the fields the runtime issue names, and a few an engineer wants."""
    stages = ("poll", "recipe", "safety", "send", "record")
    return {
        "completed": result.outcome is Outcome.COMPLETED,
        "outcome": result.outcome.value,
        "message": result.message,
        "recipe": recipe.name,
        "hand": hand.name,
        "hand_config_hash": hand.config_hash,
        "mode": "lockstep" if lockstep else "realtime",
        "phases": result.phases,
        "faults": [{"code": f.code.name, "category": FAULTS[f.code].category.name.lower(),
                    "tick": f.tick, "detail": f.detail} for f in result.faults],
        "ticks": result.ticks,
        "missed_ticks": result.missed_ticks,
        "lateness_us": _percentiles_us(result.lateness_ns),
        "stage_cpu_us_p99": {name: round(float(np.percentile(result.stage_ns[:, i], 99)) / 1e3,
                                         2) if result.ticks else 0.0
                             for i, name in enumerate(stages)},
        "max_abs_tau": {name: round(float(v), 5) for name, v in
                        zip(hand.joint_names, result.max_abs_tau, strict=True)},
        "rejected_frames": result.node_rejects,
        "bus_events": result.bus_events,
        **({"sim": sim} if sim is not None else {}),
    }


def run_recipe(req: RunRequest, status: Callable[[StatusLine], None] | None = None,
               recorder: RecordSink | None = None) -> RunReport:
    """Run ``req`` to its end (done, safety stop, or Ctrl-C/SIGTERM); never leaves torque on."""
    protocol = load_protocol()
    spec = parse_spec(req.bus, req.hand.bus)
    warnings: list[str] = []
    is_sim = spec.interface == "sim"
    lockstep = is_sim if req.lockstep is None else req.lockstep
    if lockstep and not is_sim:
        raise ConfigError("--lockstep", "", "the simulated hand (--bus sim): only it can be "
                          "stepped", req.bus)
    startup_s = 0.5
    with ExitStack() as stack:
        sim_hand: Any = None
        sim_process: SimProcess | None = None
        if is_sim and lockstep:
            from handctl.sim.hand import SimulatedHand

            channel = f"handctl-sim-{os.getpid()}-{id(req)}"
            peer_bus = stack.enter_context(open_bus(BusSpec("virtual", channel), req.hand.bus))
            sim_hand = SimulatedHand(req.hand, peer_bus, seed=req.seed)
            if req.sim_faults is not None:
                sim_hand.load_faults(req.sim_faults)
            spec = BusSpec("virtual", channel)
        elif is_sim:
            # Free-running, the simulated hand gets a process of its own: a busy thread in the
            # control process would take the interpreter from the loop for a millisecond at a
            # time. The two talk over the unix datagram bus.
            directory = stack.enter_context(tempfile.TemporaryDirectory(prefix="handctl-bus-"))
            sim_process = stack.enter_context(SimProcess(req, directory))
            spec = BusSpec("unix", directory)
            startup_s = 20.0  # the peer imports MuJoCo and builds its model first
        bus: HandBus = stack.enter_context(open_bus(spec, req.hand.bus))
        clock: Clock
        if lockstep:
            clock = LockstepClock(req.hand.bus.period_s, sim_hand.step)
        else:
            clock = RealtimeClock(req.hand.bus.period_s)
            if req.realtime_priority:
                warnings += request_realtime()
        driver = HandDriver(req.hand, protocol, bus, clock_ns=clock.now_ns)
        max_ticks = (round(req.max_seconds / req.hand.bus.period_s) if req.max_seconds
                     else 10_000_000)
        runtime = Runtime(req.hand, driver, clock, req.recipe, recorder=recorder, status=status,
                          reset_node_faults=req.reset_node_faults, max_ticks=max_ticks,
                          startup_timeout_s=startup_s)
        result = asyncio.run(_run_with_signals(runtime))
        sim_summary = None
        if sim_hand is not None:
            sim_summary = sim_hand.ground_truth_summary()
        elif sim_process is not None:
            sim_summary = sim_process.finish()
    return RunReport(result, summarise(result, req.hand, req.recipe, lockstep, sim_summary),
                     warnings, runtime.first_send_tick)


class SimProcess:
    """The simulated hand as a separate process (``handctl sim``) on a unix datagram bus."""

    def __init__(self, req: RunRequest, directory: str) -> None:
        self.summary_path = Path(directory) / "sim-summary.json"
        cmd = [sys.executable, "-m", "handctl", "sim", "--bus", f"unix:{directory}",
               "--hand", req.hand.source, "--seed", str(req.seed),
               "--summary-json", str(self.summary_path)]
        if req.sim_faults is not None:
            cmd += ["--faults", str(req.sim_faults)]
        self.proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                                     text=True)
        self.summary: dict[str, Any] | None = None

    def finish(self) -> dict[str, Any] | None:
        """Stop the peer (SIGINT: it writes its ground truth) and read what it wrote."""
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGINT)
            try:
                self.proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        if self.summary is None and self.summary_path.exists():
            self.summary = json.loads(self.summary_path.read_text())
        return self.summary

    def __enter__(self) -> SimProcess:
        return self

    def __exit__(self, *exc: object) -> None:
        self.finish()
        if self.proc.stderr is not None:
            self.proc.stderr.close()


async def _run_with_signals(runtime: Runtime) -> RunResult:
    """Ctrl-C and SIGTERM become a controlled stop inside the loop, never an exception."""
    loop = asyncio.get_running_loop()
    installed = []
    for sig in (signal.SIGINT, signal.SIGTERM):
        try:
            loop.add_signal_handler(sig, runtime.request_stop, f"signal {sig.name}")
            installed.append(sig)
        except (NotImplementedError, RuntimeError, ValueError):
            pass
    try:
        return await runtime.run()
    finally:
        for sig in installed:
            loop.remove_signal_handler(sig)
