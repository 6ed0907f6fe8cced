"""The stop signals over a run (``stopsignals.StopSignals``), raised in this very process."""

from __future__ import annotations

import asyncio
import contextlib
import signal
import threading
import time

import pytest

from handctl.config import HandConfig
from handctl.online.bus import HandBus
from handctl.online.drivers.hand import HandDriver
from handctl.online.loop import Outcome, RunResult, Runtime
from handctl.online.recipes.loader import load_recipe
from handctl.protocol import Protocol
from handctl.stopsignals import StopSignals, drives_a_hand, held_back, signal_name

from ..conftest import ROOT


@pytest.mark.parametrize(
    "sig", [signal.SIGINT, signal.SIGTERM, signal.SIGHUP, signal.SIGQUIT, signal.SIGUSR1]
)
def test_before_the_run_a_signal_is_an_interrupt_at_the_next_checkpoint(
    sig: signal.Signals,
) -> None:
    """Not where it lands (inside an import, a half-made step): the start-up goes on to its
    next checkpoint, and stops there."""
    before = signal.getsignal(sig)
    with StopSignals() as signals:
        signal.raise_signal(sig)  # nothing raised here
        with pytest.raises(KeyboardInterrupt, match=sig.name):
            signals.checkpoint()
        signal.raise_signal(sig)  # the interrupt is unwinding: this one is ignored
        signals.checkpoint()
    assert signal.getsignal(sig) is before  # put back afterwards


def test_a_signal_that_no_checkpoint_took_is_an_interrupt_at_the_end() -> None:
    with pytest.raises(KeyboardInterrupt, match="SIGHUP"), StopSignals():
        signal.raise_signal(signal.SIGHUP)


@pytest.mark.parametrize("sig", [signal.SIGHUP, signal.SIGALRM])
def test_a_run_started_with_a_signal_ignored_keeps_ignoring_it(sig: signal.Signals) -> None:
    """``nohup handctl run ...`` asks the run to outlive its terminal: the hang-up it then
    gets is not a stop."""
    before = signal.signal(sig, signal.SIG_IGN)
    try:
        with StopSignals():
            assert signal.getsignal(sig) is signal.SIG_IGN
            signal.raise_signal(sig)  # ignored: no KeyboardInterrupt
        assert signal.getsignal(sig) is signal.SIG_IGN
        with held_back() as late:  # nor held back and then named as a late one
            signal.raise_signal(sig)
        assert late == []
    finally:
        signal.signal(sig, before)


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGQUIT])
def test_sigint_and_sigquit_are_a_stop_even_when_inherited_ignored(sig: signal.Signals) -> None:
    """A shell starts a script's background job with SIGINT and SIGQUIT ignored; its user
    still means ``kill -INT`` and ``kill -QUIT`` (a jog so started kept its torque through a
    SIGQUIT: an outside audit)."""
    before = signal.signal(sig, signal.SIG_IGN)
    try:
        with pytest.raises(KeyboardInterrupt, match=sig.name), StopSignals():
            signal.raise_signal(sig)
    finally:
        signal.signal(sig, before)


def _waiting_runtime(hand: HandConfig, protocol: Protocol, host: HandBus) -> Runtime:
    """A runtime of the shipped recipe on a bus nobody else is on: its start-up waits for
    nodes that never answer (for ten minutes, far beyond any test)."""
    from handctl.online.clock import LockstepClock

    recipe = load_recipe(ROOT / "config" / "recipes" / "swap_two_cylinders.yaml", hand)
    return Runtime(
        hand,
        HandDriver(hand, protocol, host),
        LockstepClock(hand.bus.period_s, lambda: None),
        recipe,
        startup_timeout_s=600.0,
    )


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_a_signal_during_start_up_is_an_interrupt_with_nothing_sent(
    hand: HandConfig, protocol: Protocol, bus_pair: tuple[HandBus, HandBus], sig: signal.Signals
) -> None:
    """The nodes have not answered yet (nobody is on the bus): the start-up is still waiting
    for them when the signal comes. That is an interrupt (exit 130), not a failed start-up
    (exit 3): nothing went wrong with the hand, and nothing was sent to it."""
    host, listener = bus_pair
    runtime = _waiting_runtime(hand, protocol, host)

    async def run(signals: StopSignals) -> RunResult:
        asyncio.get_running_loop().call_later(0.05, signal.raise_signal, sig)
        return await signals.run(runtime)

    with StopSignals() as signals:
        result = asyncio.run(run(signals))
    assert result.outcome is Outcome.INTERRUPTED, result.message
    assert result.faults == []
    assert sig.name in result.message and "start-up" in result.message
    assert listener.drain() == []


