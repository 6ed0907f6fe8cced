"""The timing check as a user runs it: the bare loop for a fraction of a second (structure, not
figures), a recorded failing sequence through the documented seam, and a run on a bus other
than the simulated hand refused before it opens the bus."""

from __future__ import annotations

import contextlib
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import pytest

from handctl.config import HandConfig
from handctl.hostcheck import INJECT_ENV, Probe
from handctl.online.bus import open_bus

from ..conftest import ROOT, handctl
from .realtime import REALTIME

RECIPE = "config/recipes/swap_two_cylinders.yaml"
#: Recorded on a two-vCPU virtual machine: `handctl check --timing --seconds 60 --json F`.
FAILING = ROOT / "tests" / "data" / "host_stalls_failing.json"


def _bare_loop_record() -> dict[str, Any]:
    """0.4 s of the bare loop at 1 kHz that keeps every piece and switch at least as slow as
    its first 200's median (``--slow-factor 1``)."""
    done = subprocess.run(
        [
            sys.executable,
            "-m",
            "handctl.hostprobe",
            "--period-ns",
            "1000000",
            "--seconds",
            "0.4",
            "--record-ns",
            "500000",
            "--hiccup-ns",
            "100000",
            "--slow-factor",
            "1",
        ],
        cwd=ROOT,
        text=True,
        capture_output=True,
        timeout=60,
        check=False,
    )
    assert done.returncode == 0, done.stderr
    out: dict[str, Any] = json.loads(done.stdout)
    return out


def test_the_bare_loop_reports_every_wakeup() -> None:
    # Later pieces and switches as slow as the first 200's median come in any run but one
    # whose start was the slowest stretch of it (a load that eased): tried again then.
    for _ in range(3):
        out = _bare_loop_record()
        if out["work"]["slow"] and out["work"]["slow_switches"]:
            break
    assert out["wakeups"] > 0
    assert sum(out["lateness_hist_us"].values()) == out["wakeups"]
    assert out["expirations"] >= out["wakeups"]
    assert out["end_ns"] > out["start_ns"]
    for index, due, wake, missed in out["stalls"]:
        assert 0 <= index < out["wakeups"] and wake - due >= 500_000 and missed >= 0
    assert out["scheduler"]["policy"] == "SCHED_OTHER"  # no --priority: none asked
    for index, due, wake in out["hiccups"]:
        assert 0 <= index < out["wakeups"] and 100_000 <= wake - due < 500_000
    # The piece of work on each wake-up: calibrated, its usual time measured on the first 200
    # wake-ups, then every piece at least that long (--slow-factor 1) kept with its times.
    work = out["work"]
    assert work["iterations"] > 0 and work["pieces"] == out["wakeups"]
    assert work["reference_ns"] > 0
    assert work["slow"], work
    for index, start, end, cpu in work["slow"]:
        assert 200 <= index < out["wakeups"] and end - start >= work["reference_ns"]
        assert cpu > 0
    # So is the switch before each piece (asleep on the timer and back), by its CPU time.
    assert work["switch_reference_ns"] > 0
    assert work["slow_switches"], work
    stalled = {row[0] for row in out["stalls"]}
    for index, due, wake, cpu in work["slow_switches"]:
        assert 200 <= index < out["wakeups"] and index not in stalled
        assert wake >= due and cpu >= work["switch_reference_ns"]


def test_check_timing_prints_a_verdict_and_writes_its_record(tmp_path: Path) -> None:
    report = tmp_path / "timing.json"
    done = handctl("check", "--timing", "--seconds", "0.3", "--json", str(report))
    assert done.returncode in (0, 5), done.stderr  # this machine's verdict is not the test's
    assert done.stdout.startswith("timing check: ")
    assert "stalls longer than one period (1 ms)" in done.stdout
    data = json.loads(report.read_text())
    assert data["verdict"] in ("pass", "marginal", "fail")
    assert (done.returncode == 5) == (data["verdict"] == "fail")
    assert set(data["lateness_us"]) == {"p50", "p99", "max"}
    for key in (
        "stalls_over_period",
        "stalls_over_overrun_tolerance",
        "stalls_over_feedback_timeout",
        "loop_overrun_trips",
        "hiccups",
        "slow_pieces",
        "slow_switches",
        "slow_cpu_intervals",
        "slow_cpu_intervals_over_half_period",
    ):
        assert isinstance(data[key], int)
    assert "  slow CPU: " in done.stdout
    assert (data["period_ms"], data["overrun_tolerance_ms"], data["feedback_timeout_ms"]) == (
        1.0,
        3.0,
        5.0,
    )
    assert data["realtime"] is True and data["scheduler"]["policy"]
    assert {"preemption", "rtprio_limit", "isolated", "governors"} <= set(data["facts"])
    assert data["probe"]["wakeups"] > 0


