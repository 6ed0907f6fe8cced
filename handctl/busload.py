"""Worst-case bus time of every frame and the load of a hand configuration at its loop rate.

Worst case means the largest number of stuff bits the frame can carry, because a budget that
holds only for friendly payloads fails on the robot when the torques take unlucky values.

Frame model (11-bit identifiers, as every handctl frame uses):

- Classic CAN, n <= 8 data bytes: ``8n + 47`` bits (SOF to the end of the 3-bit interframe space)
  plus at most ``floor((34 + 8n - 1) / 4)`` stuff bits over the 34 + 8n bits that are stuffed.
  A payload over 8 bytes cannot travel in one classic frame: it is counted as ceil(n/8) frames,
  to show what the traffic would take; handctl itself sends every message as one frame and
  does not split, so ``handctl check`` refuses a classic-CAN hand with such a message
  (``too_long_for_classic``).
- CAN-FD with bit-rate switching: the arbitration phase (SOF, id, RRS, IDE, FDF, res, BRS:
  17 bits, plus their worst-case 4 stuff bits) and the tail (CRC delimiter, ACK slot, ACK
  delimiter, 7-bit EOF, 3-bit IFS: 13 bits) run at the nominal rate; the data phase (ESI, 4-bit
  DLC, the payload padded to its DLC size, the dynamic stuff bits beyond those counted in the
  arbitration phase, the 4-bit stuff count, a 17-bit CRC (21 bits above 16 bytes) and its fixed
  stuff bits, one per 4 bits) at the data rate. Counting the CRC delimiter at the nominal rate
  and rounding stuff bits up keeps the figure an upper bound.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

from handctl.protocol import (
    FD_DLC_SIZES,
    Layout,
    Protocol,
    most_misses_before_watchdog,
    slowest_loop_rate_hz,
)
from handctl.schema import description

if TYPE_CHECKING:  # the hand config's protocol is generated with the DLC sizes below
    from handctl.config import BusConfig, HandConfig

#: A configuration whose worst-case load exceeds this fraction is refused.
MAX_LOAD = 0.5


def classic_frame_bits(n_bytes: int) -> int:
    """Worst-case bits of one classic base frame with ``n_bytes`` (0..8) of data."""
    if not 0 <= n_bytes <= 8:
        raise ValueError(f"classic CAN carries 0 to 8 data bytes, found {n_bytes}")
    return 8 * n_bytes + 47 + (34 + 8 * n_bytes - 1) // 4


def fd_dlc_size(n_bytes: int) -> int:
    """The payload size a CAN-FD frame really carries: the next DLC size (padding included)."""
    for size in FD_DLC_SIZES:
        if size >= n_bytes:
            return size
    raise ValueError(f"CAN-FD carries at most 64 data bytes, found {n_bytes}")


def fd_frame_bits(n_bytes: int) -> tuple[int, int]:
    """Worst-case (nominal-rate bits, data-rate bits) of one CAN-FD base frame with BRS."""
    size = fd_dlc_size(n_bytes)
    arbitration = 17
    arbitration_stuff = (arbitration - 1) // 4
    tail = 13
    dynamic_bits = arbitration + 5 + 8 * size
    data_stuff = (dynamic_bits - 1) // 4 - arbitration_stuff
    crc_bits = 17 if size <= 16 else 21
    fixed_stuff = math.ceil((4 + crc_bits) / 4)
    data_phase = 5 + 8 * size + data_stuff + 4 + crc_bits + fixed_stuff
    return arbitration + arbitration_stuff + tail, data_phase


def frame_time_s(n_bytes: int, fd: bool, bitrate: int, data_bitrate: int | None) -> float:
    """Worst-case time on the wire of one message of ``n_bytes`` (all its frames on classic)."""
    if fd:
        nominal, data = fd_frame_bits(n_bytes)
        return nominal / bitrate + data / (data_bitrate or bitrate)
    frames = max(1, math.ceil(n_bytes / 8))
    remaining = n_bytes
    total = 0
    for _ in range(frames):
        chunk = min(8, remaining)
        total += classic_frame_bits(chunk)
        remaining -= chunk
    return total / bitrate


@dataclass(frozen=True)
class MessageBudget:
    name: str
    frame_id: int
    n_bytes: int
    frames: int  # frames per message on this bus (more than 1 only for classic splits)
    rate_hz: float  # 0 for event messages
    frame_time_us: float
    load: float  # fraction of the bus
    #: sent once a loop period (the host's TorqueCommand): what a slower loop makes less of.
    #: A node's Feedback is sent on its own 1 ms tick, at the loop's rate only at 1 kHz
    per_loop: bool = False


@dataclass(frozen=True)
class BusBudget:
    fd: bool
    bitrate: int
    data_bitrate: int | None
    loop_rate_hz: float
    messages: tuple[MessageBudget, ...]

    @property
    def load(self) -> float:
        return sum(m.load for m in self.messages)

    @property
    def ok(self) -> bool:
        return self.load <= MAX_LOAD

    @property
    def loop_time_per_tick_s(self) -> float:
        """Bus time of everything sent once per loop period."""
        return sum(m.frame_time_us for m in self.messages if m.per_loop) * 1e-6

    def highest_loop_rate_hz(self) -> float:
        """The loop rate at which this bus would sit exactly at ``MAX_LOAD``."""
        fixed = sum(m.load for m in self.messages if not m.per_loop)
        per_tick = self.loop_time_per_tick_s
        return max(0.0, (MAX_LOAD - fixed) / per_tick) if per_tick else math.inf


#: How the protocol has each node message sent (PROTOCOL.md), whatever a DBC's attributes
#: say: the host's command every loop tick, a node's Feedback on the node's own 1 ms tick,
#: its Status and Heartbeat every 100 ms; the rest (NodeCommand, EStop) on events. The
#: generated DBC writes these (``hand_protocol``).
PROTOCOL_SEND = {
    "TorqueCommand": "loop",
    "Feedback": "cyclic",
    "Status": "cyclic",
    "Heartbeat": "cyclic",
}
PROTOCOL_CYCLE_MS = {"TorqueCommand": 1, "Feedback": 1, "Status": 100, "Heartbeat": 100}


def _kind(layout: Layout) -> str:
    """The message's kind (``Feedback`` of ``Feedback_3``)."""
    return layout.name.rpartition("_")[0] if layout.node is not None else layout.name


