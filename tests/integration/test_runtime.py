"""The runtime against the simulated hand, in lockstep: the default recipe completes, every
safety check is tripped by a real fault on the bus, the wire carries zero (or the ramp) within
two ticks, faults latch, and only an explicit reset brings torque back, from zero."""

from __future__ import annotations

import json
import math
import re
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from handctl.config import HandConfig
from handctl.online.loop import Outcome
from handctl.online.recipes.loader import load_recipe
from handctl.online.recipes.schema import Recipe
from handctl.online.safety.faults import FAULTS, RAMP_BOUND_S, FaultCode, StopCategory
from handctl.online.safety.supervisor import State
from handctl.protocol import NodeState
from handctl.recording.reader import iter_decoded, open_recording
from handctl.sim import faults as inj

from ..conftest import ROOT, handctl
from .rig import CLOSE_AND_HOLD_2S, rig

INJECT_AT = 1.0  # s of simulated time: well inside the hold phase


@pytest.fixture(scope="module")
def hold(hand: HandConfig, tmp_path_factory: pytest.TempPathFactory) -> Recipe:
    path = tmp_path_factory.mktemp("recipes") / "hold.yaml"
    path.write_text(CLOSE_AND_HOLD_2S)
    return load_recipe(path, hand)


def test_default_recipe_completes(hand: HandConfig) -> None:
    recipe = load_recipe(ROOT / "config" / "recipes" / "swap_two_cylinders.yaml", hand)
    with rig(hand, recipe) as r:
        result = r.run()
        assert result.outcome is Outcome.COMPLETED, result.message
        assert [p["name"] for p in result.phases] == [p.name for p in recipe.phases]
        assert not result.faults
        assert r.runtime.supervisor.state is State.IDLE
        wire = r.commands()
        assert np.all(np.abs(wire[-3:]) == 0)  # ends at zero
        tau_max = np.array([j.tau_max for j in hand.joints])
        assert np.all(np.abs(wire) <= tau_max + 1e-4)
        assert all(n.state == NodeState.DISABLED for n in r.sim.nodes)  # at the end


@pytest.mark.parametrize("stop_after_s", [0.2, 0.2008, 0.2016, 0.2024, 0.2032])
def test_the_nodes_are_heard_disabled_at_the_end_above_1_khz(
    hand: HandConfig, hold: Recipe, stop_after_s: float
) -> None:
    """The run listened one period after its disable: at 1250 Hz, where some periods hold
    none of the nodes' 1 ms ticks, the run ended (and said it completed) with the simulated
    hand ENABLED, as a stop after 0.2016 s did. It now listens until every node says so."""
    fast = replace(hand, bus=replace(hand.bus, loop_rate_hz=1250.0))
    with rig(fast, load_recipe(hold.source, fast), max_seconds=stop_after_s) as r:
        result = r.run()
        assert result.outcome is Outcome.INTERRUPTED, result.message
        assert all(n.state == NodeState.DISABLED for n in r.sim.nodes)
        assert all(n.state == NodeState.DISABLED for n in r.runtime.driver.nodes)
        assert result.disable_unconfirmed == ""


def test_a_node_not_heard_disabled_at_the_end_is_said(
    hand: HandConfig, hold: Recipe, tmp_path: Path
) -> None:
    """A node gone silent (its FEEDBACK_TIMEOUT the run's stop) is not heard disabled after
    the disable: the run listens 10 ms for it and says so, and the node's own command
    watchdog is what disables it. The summary and the log say it too (stderr alone did): a
    script, or whoever reads the log later, needs to know the hand may still be ENABLED."""
    faults = tmp_path / "silent.yaml"
    faults.write_text("faults:\n  - {kind: node_silent, node: 2, start: 0.5, stop: 5.0}\n")
    log, summary = tmp_path / "run.mcap", tmp_path / "s.json"
    done = handctl(
        "run", "recipe", str(hold.source), "--sim-faults", str(faults), "--max-seconds", "2",
        "--log", str(log), "--summary-json", str(summary),
    )  # fmt: skip
    assert done.returncode == 3, done.stderr
    assert "FEEDBACK_TIMEOUT" in done.stderr
    said = "node 2 (f2) not heard disabled within 10 ms of the disable"
    assert f"warning: {said}" in done.stderr
    assert "node 1 (f1) not heard" not in done.stderr  # the others said so in time
    # what the node's watchdog does: latch a fault the next run must clear (it said the
    # watchdog "disables" the node, which is not what PROTOCOL.md says)
    assert "latches FAULT (TIMEOUT), which the next run clears with --reset-node-faults" in (
        done.stderr
    )
    assert json.loads(summary.read_text())["disable_unconfirmed"].startswith(said)
    events = [m for _, _, m in iter_decoded(open_recording(log), ("/events",))]
    assert [e["name"] for e in events if said in e.get("detail", "")] == ["disable_unconfirmed"]
    rerun = handctl("replay", str(log), "--rerun")
    assert rerun.returncode == 0, rerun.stdout + rerun.stderr


