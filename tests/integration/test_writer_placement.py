"""Where the recording's writer process runs: off the loop's CPU in a pinned real-time run, and
behind the loop in the scheduler, its live server's threads included. A real writer process
with a real live server; nothing is mocked."""

from __future__ import annotations

import os
import socket
from pathlib import Path

import pytest

from handctl.config import HandConfig
from handctl.online.recipes.loader import load_recipe
from handctl.recording.metadata import start_metadata
from handctl.recording.recorder import Recorder, writer_cpus

from ..conftest import ROOT

RECIPE = ROOT / "config" / "recipes" / "swap_two_cylinders.yaml"


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def test_writer_cpus_leave_the_loop_and_the_simulated_hand_their_cpus() -> None:
    allowed = os.sched_getaffinity(0)
    assert writer_cpus(None, None) is None  # not pinned: anywhere
    for loop_cpu in sorted(allowed):
        alone = writer_cpus(loop_cpu, None)  # a real hand: no simulated hand's process
        assert alone == (sorted(allowed - {loop_cpu}) or None)
        for sim_cpu in sorted(allowed - {loop_cpu}):
            beside = writer_cpus(loop_cpu, sim_cpu)
            # Two CPUs taken: anywhere (the loop's idle time too) when none is left
            assert beside == (sorted(allowed - {loop_cpu, sim_cpu}) or None)


def test_the_writer_and_its_live_server_run_where_and_how_they_are_told(
    tmp_path: Path, hand: HandConfig
) -> None:
    allowed = sorted(os.sched_getaffinity(0))
    if len(allowed) < 2:
        pytest.skip("one CPU: the writer cannot be kept off the loop's")
    loop_cpu = allowed[-1]
    cpus = writer_cpus(loop_cpu)
    assert cpus is not None
    recipe = load_recipe(RECIPE, hand)
    recorder = Recorder(
        tmp_path / "run.mcap",
        hand,
        start_metadata(hand, recipe, ["test"]),
        phase_names=[p.name for p in recipe.phases],
        live_port=free_port(),
        cpus=cpus,
    )
    with recorder:
        recorder.wait_ready()  # the writer placed itself and started its server before this
        pid = recorder.process.pid
        threads = [int(t) for t in os.listdir(f"/proc/{pid}/task")]
        assert len(threads) > 1  # the live server's own threads are there to be checked
        for tid in threads:
            assert os.sched_getaffinity(tid) == set(cpus), tid
            assert os.sched_getscheduler(tid) == os.SCHED_BATCH, tid
            assert os.getpriority(os.PRIO_PROCESS, tid) >= 5, tid
