"""A full transmit queue against the runtime and the simulated hand in lockstep: the host's
bus refuses chosen frames as python-can's SocketCAN bus does when the interface's queue is
full (``CanOperationError``, errno ENOBUFS; a real can0 holds 10 frames). Each frame that
matters for stopping or starting the hand is sent again on the ticks after until it goes, and
one that never goes is said as the bus's refusal (found by an outside audit)."""

from __future__ import annotations

import asyncio
import errno
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

import can
import numpy as np
import pytest

from handctl import cli
from handctl.config import HandConfig
from handctl.hand_protocol import protocol_for
from handctl.online.loop import Outcome
from handctl.online.recipes.loader import load_recipe
from handctl.online.recipes.schema import Recipe
from handctl.online.safety.faults import FaultCode
from handctl.protocol import NodeState
from handctl.sim.firmware import FaultBits

from ..dbc import decode
from .rig import CLOSE_AND_HOLD_2S, Rig, rig
from .test_hostile_peer import INJECT_AT, Every, frame, third_peer

ESTOP_ID = 0x000
#: ticks after the first command: inside the hold, torque flowing
AT_TICKS = 1000


@pytest.fixture(scope="module")
def hold(hand: HandConfig, tmp_path_factory: pytest.TempPathFactory) -> Recipe:
    path = tmp_path_factory.mktemp("recipes") / "hold.yaml"
    path.write_text(CLOSE_AND_HOLD_2S)
    return load_recipe(path, hand)


@contextmanager
def queue_full(r: Rig, refuse: Callable[[int], bool]) -> Iterator[list[int]]:
    """The host's transport raises ENOBUFS for each frame whose id ``refuse`` says, as
    SocketCAN does with a full queue; yields the ids of the frames it refused."""
    bus = r.runtime.driver.bus
    real = bus._send_frame  # type: ignore[attr-defined]
    assert real is not None, "the rig's bus sends frame by frame"
    refused: list[int] = []

    def send_frame(frame_id: int, flags: int, data: bytes) -> None:
        if refuse(frame_id):
            refused.append(frame_id)
            raise can.CanOperationError(
                "Failed to transmit: No buffer space available", errno.ENOBUFS
            )
        real(frame_id, flags, data)

    bus._send_frame = send_frame  # type: ignore[attr-defined]
    try:
        yield refused
    finally:
        bus._send_frame = real  # type: ignore[attr-defined]


def estop_at(r: Rig, ticks: int) -> None:
    """The operator's e-stop, ``ticks`` after the first command."""
    runtime = r.runtime

    def hook(tk: object) -> None:
        if runtime.tick - runtime.first_send_tick == ticks:
            runtime.request_estop("operator")

    runtime.tick_hooks.append(hook)


def latched_estop(r: Rig) -> bool:
    return all(
        n.state == int(NodeState.FAULT) and n.fault_bits & int(FaultBits.ESTOP) for n in r.sim.nodes
    )


def test_an_operator_estop_the_bus_refuses_once_goes_on_the_next_tick(
    hand: HandConfig, hold: Recipe
) -> None:
    """The queue is full as the operator's e-stop goes: it went once, and the nodes ended
    DISABLED, not latched in FAULT (ESTOP), with nothing said."""
    with rig(hand, hold) as r:
        estop_at(r, AT_TICKS)
        with queue_full(r, lambda i: i == ESTOP_ID and not refused) as refused:
            result = r.run()
    assert refused == [ESTOP_ID]
    assert result.outcome is Outcome.SAFETY_STOP
    assert result.faults[0].code is FaultCode.ESTOP
    assert r.estops() == 1
    assert latched_estop(r)
    assert "the bus refused the e-stop once (tx_queue_full: " in result.message
    assert "before it went" in result.message


def test_an_operator_estop_the_bus_never_takes_is_said(hand: HandConfig, hold: Recipe) -> None:
    """The e-stop is sent on every tick to the run's end, and that none went is said."""
    with rig(hand, hold) as r:
        estop_at(r, AT_TICKS)
        with queue_full(r, lambda i: i == ESTOP_ID) as refused:
            result = r.run()
    assert len(refused) > 1
    assert r.estops() == 0
    assert result.outcome is Outcome.SAFETY_STOP
    assert "the e-stop could not be sent: the bus refused it" in result.message
    assert "No buffer space available" in result.message
    assert "no node latched FAULT (ESTOP)" in result.message
    # the zero torque and the disable still went
    assert all(n.state == int(NodeState.DISABLED) and not any(n.applied) for n in r.sim.nodes)


