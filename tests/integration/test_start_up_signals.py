"""A signal during a run's start-up (the log opening, the modules it needs loading, the
simulated hand starting): exit 130 with one line, never a crash, and a log that is either
absent or a short MCAP that ``handctl replay`` reads, never an empty file.

The signal is raised from a point of the start-up itself (a step, an import), so each case
hits the moment it names on any machine at any load, where a signal sent after a sleep would
hit wherever the start-up happened to be."""

from __future__ import annotations

import json
import os
import signal
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

from handctl import session
from handctl.config import HandConfig
from handctl.online.recipes.loader import load_recipe
from handctl.recording.recorder import Recorder

from ..conftest import DEFAULT_RECIPE, ROOT, handctl

#: The steps of ``run_recipe``'s start-up, in order, each as the attribute of the module or
#: class that holds it, with the signal raised in it. ``Recorder._send`` is the set-up handed
#: to the recording's writer, which waits for the writer to have started: the longest wait of
#: the start-up, where every signal is tried; elsewhere one does for all.
STEPS: list[tuple[Any, str, signal.Signals]] = [
    (session, "_recorder", signal.SIGINT),
    (Recorder, "_send", signal.SIGINT),
    (Recorder, "_send", signal.SIGTERM),
    (Recorder, "_send", signal.SIGHUP),
    (session, "_reanalyser", signal.SIGINT),
    (session, "_start_peer", signal.SIGINT),
    (session, "open_bus", signal.SIGINT),
    (session, "_start_clock", signal.SIGINT),
    (session, "_start_recording", signal.SIGINT),
]


def _replays(log: Path) -> None:
    """The log reads, and says the run was interrupted (it said 'unknown (the log has no
    summary)', as a log cut short does)."""
    done = handctl("replay", str(log), timeout=120)
    assert done.returncode == 0, done.stderr
    first = done.stdout.splitlines()[0]
    assert "interrupted" in first and "no summary" not in first, first


@pytest.mark.parametrize(
    ("owner", "step", "sig"),
    STEPS,
    ids=[f"{o.__name__.rsplit('.', 1)[-1]}.{s}-{g.name}" for o, s, g in STEPS],
)
def test_a_signal_inside_each_start_up_step_is_an_interrupt_with_a_readable_log(
    hand: HandConfig,
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    owner: Any,
    step: str,
    sig: signal.Signals,
) -> None:
    """The signal comes at the start of the step: the step still runs to its end (an
    exception inside it would leave what it started half made: a log file created and never
    handed to its writer), and the start-up stops right after it. The log was opened first,
    so it is there, short and finished."""
    original: Callable[..., Any] = getattr(owner, step)

    def signalled(*args: Any, **kwargs: Any) -> Any:
        signal.raise_signal(sig)
        return original(*args, **kwargs)

    monkeypatch.setattr(owner, step, signalled)
    log = tmp_path / "run.mcap"
    recipe = load_recipe(ROOT / DEFAULT_RECIPE, hand)
    before = signal.getsignal(sig)
    with pytest.raises(KeyboardInterrupt, match=sig.name):
        session.run_recipe(session.RunRequest(hand=hand, recipe=recipe, log=log, max_seconds=1))
    assert signal.getsignal(sig) is before
    _replays(log)


#: ``sitecustomize`` of a ``python -m handctl`` the test runs: it raises a signal from inside
#: the start-up, at the point HANDCTL_TEST_SIGNAL names (read once: the run's own processes,
#: the recording's writer and the simulated hand, start without it):
#: - ``import MODULE SIGNAL``: the first time MODULE is looked up for an import, wherever the
#:   import comes from;
#: - ``exec-in MODULE SIGNAL``: in the first code that ``exec`` compiled (the methods a
#:   dataclass is given, a named tuple) to run once MODULE is being imported. A signal that
#:   comes while such code compiles is taken as it starts.
SITECUSTOMIZE = """
import os, signal, sys

point = os.environ.pop("HANDCTL_TEST_SIGNAL", "")
if point:
    kind, module, name = point.split()
    sig = signal.Signals[name]

    def in_exec(frame, event, arg):
        if frame.f_code.co_filename == "<string>":
            sys.settrace(None)
            signal.raise_signal(sig)

    class At:
        def find_spec(self, fullname, path=None, target=None):
            if fullname == module:
                sys.meta_path.remove(self)
                if kind == "import":
                    signal.raise_signal(sig)
                else:
                    sys.settrace(in_exec)
            return None

    sys.meta_path.insert(0, At())
"""


