"""An exception in any stage of a tick is a controlled stop (docs/safety.md, guarantee 17).

Each case runs a hold recipe in lockstep on the simulated hand, recorded by the real recorder,
and forces an exception in one stage of the tick while torque flows, once or on every call
from then on. A second python-can listener on the same virtual channel hears what went on the
wire, decoded with cantools from the DBC (not with handctl's codec): from the tick after the
faulting one every command frame carries zero, every node then gets a disable, and a node that
cannot be sent to gets the e-stop frame. The run ends as a safety stop with the stage's own
fault, and the log has the fault event with the exception's text.
"""

from __future__ import annotations

import asyncio
import errno
import itertools
import json
import time
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import can
import numpy as np
import pytest

from handctl import cli, session
from handctl.config import HandConfig
from handctl.errors import HandctlError
from handctl.online.bus import open_bus
from handctl.online.busspec import BusSpec
from handctl.online.clock import LockstepClock, Tick
from handctl.online.drivers.hand import HandDriver
from handctl.online.loop import (
    EXCEPTION_TEXT_CHARS,
    ZERO_TICKS_BEFORE_DISABLE,
    EndOfTicks,
    Outcome,
    Runtime,
    TickRecord,
)
from handctl.online.recipes.loader import load_recipe
from handctl.online.recipes.schema import Recipe
from handctl.online.safety import supervisor as supervisor_module
from handctl.online.safety.faults import FaultCode
from handctl.online.safety.limits import limit_torque
from handctl.protocol import NODE_COMMANDS, NodeState, load_protocol
from handctl.recording import channels as ch
from handctl.recording.metadata import run_metadata, start_metadata
from handctl.recording.reader import iter_decoded, open_recording
from handctl.recording.recorder import Recorder
from handctl.sim.hand import SimulatedHand

from ..dbc import decode
from .rig import CLOSE_AND_HOLD_1S

#: Ticks after the first command when the exception is forced: the hold torque flows by then
#: (and the status line, every 100 ticks, is due at it).
ARM_TICKS = 400
DISABLE = NODE_COMMANDS["disable"]
_channels = itertools.count()


class ForcedError(RuntimeError):
    """The exception a test forces, so that it cannot be mistaken for a real one."""


@dataclass
class Bench:
    hand: HandConfig
    sim: SimulatedHand
    runtime: Runtime
    recorder: Recorder
    listener: can.BusABC
    log: Path


@contextmanager
def bench(hand: HandConfig, recipe: Recipe, log: Path) -> Iterator[Bench]:
    """Host, simulated hand and a plain python-can listener on one private virtual channel;
    the run recorded the way ``handctl run recipe --log`` records one."""
    channel = f"tick-exception-{next(_channels)}"
    listener = can.Bus(
        interface="virtual",
        channel=channel,
        receive_own_messages=False,
        protocol=can.CanProtocol.CAN_FD,
    )
    try:
        with (
            open_bus(f"virtual:{channel}", hand.bus) as peer,
            open_bus(f"virtual:{channel}", hand.bus) as host,
        ):
            sim = SimulatedHand(hand, peer, seed=0)
            clock = LockstepClock(hand.bus.period_s, sim.step)
            driver = HandDriver(hand, load_protocol(), host, clock_ns=clock.now_ns)
            runtime = Runtime(hand, driver, clock, recipe, max_ticks=5000)
            recorder = Recorder(
                log,
                hand,
                start_metadata(hand, recipe, ["test", "exception"]),
                phase_names=[p.name for p in recipe.phases],
            )
            with recorder:
                runtime.recorder = recorder
                recorder.attach(runtime)
                recorder.add_metadata(
                    ch.META_RUN,
                    run_metadata(
                        mode="lockstep",
                        bus="virtual",
                        seed=0,
                        period_ns=1_000_000,
                        startup_ticks=runtime.startup_ticks,
                        reset_node_faults=False,
                        estimator=False,
                    ),
                )
                recorder.wait_ready()
                yield Bench(hand, sim, runtime, recorder, listener, log)
    finally:
        listener.shutdown()


class Trigger:
    """When the forced exception is due: from ARM_TICKS after the first command on, at the
    first call only (``always=False``) or at every call."""

    def __init__(self, runtime: Runtime, always: bool) -> None:
        self.runtime = runtime
        self.always = always
        self.tick = -1
        self.fired = 0
        runtime.tick_hooks.insert(0, self._see)

    def _see(self, tk: Tick) -> None:
        self.tick = tk.tick

    def __call__(self) -> bool:
        first = self.runtime.first_send_tick
        if first < 0 or self.tick < first + ARM_TICKS - 1 or (self.fired and not self.always):
            return False
        self.fired += 1
        return True


def _wrap(due: Trigger, stage: str, real: Callable[..., Any]) -> Callable[..., Any]:
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        if due():
            raise ForcedError(f"forced in the {stage} stage")
        return real(*args, **kwargs)

    return wrapper


#: The node whose frames the send and encode cases break: its frame of the faulting tick
#: comes after the first node's, which did go out.
BROKEN_NODE = 2


def force(stage: str, b: Bench, due: Trigger, mp: pytest.MonkeyPatch) -> None:  # noqa: C901 - one branch per loop stage
    """Make ``stage`` raise when ``due`` says so, inside the real code of that stage."""
    rt, protocol = b.runtime, load_protocol()
    if stage == "poll":
        mp.setattr(rt.driver, "poll", _wrap(due, stage, rt.driver.poll))
    elif stage == "decode":
        layout = protocol.layout("Feedback", 1)
        mp.setattr(layout, "decode", _wrap(due, stage, layout.decode))
    elif stage == "estimator":
        # Only the call is broken: the runner reads measured sizes from its own reference.
        mp.setattr(rt, "estimator", _wrap(due, stage, lambda angle: None))
    elif stage == "runner":
        assert rt.runner is not None
        mp.setattr(rt.runner, "advance", _wrap(due, stage, rt.runner.advance))
    elif stage == "supervisor":
        mp.setattr(supervisor_module, "limit_torque", _wrap(due, stage, limit_torque))
    elif stage == "encode":
        layout = protocol.layout("TorqueCommand", BROKEN_NODE)
        mp.setattr(layout, "encode", _wrap(due, stage, layout.encode))
    elif stage == "send":
        real_send = rt.driver.bus.send
        broken_id = protocol.layout("TorqueCommand", BROKEN_NODE).frame_id

        def send(frame_id: int, data: bytes, more: bool = False) -> bool:
            if frame_id == broken_id and due():
                raise ForcedError("forced in the send stage")
            return real_send(frame_id, data, more)

        mp.setattr(rt.driver.bus, "send", send)
    elif stage == "record":
        mp.setattr(b.recorder, "push", _wrap(due, stage, b.recorder.push))
    elif stage == "hook":
        rt.tick_hooks.append(_wrap(due, stage, lambda tk: None))
    elif stage == "clock":
        real_wait = rt.clock.wait_tick

        async def wait_tick() -> Tick:
            if due():
                raise ForcedError("forced in the clock stage")
            return await real_wait()

        mp.setattr(rt.clock, "wait_tick", wait_tick)
    elif stage == "status":
        rt.status = _wrap(due, stage, lambda line: None)
    elif stage == "accounting":
        stats = rt._stats  # the tick's own bookkeeping (tickstats), after the record
        mp.setattr(stats, "store", _wrap(due, stage, stats.store))
    else:  # pragma: no cover
        raise AssertionError(stage)


STAGE_FAULTS = {
    "poll": FaultCode.POLL_EXCEPTION,
    "decode": FaultCode.DECODE_EXCEPTION,
    "estimator": FaultCode.ESTIMATOR_EXCEPTION,
    "runner": FaultCode.RUNNER_EXCEPTION,
    "supervisor": FaultCode.SUPERVISOR_EXCEPTION,
    "encode": FaultCode.ENCODE_EXCEPTION,
    "send": FaultCode.SEND_EXCEPTION,
    "record": FaultCode.RECORD_EXCEPTION,
    "hook": FaultCode.HOOK_EXCEPTION,
    "clock": FaultCode.CLOCK_EXCEPTION,
    "status": FaultCode.STATUS_EXCEPTION,
    "accounting": FaultCode.STATUS_EXCEPTION,
}


