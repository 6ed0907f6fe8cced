"""Fault scenario files: the shipped ones load, mistakes name their key, the schedule is ordered."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest

from handctl.config import HandConfig
from handctl.errors import ConfigError
from handctl.schema import parse_yaml
from handctl.sim.faults import (
    INJECTORS,
    Babble,
    DropFeedback,
    FaultSchedule,
    TdtStuck,
    load_scenario,
    parse_scenario,
)

SCENARIOS = Path(__file__).resolve().parents[2] / "config" / "sim"


def test_every_injector_is_in_the_fault_table_of_the_docs() -> None:
    """docs/faults.md lists what each injector does to a run: a new one needs its row."""
    table = (SCENARIOS.parents[1] / "docs" / "faults.md").read_text()
    assert {kind for kind in INJECTORS if f"| `{kind}` |" not in table} == set()


def test_shipped_scenarios_load_and_switch_within_their_runs(hand: HandConfig) -> None:
    """Every shipped scenario (none may be missing from the folder) loads for the default
    hand, and every entry starts at or after 0 s and stops after it starts."""
    shipped = sorted(SCENARIOS.glob("*.yaml"))
    assert {p.name for p in shipped} >= {"every_injector.yaml", "feedback_dropout.yaml"}
    for path in shipped:
        for entry in load_scenario(path, hand):
            assert entry.start >= 0.0, (path.name, entry)
            assert entry.stop is None or entry.stop > entry.start, (path.name, entry)


def test_reference_scenario_uses_every_injector(hand: HandConfig) -> None:
    schedule = load_scenario(SCENARIOS / "every_injector.yaml", hand)
    assert {entry.injector.kind for entry in schedule} == set(INJECTORS)


def test_entries_carry_their_parameters(hand: HandConfig) -> None:
    text = """
faults:
  - {kind: babble, id: 0x020, per_tick: 7, length: 12, start: 0.5, stop: 0.75}
  - {kind: tdt_stuck, node: 3, joint: 2, start: 1.0}
"""
    babble, stuck = parse_scenario(parse_yaml(text, "s.yaml"), hand)
    assert isinstance(babble.injector, Babble)
    assert (babble.injector.id, babble.injector.per_tick, babble.injector.length) == (0x20, 7, 12)
    assert (babble.start, babble.stop) == (0.5, 0.75)
    assert isinstance(stuck.injector, TdtStuck)
    assert (stuck.injector.node, stuck.injector.joint, stuck.stop) == (3, 2, None)


@pytest.mark.parametrize(
    ("entry", "key", "expected"),
    [
        ("{kind: tdt_melt, start: 1}", "faults[0].kind", "one of"),
        ("{kind: drop_feedback, amplitude: 1, start: 1}", "faults[0].amplitude", "unknown key"),
        ("{kind: drop_feedback, start: 1, stop: 0.5}", "faults[0].stop", ">= 1"),
        ("{kind: drop_feedback, start: -1}", "faults[0].start", ">= 0"),
        ("{kind: node_silent, node: 9, start: 1}", "faults[0].node", "a node id of the hand"),
        ("{kind: tdt_offset, node: 1, joint: 4, start: 1}", "faults[0].joint", "<= 3"),
        ("{kind: babble, length: 10, start: 1}", "faults[0].length", "CAN-FD payload length"),
        ("{kind: corrupt_crc, message: commands, start: 1}", "faults[0].message", "one of"),
        ("{kind: drop_commands, start: 1, joint: 1}", "faults[0].joint", "unknown key"),
    ],
)
def test_mistakes_name_the_key(hand: HandConfig, entry: str, key: str, expected: str) -> None:
    with pytest.raises(ConfigError) as err:
        parse_scenario(parse_yaml(f"faults:\n  - {entry}\n", "bad.yaml"), hand)
    assert err.value.file == "bad.yaml"
    assert err.value.key == key
    assert expected in err.value.expected


def test_a_node_the_hand_has_not_is_named_against_the_hand_s_ids_whatever_it_is(
    hand: HandConfig,
) -> None:
    """Outside the range of the hand's node ids or inside it, an id the hand has not gets one
    message, the ids it has: bounds said "an integer >= 2 and <= 13" of a hand whose nodes
    are 2, 4, 6 and 13, as if 3 were one."""
    apart = dataclasses.replace(
        hand,
        fingers=tuple(
            dataclasses.replace(f, node_id=n) for f, n in zip(hand.fingers, (2, 6, 13), strict=True)
        ),
    )
    for node in (1, 3, 14):
        with pytest.raises(ConfigError) as err:
            parse_scenario(
                parse_yaml(f"faults:\n  - {{kind: node_silent, node: {node}, start: 1}}\n", "f"),
                apart,
            )
        assert (err.value.expected, err.value.found) == ("a node id of the hand (2, 6, 13)", node)


def test_schedule_hands_out_switchings_in_time_order() -> None:
    a, b, c = DropFeedback(node=1), DropFeedback(node=2), DropFeedback(node=3)
    schedule = FaultSchedule()
    schedule.add(a, start=0.010, stop=0.020)
    schedule.add(b, start=0.020)  # a's stop in the same tick comes first
    schedule.add(c, start=0.0004)  # rounds to tick 0
    assert list(schedule.due(0)) == [(True, c)]
    assert list(schedule.due(9)) == []
    assert list(schedule.due(10)) == [(True, a)]
    assert list(schedule.due(25)) == [(False, a), (True, b)]
    assert not schedule.pending
    with pytest.raises(ValueError, match="start <= stop"):
        schedule.add(a, start=0.5, stop=0.4)


@pytest.mark.parametrize(("start", "stop"), [(0.010, 0.010), (0.0102, 0.0107)])
def test_a_window_within_one_tick_lasts_that_tick(start: float, stop: float) -> None:
    """Its off sorted before its on in the same tick, and the fault stayed on for good: a
    node made silent from 1.0 to 1.0 s never spoke again."""
    silent = DropFeedback(node=2)
    schedule = FaultSchedule()
    schedule.add(silent, start=start, stop=stop)
    assert list(schedule.due(10)) == [(True, silent)]
    assert list(schedule.due(11)) == [(False, silent)]
    assert not schedule.pending


def test_two_windows_of_one_injector_on_one_target_may_not_overlap(hand: HandConfig) -> None:
    """The injector's state is the node's: the short window's end ended the long one, and a
    saturation from 1.5 to 3 s beside one from 1.5 to 1.52 s lasted 20 ms."""
    text = """
