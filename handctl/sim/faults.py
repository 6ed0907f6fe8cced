"""Fault injectors of the simulated hand, and the scenario files that switch them in time.

Each injector reproduces one way the real hand or its bus goes wrong, at the place where it
goes wrong: frames lost or damaged between bus and node, a node whose counter or sensors
misbehave, a node that reboots or falls silent, a bus with error frames, bus-off or a babbling
node, a tendon gone slack or a motor too weak. The host must notice each of them through the
frames alone, which is what the tests of the safety layer rely on.

An injector is switched on and off at simulated times, either from a test::

    hand.faults.add(DropFeedback(node=2), start=0.50, stop=0.52)
    hand.activate(TdtStuck(node=1, joint=2))        # now, until hand.deactivate(...)

or from a scenario file (times in seconds of simulated time since the simulated hand started;
``stop`` may be left out, and keys other than those documented per kind are refused; the keys
are not ``on``/``off`` because YAML reads those as booleans)::

    faults:
      - {kind: drop_feedback, node: 2, start: 0.50, stop: 0.52}
      - {kind: tdt_stuck, node: 1, joint: 2, start: 1.0}

``node`` is a node id of the hand config and ``joint`` a joint number of that node (1 to its
number of joints; of every node's, without ``node``); left out,
an injector acts on every node or joint. Overlapping injectors add up where that makes sense
(offsets, spikes, jumps); switching off one ``tdt_stuck`` or ``tendon_slack`` releases the joint
even if another one covers it too.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, ClassVar, Protocol

from handctl.config import HandConfig
from handctl.online.bus import EXTENDED_ID_FLAG
from handctl.schema import Doc, description, load_yaml
from handctl.sim.params import NODE_TICK_NS

if TYPE_CHECKING:
    from handctl.protocol import Layout
    from handctl.protocol import Protocol as CanProtocol
    from handctl.sim.firmware import EmulatedNode
    from handctl.sim.plant import Plant
    from handctl.sim.sensors import EncoderModel, TdtModel


class SimContext(Protocol):
    """What an injector may touch: the simulated hand's parts, seen from the fault side."""

    plant: Plant
    tdt: TdtModel
    encoders: EncoderModel
    nodes: tuple[EmulatedNode, ...]
    protocol: CanProtocol

    def joint_indices(self, node: int | None, joint: int | None) -> list[int]: ...

    def node_list(self, node: int | None) -> list[EmulatedNode]: ...

    def send_frame(self, frame_id: int, data: bytes) -> bool: ...

    def send_foreign_frame(self, frame_id: int, data: bytes) -> bool: ...

    def send_error_frame(self, error_class: int = ...) -> bool: ...


@dataclass(eq=False)
class Injector:
    """Base of every injector: switched on with ``start``, off with ``stop``.

    Subclasses set the capability flags so the simulated hand only runs the hooks an active
    injector needs: with no injector active, the frame paths pay nothing.
    """

    kind: ClassVar[str] = ""
    filters_rx: ClassVar[bool] = False  # has ``rx``: sees frames on their way to the nodes
    filters_tx: ClassVar[bool] = False  # has ``tx``: sees the nodes' frames on their way out
    periodic: ClassVar[bool] = False  # has ``tick``: runs once per tick while active
    #: Scenario keys besides kind, node, joint, start and stop (read by ``_READERS``).
    keys: ClassVar[tuple[str, ...]] = ()
    #: of the whole bus, no node's: a scenario's ``node`` was taken and did nothing (a
    #: bus-off "of node 2" silenced every node)
    bus_wide: ClassVar[bool] = False

    node: int | None = None

    def start(self, ctx: SimContext, now_ns: int) -> None:
        """Switch on."""

    def stop(self, ctx: SimContext, now_ns: int) -> None:
        """Switch off, undoing what ``start`` changed."""

    def rx(self, frame_id: int, data: bytes) -> bool:
        """True to let a received frame through to the nodes."""
        return True

    def tx(self, frame_id: int, data: bytes, now_ns: int, out: list[tuple[int, bytes]]) -> None:
        """Append what goes on the bus in place of a node's frame (nothing drops it)."""
        out.append((frame_id, data))

    def tick(self, ctx: SimContext, now_ns: int) -> None:
        """Once per tick while active, after the nodes' frames have been sent."""

    def describe(self) -> str:
        """The injector as a scenario would name it, for summaries and messages."""
        fields = ", ".join(
            f"{k}={getattr(self, k)!r}"
            for k in ("node", "joint", *self.keys)
            if getattr(self, k, None) is not None
        )
        return f"{self.kind}({fields})"


