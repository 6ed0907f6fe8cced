"""The real-time loop against the simulated hand (its own process, on the unix datagram bus),
and, in the same run, a naive asyncio.sleep loop at the same rate as the baseline.

Figures: lateness p99 of both loops and their ratio, the missed-tick rate, and the CPU time of
our own tick stages (poll, recipe, safety, send, record, feedback) at p99, the simulated hand
excluded; the simulated hand's frames that did not go and the times the host's queue was full.
The hold recipe has the soft-limit guard, a joint-space pose hold and injected joint damping,
so the feedback stage does the work of a feedback phase every tick.

Beside the loop, on its CPU one priority above it, the bare timer loop of the timing check runs
for the whole run (``handctl.hostcheck``): ``host_*`` is what it saw, and every missed tick of
the run proper is the host's (``missed_host``: the bare loop stalled at the same time;
``missed_host_slow_cpu``: its stalls, hiccups, slow pieces of work and slow switches (its own
passage through the kernel between two pieces) together explain the miss, the CPU taken away
in pieces shorter than a stall or running slow; ``missed_rival``:
a real-time task at the loop's priority or above ran on its CPU, which the bare loop one
priority up does not feel, ``handctl.rivals``; ``missed_host_catch_up``: right after the
host's miss, its catch-up tick took no more CPU time than a catch-up usually does, or it began
too late for a tick of the usual CPU time to meet the deadline; ``missed_host_off_cpu``: the
loop's thread, at a real-time priority, was held off its CPU in the tick before the miss long
enough to make it, by the kernel's account of the thread: ``handctl.online.misstrace``) or
handctl's (``missed_handctl``: none of these; ``handctl_misses`` says what the tick before each
did). Target: ``missed_handctl`` 0.

``tick_cost`` is the CPU cost of the tick, stage by stage, of this tree beside the tree of
``--baseline`` (a git revision; by default the one before the tick's cost was cut, issue #17),
in the same benchmark run: each runs ``tools/tick_cost.py`` (a lockstep hold, the same work
every time) in a process of its own, both at once (whatever else loads the host loads both),
``--tick-cost-rounds`` times, over the unix bus (a real-time run's transport) and the virtual
bus (a lockstep run's). Per stage the median over the rounds of each p50 and p99, and
``ratio_*``: this tree's over the baseline's. The recipe and feedback stages (the recipe
runner's) are a control where the runner did not change. A baseline that cannot run
``tick_cost.py`` (a revision whose handctl lacks what it imports) is tried out and refused
before anything is measured, on stderr and with exit 1; a round that fails later is its
transport's ``error`` and in ``failed``, and the benchmark exits 1 all the same.

``--rt --hygiene`` runs the loop once per real-time measure added in turn (SCHED_FIFO alone,
then separate CPUs, locked memory, prefaulted memory), each in a fresh process (a priority,
a CPU or locked memory would otherwise carry over to the next) with the bare loop beside it,
and reports each one's figures under ``hygiene``.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import subprocess
import sys
import tarfile
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
from hold_recipe import hold_recipe

from handctl.config import HandConfig, load_hand
from handctl.hostcheck import Deadlines, ProbeRecord, attribute, judge, work_figures
from handctl.online.clock import Hygiene
from handctl.online.loop import Outcome, StatusLine
from handctl.online.recipes.loader import load_recipe
from handctl.online.recipes.schema import Recipe
from handctl.session import RunReport, RunRequest, run_recipe
from handctl.summary_guard import require_whole

#: One line of ``bench.py --help`` (read from the source there, without importing this).
SUMMARY = "the real-time loop's lateness and misses; the tick's CPU beside a baseline tree"

ROOT = Path(__file__).resolve().parent.parent


#: ``tick_cost``'s baseline: the tree before the tick's CPU cost was cut (issue #17), the
#: first parent of that work's merge (eff65b6) and so the newest revision without the cuts.
#: Its handctl has everything ``tick_cost.py`` and ``hold_recipe.py`` import (a test holds
#: them to it); a later revision would have some of the cuts in it, an earlier one less of the
#: runtime than ``tick_cost.py`` drives. A baseline that cannot run is refused before the
#: benchmark measures anything (``baseline_problem``).
BASELINE_REV = "c130bf7"
#: s: the hold of the short run of each transport that tries the baseline out first
PROBE_SECONDS = 0.1
#: s: how long one ``tick_cost.py`` run may take, at most, and per second of its hold: a run
#: that hangs fails the benchmark with a message instead of holding it up for ever. Lockstep
#: holds of 1.5 s take a few seconds; a host loaded many times over takes many times that.
COST_RUN_TIMEOUT_S = 120.0
COST_RUN_TIMEOUT_PER_S = 60.0
TRANSPORTS = ("unix", "virtual")

#: The variants of ``--hygiene``, each adding one measure to the one before.
HYGIENE = {
    "fifo": Hygiene(pin=False, lock_memory=False, prefault=False),
    "fifo+cpus": Hygiene(pin=True, lock_memory=False, prefault=False),
    "fifo+cpus+mlock": Hygiene(pin=True, lock_memory=True, prefault=False),
    "fifo+cpus+mlock+prefault": Hygiene(),
}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--seconds", type=float, default=60.0, help="s, the length of each loop run"
    )
    parser.add_argument("--hand", type=Path, default=ROOT / "config/hands/hiroshima_hand.yaml")
    parser.add_argument(
        "--babble",
        type=int,
        default=0,
        metavar="FRAMES_PER_MS",
        help="a babbling node floods foreign ids at this rate the whole run "
        "(20 is about all a CAN-FD bus carries)",
    )
    parser.add_argument(
        "--rt",
        action="store_true",
        help="ask for SCHED_FIFO and locked memory, as `handctl run --rt`",
    )
    parser.add_argument(
        "--hygiene",
        action="store_true",
        help="with --rt: one run per real-time measure added in turn (FIFO "
        "alone, +separate CPUs, +locked memory, +prefault)",
    )
    parser.add_argument(
        "--variant",
        choices=list(HYGIENE),
        default=None,
        help=f"with --rt: the real-time measures of the run (default: {list(HYGIENE)[-1]})",
    )
    parser.add_argument(
        "--no-naive", action="store_true", help="leave out the naive asyncio.sleep baseline"
    )
    parser.add_argument(
        "--baseline",
        default=BASELINE_REV,
        metavar="REV",
        help=f"the git revision whose tick cost is measured beside this tree's "
        f"(default {BASELINE_REV}, before the cost was cut)",
    )
    parser.add_argument(
        "--tick-cost-rounds", type=int, default=3, help="runs of the two trees side by side"
    )
    parser.add_argument(
        "--tick-cost-seconds", type=float, default=1.5, help="the hold of each such run"
    )
    parser.add_argument(
        "--no-tick-cost", action="store_true", help="leave out the tick cost beside the baseline"
    )
    parser.add_argument(
        "--live",
        action="store_true",
        help="two recorded runs, without and with the live Foxglove server and "
        "a subscribed client: what the live view adds to the tick",
    )
    parser.add_argument(
        "--live-pairs",
        type=int,
        default=1,
        metavar="N",
        help="with --live: N pairs of runs, the added cost the median over them",
    )


class RunningSince:
    """The time the run proper began (the first status line with the hand running), so that
    the bare loop's stalls are counted over the same span as the loop's."""

    def __init__(self) -> None:
        self.ns: int | None = None

    def __call__(self, line: StatusLine) -> None:
        if self.ns is None and line.state == "running":
            self.ns = time.monotonic_ns()


def host_figures(
    report: RunReport, hand: HandConfig, first_tick: int, since_ns: int | None
) -> dict[str, object]:
    """The bare loop's figures over the run proper and whose the missed ticks were."""
    host = report.host
    if host is None:
        return {"host_verdict": "no record", "missed_host": -1, "missed_handctl": -1}
    proper = since(host, since_ns) if since_ns is not None else host
    verdict = judge(proper, Deadlines.of(hand))
    rows = [r for r in report.loop_stalls if r[0] >= first_tick]
    period = round(hand.bus.period_s * 1e9)
    own: list[int] = []
    shares = attribute(rows, host, period, own, report.rivals, report.loop_work)
    startup = attribute(
        [r for r in report.loop_stalls if r[0] < first_tick],
        host,
        period,
        None,
        report.rivals,
        report.loop_work,
    )
    f = verdict.figures
    return {
        "host_verdict": verdict.level,
        "host_lateness_p99_us": f["lateness_us"]["p99"],
        "host_stalls_over_period": f["stalls_over_period"],
        "host_stalls_over_overrun_tolerance": f["stalls_over_overrun_tolerance"],
        "host_longest_stall_ms": f["longest_stall_ms"],
        "host_hiccups": f["hiccups"],
        "host_slow_pieces": f["slow_pieces"],
        "host_slow_switches": f["slow_switches"],
        "host_slow_cpu_intervals": f["slow_cpu_intervals"],
        "host_longest_slow_cpu_ms": f["longest_slow_cpu_ms"],
        "host_slow_cpu_lost_ms": f["slow_cpu_lost_ms"],
        "host_work_reference_us": round(host.work_reference_ns / 1e3, 2),
        "host_switch_reference_us": round(host.switch_reference_ns / 1e3, 2),
        "host_steal_ms": host.steal_ms,
        **shares,
        "missed_handctl_at_ticks": own[:20],
        **work_figures(report.loop_work, own),
        "rivals": sorted(set(report.rivals.rivals.values())) if report.rivals else [],
        "startup_missed_handctl": startup["missed_handctl"],
    }


