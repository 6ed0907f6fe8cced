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
from contextlib import ExitStack, suppress
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from handctl.config import HandConfig
from handctl.convention import POSE_EVERY_TICKS  # the summaries measure the turn on these poses
from handctl.errors import ConfigError, HandctlError, said_by
from handctl.hand_protocol import protocol_for
from handctl.hostcheck import (
    LoopWork,
    Probe,
    ProbeRecord,
    beside_probe,
    host_summary,
    precheck,
    run_cpus,
)
from handctl.hostfacts import affinity, ordinary_scheduling, rttime_note
from handctl.online import timebudget
from handctl.online.bus import HandBus, open_bus
from handctl.online.buslock import BusLock, take_bus
from handctl.online.busspec import BusSpec, parse_spec, require_peers, shell_word
from handctl.online.clock import (
    LOOP_PRIORITY,
    Clock,
    Hygiene,
    LockstepClock,
    RealtimeClock,
    request_realtime,
)
from handctl.online.collector import settle_heap
from handctl.online.drivers.hand import HandDriver
from handctl.online.estimator import ObjectEstimator
from handctl.online.loop import RecordSink, RunResult, Runtime, StatusLine, TickException
from handctl.online.misstrace import MissTrace
from handctl.online.recipes.reanalysis import Reanalyser
from handctl.online.recipes.schema import Recipe
from handctl.online.safety.faults import FAULTS, FaultCode
from handctl.online.safety.recovery import Recovery
from handctl.online.tickstats import STAGES, TickWindow, percentile_us
from handctl.rivals import RivalRecord, RivalWatch
from handctl.stopsignals import StopSignals
from handctl.summary_guard import SummaryParts, least_summary, summary_head

if TYPE_CHECKING:
    from handctl.online.clock import Tick
    from handctl.recording.recorder import Recorder
    from handctl.sim.faults import FaultSchedule

#: The runtime's own tick limit when a run has no time budget: none that a run can reach.
NO_TICK_LIMIT = 1 << 62


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
    max_seconds: float | None = None  # the time budget (s): a controlled stop, TIME_BUDGET
    plot: Path | None = None  # write the overview PNG of the run here (from its recording)
    log: Path | None = None  # record the run to this MCAP file
    live_port: int | None = None  # serve the recording's channels to Foxglove on this port
    command_line: tuple[str, ...] = ()  # for the recording's metadata
    # With realtime_priority: CPUs, memory lock, prefault (docs/timing.md).
    hygiene: Hygiene = field(default_factory=Hygiene)
    # Run on a real bus even if the host fails the timing check (docs/timing.md).
    accept_missed_deadlines: bool = False
    # One joint the supervisor lets torque bring back from outside its soft limits
    # (``handctl jog --recover``; never from a recipe file). Filled in by the run.
    recovery: Recovery | None = None


@dataclass
class RunReport:
    result: RunResult
    summary: dict[str, Any]
    warnings: list[str]
    first_send_tick: int = -1  # the tick of the first torque command
    startup_missed_ticks: int = 0  # ticks missed before it
    # Real time: what the bare timer loop beside the run saw, and the loop's own missed ticks
    # as (tick, due_ns, wake_ns, missed), for ``handctl.hostcheck.attribute``.
    host: ProbeRecord | None = None
    loop_stalls: list[tuple[int, int, int, int]] = field(default_factory=list)
    # Real time: the real-time rivals seen on the loop's CPU (``handctl.rivals``).
    rivals: RivalRecord | None = None
    # Real time: the CPU time of the loop's catch-up ticks and of its usual tick.
    loop_work: LoopWork | None = None


def _percentiles_us(window: TickWindow) -> dict[str, float]:
    """Over the whole run, from its histograms (1 µs bins; the maximum is exact)."""
    hist = window.lateness_hist
    return {
        "p50": percentile_us(hist, 50),
        "p99": percentile_us(hist, 99),
        "max": round(window.lateness_max_ns / 1e3, 2),
    }


def summarise_run(
    result: RunResult, hand: HandConfig, recipe: Recipe, lockstep: bool, sim: dict[str, Any] | None
) -> dict[str, Any]:
    """The summary JSON: the fields the runtime issue names, and a few an engineer wants."""
    stages = STAGES
    return {
        **summary_head(result, hand, recipe, lockstep),
        # a phase that ran out its max_s did not do what its exits wait for: say so plainly
        "phases": [{**p, "timed_out": p["exit"].startswith("timeout")} for p in result.phases],
        "timed_out_phases": [p["name"] for p in result.phases if p["exit"].startswith("timeout")],
        "faults": [
            {
                "code": f.code.name,
                "category": FAULTS[f.code].category.name.lower(),
                "tick": f.tick,
                "detail": f.detail,
            }
            for f in result.faults
        ],
        "ticks": result.ticks,
        "missed_ticks": result.missed_ticks,
        "lateness_us": _percentiles_us(result.window),
        "stage_cpu_us_p99": {
            name: round(percentile_us(result.window.stage_hist[i], 99), 2)
            for i, name in enumerate(stages)
        },
        "max_abs_tau_nm": {
            name: round(float(v), 5)
            for name, v in zip(hand.joint_names, result.max_abs_tau, strict=True)
        },
        "rejected_frames": result.node_rejects,
        "bus_events": result.bus_events,
        # joints that sank out of their soft limits while a stop took the torque out
        **({"left_limits_in_stop": result.stop_notes} if result.stop_notes else {}),
        **({"nodes_reset": result.nodes_reset} if result.nodes_reset else {}),
        # whether the hand may still be ENABLED: what a script reading the summary most needs
        **(
            {"disable_unconfirmed": result.disable_unconfirmed}
            if result.disable_unconfirmed
            else {}
        ),
        **({"ended_in_fault": result.ended_in_fault} if result.ended_in_fault else {}),
        **({"estop_heard": result.estop_heard} if result.estop_heard else {}),
        **({"rebooted": result.rebooted} if result.rebooted else {}),
        **(
            {"exception": _exception_summary(result.exception)}
            if result.exception is not None
            else {}
        ),
        # joints whose command rang: the limits held, the joint took the swing
        **({"chatter": [asdict(r) for r in result.chatter]} if result.chatter else {}),
        # joints the recipe asked for well past what they may give: the supervisor held them
        **({"asked_beyond_tau_max_nm": asked} if (asked := asked_beyond(result, hand)) else {}),
        **({"sim": sim} if sim is not None else {}),
    }


