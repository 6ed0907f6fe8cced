"""The hand configuration: YAML in, frozen dataclasses out, or a ``ConfigError`` that says where.

The hand config is the only source of hardware limits in handctl. ``tau_max`` has no default on
purpose: a forgotten limit must stop the program, not fall back to a number someone guessed.
The ``sim`` section is kept as raw data here and validated by the simulated hand, because the
online plane never needs it; it is also left out of ``config_hash``, so a recipe compiled for a
hand stays valid whatever the simulation parameters are.
"""

from __future__ import annotations

import copy
import hashlib
import json
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from types import MappingProxyType
from typing import Any

from handctl.convention import PART_NAME, PART_NAME_RULE
from handctl.hand_protocol import (
    ESTOP_ID,
    MAX_JOINTS,
    NODE_IDS,
    check_protocol,
    frame_ids,
    protocol_for,
)
from handctl.protocol import (
    COMMAND_WATCHDOG_S,
    FEEDBACK_PERIOD_S,
    HEARTBEAT_PERIOD_S,
    MIN_LOOP_RATE_HZ,
    NODE_TIMING_MARGIN_S,
    Protocol,
    most_misses_before_watchdog,
    slowest_loop_rate_hz,
)
from handctl.schema import Doc, description, load_yaml
from handctl.wirelimits import check_wire_limits

#: Highest standard (11-bit) CAN identifier; handctl uses only standard ids.
MAX_STANDARD_ID = 0x7FF
#: m, the shortest link: a shorter one is a point, not a link (MuJoCo refuses a link of
#: 1e-12 m as "fromto points too close", and the estimator's cage has no side there)
MIN_LINK_LENGTH = 0.001
CAN_ID_KINDS = ("node_command", "torque_command", "feedback", "status", "heartbeat")
_CHANNEL = "a channel name (e.g. can0) or a channel number >= 0"


@dataclass(frozen=True)
class TdtCalibration:
    """Maps the TDT reading on the wire to joint torque: tau = scale * reading + offset (N·m)."""

    scale: float
    offset: float


@dataclass(frozen=True)
class JointConfig:
    name: str
    link_length: float  # m
    tau_max: float  # N·m, host limit; what safety lets through
    device_tau_max: float  # N·m, the node's own saturation
    rate_limit: float  # N·m/s
    angle_min: float  # rad, soft limit
    angle_max: float  # rad, soft limit
    tdt: TdtCalibration
    # m, half the link's thickness in the hand plane: a grasped object's surface lies this far
    # from the line through the joint axes (0: the paper's ideal line links). The object
    # estimator needs it to place an enveloped object from the joint angles alone.
    half_thickness: float = 0.0
    #: whether the config wrote ``half_thickness`` (a written 0 is a claim about the link the
    #: simulation must agree with; a left-out one is not): the value alone cannot tell them
    #: apart. Not compared: how a value was written does not make another hand.
    half_thickness_given: bool = field(default=False, compare=False)


@dataclass(frozen=True)
class CanIds:
    node_command: int
    torque_command: int
    feedback: int
    status: int
    heartbeat: int

    def as_dict(self) -> dict[str, int]:
        return {kind: getattr(self, kind) for kind in CAN_ID_KINDS}


@dataclass(frozen=True)
class FingerConfig:
    name: str
    node_id: int
    can_ids: CanIds
    base_x: float  # m
    base_y: float  # m
    base_angle: float  # rad
    z: float  # m, offset along the joint axes
    joints: tuple[JointConfig, ...]


@dataclass(frozen=True)
class BusConfig:
    interface: str
    channel: str
    fd: bool
    bitrate: int  # bit/s, arbitration phase (the only phase on classic CAN)
    data_bitrate: int | None  # bit/s, CAN-FD data phase
    loop_rate_hz: float

    @property
    def period_s(self) -> float:
        return 1.0 / self.loop_rate_hz