def since(record: ProbeRecord, start_ns: int) -> ProbeRecord:
    """The record's stalls, hiccups, slow pieces and slow switches from ``start_ns`` on, so the
    verdict over the run proper counts every kind of event over the same stretch (the
    lateness histogram stays the whole run's: it keeps no times)."""
    import dataclasses

    return dataclasses.replace(
        record,
        start_ns=max(record.start_ns, start_ns),
        stalls=tuple(s for s in record.stalls if s[2] >= start_ns),
        hiccups=tuple(h for h in record.hiccups if h[2] >= start_ns),
        slow=tuple(w for w in record.slow if w[2] >= start_ns),
        slow_switches=tuple(w for w in record.slow_switches if w[2] >= start_ns),
    )


async def _naive(period_s: float, seconds: float) -> np.ndarray:
    """The loop a first attempt writes: sleep until the next deadline with asyncio.sleep."""
    period_ns = round(period_s * 1e9)
    start = time.monotonic_ns()
    ticks = round(seconds / period_s)
    lateness = np.zeros(ticks, dtype=np.int64)
    for k in range(ticks):
        deadline = start + (k + 1) * period_ns
        await asyncio.sleep(max(0.0, (deadline - time.monotonic_ns()) / 1e9))
        lateness[k] = time.monotonic_ns() - deadline
    return lateness