@pytest.mark.parametrize(
    ("point", "logged", "summarised"),
    [
        # The command line module loading, before handctl.cli.main has taken the signals
        # over: Python's own Ctrl-C (a traceback), SIGTERM's default (the process killed).
        ("import handctl.cli", False, False),
        # The run's modules loading: the command stops at the run's first step, before the
        # log (its summary says so). CPython exits by SIGINT, whatever exit code was chosen,
        # after an interrupt escaped code that ``exec`` compiled (``python -m`` only).
        ("exec-in handctl.session", False, True),
        # orjson's initialisation imports uuid and crashes the process if that import fails:
        # every command loads orjson first, with the signals held back, so the signal comes
        # right after it, before anything else
        ("import uuid", False, False),
        # the simulated hand starting, the log open
        ("import mujoco", True, True),
    ],
)
@pytest.mark.parametrize(
    "sig", [signal.SIGINT, signal.SIGTERM, signal.SIGTSTP], ids=["SIGINT", "SIGTERM", "SIGTSTP"]
)
def test_a_signal_inside_the_start_up_code_is_an_interrupt(
    tmp_path: Path, point: str, logged: bool, summarised: bool, sig: signal.Signals
) -> None:
    (tmp_path / "sitecustomize.py").write_text(SITECUSTOMIZE)
    log = tmp_path / "run.mcap"
    path = os.pathsep.join(str(p) for p in (ROOT, tmp_path))
    done = handctl(
        "run",
        "recipe",
        DEFAULT_RECIPE,
        "--log",
        str(log),
        "--max-seconds",
        "1",
        "--summary-json",
        str(tmp_path / "summary.json"),
        env={"PYTHONPATH": path, "HANDCTL_TEST_SIGNAL": f"{point} {sig.name}"},
        timeout=300,
    )
    assert done.returncode == 130, done.stderr
    said = "interrupted" if sig == signal.SIGINT else f"interrupted by {sig.name}"
    assert done.stderr.strip().splitlines()[-1] == f"handctl: {said}", done.stderr
    assert "Traceback" not in done.stderr
    assert log.exists() is logged
    # once the run's start-up has begun, the summary asked for is written, and says so
    assert (tmp_path / "summary.json").exists() is summarised
    if logged:
        _replays(log)
    if summarised:
        summary = json.loads((tmp_path / "summary.json").read_text())
        assert summary["outcome"] == "interrupted" and summary["ticks"] == 0
        # (SIGTSTP's name is followed by why a run cannot be suspended)
        assert f"signal {sig.name}" in summary["message"]
        assert "during the start-up" in summary["message"]


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM], ids=["SIGINT", "SIGTERM"])
def test_a_signal_inside_orjsons_loading_is_an_interrupt_for_any_command(
    tmp_path: Path, sig: signal.Signals
) -> None:
    """``handctl replay`` crashed (SIGSEGV) on a Ctrl-C inside orjson's first import, as a
    run did: orjson is loaded for every command at its first line, the signals held back."""
    (tmp_path / "sitecustomize.py").write_text(SITECUSTOMIZE)
    path = os.pathsep.join(str(p) for p in (ROOT, tmp_path))
    done = handctl(
        "replay",
        str(tmp_path / "no-such.mcap"),
        env={"PYTHONPATH": path, "HANDCTL_TEST_SIGNAL": f"import uuid {sig.name}"},
        timeout=120,
    )
    assert done.returncode == 130, done.stderr
    said = "interrupted" if sig == signal.SIGINT else f"interrupted by {sig.name}"
    assert done.stderr.strip().splitlines()[-1] == f"handctl: {said}", done.stderr