@dataclass(frozen=True)
class SafetyConfig:
    """Host-side watchdog settings. Defaults are sane for the Hiroshima-Hand at 1 kHz; the
    torque limits themselves live per joint and have no default."""

    feedback_timeout_s: float = 0.005  # no valid feedback for this long is a fault
    heartbeat_timeout_s: float = 0.35  # heartbeats come every 0.1 s
    tdt_tolerance: float = 0.02  # N·m, plus the relative part below
    tdt_tolerance_rel: float = 0.15  # of |expected torque|
    tdt_window_s: float = 0.05  # the mismatch must hold this long
    tdt_lag_s: float = 0.01  # first-order lag between command and TDT reading
    tdt_stuck_window_s: float = 0.1
    tdt_stuck_min_change: float = 0.02  # N·m the command must move for "stuck" to mean anything
    # A live TDT reading is never bit-identical this long (sensor noise spans several ADC
    # steps), whatever the command does; 0 turns the check off for a noiseless sensor.
    tdt_stuck_still_s: float = 0.5
    enable_timeout_s: float = 0.1  # nodes must report ENABLED this soon after enable
    max_consecutive_misses: int = 3
    max_consecutive_send_failures: int = 3
    # More rejected frames of one node than this within the window is a fault: a healthy bus
    # rejects none, a lost frame costs one, a reboot one per message.
    reject_window_s: float = 0.1
    max_rejects_in_window: int = 10


@dataclass(frozen=True)
class HandConfig:
    name: str
    source: str
    bus: BusConfig
    fingers: tuple[FingerConfig, ...]
    #: of the config as read (whole numbers of real-valued keys as reals): ``rate_limit: 20``
    #: and ``20.0`` are one hand; spelled differently, every recipe compiled for one refused
    #: the other as "another hand config"
    config_hash: str
    safety: SafetyConfig = field(default_factory=SafetyConfig)
    sim: Mapping[str, Any] = field(default_factory=lambda: MappingProxyType({}))
    #: The DBC file given for this hand (``--dbc``), or None: its protocol is the one generated
    #: from its fingers (``handctl.hand_protocol.protocol_for`` decides, for every command).
    dbc: str | None = None
    #: the hash of the config as written, which recipes compiled before ``config_hash`` was
    #: taken as read carry (``config_hash`` itself for a config that wrote its reals as reals)
    legacy_hash: str = ""

    def answers_to(self, digest: str | None) -> bool:
        """Whether a recipe's ``hand_config_hash`` is this hand's, either way it was taken."""
        return digest is not None and digest in (self.config_hash, self.legacy_hash)

    @property
    def joints(self) -> tuple[JointConfig, ...]:
        """All joints, finger by finger: the order of every 9-vector in handctl."""
        return tuple(j for f in self.fingers for j in f.joints)

    @property
    def joint_names(self) -> tuple[str, ...]:
        return tuple(j.name for j in self.joints)

    @property
    def n_joints(self) -> int:
        return sum(len(f.joints) for f in self.fingers)


def load_hand(path: str | Path, dbc: str | Path | None = None) -> HandConfig:
    """Load and validate a hand config file; raises ``ConfigError`` on any problem.

    Its fingers and limits are checked against its protocol: the DBC file ``dbc`` (``--dbc``),
    which the hand then keeps, or the one generated from its fingers. A node the DBC has no
    frames for, another joint count, or a limit the wire cannot carry is refused here, not
    discovered mid-run.
    """
    return parse_hand(load_yaml(path, "hand config"), dbc=None if dbc is None else str(dbc))


def _config_hash(data: Mapping[str, Any]) -> str:
    """``sha256:`` and 16 hex digits of everything but the ``sim`` section, key order aside."""
    hashed = {k: v for k, v in data.items() if k != "sim"}
    text = json.dumps(hashed, sort_keys=True, separators=(",", ":"))
    return f"sha256:{hashlib.sha256(text.encode()).hexdigest()[:16]}"


