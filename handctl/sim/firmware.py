"""One finger's controller node, as ``firmware_protocol/PROTOCOL.md`` specifies it.

``EmulatedNode`` is the device side of the protocol and nothing else: frames and time go in,
applied torques and frames come out. It does no I/O and keeps no clock of its own, so the same
object runs in lockstep (tests, deterministic runs) and on a real-time timer, and a test can
drive it frame by frame.

A tick of the node, in the order the firmware runs it:
1. ``receive`` every frame that arrived: the receiver checks (unexpected id, length, CRC,
   repeated or skipped counter) in the documented order; a rejected frame is counted by kind,
   scores +10, and is never applied; an accepted frame scores -1. At 100 the node latches
   FAULT(RX_ERRORS). An ``EStop`` is honoured even when it is malformed.
2. ``update``: the command watchdog (10 ms without an accepted ``TorqueCommand`` while ENABLED
   zeroes torque and latches FAULT(TIMEOUT)), and the end of a reboot.
3. The torque in ``applied`` goes to the motors.
4. ``publish`` with the sensor readings of this tick: the self-check (TDT out of range, encoder
   jump), then the ``Status`` frames of this tick's state changes, ``Feedback``, a periodic
   ``Status`` if due and the ``Heartbeat``.

Readings of the spec worth stating:
- "receive counters" reset by a fault reset are the rolling-counter states (the next frame of
  each message is accepted with any counter), not the reject counts, which stay as diagnostics
  until the node reboots;
- a ``Status`` due both for a state change and for the 100 ms period in the same tick is sent
  once, since it says the same;
- a ``NodeCommand`` with a ``Command`` value the spec does not define is accepted (it passed
  every check) and ignored;
- frames with ids the node does not take are counted in ``reject_unexpected``, which no frame
  carries and which does not touch the reject score: they are not addressed to the node.

A new host (PROTOCOL.md, "A new host"): a host that starts counts its frames from wherever it
likes, so a node that is DISABLED, or in FAULT and has heard nothing from any host for the
watchdog time, takes the next intact ``NodeCommand``'s counter as its baseline. An ``enable``
opens the ``TorqueCommand`` stream, and the first ``TorqueCommand`` of an open stream only sets
the baseline: it is never applied. Torque thus only ever comes from a command whose counter
follows one accepted before it, so no single stale or replayed frame moves a joint.
"""

from __future__ import annotations

import enum
from collections.abc import Sequence

from handctl.config import FingerConfig
from handctl.errors import ConfigError
from handctl.protocol import (
    COMMAND_WATCHDOG_S,
    HEARTBEAT_PERIOD_S,
    NODE_COMMANDS,
    Layout,
    NodeState,
    Protocol,
)
from handctl.sim.params import NODE_TICK_NS

#: No accepted TorqueCommand for this long while ENABLED latches TIMEOUT (the protocol's, which
#: the hand config's slowest loop is held to).
WATCHDOG_NS = round(COMMAND_WATCHDOG_S * 1e9)
REJECT_PENALTY = 10
REJECT_LIMIT = 100
STATUS_PERIOD_MS = 100
HEARTBEAT_PERIOD_MS = round(HEARTBEAT_PERIOD_S * 1000)
#: The firmware version the emulated nodes report (major, minor, patch) in Status.
FIRMWARE_VERSION = (0, 2, 0)
_SATURATING = 255

_ENABLE = NODE_COMMANDS["enable"]
_DISABLE = NODE_COMMANDS["disable"]
_FAULT_RESET = NODE_COMMANDS["fault_reset"]


class FaultBits(enum.IntFlag):
    TIMEOUT = 0x01
    ESTOP = 0x02
    RX_ERRORS = 0x04
    SENSOR = 0x08
    SATURATED = 0x10


LATCHED = int(FaultBits.TIMEOUT | FaultBits.ESTOP | FaultBits.RX_ERRORS | FaultBits.SENSOR)
# Plain ints on the hot path: IntFlag arithmetic costs microseconds per operation.
_TIMEOUT = int(FaultBits.TIMEOUT)
_ESTOP = int(FaultBits.ESTOP)
_RX_ERRORS = int(FaultBits.RX_ERRORS)
_SENSOR = int(FaultBits.SENSOR)
_SATURATED = int(FaultBits.SATURATED)
_DISABLED = int(NodeState.DISABLED)
_ENABLED = int(NodeState.ENABLED)
_FAULT = int(NodeState.FAULT)


