"""The log file against what the system around a run may do to it and to the run's own
descriptors. Each test drives a run's real writer process, never a stand-in."""

from __future__ import annotations

import json
import os
import pty
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import pytest

from handctl.config import HandConfig
from handctl.errors import ConfigError, HandctlError
from handctl.recording import channels as ch
from handctl.recording.metadata import start_metadata
from handctl.recording.reader import open_recording
from handctl.recording.recorder import Recorder

from ..conftest import DEFAULT_RECIPE, HAND_YAML, ROOT, handctl
from .rig import HOLD_LONG, read_until


def _recorder(hand: HandConfig, path: Path, argv: tuple[str, ...] = ("test",)) -> Recorder:
    """A recorder whose writer has the file open and its header written."""
    recorder = Recorder(path, hand, start_metadata(hand, None, argv))
    recorder.wait_ready()
    return recorder


def test_a_log_that_cannot_be_synced_is_no_writer_failure(hand: HandConfig) -> None:
    """``fdatasync`` of /dev/null is EINVAL: the writer ended with that traceback. A file that
    cannot be synced has nothing to make durable; the recording goes on."""
    stats = _recorder(hand, Path(os.devnull)).close({"outcome": "test"})
    assert stats["writer_exit"] == 0


def test_arguments_and_paths_that_are_not_utf_8_are_recorded_shown_as_bytes(
    hand: HandConfig, tmp_path: Path
) -> None:
    """A byte that is not UTF-8 in ``--log``'s path (Python holds it as a lone surrogate)
    failed the run's start with a TypeError from the JSON encoder, and no log. Now the file
    is at the path as given, and the metadata show the byte as ``\\xff``."""
    name = os.fsdecode(b"l_\xff.mcap")
    path = tmp_path / name
    argv = ("handctl", "run", "--log", name)
    recorder = _recorder(hand, path, argv)
    recorder.add_metadata("handctl.test", {"path": str(path)})
    recorder.close({"outcome": "test", "recording": {"path": str(path)}})
    assert os.fsencode(path) in [os.fsencode(tmp_path / p) for p in os.listdir(tmp_path)]
    recording = open_recording(path)
    assert recording.complete
    shown = str(tmp_path / "l_\\xff.mcap")
    assert json.loads(recording.meta("handctl.command", "command_line")) == [
        "handctl",
        "run",
        "--log",
        "l_\\xff.mcap",
    ]
    assert recording.meta("handctl.test", "path") == shown
    summary = recording.json_meta("handctl.summary")
    assert summary is not None and summary["recording"]["path"] == shown


#: A recorder started by a process whose descriptors 0 and 1 are closed (``handctl run ...
#: >&- <&-``), so that the log and the shared memory take them; it prints nothing.
_CLOSED_STDIO = """
import os, sys
from handctl.config import load_hand
from handctl.recording.metadata import start_metadata
from handctl.recording.recorder import Recorder
os.close(0)
os.close(1)
hand = load_hand(sys.argv[1])
recorder = Recorder(sys.argv[2], hand, start_metadata(hand, None, ["closed"]))
recorder.wait_ready()
recorder.close({"outcome": "test"})
"""


def test_a_run_started_with_stdin_and_stdout_closed_still_records(tmp_path: Path) -> None:
    """The log opened as descriptor 0 or 1 was handed to the writer there, where its own
    stdin or stdout replaced it: the writer wrote the recording to /dev/null, the log was
    empty and the sync of /dev/null failed the writer."""
    path = tmp_path / "closed.mcap"
    env = {
        **os.environ,
        "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]),
    }
    done = subprocess.run(
        [sys.executable, "-c", _CLOSED_STDIO, str(HAND_YAML), str(path)],
        cwd=ROOT,
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
        check=False,
    )
    assert done.returncode == 0, done.stderr
    recording = open_recording(path)
    assert recording.complete
    assert recording.meta("handctl.command", "command_line") == '["closed"]'
    assert recording.json_meta("handctl.summary") == {"outcome": "test"}