def test_a_recorded_failing_sequence_fails_the_check() -> None:
    done = handctl("check", "--timing", "--seconds", "0.2", env={INJECT_ENV: str(FAILING)})
    assert done.returncode == 5, done.stdout + done.stderr
    assert done.stdout.startswith("timing check: FAIL")
    assert f"injected from {FAILING}" in done.stdout
    assert "LOOP_OVERRUN" in done.stdout


def test_a_bad_recorded_sequence_is_bad_input(tmp_path: Path) -> None:
    bad = tmp_path / "bad.json"
    data = json.loads(FAILING.read_text())
    data["probe"]["stalls"][0] = [1, 2, 3]
    bad.write_text(json.dumps(data))
    done = handctl("check", "--timing", "--seconds", "0.2", env={INJECT_ENV: str(bad)})
    assert done.returncode == 2
    assert f"{bad}: probe.stalls[0]: expected [index, due_ns, wake_ns, missed]" in done.stderr


def test_a_recorded_sequence_of_another_loop_or_nested_past_json_is_bad_input(
    tmp_path: Path,
) -> None:
    """A probe of another loop's period was judged against this hand's deadlines, and a file
    nested 100 000 deep ended in a traceback (RecursionError), exit 1."""
    other = tmp_path / "other.json"
    data = json.loads(FAILING.read_text())
    data["probe"]["period_ns"] = 1
    other.write_text(json.dumps(data))
    done = handctl("check", "--timing", "--seconds", "0.2", env={INJECT_ENV: str(other)})
    assert done.returncode == 2, done.stderr
    assert (
        f"{other}: probe.period_ns: expected the hand's loop period, 1000000 ns ({INJECT_ENV}), "
        "found 1"
    ) in done.stderr
    deep = tmp_path / "deep.json"
    deep.write_text("[" * 100_000 + "]" * 100_000)
    done = handctl("check", "--timing", "--seconds", "0.2", env={INJECT_ENV: str(deep)})
    assert done.returncode == 2, done.stderr
    assert f"{deep}: expected valid JSON ({INJECT_ENV}), found arrays or objects nested" in (
        done.stderr
    )


def test_a_recorded_sequence_that_is_a_fifo_is_refused_not_waited_on(tmp_path: Path) -> None:
    """A FIFO named by the variable held the check in its open() until Ctrl-C; another
    file's mistake did not say the variable had named it."""
    fifo = tmp_path / "fifo"
    os.mkfifo(fifo)
    done = handctl("check", "--timing", "--seconds", "0.2", env={INJECT_ENV: str(fifo)})
    assert done.returncode == 2, done.stderr
    assert f"{fifo}: expected a regular file (a readable JSON file ({INJECT_ENV}))" in done.stderr
    text = tmp_path / "not.json"
    text.write_text("timing: no\n")
    done = handctl("check", "--timing", "--seconds", "0.2", env={INJECT_ENV: str(text)})
    assert done.returncode == 2 and f"expected valid JSON ({INJECT_ENV})" in done.stderr
    missing = tmp_path / "no-such.json"
    done = handctl("check", "--timing", "--seconds", "0.2", env={INJECT_ENV: str(missing)})
    assert done.returncode == 2, done.stderr
    assert (
        f"{missing}: expected an existing file (a readable JSON file ({INJECT_ENV}))" in done.stderr
    )


def test_a_run_on_a_real_bus_is_refused_on_a_failing_host(tmp_path: Path, hand: HandConfig) -> None:
    directory = tmp_path / "bus"
    with open_bus(f"unix:{directory}", hand.bus) as listener:
        before = set(directory.iterdir())
        done = handctl(
            "run", "recipe", RECIPE, "--bus", f"unix:{directory}", env={INJECT_ENV: str(FAILING)}
        )
        assert done.returncode == 5, done.stderr
        assert "handctl: refused: timing check: FAIL" in done.stderr
        assert "--accept-missed-deadlines" in done.stderr
        # The bus was never opened: no socket of the run's appeared, nothing arrived.
        assert set(directory.iterdir()) == before
        assert listener.drain() == []

        # Accepting the risk by name gets past the check to the bus, where nobody answers.
        out = tmp_path / "out.json"
        done = handctl(
            "run",
            "recipe",
            RECIPE,
            "--bus",
            f"unix:{directory}",
            "--accept-missed-deadlines",
            "--summary-json",
            str(out),
            env={INJECT_ENV: str(FAILING)},
        )
        assert done.returncode == 3, done.stderr
        assert "running with --accept-missed-deadlines on a host that failed" in done.stderr
        assert "nodes not ready" in done.stderr
        check = json.loads(out.read_text())["host_check"]  # the run says what it accepted
        assert check["verdict"] == "fail" and check["injected"][0]["verdict"] == "fail"