class EmulatedNode:
    """The controller of one finger: per joint a motor, a TDT sensor and an encoder, as many
    as its ``TorqueCommand`` carries torques (``Torque1..k``)."""

    def __init__(
        self,
        finger: FingerConfig,
        protocol: Protocol,
        *,
        tdt_range: float,
        encoder_max_step: float,
        now_ns: int = 0,
    ) -> None:
        self.finger = finger
        self.node_id = finger.node_id
        n = finger.node_id
        self._estop = protocol.layout("EStop")
        self._command = protocol.layout("NodeCommand", n)
        self._torque = protocol.layout("TorqueCommand", n)
        self._feedback = protocol.layout("Feedback", n)
        self._status = protocol.layout("Status", n)
        self._heartbeat = protocol.layout("Heartbeat", n)
        for kind, layout in (
            ("node_command", self._command),
            ("torque_command", self._torque),
            ("feedback", self._feedback),
            ("status", self._status),
            ("heartbeat", self._heartbeat),
        ):
            configured = getattr(finger.can_ids, kind)
            if configured != layout.frame_id:
                raise ConfigError(
                    protocol.source,
                    f"{layout.name}",
                    f"the id of {finger.name}.can_ids.{kind} "
                    f"(0x{configured:03X}) in the hand config",
                    f"0x{layout.frame_id:03X}",
                )
        self._rx: dict[int, Layout] = {
            layout.frame_id: layout for layout in (self._estop, self._command, self._torque)
        }
        self._estop_id = self._estop.frame_id
        self._command_id = self._command.frame_id
        self._torque_id = self._torque.frame_id
        self.tx_ids = (self._feedback.frame_id, self._status.frame_id, self._heartbeat.frame_id)
        self._n = len(finger.joints)
        #: Joints on the wire: the command's torques. A finger of fewer joints than its frames
        #: carry leaves the rest at zero, both ways.
        self._wire = len(self._torque.signals)
        if self._n > self._wire:
            raise ConfigError(
                protocol.source,
                self._torque.name,
                f"a torque per joint of {finger.name} ({self._n})",
                f"{self._wire} torques",
            )
        self._limit_items = tuple(enumerate(j.device_tau_max for j in finger.joints))
        self._absent = tuple(range(self._n, self._wire))
        self._pad_zeros = [0.0] * (self._wire - self._n)
        self.tdt_range = tdt_range
        self.encoder_max_step = encoder_max_step
        #: How much each sent counter advances: 1 normally; 0 (repeat) or 2 (skip) under the
        #: counter injectors. Keyed by message kind: Feedback, Status, Heartbeat.
        self.counter_step = {"Feedback": 1, "Status": 1, "Heartbeat": 1}
        #: What Status reports: the protocol version (the DBC's unless a test makes the node
        #: speak another one, to see the host refuse it) and the firmware version.
        self.protocol_version = protocol.version
        self.firmware_version = FIRMWARE_VERSION
        self.reboots = 0
        self._down_until: int | None = None
        self.boot(now_ns)

    # -- life cycle -------------------------------------------------------------------------
    def boot(self, now_ns: int) -> None:
        """Power-on state: DISABLED, counters at 0, every receive state fresh."""
        self._boot_ns = now_ns
        self._down_until = None
        self.state = _DISABLED  # a NodeState value, kept as int for speed
        self.fault_bits = 0
        self.applied = [0.0] * self._wire
        self.commanded: Sequence[float] = (0.0,) * self._wire  # last accepted command, unclipped
        self._rx_last: dict[int, int | None] = dict.fromkeys(self._rx)
        self.reject_crc = 0
        self.reject_counter = 0
        self.reject_length = 0
        self.reject_unexpected = 0  # not on the wire: Status has no field for it
        self.accepted = 0
        self.score = 0
        self._last_command_ns: int | None = None
        self._watchdog_ref_ns = now_ns
        self._host_heard_ns = now_ns  # the last accepted NodeCommand or TorqueCommand
        self._last_angles: list[float] | None = None
        self._tx_feedback = 0
        self._tx_status = 0
        self._tx_heartbeat = 0
        self._pending_status: list[tuple[int, int]] = []

    def reboot(self, now_ns: int, downtime_ns: int) -> None:
        """Lose power now and boot again after ``downtime_ns``; silent and torque-free meanwhile."""
        self.reboots += 1
        self._down_until = now_ns + max(downtime_ns, 0)
        self.applied = [0.0] * self._wire

    @property
    def down(self) -> bool:
        """True while the node is rebooting: it neither hears nor speaks."""
        return self._down_until is not None

    def uptime_ms(self, now_ns: int) -> int:
        return (now_ns - self._boot_ns) // NODE_TICK_NS

    # -- receiving --------------------------------------------------------------------------
    def receive(self, frame_id: int, data: bytes, now_ns: int) -> None:
        """Check one frame seen on the bus and act on it if it is accepted."""
        layout = self._rx.get(frame_id)
        if self._down_until is not None:
            return
        if layout is None:
            self.reject_unexpected += 1
            return
        if len(data) != layout.length:
            self.reject_length = min(self.reject_length + 1, _SATURATING)
        elif not layout.crc_ok(data):
            self.reject_crc = min(self.reject_crc + 1, _SATURATING)
        else:
            counter = data[1]
            last = self._rx_last[frame_id]
            if (
                last is None
                or counter == (last + 1) & 0xFF
                or (frame_id == self._command_id and self._new_host_possible(now_ns))
            ):
                self._rx_last[frame_id] = counter
                self.accepted += 1
                if self.score:
                    self.score -= 1
                if frame_id != self._estop_id:
                    self._host_heard_ns = now_ns
                if layout is self._torque:  # the 1 kHz case first
                    if last is not None:  # the first of a stream is a baseline, never a torque
                        self._last_command_ns = self._watchdog_ref_ns = now_ns
                        self.commanded = layout.decode(data)[1]
                        if self.state == _ENABLED:
                            self._saturate()
                else:
                    self._apply(layout, data, now_ns)
                return
            self.reject_counter = min(self.reject_counter + 1, _SATURATING)
            if counter != last:  # skipped: re-synchronise so only this frame is lost
                self._rx_last[frame_id] = counter
        self.score += REJECT_PENALTY
        if self.score >= REJECT_LIMIT:
            self._fault(_RX_ERRORS)
        if frame_id == self._estop_id:  # stopping is always the safe reading of a bad e-stop
            self._fault(_ESTOP)

    def remote(self, frame_id: int) -> None:
        """A remote frame (RTR) seen on the bus: it has no data, so it is no command and is
        not counted as a rejected one (it was taken as a data frame of 0 bytes, a length
        reject). On id 0x000 it is still an e-stop: PROTOCOL.md has every node obey any frame
        with that id, whatever it carries (only a 29-bit id 0 is excepted), since stopping is
        always the safe reading."""
        if self._down_until is None and frame_id == self._estop_id:
            self._fault(_ESTOP)

    def _new_host_possible(self, now_ns: int) -> bool:
        """Whether a NodeCommand may start a new counter baseline (PROTOCOL.md, "A new host").

        Only where it cannot move a joint: DISABLED applies no torque and an enable opens the
        torque stream afresh; a node in FAULT must first have heard no host frame for the
        watchdog time, so a live host's stream is still checked and a replayed fault_reset
        cannot slip in while it runs. Never while ENABLED.
        """
        state = self.state
        return state == _DISABLED or (
            state == _FAULT and now_ns - self._host_heard_ns >= WATCHDOG_NS
        )

    def _apply(self, layout: Layout, data: bytes, now_ns: int) -> None:
        if layout is self._command:
            command = layout.decode(data)[1][0]
            if command == _ENABLE:
                self._enable(now_ns)
            elif command == _DISABLE:
                if self.state == _ENABLED:
                    self.applied = [0.0] * self._wire
                    self._set_state(_DISABLED)
            elif command == _FAULT_RESET:
                self._fault_reset()
            # any other value is a command this firmware does not know: accepted, ignored
        else:
            self._fault(_ESTOP)

    def _enable(self, now_ns: int) -> None:
        if self.state != _DISABLED:
            return  # ENABLED stays; FAULT refuses until a fault reset
        self._watchdog_ref_ns = now_ns
        self.commanded = (0.0,) * self._wire
        self.applied = [0.0] * self._wire
        # The torque stream starts afresh: its next frame sets the baseline and is not applied.
        self._rx_last[self._torque_id] = None
        self._set_state(_ENABLED)

    def _fault_reset(self) -> None:
        if self.state == _FAULT:
            self.fault_bits = 0
            self.score = 0
            self._rx_last = dict.fromkeys(self._rx)
            self._last_angles = None
            self._set_state(_DISABLED)
        elif self.state == _DISABLED:
            self.fault_bits &= LATCHED

    def _saturate(self) -> None:
        applied = list(self.commanded)
        clipped = False
        for k, limit in self._limit_items:
            value = applied[k]
            if value > limit:
                applied[k] = limit
                clipped = True
            elif value < -limit:
                applied[k] = -limit
                clipped = True
        for k in self._absent:
            applied[k] = 0.0
        self.applied = applied
        if clipped:
            self.fault_bits |= _SATURATED
        elif self.fault_bits & _SATURATED:
            self.fault_bits &= ~_SATURATED & 0xFF

    def _fault(self, bits: int) -> None:
        self.fault_bits |= bits
        self.applied = [0.0] * self._wire
        if self.state != _FAULT:
            self._set_state(_FAULT)

    def _set_state(self, state: int) -> None:
        self.state = state
        self._pending_status.append((state, self.fault_bits))

    # -- the rest of the tick ---------------------------------------------------------------
    def update(self, now_ns: int) -> None:
        """Watchdog and reboot; call once per tick after ``receive`` and before the motors."""
        if self._down_until is not None:
            if now_ns >= self._down_until:
                self.boot(now_ns)
            return
        if self.state == _ENABLED and now_ns - self._watchdog_ref_ns >= WATCHDOG_NS:
            self._fault(_TIMEOUT)

    def command_age_ms(self, now_ns: int) -> int:
        if self._last_command_ns is None:
            return _SATURATING
        return min((now_ns - self._last_command_ns) // NODE_TICK_NS, _SATURATING)

    def publish(
        self, now_ns: int, tdt: list[float], angles: list[float], out: list[tuple[int, bytes]]
    ) -> None:
        """Self-check the readings and append this tick's frames to ``out``.

        ``tdt`` (N·m, factory calibration) and ``angles`` (rad) hold one value per joint; a
        finger with fewer joints than its Feedback carries sends zeros in the unused signals.
        The node keeps ``angles`` for the next tick's encoder check: the caller must pass a
        fresh list.
        """
        if self._down_until is not None:
            return
        # Self-check, inline because it runs for every node every tick: what the firmware can
        # tell on its own is a TDT reading out of the sensor's range, or an encoder that moved
        # further in one tick than the joint physically can.
        limit = self.tdt_range
        failed = max(tdt) > limit or min(tdt) < -limit
        last = self._last_angles
        self._last_angles = angles
        if last is not None:
            step = self.encoder_max_step
            for a, b in zip(angles, last, strict=True):
                if a - b > step or b - a > step:
                    failed = True
        if failed:
            self._fault(_SENSOR)
        state = self.state
        bits = self.fault_bits
        if self._pad_zeros:
            tdt = tdt + self._pad_zeros
            angles = angles + self._pad_zeros
        # The Status frames of this tick's state changes go before the Feedback: they tell of
        # states the node passed through before the one the Feedback reports. After it, a
        # node enabled and faulted in one tick said FAULT, then ENABLED (the older change),
        # which a host rightly takes for a node contradicting itself.
        changed = bool(self._pending_status)
        if changed:
            self._publish_status(now_ns, out)
        feedback = self._feedback
        out.append(
            (feedback.frame_id, feedback.encode(self._tx_feedback, (*tdt, *angles, state, bits)))
        )
        self._tx_feedback = (self._tx_feedback + self.counter_step["Feedback"]) & 0xFF
        uptime = (now_ns - self._boot_ns) // NODE_TICK_NS
        if not changed and uptime % STATUS_PERIOD_MS == 0:
            self._publish_status(now_ns, out)
        if uptime % HEARTBEAT_PERIOD_MS == 0:
            heartbeat = self._heartbeat
            out.append(
                (
                    heartbeat.frame_id,
                    heartbeat.encode(self._tx_heartbeat, (state, uptime & 0xFFFFFFFF)),
                )
            )
            self._tx_heartbeat = (self._tx_heartbeat + self.counter_step["Heartbeat"]) & 0xFF

    def _publish_status(self, now_ns: int, out: list[tuple[int, bytes]]) -> None:
        snapshots = self._pending_status or [(self.state, self.fault_bits)]
        self._pending_status = []
        age = self.command_age_ms(now_ns)
        status = self._status
        for state, bits in snapshots:
            out.append(
                (
                    status.frame_id,
                    status.encode(
                        self._tx_status,
                        (
                            state,
                            bits,
                            self.reject_crc,
                            self.reject_counter,
                            self.reject_length,
                            age,
                            self.protocol_version,
                            *self.firmware_version,
                        ),
                    ),
                )
            )
            self._tx_status = (self._tx_status + self.counter_step["Status"]) & 0xFF
