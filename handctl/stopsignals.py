"""The stop signals of a run: SIGINT, SIGTERM, SIGHUP, SIGTSTP, SIGQUIT and the others whose
default ends the process, each a controlled stop with exit 130 whenever it comes
(``StopSignals``).

A module of its own, light to import (the standard library only, the runtime's modules when a
run is handed over), so that ``handctl run`` takes the signals over before it loads the
modules a run needs: a signal raised inside one of those imports is what the class keeps
from happening.
"""

from __future__ import annotations

import contextlib
import signal
import threading
from collections.abc import Iterator, Sequence
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    import asyncio

    from handctl.online.loop import RunResult, Runtime


def _ending() -> tuple[signal.Signals | int, ...]:
    named = (
        "SIGHUP", "SIGQUIT", "SIGUSR1", "SIGUSR2", "SIGALRM", "SIGXCPU", "SIGVTALRM",
        "SIGPROF", "SIGIO", "SIGPWR", "SIGSTKFLT",
    )  # fmt: skip
    found: list[signal.Signals | int] = [getattr(signal, n) for n in named if hasattr(signal, n)]
    low, high = getattr(signal, "SIGRTMIN", 0), getattr(signal, "SIGRTMAX", -1)
    found += [n for n in range(int(low), int(high) + 1) if n not in found]
    return tuple(found)


#: Every signal whose default ends the process by the signal and that a process can catch,
#: but SIGINT and SIGTERM (taken apart) and the faults the process raises on itself (SIGSEGV,
#: SIGBUS, SIGILL, SIGFPE, SIGTRAP, SIGSYS, SIGABRT: a handler cannot resume after those):
#: a terminal, a session's end, a stray ``kill`` and the kernel's resource limits can send
#: them. SIGXCPU is the one an ``--rt`` run meets for real: the kernel sends it to a
#: SCHED_FIFO loop past the soft limit of its ``RLIMIT_RTTIME`` (and to any process past
#: ``ulimit -S -t``), and it killed the run with its last torque on the bus, no zero, no
#: disable, no summary. (At a hard limit the kernel sends SIGKILL, which no process can catch:
#: a limit meant to stop a run gently is a soft one.) Every command takes them as Ctrl-C
#: (``__main__.entry``, ``cli.main``) and a run as its controlled stop, unless it was started
#: with one ignored (``nohup``: asked to go on). SIGPIPE and SIGXFSZ are not among them:
#: Python ignores both, and a closed pipe or a file past ``ulimit -f`` is an error of the
#: write (a log's is the recording's failure, docs/recording.md).
ENDING = _ending()


def signal_name(number: int) -> str:
    """``SIGXCPU``, or ``SIGRTMIN+3`` for a real-time signal (``signal.Signals`` names only the
    first and the last of those, and raised on the others inside the handler)."""
    try:
        return signal.Signals(number).name
    except ValueError:
        low = int(getattr(signal, "SIGRTMIN", 0))
        return f"SIGRTMIN+{number - low}" if low and number > low else f"signal {number}"


#: The names of the stop signals that came after the command had its result (``finished``):
#: noted, not raised. Empty while the command works (``working``).
LATE: list[str] = []


class _Command:
    finished = False  # whether the command has its result (``finished``)
    raised = ""  # the signal ``interrupt`` last raised as an interrupt ("": none)


def working() -> None:
    """A command begins (``cli.main``): a stop signal interrupts it again."""
    _Command.finished = False
    _Command.raised = ""
    LATE.clear()


def raised() -> str:
    """The stop signal this command raised as an interrupt ("": none). An interrupt raised
    inside an extension module's import comes out as that import's failure (mujoco's
    ``ImportError: initialization failed``, numpy's advice to reinstall it): a Ctrl-C in the
    first second of ``nodes`` or ``monitor`` was said as an internal error, exit 1. Such an
    error after an interrupt is the interrupt."""
    return _Command.raised


#: The commands that drive a hand: their Ctrl-Z (SIGTSTP) is a stop from the first line
#: (``__main__.entry``), not only once a run's ``StopSignals`` takes it. Before, one that
#: came while the command's modules loaded (seconds on a loaded machine) suspended the
#: process, and once resumed the run went on to drive the hand and exit 0, the operator's
#: stop lost. ``replay --to-bus`` as well. Every other command may be suspended as any
#: program is.
DRIVING = ("run", "jog", "calibrate")