def parse_hand(doc: Doc, protocol: Protocol | None = None, dbc: str | None = None) -> HandConfig:
    """The hand config in ``doc``, checked against ``protocol`` if given (a recording's), else
    against the protocol of the hand and ``dbc`` (``protocol_for``)."""
    # as written, before reading turns the whole numbers of real-valued keys into reals: the
    # hash recipes compiled before that was done carry (``legacy_hash``). Hashed once the
    # config is known good: a key that is no string fails the hash's sort, not the reading.
    as_written = copy.deepcopy(dict(doc.data))
    # a recording's hand is read as it ran; a hand to run takes a loop the rules allow now
    name = doc.label("name", as_recorded=protocol is not None)
    bus = _parse_bus(
        doc.mapping("bus"), MIN_LOOP_RATE_HZ if protocol is not None else slowest_loop_rate_hz()
    )
    finger_docs = doc.mappings("fingers", min_len=1, max_len=len(NODE_IDS))
    fingers = tuple(_parse_finger(f) for f in finger_docs)
    safety = _parse_safety(doc.mapping("safety", default={}), bus.loop_rate_hz)
    sim_raw = doc.raw("sim", None)
    if doc.has("sim") and protocol is None and (sim_raw is None or sim_raw == {}):
        # read as no section at all, then a run on the simulated hand said "the key is
        # missing" of a key that is there; a recording's hand is read as it ran
        doc.fail(
            "sim",
            "the simulated hand's section, a mapping of its keys (docs/simulation.md), or no "
            "sim key at all for a hand that is never simulated",
            description("an empty section" if sim_raw == {} else "an empty section (null)"),
        )
    if sim_raw is not None and not isinstance(sim_raw, dict):
        doc.fail("sim", "a mapping", description(type(sim_raw).__name__))
    doc.done()
    _check_unique(doc, fingers)
    if protocol is None:
        # a recording's hand (protocol given) is read as it ran, whatever the rules now
        _check_names(doc, fingers)
    hand = HandConfig(
        name=name,
        source=doc.file,
        bus=bus,
        fingers=fingers,
        config_hash=_config_hash(doc.data),
        legacy_hash=_config_hash(as_written),
        safety=safety,
        sim=MappingProxyType(dict(sim_raw or {})),
        dbc=dbc,
    )
    if protocol is None:
        protocol = protocol_for(hand)
        # a recording's hand (protocol given) is read as it ran, whatever the rules now
        _check_misses_before_watchdog(doc, hand)
        check_wire_limits(hand, protocol)
        _check_tdt_tolerance(doc, hand)  # against limits the wire carries
        _check_checks_can_fire(doc, hand)
    else:
        check_protocol(hand, protocol)
        check_wire_limits(hand, protocol)
    return hand


def _too_slow() -> str:
    """What a loop rate below the slowest one allowed is told."""
    return (
        f"at least {slowest_loop_rate_hz():g} Hz: two periods, a tick and a late one, "
        f"within the nodes' {COMMAND_WATCHDOG_S * 1e3:g} ms command watchdog with "
        f"{NODE_TIMING_MARGIN_S * 1e3:g} ms to spare for the bus and the node's tick"
    )


def _check_tdt_tolerance(doc: Doc, hand: HandConfig) -> None:
    """The TDT cross-check must be able to see a sensor that reads a joint's whole torque
    wrong. Its absolute part is one figure for every joint, chosen for joints of tenths of a
    N·m: on a hand of joints of a thousandth, its default 0.02 N·m let a TDT read twenty
    times the most the joint's drive can give, without a fault."""
    tolerance = hand.safety.tdt_tolerance
    weakest = min(hand.joints, key=lambda j: j.tau_max)
    if tolerance >= weakest.tau_max / 2:
        written = doc.mapping("safety", default={}).has("tdt_tolerance")
        doc.fail(
            "safety.tdt_tolerance",
            f"less than half of every joint's tau_max ({weakest.name}: {weakest.tau_max:g} "
            f"N·m, so below {weakest.tau_max / 2:g} N·m): the TDT cross-check must see a "
            "sensor that reads a joint's whole torque wrong",
            description(f"{tolerance:g} N·m" + ("" if written else " (the default)")),
        )


