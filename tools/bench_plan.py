"""A small plan with one worker and with more: ``python tools/bench.py plan --json``.

The shipped template cut to its first four phases (approach, lift, a short hold, one short
turn) with a small search, planned twice in one run: in this process (``--workers 1``) and on a
local pool of ``--workers`` processes (default 2). ``models_per_s`` is model runs (one phase on
one perturbed model, the unit of a plan's work) per second of wall time with the pool;
``speedup`` is the one-worker wall time over the pool's, pool start included. ``same_recipe``
says the two compiled recipes are equal byte for byte (they must be). The target on a 2-core
machine is ``speedup >= 1.7``; a shared machine's other load lowers it.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import yaml

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from handctl.config import load_hand  # noqa: E402
from handctl.errors import ConfigError  # noqa: E402
from handctl.executor import check_pool_options, open_pool  # noqa: E402
from handctl.planning.compile import plan_recipe, recipe_text  # noqa: E402
from handctl.planning.search import Budget  # noqa: E402
from handctl.planning.template import MAX_MODELS, load_template  # noqa: E402
from handctl.progress import Progress, close_active, say  # noqa: E402

#: One line of ``bench.py --help`` (read from the source there, without importing this).
SUMMARY = "a small plan with one worker and with a local pool of them"

TEMPLATE = ROOT / "config" / "recipes" / "swap_two_cylinders.template.yaml"
HAND = ROOT / "config" / "hands" / "hiroshima_hand.yaml"


#: the least of each count this benchmark takes, where it is not 1 (``bench._out_of_range``):
#: the pool is compared with one worker
LEAST = {"workers": 2}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--workers",
        type=int,
        default=2,
        help="the pool compared with one worker, at least 2 (default 2)",
    )
    parser.add_argument("--models", type=int, default=4, help="perturbed models (default 4)")
    parser.add_argument("--generations", type=int, default=1)
    parser.add_argument("--population", type=int, default=8)


def small_template(folder: Path) -> Path:
    """The shipped template cut short. The turn keeps its whole ramp and half a second more:
    a phase shorter than its ``ramp_s`` is refused, and a fixed 1 s turn broke this bench
    (exit 2, measuring nothing) once the template's ramp grew to 1.5 s."""
    data: dict[str, Any] = yaml.safe_load(TEMPLATE.read_text())
    data["search"]["random_seeds"] = 0
    phases = data["phases"]
    phases[2]["max_s"] = 0.5
    phases[3]["max_s"] = float(phases[3].get("ramp_s", 0.0)) + 0.5
    data["phases"] = phases[:4]
    path = folder / "small.template.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def run(args: argparse.Namespace) -> dict[str, Any]:
    # before any work: --workers 9 was refused only after the one-worker plan had run, and
    # --models 1000 ran where handctl plan takes at most MAX_MODELS
    if not 1 <= args.models <= MAX_MODELS:
        raise ConfigError("--models", "", f"1 to {MAX_MODELS} models, as handctl plan", args.models)
    if args.workers < 2:
        # the pool is compared with one worker: --workers 1 planned twice in this process
        # and printed a speedup of 1.0, exit 0, having measured nothing (an outside audit);
        # first, so that --workers 0 is not told that 1 would do
        raise ConfigError(
            "--workers", "", "at least 2 workers (the pool compared with one worker)", args.workers
        )
    # no --scheduler here, so none is pointed at; checked, not a pool started and closed
    check_pool_options(args.workers, None, offers_scheduler=False)
    hand = load_hand(HAND)
    budget = Budget(
        generations=args.generations, population=args.population, elite=min(4, args.population)
    )
    with tempfile.TemporaryDirectory() as folder:
        template = load_template(small_template(Path(folder)), hand)
        walls: dict[int, float] = {}
        texts: dict[int, str] = {}
        runs: dict[int, int] = {}
        for workers in (1, args.workers):
            say(f"plan with {workers} worker(s)")
            t0 = time.perf_counter()
            try:
                with open_pool(workers, offers_scheduler=False) as pool:
                    result = plan_recipe(
                        template,
                        hand,
                        models=args.models,
                        budget=budget,
                        executor=pool,
                        meter=Progress,
                    )
                    runs[workers] = pool.tasks_run
            finally:
                close_active()
            walls[workers] = time.perf_counter() - t0
            texts[workers] = recipe_text(result, "bench")
    wide = args.workers
    return {
        "benchmark": "plan",
        "models": args.models,
        "workers": wide,
        "model_runs": runs[wide],
        "wall_1_s": round(walls[1], 2),
        f"wall_{wide}_s": round(walls[wide], 2),
        "models_per_s": round(runs[wide] / walls[wide], 2),
        "models_per_s_1": round(runs[1] / walls[1], 2),
        "speedup": round(walls[1] / walls[wide], 3),
        "same_recipe": texts[1] == texts[wide],
    }
