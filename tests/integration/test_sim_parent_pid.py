"""``handctl sim --parent-pid``: the simulated hand of a real-time host, which stops when its
host ends and then removes the host's unix bus directory. A pid that is not this process's
parent is bad input, and a hand that was never its parent's removes nothing: before, any pid
that was not the parent was taken for a host already gone, the message said only
"interrupted", and the bus directory named on the command line was emptied of every socket,
other peers' included."""

from __future__ import annotations

import os
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
