"""SIGINT, SIGTERM and SIGHUP over a run (``session.StopSignals``), raised in this very process."""

from __future__ import annotations

import asyncio
import signal

import pytest

from handctl.config import HandConfig
from handctl.online.bus import HandBus
from handctl.online.drivers.hand import HandDriver
from handctl.online.loop import Outcome, RunResult, Runtime
from handctl.online.recipes.loader import load_recipe
from handctl.protocol import Protocol
from handctl.session import StopSignals

from ..conftest import ROOT


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM, signal.SIGHUP])
def test_before_the_run_a_signal_is_an_interrupt(sig: signal.Signals) -> None:
    before = signal.getsignal(sig)
    with StopSignals(), pytest.raises(KeyboardInterrupt):
        signal.raise_signal(sig)
    assert signal.getsignal(sig) is before  # put back afterwards


def test_a_run_started_under_nohup_keeps_ignoring_sighup() -> None:
    """``nohup handctl run ...`` asks the run to outlive its terminal: the hang-up it then
    gets is not a stop."""
    before = signal.signal(signal.SIGHUP, signal.SIG_IGN)
    try:
        with StopSignals():
            assert signal.getsignal(signal.SIGHUP) is signal.SIG_IGN
            signal.raise_signal(signal.SIGHUP)  # ignored: no KeyboardInterrupt
        assert signal.getsignal(signal.SIGHUP) is signal.SIG_IGN
    finally:
        signal.signal(signal.SIGHUP, before)


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_a_signal_during_start_up_is_an_interrupt_with_nothing_sent(
    hand: HandConfig, protocol: Protocol, bus_pair: tuple[HandBus, HandBus], sig: signal.Signals
) -> None:
    """The nodes have not answered yet (nobody is on the bus): the start-up is still waiting
    for them when the signal comes. That is an interrupt (exit 130), not a failed start-up
    (exit 3): nothing went wrong with the hand, and nothing was sent to it."""
    from handctl.online.clock import LockstepClock

    host, listener = bus_pair
    recipe = load_recipe(ROOT / "config" / "recipes" / "swap_two_cylinders.yaml", hand)
    runtime = Runtime(
        hand,
        HandDriver(hand, protocol, host),
        LockstepClock(hand.bus.period_s, lambda: None),
        recipe,
        startup_timeout_s=600.0,
    )

    async def run(signals: StopSignals) -> RunResult:
        asyncio.get_running_loop().call_later(0.05, signal.raise_signal, sig)
        return await signals.run(runtime)

    with StopSignals() as signals:
        result = asyncio.run(run(signals))
    assert result.outcome is Outcome.INTERRUPTED, result.message
    assert result.faults == []
    assert sig.name in result.message and "start-up" in result.message
    assert listener.drain() == []


def test_an_interrupt_that_c_code_turned_into_its_own_error_is_still_an_interrupt() -> None:
    """Ctrl-C while MuJoCo is being imported comes out as ``ImportError: initialization
    failed`` (exit 1 and a traceback); it is an interrupt (exit 130)."""
    with pytest.raises(KeyboardInterrupt), StopSignals():
        try:
            signal.raise_signal(signal.SIGINT)
        except KeyboardInterrupt as exc:
            raise ImportError("initialization failed") from exc


def test_other_errors_pass_through() -> None:
    with pytest.raises(ImportError), StopSignals():
        raise ImportError("a real one")