def follows_loop(layout: Layout) -> bool:
    """Whether the message goes once a loop tick: the protocol's word, the DBC's for a
    message the protocol does not name."""
    return PROTOCOL_SEND.get(_kind(layout), layout.send) == "loop"


def message_rate(layout: Layout, loop_rate_hz: float) -> float:
    """Frames per second of a message: loop messages follow the loop, cyclic ones the DBC,
    and never fewer than the protocol sends. The host sends its commands every tick and a
    node its reports at the protocol's rates whatever a DBC says, so a DBC that called the
    Feedback an event, or its cycle 1 s, had the budget count a hand at a fifth of its load
    and pass one over the limit (found by an outside audit); a DBC may count more, never
    less."""
    kind = _kind(layout)
    floor = 0.0
    if PROTOCOL_SEND.get(kind) == "loop":
        floor = loop_rate_hz
    elif kind in PROTOCOL_CYCLE_MS:
        floor = 1000.0 / PROTOCOL_CYCLE_MS[kind]
    said = 0.0
    if layout.send == "loop":
        said = loop_rate_hz
    elif layout.send == "cyclic" and layout.cycle_time_ms:
        said = 1000.0 / layout.cycle_time_ms
    return max(floor, said)


def hand_budget(
    hand: HandConfig,
    protocol: Protocol,
    *,
    nodes: set[int] | None = None,
    fd: bool | None = None,
    bitrate: int | None = None,
    data_bitrate: int | None = None,
) -> BusBudget:
    """The budget of the hand's messages (of ``nodes`` only, if given) on its bus or another.

    The overrides let ``handctl check`` say what *would* fit: CAN-FD, or a faster data phase.
    """
    use_fd = hand.bus.fd if fd is None else fd
    rate = hand.bus.bitrate if bitrate is None else bitrate
    data_rate = hand.bus.data_bitrate if data_bitrate is None else data_bitrate
    wanted = {f.node_id for f in hand.fingers} if nodes is None else nodes
    rows = []
    for layout in protocol.layouts:
        if layout.node is not None and layout.node not in wanted:
            continue
        t = frame_time_s(layout.length, use_fd, rate, data_rate)
        hz = message_rate(layout, hand.bus.loop_rate_hz)
        frames = 1 if use_fd else max(1, math.ceil(layout.length / 8))
        rows.append(
            MessageBudget(
                layout.name,
                layout.frame_id,
                layout.length,
                frames,
                hz,
                t * 1e6,
                t * hz,
                per_loop=follows_loop(layout),
            )
        )
    return BusBudget(use_fd, rate, data_rate, hand.bus.loop_rate_hz, tuple(rows))