def drives_a_hand(argv: Sequence[str]) -> bool:
    """Whether ``argv`` (without the program's name) is a command of ``DRIVING`` (its first
    word that is not an option), or a replay onto a bus."""
    command = next((a for a in argv if not a.startswith("-")), "")
    if command == "replay":
        return any(a == "--to-bus" or a.startswith("--to-bus=") for a in argv)
    return command in DRIVING


def ignore_stops() -> None:
    """The stop signals this command takes as Ctrl-C (``interrupt``) ignored for what is left
    of it, the interpreter's shutdown: the shutdown puts back the default of every signal with
    a Python handler, and a SIGTERM in its last tens of milliseconds killed the process by the
    signal (exit 143), after a command that had its result or had said "interrupted"."""
    for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGTSTP, *ENDING):
        if signal.getsignal(sig) is interrupt:
            signal.signal(sig, signal.SIG_IGN)


def interruption() -> str:
    """The last line of a command a stop signal interrupted: "interrupted", and by which
    signal when it was not Ctrl-C. A supervisor's SIGTERM, a terminal's SIGHUP and the
    kernel's SIGXCPU at a real-time limit were all said as a bare "interrupted", as if
    someone had pressed Ctrl-C: the one who reads the log was left to guess which."""
    name = _Command.raised
    return f"interrupted by {name}" if name and name != "SIGINT" else "interrupted"


def finished() -> None:
    """The command has its result (its exit code, its files written): a stop signal from
    here on has nothing left to stop. Raised as an interrupt, one that came as a run's summary
    was printed turned the run's exit 0 into 130 ("interrupted", over a summary that says
    completed)."""
    _Command.finished = True


def interrupt(signum: int, frame: object) -> None:
    """A signal as Ctrl-C: an interrupt that unwinds what was started, then exit 130 (the
    handler of every command's stop signals before, and outside, a run's ``StopSignals``);
    once the command has its result (``finished``), noted in ``LATE`` instead."""
    if _Command.finished:
        LATE.append(signal_name(signum))
        return
    _Command.raised = signal_name(signum)
    raise KeyboardInterrupt(_Command.raised)


