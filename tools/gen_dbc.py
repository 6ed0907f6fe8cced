"""Write the DBC of a hand config: ``python tools/gen_dbc.py [--hand HAND.yaml] [--check]``.

The frames follow from the hand (``handctl/hand_protocol.py``); this writes them down for a
firmware author or a CAN tool. Without ``--hand`` it writes the packaged
``firmware_protocol/handctl.dbc`` from the default hand, and ``--check`` fails when the
committed file is not what the hand generates, byte for byte.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from generated import DEFAULT_DBC, ROOT, display_path, write_or_check

from handctl.config import load_hand
from handctl.hand_protocol import generate_dbc, hand_shape

DEFAULT_HAND = ROOT / "handctl" / "hands" / "hiroshima_hand.yaml"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0] if __doc__ else None)
    parser.add_argument("--hand", type=Path, default=DEFAULT_HAND, help="hand config to read")
    parser.add_argument("--out", type=Path, default=DEFAULT_DBC, help="DBC file to write")
    parser.add_argument(
        "--check",
        action="store_true",
        help="write nothing; exit 1 if the file on disk is not up to date",
    )
    args = parser.parse_args(argv)
    try:
        text = generate_dbc(hand_shape(load_hand(args.hand)))
    except ValueError as exc:  # ConfigError is a ValueError
        print(f"gen_dbc.py: {exc}", file=sys.stderr)
        return 2
    command = "python tools/gen_dbc.py"
    if args.hand.resolve() != DEFAULT_HAND.resolve():
        command += f" --hand {display_path(args.hand)}"
    return write_or_check(
        "gen_dbc.py", {args.out: text}, display_path(args.hand), command, args.check
    )


if __name__ == "__main__":
    sys.exit(main())
