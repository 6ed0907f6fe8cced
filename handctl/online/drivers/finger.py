"""One finger node from the host's side: pure frame building and parsing, plus its state.

Building a command is a pure function of the applied torques and the counter (the moteus way):
the only side effect of a tick is the one send. Parsing a feedback frame is pure too; the node
state object only remembers what the frames said, so it can be inspected, logged and tested
without a bus.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import NamedTuple

from handctl.config import FingerConfig
from handctl.online.drivers.receiver import CounterCheck, Reject, RejectCounts, validate
from handctl.protocol import (
    NODE_COMMANDS,
    Layout,
    NodeState,
    Protocol,
    foreign_status_version,
    node_state_name,
)

#: FaultBits of the device (PROTOCOL.md), by name.
FAULT_BITS = {"TIMEOUT": 0x01, "ESTOP": 0x02, "RX_ERRORS": 0x04, "SENSOR": 0x08, "SATURATED": 0x10}
#: Bits only a node in FAULT may report (they latch it), and bits the protocol reserves.
LATCHED_BITS = 0x0F
RESERVED_BITS = 0xE0
_DISABLED = int(NodeState.DISABLED)  # plain ints on the hot path
_ENABLED = int(NodeState.ENABLED)
_FAULT = int(NodeState.FAULT)
_DEFINED_STATES = frozenset((_DISABLED, _ENABLED, _FAULT))
_COUNTER_REJECTS = frozenset((Reject.COUNTER_SKIP, Reject.COUNTER_REPEAT))


def fault_names(bits: int) -> list[str]:
    """Names of the fault bits set in ``bits`` (unknown bits as ``BIT<n>``)."""
    names = [name for name, mask in FAULT_BITS.items() if bits & mask]
    names += [
        f"BIT{i}"
        for i in range(8)
        if bits & (1 << i) and not any(mask == 1 << i for mask in FAULT_BITS.values())
    ]
    return names


#: ns: how long after a node's first FAULT report an ENABLED of another stream (one that has
#: not said FAULT itself) may still be one it queued before the fault. Frames a node queues in
#: one of its 1 ms ticks leave in that tick, in the order of their identifiers; a stream that
#: goes on saying ENABLED after that is contradicting the FAULT (a forged Heartbeat hiding it).
REORDERED_WITHIN_NS = 1_000_000


#: ns: a frame with the counter of the one accepted on its stream, other contents, and
#: arriving this soon after it, is a second sender (``FingerNode._second_sender``). Later, it
#: is the counter come round again after frames were lost: 256 of a 1 kHz stream take 256
#: ms, and a run's host, starved under load in its start-up, lost just that many (its
#: receive queue full) and was stopped on a contradiction (CI). A forged frame and the node's
#: own of that counter arrive within one of the node's 1 ms ticks of each other.
SECOND_SENDER_WITHIN_NS = 100_000_000


#: ms: the range of a Heartbeat's uptime, a uint32 of ms (PROTOCOL.md): it wraps to 0 after
#: 49.7 days.
UPTIME_RANGE_MS = 1 << 32
#: ms: how much a node's uptime may have gone on past its wrap beyond what the host's clock
#: says passed between two of its Heartbeats (their delivery, the two clocks' rates), for the
#: drop to be the wrap and not a reboot. A node that reboots within this of its wrap is taken
#: for one that wrapped: once in 49.7 days of uptime, for one second.
UPTIME_WRAP_SLACK_MS = 1000


def rebooted(last_ms: int, uptime_ms: int, elapsed_ns: int) -> bool:
    """Whether a Heartbeat's uptime ``uptime_ms``, ``elapsed_ns`` on the host's clock after
    one that said ``last_ms``, says the node rebooted. A smaller uptime was a reboot, so a
    node whose uptime wrapped past 2**32 ms stopped the run as rebooted (found by an outside
    audit): a drop is the wrap when the uptime, counted past 2**32, went on about as far as
    the host's clock did; any other drop is a reboot."""
    if uptime_ms >= last_ms:
        return False
    went_on_ms = (uptime_ms - last_ms) % UPTIME_RANGE_MS
    return went_on_ms > elapsed_ns / 1e6 + UPTIME_WRAP_SLACK_MS