def run(args: argparse.Namespace) -> dict[str, object]:
    _check_options(args)
    if args.live:
        from live_view_cost import compare

        return compare(run, args)
    # Once per benchmark: not again in each run of the live-view comparison (``record``).
    if args.no_tick_cost or getattr(args, "record", False):
        return _measure(args, None)
    with tempfile.TemporaryDirectory(prefix="handctl-baseline-") as baseline:
        # Before anything is measured: a baseline that cannot run would otherwise be found
        # out after the loop's whole run, as an error among figures of a benchmark that
        # exited 0.
        print(f"tick cost: trying the baseline {args.baseline} ...", file=sys.stderr)
        problem = baseline_problem(args.baseline, Path(baseline), args.hand)
        if problem:
            raise SystemExit(
                f"bench.py loop: the baseline {args.baseline} cannot run tools/tick_cost.py "
                f"beside this tree: {problem}\n(give --baseline a revision whose handctl has "
                f"what tools/tick_cost.py imports, as the default {BASELINE_REV} has, or "
                "--no-tick-cost)"
            )
        return _measure(args, Path(baseline))


def _check_options(args: argparse.Namespace) -> None:
    """Options that would do nothing, and a hand that is none, refused before any work: a
    --hygiene without --rt ran an ordinary loop and said nothing, and a fault list given as
    --hand was blamed on the baseline revision after it had been checked out."""
    from handctl.errors import ConfigError

    rt, live = getattr(args, "rt", False), getattr(args, "live", False)
    for option, given, needs, has in (
        ("--hygiene", getattr(args, "hygiene", False), "--rt", rt),
        ("--variant", getattr(args, "variant", None) is not None, "--rt", rt),
        ("--live-pairs", getattr(args, "live_pairs", 1) != 1, "--live", live),
    ):
        if given and not has:
            raise ConfigError(option, "", f"{needs} as well (it is a measure of {needs})", given)
    load_hand(args.hand)


