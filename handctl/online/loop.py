"""The 1 kHz tick and the run around it: start the nodes, run a recipe, stop safely.

One tick, always in this order (docs/architecture.md, "One tick"):

1. ``clock.wait_tick()``: the tick's number, its time, the ticks missed before it;
2. ``hand.poll()``: drain every frame that arrived, update the joint state;
3. ``runner.step()``: the desired torques of the current phase;
4. ``supervisor.observe()`` and ``supervisor.filter()``: faults, and the applied torques;
5. ``hand.send()``: one command frame per node;
6. ``recorder.push()``: the tick's record, handed over without blocking.

An exception in any stage is a safety stop, not a crash: the stage it came from (read from
the traceback afterwards, so the tick pays nothing for it) latches a fault of its own code,
and the nodes get zero torque and then a disable from frames the driver encoded at start-up,
through a path that touches none of the stages (``Runtime._stop_after_exception``).

Per-tick accounting (lateness, missed ticks, CPU time of each stage) is kept in bounded,
preallocated arrays (``handctl.online.tickstats``): the last ticks one by one, the whole run as
histograms, so neither the loop's cost nor its memory grows with the run.
"""

from __future__ import annotations

import asyncio
import contextlib
import enum
import os
import time
import traceback
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from types import FrameType
from typing import Any, Protocol

import numpy as np

import handctl
from handctl import protocol as wire
from handctl.config import HandConfig
from handctl.errors import said_by
from handctl.online.bus import BusEvent, BusEventKind
from handctl.online.clock import Clock, Tick
from handctl.online.collector import LoopCollector
from handctl.online.drivers import finger, receiver
from handctl.online.drivers.hand import (
    ESTOP_HOST_SAFETY,
    ESTOP_OPERATOR,
    AppliedTorques,
    HandDriver,
    JointState,
)
from handctl.online.misstrace import (
    NOTE_BUS_EVENT,
    NOTE_COLLECT,
    NOTE_FAULT,
    NOTE_PHASE,
    NOTE_STATE,
    NOTE_STATUS,
    MissTrace,
)
from handctl.online.recipes import runner as recipe_runner
from handctl.online.recipes.backoff import RateBackoff
from handctl.online.recipes.reanalysis import Reanalyser
from handctl.online.recipes.runner import RecipeRunner, RunStatus
from handctl.online.recipes.schema import MeasuredSizes, Recipe
from handctl.online.safety import faults as safety_faults
from handctl.online.safety.chatter import ChatterWatch, Ringing
from handctl.online.safety.faults import Fault, FaultCode
from handctl.online.safety.supervisor import State, Supervisor
from handctl.online.safety.watchdog import StartupRejects, ticks_lasting
from handctl.online.tickstats import DEFAULT_WINDOW, STAGES, TickStats, TickWindow
from handctl.protocol import NodeState

#: Ticks the loop keeps sending zero after a stop before it disables the nodes: frames in
#: flight are superseded, and the nodes see zero before they see "disable".
ZERO_TICKS_BEFORE_DISABLE = 5
#: After the disable, the ticks a run listens for every node to report it (s): the nodes' own
#: command watchdog (10 ms) would stop a node the frame missed by then anyway (FAULT, TIMEOUT).
DISABLE_CONFIRM_S = 0.010
#: periods after the disable from which a node's Feedback still saying ENABLED is a node that
#: disobeys it (one sent before the node acted on the disable arrives within two: the node's
#: tick and the bus), and the host sends the e-stop
DEFIANT_AFTER_PERIODS = 3
STATUS_EVERY_TICKS = 100
#: The bus events that end the start-up with nothing enabled, each an immediate stop in a run
#: (safety.md #41): the start-up enabled every node and the run stopped on it at its first
#: running tick. The other bus events wait for that tick, as ever.
REFUSE_STARTUP = {
    BusEventKind.BUS_OFF: (FaultCode.BUS_ERROR, "bus-off"),
    BusEventKind.RX_BACKLOG: (FaultCode.RX_BACKLOG, "receive backlog"),
}
#: A tick of the stop after an exception waits this long at most for the clock; a clock that
#: does not answer is given up and the rest of the stop's frames go at once, in order.
STOP_TICK_TIMEOUT_S = 0.1
#: A clock that gives no tick for this long (s) while the run waits for one has stopped: its
#: fault (``CLOCK_EXCEPTION``, ``ClockSilentError``) and the stop after an exception. A real-time
#: clock whose timer callback raised was waited for forever, deaf to the stop signals (found
#: by an outside audit). Seconds, far above any stall of a loaded host (tens of ms); the time
#: the process did not run (SIGSTOP, a blocked loop) is not counted (``Runtime._watch_clock``).
CLOCK_SILENT_S = 2.0
#: What ends a run as an interrupt (zero and a disable at once, then it goes on) and not as a
#: broken stage's safety stop: every other BaseException is a stage's (``Runtime.run``).
INTERRUPTS = (KeyboardInterrupt, asyncio.CancelledError)
#: An exception's message is cut to this many characters, so that the fault with its place
#: fits in one event of the log (480 bytes) and a message never carries a huge object.
EXCEPTION_TEXT_CHARS = 200


#: The phase name of a run without a recipe (the record and the status line alike).
NO_PHASE = "-"


def _any_heard(nodes: Sequence[finger.FingerNode], since: int) -> bool:
    """Whether a frame of any node has come in since ``since`` (ns): the hand is there."""
    return any(
        (n.feedback_ns is not None and n.feedback_ns >= since)
        or (n.heartbeat_ns is not None and n.heartbeat_ns >= since)
        for n in nodes
    )


def _times(n: int) -> str:
    """How many times something happened, in words a person reads: "once", "twice", "3 times"."""
    return {1: "once", 2: "twice"}.get(n, f"{n} times")


def _no_feedback(rejects: dict[str, int]) -> str:
    """Why no feedback of a node was taken at start-up: none came, or frames came and every
    one was rejected (a bad CRC, a second sender on its ids), which points elsewhere than a
    silent node does (power, wiring) and is said with the counts."""
    heard = {kind: n for kind, n in rejects.items() if n}
    if not heard:
        return "no feedback"
    kinds = ", ".join(f"{kind} {n}" for kind, n in heard.items())
    return (
        f"no feedback accepted: {sum(heard.values())} frames heard and rejected ({kinds}); "
        "`handctl nodes` shows them"
    )


class _Survive:
    """``contextlib.suppress`` of whatever is raised but an interrupt (``INTERRUPTS``, which
    go on): for the parts of a stop that the stop does not need, SystemExit included."""

    def __enter__(self) -> None:
        return None

    def __exit__(self, kind: object, exc: BaseException | None, tb: object) -> bool:
        return exc is not None and not isinstance(exc, INTERRUPTS)


class ClockSilentError(Exception):
    """The clock gave no tick for ``Runtime.clock_silent_s`` while the run waited for one."""


class EndOfTicks(Exception):  # noqa: N818 - an end, not an error
    """A lockstep clock has no more ticks to give (a re-run reaching the end of its log): the
    run ends where it stands, sending nothing more, and this propagates to the caller.

    Only a lockstep clock may end a run this way; from a real-time clock it is an exception
    like any other, and the hand is stopped."""


class Outcome(enum.Enum):
    COMPLETED = "completed"
    SAFETY_STOP = "safety_stop"
    INTERRUPTED = "interrupted"
    TIME_BUDGET = "time_budget"  # stopped (controlled) at the run's time budget, as asked
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


class Estimator(MeasuredSizes, Protocol):
    """The object estimator as the loop uses it: the estimates of a tick, and the objects'
    measured sizes a phase's ``schedule`` chooses on."""

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
    """Where a run is, for a person watching it: a line every ``STATUS_EVERY_TICKS``."""

    t_s: float  # since the run's first tick; simulated time when ``simulated``
    phase: str
    state: str
    max_abs_tau: float  # N·m, over the joints, this tick
    lateness_us: float
    timed_out: tuple[str, ...] = ()  # phases so far that ended on their timeout, not an exit
    phase_number: int = 0  # 1..phase_count while a phase runs; 0 before, phase_count + 1 after
    phase_count: int = 0
    phase_s: float = 0.0  # time in the current phase (s)
    simulated: bool = False  # a lockstep clock: the times are the simulated hand's, not wall


@dataclass(frozen=True)
class TickException:
    """An exception that ended a run, as the fault it became."""

    code: FaultCode  # the stage it came from
    tick: int
    type: str
    message: str  # cut to EXCEPTION_TEXT_CHARS
    where: str  # the innermost frame: function (file:line)
    traceback: str  # the last frames and the exception, for whoever fixes the cause

    @property
    def detail(self) -> str:
        return f"{self.type}: {self.message} (in {self.where})"


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
    exception: TickException | None = None  # what raised, when the run ended on one
    #: joints that left their soft limits in a controlled stop, not by their own torque
    #: (``Supervisor._left_while_stopping``): not faults, said
    stop_notes: list[str] = field(default_factory=list)
    #: the nodes' faults ``--reset-node-faults`` cleared at start-up ("": none)
    nodes_reset: str = ""
    #: nodes not heard DISABLED after the run's disable ("": every one was)
    disable_unconfirmed: str = ""
    #: nodes in FAULT at the end that no fault of the run stands for ("": none)
    ended_in_fault: str = ""
    #: e-stop frames another sender put on the bus, which every node obeys ("": none)
    estop_heard: str = ""
    #: nodes a Heartbeat says rebooted after the torque was armed, that no fault names
    rebooted: str = ""
    #: joints whose command rang (``safety.chatter``)
    chatter: list[Ringing] = field(default_factory=list)
    #: N·m, per joint, the largest |desired torque| the recipe asked for (finite values)
    max_asked_tau: np.ndarray | None = None


