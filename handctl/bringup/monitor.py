"""``handctl monitor``: the bus decoded, message by message, as it goes by.

Per message of the DBC that is heard: how many frames, their rate, the last values in units,
and what a receiver would reject (wrong length, bad CRC, repeated or skipped counter, in the
protocol's order); frames on ids the DBC does not have are counted by id, and the bus's
events (error frames, bus-off, frames it dropped as malformed) by kind. It reads a bus and
never sends, or reads the raw frames of an MCAP log (``handctl run recipe --log``), both
directions of the wire, at the speed the file can be read.

The view is data (``BusView``, ``snapshot``); the command turns it into a full-screen table on
a terminal or JSON lines on a pipe.
"""

from __future__ import annotations

import time
from collections import Counter
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from handctl.bringup.idcount import IdCounts
from handctl.errors import ConfigError
from handctl.online.bus import EXTENDED_ID_FLAG, BusEvent, HandBus
from handctl.online.drivers.finger import fault_names
from handctl.online.drivers.receiver import CounterCheck, Reject
from handctl.protocol import Layout, Protocol, node_state_name

if TYPE_CHECKING:
    from handctl.config import HandConfig
    from handctl.recording.reader import Recording


@dataclass
class MessageStats:
    layout: Layout
    frames: int = 0
    accepted: int = 0
    rejects: Counter[str] = field(default_factory=Counter)
    values: tuple[float, ...] | None = None  # the last accepted frame's
    last_ns: int | None = None
    counters: CounterCheck = field(default_factory=CounterCheck)
    frames_at_snapshot: int = 0


class BusView:
    """What the frames seen so far say, per message id. Fed one frame at a time."""

    def __init__(self, protocol: Protocol) -> None:
        self.protocol = protocol
        self.messages: dict[int, MessageStats] = {}
        self.unknown = IdCounts()
        self.frames = 0
        self.first_ns: int | None = None
        self.last_ns: int | None = None
        self._snapshot_ns: int | None = None
        #: Frames this listener lost before it read them, as far as its bus tells it (the unix
        #: bus does): a gap in a message's counters then may be the listener's, not the node's.
        self.frames_lost = 0
        #: What the bus said besides frames (``BusEvent``): error frames, bus-off, error-passive,
        #: frames it dropped as malformed (over 64 bytes, a malformed datagram), by kind, and
        #: the last detail of each. A flood of them carries no frame, and was shown as nothing.
        self.bus_events: Counter[str] = Counter()
        self.last_event: dict[str, str] = {}

    def observe(self, frame_id: int, data: bytes, t_ns: int) -> None:
        self.frames += 1
        if self.first_ns is None:
            self.first_ns = self._snapshot_ns = t_ns
        self.last_ns = t_ns
        layout = None if frame_id & EXTENDED_ID_FLAG else self.protocol.by_id.get(frame_id)
        if layout is None:
            self.unknown.add(frame_id)
            return
        stats = self.messages.get(frame_id)
        if stats is None:
            stats = self.messages[frame_id] = MessageStats(layout)
        stats.frames += 1
        stats.last_ns = t_ns
        if len(data) != layout.length:
            stats.rejects[Reject.LENGTH.name.lower()] += 1
        elif not layout.crc_ok(data):
            stats.rejects[Reject.CRC.name.lower()] += 1
        else:
            reason = stats.counters.check(data[1])
            if reason is not None:
                stats.rejects[reason.name.lower()] += 1
            else:
                stats.accepted += 1
                stats.values = layout.decode(data)[1]

    def note_events(self, events: Iterable[BusEvent]) -> None:
        """Count what the bus said besides frames (``HandBus.events``)."""
        for event in events:
            self.note_event(event.kind.value, event.detail)

    def note_event(self, kind: str, detail: str) -> None:
        """Count one bus event by its kind's name: a recording keeps the name, not the enum
        (``/events``, kind ``bus``)."""
        self.bus_events[kind] += 1
        self.last_event[kind] = detail

    def snapshot(self, now_ns: int | None = None, *, whole: bool = False) -> dict[str, Any]:
        """The view as JSON-ready data; rates are over the time since the previous snapshot,
        or with ``whole`` over all of it since the first frame: the last snapshot's, which
        came a moment after the one before (``--seconds`` a multiple of ``--every``) and
        said every rate was 0."""
        now = self.last_ns if now_ns is None else now_ns
        since = self.first_ns if whole else self._snapshot_ns
        span_s = (now - since) * 1e-9 if now is not None and since is not None else 0.0
        self._snapshot_ns = now
        messages = []
        for fid in sorted(self.messages):
            stats = self.messages[fid]
            new = stats.frames if whole else stats.frames - stats.frames_at_snapshot
            stats.frames_at_snapshot = stats.frames
            layout = stats.layout
            messages.append(
                {
                    "id": f"0x{fid:03X}",
                    "message": layout.name,
                    "frames": stats.frames,
                    "rate_hz": round(new / span_s, 1) if span_s > 0 else None,
                    "rejects": dict(stats.rejects),
                    "values": None
                    if stats.values is None
                    else {
                        spec.name: value if isinstance(value, int) else round(value, 9)
                        for spec, value in zip(layout.signals, stats.values, strict=True)
                    },
                    "units": {spec.name: spec.unit for spec in layout.signals if spec.unit},
                }
            )
        start = self.first_ns
        return {
            "t_s": None if now is None or start is None else round((now - start) * 1e-9, 3),
            "frames": self.frames,
            "frames_lost": self.frames_lost,
            "bus_events": dict(self.bus_events),
            "last_event": dict(self.last_event),
            "messages": messages,
            "unknown_ids": {
                f"0x{fid & ~EXTENDED_ID_FLAG:03X}"
                + (" (29-bit)" if fid & EXTENDED_ID_FLAG else ""): n
                for fid, n in sorted(self.unknown.by_id.items())
            },
            # frames of unknown ids beyond the first MAX_IDS (``idcount``)
            **({"unknown_ids_more_frames": self.unknown.others} if self.unknown.others else {}),
        }


