"""The hand config's limits checked against what the DBC's signals can carry.

A limit the wire cannot carry is not enforced where it matters: a torque the supervisor lets
through but the command signal cannot hold makes ``encode`` fail in the middle of a run, and an
angle limit beyond the feedback signal's range is never seen crossed, because the reading
saturates first. So every loaded hand config is held against the DBC (the ranges come from
``handctl/protocol.py``, never from numbers written here), joint by joint, in the signal order
the driver uses (joint k of node n: ``TorqueCommand_n`` signal k; ``Feedback_n`` signal k is its
torque reading and signal k + joints-per-node its angle):

- ``tau_max`` and ``device_tau_max``: ±limit lies within the range of the command signal, so
  every torque up to the limit can be sent and the node's own saturation is one it can be asked
  to reach; and ``tau_max`` is at least the signal's resolution, or no torque the supervisor
  lets through is anything but zero on the wire;
- ``device_tau_max``, through the TDT calibration (reading = (τ - offset) / scale): the
  readings of ±device_tau_max lie within the range of the feedback torque signal, so the host
  sees every torque the node can apply instead of a saturated reading;
- ``angle_min`` and ``angle_max``: strictly inside the range of the feedback angle signal, so a
  joint past its soft limit reads past it before the reading saturates; and the signal's
  resolution at most ``MAX_ANGLE_RESOLUTION_RAD``, so that it reads past it promptly;
- zero: the command signal carries 0 N·m exactly (its offset a multiple of its factor), so
  that a stop is a zero torque and not the nearest value to it; the supervisor keeps every
  applied torque on that signal's grid (``handctl/online/safety/limits.py``);
- ``rate_limit``: one tick's step (rate_limit / bus.loop_rate_hz) is at least the command
  signal's resolution and at most its whole span. A smaller step travels as a one-resolution
  jump every few ticks, which is a faster change between two frames than the limit allows; a
  step larger than the span limits nothing the wire can express.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, NoReturn

from handctl.errors import ConfigError, Description
from handctl.protocol import Layout, Protocol, SignalSpec

if TYPE_CHECKING:
    from handctl.config import FingerConfig, HandConfig, JointConfig

#: rad, the coarsest feedback angle signal (its factor) through which soft limits are watched.
#: A reading rounds to its grid, so a joint is up to half a step past its limit before it reads
#: past it, and the soft-limit guard reads the joint's depth in its band from the same reading.
#: At a tenth of the guard's narrowest band (``GUARD_BAND_MIN`` of
#: ``handctl/online/recipes/loader.py``, 0.02 rad) that band is ten readings deep, a spring and
#: not the cliff a narrower band is, and a joint is at most 1 mrad past its limit unseen, a
#: tenth of the margin the simulated hand starts its joints inside their limits by. A DBC of
#: 1 rad steps passed check, and a run logged a joint 0.3 rad past its limit as on it.
MAX_ANGLE_RESOLUTION_RAD = 0.002


def check_wire_limits(hand: HandConfig, protocol: Protocol) -> None:
    """Raise a ``ConfigError`` naming the limit, the signal and both ranges for the first limit
    of ``hand`` that the signals of ``protocol`` cannot carry."""
    dbc = Path(protocol.source).name
    for i, finger in enumerate(hand.fingers):
        command, feedback = _layouts(hand, protocol, i, finger)
        per_node = len(command.signals)
        if len(finger.joints) > per_node or len(feedback.signals) < 2 * per_node:
            raise ConfigError(
                hand.source,
                f"fingers[{i}].joints",
                f"at most {per_node} joints ({command.name} and {feedback.name} "
                f"in {dbc} carry {per_node})",
                f"{len(finger.joints)} joints",
            )
        for k, joint in enumerate(finger.joints):
            _check_zero(protocol, command.name, command.signals[k])
            check = _JointCheck(hand, f"fingers[{i}].joints[{k}]", joint)
            check.torque_limits(command.name, command.signals[k])
            check.reading(feedback.name, feedback.signals[k])
            _check_angle_resolution(protocol, feedback.name, feedback.signals[per_node + k], joint)
            check.angles(feedback.name, feedback.signals[per_node + k])
            check.rate(command.name, command.signals[k], hand.bus.loop_rate_hz)


def _check_zero(protocol: Protocol, message: str, signal: SignalSpec) -> None:
    raw_zero = -signal.offset / signal.scale
    if abs(raw_zero - round(raw_zero)) > 1e-9 * max(1.0, abs(raw_zero)):
        raise ConfigError(
            protocol.source,
            f"{message}.{signal.name}",
            "a factor and an offset that carry 0 N·m exactly (the offset a multiple of the "
            "factor): a stop sends zero torque, not the nearest value to it",
            f"factor {signal.scale:g}, offset {signal.offset:g}",
        )


def _check_angle_resolution(
    protocol: Protocol, message: str, signal: SignalSpec, joint: JointConfig
) -> None:
    # a DBC's property, not the joint's: named in the DBC, as the zero of the command signal
    if signal.scale > MAX_ANGLE_RESOLUTION_RAD * (1 + 1e-9):
        raise ConfigError(
            protocol.source,
            f"{message}.{signal.name}",
            f"a factor of at most {MAX_ANGLE_RESOLUTION_RAD:g} rad ({joint.name}'s angle): a "
            "coarser reading shows a joint past its soft limit as still on it",
            Description(f"factor {signal.scale:g}"),
        )


def _layouts(
    hand: HandConfig, protocol: Protocol, i: int, finger: FingerConfig
) -> tuple[Layout, Layout]:
    found = []
    for kind in ("TorqueCommand", "Feedback"):
        layout = protocol.by_name.get(f"{kind}_{finger.node_id}")
        if layout is None:
            raise ConfigError(
                hand.source,
                f"fingers[{i}].node_id",
                f"a node id with a {kind} message in {Path(protocol.source).name}",
                finger.node_id,
            )
        found.append(layout)
    return found[0], found[1]


def _span(lo: float, hi: float, unit: str) -> str:
    return f"{lo:g}..{hi:g} {unit}"


class _JointCheck:
    """The checks of one joint, sharing the names a message needs."""

    def __init__(self, hand: HandConfig, path: str, joint: JointConfig) -> None:
        self.hand = hand
        self.path = path
        self.joint = joint

    def fail(self, key: str, expected: str, found: float) -> NoReturn:
        raise ConfigError(self.hand.source, f"{self.path}.{key}", expected, found)

    def torque_limits(self, message: str, signal: SignalSpec) -> None:
        lo, hi = signal.carried_range()
        for key in ("tau_max", "device_tau_max"):
            limit: float = getattr(self.joint, key)
            if -limit < lo or limit > hi:
                self.fail(
                    key,
                    f"±{key} ({_span(-limit, limit, 'N·m')}) within what "
                    f"{message}.{signal.name} carries ({_span(lo, hi, 'N·m')})",
                    limit,
                )
        # Under one step every torque the supervisor may apply is on the grid's zero: the
        # joint could never be driven, though check, a run and a plan took it (a jog of the
        # same torque is refused). The same relative tolerance as ``rate``'s.
        resolution = abs(signal.scale)
        if self.joint.tau_max < resolution * (1 - 1e-9):
            self.fail(
                "tau_max",
                f"a tau_max >= {resolution:g} N·m, the resolution of {message}.{signal.name}: "
                "every torque below it reaches the joint as zero",
                self.joint.tau_max,
            )

    def reading(self, message: str, signal: SignalSpec) -> None:
        lo, hi = signal.carried_range()
        tdt = self.joint.tdt
        limit = self.joint.device_tau_max
        ends = sorted(((-limit - tdt.offset) / tdt.scale, (limit - tdt.offset) / tdt.scale))
        if ends[0] < lo or ends[1] > hi:
            self.fail(
                "device_tau_max",
                f"±device_tau_max to read as TDT values "
                f"({_span(ends[0], ends[1], 'N·m')} through tdt scale {tdt.scale:g} and "
                f"offset {tdt.offset:g}) within what {message}.{signal.name} carries "
                f"({_span(lo, hi, 'N·m')})",
                limit,
            )

    def angles(self, message: str, signal: SignalSpec) -> None:
        lo, hi = signal.carried_range()
        q_lo, q_hi = self.joint.angle_min, self.joint.angle_max
        inside = f"strictly inside what {message}.{signal.name} carries ({_span(lo, hi, 'rad')})"
        if q_lo <= lo:
            self.fail(
                "angle_min",
                f"angle limits ({_span(q_lo, q_hi, 'rad')}) {inside}, so a "
                "joint past its limit reads past it",
                q_lo,
            )
        if q_hi >= hi:
            self.fail(
                "angle_max",
                f"angle limits ({_span(q_lo, q_hi, 'rad')}) {inside}, so a "
                "joint past its limit reads past it",
                q_hi,
            )

    def rate(self, message: str, signal: SignalSpec, loop_rate_hz: float) -> None:
        lo, hi = signal.carried_range()
        step = self.joint.rate_limit / loop_rate_hz
        resolution = abs(signal.scale)
        # A relative tolerance for the division: 0.1 N·m/s at 1 kHz is one 0.0001 N·m step.
        if resolution * (1 - 1e-9) <= step <= hi - lo:
            return
        self.fail(
            "rate_limit",
            f"a rate_limit of {resolution * loop_rate_hz:g}.."
            f"{(hi - lo) * loop_rate_hz:g} N·m/s: at bus.loop_rate_hz {loop_rate_hz:g} Hz "
            f"one tick's step (here {step:.6g} N·m) must lie between the resolution and "
            f"the span of {message}.{signal.name} ({resolution:g}..{hi - lo:g} N·m)",
            self.joint.rate_limit,
        )
