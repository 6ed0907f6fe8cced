"""``handctl nodes``: who is on the bus, in which state, speaking which protocol.

It only listens: the nodes send Feedback, Status and Heartbeat whatever their state, so a
moment of listening says which configured nodes are there, their state and fault bits, their
protocol and firmware versions, how often their feedback comes, what each side rejected, and
which frames came from nodes the hand config does not know. Frames go through the host's own
receive checks (``FingerNode``), so what this shows is what a run would believe.
"""

from __future__ import annotations

import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from handctl.bringup.idcount import IdCounts
from handctl.busload import message_rate
from handctl.config import HandConfig
from handctl.hand_protocol import check_protocol, node_message
from handctl.online.bus import EXTENDED_ID_FLAG, BusEventKind, HandBus
from handctl.online.drivers.finger import FingerLayouts, FingerNode, fault_names, rebooted
from handctl.protocol import NodeState, Protocol

#: Messages a finger node sends (the host's receive streams of a node).
NODE_KINDS = ("Feedback", "Status", "Heartbeat")
#: How long a listening loop sleeps between drains (s): short against the queues it empties.
POLL_S = 0.005
#: A node whose accepted feedback comes at less than this share of its rate (the DBC's: the
#: loop rate) is flagged. Far below, not a little: a loaded listener reads late but loses
#: nothing on a kernel queue, while a node whose frames are mostly rejected (a bad CRC every
#: other frame, a second sender on its id) has a handful of hertz of a thousand left.
MIN_FEEDBACK_SHARE = 0.5
#: Bus events that are the listener's own, not the bus's: a drain that met its limit reads
#: the rest at the next one.
LISTENER_EVENTS = frozenset({BusEventKind.RX_BACKLOG.value})
#: Heartbeat streams of one id kept apart (``_Heard``): a node's own, a second sender's,
#: and room for a reboot's and a lost frame's restart among them.
MAX_STREAMS = 4


@dataclass
class NodeRow:
    """One configured node as the bus showed it."""

    node_id: int
    name: str
    present: bool
    state: str
    fault_bits: int
    protocol_version: int | None
    firmware: str
    uptime_ms: int | None
    feedback_hz: float  # accepted feedback frames a second
    feedback_expected_hz: float  # the DBC's rate of the node's Feedback
    heartbeats: int
    statuses: int
    host_rejects: dict[str, int]
    node_rejects: dict[str, int] | None  # what its last Status said it rejected
    command_age_ms: int | None
    problem: str

    @property
    def faults(self) -> list[str]:
        return fault_names(self.fault_bits)

    def as_dict(self) -> dict[str, Any]:
        return {
            "node_id": self.node_id,
            "name": self.name,
            "present": self.present,
            "state": self.state,
            "fault_bits": self.fault_bits,
            "faults": self.faults,
            "protocol_version": self.protocol_version,
            "firmware": self.firmware,
            "uptime_ms": self.uptime_ms,
            "feedback_hz": round(self.feedback_hz, 1),
            "feedback_expected_hz": round(self.feedback_expected_hz, 1),
            "heartbeats": self.heartbeats,
            "statuses": self.statuses,
            "host_rejects": self.host_rejects,
            "node_rejects": self.node_rejects,
            "command_age_ms": self.command_age_ms,
            "problem": self.problem,
        }


