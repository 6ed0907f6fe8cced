"""What a simulated hand removes when it outlives its host: the run's private bus directory,
and never anything handctl did not put there."""

from __future__ import annotations

import socket
from pathlib import Path

from handctl.parent_death import remove_orphaned_bus


def _bus(directory: Path, *names: str) -> list[socket.socket]:
    directory.mkdir()
    sockets = []
    for name in names:
        sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        sock.bind(str(directory / name))
        sockets.append(sock)
    return sockets


def test_a_private_bus_directory_is_removed(tmp_path: Path) -> None:
    directory = tmp_path / "handctl-bus-x"
    sockets = _bus(directory, "101-0.sock", "202-0.sock")
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
    sockets = _bus(directory, "101-0.sock")
    (directory / "notes.txt").write_text("keep me")
    (directory / "7-1.sock").write_text("a file, not a socket")
    (directory / "sub").mkdir()
    try:
        remove_orphaned_bus(f"unix:{directory}", None)
    finally:
        for sock in sockets:
            sock.close()
    assert sorted(p.name for p in directory.iterdir()) == ["7-1.sock", "notes.txt", "sub"]


def test_other_buses_are_left_alone(tmp_path: Path) -> None:
    directory = tmp_path / "virtual"
    directory.mkdir()
    remove_orphaned_bus(f"virtual:{directory}", None)
    assert directory.exists()
