"""Lines written from inside a tick (``handctl.lossyout``) never wait for a terminal or a
pipe that does not take them: they are dropped whole, and a line taken in part is finished
before any other."""

from __future__ import annotations

import io
import os
import pty
import socket
import threading

import pytest

from handctl.lossyout import LossyOut

LINE = "x" * 73 + "\n"


def _write_lines(out: LossyOut, n: int) -> bool:
    """``n`` lines through ``out`` in a thread; whether they were all through in 30 s."""
    thread = threading.Thread(target=lambda: [out.write(LINE) for _ in range(n)], daemon=True)
    thread.start()
    thread.join(30.0)
    return not thread.is_alive()


def _read_all(fd: int) -> bytes:
    seen = b""
    while True:
        try:
            chunk = os.read(fd, 65536)
        except OSError:  # the other end closed
            return seen
        if not chunk:
            return seen
        seen += chunk


def test_a_terminal_whose_reader_stalled_never_blocks_a_line() -> None:
    """A terminal polls writable with any room at all, and a line longer than the room (its
    newline two characters there) blocked the write that followed the poll: jog's table on
    a terminal whose reader stalled (an SSH session) held the loop, its torque on, until the
    nodes' watchdogs (found by an outside audit, on the 241st line). Every line is dropped
    or taken now, and what went out is whole lines only, once the reader reads again."""
    master, slave = pty.openpty()
    stream = open(slave, "w", closefd=False)  # noqa: SIM115 -- closed below
    try:
        out = LossyOut(stream)
        assert _write_lines(out, 3000), "a line waited for a terminal that was not read"
        assert out.dropped > 0 and out.written > 0
        assert out.written + out.dropped == 3000
        reader = threading.Thread(target=lambda: shown.append(_read_all(master)), daemon=True)
        shown: list[bytes] = []
        reader.start()
        out.finish()  # the line taken in part, finished
        stream.close()
        os.close(slave)
        reader.join(30.0)
        lines = shown[0].split(b"\r\n")
        assert lines[-1] == b""
        assert lines[:-1] == [LINE[:-1].encode()] * out.written
    finally:
        os.close(master)


def test_a_full_pipe_never_blocks_a_line() -> None:
    read_end, write_end = os.pipe()
    stream = open(write_end, "w", closefd=False)  # noqa: SIM115 -- closed below
    try:
        out = LossyOut(stream)
        assert _write_lines(out, 3000)  # 222 kB into a pipe of 64 kB never read
        assert out.dropped > 0 and out.written > 0
        out.finish()
        stream.close()
        os.close(write_end)
        lines = _read_all(read_end).split(b"\n")
        assert lines[:-1] == [LINE[:-1].encode()] * out.written
    finally:
        os.close(read_end)


def test_a_stream_without_a_descriptor_is_written_as_it_is() -> None:
    stream = io.StringIO()
    out = LossyOut(stream)
    assert out.write(LINE) and out.write(LINE)
    out.finish()
    assert stream.getvalue() == LINE * 2 and out.dropped == 0


def test_a_reader_gone_is_no_line_dropped_for_want_of_room() -> None:
    """``handctl jog ... | head -2``: the reader leaves, and what is not shown after is not
    for want of room; jog said "18 of the table's 19 lines were not shown ... a reader that
    fell behind" of a reader that had gone, which is normal and passes in silence."""
    read_end, write_end = os.pipe()
    stream = open(write_end, "w", closefd=False)  # noqa: SIM115 -- closed below
    try:
        out = LossyOut(stream)
        os.close(read_end)
        assert not out.write(LINE)
        assert out.gone
        out.finish()
    finally:
        stream.close()
        os.close(write_end)


def test_a_socket_whose_reader_stalled_never_blocks_a_line() -> None:
    """stdout a socket (a service manager's journal, a supervisor's socketpair): written
    through the stream, which blocks, it held jog's loop with its torque on until the nodes'
    watchdogs (found by an outside audit). Sent to without waiting, as a pipe is written."""
    ours, theirs = socket.socketpair()
    ours.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, 4096)
    stream = open(ours.fileno(), "w", closefd=False)  # noqa: SIM115 -- closed below
    try:
        out = LossyOut(stream)
        assert _write_lines(out, 3000), "a line waited for a socket that was not read"
        assert out.dropped > 0 and out.written > 0
        out.finish()
        stream.close()
        ours.shutdown(socket.SHUT_WR)
        seen = b""
        while chunk := theirs.recv(65536):
            seen += chunk
        assert seen.split(b"\n")[:-1] == [LINE[:-1].encode()] * out.written
    finally:
        ours.close()
        theirs.close()


def test_a_terminal_or_pipe_that_cannot_be_opened_again_is_not_written_at_all(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Another user's terminal or pipe (``sudo -u robot handctl jog ... | less``), or no
    /proc: it cannot be opened again, and the lines went through the stream, blocking,
    which is what this module exists to stop (found by an outside audit). Nothing is
    written then, and ``off`` says why, for the command to say before its loop. The refusal
    is forced here: a test run as root opens anything."""
    real_open = os.open

    def refused(path: str, *args: int) -> int:
        if str(path).startswith("/proc/self/fd/"):
            raise PermissionError(13, "Permission denied", path)
        return real_open(path, *args)

    read_end, write_end = os.pipe()
    stream = open(write_end, "w", closefd=False)  # noqa: SIM115 -- closed below
    try:
        monkeypatch.setattr(os, "open", refused)
        out = LossyOut(stream)
        monkeypatch.undo()
        assert out.off.startswith("a pipe this process cannot open again")
        assert _write_lines(out, 3000)
        assert out.written == 0 and out.dropped == 3000
        out.finish()
    finally:
        stream.close()
        os.close(write_end)
        os.close(read_end)
