"""``tools/bench.py``: ``--help`` lists the benchmarks (it was taken for a benchmark's name
and exited 2), and a benchmark whose figures say what failed exits 1, saying it on stderr,
rather than 0 with the error inside the JSON."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import types
from pathlib import Path

import pytest

from handctl.config import HandConfig

from ..conftest import ROOT, load_tool


@pytest.mark.parametrize("flag", ["--help", "-h"])
def test_help_lists_every_benchmark_with_its_line(
    flag: str, capsys: pytest.CaptureFixture[str]
) -> None:
    bench = load_tool("bench")
    assert bench.main([flag]) == 0
    out = capsys.readouterr().out
    assert out.startswith("usage: bench.py NAME")
    names = bench.available()
    assert "loop" in names and "recording" in names
    for name in names:
        summary = bench.summary(name)
        assert summary and "\n" not in summary, f"bench_{name}.py has no SUMMARY line"
        assert any(line.split() == [name, *summary.split()] for line in out.splitlines())


def test_help_from_the_command_line() -> None:
    done = subprocess.run(
        [sys.executable, str(ROOT / "tools" / "bench.py"), "--help"],
        capture_output=True,
        text=True,
        check=False,
        timeout=120,
    )
    assert done.returncode == 0, done.stderr
    assert "benchmarks:" in done.stdout and done.stderr == ""


def test_no_name_still_exits_2_and_points_at_help(capsys: pytest.CaptureFixture[str]) -> None:
    assert load_tool("bench").main([]) == 2
    assert "bench.py --help lists them" in capsys.readouterr().err


def _fake(figures: dict[str, object]) -> types.ModuleType:
    module = types.ModuleType("bench_fake", "A benchmark of the test's.")
    module.add_arguments = lambda parser: None  # type: ignore[attr-defined]
    module.run = lambda args: figures  # type: ignore[attr-defined]
    return module


@pytest.mark.parametrize(
    ("figures", "code"),
    [({"x": 1}, 0), ({"x": 1, "failed": ["tick_cost.unix: exit 1"]}, 1)],
)
def test_figures_that_hold_failures_exit_1_and_say_each(
    figures: dict[str, object],
    code: int,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    bench = load_tool("bench")
    monkeypatch.setattr(sys, "path", list(sys.path))  # main puts the tools on it
    monkeypatch.setattr(bench, "available", lambda: ["fake"])
    monkeypatch.setitem(sys.modules, "bench_fake", _fake(figures))
    assert bench.main(["fake", "--json"]) == code
    out, err = capsys.readouterr()
    assert json.loads(out) == figures
    assert err == ("bench.py fake: failed: tick_cost.unix: exit 1\n" if code else "")


@pytest.mark.parametrize(
    ("argv", "says"),
    [
        (["experiment", "--seeds", "0"], "--seeds: expected a whole number >= 1, found 0"),
        (["experiment", "--first-seed", "-1"], "--first-seed: expected a whole number >= 0"),
        (["analysis", "--tolerance", "nan"], "--tolerance: expected a finite number > 0"),
        (["sim", "--seconds", "-1"], "--seconds: expected a finite number > 0, found -1.0"),
        (["codec", "--ticks", "0"], "--ticks: expected a whole number >= 1, found 0"),
        # an IndexError after ten seconds of loop; a baseline blamed for a zero hold
        (["loop", "--tick-cost-rounds", "0"], "--tick-cost-rounds: expected a whole number"),
        (["loop", "--tick-cost-seconds", "0"], "--tick-cost-seconds: expected a finite"),
        # ran an ordinary loop and said nothing; blamed the baseline revision
        (["loop", "--hygiene"], "--hygiene: expected --rt as well"),
        (["loop", "--variant", "fifo"], "--variant: expected --rt as well"),
        (["loop", "--live-pairs", "3"], "--live-pairs: expected --live as well"),
        (
            ["loop", "--hand", str(ROOT / "config" / "sim" / "bus_trouble.yaml")],
            "expected a hand config, found a fault list",
        ),
    ],
)
def test_a_shared_option_out_of_its_range_is_bad_input_before_any_work(
    capsys: pytest.CaptureFixture[str], argv: list[str], says: str
) -> None:
    """0 seeds divided by zero after the nominal run had been simulated; a NaN tolerance went
    into the JSON as NaN, which no JSON parser takes; a negative duration was clamped and its
    target reported as met; 0 ticks was a StatisticsError."""
    assert load_tool("bench").main(argv) == 2
    assert says in capsys.readouterr().err


def test_bad_input_found_by_a_benchmark_is_said_and_exits_2(
    capsys: pytest.CaptureFixture[str],
) -> None:
    """A recipe that is not there was a ConfigError traceback, exit 1."""
    argv = ["experiment", "--seeds", "1", "--recipe", "nosuch.yaml", "--family", "all"]
    assert load_tool("bench").main(argv) == 2
    err = capsys.readouterr().err
    assert "bench.py experiment: error: nosuch.yaml: expected an existing file" in err


def _raising(what: BaseException | None = None, sig: int | None = None) -> types.ModuleType:
    module = types.ModuleType("bench_fake", "A benchmark of the test's.")
    module.add_arguments = lambda parser: None  # type: ignore[attr-defined]

    def run(args: object) -> dict[str, object]:
        if sig is not None:
            import signal

            signal.raise_signal(sig)
        if what is not None:
            raise what
        return {}

    module.run = run  # type: ignore[attr-defined]
    return module


def test_a_cluster_lost_is_a_failed_result_and_a_stop_signal_an_interrupt(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """A cluster lost mid-run was said as bad input (exit 2); SIGTERM ended the bench with 143
    and a leaked semaphore, Ctrl-C with a KeyboardInterrupt traceback."""
    import signal

    from handctl.executor import ClusterLostError

    bench = load_tool("bench")
    monkeypatch.setattr(sys, "path", list(sys.path))
    monkeypatch.setattr(bench, "available", lambda: ["fake"])
    before = signal.getsignal(signal.SIGTERM)
    try:
        monkeypatch.setitem(sys.modules, "bench_fake", _raising(ClusterLostError("tcp://h:1")))
        assert bench.main(["fake"]) == 1
        assert capsys.readouterr().err.startswith(
            "bench.py fake: failed: --scheduler tcp://h:1: the Dask scheduler was lost"
        )
        monkeypatch.setitem(sys.modules, "bench_fake", _raising(sig=signal.SIGTERM))
        assert bench.main(["fake"]) == 130
        assert capsys.readouterr().err == "bench.py fake: interrupted\n"
    finally:
        signal.signal(signal.SIGTERM, before)


@pytest.mark.parametrize(
    ("argv", "says"),
    [
        (["plan", "--models", "1000"], "--models: expected 1 to 100 models"),
        (["plan", "--workers", "100000"], "--workers: expected at most"),
        # it planned twice in this process, speedup 1.0, exit 0: nothing measured
        (["plan", "--workers", "1"], "--workers: expected a whole number >= 2, found 1"),
        # told ">= 1", then 1 refused (found by an outside audit)
        (["plan", "--workers", "0"], "--workers: expected a whole number >= 2, found 0"),
    ],
)
def test_the_plan_bench_checks_its_options_before_any_plan(
    capsys: pytest.CaptureFixture[str], argv: list[str], says: str
) -> None:
    """--workers 9 was refused only after the one-worker plan had run; --models 1000 ran."""
    assert load_tool("bench").main(argv) == 2
    err = capsys.readouterr().err
    assert says in err and "plan with" not in err


@pytest.mark.parametrize("name", ["plan", "analysis"])
def test_a_bench_without_a_scheduler_option_does_not_point_at_one(
    capsys: pytest.CaptureFixture[str], name: str
) -> None:
    """Too many workers was refused with "a cluster takes --scheduler", an option these
    benchmarks do not have."""
    assert load_tool("bench").main([name, "--workers", "100000"]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"bench.py {name}: error: --workers: expected at most "), err
    assert "--scheduler" not in err


def test_the_experiment_bench_refuses_workers_with_a_scheduler(
    capsys: pytest.CaptureFixture[str],
) -> None:
    """It ignored --workers (999 too) beside --scheduler, where handctl plan refused it."""
    argv = ["experiment", "--seeds", "1", "--workers", "999", "--scheduler", "tcp://127.0.0.1:1"]
    assert load_tool("bench").main(argv) == 2
    assert capsys.readouterr().err.startswith(
        "bench.py experiment: error: --workers: expected no --workers with --scheduler"
    )


def test_the_fault_campaign_refuses_workers_with_a_scheduler(
    capsys: pytest.CaptureFixture[str],
) -> None:
    """As every command does: it was a traceback (exit 1) for a bad option or address."""
    gen = load_tool("gen_fault_table")
    argv = ["--campaign", "--workers", "2", "--scheduler", "tcp://127.0.0.1:1"]
    assert gen.main(argv) == 2
    assert capsys.readouterr().err.startswith(
        "gen_fault_table.py: error: --workers: expected no --workers with --scheduler"
    )


def test_the_plan_bench_s_template_is_one_handctl_plan_takes(
    tmp_path: Path, hand: HandConfig
) -> None:
    """Its turn was cut to 1 s, shorter than the template's ramp once that grew to 1.5 s: the
    bench exited 2 at its first plan and measured nothing (found by an outside audit)."""
    from handctl.planning.template import load_template

    small = load_tool("bench_plan").small_template(tmp_path)
    template = load_template(small, hand)
    assert [p.name for p in template.phases] == ["approach", "lift", "envelop", "manipulate_1"]


@pytest.mark.parametrize("name", ["analysis", "experiment", "recording"])
def test_a_benchmark_s_help_on_an_ascii_stdout(name: str) -> None:
    """'×', '°' and '±' in three benchmarks' help ended in a UnicodeEncodeError under LANG=C;
    every option's default is said."""
    done = subprocess.run(
        [sys.executable, str(ROOT / "tools" / "bench.py"), name, "--help"],
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
        env={**os.environ, "PYTHONIOENCODING": "ascii"},
    )
    assert done.returncode == 0, done.stderr
    assert "Traceback" not in done.stderr
    assert "(default: " in done.stdout