def _node_ids(ctx: SimContext, node: int | None, kinds: tuple[str, ...]) -> frozenset[int]:
    """CAN ids of the messages ``kinds`` of ``node`` (or of every node)."""
    return frozenset(
        ctx.protocol.layout(kind, n.node_id).frame_id for n in ctx.node_list(node) for kind in kinds
    )


_MESSAGES = {
    "feedback": ("Feedback",),
    "status": ("Status",),
    "heartbeat": ("Heartbeat",),
    "all": ("Feedback", "Status", "Heartbeat"),
}


@dataclass(eq=False)
class DropCommands(Injector):
    """TorqueCommand frames lost before they reach the node: ``count`` of them, or all while on."""

    kind: ClassVar[str] = "drop_commands"
    filters_rx: ClassVar[bool] = True
    keys: ClassVar[tuple[str, ...]] = ("count",)
    count: int | None = None
    dropped: int = field(default=0, init=False)
    _ids: frozenset[int] = field(default=frozenset(), init=False, repr=False)

    def start(self, ctx: SimContext, now_ns: int) -> None:
        self.dropped = 0
        self._ids = _node_ids(ctx, self.node, ("TorqueCommand",))

    def rx(self, frame_id: int, data: bytes) -> bool:
        if frame_id in self._ids and (self.count is None or self.dropped < self.count):
            self.dropped += 1
            return False
        return True


@dataclass(eq=False)
class DropFeedback(Injector):
    """Feedback frames lost on the way to the host."""

    kind: ClassVar[str] = "drop_feedback"
    filters_tx: ClassVar[bool] = True
    _ids: frozenset[int] = field(default=frozenset(), init=False, repr=False)

    def start(self, ctx: SimContext, now_ns: int) -> None:
        self._ids = _node_ids(ctx, self.node, ("Feedback",))

    def tx(self, frame_id: int, data: bytes, now_ns: int, out: list[tuple[int, bytes]]) -> None:
        if frame_id not in self._ids:
            out.append((frame_id, data))


@dataclass(eq=False)
class DelayFeedback(Injector):
    """Feedback frames held back by ``delay`` seconds (a congested gateway); flushed at stop."""

    kind: ClassVar[str] = "delay_feedback"
    filters_tx: ClassVar[bool] = True
    periodic: ClassVar[bool] = True
    keys: ClassVar[tuple[str, ...]] = ("delay",)
    delay: float = 0.005
    _ids: frozenset[int] = field(default=frozenset(), init=False, repr=False)
    _held: deque[tuple[int, int, bytes]] = field(default_factory=deque, init=False, repr=False)

    def start(self, ctx: SimContext, now_ns: int) -> None:
        self._ids = _node_ids(ctx, self.node, ("Feedback",))
        self._held.clear()

    def tx(self, frame_id: int, data: bytes, now_ns: int, out: list[tuple[int, bytes]]) -> None:
        if frame_id in self._ids:
            self._held.append((now_ns + round(self.delay * 1e9), frame_id, data))
        else:
            out.append((frame_id, data))

    def tick(self, ctx: SimContext, now_ns: int) -> None:
        held = self._held
        while held and held[0][0] <= now_ns:
            _, frame_id, data = held.popleft()
            ctx.send_frame(frame_id, data)

    def stop(self, ctx: SimContext, now_ns: int) -> None:
        while self._held:
            _, frame_id, data = self._held.popleft()
            ctx.send_frame(frame_id, data)


