"""The 1 kHz tick and the run around it: start the nodes, run a recipe, stop safely.

One tick, always in this order (DESIGN.md):

1. ``clock.wait_tick()``: tick k, its time, the ticks missed before it;
2. ``hand.poll()``: drain every frame that arrived, update the joint state;
3. ``runner.step()``: the desired torques of the current phase;
4. ``supervisor.observe()`` and ``supervisor.filter()``: faults, and the applied torques;
5. ``hand.send()``: one command frame per node;
6. ``recorder.push()``: the tick's record, handed over without blocking.

Per-tick accounting (lateness, missed ticks, CPU time of each stage) is kept in bounded,
preallocated arrays (``handctl.tickstats``): the last ticks one by one, the whole run as
histograms, so neither the loop's cost nor its memory grows with the run.
"""

from __future__ import annotations

import enum
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np

from handctl.bus import BusEvent
from handctl.clock import Clock, Tick
from handctl.config import HandConfig
from handctl.drivers.hand import AppliedTorques, HandDriver
from handctl.recipes.runner import RecipeRunner, RunStatus
from handctl.recipes.schema import Recipe
from handctl.safety.faults import Fault, FaultCode
from handctl.safety.supervisor import State, Supervisor
from handctl.tickstats import DEFAULT_WINDOW, TickStats, TickWindow

#: ``feedback`` is the recipe phase's feedback and the soft-limit guard (``runner.feedback``);
#: it comes last so that the first five keep their places in recordings and benchmarks
STAGES = ("poll", "recipe", "safety", "send", "record", "feedback")
#: Ticks the loop keeps sending zero after a stop before it disables the nodes: frames in
#: flight are superseded, and the nodes see zero before they see "disable".
ZERO_TICKS_BEFORE_DISABLE = 5
STATUS_EVERY_TICKS = 100


class Outcome(enum.Enum):
    COMPLETED = "completed"
    SAFETY_STOP = "safety_stop"
    INTERRUPTED = "interrupted"
    STARTUP_FAILED = "startup_failed"


class RecordSink(Protocol):
    """Where the loop's records go. Every method returns at once: it copies numbers and goes."""

    def begin_tick(self, tick: Tick) -> None:
        """Tick ``tick`` has begun (start-up and shut-down ticks too), before its poll: the
        frames drained and sent from now on belong to it."""

    def push(self, record: TickRecord) -> None: ...

    def note(self, kind: str, detail: str, tick: int) -> None:
        """A request from outside the tick (``stop``, ``estop``, ``reset``) that takes effect
        at tick ``tick``: what a replay must repeat to reach the same torques."""


class Estimator(Protocol):
    def __call__(self, angle: np.ndarray) -> Sequence[float]: ...


@dataclass(slots=True)
class TickRecord:
    """Everything one tick saw and did. The record and its arrays are the loop's own
    buffers, refilled every tick and valid only during ``push``: the sink copies what it
    keeps."""

    tick: int
    t_ns: int
    lateness_ns: int
    missed: int
    angle: np.ndarray
    tdt: np.ndarray
    desired: np.ndarray
    applied: np.ndarray
    state: str
    phase: str
    stage_ns: tuple[int, ...]
    faults: list[Fault]


@dataclass(frozen=True)
class StatusLine:
    t_s: float
    phase: str
    state: str
    max_abs_tau: float
    lateness_us: float
    timed_out: tuple[str, ...] = ()  # phases so far that ended on their timeout, not an exit


@dataclass
class RunResult:
    outcome: Outcome
    ticks: int
    missed_ticks: int
    lateness_ns: np.ndarray  # the last ``window.lateness_ns.size`` ticks (tickstats)
    missed: np.ndarray  # ticks missed just before each of them
    stage_ns: np.ndarray  # (ticks, stages)
    window: TickWindow  # the same, with the whole run's histograms
    max_abs_tau: np.ndarray
    faults: list[Fault]
    phases: list[dict[str, Any]]
    message: str = ""
    node_rejects: dict[str, int] = field(default_factory=dict)
    unexpected_ids: dict[int, int] = field(default_factory=dict)
    bus_events: int = 0
    supervisor_history: list[tuple[int, str, str, str]] = field(default_factory=list)