class StopSignals:
    """The stop signals (``SIGNALS``) over a whole run, from before anything starts to the last
    line of the log, so that each ends the run the same way whenever it comes, with exit 130:

    - before the runtime runs (the modules loading, the log opening, the simulated hand
      starting): noted, and raised as an interrupt (``KeyboardInterrupt``) at the start-up's
      next ``checkpoint``, between two of its steps, which unwinds what was started; nothing
      was sent. Never from the handler itself: that would raise wherever the main thread is,
      inside an extension module's initialisation that cannot survive an exception (orjson's
      dereferences the failed import and crashes the process), inside code that ``exec``
      compiled (CPython then exits by SIGINT whatever exit code was chosen), or between a
      resource's creation and its registration for clean-up (a log file created and left
      empty). A signal noted when the runtime is handed over becomes its controlled stop;
    - while it runs, start-up included: the runtime's controlled stop (torque to zero, nodes
      disabled), asked for through the event loop, never by an exception inside a tick;
    - afterwards (the hand is stopped; the log and the summary are being finished), and once
      the first interrupt is unwinding: noted and otherwise ignored, so that they finish.

    One handler throughout, rather than asyncio's own for the run: asyncio puts back the
    default handlers when it removes its own, and a SIGTERM then would kill the process before
    its log is finished. Outside the main thread signals cannot be handled: nothing changes.
    """

    #: SIGHUP too: the terminal or the SSH session a run was started from going away must not
    #: kill the host mid-grasp (no stop, nodes left enabled until their watchdogs trip, the
    #: log without its last tick and summary); it is a controlled stop like the others. Unless
    #: the run was started with it ignored (``nohup``): then it was asked to go on, and does.
    #: SIGTSTP (Ctrl-Z) as well: suspended mid-grasp, the loop froze, the nodes' watchdogs
    #: dropped the torque at once and latched a TIMEOUT fault the next run had to reset, and
    #: the log and the summary waited for a resume. A run that drives a hand cannot pause; it
    #: stops, as asked, and says why.
    #: SIGQUIT (Ctrl-\\, the key pressed when Ctrl-C seems slow), SIGUSR1, SIGUSR2, SIGALRM,
    #: SIGXCPU and the rest of ``ENDING``: their default ends the process by the signal, with
    #: the same result as a hang-up's,
    #: and a stray ``kill -USR1`` or a second terminal key is no reason to leave a hand under
    #: torque. A run started with SIGHUP or one of these but SIGQUIT ignored keeps ignoring it
    #: (``HONOURED_IF_IGNORED`` are the ones taken whatever was inherited).
    SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGTSTP, *ENDING)
    #: SIGINT, SIGQUIT and SIGTERM are a stop even when inherited ignored: a shell starts a
    #: script's background job with SIGINT and SIGQUIT ignored, whatever its user meant, and
    #: its user still means ``kill -INT`` and ``kill -QUIT`` (a jog started so kept its torque
    #: through a SIGQUIT); SIGTSTP cannot be asked for by ignoring it. Only SIGHUP ignored is a
    #: wish (``nohup``), and the rest are ignored only by someone who meant it.
    HONOURED_IF_IGNORED = (signal.SIGINT, signal.SIGQUIT, signal.SIGTERM, signal.SIGTSTP)
    #: SIGTTOU and SIGTTIN suspend a process as SIGTSTP does: a run in the background of a
    #: terminal set ``stty tostop`` was stopped mid-grasp by its own status line (or by a
    #: ``kill -TTOU``), with its torque on. Ignored, a write to the terminal goes through and
    #: a read fails; nothing suspends the run. Not a stop: a run put in the background is
    #: not asked to end. (Caught instead, the write the signal interrupts is tried again
    #: and signalled again, for ever.)
    DEAF = (signal.SIGTTOU, signal.SIGTTIN)

    def __init__(self) -> None:
        self.runtime: Runtime | None = None
        self.finishing = False
        self.noted = ""  # a signal during start-up that no checkpoint has raised yet
        self.interrupted = ""  # the signal that interrupted the run before the runtime ran
        self.ignored: list[str] = []
        self._loop: asyncio.AbstractEventLoop | None = None
        self._saved: dict[int, Any] = {}

    def __enter__(self) -> StopSignals:
        if threading.current_thread() is threading.main_thread():
            for deaf in self.DEAF:
                self._saved[deaf] = signal.signal(deaf, signal.SIG_IGN)
            for sig in self.SIGNALS:
                if sig not in self.HONOURED_IF_IGNORED and signal.getsignal(sig) is signal.SIG_IGN:
                    continue  # started under nohup, for one: asked to outlive its terminal
                self._saved[sig] = signal.signal(sig, self._handle)
        return self

    def __exit__(self, kind: object, exc: BaseException | None, tb: object) -> None:
        for sig, handler in self._saved.items():
            signal.signal(sig, handler)
        if self.noted and exc is None:
            # The start-up ended without another checkpoint or a runtime to stop: the signal
            # still ends the command as the interrupt it was.
            self.interrupted, self.noted = self.noted, ""
            raise KeyboardInterrupt(self.interrupted)
        interrupted = self.interrupted or self.noted
        if interrupted and exc is not None and not isinstance(exc, KeyboardInterrupt):
            # Whatever else went wrong once a stop was asked for, the run was interrupted.
            raise KeyboardInterrupt(interrupted) from exc

    def checkpoint(self) -> None:
        """Raise the interrupt a signal asked for during start-up, if one did: here, between
        two steps, everything started so far is on the run's exit stack and unwinds."""
        if self.noted and not self.finishing:
            self.finishing = True
            self.interrupted, self.noted = self.noted, ""
            raise KeyboardInterrupt(self.interrupted)

    def _handle(self, signum: int, frame: object) -> None:
        name = signal_name(signum)
        if signum == signal.SIGTSTP:
            name += " (Ctrl-Z: a run that drives a hand cannot be suspended; stopped instead)"
        if self.finishing or self.noted:
            self.ignored.append(name)
            return
        if self.runtime is None or self._loop is None:
            self.noted = f"signal {name}"  # for the next checkpoint (class docstring)
            _Command.raised = signal_name(signum)  # raised there, as ``interrupt`` raises it
            return
        try:
            self._loop.call_soon_threadsafe(self.runtime.request_stop, f"signal {name}")
        except RuntimeError:  # the loop has just closed: the run is over
            self.ignored.append(name)

    async def run(self, runtime: Runtime) -> RunResult:
        """Run ``runtime`` with the signals as its controlled stop.

        A stop asked for before the nodes were enabled is the same interrupt as one asked for
        later (exit 130), not a failed start-up: nothing went wrong with the hand.
        """
        # Here, not at the top: loaded by now, by the run being handed over (module docstring).
        import asyncio

        self._loop = asyncio.get_running_loop()
        self.runtime = runtime
        if self.noted:  # came after the last checkpoint: the runtime's stop, before it sends
            runtime.request_stop(self.noted)
            self.noted = ""
        try:
            return await runtime.run()
        finally:
            self.finishing = True
            self.runtime = None