@dataclass
class Wire:
    """What the listener heard, in bus order: per node its torque commands (position on the
    wire, three N·m) and the positions of its disables; the positions of e-stops."""

    torques: dict[int, list[tuple[int, np.ndarray]]]
    disables: dict[int, list[int]]
    estops: list[int]


def hear(listener: can.BusABC, hand: HandConfig) -> Wire:
    torque_ids = {f.can_ids.torque_command: f.node_id for f in hand.fingers}
    command_ids = {f.can_ids.node_command: f.node_id for f in hand.fingers}
    wire = Wire({f.node_id: [] for f in hand.fingers}, {f.node_id: [] for f in hand.fingers}, [])
    pos = 0
    while (msg := listener.recv(timeout=0)) is not None:
        pos += 1
        frame_id, data = msg.arbitration_id, bytes(msg.data)
        if frame_id in torque_ids:
            sig = decode(frame_id, data)
            wire.torques[torque_ids[frame_id]].append(
                (pos, np.array([sig["Torque1"], sig["Torque2"], sig["Torque3"]]))
            )
        elif (
            frame_id in command_ids and decode(frame_id, data, choices=False)["Command"] == DISABLE
        ):
            wire.disables[command_ids[frame_id]].append(pos)
        elif frame_id == 0:
            wire.estops.append(pos)
    return wire


def assert_stopped_on_the_wire(wire: Wire, fault_row: int, unreachable: Sequence[int] = ()) -> None:
    """From the command after the faulting tick's (row ``fault_row`` of each node: command n
    of a node belongs to tick first_send_tick + n) every torque is zero, at least
    ZERO_TICKS_BEFORE_DISABLE of them, and then the node gets a disable; a node that could
    not be sent to gets the e-stop frame instead."""
    for node, rows in wire.torques.items():
        last_torque_pos, last_torque = rows[fault_row - 1]
        assert np.any(last_torque != 0), f"node {node}: no torque flowed before the fault"
        after = rows[fault_row + 1 :]
        assert all(not np.any(values) for _, values in after), (
            f"node {node}: torque after the faulting tick: {[v for _, v in after if v.any()]}"
        )
        if node in unreachable:
            assert any(p > last_torque_pos for p in wire.estops), f"node {node}: no e-stop"
        else:
            assert len(after) >= ZERO_TICKS_BEFORE_DISABLE, f"node {node}: {len(after)} zeros"
        disables = [p for p in wire.disables[node] if p > last_torque_pos]
        assert disables, f"node {node}: never disabled after the fault"
        assert disables[-1] > rows[-1][0], f"node {node}: a torque command after its disable"


def logged_torques(log: Path) -> dict[int, tuple[float, str]]:
    """Per tick of the log's ``/control/torque`` rows: the largest |applied| (N·m) and the
    supervisor's state of ``/safety/state`` at that tick."""
    recording = open_recording(log)
    torque: dict[int, float] = {}
    states: dict[int, str] = {}
    state = ""
    for topic, _, msg in iter_decoded(recording, [ch.TORQUE, ch.SAFETY]):
        if topic == ch.TORQUE:
            torque[msg["tick"]] = max(abs(v) for v in msg["applied_nm"])
        else:
            state = msg["state"]
            states[msg["tick"]] = state
    out = {}
    for tick in sorted(torque):
        state = states.get(tick, state)
        out[tick] = (torque[tick], state)
    return out


def logged_faults(log: Path) -> tuple[bool, int, list[dict[str, Any]]]:
    """Whether the log is complete, its ticks, and its fault events."""
    recording = open_recording(log)
    ticks = 0
    faults = []
    for topic, _, msg in iter_decoded(recording, [ch.EVENTS, ch.TIMING]):
        if topic == ch.TIMING:
            ticks += 1
        elif msg["kind"] == "fault":
            faults.append(msg)
    return recording.complete, ticks, faults


@pytest.fixture(scope="module")
def hold(hand: HandConfig, tmp_path_factory: pytest.TempPathFactory) -> Recipe:
    path = tmp_path_factory.mktemp("recipes") / "hold.yaml"
    path.write_text(CLOSE_AND_HOLD_1S)
    return load_recipe(path, hand)


@pytest.mark.parametrize("always", [False, True], ids=["once", "every_call"])
@pytest.mark.parametrize("stage", list(STAGE_FAULTS))
def test_an_exception_in_any_stage_is_a_controlled_stop(
    hand: HandConfig,
    hold: Recipe,
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    stage: str,
    always: bool,
) -> None:
    code = STAGE_FAULTS[stage]
    with bench(hand, hold, tmp_path / "run.mcap") as b:
        due = Trigger(b.runtime, always)
        force(stage, b, due, monkeypatch)
        result = asyncio.run(b.runtime.run())
        monkeypatch.undo()
        b.recorder.close(session.summarise_run(result, hand, hold, True, None))
        wire = hear(b.listener, hand)
    assert due.fired, "the forced exception never came"
    assert result.outcome is Outcome.SAFETY_STOP, result.message
    failure = result.exception
    assert failure is not None and failure.code is code, failure
    assert failure.type == "ForcedError" and failure.message == f"forced in the {stage} stage"
    first = result.faults[0]
    assert first.code is code and first.tick == failure.tick
    assert "ForcedError: forced in the" in first.detail
    # The wire: zero from the faulting tick on, then disable (the e-stop where a node could
    # not be sent to).
    unreachable = [BROKEN_NODE] if stage == "send" and always else []
    assert_stopped_on_the_wire(wire, first.tick - b.runtime.first_send_tick, unreachable)
    if not (stage == "clock" and always):  # without its clock the simulated hand stands still
        assert all(not any(n.applied) and n.state != NodeState.ENABLED for n in b.sim.nodes)
    # The summary and the log.
    summary = session.summarise_run(result, hand, hold, True, None)
    assert summary["outcome"] == "safety_stop"
    assert summary["faults"][0]["code"] == code.name
    assert summary["faults"][0]["category"] == "immediate"
    assert summary["exception"]["code"] == code.name
    assert summary["exception"]["type"] == "ForcedError"
    complete, ticks, faults = logged_faults(tmp_path / "run.mcap")
    assert complete
    if not (stage == "accounting" and always):  # then the run could count no tick after it
        assert ticks == result.ticks
    assert [(f["name"], f["category"], f["tick"]) for f in faults] == [
        (code.name, "immediate", first.tick)
    ]
    assert f"ForcedError: forced in the {stage} stage" in faults[0]["detail"]
    # The phase under way ends on the exception, and the log's rows say what was sent: zero,
    # faulted, from the tick that raised to the disable (they stopped at the last torque the
    # runner asked for, which a plot of the log then held to its end).
    assert result.phases[-1]["exit"] == f"safety stop: {code.name}"
    assert result.phases[-1]["end_s"] is not None
    if stage != "record" and not (stage == "clock" and always):  # no rows, no ticks
        rows = logged_torques(tmp_path / "run.mcap")
        # the status line and the accounting come after the tick's send and its row: that
        # tick sent what its row says
        since = first.tick + (stage in ("status", "accounting"))
        after = {t: v for t, v in rows.items() if t >= since}
        assert max(after, default=-1) >= first.tick + ZERO_TICKS_BEFORE_DISABLE, sorted(after)
        assert all(v == (0.0, "faulted") for v in after.values()), after