@dataclass(eq=False)
class CorruptCrc(Injector):
    """A node's frames leave with a wrong CRC byte (a flipped bit the CAN CRC missed)."""

    kind: ClassVar[str] = "corrupt_crc"
    filters_tx: ClassVar[bool] = True
    keys: ClassVar[tuple[str, ...]] = ("message",)
    message: str = "feedback"
    _ids: frozenset[int] = field(default=frozenset(), init=False, repr=False)

    def start(self, ctx: SimContext, now_ns: int) -> None:
        self._ids = _node_ids(ctx, self.node, _MESSAGES[self.message])

    def tx(self, frame_id: int, data: bytes, now_ns: int, out: list[tuple[int, bytes]]) -> None:
        if frame_id in self._ids:
            data = bytes((data[0] ^ 0x5A,)) + data[1:]
        out.append((frame_id, data))


@dataclass(eq=False)
class _CounterFault(Injector):
    keys: ClassVar[tuple[str, ...]] = ("message",)
    step: ClassVar[int] = 1
    message: str = "feedback"

    def _set(self, ctx: SimContext, step: int) -> None:
        for node in ctx.node_list(self.node):
            for kind in _MESSAGES[self.message]:
                node.counter_step[kind] = step

    def start(self, ctx: SimContext, now_ns: int) -> None:
        self._set(ctx, self.step)

    def stop(self, ctx: SimContext, now_ns: int) -> None:
        self._set(ctx, 1)


@dataclass(eq=False)
class CounterRepeat(_CounterFault):
    """The node's sent counter stops advancing: every frame repeats the previous counter."""

    kind: ClassVar[str] = "counter_repeat"
    step: ClassVar[int] = 0


@dataclass(eq=False)
class CounterSkip(_CounterFault):
    """The node's sent counter advances by two: every frame skips one value."""

    kind: ClassVar[str] = "counter_skip"
    step: ClassVar[int] = 2


@dataclass(eq=False)
class _JointFault(Injector):
    joint: int | None = None

    def _indices(self, ctx: SimContext) -> list[int]:
        return ctx.joint_indices(self.node, self.joint)


@dataclass(eq=False)
class TdtStuck(_JointFault):
    """A TDT sensor repeats the reading it had when the fault came, whatever the joint feels."""

    kind: ClassVar[str] = "tdt_stuck"

    def start(self, ctx: SimContext, now_ns: int) -> None:
        for i in self._indices(ctx):
            ctx.tdt.stuck[i] = True
            ctx.tdt.stuck_value[i] = ctx.tdt.reading[i]
        ctx.tdt.update_faults()

    def stop(self, ctx: SimContext, now_ns: int) -> None:
        for i in self._indices(ctx):
            ctx.tdt.stuck[i] = False
        ctx.tdt.update_faults()


@dataclass(eq=False)
class TdtOffset(_JointFault):
    """A TDT reading shifted by ``offset`` N·m (a drifted bridge, a knocked sensor)."""

    kind: ClassVar[str] = "tdt_offset"
    keys: ClassVar[tuple[str, ...]] = ("offset",)
    offset: float = 0.1

    def start(self, ctx: SimContext, now_ns: int) -> None:
        for i in self._indices(ctx):
            ctx.tdt.added[i] += self.offset
        ctx.tdt.update_faults()

    def stop(self, ctx: SimContext, now_ns: int) -> None:
        for i in self._indices(ctx):
            ctx.tdt.added[i] -= self.offset
        ctx.tdt.update_faults()


@dataclass(eq=False)
class TdtSpike(_JointFault):
    """A TDT reading jumps by ``amplitude`` N·m for ``duration`` s after switching on (EMI)."""

    kind: ClassVar[str] = "tdt_spike"
    periodic: ClassVar[bool] = True
    keys: ClassVar[tuple[str, ...]] = ("amplitude", "duration")
    amplitude: float = 1.0
    duration: float = 0.001
    _until: int | None = field(default=None, init=False, repr=False)

    def start(self, ctx: SimContext, now_ns: int) -> None:
        for i in self._indices(ctx):
            ctx.tdt.added[i] += self.amplitude
        ctx.tdt.update_faults()
        self._until = now_ns + round(self.duration * 1e9)

    def tick(self, ctx: SimContext, now_ns: int) -> None:
        if self._until is not None and now_ns + NODE_TICK_NS >= self._until:
            self._end(ctx)

    def stop(self, ctx: SimContext, now_ns: int) -> None:
        self._end(ctx)

    def _end(self, ctx: SimContext) -> None:
        if self._until is None:
            return
        self._until = None
        for i in self._indices(ctx):
            ctx.tdt.added[i] -= self.amplitude
        ctx.tdt.update_faults()


