"""``handctl plan`` at scale: the same recipe byte for byte with one worker, two, and a real
Dask cluster; Ctrl-C stops the plan and every process it started."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import psutil
import pytest
import yaml

from handctl.config import HandConfig
from handctl.executor import open_pool
from handctl.planning.compile import plan_recipe, quick_budget, recipe_text
from handctl.planning.template import load_template

from ..conftest import ROOT

TEMPLATE = ROOT / "config" / "recipes" / "swap_two_cylinders.template.yaml"
#: the smallest template that plans, and its hand
PLANAR = ROOT / "config" / "recipes" / "planar_lift_turn.template.yaml"
PLANAR_HAND = ROOT / "config" / "hands" / "planar_2f2j.yaml"


def tiny_template(tmp_path: Path) -> Path:
    """The shipped template cut to the approach and a short lift: the least that searches."""
    data: dict[str, Any] = yaml.safe_load(TEMPLATE.read_text())
    data["search"]["random_seeds"] = 1  # a draw from the plan's generator before the search's
    phases = data["phases"]
    phases[0]["max_s"] = 0.5
    phases[1]["max_s"] = 0.3
    data["phases"] = phases[:2]
    path = tmp_path / "tiny.template.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def plan_command(template: Path, out: Path, *options: str) -> list[str]:
    return [
        sys.executable,
        "-m",
        "handctl",
        "plan",
        str(template),
        "-o",
        str(out),
        "--quick",
        "--models",
        "2",
        *options,
    ]


def body(path: Path) -> str:
    """The compiled recipe without its header (which names the output file)."""
    return "".join(path.read_text().splitlines(keepends=True)[2:])


def test_the_recipe_is_the_same_with_one_worker_and_with_two(
    tmp_path: Path, hand: HandConfig
) -> None:
    template = load_template(tiny_template(tmp_path), hand)
    texts = []
    for workers in (1, 2):
        with open_pool(workers) as pool:
            result = plan_recipe(template, hand, models=2, budget=quick_budget(), executor=pool)
        texts.append(recipe_text(result, "cmd"))
    assert texts[0] == texts[1]
    search = yaml.safe_load(texts[0])["phases"][1]["provenance"]["search"]
    assert search["models"] == 2
    assert search["evaluated"] == len(search["seed_scores"]) + 2  # 1 generation of 2


def test_a_plan_on_a_dask_cluster_equals_the_local_pools(tmp_path: Path, hand: HandConfig) -> None:
    distributed = pytest.importorskip("distributed")
    template = tiny_template(tmp_path)
    remote = tmp_path / "remote.yaml"
    with distributed.LocalCluster(
        n_workers=2, threads_per_worker=1, processes=True, dashboard_address=":0", scheduler_port=0
    ) as cluster:
        done = subprocess.run(
            plan_command(template, remote, "--scheduler", cluster.scheduler_address),
            cwd=ROOT,
            text=True,
            capture_output=True,
            timeout=300,
            check=False,
        )
        assert done.returncode == 0, done.stderr
        assert "planning on the Dask cluster at tcp://" in done.stderr
        assert "(2 workers)" in done.stderr
        assert "s CPU (this process only, not the cluster's workers) on the Dask" in done.stdout
        with distributed.Client(cluster.scheduler_address) as client:
            # the tasks ran in the cluster's worker processes: they built the models there
            kept = client.run(_kept_models)
        assert sum(kept.values()) >= 2, kept
    with open_pool(2) as pool:
        local = plan_recipe(
            load_template(template, hand), hand, models=2, budget=quick_budget(), executor=pool
        )
    assert body(remote) == recipe_text(local, "cmd").split("\n", 2)[2]


def test_a_worker_whose_environment_asks_for_an_opengl_mujoco_cannot_load_plans(
    tmp_path: Path,
) -> None:
    """A Dask worker never runs handctl's command line, which turns MuJoCo's OpenGL off: one
    started with ``MUJOCO_GL=osmesa`` on a machine without OSMesa passed the cluster check,
    died of its first task (``import mujoco`` raised as the task was unpickled), and the plan
    said 30 s later that the cluster had no worker (an outside audit). A value MuJoCo does not
    know fails its import on every machine; the task turns the OpenGL off itself."""
    distributed = pytest.importorskip("distributed")
    out = tmp_path / "r.yaml"
    with distributed.LocalCluster(
        n_workers=1,
        threads_per_worker=1,
        processes=True,
        dashboard_address=":0",
        scheduler_port=0,
        env={"MUJOCO_GL": "no-such-renderer"},
    ) as cluster:
        done = subprocess.run(
            [
                sys.executable,
                "-m",
                "handctl",
                "plan",
                str(PLANAR),
                "--hand",
                str(PLANAR_HAND),
                "-o",
                str(out),
                "--quick",
                "--models",
                "2",
                "--scheduler",
                cluster.scheduler_address,
            ],
            cwd=ROOT,
            text=True,
            capture_output=True,
            timeout=300,
            check=False,
        )
    assert done.returncode == 0, done.stderr
    assert "(1 worker)" in done.stderr
    assert out.exists()


def test_each_thread_of_a_worker_has_its_own_episodes(hand: HandConfig) -> None:
    """A worker of two threads (``dask worker``'s default is one per core) ran two tasks of
    one model on one kept episode, one MuJoCo state, at once: plans that exited 0 with
    scores other than the same plan's on one thread, FatalErrors and segfaults (found by an
    outside audit). Each thread keeps its own; within one the episode is built once."""
    import threading

    from handctl.planning.phase_task import World, episode_of, kept_models
    from handctl.sim.params import parse_sim

    template = load_template(TEMPLATE, hand)
    world = World.of(hand, parse_sim(hand), template.objects, None, template.pairs)
    mine = episode_of(world)
    assert episode_of(world) is mine  # kept: built once per thread
    theirs: list[object] = []
    other = threading.Thread(target=lambda: theirs.append(episode_of(world)))
    other.start()
    other.join()
    assert theirs and theirs[0] is not mine
    assert kept_models() >= 2


def _kept_models() -> int:
    from handctl.planning import phase_task

    return phase_task.kept_models()


#: Starts the rest of its command line with SIGINT ignored, as a background job of a script
#: is started: the ignored disposition survives exec, and Ctrl-C must still stop handctl.
SIGINT_IGNORED = [
    sys.executable,
    "-c",
    "import os, signal, sys; signal.signal(signal.SIGINT, signal.SIG_IGN); "
    "os.execv(sys.executable, [sys.executable, *sys.argv[1:]])",
]


def test_ctrl_c_stops_the_plan_and_all_its_workers(tmp_path: Path) -> None:
    out = tmp_path / "r.yaml"
    proc = subprocess.Popen(
        [
            *SIGINT_IGNORED,
            "-m",
            "handctl",
            "plan",
            str(TEMPLATE),
            "-o",
            str(out),
            "--models",
            "2",
            "--workers",
            "2",
        ],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        parent = psutil.Process(proc.pid)
        children: list[psutil.Process] = []
        deadline = time.monotonic() + 240.0
        while time.monotonic() < deadline and proc.poll() is None:
            # the workers exist once the first phase has been submitted to them
            children = [c for c in parent.children(recursive=True) if c.is_running()]
            workers = [
                c
                for c in children
                if "multiprocessing" in " ".join(_cmdline(c))
                and "resource_tracker" not in " ".join(_cmdline(c))
            ]
            if len(workers) >= 2:
                break
            time.sleep(0.2)
        assert proc.poll() is None, proc.communicate()[1]
        assert len(workers) >= 2, [_cmdline(c) for c in children]
        time.sleep(1.0)  # let the workers be busy with a phase
        children = parent.children(recursive=True)
        os.kill(proc.pid, signal.SIGINT)
        _, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()  # reaps it and closes its pipes, which a later test's collection
            # would otherwise find open and report as that test's failure
    assert proc.returncode == 130, err
    assert "handctl: interrupted" in err
    assert "Traceback" not in err
    _, alive = psutil.wait_procs(children, timeout=20.0)
    assert alive == [], [_cmdline(c) for c in alive]
    assert not out.exists()


def _cmdline(process: psutil.Process) -> list[str]:
    try:
        line: list[str] = process.cmdline()
    except psutil.Error:
        return []
    return line


@pytest.mark.parametrize(
    ("options", "message"),
    [
        (["--workers", "0"], "handctl: error: --workers: expected at least 1 worker, found 0"),
        (["--workers", "100000"], "handctl: error: --workers: expected at most "),
        (
            ["--scheduler", "localhost:8786"],
            "handctl: error: --scheduler: expected a Dask scheduler "
            "address like tcp://HOST:8786 (tcp, tls, ws or wss; a port 1-65535), "
            "found 'localhost:8786'",
        ),
        (
            ["--scheduler", "tcp://127.0.0.1"],  # no port: Dask failed on it only connecting
            "handctl: error: --scheduler: expected a Dask scheduler address like tcp://HOST:8786",
        ),
        (
            ["--workers", "2", "--scheduler", "tcp://127.0.0.1:8786"],
            "handctl: error: --workers: expected no --workers with --scheduler",
        ),
    ],
)
def test_bad_scale_options_are_named_and_exit_2(
    tmp_path: Path, options: list[str], message: str, capsys: pytest.CaptureFixture[str]
) -> None:
    from handctl.cli import main

    out = tmp_path / "r.yaml"
    assert main(["plan", str(TEMPLATE), "-o", str(out), *options]) == 2
    assert capsys.readouterr().err.startswith(message)
    assert not out.exists()


#: A scheduler and one worker in one process (threads), which says its address and is killed
#: (SIGKILL) the moment the first task goes to its worker: the scheduler lost mid-plan, and no
#: worker process left behind.
DYING_CLUSTER = """
import os, signal, time
from distributed import LocalCluster
from distributed.diagnostics.plugin import SchedulerPlugin

