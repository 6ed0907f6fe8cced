"""The fault campaign: every injector of the simulated hand in every kind of recipe phase,
against the real runtime, judged on what went on the wire.

For each (injector, phase) case the runtime runs a short recipe in lockstep with a sniffer on
the bus, the way a CAN analyser listens on a real bench. The case records whether and when a
fault was detected, the stop the supervisor took, how many command frames were unsafe (over a
limit, faster than the rate limit, or carrying torque after a fault that demands zero, allowing
the two ticks the runtime issue grants), and whether only an explicit reset brought torque
back, from zero. ``tools/fault_campaign.py`` writes the table into ``docs/faults.md``; a test
runs the same cases and checks them against what each injector must cause.
"""

from __future__ import annotations

import asyncio
import itertools
import math
import tempfile
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from handctl.bus import HandBus, open_bus
from handctl.clock import LockstepClock, Tick
from handctl.config import HandConfig
from handctl.drivers.hand import HandDriver
from handctl.loop import Outcome, Runtime
from handctl.protocol import load_protocol
from handctl.recipes.loader import load_recipe
from handctl.recipes.schema import Recipe
from handctl.safety.faults import FAULTS, RAMP_BOUND_S, StopCategory
from handctl.sim import faults as inj
from handctl.sim.hand import SimulatedHand

#: The campaign recipe: one phase of each kind, torques that keep every joint well inside its
#: soft limits on the default hand. Times in s.
PHASES = (("idle", 0.4), ("approach", 0.4), ("holding", 0.6), ("manipulating", 0.6))
RECIPE = """
recipe: fault_campaign
description: one phase of each kind, for the fault campaign
end_ramp_s: 0.1
phases:
  - {name: idle, torques: [0, 0, 0, 0, 0, 0, 0, 0, 0], ramp_s: 0.0, max_s: 0.4,
     on_timeout: next}
  - {name: approach, torques: [0.06, 0.05, 0.03, 0.06, 0.05, 0.03, -0.06, -0.05, -0.03],
     ramp_s: 0.3, max_s: 0.4, on_timeout: next}
  - {name: holding, torques: [0.07, 0.05, 0.03, 0.07, 0.05, 0.03, -0.07, -0.05, -0.03],
     ramp_s: 0.1, max_s: 0.6, on_timeout: next}
  - {name: manipulating, torques: [0.08, 0.05, 0.03, 0.08, 0.05, 0.03, -0.06, -0.05, -0.03],
     ramp_s: 0.1, max_s: 0.6, on_timeout: next}
"""
#: Injectors with the settings the campaign uses: each severe enough to matter, as a robot
#: would meet it. Kept on for FAULT_ON_S.
CASES: dict[str, Callable[[], inj.Injector]] = {
    "drop_commands": lambda: inj.DropCommands(node=3, count=15),
    "drop_feedback": lambda: inj.DropFeedback(node=1),
    "delay_feedback": lambda: inj.DelayFeedback(node=2, delay=0.02),
    "corrupt_crc": lambda: inj.CorruptCrc(node=1, message="feedback"),
    "counter_repeat": lambda: inj.CounterRepeat(node=2, message="feedback"),
    "counter_skip": lambda: inj.CounterSkip(node=3, message="all"),
    "tdt_stuck": lambda: inj.TdtStuck(node=1, joint=1),
    "tdt_spike": lambda: inj.TdtSpike(node=2, joint=1, amplitude=0.3, duration=0.002),
    "tdt_offset": lambda: inj.TdtOffset(node=3, joint=2, offset=0.3),
    "encoder_jump": lambda: inj.EncoderJump(node=1, joint=2, counts=4000),
    "node_reboot": lambda: inj.NodeReboot(node=2, downtime=0.02),
    "node_silent": lambda: inj.NodeSilent(node=3),
    "error_frames": lambda: inj.ErrorFrames(per_tick=2),
    "bus_off": inj.BusOff,
    "babble": lambda: inj.Babble(id=0x050, per_tick=20, length=8),
    "tendon_slack": lambda: inj.TendonSlack(node=2, joint=1),
    "motor_saturation": lambda: inj.MotorSaturation(node=1, joint=1, limit=0.01),
}
FAULT_ON_S = 0.25
#: A stuck sensor while the command holds still is only caught by the 0.5 s "still" check.
ON_S = {"tdt_stuck": 0.6}
_channels = itertools.count()