#: s: the longest a host may go on commanding torque without a node's feedback (100 ticks at
#: 1 kHz). Up to 1 s was accepted: a thousand ticks of torque sent blind.
MAX_FEEDBACK_TIMEOUT_S = 0.1
#: of |expected torque|: the TDT cross-check's relative part, at most half. With 1 or more a
#: sensor reading 0 while the joint was commanded any torque was never a mismatch (a slack
#: tendon went unseen and the run exited 0); at a half, with the absolute part under half of
#: tau_max (``_check_tdt_tolerance``), a reading of 0 at tau_max is still one.
MAX_TDT_TOLERANCE_REL = 0.5
#: s: the longest a watchdog's window may be, the TDT cross-check's and the stuck-sensor's
#: (a mismatch or a still reading must last it to be a fault). 10 s was accepted: a slack
#: tendon ran nine seconds unseen and the run stopped only on a joint's soft limit.
MAX_WATCHDOG_WINDOW_S = 0.5
#: s: the longest the host may go without a node's heartbeat (ten of its periods)
MAX_HEARTBEAT_TIMEOUT_S = 1.0


def _check_checks_can_fire(doc: Doc, hand: HandConfig) -> None:
    """A safety setting that switches its own check off is refused: each watchdog of the
    ``safety:`` section must be able to fire on a hand of these limits. (Not for a recording's
    hand, read as it ran.)"""
    safety = hand.safety
    weakest = min(hand.joints, key=lambda j: j.tau_max)
    if safety.tdt_tolerance_rel > MAX_TDT_TOLERANCE_REL:
        doc.fail(
            "safety.tdt_tolerance_rel",
            f"at most {MAX_TDT_TOLERANCE_REL:g} (of the expected torque): the TDT cross-check "
            "must see a sensor that reads 0 while its joint is commanded tau_max",
            description(f"{safety.tdt_tolerance_rel:g}"),
        )
    # written only: the default (0.02 N·m) is a figure for joints of tenths of a N·m, and a
    # hand of smaller ones that does not set it was accepted before this check
    written = doc.mapping("safety", default={}).has("tdt_stuck_min_change")
    if written and safety.tdt_stuck_min_change >= 2 * weakest.tau_max:
        doc.fail(
            "safety.tdt_stuck_min_change",
            f"less than twice every joint's tau_max ({weakest.name}: {weakest.tau_max:g} N·m, "
            f"so below {2 * weakest.tau_max:g} N·m, the most its command can move): a command "
            "that must move further never makes a stuck sensor a fault",
            description(f"{safety.tdt_stuck_min_change:g} N·m"),
        )
    if safety.feedback_timeout_s > MAX_FEEDBACK_TIMEOUT_S:
        doc.fail(
            "safety.feedback_timeout_s",
            f"at most {MAX_FEEDBACK_TIMEOUT_S:g} s: the host must not command torque for longer "
            "without hearing the joint",
            description(f"{safety.feedback_timeout_s:g} s"),
        )
    windows = (
        ("tdt_window_s", safety.tdt_window_s, MAX_WATCHDOG_WINDOW_S),
        ("tdt_stuck_window_s", safety.tdt_stuck_window_s, MAX_WATCHDOG_WINDOW_S),
        ("heartbeat_timeout_s", safety.heartbeat_timeout_s, MAX_HEARTBEAT_TIMEOUT_S),
    )
    for key, value, most in windows:
        if value > most:
            doc.fail(
                f"safety.{key}",
                f"at most {most:g} s: longer, the watchdog sees a fault only once the hand has "
                "lived with it that long (a slack tendon ran nine seconds unseen at 10 s)",
                description(f"{value:g} s"),
            )
    ticks = round(safety.reject_window_s * hand.bus.loop_rate_hz)
    if safety.max_rejects_in_window >= max(ticks, 1):
        doc.fail(
            "safety.max_rejects_in_window",
            f"fewer than the {max(ticks, 1)} ticks of reject_window_s "
            f"({safety.reject_window_s:g} s at {hand.bus.loop_rate_hz:g} Hz): more would let a "
            "node whose every frame is rejected run on without a REJECT_RATE stop",
            description(f"{safety.max_rejects_in_window}"),
        )