HOLD = """
recipe: hold
description: close the hand gently and hold it
phases:
  - name: hold
    torques: [0.06, 0.05, 0.03, 0.06, 0.05, 0.03, -0.06, -0.05, -0.03]
    ramp_s: 0.3
    max_s: 30.0
    on_timeout: next
"""


@REALTIME
@pytest.mark.skipif(len(os.sched_getaffinity(0)) < 2, reason="one CPU: nothing to separate")
def test_a_real_time_run_says_what_the_host_did_when_it_stops(tmp_path: Path) -> None:
    """On the simulated hand the host's verdict is a warning beside the stop; with --rt the
    loop and the simulated hand run on CPUs of their own."""
    recipe = tmp_path / "hold.yaml"
    recipe.write_text(HOLD)
    out = tmp_path / "out.json"
    done = handctl(
        "run",
        "recipe",
        str(recipe),
        "--realtime",
        "--rt",
        "--max-seconds",
        "40",
        "--sim-faults",
        "config/sim/feedback_dropout.yaml",
        "--summary-json",
        str(out),
    )
    summary = json.loads(out.read_text())
    assert done.returncode == 3, done.stderr
    # The dropout stops it on FEEDBACK_TIMEOUT, unless this loaded machine stopped it first.
    stops = sorted({f["code"] for f in summary["faults"]} & {"FEEDBACK_TIMEOUT", "LOOP_OVERRUN"})
    assert stops, summary["faults"]
    assert (
        f"the run stopped on {', '.join(stops)}; the bare timer loop beside it says the "
        "host was " in done.stderr
    )
    assert "host (bare timer loop beside the run): " in done.stdout
    host = summary["host"]
    assert host["verdict"] in ("pass", "marginal", "fail")
    # every missed tick in one share: the catch-up and off-CPU shares are the host's too
    # (``hostcheck.attribute``); left out of this sum, a loaded run that had them failed here
    assert (
        host["missed_host"]
        + host["missed_host_slow_cpu"]
        + host["missed_rival"]
        + host["missed_host_catch_up"]
        + host["missed_host_off_cpu"]
        + host["missed_handctl"]
        + host["missed_unobserved"]
        == summary["missed_ticks"]
    )
    assert host["probe_period_us"] == 500.0
    loop, sim = host["cpus"]["loop"], host["cpus"]["sim"]
    assert len(loop) == 1 and len(sim) == 1 and loop != sim
    if host["scheduler"]["policy"] == "SCHED_FIFO":  # root, or granted rtprio
        assert host["scheduler"]["cpus"] == loop  # the bare loop shares the loop's CPU
    # A second bare loop watches the simulated hand's CPU, for a feedback that came late.
    assert host["sim_cpu"]["cpus"] == sim
    assert host["sim_cpu"]["verdict"] in ("pass", "marginal", "fail")
    if "FEEDBACK_TIMEOUT" in stops:
        assert f"on the simulated hand's CPU {sim} the host was " in done.stderr


def test_cpus_outside_the_machine_are_bad_input() -> None:
    done = handctl("run", "recipe", RECIPE, "--realtime", "--rt", "--loop-cpu", "4096")
    assert done.returncode == 2
    assert "--loop-cpu: expected one of the CPUs this process may use" in done.stderr
    assert "found 4096" in done.stderr


def test_a_named_virtual_bus_counts_as_a_real_one() -> None:
    """handctl cannot know what is at the other end of a bus: only its own simulated hand
    runs without the check."""
    done = handctl(
        "run",
        "recipe",
        RECIPE,
        "--bus",
        "virtual:handctl-test-precheck",
        env={INJECT_ENV: str(FAILING)},
    )
    assert done.returncode == 5, done.stderr
    assert "handctl: refused: timing check: FAIL" in done.stderr