@dataclass(frozen=True)
class CaseResult:
    injector: str
    phase: str
    fault: str  # the first fault code, or "" when none was detected
    category: str  # "immediate", "ramp" or ""
    latency_ms: float | None  # from injection to detection
    unsafe_frames: int
    frames: int
    recovered: bool | None  # None when there was nothing to recover from
    foreign_frames: int
    bus_events: int
    rejected_frames: int


@contextmanager
def hil_bench(hand: HandConfig, recipe: Recipe | None, seed: int = 0, max_ticks: int = 20_000
              ) -> Iterator[tuple[SimulatedHand, Runtime, HandBus]]:
    """The runtime and the simulated hand in lockstep on one private virtual bus, plus a
    sniffer that hears every frame, as a CAN analyser would on a bench."""
    channel = f"hil-{next(_channels)}"
    with open_bus(f"virtual:{channel}", hand.bus) as peer, \
            open_bus(f"virtual:{channel}", hand.bus) as host, \
            open_bus(f"virtual:{channel}", hand.bus) as sniffer:
        sim = SimulatedHand(hand, peer, seed=seed)
        clock = LockstepClock(hand.bus.period_s, sim.step)
        driver = HandDriver(hand, load_protocol(), host, clock_ns=clock.now_ns)
        yield sim, Runtime(hand, driver, clock, recipe, max_ticks=max_ticks), sniffer


def _commands(sniffer: HandBus, hand: HandConfig) -> np.ndarray:
    """The torque commands on the wire, one row per tick (decoded with the DBC layouts)."""
    protocol = load_protocol()
    rows: dict[int, list[tuple[float, ...]]] = {f.node_id: [] for f in hand.fingers}
    layouts = {protocol.layout("TorqueCommand", n).frame_id: (n, protocol.layout(
        "TorqueCommand", n)) for n in rows}
    for frame in sniffer.drain(limit=10**7):
        hit = layouts.get(frame.arbitration_id)
        if hit is not None:
            rows[hit[0]].append(hit[1].decode(frame.data)[1])
    n = min(len(r) for r in rows.values())
    return np.hstack([np.array(rows[k][:n]).reshape(n, 3) for k in sorted(rows)])


def unsafe_frames(wire: np.ndarray, hand: HandConfig, fault_row: int | None,
                  category: StopCategory | None) -> int:
    """Rows that break a limit, the rate limit, or the stop a fault demands."""
    step = 1e-4  # one raw unit of the wire encoding
    tau_max = np.array([j.tau_max for j in hand.joints])
    rate = np.array([j.rate_limit for j in hand.joints]) * hand.bus.period_s
    bad = np.any(np.abs(wire) > tau_max + step, axis=1)
    old, new = wire[:-1], wire[1:]
    # A change faster than the rate limit is unsafe unless it goes towards zero (a stop).
    towards_zero = (new == 0) | ((np.sign(new) == np.sign(old)) & (np.abs(new) <= np.abs(old)))
    jumps = (np.abs(new - old) > rate + 2 * step) & ~towards_zero
    bad[1:] |= np.any(jumps, axis=1)
    if fault_row is not None and category is not None:
        grace = 2  # the runtime issue: zero (or the ramp) at most 2 ticks after detection
        if category is StopCategory.IMMEDIATE:
            bad[fault_row + grace:] |= np.any(wire[fault_row + grace:] != 0, axis=1)
        else:
            ramp_end = fault_row + grace + math.ceil(RAMP_BOUND_S / hand.bus.period_s)
            bad[ramp_end:] |= np.any(wire[ramp_end:] != 0, axis=1)
            mags = np.abs(wire[fault_row:]).max(axis=1)
            rising = np.flatnonzero(np.diff(mags) > step) + fault_row + 1
            bad[rising] = True
    return int(bad.sum())


