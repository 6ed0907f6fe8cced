"""The fault campaign: every injector of the simulated hand in every kind of recipe phase,
against the real runtime, judged on what went on the wire.

For each (injector, phase) case the runtime runs a short recipe in lockstep with a sniffer on
the bus, the way a CAN analyser listens on a real bench. The case records whether and when a
fault was detected, the stop the supervisor took, how many command frames were unsafe (over a
limit, faster than the rate limit, or carrying torque after a fault that demands zero, allowing
the two ticks the runtime issue grants), and whether only an explicit reset brought torque
back, from zero. ``tools/gen_fault_table.py --campaign`` writes the table into
``docs/faults.md``; a test runs the same cases and checks them against what each injector must
cause.

Every case is recorded to MCAP by the real recorder (``handctl/recording/``: shared-memory
rings, the writer process), as ``handctl run recipe --log`` records a run, and the file is read
back: a fault that is not in the log did not happen as far as anyone investigating it later can
tell. ``logged`` says whether the log shows what the case showed (see ``judge_log``).
"""

from __future__ import annotations

import asyncio
import itertools
import json
import math
import tempfile
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from handctl.config import HandConfig
from handctl.executor import WorkPool, open_pool
from handctl.hand_protocol import protocol_for
from handctl.handshape import flexion_sign
from handctl.online.bus import HandBus, open_bus
from handctl.online.clock import LockstepClock, Tick
from handctl.online.drivers.hand import HandDriver
from handctl.online.loop import Outcome, RunResult, Runtime
from handctl.online.recipes.loader import load_recipe
from handctl.online.recipes.schema import Recipe
from handctl.online.safety.faults import FAULTS, RAMP_BOUND_S, StopCategory
from handctl.portable import local_hand, portable_hand
from handctl.progress import Progress
from handctl.recording import channels as ch
from handctl.recording.metadata import run_metadata, start_metadata
from handctl.recording.reader import iter_decoded, open_recording
from handctl.recording.recorder import Recorder
from handctl.sim import faults as inj
from handctl.sim.hand import SimulatedHand
from handctl.sim.params import SimParams

#: The campaign recipe: one phase of each kind, torques that keep every joint well inside its
#: soft limits on the default hand. Times in s.
PHASES = (("idle", 0.4), ("approach", 0.4), ("holding", 0.6), ("manipulating", 0.6))
#: N·m per joint level (proximal first; deeper levels take the last): the campaign's gentle
#: closing torques, each phase's own, signed by each finger's flexion. The manipulation phase
#: pushes the fingers of the flexing-positive side harder than the others, so the hand moves.
CAMPAIGN_TORQUES = {
    "approach": (0.06, 0.05, 0.03),
    "holding": (0.07, 0.05, 0.03),
    "manipulating": (0.08, 0.05, 0.03),
}
MANIPULATING_OTHER_SIDE_J1 = 0.06  # N·m, the first joint of the fingers that flex negative
#: (name, ramp_s, max_s) of the campaign's phases, one of each kind
CAMPAIGN_PHASES = (
    ("idle", 0.0, 0.4),
    ("approach", 0.3, 0.4),
    ("holding", 0.1, 0.6),
    ("manipulating", 0.1, 0.6),
)


def campaign_recipe(hand: HandConfig) -> str:
    """The campaign's recipe for ``hand``: one phase of each kind, each joint's torque from its
    level in ``CAMPAIGN_TORQUES``, signed by its finger's flexion and never above half its
    tau_max (a small hand's joints are not pushed to their limits by a fault test)."""
    phases: list[dict[str, object]] = []
    for name, ramp_s, max_s in CAMPAIGN_PHASES:
        torques: list[float] = []
        for finger in hand.fingers:
            sign = flexion_sign(hand, finger)
            for level, joint in enumerate(finger.joints):
                if name == "idle":
                    torques.append(0.0)
                    continue
                levels = CAMPAIGN_TORQUES[name]
                size = levels[min(level, len(levels) - 1)]
                if name == "manipulating" and level == 0 and sign < 0:
                    size = MANIPULATING_OTHER_SIDE_J1
                torques.append(sign * min(size, 0.5 * joint.tau_max))
        phases.append(
            {
                "name": name,
                "torques": torques,
                "ramp_s": ramp_s,
                "max_s": max_s,
                "on_timeout": "next",
            }
        )
    return json.dumps(
        {
            "recipe": "fault_campaign",
            "description": "one phase of each kind, for the fault campaign",
            "end_ramp_s": 0.1,
            "phases": phases,
        }
    )  # JSON is YAML