def test_a_second_run_on_a_log_being_written_is_refused_and_the_first_s_file_kept(
    hand: HandConfig, tmp_path: Path
) -> None:
    """Both runs said they were done and the file held chunks of each: now the second is bad
    input naming the file, before anything starts, and the first's file is whole."""
    path = tmp_path / "same.mcap"
    first = _recorder(hand, path)
    written = path.stat().st_size
    assert written > 0
    with pytest.raises(ConfigError) as refused:
        Recorder(path, hand, start_metadata(hand, None, ("second",)))
    assert str(path) in str(refused.value) and "another process writing it" in str(refused.value)
    done = handctl("run", "recipe", DEFAULT_RECIPE, "--log", str(path))
    assert done.returncode == 2, done.stdout + done.stderr
    assert f"{path}: expected a log no other run is writing" in done.stderr
    assert "Traceback" not in done.stderr
    # refused alone: it first warned that it would replace the log (an outside audit)
    assert "is a recording already" not in done.stderr
    assert path.stat().st_size >= written  # not emptied by either
    first.close({"outcome": "test"})
    recording = open_recording(path)
    assert recording.complete and not recording.problem
    assert recording.meta(ch.META_HAND, "name") == hand.name
    assert recording.meta("handctl.command", "command_line") == '["test"]'
    # The lock went with the run that held it: the path is free again.
    _recorder(hand, path).close()
    assert open_recording(path).complete


@pytest.mark.parametrize("how", ["directory_removed", "file_removed", "file_replaced"])
def test_a_log_that_is_not_at_its_path_at_the_end_is_said(
    hand: HandConfig, tmp_path: Path, how: str
) -> None:
    """The run said "recorded ... to deld/x.mcap" and there was no such file. Now the close
    raises (the run turns it into a warning, as a writer that failed), naming the path and
    what is there instead."""
    directory = tmp_path / "deld"
    directory.mkdir()
    path = directory / "x.mcap"
    recorder = _recorder(hand, path)
    if how == "directory_removed":
        shutil.rmtree(directory)
    elif how == "file_removed":
        path.unlink()
    else:
        path.unlink()
        path.write_text("another file\n")
    with pytest.raises(HandctlError) as lost:
        recorder.close({"outcome": "test"})
    said = str(lost.value)
    assert said.startswith(f"{path}: expected the recording at this path at the end of the run")
    if how == "file_replaced":
        assert "another file is there now (the log was replaced)" in said
        assert path.read_text() == "another file\n"  # left as it is
    else:
        assert "nothing is there now: the recording is lost" in said
    assert recorder.stats["writer_exit"] == 0  # the writer itself finished


def test_a_log_emptied_in_place_during_the_run_is_said_lost(
    hand: HandConfig, tmp_path: Path
) -> None:
    """``: > RUN.mcap`` (what logrotate's copytruncate does) while the run recorded: the
    writer went on at its own offset after a hole of zeros, the file was no MCAP any more,
    and the run said it had recorded, exit 0 (found by an outside audit)."""
    path = tmp_path / "run.mcap"
    recorder = _recorder(hand, path)
    with path.open("r+b") as handle:
        handle.truncate(0)
    with pytest.raises(HandctlError) as lost:
        recorder.close({"outcome": "test"})
    said = str(lost.value)
    assert said.startswith(f"{path}: expected the recording at this path at the end of the run")
    assert "no longer begins as one: it was emptied or written over" in said
    assert recorder.stats["writer_exit"] == 0


def test_a_writer_killed_is_said_with_its_signal_not_an_empty_reason(
    hand: HandConfig, tmp_path: Path
) -> None:
    """A writer SIGKILLed while the run waited for it at its end was said as "the writer
    failed (exit -9): " and nothing after the colon (found by an outside audit)."""
    recorder = _recorder(hand, tmp_path / "run.mcap")
    recorder.process.kill()
    recorder.process.wait()
    assert recorder._writer_failed("", "") == "the writer failed (signal 9)"
    assert recorder._writer_failed("", "OSError: no space") == (
        "the writer failed (signal 9): OSError: no space"
    )
    with pytest.raises(HandctlError):
        recorder.close({"outcome": "test"})


def test_a_log_still_at_its_path_is_no_warning(hand: HandConfig, tmp_path: Path) -> None:
    """Through a symbolic link too: the path names the file written."""
    path = tmp_path / "run.mcap"
    link = tmp_path / "link.mcap"
    path.touch()
    link.symlink_to(path)
    stats = _recorder(hand, link).close({"outcome": "test"})
    assert stats["writer_exit"] == 0
    assert open_recording(path).complete