def run_case(hand: HandConfig, injector: str, phase: str, seed: int = 0) -> CaseResult:
    """One injector switched on in the middle of one phase, then an explicit reset."""
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "campaign.yaml"
        path.write_text(RECIPE)
        recipe = load_recipe(path, hand)
    with hil_bench(hand, recipe, seed) as (sim, runtime, sniffer):
        # Inject in the middle of the phase, whenever the run gets there (start-up takes as
        # long as the nodes take to answer).
        on_s = ON_S.get(injector, FAULT_ON_S)
        half = dict(PHASES)[phase] / 2
        entered: list[float] = []
        injected: list[tuple[int, float]] = []  # (tick, simulated time) of the switch-on

        def inject(tick: Tick) -> None:
            runner = runtime.runner
            if injected or runner is None or runner.phase_name != phase:
                return
            if not entered:
                entered.append(sim.time)
            elif sim.time >= entered[0] + half:
                injected.append((tick.k, sim.time))
                sim.faults.add(CASES[injector](), sim.time, sim.time + on_s)

        runtime.tick_hooks.append(inject)
        result = asyncio.run(runtime.run())
        runtime.tick_hooks.remove(inject)
        if not injected:
            raise RuntimeError(f"{injector}: the run never reached the middle of '{phase}'")
        inject_tick, at = injected[0]
        wire = _commands(sniffer, hand)
        first = result.faults[0] if result.faults else None
        category = FAULTS[first.code].category if first else None
        row = None if first is None else first.tick - runtime.first_send_tick
        unsafe = unsafe_frames(wire, hand, row, category)
        recovered: bool | None = None
        if first is not None:
            # Nothing comes back by itself: the runtime ended and stays down. Let the fault
            # pass (the simulated hand runs on, the host silent), then reset explicitly.
            while sim.time < at + on_s + 0.05:
                sim.step()
            sniffer.drain(limit=10**7)
            recovered = runtime.reset()
            if recovered:
                runtime.tick_hooks.append(lambda tk: runtime.request_stop("case over")
                                          if runtime.runner is not None
                                          and runtime.runner.phase_name == "holding" else None)
                again = asyncio.run(runtime.run())
                more = _commands(sniffer, hand)
                steps = np.array([j.rate_limit for j in hand.joints]) * hand.bus.period_s
                recovered = (again.outcome in (Outcome.COMPLETED, Outcome.INTERRUPTED)
                             and len(more) > 0 and bool(np.all(np.abs(more[0]) <= steps + 1e-4)))
                unsafe += unsafe_frames(more, hand, None, None)
        latency = None
        if first is not None:
            latency = round((first.tick - inject_tick) * hand.bus.period_s * 1e3, 1)
        rejects = sum(v for k, v in result.node_rejects.items() if k != "unexpected_id")
        return CaseResult(
            injector=injector, phase=phase, fault=first.code.name if first else "",
            category=("immediate" if category is StopCategory.IMMEDIATE else "ramp")
            if category else "", latency_ms=latency, unsafe_frames=unsafe, frames=len(wire),
            recovered=recovered, foreign_frames=result.node_rejects.get("unexpected_id", 0),
            bus_events=result.bus_events, rejected_frames=rejects)


def run_campaign(hand: HandConfig, progress: Callable[[str], None] | None = None,
                 injectors: list[str] | None = None) -> list[CaseResult]:
    results = []
    for injector in injectors or list(CASES):
        for phase, _ in PHASES:
            results.append(run_case(hand, injector, phase))
            if progress is not None:
                r = results[-1]
                progress(f"{injector:<17} {phase:<13} {r.fault or 'no fault':<17} "
                         f"{r.latency_ms if r.latency_ms is not None else '-':>6} ms "
                         f"unsafe {r.unsafe_frames}")
    return results


def render_table(results: list[CaseResult]) -> str:
    """The campaign's Markdown table: one row per injector, one column group per phase."""
    lines = ["| injector | " + " | ".join(p for p, _ in PHASES) + " | unsafe frames |",
             "|---|" + "---|" * (len(PHASES) + 1)]
    by_injector: dict[str, list[CaseResult]] = {}
    for r in results:
        by_injector.setdefault(r.injector, []).append(r)
    for injector, rows in by_injector.items():
        cells = []
        for r in rows:
            if r.fault:
                cell = f"`{r.fault}` {r.category}, {r.latency_ms:g} ms"
                cell += ", reset ok" if r.recovered else ", reset FAILED"
            else:
                seen = []
                if r.rejected_frames:
                    seen.append(f"{r.rejected_frames} rejected")
                if r.foreign_frames:
                    seen.append(f"{r.foreign_frames} foreign")
                if r.bus_events:
                    seen.append(f"{r.bus_events} bus events")
                cell = "tolerated" + (f" ({', '.join(seen)})" if seen else "")
            cells.append(cell)
        lines.append(f"| `{injector}` | " + " | ".join(cells)
                     + f" | {sum(r.unsafe_frames for r in rows)} |")
    return "\n".join(lines)