#: Classic CAN carries at most this many data bytes in one frame.
CLASSIC_MAX_BYTES = 8
#: CAN-FD data-phase rates (bit/s) ``what_would_fit`` tries: common transceiver settings.
FD_DATA_BITRATES = (2_000_000, 4_000_000, 5_000_000, 8_000_000, 10_000_000)
#: CAN-FD arbitration rates (bit/s) it tries where no data phase is enough
FD_ARBITRATION_BITRATES = (250_000, 500_000, 1_000_000)


def too_long_for_classic(hand: HandConfig, protocol: Protocol) -> list[str]:
    """The hand's messages (``Name (n bytes)``) that one classic CAN frame cannot carry."""
    nodes = {f.node_id for f in hand.fingers}
    return [
        f"{layout.name} ({layout.length} bytes)"
        for layout in protocol.layouts
        if layout.length > CLASSIC_MAX_BYTES and (layout.node is None or layout.node in nodes)
    ]


def bus_refusals(
    hand: HandConfig, protocol: Protocol, budget: BusBudget
) -> list[tuple[str, str, object]]:
    """Why the hand's bus cannot carry it, as ``(key, expected, found)`` of its config: frames
    too long for classic CAN, a worst-case load over ``MAX_LOAD`` (``budget``, the hand's)
    with what would fit. ``handctl check`` prints each, and ``handctl run`` refuses the hand
    on the first: one reading of the bus for both."""
    out: list[tuple[str, str, object]] = []
    too_long = [] if hand.bus.fd else too_long_for_classic(hand, protocol)
    if too_long:
        expected = (
            f"true (CAN-FD): {', '.join(too_long)} {'is' if len(too_long) == 1 else 'are'} "
            "longer than the 8 bytes of a classic CAN frame, and handctl sends every message "
            "in one frame (no hand fits classic CAN: Status_n is 12 bytes for any joints)"
        )
        out.append(("bus.fd", expected, description("false")))  # as YAML writes it
    if not budget.ok:
        # what would fit goes with what is expected: a found value is cut to one short line
        # in a message, and the hint was cut off there
        fits = "; ".join(what_would_fit(hand, protocol))
        found = f"{budget.load * 100:.1f} % at {hand.bus.loop_rate_hz:g} Hz"
        out.append(("bus", f"a worst-case load <= {MAX_LOAD * 100:.0f} % ({fits})", found))
    return out


