"""The hand-level driver: every joint over its finger's node, one drain and one send per tick.

Joint vectors everywhere in handctl are in config order (finger by finger, joint by joint); this
module is where that order meets the per-node frames. The state arrays are allocated once and
updated in place, so a tick allocates little beyond the frames themselves.
"""

from __future__ import annotations

import struct
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import NewType

import numpy as np
import numpy.typing as npt

from handctl.arrays import FloatArray
from handctl.busload import frames_per_period
from handctl.config import HandConfig
from handctl.hand_protocol import check_protocol
from handctl.online.bus import DRAIN_LIMIT, EXTENDED_ID_FLAG, BusEvent, BusEventKind, FrameBus
from handctl.online.drivers.finger import FingerLayouts, FingerNode
from handctl.online.drivers.receiver import Reject, RejectCounts
from handctl.protocol import ESTOP_REASONS, NODE_COMMANDS, Protocol

#: Torques that came out of the safety supervisor. Only ``handctl/online/safety/supervisor.py``
#: makes one (a test checks), and ``HandDriver.send`` takes nothing else, so the type checker proves
#: that no torque reaches a command frame without passing the limiter.
AppliedTorques = NewType("AppliedTorques", FloatArray)
#: Every value a frame's rolling ``Counter`` takes: 8 bits (``handctl/protocol.py`` refuses a
#: DBC with any other width).
COUNTER_VALUES = 256
#: The bus events of a frame the host could not send.
TX_REFUSED = frozenset({BusEventKind.TX_QUEUE_FULL, BusEventKind.TX_FAILED})
#: The e-stop reasons (PROTOCOL.md): the operator's, and host safety, which the stop's
#: prepared e-stop frames carry.
ESTOP_OPERATOR = 1
ESTOP_HOST_SAFETY = 2


@dataclass
class JointState:
    """What the host believes about the joints after the last poll (SI units, host clock)."""

    angle: FloatArray  # rad
    tdt: FloatArray  # N·m, the transmitted torque the TDTs measure, after the host calibration
    feedback_ns: npt.NDArray[np.int64]  # arrival (host clock) of the last good feedback, or -1
    node_state: list[int] = field(default_factory=list)  # per finger, -1 unknown
    node_faults: list[int] = field(default_factory=list)

    def age_s(self, now_ns: int) -> FloatArray:
        """Age of each joint's last good feedback; infinite before the first one."""
        age = (now_ns - self.feedback_ns) * 1e-9
        return np.where(self.feedback_ns < 0, np.inf, age)


