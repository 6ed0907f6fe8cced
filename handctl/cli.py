"""The ``handctl`` command: the one place in handctl that prints.

Exit codes (the same for every subcommand):

==== =====================================================================
0    done
1    finished, but the result is a failure (e.g. a replay mismatch)
2    bad input: configuration, recipe, scenario, arguments; nothing was sent
3    safety stop: a fault stopped the hand
4    bus unavailable or failed
130  interrupted (Ctrl-C or SIGTERM), after a controlled stop
==== =====================================================================
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable, Sequence
from pathlib import Path

from handctl import __version__
from handctl.errors import BusError, ConfigError, HandctlError

EXIT_OK = 0
EXIT_FAILED = 1
EXIT_BAD_INPUT = 2
EXIT_SAFETY_STOP = 3
EXIT_BUS = 4
EXIT_INTERRUPTED = 130

DEFAULT_HAND = Path("config/hands/hiroshima_hand.yaml")


def _progress(message: str) -> None:
    """Progress of long work goes to stderr, so stdout stays clean for results."""
    print(message, file=sys.stderr, flush=True)


# -- check ---------------------------------------------------------------------------------------
def _cmd_check(args: argparse.Namespace) -> int:
    from handctl.busload import MAX_LOAD, hand_budget
    from handctl.config import load_hand
    from handctl.drivers.hand import check_ids
    from handctl.protocol import DEFAULT_DBC, load_protocol

    hand = load_hand(args.hand)
    protocol = load_protocol(args.dbc or DEFAULT_DBC)
    check_ids(hand, protocol)
    bus = hand.bus
    kind = (f"CAN-FD {bus.bitrate / 1e6:g}/{(bus.data_bitrate or 0) / 1e6:g} Mbit/s"
            if bus.fd else f"classic CAN {bus.bitrate / 1e6:g} Mbit/s")
    print(f"hand {hand.name} ({args.hand}), config hash {hand.config_hash}")
    print(f"bus {bus.interface}:{bus.channel}, {kind}, loop {bus.loop_rate_hz:g} Hz")
    print(f"{'joint':<8} {'tau_max':>8} {'device':>8} {'rate':>9} {'angle range':>17}")
    for finger in hand.fingers:
        for joint in finger.joints:
            limits = f"[{joint.angle_min:+.2f}, {joint.angle_max:+.2f}] rad"
            print(f"{joint.name:<8} {joint.tau_max:>6.3f}Nm {joint.device_tau_max:>6.3f}Nm "
                  f"{joint.rate_limit:>6.1f}N·m/s {limits}")
    for finger in hand.fingers:
        ids = ", ".join(f"{k} 0x{v:03X}" for k, v in finger.can_ids.as_dict().items())
        print(f"node {finger.node_id} ({finger.name}): {ids}")
    budget = hand_budget(hand, protocol)
    print(f"\nworst-case bus budget ({kind}, {bus.loop_rate_hz:g} Hz loop):")
    print(f"{'message':<17} {'id':>6} {'bytes':>5} {'frames':>6} {'rate':>8} {'time':>9} "
          f"{'load':>7}")
    for m in budget.messages:
        rate = f"{m.rate_hz:g} Hz" if m.rate_hz else "event"
        print(f"{m.name:<17} 0x{m.frame_id:03X} {m.n_bytes:>5} {m.frames:>6} {rate:>8} "
              f"{m.frame_time_us:>7.1f}us {m.load * 100:>6.2f}%")
    print(f"total {budget.load * 100:.1f} % (limit {MAX_LOAD * 100:.0f} %)")
    if budget.ok:
        print("ok")
        return EXIT_OK
    hints = [f"the highest loop rate that fits is {budget.highest_loop_rate_hz():.0f} Hz"]
    per_finger = max(hand_budget(hand, protocol, nodes={f.node_id}).load for f in hand.fingers)
    hints.append(f"one bus per finger would carry {per_finger * 100:.1f} %")
    if not bus.fd:
        fd = hand_budget(hand, protocol, fd=True, bitrate=1_000_000, data_bitrate=5_000_000)
        hints.append(f"CAN-FD 1/5 Mbit/s would carry {fd.load * 100:.1f} %")
    print(f"handctl: error: {args.hand}: bus: expected a worst-case load <= "
          f"{MAX_LOAD * 100:.0f} %, found {budget.load * 100:.1f} % at "
          f"{bus.loop_rate_hz:g} Hz; " + "; ".join(hints), file=sys.stderr)
    return EXIT_BAD_INPUT


# -- parser --------------------------------------------------------------------------------------
def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="handctl",
        description="Grasp and manipulate two objects with a joint-torque-controlled "
                    "three-fingered hand over CAN.",
        epilog="Exit codes: 0 done, 1 failed result, 2 bad input, 3 safety stop, "
               "4 bus error, 130 interrupted.")
    parser.add_argument("--version", action="version", version=f"handctl {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)

    check = sub.add_parser("check", help="validate a hand config and its bus-load budget",
                           description="Validate a hand config against the protocol (DBC) and "
                                       "print its worst-case bus-load budget; exit 2 if over 50 %.")
    check.add_argument("hand", type=Path, nargs="?", default=DEFAULT_HAND,
                       help=f"hand config YAML (default {DEFAULT_HAND})")
    check.add_argument("--dbc", type=Path, help="protocol DBC (default: the packaged one)")
    check.set_defaults(func=_cmd_check)

    return parser


def _run(func: Callable[[argparse.Namespace], int], args: argparse.Namespace) -> int:
    try:
        return func(args)
    except ConfigError as exc:
        print(f"handctl: error: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except BusError as exc:
        print(f"handctl: bus error: {exc}", file=sys.stderr)
        return EXIT_BUS
    except HandctlError as exc:
        print(f"handctl: error: {exc}", file=sys.stderr)
        return EXIT_FAILED
    except KeyboardInterrupt:
        print("handctl: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    return _run(args.func, args)


if __name__ == "__main__":
    raise SystemExit(main())