#: a joint asked for more than its tau_max by this share of it is said; a feedback at its
#: bound asks a few per cent past it for a few ticks in an ordinary run (the guard's spring
#: on a middle joint of the nominal run: 1.3 % for 22 ticks)
ASKED_SLACK = 0.1


def asked_beyond(result: RunResult, hand: HandConfig) -> dict[str, float]:
    """N·m, each joint the recipe asked for more than ``1 + ASKED_SLACK`` times its tau_max,
    and the most it asked. The supervisor clamps every torque to tau_max, so nothing unsafe
    went out; but a pose stiffness or a torque written for another hand that asks a
    hundred times what a joint can give is a recipe that does not do what it says, and the
    run said nothing of it (only a replay's desired torques showed it)."""
    if result.max_asked_tau is None:
        return {}
    return {
        joint.name: round(float(asked), 5)
        for joint, asked in zip(hand.joints, result.max_asked_tau.tolist(), strict=True)
        if asked > joint.tau_max * (1 + ASKED_SLACK)
    }


def _run_warnings(result: RunResult, hand: HandConfig) -> list[str]:
    """What the run says beside its outcome: an exception it stopped on, joints that sank out
    of their limits in its stop, node faults it cleared at start-up, joints asked for well
    past their tau_max."""
    said = []
    if result.exception is not None:
        said.append(
            f"the run stopped on an exception ({result.exception.code.name}); "
            "the hand was stopped.\n" + result.exception.traceback.rstrip()
        )
    said += result.stop_notes
    if result.nodes_reset:
        said.append(result.nodes_reset)
    if result.disable_unconfirmed:
        said.append(result.disable_unconfirmed)
    if result.ended_in_fault:
        said.append(result.ended_in_fault)
    if result.estop_heard:
        said.append(result.estop_heard)
    if result.rebooted:
        said.append(result.rebooted)
    said += [ringing.text() for ringing in result.chatter]
    if "SIGXCPU" in result.message:
        said += rttime_note()  # at a real-time policy: which limit, and its value
    asked = asked_beyond(result, hand)
    if asked:
        tau_max = {j.name: j.tau_max for j in hand.joints}
        each = ", ".join(
            f"{name} {v:.4g} N·m (tau_max {tau_max[name]:g})" for name, v in asked.items()
        )
        said.append(
            f"the recipe asked for more than tau_max, and the supervisor held each joint to "
            f"it: {each} at the most. A torque, stiffness or gain past what the joint may "
            "give: the run was not the one the recipe describes"
        )
    return said


def _exception_summary(exc: TickException) -> dict[str, Any]:
    """The exception a run stopped on: its fault (the stage), what it said, and where."""
    return {
        "code": exc.code.name,
        "tick": exc.tick,
        "type": exc.type,
        "message": exc.message,
        "where": exc.where,
        "traceback": exc.traceback.splitlines(),
    }