@dataclass(eq=False)
class EncoderJump(_JointFault):
    """An encoder that lost ``counts`` counts (a missed index pulse); jumps back at stop."""

    kind: ClassVar[str] = "encoder_jump"
    keys: ClassVar[tuple[str, ...]] = ("counts",)
    counts: int = 64

    def start(self, ctx: SimContext, now_ns: int) -> None:
        for i in self._indices(ctx):
            ctx.encoders.jump[i] += self.counts * ctx.encoders.step
        ctx.encoders.update_faults()

    def stop(self, ctx: SimContext, now_ns: int) -> None:
        for i in self._indices(ctx):
            ctx.encoders.jump[i] -= self.counts * ctx.encoders.step
        ctx.encoders.update_faults()


@dataclass(eq=False)
class NodeReboot(Injector):
    """A node browns out: silent and torque-free for ``downtime`` s, then boots DISABLED."""

    kind: ClassVar[str] = "node_reboot"
    keys: ClassVar[tuple[str, ...]] = ("downtime",)
    downtime: float = 0.05

    def start(self, ctx: SimContext, now_ns: int) -> None:
        for node in ctx.node_list(self.node):
            node.reboot(now_ns, round(self.downtime * 1e9))


@dataclass(eq=False)
class NodeSilent(Injector):
    """A node whose transmitter died: it still hears and acts, but sends nothing."""

    kind: ClassVar[str] = "node_silent"
    filters_tx: ClassVar[bool] = True
    _ids: frozenset[int] = field(default=frozenset(), init=False, repr=False)

    def start(self, ctx: SimContext, now_ns: int) -> None:
        self._ids = _node_ids(ctx, self.node, _MESSAGES["all"])

    def tx(self, frame_id: int, data: bytes, now_ns: int, out: list[tuple[int, bytes]]) -> None:
        if frame_id not in self._ids:
            out.append((frame_id, data))


@dataclass(eq=False)
class ErrorFrames(Injector):
    """``per_tick`` error frames on the bus every tick (a bad termination, a noisy cable)."""

    kind: ClassVar[str] = "error_frames"
    periodic: ClassVar[bool] = True
    bus_wide: ClassVar[bool] = True
    keys: ClassVar[tuple[str, ...]] = ("per_tick",)
    per_tick: int = 1

    def tick(self, ctx: SimContext, now_ns: int) -> None:
        for _ in range(self.per_tick):
            ctx.send_error_frame()


@dataclass(eq=False)
class BusOff(Injector):
    """The nodes' controllers go bus-off: a bus-off error frame (class 0x040, as SocketCAN
    reports it), then nothing from any node until off, then a restarted frame (0x100).

    The nodes keep running (the watchdog still sees the host's commands, if any get through).
    """

    kind: ClassVar[str] = "bus_off"
    filters_tx: ClassVar[bool] = True
    bus_wide: ClassVar[bool] = True

    def start(self, ctx: SimContext, now_ns: int) -> None:
        ctx.send_error_frame(0x040)

    def stop(self, ctx: SimContext, now_ns: int) -> None:
        ctx.send_error_frame(0x100)

    def tx(self, frame_id: int, data: bytes, now_ns: int, out: list[tuple[int, bytes]]) -> None:
        return


@dataclass(eq=False)
class Babble(Injector):
    """A babbling node: ``per_tick`` frames of ``length`` bytes on ``id`` every tick, heard by
    the host and by the emulated nodes alike (on id 0 it is a malformed e-stop, and honoured)."""

    kind: ClassVar[str] = "babble"
    periodic: ClassVar[bool] = True
    bus_wide: ClassVar[bool] = True
    keys: ClassVar[tuple[str, ...]] = ("id", "per_tick", "length")
    id: int = 0x050
    per_tick: int = 20
    length: int = 8
    sent: int = field(default=0, init=False)

    def tick(self, ctx: SimContext, now_ns: int) -> None:
        for _ in range(self.per_tick):
            data = bytes((self.sent + k) & 0xFF for k in range(self.length))
            ctx.send_foreign_frame(self.id, data)
            self.sent += 1