@dataclass
class Survey:
    bus: str
    seconds: float
    host_protocol: int
    rows: list[NodeRow]
    #: Frames on ids that are none of the configured nodes': id -> (what it is, frames).
    foreign: dict[int, tuple[str, int]] = field(default_factory=dict)
    #: frames of foreign ids beyond the first ``idcount.MAX_IDS`` (counted together)
    foreign_more_frames: int = 0
    bus_events: dict[str, int] = field(default_factory=dict)
    #: Frames this listener lost before it read them, as its bus told it (the unix bus does).
    frames_lost: int = 0
    #: The last detail of each kind of bus event: which id a remote frame was on, say.
    last_event: dict[str, str] = field(default_factory=dict)

    @property
    def bus_problem(self) -> str:
        """The bus's events that say the bus is unwell (error frames, bus-off, frames it
        dropped as malformed), empty if none: what a node row cannot show."""
        trouble = {k: n for k, n in self.bus_events.items() if k not in LISTENER_EVENTS}
        if not trouble:
            return ""
        return "bus events: " + ", ".join(f"{k} {n}" for k, n in sorted(trouble.items()))

    @property
    def ok(self) -> bool:
        """Every configured node there, DISABLED, in no fault, of the host's protocol, its
        feedback coming and accepted; nobody else (no frame on another id: another host's
        commands, a node the config lacks, an id the DBC does not have); a bus without error
        events. Before, another host's commands and ids outside the DBC left it true."""
        return (
            all(not row.problem for row in self.rows)
            and not self.foreign
            and not self.foreign_more_frames
            and not self.bus_problem
        )

    def as_dict(self) -> dict[str, Any]:
        return {
            "bus": self.bus,
            "seconds": round(self.seconds, 3),
            "host_protocol": self.host_protocol,
            "ok": self.ok,
            "nodes": [row.as_dict() for row in self.rows],
            "foreign_ids": [
                {"id": id_text(fid), "what": what, "frames": n}
                for fid, (what, n) in sorted(self.foreign.items())
            ],
            **(
                {"foreign_ids_more_frames": self.foreign_more_frames}
                if self.foreign_more_frames
                else {}
            ),
            "bus_events": self.bus_events,
            "last_event": self.last_event,
            "bus_problem": self.bus_problem,
            "frames_lost": self.frames_lost,
        }


def describe_id(frame_id: int, protocol: Protocol, node_ids: set[int]) -> str:
    """What a frame on an id that no configured node uses is, as far as the DBC says."""
    if frame_id & EXTENDED_ID_FLAG:
        return f"29-bit id 0x{frame_id & ~EXTENDED_ID_FLAG:08X}: not handctl's"
    layout = protocol.by_id.get(frame_id)
    if layout is None:
        # The hand's DBC has frames for its own nodes only: another node is named by the id
        # rule of every generated DBC.
        found = node_message(frame_id)
        if found is None or found[1] in node_ids:
            return "not in the DBC"
        return f"{found[0]}_{found[1]}: node {found[1]}, not in the hand config"
    if layout.kind in NODE_KINDS and layout.node not in node_ids:
        return f"{layout.name}: node {layout.node}, not in the hand config"
    return f"{layout.name}: sent by another host"


def survey(
    hand: HandConfig,
    protocol: Protocol,
    bus: HandBus,
    seconds: float,
    clock: Callable[[], int] = time.monotonic_ns,
    sleep: Callable[[float], None] = time.sleep,
) -> Survey:
    """Listen to ``bus`` for ``seconds`` and say what each configured node is. Sends nothing."""
    check_protocol(hand, protocol)
    nodes = [FingerNode(f, FingerLayouts.for_node(protocol, f.node_id)) for f in hand.fingers]
    dispatch = {fid: node for node in nodes for fid in node.streams}
    counts: dict[int, Counter[str]] = {node.node_id: Counter() for node in nodes}
    heard = {node.node_id: _Heard() for node in nodes}
    foreign = IdCounts()
    events: Counter[str] = Counter()
    last_event: dict[str, str] = {}
    bus.use_clock(clock)
    bus.drain(limit=10**6)  # what waited before we listened says nothing of now
    bus.events()
    lost_before = bus.transport_counts().get("rx_frames_lost", 0)
    start = clock()
    end = start + round(seconds * 1e9)
    while True:
        for frame in bus.drain():
            fid = frame.arbitration_id
            node = dispatch.get(fid)
            if node is None:
                foreign.add(fid)
                continue
            count = counts[node.node_id]
            count["frames"] += 1
            if node.receive(fid, frame.data, frame.timestamp_ns) is None:
                count[node.streams[fid][0].kind] += 1
            heard[node.node_id].hear(node, fid, frame.data, frame.timestamp_ns)
        for event in bus.events():
            events[event.kind.value] += 1
            last_event[event.kind.value] = event.detail
        now = clock()
        if now >= end:
            break
        sleep(min(POLL_S, (end - now) * 1e-9))
    elapsed = max((clock() - start) * 1e-9, 1e-9)
    lost = max(0, bus.transport_counts().get("rx_frames_lost", 0) - lost_before)
    node_ids = {f.node_id for f in hand.fingers}
    rows = [
        _row(
            node,
            counts[node.node_id],
            elapsed,
            message_rate(node.layouts.feedback, hand.bus.loop_rate_hz),
            lost,
            heard[node.node_id],
        )
        for node in nodes
    ]
    described = {fid: (describe_id(fid, protocol, node_ids), n) for fid, n in foreign.by_id.items()}
    return Survey(
        str(bus.spec),
        elapsed,
        protocol.version,
        rows,
        described,
        foreign.others,
        dict(events),
        lost,
        last_event,
    )