def run_recipe(
    req: RunRequest,
    status: Callable[[StatusLine], None] | None = None,
    recorder: RecordSink | None = None,
    signals: StopSignals | None = None,
) -> RunReport:
    """Run ``req`` to its end (done, safety stop, or Ctrl-C/SIGTERM); never leaves torque on.

    ``signals``: the stop signals already taken over by the caller (``handctl run``, before
    it loaded the modules of a run); None: taken over here."""
    timebudget.check(req.max_seconds)
    protocol = protocol_for(req.hand)
    spec = parse_spec(req.bus, req.hand.bus, req.hand.source)
    warnings: list[str] = []
    is_sim = spec.interface == "sim"
    lockstep = _lockstep(req, is_sim)
    if is_sim and req.recipe.objects:
        from handctl.sim.params import check_scene_names

        # the experiment is measured on the simulated objects of the recipe's names
        check_scene_names(req.recipe.source, [o.name for o in req.recipe.objects], req.hand)
        warnings += _object_order(req)
        warnings += _object_sizes(req)
    sim_faults: FaultSchedule | None = None
    if is_sim and req.sim_faults is not None:
        from handctl.sim.faults import load_scenario

        # Read here, before the log is opened or a process started: a file the simulated
        # hand would refuse truncated an existing --log first, and in real time its process
        # ended with exit 2 while the host listened out its start-up (20 s, exit 3). The
        # lockstep hand takes it as read; a hand of its own process reads the file itself.
        sim_faults = load_scenario(req.sim_faults, req.hand)
    loop_cpu, sim_cpu = run_cpus(req.hygiene) if req.realtime_priority else (None, None)
    host_check: dict[str, Any] | None = None
    bus_lock = BusLock(None)  # a simulated hand's bus is this run's own
    if not is_sim:
        bus_lock, host_check, checked = _before_the_bus(spec, req, loop_cpu)
        warnings += checked
    with ExitStack() as stack:
        stack.callback(bus_lock.release)  # the last to go: after the disable and the peer
        # First in, last out: from here to the end a signal ends the run as StopSignals says;
        # until the runtime runs, at the checkpoints between the steps of the start-up.
        if signals is None:
            signals = stack.enter_context(StopSignals())
        signals.checkpoint()  # before the log: a signal so far leaves no file
        # The recording first: a log path that cannot be written is refused before anything
        # starts, and the file is finished however the run ends.
        peer_process = is_sim and not lockstep  # the simulated hand on ``sim_cpu``
        # The plot is drawn from the run's recording (``handctl.recording.plot``), the
        # replay's plot of the same log: a run asked for a plot and no log records to a
        # file of its own, gone with the run.
        log = req.log
        if log is None and req.plot is not None:
            directory = stack.enter_context(tempfile.TemporaryDirectory(prefix="handctl-"))
            log = Path(directory) / "plot.mcap"
        recording = (
            stack.enter_context(
                _recorder(
                    req, log, is_sim and lockstep, loop_cpu, sim_cpu if peer_process else None
                )
            )
            if log
            else None
        )
        if recording is not None:
            recorder = recording
        # unwound before the recorder's own exit: a start-up a signal ended finishes the log
        # with a summary that says so (it was a log of 'no summary', as if cut short), and a
        # run interrupted inside a tick with the summary of what it did
        ran: list[Runtime] = []
        stack.push(_summary_if_interrupted(recording, req, ran, lockstep))
        signals.checkpoint()
        estimator = (
            ObjectEstimator(req.hand, req.recipe.objects, req.recipe.pairs)
            if req.recipe.objects
            else None
        )
        # before the clock asks for the loop's priority and CPU, which a process started
        # later would inherit
        reanalyser = _reanalyser(stack, req, estimator, lockstep, {loop_cpu, sim_cpu})
        signals.checkpoint()
        peer = _start_peer(stack, req, spec, lockstep, sim_cpu, sim_faults)
        signals.checkpoint()
        bus: HandBus = stack.enter_context(open_bus(peer.spec, req.hand.bus))
        signals.checkpoint()
        timing = _start_clock(stack, req, peer, lockstep, loop_cpu, sim_cpu)
        signals.checkpoint()
        clock = timing.clock
        driver = HandDriver(req.hand, protocol, bus, clock_ns=clock.now_ns)
        runtime = Runtime(
            req.hand,
            driver,
            clock,
            req.recipe,
            recorder=recorder,
            status=status,
            reset_node_faults=req.reset_node_faults,
            max_ticks=NO_TICK_LIMIT,
            startup_timeout_s=peer.startup_s,
            answer_timeout_s=peer.answer_s,
            estimator=estimator,
            reanalyser=reanalyser,
        )
        ran.append(runtime)
        runtime.supervisor.recovery = req.recovery
        if peer.sim_process is not None:
            runtime.peer_gone = peer.sim_process.gone
        if isinstance(clock, RealtimeClock):
            runtime.trace = MissTrace(clock.period_ns)
            stack.callback(runtime.trace.close)
        # Ground truth of the experiment, recorded every tick and never fed back.
        tracker = None
        if peer.sim_hand is not None and req.recipe.objects:
            from handctl.experiment.merit import track

            tracker = track(runtime, peer.sim_hand)
        if req.max_seconds is not None:
            timebudget.install(runtime, req.max_seconds)
        if recording is not None:
            _start_recording(recording, runtime, req, peer.spec, lockstep, peer.sim_hand)
        signals.checkpoint()
        if recording is not None:
            # the run begins: a log at --log before it is this run's from here; a run that
            # ended before (refused, interrupted, failed to start) left it as it was
            recording.claim()
        _raise_priority(req, loop_cpu, timing, peer, warnings)
        result = timebudget.outcome(asyncio.run(signals.run(runtime)), runtime.stop_requested)
        # Each part of the account below may fail only by a bug of handctl's, with the hand
        # already stopped: it is said in the summary (``summary_errors``, exit 1) and the
        # rest is made, so the outcome, the summary file and the log's summary are not lost
        # with it (they were: a traceback, exit 1, a log of "no summary").
        parts = SummaryParts()
        warnings += parts.make("warnings", lambda: _run_warnings(result, req.hand), [])
        sim = parts.make("sim", lambda: _peer_summary(peer, warnings), None)
        summary = parts.make(
            "summary",
            lambda: summarise_run(result, req.hand, req.recipe, lockstep, sim),
            None,
        ) or least_summary(result, req.hand, req.recipe, lockstep, sim)
        parts.make("frames_lost", lambda: _frames_lost(summary, runtime.driver), None)
        # what the loop measured of its catch-up ticks and its usual one (``attribute``)
        loop_work = parts.make("loop_work", lambda: _loop_work(clock, runtime), None)
        no_host: tuple[ProbeRecord | None, RivalRecord | None] = (None, None)
        host, rivals = parts.make(
            "host",
            lambda: _host_summary(summary, req, timing, result, host_check, warnings, loop_work),
            no_host,
        )
        parts.make("experiment", lambda: _experiment_summary(summary, req, tracker, warnings), None)
        parts.said_in(summary, warnings)
        if recording is not None:
            _close_recording(recording, summary, req, warnings)
            if req.plot is not None:
                parts.make("plot", lambda: _plot(summary, req, warnings), None)
                parts.said_in(summary, warnings)
    return RunReport(
        result,
        summary,
        warnings,
        runtime.first_send_tick,
        runtime.startup_missed_ticks,
        host,
        clock.stalls.rows() if isinstance(clock, RealtimeClock) else [],
        rivals,
        loop_work,
    )


