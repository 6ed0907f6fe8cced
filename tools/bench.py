"""Run one named benchmark and print its figures: ``python tools/bench.py NAME --json``.

Each benchmark lives in ``tools/bench_NAME.py`` with ``add_arguments(parser)`` and
``run(args) -> dict``. Figures that are targets are ratios against a baseline measured in the
same run, because the machine is shared and absolute times are noisy. Progress goes to stderr
so that stdout is exactly one JSON object.

A benchmark that cannot measure what it was asked to says so on stderr and exits non-zero: one
that finds out before measuring raises ``SystemExit`` with the reason (no figures); one whose
figures hold ``failed`` (what could not be measured, each a sentence) has them printed and
exits 1, each failure on stderr. An error inside figures that exit 0 reads as a success to a
script, or to a reader who does not open the JSON.
"""

from __future__ import annotations

import argparse
import importlib
import json
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent


def available() -> list[str]:
    return sorted(p.stem.removeprefix("bench_") for p in HERE.glob("bench_*.py"))


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    names = available()
    if not argv or argv[0] not in names:
        given = argv[0] if argv else "nothing"
        print(
            f"bench.py: expected a benchmark name, one of {', '.join(names)}; found {given}",
            file=sys.stderr,
        )
        return 2
    name = argv[0]
    # This tree's handctl, not an installed one: a script's path starts at its own folder, so
    # a bench run from a second checkout would otherwise measure the installed tree's code
    # beside this tree's helper processes (they start with ``python -m`` from the cwd).
    sys.path.insert(0, str(HERE.parent))
    sys.path.insert(0, str(HERE))
    module = importlib.import_module(f"bench_{name}")
    parser = argparse.ArgumentParser(prog=f"bench.py {name}", description=module.__doc__)
    parser.add_argument("--json", action="store_true", help="print one JSON object (default)")
    module.add_arguments(parser)
    args = parser.parse_args(argv[1:])
    figures = module.run(args)
    print(json.dumps(figures, sort_keys=True))
    failed = figures.get("failed") or []
    for failure in failed:
        print(f"bench.py {name}: failed: {failure}", file=sys.stderr)
    return 1 if failed else 0


if __name__ == "__main__":
    raise SystemExit(main())