def what_would_fit(hand: HandConfig, protocol: Protocol) -> list[str]:
    """What would bring an over-budget hand within ``MAX_LOAD``, each with its figure.

    On CAN-FD: the highest loop rate on this bus and the lowest data-phase rate that fits. On
    classic CAN only CAN-FD at 1 Mbit/s, with the slowest data phase that fits: the Feedback
    and Status frames are longer than a classic frame (``too_long_for_classic``), so no rate
    of a classic bus would carry them. Not the fingers shared out over several buses: a hand
    config has one bus and a run drives one hand, so that hint named a hand handctl could not
    run.
    """
    if not hand.bus.fd:
        # CAN-FD at 1 Mbit/s, with the slowest data phase from 5 Mbit/s on that fits: a hand
        # that needs 8 was told that 1/5 "would carry 53.2 %", over the limit itself, and
        # never what would fit (found by an outside audit)
        tried = [r for r in FD_DATA_BITRATES if r >= 5_000_000]
        for rate in tried:
            fd = hand_budget(hand, protocol, fd=True, bitrate=1_000_000, data_bitrate=rate)
            if fd.ok:
                return [f"CAN-FD 1/{rate / 1e6:g} Mbit/s would carry {fd.load * 100:.1f} %"]
        return [
            f"not even CAN-FD 1/{tried[-1] / 1e6:g} Mbit/s would carry it "
            f"({fd.load * 100:.1f} %): fewer joints on this bus, or a slower loop on CAN-FD"
        ]
    budget = hand_budget(hand, protocol)
    highest = budget.highest_loop_rate_hz()
    # whole hertz down: rounded to the nearest, a hint of 1641 Hz for 1640.9 was refused
    rate_hint = (
        f"the highest loop rate that fits is {math.floor(highest)} Hz"
        if highest < math.inf
        else "any loop rate fits"
    )
    most = most_misses_before_watchdog(math.floor(highest)) if highest < math.inf else 0
    if highest < math.inf and most < hand.safety.max_consecutive_misses:
        # the hint must lead to a config check takes: a slower loop allows fewer misses
        rate_hint += f" (with safety.max_consecutive_misses at most {most})"
    hints = (
        [rate_hint]
        if highest >= slowest_loop_rate_hz()
        # a slower loop would let the nodes' command watchdog trip between two ticks
        else [f"no loop rate of {slowest_loop_rate_hz():.0f} Hz or more fits on one bus"]
    )
    for rate in FD_DATA_BITRATES:
        if rate > (hand.bus.data_bitrate or 0):
            fd = hand_budget(hand, protocol, data_bitrate=rate)
            if fd.ok:
                hints.append(
                    f"a data phase of {rate / 1e6:g} Mbit/s would carry {fd.load * 100:.1f} %"
                )
                return hints
    # a slow arbitration phase (125 kbit/s) is more than any data phase can make up for: the
    # hint was then a loop rate the watchdog refuses, and nothing else
    for nominal in FD_ARBITRATION_BITRATES:
        if nominal > hand.bus.bitrate:
            for rate in FD_DATA_BITRATES:
                if rate >= max(nominal, hand.bus.data_bitrate or 0):
                    fd = hand_budget(hand, protocol, bitrate=nominal, data_bitrate=rate)
                    if fd.ok:
                        hints.append(
                            f"an arbitration phase of {nominal / 1e6:g} Mbit/s and a data "
                            f"phase of {rate / 1e6:g} Mbit/s would carry {fd.load * 100:.1f} %"
                        )
                        return hints
    return hints


def shortest_frame_time_s(fd: bool, bitrate: int, data_bitrate: int | None) -> float:
    """The least time any frame can take on the bus: no data and not one stuff bit.

    A bus cannot carry more frames than this allows, whoever sends them; it is the bound the
    host holds its drain to (``frames_per_period``). Classic: the 47 bits of an empty base
    frame. CAN-FD with bit-rate switching: the 30 arbitration and tail bits at the nominal
    rate, and at the data rate ESI and DLC (5), the stuff count (4), a 17-bit CRC and its 6
    fixed stuff bits.
    """
    if not fd:
        return 47 / bitrate
    data_bits = 5 + 4 + 17 + math.ceil((4 + 17) / 4)
    return 30 / bitrate + data_bits / (data_bitrate or bitrate)


def frames_per_period(bus: BusConfig) -> int:
    """The most frames the hand's bus can carry in one loop period (27 on 1 Mbit/s CAN-FD
    with a 5 Mbit/s data phase at 1 kHz, 21 on classic CAN at 1 Mbit/s)."""
    shortest = shortest_frame_time_s(bus.fd, bus.bitrate, bus.data_bitrate)
    return max(1, math.floor(bus.period_s / shortest + 1e-9))