def _measure(args: argparse.Namespace, baseline: Path | None) -> dict[str, object]:
    """The benchmark proper; the tick's cost beside ``baseline``, a tree already tried out,
    unless it is None. A round of it that failed all the same is in ``failed``, which makes
    ``bench.py`` exit 1."""
    hand = load_hand(args.hand)
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "hold.yaml"
        path.write_text(hold_recipe(hand, "bench_hold", args.seconds))
        recipe = load_recipe(path, hand)
        faults = None
        if args.babble:
            faults = Path(tmp) / "babble.yaml"
            faults.write_text(
                "description: a babbling node for the load benchmark\nfaults:\n"
                f"  - {{kind: babble, id: 0x050, per_tick: {args.babble}, "
                "length: 8, start: 0.0}\n"
            )
        variants = {}
        if args.hygiene and args.rt:
            for name in HYGIENE:
                print(f"hygiene {name} ...", file=sys.stderr)
                variants[name] = _variant(name, args)
            figures = dict(variants[list(HYGIENE)[-1]])
        else:
            figures = _one(
                hand,
                recipe,
                faults,
                args,
                HYGIENE[args.variant or list(HYGIENE)[-1]],
                Path(tmp) / "run.mcap",
            )
    if not args.no_naive and "lateness_p99_us" in figures:
        print(f"naive asyncio.sleep loop, {args.seconds:g} s ...", file=sys.stderr)
        naive = asyncio.run(_naive(hand.bus.period_s, args.seconds))
        naive_p99 = float(np.percentile(naive, 99)) / 1e3
        figures["naive_lateness_p99_us"] = round(naive_p99, 1)
        figures["lateness_ratio"] = round(float(figures["lateness_p99_us"]) / naive_p99, 4)  # type: ignore[arg-type]
    if baseline is not None:
        cost = tick_cost(
            args.hand, args.baseline, baseline, args.tick_cost_rounds, args.tick_cost_seconds
        )
        figures["tick_cost"] = cost
        failed = [
            f"tick_cost.{t} (baseline {args.baseline}): {cost[t]['error']}"
            for t in TRANSPORTS
            if "error" in cost[t]
        ]
        if failed:
            figures["failed"] = failed
    if variants:
        keep = (
            "lateness_p99_us",
            "missed_rate",
            "missed_host",
            "missed_host_slow_cpu",
            "missed_rival",
            "missed_host_catch_up",
            "missed_host_off_cpu",
            "missed_handctl",
            "missed_handctl_after_host",
            "startup_missed_ticks",
            "startup_missed_handctl",
            "ticks",
            "host_lateness_p99_us",
            "host_stalls_over_period",
            "host_longest_stall_ms",
            "host_slow_cpu_intervals",
            "tick_cpu_us_p99",
            "outcome",
            "rt",
        )
        figures["hygiene"] = {name: {k: v.get(k) for k in keep} for name, v in variants.items()}
    return figures


def _variant(name: str, args: argparse.Namespace) -> dict[str, object]:
    """One variant in a process of its own: what request_realtime did to this one (priority,
    CPU, locked memory) cannot be undone exactly."""
    cmd = [
        sys.executable,
        str(Path(__file__).resolve().parent / "bench.py"),
        "loop",
        "--rt",
        "--variant",
        name,
        "--seconds",
        str(args.seconds),
        "--hand",
        str(args.hand),
        "--babble",
        str(args.babble),
        "--no-naive",
        "--no-tick-cost",
    ]
    done = subprocess.run(cmd, stdout=subprocess.PIPE, text=True, check=False)
    if done.returncode != 0:
        return {"error": f"exit {done.returncode}"}
    figures: dict[str, object] = json.loads(done.stdout)
    return figures