@dataclass(eq=False)
class ExtendedTwin(Injector):
    """Every frame of a node's ``message`` also goes out on the 29-bit identifier with the same
    number (0x181 as 0x00000181), the same payload, right after it: a device that speaks the
    protocol on extended ids (a misconfigured gateway, or an attacker). Only 11-bit ids are
    the protocol's."""

    kind: ClassVar[str] = "extended_twin"
    filters_tx: ClassVar[bool] = True
    keys: ClassVar[tuple[str, ...]] = ("message",)
    message: str = "feedback"
    sent: int = field(default=0, init=False)
    _ids: frozenset[int] = field(default=frozenset(), init=False, repr=False)

    def start(self, ctx: SimContext, now_ns: int) -> None:
        self._ids = _node_ids(ctx, self.node, _MESSAGES[self.message])

    def tx(self, frame_id: int, data: bytes, now_ns: int, out: list[tuple[int, bytes]]) -> None:
        out.append((frame_id, data))
        if frame_id in self._ids:
            out.append((frame_id | EXTENDED_ID_FLAG, data))
            self.sent += 1


@dataclass(eq=False)
class Contradict(Injector):
    """A node whose reports contradict each other, each frame still valid (CRC, counter):

    - ``report: fault_bits``: its Feedback carries latched fault ``bits`` (TIMEOUT by
      default) whatever its state, so an ENABLED node says it has timed out;
    - ``report: heartbeat``: after its frames of every tick a Heartbeat saying ENABLED (its own
      heartbeats are held back), so a node in FAULT says FAULT in its Feedback and ENABLED
      after it, in the same tick.
    """

    kind: ClassVar[str] = "contradict"
    filters_tx: ClassVar[bool] = True
    periodic: ClassVar[bool] = True
    keys: ClassVar[tuple[str, ...]] = ("report", "bits")
    report: str = "fault_bits"
    bits: int = 0x01
    _feedback: dict[int, Layout] = field(default_factory=dict, init=False, repr=False)
    _heartbeat: dict[int, Layout] = field(default_factory=dict, init=False, repr=False)
    _nodes: list[EmulatedNode] = field(default_factory=list, init=False, repr=False)
    _counters: dict[int, int] = field(default_factory=dict, init=False, repr=False)

    def start(self, ctx: SimContext, now_ns: int) -> None:
        self._nodes = ctx.node_list(self.node)
        self._feedback = {
            ctx.protocol.layout("Feedback", n.node_id).frame_id: ctx.protocol.layout(
                "Feedback", n.node_id
            )
            for n in self._nodes
        }
        self._heartbeat = {
            n.node_id: ctx.protocol.layout("Heartbeat", n.node_id) for n in self._nodes
        }

    def tx(self, frame_id: int, data: bytes, now_ns: int, out: list[tuple[int, bytes]]) -> None:
        if self.report == "fault_bits":
            layout = self._feedback.get(frame_id)
            if layout is not None:
                counter, values = layout.decode(data)
                *signals, bits = values
                data = layout.encode(counter, (*signals, int(bits) | self.bits))
        elif any(frame_id == hb.frame_id for hb in self._heartbeat.values()):
            return  # the node's own heartbeat is held back; ``tick`` sends the lie
        out.append((frame_id, data))

    def tick(self, ctx: SimContext, now_ns: int) -> None:
        if self.report != "heartbeat":
            return
        for node in self._nodes:
            if node.down:
                continue
            layout = self._heartbeat[node.node_id]
            counter = self._counters.get(node.node_id, 0)
            ctx.send_frame(
                layout.frame_id, layout.encode(counter, (1, node.uptime_ms(now_ns) & 0xFFFFFFFF))
            )
            self._counters[node.node_id] = (counter + 1) & 0xFF