def _reanalyser(
    stack: ExitStack,
    req: RunRequest,
    estimator: ObjectEstimator | None,
    lockstep: bool,
    busy_cpus: set[int | None],
) -> Reanalyser | None:
    """The analysis at the measured configuration, for a recipe with ``reanalyse`` phases:
    on the tick in lockstep (the hand waits for it), in a process of its own in real time
    (``handctl.planning.reanalysis``), off ``busy_cpus`` (the loop's and the hand's)."""
    if estimator is None or not any(p.reanalyse is not None for p in req.recipe.phases):
        return None
    from handctl.planning.reanalysis import ReanalysisOnTick, ReanalysisWorker

    if lockstep:
        return ReanalysisOnTick(req.hand, req.recipe, estimator)
    avoid = frozenset(cpu for cpu in busy_cpus if cpu is not None)
    worker = ReanalysisWorker(req.hand, req.recipe, estimator, avoid)
    stack.callback(worker.close)
    return worker


def _lockstep(req: RunRequest, is_sim: bool) -> bool:
    """Whether the run is stepped with the simulated hand: by default on it, and only on it."""
    lockstep = is_sim if req.lockstep is None else req.lockstep
    if lockstep and not is_sim:
        raise ConfigError(
            "--lockstep", "", "the simulated hand (--bus sim): only it can be stepped", req.bus
        )
    return lockstep


@dataclass
class _Peer:
    """What the run's bus leads to: the bus to open and, on the simulated hand, the hand, in
    this process (lockstep) or in a process of its own (free-running)."""

    spec: BusSpec
    sim_hand: Any = None
    sim_process: SimProcess | None = None
    startup_s: float = 0.5  # how long the nodes may take to answer
    #: s, how long the rest may take once one node is heard; None: the whole start-up
    answer_s: float | None = None


def _start_peer(
    stack: ExitStack,
    req: RunRequest,
    spec: BusSpec,
    lockstep: bool,
    sim_cpu: int | None,
    faults: FaultSchedule | None = None,
) -> _Peer:
    """On ``--bus sim``, start the simulated hand (with ``faults``, the scenario of
    ``req.sim_faults`` as read) and name the bus it is on; any other bus is opened as it is
    named."""
    if spec.interface != "sim":
        return _Peer(spec)
    if lockstep:
        from handctl.sim.hand import SimulatedHand

        channel = f"handctl-sim-{os.getpid()}-{id(req)}"
        peer_bus = stack.enter_context(open_bus(BusSpec("virtual", channel), req.hand.bus))
        sim_hand = SimulatedHand(req.hand, peer_bus, seed=req.seed, faults=faults)
        return _Peer(BusSpec("virtual", channel), sim_hand=sim_hand)
    # Free-running, the simulated hand gets a process of its own: a busy thread in the
    # control process would take the interpreter from the loop for a millisecond at a
    # time. The two talk over the unix datagram bus.
    directory = stack.enter_context(tempfile.TemporaryDirectory(prefix="handctl-bus-"))
    sim_process = stack.enter_context(SimProcess(req, directory, sim_cpu))
    # The peer imports MuJoCo and builds its model first.
    # Once one node is heard the hand is up: a node of it still silent 2 s later is missing
    # (said after the whole 20 s before)
    return _Peer(BusSpec("unix", directory), sim_process=sim_process, startup_s=20.0, answer_s=2.0)


@dataclass
class _Timing:
    """The run's clock and, in real time, the bare timer loops beside the run (one on the
    simulated hand's CPU if it has one) and the CPUs the two processes ran on."""

    clock: Clock
    probe: Probe | None = None
    peer_probe: Probe | None = None
    rival_watch: RivalWatch | None = None
    cpus: dict[str, Any] = field(default_factory=dict)


def _start_clock(
    stack: ExitStack,
    req: RunRequest,
    peer: _Peer,
    lockstep: bool,
    loop_cpu: int | None,
    sim_cpu: int | None,
) -> _Timing:
    """The simulated hand's steps in lockstep; in real time a timer clock and the probes
    beside it (the scheduling comes last, ``_raise_priority``)."""
    if lockstep:
        return _Timing(LockstepClock(req.hand.bus.period_s, peer.sim_hand.step))
    timing = _Timing(RealtimeClock(req.hand.bus.period_s))
    timing.probe = stack.enter_context(
        beside_probe(req.hand, req.realtime_priority, loop_cpu, req.hygiene.lock_memory)
    )
    if peer.sim_process is not None and sim_cpu is not None:
        # On the hand's CPU the loop does not run: the loop's priority is above the hand.
        timing.peer_probe = stack.enter_context(
            beside_probe(
                req.hand, req.realtime_priority, sim_cpu, req.hygiene.lock_memory, LOOP_PRIORITY
            )
        )
    # Before the loop's priority is raised: starting a process at SCHED_FIFO costs the CPU.
    timing.rival_watch = stack.enter_context(
        RivalWatch(
            loop_cpu,
            LOOP_PRIORITY if req.realtime_priority else 1,
            [p.proc.pid for p in (timing.probe, timing.peer_probe) if p is not None],
            # the simulated hand, the writer, the workers: this run's own, never its rivals
            family=os.getpid(),
        )
    )
    return timing