class Runtime:
    """Drives one recipe on one hand through one clock."""

    def __init__(
        self,
        hand: HandConfig,
        driver: HandDriver,
        clock: Clock,
        recipe: Recipe | None,
        *,
        recorder: RecordSink | None = None,
        estimator: Estimator | None = None,
        reanalyser: Reanalyser | None = None,
        status: Callable[[StatusLine], None] | None = None,
        reset_node_faults: bool = False,
        startup_timeout_s: float = 0.5,
        answer_timeout_s: float | None = None,
        max_ticks: int = 10_000_000,
        window_ticks: int = DEFAULT_WINDOW,
    ) -> None:
        self.hand = hand
        self.driver = driver
        self.clock = clock
        self.recipe = recipe
        # on the grid of the frames it drives (``limit_torque``)
        self.supervisor = Supervisor(hand, driver.protocol)
        # the analysis at the measured configuration, for a recipe's ``reanalyse`` phases
        self.reanalyser = reanalyser
        self.estimator = estimator
        self.runner = self._new_runner()
        self.recorder = recorder
        self.status = status
        self.reset_node_faults = reset_node_faults
        self.startup_ticks = max(1, round(startup_timeout_s / hand.bus.period_s))
        # once any node is heard, the rest have this long to answer: a simulated hand in a
        # process of its own may take the whole start-up to import and build, and a node of
        # it that stays silent was said only once all of it (20 s) had passed
        self.answer_ticks = (
            self.startup_ticks
            if answer_timeout_s is None
            else max(1, round(answer_timeout_s / hand.bus.period_s))
        )
        self.max_ticks = max_ticks
        #: s, how long the clock may give no tick (``CLOCK_SILENT_S``; a test shortens it)
        self.clock_silent_s = CLOCK_SILENT_S
        #: ticks the clock has given, whether the run waits for one now, and whether the
        #: watch found it silent (``_watch_clock``)
        self._clock_ticks = 0
        self._clock_waiting = False
        self._clock_silent = False
        self._clock_watch: asyncio.TimerHandle | None = None
        self.stop_requested = ""
        #: the stops asked for during the stop after an exception (None: not in one), said in
        #: its message: they went unsaid, the signals of README's last line lost
        self._asked_in_stop: list[str] | None = None
        self.estop_requested = ""
        self._stop_notes_said = 0  # of ``supervisor.stop_notes``, in the log
        #: the nodes' faults ``--reset-node-faults`` cleared at start-up ("": none)
        self.nodes_reset = ""
        self.disable_unconfirmed = ""
        #: nodes in FAULT at the end that no fault of the run stands for ("": none)
        self.ended_in_fault = ""
        #: nodes rebooted after the torque was armed that no fault names ("": none)
        self.rebooted = ""
        #: whether the e-stop went to nodes still ENABLED after the disable
        self._estop_at_the_end = False
        #: The e-stop the nodes are owed, by its reason (``ESTOP_*``; 0: none), and how many
        #: times the bus refused it: one the bus refuses (a full transmit queue) is sent
        #: again on every tick after, to the run's end, until one goes (``_owe_estop``).
        #: Before, the operator's e-stop and a second master's went once: refused, nothing
        #: was said, and no node latched FAULT (ESTOP) (found by an outside audit).
        self._estop_owed = 0
        self._estop_refusals = 0
        #: The disable at the end: whether the nodes are still owed it (a frame of it
        #: refused, and no e-stop in its place), how many times the bus refused it, and
        #: whether an e-stop went in its place. One the bus refuses is sent again on every
        #: tick of the wait for the nodes' DISABLED: it was tried three times within
        #: microseconds, and against a full transmit queue the run ended "completed", exit
        #: 0, with the nodes ENABLED (found by an outside audit).
        self._disable_owed = False
        self._disable_refusals = 0
        self._disable_estopped = False
        #: The nodes whose enable the bus refused, and how many times it refused one: sent
        #: again on every tick of the enabling until it goes (the supervisor's enable
        #: deadline bounds it); one that never went is said as the bus's, not the nodes'.
        self._enable_owed: list[int] = []
        self._enable_refusals = 0
        #: a peer process the start-up waits for (the simulated hand of a real-time run):
        #: what it said if it has ended, else ""; asked every start-up tick, so that a hand
        #: that died is said at once and not after the whole start-up timeout (20 s)
        self.peer_gone: Callable[[], str] | None = None
        self.first_send_tick = -1
        self.startup_missed_ticks = 0
        self.tick_hooks: list[Callable[[Tick], None]] = []
        #: Garbage collection between ticks only, for the length of ``run`` (collector.py).
        self.collector = LoopCollector()
        self._stats = TickStats(len(STAGES), window_ticks)
        self._max_abs = np.zeros(hand.n_joints)
        self._max_asked = np.zeros(hand.n_joints)  # N·m, what the recipe asked (``asked_beyond``)
        self._asked = np.empty(hand.n_joints)  # scratch for it: the tick allocates nothing
        #: joints whose command rings (a feedback too stiff for them)
        self.chatter = ChatterWatch(
            hand.joint_names, np.array([j.tau_max for j in hand.joints]), hand.bus.period_s
        )
        self._missed = 0
        self.tick = 0  # the number of the tick under way (or next): as many have run before it
        self._t0_ns: int | None = None
        self._zero = np.zeros(hand.n_joints)
        self._bus_events = 0
        self._recipe_done_ns = 0
        self.exception: TickException | None = None
        #: The run's result up to a KeyboardInterrupt or cancellation that ended it
        #: (``_keep_interrupted``); None otherwise.
        self.interrupted: RunResult | None = None
        #: s, the recipe time of the last tick that began its stages: where a phase that an
        #: exception or an interrupt ends, ends.
        self._t_s = 0.0
        self._feedback_ns = 0  # CPU time of this tick's feedback stage (part of the recipe's)
        self._feedback_start_ns = -1  # when it began, if it ran this tick
        #: CPU time of the loop's thread, for the per-stage accounting (a re-run, which has no
        #: use for it, puts a cheaper clock here).
        self.cpu_clock: Callable[[], int] = time.thread_time_ns
        # One record, refilled every tick: the sink copies what it keeps during ``push``.
        self._record = TickRecord(
            0, 0, 0, 0, self._zero, self._zero, self._zero, self._zero, "", "", (), []
        )
        #: The supervisor state whose name the record holds.
        self._record_state: State | None = None
        #: What the tick before each late wake-up did (a real-time run's; None: not kept).
        self.trace: MissTrace | None = None
        self._traced_state: State | None = None  # the state and phase the trace last saw
        self._traced_phase = -1

    # -- requests from outside (signal handlers, tests) -----------------------------------
    def request_stop(self, reason: str = "interrupted") -> None:
        """A controlled stop: zero torque, nodes disabled, the run ends as INTERRUPTED."""
        if self._asked_in_stop is not None:  # a stop under way already, whatever is asked
            self._asked_in_stop.append(reason)
        if not self.stop_requested:
            self.stop_requested = reason
            if self.recorder is not None:
                self.recorder.note("stop", reason, self.tick)

    def _new_runner(self) -> RecipeRunner | None:
        """The recipe's runner from its first phase (None without a recipe): at the start,
        and again after a reset, each with a back-off that mirrors this supervisor's limiter
        from zero torque, where the supervisor starts (and restarts) too."""
        if self.recipe is None:
            return None
        return RecipeRunner(
            self.recipe,
            self.hand.n_joints,
            reanalyser=self.reanalyser,
            sizes=self.estimator,
            backoff=RateBackoff.for_hand(self.hand, self.supervisor.dt),
            period_s=self.supervisor.dt,
        )

    def request_estop(self, reason: str = "operator") -> None:
        self.estop_requested = reason
        if self.recorder is not None:
            self.recorder.note("estop", reason, self.tick)

    def reset(self) -> bool:
        """The explicit reset after a safety stop: clear the latched faults, host and nodes.

        The recipe does not resume: the next ``run()`` starts it again from its first phase,
        with the nodes enabled afresh and torque ramping up from zero through the rate limit.
        """
        if self.supervisor.state is not State.FAULTED:
            return False
        self.supervisor.reset(self.tick)
        if self.recorder is not None:
            self.recorder.note("reset", "", self.tick)
        self.driver.node_command("fault_reset")
        self.runner = self._new_runner()
        self.stop_requested = ""
        self._asked_in_stop = None
        self.estop_requested = ""
        self._estop_owed = self._estop_refusals = 0  # the nodes' FAULT was just cleared
        self.exception = None
        return True

    # -- the run --------------------------------------------------------------------------
    async def run(self) -> RunResult:
        loop = asyncio.get_running_loop()
        task = asyncio.current_task()
        due = loop.time() + self.clock_silent_s
        self._clock_watch = loop.call_at(due, self._watch_clock, task, -1, due)
        try:
            with self.collector.running():  # the stop's ticks too
                try:
                    outcome, message = await self._run()
                except BaseException as exc:  # any stage: a safety stop (module doc)
                    if _interrupts(exc, task):
                        # Ctrl-C without a signal handler, a cancelled task, the run's
                        # coroutine closed: no tick is left to wait for, so zero and disable
                        # at once (in this order on the bus), and what ran is kept for the
                        # summary (``interrupted``) before it goes on
                        self._keep_interrupted(exc, self._stop_at_once())
                        raise
                    # SystemExit too: nothing in a tick asks the process to end (a stop signal
                    # is a request to the loop); a library's exit() inside one is a broken
                    # stage, and went out as the process' exit code with no summary. So is
                    # any other BaseException but an interrupt (a GeneratorExit, a library's
                    # own): it crashed the command, exit 1, with no summary and no zero ticks
                    if isinstance(exc, EndOfTicks) and self.clock.lockstep:
                        raise
                    try:
                        outcome, message = await self._stop_after_exception(exc)
                    except BaseException as interrupt:
                        # the stop's own ticks interrupted (Ctrl-C in a program that embeds
                        # the Runtime, a cancelled task): the interrupt's branch above does
                        # not cover this one, and one zero frame went with no disable, the
                        # nodes left ENABLED for their watchdog and no result kept
                        self._keep_stop_interrupted(interrupt, self._stop_at_once())
                        raise
        finally:
            if self._clock_watch is not None:
                self._clock_watch.cancel()
            closed = self._close_clock()
        return self._result(
            outcome, f"{message}; {closed}" if message and closed else message or closed
        )

    def _close_clock(self) -> str:
        """Close the clock; what its close raised, for the run's message ("": nothing). It
        replaced the run's result, a safety stop's included (an internal error, exit 1, no
        summary), and the clock that broke is the likeliest not to close either (a real-time
        clock takes its timer out of the event loop). An interrupt goes on."""
        try:
            self.clock.close()
        except INTERRUPTS:
            raise
        except BaseException as exc:
            said = said_by(exc)[:EXCEPTION_TEXT_CHARS]
            return f"closing the clock raised {type(exc).__name__}" + (f": {said}" if said else "")
        return ""

    async def _run(self) -> tuple[Outcome, str]:
        sup = self.supervisor
        # 1. Listen until every node has spoken (feedback and heartbeat); send nothing yet.
        problem = await self._startup()
        if problem:
            self._bus_events += len(self.driver.take_bus_events())  # the log has them
            if self.stop_requested and not sup.faults:
                # a stop asked for before the nodes were enabled is the same interrupt as
                # one asked for later, not a failed start-up: nothing went wrong with the
                # hand. Said here, where a re-run of the log says it too (the run's signal
                # handling said it alone, and the re-run of such a log found "NOTHING
                # COMPARED", exit 1)
                return Outcome.INTERRUPTED, problem
            return Outcome.STARTUP_FAILED, problem
        # 2. Enable, with zero torque every tick from now on (the device watchdog is armed).
        tick = self.tick
        sup.start(tick)
        self._enable_owed = self.driver.node_command_unsent("enable")
        self._enable_refusals = 1 if self._enable_owed else 0
        sup.enable_unsent = self._enable_refused() if self._enable_owed else ""
        if self.trace is not None:  # in the last start-up tick's interval
            self.trace.note(NOTE_STATE)
            self._traced_state = sup.state
        self.first_send_tick = self.tick  # command frame n of each node belongs to this + n
        self.startup_missed_ticks = self._missed  # before it the peer may still be starting
        stopping_since: int | None = None
        while True:
            tk = await self._tick()
            if sup.state is State.IDLE and stopping_since is None:
                stopping_since = tk.tick
            if sup.state is State.FAULTED and stopping_since is None:
                stopping_since = tk.tick
            if stopping_since is not None and tk.tick - stopping_since >= ZERO_TICKS_BEFORE_DISABLE:
                break
            if self.tick >= self.max_ticks:
                self.request_stop("tick budget exhausted")
        self._disable_owed = self._disable_estopped = False
        self._disable_refusals = 0
        if not self.driver.node_command("disable"):
            # a disable frame the bus refused: again from the prepared frames (which send the
            # e-stop after them), and on the ticks of the wait until it or the e-stop goes;
            # said as the bus's, not as nodes that went on ENABLED after a disable they
            # never had
            self._disable_refusals = 1
            self._disable_owed = not self._send_disable()
        await self._confirm_disabled(tk.now_ns)
        refused = self._disable_refused()
        if self._disable_owed or self._disable_estopped:
            if not self.disable_unconfirmed:  # every node heard stopped, not by the disable
                self.disable_unconfirmed = refused
            # the disable never went to every node: the run did not end as it should, on a
            # bus that failed (README: exit 3), whatever the nodes were heard to say
            sup.trip(FaultCode.BUS_ERROR, refused, self.tick)
        if not sup.faults:  # a node fault in the run is its stop, said as such
            self._say_ended_in_fault()
        self._say_rebooted()
        # the last tick's bus events, which the log has: the summary's count had them not
        self._bus_events += len(self.driver.take_bus_events())
        if sup.faults:
            return Outcome.SAFETY_STOP, "; ".join(str(f) for f in sup.faults) + self._estop_said()
        if self.stop_requested:
            return Outcome.INTERRUPTED, self.stop_requested
        return Outcome.COMPLETED, ""

    async def _confirm_disabled(self, sent_ns: int) -> None:
        """Listen after the disable (sent after the tick of ``sent_ns``) until every node's
        own Feedback, heard since, says it is no longer ENABLED, for ``DISABLE_CONFIRM_S``
        at most, before the bus is closed (a node none of whose Feedback is heard in that
        time is taken at its other reports' word). One period alone was waited: above 1 kHz
        in lockstep the simulated nodes, on their own 1 ms tick, had not run one in it, and
        the run ended (exit 0 as well) with the hand ENABLED. Any report's DISABLED was
        taken at first: one forged Heartbeat after the disable hid a node that ignored it,
        and no e-stop went. Then one Feedback's: a forged Feedback DISABLED with the node's
        next counter hid it the same way, the wait over before the node's own frame of that
        counter came to contradict it (found by an outside audit). So a node's DISABLED is
        confirmed by a later Feedback that says so too, a node tick on, when its own frame of
        the counter has had time to come, and a node contradicted since the disable is
        never confirmed (``_contradicted_after_the_disable``). A node that does not say so in
        time is said in the summary's warnings: its watchdog is what disables it."""
        period_s = self.hand.bus.period_s
        ticks = max(1, ticks_lasting(DISABLE_CONFIRM_S, period_s))
        enabled = int(NodeState.ENABLED)
        nodes = self.driver.nodes
        # before the wait: a node contradicted already has stopped the run on it, and may
        # go on contradicting itself (each Status of another protocol does): its first
        # contradiction in the wait is what the wait stops on
        contradictions = [n.contradictions if not n.contradiction else -1 for n in nodes]
        rejects = [_rejects_so_far(n) for n in nodes]
        #: when the first Feedback not ENABLED heard of each node since the disable arrived
        first_ns: list[int | None] = [None] * len(nodes)
        stopped_on_contradiction = False

        def heard(n: finger.FingerNode) -> bool:  # a Feedback of it since the disable
            return n.feedback_ns is not None and n.feedback_ns >= sent_ns

        def observe() -> None:  # after each poll
            for i, n in enumerate(nodes):
                if not heard(n) or n.feedback_enabled:
                    first_ns[i] = None
                elif first_ns[i] is None:
                    first_ns[i] = n.feedback_ns

        def contradicted(i: int) -> bool:
            return _contradicted_since(nodes[i], contradictions[i])

        def confirmed(i: int) -> bool:
            n, first = nodes[i], first_ns[i]
            return (
                first is not None
                and n.feedback_ns is not None
                and n.feedback_ns - first >= finger.REORDERED_WITHIN_NS
                and not n.feedback_enabled
                and n.state != enabled
                and not contradicted(i)
            )

        # a Feedback sent this long after the disable was sent by a node that had had the
        # disable a tick to act on: its ENABLED is not one sent before it
        defiant_after_ns: int | None = None
        for _ in range(ticks):
            tk = await self._next_tick()
            if defiant_after_ns is None:
                defiant_after_ns = tk.now_ns + round(DEFIANT_AFTER_PERIODS * period_s * 1e9)
            self._account_idle(tk)
            self.driver.poll(tk.now_ns)
            observe()
            if self._estop_owed:  # refused on an earlier tick: again, until one goes
                self._owe_estop(self._estop_owed)
            if self._disable_owed:  # likewise the disable, until it or the e-stop goes
                self._disable_owed = not self._send_disable()
            self._foreign_after_the_disable(tk.tick)
            if not stopped_on_contradiction:
                stopped_on_contradiction = self._contradicted_after_the_disable(
                    tk.tick, contradictions
                )
            if all(confirmed(i) for i in range(len(nodes))) and not self._estop_owed:
                return
        # a node whose Feedback went unheard all the while (its frames rejected, or lost) is
        # taken at its other reports' word, at the end of the wait
        still = [
            i
            for i, n in enumerate(nodes)
            if not confirmed(i) and (heard(n) or n.state == enabled or contradicted(i))
        ]
        if not still:
            return
        defiant = [
            i
            for i in still
            if defiant_after_ns is not None
            and (n := nodes[i]).feedback_ns is not None
            and n.feedback_ns >= defiant_after_ns
            and n.feedback_enabled
        ]
        said = [i for i in still if contradicted(i)]
        self._say_unconfirmed(still, said, defiant, rejects, ticks * period_s)

    def _say_unconfirmed(
        self,
        still: list[int],
        contradicted: list[int],
        defiant: list[int],
        rejects: list[tuple[int, int]],
        waited_s: float,
    ) -> None:
        """Say which nodes (indices into the driver's) the wait for the disable did not
        confirm and why, and send the e-stop to the ``defiant`` ones: ``rejects`` are the
        nodes' reject totals when the wait began."""
        nodes = self.driver.nodes

        def names(indices: list[int]) -> str:
            return ", ".join(f"node {nodes[i].node_id} ({nodes[i].finger.name})" for i in indices)

        self.disable_unconfirmed = (
            f"{names(still)} not heard disabled within {waited_s * 1e3:g} ms of "
            "the disable (last heard ENABLED, or silent since); a node that hears no command "
            f"for {wire.COMMAND_WATCHDOG_S * 1e3:g} ms sets its torque to zero and latches "
            "FAULT (TIMEOUT), which the next run clears with --reset-node-faults"
        )
        if contradicted:  # the e-stop went, or was owed, when the contradiction was heard
            what = "the e-stop was sent" if self._estop_at_the_end else "the e-stop is owed"
            self.disable_unconfirmed += (
                f"; {names(contradicted)} contradicted after the disable (NODE_CONTRADICTION), "
                f"so no DISABLED of it is believed: {what}"
            )
        if self._disable_refusals:
            self.disable_unconfirmed += f" ({self._disable_refused()})"
            defiant = []  # they may never have had it; the e-stop, if any, has gone
        if defiant:
            # a node that goes on saying ENABLED after the disable disobeys it: the e-stop,
            # which every node honours (PROTOCOL.md), is the last word the host has; it
            # latches FAULT (ESTOP) on every node, for --reset-node-faults to clear. A node
            # whose frames were being rejected meanwhile (a replayed stream, REJECT_RATE)
            # may not have said that ENABLED itself: the e-stop all the same, but it is not
            # blamed for a disobedience the host cannot tell from the replay
            if not (contradicted and self._estop_at_the_end):  # else it went at the contradiction
                self._estop_at_the_end = self.driver.send_estop()
            what = (
                "the e-stop was sent" if self._estop_at_the_end else "the e-stop could not be sent"
            )
            doubted = [i for i in defiant if _doubting_rejects(nodes[i], rejects[i])]
            disobeyed = [i for i in defiant if i not in doubted]
            if disobeyed:
                self.disable_unconfirmed += (
                    f"; {names(disobeyed)} went on saying ENABLED after the disable: {what}"
                )
            if doubted:
                counts = ", ".join(str(_doubting_rejects(nodes[i], rejects[i])) for i in doubted)
                self.disable_unconfirmed += (
                    f"; {names(doubted)} could not be confirmed disabled: frames of it were "
                    f"being rejected after the disable ({counts}), so the ENABLED heard may be "
                    f"replayed or forged, not the node's own: {what}"
                )
        if self.recorder is not None:  # the log says it too: whether the hand may be ENABLED
            self.recorder.note("disable_unconfirmed", self.disable_unconfirmed, self.tick)

    def _contradicted_after_the_disable(self, tick: int, before: Sequence[int]) -> bool:
        """A node contradicted while the run listens for its disable (a Feedback with the
        counter of one accepted and other contents, row 92 of docs/safety.md) is
        ``NODE_CONTRADICTION`` there too, with the e-stop at once: one of its two streams is
        not the node's, and the DISABLED may be the forged one, sent to hide a node that
        ignored the disable (found by an outside audit). ``before``: each node's count of
        contradictions when the wait began (-1: contradicted before it, and said then).
        Whether it stopped on one (once is enough)."""
        nodes = self.driver.nodes
        new = [n for n, count in zip(nodes, before, strict=True) if _contradicted_since(n, count)]
        if not new:
            return False
        self.supervisor.trip(
            FaultCode.NODE_CONTRADICTION,
            "after this run's disable, "
            + "; ".join(f"node {n.node_id} ({n.finger.name}): {n.contradiction}" for n in new),
            tick,
        )
        self._estop_at_the_end = self._owe_estop(ESTOP_HOST_SAFETY)
        return True

    def _foreign_after_the_disable(self, tick: int) -> None:
        """Another sender on the nodes' command identifiers while the run listens for its
        disable is ``FOREIGN_COMMAND`` there too, with the e-stop at once: a second host that
        waited for this one's disable and then enabled the nodes with its own torques had
        them for the rest of the wait, which ended on the nodes' DISABLED (heard in the same
        poll: exit 0, nothing said) or blamed the nodes for an ENABLED that was the other
        host's doing. The e-stop latches FAULT (ESTOP) on every node, which the other
        sender cannot lift with an enable (found by an outside audit)."""
        sup = self.supervisor
        if FaultCode.FOREIGN_COMMAND in sup.active_codes:
            return  # said, and the e-stop sent, when it was first heard
        foreign = [
            f"node {n.node_id} ({n.finger.name}): {n.foreign_command}"
            for n in self.driver.nodes
            if n.foreign_command
        ]
        if not foreign:
            return
        sup.trip(
            FaultCode.FOREIGN_COMMAND,
            "after this run's disable, " + "; ".join(foreign),
            tick,
        )
        self._estop_at_the_end = self._owe_estop(ESTOP_HOST_SAFETY)

    def _enable_again(self) -> None:
        """Send the enable again to the nodes the bus refused it to, while the supervisor
        waits for them to say ENABLED (nothing once it has stopped waiting), and tell it what
        its enable deadline says if it comes before the enable goes."""
        sup = self.supervisor
        if sup.state is not State.ENABLING:
            self._enable_owed = []
            sup.enable_unsent = ""
            return
        self._enable_owed = self.driver.node_command_unsent("enable", self._enable_owed)
        if self._enable_owed:
            self._enable_refusals += 1
        sup.enable_unsent = self._enable_refused() if self._enable_owed else ""

    def _enable_refused(self) -> str:
        """The enable frames that never left the host, and what the bus said of them."""
        names = ", ".join(
            f"node {n.node_id} ({n.finger.name})"
            for n in self.driver.nodes
            if n.node_id in self._enable_owed
        )
        error = self.driver.last_tx_error
        return (
            f"the bus refused the enable of {names} {_times(self._enable_refusals)}"
            + (f" ({error})" if error else "")
            + ": it never left the host"
        )

    def _send_disable(self) -> bool:
        """The prepared disable to every node, the e-stop after it if a frame of it did not
        go (``HandDriver.send_disable``); whether the nodes have had one or the other."""
        driver = self.driver
        lost = driver.stop_estops_lost
        if driver.send_disable():
            return True
        self._disable_refusals += 1
        if driver.stop_estops_lost == lost:  # the e-stop went in its place
            self._disable_estopped = True
            return True
        return False

    def _disable_refused(self) -> str:
        """What the bus did to the disable at the end ("": it went at once)."""
        refused = self._disable_refusals
        if not refused:
            return ""
        error = self.driver.last_tx_error
        times = _times(refused) + (f" ({error})" if error else "")
        if self._disable_estopped:
            return (
                f"the bus refused the disable at the end {times}, and the e-stop was sent in "
                "its place: every node latches FAULT (ESTOP), which the next run clears with "
                "--reset-node-faults"
            )
        if self._disable_owed:
            return (
                f"the bus refused the disable at the end {times}, and the e-stop after it, on "
                "every tick of the wait for the nodes' DISABLED: a node still ENABLED stops "
                f"only when it has heard no command for {wire.COMMAND_WATCHDOG_S * 1e3:g} ms, "
                "and latches FAULT (TIMEOUT), which the next run clears with --reset-node-faults"
            )
        return f"the bus refused the disable at the end {times} before it went"

    def _owe_estop(self, reason: int) -> bool:
        """Send the e-stop of ``reason`` (``ESTOP_*``); one the bus refuses stays owed, and
        every tick after sends it again (the running ticks, the zero ticks before the
        disable and the wait for the nodes' DISABLED), until one goes or the run ends, as a
        stop frame the bus refuses is followed by the e-stop (docs/safety.md, the stop's
        frames). Whether it went."""
        if self.driver.send_estop(reason):
            self._estop_owed = 0
            return True
        self._estop_owed = reason
        self._estop_refusals += 1
        return False

    def _estop_said(self) -> str:
        """What the outcome's message says of an e-stop the bus refused: that it went late,
        or that it never went, and so no node is latched in FAULT (ESTOP) by it ("" when
        every e-stop went at once)."""
        refused = self._estop_refusals
        if not refused:
            return ""
        error = self.driver.last_tx_error
        why = f" ({error})" if error else ""
        times = _times(refused)
        if not self._estop_owed:
            return f"; the bus refused the e-stop {times}{why} before it went"
        return (
            f"; the e-stop could not be sent: the bus refused it {times}, on every "
            f"tick to the run's end{why}, so no node latched FAULT (ESTOP) on it: the zero "
            "torque and the disable are what stopped them"
        )

    def _say_ended_in_fault(self) -> None:
        """Nodes in FAULT at the run's end that no fault of the run stands for: latched after
        the stop took the torque out, before the disable (a watchdog's TIMEOUT as commands
        stopped coming, an e-stop pressed then). The hand is safe, but the next run is
        refused until ``--reset-node-faults``; the run said nothing of it, exit 0 and
        "success", and only the simulated hand's own summary showed it."""
        from handctl.online.drivers.finger import fault_names

        faulted = [n for n in self.driver.nodes if n.state == int(NodeState.FAULT)]
        if not faulted or self._estop_at_the_end:  # the nodes' FAULT is that e-stop's, said
            return
        said = ", ".join(
            f"node {n.node_id} ({n.finger.name}, "
            f"{'+'.join(fault_names(n.fault_bits)) or 'no fault bits'})"
            for n in faulted
        )
        self.ended_in_fault = (
            f"{said} in FAULT at the end of the run, latched after its stop had taken the "
            "torque out; the next run is refused until --reset-node-faults clears it"
        )
        if self.recorder is not None:
            self.recorder.note("ended_in_fault", self.ended_in_fault, self.tick)

    def _say_rebooted(self) -> None:
        """Nodes a Heartbeat says rebooted after the torque was armed, when no
        ``NODE_REBOOT`` of the run says it: one that rebooted in the stop's zero ticks or
        the wait for the disable was never mentioned (completed, exit 0, a count of counter
        skips alone), and one that rebooted while armed stopped the run as DISABLED
        (``NODE_STATE``), its reboot unsaid. A node comes back from a reboot DISABLED, its
        torque zero, so this is said, not a fault: it tells why the node stopped, or of
        a power supply or firmware to look at."""
        sup = self.supervisor
        if FaultCode.NODE_REBOOT in sup.active_codes:
            return
        said = sup.node_watch.rebooted_since_armed(self.driver.nodes)
        if not said:
            return
        self.rebooted = (
            "; ".join(said) + ": rebooted after the torque was armed, which no fault of the "
            "run names (a node boots DISABLED, at zero torque; if it did not reboot, another "
            "sender is on its Heartbeat id: `handctl nodes` shows it)"
        )

    def _estop_heard(self) -> str:
        """The e-stop frames of another sender the run heard, in words ("": none): every
        node latches FAULT (ESTOP) on one, and the run's stop (or its ``ended_in_fault``)
        named the nodes' FAULT alone, the frame that caused it only counted as an unexpected
        id, so the operator looked for a node that had stopped itself."""
        driver = self.driver
        if not driver.estops_heard:
            return ""
        more = f", {driver.estops_heard} in all" if driver.estops_heard > 1 else ""
        return (
            f"{driver.estop_heard} was heard{more}: every node latches FAULT (ESTOP) on it, "
            "which the next run clears with --reset-node-faults"
        )

    def _stop_at_once(self) -> str:
        """Zero torque and the disable to every node at once, for an interrupt that leaves
        no tick to wait for (the e-stop after a frame the bus refused, ``send_prepared``);
        what went, in words. The interrupt's result said "zero torque and a disable were
        sent at once" when the bus had refused them all and the nodes held their last
        torque until their watchdog (found by an outside audit). Never raises."""
        driver = self.driver
        estops, lost = driver.stop_estops, driver.stop_estops_lost
        zero, disable = driver.send_zero(), driver.send_disable()
        if zero and disable:
            return "zero torque and a disable were sent at once"
        with contextlib.suppress(Exception):
            refused = " and ".join(
                what for what, ok in (("the zero torque", zero), ("the disable", disable)) if not ok
            )
            error = driver.last_tx_error
            said = (
                "zero torque and a disable were tried at once, but the bus refused "
                f"{refused} to a node" + (f" ({error})" if error else "")
            )
            if driver.stop_estops_lost - lost < driver.stop_estops - estops:
                return (
                    f"{said}, so the e-stop was sent: each node latches FAULT (ESTOP), which "
                    "the next run clears with --reset-node-faults"
                )
            return (
                f"{said}, and the e-stop after it, with no tick left to send them again: a "
                "node that missed them is stopped only by its own command watchdog (FAULT "
                "TIMEOUT, cleared with --reset-node-faults)"
            )
        return "zero torque and a disable were tried at once; the bus refused a frame of them"

    def _keep_interrupted(self, exc: BaseException, sent: str) -> None:
        """What the run did up to a KeyboardInterrupt or a cancellation inside it, as its
        result (``interrupted``): the run's summary says so, not that nothing was sent, and
        ``sent`` (``_stop_at_once``) says what the bus took of the stop. Never raises: the
        interrupt goes on whatever this finds."""
        tick = self.tick
        said = said_by(exc)  # an interrupt whose __str__ raised replaced itself and its result
        message = (
            f"{type(exc).__name__} in tick {tick}" + (f" ({said})" if said else "") + f": {sent}"
        )
        self._end_phase_quietly(f"interrupted: {type(exc).__name__}", tick)
        with contextlib.suppress(Exception):
            self.interrupted = self._result(Outcome.INTERRUPTED, message)

    def _keep_stop_interrupted(self, interrupt: BaseException, sent: str) -> None:
        """The result of a run whose stop after an exception was itself interrupted: the
        exception's safety stop, and that its stop was cut short (``interrupted``, as
        ``_keep_interrupted``). Never raises."""
        with contextlib.suppress(Exception):
            message = (
                f"{self._exception_stop_message()}; {type(interrupt).__name__} during the "
                f"stop: {sent}"
            )
            self.interrupted = self._result(Outcome.SAFETY_STOP, message)

    def _end_phase_quietly(self, reason: str, tick: int) -> None:
        """End the phase under way for ``reason`` at ``tick`` (it had no end in the summary),
        if the runner can: an exception or an interrupt may have come from the runner."""
        with _Survive():
            if self.runner is not None and self.runner.in_phase:
                self._abort_phase(self._t_s, reason, tick)

    async def _stop_after_exception(self, exc: BaseException) -> tuple[Outcome, str]:
        """The stop after an exception: latch its fault, then zero torque and disable with
        the driver's prepared frames, as the normal stop does (zero in this tick and the next
        ZERO_TICKS_BEFORE_DISABLE, then disable, then one tick for it to go).

        Nothing here uses a stage that may have raised: no codec, no runner, no supervisor
        check. The clock, the recorder's tick boundary and the poll are tried once a tick and
        left out from their first failure on (an exception that recurs every tick costs one
        try each); without the clock the remaining frames go at once, in the same order.
        """
        tk = self._latch_exception(exc)
        self._asked_in_stop = []
        driver = self.driver
        if tk is not None and self.tick == tk.tick:  # the tick that raised was not counted
            self._count_stop_tick(tk)
        driver.send_zero()
        rows_ok = self._end_phase_on_exception(tk)
        clock_ok = recorder_ok = poll_ok = True
        disabled_ns: int | None = None  # the tick after which the disable went
        for n in range(1, ZERO_TICKS_BEFORE_DISABLE + 2):  # the ticks after the one that raised
            tk = None
            # Each part is left out at its first failure, whatever it raised but an
            # interrupt: a SystemExit that recurred every tick went out through the
            # interrupt's handler, the process exiting with its code and no summary.
            if clock_ok:
                tk = await self._stop_tick()
                clock_ok = tk is not None  # it gave up pacing: the frames go without it
            if tk is not None:
                self._count_stop_tick(tk)
                if recorder_ok and self.recorder is not None:
                    try:
                        self.recorder.begin_tick(tk)
                    except INTERRUPTS:
                        raise
                    except BaseException:  # later frames go with the last tick it began
                        recorder_ok = False
            state = None
            if poll_ok:
                try:
                    state = driver.poll(tk.now_ns if tk is not None else None)
                    self._bus_events += len(driver.take_bus_events())
                except INTERRUPTS:
                    raise
                except BaseException:  # polling only feeds the log here: not needed to stop
                    poll_ok = False
            if self._stop_frames(n) and tk is not None:
                disabled_ns = tk.now_ns
            if tk is not None and recorder_ok and rows_ok:
                rows_ok = self._record_stop_tick(tk, state)
        if clock_ok and recorder_ok and poll_ok and disabled_ns is not None:
            # heard disabled, as after any other stop (``disable_unconfirmed`` could not be
            # said after an exception); the hand is stopped whatever this finds
            with _Survive():
                await self._confirm_disabled(disabled_ns)
        if (self._disable_owed or self._disable_estopped) and not self.disable_unconfirmed:
            # every node heard stopped, but not by the disable (its watchdog's TIMEOUT, or the
            # e-stop in the disable's place): the summary says what the bus did to it
            self.disable_unconfirmed = self._disable_refused()
        return Outcome.SAFETY_STOP, self._exception_stop_message() + self._asked_said()

    def _asked_said(self) -> str:
        """The stops asked for during the stop after an exception, for its message ("":
        none): it goes on to its end whatever is asked, and says what was."""
        asked = self._asked_in_stop
        if not asked:
            return ""
        return (
            f"; {', '.join(dict.fromkeys(asked))} came during this stop, which went on to its end"
        )

    async def _stop_tick(self) -> Tick | None:
        """The clock's next tick for the stop after an exception, ``STOP_TICK_TIMEOUT_S`` at
        most; None if it raised anything but an interrupt, or gave nothing in time. Waited
        for in this task: ``asyncio.wait_for`` ran it in a task of its own, out of which a
        SystemExit left the event loop itself."""
        try:
            async with asyncio.timeout(STOP_TICK_TIMEOUT_S):
                return await self.clock.wait_tick()
        except INTERRUPTS:
            raise
        except BaseException:
            return None

    def _stop_frames(self, n: int) -> bool:
        """The frames of the ``n``-th tick after the one that raised: zero torque up to
        ``ZERO_TICKS_BEFORE_DISABLE``, the disable on that tick; whether this was the
        disable's tick. A disable the bus refuses, and the e-stop after it, is owed: sent
        again on the ticks after and through the wait for the nodes' DISABLED, as at the end
        of any other run (it went once, and the nodes stayed ENABLED at zero torque until
        their watchdog acted, nothing said)."""
        if n <= ZERO_TICKS_BEFORE_DISABLE:
            self.driver.send_zero()
        if n == ZERO_TICKS_BEFORE_DISABLE:
            self._disable_refusals = 0
            self._disable_estopped = False
            self._disable_owed = not self._send_disable()
            return True
        if n > ZERO_TICKS_BEFORE_DISABLE and self._disable_owed:
            self._disable_owed = not self._send_disable()
        return False

    def _end_phase_on_exception(self, tk: Tick | None) -> bool:
        """End the phase under way on the exception (it had no end in the summary), and push
        the row of the tick that raised if it had none: the log's per-tick rows go on to the
        disable with the zero torque sent (they stopped at the last torque asked, which a plot
        then held to the log's end). Whether rows can still be pushed."""
        failure = self.exception
        code = failure.code.name if failure is not None else FaultCode.RUN_EXCEPTION.name
        self._end_phase_quietly(f"safety stop: {code}", tk.tick if tk is not None else self.tick)
        if self.recorder is None:
            return False
        if tk is not None and self._record.tick != tk.tick:  # its row was not pushed
            return self._record_stop_tick(tk, None)
        return True

    def _exception_stop_message(self) -> str:
        message = "; ".join(str(f) for f in self._faults()) + self._estop_said()
        driver = self.driver
        refused = self._disable_refused()
        if driver.stop_estops and driver.stop_estops_lost == driver.stop_estops:
            message += (
                "; a stop frame did not go to every node, and neither did the e-stop sent after it"
            )
            if refused and not self._disable_owed:  # the disable went on a later tick
                return f"{message}; {refused}"
            message += (
                ": the bus took none of them, so a node that missed its zero and disable is "
                "stopped only by its own command watchdog (FAULT TIMEOUT, cleared with "
                "--reset-node-faults)"
            )
        elif driver.stop_estops:
            message += (
                "; a stop frame did not go to every node, so the e-stop was sent: each node "
                "latches FAULT (ESTOP), which the next run clears with --reset-node-faults"
            )
        return f"{message}; {refused}" if refused else message

    def _record_stop_tick(self, tk: Tick, state: JointState | None) -> bool:
        """The row of a tick of the stop after an exception, as a fault stop's: zero torque
        asked and sent, the supervisor faulted, the angles polled (the last ones without).
        False when the recorder failed: the stop goes on without it."""
        record = self._record
        try:
            record.tick, record.t_ns, now_ns, record.missed = tk
            record.lateness_ns = now_ns - tk.scheduled_ns
            if state is not None:
                record.angle, record.tdt = state.angle, state.tdt
            record.desired = record.applied = self._zero
            record.state, self._record_state = State.FAULTED.value, State.FAULTED
            record.phase = self._phase_name()
            record.stage_ns = (0,) * len(STAGES)
            record.faults = []
            assert self.recorder is not None
            self.recorder.push(record)
        except INTERRUPTS:
            raise
        except BaseException:
            return False
        return True

    def _count_stop_tick(self, tk: Tick) -> None:
        """Count a tick of the stop; the accounting may be what raised, and the stop does
        not need it."""
        with _Survive():
            self._store(tk, (0,) * len(STAGES))

    def _latch_exception(self, exc: BaseException) -> Tick | None:
        """Turn ``exc`` into the fault of its stage, latched (and kept in ``exception``);
        return the tick under way when it was raised, if known. Never raises."""
        exc = _as_raised(exc)
        try:
            code, tk = _stage_of(exc)
        except Exception:  # a traceback that cannot be read still stops the hand
            code, tk = FaultCode.RUN_EXCEPTION, None
        tick = tk.tick if tk is not None else self.tick
        failure = _describe(exc, code, tick)
        self.exception = failure
        # A supervisor that cannot take the fault is itself broken: ``_faults`` reports it.
        with _Survive():
            self.supervisor.trip(code, failure.detail, tick)
        return tk

    def _faults(self) -> list[Fault]:
        """The latched faults, and the exception's even when the supervisor could not take
        it."""
        faults = list(self.supervisor.faults)
        failure = self.exception
        if failure is not None and all(f.code is not failure.code for f in faults):
            faults.append(Fault(failure.code, failure.detail, failure.tick))
        return faults

    async def _startup(self) -> str:
        nodes = self.driver.nodes
        reset_sent = False
        since: int | None = None
        self.driver.discard_pending()
        # the nodes' frames judged at the reject rate before anything is enabled
        rejects = StartupRejects(self.hand.safety, self.hand.bus.period_s, nodes)
        deadline = self.startup_ticks
        waited = 0
        while waited < deadline:
            waited += 1
            tk = await self._next_tick()
            self._account_idle(tk)
            if since is None:
                since = tk.now_ns
            self.driver.poll(tk.now_ns)
            if deadline == self.startup_ticks and _any_heard(nodes, since):
                deadline = min(deadline, waited + self.answer_ticks)
            rate = rejects.check(tk.tick, nodes)
            if rate:
                detail = f"{rate} at start-up: no node was enabled"
                self.supervisor.trip(FaultCode.REJECT_RATE, detail, tk.tick)
                return detail
            # The first send's one-time work (the unix bus looks its receivers up) here, where
            # the tick only listens, not in the nodes' enable before the first running tick.
            self.driver.prepare_send()
            if self.stop_requested:
                # said after "stopped:": "stopped: signal SIGTERM during start-up, ..."
                return f"{self.stop_requested} during start-up, no node enabled"
            # Judge the nodes on what they say now, not on what a previous run last heard:
            # fresh feedback and a fresh heartbeat from every node (the heartbeat's uptime is
            # the baseline against which a reboot during the run is recognised).
            refused = self._refused_at_startup(since, tk.tick)
            if refused is not None:
                self.supervisor.trip(refused[0], refused[1], tk.tick)
                return refused[1]
            heard = all(
                n.feedback_ns is not None
                and n.feedback_ns >= since
                and n.heartbeat_ns is not None
                and n.heartbeat_ns >= since
                and n.version_ns is not None
                and n.version_ns >= since
                for n in nodes
            )
            if not heard:
                continue
            faulted = [n for n in nodes if n.state == NodeState.FAULT]
            if not faulted:
                if all(n.state == NodeState.DISABLED for n in nodes) and rejects.settled(tk.tick):
                    return ""
                continue
            faults = self._faulted_at_startup(faulted, tk.tick, reset_sent)
            if faults:
                return faults
            reset_sent = True
        return self._not_ready(since, deadline < self.startup_ticks)

    def _not_ready(self, since: int | None, answered: bool) -> str:
        """The start-up's end with a node not ready (its fault latched): which node, and
        what of it was not heard since ``since`` (ns); ``answered``: it ended on the nodes'
        time to answer once one was heard, not on the whole start-up's."""
        silent = []
        for n in self.driver.nodes:
            who = f"node {n.node_id} ({n.finger.name})"
            if n.feedback_ns is None or since is None or n.feedback_ns < since:
                silent.append(f"{who}: {_no_feedback(n.rejects.as_dict())}")
            elif n.heartbeat_ns is None or n.heartbeat_ns < since:
                silent.append(f"{who}: no heartbeat")
            elif n.version_ns is None or n.version_ns < since:
                silent.append(f"{who}: no Status (its protocol version unknown)")
            elif n.state != NodeState.DISABLED:
                silent.append(f"{who} is {n.state_name}")
        detail = "; ".join(silent) or "nodes not ready"
        self.supervisor.trip(FaultCode.STARTUP, detail, self.tick)
        if answered:
            return (
                f"nodes not ready within {self.answer_ticks} ticks of the first node heard: "
                f"{detail}"
            )
        return f"nodes not ready within {self.startup_ticks} ticks: {detail}"

    def _faulted_at_startup(self, faulted: list[finger.FingerNode], tick: int, sent: bool) -> str:
        """Nodes in FAULT at start-up: the reason to refuse (without ``--reset-node-faults``),
        or "" once their reset is sent (``sent``: already), said in the summary, on stderr and
        in the log (before, only the NodeCommand frames in the log showed what was cleared)."""
        from handctl.online.drivers.finger import fault_names

        names = "; ".join(
            f"node {n.node_id} ({n.finger.name}) in FAULT "
            f"({', '.join(fault_names(n.fault_bits)) or 'no bits'})"
            for n in faulted
        )
        if not self.reset_node_faults:
            self.supervisor.trip(FaultCode.STARTUP, names, tick)
            return (
                f"{names}: check the hand, then clear the faults explicitly with "
                "--reset-node-faults"
            )
        if not sent:
            self.driver.node_command("fault_reset", [n.node_id for n in faulted])
            self.nodes_reset = f"cleared at start-up (--reset-node-faults): {names}"
            if self.recorder is not None:
                self.recorder.note("node_reset", self.nodes_reset, tick)
        return ""

    def _refused_at_startup(self, since: int, tick: int) -> tuple[FaultCode, str] | None:
        """Why the nodes must not be enabled, whatever they say of their state (None if
        nothing refuses them): a peer process that ended (the simulated hand of a real-time
        run: said at once, not after the whole start-up timeout), a bus-off or a receive
        backlog (``REFUSE_STARTUP``), a node of another protocol version (its frames may
        mean something else than this host reads into them), or
        another sender on the host's command ids (the nodes would hear two hosts)."""
        gone = self.peer_gone() if self.peer_gone is not None else ""
        if gone:
            if self.recorder is not None:
                # an input from outside the bus: logged, so that the re-run refuses the
                # start-up at this tick too (it could not, and a genuine log said MISMATCH)
                self.recorder.note("peer_gone", gone, tick)
            return FaultCode.STARTUP, gone
        event = next((e for e in self.driver.bus_events if e.kind in REFUSE_STARTUP), None)
        if event is not None:
            code, what = REFUSE_STARTUP[event.kind]
            return code, f"{what} during start-up ({event.detail}): no node was enabled"
        nodes = self.driver.nodes
        wrong = [
            problem
            for n in nodes
            if n.version_ns is not None
            and n.version_ns >= since
            and (problem := n.version_problem())
        ]
        if wrong:
            return FaultCode.STARTUP, "; ".join(wrong)
        foreign = [
            f"node {n.node_id} ({n.finger.name}): {n.foreign_command}"
            for n in nodes
            if n.foreign_command
        ]
        if foreign:
            return FaultCode.FOREIGN_COMMAND, "; ".join(foreign)
        return None

    async def _next_tick(self) -> Tick:
        """Every tick of the run starts here, so the recorder sees each one before its poll;
        the garbage the ticks before it left is collected here too, if it is time to."""
        if self.collector.after_tick() and self.trace is not None:
            self.trace.note(NOTE_COLLECT)
        self._clock_waiting = True
        try:
            tk = await self.clock.wait_tick()
        except asyncio.CancelledError:
            task = asyncio.current_task()
            if not self._clock_silent or task is None or task.uncancel():
                raise  # a cancellation of the run's own
            self._clock_silent = False
            raise ClockSilentError(
                f"no tick from the clock for {self.clock_silent_s:g} s (a timer that stopped, "
                "or whose callback raised: asyncio's own log says what)"
            ) from None
        finally:
            self._clock_waiting = False
        self._clock_ticks += 1
        if self.recorder is not None:
            self.recorder.begin_tick(tk)
        return tk

    def _watch_clock(self, task: asyncio.Task[Any] | None, seen: int, due: float) -> None:
        """Every ``clock_silent_s`` while the run lasts: a run waiting for its clock that has
        had no tick since the last look (``seen``) is stopped as the clock's fault
        (``ClockSilentError`` from ``_next_tick``). A look that comes late by half of that or more
        found a process that did not run (SIGSTOP, a loop held up), not a silent clock: the
        clock gets the whole time again, from now, and the missed ticks are judged as ever."""
        loop = asyncio.get_running_loop()
        now = loop.time()
        ticks = self._clock_ticks
        late = now - due >= self.clock_silent_s / 2
        if task is not None and self._clock_waiting and ticks == seen and not late:
            self._clock_silent = True
            task.cancel()
            # and the watch goes on: the wait for the nodes' DISABLED after the stop reads the
            # clock again, and a clock silent there hung the run (found by an outside audit)
        due = now + self.clock_silent_s
        self._clock_watch = loop.call_at(due, self._watch_clock, task, ticks, due)

    def _account_idle(self, tk: Tick) -> None:
        """A tick with no stages (start-up, the last): counted, and traced, since the first
        running tick may have missed by what the last start-up tick did."""
        if self.trace is not None:
            self.trace.woke(tk.tick, tk.now_ns - tk.scheduled_ns, tk.missed, self.cpu_clock())
        if self._t0_ns is None:
            self._t0_ns = tk.scheduled_ns
        self._store(tk, (0,) * len(STAGES))

    async def _tick(self) -> Tick:
        sup = self.supervisor
        driver = self.driver
        cpu = self.cpu_clock
        # The stage stamps c0..c5 (and ``desired``) also tell ``_stage_of`` which stage an
        # exception came from: keep their names and order in step with it.
        tk = await self._next_tick()
        for hook in self.tick_hooks:
            hook(tk)
        c0 = cpu()
        trace = self.trace
        if trace is not None:
            trace.woke(tk.tick, tk.now_ns - tk.scheduled_ns, tk.missed, c0)
        state = driver.poll(tk.now_ns)
        events = driver.take_bus_events()
        self._bus_events += len(events)
        c1 = cpu()
        t_s = (tk.scheduled_ns - (self._t0_ns or 0)) * 1e-9
        self._t_s = t_s
        if self.estop_requested:  # the frame first; ``decide`` latches the fault
            self._owe_estop(ESTOP_OPERATOR)
        elif self._estop_owed:  # refused on an earlier tick: again, until one goes
            self._owe_estop(self._estop_owed)
        desired, applied, new_faults = self.decide(
            tk.tick, tk.now_ns, tk.missed, t_s, state.angle, state.tdt, events
        )
        if self._enable_owed:  # after the tick's checks: no enable once a stop is decided
            self._enable_again()
        c2, c3 = self._recipe_done_ns, cpu()
        if len(sup.stop_notes) > self._stop_notes_said:  # grows only in a controlled stop
            self._say_stop_notes(tk.tick)
        ok = driver.send(applied)
        sup.sent(ok, tk.tick, driver.unsent_joints)
        if new_faults and self._another_master(new_faults):
            self._owe_estop(ESTOP_HOST_SAFETY)
        np.maximum(self._max_abs, np.abs(applied), out=self._max_abs)
        # a NaN is a fault of its own (fmax passes over it)
        np.fmax(self._max_asked, np.abs(desired, out=self._asked), out=self._max_asked)
        self.chatter.observe(applied, t_s)
        c4 = cpu()  # the record stage is the recording alone
        if self.recorder is not None:
            # The refill runs no Python-level call it can do without (``Tick.lateness_ns``,
            # an enum's ``value``, ``_phase_name``): in the running loop, where the
            # recording's code runs cold, each costs about half a microsecond.
            record = self._record
            record.tick, record.t_ns, now_ns, record.missed = tk
            record.lateness_ns = now_ns - tk.scheduled_ns
            record.angle, record.tdt, record.desired, record.applied = (
                state.angle,
                state.tdt,
                desired,
                applied,
            )
            if sup.state is not self._record_state:
                self._record_state = sup.state
                record.state = sup.state.value
            runner = self.runner
            record.phase = runner.phase_name if runner is not None else NO_PHASE
            fb = self._feedback_ns
            record.stage_ns = (c1 - c0, c2 - c1 - fb, c3 - c2, c4 - c3, 0, fb)
            record.faults = new_faults
            self.recorder.push(record)
        # The CPU clock is a system call (about 1 µs): the record stage of a run that records
        # nothing is nothing, not another reading.
        c5 = cpu() if self.recorder is not None else c4
        fb = self._feedback_ns
        self._store(tk, (c1 - c0, c2 - c1 - fb, c3 - c2, c4 - c3, c5 - c4, fb))
        if trace is not None:
            trace.done(c5, self._trace_notes(tk.tick, events, new_faults))
        if self.status is not None and tk.tick % STATUS_EVERY_TICKS == 0:
            runner = self.runner
            self.status(
                StatusLine(
                    t_s,
                    self._phase_name(),
                    sup.state.value,
                    float(np.max(np.abs(applied))),
                    tk.lateness_ns / 1e3,
                    phase_number=runner.index + 1 if runner is not None else 0,
                    phase_count=len(runner.recipe.phases) if runner is not None else 0,
                    phase_s=t_s - runner.phase_start if runner is not None else 0.0,
                    simulated=self.clock.lockstep,
                    timed_out=self._timed_out(),
                )
            )
        return tk

    def _trace_notes(self, tick: int, events: Sequence[BusEvent], faults: list[Fault]) -> int:
        """What happened in this tick, for the trace (``NOTE_*``)."""
        notes = NOTE_BUS_EVENT if events else 0
        if faults:
            notes |= NOTE_FAULT
        state = self.supervisor.state
        if state is not self._traced_state:
            self._traced_state = state
            notes |= NOTE_STATE
        phase = self.runner.index if self.runner is not None else -1
        if phase != self._traced_phase:
            self._traced_phase = phase
            notes |= NOTE_PHASE
        if self.status is not None and tick % STATUS_EVERY_TICKS == 0:
            notes |= NOTE_STATUS
        return notes

    def decide(
        self,
        tick: int,
        now_ns: int,
        missed: int,
        t_s: float,
        angle: np.ndarray,
        tdt: np.ndarray,
        events: Sequence[BusEvent] = (),
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
            sup.trip(FaultCode.ESTOP, self.estop_requested, tick)
            self.estop_requested = ""
        self._feedback_start_ns = -1
        desired = self._desired(t_s, angle, tdt)
        done = self._recipe_done_ns = self.cpu_clock()
        # The feedback stage ends with the recipe part: one reading of the clock for both.
        start = self._feedback_start_ns
        self._feedback_ns = done - start if start >= 0 else 0
        new_faults = sup.observe(tick, now_ns, self.driver.nodes, angle, tdt, missed, events)
        if self.stop_requested and sup.state in (State.RUNNING, State.ENABLING):
            if self.runner is not None:
                self._abort_phase(t_s, f"stopped: {self.stop_requested}", tick)
            sup.stop(tick)
        elif sup.faults and self.runner is not None and self.runner.in_phase:
            # the phase under way ends here, on the fault: it had no end and no exit in the
            # summary, and the replay ended it at the log's last tick. What the runner
            # proposed in this tick is kept for the log (its abort empties the buffer); the
            # supervisor, ramping down, no longer reads it.
            proposed = desired.copy() if isinstance(desired, np.ndarray) else desired
            self._abort_phase(t_s, f"safety stop: {sup.faults[0].code.name}", tick)
            desired = proposed
        applied = sup.filter(tick, desired, missed)
        if sup.refused is FaultCode.WRONG_SHAPE:
            # no torque vector (its fault says what it was): the tick's bookkeeping and the
            # record read zero asked, where they raised a second, misplaced fault on it
            desired = self._zero
        return desired, applied, new_faults

    def _abort_phase(self, t_s: float, reason: str, tick: int) -> None:
        """End the recipe where it is, and say in the log where the phase under way ended and
        why (a ``phase_end`` note), which no change of phase name shows a replay."""
        runner = self.runner
        assert runner is not None
        under_way = runner.in_phase
        runner.abort(t_s, reason)
        if under_way and self.recorder is not None:
            self.recorder.note("phase_end", reason, tick)

    def _say_stop_notes(self, tick: int) -> None:
        """The supervisor's new stop notes into the log, where the tick's faults go."""
        notes = self.supervisor.stop_notes
        if self.recorder is not None:
            for note in notes[self._stop_notes_said :]:
                self.recorder.note("limit", note, tick)
        self._stop_notes_said = len(notes)

    @staticmethod
    def _another_master(faults: Sequence[Fault]) -> bool:
        """Whether another sender commands the nodes (``FOREIGN_COMMAND``): then the stop is
        an e-stop as well, which the nodes latch whatever the other sender tells them next;
        zero torque and a disable alone are two commands among its own."""
        return any(f.code is FaultCode.FOREIGN_COMMAND for f in faults)

    def _desired(self, t_s: float, angle: np.ndarray, tdt: np.ndarray) -> np.ndarray:
        sup = self.supervisor
        runner = self.runner
        if runner is None or sup.state is not State.RUNNING:
            return self._zero
        if runner.done:
            sup.stop(self.tick)
            return self._zero
        estimates = self.estimator(angle) if self.estimator is not None else None
        runner.advance(t_s, angle, tdt, estimates)
        self._feedback_start_ns = self.cpu_clock()  # its end is the recipe part's (decide)
        desired = runner.feedback(t_s, angle, estimates)
        if desired is None:
            # the supervisor holds the last torque on None (nothing asked); a recipe that
            # proposes nothing is broken, and was held until the bookkeeping raised on it
            sup.trip(FaultCode.WRONG_SHAPE, "the recipe proposed no torques (None)", self.tick)
            return self._zero
        if runner.status is RunStatus.ABORTED and not self.stop_requested:
            sup.trip(FaultCode.RECIPE_ABORT, runner.abort_reason, self.tick)
            if self.recorder is not None and runner.records:
                self.recorder.note("phase_end", runner.records[-1].exit, self.tick)
        return desired

    def _damping_backoff(self, k: int) -> dict[str, dict[str, float]]:
        """``damping_backoff`` of phase record ``k`` for the summary: the least gain of each
        joint whose injected damping backed off there (none: no key)."""
        assert self.runner is not None
        names = self.hand.joint_names
        least = {names[j]: round(g, 3) for j, g in self.runner.damping_backoff(k)}
        return {"damping_backoff": least} if least else {}

    def _timed_out(self) -> tuple[str, ...]:
        if self.runner is None:
            return ()
        return tuple(r.name for r in self.runner.records if r.exit.startswith("timeout"))

    def _phase_name(self) -> str:
        return self.runner.phase_name if self.runner is not None else NO_PHASE

    def _store(self, tk: Tick, stages: tuple[int, ...]) -> None:
        self._stats.store(tk.lateness_ns, tk.missed, stages)
        self._missed += tk.missed
        self.tick += 1

    def _result(self, outcome: Outcome, message: str) -> RunResult:
        phases = []
        if self.runner is not None:
            phases = [
                {
                    "name": r.name,
                    "start_s": round(r.start_s, 6),
                    "end_s": None if r.end_s is None else round(r.end_s, 6),
                    "exit": r.exit,
                    **({"reanalysis": r.reanalysis} if r.reanalysis else {}),
                    **({"schedule": r.schedule} if r.schedule else {}),
                    **self._damping_backoff(k),
                }
                for k, r in enumerate(self.runner.records)
            ]
        window = self._stats.result()
        return RunResult(
            outcome=outcome,
            ticks=self.tick,
            missed_ticks=self._missed,
            lateness_ns=window.lateness_ns,
            missed=window.missed,
            stage_ns=window.stage_ns,
            window=window,
            max_abs_tau=self._max_abs.copy(),
            faults=self._faults(),
            phases=phases,
            message=message,
            node_rejects=self.driver.reject_counts(),
            unexpected_ids=dict(self.driver.unexpected_ids),
            bus_events=self._bus_events,
            supervisor_history=[
                (tick, a.value, e.value, b.value) for tick, a, e, b in self.supervisor.history
            ],
            exception=self.exception,
            stop_notes=list(self.supervisor.stop_notes),
            nodes_reset=self.nodes_reset,
            disable_unconfirmed=self.disable_unconfirmed,
            ended_in_fault=self.ended_in_fault,
            estop_heard=self._estop_heard(),
            rebooted=self.rebooted,
            chatter=self.chatter.found(),
            max_asked_tau=self._max_asked.copy(),
        )


# -- which stage raised ----------------------------------------------------------------------
# Read after the fact from the traceback, so that the tick pays nothing for it: the innermost
# frame of the Runtime's own tick code says which stage was under way by the local names it
# had bound (the stage stamps c0..c5 of ``_tick``, ``desired`` and ``estimates``), and the
# frames below it split the driver's stages by the module they reached (the codec, or the
# safety and recipe packages). A change to those names in ``_tick``, ``_next_tick``,
# ``decide`` or ``_desired`` must be made here too; the tests force an exception in every
# stage and check its code.
_CODEC_FILES = frozenset({finger.__file__, receiver.__file__, wire.__file__})
_SAFETY_DIR = os.path.dirname(safety_faults.__file__) + os.sep
_RECIPES_DIR = os.path.dirname(recipe_runner.__file__) + os.sep
#: the recording plane's folder, by path: the online plane does not import it. A note to the
#: log that raised inside ``decide`` (a phase's end at a stop) was said as the supervisor's
_RECORDING_DIR = os.path.join(os.path.dirname(os.path.dirname(__file__)), "recording") + os.sep


def _in_codec(frame: FrameType) -> bool:
    name = frame.f_code.co_filename
    return name in _CODEC_FILES or name.startswith("<layout ")  # compiled per DBC message


def _interrupts(exc: BaseException, task: asyncio.Task[Any] | None) -> bool:
    """Whether ``exc`` ends the run of ``task`` as an interrupt: ``INTERRUPTS``, or the
    GeneratorExit of its coroutine closed from outside (its task gone with its loop), which
    no tick can be awaited after; the same raised by a stage in the run's own task is that
    stage's fault."""
    if isinstance(exc, INTERRUPTS):
        return True
    if not isinstance(exc, GeneratorExit):
        return False
    try:
        return asyncio.current_task() is not task
    except RuntimeError:  # no event loop runs: closed from outside
        return True


def _contradicted_since(node: finger.FingerNode, before: int) -> bool:
    """Whether ``node`` contradicted itself since its count of contradictions was ``before``
    (-1: it had been already, and was said then)."""
    return before >= 0 and node.contradictions > before


def _rejects_so_far(node: finger.FingerNode) -> tuple[int, int]:
    """A node's rejected frames so far, all and those of a skipped counter."""
    rejects = node.rejects
    return rejects.total, rejects.counts[receiver.Reject.COUNTER_SKIP]


def _doubting_rejects(node: finger.FingerNode, before: tuple[int, int]) -> int:
    """The frames of a node rejected since ``before`` (``_rejects_so_far``) if they put its
    stream in doubt, else 0: one skipped counter alone is a frame lost on the bus (the one
    after it is taken again), and one lost Feedback in the wait for the disable made a node
    that disobeyed it read as a replay (an outside audit); a replayed stream is skip after
    skip, or repeats."""
    total, skips = _rejects_so_far(node)
    new, new_skips = total - before[0], skips - before[1]
    return 0 if new == new_skips <= 1 else new


#: How Python words the RuntimeError a StopIteration leaving a generator or a coroutine
#: becomes (PEP 479); a stage's own ``raise RuntimeError(...) from stop`` is its own, and
#: was read as the bare StopIteration it chained (found by an outside audit)
PEP479_ENDINGS = ("raised StopIteration", "raised StopAsyncIteration")


def _as_raised(exc: BaseException) -> BaseException:
    """The exception as the stage raised it: a StopIteration that leaves a coroutine (or a
    generator) is a RuntimeError there (PEP 479), whose traceback begins above the tick, and
    the run's fault was RUN_EXCEPTION at no tick (and the tick that raised went uncounted);
    its cause has the stage, the tick and the place (found by an outside audit)."""
    cause = exc.__cause__
    if (
        type(exc) is RuntimeError
        and isinstance(cause, (StopIteration, StopAsyncIteration))
        and cause.__traceback__ is not None
        and str(exc).endswith(PEP479_ENDINGS)
    ):
        return cause
    return exc


def _stage_of(exc: BaseException) -> tuple[FaultCode, Tick | None]:
    """The fault code of the stage ``exc`` came from, and the tick under way (if known)."""
    frames = [frame for frame, _ in traceback.walk_tb(exc.__traceback__)]
    tick_code, next_code = Runtime._tick.__code__, Runtime._next_tick.__code__
    decide_code, desired_code = Runtime.decide.__code__, Runtime._desired.__code__
    own = {tick_code, next_code, decide_code, desired_code}
    tk = next((f.f_locals.get("tk") for f in frames if f.f_code is tick_code), None)
    tick = tk if isinstance(tk, Tick) else None
    at = next((i for i in range(len(frames) - 1, -1, -1) if frames[i].f_code in own), None)
    if at is None:
        return FaultCode.RUN_EXCEPTION, tick
    frame, below = frames[at], frames[at + 1 :]
    if any(f.f_code.co_filename.startswith(_RECORDING_DIR) for f in below):
        return FaultCode.RECORD_EXCEPTION, tick  # the recorder's, whichever stage called it
    bound = frame.f_locals
    callee = below[0].f_code.co_filename if below else ""
    code = frame.f_code
    if code is next_code:
        return (
            FaultCode.CLOCK_EXCEPTION if "tk" not in bound else FaultCode.RECORD_EXCEPTION
        ), tick
    if code is decide_code:
        return (
            FaultCode.RUNNER_EXCEPTION
            if callee.startswith(_RECIPES_DIR)
            else FaultCode.SUPERVISOR_EXCEPTION
        ), tick
    if code is desired_code:
        if callee.startswith(_SAFETY_DIR):
            return FaultCode.SUPERVISOR_EXCEPTION, tick
        return (
            FaultCode.ESTIMATOR_EXCEPTION
            if "estimates" not in bound
            else FaultCode.RUNNER_EXCEPTION
        ), tick
    if "c0" not in bound:
        return FaultCode.HOOK_EXCEPTION, tick
    if "c1" not in bound:
        return (
            FaultCode.DECODE_EXCEPTION
            if any(_in_codec(f) for f in below)
            else FaultCode.POLL_EXCEPTION
        ), tick
    if "desired" not in bound:  # the operator's e-stop frame, sent before ``decide``
        return FaultCode.SEND_EXCEPTION, tick
    if "c4" not in bound:
        if callee.startswith(_SAFETY_DIR):
            return FaultCode.SUPERVISOR_EXCEPTION, tick
        return (
            FaultCode.ENCODE_EXCEPTION
            if any(_in_codec(f) for f in below)
            else FaultCode.SEND_EXCEPTION
        ), tick
    if "c5" not in bound:
        return FaultCode.RECORD_EXCEPTION, tick
    return FaultCode.STATUS_EXCEPTION, tick


def _describe(exc: BaseException, code: FaultCode, tick: int) -> TickException:
    """What ``exc`` said and where, bounded, whatever its ``__str__`` does."""
    message = said_by(exc)
    if len(message) > EXCEPTION_TEXT_CHARS:
        message = message[: EXCEPTION_TEXT_CHARS - 3] + "..."
    where = "?"
    text = ""
    try:
        frames = traceback.extract_tb(exc.__traceback__)
        if frames:
            last = frames[-1]
            where = f"{last.name} ({_short_path(last.filename)}:{last.lineno})"
        text = "".join(traceback.format_exception(exc, limit=-12))
    except Exception:  # the description is a courtesy; the stop does not depend on it
        pass
    return TickException(code, tick, type(exc).__name__, message, where, text)


def _short_path(filename: str) -> str:
    """A file of handctl relative to the package's parent, others as they are (the parent
    found from the package, not from this module's place in it)."""
    root = os.path.dirname(os.path.dirname(os.path.abspath(handctl.__file__))) + os.sep
    return filename[len(root) :] if filename.startswith(root) else filename
