"""Decoder fuzz at benchmark scale: at least 100 000 Hypothesis-drawn frames through the host's
real receive path (a virtual bus, ``HandDriver.poll``: id dispatch, length, CRC and rolling
counter checks, decoding), from the strategies the property tests use (``tests/strategies.py``).

Every frame must come out accepted or rejected, never as an exception, and never as a joint
state outside what the protocol can carry. CI runs the same strategies with a few thousand
frames (``tests/property/test_codec_properties.py``); this is the large run.

Figures: ``frames``, ``accepted``, ``rejected`` (and by kind), ``exceptions`` (target 0),
``miscounted`` (frames neither accepted nor rejected, or both; target 0), ``out_of_range``
(target 0), ``frames_per_s`` (through the receive path: time in ``poll`` only) and
``drawn_frames_per_s`` (the whole run, Hypothesis drawing included).
"""

from __future__ import annotations

import argparse
import itertools
import math
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from hypothesis import HealthCheck, Phase, given, seed, settings

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from handctl.config import load_hand  # noqa: E402
from handctl.hand_protocol import protocol_for  # noqa: E402
from handctl.online.bus import open_bus  # noqa: E402
from handctl.online.drivers.hand import HandDriver  # noqa: E402
from tests.strategies import Frame, frame_batches  # noqa: E402

#: One line of ``bench.py --help`` (read from the source there, without importing this).
SUMMARY = "decoder fuzz: 100 000 and more drawn frames through the host's receive path"

#: Examples per Hypothesis run at most; runs repeat with the next seed until enough frames are
#: drawn (an example is a poll's worth: about 25 frames).
EXAMPLES_PER_RUN = 500
FRAMES_PER_EXAMPLE = 25


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--frames",
        type=int,
        default=100_000,
        help="frames to decode at least (the issue asks for >= 100 000)",
    )
    parser.add_argument("--seed", type=int, default=0, help="Hypothesis seed of the first run")
    parser.add_argument("--hand", type=Path, default=ROOT / "config/hands/hiroshima_hand.yaml")


@dataclass
class Tally:
    frames: int = 0
    polls: int = 0
    exceptions: int = 0
    miscounted: int = 0
    out_of_range: int = 0
    poll_ns: int = 0
    problems: list[str] = field(default_factory=list)

    def problem(self, text: str) -> None:
        if len(self.problems) < 5:
            self.problems.append(text)


def run(args: argparse.Namespace) -> dict[str, Any]:
    hand = load_hand(args.hand)
    protocol = protocol_for(hand)
    angle_limit = 3.2768  # rad: the largest angle the Feedback encoding can carry
    tally = Tally()
    started = time.perf_counter()
    with (
        open_bus("virtual:handctl-bench-fuzz", hand.bus) as host,
        open_bus("virtual:handctl-bench-fuzz", hand.bus) as peer,
    ):
        # One driver for the whole run, as on a bus that stays up: the counter checks see
        # long streams, not only the first frame after a start. Each batch arrives over a
        # second of bus time, so one poll may take all of it: the drain's budget (what a
        # bus carries between two polls) is not what this measures.
        bus_time = [0]
        driver = HandDriver(hand, protocol, host, clock_ns=lambda: bus_time[0])

        def handled() -> int:
            return sum(driver.reject_counts().values()) + sum(n.accepted for n in driver.nodes)

        def decode(batch: list[Frame]) -> None:
            before = handled()
            bus_time[0] += 1_000_000_000
            for frame_id, data in batch:
                if not peer.send(frame_id, data):
                    raise RuntimeError(f"the virtual bus refused 0x{frame_id:03X}")
            t0 = time.perf_counter_ns()
            try:
                state = driver.poll()
            except Exception as exc:  # a finding: counted and shown, never fatal here
                tally.exceptions += 1
                tally.problem(f"{type(exc).__name__}: {exc} on {batch!r}"[:400])
                driver.bus.drain()  # what the failed poll left behind
                return
            finally:
                tally.poll_ns += time.perf_counter_ns() - t0
                tally.frames += len(batch)
                tally.polls += 1
            if handled() - before != len(batch):
                tally.miscounted += abs(handled() - before - len(batch))
                tally.problem(f"{handled() - before} of {len(batch)} frames counted")
            bad = [a for a in state.angle.tolist() + state.tdt.tolist() if not math.isfinite(a)] + [
                a for a in state.angle.tolist() if abs(a) > angle_limit
            ]
            if bad:
                tally.out_of_range += 1
                tally.problem(f"state out of range: {bad[:3]}")

        for n in itertools.count():
            if tally.frames >= args.frames:
                break
            examples = min(EXAMPLES_PER_RUN, 1 + (args.frames - tally.frames) // FRAMES_PER_EXAMPLE)
            drawn = given(frame_batches(protocol, min_size=10, max_size=40))(decode)
            fuzz = settings(
                max_examples=examples,
                database=None,
                deadline=None,
                phases=[Phase.generate],
                suppress_health_check=list(HealthCheck),
            )(seed(args.seed + n)(drawn))
            fuzz()
            print(f"  {tally.frames} frames, {tally.exceptions} exceptions", file=sys.stderr)
    wall = time.perf_counter() - started
    rejects = driver.reject_counts()
    accepted = sum(node.accepted for node in driver.nodes)
    return {
        "frames": tally.frames,
        "polls": tally.polls,
        "accepted": accepted,
        "rejected": sum(rejects.values()),
        "rejected_by_kind": rejects,
        "exceptions": tally.exceptions,
        "miscounted": tally.miscounted,
        "out_of_range": tally.out_of_range,
        "problems": tally.problems,
        "frames_per_s": round(tally.frames / max(tally.poll_ns * 1e-9, 1e-9)),
        "drawn_frames_per_s": round(tally.frames / wall),
        "wall_s": round(wall, 1),
        "seed": args.seed,
    }