def test_a_signal_before_the_runtime_runs_is_its_stop_with_nothing_sent(
    hand: HandConfig, protocol: Protocol, bus_pair: tuple[HandBus, HandBus]
) -> None:
    """After the start-up's last checkpoint: the runtime stops before it sends anything."""
    host, listener = bus_pair
    runtime = _waiting_runtime(hand, protocol, host)
    with StopSignals() as signals:
        signal.raise_signal(signal.SIGTERM)
        result = asyncio.run(signals.run(runtime))
    assert result.outcome is Outcome.INTERRUPTED, result.message
    assert result.faults == []
    assert "SIGTERM" in result.message
    assert listener.drain() == []


def test_an_error_once_a_signal_came_is_still_the_interrupt() -> None:
    """Whatever else went wrong once a stop was asked for, the run was interrupted (exit
    130), the error its cause."""
    with pytest.raises(KeyboardInterrupt) as caught, StopSignals():
        signal.raise_signal(signal.SIGINT)
        raise ImportError("initialization failed")
    assert isinstance(caught.value.__cause__, ImportError)


def test_other_errors_pass_through() -> None:
    with pytest.raises(ImportError), StopSignals():
        raise ImportError("a real one")


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM, signal.SIGHUP, signal.SIGQUIT])
def test_a_signal_during_a_commands_last_step_is_taken_off_and_named(
    sig: signal.Signals,
) -> None:
    """A file replaced and the line saying so: a signal then came after the work was done,
    so it neither cuts the step nor turns a done command into an interrupted one."""
    before = signal.getsignal(sig)
    seen: list[int] = []
    signal.signal(sig, lambda signum, frame: seen.append(signum))
    try:
        with held_back() as late:
            signal.raise_signal(sig)
            assert not seen  # held back: the step goes on
        assert late == [sig.name] and not seen  # taken off, never delivered
        signal.raise_signal(sig)
        assert seen == [sig]  # and the handler is as it was
    finally:
        signal.signal(sig, before)


def test_a_signal_given_to_another_thread_is_held_back_too() -> None:
    """A calibration has a second thread alive as it writes its file: the kernel gave a
    process-wide SIGINT to that thread, which the main thread's signal mask did not hold, and
    Python raised the interrupt in the main thread inside the step (the file written, the
    command saying "interrupted", exit 130; found by an outside audit)."""
    release = threading.Event()
    other = threading.Thread(target=release.wait, daemon=True)
    other.start()
    seen: list[int] = []
    before = signal.signal(signal.SIGINT, lambda signum, frame: seen.append(signum))
    try:
        with held_back() as late:
            assert other.ident is not None
            signal.pthread_kill(other.ident, signal.SIGINT)
            for _ in range(1000):  # the main thread runs Python code: the handler's chance
                if late or seen:
                    break
                time.sleep(0.001)
            assert not seen  # held back: the step goes on
        assert late == ["SIGINT"] and not seen
    finally:
        signal.signal(signal.SIGINT, before)
        release.set()
        other.join()