def test_a_hung_writer_is_said_then_given_up_on(
    hand: HandConfig, tmp_path: Path, capfd: pytest.CaptureFixture[str]
) -> None:
    """A writer that moves nothing (SIGSTOP, a disk that hangs) held the run's exit, with
    no word, until it went on. Now the wait is said on stderr, the writer is killed once it
    has moved nothing for the stall time, and the close says the log may be incomplete."""
    path = tmp_path / "hung.mcap"
    recorder = _recorder(hand, path)
    os.kill(recorder.process.pid, signal.SIGSTOP)
    try:
        with pytest.raises(HandctlError) as hung:
            recorder.close({"outcome": "test"}, stall_timeout_s=3.0)
    finally:
        if recorder.process.returncode is None:  # only if the close failed to end it
            os.kill(recorder.process.pid, signal.SIGKILL)
            recorder.process.wait()
    assert recorder.process.returncode == -signal.SIGKILL
    said = str(hung.value)
    assert said.startswith(f"{path}: the recording writer moved nothing for")
    assert "(stopped or hung) and was killed" in said and "the log may be incomplete" in said
    err = capfd.readouterr().err
    assert "waiting" in err and f"for the recording writer to finish {path}" in err
    assert "the hand is stopped" in err
    assert not open_recording(path).complete  # what the writer had flushed, without its end


def test_a_hung_writer_holds_no_send_of_a_summary_larger_than_the_pipe(
    hand: HandConfig, tmp_path: Path
) -> None:
    """The summary goes down a pipe the writer reads; one larger than the pipe holds (a run's
    with many faults or notes) blocked the close for ever on a writer that read nothing, before
    the wait that says so and gives up. Now the send too gives up after the stall time."""
    import threading

    path = tmp_path / "hung.mcap"
    recorder = _recorder(hand, path)
    os.kill(recorder.process.pid, signal.SIGSTOP)
    raised: list[BaseException] = []

    def close() -> None:
        try:
            recorder.close({"notes": "x" * 300_000}, stall_timeout_s=2.0)
        except BaseException as exc:
            raised.append(exc)

    closing = threading.Thread(target=close, daemon=True)
    closing.start()
    closing.join(120)
    held = closing.is_alive()
    if recorder.process.returncode is None:
        os.kill(recorder.process.pid, signal.SIGKILL)  # frees a close still held, if one is
        closing.join(30)
    assert not held, "the close was still sending its summary after 120 s"
    assert len(raised) == 1 and isinstance(raised[0], HandctlError), raised
    said = str(raised[0])
    assert "the recording writer took nothing of its control messages for 2 s" in said
    assert said.endswith("(stopped or hung), and the run's summary is not in it")


@pytest.mark.parametrize("before", [False, True])
def test_a_writer_the_open_files_limit_keeps_from_starting_is_said(
    tmp_path: Path, before: bool
) -> None:
    """Under ``ulimit -n`` 13 to 16 the writer's pipes or process could not be made: an
    ``OSError`` traceback (or, at 12, a message naming /dev/null), and no word of the limit.
    A log at the path before is left as it was (it was deleted)."""
    import resource

    log = tmp_path / "run.mcap"
    previous = b"\x89MCAP0\r\n a previous run's log"
    if before:
        log.write_bytes(previous)

    def few_files() -> None:
        resource.setrlimit(resource.RLIMIT_NOFILE, (14, 14))

    done = handctl(
        *("run", "recipe", str(DEFAULT_RECIPE), "--max-seconds", "0.2", "--log", str(log)),
        timeout=300,
        preexec_fn=few_files,
    )
    assert done.returncode == 1, done.stderr
    assert "Traceback" not in done.stderr
    assert (
        "the recording writer could not be started: Too many open files (the open-files "
        "limit, ulimit -n); nothing was sent"
    ) in done.stderr
    assert (log.read_bytes() == previous) if before else not log.exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == (["run.mcap"] if before else [])