def test_a_check_of_no_length_is_bad_input(tmp_path: Path) -> None:
    done = handctl("check", "--timing", "--seconds", "0")
    assert done.returncode == 2
    assert "--seconds: expected a number of seconds >= 0.01 and <= 3600, found 0.0" in done.stderr
    tiny = handctl("check", "--timing", "--seconds", "1e-300")  # a verdict on no tick
    assert tiny.returncode == 2 and "found 1e-300" in tiny.stderr
    # relative, so that the message holds all of it: a value over 80 characters is cut there,
    # and a worker's temporary directory is long
    nowhere = Path("missing", "t.json")
    done = handctl("check", "--timing", "--json", str(nowhere), cwd=tmp_path)
    assert done.returncode == 2
    assert f"--json: expected a file in an existing directory, found '{nowhere}'" in done.stderr


_ORPHANING_PARENT = """
import os, subprocess, sys
probe = subprocess.Popen([sys.executable, "-m", "handctl.hostprobe", "--period-ns", "1000000",
                          "--parent-pid", str(os.getpid())], stdout=subprocess.DEVNULL)
print(probe.pid, flush=True)
sys.stdin.readline()  # until the test has seen the probe run
os._exit(0)  # as SIGKILL would: no clean-up
"""


def test_the_bare_loop_ends_with_the_run_that_started_it() -> None:
    """A run killed with SIGKILL must not leave a SCHED_FIFO loop behind."""
    parent = subprocess.Popen(
        [sys.executable, "-c", _ORPHANING_PARENT],
        cwd=ROOT,
        text=True,
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
    )
    assert parent.stdout is not None and parent.stdin is not None
    pid = int(parent.stdout.readline())
    try:
        for _ in range(200):  # the probe is up once it has its own command line
            if b"hostprobe" in Path(f"/proc/{pid}/cmdline").read_bytes():
                break
            time.sleep(0.05)
        parent.communicate("go\n", timeout=30)
        for _ in range(200):
            if not _alive(pid):
                break
            time.sleep(0.05)
        assert not _alive(pid)
    finally:
        if _alive(pid):
            os.kill(pid, signal.SIGKILL)


def _alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state != "Z"


#: A real-time task that runs 10 ms in every 60 ms on CPU 0 at SCHED_FIFO 1 (below any of
#: handctl's), or exits 77 where real-time priority is refused.
RIVAL = """
import os, sys, time
try:
    os.sched_setaffinity(0, {0})
    os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(1))
except OSError:
    sys.exit(77)
print("ready", flush=True)
end = time.monotonic() + 20
while time.monotonic() < end:
    busy = time.monotonic() + 0.01
    while time.monotonic() < busy:
        pass
    time.sleep(0.05)
"""


@REALTIME  # beside the other real-time tests, not among them: their tasks are rivals too
def test_the_watcher_sees_a_real_time_rival_run_on_the_loops_cpu() -> None:
    from handctl.rivals import RivalWatch

    rival = subprocess.Popen([sys.executable, "-c", RIVAL], stdout=subprocess.PIPE, text=True)
    try:
        assert rival.stdout is not None
        if rival.stdout.readline().strip() != "ready":
            rival.wait(timeout=10)
            pytest.skip(f"real-time priority refused here (exit {rival.returncode})")
        with RivalWatch(0, 1, []) as watch:
            time.sleep(1.3)  # two looks at least
            seen = watch.stop()
        with RivalWatch(1, 1, [rival.pid]) as watch:  # excluded: not seen
            time.sleep(0.6)
            unseen = watch.stop()
        with RivalWatch(0, 1, [], family=os.getpid()) as watch:  # this process's: not seen
            time.sleep(1.3)
            own = watch.stop()
    finally:
        rival.kill()
        rival.communicate()
    label = f"python (pid {rival.pid}, tid {rival.pid}, SCHED_FIFO 1)"
    assert label in seen.rivals.values()
    ran = [s for s in seen.spans if s[2] == rival.pid]
    assert ran and all(r[3] > 0 for r in ran)
    # Another real-time task of the machine may have run in the same look as well.
    assert label in seen.active(ran[0][0], ran[0][1])
    assert rival.pid not in unseen.rivals
    assert rival.pid not in own.rivals