def test_every_catchable_signal_that_ends_a_process_is_a_stop() -> None:
    """Those a run meets for real (the kernel's SIGXCPU past ``RLIMIT_CPU`` or
    ``RLIMIT_RTTIME``) and the real-time ones, which ``signal.Signals`` cannot name; never a
    fault the process raises on itself, nor SIGXFSZ and SIGPIPE, which Python ignores (the
    write fails instead)."""
    for sig in (signal.SIGXCPU, signal.SIGVTALRM, signal.SIGPROF, signal.SIGIO):
        assert sig in StopSignals.SIGNALS
    assert signal.SIGXFSZ not in StopSignals.SIGNALS and signal.SIGPIPE not in StopSignals.SIGNALS
    assert set(range(signal.SIGRTMIN, signal.SIGRTMAX + 1)) <= set(StopSignals.SIGNALS)
    for fault in (signal.SIGSEGV, signal.SIGBUS, signal.SIGILL, signal.SIGFPE, signal.SIGABRT):
        assert fault not in StopSignals.SIGNALS
    assert signal_name(signal.SIGRTMIN + 3) == "SIGRTMIN+3"
    assert signal_name(signal.SIGXCPU) == "SIGXCPU"


def test_nothing_suspends_a_run_from_the_terminal() -> None:
    """SIGTTOU (a background run's status line on a terminal set ``stty tostop``, or a
    ``kill -TTOU``) and SIGTTIN suspended the run as Ctrl-Z did, its torque on: ignored over
    the run, and put back after."""
    before = {sig: signal.getsignal(sig) for sig in (signal.SIGTTOU, signal.SIGTTIN)}
    with StopSignals():
        for sig in before:
            assert signal.getsignal(sig) is signal.SIG_IGN
            signal.raise_signal(sig)  # ignored: this process goes on
    assert {sig: signal.getsignal(sig) for sig in before} == before


def test_an_interrupt_that_came_out_as_another_error_is_said_as_the_interrupt(
    capsys: pytest.CaptureFixture[str],
) -> None:
    """A Ctrl-C inside an extension module's import comes out as that import's failure
    (mujoco's pybind11 set-up: "ImportError: initialization failed", the interrupt its
    cause; numpy's: an ImportError without it): ``nodes`` and ``monitor`` said it as an
    internal error with a traceback, exit 1, one Ctrl-C in ten in their first second (an
    outside probe). The command raised an interrupt, so the error is it: exit 130."""
    import argparse

    from handctl import cli
    from handctl.stopsignals import interrupt, working

    def imports(args: argparse.Namespace) -> int:
        with contextlib.suppress(KeyboardInterrupt):  # the import's own handling
            interrupt(signal.SIGINT, None)
        raise ImportError("PyCapsule_Import could not import module")  # the cause lost

    def fails(args: argparse.Namespace) -> int:
        raise ImportError("initialization failed")

    working()
    assert cli._run(imports, argparse.Namespace()) == cli.EXIT_INTERRUPTED
    err = capsys.readouterr().err
    assert err.startswith("handctl: interrupted (SIGINT: ImportError: PyCapsule_Import"), err
    assert "internal error" not in err and "Traceback" not in err
    working()  # a command of its own: no interrupt raised in it, the error is a bug
    assert cli._run(fails, argparse.Namespace()) == cli.EXIT_FAILED
    assert "handctl: internal error: ImportError: initialization failed" in capsys.readouterr().err


@pytest.mark.parametrize(
    ("argv", "drives"),
    [
        (["run", "recipe", "r.yaml"], True),
        (["jog", "f1_j2", "--torque", "0.01"], True),
        (["calibrate", "tdt", "-o", "c.yaml"], True),
        (["replay", "log.mcap", "--to-bus", "unix:bus"], True),
        (["replay", "log.mcap", "--to-bus=unix:bus"], True),
        (["replay", "log.mcap", "--rerun"], False),
        (["plan", "t.yaml", "-o", "r.yaml"], False),
        (["--version"], False),
        ([], False),
    ],
)
def test_the_commands_that_drive_a_hand_take_ctrl_z_from_their_first_line(
    argv: list[str], drives: bool
) -> None:
    """A Ctrl-Z while such a command loaded suspended it, and once resumed it drove the hand
    (``replay --to-bus`` enabled the nodes and sent 3855 commands after ``fg``); any other
    command may be suspended."""
    assert drives_a_hand(argv) is drives