def test_a_signal_after_the_hand_has_stopped_is_said_and_the_run_finishes(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A SIGTERM while the summary was being made (the loop over, the hand stopped) was
    ignored, as it should be so that the log and summary finish, but said nowhere: the run
    exited 0 as if it had never come."""
    from handctl import cli

    original = session.summarise_run

    def signalled(*args: Any, **kwargs: Any) -> Any:
        signal.raise_signal(signal.SIGTERM)
        return original(*args, **kwargs)

    monkeypatch.setattr(session, "summarise_run", signalled)
    summary = tmp_path / "summary.json"
    args = ["run", "recipe", str(ROOT / DEFAULT_RECIPE), "--max-seconds", "0.3"]
    assert cli.main([*args, "--summary-json", str(summary)]) == cli.EXIT_OK
    err = capsys.readouterr().err
    assert "handctl: SIGTERM came after the hand had stopped" in err
    assert json.loads(summary.read_text())["outcome"] == "time_budget"


#: a SIGTERM to the command once it has its result: from a thread, as soon as the run's
#: summary is written (renamed into place whole), or from the last exit handler, in the
#: interpreter's own shutdown
AFTER_THE_RESULT = """
import atexit, os, signal, sys, threading, time

when, summary = os.environ.pop("HANDCTL_TEST_LATE_SIGNAL", " ").split(" ", 1)

def watch():
    while not os.path.exists(summary):
        time.sleep(0.0005)
    os.kill(os.getpid(), signal.SIGTERM)

if when == "summarised":
    threading.Thread(target=watch, daemon=True).start()
elif when == "shutdown":
    atexit.register(os.kill, os.getpid(), signal.SIGTERM)  # registered first, run last
"""


@pytest.mark.parametrize("when", ["summarised", "shutdown"])
def test_a_signal_after_the_command_has_its_result_leaves_its_exit(
    tmp_path: Path, when: str
) -> None:
    """A SIGTERM once a run had finished and written its summary: raised as an interrupt as
    the summary was printed, it turned the run's exit 0 into 130 ('interrupted'), and in the
    interpreter's shutdown, which puts back every signal's default, it killed the process by
    the signal (143 in a shell). The result stands."""
    (tmp_path / "sitecustomize.py").write_text(AFTER_THE_RESULT)
    summary = tmp_path / "summary.json"
    path = os.pathsep.join(str(p) for p in (ROOT, tmp_path))
    done = handctl(
        "run", "recipe", DEFAULT_RECIPE, "--max-seconds", "0.3", "--summary-json", str(summary),
        env={"PYTHONPATH": path, "HANDCTL_TEST_LATE_SIGNAL": f"{when} {summary}"},
        timeout=300,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    assert json.loads(summary.read_text())["outcome"] == "time_budget"
    for said in ("interrupted", "Traceback", "Exception ignored"):
        assert said not in done.stderr, done.stderr


#: ``handctl.cli.main`` interrupted, as a stop signal that lands outside the command's own
#: handling (in its last lines, or in an import before them) leaves it: what ``entry`` then
#: leaves the stop signals as, for the interpreter's shutdown
INTERRUPTED_ENTRY = """
import signal, sys
import handctl.cli
from handctl import __main__

def main():
    raise KeyboardInterrupt("SIGTERM")

handctl.cli.main = main
code = __main__.entry()
left = [s.name for s in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)
        if signal.getsignal(s) is not signal.SIG_IGN]
print(code, left)
"""


def test_an_interrupted_command_leaves_the_stop_signals_ignored_for_its_shutdown() -> None:
    """A supervisor retrying its SIGTERM every 2 ms: ``nodes`` (and ``jog``) said
    "interrupted" and then died by the signal (exit 143, 1 run in 3; an outside probe). The
    interrupt had left ``__main__.entry`` the one way that did not ignore the stop signals
    before the interpreter's shutdown, which puts their defaults back."""
    import subprocess
    import sys

    done = subprocess.run(
        [sys.executable, "-c", INTERRUPTED_ENTRY],
        cwd=ROOT,
        env={**os.environ, "PYTHONPATH": str(ROOT)},
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    assert done.returncode == 0, done.stderr
    assert done.stdout.split("\n")[0] == "130 []", done.stdout
    assert done.stderr == "handctl: interrupted\n"