class HandDriver:
    """Host side of the hand: polls feedback into ``state`` and sends per-node commands.

    The bus stamps frames on arrival on ``clock_ns``, the loop's clock, so the age of what a
    node said is measured from when it arrived. A poll drains at most what the bus can carry
    since the previous poll (``frames_per_period`` per period elapsed, plus one period's
    worth); frames beyond it wait, and the bus reports them (``RX_BACKLOG``).
    """

    def __init__(
        self,
        hand: HandConfig,
        protocol: Protocol,
        bus: FrameBus,
        clock_ns: Callable[[], int] = time.monotonic_ns,
    ) -> None:
        check_protocol(hand, protocol)
        self.hand = hand
        self.protocol = protocol
        self.bus = bus
        self.clock_ns = clock_ns
        bus.use_clock(clock_ns)
        #: Frames the bus can carry in one loop period (``handctl/busload.py``).
        self.frames_per_period = frames_per_period(hand.bus)
        self._period_ns = max(1, round(hand.bus.period_s * 1e9))
        self._last_poll_ns: int | None = None
        self.nodes = [
            FingerNode(f, FingerLayouts.for_node(protocol, f.node_id)) for f in hand.fingers
        ]
        self._dispatch = {fid: node for node in self.nodes for fid in node.streams}
        #: The ids this host sends commands on, by node: heard on the bus, another sender.
        self._command_owner = {fid: node for node in self.nodes for fid in node.command_ids}
        self._slices = []
        start = 0
        for finger in hand.fingers:
            self._slices.append(slice(start, start + len(finger.joints)))
            start += len(finger.joints)
        #: Zeros after each finger's torques, up to what its TorqueCommand carries.
        self._pads = [
            [0.0] * (len(node.layouts.command.signals) - (sl.stop - sl.start))
            for node, sl in zip(self.nodes, self._slices, strict=True)
        ]
        n = hand.n_joints
        #: Per node: where its joints start, how many, and the feedback last folded in.
        self._spans = [(sl.start, sl.stop - sl.start) for sl in self._slices]
        self._folded: list[object] = [None] * len(self.nodes)
        #: Per joint: whether this tick's command frame of its node did not go (``send``).
        #: The supervisor puts those joints back to what their node still holds, so the next
        #: frame steps one rate step from it, not one per tick the bus refused.
        self.unsent_joints = np.zeros(n, dtype=bool)
        self._all_went = True  # ``unsent_joints`` all False: nothing to clear a tick
        # The angles and the calibrated torques side by side in one block: a recorder copies
        # both into its row with one call (``handctl.recording.recorder``).
        joints = np.zeros((2, n))
        self.state = JointState(
            joints[0],
            joints[1],
            np.full(n, -1, dtype=np.int64),
            [-1] * len(self.nodes),
            [0] * len(self.nodes),
        )
        # A node's new feedback goes straight into its span of the arrays, one packing call
        # per array (cheaper than a NumPy slice assignment from a tuple); the TDT readings
        # as the nodes report them, calibrated for all joints at once after.
        self._tdt_scale = np.array([j.tdt.scale for j in hand.joints])
        self._tdt_offset = np.array([j.tdt.offset for j in hand.joints])
        self._tdt_raw = np.zeros(n)  # N·m as the nodes report it, before calibration
        self._angle_bytes = self.state.angle.data.cast("B")
        self._tdt_raw_bytes = self._tdt_raw.data.cast("B")
        self._feedback_ns_bytes = self.state.feedback_ns.data.cast("B")
        self._packers = [
            (8 * start, k, struct.Struct(f"={k}d").pack_into, struct.Struct(f"={k}q").pack_into)
            for start, k in self._spans
        ]
        self.unexpected = RejectCounts()
        self.unexpected_ids: dict[int, int] = {}
        self.bus_events: list[BusEvent] = []
        self._estop_counter = 0
        #: How many times a stop's prepared frame did not go to every node and the e-stop
        #: followed (``_send_prepared``): each node latches FAULT (ESTOP) on it; and how many
        #: of those e-stops the bus did not take either (only the nodes' own command
        #: watchdogs then stop them: said so, not that they were e-stopped)
        self.stop_estops = 0
        self.stop_estops_lost = 0
        #: What the bus said of the last frame it refused, as the polls have heard it ("":
        #: none): a frame that did not go is said with the bus's reason, not as the nodes'
        self.last_tx_error = ""
        self._estop_layout = protocol.layout("EStop")
        #: E-stop frames heard on the bus, and the first of them in words ("": none). The host
        #: never hears its own frames (``FingerNode.command_ids``), so each is another
        #: sender's: an e-stop button, a node, a second host (PROTOCOL.md: "host (or any
        #: node) → all"). Every node latches FAULT (ESTOP) on one; the run's stop named the
        #: nodes' FAULT and counted the frame as an unexpected id, nothing more.
        self.estops_heard = 0
        self.estop_heard = ""
        self._prepare_stop_frames()

    def poll(self, now_ns: int | None = None) -> JointState:
        """Drain the bus (within the receive budget) and fold every accepted frame into
        ``state``; a frame's age counts from its arrival."""
        now = self.clock_ns() if now_ns is None else now_ns
        for frame in self.bus.drain(self.drain_budget(now)):
            frame_id = frame.arbitration_id
            node = self._dispatch.get(frame_id)
            if node is None:
                self.unexpected.add(
                    Reject.EXTENDED_ID if frame_id & EXTENDED_ID_FLAG else Reject.UNEXPECTED_ID
                )
                ids = self.unexpected_ids
                if len(ids) < 64 or frame_id in ids:
                    ids[frame_id] = ids.get(frame_id, 0) + 1
                owner = self._command_owner.get(frame_id)
                if owner is not None:
                    owner.heard_command(frame_id, frame.data)
                elif frame_id == self._estop_layout.frame_id:
                    self._heard_estop(frame.data)
                continue
            node.receive(frame_id, frame.data, frame.timestamp_ns)
        events = self.bus.events()
        if events:
            self.bus_events.extend(events)
            for event in events:
                if event.kind is BusEventKind.REMOTE_FRAME and event.frame_id is not None:
                    self._heard_remote(event.frame_id)
                elif event.kind in TX_REFUSED:
                    self.last_tx_error = f"{event.kind.value}: {event.detail}"
        state = self.state
        folded = self._folded
        node_state, node_faults = state.node_state, state.node_faults
        for i, node in enumerate(self.nodes):
            fb = node.feedback
            if fb is not None and node.feedback_ns is not None and fb is not folded[i]:
                folded[i] = fb  # a node's Feedback is a new object per accepted frame
                offset, k, floats, ints = self._packers[i]
                floats(self._angle_bytes, offset, *fb.angles[:k])
                floats(self._tdt_raw_bytes, offset, *fb.tdt[:k])
                ints(self._feedback_ns_bytes, offset, *([node.feedback_ns] * k))
            node_state[i] = node.state
            node_faults[i] = node.fault_bits
        np.multiply(self._tdt_raw, self._tdt_scale, out=state.tdt)
        state.tdt += self._tdt_offset
        return state

    def _heard_estop(self, data: bytes | None) -> None:
        """An e-stop frame of another sender: counted, and the first said with its reason
        (the nodes honour it even malformed, PROTOCOL.md, so a malformed one is said too, and
        a remote frame, ``data`` None, on its id)."""
        self.estops_heard += 1
        if self.estop_heard:
            return
        layout = self._estop_layout
        if data is None:
            what = "a remote frame (RTR)"
        elif len(data) == layout.length and layout.crc_ok(data):
            value = int(layout.decode(data)[1][0])
            name = next((k for k, v in ESTOP_REASONS.items() if v == value), "")
            what = f"reason {value}" + (f", {name}" if name else "")
        else:
            what = f"malformed, {len(data)} bytes: {data[:16].hex()}"
        self.estop_heard = (
            f"an e-stop frame (id 0x{layout.frame_id:03X}, {what}) from another sender"
        )

    def _heard_remote(self, frame_id: int) -> None:
        """A remote frame (RTR): no data frame, so never a node's (the bus hands it on as an
        event, not a ``Frame``), but a frame on its id all the same: counted as an unexpected
        one, and on a node's command id another sender on it, as a data frame there is."""
        self.unexpected.add(
            Reject.EXTENDED_ID if frame_id & EXTENDED_ID_FLAG else Reject.UNEXPECTED_ID
        )
        owner = self._command_owner.get(frame_id)
        if owner is not None:
            owner.heard_command(frame_id, None)
        elif frame_id == self._estop_layout.frame_id:
            # the nodes latch ESTOP on a remote frame there too: said as a data frame is
            # (found by an outside audit)
            self._heard_estop(None)

    def drain_budget(self, now_ns: int) -> int:
        """Frames the poll at ``now_ns`` may drain: what the bus can carry since the previous
        poll, plus one period's worth of slack (the first poll after a start: ``DRAIN_LIMIT``).
        It depends only on the polls' times, so a re-run of a log drains as the run did."""
        last, self._last_poll_ns = self._last_poll_ns, now_ns
        if last is None:
            return DRAIN_LIMIT
        periods = max(1, -(-(now_ns - last) // self._period_ns))
        return self.frames_per_period * (periods + 1)

    def prepare_send(self) -> None:
        """Ready the bus for the first command frames while there is time (start-up)."""
        self.bus.prepare_send()

    def discard_pending(self) -> int:
        """Drop every frame already waiting in the receive queue, unread.

        At start-up, frames queued while nobody listened (a previous run's end, a reset) say
        what the nodes were, not what they are; judging the nodes on them would be wrong, and
        so would holding against them what they contradicted before. For the same reason each
        node's receive counters start afresh (PROTOCOL.md, "A new host"). The backlog this
        leaves behind it is no fault; the bus's other events are kept for the first tick.
        """
        for node in self.nodes:
            node.resynchronise()
        dropped = 0
        while True:
            frames = self.bus.drain()
            dropped += len(frames)
            if len(frames) < DRAIN_LIMIT:
                break
        self.bus_events.extend(
            e for e in self.bus.events() if e.kind is not BusEventKind.RX_BACKLOG
        )
        self._last_poll_ns = None
        for node in self.nodes:
            node.clear_contradiction()
        return dropped

    def take_bus_events(self) -> list[BusEvent]:
        events, self.bus_events = self.bus_events, []
        return events

    def send(self, torques: AppliedTorques) -> bool:
        """Send one command frame per node; the torques must already have passed safety.

        Returns False when any frame could not be sent (the bus event says why).
        """
        ok = True
        if not self._all_went:
            self.unsent_joints[:] = False
            self._all_went = True
        values = torques.tolist()  # one conversion for every node, plain floats after
        bus = self.bus
        batching = bus.batching
        nodes = self.nodes
        last = len(nodes) - 1
        # nodes[unsent:upto + 1] have frames not yet seen to go (upto: the last whose counter
        # was used): a frame that did not go (refused, or the send raised; on a batching bus,
        # every frame of its burst) gives its counter back, so the next frame is in sequence.
        # Indices, not a list: no allocation a tick.
        unsent, upto = 0, -1
        try:
            for i, (node, (start, k), pad) in enumerate(
                zip(nodes, self._spans, self._pads, strict=True)
            ):
                mine = values[start : start + k]
                if pad:
                    mine += pad
                frame_id, data = node.next_command(mine)
                upto = i
                more = i < last
                if not bus.send(frame_id, data, more=more):
                    ok = False
                    self._take_back(unsent, i)
                    unsent = i + 1
                elif not (batching and more):
                    unsent = i + 1
        except BaseException:
            # A batching bus still holds the frames of the nodes whose counters go back: they
            # must not go with the stop's first frame (the tick that raised sends nothing more)
            bus.drop_burst()
            self._take_back(unsent, upto)
            raise
        return ok

    def _take_back(self, first: int, last: int) -> None:
        """Nodes ``first``..``last``'s last command frames did not go (``take_back_command``),
        and their joints are this tick's ``unsent_joints``."""
        for node, (start, k) in zip(
            self.nodes[first : last + 1], self._spans[first : last + 1], strict=True
        ):
            node.take_back_command()
            self.unsent_joints[start : start + k] = True
            self._all_went = False

    # -- the stop that needs no codec -----------------------------------------------------
    def _prepare_stop_frames(self) -> None:
        """Encode, once, every frame a stop after an exception may need: per node a zero-torque
        command and a disable for each counter value, and the e-stop for each counter value.

        A tick that raised may have raised in the codec itself (a torque the wire cannot
        carry), so the stop must not encode anything: it picks the frame for the node's next
        counter from these tables and hands it to the bus, so the node accepts it in sequence.
        """
        disable = (NODE_COMMANDS["disable"],)
        self._zero_frames = [
            (
                n.layouts.command.frame_id,
                tuple(
                    n.layouts.command.encode(c, [0.0] * len(n.layouts.command.signals))
                    for c in range(COUNTER_VALUES)
                ),
            )
            for n in self.nodes
        ]
        self._disable_frames = [
            (
                n.layouts.node_command.frame_id,
                tuple(n.layouts.node_command.encode(c, disable) for c in range(COUNTER_VALUES)),
            )
            for n in self.nodes
        ]
        self._estop_frames = {
            reason: tuple(self._estop_layout.encode(c, (reason,)) for c in range(COUNTER_VALUES))
            for reason in (ESTOP_OPERATOR, ESTOP_HOST_SAFETY)
        }

    def send_zero(self) -> bool:
        """Zero torque to every node from the prepared frames, without the codec.

        Every node is tried whatever happens to the others; when any frame did not go (the
        bus refused it or raised), the e-stop frame follows. Never raises; False when any
        frame did not go.
        """
        return self._send_prepared(self._zero_frames, "command_counter")

    def send_disable(self) -> bool:
        """Disable every node from the prepared frames, as ``send_zero`` sends zero."""
        return self._send_prepared(self._disable_frames, "node_command_counter")

    def _send_prepared(
        self, prepared: list[tuple[int, tuple[bytes, ...]]], counter_name: str
    ) -> bool:
        """One prepared frame per node, at the node's next counter (``counter_name``);
        every node tried, then the e-stop frame if any did not go."""
        ok = True
        for node, (frame_id, frames) in zip(self.nodes, prepared, strict=True):
            counter = getattr(node, counter_name) % COUNTER_VALUES
            if self._send_quietly(frame_id, frames[counter]):
                # only a frame that went uses its counter up (``send``)
                setattr(node, counter_name, (counter + 1) % COUNTER_VALUES)
            else:
                ok = False
        if not ok:
            self.stop_estops += 1
            if not self.send_estop():
                self.stop_estops_lost += 1
        return ok

    def _send_quietly(self, frame_id: int, data: bytes) -> bool:
        """One frame, whatever the bus does: False when it refused or raised."""
        try:
            return self.bus.send(frame_id, data)
        except Exception:  # the stop goes on to the next frame, whatever this was
            return False

    def send_estop(self, reason: int = ESTOP_HOST_SAFETY) -> bool:
        """The prepared e-stop frame (host safety, or the operator's), without the codec;
        never raises: a caller that must see it go sends it again (``Runtime``'s owed
        e-stop)."""
        counter = self._estop_counter % COUNTER_VALUES
        self._estop_counter = (counter + 1) % COUNTER_VALUES
        return self._send_quietly(self._estop_layout.frame_id, self._estop_frames[reason][counter])

    def node_command(self, command: str, nodes: Iterable[int] | None = None) -> bool:
        """Send enable / disable / fault_reset to the given node ids (all by default);
        whether every frame went."""
        return not self.node_command_unsent(command, nodes)

    def node_command_unsent(self, command: str, nodes: Iterable[int] | None = None) -> list[int]:
        """``node_command``, returning the ids of the nodes whose frame did not go, for a
        caller that sends it again to those alone (each frame that went used its counter)."""
        wanted = None if nodes is None else set(nodes)
        unsent = []
        for node in self.nodes:
            if wanted is None or node.node_id in wanted:
                frame_id, data = node.next_node_command(command)
                if not self.bus.send(frame_id, data):
                    node.take_back_node_command()
                    unsent.append(node.node_id)
        return unsent

    def reject_counts(self) -> dict[str, int]:
        """All rejections, host side: by kind over every node, plus unexpected ids."""
        total = RejectCounts()
        for node in self.nodes:
            for kind, count in enumerate(node.rejects.counts):
                total.counts[kind] += count
        for kind in (Reject.UNEXPECTED_ID, Reject.EXTENDED_ID):
            total.counts[kind] += self.unexpected.counts[kind]
        return total.as_dict()