def _check_misses_before_watchdog(doc: Doc, hand: HandConfig) -> None:
    """The host's LOOP_OVERRUN stop must come before a node's command watchdog
    (``most_misses_before_watchdog``): otherwise the nodes stop the hand themselves, latch a
    TIMEOUT fault the next run must reset, and the host's summary says no tick was missed."""
    rate = hand.bus.loop_rate_hz
    most = most_misses_before_watchdog(rate)
    watchdog_ms = COMMAND_WATCHDOG_S * 1e3
    # (a loop too slow for one miss was refused when the bus section was read: ``_parse_bus``)
    misses = hand.safety.max_consecutive_misses
    if misses > most:
        doc.fail(
            "safety.max_consecutive_misses",
            f"at most {most} at a {rate:g} Hz loop: the host must stop on missed ticks before "
            f"a node's {watchdog_ms:g} ms command watchdog trips ({misses + 1} periods of "
            f"{1e3 / rate:.3g} ms, with {NODE_TIMING_MARGIN_S * 1e3:g} ms to spare for the bus "
            "and the node's tick)",
            misses,
        )
    # ticks whose command frames did not go leave the nodes without a command as missed ticks
    # do: the host's BUS_ERROR must come first (100 were taken, and the nodes latched TIMEOUT,
    # a fault the next run must reset, while the host said nothing of its bus)
    failures = hand.safety.max_consecutive_send_failures
    if failures > most:
        doc.fail(
            "safety.max_consecutive_send_failures",
            f"at most {most} at a {rate:g} Hz loop: the host must stop on commands that did "
            f"not go before a node's {watchdog_ms:g} ms command watchdog trips ({failures + 1} "
            f"periods of {1e3 / rate:.3g} ms, with {NODE_TIMING_MARGIN_S * 1e3:g} ms to spare "
            "for the bus and the node's tick)",
            failures,
        )


def _parse_safety(doc: Doc, loop_rate_hz: float) -> SafetyConfig:
    d = SafetyConfig()
    # the default stop on missed ticks comes before the nodes' watchdog at any loop rate the
    # bus section allows: a 250 Hz hand was refused for a 3 it never wrote
    # (``_check_misses_before_watchdog``); a value written is held to it as it is
    misses = most_misses_before_watchdog(loop_rate_hz)
    default_misses = (
        min(d.max_consecutive_misses, misses) if misses >= 1 else d.max_consecutive_misses
    )
    # the same for ticks whose command frames did not go (``_check_misses_before_watchdog``)
    default_failures = (
        min(d.max_consecutive_send_failures, misses)
        if misses >= 1
        else d.max_consecutive_send_failures
    )
    s = SafetyConfig(
        # longer than the nodes' feedback period and the bus's and their tick's jitter, or a
        # run stops on FEEDBACK_TIMEOUT from a frame 1.8 ms old on a host with no late tick
        feedback_timeout_s=doc.number(
            "feedback_timeout_s",
            default=d.feedback_timeout_s,
            min=FEEDBACK_PERIOD_S + NODE_TIMING_MARGIN_S,
            max=1.0,
            unit="s",
        ),
        # longer than the nodes' heartbeat period, or every run stops on HEARTBEAT_LOST
        # within a tenth of a second of a config that `handctl check` passed
        heartbeat_timeout_s=doc.number(
            "heartbeat_timeout_s",
            default=d.heartbeat_timeout_s,
            min=HEARTBEAT_PERIOD_S,
            min_exclusive=True,
            max=10.0,
            unit="s",
        ),
        tdt_tolerance=doc.number(
            "tdt_tolerance", default=d.tdt_tolerance, min=0.0, max=10.0, unit="N·m"
        ),
        tdt_tolerance_rel=doc.number(
            "tdt_tolerance_rel", default=d.tdt_tolerance_rel, min=0.0, max=10.0
        ),
        tdt_window_s=doc.number(
            "tdt_window_s", default=d.tdt_window_s, min=0.001, max=10.0, unit="s"
        ),
        tdt_lag_s=doc.number("tdt_lag_s", default=d.tdt_lag_s, min=0.0, max=1.0, unit="s"),
        tdt_stuck_window_s=doc.number(
            "tdt_stuck_window_s", default=d.tdt_stuck_window_s, min=0.005, max=10.0, unit="s"
        ),
        tdt_stuck_min_change=doc.number(
            "tdt_stuck_min_change", default=d.tdt_stuck_min_change, min=0.0, max=10.0, unit="N·m"
        ),
        tdt_stuck_still_s=doc.number(
            "tdt_stuck_still_s", default=d.tdt_stuck_still_s, min=0.0, max=60.0, unit="s"
        ),
        enable_timeout_s=doc.number(
            "enable_timeout_s", default=d.enable_timeout_s, min=0.005, max=10.0, unit="s"
        ),
        max_consecutive_misses=doc.integer(
            "max_consecutive_misses", default=default_misses, min=1, max=100
        ),
        max_consecutive_send_failures=doc.integer(
            "max_consecutive_send_failures", default=default_failures, min=1, max=100
        ),
        reject_window_s=doc.number(
            "reject_window_s", default=d.reject_window_s, min=0.001, max=10.0, unit="s"
        ),
        max_rejects_in_window=doc.integer(
            "max_rejects_in_window", default=d.max_rejects_in_window, min=0, max=100_000
        ),
    )
    still = s.tdt_stuck_still_s
    if 0.0 < still < MIN_TDT_STUCK_STILL_S:
        doc.fail(
            "tdt_stuck_still_s",
            f"0 (off) or at least {MIN_TDT_STUCK_STILL_S:g} s: a live sensor's reading stays on "
            "one step for a few of its 1 ms samples by chance, and at 0.001 s every run "
            "stopped on TDT_STUCK in its third tick",
            still,
        )
    doc.done()
    return s