def _raise_priority(
    req: RunRequest, loop_cpu: int | None, timing: _Timing, peer: _Peer, warnings: list[str]
) -> None:
    """With ``--rt``, the scheduling asked for, the last step before the first tick (what
    could not be had is a warning); and the CPUs the loop and the hand got.

    Last, after the heap is settled (``settle_heap``): every start-up step after the priority
    was raised (the runtime built, the recording started, the start-up heap collected in full)
    ran at SCHED_FIFO without blocking, tens of ms that held the CPU from every task below, and
    that a soft RLIMIT_RTTIME of 20 ms ended with SIGXCPU before the first tick."""
    if not isinstance(timing.clock, RealtimeClock):
        return  # lockstep: nothing to raise or place
    if req.realtime_priority:
        settle_heap()
        warnings += request_realtime(
            LOOP_PRIORITY,
            cpu=loop_cpu,
            lock_memory=req.hygiene.lock_memory,
            prefault_memory=req.hygiene.prefault,
        )
    timing.cpus = {
        "loop": affinity(0),
        "sim": affinity(peer.sim_process.proc.pid) if peer.sim_process else None,
    }


def _before_the_bus(
    spec: BusSpec, req: RunRequest, loop_cpu: int | None
) -> tuple[BusLock, dict[str, Any] | None, list[str]]:
    """What a run on a bus (not a simulated hand of its own) settles before it opens the bus
    for the run: the host lock, held from here to the run's end, nobody else commanding the
    nodes, and the host's timing check (its verdict and its warnings)."""
    # The bus is there, first: opening it sends nothing, and a bus that cannot be opened is
    # said as such (exit 4) rather than behind a verdict on the host's timing that a loaded
    # host may or may not give (it was exit 5 or 4 by the host's load). A unix bus no hand is
    # on is said as such, not made and listened out.
    require_peers(spec)
    # One handctl host per bus on this machine, taken before the listen: a first run still in
    # its start-up has sent nothing to hear (``buslock``)
    bus_lock = take_bus(spec, "this run")
    try:
        # And nobody else commands its nodes: a second run or jog beside one took real-time
        # priority on the first's CPU for its timing check before its driver heard the other
        # host and refused, and the first lost its ticks and latched every node's TIMEOUT.
        _refuse_another_host(spec, req.hand)
        # Before the bus is opened for the run: a host that cannot hold the deadlines sends
        # nothing.
        host_check, checked = precheck(
            req.hand, req.realtime_priority, loop_cpu, req.accept_missed_deadlines
        )
    except BaseException:
        bus_lock.release()
        raise
    return bus_lock, host_check, checked


def _refuse_another_host(spec: BusSpec, hand: HandConfig) -> None:
    """``BusError`` when another host is heard commanding ``hand``'s nodes on the bus before
    this run has sent anything (``otherhost.refuse_another_host``)."""
    from handctl.online.otherhost import refuse_another_host

    with open_bus(spec, hand.bus) as bus:
        refuse_another_host(bus, hand, str(spec), "this run")


def _frames_lost(summary: dict[str, Any], driver: HandDriver) -> None:
    """Into ``summary``: the frames the host's own receive queue lost (``frames_lost``), on a
    bus that tells its listener so (the unix bus; python-can's interfaces do not). Each such
    loss shows as a counter skip of the node whose frame it was, and the run said only
    "frames rejected by the host's receive checks: counter_skip 3", as if the nodes had
    skipped them (found by an outside audit of the first hour; the bring-up tools said it)."""
    bus = driver.bus
    lost = bus.transport_counts().get("rx_frames_lost") if isinstance(bus, HandBus) else None
    if lost:
        summary["frames_lost"] = lost


def _loop_work(clock: Clock, runtime: Runtime) -> LoopWork | None:
    """What a real-time loop measured of its catch-up ticks and its usual one; None in
    lockstep."""
    if not isinstance(clock, RealtimeClock):
        return None
    return LoopWork(
        clock.stalls.work_ns(),
        # a run stopped too soon for a sample after its first command: the start-up ticks'
        # (they only listen, so the usual is understated, never excused more)
        clock.usual.median_ns(runtime.first_send_tick) or clock.usual.median_ns(),
        runtime.trace.rows() if runtime.trace is not None else {},
        runtime.trace.usual_run_delay_ns() if runtime.trace is not None else -1,
        # the loop's thread is this one, which kept its scheduling after the run
        os.sched_getscheduler(0) in (os.SCHED_FIFO, os.SCHED_RR),
        os.sched_getparam(0).sched_priority,
    )


def _peer_summary(peer: _Peer, warnings: list[str]) -> dict[str, Any] | None:
    """The simulated hand's own account of the run, wherever it ran; None on a real hand."""
    if peer.sim_hand is not None:
        summary: dict[str, Any] = peer.sim_hand.ground_truth_summary()
        return summary
    if peer.sim_process is not None:
        finished = peer.sim_process.finish()
        if peer.sim_process.problem():
            warnings.append(peer.sim_process.problem())
        return finished
    return None


def _host_summary(
    summary: dict[str, Any],
    req: RunRequest,
    timing: _Timing,
    result: RunResult,
    host_check: dict[str, Any] | None,
    warnings: list[str],
    loop_work: LoopWork | None,
) -> tuple[ProbeRecord | None, RivalRecord | None]:
    """Into ``summary``: in real time, whose the missed ticks were (the host's or handctl's)
    and the CPUs; the timing check made before the bus was opened. The probe's and the rivals'
    watcher's records."""
    host: ProbeRecord | None = None
    rivals: RivalRecord | None = None
    if timing.probe is not None:
        assert isinstance(timing.clock, RealtimeClock)
        host, rivals, summary["host"] = host_summary(
            req.hand,
            timing.probe,
            timing.clock.stalls,
            result.faults,
            warnings,
            timing.peer_probe,
            timing.rival_watch,
            loop_work,
            result.ticks * req.hand.bus.period_s,
        )
        summary["host"]["cpus"] = timing.cpus
    if host_check is not None:
        summary["host_check"] = host_check
    return host, rivals