@REALTIME  # at SCHED_FIFO for a moment: not beside the other real-time tests
def test_helpers_leave_a_callers_real_time_policy_behind(tmp_path: Path, hand: HandConfig) -> None:
    """Under a caller's ``chrt -f 90`` the bare loop without --rt, the rivals' watcher and the
    simulated hand without --rt inherited SCHED_FIFO 90: above the loop they serve, and the
    hand then blamed as the run's rival. Each is at the ordinary scheduler from its start."""
    from handctl.online.recipes.loader import load_recipe
    from handctl.rivals import RivalWatch
    from handctl.session import RunRequest, SimProcess

    request = RunRequest(hand=hand, recipe=load_recipe(ROOT / RECIPE, hand))
    with contextlib.ExitStack() as stack:
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(1))
        except PermissionError:
            pytest.skip("real-time priority refused here")
        try:  # at SCHED_FIFO only while the helpers start (they inherit it from fork on)
            probe = stack.enter_context(Probe(1_000_000, record_ns=500_000, seconds=0.3))
            watch = stack.enter_context(RivalWatch(None, 1, []))
            sim = stack.enter_context(SimProcess(request, str(tmp_path)))
        finally:
            os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
        for helper in (probe.proc, watch.proc, sim.proc):
            assert os.sched_getscheduler(helper.pid) == os.SCHED_OTHER, helper.args
        assert probe.stop().scheduler["policy"] == "SCHED_OTHER"
        watch.close()
        watch.proc.communicate()  # its pipes closed: it measured nothing worth reading


def _children(pid: int) -> list[int]:
    """The processes ``pid`` started (Linux: /proc/PID/task/*/children)."""
    found: list[int] = []
    for task in Path(f"/proc/{pid}/task").iterdir():
        with contextlib.suppress(OSError):
            found += [int(c) for c in (task / "children").read_text().split()]
    return found


def test_a_check_whose_probe_is_stopped_from_outside_gives_no_verdict() -> None:
    """A SIGTERM to the bare loop from outside ends it early and cleanly, as handctl's own
    stop does: a check of 2 s of the 30 asked gave its verdict as if whole."""
    path = os.pathsep.join(p for p in (str(ROOT), os.environ.get("PYTHONPATH", "")) if p)
    proc = subprocess.Popen(
        [sys.executable, "-m", "handctl", "check", "--timing", "--seconds", "30", "--no-rt"],
        cwd=ROOT,
        env={**os.environ, "PYTHONPATH": path},
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        deadline = time.monotonic() + 60
        probes: list[int] = []
        while not probes and time.monotonic() < deadline and proc.poll() is None:
            time.sleep(0.2)
            probes = _children(proc.pid)
        assert probes, "the check started no probe"
        time.sleep(1.0)  # let it measure a little, as a user's stray kill would
        for pid in probes:
            os.kill(pid, signal.SIGTERM)
        out, err = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 1, out + err
    assert "the timing probe was stopped after" in err and "of the 30 s asked" in err
    assert not any(word in out for word in ("PASS", "MARGINAL", "FAIL"))  # no verdict


def test_a_bare_loop_below_the_loop_says_nothing_of_whose_the_misses_were(
    hand: HandConfig,
) -> None:
    """A host that grants the loop SCHED_FIFO 80 but not the bare loop its 81 left the bare
    loop at SCHED_OTHER below the loop, whose own ticks then held it: "163 the host's, 0
    handctl's", the refusal only in the JSON. A bare loop below a real-time loop judges
    nobody's misses, and says so."""
    from handctl.hostcheck import LoopWork, host_summary
    from handctl.online.clock import LOOP_PRIORITY, StallLog
    from handctl.online.safety.faults import Fault, FaultCode

    now = time.monotonic_ns()
    loop = StallLog(500_000)
    loop.add(5, now, now + 120 * 10**9, 120_000)  # spans the whole of the bare loop's run
    warnings: list[str] = []
    work = LoopWork({}, 300_000, realtime=True, priority=LOOP_PRIORITY)
    with Probe(1_000_000, record_ns=500_000, seconds=0.3) as probe:  # SCHED_OTHER: no priority
        record, _, summary = host_summary(
            hand, probe, loop, [Fault(FaultCode.LOOP_OVERRUN, "", 5)], warnings, work=work
        )
    assert record is not None and record.scheduler["policy"] == "SCHED_OTHER"
    assert summary["missed_unobserved"] == 120_000
    assert summary["missed_host"] == summary["missed_handctl"] == 0
    assert "not above the control loop's real-time priority 80" in summary["attribution_void"]
    assert summary["attribution_void"] in warnings
    assert any("ran below the loop, so it says nothing of the host" in w for w in warnings)
