"""`handctl run recipe` as a user runs it: the summary, the exit codes, and Ctrl-C."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time
from pathlib import Path

from ..conftest import ROOT

RECIPE = "config/recipes/swap_two_cylinders.yaml"


def handctl(*args: str, timeout: float = 300) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "handctl", *args], cwd=ROOT, text=True,
                          capture_output=True, timeout=timeout, check=False)


def test_main_job_completes_with_a_summary(tmp_path: Path) -> None:
    out = tmp_path / "out.json"
    done = handctl("run", "recipe", RECIPE, "--summary-json", str(out))
    assert done.returncode == 0, done.stderr
    summary = json.loads(out.read_text())
    assert summary["completed"] is True
    assert summary["mode"] == "lockstep"
    import yaml

    wanted = [p["name"] for p in yaml.safe_load((ROOT / RECIPE).read_text())["phases"]]
    assert [p["name"] for p in summary["phases"]] == wanted
    assert all(p["end_s"] is not None and p["exit"] for p in summary["phases"])
    assert summary["faults"] == []
    assert summary["ticks"] > 10_000 and summary["missed_ticks"] == 0
    assert set(summary["lateness_us"]) == {"p50", "p99", "max"}
    assert set(summary["max_abs_tau"]) == {f"f{f}_j{j}" for f in (1, 2, 3) for j in (1, 2, 3)}
    objects = summary["sim"]["objects"]
    assert set(objects) == {"cyl1", "cyl2"}
    assert "completed" in done.stdout


def test_bad_recipe_exits_2_before_anything_is_sent(tmp_path: Path) -> None:
    import yaml

    data = yaml.safe_load((ROOT / RECIPE).read_text())
    torques = data["phases"][1]["torques"]
    if isinstance(torques, dict):
        torques["f1_j2"] = 0.55
    else:
        torques[1] = 0.55
    bad = tmp_path / "bad.yaml"
    bad.write_text(yaml.safe_dump(data))
    done = handctl("run", "recipe", str(bad))
    assert done.returncode == 2
    assert f"{bad}: phases[1].torques.f1_j2" in done.stderr
    assert "0.45 N·m" in done.stderr and "0.55" in done.stderr


HOLD_LONG = """
recipe: hold_long
phases:
  - name: hold
    torques: [0.06, 0.05, 0.03, 0.06, 0.05, 0.03, -0.06, -0.05, -0.03]
    ramp_s: 0.3
    max_s: 600
"""


def test_sigint_is_a_controlled_stop(tmp_path: Path) -> None:
    """Lockstep, so the stop is judged on behaviour alone, whatever the machine's load."""
    out = tmp_path / "out.json"
    recipe = tmp_path / "hold.yaml"
    recipe.write_text(HOLD_LONG)
    proc = subprocess.Popen(
        [sys.executable, "-m", "handctl", "run", "recipe", str(recipe), "--summary-json",
         str(out)], cwd=ROOT, text=True, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    try:
        time.sleep(3.0)  # imports, start-up, and into the (ten-minute) phase
        proc.send_signal(signal.SIGINT)
        _, stderr = proc.communicate(timeout=60)
    finally:
        proc.kill()
    assert proc.returncode == 130, stderr
    summary = json.loads(out.read_text())
    assert summary["outcome"] == "interrupted"
    assert summary["phases"][0]["exit"].startswith("stopped")
    assert "stopped" in stderr
    # The nodes were left disabled, at zero torque, by the host, not by their watchdogs.
    nodes = summary["sim"]["nodes"]
    assert all(n["state"] == "DISABLED" and n["fault_bits"] == 0 for n in nodes.values())


def test_realtime_run_on_the_simulated_hand_in_its_own_process(tmp_path: Path) -> None:
    """The real-time path: timerfd ticks, the simulated hand as a separate process on the unix
    datagram bus. --rt asks for SCHED_FIFO so other load cannot starve the loop (where the
    system refuses, the run says so and goes on)."""
    out = tmp_path / "out.json"
    recipe = tmp_path / "hold.yaml"
    recipe.write_text(HOLD_LONG)
    done = handctl("run", "recipe", str(recipe), "--realtime", "--rt", "--max-seconds", "1.5",
                   "--summary-json", str(out))
    summary = json.loads(out.read_text())
    assert done.returncode == 130, done.stderr  # ended by its time budget: a controlled stop
    assert summary["mode"] == "realtime"
    assert summary["outcome"] == "interrupted"
    assert summary["ticks"] >= 1400
    nodes = summary["sim"]["nodes"]
    assert all(n["state"] == "DISABLED" and n["fault_bits"] == 0 for n in nodes.values())