def _object_order(req: RunRequest) -> list[str]:
    """A warning when the recipe lists its objects in another order than the simulated hand's
    scene lays them along the palm: the estimator names the objects in the recipe's order
    along the palm (``handshape.palm_ends``), so each estimate, and every exit and feedback
    on it, would read another object's (pair errors of 179 degrees, without a word)."""
    from handctl.handshape import order_along_palm
    from handctl.sim.params import parse_sim

    names = [o.name for o in req.recipe.objects]
    if len(names) < 2:
        return []
    scene = {o.name: (o.x, o.y) for o in parse_sim(req.hand).objects}
    along = order_along_palm(req.hand, {name: scene[name] for name in names})
    if along == names:
        return []
    return [
        f"{req.recipe.source}: objects are listed {', '.join(names)}, but the simulated "
        f"hand's scene lays them {', '.join(along)} along the palm (from the finger base of "
        "the smaller x): the estimator names them in the recipe's order, so each estimate "
        "reads another object's; list them in their order along the palm"
    ]


def _object_sizes(req: RunRequest) -> list[str]:
    """A warning for each of the recipe's objects whose radius in the simulated hand's scene is
    further from the recipe's than the estimator fits (``RADIUS_RANGE``): it cannot measure
    such an object, so every exit and feedback on its estimates reads a wrong one. A recipe
    written for 20 mm cylinders ran on a scene of 5 and 30 mm ones without a word."""
    from handctl.online.estimator import RADIUS_RANGE
    from handctl.sim.params import parse_sim

    scene = {o.name: o.radius for o in parse_sim(req.hand).objects}
    out = []
    for obj in req.recipe.objects:
        actual = scene[obj.name]
        low, high = obj.radius * (1.0 - RADIUS_RANGE), obj.radius * (1.0 + RADIUS_RANGE)
        if not low <= actual <= high:
            out.append(
                f"{req.recipe.source}: {obj.name}'s radius is {obj.radius * 1e3:g} mm in the "
                f"recipe and {actual * 1e3:g} mm in the simulated hand's scene: the estimator "
                f"fits a radius within ±{RADIUS_RANGE * 100:g} % of the recipe's "
                f"({low * 1e3:.3g} to {high * 1e3:.3g} mm), so it cannot measure this one, "
                "and its estimates, with every exit and feedback on them, are off"
            )
    return out


def _experiment_summary(
    summary: dict[str, Any], req: RunRequest, tracker: Any, warnings: list[str]
) -> None:
    """Into ``summary``: how the objects moved (the simulated hand's ground truth)."""
    if tracker is not None:
        from handctl.experiment.merit import experiment_summary

        summary["experiment"] = experiment_summary(
            tracker.trace, req.recipe.min_total_turn_deg, summary["outcome"]
        )


def _plot(summary: dict[str, Any], req: RunRequest, warnings: list[str]) -> None:
    """The run's plot, from its finished recording; the recording of a run that was recorded
    only for it is left out of the summary (its file goes with the run)."""
    from handctl.recording.plot import plot_log
    from handctl.wholefile import PictureNotWrittenError

    assert req.plot is not None
    recorded = summary["recording"] if req.log else summary.pop("recording")
    if "error" in recorded:
        warnings.append(f"no plot written: the run's recording failed ({recorded['error']})")
        # a file the run was told to write and did not: the exit says so (cli), not only
        # a warning above a run that exited 0
        summary["plot"] = {"path": str(req.plot), "error": "the run's recording failed"}
        return
    try:
        plot_log(Path(recorded["path"]), req.plot)
    except (OSError, HandctlError) as exc:
        # after the run, as a log that could not be finished: said, never raised (a
        # traceback, the summary never printed or written, and an exit 1 or 2 that hid a
        # safety stop)
        why = exc.why if isinstance(exc, PictureNotWrittenError) else str(exc)
        warnings.append(f"--plot: no plot written to {req.plot} ({why})")
        summary["plot"] = {"path": str(req.plot), "error": why}
        return
    summary["plot"] = {"path": str(req.plot)}


def interrupted_summary(req: RunRequest, why: str) -> dict[str, Any]:
    """The summary of a run a stop signal ended before its runtime ran (at a start-up
    checkpoint): nothing was sent to the hand, no tick ran."""
    return {
        "recipe": req.recipe.name,
        "hand": req.hand.name,
        "outcome": "interrupted",
        "message": f"{why or 'interrupted'} during the start-up, before the first tick: "
        "nothing was sent to the hand",
        "ticks": 0,
    }


class RunInterrupted(KeyboardInterrupt):
    """A KeyboardInterrupt (or a cancellation) that ended a run, with the run's summary:
    what ran, or that nothing was sent if it came before the first tick."""

    def __init__(self, why: str, summary: dict[str, Any]) -> None:
        super().__init__(why)
        self.summary = summary


def _summary_if_interrupted(
    recording: Recorder | None, req: RunRequest, ran: list[Runtime], lockstep: bool
) -> Callable[[type[BaseException] | None, BaseException | None, object], bool]:
    def finish(kind: object, exc: BaseException | None, tb: object) -> bool:
        # a CancelledError raised inside a tick ends the run as an interrupt does (the loop
        # sent zero and a disable at once); it crashed the command with a traceback, no summary
        interrupt = isinstance(exc, (KeyboardInterrupt, asyncio.CancelledError))
        if exc is None or not interrupt or isinstance(exc, RunInterrupted):
            return False
        result = ran[0].interrupted if ran else None
        summary = (
            interrupted_summary(req, said_by(exc))
            if result is None
            else summarise_run(result, req.hand, req.recipe, lockstep, None)
        )
        if recording is not None and not recording.closed:
            with suppress(HandctlError):  # said by the recorder's own exit
                recording.close(summary)
            recording.say_if_previous_kept()
        raise RunInterrupted(summary["message"], summary) from exc

    return finish