def test_a_previous_log_is_replaced_only_once_the_run_begins(
    hand: HandConfig, tmp_path: Path
) -> None:
    """A run refused or failed before it began (its simulated hand not starting, a bus not
    there, a signal during its start-up) emptied or deleted the log at its path, and left a
    log of nothing. The recording goes beside the path until the run begins (``claim``),
    and through a symbolic link as before."""
    log = tmp_path / "run.mcap"
    previous = b"\x89MCAP0\r\n a previous run's log"
    log.write_bytes(previous)
    never = Recorder(log, hand, start_metadata(hand, None, ("never",)), keep_previous=True)
    assert log.read_bytes() == previous  # while the run starts
    stats = never.close({"outcome": "never began"})
    assert stats["previous_kept"] and log.read_bytes() == previous
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run.mcap"]
    began = Recorder(log, hand, start_metadata(hand, None, ("began",)), keep_previous=True)
    began.claim()
    began.close({"outcome": "began"})
    assert open_recording(log).json_meta("handctl.summary") == {"outcome": "began"}
    link = tmp_path / "link.mcap"
    link.symlink_to(log)
    fresh = tmp_path / "fresh.mcap"
    for path, outcome in ((link, "through a link"), (fresh, "nothing there before")):
        recorder = Recorder(path, hand, start_metadata(hand, None, ("x",)), keep_previous=True)
        if path == link:
            recorder.claim()
        recorder.close({"outcome": outcome})  # a path that named nothing: the log is put there
        assert open_recording(path).json_meta("handctl.summary") == {"outcome": outcome}
    assert link.is_symlink() and open_recording(log).complete
    assert sorted(p.name for p in tmp_path.iterdir()) == ["fresh.mcap", "link.mcap", "run.mcap"]


def test_a_file_put_at_the_log_s_path_while_the_run_starts_is_not_replaced(
    hand: HandConfig, tmp_path: Path
) -> None:
    """A file put at the path between the run's placeholder and its start (``claim``) was
    replaced by the recording without a word (found by an outside audit): the run is
    refused there, before anything is sent, and the file is left as it is."""
    log = tmp_path / "run.mcap"
    recorder = Recorder(log, hand, start_metadata(hand, None, ("x",)), keep_previous=True)
    recorder.wait_ready()
    log.unlink()
    log.write_text("notes of mine\n")
    with pytest.raises(HandctlError) as refused:
        recorder.claim()
    assert str(refused.value).startswith(
        f"{log}: another file was put at this path while the run started; it is left as it "
        "is, and nothing was sent"
    )
    recorder.close({"outcome": "never began"})
    assert log.read_text() == "notes of mine\n"


def _writer_running(run_pid: int) -> bool:
    """Whether the run's recording writer is still alive (not even a zombie): the recorder
    checks the log's path only after it has reaped the writer, so a log removed while this
    is true is one the check sees."""
    return _writer_pid(run_pid, alive=True) is not None


def _run_and_then(
    tmp_path: Path, log: Path, options: list[str], then: Callable[[subprocess.Popen[bytes]], None]
) -> tuple[int, str]:
    """``handctl run recipe`` of a long hold recording to ``log``, its status line on a
    terminal; ``then(process)`` once the line says the phase runs, many simulated seconds
    before it ends, and only while the writer is still alive, so the end-of-run check comes
    after it whatever the machine's load. The exit code and what the terminal showed."""
    recipe = tmp_path / "hold.yaml"
    recipe.write_text(HOLD_LONG)
    terminal, stderr_end = pty.openpty()
    command = [sys.executable, "-m", "handctl", "run", "recipe", str(recipe), "--log", str(log)]
    proc = subprocess.Popen(
        [*command, *options],
        cwd=ROOT,
        env={
            **os.environ,
            "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]),
        },
        stdout=subprocess.DEVNULL,
        stderr=stderr_end,
    )
    os.close(stderr_end)
    try:
        shown = read_until(terminal, "running")
        assert "running" in shown, shown
        then(proc)
        shown += read_until(terminal, None)
        proc.wait(timeout=60)
    finally:
        proc.kill()
        os.close(terminal)
    return proc.returncode, shown