@dataclass(eq=False)
class ReplayFrames(Injector):
    """A recording of a node's own ``message`` frames played back ``delay`` s late, two a tick
    (consecutive counters, valid CRCs): interleaved with the live stream, each tick the host
    rejects the live frame and the first replayed one and accepts the second, so what that
    stream says (angles, torques, state) is ``delay`` old, unless the host minds the rejects.
    ``delay`` counts frames of the message at 1 kHz: it suits ``feedback``."""

    kind: ClassVar[str] = "replay_frames"
    filters_tx: ClassVar[bool] = True
    keys: ClassVar[tuple[str, ...]] = ("message", "delay")
    message: str = "feedback"
    delay: float = 0.2
    replayed: int = field(default=0, init=False)
    _ids: frozenset[int] = field(default=frozenset(), init=False, repr=False)
    _log: dict[int, deque[bytes]] = field(default_factory=dict, init=False, repr=False)

    def start(self, ctx: SimContext, now_ns: int) -> None:
        self._ids = _node_ids(ctx, self.node, _MESSAGES[self.message])
        self._log = {frame_id: deque() for frame_id in self._ids}

    def tx(self, frame_id: int, data: bytes, now_ns: int, out: list[tuple[int, bytes]]) -> None:
        out.append((frame_id, data))
        log = self._log.get(frame_id)
        if log is None:
            return
        log.append(data)
        if len(log) > max(1, round(self.delay * 1e9) // NODE_TICK_NS) + 1:
            out.append((frame_id, log.popleft()))
            out.append((frame_id, log[0]))
            self.replayed += 2


@dataclass(eq=False)
class TendonSlack(_JointFault):
    """A slack tendon: the motor pulls, the joint gets no torque, the TDT reads about zero."""

    kind: ClassVar[str] = "tendon_slack"

    def start(self, ctx: SimContext, now_ns: int) -> None:
        for i in self._indices(ctx):
            ctx.plant.set_tendon_slack(i, True)

    def stop(self, ctx: SimContext, now_ns: int) -> None:
        for i in self._indices(ctx):
            ctx.plant.set_tendon_slack(i, False)


@dataclass(eq=False)
class MotorSaturation(_JointFault):
    """A motor that gives no more than ``limit`` N·m (overheated, low supply), unknown to the
    node: the command is applied, the TDT shows the shortfall."""

    kind: ClassVar[str] = "motor_saturation"
    keys: ClassVar[tuple[str, ...]] = ("limit",)
    limit: float = 0.05

    def start(self, ctx: SimContext, now_ns: int) -> None:
        for i in self._indices(ctx):
            ctx.plant.set_motor_limit(i, self.limit)

    def stop(self, ctx: SimContext, now_ns: int) -> None:
        for i in self._indices(ctx):
            ctx.plant.set_motor_limit(i, None)


INJECTORS: dict[str, type[Injector]] = {
    cls.kind: cls
    for cls in (
        DropCommands,
        DropFeedback,
        DelayFeedback,
        CorruptCrc,
        CounterRepeat,
        CounterSkip,
        TdtStuck,
        TdtSpike,
        TdtOffset,
        EncoderJump,
        NodeReboot,
        NodeSilent,
        ErrorFrames,
        BusOff,
        Babble,
        ExtendedTwin,
        Contradict,
        ReplayFrames,
        TendonSlack,
        MotorSaturation,
    )
}


#: injectors whose state is another's: both set a node's counter step, and the end of one
#: ended the other's window (``_refuse_overlaps`` holds them to one group)
_SHARED_STATE: dict[type, type] = {CounterRepeat: _CounterFault, CounterSkip: _CounterFault}


# -- schedule ----------------------------------------------------------------------------------
@dataclass(frozen=True)
class Scheduled:
    """One injector and when it is on: from ``start`` to ``stop`` (s of simulated time)."""

    injector: Injector
    start: float
    stop: float | None = None

    def ticks(self) -> tuple[int, int | None]:
        """The node ticks it is switched on and off at (off: None, never): the times rounded
        to the 1 ms tick, and a window within one tick (start == stop) lasts that tick (its
        off, sorted before its on in the same tick, left the fault on for good)."""
        on = round(self.start * 1e9) // NODE_TICK_NS
        if self.stop is None:
            return on, None
        return on, max(round(self.stop * 1e9) // NODE_TICK_NS, on + 1)


class FaultSchedule:
    """Injectors with their switching times; the simulated hand consults it every tick."""

    def __init__(self, entries: Iterable[Scheduled] = ()) -> None:
        self._events: list[tuple[int, int, int, Injector]] = []  # (tick, order, on=1/off=0, inj)
        self._order = 0
        self._next = 0
        self.entries: list[Scheduled] = []
        for entry in entries:
            self.add(entry.injector, entry.start, entry.stop)

    def __iter__(self) -> Iterator[Scheduled]:
        return iter(self.entries)

    def __len__(self) -> int:
        return len(self.entries)

    def add(self, injector: Injector, start: float, stop: float | None = None) -> None:
        """Switch ``injector`` on at ``start`` s and off at ``stop`` s (never, if ``None``).

        Times are rounded to the 1 ms tick, and a window lasts one tick at least. Adding an
        event in the past makes it happen at the next tick.
        """
        if start < 0 or (stop is not None and stop < start):
            raise ValueError(
                f"{injector.describe()}: expected 0 <= start <= stop, found "
                f"start={start!r}, stop={stop!r}"
            )
        entry = Scheduled(injector, start, stop)
        self.entries.append(entry)
        on, off = entry.ticks()
        self._insert(on, 1, injector)
        if off is not None:
            self._insert(off, 0, injector)

    def _insert(self, tick: int, on: int, injector: Injector) -> None:
        # Off events sort before on events of the same tick, so an off and an on at the same
        # time hand over cleanly; insertion order breaks the remaining ties. Events already
        # handed out stay where they are.
        self._order += 1
        self._events.append((tick, on, self._order, injector))
        self._events[self._next :] = sorted(self._events[self._next :], key=lambda e: e[:3])

    def due(self, tick: int) -> Iterator[tuple[bool, Injector]]:
        """The switchings that are due at ``tick`` (each returned once), in order."""
        events = self._events
        while self._next < len(events) and events[self._next][0] <= tick:
            _, on, _, injector = events[self._next]
            self._next += 1
            yield bool(on), injector

    @property
    def pending(self) -> bool:
        return self._next < len(self._events)


def load_scenario(path: str | Path, hand: HandConfig) -> FaultSchedule:
    """Read a fault scenario file; every mistake is a ``ConfigError`` that names the key."""
    return parse_scenario(load_yaml(path, "fault list"), hand)


def parse_scenario(doc: Doc, hand: HandConfig) -> FaultSchedule:
    doc.string("description", default="-")
    entries = [_parse_entry(d, hand) for d in doc.mappings("faults", min_len=1)]
    _refuse_overlaps(doc, entries)
    doc.done()
    return FaultSchedule(entries)


def _refuse_overlaps(doc: Doc, entries: Sequence[Scheduled]) -> None:
    """Two windows of one injector on one target may not overlap: the injector's state is the
    node's (a saturation, a counter's repeat), so the first window's end ended the other's,
    and a long fault beside a short one lasted the short one."""
    seen: dict[type, list[tuple[int, Scheduled, int, float]]] = {}
    for k, entry in enumerate(entries):
        injector = entry.injector
        end = math.inf if entry.stop is None else entry.stop
        # on the ticks the schedule switches them (a window lasts one tick at least):
        # 0.1..0.1 s and 0.1005..0.9 s both came on at tick 100, and the first one's end at
        # tick 101 ended the second
        on, off = entry.ticks()
        until = math.inf if off is None else off
        # its kind and target, whatever its other keys (a saturation's limit, say); a window
        # on every node (or every joint) shares a target with each one's: its end cleared
        # theirs, so a stuck TDT on one joint inside one on all of them ended with the short
        # one, and the scenario injected less than it said
        group = _SHARED_STATE.get(type(injector), type(injector))
        for j, other, other_on, other_until in seen.get(group, []):
            if not (
                _same(injector, other.injector, "node") and _same(injector, other.injector, "joint")
            ):
                continue
            if on < other_until and other_on < until:
                other_end = math.inf if other.stop is None else other.stop
                doc.fail(
                    f"faults[{k}]",
                    f"a window that does not overlap faults[{j}]'s ({other.start:g}"
                    f"..{other_end:g} s) on the 1 ms ticks they switch at: the same "
                    "injector (or one of its state: counter_repeat and counter_skip) on the "
                    "same target, whose end would end both",
                    description(f"{injector.describe()} from {entry.start:g} to {end:g} s"),
                )
        seen.setdefault(group, []).append((k, entry, on, until))


def _same(a: object, b: object, key: str) -> bool:
    """Whether two injectors' ``key`` (node, joint) can name one target: equal, or either
    of them every one (None)."""
    mine, theirs = getattr(a, key, None), getattr(b, key, None)
    return mine is None or theirs is None or mine == theirs


def _parse_entry(doc: Doc, hand: HandConfig) -> Scheduled:
    kind = doc.string("kind", choices=sorted(INJECTORS))
    cls = INJECTORS[kind]
    start = doc.number("start", min=0.0, max=1e6, unit="s")
    stop: float | None = None
    if doc.has("stop"):
        stop = doc.number("stop", min=start, max=1e6, unit="s")
    kwargs: dict[str, object] = {}
    node_ids = [f.node_id for f in hand.fingers]
    if cls.bus_wide and doc.has("node"):
        doc.fail(
            "node",
            f"no node: {kind} is of the whole bus (a node that stops sending is node_silent)",
            doc.raw("node"),
        )
    if doc.has("node"):
        # one message for every id the hand has not: bounds said "an integer >= 2 and <= 13"
        # of a hand whose nodes are 2, 4, 6 and 13, as if any id between were one
        node = doc.integer("node")
        if node not in node_ids:
            doc.fail("node", "a node id of the hand (" + ", ".join(map(str, node_ids)) + ")", node)
        kwargs["node"] = node
    if issubclass(cls, _JointFault) and doc.has("joint"):
        fingers = [f for f in hand.fingers if f.node_id == kwargs.get("node")] or hand.fingers
        kwargs["joint"] = doc.integer("joint", min=1, max=min(len(f.joints) for f in fingers))
    for key in cls.keys:
        if doc.has(key):
            kwargs[key] = _READERS[key](doc, key)
    doc.done()
    return Scheduled(cls(**kwargs), start, stop)  # type: ignore[arg-type]


def _message(doc: Doc, key: str) -> str:
    return doc.string(key, choices=sorted(_MESSAGES))


def _length(doc: Doc, key: str) -> int:
    value = doc.integer(key, min=0, max=64)
    if value not in _FD_LENGTHS:
        doc.fail(key, "a CAN-FD payload length (" + ", ".join(map(str, _FD_LENGTHS)) + ")", value)
    return value


def _report(doc: Doc, key: str) -> str:
    return doc.string(key, choices=["fault_bits", "heartbeat"])


_FD_LENGTHS = (0, 1, 2, 3, 4, 5, 6, 7, 8, 12, 16, 20, 24, 32, 48, 64)
_READERS: dict[str, Callable[[Doc, str], object]] = {
    "count": lambda d, k: d.integer(k, min=1, max=10**9),
    "delay": lambda d, k: d.number(k, min=0.0, max=10.0, min_exclusive=True, unit="s"),
    "message": _message,
    "offset": lambda d, k: d.number(k, min=-3.0, max=3.0, unit="N·m"),
    "amplitude": lambda d, k: d.number(k, min=-10.0, max=10.0, unit="N·m"),
    "duration": lambda d, k: d.number(k, min=0.0, max=10.0, min_exclusive=True, unit="s"),
    "counts": lambda d, k: d.integer(k, min=-(2**20), max=2**20),
    "downtime": lambda d, k: d.number(k, min=0.0, max=60.0, unit="s"),
    "per_tick": lambda d, k: d.integer(k, min=1, max=1000),
    "id": lambda d, k: d.integer(k, min=0, max=0x7FF),
    "length": _length,
    "limit": lambda d, k: d.number(k, min=0.0, max=100.0, unit="N·m"),
    "report": _report,
    "bits": lambda d, k: d.integer(k, min=1, max=0xFF),
}
