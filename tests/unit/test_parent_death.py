"""What a simulated hand removes when it outlives its host: the run's private bus directory,
and never anything handctl did not put there."""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
from pathlib import Path

import pytest

from handctl.errors import HandctlError
from handctl.parent_death import JsonHelper, remove_orphaned_bus


def _bus(directory: Path, *names: str) -> list[socket.socket]:
    directory.mkdir()
    sockets = []
    for name in names:
        sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        sock.bind(str(directory / name))
        sockets.append(sock)
    return sockets


def _dead_pid() -> int:
    """The id of a process that has ended (reaped: nobody has it until the kernel reuses it)."""
    done = subprocess.Popen([sys.executable, "-c", "pass"])
    done.wait()
    return done.pid


def test_a_private_bus_directory_is_removed(tmp_path: Path) -> None:
    directory = tmp_path / "handctl-bus-x"
    sockets = _bus(directory, f"{_dead_pid()}-0.sock", f"{_dead_pid()}-0.sock")
    summary = directory / "sim-summary.json"
    summary.write_text("{}")
    try:
        remove_orphaned_bus(f"unix:{directory}", summary)
    finally:
        for sock in sockets:
            sock.close()
    assert not directory.exists()


def test_a_directory_holding_anything_else_keeps_it(tmp_path: Path) -> None:
    """A user who pointed --bus unix: at a directory of their own loses nothing but sockets."""
    directory = tmp_path / "mine"
    sockets = _bus(directory, f"{_dead_pid()}-0.sock")
    (directory / "notes.txt").write_text("keep me")
    (directory / "7-1.sock").write_text("a file, not a socket")
    (directory / "sub").mkdir()
    try:
        remove_orphaned_bus(f"unix:{directory}", None)
    finally:
        for sock in sockets:
            sock.close()
    assert sorted(p.name for p in directory.iterdir()) == ["7-1.sock", "notes.txt", "sub"]


def test_a_live_peers_endpoint_is_its_own(tmp_path: Path) -> None:
    """A process still on the bus keeps its endpoint, and so the directory stays; the dead
    host's endpoint goes. Before, every endpoint went, a live peer's too."""
    directory = tmp_path / "shared"
    live, dead = f"{os.getppid()}-3.sock", f"{_dead_pid()}-0.sock"
    sockets = _bus(directory, live, dead)
    try:
        remove_orphaned_bus(f"unix:{directory}", None)
    finally:
        for sock in sockets:
            sock.close()
    assert sorted(p.name for p in directory.iterdir()) == [live]


def test_a_host_that_ended_and_is_not_yet_reaped_is_gone(tmp_path: Path) -> None:
    """A host killed with SIGKILL is a zombie until its parent waits for it, and its hand
    tidies up in that moment: its endpoint goes, and with it the directory."""
    host = subprocess.Popen([sys.executable, "-c", "pass"])
    try:
        os.waitid(os.P_PID, host.pid, os.WEXITED | os.WNOWAIT)  # ended, not reaped
        directory = tmp_path / "handctl-bus-z"
        sockets = _bus(directory, f"{host.pid}-0.sock")
        try:
            remove_orphaned_bus(f"unix:{directory}", None)
        finally:
            for sock in sockets:
                sock.close()
        assert not directory.exists()
    finally:
        host.wait()


def test_other_buses_are_left_alone(tmp_path: Path) -> None:
    directory = tmp_path / "virtual"
    directory.mkdir()
    remove_orphaned_bus(f"virtual:{directory}", None)
    assert directory.exists()


def test_a_helper_stopped_before_it_started_up_says_so() -> None:
    # timeit never handles SIGTERM, as a helper still starting up does not yet
    helper = JsonHelper("timeit", ["-n", "1000000000000", "pass"], "the timing probe")
    with helper, pytest.raises(HandctlError) as info:
        helper.finish(timeout_s=60.0)
    message = str(info.value)
    assert message.startswith("the timing probe measured nothing: handctl stopped it (SIGTERM)")
    assert "before it had started up" in message and not message.endswith(": ")


def test_a_helper_that_failed_shows_its_exit_and_what_it_said(tmp_path: Path) -> None:
    helper = JsonHelper("json.tool", [str(tmp_path / "none.json")], "the helper")
    with helper, pytest.raises(HandctlError) as info:
        helper.finish(timeout_s=60.0, terminate=False)
    message = str(info.value)
    assert message.startswith("the helper ended with exit 2: ") and "none.json" in message


def test_a_probe_stopped_before_its_first_wake_up_says_it_measured_nothing(
    tmp_path: Path,
) -> None:
    """A jog that stopped on its first ticks stopped the timing probe beside it after it had
    started up and before its timer first expired: its record of no wake-up was refused by
    the record's own check, said as "the timing probe: wakeups: expected an integer >= 1,
    found 0" (an outside probe, 4 runs in 35). The record is a real probe's, its wake-ups
    taken out, as such a probe writes it."""
    from handctl.hostcheck import Probe

    with Probe(10**6, record_ns=10**6, seconds=0.2) as probe:
        record = probe.finish(timeout_s=60.0, terminate=False)  # a real probe's record
    record.update(wakeups=0, lateness_hist_us={}, stalls=[], hiccups=[])
    written = tmp_path / "record.json"
    written.write_text(json.dumps(record))

    class Stopped(Probe):
        def __init__(self) -> None:  # the probe's record as it wrote it, read back
            JsonHelper.__init__(self, "json.tool", [str(written)], "the timing probe")
            self.seconds = 0.0

    with Stopped() as stopped, pytest.raises(HandctlError) as info:
        stopped.stop()
    message = str(info.value)
    assert message.startswith("the timing probe measured nothing: handctl stopped it"), message
    assert "wakeups" not in message