faults:
  - {kind: motor_saturation, node: 1, joint: 1, limit: 0.01, start: 1.5, stop: 3.0}
  - {kind: motor_saturation, node: 1, joint: 1, limit: 0.02, start: 1.5, stop: 1.52}
"""
    with pytest.raises(ConfigError) as err:
        parse_scenario(parse_yaml(text, "s.yaml"), hand)
    assert err.value.key == "faults[1]"
    assert "a window that does not overlap faults[0]'s (1.5..3 s)" in err.value.expected
    # one after the other, or on another joint, they may
    after = text.replace("start: 1.5, stop: 1.52", "start: 3.0, stop: 3.5")
    parse_scenario(parse_yaml(after, "s.yaml"), hand)
    elsewhere = text.replace("joint: 1, limit: 0.02", "joint: 2, limit: 0.02")
    parse_scenario(parse_yaml(elsewhere, "s.yaml"), hand)


@pytest.mark.parametrize(
    ("first", "second"),
    [
        (
            "{kind: tdt_stuck, start: 0.25, stop: 0.30}",
            "{kind: tdt_stuck, node: 1, joint: 2, start: 0.28, stop: 1.2}",
        ),
        (
            "{kind: tdt_stuck, node: 1, start: 0.25, stop: 0.30}",
            "{kind: tdt_stuck, node: 1, joint: 2, start: 0.28, stop: 1.2}",
        ),
        ("{kind: node_silent, start: 0.2, stop: 0.3}", "{kind: node_silent, node: 1, start: 0.25}"),
    ],
)
def test_a_window_on_every_target_overlaps_one_on_any_of_them(
    hand: HandConfig, first: str, second: str
) -> None:
    """A window on every node (or joint) ends each one's state at its end: a stuck TDT on
    f1_j2 from 0.28 to 1.2 s inside one on every joint to 0.30 s ended at 0.30 s, and the run
    that should have stopped on TDT_STUCK exited 0 (an outside audit)."""
    text = f"faults:\n  - {first}\n  - {second}\n"
    with pytest.raises(ConfigError) as err:
        parse_scenario(parse_yaml(text, "s.yaml"), hand)
    assert err.value.key == "faults[1]"
    assert "a window that does not overlap faults[0]'s" in err.value.expected
    # on another node, the one on a single node does not meet it
    if "node: 1, start: 0.25" in first:
        parse_scenario(
            parse_yaml(text.replace("node: 1, joint: 2", "node: 2, joint: 2"), "s.yaml"), hand
        )


@pytest.mark.parametrize(
    ("first", "second"),
    [
        # both come on at tick 100, and the first one's end at tick 101 ended the second
        (
            "{kind: counter_repeat, node: 1, message: heartbeat, start: 0.1, stop: 0.1}",
            "{kind: counter_repeat, node: 1, message: heartbeat, start: 0.1005, stop: 0.9}",
        ),
        # both set the node's counter step: the skip's end ended the repeat after 50 ms
        (
            "{kind: counter_repeat, node: 1, message: heartbeat, start: 0.1, stop: 0.9}",
            "{kind: counter_skip, node: 1, message: heartbeat, start: 0.15, stop: 0.16}",
        ),
    ],
)
def test_windows_that_share_a_tick_or_a_state_may_not_overlap(
    hand: HandConfig, first: str, second: str
) -> None:
    """Two windows that did not overlap in seconds but did on the ticks they switch on, and
    two injectors of one state, passed the check, and the scenario injected less than it
    said: the runs exited 0 where the second window alone stopped on HEARTBEAT_LOST (an
    outside audit)."""
    text = f"faults:\n  - {first}\n  - {second}\n"
    with pytest.raises(ConfigError) as err:
        parse_scenario(parse_yaml(text, "s.yaml"), hand)
    assert err.value.key == "faults[1]"
    assert "a window that does not overlap faults[0]'s" in err.value.expected
    apart = text.replace("start: 0.1005, stop: 0.9", "start: 0.102, stop: 0.9").replace(
        "start: 0.15, stop: 0.16", "start: 0.95, stop: 0.96"
    )
    parse_scenario(parse_yaml(apart, "s.yaml"), hand)


@pytest.mark.parametrize("kind", ["bus_off", "error_frames", "babble"])
def test_a_fault_of_the_whole_bus_takes_no_node(hand: HandConfig, kind: str) -> None:
    """``node: 2`` on a bus-off was taken and did nothing: every node fell silent."""
    text = f"faults:\n  - {{kind: {kind}, node: 2, start: 0.3, stop: 0.31}}\n"
    with pytest.raises(ConfigError) as err:
        parse_scenario(parse_yaml(text, "s.yaml"), hand)
    assert err.value.key == "faults[0].node"
    assert f"no node: {kind} is of the whole bus" in err.value.expected
    parse_scenario(parse_yaml(text.replace("node: 2, ", ""), "s.yaml"), hand)
