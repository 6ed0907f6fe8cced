"""``handctl sim --parent-pid``: the simulated hand of a real-time host, which stops when its
host ends and then removes the host's unix bus directory. A pid that is not this process's
parent is bad input, and a hand that was never its parent's removes nothing: before, any pid
that was not the parent was taken for a host already gone, the message said only
"interrupted", and the bus directory named on the command line was emptied of every socket,
other peers' included."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

from ..conftest import handctl


@pytest.fixture
def shared_bus(tmp_path: Path) -> Iterator[Path]:
    """A unix bus directory another peer is on: this process, one bound endpoint."""
    directory = tmp_path / "bus"
    directory.mkdir()
    peer = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    peer.bind(str(directory / PEER))
    try:
        yield directory
    finally:
        peer.close()


#: the live peer's endpoint: named for this process, as the unix bus names them
PEER = f"{os.getpid()}-1.sock"


def sim(bus: Path, pid: int) -> subprocess.CompletedProcess[str]:
    return handctl("sim", "--bus", f"unix:{bus}", "--seconds", "1", "--parent-pid", str(pid))


@pytest.mark.parametrize("pid", [-1, 0])
def test_a_pid_that_is_no_process_id_is_bad_input(shared_bus: Path, pid: int) -> None:
    done = sim(shared_bus, pid)
    assert done.returncode == 2, done.stderr
    assert f"--parent-pid: expected a process id > 0, found {pid}" in done.stderr
    assert (shared_bus / PEER).exists()


def test_a_pid_no_process_could_have_had_is_bad_input(shared_bus: Path) -> None:
    """Above the system's largest process id it is no parent that ended (exit 130, "ended
    before its simulated hand started"), but a mistake (an outside audit)."""
    highest = int(Path("/proc/sys/kernel/pid_max").read_text())
    done = sim(shared_bus, highest + 1)
    assert done.returncode == 2, done.stderr
    assert f"--parent-pid: expected a process id the system can give (at most {highest}" in (
        done.stderr
    )
    assert (shared_bus / PEER).exists()


def test_a_live_process_that_is_not_the_parent_is_bad_input_and_nothing_is_removed(
    shared_bus: Path,
) -> None:
    other = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        done = sim(shared_bus, other.pid)
    finally:
        other.kill()
        other.wait()
    assert done.returncode == 2, done.stderr
    assert "--parent-pid: expected the id of this process's parent (" in done.stderr
    assert f"found {other.pid}" in done.stderr
    assert (shared_bus / PEER).exists()


def test_a_parent_gone_before_the_hand_started_is_said_and_removes_nothing(
    shared_bus: Path,
) -> None:
    gone = subprocess.Popen([sys.executable, "-c", "pass"])
    gone.wait()
    done = sim(shared_bus, gone.pid)
    assert done.returncode == 130, done.stderr
    assert f"process {gone.pid} ended before its simulated hand started" in done.stderr
    assert "Traceback" not in done.stderr
    assert (shared_bus / PEER).exists()


def test_a_real_time_hand_ended_by_sigxcpu_names_the_limit(tmp_path: Path) -> None:
    """The kernel's SIGXCPU at a soft RLIMIT_RTTIME ended a ``--rt`` hand without a word of
    the limit: "interrupted", nothing pointing to ``prlimit --rttime``. It names the limit and
    its value."""
    import resource
    import time

    from ..conftest import ROOT

    bus, log = tmp_path / "bus", tmp_path / "sim.log"
    parent = ["--parent-pid", str(os.getpid())]
    path = os.pathsep.join(p for p in (str(ROOT), os.environ.get("PYTHONPATH", "")) if p)
    with log.open("w") as err:
        hand = subprocess.Popen(
            [sys.executable, "-m", "handctl", "sim", "--bus", f"unix:{bus}", "--rt", *parent],
            cwd=ROOT,
            env={**os.environ, "PYTHONPATH": path, "PYTHONDONTWRITEBYTECODE": "1"},
            stdout=subprocess.DEVNULL,
            stderr=err,
        )
    try:
        deadline = time.monotonic() + 120
        while not log.read_text().strip():  # its first progress line: it ticks
            assert hand.poll() is None and time.monotonic() < deadline, log.read_text()
            time.sleep(0.1)
        said = log.read_text()
        if "SCHED_FIFO priority" in said and "refused" in said:
            pytest.skip("real-time priority refused here")
        # a soft limit well above what the hand uses between two blocking calls
        resource.prlimit(hand.pid, resource.RLIMIT_RTTIME, (10_000_000, resource.RLIM_INFINITY))
        hand.send_signal(signal.SIGXCPU)
        code = hand.wait(timeout=120)
    finally:
        if hand.poll() is None:
            hand.kill()
            hand.wait()
    lines = log.read_text().strip().splitlines()
    assert code == 0, lines  # a stop while it ticks, as Ctrl-C: its summary, then exit 0
    assert any(
        "SIGXCPU at SCHED_FIFO: the soft RLIMIT_RTTIME is 10000000 µs (10000 ms;" in line
        for line in lines
    ), lines
