"""Watchdogs that turn what the nodes said (or did not say) into faults.

Each monitor keeps a few fixed-size arrays and is updated once per tick; none allocates per
joint per tick beyond small numpy temporaries, and none waits for anything.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

from handctl.arrays import FloatArray
from handctl.config import SafetyConfig
from handctl.online.drivers.finger import FingerNode, fault_names
from handctl.online.safety.faults import FaultCode
from handctl.protocol import COMMAND_WATCHDOG_S, Layout, NodeState

ENABLED = int(NodeState.ENABLED)  # plain ints: compared for every node every tick
FAULT = int(NodeState.FAULT)
Finding = tuple[FaultCode, str]


def ticks_lasting(seconds: float, dt: float) -> int:
    """The fewest whole ticks that last at least ``seconds``: a window the config states in
    seconds ("the mismatch must hold this long") must not end sooner at a loop rate that does
    not divide it. Rounding to the nearest made 50 ms 12 ticks (48 ms) at 250 Hz. The slack
    keeps an exact quotient (0.05 s at 1 kHz) from rounding up on its last bit."""
    return math.ceil(seconds / dt - 1e-9)


def node_fault(node: FingerNode) -> Finding:
    """A node in FAULT, said with its fault bits: ESTOP if one of them is the e-stop's (an
    operator's or a node's stop, which must be named as such), NODE_FAULT otherwise."""
    names = fault_names(node.fault_bits)
    code = FaultCode.ESTOP if "ESTOP" in names else FaultCode.NODE_FAULT
    why = ""
    if "TIMEOUT" in names:
        # the node's own watchdog: what it says is of the host or the bus (a host frozen
        # within a tick was read as the node's fault, its LOOP_OVERRUN a tick later)
        why = (
            f": it heard no command for its {COMMAND_WATCHDOG_S * 1e3:g} ms "
            "watchdog (the host stalled, or its commands did not reach it)"
        )
    who = f"node {node.node_id} ({node.finger.name})"
    return code, f"{who} in FAULT ({', '.join(names) or 'no bits'}){why}"


def add_node_fault(found: list[Finding], node: FingerNode) -> None:
    """Add ``node_fault(node)`` to ``found``, joined to a finding of its code already there.

    Why: the supervisor latches a code once, so a second node's finding of the same code in
    the same tick was dropped. An e-stop frame latches every node in FAULT (ESTOP) in the
    same node tick, and the stop named the first node in FAULT (ESTOP) alone, as if one node
    had stopped itself."""
    code, detail = node_fault(node)
    for k, (known, said) in enumerate(found):
        if known is code:
            found[k] = (code, f"{said}; {detail}")
            return
    found.append((code, detail))


def node_faults(nodes: Sequence[FingerNode]) -> list[Finding]:
    """``node_fault`` of each of ``nodes``, one finding per code naming every node of it."""
    found: list[Finding] = []
    for node in nodes:
        add_node_fault(found, node)
    return found


def rejected_since(node: FingerNode, layout: Layout, now_ns: int, timeout_ns: int) -> str:
    """What a timeout of ``layout``'s stream adds when frames of it came and were rejected
    since the last one accepted ("" when none came): a stream that went on arriving, every
    frame refused (a second sender on its id, bad CRCs), is no silent node, and the stop
    said "last heartbeat 351 ms ago" of a node whose Heartbeats never stopped, sending the
    operator to its power and wiring. Said with the counts, as the start-up says it of a
    node none of whose Feedback it could take (``loop._no_feedback``). Only a stream whose
    rejected frames still came within half of ``timeout_ns`` before ``now_ns`` is said to
    be no silent node: one that fell silent after a bad frame or two (a brown-out) is said
    as that, with when its last frame came (found by an outside audit of the first
    wording)."""
    heard, last_ns = node.rejected_since_accepted(layout)
    if not heard:
        return ""
    kinds = ", ".join(f"{kind} {n}" for kind, n in heard.items())
    name = layout.name.rpartition("_")[0]  # Heartbeat_2: Heartbeat
    count = sum(heard.values())
    said = (
        f"; {count} {name} frame{'s' if count != 1 else ''} heard since and rejected "
        f"({kinds}), none accepted, the last {(now_ns - last_ns) / 1e6:.1f} ms ago"
    )
    if 2 * (now_ns - last_ns) <= timeout_ns:  # still coming, a frame at least each half of it
        return said + ": not a silent node; `handctl nodes` shows them"
    return said + ": the node fell silent after them"


class NodeWatch:
    """Feedback age, heartbeat age, device state and reboots of every node."""

    def __init__(self, safety: SafetyConfig) -> None:
        self.feedback_timeout_ns = int(safety.feedback_timeout_s * 1e9)
        self.heartbeat_timeout_ns = int(safety.heartbeat_timeout_s * 1e9)
        self._reboots: list[int] = []
        self._reboots_in_rejects: list[int] = []

    def arm(self, nodes: Sequence[FingerNode]) -> None:
        """Remember the reboot counts at the moment torque starts to flow."""
        self._reboots = [node.reboots for node in nodes]
        self._reboots_in_rejects = [node.reboots_in_rejects for node in nodes]

    def rebooted_since_armed(self, nodes: Sequence[FingerNode]) -> list[str]:
        """Each node a Heartbeat says rebooted since ``arm``, in words (none if never armed).

        Checked at a run's end, not each tick: ``check`` runs while the torque is armed only,
        and the first Heartbeat after a reboot is rejected (the node's counters restart), so
        a node that rebooted in the stop's zero ticks or the wait for the disable was seen by
        nothing but a count of counter skips, and the run said "completed"."""
        said = []
        for i, node in enumerate(nodes[: len(self._reboots)]):
            who = f"node {node.node_id} ({node.finger.name})"
            if node.reboots > self._reboots[i]:
                said.append(f"{who}: its Heartbeat's uptime went back")
            elif node.reboots_in_rejects > self._reboots_in_rejects[i]:
                said.append(
                    f"{who}: a Heartbeat of it with its uptime gone back to "
                    f"{node.rejected_uptime_ms} ms, rejected for its counter (which a reboot "
                    "restarts)"
                )
        return said

    def check(
        self, now_ns: int, nodes: Sequence[FingerNode], expect_enabled: bool
    ) -> list[Finding]:
        found: list[Finding] = []
        feedback_timeout, heartbeat_timeout = self.feedback_timeout_ns, self.heartbeat_timeout_ns
        for i, node in enumerate(nodes):
            # The common tick finds nothing: compare numbers, build no text.
            fb, hb = node.feedback_ns, node.heartbeat_ns
            if (
                fb is not None
                and now_ns - fb <= feedback_timeout
                and hb is not None
                and now_ns - hb <= heartbeat_timeout
                and node.state == ENABLED
                and (i >= len(self._reboots) or node.reboots <= self._reboots[i])
            ):
                continue
            who = f"node {node.node_id} ({node.finger.name})"
            if fb is None or now_ns - fb > feedback_timeout:
                age = "never" if fb is None else f"{(now_ns - fb) / 1e6:.1f} ms ago"
                found.append(
                    (
                        FaultCode.FEEDBACK_TIMEOUT,
                        f"{who}: last valid feedback {age}"
                        + rejected_since(node, node.layouts.feedback, now_ns, feedback_timeout),
                    )
                )
            if hb is None or now_ns - hb > heartbeat_timeout:
                age = "never" if hb is None else f"{(now_ns - hb) / 1e6:.0f} ms ago"
                found.append(
                    (
                        FaultCode.HEARTBEAT_LOST,
                        f"{who}: last heartbeat {age}"
                        + rejected_since(node, node.layouts.heartbeat, now_ns, heartbeat_timeout),
                    )
                )
            if i < len(self._reboots) and node.reboots > self._reboots[i]:
                found.append((FaultCode.NODE_REBOOT, f"{who} rebooted"))
            if node.state == FAULT:
                add_node_fault(found, node)
            elif expect_enabled and node.state != ENABLED:
                found.append(
                    (FaultCode.NODE_STATE, f"{who} is {node.state_name}, expected ENABLED")
                )
        return found


class TdtMonitor:
    """TDT torque against the applied command: a tolerance held over a window, and a sensor
    whose reading does not move at all while the command does (stuck).

    Plain Python over nine joints: at this size a loop of float operations costs a third of
    the twenty-odd numpy calls the vectorised form needs, and this runs every tick.
    """

    def __init__(
        self, safety: SafetyConfig, n_joints: int, dt: float, names: Sequence[str]
    ) -> None:
        self.names = tuple(names)
        self.n = n_joints
        self.tol = safety.tdt_tolerance
        self.rel = safety.tdt_tolerance_rel
        self.alpha = dt / (safety.tdt_lag_s + dt)
        self.window = max(1, ticks_lasting(safety.tdt_window_s, dt))
        self.stuck_window = max(2, ticks_lasting(safety.tdt_stuck_window_s, dt))
        self.min_change = safety.tdt_stuck_min_change
        still = ticks_lasting(safety.tdt_stuck_still_s, dt)
        self.still_window = still if still > 0 else 1 << 62
        #: ticks a sensor is given to answer a command that has moved: three of its lags (95 %
        #: of a step), within the stuck window. Without it, a reading that had sat still at a
        #: steady torque for a window (a sensor quieter than its resolution) was "stuck" at the
        #: first fast ramp, before the joint's torque could have moved at all.
        self.answer_ticks = min(max(1, round(3 * safety.tdt_lag_s / dt)), self.stuck_window - 1)
        self.expected = [0.0] * n_joints
        self.mismatch_ticks = [0] * n_joints
        self.same_ticks = [0] * n_joints
        self.last_reading = [float("nan")] * n_joints
        self.cmd_lo = [0.0] * n_joints
        self.cmd_hi = [0.0] * n_joints
        #: the count of ``same_ticks`` at which the command had first moved ``min_change``
        #: while the reading stood (-1: not yet)
        self.moved_at = [-1] * n_joints

    def reset(self, applied: FloatArray) -> None:
        self.expected = [float(a) for a in applied]
        self.mismatch_ticks = [0] * self.n
        self.same_ticks = [0] * self.n
        self.last_reading = [float("nan")] * self.n
        self.moved_at = [-1] * self.n

    def update(self, applied: FloatArray, reading: FloatArray) -> list[Finding]:
        """Fold one tick in: ``applied`` is what the nodes were last told, ``reading`` the TDT."""
        found: list[Finding] = []
        alpha, tol, rel = self.alpha, self.tol, self.rel
        expected, mismatch = self.expected, self.mismatch_ticks
        same_ticks, last = self.same_ticks, self.last_reading
        lo, hi, moved_at = self.cmd_lo, self.cmd_hi, self.moved_at
        for j, (a, r) in enumerate(zip(applied.tolist(), reading.tolist(), strict=True)):
            e = expected[j] + (a - expected[j]) * alpha
            expected[j] = e
            if abs(r - e) > tol + rel * abs(e):
                mismatch[j] += 1
                if mismatch[j] >= self.window:
                    found.append(
                        (
                            FaultCode.TDT_MISMATCH,
                            # to the wire's 0.0001 N·m: a hand of joints of a thousandth
                            # read "TDT +0.001 N·m, expected -0.000 N·m"
                            f"{self.names[j]}: TDT {r:+.4f} N·m, expected {e:+.4f} N·m "
                            f"for {mismatch[j]} ticks",
                        )
                    )
            else:
                mismatch[j] = 0
            if r == last[j]:
                same_ticks[j] += 1
                lo[j] = min(lo[j], a)
                hi[j] = max(hi[j], a)
                n = same_ticks[j]
                if moved_at[j] < 0 and hi[j] - lo[j] >= self.min_change:
                    moved_at[j] = n
                if (
                    n >= self.stuck_window
                    and moved_at[j] >= 0
                    and n - moved_at[j] >= self.answer_ticks
                ) or n >= self.still_window:
                    found.append(
                        (
                            FaultCode.TDT_STUCK,
                            f"{self.names[j]}: TDT fixed at {r:+.4f} N·m for "
                            f"{same_ticks[j]} ticks while the command moved "
                            f"{hi[j] - lo[j]:.4f} N·m"
                            + (
                                ""
                                if moved_at[j] >= 0
                                else " (no live sensor reads so still so long: "
                                "safety.tdt_stuck_still_s)"
                            ),
                        )
                    )
            else:
                same_ticks[j] = 0
                lo[j] = hi[j] = a
                moved_at[j] = -1
                last[j] = r
        return found


class TickWatch:
    """Late ticks and failed sends, counted consecutively."""

    def __init__(self, safety: SafetyConfig) -> None:
        self.max_misses = safety.max_consecutive_misses
        self.max_send_failures = safety.max_consecutive_send_failures
        self.consecutive_misses = 0
        self.consecutive_send_failures = 0

    def tick(self, missed: int) -> list[Finding]:
        """``missed``: ticks the clock skipped before this one (0 when on time)."""
        if missed <= 0:
            self.consecutive_misses = 0
            return []
        self.consecutive_misses += missed
        if self.consecutive_misses >= self.max_misses:
            return [(FaultCode.LOOP_OVERRUN, f"{self.consecutive_misses} consecutive ticks missed")]
        return []

    def sent(self, ok: bool) -> list[Finding]:
        self.consecutive_send_failures = 0 if ok else self.consecutive_send_failures + 1
        if self.consecutive_send_failures >= self.max_send_failures:
            return [
                (
                    FaultCode.BUS_ERROR,
                    f"{self.consecutive_send_failures} consecutive ticks with command frames "
                    "that could not be sent",
                )
            ]
        return []


class ReceiveWatch:
    """Whether the host can still believe what a node's frames say: no contradiction among
    its reports, and no more rejected frames within the window than the safety section allows;
    and whether the node hears only this host: no frame on the host's command ids from
    another sender.

    Rejected frames are counted by the receiver without bound; a stream of replayed or
    corrupted frames can keep the genuine ones from being accepted while enough of its own
    pass to look alive (a node's FAULT then goes unseen). A rate, per node over a sliding
    window of ticks, is what tells that from the odd lost frame. The window restarts whenever
    the watch resumes after a pause (a gap in the ticks it is given).
    """

    def __init__(self, safety: SafetyConfig, dt: float) -> None:
        self.window = max(1, ticks_lasting(safety.reject_window_s, dt))
        self.limit = safety.max_rejects_in_window
        self._totals: list[list[int]] = []  # per node: its reject total at each tick of the window
        self._pos = 0
        self._last_tick: int | None = None

    def check(self, tick: int, nodes: Sequence[FingerNode]) -> list[Finding]:
        found: list[Finding] = []
        if (
            self._last_tick is None
            or tick != self._last_tick + 1
            or len(self._totals) != len(nodes)
        ):
            self._totals = [[node.rejects.total] * self.window for node in nodes]
            self._pos = 0
        self._last_tick = tick
        pos = self._pos
        for node, totals in zip(nodes, self._totals, strict=True):
            total = node.rejects.total
            recent = total - totals[pos]  # rejected within the last ``window`` ticks
            totals[pos] = total
            if recent > self.limit:
                found.append(
                    (
                        FaultCode.REJECT_RATE,
                        f"node {node.node_id} ({node.finger.name}): {recent} frames "
                        f"rejected within {self.window} ticks (at most {self.limit}; "
                        "so far: "
                        + ", ".join(f"{k} {v}" for k, v in node.rejects.as_dict().items() if v)
                        + ")",
                    )
                )
            if node.contradiction:
                found.append(
                    (
                        FaultCode.NODE_CONTRADICTION,
                        f"node {node.node_id} ({node.finger.name}): {node.contradiction}",
                    )
                )
            if node.foreign_command:
                found.append(
                    (
                        FaultCode.FOREIGN_COMMAND,
                        f"node {node.node_id} ({node.finger.name}): {node.foreign_command}",
                    )
                )
        self._pos = (pos + 1) % self.window
        return found


class StartupRejects:
    """The reject rate of ``ReceiveWatch``, judged while the start-up listens, before any
    node is enabled.

    Why: a second hand on the bus answering to the same ids, or a stream replayed from a
    log, interleaves its counters with the node's, so nearly every frame is rejected; yet
    the first frame of each node was heard as fresh, and the start-up enabled the nodes
    (on a bus where an enable reaches both hands). The start-up is short (a few ticks in
    lockstep), shorter than a reject window, so a start-up that has heard a rejected frame
    is not ``settled`` until a whole window has passed since; a clean one is unchanged."""

    def __init__(self, safety: SafetyConfig, dt: float, nodes: Sequence[FingerNode]) -> None:
        self.watch = ReceiveWatch(safety, dt)
        self._before = [n.rejects.total for n in nodes]
        self._first: int | None = None  # the tick of the first rejected frame heard

    def check(self, tick: int, nodes: Sequence[FingerNode]) -> str:
        """The reject rate's finding this tick ("" for none); to be called every tick."""
        rate = [d for code, d in self.watch.check(tick, nodes) if code is FaultCode.REJECT_RATE]
        if self._first is None and any(
            n.rejects.total > before for n, before in zip(nodes, self._before, strict=True)
        ):
            self._first = tick
        return "; ".join(rate)

    def settled(self, tick: int) -> bool:
        """Whether no rejected frame was heard, or a whole window has passed since one."""
        return self._first is None or tick - self._first >= self.watch.window