class Runtime:
    """Drives one recipe on one hand through one clock."""

    def __init__(self, hand: HandConfig, driver: HandDriver, clock: Clock,
                 recipe: Recipe | None, *, recorder: RecordSink | None = None,
                 estimator: Estimator | None = None,
                 status: Callable[[StatusLine], None] | None = None,
                 reset_node_faults: bool = False, startup_timeout_s: float = 0.5,
                 max_ticks: int = 10_000_000, window_ticks: int = DEFAULT_WINDOW) -> None:
        self.hand = hand
        self.driver = driver
        self.clock = clock
        self.recipe = recipe
        self.supervisor = Supervisor(hand)
        self.runner = RecipeRunner(recipe, hand.n_joints) if recipe is not None else None
        self.recorder = recorder
        self.estimator = estimator
        self.status = status
        self.reset_node_faults = reset_node_faults
        self.startup_ticks = max(1, round(startup_timeout_s / hand.bus.period_s))
        self.max_ticks = max_ticks
        self.stop_requested = ""
        self.estop_requested = ""
        self.first_send_tick = -1
        self.startup_missed_ticks = 0
        self.tick_hooks: list[Callable[[Tick], None]] = []
        self._stats = TickStats(len(STAGES), window_ticks)
        self._max_abs = np.zeros(hand.n_joints)
        self._missed = 0
        self._ticks = 0
        self._t0_ns: int | None = None
        self._zero = np.zeros(hand.n_joints)
        self._bus_events = 0
        self._recipe_done_ns = 0
        self._feedback_ns = 0  # CPU time of this tick's feedback stage (part of the recipe's)
        #: CPU time of the loop's thread, for the per-stage accounting (a re-run, which has no
        #: use for it, puts a cheaper clock here).
        self.cpu_clock: Callable[[], int] = time.thread_time_ns
        # One record, refilled every tick: the sink copies what it keeps during ``push``.
        self._record = TickRecord(0, 0, 0, 0, self._zero, self._zero, self._zero, self._zero,
                                  "", "", (), [])

    # -- requests from outside (signal handlers, tests) -----------------------------------
    def request_stop(self, reason: str = "interrupted") -> None:
        """A controlled stop: zero torque, nodes disabled, the run ends as INTERRUPTED."""
        if not self.stop_requested:
            self.stop_requested = reason
            if self.recorder is not None:
                self.recorder.note("stop", reason, self._ticks)

    def request_estop(self, reason: str = "operator") -> None:
        self.estop_requested = reason
        if self.recorder is not None:
            self.recorder.note("estop", reason, self._ticks)

    def reset(self) -> bool:
        """The explicit reset after a safety stop: clear the latched faults, host and nodes.

        The recipe does not resume: the next ``run()`` starts it again from its first phase,
        with the nodes enabled afresh and torque ramping up from zero through the rate limit.
        """
        if self.supervisor.state is not State.FAULTED:
            return False
        self.supervisor.reset(self._ticks)
        if self.recorder is not None:
            self.recorder.note("reset", "", self._ticks)
        self.driver.node_command("fault_reset")
        if self.recipe is not None:
            self.runner = RecipeRunner(self.recipe, self.hand.n_joints)
        self.stop_requested = ""
        self.estop_requested = ""
        return True

    # -- the run --------------------------------------------------------------------------
    async def run(self) -> RunResult:
        try:
            outcome, message = await self._run()
        finally:
            self.clock.close()
        return self._result(outcome, message)

    async def _run(self) -> tuple[Outcome, str]:
        sup = self.supervisor
        # 1. Listen until every node has spoken (feedback and heartbeat); send nothing yet.
        problem = await self._startup()
        if problem:
            return Outcome.STARTUP_FAILED, problem
        # 2. Enable, with zero torque every tick from now on (the device watchdog is armed).
        tick = self._ticks
        sup.start(tick)
        self.driver.node_command("enable")
        self.first_send_tick = self._ticks  # command frame n of each node belongs to this + n
        self.startup_missed_ticks = self._missed  # before it the peer may still be starting
        stopping_since: int | None = None
        while True:
            tk = await self._tick()
            if sup.state is State.IDLE and stopping_since is None:
                stopping_since = tk.k
            if sup.state is State.FAULTED and stopping_since is None:
                stopping_since = tk.k
            if stopping_since is not None and tk.k - stopping_since >= ZERO_TICKS_BEFORE_DISABLE:
                break
            if self._ticks >= self.max_ticks:
                self.request_stop("tick budget exhausted")
        self.driver.node_command("disable")
        # One more period so the disable is on its way (in lockstep: so the hand steps once
        # more and sees it) before the bus is closed.
        tk = await self._next_tick()
        self._account_idle(tk)
        self.driver.poll(tk.now_ns)
        if sup.faults:
            return Outcome.SAFETY_STOP, "; ".join(str(f) for f in sup.faults)
        if self.stop_requested:
            return Outcome.INTERRUPTED, self.stop_requested
        return Outcome.COMPLETED, ""

    async def _startup(self) -> str:
        nodes = self.driver.nodes
        reset_sent = False
        since: int | None = None
        self.driver.discard_pending()
        for _ in range(self.startup_ticks):
            tk = await self._next_tick()
            self._account_idle(tk)
            if since is None:
                since = tk.now_ns
            self.driver.poll(tk.now_ns)
            if self.stop_requested:
                return f"stopped during start-up ({self.stop_requested})"
            # Judge the nodes on what they say now, not on what a previous run last heard:
            # fresh feedback and a fresh heartbeat from every node (the heartbeat's uptime is
            # the baseline against which a reboot during the run is recognised).
            heard = all(n.feedback_ns is not None and n.feedback_ns >= since
                        and n.heartbeat_ns is not None and n.heartbeat_ns >= since
                        for n in nodes)
            if not heard:
                continue
            faulted = [n for n in nodes if n.state == 2]
            if not faulted:
                if all(n.state == 0 for n in nodes):
                    return ""
                continue
            if not self.reset_node_faults:
                from handctl.drivers.finger import fault_names

                names = "; ".join(f"node {n.node_id} ({n.finger.name}) in FAULT "
                                  f"({', '.join(fault_names(n.fault_bits)) or 'no bits'})"
                                  for n in faulted)
                self.supervisor.trip(FaultCode.STARTUP, names, tk.k)
                return (f"{names}: check the hand, then clear the faults explicitly with "
                        "--reset-node-faults")
            if not reset_sent:
                self.driver.node_command("fault_reset", [n.node_id for n in faulted])
                reset_sent = True
        silent = []
        for n in nodes:
            who = f"node {n.node_id} ({n.finger.name})"
            if n.feedback_ns is None or since is None or n.feedback_ns < since:
                silent.append(f"{who}: no feedback")
            elif n.heartbeat_ns is None or n.heartbeat_ns < since:
                silent.append(f"{who}: no heartbeat")
            elif n.state != 0:
                silent.append(f"{who} is {n.state_name}")
        detail = "; ".join(silent) or "nodes not ready"
        self.supervisor.trip(FaultCode.STARTUP, detail, self._ticks)
        return f"nodes not ready within {self.startup_ticks} ticks: {detail}"

    async def _next_tick(self) -> Tick:
        """Every tick of the run starts here, so the recorder sees each one before its poll."""
        tk = await self.clock.wait_tick()
        if self.recorder is not None:
            self.recorder.begin_tick(tk)
        return tk

    def _account_idle(self, tk: Tick) -> None:
        if self._t0_ns is None:
            self._t0_ns = tk.scheduled_ns
        self._store(tk, (0,) * len(STAGES))

    async def _tick(self) -> Tick:
        sup = self.supervisor
        driver = self.driver
        cpu = self.cpu_clock
        tk = await self._next_tick()
        for hook in self.tick_hooks:
            hook(tk)
        c0 = cpu()
        state = driver.poll(tk.now_ns)
        events = driver.take_bus_events()
        self._bus_events += len(events)
        c1 = cpu()
        t_s = (tk.scheduled_ns - (self._t0_ns or 0)) * 1e-9
        if self.estop_requested:
            driver.estop(reason=1)  # the frame first; ``decide`` latches the fault
        desired, applied, new_faults = self.decide(tk.k, tk.now_ns, tk.missed, t_s, state.angle,
                                                   state.torque, events)
        c2, c3 = self._recipe_done_ns, cpu()
        ok = driver.send(applied)
        sup.sent(ok, tk.k)
        np.maximum(self._max_abs, np.abs(applied), out=self._max_abs)
        c4 = cpu()  # the record stage is the recording alone
        if self.recorder is not None:
            record = self._record
            record.tick, record.t_ns, record.lateness_ns, record.missed = \
                tk.k, tk.scheduled_ns, tk.lateness_ns, tk.missed
            record.angle, record.tdt, record.desired, record.applied = \
                state.angle, state.torque, desired, applied
            record.state, record.phase = sup.state.value, self._phase_name()
            fb = self._feedback_ns
            record.stage_ns = (c1 - c0, c2 - c1 - fb, c3 - c2, c4 - c3, 0, fb)
            record.faults = new_faults
            self.recorder.push(record)
        c5 = cpu()
        fb = self._feedback_ns
        self._store(tk, (c1 - c0, c2 - c1 - fb, c3 - c2, c4 - c3, c5 - c4, fb))
        if self.status is not None and tk.k % STATUS_EVERY_TICKS == 0:
            self.status(StatusLine(t_s, self._phase_name(), sup.state.value,
                                   float(np.max(np.abs(applied))), tk.lateness_ns / 1e3,
                                   self._timed_out()))
        return tk

    def decide(self, k: int, now_ns: int, missed: int, t_s: float, angle: np.ndarray,
               tdt: np.ndarray, events: Sequence[BusEvent] = ()
               ) -> tuple[np.ndarray, AppliedTorques, list[Fault]]:
        """The tick's decision from what the poll found: recipe runner (and the object
        estimator it reads), the supervisor's checks, the limiter. No bus I/O, so that
        ``handctl replay --rerun`` runs this very function on logged feedback.

        Returns the desired torques, the applied ones (the supervisor's buffer, valid until
        the next tick) and the faults latched in this tick. When the recipe part ended (CPU
        time) is left in ``_recipe_done_ns`` for the stage accounting.
        """
        sup = self.supervisor
        if self.estop_requested:
            sup.trip(FaultCode.ESTOP, self.estop_requested, k)
            self.estop_requested = ""
        self._feedback_ns = 0
        desired = self._desired(t_s, angle, tdt)
        self._recipe_done_ns = self.cpu_clock()
        new_faults = sup.observe(k, now_ns, self.driver.nodes, angle, tdt, missed, events)
        if self.stop_requested and sup.state in (State.RUNNING, State.ENABLING):
            if self.runner is not None:
                self.runner.abort(t_s, f"stopped: {self.stop_requested}")
            sup.stop(k)
        return desired, sup.filter(k, desired, missed), new_faults

    def _desired(self, t_s: float, angle: np.ndarray, tdt: np.ndarray) -> np.ndarray:
        sup = self.supervisor
        runner = self.runner
        if runner is None or sup.state is not State.RUNNING:
            return self._zero
        if runner.done:
            sup.stop(self._ticks)
            return self._zero
        estimates = self.estimator(angle) if self.estimator is not None else None
        runner.advance(t_s, angle, tdt, estimates)
        f0 = self.cpu_clock()
        desired = runner.feedback(t_s, angle, estimates)
        self._feedback_ns = self.cpu_clock() - f0
        if runner.status is RunStatus.ABORTED and not self.stop_requested:
            sup.trip(FaultCode.RECIPE_ABORT, runner.abort_reason, self._ticks)
        return desired

    def _timed_out(self) -> tuple[str, ...]:
        if self.runner is None:
            return ()
        return tuple(r.name for r in self.runner.records if r.exit.startswith("timeout"))

    def _phase_name(self) -> str:
        return self.runner.phase_name if self.runner is not None else "-"

    def _store(self, tk: Tick, stages: tuple[int, ...]) -> None:
        self._stats.store(tk.lateness_ns, tk.missed, stages)
        self._missed += tk.missed
        self._ticks += 1

    def _result(self, outcome: Outcome, message: str) -> RunResult:
        phases = []
        if self.runner is not None:
            phases = [{"name": r.name, "start_s": round(r.start_s, 6),
                       "end_s": None if r.end_s is None else round(r.end_s, 6), "exit": r.exit}
                      for r in self.runner.records]
        window = self._stats.result()
        return RunResult(
            outcome=outcome, ticks=self._ticks, missed_ticks=self._missed,
            lateness_ns=window.lateness_ns, missed=window.missed, stage_ns=window.stage_ns,
            window=window,
            max_abs_tau=self._max_abs.copy(), faults=list(self.supervisor.faults),
            phases=phases, message=message, node_rejects=self.driver.reject_counts(),
            unexpected_ids=dict(self.driver.unexpected_ids), bus_events=self._bus_events,
            supervisor_history=[(k, a.value, e.value, b.value)
                                for k, a, e, b in self.supervisor.history])
