"""A recording's frames: back onto a bus with their timing, or out to python-can's log formats."""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Iterator
from typing import Any

from handctl.errors import ConfigError
from handctl.recording import channels as ch
from handctl.recording.metadata import recorded_hand
from handctl.recording.reader import Recording, iter_decoded, require_topics


def logged_frames(
    recording: Recording, direction: str = "both"
) -> Iterator[tuple[int, int, bytes, bool]]:
    """``(log_time_ns, arbitration_id, data, is_rx)`` in the order they were on the wire."""
    topics = {"both": (ch.CAN_RX, ch.CAN_TX), "rx": (ch.CAN_RX,), "tx": (ch.CAN_TX,)}
    if direction not in topics:
        raise ConfigError("--direction", "", "both, rx or tx", direction)
    for topic, log_time, msg in iter_decoded(recording, topics[direction]):
        if topic == ch.CAN_TX and msg.get("ok") is False:
            continue  # the bus refused it: it never was on the wire
        yield log_time, msg["id"], bytes.fromhex(msg["data"]), topic == ch.CAN_RX


def to_bus(
    recording: Recording,
    spec: str,
    speed: float = 1.0,
    direction: str = "both",
    sleep: Callable[[float], None] = time.sleep,
    clock: Callable[[], float] = time.perf_counter,
) -> dict[str, Any]:
    """Send the logged frames onto the bus ``spec`` with their original spacing / ``speed``.

    Frames are paced against their due times (not slept frame to frame), so the time spent
    sending does not add up into drift."""
    from handctl.online.bus import open_bus

    if not speed > 0 or not math.isfinite(speed):
        raise ConfigError("--speed", "", "a speed factor > 0 (1 = as recorded)", speed)
    require_topics(recording, (ch.CAN_RX, ch.CAN_TX), "--to-bus")
    hand = recorded_hand(recording)
    assert hand is not None
    sent = failed = 0
    worst_late = 0.0
    with open_bus(spec, hand.bus) as bus:
        start: float | None = None
        first = 0
        for log_time, frame_id, data, _ in logged_frames(recording, direction):
            if start is None:
                start, first = clock(), log_time
            due = start + (log_time - first) * 1e-9 / speed
            wait = due - clock()
            if wait > 0:
                sleep(wait)
            else:
                worst_late = max(worst_late, -wait)
            if bus.send(frame_id, data):
                sent += 1
            else:
                failed += 1
    return {
        "sent": sent,
        "failed": failed,
        "worst_late_ms": round(worst_late * 1e3, 3),
        "bus": spec,
        "speed": speed,
        "direction": direction,
    }


def export(recording: Recording, fmt: str, out: str) -> int:
    """Write the logged frames in a python-can log format (candump, asc, blf)."""
    from handctl.recording.canlog import LOG_FORMATS, write_frames

    if fmt not in LOG_FORMATS:
        raise ConfigError("--export", "", "one of " + ", ".join(LOG_FORMATS), fmt)
    require_topics(recording, (ch.CAN_RX, ch.CAN_TX), "--export")
    hand = recorded_hand(recording, required=False)
    fd = hand.bus.fd if hand is not None else True
    started = recording.meta_int("handctl.command", "started_unix_ns", 0)
    frames = logged_frames(recording)
    first: list[int] = []

    def stamped() -> Iterator[tuple[float, int, bytes, bool, bool]]:
        for log_time, frame_id, data, is_rx in frames:
            if not first:
                first.append(log_time)
            yield ((started + log_time - first[0]) * 1e-9, frame_id, data, is_rx, fd)

    try:
        return write_frames(out, fmt, stamped())
    except OSError as exc:
        raise ConfigError(
            out, "", "a path where the export can be written", exc.strerror or str(exc)
        ) from None