@pytest.mark.parametrize("end", ["time_budget", "interrupted"])
def test_a_run_whose_log_is_moved_during_it_says_so_in_its_exit(tmp_path: Path, end: str) -> None:
    """A run that warned that its log was not at its path exited 0, as if the log could be
    trusted. Now a log not where the run said (here its directory renamed: the recording
    is elsewhere, whole) is a failed result, exit 1, said last; a run that stops for a
    reason of its own (here Ctrl-C, 130) keeps its code and says the log too. Lockstep."""
    directory = tmp_path / "logs"
    directory.mkdir()
    log = directory / "run.mcap"

    def move_the_log(proc: subprocess.Popen[bytes]) -> None:
        directory.rename(tmp_path / "elsewhere")
        assert _writer_running(proc.pid), "the run ended before its log could be moved"
        if end == "interrupted":
            proc.send_signal(signal.SIGINT)

    budget = ["--max-seconds", "10"] if end == "time_budget" else []
    code, shown = _run_and_then(tmp_path, log, budget, move_the_log)
    assert code == (1 if end == "time_budget" else 130), shown
    assert "Traceback" not in shown
    assert f"{log}: expected the recording at this path at the end of the run" in shown
    assert "the recording is elsewhere" in shown
    last = shown.strip().splitlines()[-1]
    if end == "time_budget":
        assert last.startswith("handctl: failed: the run ended as asked, but its log"), shown
    else:
        assert last.startswith("handctl: and the run's log"), shown
    assert f"{log} is lost or may be incomplete" in last


def test_a_run_whose_log_is_removed_during_it_stops(tmp_path: Path) -> None:
    """A log removed during the run (``rm``, or its directory): what the writer goes on
    writing has no name and is lost when it closes. The run went on driving the hand
    unrecorded to its end and said so only then (exit 1; found by an outside audit); it
    stops now on ``RECORDING_LOST`` at the writer watch's next look (safety.md row 96), many
    simulated seconds before its budget, and says the log is lost. Lockstep."""
    directory = tmp_path / "logs"
    directory.mkdir()
    log = directory / "run.mcap"
    out = tmp_path / "out.json"

    def remove_the_log(proc: subprocess.Popen[bytes]) -> None:
        shutil.rmtree(directory)
        assert _writer_running(proc.pid), "the run ended before its log could be removed"

    options = ["--max-seconds", "10", "--summary-json", str(out)]
    code, shown = _run_and_then(tmp_path, log, options, remove_the_log)
    assert code == 3, shown
    assert "Traceback" not in shown
    summary = json.loads(out.read_text())
    [fault] = summary["faults"]
    assert fault["code"] == "RECORDING_LOST"
    assert "the log was removed" in fault["detail"]
    assert summary["ticks"] < 5000, summary["ticks"]  # long before the budget's 10 s
    assert f"{log}: expected the recording at this path at the end of the run" in shown
    assert f"{log} is lost or may be incomplete" in shown.strip().splitlines()[-1]