class _RejectedSince:
    """The frames of one stream rejected since ``after``, its last accepted frame (the
    object ``CounterCheck.frame`` holds; None: none yet), by kind, and when the last of them
    arrived (ns)."""

    __slots__ = ("after", "counts", "last_ns")

    def __init__(self, after: bytes | None) -> None:
        self.after = after
        self.counts = RejectCounts()
        self.last_ns = 0


@dataclass(frozen=True)
class FingerLayouts:
    """The DBC layouts one finger node uses, looked up once."""

    command: Layout
    node_command: Layout
    feedback: Layout
    status: Layout
    heartbeat: Layout
    #: The protocol version of the DBC these layouts come from: what the node must speak.
    protocol_version: int = 0

    @classmethod
    def for_node(cls, protocol: Protocol, node_id: int) -> FingerLayouts:
        return cls(
            command=protocol.layout("TorqueCommand", node_id),
            node_command=protocol.layout("NodeCommand", node_id),
            feedback=protocol.layout("Feedback", node_id),
            status=protocol.layout("Status", node_id),
            heartbeat=protocol.layout("Heartbeat", node_id),
            protocol_version=protocol.version,
        )


def make_command(layout: Layout, counter: int, torques: Sequence[float]) -> tuple[int, bytes]:
    """The torque-command frame (id, payload) for one finger's applied torques in N·m."""
    return layout.frame_id, layout.encode(counter, torques)


def make_node_command(layout: Layout, counter: int, command: str) -> tuple[int, bytes]:
    """An enable / disable / fault_reset frame."""
    return layout.frame_id, layout.encode(counter, (NODE_COMMANDS[command],))


class Feedback(NamedTuple):
    """One decoded feedback frame, before the host's TDT calibration.

    A named tuple, not a frozen dataclass: one is built for every feedback frame, three or more
    a tick, and a frozen dataclass's constructor sets each field through ``object.__setattr__``
    (about three times the cost). Immutable all the same."""

    tdt: tuple[float, ...]  # N·m, node calibration, one per joint on the wire
    angles: tuple[float, ...]  # rad
    state: int
    fault_bits: int


def parse_feedback(values: Sequence[float]) -> Feedback:
    """Turn the decoded signal values of a Feedback frame (``Torque1..k``, ``Angle1..k``,
    ``State``, ``FaultBits``; k the node's joints) into named quantities."""
    k = (len(values) - 2) // 2
    return Feedback(
        tuple(values[:k]), tuple(values[k : 2 * k]), int(values[2 * k]), int(values[2 * k + 1])
    )