def test_a_second_master_s_estop_the_bus_refuses_once_still_latches_the_nodes(
    hand: HandConfig, hold: Recipe
) -> None:
    """A second master on the host's command ids, and the queue full for the e-stop that
    answers it: no e-stop reached the wire and the nodes were left unlatched, for the other
    master to enable again."""
    layout = protocol_for(hand).layout("TorqueCommand", 1)
    with rig(hand, hold) as r, third_peer(r) as peer:
        host_node = r.runtime.driver.nodes[0]

        def second_master() -> None:
            data = layout.encode(host_node.command_counter, [0.5, 0.4, 0.3])
            peer.send(frame(layout.frame_id, data))

        r.sim.faults.add(Every(send=second_master), INJECT_AT)
        with queue_full(r, lambda i: i == ESTOP_ID and not refused) as refused:
            result = r.run()
    assert refused == [ESTOP_ID]
    assert result.faults[0].code is FaultCode.FOREIGN_COMMAND
    assert r.estops() == 1
    assert latched_estop(r)


def refuse_the_disable(r: Rig, times: int | None) -> Callable[[int], bool]:
    """Refuse the NodeCommand frames after the enable (the disable at the end: codec,
    prepared) and the e-stop after them, the first ``times`` frames of them (None: all)."""
    runtime = r.runtime
    commands = {n.layouts.node_command.frame_id for n in runtime.driver.nodes}
    refused = [0]

    def refuse(frame_id: int) -> bool:
        if runtime.first_send_tick < 0 or frame_id not in commands | {ESTOP_ID}:
            return False
        if times is not None and refused[0] >= times:
            return False
        refused[0] += 1
        return True

    return refuse


def test_a_disable_the_bus_refuses_at_the_end_goes_on_a_later_tick(
    hand: HandConfig, hold: Recipe
) -> None:
    """The queue is full as the recipe ends: the disable (codec, then prepared) and the
    e-stop after it, all within microseconds, were refused, nothing was sent in the wait
    for the nodes' DISABLED, and the run ended "completed", exit 0, the nodes ENABLED. It is
    sent again on the next tick of the wait, and goes."""
    with rig(hand, hold) as r:
        nodes = len(r.runtime.driver.nodes)
        with queue_full(r, refuse_the_disable(r, 2 * nodes + 1)) as refused:
            result = r.run()
    assert len(refused) == 2 * nodes + 1
    assert r.estops() == 0
    assert result.outcome is Outcome.COMPLETED, result.message
    assert result.disable_unconfirmed == ""
    assert [n.state for n in r.sim.nodes] == [int(NodeState.DISABLED)] * nodes


def test_a_disable_the_bus_never_takes_is_a_safety_stop(hand: HandConfig, hold: Recipe) -> None:
    """The disable and the e-stop after it refused on every try: the nodes may be ENABLED,
    the run is not "completed" (exit 3: a bus that failed during a run, README)."""
    with rig(hand, hold) as r, queue_full(r, refuse_the_disable(r, None)) as refused:
        result = r.run()
    assert len(refused) > 2 * len(r.sim.nodes) + 1  # sent again in the wait
    assert r.estops() == 0
    assert result.outcome is Outcome.SAFETY_STOP
    [fault] = result.faults
    assert fault.code is FaultCode.BUS_ERROR
    assert fault.detail.startswith("the bus refused the disable at the end ")
    assert "(tx_queue_full: Failed to transmit: No buffer space available" in fault.detail
    assert "and the e-stop after it, on every tick of the wait" in fault.detail
    assert "--reset-node-faults" in fault.detail
    assert "the bus refused the disable at the end" in result.disable_unconfirmed
    assert cli._outcome_exit_code(result, {}) == cli.EXIT_SAFETY_STOP