def test_a_log_lost_under_an_exception_in_flight_is_said_too(
    hand: HandConfig, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A run that ends on an exception (a bus error, exit 4) keeps that exception and its
    code; the log's own failure to close was swallowed without a word."""
    path = tmp_path / "run.mcap"
    recorder = _recorder(hand, path)
    recorder.process.kill()
    recorder.process.wait()
    with pytest.raises(RuntimeError, match="the bus went away"), recorder:
        raise RuntimeError("the bus went away")
    err = capsys.readouterr().err
    assert f"handctl: and the run's log {path} is lost or may be incomplete: " in err


def test_a_writer_that_never_started_is_said_once(
    hand: HandConfig, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The exception in flight is the writer's not starting: the log's own close failure was
    said before it too, as if the run had lost a log it never began."""
    path = tmp_path / "run.mcap"
    recorder = Recorder(path, hand, start_metadata(hand, None, ("test",)))
    recorder.process.kill()
    recorder.process.wait()
    with pytest.raises(HandctlError, match="the recording writer did not start"), recorder:
        recorder.wait_ready()
    assert "is lost or may be incomplete" not in capsys.readouterr().err


def test_a_control_process_gone_before_the_set_up_leaves_an_mcap_that_says_so(
    tmp_path: Path,
) -> None:
    """Killed while it started the writer (SIGKILL in the first half second of a run), the
    control process had emptied the log, and the writer, its set-up never come, left it
    empty: no MCAP at all for a run that had begun. The writer finishes an MCAP that says why
    it holds nothing."""
    from handctl.recording.writer import ENDED_BEFORE_SETUP

    log = tmp_path / "run.mcap"
    out_fd = os.open(log, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
    shm_fd = os.memfd_create("shm", 0)
    ctl_r, ctl_w = os.pipe()
    ready_r, ready_w = os.pipe()
    fds = (shm_fd, ctl_r, out_fd, ready_w)
    writer = subprocess.Popen(
        [sys.executable, "-m", "handctl.recording.writer", *(str(fd) for fd in fds)],
        pass_fds=fds,
        cwd=ROOT,
        stderr=subprocess.PIPE,
    )
    for fd in (*fds, ctl_w):  # the control end closes with nothing sent: as if killed
        os.close(fd)
    _, err = writer.communicate(timeout=60)
    os.close(ready_r)
    assert writer.returncode == 1, err
    recording = open_recording(log)
    assert recording.complete
    assert recording.meta(ch.META_END, "ended") == ENDED_BEFORE_SETUP
    done = handctl("replay", str(log))
    assert done.returncode == 0, done.stderr
    assert f"0 ticks, 0 chunks, complete (but {ENDED_BEFORE_SETUP})" in done.stdout


def test_what_the_writer_said_of_a_log_it_finished_is_kept(
    hand: HandConfig, tmp_path: Path
) -> None:
    """A writer that could not derive the Foxglove channels (the hand it was given does not
    read) finished the log without them, and its word on stderr was read only when a writer
    failed: the run said nothing of the channels it lacked."""
    from handctl.recording import channels as ch

    metadata = start_metadata(hand, None, ("test",))
    metadata[ch.META_HAND] = {**metadata[ch.META_HAND], "yaml": "name: no_fingers\n"}
    recorder = Recorder(tmp_path / "run.mcap", hand, metadata)
    recorder.wait_ready()
    stats = recorder.close({"outcome": "test"})
    assert stats["writer_exit"] == 0
    assert stats["writer_notes"].startswith("handctl writer: no Foxglove channels: ")
    assert "the recorded hand config: bus: expected this key" in stats["writer_notes"]
    whole = _recorder(hand, tmp_path / "whole.mcap").close({"outcome": "test"})
    assert "writer_notes" not in whole


def _writer_pid(run_pid: int, alive: bool = False) -> int | None:
    """The pid of the run's recording writer, once it is there (with ``alive``, not a
    zombie either)."""
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            stat_line = (entry / "stat").read_text()
            cmdline = (entry / "cmdline").read_bytes()
        except OSError:  # gone meanwhile
            continue
        state, ppid = stat_line.rpartition(")")[2].split()[:2]
        if int(ppid) != run_pid or b"handctl.recording.writer" not in cmdline:
            continue
        if not (alive and state == "Z"):
            return int(entry.name)
    return None


#: s between looks at the writer's process: polled, not spun, as the run needs the other core
POLL_S = 0.005


def test_a_run_whose_writer_drops_records_is_stopped(tmp_path: Path) -> None:
    """The writer held back (stopped here; a live view's clients did it in an outside audit)
    while the lockstep run goes on: its rings hold 8 s of ticks and the rest are dropped. The
    run exited 0 with "(N records dropped)" in a parenthesis; then 1 at its end, after it had
    driven the hand unrecorded for the rest of the recipe (4530 ticks dropped of a writer
    stopped 12 s, another outside audit). Now the first records dropped stop it,
    RECORDING_LOST (a ramp stop, exit 3), and replay heads the log with what it lacks. The
    writer is let go once the run has ended and waits for it, so it finishes the file."""
    log = tmp_path / "run.mcap"
    command = [
        *(sys.executable, "-m", "handctl", "run", "recipe", str(ROOT / DEFAULT_RECIPE)),
        *("--lockstep", "--log", str(log), "--summary-json", str(tmp_path / "s.json")),
    ]
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    with subprocess.Popen(
        command, cwd=tmp_path, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
    ) as proc:
        try:
            writer = None
            while writer is None:
                assert proc.poll() is None, proc.communicate()
                writer = _writer_pid(proc.pid)
                if writer is None:
                    time.sleep(POLL_S)
            # once it has said it is ready, which the run's start waits for: it closes the
            # descriptor it said it on (its fourth argument)
            ready_fd = (Path("/proc") / str(writer) / "cmdline").read_bytes().split(b"\0")[-2]
            while (Path("/proc") / str(writer) / "fd" / ready_fd.decode()).exists():
                assert proc.poll() is None, proc.communicate()
                time.sleep(POLL_S)
            os.kill(writer, signal.SIGSTOP)
            assert proc.stderr is not None
            err = ""
            while "for the recording writer to finish" not in err:  # the run has ended
                line = proc.stderr.readline()
                assert line, err
                err += line
            os.kill(writer, signal.SIGCONT)
            _, rest = proc.communicate(timeout=300)
        finally:
            if proc.poll() is None:
                proc.kill()
    err += rest
    assert proc.returncode == 3, err
    summary = json.loads((tmp_path / "s.json").read_text())
    recording = summary["recording"]
    dropped = recording["dropped_ticks"] + recording["dropped_frames"] + recording["dropped_events"]
    assert recording["dropped_ticks"] > 0 and "error" not in recording
    assert [f["code"] for f in summary["faults"]] == ["RECORDING_LOST"]
    assert "the recording writer has not taken the run's records in time" in err
    # stopped within a look (0.1 s) and the ramp (0.05 s) of the first drop, not at the end
    assert recording["dropped_ticks"] < 200 < summary["ticks"]
    done = handctl("replay", str(log))
    assert done.returncode == 0, done.stderr
    assert f"complete, but without {dropped} records the writer dropped during the run" in (
        done.stdout
    )


def test_the_run_says_its_log_s_name_escaped(tmp_path: Path) -> None:
    """A log named with a newline split the run's last line in two, and a byte that is not
    UTF-8 went to the terminal raw; replay said both escaped."""
    log = tmp_path / "a\nb.mcap"
    done = handctl(
        "run", "recipe", str(DEFAULT_RECIPE), "--max-seconds", "0.05", "--log", str(log)
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    assert f"frames to {tmp_path}/a\\nb.mcap\n" in done.stdout
    assert log.exists()


def test_a_bus_event_before_the_first_tick_leaves_a_readable_log(
    hand: HandConfig, tmp_path: Path
) -> None:
    """A bus event heard while the run starts, before its first tick (a remote frame, an
    error frame on a busy bus), was stamped tick -1, and every reader refused the whole log:
    "tick: expected an integer, at least 0, found -1" (found by an outside audit). It is the
    first tick's, whose poll takes it."""
    from handctl.online.bus import BusEvent, BusEventKind
    from handctl.recording import channels as ch
    from handctl.recording.reader import iter_decoded, open_recording

    path = tmp_path / "run.mcap"
    recorder = _recorder(hand, path)
    recorder._bus_event(BusEvent(BusEventKind.REMOTE_FRAME, "remote frame on 0x7FF", 1, 0x7FF))
    recorder.close({"outcome": "test"})
    recording = open_recording(path)
    events = [m for _, _, m in iter_decoded(recording, [ch.EVENTS])]
    assert [(e["kind"], e["tick"]) for e in events if e["kind"] == "bus"] == [("bus", 0)]


#: A run's start-up up to its log (``Recorder`` with the previous log kept, its writer
#: started), in a process of its own, killed by the test once it says "ready"
STARTED_AND_HELD = """
import sys
from pathlib import Path
from handctl.config import load_hand
from handctl.recording.metadata import start_metadata
from handctl.recording.recorder import Recorder

hand = load_hand(Path(sys.argv[1]))
recorder = Recorder(Path(sys.argv[2]), hand, start_metadata(hand, None, ("killed",)),
                    keep_previous=True)
recorder.wait_ready()
print("ready", flush=True)
sys.stdin.read()
"""

#: A process holding a file open (``locked``: with the lock a run's writer takes on it)
#: until its stdin closes
HOLDING = """
import fcntl, os, sys
fd = os.open(sys.argv[1], os.O_WRONLY | os.O_CREAT, 0o644)
if sys.argv[2] == "locked":
    fcntl.flock(fd, fcntl.LOCK_EX)
print("ready", flush=True)
sys.stdin.read()
"""


def _started(code: str, *args: str) -> subprocess.Popen[str]:
    proc = subprocess.Popen(
        [sys.executable, "-c", code, *args],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
        env={
            **os.environ,
            "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]),
        },
    )
    assert proc.stdout is not None and proc.stdout.readline() == "ready\n"
    return proc


def _unlocked(path: Path, timeout_s: float = 60.0) -> None:
    """Until nobody holds the lock on ``path`` (a killed run's writer finishes the file)."""
    import fcntl

    deadline = time.monotonic() + timeout_s
    fd = os.open(path, os.O_RDONLY)
    try:
        while True:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                return
            except BlockingIOError:
                assert time.monotonic() < deadline, f"{path} still locked"
                time.sleep(0.05)
    finally:
        os.close(fd)


def test_a_killed_run_s_recording_beside_its_log_goes_with_the_next_run_on_it(
    hand: HandConfig, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A run killed (SIGKILL) in its start-up leaves its recording beside the log, and every
    later run on the same log went on beside it: the hidden files piled up for good (found
    by an outside audit). The next run removes one nothing writes any more, and says so;
    one a live process writes (its writer's lock on it, or its run's process holding it
    open) stays, and so does another log's."""
    log = tmp_path / "run.mcap"
    killed = _started(STARTED_AND_HELD, str(HAND_YAML), str(log))
    left = tmp_path / f".run.mcap.{killed.pid}.handctl-partial"
    assert left.exists()
    killed.kill()
    killed.communicate()
    _unlocked(left)  # its writer, seeing its run gone, finishes the file and ends
    assert left.exists()
    holders = []
    try:
        # a writer whose run is gone (a pid no process has), and a run's process in the
        # moment between making its file and locking it
        gone = subprocess.Popen([sys.executable, "-c", ""])
        gone.wait()
        kept = []
        for how, pid in (("locked", gone.pid), ("open", None)):
            holders.append(_started(HOLDING, str(tmp_path / f"{how}.tmp"), how))
            kept.append(tmp_path / f".run.mcap.{pid or holders[-1].pid}.handctl-partial")
            (tmp_path / f"{how}.tmp").rename(kept[-1])
        # a live process of the name's pid that does not write it (a pid given again)
        holders.append(_started(HOLDING, str(tmp_path / "unrelated.tmp"), "open"))
        reused = tmp_path / f".run.mcap.{holders[-1].pid}.handctl-partial"
        shutil.copy(left, reused)
        other_log = tmp_path / f".other.mcap.{killed.pid}.handctl-partial"
        shutil.copy(left, other_log)
        capsys.readouterr()
        recorder = Recorder(log, hand, start_metadata(hand, None, ("next",)), keep_previous=True)
        recorder.wait_ready()
        recorder.claim()
        recorder.close({"outcome": "next"})
        err = capsys.readouterr().err
    finally:
        for holder in holders:
            holder.communicate("")
    for removed in (left, reused):
        assert not removed.exists()
        said = f"handctl: removed {removed}: left beside this log by a run killed before it began"
        assert said in err, err
    assert all(p.exists() for p in kept) and other_log.exists()
    assert open_recording(log).json_meta("handctl.summary") == {"outcome": "next"}


def test_the_summaries_of_a_log_whose_path_is_not_utf_8_are_strict_json(tmp_path: Path) -> None:
    """``--summary-json`` and ``replay --json`` wrote such a path as ``"\\udcff"``, a lone
    surrogate that strict JSON readers (orjson, Rust's, Go's) refuse with the whole file; now
    the byte is ``\\xff``, as the metadata have it."""
    import orjson

    log = tmp_path / os.fsdecode(b"we\xffird.mcap")
    shown = str(tmp_path / "we\\xffird.mcap")
    run_json, replay_json = tmp_path / "run.json", tmp_path / "replay.json"
    done = handctl(
        "run", "recipe", DEFAULT_RECIPE, "--log", str(log), "--max-seconds", "0.2",
        "--summary-json", str(run_json),
    )  # fmt: skip
    assert done.returncode == 0, done.stdout + done.stderr
    done = handctl("replay", str(log), "--json", str(replay_json))
    assert done.returncode == 0, done.stdout + done.stderr
    run = orjson.loads(run_json.read_bytes())
    assert run["recording"]["path"] == shown
    replay = orjson.loads(replay_json.read_bytes())
    assert replay["summary"]["file"] == shown