def id_text(frame_id: int) -> str:
    """An id as the wire carries it: a 29-bit one with its 8 digits and said so (the flag that
    marks it inside handctl is no part of any CAN id)."""
    if frame_id & EXTENDED_ID_FLAG:
        return f"0x{frame_id & ~EXTENDED_ID_FLAG:08X} (29-bit)"
    return f"0x{frame_id:03X}"


class _Heard:
    """What a node said during the survey besides its last word: the node's state at the end
    is what the table shows, and a node that was in FAULT and left it with no reset from any
    host, one that rebooted, or one whose angles were past its limits said "ok", exit 0."""

    def __init__(self) -> None:
        self.fault_bits: int | None = None  # the bits of the first FAULT heard
        self.outside = ""  # the first angle heard past its joint's limits
        self.uptime_ms: int | None = None
        #: Heartbeats whose uptime went back. Read from every intact Heartbeat, the ones
        #: refused for their counter too: a rebooted node's counters restart, so its first
        #: Heartbeat is refused, and the next may already say more uptime than the last one
        #: the driver took (a node that had been up a short while), and the reboot went
        #: unsaid (``FingerNode.reboots`` counts what the run's driver takes).
        self.reboots = 0
        #: The Heartbeat streams heard, ``(counter, uptime_ms, arrival_ns)`` of each one's
        #: last frame, the latest last (``MAX_STREAMS``). A frame continues a stream when its
        #: counter is the next and its uptime no less (or wrapped, ``finger.rebooted``); one
        #: that continues none begins another.
        self._streams: list[tuple[int, int, int]] = []
        #: Heartbeats that continued a stream other than the latest: an earlier stream went
        #: on beside a newer one, which a reboot never does (its old stream ends). Two
        #: senders on the id (a second node, a participant sending its own Heartbeat): their
        #: uptimes alternate, and every other one went back; that was said as a reboot, 6x.
        self.interleaved = 0

    def hear(self, node: FingerNode, frame_id: int, data: bytes, arrival_ns: int) -> None:
        heartbeat = node.layouts.heartbeat
        if frame_id == heartbeat.frame_id and heartbeat.crc_ok(data):
            uptime = int(heartbeat.decode(data)[1][1])
            self._stream(data[1], uptime, arrival_ns)
            self.uptime_ms = uptime
        if node.state == NodeState.FAULT and self.fault_bits is None:
            self.fault_bits = node.fault_bits
        feedback = node.feedback
        if feedback is None or self.outside:
            return
        for joint, angle in zip(node.finger.joints, feedback.angles, strict=False):
            if not joint.angle_min <= angle <= joint.angle_max:
                self.outside = (
                    f"{joint.name} read {angle:+.3f} rad, past its limits "
                    f"[{joint.angle_min:+.2f}, {joint.angle_max:+.2f}]"
                )
                return

    def _stream(self, counter: int, uptime: int, arrival_ns: int) -> None:
        """Which Heartbeat stream a frame continues, and whether it is a reboot's."""
        streams = self._streams
        for i in range(len(streams) - 1, -1, -1):
            last_counter, last_uptime, last_ns = streams[i]
            if counter == (last_counter + 1) % 256 and not rebooted(
                last_uptime, uptime, arrival_ns - last_ns
            ):
                if i != len(streams) - 1:
                    self.interleaved += 1
                del streams[i]
                break
        else:
            if streams and rebooted(streams[-1][1], uptime, arrival_ns - streams[-1][2]):
                self.reboots += 1
        streams.append((counter, uptime, arrival_ns))
        del streams[:-MAX_STREAMS]

    def problems(self, node: FingerNode) -> list[str]:
        said = []
        if self.fault_bits is not None and node.state != NodeState.FAULT:
            bits = ", ".join(fault_names(self.fault_bits)) or "no bits"
            said.append(f"was in FAULT ({bits}) during the survey and left it")
        if self.interleaved:
            said.append(
                f"two senders on {node.layouts.heartbeat.name} (0x"
                f"{node.layouts.heartbeat.frame_id:03X}): its uptime and counter alternate "
                f"between streams ({self.interleaved} frames went back to an earlier one); "
                "another node or host sends on this node's id"
            )
        elif self.reboots:
            said.append(f"rebooted during the survey (its uptime went back, {self.reboots}x)")
        if self.outside:
            said.append(self.outside)
        return said


