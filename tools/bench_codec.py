"""Codec cost of one 1 kHz tick: encode every finger's command frame and check and decode every
finger's feedback frame, with handctl's compiled layouts and with cantools (same run), for the
hand's own protocol (the default hand's: three fingers of three joints)."""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from collections.abc import Callable

import cantools

from handctl.cli import DEFAULT_HAND
from handctl.config import load_hand
from handctl.hand_protocol import protocol_for

#: One line of ``bench.py --help`` (read from the source there, without importing this).
SUMMARY = "codec cost of one 1 kHz tick: handctl's compiled layouts against cantools"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--ticks", type=int, default=20_000, help="ticks per measurement")
    parser.add_argument("--repeats", type=int, default=5, help="measurements per codec")
    parser.add_argument("--hand", default=str(DEFAULT_HAND), help="hand config (HAND.yaml)")


def _measure(tick: Callable[[int], None], ticks: int, repeats: int) -> list[float]:
    """Per-tick times in microseconds: the median of batches, robust to a noisy machine."""
    samples = []
    for _ in range(repeats):
        batch = []
        for k in range(ticks):
            t0 = time.perf_counter_ns()
            tick(k)
            batch.append((time.perf_counter_ns() - t0) / 1e3)
        samples.append(statistics.median(batch))
    return samples


def run(args: argparse.Namespace) -> dict[str, float]:
    hand = load_hand(args.hand)
    protocol = protocol_for(hand)
    db = cantools.database.load_string(protocol.text, database_format="dbc")
    assert isinstance(db, cantools.database.can.Database)
    nodes = [f.node_id for f in hand.fingers]
    commands = [protocol.layout("TorqueCommand", n) for n in nodes]
    feedbacks = [protocol.layout("Feedback", n) for n in nodes]
    torques = [
        tuple(0.1234 * (-1) ** j / (i + 1) for j in range(len(lay.signals)))
        for i, lay in enumerate(commands)
    ]
    fb_frames = [
        lay.encode(k, [0.1 * (j + 1) for j in range(len(lay.signals) - 2)] + [1, 0])
        for k, lay in enumerate(feedbacks)
    ]
    cmd_msgs = [db.get_message_by_frame_id(lay.frame_id) for lay in commands]
    fb_msgs = [db.get_message_by_frame_id(lay.frame_id) for lay in feedbacks]

    def ours(k: int) -> None:
        for lay, tau in zip(commands, torques, strict=True):
            lay.encode(k & 0xFF, tau)
        for lay, data in zip(feedbacks, fb_frames, strict=True):
            if lay.crc_ok(data):
                lay.decode(data)

    def theirs(k: int) -> None:
        # cantools has no CRC of its own; it gets ours, which favours cantools slightly.
        for lay, msg, tau in zip(commands, cmd_msgs, torques, strict=True):
            body = msg.encode(
                {"Crc": 0, "Counter": k & 0xFF, **{f"Torque{j + 1}": t for j, t in enumerate(tau)}}
            )
            lay.crc_ok(body)
        for lay, msg, data in zip(feedbacks, fb_msgs, fb_frames, strict=True):
            if lay.crc_ok(data):
                msg.decode(data)

    print("measuring handctl codec ...", file=sys.stderr)
    ours_us = _measure(ours, args.ticks, args.repeats)
    print("measuring cantools ...", file=sys.stderr)
    theirs_us = _measure(theirs, max(1, args.ticks // 4), args.repeats)
    p50 = statistics.median(ours_us)
    base = statistics.median(theirs_us)
    return {
        "tick_us_p50": round(p50, 2),
        "cantools_tick_us_p50": round(base, 2),
        "speedup_vs_cantools": round(base / p50, 2),
    }