def _close_recording(
    recording: Recorder, summary: dict[str, Any], req: RunRequest, warnings: list[str]
) -> None:
    """Finish the file with the summary; a log that could not be finished is said, not
    raised: the run is over and the hand is safe."""
    try:
        summary["recording"] = recording.close(summary)
        notes = summary["recording"].get("writer_notes")
        if notes:
            warnings.extend(str(notes).splitlines())
    except HandctlError as exc:
        warnings.append(str(exc))
        summary["recording"] = {"path": str(recording.path), "error": str(exc)}


def _recorder(
    req: RunRequest, log: Path, lockstep_sim: bool, loop_cpu: int | None, sim_cpu: int | None
) -> Recorder:
    from handctl.recording.channels import pose_pairs
    from handctl.recording.metadata import start_metadata
    from handctl.recording.recorder import Recorder, writer_cpus

    objects: list[str] = []
    if lockstep_sim:
        from handctl.sim.params import parse_sim

        objects = [o.name for o in parse_sim(req.hand).objects]
    # the lines the recipe measures (its pairs), not those of the first two objects
    named = [(req.recipe.objects[a].name, req.recipe.objects[b].name) for a, b in req.recipe.pairs]
    return Recorder(
        log,
        req.hand,
        start_metadata(req.hand, req.recipe, req.command_line),
        phase_names=[p.name for p in req.recipe.phases],
        object_names=objects,
        object_pairs=pose_pairs(objects, named),
        live_port=req.live_port,
        cpus=writer_cpus(loop_cpu, sim_cpu),
        keep_previous=True,
    )


#: s between two looks at whether the recording writer still runs (``_WriterWatch``)
WRITER_WATCH_S = 0.1


class _WriterWatch:
    """A tick hook: the recording writer's process ended while the run goes on (killed, out
    of memory, a crash), or the records it has not taken overflowed the rings (a writer
    stopped, a disk that hangs, a live view's clients holding it back), is a ramp stop,
    RECORDING_LOST. The run went on driving the hand unrecorded to its end (minutes on a
    whole recipe) and said so only then (found by outside audits: a writer stopped for 12 s
    lost 4530 ticks of a 13771-tick run, exit 1 at its end). The log removed during the run
    (``rm``, its directory) is the same: the recording has no name left. One ``waitpid``, a
    read of the drop counts and an ``fstat`` every ``WRITER_WATCH_S``; said once."""

    def __init__(self, recording: Recorder, runtime: Runtime) -> None:
        self.recording = recording
        self.runtime = runtime
        self.every = max(1, round(WRITER_WATCH_S / runtime.hand.bus.period_s))
        self.said = False

    def __call__(self, tk: Tick) -> None:
        if self.said or tk.tick % self.every:
            return
        code = self.recording.process.poll()
        dropped = self.recording.dropped_records()
        removed = self.recording.log_removed()
        if code is None and not dropped and not removed:
            return
        self.said = True
        if code is not None:
            from handctl.recording.recorder import how_it_ended  # imported with the recorder

            what = f"the recording writer ended ({how_it_ended(code)})"
        elif removed:
            what = (
                "the log was removed (or its directory) while the run recorded to it: what "
                "the writer goes on writing has no name, and is lost when it closes"
            )
        else:
            what = (
                f"the recording writer has not taken the run's records in time ({dropped} "
                "dropped: its rings overflowed; the writer stopped, its disk hangs, or a "
                "live view's clients hold it back)"
            )
        self.runtime.supervisor.trip(
            FaultCode.RECORDING_LOST,
            f"{self.recording.path}: {what}; the run was stopped rather than drive the hand "
            "unrecorded",
            tk.tick,
        )


def _start_recording(
    recording: Recorder,
    runtime: Runtime,
    req: RunRequest,
    spec: BusSpec,
    lockstep: bool,
    sim_hand: Any,
) -> None:
    """Tap the runtime, note how it is set up, and (lockstep) sample the objects' poses."""
    from handctl.recording.channels import META_RUN
    from handctl.recording.metadata import run_metadata

    recording.attach(runtime)
    recording.add_metadata(
        META_RUN,
        run_metadata(
            mode="lockstep" if lockstep else "realtime",
            bus=f"{req.bus} ({spec})",
            seed=req.seed,
            period_ns=round(req.hand.bus.period_s * 1e9),
            startup_ticks=runtime.startup_ticks,
            answer_ticks=runtime.answer_ticks,
            reset_node_faults=req.reset_node_faults,
            estimator=runtime.estimator is not None,
            sim_faults=str(req.sim_faults or ""),
        ),
    )
    if sim_hand is not None:
        every = POSE_EVERY_TICKS

        def sample_poses(tk: Tick) -> None:
            if tk.tick % every == 0:
                recording.poses([(o.x, o.y, o.angle) for o in sim_hand.ground_truth().objects])

        runtime.tick_hooks.append(sample_poses)
    if req.log is not None:  # a log asked for; a plot's own recording stops nothing
        runtime.tick_hooks.append(_WriterWatch(recording, runtime))
    recording.wait_ready()
    if req.live_port is not None:
        # said once the writer has bound its port: said as the run started, a client that
        # connected when told was refused for a second
        from handctl.foxglove import HOST  # not ``live``: the SDK stays out of this process
        from handctl.progress import say

        # the hand's file as a shell word with its control characters escaped: quoted by
        # ``shlex`` alone, an escape sequence in its name reached the terminal raw
        say(
            f"live: Foxglove WebSocket on ws://{HOST}:{req.live_port} "
            f"(its layout: handctl layout {shell_word(req.hand.source)} -o LAYOUT.json)"
        )