@contextlib.contextmanager
def held_back() -> Iterator[list[str]]:
    """The stop signals held back over a command's last step (a result file replaced, and the
    line saying so), so that what the command says and its exit code agree with what it did.

    A signal raised in the middle of that step interrupted the command after the file was
    replaced: exit 130 and "interrupted", with the new file in place. Held back, a signal that
    came during the step is noted, never acted on, and its name is yielded for the command to
    say it came too late to stop anything. Held by this process's handlers, not by a signal
    mask: a mask is the calling thread's, and with another thread alive (a calibration's) the
    kernel gave the signal to that one, whose handler Python then ran in the main thread all
    the same. A signal this process ignores stays ignored. Outside the main thread nothing is
    held."""
    late: list[str] = []
    if threading.current_thread() is not threading.main_thread():
        yield late
        return

    def note(signum: int, frame: object) -> None:
        name = signal_name(signum)
        if name not in late:
            late.append(name)

    # (None: a handler not installed from Python, which cannot be put back)
    taken = [
        sig for sig in StopSignals.SIGNALS if signal.getsignal(sig) not in (signal.SIG_IGN, None)
    ]
    with _handled(dict.fromkeys(taken, note)):
        yield late


@contextlib.contextmanager
def _handled(handlers: dict[int, Any]) -> Iterator[None]:
    """``handlers`` (signal: handler) in place over the block, the ones before put back."""
    saved: dict[int, Any] = {}
    try:
        for sig, handler in handlers.items():
            saved[sig] = signal.signal(sig, handler)
        yield
    finally:
        for sig, handler in saved.items():
            signal.signal(sig, handler)


class Noted:
    """The stop signals that came over a ``noted_stops`` stretch: the first, and the others."""

    def __init__(self) -> None:
        self.first = ""
        self.later: list[str] = []


@contextlib.contextmanager
def noted_stops() -> Iterator[Noted]:
    """The stop signals (``StopSignals.SIGNALS``, SIGTSTP among them) noted, never raised, over
    a stretch that drives a hand outside a run: ``replay --to-bus``, which looks at
    ``first`` between two frames and then sends its stop. Raised as an interrupt, a second
    Ctrl-C cut the stop itself short (the hand left under the last torques sent, no zero, no
    disable), and Ctrl-Z suspended the replay mid-stream; SIGTTOU and SIGTTIN are ignored as
    in a run (``StopSignals.DEAF``). A signal inherited ignored stays so, but for
    ``StopSignals.HONOURED_IF_IGNORED``. Outside the main thread nothing is noted."""
    noted = Noted()
    if threading.current_thread() is not threading.main_thread():
        yield noted
        return

    def note(signum: int, frame: object) -> None:
        name = signal_name(signum)
        if signum == signal.SIGTSTP:
            name += " (Ctrl-Z: a replay onto a bus cannot be suspended; stopped instead)"
        if noted.first:
            noted.later.append(name)
        else:
            noted.first = name
            # the command's last line names it too (``interruption``): it said a bare
            # "interrupted" after a SIGTERM (found by an outside audit)
            _Command.raised = signal_name(signum)

    handlers: dict[int, Any] = dict.fromkeys(StopSignals.DEAF, signal.SIG_IGN)
    for sig in StopSignals.SIGNALS:
        inherited = signal.getsignal(sig)
        if inherited is not None and (
            inherited is not signal.SIG_IGN or sig in StopSignals.HONOURED_IF_IGNORED
        ):
            handlers[sig] = note
    with _handled(handlers):
        yield noted


@contextlib.contextmanager
def ctrl_c_at_once() -> Iterator[None]:
    """SIGINT as the interrupt it is (``interrupt``), at once, over an event loop a command
    runs to its end, ``replay --rerun``'s. With Python's own handler in place, ``asyncio.run``
    puts in one that only cancels its task, which the re-run's lockstep ticks took at the
    end: a Ctrl-C waited out the whole re-run (seconds, minutes on a long log), and its
    result was then thrown away (SIGTERM ended it at once)."""
    main = threading.current_thread() is threading.main_thread()
    if not main or signal.getsignal(signal.SIGINT) is not signal.default_int_handler:
        yield
        return
    with _handled({signal.SIGINT: interrupt}):
        yield