def refuse_the_enable(r: Rig, times: int | None) -> Callable[[int], bool]:
    """Refuse the NodeCommand frames before the first running tick (the enable), the first
    ``times`` of them (None: every NodeCommand frame, the disable at the end too)."""
    runtime = r.runtime
    commands = {n.layouts.node_command.frame_id for n in runtime.driver.nodes}
    refused = [0]

    def refuse(frame_id: int) -> bool:
        if frame_id not in commands or (times is not None and refused[0] >= times):
            return False
        refused[0] += 1
        return True

    return refuse


def test_an_enable_the_bus_refuses_is_sent_again_until_it_goes(
    hand: HandConfig, hold: Recipe
) -> None:
    """The queue is full as the nodes are enabled: the enable went once, and the run
    stopped at the enable deadline blaming the nodes ('nodes not ENABLED in time: node 1
    DISABLED ...')."""
    with rig(hand, hold) as r:
        nodes = len(r.runtime.driver.nodes)
        with queue_full(r, refuse_the_enable(r, nodes)) as refused:
            result = r.run()
    assert len(refused) == nodes
    assert result.outcome is Outcome.COMPLETED, result.message
    assert [p["exit"] for p in result.phases] == ["timeout", "timeout"]


def test_an_enable_the_bus_never_takes_is_said_as_the_bus_s(hand: HandConfig, hold: Recipe) -> None:
    """Sent again on every tick of the enabling, refused every time: the run stops at the
    enable deadline on the bus (BUS_ERROR, naming what the bus said), not on nodes 'not
    ENABLED in time', and no torque went."""
    with rig(hand, hold) as r, queue_full(r, refuse_the_enable(r, None)) as refused:
        result = r.run()
    deadline = r.runtime.supervisor.enable_deadline_ticks
    assert len(refused) >= deadline * len(r.sim.nodes)  # sent again on every tick
    assert result.outcome is Outcome.SAFETY_STOP
    first = result.faults[0]
    assert first.code is FaultCode.BUS_ERROR, result.message
    assert first.detail.startswith(
        "the bus refused the enable of node 1 (f1), node 2 (f2), node 3 (f3) "
    )
    assert "(tx_queue_full: Failed to transmit: No buffer space available" in first.detail
    assert "it never left the host" in first.detail
    assert "not ENABLED in time" not in result.message
    assert not r.commands().any()


def runner_raises_at(r: Rig, ticks: int) -> None:
    """The recipe's runner raises ``ticks`` after the first command, once: the stop after an
    exception, which sends its frames without the codec (``Runtime._stop_after_exception``)."""
    runtime = r.runtime
    runner = runtime.runner
    assert runner is not None
    real = runner.advance
    fired: list[int] = []

    def advance(*args: object, **kwargs: object) -> object:
        if runtime.tick - runtime.first_send_tick >= ticks and not fired:
            fired.append(runtime.tick)
            raise RuntimeError("forced in the runner")
        return real(*args, **kwargs)  # type: ignore[arg-type]

    runner.advance = advance  # type: ignore[method-assign,assignment]


def test_a_disable_the_bus_refuses_after_an_exception_goes_on_a_later_tick(
    hand: HandConfig, hold: Recipe
) -> None:
    """The queue is full as the stop after an exception disables the nodes: its disable and
    the e-stop after it went once each, were refused, and the nodes were left ENABLED (at
    zero torque) for their watchdog to latch FAULT (TIMEOUT), nothing said. It is sent again
    on the ticks after, as at the end of any other run, and goes."""
    with rig(hand, hold) as r:
        nodes = len(r.runtime.driver.nodes)
        runner_raises_at(r, AT_TICKS)
        with queue_full(r, refuse_the_disable(r, nodes + 1)) as refused:
            result = r.run()
    assert len(refused) == nodes + 1
    assert result.outcome is Outcome.SAFETY_STOP
    assert result.exception is not None
    assert r.estops() == 0
    assert result.disable_unconfirmed == ""
    assert "the bus refused the disable at the end once (tx_queue_full: " in result.message
    assert "before it went" in result.message
    assert [n.state for n in r.sim.nodes] == [int(NodeState.DISABLED)] * nodes