def _one(
    hand: HandConfig,
    recipe: Recipe,
    faults: Path | None,
    args: argparse.Namespace,
    hygiene: Hygiene,
    log: Path,
) -> dict[str, object]:
    """One run; recorded to ``log`` with ``args.record``, and served live with
    ``args.live_port`` (both set by ``live_view_cost.compare``)."""
    print(
        f"real-time loop with the simulated hand, {args.seconds:g} s"
        f"{f', babble {args.babble}/ms' if args.babble else ''} ...",
        file=sys.stderr,
    )
    running = RunningSince()
    live_port = getattr(args, "live_port", None)
    record = getattr(args, "record", False) or live_port is not None
    report = run_recipe(
        RunRequest(
            hand=hand,
            recipe=recipe,
            bus="sim",
            lockstep=False,
            realtime_priority=args.rt,
            sim_faults=faults,
            hygiene=hygiene,
            log=log if record else None,
            live_port=live_port,
        ),
        status=running,
    )
    require_whole(report.summary, "the loop benchmark's run")
    for warning in report.warnings:
        print(f"warning: {warning}", file=sys.stderr)
    result = report.result
    if result.outcome is Outcome.INTERRUPTED:
        # Ctrl-C or SIGTERM stopped the run: its figures are of a fraction of it, not the
        # benchmark's (exit 0 with 117 ticks of a 20 s run, before)
        raise KeyboardInterrupt(result.message or "interrupted")
    # Ticks of the run proper: from the first command on. Before it the peer process is still
    # importing MuJoCo and building its model on the same two cores, which is start-up, not
    # the loop's steady state; the start-up misses are reported apart.
    first = max(0, report.first_send_tick)
    ours = result.lateness_ns[first:]
    missed = int(result.missed[first:].sum())
    cpu = result.stage_ns[first:].sum(axis=1)
    # What the simulated hand's frames met on the way (its own count, from its process): frames
    # that never went, the times the host's socket queue was full so frames waited, and the
    # frames lost for a receiver that fell so far behind that its transmit queue was full (on
    # the unix bus that costs the receiver, not the sender's send).
    sim = report.summary.get("sim") or {}
    transport = sim.get("transport") or {}
    return {
        **(_writer_figures(log, result.ticks * hand.bus.period_s) if record else {}),
        "seconds": args.seconds,
        "babble_per_ms": args.babble,
        "foreign_frames": result.node_rejects.get("unexpected_id", 0),
        "sim_tx_failed": int(sim.get("tx_failed", -1)),
        "sim_queue_full": int(transport.get("queue_full", -1)),
        "sim_frames_dropped": int(transport.get("frames_dropped", -1)),
        "rt": bool(args.rt and not any("refused" in w for w in report.warnings)),
        "outcome": result.outcome.value,
        "message": result.message,
        "ticks": int(ours.size),
        "lateness_p99_us": round(float(np.percentile(ours, 99)) / 1e3, 1),
        "lateness_p50_us": round(float(np.percentile(ours, 50)) / 1e3, 1),
        "missed_rate": round(missed / max(1, ours.size), 6),
        "missed_ticks": missed,
        "startup_missed_ticks": int(result.missed[:first].sum()),
        "tick_cpu_us_p99": round(float(np.percentile(cpu, 99)) / 1e3, 1),
        "tick_cpu_us_p50": round(float(np.percentile(cpu, 50)) / 1e3, 1),
        **host_figures(report, hand, first, running.ns),
        **{f"{name}_cpu_us_p99": v for name, v in report.summary["stage_cpu_us_p99"].items()},
    }


def baseline_problem(rev: str, into: Path, hand: Path) -> str:
    """Why git revision ``rev``'s handctl, extracted under ``into``, cannot run
    ``tools/tick_cost.py``, or "": a short hold on each transport, both at once, as the
    benchmark will run it (an import it lacks, a recipe or hand it reads otherwise, a runtime
    that does not complete)."""
    problem = _extract(rev, into)
    if problem:
        return problem
    started = {t: _cost_run(str(into), hand, t, PROBE_SECONDS) for t in TRANSPORTS}
    problems = []
    for transport, finish in started.items():
        result = finish()
        if "error" in result:
            problems.append(f"{transport} bus: {result['error']}")
    return "; ".join(problems)