#: s, the shortest ``tdt_stuck_still_s`` but 0: a sensor whose noise is half its step (what the
#: simulated hand requires) stays on one step a sample with a chance of 0.68, so for 100
#: samples in a row with one of 2e-17, which the 10^5 windows of a run of nine joints never
#: meet (50 samples: one run in a few thousand)
MIN_TDT_STUCK_STILL_S = 0.1


def _parse_bus(doc: Doc, min_loop_rate_hz: float) -> BusConfig:
    interface = doc.string("interface")
    # A name (``can0``) or, for interfaces that number their channels, a number (``0``): never
    # a list, a mapping, a boolean or null, which str() would turn into a channel called
    # "[1, 2]", "True" or "None".
    raw_channel = doc.raw("channel")
    if (
        isinstance(raw_channel, bool)
        or not isinstance(raw_channel, (str, int))
        or (isinstance(raw_channel, int) and raw_channel < 0)
        or not str(raw_channel).strip()
    ):
        doc.fail("channel", _CHANNEL, raw_channel)
    channel = str(raw_channel)
    fd = doc.boolean("fd")
    bitrate = doc.integer("bitrate", min=10_000, max=1_000_000)
    data_bitrate: int | None = None
    if fd:
        data_bitrate = doc.integer("data_bitrate", min=bitrate, max=10_000_000)
    elif doc.has("data_bitrate"):
        doc.fail(
            "data_bitrate", "no data_bitrate on classic CAN (fd: false)", doc.raw("data_bitrate")
        )
    # a tick at most half the nodes' command watchdog: at 100 Hz or below every run stopped
    # on the nodes' TIMEOUT at its second tick, a config `handctl check` had passed
    # (``min_loop_rate_hz``: the slowest the nodes' watchdog allows a missed tick at, said
    # with why for a number below it, and as the bound for a value that is no number)
    raw_rate = doc.raw("loop_rate_hz", None)
    if (
        isinstance(raw_rate, (int, float))
        and not isinstance(raw_rate, bool)
        and raw_rate < min_loop_rate_hz
        and min_loop_rate_hz > MIN_LOOP_RATE_HZ
    ):
        doc.fail("loop_rate_hz", _too_slow(), raw_rate)
    loop_rate = doc.number("loop_rate_hz", min=min_loop_rate_hz, max=10_000.0, unit="Hz")
    doc.done()
    return BusConfig(interface, channel, fd, bitrate, data_bitrate, loop_rate)