class DieAtTheFirstTask(SchedulerPlugin):
    def transition(self, key, start, finish, *args, **kwargs):
        if finish == "processing":
            os.kill(os.getpid(), signal.SIGKILL)

cluster = LocalCluster(
    n_workers=1, threads_per_worker=1, processes=False, protocol="tcp",
    dashboard_address=":0", scheduler_port=0,
)
cluster.scheduler.add_plugin(DieAtTheFirstTask())
print(cluster.scheduler_address, flush=True)
time.sleep(600)
"""


def test_a_scheduler_lost_mid_plan_is_a_failed_result_named(tmp_path: Path) -> None:
    """Killed under the plan, the scheduler takes every result not yet back with it: one line
    that says so (not Dask's traceback), exit 1, and no recipe."""
    pytest.importorskip("distributed")
    out = tmp_path / "r.yaml"
    with subprocess.Popen(
        [sys.executable, "-c", DYING_CLUSTER], cwd=ROOT, stdout=subprocess.PIPE, text=True
    ) as cluster:
        try:
            assert cluster.stdout is not None
            address = cluster.stdout.readline().strip()
            done = subprocess.run(
                plan_command(tiny_template(tmp_path), out, "--scheduler", address),
                cwd=ROOT,
                text=True,
                capture_output=True,
                timeout=300,
                check=False,
            )
            assert cluster.wait(timeout=60) == -signal.SIGKILL  # it was lost, as meant
        finally:
            if cluster.poll() is None:
                cluster.kill()
    assert done.returncode == 1, done.stderr
    assert "Traceback" not in done.stderr
    assert done.stderr.splitlines()[-1] == (
        f"handctl: error: --scheduler {address}: the Dask scheduler was lost mid-plan "
        "(the connection to it closed); nothing was written"
    )
    assert not out.exists()