def tick_cost(hand: Path, rev: str, baseline: Path, rounds: int, seconds: float) -> dict[str, Any]:
    """The tick's CPU per stage, this tree beside that of git revision ``rev`` (extracted in
    ``baseline``), side by side in one run (see the module's docstring); per transport
    ``error`` instead when a run of either failed."""
    trees = {"baseline": str(baseline), "current": str(ROOT)}
    runs: dict[str, dict[str, list[dict[str, Any]]]] = {
        t: {name: [] for name in trees} for t in TRANSPORTS
    }
    for k in range(rounds):
        for transport in TRANSPORTS:
            print(f"tick cost {k + 1}/{rounds}: {transport} bus ...", file=sys.stderr)
            # Both trees at once: whatever else loads the host then loads both alike.
            started = {
                name: _cost_run(tree, hand, transport, seconds) for name, tree in trees.items()
            }
            for name, finish in started.items():
                runs[transport][name].append(finish())
    out: dict[str, Any] = {"baseline": rev, "rounds": rounds, "seconds": seconds}
    for transport, by_tree in runs.items():
        failed = [r["error"] for results in by_tree.values() for r in results if "error" in r]
        if failed:
            out[transport] = {"error": failed[0]}
            continue
        summary: dict[str, Any] = {
            name: _median_figures(results) for name, results in by_tree.items()
        }
        for q in ("p50_us", "p99_us"):
            summary[f"ratio_{q.removesuffix('_us')}"] = {
                stage: round(cur[q] / base[q], 3) if base[q] > 0 else None
                for stage, cur in summary["current"].items()
                if (base := summary["baseline"][stage])
            }
        out[transport] = summary
    return out


def _extract(rev: str, into: Path) -> str:
    """The ``handctl`` package of git revision ``rev`` under ``into``; a problem, or ""."""
    archive = into / "tree.tar"
    done = subprocess.run(
        ["git", "-C", str(ROOT), "archive", "-o", str(archive), rev, "handctl"],
        capture_output=True,
        text=True,
        check=False,
    )
    if done.returncode != 0:
        return f"git archive {rev}: {done.stderr.strip() or f'exit {done.returncode}'}"
    with tarfile.open(archive) as tar:
        tar.extractall(into, filter="data")
    archive.unlink()
    return ""


def _cost_run(
    tree: str, hand: Path, transport: str, seconds: float
) -> Callable[[], dict[str, Any]]:
    """One ``tick_cost.py`` run with ``tree``'s handctl first on the path, started; the
    function returned waits for its figures."""
    cmd = [
        sys.executable,
        str(Path(__file__).resolve().parent / "tick_cost.py"),
        "--hand",
        str(hand),
        "--transport",
        transport,
        "--seconds",
        str(seconds),
    ]
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([tree, os.environ.get("PYTHONPATH", "")])}
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)

    def finish() -> dict[str, Any]:
        timeout = COST_RUN_TIMEOUT_S + COST_RUN_TIMEOUT_PER_S * seconds
        try:
            out, err = proc.communicate(timeout=timeout)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.communicate()
            return {"error": f"{tree}: no figures after {timeout:g} s (stopped)"}
        if proc.returncode != 0:
            # The traceback's last line says what failed; its path says which tree.
            lines = err.strip().splitlines() or [""]
            return {"error": f"{tree}: exit {proc.returncode}: {lines[-1][-300:]}"}
        figures: dict[str, Any] = json.loads(out)
        if figures.get("outcome") != "completed":
            return {"error": f"{tree}: {figures.get('outcome')}: {figures.get('message')}"}
        return figures

    return finish


def _median_figures(results: list[dict[str, Any]]) -> dict[str, dict[str, float]]:
    """Per stage, the median over the runs of each figure."""
    stages = [k for k, v in results[0].items() if isinstance(v, dict)]
    return {
        stage: {
            q: round(float(np.median([r[stage][q] for r in results])), 1) for q in results[0][stage]
        }
        for stage in stages
    }


def _writer_figures(log: Path, run_s: float) -> dict[str, object]:
    """What the recording's writer process took of the machine (its CPU time per second of
    run, the live server's threads included) and what it dropped, from the file's end record."""
    from handctl.recording import channels as ch
    from handctl.recording.reader import open_recording

    try:
        end = open_recording(log).metadata.get(ch.META_END, {})
    except Exception as exc:  # the figures of the loop stand without the writer's
        return {"writer_error": str(exc)}
    cpu_s = float(end.get("writer_cpu_s", "nan"))
    return {
        "writer_cpu_s": cpu_s,
        "writer_cpu_share": round(cpu_s / run_s, 4) if run_s > 0 else float("nan"),
        "writer_dropped_ticks": int(end.get("dropped_ticks", -1)),
        "writer_dropped_frames": int(end.get("dropped_frames", -1)),
    }