def test_a_node_that_cannot_be_sent_to_gets_the_estop(
    hand: HandConfig, hold: Recipe, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Sending raises for one node on every try: the others still get zero and a disable,
    and the e-stop frame stops the one that cannot be reached."""
    with bench(hand, hold, tmp_path / "run.mcap") as b:
        force("send", b, Trigger(b.runtime, always=True), monkeypatch)
        result = asyncio.run(b.runtime.run())
        monkeypatch.undo()
        wire = hear(b.listener, hand)
    row = result.faults[0].tick - b.runtime.first_send_tick
    assert len(wire.torques[BROKEN_NODE]) == row  # nothing reached it after the fault
    assert_stopped_on_the_wire(wire, row, unreachable=[BROKEN_NODE])
    broken = next(n for n in b.sim.nodes if n.node_id == BROKEN_NODE)
    assert broken.state == NodeState.FAULT and not any(broken.applied)  # e-stop, no torque
    # said, with what the next run needs (it was not: the next run refused the nodes)
    assert "the e-stop was sent" in result.message
    assert "--reset-node-faults" in result.message


def test_a_stop_whose_frames_and_e_stop_the_bus_refuses_says_so(
    hand: HandConfig, hold: Recipe, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """After the runner's exception the bus refuses every frame: no zero, no disable and no
    e-stop went, and the message said "the e-stop was sent: each node latches FAULT (ESTOP)"
    where only the nodes' own watchdog stopped them (found by an outside audit)."""
    with bench(hand, hold, tmp_path / "run.mcap") as b:
        due = Trigger(b.runtime, always=False)
        force("runner", b, due, monkeypatch)
        real = b.runtime.driver.bus.send

        def send(frame_id: int, data: bytes, more: bool = False) -> bool:
            return False if due.fired else real(frame_id, data, more)

        monkeypatch.setattr(b.runtime.driver.bus, "send", send)
        result = asyncio.run(b.runtime.run())
        monkeypatch.undo()
        wire = hear(b.listener, hand)
    assert result.outcome is Outcome.SAFETY_STOP
    row = result.faults[0].tick - b.runtime.first_send_tick
    assert all(len(rows) == row for rows in wire.torques.values())  # nothing after it
    assert not any(wire.disables.values())
    assert "the e-stop was sent" not in result.message
    assert "neither did the e-stop sent after it" in result.message
    assert "its own command watchdog (FAULT TIMEOUT" in result.message


def test_a_disable_the_bus_refuses_at_the_end_is_said_as_the_bus_s(
    hand: HandConfig, hold: Recipe, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The bus refuses every NodeCommand frame once the run is under way: at the end of a
    completed run no disable went, and the nodes were said to have gone on ENABLED "after
    the disable" (found by an outside audit). The prepared disable is tried again, then the
    e-stop, and the bus's refusal is what is said: a bus that failed, a safety stop (it
    ended "completed", exit 0, found by an outside audit too)."""
    with bench(hand, hold, tmp_path / "run.mcap") as b:
        real = b.runtime.driver.bus.send
        rt = b.runtime
        command_ids = {n.layouts.node_command.frame_id for n in rt.driver.nodes}

        def send(frame_id: int, data: bytes, more: bool = False) -> bool:
            if (
                frame_id in command_ids
                and rt.first_send_tick >= 0
                and rt.tick > rt.first_send_tick + 5
            ):
                return False
            return real(frame_id, data, more)

        monkeypatch.setattr(b.runtime.driver.bus, "send", send)
        result = asyncio.run(b.runtime.run())
        monkeypatch.undo()
        wire = hear(b.listener, hand)
    assert result.outcome is Outcome.SAFETY_STOP
    [fault] = result.faults
    assert fault.code is FaultCode.BUS_ERROR
    assert not any(wire.disables.values())
    assert "went on saying ENABLED after the disable" not in result.disable_unconfirmed
    said = "the bus refused the disable at the end twice, and the e-stop was sent in its place"
    assert said in result.disable_unconfirmed
    assert said in fault.detail
    assert all(n.state == NodeState.FAULT for n in b.sim.nodes)  # the e-stop went


@pytest.mark.parametrize(
    "proposed",
    [None, [0.01] * 8, [[0.01] * 9], ["0.01"] * 9],
    ids=["none", "eight", "matrix", "strings"],
)
def test_a_recipe_that_proposes_no_torque_vector_is_stopped_on_that_alone(
    hand: HandConfig, hold: Recipe, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, proposed: Any
) -> None:
    """None was held as the last torque (the supervisor's "nothing asked") until the
    bookkeeping after the send raised on it; a wrong shape or strings were refused, but that
    bookkeeping then raised a second fault, SEND_EXCEPTION, which named the wrong stage and
    took the stop down the exception's path (found by an outside audit)."""
    with bench(hand, hold, tmp_path / "run.mcap") as b:
        due = Trigger(b.runtime, always=False)
        runner = b.runtime.runner
        assert runner is not None
        real = runner.feedback
        monkeypatch.setattr(runner, "feedback", lambda *args: proposed if due() else real(*args))
        result = asyncio.run(b.runtime.run())
        monkeypatch.undo()
        wire = hear(b.listener, hand)
    assert [f.code for f in result.faults] == [FaultCode.WRONG_SHAPE]
    assert result.exception is None
    row = result.faults[0].tick - b.runtime.first_send_tick
    assert_stopped_on_the_wire(wire, row)
    complete, _, faults = logged_faults(b.log)
    assert complete and [f["name"] for f in faults] == ["WRONG_SHAPE"]


def test_an_exception_while_enabling_is_a_controlled_stop(
    hand: HandConfig, hold: Recipe, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Outside the tick's stages (here: the enable, which the first node got), the stop is
    the same: RUN_EXCEPTION, zero to every node, then a disable."""
    with bench(hand, hold, tmp_path / "run.mcap") as b:
        real = b.runtime.driver.node_command_unsent

        def node_command_unsent(command: str, nodes: Any = None) -> list[int]:
            unsent = real(command, [hand.fingers[0].node_id] if command == "enable" else nodes)
            if command == "enable":
                raise ForcedError("forced while enabling")
            return unsent

        monkeypatch.setattr(b.runtime.driver, "node_command_unsent", node_command_unsent)
        result = asyncio.run(b.runtime.run())
        monkeypatch.undo()
        wire = hear(b.listener, hand)
    assert result.outcome is Outcome.SAFETY_STOP
    assert [f.code for f in result.faults] == [FaultCode.RUN_EXCEPTION]
    assert "ForcedError: forced while enabling" in result.faults[0].detail
    for node, rows in wire.torques.items():
        assert len(rows) >= ZERO_TICKS_BEFORE_DISABLE
        assert all(not np.any(values) for _, values in rows)
        assert wire.disables[node] and wire.disables[node][-1] > rows[-1][0]
    assert all(not any(n.applied) and n.state == NodeState.DISABLED for n in b.sim.nodes)


def test_ctrl_c_without_a_signal_handler_zeroes_and_disables_before_it_goes_on(
    hand: HandConfig, hold: Recipe, tmp_path: Path
) -> None:
    """A KeyboardInterrupt (or a cancelled task) inside a tick is not the runtime's to
    swallow, but it leaves no torque on: zero and disable go out before it propagates."""
    with bench(hand, hold, tmp_path / "run.mcap") as b:
        due = Trigger(b.runtime, always=False)

        def interrupt(tk: Tick) -> None:
            if due():
                raise KeyboardInterrupt

        b.runtime.tick_hooks.append(interrupt)
        with pytest.raises(KeyboardInterrupt):
            asyncio.run(b.runtime.run())
        wire = hear(b.listener, hand)
    for node, rows in wire.torques.items():
        nonzero = [i for i, (_, values) in enumerate(rows) if np.any(values)]
        assert nonzero and nonzero[-1] == len(rows) - 2, f"node {node}: no zero after torque"
        assert wire.disables[node] and wire.disables[node][-1] > rows[-1][0], f"node {node}"


@pytest.mark.parametrize("estop_goes", [False, True], ids=["nothing_goes", "estop_goes"])
def test_an_interrupt_whose_stop_the_bus_refuses_says_so(
    hand: HandConfig,
    hold: Recipe,
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    estop_goes: bool,
) -> None:
    """Ctrl-C inside a tick while the bus refuses the nodes' frames: the run said "zero
    torque and a disable were sent at once" when none went and the nodes held their last
    torque until their watchdog (found by an outside audit). What the bus did is said."""
    with bench(hand, hold, tmp_path / "run.mcap") as b:
        rt = b.runtime
        due = Trigger(rt, always=False)

        def interrupt(tk: Tick) -> None:
            if due():
                raise KeyboardInterrupt

        rt.tick_hooks.append(interrupt)
        real = rt.driver.bus.send

        def send(frame_id: int, data: bytes, more: bool = False) -> bool:
            if due.fired and not (estop_goes and frame_id == 0):
                return False
            return real(frame_id, data, more)

        monkeypatch.setattr(rt.driver.bus, "send", send)
        with pytest.raises(KeyboardInterrupt):
            asyncio.run(rt.run())
        monkeypatch.undo()
        wire = hear(b.listener, hand)
    assert not any(wire.disables.values())
    assert bool(wire.estops) is estop_goes
    kept = rt.interrupted
    assert kept is not None and kept.outcome is Outcome.INTERRUPTED
    assert "were sent at once" not in kept.message, kept.message
    assert "the bus refused the zero torque and the disable to a node" in kept.message
    if estop_goes:
        assert "so the e-stop was sent: each node latches FAULT (ESTOP)" in kept.message
    else:
        assert "stopped only by its own command watchdog" in kept.message


def test_a_run_whose_coroutine_is_closed_from_outside_zeroes_and_disables(
    hand: HandConfig, hold: Recipe, tmp_path: Path
) -> None:
    """The run's coroutine closed from outside (its task gone with its loop) gets a
    GeneratorExit at its await: an interrupt, not a stage's fault, since no tick can be
    awaited after it; zero and disable go at once, and the close goes on."""
    with bench(hand, hold, tmp_path / "run.mcap") as b:
        rt = b.runtime
        due = Trigger(rt, always=False)
        loop = asyncio.new_event_loop()

        def leave(tk: Tick) -> None:
            if due():
                loop.stop()  # the loop ends with the run's task pending

        rt.tick_hooks.append(leave)
        run = rt.run()
        try:
            task = loop.create_task(run)
            loop.run_forever()
            assert not task.done()
            run.close()
        finally:
            loop.close()
        wire = hear(b.listener, hand)
    for node, rows in wire.torques.items():
        assert np.any(rows[-2][1]) and not np.any(rows[-1][1]), f"node {node}: {rows[-3:]}"
        assert wire.disables[node] and wire.disables[node][-1] > rows[-1][0], f"node {node}"
    kept = rt.interrupted
    assert kept is not None and kept.outcome is Outcome.INTERRUPTED
    assert kept.message.startswith("GeneratorExit in tick "), kept.message


@pytest.mark.parametrize("interrupt", [KeyboardInterrupt, asyncio.CancelledError])
def test_an_interrupt_during_the_stop_after_an_exception_still_disables(
    hand: HandConfig, hold: Recipe, tmp_path: Path, interrupt: type[BaseException]
) -> None:
    """Ctrl-C or a cancellation while the stop after an exception waits for its next tick
    (found by an outside audit): one zero frame went, then no disable and no e-stop, the
    nodes left ENABLED for their watchdog, and no result kept. Now zero and the disable go
    at once, as for an interrupt in any tick, and the result is the exception's stop."""
    with bench(hand, hold, tmp_path / "run.mcap") as b:
        runtime = b.runtime
        due = Trigger(runtime, always=False)

        def raise_once(tk: Tick) -> None:
            if due():
                raise ForcedError("forced in a tick hook")

        runtime.tick_hooks.append(raise_once)
        wait_tick = runtime.clock.wait_tick

        async def interrupted_in_the_stop() -> Tick:
            if runtime.exception is not None:
                raise interrupt
            return await wait_tick()

        runtime.clock.wait_tick = interrupted_in_the_stop  # type: ignore[method-assign]
        with pytest.raises(interrupt):
            asyncio.run(runtime.run())
        wire = hear(b.listener, hand)
        b.sim.step()  # the nodes take the disable on their next tick
    for node, rows in wire.torques.items():
        assert np.any(rows[-3][1]) and not np.any(rows[-1][1]), f"node {node}: {rows[-3:]}"
        assert wire.disables[node] and wire.disables[node][-1] > rows[-1][0], f"node {node}"
    assert [n.state for n in b.sim.nodes] == [int(NodeState.DISABLED)] * len(hand.fingers)
    kept = runtime.interrupted
    assert kept is not None and kept.outcome is Outcome.SAFETY_STOP
    assert "ForcedError: forced in a tick hook" in kept.message, kept.message
    assert kept.message.endswith(
        f"; {interrupt.__name__} during the stop: zero torque and a disable were sent at once"
    )


def test_only_a_lockstep_clock_may_end_a_run_without_a_stop(
    hand: HandConfig, hold: Recipe, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A re-run ends at the end of its log with EndOfTicks, sending nothing more; the same
    from a clock that is not lockstep (a real-time one never runs out) is a clock fault."""
    with bench(hand, hold, tmp_path / "run.mcap") as b:
        due = Trigger(b.runtime, always=True)
        real_wait = b.runtime.clock.wait_tick

        async def wait_tick() -> Tick:
            if due():
                raise EndOfTicks
            return await real_wait()

        monkeypatch.setattr(b.runtime.clock, "wait_tick", wait_tick)
        monkeypatch.setattr(b.runtime.clock, "lockstep", False)
        result = asyncio.run(b.runtime.run())
        monkeypatch.undo()
        wire = hear(b.listener, hand)
    assert [f.code for f in result.faults] == [FaultCode.CLOCK_EXCEPTION]
    assert_stopped_on_the_wire(wire, result.faults[0].tick - b.runtime.first_send_tick)


def test_a_stop_iteration_in_a_stage_keeps_its_stage_and_its_tick(
    hand: HandConfig, hold: Recipe, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A StopIteration raised in a stage leaves the tick's coroutine as a RuntimeError (PEP
    479) whose traceback begins above the tick: the fault was RUN_EXCEPTION "coroutine
    raised StopIteration (in _run ...)", and the tick that raised went uncounted, one less
    than the log's (found by an outside audit)."""
    with bench(hand, hold, tmp_path / "run.mcap") as b:
        rt = b.runtime
        due = Trigger(rt, always=False)
        assert rt.runner is not None
        real = rt.runner.advance

        def advance(*args: Any, **kwargs: Any) -> None:
            if due():
                raise StopIteration("forced in the runner stage")
            real(*args, **kwargs)

        monkeypatch.setattr(rt.runner, "advance", advance)
        result = asyncio.run(rt.run())
        monkeypatch.undo()
        b.recorder.close(session.summarise_run(result, hand, hold, True, None))
    failure = result.exception
    assert failure is not None and failure.code is FaultCode.RUNNER_EXCEPTION, failure
    assert failure.type == "StopIteration" and failure.message == "forced in the runner stage"
    assert failure.where.startswith("advance (tests/integration/")
    _, ticks, faults = logged_faults(tmp_path / "run.mcap")
    assert ticks == result.ticks
    assert [(f["name"], f["tick"]) for f in faults] == [("RUNNER_EXCEPTION", failure.tick)]


def test_a_clock_that_gives_no_more_ticks_is_a_clock_fault_not_a_hang(
    hand: HandConfig, hold: Recipe, tmp_path: Path
) -> None:
    """The clock stops giving ticks (a real-time clock whose timer callback raised, which
    asyncio logs and swallows): the run waited for it forever, deaf to the stop signals
    (found by an outside audit). A clock silent for ``clock_silent_s`` is the clock's fault,
    and the stop's frames go without it."""
    with bench(hand, hold, tmp_path / "run.mcap") as b:
        rt = b.runtime
        rt.clock_silent_s = 0.3  # CLOCK_SILENT_S, seconds, in a run
        due = Trigger(rt, always=True)
        real_wait = rt.clock.wait_tick

        async def wait_tick() -> Tick:
            if due():
                await asyncio.get_running_loop().create_future()  # never comes
            return await real_wait()

        rt.clock.wait_tick = wait_tick  # type: ignore[method-assign]
        result = asyncio.run(rt.run())
        wire = hear(b.listener, hand)
    assert result.outcome is Outcome.SAFETY_STOP
    failure = result.exception
    assert failure is not None and failure.code is FaultCode.CLOCK_EXCEPTION, failure
    assert failure.type == "ClockSilentError"
    assert_stopped_on_the_wire(wire, result.faults[0].tick - rt.first_send_tick)


def test_a_loop_held_up_while_it_waits_for_its_clock_is_not_a_silent_clock(
    hand: HandConfig, hold: Recipe, tmp_path: Path
) -> None:
    """The process does not run for longer than ``clock_silent_s`` while it waits for its
    tick (a SIGSTOP and SIGCONT, here a callback that holds the event loop): its clock did
    not fall silent, and the run goes on (a multi-second pause is judged by its missed
    ticks, as ever)."""
    with bench(hand, hold, tmp_path / "run.mcap") as b:
        rt = b.runtime
        rt.clock_silent_s = 0.3
        due = Trigger(rt, always=False)
        real_wait = rt.clock.wait_tick

        async def wait_tick() -> Tick:
            if due():
                loop = asyncio.get_running_loop()
                loop.call_later(0.25, time.sleep, 1.0)  # the process held, mid-wait
                tick_due = loop.create_future()
                loop.call_later(0.28, tick_due.set_result, None)  # due while it is held
                await tick_due
            return await real_wait()

        rt.clock.wait_tick = wait_tick  # type: ignore[method-assign]
        result = asyncio.run(rt.run())
    assert due.fired
    assert result.outcome is Outcome.COMPLETED, result.message


def test_a_huge_exception_message_is_cut_and_its_place_kept(
    hand: HandConfig, hold: Recipe, tmp_path: Path
) -> None:
    """An exception carrying a huge object: the fault, the summary and the log get its
    beginning, and the log's event still ends with where it was raised."""
    with bench(hand, hold, tmp_path / "run.mcap") as b:
        due = Trigger(b.runtime, always=False)

        def hook(tk: Tick) -> None:
            if due():
                raise ForcedError("x" * 1_000_000)

        b.runtime.tick_hooks.append(hook)
        result = asyncio.run(b.runtime.run())
        b.recorder.close()
    failure = result.exception
    assert failure is not None and len(failure.message) <= EXCEPTION_TEXT_CHARS
    assert len(result.faults[0].detail) < 2 * EXCEPTION_TEXT_CHARS
    _, _, faults = logged_faults(tmp_path / "run.mcap")
    assert faults[0]["detail"].endswith(
        f"(in hook (tests/integration/{Path(__file__).name}:{hook.__code__.co_firstlineno + 2}))"
    )


def test_a_non_ascii_exception_message_is_cut_on_characters_and_its_place_kept(
    hand: HandConfig, hold: Recipe, tmp_path: Path
) -> None:
    """A message of 300 characters of three bytes each: cut to its characters, the fault fits
    its event in the log with its place, no character broken (the event was cut at its 480th
    byte: in the middle of a character, its place gone; found by an outside audit)."""
    with bench(hand, hold, tmp_path / "run.mcap") as b:
        due = Trigger(b.runtime, always=False)

        def hook(tk: Tick) -> None:
            if due():
                raise ForcedError("\u20ac" * 300)

        b.runtime.tick_hooks.append(hook)
        result = asyncio.run(b.runtime.run())
        b.recorder.close()
    assert result.exception is not None
    _, _, faults = logged_faults(tmp_path / "run.mcap")
    detail = faults[0]["detail"]
    assert detail.startswith("ForcedError: \u20ac\u20ac") and "\ufffd" not in detail
    assert set(detail.split(" (in ")[0].removeprefix("ForcedError: ")) <= {"\u20ac", "."}
    assert detail.endswith(
        f"(in hook (tests/integration/{Path(__file__).name}:{hook.__code__.co_firstlineno + 2}))"
    )


# -- the two reproductions of the issue, through the command line ------------------------------
TOO_MUCH = """
recipe: too_much
phases:
  - name: ramp
    torques: [4.0, 0, 0, 0, 0, 0, 0, 0, 0]
    ramp_s: 0.03
    max_s: 1.0
    on_timeout: next
"""
TWO_OBJECTS = """
recipe: two_objects
objects:
  - {name: cyl1, radius: 0.02}
  - {name: cyl2, radius: 0.02}
phases:
  - name: close
    torques: [0.06, 0.05, 0.03, 0.06, 0.05, 0.03, -0.06, -0.05, -0.03]
    ramp_s: 0.2
    max_s: 0.5
    on_timeout: next
"""


def _cli_run(args: list[str], monkeypatch: pytest.MonkeyPatch) -> tuple[int, can.BusABC]:
    """``handctl run recipe`` in this process, with a plain python-can listener joined to the
    simulated hand's private virtual channel as soon as the run opens it."""
    listeners: list[can.BusABC] = []
    real_open = open_bus

    def open_and_listen(spec: Any, *rest: Any, **kwargs: Any) -> Any:
        bus = real_open(spec, *rest, **kwargs)
        if isinstance(spec, BusSpec) and spec.interface == "virtual" and not listeners:
            listeners.append(
                can.Bus(
                    interface="virtual",
                    channel=spec.channel,
                    receive_own_messages=False,
                    protocol=can.CanProtocol.CAN_FD,
                )
            )
        return bus

    monkeypatch.setattr(session, "open_bus", open_and_listen)
    try:
        code = cli.main(["run", "recipe", *args])
    except BaseException:
        for listener in listeners:
            listener.shutdown()
        raise
    assert listeners, "the run opened no virtual channel"
    return code, listeners[0]


def _cli_run_heard(
    text: str, hand: HandConfig, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> tuple[int, Wire, dict[str, Any], Path]:
    """``handctl run recipe`` of the recipe ``text`` with ``--summary-json`` and ``--log``:
    its exit code, what a listener heard of ``hand``'s frames, the summary, and the log."""
    recipe = tmp_path / "recipe.yaml"
    recipe.write_text(text)
    out, log = tmp_path / "out.json", tmp_path / "run.mcap"
    code, listener = _cli_run(
        [str(recipe), "--summary-json", str(out), "--log", str(log)], monkeypatch
    )
    try:
        wire = hear(listener, hand)
    finally:
        listener.shutdown()
    return code, wire, json.loads(out.read_text()), log


def _stopped_after_torque(wire: Wire) -> None:
    """Judged on the wire alone: after each node's last torque, only zeros (at least
    ZERO_TICKS_BEFORE_DISABLE), then a disable."""
    for node, rows in wire.torques.items():
        nonzero = [i for i, (_, values) in enumerate(rows) if np.any(values)]
        tail = rows[nonzero[-1] + 1 :] if nonzero else rows
        assert len(tail) >= ZERO_TICKS_BEFORE_DISABLE, f"node {node}"
        assert wire.disables[node] and wire.disables[node][-1] > rows[-1][0], f"node {node}"


def test_a_tau_max_the_wire_cannot_carry_ends_in_a_safety_stop(
    hand: HandConfig, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The issue's first finding: tau_max 5 N·m (the wire carries ±3.2767) and a recipe
    asking 4 N·m. The config is built here, past the loader (which refuses it), so this holds
    whatever the loader checks."""
    f1 = hand.fingers[0]
    j1 = replace(f1.joints[0], tau_max=5.0, rate_limit=200.0)
    strong = replace(hand, fingers=(replace(f1, joints=(j1, *f1.joints[1:])), *hand.fingers[1:]))
    monkeypatch.setattr("handctl.config.load_hand", lambda path: strong)
    code, wire, summary, log = _cli_run_heard(TOO_MUCH, strong, tmp_path, monkeypatch)
    assert code == cli.EXIT_SAFETY_STOP
    assert summary["outcome"] == "safety_stop"
    assert summary["faults"][0]["code"] == "ENCODE_EXCEPTION"
    assert summary["exception"]["type"] == "ProtocolError"
    assert "TorqueCommand_1.Torque1" in summary["exception"]["message"]
    assert max(float(np.max(np.abs(v))) for _, v in wire.torques[1]) > 3.0  # it got close
    _stopped_after_torque(wire)
    _, _, faults = logged_faults(log)
    assert [f["name"] for f in faults] == ["ENCODE_EXCEPTION"]
    assert "ProtocolError" in faults[0]["detail"]


def test_a_recipe_with_more_objects_than_the_hand_is_refused_before_any_bus_opens(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """The issue's second finding: a recipe declaring two objects on a simulated hand with
    one, whose ground-truth tick hook raised IndexError mid-run. It is now bad input (exit 2),
    named by the recipe's key, and no bus is opened, so nothing is sent."""
    from ..conftest import HAND_YAML

    text = HAND_YAML.read_text()
    second = [line for line in text.splitlines() if "{name: cyl2," in line]
    assert len(second) == 1
    one_object = tmp_path / "one_object.yaml"
    one_object.write_text(text.replace(second[0] + "\n", ""))
    recipe = tmp_path / "two_objects.yaml"
    recipe.write_text(TWO_OBJECTS)
    opened: list[Any] = []
    monkeypatch.setattr(session, "open_bus", lambda *args, **kwargs: opened.append(args))
    code = cli.main(
        [
            "run",
            "recipe",
            str(recipe),
            "--hand",
            str(one_object),
            "--summary-json",
            str(tmp_path / "out.json"),
        ]
    )
    assert code == cli.EXIT_BAD_INPUT
    assert opened == []
    err = capsys.readouterr().err
    assert "two_objects.yaml: objects[1].name" in err and "found 'cyl2'" in err


def test_a_recorder_that_breaks_inside_still_leaves_a_finished_log(
    hand: HandConfig, hold: Recipe, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The recorder's own code raises from one tick on, in the run and again when it is
    closed: the hand is stopped, the run ends in exit 3 with its summary, and the log is
    finished with every tick up to the fault, the fault event and the summary."""
    broken_from = 300
    real_push, real_publish_idle = Recorder.push, Recorder._publish_idle

    def push(self: Recorder, record: TickRecord) -> None:
        if self._tick >= broken_from:
            raise ForcedError("forced inside the recorder")
        real_push(self, record)

    def publish_idle(self: Recorder) -> None:  # the last tick's row, when it is closed
        if self._tick >= broken_from:
            raise ForcedError("forced inside the recorder, again")
        real_publish_idle(self)

    monkeypatch.setattr(Recorder, "push", push)
    monkeypatch.setattr(Recorder, "_publish_idle", publish_idle)
    code, wire, summary, log = _cli_run_heard(CLOSE_AND_HOLD_1S, hand, tmp_path, monkeypatch)
    assert code == cli.EXIT_SAFETY_STOP
    assert summary["faults"][0]["code"] == "RECORD_EXCEPTION"
    assert "ForcedError" in summary["recording"]["error"]
    _stopped_after_torque(wire)
    complete, ticks, faults = logged_faults(log)
    assert complete and ticks == broken_from
    assert [(f["name"], f["tick"]) for f in faults] == [("RECORD_EXCEPTION", broken_from)]
    logged = open_recording(log).json_meta(ch.META_SUMMARY)
    assert logged is not None and logged["outcome"] == "safety_stop"


@pytest.mark.parametrize("always", [False, True], ids=["once", "every_call"])
def test_a_recorder_tap_that_raises_is_the_record_stage_s_and_its_frames_went(
    hand: HandConfig, hold: Recipe, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, always: bool
) -> None:
    """The recorder's transmit tap raises after the bus took the frames (and it recorded
    them). Its exception came out of the bus's send: the run stopped as SEND_EXCEPTION, the
    frames that went were counted as refused and their counters given back, so a node
    rejected the stop's zero torque and held its torque a tick longer; raised at every call,
    every stop frame was taken for refused and brought an e-stop, and the nodes ended in FAULT
    (found by an outside audit). It is the recorder's failure, and the frames went."""
    with bench(hand, hold, tmp_path / "run.mcap") as b:
        due = Trigger(b.runtime, always)
        bus = b.runtime.driver.bus
        recorded = bus.tap
        assert recorded is not None

        def tap(frames: list[tuple[int, bytes]], direction: int) -> None:
            recorded(frames, direction)
            if due():
                raise ForcedError("forced in the recorder's tap")

        monkeypatch.setattr(bus, "tap", tap)
        result = asyncio.run(b.runtime.run())
        monkeypatch.undo()
        if always:  # the stop's frames were tapped after the last row: said at the end
            with pytest.raises(HandctlError, match="a tap of the recorder failed after"):
                b.recorder.close()
        else:
            b.recorder.close()
        wire = hear(b.listener, hand)
    assert due.fired and result.outcome is Outcome.SAFETY_STOP, result.message
    assert [f.code for f in result.faults] == [FaultCode.RECORD_EXCEPTION], result.faults
    failure = result.exception
    assert failure is not None and failure.message == "forced in the recorder's tap"
    assert bus.tx_failed == 0  # type: ignore[attr-defined]
    assert not wire.estops and "e-stop" not in result.message and "refused" not in result.message
    assert_stopped_on_the_wire(wire, result.faults[0].tick - b.runtime.first_send_tick)
    assert [n.reject_counter for n in b.sim.nodes] == [0] * len(b.sim.nodes)
    assert all(not any(n.applied) and n.state == NodeState.DISABLED for n in b.sim.nodes)
    _, _, faults = logged_faults(tmp_path / "run.mcap")
    assert [f["name"] for f in faults] == ["RECORD_EXCEPTION"]


def _raise_in_the_runner_at(tick: int, exc: BaseException, mp: pytest.MonkeyPatch) -> None:
    """The recipe runner of every run in this process raises ``exc`` from its ``advance`` at
    run tick ``tick``, once."""
    from handctl.online.recipes.runner import RecipeRunner

    real = RecipeRunner.advance
    calls = [0]

    def advance(self: RecipeRunner, *args: Any, **kwargs: Any) -> None:
        calls[0] += 1
        if calls[0] == tick:
            raise exc
        real(self, *args, **kwargs)

    mp.setattr(RecipeRunner, "advance", advance)


def test_a_system_exit_inside_a_tick_is_a_safety_stop_with_its_summary(
    hand: HandConfig, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A library's exit() inside a stage went out as the process' exit code (here 7), with no
    summary and a log of 'no summary': it is a broken stage like any other."""
    _raise_in_the_runner_at(300, SystemExit(7), monkeypatch)
    code, wire, summary, log = _cli_run_heard(CLOSE_AND_HOLD_1S, hand, tmp_path, monkeypatch)
    assert code == cli.EXIT_SAFETY_STOP
    _stopped_after_torque(wire)
    assert summary["outcome"] == "safety_stop"
    assert summary["exception"]["code"] == "RUNNER_EXCEPTION"
    assert summary["exception"]["type"] == "SystemExit"
    logged = open_recording(log).json_meta(ch.META_SUMMARY)
    assert logged is not None and logged["outcome"] == "safety_stop"


@pytest.mark.parametrize("stage", ["poll", "clock"])
def test_a_system_exit_on_every_call_still_ends_in_the_stop_with_its_summary(
    hand: HandConfig, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, stage: str
) -> None:
    """The poll or the clock raises SystemExit(0) from one call on: the stop after the
    first one tried it again, and the second went out through the interrupt's handler, the
    process exiting 0 with no word and no summary, zero and disable back to back (the clock's
    from a task of ``asyncio.wait_for``'s own, out of the event loop) (found by an outside
    audit). The stop drops it, as any exception that recurs."""
    from handctl.online.clock import LockstepClock

    calls = [0]
    if stage == "poll":
        real_poll = HandDriver.poll

        def poll(self: HandDriver, *args: Any, **kwargs: Any) -> Any:
            calls[0] += 1
            if calls[0] >= 300:
                raise SystemExit(0)
            return real_poll(self, *args, **kwargs)

        monkeypatch.setattr(HandDriver, "poll", poll)
    else:
        real_wait = LockstepClock.wait_tick

        async def wait_tick(self: LockstepClock) -> Tick:
            calls[0] += 1
            if calls[0] >= 300:
                raise SystemExit(0)
            return await real_wait(self)

        monkeypatch.setattr(LockstepClock, "wait_tick", wait_tick)
    code, wire, summary, log = _cli_run_heard(CLOSE_AND_HOLD_1S, hand, tmp_path, monkeypatch)
    assert code == cli.EXIT_SAFETY_STOP
    _stopped_after_torque(wire)
    assert summary["outcome"] == "safety_stop"
    assert summary["exception"]["code"] == f"{stage.upper()}_EXCEPTION"
    assert summary["exception"]["type"] == "SystemExit"
    logged = open_recording(log).json_meta(ch.META_SUMMARY)
    assert logged is not None and logged["outcome"] == "safety_stop"


def test_a_clock_that_cannot_close_either_keeps_the_stop_s_result(
    hand: HandConfig, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The clock raises from one tick on, and its close raises too (as a real-time clock's
    can, taking its broken timer out of the loop): the close's exception replaced the safety
    stop with an internal error, exit 1, no summary (found by an outside audit)."""
    from handctl.online.clock import LockstepClock

    real_wait, calls = LockstepClock.wait_tick, [0]

    async def wait_tick(self: LockstepClock) -> Tick:
        calls[0] += 1
        if calls[0] >= 300:
            raise ForcedError("forced in the clock")
        return await real_wait(self)

    def close(self: LockstepClock) -> None:
        raise ForcedError("forced in the clock's close")

    monkeypatch.setattr(LockstepClock, "wait_tick", wait_tick)
    monkeypatch.setattr(LockstepClock, "close", close)
    code, wire, summary, log = _cli_run_heard(CLOSE_AND_HOLD_1S, hand, tmp_path, monkeypatch)
    assert code == cli.EXIT_SAFETY_STOP
    _stopped_after_torque(wire)
    assert summary["exception"]["code"] == "CLOCK_EXCEPTION"
    assert "closing the clock raised ForcedError: forced in the clock's close" in summary["message"]
    logged = open_recording(log).json_meta(ch.META_SUMMARY)
    assert logged is not None and logged["outcome"] == "safety_stop"


def test_stop_signals_during_the_stop_after_an_exception_are_said(
    hand: HandConfig,
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    """SIGINT and SIGTERM while the stop after an exception runs its ticks: the stop wins, as
    it should, but neither signal was said anywhere (found by an outside audit); README's
    last line names the signal."""
    import os
    import signal

    from handctl.online.clock import LockstepClock

    _raise_in_the_runner_at(300, ForcedError("forced in the runner"), monkeypatch)
    real_wait, stopping = LockstepClock.wait_tick, [0]
    from handctl.online.recipes.runner import RecipeRunner

    real_abort = RecipeRunner.abort

    def abort(self: RecipeRunner, *args: Any, **kwargs: Any) -> None:
        stopping[0] = 1  # the phase ends on the exception as its stop begins
        real_abort(self, *args, **kwargs)

    async def wait_tick(self: LockstepClock) -> Tick:
        if stopping[0]:
            stopping[0] += 1
            if stopping[0] in (2, 3):  # the stop's first two ticks
                os.kill(os.getpid(), signal.SIGINT if stopping[0] == 2 else signal.SIGTERM)
        return await real_wait(self)

    monkeypatch.setattr(RecipeRunner, "abort", abort)
    monkeypatch.setattr(LockstepClock, "wait_tick", wait_tick)
    code, wire, summary, _ = _cli_run_heard(CLOSE_AND_HOLD_1S, hand, tmp_path, monkeypatch)
    assert code == cli.EXIT_SAFETY_STOP
    _stopped_after_torque(wire)
    said = "signal SIGINT, signal SIGTERM came during this stop, which went on to its end"
    assert said in summary["message"]
    last = capsys.readouterr().err.strip().splitlines()[-1]
    assert last.startswith("handctl: safety stop: ") and said in last


class _LibrarysOwn(BaseException):
    """A BaseException of a library's own, neither an interrupt nor an exit."""


@pytest.mark.parametrize(
    "raised", [GeneratorExit(), _LibrarysOwn("a library's own")], ids=["generator_exit", "own"]
)
def test_any_other_base_exception_inside_a_tick_is_a_safety_stop_with_its_summary(
    hand: HandConfig, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, raised: BaseException
) -> None:
    """A GeneratorExit or another BaseException that is no interrupt, raised in a stage,
    crashed the command: a bare traceback, exit 1, no summary, a log of 'no summary', and
    zero and disable back to back with no zero ticks (found by an outside audit)."""
    _raise_in_the_runner_at(300, raised, monkeypatch)
    code, wire, summary, log = _cli_run_heard(CLOSE_AND_HOLD_1S, hand, tmp_path, monkeypatch)
    assert code == cli.EXIT_SAFETY_STOP
    _stopped_after_torque(wire)
    assert summary["outcome"] == "safety_stop"
    assert summary["exception"]["code"] == "RUNNER_EXCEPTION"
    assert summary["exception"]["type"] == type(raised).__name__
    logged = open_recording(log).json_meta(ch.META_SUMMARY)
    assert logged is not None and logged["outcome"] == "safety_stop"


class _SaysNothing(KeyboardInterrupt):
    """An interrupt whose ``__str__`` raises: the code handling it raised a ValueError in its
    place, and the run's result was lost (found by an outside audit)."""

    def __str__(self) -> str:
        raise ValueError("__str__ itself raised")


@pytest.mark.parametrize(
    "interrupt",
    [KeyboardInterrupt, asyncio.CancelledError, _SaysNothing],
    ids=["keyboard", "cancelled", "unsayable"],
)
def test_an_interrupt_inside_a_tick_says_what_ran_not_that_nothing_was_sent(
    hand: HandConfig,
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
    interrupt: type[BaseException],
) -> None:
    """A KeyboardInterrupt inside a tick (Ctrl-C where no signal handler is installed, or code
    raising it) goes on as an interrupt, exit 130; the summary and the log said 'before the
    first tick: nothing was sent to the hand' after hundreds of ticks of torque. A
    CancelledError raised there (a stage's own asyncio) crashed the command with its
    traceback, exit 1 and no summary, after the loop had stopped the hand as for an
    interrupt (found by an outside audit)."""
    recipe = tmp_path / "hold.yaml"
    recipe.write_text(CLOSE_AND_HOLD_1S)
    out, log = tmp_path / "out.json", tmp_path / "run.mcap"
    _raise_in_the_runner_at(300, interrupt(), monkeypatch)
    code, listener = _cli_run(
        [str(recipe), "--summary-json", str(out), "--log", str(log)], monkeypatch
    )
    listener.shutdown()
    assert code == cli.EXIT_INTERRUPTED
    summary = json.loads(out.read_text())
    assert summary["outcome"] == "interrupted"
    assert summary["ticks"] > 300
    assert "zero torque and a disable were sent" in summary["message"]
    assert "nothing was sent" not in summary["message"]
    assert summary["phases"][-1]["exit"] == f"interrupted: {interrupt.__name__}"
    logged = open_recording(log).json_meta(ch.META_SUMMARY)
    assert logged is not None and logged["outcome"] == "interrupted"
    assert logged["ticks"] == summary["ticks"]
    assert summary["message"] in capsys.readouterr().err
    if interrupt is _SaysNothing:
        assert "(its message could not be made)" in summary["message"]


def test_a_node_not_heard_disabled_after_an_exception_is_said(
    hand: HandConfig, hold: Recipe, tmp_path: Path
) -> None:
    """The stop after an exception listens for the nodes to say they are disabled, as every
    other stop does: a node whose transmitter dies as the exception comes is said (the stop
    ended a tick after the disable and could never say it)."""
    from handctl.sim.faults import NodeSilent

    with bench(hand, hold, tmp_path / "run.mcap") as b:
        due = Trigger(b.runtime, always=False)

        def raise_as_node_2_falls_silent(tk: Tick) -> None:
            if due():
                b.sim.faults.add(NodeSilent(node=2), 0.0)  # from the simulated hand's next tick
                raise ForcedError("forced in a tick hook")

        b.runtime.tick_hooks.append(raise_as_node_2_falls_silent)
        result = asyncio.run(b.runtime.run())
    assert result.outcome is Outcome.SAFETY_STOP
    assert result.disable_unconfirmed.startswith("node 2 (f2) not heard disabled"), (
        result.disable_unconfirmed
    )
    assert "node 1" not in result.disable_unconfirmed


def test_an_exception_before_the_first_tick_is_said_as_handctls_own_fault(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """A bug in the run's set-up (here the estimator's) was a bare traceback: the first line
    now says it is handctl's fault, not the input's, and what to report; exit 1."""
    from handctl.online import estimator

    def broken(*args: Any, **kwargs: Any) -> None:
        raise ForcedError("forced in the estimator's set-up")

    monkeypatch.setattr(estimator.ObjectEstimator, "__init__", broken)
    recipe = tmp_path / "two.yaml"
    recipe.write_text(TWO_OBJECTS)
    assert cli.main(["run", "recipe", str(recipe)]) == cli.EXIT_FAILED
    err = capsys.readouterr().err
    first = next(line for line in err.splitlines() if line.startswith("handctl:"))
    assert first.startswith(
        "handctl: internal error: ForcedError: forced in the estimator's set-up (a bug in "
        "handctl, not in the input"
    )
    assert "Traceback (most recent call last)" in err


@pytest.mark.parametrize("where", ["result", "mujoco_value", "mujoco_fatal"])
def test_the_host_out_of_memory_is_said_as_such(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str], where: str
) -> None:
    """An allocation that fails is the host's limit (``ulimit -v``, a full machine), not a
    bug, nor the input's: after a whole run, the result's copy of the tick statistics under
    a memory limit said "internal error ... a bug in handctl" with a traceback, and MuJoCo's
    own allocation at start-up blamed the hand config (``sim: expected numbers MuJoCo can
    build the simulated hand from``, exit 2) or was an internal error (found by an outside
    audit). One line now, exit 1. The failures are forced where each was seen."""
    import mujoco

    from handctl.online import tickstats

    def no_memory(*args: Any, **kwargs: Any) -> None:
        if where == "result":
            raise MemoryError("Unable to allocate 938. KiB for an array")
        if where == "mujoco_value":
            raise ValueError("Error: engine error: Could not allocate memory")
        raise mujoco.FatalError("Could not allocate memory")

    if where == "result":
        monkeypatch.setattr(tickstats.TickStats, "result", no_memory)
    else:
        monkeypatch.setattr(mujoco.MjModel, "from_xml_string", no_memory)
    recipe = tmp_path / "two.yaml"
    recipe.write_text(TWO_OBJECTS)
    assert cli.main(["run", "recipe", str(recipe), "--max-seconds", "0.3"]) == cli.EXIT_FAILED
    err = capsys.readouterr().err
    first = next(line for line in err.splitlines() if line.startswith("handctl:"))
    assert first.startswith("handctl: error: this host ran out of memory ("), err
    assert "Traceback" not in err


@pytest.mark.parametrize("stage", ["runner", "clock"])
def test_the_rerun_of_a_run_that_stopped_on_an_exception_compares_up_to_it(
    hand: HandConfig, hold: Recipe, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, stage: str
) -> None:
    """The exception came from outside the logged inputs (here a forced one), so the re-run
    does not raise it: it compares every tick before it, bit-exact, and says where it
    stopped comparing (it said MISMATCH on the stop's ticks, exit 1, as for a log altered).
    A clock's exception comes before its tick began: the stop's frames are logged in the
    tick before, and were said as frames the re-run did not send (an outside audit)."""
    from handctl.recording.rerun import rerun

    log = tmp_path / "run.mcap"
    with bench(hand, hold, log) as b:
        due = Trigger(b.runtime, always=False)
        force(stage, b, due, monkeypatch)
        result = asyncio.run(b.runtime.run())
        monkeypatch.undo()
        b.recorder.close(session.summarise_run(result, hand, hold, True, None))
    assert result.exception is not None
    raised = result.exception.tick
    report = rerun(open_recording(log))
    assert report.ok, report.as_dict()
    assert report.compared >= raised - b.runtime.first_send_tick - 1
    said = [n for n in report.notes if "stopped on an exception" in n]
    assert said and f"compared up to tick {raised}" in said[0]
    code = STAGE_FAULTS[stage].name
    assert f"{code}: ForcedError: forced in the {stage} stage" in said[0]


def test_a_note_to_the_log_that_raises_is_the_record_stage_s(
    hand: HandConfig, hold: Recipe, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The recorder's note of a phase's end, written inside ``decide`` when a stop ends the
    phase, raised and was said as SUPERVISOR_EXCEPTION: the stage is named by the code it
    came from, and the recorder is the record stage's (found by an outside audit)."""
    with bench(hand, hold, tmp_path / "run.mcap") as b:
        rt = b.runtime
        due = Trigger(rt, always=False)

        def stop(tk: Tick) -> None:
            if due():
                rt.request_stop("test")

        rt.tick_hooks.append(stop)
        real = b.recorder._event

        def event(kind: int, tick: int, name: str, *args: Any) -> None:
            if name == "phase_end":  # inside the recorder's own note
                raise OSError(errno.EIO, "forced in the recorder's note")
            real(kind, tick, name, *args)

        monkeypatch.setattr(b.recorder, "_event", event)
        result = asyncio.run(rt.run())
        monkeypatch.undo()
    failure = result.exception
    assert failure is not None and failure.code is FaultCode.RECORD_EXCEPTION, failure
    assert result.outcome is Outcome.SAFETY_STOP


def test_a_clock_silent_again_in_the_wait_for_the_disable_is_caught_again(
    hand: HandConfig, hold: Recipe, tmp_path: Path
) -> None:
    """The clock falls silent, gives the stop's ticks, and falls silent again while the run
    waits for the nodes' DISABLED: the watch had fired once and was not armed again, and the
    run hung there, deaf to stop signals (found by an outside audit)."""
    with bench(hand, hold, tmp_path / "run.mcap") as b:
        rt = b.runtime
        rt.clock_silent_s = 0.3
        due = Trigger(rt, always=True)
        real_wait = rt.clock.wait_tick
        calls = [0]

        async def wait_tick() -> Tick:
            if due():
                calls[0] += 1
                # silent at first, then the stop's ticks, then silent for good
                if calls[0] == 1 or calls[0] > ZERO_TICKS_BEFORE_DISABLE + 2:
                    await asyncio.get_running_loop().create_future()
            return await real_wait()

        rt.clock.wait_tick = wait_tick  # type: ignore[method-assign]

        async def bounded() -> Any:
            # seconds of the test's own: a hang is a failure, not a stuck suite
            return await asyncio.wait_for(rt.run(), 60.0)

        result = asyncio.run(bounded())
    assert calls[0] > ZERO_TICKS_BEFORE_DISABLE + 2  # the wait for DISABLED read it again
    assert result.outcome is Outcome.SAFETY_STOP
    failure = result.exception
    assert failure is not None and failure.code is FaultCode.CLOCK_EXCEPTION, failure


def test_a_stage_s_own_runtime_error_from_a_stop_iteration_is_its_own(
    hand: HandConfig, hold: Recipe, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A stage that says ``raise RuntimeError(...) from stop`` over an exhausted iterator was
    reported as the bare StopIteration it chained, at no stage (found by an outside audit):
    only Python's own wording of PEP 479 is unwrapped."""
    with bench(hand, hold, tmp_path / "run.mcap") as b:
        rt = b.runtime
        due = Trigger(rt, always=False)
        assert rt.runner is not None
        real = rt.runner.advance

        def advance(*args: Any, **kwargs: Any) -> None:
            if due():
                try:
                    next(iter(()))
                except StopIteration as stop:
                    raise RuntimeError("calibration table exhausted") from stop
            real(*args, **kwargs)

        monkeypatch.setattr(rt.runner, "advance", advance)
        result = asyncio.run(rt.run())
        monkeypatch.undo()
    failure = result.exception
    assert failure is not None and failure.code is FaultCode.RUNNER_EXCEPTION, failure
    assert failure.type == "RuntimeError" and failure.message == "calibration table exhausted"