def _parse_finger(doc: Doc) -> FingerConfig:
    name = doc.string("name")
    node_id = doc.integer("node_id", min=NODE_IDS.start, max=NODE_IDS.stop - 1)
    # The ids follow from the node id (PROTOCOL.md); ids written here are checked against the
    # protocol's (``check_protocol``), for a DBC given with --dbc that numbers them otherwise.
    derived = frame_ids(node_id)
    ids_doc = doc.mapping("can_ids", default={})
    ids = CanIds(
        **{
            kind: ids_doc.integer(kind, default=derived[kind], min=1, max=MAX_STANDARD_ID)
            for kind in CAN_ID_KINDS
        }
    )
    ids_doc.done()
    base = doc.mapping("base")
    base_x = base.number("x", min=-1.0, max=1.0, unit="m")
    base_y = base.number("y", min=-1.0, max=1.0, unit="m")
    base_angle = base.number("angle", min=-2 * math.pi, max=2 * math.pi, unit="rad")
    base.done()
    z = doc.number("z", default=0.0, min=-1.0, max=1.0, unit="m")
    joints = tuple(_parse_joint(j) for j in doc.mappings("joints", min_len=1, max_len=MAX_JOINTS))
    doc.done()
    return FingerConfig(name, node_id, ids, base_x, base_y, base_angle, z, joints)


#: every key a joint of a hand config may have: declared, so that a missing one is not
#: taken for a misspelling of another still to be read (a joint without ``tau_max`` was
#: told ``device_tau_max`` was "here instead")
JOINT_KEYS = (
    "name",
    "link_length",
    "tau_max",
    "device_tau_max",
    "rate_limit",
    "angle_min",
    "angle_max",
    "tdt",
    "half_thickness",
)


def _parse_joint(doc: Doc) -> JointConfig:
    doc.expect(JOINT_KEYS)
    name = doc.string("name")
    link = doc.number("link_length", min=MIN_LINK_LENGTH, max=1.0, unit="m")
    tau_max = doc.number("tau_max", min=0.0, max=100.0, min_exclusive=True, unit="N·m")
    device = doc.number("device_tau_max", min=0.0, max=100.0, min_exclusive=True, unit="N·m")
    if tau_max > device:
        doc.fail("tau_max", f"a value <= device_tau_max ({device:g} N·m)", tau_max)
    rate = doc.number("rate_limit", min=0.0, max=1e5, min_exclusive=True, unit="N·m/s")
    lo = doc.number("angle_min", min=-2 * math.pi, max=2 * math.pi, unit="rad")
    hi = doc.number("angle_max", min=-2 * math.pi, max=2 * math.pi, unit="rad")
    if hi <= lo:
        doc.fail("angle_max", f"a value > angle_min ({lo:g} rad)", hi)
    tdt_doc = doc.mapping("tdt")
    scale = tdt_doc.number("scale", min=0.1, max=10.0)
    offset = tdt_doc.number("offset", min=-10.0, max=10.0, unit="N·m")
    tdt_doc.done()
    given = doc.has("half_thickness")
    half_thickness = doc.number("half_thickness", default=0.0, min=0.0, max=0.1, unit="m")
    doc.done()
    return JointConfig(
        name,
        link,
        tau_max,
        device,
        rate,
        lo,
        hi,
        TdtCalibration(scale, offset),
        half_thickness,
        half_thickness_given=given,
    )


#: keys a log's per-tick joint message (``/hand/joints``) has beside the joints' names
RESERVED_JOINT_NAMES = ("tick",)
#: The scene's own parts, each with what it is: the simulated hand's model names its bodies
#: by them (``world`` is MuJoCo's own), and a log's Foxglove frame tree is rooted at
#: ``world`` (``handctl/foxglove/scene.py``). Each finger's base adds ``<finger>_base``.
SCENE_NAMES = {
    "world": "the scene's root frame",
    "palm": "the scene's palm",
    "table": "the scene's table",
}


def scene_names(fingers: Sequence[FingerConfig]) -> dict[str, str]:
    """Every name the scene takes for itself, with what has it: ``SCENE_NAMES`` and each
    finger's ``<finger>_base``. A joint's frame and its simulated body carry the joint's
    name, so a joint named like one of these is two things under one name: a model that
    does not build, or a frame tree with a cycle (a joint ``world``) or a frame with two
    parents (a joint ``<finger>_base``), in every log of the hand, simulated or not."""
    taken = {f"{f.name}_base": f"the base of {f.name}" for f in fingers}
    taken |= SCENE_NAMES
    return taken