#: How long the simulated hand's process has to end on SIGINT, writing its summary, before it
#: is killed (s). It writes within a second; longer is a process stopped (SIGSTOP) or hung.
SIM_FINISH_S = 10.0
#: How the simulated hand's process ends on this process's SIGINT before it listens:
#: ``handctl sim``'s exit 130, or, while the interpreter itself starts, by the signal.
STOPPED_UNHEARD = (130, -signal.SIGINT)


class SimProcess:
    """The simulated hand as a separate process (``handctl sim``) on a unix datagram bus.

    Its stderr (a progress line a second) goes to ``sim.log`` beside the bus sockets, not to a
    pipe: nobody reads a pipe during the run, and a full one (64 KiB, some ten minutes of
    progress) would stop the hand mid-run. What it said is kept for a hand that fails.

    It lives and dies with this process. It runs in a session of its own, so a Ctrl-C on the
    terminal (SIGINT to the whole foreground process group) reaches only the host, whose stop
    ramp needs the hand's feedback; the host stops it after the ramp. ``--parent-pid`` makes it
    end when this process ends however it ends (``kill -9`` included), and then remove the bus
    directory, which this process can no longer do."""

    def __init__(self, req: RunRequest, directory: str, cpu: int | None = None) -> None:
        self.summary_path = Path(directory) / "sim-summary.json"
        self.log_path = Path(directory) / "sim.log"
        cmd = [
            sys.executable,
            "-m",
            "handctl",
            "sim",
            "--bus",
            f"unix:{directory}",
            "--hand",
            req.hand.source,
            "--seed",
            str(req.seed),
            "--summary-json",
            str(self.summary_path),
            "--parent-pid",
            str(os.getpid()),
        ]
        if req.hand.dbc is not None:
            cmd += ["--dbc", req.hand.dbc]
        if req.sim_faults is not None:
            cmd += ["--faults", str(req.sim_faults)]
        if req.realtime_priority:
            # A real-time run gets a real-time hand: the real one has a controller per finger;
            # this one shares two cores with everything else on the machine.
            cmd.append("--rt")
        with self.log_path.open("wb") as log:
            self.proc = subprocess.Popen(
                cmd, stdout=subprocess.DEVNULL, stderr=log, start_new_session=True
            )
        if not req.realtime_priority:
            # Not the scheduling this process was started with (a caller's ``chrt -f 90``):
            # a hand above the loop it serves, blamed as the loop's real-time rival. With
            # --rt it sets its own (SIM_RT_PRIORITY), which this must not race to undo.
            ordinary_scheduling(self.proc.pid)
        if cpu is not None:
            # Now, while the child has one thread: the node timer thread it starts inherits it.
            with suppress(ProcessLookupError):  # gone already: problem() says why
                os.sched_setaffinity(self.proc.pid, {cpu})
        self.summary: dict[str, Any] | None = None
        self.stopped = False  # by finish(): its SIGINT sent while the process was alive
        self.killed = False  # by finish(), after it did not end on SIGINT

    def finish(self) -> dict[str, Any] | None:
        """Stop the peer (SIGINT: it writes its ground truth) and read what it wrote."""
        if self.proc.poll() is None:
            self.stopped = True
            self.proc.send_signal(signal.SIGINT)
            try:
                self.proc.wait(timeout=SIM_FINISH_S)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
                self.killed = True
        if self.summary is None and self.summary_path.exists():
            self.summary = json.loads(self.summary_path.read_text())
        return self.summary

    def gone(self) -> str:
        """What the simulated hand said if its process has ended, else ""."""
        return "" if self.proc.poll() is None else self.problem()

    def problem(self) -> str:
        """Empty if the simulated hand ended well; else its exit and the end of its log."""
        if self.summary is not None and self.proc.returncode == 0:
            return ""
        if (
            self.stopped
            and not self.killed
            and self.summary is None
            and self.proc.returncode in STOPPED_UNHEARD
        ):
            # this process's SIGINT ended it before it listened (a run stopped during its
            # start-up; a hand that listened writes its summary): the stop was the host's,
            # not the hand's failure. It was said as one ("ended with exit 130 and no
            # summary: handctl: interrupted", found by an outside audit). One that ended by
            # itself is still said, and so is one that listened and then ended on 130 (a
            # SIGTERM of its own, then this process's SIGINT while it waited for it)
            return ""
        tail = (
            self.log_path.read_text(errors="replace").strip().splitlines()[-5:]
            if self.log_path.exists()
            else []
        )
        if self.killed:
            # its -9 is this process's doing: say why, or it reads as the hand's own crash
            ended = (
                f"did not end within {SIM_FINISH_S:g} s of SIGINT (stopped or hung?) and "
                "was killed (SIGKILL), with"
            )
        else:
            ended = f"ended with exit {self.proc.returncode} and"
        return (
            f"the simulated hand's process {ended} "
            f"{'its summary' if self.summary is not None else 'no summary'}"
            + (": " + " | ".join(tail) if tail else "")
        )

    def __enter__(self) -> SimProcess:
        return self

    def __exit__(self, *exc: object) -> None:
        self.finish()