def test_lockstep_runs_are_deterministic(hand: HandConfig, hold: Recipe) -> None:
    wires = []
    for _ in range(2):
        with rig(hand, hold, seed=3) as r:
            r.run()
            wires.append(r.wire)
    assert wires[0] == wires[1]


#: Injection times other than INJECT_AT: a stuck sensor only shows while the command moves, so
#: it is injected during the first ramp.
INJECT_TIMES = {"tdt_stuck": 0.15}

SCENARIOS = [
    ("node_silent", lambda: inj.NodeSilent(node=2), FaultCode.FEEDBACK_TIMEOUT),
    ("drop_feedback", lambda: inj.DropFeedback(node=1), FaultCode.FEEDBACK_TIMEOUT),
    (
        "corrupt_heartbeat",
        lambda: inj.CorruptCrc(node=3, message="heartbeat"),
        FaultCode.HEARTBEAT_LOST,
    ),
    # a counter that does not advance while the readings move: one counter with two
    # contents, which the host cannot tell from a second sender, at the first repeat
    (
        "counter_repeat",
        lambda: inj.CounterRepeat(node=1, message="feedback"),
        FaultCode.NODE_CONTRADICTION,
    ),
    ("tdt_stuck", lambda: inj.TdtStuck(node=1, joint=1), FaultCode.TDT_STUCK),
    ("tdt_offset", lambda: inj.TdtOffset(node=3, joint=2, offset=0.3), FaultCode.TDT_MISMATCH),
    ("tendon_slack", lambda: inj.TendonSlack(node=2, joint=1), FaultCode.TDT_MISMATCH),
    (
        "motor_saturation",
        lambda: inj.MotorSaturation(node=1, joint=1, limit=0.01),
        FaultCode.TDT_MISMATCH,
    ),
    ("node_reboot", lambda: inj.NodeReboot(node=2, downtime=0.02), FaultCode.FEEDBACK_TIMEOUT),
    ("drop_commands", lambda: inj.DropCommands(node=3, count=15), FaultCode.NODE_FAULT),
    ("encoder_jump", lambda: inj.EncoderJump(node=1, joint=2, counts=4000), FaultCode.NODE_FAULT),
    ("bus_off", inj.BusOff, FaultCode.BUS_ERROR),
    ("babble_estop", lambda: inj.Babble(id=0x000, per_tick=1, length=3), FaultCode.ESTOP),
]


@pytest.mark.parametrize(("name", "make", "code"), SCENARIOS, ids=[s[0] for s in SCENARIOS])
def test_fault_is_detected_stopped_and_latched(
    hand: HandConfig, hold: Recipe, name: str, make: object, code: FaultCode
) -> None:
    with rig(hand, hold) as r:
        at = INJECT_TIMES.get(name, INJECT_AT)
        r.sim.faults.add(make(), at)  # type: ignore[operator]
        result = r.run()
        assert result.outcome is Outcome.SAFETY_STOP
        first = result.faults[0]
        assert first.code is code, [str(f) for f in result.faults]
        inject_tick = round(at / hand.bus.period_s)
        assert first.tick >= inject_tick - 1, "detected before it happened"
        assert first.tick - inject_tick < 600, "detected far too late"
        sup = r.runtime.supervisor
        assert sup.state is State.FAULTED and sup.faults  # latched
        wire = r.commands()
        row = first.tick - r.runtime.first_send_tick
        assert np.abs(wire[row - 1]).max() > 0.01  # torque was flowing before
        if FAULTS[first.code].category is StopCategory.IMMEDIATE:
            assert not np.any(wire[row : row + 3][-1]), "not zero within 2 ticks"
            assert not np.any(wire[row + 2 :])
        else:
            ramp = np.abs(wire[row:]).max(axis=1)
            assert np.all(np.diff(ramp) <= 1e-4), "the ramp must only go down"
            ticks_to_zero = int(np.argmax(ramp == 0))
            assert ramp[ticks_to_zero] == 0
            assert ticks_to_zero <= RAMP_BOUND_S / hand.bus.period_s + 2
            # and no slower than the rate limit: the line to zero at the bound alone kept a
            # joint's torque on 35 ticks longer than a stop would have (an outside audit)
            step = np.array([j.rate_limit for j in hand.joints]) * hand.bus.period_s
            assert ticks_to_zero <= math.ceil(float(np.max(np.abs(wire[row - 1]) / step))) + 1
        # The nodes end disabled or in their own FAULT: never enabled with torque.
        assert all(n.state != NodeState.ENABLED or not any(n.applied) for n in r.sim.nodes)