def _check_unique(doc: Doc, fingers: tuple[FingerConfig, ...]) -> None:
    """Names, node ids and CAN ids must be unique: a clash would route frames to the wrong node."""
    seen_names: dict[str, str] = {}
    seen_nodes: dict[int, int] = {}
    seen_ids: dict[int, str] = {ESTOP_ID: "the e-stop frame"}
    owners: dict[int, int] = {}  # CAN id -> the finger index that has it
    for i, finger in enumerate(fingers):
        where = f"fingers[{i}]"
        for name, path in [(finger.name, f"{where}.name")] + [
            (j.name, f"{where}.joints[{k}].name") for k, j in enumerate(finger.joints)
        ]:
            if name in seen_names:
                _fail_at(doc, path, f"a name not used before (also {seen_names[name]})", name)
            seen_names[name] = path
        if finger.node_id in seen_nodes:
            _fail_at(
                doc,
                f"{where}.node_id",
                f"a node id not used before (fingers[{seen_nodes[finger.node_id]}] has it)",
                finger.node_id,
            )
        seen_nodes[finger.node_id] = i
        for kind, can_id in finger.can_ids.as_dict().items():
            if can_id in seen_ids:
                _fail_at(
                    doc,
                    f"{where}.can_ids.{kind}",
                    f"a CAN id not used before ({seen_ids[can_id]} has it"
                    f"{_whose_id(fingers, owners.get(can_id), can_id)})",
                    description(f"0x{can_id:03X}"),  # written as the config writes ids
                )
            seen_ids[can_id] = f"{where}.can_ids.{kind}"
            owners[can_id] = i


def _whose_id(fingers: tuple[FingerConfig, ...], owner: int | None, can_id: int) -> str:
    """Which node the id rule gives a clashing id, when it is not the earlier finger's own:
    the clash is then that finger's mistake, and the message blamed the later one only (a
    finger given the next node's ids)."""
    if owner is None:
        return ""
    node = fingers[owner].node_id
    if can_id in frame_ids(node).values():
        return ""
    rule = [n for n in NODE_IDS if can_id in frame_ids(n).values()]
    said = f"node {rule[0]}'s by the id rule" if rule else "no node's by the id rule"
    return f", where it is {said}, not its node {node}'s"


def _check_names(doc: Doc, fingers: tuple[FingerConfig, ...]) -> None:
    """Finger and joint names by ``PART_NAME``, as objects' are by ``OBJECT_NAME``: a joint
    a recipe condition cannot name cannot be waited on, and names are printed as they are.
    And no joint is named like the scene (``scene_names``): refused for the simulated hand
    alone, a hand without ``sim:`` recorded a frame tree that was no tree."""
    taken = scene_names(fingers)
    for i, finger in enumerate(fingers):
        if not PART_NAME.match(finger.name):
            _fail_at(
                doc,
                f"fingers[{i}].name",
                f"{PART_NAME_RULE} (e.g. index): the sim section names a finger by it, and "
                "check and nodes print it",
                finger.name,
            )
        for k, joint in enumerate(finger.joints):
            if not PART_NAME.match(joint.name):
                _fail_at(
                    doc,
                    f"fingers[{i}].joints[{k}].name",
                    f"{PART_NAME_RULE} (e.g. index_j1): recipe conditions name a joint by it "
                    "(angle.NAME, tdt.NAME)",
                    joint.name,
                )
            if joint.name in RESERVED_JOINT_NAMES:
                # a log's per-tick joint messages key each joint by its name beside these:
                # a joint named tick overwrote the tick number in every one of them
                _fail_at(
                    doc,
                    f"fingers[{i}].joints[{k}].name",
                    f"a name other than {', '.join(RESERVED_JOINT_NAMES)} (a log's joint "
                    "messages carry that key beside the joints' names)",
                    joint.name,
                )
            if joint.name in taken:
                _fail_at(
                    doc,
                    f"fingers[{i}].joints[{k}].name",
                    f"a name the scene does not take ({joint.name!r} is {taken[joint.name]}: "
                    "a log's frame tree, world -> <finger>_base -> <joint>, and the simulated "
                    "hand name the joint's frame and body by it)",
                    joint.name,
                )


def _fail_at(doc: Doc, path: str, expected: str, found: object) -> None:
    Doc({}, doc.file, "").fail(path, expected, found)