class FingerNode:
    """What the host knows of one finger node, updated only by frames that passed every check."""

    def __init__(self, finger: FingerConfig, layouts: FingerLayouts) -> None:
        self.finger = finger
        self.node_id = finger.node_id
        self.layouts = layouts
        self.streams = {
            layout.frame_id: (layout, CounterCheck())
            for layout in (layouts.feedback, layouts.status, layouts.heartbeat)
        }
        self.rejects = RejectCounts()
        #: Per stream id: its frames rejected since its last accepted one. Kept in the reject
        #: path alone (the accepted one is the 1 kHz path): counts whose frame is not the
        #: stream's last accepted object any more are of an earlier gap, and start again.
        #: Whether a node's Heartbeat went silent or came and was all rejected (a second
        #: sender on its id) is two different stops, with two places to look (``NodeWatch``).
        self._rejected_since: dict[int, _RejectedSince] = {}
        self.accepted = 0
        self.command_counter = 0
        self.node_command_counter = 0
        self.state = -1  # unknown until the node speaks
        self.fault_bits = 0
        #: The first report since ``clear_contradiction`` that contradicts another or the
        #: protocol (empty if none), and how many there were in all.
        self.contradiction = ""
        self.contradictions = 0
        #: The host's own command identifiers for this node: a frame on one of them that the
        #: host hears was sent by someone else (SocketCAN, the unix and the virtual bus do not
        #: hand a sender its own frames).
        self.command_ids = frozenset((layouts.command.frame_id, layouts.node_command.frame_id))
        #: The first frame on ``command_ids`` heard since ``clear_contradiction`` (empty if
        #: none), and how many were heard in all.
        self.foreign_command = ""
        self.foreign_commands = 0
        #: Whether this host commands the node (it sent a node command): only then is an
        #: ENABLED after DISABLED judged by the enables it sent. A listener (``nodes``,
        #: ``monitor``) hears another host enable the node, which is no contradiction.
        self._commanding = False
        #: The streams (Feedback, Heartbeat, Status) not yet heard saying ENABLED since this
        #: host's last enable: until each has, a DISABLED of that stream may be one sent
        #: before the enable (CAN keeps the order within an identifier, not across them).
        self._since_enable: set[str] = set()
        #: When the first ENABLED report since this host's last enable arrived (host clock;
        #: None before one has). Frames a node queues in one of its ticks leave within it, so
        #: a DISABLED later than ``REORDERED_WITHIN_NS`` after that is no report from before
        #: the enable, whichever stream it comes on: a node whose Feedback went on saying
        #: DISABLED beside a forged Heartbeat ENABLED was taken for enabled for a whole run.
        self._enabled_ns: int | None = None
        #: The streams not yet heard saying FAULT since the host took the node for FAULT: until
        #: each has, an ENABLED of that stream may be one sent before the fault. A node enabled
        #: and e-stopped in one of its ticks queues a Status ENABLED, then sends a Feedback
        #: FAULT that wins the bus by its lower identifier and arrives first; that ENABLED was
        #: taken for the node contradicting itself, and the stop named no e-stop.
        self._since_fault: set[str] = set()
        self._fault_ns = 0  # when the report that the node is in FAULT arrived (host clock)
        #: Whether the node may now go from DISABLED to ENABLED: this host enabled it, and
        #: no stream that had already said ENABLED since has said DISABLED again.
        self._may_enable = False
        self.feedback: Feedback | None = None
        self.feedback_ns: int | None = None  # when the last good feedback arrived (host clock)
        self.heartbeat_ns: int | None = None
        self.uptime_ms: int | None = None
        self.reboots = 0
        #: Heartbeats rejected for their counter whose uptime says the node rebooted, and the
        #: last such uptime (ms). Never applied: a node's counters restart at its boot, so the
        #: first Heartbeat after a reboot is a counter skip, and ``reboots`` counts the reboot
        #: only at the next, 100 ms on. A node that rebooted in a run's last 100 ms (its
        #: stop's zero ticks, the wait for its disable) went unsaid (found by an outside
        #: audit); this is what the run says it by (``NodeWatch.rebooted_since_armed``).
        self.reboots_in_rejects = 0
        self.rejected_uptime_ms = 0
        self.status: tuple[float, ...] | None = None
        self.status_ns: int | None = None
        #: What the node's last intact Status said of its versions (a Status of another
        #: protocol too, which is rejected all the same), and when it arrived (host clock).
        self.protocol_version: int | None = None
        self.firmware_version: tuple[int, int, int] | None = None
        self.version_ns: int | None = None

    def resynchronise(self) -> None:
        """Take the node's next frame of each stream with whatever counter it carries.

        For the start of a run: while no run listened, the node kept counting (or rebooted, or
        a new simulated hand took its place), so the counters last heard say nothing about the
        next ones, and rejecting its first frames would be the host's mistake, not the node's.
        """
        for _, counters in self.streams.values():
            counters.reset()
        self._rejected_since.clear()

    @property
    def state_name(self) -> str:
        return node_state_name(self.state)

    def next_command(self, torques: Sequence[float]) -> tuple[int, bytes]:
        frame = make_command(self.layouts.command, self.command_counter, torques)
        self.command_counter = (self.command_counter + 1) & 0xFF
        return frame

    def take_back_command(self) -> None:
        """The last ``next_command``'s frame never went: its counter is the next frame's. Used
        up, the node would take the next frame (the stop's zero torque too) for a skip and
        reject it, keeping its last torque a period longer."""
        self.command_counter = (self.command_counter - 1) & 0xFF

    def next_node_command(self, command: str) -> tuple[int, bytes]:
        self._commanding = True
        if command == "enable":
            self._since_enable = {"Feedback", "Heartbeat", "Status"}
            self._enabled_ns = None
            self._may_enable = True
        frame = make_node_command(self.layouts.node_command, self.node_command_counter, command)
        self.node_command_counter = (self.node_command_counter + 1) & 0xFF
        return frame

    def take_back_node_command(self) -> None:
        """The last ``next_node_command``'s frame never went (``take_back_command``)."""
        self.node_command_counter = (self.node_command_counter - 1) & 0xFF

    def receive(self, frame_id: int, data: bytes, arrival_ns: int) -> Reject | None:
        """Apply one frame addressed to this node's streams; return why it was rejected, if so.

        ``arrival_ns`` is when the frame reached the host (its receive time), not when it was
        read: the age of what the node said is measured from it.
        """
        layout, counters = self.streams[frame_id]
        reason = validate(layout, data, counters)
        if reason is not None:
            self.rejects.add(reason)
            since = self._rejected_since.get(frame_id)
            if since is None or since.after is not counters.frame:
                since = self._rejected_since[frame_id] = _RejectedSince(counters.frame)
            since.counts.add(reason)
            since.last_ns = arrival_ns
            if layout is self.layouts.heartbeat and reason in _COUNTER_REJECTS:
                self._reboot_in_reject(layout, data, arrival_ns)
            if (
                reason is Reject.COUNTER_REPEAT
                and data != counters.frame
                and arrival_ns - counters.frame_ns <= SECOND_SENDER_WITHIN_NS
            ):
                self._second_sender(layout, data)
            if reason is Reject.LENGTH and layout is self.layouts.status:
                version = foreign_status_version(layout, data)
                if version is not None:
                    self.protocol_version, self.firmware_version = version, None
                    self.version_ns = arrival_ns
                    self._check_version(version)
            return reason
        self.accepted += 1
        counters.frame, counters.frame_ns = data, arrival_ns
        _, values = layout.decode(data)
        if layout is self.layouts.feedback:
            fb = parse_feedback(values)
            self.feedback = fb
            self.feedback_ns = arrival_ns
            if fb.fault_bits == 0 and fb.state == self.state:  # every tick, as a rule
                self.fault_bits = 0  # all ``_report`` would do: nothing to contradict
            else:
                self._report(fb.state, fb.fault_bits, "Feedback", arrival_ns)
        elif layout is self.layouts.heartbeat:
            state, uptime = int(values[0]), int(values[1])
            last_ns = self.heartbeat_ns
            if (
                self.uptime_ms is not None
                and last_ns is not None
                and rebooted(self.uptime_ms, uptime, arrival_ns - last_ns)
            ):
                # Uptime went backwards, not by its wrap: the node rebooted (and came back
                # DISABLED). Its counters restarted; each stream re-synchronises after one
                # rejected frame.
                self.reboots += 1
            self.uptime_ms = uptime
            self.heartbeat_ns = arrival_ns
            self._report(state, None, "Heartbeat", arrival_ns)
        else:
            self.status = values
            self.status_ns = arrival_ns
            self.protocol_version = int(values[6])
            self.firmware_version = (int(values[7]), int(values[8]), int(values[9]))
            self.version_ns = arrival_ns
            self._check_version(self.protocol_version)
            self._report(int(values[0]), int(values[1]), "Status", arrival_ns)
        return None

    def _reboot_in_reject(self, layout: Layout, data: bytes, arrival_ns: int) -> None:
        """A Heartbeat rejected for its counter (so intact: length and CRC passed): count it
        in ``reboots_in_rejects`` if its uptime says the node rebooted since the last one
        accepted. Nothing of it is applied; it is what the run's end says."""
        last_ms, last_ns = self.uptime_ms, self.heartbeat_ns
        if last_ms is None or last_ns is None:
            return
        uptime = int(layout.decode(data)[1][1])
        if rebooted(last_ms, uptime, arrival_ns - last_ns):
            self.reboots_in_rejects += 1
            self.rejected_uptime_ms = uptime

    def rejected_since_accepted(self, layout: Layout) -> tuple[dict[str, int], int]:
        """The frames of ``layout``'s stream (one of this node's) rejected since the last one
        of it that was accepted (or since the run began listening, when none was), by kind:
        only the kinds that occurred, empty when none; and when the last of them arrived
        (ns; 0 when none)."""
        since = self._rejected_since.get(layout.frame_id)
        if since is None or since.after is not self.streams[layout.frame_id][1].frame:
            return {}, 0
        return {kind: n for kind, n in since.counts.as_dict().items() if n}, since.last_ns

    @property
    def feedback_enabled(self) -> bool:
        """Whether the node's own 1 kHz Feedback last said ENABLED. What arms the torque and
        what confirms the disable: the stream that carries the angles and goes with every
        command, not whichever report came last (a single forged Heartbeat DISABLED after the
        disable hid a node that had ignored it, and its e-stop was never sent)."""
        return self.feedback is not None and self.feedback.state == _ENABLED

    def _second_sender(self, layout: Layout, data: bytes) -> None:
        """A frame with the counter of the one just accepted on its stream, and other
        contents: two senders on one identifier (a forged frame, or two nodes set to one id),
        or a node whose counter does not advance, which the host cannot tell apart from them.
        One of them was believed; the counter rule alone counted the other as a lost frame,
        so a forgery one frame in ten went on being believed under the reject-rate limit."""
        kind = layout.name.rpartition("_")[0]  # Feedback_1: Feedback
        self._contradicted(
            f"two {kind} frames (id 0x{layout.frame_id:03X}) with counter {data[1]} and "
            "other contents: a second sender on this node's identifier (a forged frame, "
            "or two nodes set to one id), or a node whose counter does not advance"
        )

    @property
    def firmware_text(self) -> str:
        """The firmware version as major.minor.patch, or "?" when no Status said it."""
        fw = self.firmware_version
        return "?" if fw is None else f"{fw[0]}.{fw[1]}.{fw[2]}"

    def version_problem(self, since_ns: int | None = None) -> str:
        """Why the host must not drive this node for its protocol version ("" if it may):
        another version than the host's, or (after ``since_ns``) no Status that said one."""
        who = f"node {self.node_id} ({self.finger.name})"
        if self.version_ns is None or (since_ns is not None and self.version_ns < since_ns):
            return f"{who}: no Status, so its protocol version is unknown"
        if self.protocol_version != self.layouts.protocol_version:
            return (
                f"{who} speaks handctl protocol {self.protocol_version}, this host "
                f"protocol {self.layouts.protocol_version}: update the node's firmware "
                "or use the handctl of its protocol"
            )
        return ""

    def _report(self, state: int, bits: int | None, message: str, arrival_ns: int) -> None:
        """Fold in what one accepted frame says of the node's state (and fault bits).

        The last report does not simply win: each must agree with the protocol and with the
        reports before it. Latched fault bits outside FAULT, reserved bits, ENABLED after
        FAULT without the DISABLED a fault reset leads to, or (on a node this host commands)
        ENABLED after DISABLED without an enable of this host's, is a contradiction; the host
        then keeps believing the earlier state, and the supervisor stops on the contradiction.
        Before, a DISABLED that arrived in the same poll as the next ENABLED was overruled by
        it: a node that dropped its torque for a moment, or a forged report, went unseen.
        """
        problem = ""
        if state not in _DEFINED_STATES:
            # never the node's state: what the host knew stands, and the stop says why. A
            # Status of state 3 had taken a FAULT's place, and an ENABLED after it was then
            # judged against neither the FAULT nor a DISABLED
            shown = f" (fault bits 0x{bits:02X})" if bits else ""
            self._contradicted(
                f"{message} says state {state}, which the protocol does not define{shown}"
            )
            return
        if bits is not None and bits & RESERVED_BITS:
            problem = f"{message} sets reserved fault bits 0x{bits & RESERVED_BITS:02X}"
        elif bits is not None and bits & LATCHED_BITS and state != _FAULT:
            problem = (
                f"{message} says {node_state_name(state, f'state {state}')} with "
                f"latched fault bits ({', '.join(fault_names(bits & LATCHED_BITS))})"
            )
        if self.state == _FAULT and state == _ENABLED:
            older = (
                message in self._since_fault and arrival_ns - self._fault_ns <= REORDERED_WITHIN_NS
            )
            if not older:  # this stream said FAULT since, or too long after to be older
                problem = problem or f"{message} says ENABLED after FAULT without a fault reset"
            state, bits = _FAULT, None  # what the FAULT report said stands
        elif (
            self.state == _DISABLED
            and state == _ENABLED
            and self._commanding
            and not self._may_enable
        ):
            problem = problem or (
                f"{message} says ENABLED after DISABLED without an enable from this host"
            )
            state = _DISABLED  # what the DISABLED report said stands
        if state == _FAULT:
            if self.state != _FAULT:
                self._since_fault = {"Feedback", "Heartbeat", "Status"}
                self._fault_ns = arrival_ns
            self._since_fault.discard(message)
        if state == _ENABLED:
            self._since_enable.discard(message)
            if self._enabled_ns is None:
                self._enabled_ns = arrival_ns
        elif state == _DISABLED and not self._sent_before_enable(message, arrival_ns):
            self._may_enable = False  # a new DISABLED
        if problem:
            self._contradicted(problem)
        self.state = state
        if bits is not None:
            self.fault_bits = bits

    def _sent_before_enable(self, message: str, arrival_ns: int) -> bool:
        """Whether a DISABLED of stream ``message`` may be one the node sent before it took
        this host's enable: its stream has not said ENABLED since, and it came within
        ``REORDERED_WITHIN_NS`` of the first ENABLED report (or before one)."""
        if message not in self._since_enable:
            return False
        return self._enabled_ns is None or arrival_ns - self._enabled_ns <= REORDERED_WITHIN_NS

    def _contradicted(self, problem: str) -> None:
        """Count a contradiction; the first since ``clear_contradiction`` is the one said."""
        self.contradictions += 1
        if not self.contradiction:
            self.contradiction = problem

    def heard_command(self, frame_id: int, data: bytes | None) -> None:
        """A frame on one of this node's command identifiers, heard by the host: another
        sender is commanding the node (a second host, a bring-up tool left running, a forged
        frame). Never applied, as any unexpected frame; remembered for the supervisor.
        ``data`` None: a remote frame (RTR), no command, but another sender on the id."""
        self.foreign_commands += 1
        if not self.foreign_command:
            name = "TorqueCommand" if frame_id == self.layouts.command.frame_id else "NodeCommand"
            what = (
                "a remote frame (RTR)" if data is None else f"{len(data)} bytes: {data[:16].hex()}"
            )
            self.foreign_command = (
                f"another sender on this host's {name} id 0x{frame_id:03X} "
                f"({what}): a second host or a forged command, "
                "which the node may obey instead of this host"
            )

    def _check_version(self, version: int) -> None:
        """A Status announcing another protocol than the host's is a contradiction: the start-up
        refuses such a node, so during a run it is a node that cannot be what it said it was
        (a node changes its protocol only by a reboot into other firmware), or a forged Status;
        either way its frames may no longer mean what this host reads into them."""
        if version != self.layouts.protocol_version:
            self.contradictions += 1
            if not self.contradiction:
                self.contradiction = (
                    f"Status says handctl protocol {version}, this host protocol "
                    f"{self.layouts.protocol_version}"
                )

    def clear_contradiction(self) -> None:
        """Judge the node afresh (a new start-up): earlier contradictions, and commands of
        another sender heard before, are not its now."""
        self.contradiction = ""
        self.foreign_command = ""