def _row(
    node: FingerNode,
    count: Counter[str],
    elapsed: float,
    expected_hz: float,
    lost: int,
    heard: _Heard | None = None,
) -> NodeRow:
    present = count["frames"] > 0
    status = node.status
    node_rejects = (
        None
        if status is None
        else {"crc": int(status[2]), "counter": int(status[3]), "length": int(status[4])}
    )
    problem = ""
    if not present:
        problem = f"missing: nothing heard in {elapsed:.2f} s"
    elif node.version_ns is not None and node.version_problem():
        problem = node.version_problem()
    elif node.version_ns is None:
        problem = "no Status heard: its protocol version is unknown"
    elif node.state == NodeState.FAULT:
        problem = f"in FAULT ({', '.join(fault_names(node.fault_bits)) or 'no bits'})"
    elif node.contradiction:
        problem = f"contradicts itself: {node.contradiction}"
    elif node.state == NodeState.ENABLED:
        # a node takes torque only from a host: another one is driving the hand, or left it
        # enabled (docs/bringup.md: good is DISABLED)
        problem = "ENABLED: another host is driving it, or left it enabled"
    feedback_hz = count["Feedback"] / elapsed
    if present:
        rates = feedback_problem(node.rejects.as_dict(), feedback_hz, expected_hz, lost)
        also = heard.problems(node) if heard is not None else []
        problem = "; ".join(p for p in (problem, rates, *also) if p)
    return NodeRow(
        node_id=node.node_id,
        name=node.finger.name,
        present=present,
        state=node.state_name if present else "-",
        fault_bits=node.fault_bits,
        protocol_version=node.protocol_version,
        firmware=node.firmware_text,
        uptime_ms=node.uptime_ms,
        feedback_hz=feedback_hz,
        feedback_expected_hz=expected_hz,
        heartbeats=count["Heartbeat"],
        statuses=count["Status"],
        host_rejects={k: v for k, v in node.rejects.as_dict().items() if v},
        node_rejects=node_rejects,
        command_age_ms=None if status is None else int(status[5]),
        problem=problem,
    )


def feedback_problem(
    rejects: dict[str, int], feedback_hz: float, expected_hz: float, lost: int
) -> str:
    """What is wrong with what a node sent, by the bring-up's own criteria (docs/bringup.md:
    feedback near its rate, rejects 0); empty if nothing.

    A listener that lost frames itself (``lost``, as its bus told it) skips a counter for
    each gap it made: that many counter skips are not held against the node, and a low rate
    says the listener lost frames too."""
    rejected = dict(rejects)
    if lost and rejected.get("counter_skip"):
        rejected["counter_skip"] = max(0, rejected["counter_skip"] - lost)
    text = ", ".join(f"{k} {n}" for k, n in rejected.items() if n)
    problems = []
    if feedback_hz < MIN_FEEDBACK_SHARE * expected_hz:
        slow = f"feedback {feedback_hz:.0f} Hz accepted, expected {expected_hz:.0f} Hz"
        if lost:
            slow += f" (this listener lost {lost} frames itself)"
        problems.append(slow)
    if text:
        problems.append(f"frames rejected: {text}")
    return "; ".join(problems)