def test_operator_estop_then_explicit_reset_ramps_from_zero(hand: HandConfig, hold: Recipe) -> None:
    with rig(hand, hold) as r:
        r.runtime.tick_hooks.append(
            lambda tk: r.runtime.request_estop("test") if tk.tick == 900 else None
        )
        result = r.run()
        assert result.outcome is Outcome.SAFETY_STOP
        assert result.faults[0].code is FaultCode.ESTOP
        assert r.estops() == 1
        assert all(n.state == NodeState.FAULT for n in r.sim.nodes)  # they latched ESTOP too
        # Nothing resumes by itself: the runtime is done until somebody resets.
        assert r.runtime.supervisor.state is State.FAULTED
        sent_before = len(r.commands())
        assert r.runtime.reset()
        second = r.run()
        assert second.outcome is Outcome.COMPLETED, second.message
        wire = r.commands()[sent_before:]
        steps = np.array([j.rate_limit for j in hand.joints]) * hand.bus.period_s
        assert np.all(np.abs(wire[0]) <= steps + 1e-4)  # from zero, through the rate limit
        assert [p["name"] for p in second.phases] == ["close", "hold"]  # from the beginning


def test_consecutive_late_ticks_are_a_fault(hand: HandConfig, hold: Recipe) -> None:
    """The lockstep clock never runs late, so a clock that reports misses is put in its place:
    a real clock object, late on purpose."""
    with rig(hand, hold) as r:
        clock = r.runtime.clock
        original = clock.wait_tick

        async def late_tick() -> object:
            tk = await original()
            if 800 <= tk.tick < 803:
                return tk._replace(missed=1)
            return tk

        clock.wait_tick = late_tick  # type: ignore[method-assign,assignment]
        result = r.run()
        assert result.faults[0].code is FaultCode.LOOP_OVERRUN
        assert result.faults[0].tick == 802
        assert result.missed_ticks == 3


def test_angle_limit_is_a_ramp_stop(hand: HandConfig, tmp_path: Path) -> None:
    from dataclasses import replace

    fingers = list(hand.fingers)
    joints = list(fingers[0].joints)
    joints[0] = replace(joints[0], angle_max=-0.5)  # the finger flexes past this while closing
    fingers[0] = replace(fingers[0], joints=tuple(joints))
    tight = replace(hand, fingers=tuple(fingers))
    path = tmp_path / "hold.yaml"
    path.write_text(CLOSE_AND_HOLD_2S)
    with rig(tight, load_recipe(path, tight)) as r:
        result = r.run()
    assert result.faults[0].code is FaultCode.ANGLE_LIMIT
    assert "f1_j1" in result.faults[0].detail


def test_startup_refuses_nodes_in_fault_without_explicit_reset(
    hand: HandConfig, hold: Recipe
) -> None:
    with rig(hand, hold) as r:
        # The nodes latched an e-stop before the host started (say, in an earlier session).
        r.sim.faults.add(inj.Babble(id=0x000, per_tick=1, length=3), 0.0, 0.01)
        for _ in range(50):
            r.sim.step()
        result = r.run()
        assert result.outcome is Outcome.STARTUP_FAILED
        assert "--reset-node-faults" in result.message
        assert r.commands().size == 0  # not one torque frame
    with rig(hand, hold) as r:
        r.sim.faults.add(inj.Babble(id=0x000, per_tick=1, length=3), 0.0, 0.01)
        for _ in range(50):
            r.sim.step()
        r.runtime.reset_node_faults = True
        result = r.run()
        assert result.outcome is Outcome.COMPLETED, result.message
        # what was cleared is said (before, only the NodeCommand frames in the log showed it)
        assert result.nodes_reset.startswith("cleared at start-up (--reset-node-faults): node 1")
        assert "in FAULT (ESTOP" in result.nodes_reset


