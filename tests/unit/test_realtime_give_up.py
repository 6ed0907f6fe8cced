"""When a real-time test gives up on a loaded machine: only a stop its own probes put on the
host is skipped (``tests/integration/realtime.py``); a stop with a tick handctl missed fails."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import pytest
import yaml

from handctl.config import MAX_FEEDBACK_TIMEOUT_S, HandConfig, load_hand
from handctl.hostcheck import ProbeRecord
from handctl.protocol import most_misses_before_watchdog

from ..conftest import HAND_YAML
from ..integration.realtime import (
    give_up,
    hand_cpu_text,
    host_stopped,
    load_stopped,
    stop_faults,
    stopped_by_load,
    tolerant_hand,
)

DATA = Path(__file__).resolve().parent.parent / "data"

_OVERRUN = (
    "warning: the run stopped on LOOP_OVERRUN; the bare timer loop beside it says the host "
    "was MARGINAL; slow CPU (longest host stall 2.1 ms; missed ticks: {counts}); see "
    "'handctl check --timing' and docs/timing.md"
)


@pytest.mark.parametrize(
    ("counts", "host"),
    [
        ("3 the host's, 4 its slow CPU's, 0 handctl's", True),
        ("0 the host's, 0 handctl's, 2 a real-time rival's: spin (1234)", True),
        ("3 the host's, 4 its slow CPU's, 1 handctl's", False),
        ("1 the host's, 2 its slow CPU's, 4 its catch-up ticks', 0 handctl's", True),
        ("1 the host's, 4 its catch-up ticks', 1 handctl's", False),
        ("0 the host's, 0 handctl's", False),  # nothing the probes saw explains the stop
    ],
)
def test_an_overrun_is_the_host_s_when_its_probes_explain_every_missed_tick(
    counts: str, host: bool
) -> None:
    assert host_stopped(_OVERRUN.format(counts=counts)) is host


def test_a_feedback_timeout_is_the_host_s_when_the_hand_s_cpu_failed() -> None:
    text = (
        "the run stopped on FEEDBACK_TIMEOUT; the bare timer loop beside it says the host was "
        "PASS (longest host stall 0.1 ms; missed ticks: 0 the host's, 0 handctl's); on the "
        "simulated hand's CPU [1] the host was FAIL (longest stall 31 ms, 1 longer than the "
        "feedback timeout)"
    )
    assert host_stopped(text)
    assert not host_stopped(text.replace("CPU [1] the host was FAIL", "CPU [1] the host was PASS"))


def test_a_flood_from_a_hand_catching_up_is_the_host_s_when_the_hand_s_cpu_failed(
    hand: HandConfig,
) -> None:
    # A test's own bare loop beside a simulated hand it started (``handctl sim`` runs none),
    # said as a run says it of its own hand's CPU; here the record of a failing host.
    failing = json.loads((DATA / "host_stalls_failing.json").read_text())
    on_the_hand = hand_cpu_text(ProbeRecord.from_json(failing, "failing"), hand)
    stop = "handctl: safety stop: RX_BACKLOG at tick 40: 54 frames drained, more waiting"
    assert host_stopped(f"{stop}; {on_the_hand}")
    assert not host_stopped(f"{stop}; {on_the_hand.replace('was FAIL', 'was PASS')}")
    assert not host_stopped(stop)


def test_giving_up_skips_only_when_every_stop_was_the_host_s() -> None:
    host = _OVERRUN.format(counts="3 the host's, 0 handctl's")
    own = _OVERRUN.format(counts="3 the host's, 2 handctl's")
    with pytest.raises(pytest.skip.Exception):
        give_up("run", [host, host])
    with pytest.raises(AssertionError):
        give_up("run", [host, own])
    with pytest.raises(AssertionError):
        give_up("run", [])


def test_a_node_watchdog_timing_out_on_the_same_stall_is_still_the_loads_stop() -> None:
    """The loop held for 9 ms stops on LOOP_OVERRUN, and a node whose commands stopped for as
    long times out a tick later: the load's stop, tried again. A node's fault of its own (a
    sensor), or a node timing out first, is not the load's."""
    overrun = {"code": "LOOP_OVERRUN", "tick": 641, "detail": "9 consecutive ticks missed"}
    timeout = {"code": "NODE_FAULT", "tick": 642, "detail": "node 1 (f1) in FAULT (TIMEOUT)"}
    sensor = {"code": "NODE_FAULT", "tick": 642, "detail": "node 1 (f1) in FAULT (SENSOR)"}
    assert load_stopped([overrun])
    assert load_stopped([timeout, overrun])  # in the summary's order or not
    assert not load_stopped([overrun, sensor])
    assert not load_stopped([{**timeout, "tick": 600}, overrun])
    assert not load_stopped([])


