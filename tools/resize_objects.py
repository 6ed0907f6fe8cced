"""Write a copy of a hand config whose simulated objects are resized, for trying a recipe on
objects of another size than it was planned for (docs/experiment.md, *A torque scheduled on
the measured radius*):

    python tools/resize_objects.py --scale OBJECT=1.12 -o big.yaml
    handctl run recipe config/recipes/swap_two_cylinders.yaml --hand big.yaml

Each named object's radius is multiplied by its factor (the others keep theirs), it rests on
the table as before, and a pair stays side by side with the gap it had, around the middle it
had, so that no cylinder starts inside another. Every other parameter is the config's own,
so what changes is the size alone (the bench's ``objects`` family draws mass and radius
together).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

import yaml

DEFAULT_HAND = Path(__file__).resolve().parent.parent / "config" / "hands" / "hiroshima_hand.yaml"
#: the radius factors accepted: the model set draws ±20 %, the estimator fits ±40 %
MIN_SCALE, MAX_SCALE = 0.5, 1.5


def resized(data: dict[str, Any], scales: dict[str, float], source: str) -> dict[str, Any]:
    """``data`` (a hand config) with its ``sim.objects`` resized by ``scales`` (name: factor);
    ``ValueError`` naming the file and the key for an object it does not have."""
    objects = data.get("sim", {}).get("objects") or []
    names = [o.get("name") for o in objects]
    for name in scales:
        if name not in names:
            raise ValueError(
                f"{source}: sim.objects: expected an object named {name!r} "
                f"(one of {', '.join(map(str, names)) or 'none'}), found none"
            )
    table = data["sim"]["table"]["height"]
    pair = len(objects) == 2
    if pair:
        left, right = sorted(objects, key=lambda o: o["x"])
        gap = (right["x"] - right["radius"]) - (left["x"] + left["radius"])
        middle = (left["x"] + right["x"]) / 2
    for obj in objects:
        obj["radius"] = obj["radius"] * scales.get(obj["name"], 1.0)
        obj["y"] = table + obj["radius"]
    if pair:
        left["x"] = middle - gap / 2 - left["radius"]
        right["x"] = middle + gap / 2 + right["radius"]
    return data


def _scale(text: str) -> tuple[str, float]:
    name, sep, value = text.partition("=")
    try:
        factor = float(value)
    except ValueError:
        factor = float("nan")
    if not sep or not name or not MIN_SCALE <= factor <= MAX_SCALE:
        raise argparse.ArgumentTypeError(
            f"expected NAME=FACTOR with FACTOR in [{MIN_SCALE:g}, {MAX_SCALE:g}], found {text!r}"
        )
    return name, factor


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--hand", type=Path, default=DEFAULT_HAND, help="the hand config to copy")
    parser.add_argument(
        "--scale",
        type=_scale,
        action="append",
        required=True,
        metavar="NAME=FACTOR",
        help="an object's radius factor (repeat for several objects)",
    )
    parser.add_argument("-o", "--output", type=Path, required=True)
    args = parser.parse_args(argv)
    from handctl.errors import ConfigError
    from handctl.outfile import check_writable, refuse_same_files, write_atomically

    names = [name for name, _ in args.scale]
    try:
        twice = sorted({n for n in names if names.count(n) > 1})
        if twice:  # the last one won, without a word
            raise ConfigError("--scale", "", "each object scaled once", ", ".join(twice))
        # the hand's file given as -o was dumped over, its comments and anchors lost; a
        # missing hand or a directory as -o were tracebacks
        refuse_same_files({"-o": args.output}, {"--hand": args.hand})
        target = check_writable(args.output, "-o")
        try:
            text = args.hand.read_text(encoding="utf-8")
        except OSError as exc:
            raise ConfigError(
                "--hand", "", "a hand config to read", f"{args.hand} ({exc})"
            ) from None
        out = resized(yaml.safe_load(text), dict(args.scale), str(args.hand))
    except ValueError as exc:  # ConfigError is a ValueError
        print(f"error: {exc}", file=sys.stderr)
        return 2
    write_atomically(target, yaml.safe_dump(out, sort_keys=False))
    return 0


if __name__ == "__main__":
    sys.exit(main())