def test_a_dead_host_is_stopped_by_the_node_watchdogs(hand: HandConfig, hold: Recipe) -> None:
    """The runtime freezes without any clean-up while the hand goes on: the nodes' 10 ms
    command watchdogs must zero the torque on their own.

    In lockstep, so that it asserts the watchdogs and not the machine's load: once the
    runtime has torque flowing, one of its ticks steps the simulated hand 30 of its own 1 ms
    ticks with no frame from the host in between, as a frozen host would leave it. The same
    death in real time, a host process killed with SIGKILL beside its simulated hand's own
    process, is ``test_cli_run.py``'s."""
    seen: dict[str, list[Any]] = {}
    with rig(hand, hold) as r:

        def freeze(tick: object) -> None:
            flowing = any(any(n.applied) for n in r.sim.nodes)
            if r.runtime.supervisor.state is not State.RUNNING or "torque" in seen or not flowing:
                return
            seen["torque"] = [list(n.applied) for n in r.sim.nodes]
            for _ in range(30):
                r.sim.step()
            seen["states"] = [n.state for n in r.sim.nodes]
            seen["faults"] = [n.fault_bits for n in r.sim.nodes]
            seen["applied"] = [list(n.applied) for n in r.sim.nodes]
            r.runtime.request_stop("test over")

        r.runtime.tick_hooks.append(freeze)
        r.run()
    assert "states" in seen, "the runtime never got torque flowing"
    assert any(any(t) for t in seen["torque"])
    assert seen["states"] == [NodeState.FAULT] * 3
    assert all(bits & 0x01 for bits in seen["faults"])
    assert seen["applied"] == [[0.0, 0.0, 0.0]] * 3


def test_start_up_says_feedback_was_heard_and_rejected_not_that_none_came(
    hand: HandConfig, hold: Recipe
) -> None:
    """Every feedback frame of node 1 with a bad CRC: a thousand frames a second heard, and
    start-up said "no feedback", as for a node with no power. The start-up judges the
    frames at the reject rate as a run does, so it now says so within the reject window,
    not at the end of its timeout."""
    with rig(hand, hold) as r:
        r.sim.activate(inj.CorruptCrc(node=1, message="feedback"))
        result = r.run()
    assert result.outcome is Outcome.STARTUP_FAILED
    assert [f.code for f in result.faults] == [FaultCode.REJECT_RATE]
    assert result.message.startswith("node 1 (f1): ")
    assert re.search(r"\d+ frames rejected within \d+ ticks \(.*crc \d+\)", result.message)
    assert "no feedback" not in result.message
    assert "node 2" not in result.message and "node 3" not in result.message


def test_a_silent_node_is_said_once_the_others_have_had_their_time_to_answer(
    hand: HandConfig, hold: Recipe
) -> None:
    """A simulated hand in its own process has the whole start-up (20 s) to import and build
    itself, and a node of it that never spoke was said only when all of it had passed. Once
    any node is heard, the others now have ``answer_ticks`` to answer."""
    for answer in (40, None):
        with rig(hand, hold) as r:
            r.sim.activate(inj.NodeSilent(node=1))
            r.runtime.startup_ticks = 300
            r.runtime.answer_ticks = 300 if answer is None else answer
            result = r.run()
            ticks = r.runtime.tick
        assert result.outcome is Outcome.STARTUP_FAILED
        assert [f.code for f in result.faults] == [FaultCode.STARTUP]
        if answer is None:
            assert "nodes not ready within 300 ticks: node 1 (f1): no feedback" in result.message
            assert ticks >= 299
        else:
            assert (
                "nodes not ready within 40 ticks of the first node heard: node 1 (f1): no feedback"
            ) in result.message
            assert ticks <= 45