def value_text(name: str, value: float, unit: str) -> str:
    """A signal's value as an engineer reads it: states and fault bits by name, units."""
    if name == "State":
        return node_state_name(int(value), str(int(value)))
    if name == "FaultBits":
        return ",".join(fault_names(int(value))) or "-"
    text = str(value) if isinstance(value, int) else f"{value:+.4f}"
    return f"{text} {unit}" if unit else text


def table(snapshot: dict[str, Any], title: str) -> Any:
    """The snapshot as a ``rich`` table (what the terminal view shows)."""
    from rich.table import Table

    view = Table(title=title, expand=True)
    if snapshot.get("frames_lost"):
        view.caption = (
            f"{snapshot['frames_lost']} frames lost by this listener before it read them: "
            "a counter skipped then may be its own gap, not the node's"
        )
    if snapshot.get("bus_events"):
        events = ", ".join(f"{k} {v}" for k, v in snapshot["bus_events"].items())
        last = "; ".join(f"{k}: {v}" for k, v in snapshot.get("last_event", {}).items())
        line = f"[red]bus events: {events}[/red] (last: {last})"
        view.caption = line if view.caption is None else f"{view.caption}\n{line}"
    for name, justify in (
        ("id", "right"),
        ("message", "left"),
        ("frames", "right"),
        ("Hz", "right"),
        ("rejects", "left"),
        ("last values", "left"),
    ):
        view.add_column(name, justify=justify)  # type: ignore[arg-type]
    for m in snapshot["messages"]:
        values = m["values"]
        text = (
            "-"
            if values is None
            else "  ".join(
                f"{k} {value_text(k, v, m['units'].get(k, ''))}" for k, v in values.items()
            )
        )
        rejects = ", ".join(f"{k} {v}" for k, v in m["rejects"].items()) or "-"
        rate = "-" if m["rate_hz"] is None else f"{m['rate_hz']:.0f}"
        view.add_row(
            m["id"],
            m["message"],
            str(m["frames"]),
            rate,
            f"[red]{rejects}[/red]" if m["rejects"] else rejects,
            text,
        )
    for fid, count in snapshot["unknown_ids"].items():
        view.add_row(fid, "[yellow]unknown id[/yellow]", str(count), "-", "-", "-")
    if snapshot.get("unknown_ids_more_frames"):
        more = str(snapshot["unknown_ids_more_frames"])
        view.add_row("more ids", "[yellow]unknown ids[/yellow]", more, "-", "-", "-")
    return view