def test_a_disable_the_bus_never_takes_after_an_exception_is_said(
    hand: HandConfig, hold: Recipe
) -> None:
    """Refused on every try after an exception: sent again through the wait, and the
    message says the nodes may be ENABLED until their watchdog acts."""
    with rig(hand, hold) as r:
        nodes = len(r.runtime.driver.nodes)
        runner_raises_at(r, AT_TICKS)
        with queue_full(r, refuse_the_disable(r, None)) as refused:
            result = r.run()
    assert len(refused) > 2 * (nodes + 1)  # sent again after the first tick's try
    assert result.outcome is Outcome.SAFETY_STOP
    assert r.estops() == 0
    assert "and the e-stop after it, on every tick of the wait" in result.message
    assert "the bus refused the disable at the end" in result.disable_unconfirmed
    assert cli._outcome_exit_code(result, {}) == cli.EXIT_SAFETY_STOP


#: One phase whose first joint ramps at its rate limit (20 N·m/s: 0.1 N·m in 0.005 s).
STEP_1S = """
recipe: step
phases:
  - name: step
    torques: [0.1, 0.05, 0.03, 0.06, 0.05, 0.03, -0.06, -0.05, -0.03]
    ramp_s: 0.005
    max_s: 0.2
    on_timeout: next
"""


def test_a_command_the_bus_refuses_is_not_stepped_over_by_the_next(
    hand: HandConfig, tmp_path: Path
) -> None:
    """The queue is full for node 1's torque command on two ticks in a row while its
    first joint ramps at the rate limit: the frame after them stepped that joint three
    rate steps at once (the limiter went on from torques that never left the host). Each
    frame the node gets now is within one rate step of the one before."""
    path = tmp_path / "step.yaml"
    path.write_text(STEP_1S)
    recipe = load_recipe(path, hand)
    step = hand.joints[0].rate_limit * hand.bus.period_s
    with rig(hand, recipe) as r:
        runtime = r.runtime
        command_id = runtime.driver.nodes[0].layouts.command.frame_id

        def refuse(frame_id: int) -> bool:
            return frame_id == command_id and 2 <= runtime.tick - runtime.first_send_tick <= 3

        with queue_full(r, refuse) as refused:
            result = r.run()
    assert refused == [command_id, command_id]
    assert result.outcome is Outcome.COMPLETED, result.message
    first = [decode(i, d)["Torque1"] for i, d in r.wire if i == command_id]
    assert max(first) == pytest.approx(0.1)  # the ramp went through the refusals
    steps = np.diff([0.0, *first])
    assert steps.max() <= step + 1e-9, steps[:12]


def test_a_run_whose_bus_refused_commands_reruns_bit_exact(
    hand: HandConfig, tmp_path: Path
) -> None:
    """The joints of a refused command keep what their node holds: the re-run, whose bus
    answers each send as the run's did, comes to the same applied torques tick by tick."""
    from handctl import session
    from handctl.recording import channels as ch
    from handctl.recording.reader import check_format, iter_decoded, open_recording
    from handctl.recording.rerun import rerun

    from .test_tick_exception import bench

    path = tmp_path / "step.yaml"
    path.write_text(STEP_1S)
    recipe = load_recipe(path, hand)
    log = tmp_path / "run.mcap"
    with bench(hand, recipe, log) as b:
        runtime = b.runtime
        command_id = runtime.driver.nodes[0].layouts.command.frame_id

        def refuse(frame_id: int) -> bool:
            return frame_id == command_id and 2 <= runtime.tick - runtime.first_send_tick <= 3

        with queue_full(b, refuse) as refused:  # type: ignore[arg-type]
            result = asyncio.run(runtime.run())
        b.recorder.close(session.summarise_run(result, hand, recipe, True, None))
    assert len(refused) == 2
    assert result.outcome is Outcome.COMPLETED, result.message
    recording = open_recording(log)
    # the refused frames are logged on /can/tx, ok false, and counted in the end record's
    # frames: the log reads as the healthy one it is
    check_format(recording)
    sent = [m["ok"] for _, _, m in iter_decoded(recording, (ch.CAN_TX,))]
    assert sent.count(False) == 2
    report = rerun(recording)
    assert report.ok, report.as_dict()
    assert report.compared > 3
