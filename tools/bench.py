"""Run one named benchmark and print its figures: ``python tools/bench.py NAME --json``.

Each benchmark lives in ``tools/bench_NAME.py`` with ``add_arguments(parser)``, ``run(args) ->
dict`` and ``SUMMARY``, its line of ``--help``. Figures that are targets are ratios against a
baseline measured in the same run, because the machine is shared and absolute times are noisy.
Progress goes to stderr so that stdout is exactly one JSON object.

A benchmark that cannot measure what it was asked to says so on stderr and exits non-zero: one
that finds out before measuring raises ``SystemExit`` with the reason (no figures); one whose
figures hold ``failed`` (what could not be measured, each a sentence) has them printed and
exits 1, each failure on stderr. An error inside figures that exit 0 reads as a success to a
script, or to a reader who does not open the JSON.
"""

from __future__ import annotations

import argparse
import ast
import importlib
import io
import json
import math
import os
import signal
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
USAGE = "usage: bench.py NAME [--json] [options]   (bench.py NAME --help: its options)"


def available() -> list[str]:
    return sorted(p.stem.removeprefix("bench_") for p in HERE.glob("bench_*.py"))


def summary(name: str) -> str:
    """Benchmark ``name``'s ``SUMMARY``, read from its source without importing it: the list
    costs no benchmark's imports (MuJoCo, the runtime) and shows a benchmark whose imports
    fail; the first line of its docstring when it has none."""
    tree = ast.parse((HERE / f"bench_{name}.py").read_text(encoding="utf-8"))
    for node in tree.body:
        if (
            isinstance(node, ast.Assign)
            and [getattr(t, "id", None) for t in node.targets] == ["SUMMARY"]
            and isinstance(node.value, ast.Constant)
            and isinstance(node.value.value, str)
        ):
            return node.value.value
    return (ast.get_docstring(tree) or "").partition("\n")[0]


def listing() -> str:
    """What ``--help`` prints: the usage and each benchmark with its line."""
    names = available()
    width = max(map(len, names))
    lines = [USAGE, "", "benchmarks:"]
    lines += [f"  {name:<{width}}  {summary(name)}" for name in names]
    return "\n".join(lines)


#: The options the benchmarks share by name, and what each takes: a count (1 or more), a
#: number from 0 (a seed, a babble rate), a positive or non-negative finite number of units.
#: Checked once here, after parsing: 0 seeds divided by zero after the nominal run, a NaN
#: tolerance printed NaN into the JSON (no JSON parser takes it), a negative duration was
#: clamped and reported as met.
_COUNTS = (
    "seeds",
    "workers",
    "repeat",
    "repeats",
    "ticks",
    "frames",
    "grid",
    "models",
    "population",
    "generations",
    "tick_cost_rounds",
    "live_pairs",
)
_FROM_ZERO = ("first_seed", "seed", "babble")
_POSITIVE = (
    "seconds",
    "minutes",
    "tolerance",
    "swap_deg",
    "phase_deg",
    "phase_tolerance_deg",
    "tick_cost_seconds",
)
_NON_NEGATIVE = ("warmup_s",)


def _out_of_range(args: argparse.Namespace, least: dict[str, int] | None = None) -> str:
    """What the first shared option out of its range is, said as the CLI says it; "" if none.
    ``least``: a benchmark's own lower bound of a count (the plan bench's two workers: told
    ">= 1" for 0, and then refused 1)."""
    for key, value in vars(args).items():
        if value is None or isinstance(value, bool) or not isinstance(value, int | float):
            continue
        option = "--" + key.replace("_", "-")
        fewest = (least or {}).get(key, 1)
        if key in _COUNTS and not value >= fewest:
            return f"{option}: expected a whole number >= {fewest}, found {value}"
        if key in _FROM_ZERO and not value >= 0:
            return f"{option}: expected a whole number >= 0, found {value}"
        if key in _POSITIVE and not (math.isfinite(value) and value > 0):
            return f"{option}: expected a finite number > 0, found {value}"
        if key in _NON_NEGATIVE and not (math.isfinite(value) and value >= 0):
            return f"{option}: expected a finite number >= 0, found {value}"
    return ""


class _Formatter(argparse.RawDescriptionHelpFormatter, argparse.ArgumentDefaultsHelpFormatter):
    """The benchmark's description as written, and each option's default after its help
    unless the help already says it."""

    def _get_help_string(self, action: argparse.Action) -> str | None:
        text = action.help or ""
        if "default" in text:
            return text
        return super()._get_help_string(action)


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    # an output encoding without '°', '±' or '×' (LANG=C) gets their escapes, as handctl's
    # own commands do: the help of three benchmarks ended in a UnicodeEncodeError
    for stream in (sys.stdout, sys.stderr):
        if isinstance(stream, io.TextIOWrapper):
            stream.reconfigure(errors="backslashreplace")
    if argv and argv[0] in ("-h", "--help"):
        print(listing())
        return 0
    names = available()
    if not argv or argv[0] not in names:
        given = argv[0] if argv else "nothing"
        print(
            f"bench.py: expected a benchmark name, one of {', '.join(names)}; found {given} "
            "(bench.py --help lists them)",
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
    parser = argparse.ArgumentParser(
        prog=f"bench.py {name}",
        description=module.__doc__,
        formatter_class=_Formatter,
        allow_abbrev=False,
    )
    parser.add_argument("--json", action="store_true", help="print one JSON object (default)")
    module.add_arguments(parser)
    for action in parser._actions:
        # every option's default in its help, those a benchmark gave no words too
        if action.help is None and action.option_strings:
            action.help = "(default: %(default)s)"
    args = parser.parse_args(argv[1:])
    wrong = _out_of_range(args, getattr(module, "LEAST", None))
    if wrong:
        print(f"bench.py {name}: {wrong}", file=sys.stderr)
        return 2
    from handctl.errors import ConfigError, HandctlError

    # SIGTERM as Ctrl-C, as handctl's commands take it: the pool's workers stopped, exit 130
    # (it was 143 with a leaked semaphore; Ctrl-C a KeyboardInterrupt traceback)
    signal.signal(signal.SIGTERM, _interrupt)
    try:
        figures = module.run(args)
    except ConfigError as exc:  # bad input found by handctl (a recipe, a hand, an address)
        print(f"bench.py {name}: error: {exc}", file=sys.stderr)
        return 2
    except HandctlError as exc:  # a failed result (a cluster lost mid-run): not bad input
        print(f"bench.py {name}: failed: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print(f"bench.py {name}: interrupted", file=sys.stderr)
        return 130
    try:
        print(json.dumps(figures, sort_keys=True), flush=True)
    except BrokenPipeError:
        raise  # a reader that stopped early: said nothing of (``__main__`` below)
    except OSError as exc:
        # a stdout that cannot be written (a full disk, /dev/full): the one thing the bench
        # makes is lost, so said, exit 1, where it ended in a traceback
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        print(f"bench.py {name}: failed: its figures could not be written ({exc})", file=sys.stderr)
        return 1
    failed = figures.get("failed") or []
    for failure in failed:
        print(f"bench.py {name}: failed: {failure}", file=sys.stderr)
    return 1 if failed else 0


def _interrupt(signum: int, frame: object) -> None:
    raise KeyboardInterrupt(signal.Signals(signum).name)


if __name__ == "__main__":
    try:
        raise SystemExit(main())
    except BrokenPipeError:
        # a reader that stopped early (``bench.py --help | head``) is not a failure of the
        # bench; stdout goes to /dev/null so that Python's own flush at exit says nothing
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        raise SystemExit(0) from None