@dataclass(frozen=True)
class Targets:
    """What the injectors aim at, taken from the hand: its first, middle and last node (by id;
    all one node on a one-finger hand), and a joint number of each (1-based, within the node):
    the first, and the second where the node has one. Spread over the nodes, so that a fault
    is not always on the same finger."""

    first: int
    middle: int
    last: int

    @classmethod
    def of(cls, hand: HandConfig) -> Targets:
        nodes = sorted(f.node_id for f in hand.fingers)
        return cls(nodes[0], nodes[len(nodes) // 2], nodes[-1])


def _second_joint(hand: HandConfig, node: int) -> int:
    """Joint 2 of ``node``, or its only joint."""
    finger = next(f for f in hand.fingers if f.node_id == node)
    return min(2, len(finger.joints))


#: Injectors with the settings the campaign uses: each severe enough to matter, as a robot
#: would meet it, aimed at the hand's ``Targets``. Kept on for FAULT_ON_S.
CASES: dict[str, Callable[[HandConfig, Targets], inj.Injector]] = {
    "drop_commands": lambda h, t: inj.DropCommands(node=t.last, count=15),
    "drop_feedback": lambda h, t: inj.DropFeedback(node=t.first),
    "delay_feedback": lambda h, t: inj.DelayFeedback(node=t.middle, delay=0.02),
    "corrupt_crc": lambda h, t: inj.CorruptCrc(node=t.first, message="feedback"),
    "counter_repeat": lambda h, t: inj.CounterRepeat(node=t.middle, message="feedback"),
    "counter_skip": lambda h, t: inj.CounterSkip(node=t.last, message="all"),
    "tdt_stuck": lambda h, t: inj.TdtStuck(node=t.first, joint=1),
    "tdt_spike": lambda h, t: inj.TdtSpike(node=t.middle, joint=1, amplitude=0.3, duration=0.002),
    "tdt_offset": lambda h, t: inj.TdtOffset(
        node=t.last, joint=_second_joint(h, t.last), offset=0.3
    ),
    "encoder_jump": lambda h, t: inj.EncoderJump(
        node=t.first, joint=_second_joint(h, t.first), counts=4000
    ),
    "node_reboot": lambda h, t: inj.NodeReboot(node=t.middle, downtime=0.02),
    "node_silent": lambda h, t: inj.NodeSilent(node=t.last),
    "error_frames": lambda h, t: inj.ErrorFrames(per_tick=2),
    "bus_off": lambda h, t: inj.BusOff(),
    "babble": lambda h, t: inj.Babble(id=0x050, per_tick=20, length=8),
    "tendon_slack": lambda h, t: inj.TendonSlack(node=t.middle, joint=1),
    "motor_saturation": lambda h, t: inj.MotorSaturation(node=t.first, joint=1, limit=0.01),
    "extended_twin": lambda h, t: inj.ExtendedTwin(node=t.first, message="feedback"),
    "contradict": lambda h, t: inj.Contradict(node=t.middle, report="fault_bits"),
    "replay_frames": lambda h, t: inj.ReplayFrames(node=t.last, message="feedback", delay=0.05),
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
    fault_tick: int | None  # the tick that detected the first fault (the log's tick numbers)
    logged: bool  # the MCAP log shows the fault (or the counted disturbance) as it happened


@contextmanager
def hil_bench(
    hand: HandConfig,
    recipe: Recipe | None,
    seed: int = 0,
    max_ticks: int = 20_000,
    params: SimParams | None = None,
) -> Iterator[tuple[SimulatedHand, Runtime, HandBus]]:
    """The runtime and the simulated hand in lockstep on one private virtual bus, plus a
    sniffer that hears every frame, as a CAN analyser would on a bench. ``params``: the
    simulated hand's own (default: the hand config's), for a hand no config describes (one
    that starts where a config may not put it)."""
    channel = f"hil-{next(_channels)}"
    with (
        open_bus(f"virtual:{channel}", hand.bus) as peer,
        open_bus(f"virtual:{channel}", hand.bus) as host,
        open_bus(f"virtual:{channel}", hand.bus) as sniffer,
    ):
        sim = SimulatedHand(hand, peer, seed=seed, params=params)
        clock = LockstepClock(hand.bus.period_s, sim.step)
        driver = HandDriver(hand, protocol_for(hand), host, clock_ns=clock.now_ns)
        yield sim, Runtime(hand, driver, clock, recipe, max_ticks=max_ticks), sniffer


def _commands(sniffer: HandBus, hand: HandConfig) -> np.ndarray:
    """The torque commands on the wire, one row per tick (decoded with the DBC layouts)."""
    protocol = protocol_for(hand)
    rows: dict[int, list[tuple[float, ...]]] = {f.node_id: [] for f in hand.fingers}
    layouts = {
        protocol.layout("TorqueCommand", n).frame_id: (n, protocol.layout("TorqueCommand", n))
        for n in rows
    }
    for frame in sniffer.drain(limit=10**7):
        hit = layouts.get(frame.arbitration_id)
        if hit is not None:
            rows[hit[0]].append(hit[1].decode(frame.data)[1])
    n = min(len(r) for r in rows.values())
    # columns in the hand config's joint order, as the limits they are judged against
    return np.hstack(
        [np.array(rows[f.node_id][:n]).reshape(n, len(f.joints)) for f in hand.fingers]
    )


def unsafe_frames(
    wire: np.ndarray, hand: HandConfig, fault_row: int | None, category: StopCategory | None
) -> int:
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
            bad[fault_row + grace :] |= np.any(wire[fault_row + grace :] != 0, axis=1)
        else:
            ramp_end = fault_row + grace + math.ceil(RAMP_BOUND_S / hand.bus.period_s)
            bad[ramp_end:] |= np.any(wire[ramp_end:] != 0, axis=1)
            mags = np.abs(wire[fault_row:]).max(axis=1)
            rising = np.flatnonzero(np.diff(mags) > step) + fault_row + 1
            bad[rising] = True
    return int(bad.sum())


@dataclass(frozen=True)
class LoggedCase:
    """What a case's MCAP log says, read back with handctl's reader."""

    complete: bool  # footer read: the writer finished the file
    dropped: int  # records the recorder or writer dropped
    ticks: int  # /loop/timing messages
    faults: list[tuple[str, str, int]]  # (code, category, tick) of each fault event
    resets: list[int]  # ticks of the explicit reset requests
    rejects: dict[str, int]  # rejected frames by kind, summed over the events
    bus_events: int  # bus events


def read_case_log(path: Path) -> LoggedCase:
    """The events of a case's log that the campaign judges, and the log's own accounts."""
    recording = open_recording(path)
    faults: list[tuple[str, str, int]] = []
    resets: list[int] = []
    rejects: dict[str, int] = {}
    bus = ticks = 0
    for topic, _, msg in iter_decoded(recording, [ch.EVENTS, ch.TIMING]):
        if topic == ch.TIMING:
            ticks += 1
        elif msg["kind"] == "fault":
            faults.append((msg["name"], msg.get("category", ""), msg["tick"]))
        elif msg["kind"] == "request" and msg["name"] == "reset":
            resets.append(msg["tick"])
        elif msg["kind"] == "rejected_frames":
            rejects[msg["name"]] = rejects.get(msg["name"], 0) + msg.get("count", 0)
        elif msg["kind"] == "bus":
            bus += 1
    dropped = sum(recording.meta_int(ch.META_END, k, 0) for k in ch.DROPPED_KEYS)
    return LoggedCase(recording.complete, dropped, ticks, faults, resets, rejects, bus)


def judge_log(
    log: LoggedCase,
    fault: tuple[str, str, int] | None,
    reset_tick: int | None,
    rejects: dict[str, int],
    bus_events: int,
    ticks: int,
) -> bool:
    """Whether the log shows what the case showed.

    The log must be whole (finished, nothing dropped, every tick the runtime ran). A fault
    must be its first ``fault`` event, with the code, the stop category and the tick that
    detected it, and the explicit reset a ``request`` event after it. Without a fault, the
    disturbance must be counted in the log as the runtime counted it: rejected frames by kind,
    foreign ids among them, and bus events.
    """
    if not log.complete or log.dropped or log.ticks != ticks:
        return False
    if fault is not None:
        if not log.faults or log.faults[0] != fault:
            return False
        if reset_tick is not None and reset_tick not in log.resets:
            return False
        return all(t > fault[2] for t in log.resets)
    if log.faults or log.resets:
        return False
    nonzero = {k: v for k, v in rejects.items() if v}
    return log.rejects == nonzero and log.bus_events == bus_events


def _record(
    path: Path,
    hand: HandConfig,
    recipe: Recipe,
    runtime: Runtime,
    injector: str,
    phase: str,
    seed: int,
) -> Recorder:
    """Record the case the way ``handctl run recipe --log`` records a lockstep run."""
    recorder = Recorder(
        path,
        hand,
        start_metadata(hand, recipe, ["campaign", injector, phase]),
        phase_names=[p.name for p in recipe.phases],
    )
    runtime.recorder = recorder
    recorder.attach(runtime)
    recorder.add_metadata(
        ch.META_RUN,
        run_metadata(
            mode="lockstep",
            bus="virtual (fault campaign)",
            seed=seed,
            period_ns=round(hand.bus.period_s * 1e9),
            startup_ticks=runtime.startup_ticks,
            reset_node_faults=False,
            estimator=False,
            sim_faults=f"{injector} in {phase}",
        ),
    )
    return recorder


def run_case(
    hand: HandConfig, injector: str, phase: str, seed: int = 0, log: Path | None = None
) -> CaseResult:
    """One injector switched on in the middle of one phase, then an explicit reset; recorded
    to ``log`` (a temporary file when None) and judged on the log as well as on the wire."""
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "fault_campaign.yaml"
        path.write_text(campaign_recipe(hand))
        recipe = load_recipe(path, hand)
        return _run_case(
            hand, recipe, injector, phase, seed, log or Path(tmp) / f"{injector}-{phase}.mcap"
        )


def _run_case(
    hand: HandConfig, recipe: Recipe, injector: str, phase: str, seed: int, log: Path
) -> CaseResult:
    with hil_bench(hand, recipe, seed) as (sim, runtime, sniffer):
        # The writer process starts while the run goes (the rings hold far more than a case),
        # so its start-up costs the campaign no time; ``wait_ready`` after the run still
        # turns a writer that never started into an error.
        recorder = _record(log, hand, recipe, runtime, injector, phase, seed)
        with recorder:
            result, recovered, unsafe, wire, inject_tick, ticks = _drive(
                hand, injector, phase, sim, runtime, sniffer
            )
            recorder.wait_ready()
            recorder.close({"outcome": result.outcome.value, "injector": injector, "phase": phase})
        first = result.faults[0] if result.faults else None
        category = FAULTS[first.code].category if first else None
        category_name = (
            ("immediate" if category is StopCategory.IMMEDIATE else "ramp") if category else ""
        )
        latency = None
        if first is not None:
            latency = round((first.tick - inject_tick) * hand.bus.period_s * 1e3, 1)
        rejects = sum(v for k, v in result.node_rejects.items() if k != "unexpected_id")
        reset_tick = next(
            (k for k, _, event, _ in runtime.supervisor.history if event.value == "reset"), None
        )
        logged = judge_log(
            read_case_log(log),
            (first.code.name, category_name, first.tick) if first else None,
            reset_tick,
            result.node_rejects,
            result.bus_events,
            ticks,
        )
        return CaseResult(
            injector=injector,
            phase=phase,
            fault=first.code.name if first else "",
            category=category_name,
            latency_ms=latency,
            unsafe_frames=unsafe,
            frames=wire,
            recovered=recovered,
            foreign_frames=result.node_rejects.get("unexpected_id", 0),
            bus_events=result.bus_events,
            rejected_frames=rejects,
            fault_tick=first.tick if first else None,
            logged=logged,
        )


def _drive(
    hand: HandConfig,
    injector: str,
    phase: str,
    sim: SimulatedHand,
    runtime: Runtime,
    sniffer: HandBus,
) -> tuple[RunResult, bool | None, int, int, int, int]:
    """The case itself: run, inject, judge the wire, and after a fault the explicit reset.

    Returns the first run's result, whether the reset brought torque back, the unsafe frames,
    the command rows on the wire, the tick the injector was switched on, and the ticks run in
    all (both runs: tick numbers go on across a reset).
    """
    # Inject in the middle of the phase, whenever the run gets there (start-up takes as long
    # as the nodes take to answer).
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
            injected.append((tick.tick, sim.time))
            sim.faults.add(CASES[injector](hand, Targets.of(hand)), sim.time, sim.time + on_s)

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
    ticks = result.ticks
    if first is not None:
        # Nothing comes back by itself: the runtime ended and stays down. Let the fault
        # pass (the simulated hand runs on, the host silent), then reset explicitly.
        while sim.time < at + on_s + 0.05:
            sim.step()
        sniffer.drain(limit=10**7)
        recovered = runtime.reset()
        if recovered:
            runtime.tick_hooks.append(
                lambda tk: (
                    runtime.request_stop("case over")
                    if runtime.runner is not None and runtime.runner.phase_name == "holding"
                    else None
                )
            )
            again = asyncio.run(runtime.run())
            ticks = again.ticks
            more = _commands(sniffer, hand)
            steps = np.array([j.rate_limit for j in hand.joints]) * hand.bus.period_s
            recovered = (
                again.outcome in (Outcome.COMPLETED, Outcome.INTERRUPTED)
                and len(more) > 0
                and bool(np.all(np.abs(more[0]) <= steps + 1e-4))
            )
            unsafe += unsafe_frames(more, hand, None, None)
    return result, recovered, unsafe, len(wire), inject_tick, ticks


@dataclass(frozen=True)
class CaseTask:
    """One case as a task any worker can run (``handctl.executor``): the hand travels as
    data, and the log comes back as bytes when asked for, since a worker's files are not the
    caller's."""

    hand: HandConfig  # a ``portable_hand``
    injector: str
    phase: str
    seed: int = 0
    keep_log: bool = False


def run_case_task(task: CaseTask) -> tuple[CaseResult, bytes | None]:
    with tempfile.TemporaryDirectory() as tmp:
        log = Path(tmp) / f"{task.injector}-{task.phase}.mcap"
        result = run_case(local_hand(task.hand), task.injector, task.phase, task.seed, log=log)
        return result, (log.read_bytes() if task.keep_log else None)


def run_campaign(
    hand: HandConfig,
    progress: Callable[[str], None] | None = None,
    injectors: list[str] | None = None,
    log_dir: Path | None = None,
    executor: WorkPool | None = None,
    meter: Callable[[str, int], Progress] | None = None,
) -> list[CaseResult]:
    """Every case; with ``log_dir`` each case's log is kept there as INJECTOR-PHASE.mcap.

    The cases are independent, so they run as tasks of ``executor`` (default: here, one
    after another); the results come in the campaign's order wherever they ran."""
    if executor is None:
        with open_pool(workers=1) as inline:
            return run_campaign(hand, progress, injectors, log_dir, inline, meter)
    tasks = [
        CaseTask(portable_hand(hand), injector, phase, keep_log=log_dir is not None)
        for injector in injectors or list(CASES)
        for phase, _ in PHASES
    ]
    bar = meter("cases", len(tasks)) if meter is not None else None
    try:
        done = executor.map(run_case_task, tasks, bar)
    finally:
        if bar is not None:
            bar.close()
    results = []
    for r, data in done:
        if log_dir is not None and data is not None:
            (log_dir / f"{r.injector}-{r.phase}.mcap").write_bytes(data)
        results.append(r)
        if progress is not None:
            progress(
                f"{r.injector:<17} {r.phase:<13} {r.fault or 'no fault':<17} "
                f"{r.latency_ms if r.latency_ms is not None else '-':>6} ms "
                f"unsafe {r.unsafe_frames} logged {'yes' if r.logged else 'NO'}"
            )
    return results


def render_table(results: list[CaseResult]) -> str:
    """The campaign's Markdown table: one row per injector, one column group per phase."""
    lines = [
        "| injector | " + " | ".join(p for p, _ in PHASES) + " | unsafe frames | in the log |",
        "|---|" + "---|" * (len(PHASES) + 2),
    ]
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
        missing = [r.phase for r in rows if not r.logged]
        logged = "all" if not missing else "MISSING: " + ", ".join(missing)
        lines.append(
            f"| `{injector}` | "
            + " | ".join(cells)
            + f" | {sum(r.unsafe_frames for r in rows)} | {logged} |"
        )
    return "\n".join(lines)
