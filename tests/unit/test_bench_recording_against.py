"""``bench.py recording --against REV`` runs REV's recorder and bus beside this tree's runtime,
the two runtimes of a pair waiting for each other every tick. A revision whose bus lacked
what this tree's driver calls stopped its runtime at the first tick, and the other spun in
its wait for ever, saying nothing. The bench now tries REV out in a short pair and refuses
one that cannot run, saying why; and a runtime of any pair that ends or stalls while the
other waits for it breaks the pair off with a message instead of a hang."""

from __future__ import annotations

import argparse
import time
from typing import Any

import pytest

from handctl.config import HandConfig
from handctl.online.bus import HandBus, open_bus
from handctl.online.recipes.loader import load_recipe
from handctl.online.recipes.schema import Recipe
from handctl.recording.recorder import Recorder

from ..conftest import DEFAULT_RECIPE, ROOT, load_tool


@pytest.fixture(scope="module")
def bench() -> Any:
    return load_tool("bench_recording")


@pytest.fixture
def recipe(hand: HandConfig) -> Recipe:
    return load_recipe(ROOT / DEFAULT_RECIPE, hand)


def test_a_wait_for_a_runtime_that_ended_breaks_the_pair(bench: Any) -> None:
    turns = bench.Turns()
    turns.ended["b"] = "the other runtime ended at tick 7: safety_stop"
    with pytest.raises(bench.BrokenPairError, match=r"ended at tick 7.*waited for it at tick 8"):
        turns.wait_in_vain("a", 8, time.monotonic())
    with pytest.raises(bench.BrokenPairError, match="ended at tick 7"):
        turns.check()


def test_a_wait_past_its_bound_breaks_the_pair(bench: Any) -> None:
    turns = bench.Turns()
    turns.wait_in_vain("a", 3, time.monotonic())  # the other may still come
    turns.check()
    since = time.monotonic() - bench.PARTNER_WAIT_S - 1.0
    with pytest.raises(bench.BrokenPairError, match="did not begin tick 3"):
        turns.wait_in_vain("a", 3, since)


def _bus_without_prepare_send(channel: str, config: Any) -> HandBus:
    """This tree's bus, but as a revision before ``prepare_send`` had it."""
    bus = open_bus(channel, config)

    def missing() -> None:
        raise AttributeError("'HandBus' object has no attribute 'prepare_send'")

    bus.prepare_send = missing  # type: ignore[method-assign]
    return bus


def test_a_reference_whose_bus_this_driver_cannot_use_is_refused(
    bench: Any, hand: HandConfig, recipe: Recipe
) -> None:
    problem = bench.against_problem(hand, recipe, Recorder, _bus_without_prepare_send, "old")
    assert "the runtime with old's recorder ended at tick" in problem
    assert "no attribute 'prepare_send'" in problem
    assert "while the other waited for it" in problem


def test_this_trees_own_recorder_and_bus_pass_the_trial(
    bench: Any, hand: HandConfig, recipe: Recipe
) -> None:
    assert bench.against_problem(hand, recipe, Recorder, open_bus, "this tree") == ""


def _args(bench: Any, argv: list[str]) -> argparse.Namespace:
    parser = argparse.ArgumentParser()
    bench.add_arguments(parser)
    return parser.parse_args(argv)


def test_the_bench_refuses_before_measuring(bench: Any, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(bench, "recorder_of", lambda rev: Recorder)
    monkeypatch.setattr(bench, "bus_opener_of", lambda rev: _bus_without_prepare_send)

    def measured(*_: object, **__: object) -> None:
        raise AssertionError("a pair measured after the trial failed")

    monkeypatch.setattr(bench, "against_once", measured)
    args = _args(bench, ["--against", "old", "--repeat", "1"])
    with pytest.raises(SystemExit) as refused:
        bench.run(args)
    message = str(refused.value.code)
    assert message.startswith("bench.py recording --against old: its recorder and bus cannot")
    assert "prepare_send" in message and "docs/recording.md says which" in message
