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
    assert [p["name"] for p in summary["phases"]][:2] == ["approach", "close"]
    assert all(p["end_s"] is not None and p["exit"] for p in summary["phases"])
    assert summary["faults"] == []
    assert summary["ticks"] > 10_000 and summary["missed_ticks"] == 0
    assert set(summary["lateness_us"]) == {"p50", "p99", "max"}
    assert set(summary["max_abs_tau"]) == {f"f{f}_j{j}" for f in (1, 2, 3) for j in (1, 2, 3)}
    objects = summary["sim"]["objects"]
    assert set(objects) == {"cyl1", "cyl2"}
    assert "completed" in done.stdout


def test_bad_recipe_exits_2_before_anything_is_sent(tmp_path: Path) -> None:
    text = (ROOT / RECIPE).read_text().replace("f1_j2: 0.25", "f1_j2: 0.55", 1)
    bad = tmp_path / "bad.yaml"
    bad.write_text(text)
    done = handctl("run", "recipe", str(bad))
    assert done.returncode == 2
    assert f"{bad}: phases[" in done.stderr and "torques.f1_j2" in done.stderr
    assert "0.45 N·m" in done.stderr and "0.55" in done.stderr


def test_sigint_is_a_controlled_stop(tmp_path: Path) -> None:
    out = tmp_path / "out.json"
    proc = subprocess.Popen(
        [sys.executable, "-m", "handctl", "run", "recipe", RECIPE, "--realtime",
         "--summary-json", str(out)], cwd=ROOT, text=True, stdout=subprocess.PIPE,
        stderr=subprocess.PIPE)
    try:
        time.sleep(2.5)  # imports, start-up, and into the recipe
        proc.send_signal(signal.SIGINT)
        _, stderr = proc.communicate(timeout=60)
    finally:
        proc.kill()
    assert proc.returncode == 130, stderr
    summary = json.loads(out.read_text())
    assert summary["outcome"] == "interrupted"
    assert summary["mode"] == "realtime"
    assert "stopped" in stderr
    # The nodes were left disabled, at zero torque, by the host, not by their watchdogs.
    nodes = summary["sim"]["nodes"]
    assert all(n["state"] == "DISABLED" and n["fault_bits"] == 0 for n in nodes.values())