def test_the_sim_bench_drives_a_hand_of_two_joint_fingers() -> None:
    """Its commands were padded to three torques a finger: 'TorqueCommand_1: expected 2
    values (Torque1, Torque2), found 3' on the planar hand."""
    from handctl.config import load_hand

    planar = load_hand(ROOT / "config" / "hands" / "planar_2f2j.yaml")
    rtf, frames_per_tick, _ = load_tool("bench_sim").bench_bus(planar, 50)
    assert rtf > 0 and frames_per_tick > 0


@pytest.mark.skipif(not Path("/dev/full").exists(), reason="no /dev/full here")
def test_figures_that_cannot_be_written_are_a_failure_said_not_a_traceback() -> None:
    with open("/dev/full", "w") as full:
        done = subprocess.run(
            [sys.executable, str(ROOT / "tools" / "bench.py"), "codec", "--ticks", "200"],
            stdout=full,
            stderr=subprocess.PIPE,
            text=True,
            timeout=300,
            check=False,
        )
    assert done.returncode == 1, done.stderr
    assert "failed: its figures could not be written" in done.stderr
    assert "Traceback" not in done.stderr


def test_the_recording_bench_s_noise_floor_has_figures_in_a_short_run() -> None:
    """A recipe shorter than the window's settling (3000 ticks: the bring-up hold recipe, 2.5
    s) left the noise floor without a sample, and the bench ended on a numpy traceback
    (found by an outside audit)."""
    bench = load_tool("bench_recording")
    window = bench.Window(1_000.0)
    for tick in range(2_500):
        window(tick)
    assert window.ns == [] and len(window.kept()) == 1_250
    for tick in range(2_500, bench.WINDOW_SETTLE + 10):
        window(tick)
    assert window.kept() == window.ns and len(window.ns) == 10