#: A stop seen beside a full test suite: the loop held after its wake-up of tick 1922 read the
#: timer, the node's watchdog timing out before the loop drained the bus, the 13 ticks counted
#: at the next wake-up.
_HELD_BEFORE_THE_DRAIN = (
    "handctl: warning: the run stopped on LOOP_OVERRUN; the bare timer loop beside it says the "
    "host was MARGINAL (longest host stall 2.586 ms; missed ticks: 2 the host's, 6 with the "
    "loop held off its CPU, 7 handctl's)\n"
    "  handctl: safety stop: NODE_FAULT at tick 1922: node 1 (f1) in FAULT (TIMEOUT): it heard "
    "no command for its 10 ms watchdog (the host stalled, or its commands did not reach it); "
    "LOOP_OVERRUN at tick 1923: {missed} consecutive ticks missed\n"
)


def test_a_stop_s_faults_are_read_from_its_line() -> None:
    faults = stop_faults(_HELD_BEFORE_THE_DRAIN.format(missed=13))
    assert [(f["code"], f["tick"]) for f in faults] == [
        ("NODE_FAULT", 1922),
        ("LOOP_OVERRUN", 1923),
    ]
    assert str(faults[0]["detail"]).endswith("did not reach it)")
    assert faults[1]["detail"] == "13 consecutive ticks missed"
    assert stop_faults("handctl: error: no such file") == []


def test_a_node_timing_out_just_before_the_loop_counts_the_same_stall_is_the_loads() -> None:
    """Tried again only when the overrun comes in the next tick and spans the watchdog: a loop
    held 13 ms explains a node that heard nothing for 10 ms, one held 6 ms does not, nor an
    overrun later than the next tick, nor a node's fault other than its watchdog's."""
    held = _HELD_BEFORE_THE_DRAIN.format(missed=13)
    assert stopped_by_load(held)
    assert not stopped_by_load(_HELD_BEFORE_THE_DRAIN.format(missed=5))
    assert not stopped_by_load(held, period_s=0.5e-3)  # 13 ticks of 0.5 ms: 7 ms, not 10
    assert not stopped_by_load(held.replace("tick 1923", "tick 1924"))
    assert not stopped_by_load(held.replace("(TIMEOUT)", "(SENSOR)"))
    assert not stopped_by_load(held.replace("; LOOP_OVERRUN at tick 1923: 13 consecutive", " 13"))


@pytest.mark.parametrize("rate_hz", [1000.0, 500.0])
def test_a_hand_tolerant_of_load_is_one_the_config_check_takes(
    tmp_path: Path, rate_hz: float
) -> None:
    """The lenient watchdogs are the most the check allows, not past it: a hand the check
    refused would fail the real-time tests that use it for a reason of its own."""
    source = tmp_path / "source" / "hand.yaml"
    source.parent.mkdir()
    doc = yaml.safe_load(HAND_YAML.read_text())
    doc["bus"]["loop_rate_hz"] = rate_hz
    source.write_text(yaml.safe_dump(doc))
    default = load_hand(source).safety
    tolerant = load_hand(tolerant_hand(source, tmp_path)).safety
    assert tolerant.max_consecutive_misses == most_misses_before_watchdog(rate_hz)
    assert tolerant.max_consecutive_misses >= default.max_consecutive_misses
    assert tolerant.feedback_timeout_s == MAX_FEEDBACK_TIMEOUT_S > default.feedback_timeout_s
    # nothing else of the hand changed
    assert replace(tolerant, max_consecutive_misses=0, feedback_timeout_s=0) == replace(
        default, max_consecutive_misses=0, feedback_timeout_s=0
    )