def listen(
    bus: HandBus,
    seconds: float | None,
    keep_going: Callable[[], bool] = lambda: True,
    clock: Callable[[], int] = time.monotonic_ns,
    poll_s: float = 0.005,
    view: BusView | None = None,
) -> Iterator[list[tuple[int, bytes, int]]]:
    """Batches of ``(id, data, arrival_ns)`` from ``bus`` until ``seconds`` have passed (None:
    until ``keep_going`` says no). Only drains: nothing is ever sent. ``view`` is kept told
    of the frames the listener lost (``BusView.frames_lost``) and of the bus's events
    (``BusView.bus_events``)."""
    bus.use_clock(clock)
    end = None if seconds is None else clock() + round(seconds * 1e9)
    while keep_going():
        batch = [(f.arbitration_id, f.data, f.timestamp_ns) for f in bus.drain()]
        events = bus.events()
        if view is not None:
            view.note_events(events)
            view.frames_lost = bus.transport_counts().get("rx_frames_lost", 0)
        yield batch
        now = clock()
        if end is not None and now >= end:
            return
        if not batch:
            time.sleep(poll_s)


def log_protocol(
    recording: Recording,
    hand: HandConfig | None,
    dbc: Path | None,
    fallback: Callable[[], HandConfig],
) -> Protocol:
    """The protocol to decode a recording's frames with: the one its run spoke.

    A recording keeps its hand and that hand's DBC; decoding with any other protocol (the
    default hand's, say) reads another hand's frames as length rejects and unknown ids, which
    looks like a broken bus, not a wrong option. So ``hand`` (``--hand``) and ``dbc``
    (``--dbc``), None when not given, only choose for a recording from before the hand was
    recorded; one that is not the recorded one is refused rather than warned about: the user
    asked to decode with a hand or DBC the frames were not sent with, and either choice
    (ignore the option, or decode with it) would silently show something else than was asked
    for. ``fallback`` (the default hand) is for a recording that keeps no hand when no
    ``hand`` is given.
    """
    from handctl.hand_protocol import protocol_for
    from handctl.recording import channels as ch
    from handctl.recording.metadata import recorded_hand, recorded_protocol

    recorded = recorded_hand(recording, required=False)
    if recorded is None:
        return protocol_for(fallback() if hand is None else hand, dbc)
    protocol = recorded_protocol(recording) or protocol_for(recorded)
    if hand is not None and hand.config_hash != recorded.config_hash:
        raise ConfigError(
            "--hand",
            "",
            f"the hand {recording.path} was recorded with ({recorded.name}, config hash "
            f"{recorded.config_hash}; leave --hand out to decode with it)",
            f"config hash {hand.config_hash} ({hand.name})",
        )
    if dbc is not None and protocol_for(recorded, dbc).text != protocol.text:
        raise ConfigError(
            "--dbc",
            "",
            f"the DBC {recording.path} was recorded with (metadata {ch.META_HAND}.dbc; "
            "leave --dbc out to decode with it)",
            dbc,
        )
    return protocol


def from_log(recording: Recording, view: BusView | None = None) -> Iterable[tuple[int, bytes, int]]:
    """The raw frames of a recording, both directions, in wire order, on the log's clock;
    ``view`` is told of the bus events the run logged (``/events``, kind ``bus``) where they
    are in the file, as ``listen`` tells a live view. Frames alone said "no bus events" of a
    run that stopped on a bus-off."""
    from handctl.recording.frames import logged_frames

    told = view.note_event if view is not None else None
    for log_ns, frame_id, data, _ in logged_frames(recording, bus_events=told):
        yield frame_id, data, log_ns
