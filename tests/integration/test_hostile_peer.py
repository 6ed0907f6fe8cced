"""A third peer on the hand's bus, against the runtime and the simulated hand in lockstep: a
python-can bus of its own on the rig's virtual channel that sends what a hostile or confused
participant would. Each attack is stopped (or cannot pass), and the wire carries zero within
two ticks of detection."""

from __future__ import annotations

import re
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import ClassVar

import can
import numpy as np
import pytest

from handctl import cli
from handctl.config import HandConfig
from handctl.hand_protocol import protocol_for
from handctl.online.clock import Tick
from handctl.online.loop import ZERO_TICKS_BEFORE_DISABLE, Outcome
from handctl.online.recipes.loader import load_recipe
from handctl.online.recipes.schema import Recipe
from handctl.online.safety.faults import FaultCode
from handctl.protocol import Layout, NodeState
from handctl.sim.faults import Injector, SimContext
from handctl.sim.firmware import FaultBits

from ..conftest import ROOT
from .another_host import commanding
from .rig import CLOSE_AND_HOLD_2S, Rig, rig, stopped_at_once

INJECT_AT = 1.0  # s of simulated time: inside the hold phase
INJECT_TICK = round(INJECT_AT / 0.001)
HOST_IDS = {0x000, 0x011, 0x012, 0x013, 0x101, 0x102, 0x103}


@pytest.fixture(scope="module")
def hold(hand: HandConfig, tmp_path_factory: pytest.TempPathFactory) -> Recipe:
    path = tmp_path_factory.mktemp("recipes") / "hold.yaml"
    path.write_text(CLOSE_AND_HOLD_2S)
    return load_recipe(path, hand)


@contextmanager
def third_peer(r: Rig) -> Iterator[can.BusABC]:
    """A plain python-can bus on the rig's channel: neither the host nor the hand."""
    bus = can.Bus(interface="virtual", channel=r.sniffer.spec.channel)
    try:
        yield bus
    finally:
        bus.shutdown()


@dataclass(eq=False)
class Every(Injector):
    """Not a fault of the hand: only the clock of the third peer, which sends from its own
    bus once every simulated tick while this is on (in lockstep the tests have no other)."""

    periodic: ClassVar[bool] = True
    send: Callable[[], None] = field(default=lambda: None)

    def tick(self, ctx: SimContext, now_ns: int) -> None:
        self.send()


def deaf_to(r: Rig, node_id: int, command: str) -> None:
    """Simulated node ``node_id`` drops every NodeCommand ``command`` (``enable``,
    ``disable``): firmware that ignores it, or an interlock that keeps it from acting."""
    from handctl.protocol import NODE_COMMANDS

    node = r.sim.nodes[node_id - 1]
    layout = protocol_for(r.hand).layout("NodeCommand", node_id)
    obey = node._apply

    def deaf(lay: Layout, data: bytes, now_ns: int) -> None:
        if lay is layout and layout.decode(data)[1][0] == NODE_COMMANDS[command]:
            return
        obey(lay, data, now_ns)

    setattr(node, "_apply", deaf)  # noqa: B010 (a method replaced on one instance)


def frame(frame_id: int, data: bytes) -> can.Message:
    return can.Message(arbitration_id=frame_id, data=data, is_extended_id=False, is_fd=True)


def test_a_second_master_on_the_host_s_command_ids_is_stopped_at_once(
    hand: HandConfig, hold: Recipe
) -> None:
    """Another sender puts TorqueCommand_1 frames on the bus, each a counter ahead of the host,
    with 3 N·m: node 1 took them and rejected the host's as repeats. The host counted them as
    unexpected ids and went on until the node latched a fault of its own (10 ticks on)."""
    layout = protocol_for(hand).layout("TorqueCommand", 1)
    with rig(hand, hold) as r, third_peer(r) as peer:
        host_node = r.runtime.driver.nodes[0]

        forged: list[tuple[int, bytes]] = []

        def second_master() -> None:
            data = layout.encode(host_node.command_counter, [3.0, 3.0, 3.0])
            peer.send(frame(layout.frame_id, data))
            forged.append((layout.frame_id, data))

        r.sim.faults.add(Every(send=second_master), INJECT_AT)
        result = r.run()
        for sent in forged:  # the sniffer heard them too: the host's frames are judged
            r.wire.remove(sent)
        tick = stopped_at_once(r, result, FaultCode.FOREIGN_COMMAND)
        assert tick == INJECT_TICK
        assert "TorqueCommand id 0x101" in result.faults[0].detail
        assert FaultCode.NODE_FAULT not in {f.code for f in result.faults}
        # zero torque and a disable are two commands among the other sender's: the host
        # e-stops as well, which every node latches whatever it is told next
        assert r.estops() >= 1
        assert [n.state for n in r.sim.nodes] == [int(NodeState.FAULT)] * 3
        assert all(n.fault_bits & int(FaultBits.ESTOP) for n in r.sim.nodes)


def test_a_second_master_in_the_zero_ticks_after_the_recipe_is_stopped_too(
    hand: HandConfig, hold: Recipe
) -> None:
    """The recipe done, the supervisor idle, the nodes still enabled for the zero ticks before
    the disable: another sender's 0.3 N·m a counter ahead of the host was taken by the nodes
    for 4 ms and the run said completed, exit 0. It is the same second master as mid-run."""
    from handctl.online.safety.supervisor import State

    layouts = [protocol_for(hand).layout("TorqueCommand", n) for n in (1, 2, 3)]
    with rig(hand, hold) as r, third_peer(r) as peer:
        runtime = r.runtime
        forged: list[tuple[int, bytes]] = []

        def second_master() -> None:
            if runtime.supervisor.state is not State.IDLE or runtime.runner is None:
                return
            if not runtime.runner.done or forged:
                return
            for layout, node in zip(layouts, runtime.driver.nodes, strict=True):
                data = layout.encode(node.command_counter, [0.3, 0.3, 0.3])
                peer.send(frame(layout.frame_id, data))
                forged.append((layout.frame_id, data))

        r.sim.faults.add(Every(send=second_master), INJECT_AT)
        result = r.run()
    assert forged, "the recipe never ended with the nodes enabled"
    assert result.outcome is Outcome.SAFETY_STOP, result.message
    assert FaultCode.FOREIGN_COMMAND in {f.code for f in result.faults}
    assert r.estops() >= 1
    assert all(n.fault_bits & int(FaultBits.ESTOP) for n in r.sim.nodes)


def test_a_second_master_heard_at_start_up_sends_nothing(hand: HandConfig) -> None:
    layout = protocol_for(hand).layout("NodeCommand", 2)
    with rig(hand, None, max_seconds=1.0) as r, third_peer(r) as peer:
        enable = layout.encode(0, [1])

        def second_master() -> None:
            peer.send(frame(layout.frame_id, enable))

        r.sim.faults.add(Every(send=second_master), 0.0, 0.001)
        result = r.run()
        r.wire.remove((layout.frame_id, enable))  # the sniffer heard it too
    assert result.outcome is Outcome.STARTUP_FAILED, [str(f) for f in result.faults]
    assert [f.code for f in result.faults] == [FaultCode.FOREIGN_COMMAND]
    assert "NodeCommand id 0x012" in result.message
    assert not [fid for fid, _ in r.wire if fid in HOST_IDS]  # the host sent nothing


@pytest.mark.parametrize("version", [1, 3])
def test_a_node_that_changes_its_protocol_mid_run_is_stopped(
    hand: HandConfig, hold: Recipe, version: int
) -> None:
    """Node 2's Status says another protocol from 1 s on (its next Status, within 100 ms).
    The start-up refuses such a node; mid-run the host took the new version in and the run
    ended COMPLETED."""
    with rig(hand, hold) as r:

        def switch(tk: object) -> None:
            if r.runtime.tick == INJECT_TICK:
                r.sim.nodes[1].protocol_version = version

        r.runtime.tick_hooks.append(switch)
        result = r.run()
        tick = stopped_at_once(r, result, FaultCode.NODE_CONTRADICTION)
        assert INJECT_TICK < tick <= INJECT_TICK + 101  # Status: every 100 ms
        detail = result.faults[0].detail
        assert (
            f"node 2 (f2): Status says handctl protocol {version}, this host protocol 2" in detail
        )
        assert [n.state for n in r.sim.nodes] == [int(NodeState.DISABLED)] * 3


def twin_feedback(hand: HandConfig, counter: int) -> can.Message:
    """A Feedback frame of node 1 from a twin of it: every joint at rest, DISABLED."""
    layout = protocol_for(hand).layout("Feedback", 1)
    joints = (len(layout.signals) - 2) // 2
    values = [0.0] * (2 * joints) + [int(NodeState.DISABLED), 0]
    return frame(layout.frame_id, layout.encode(counter, values))


def test_a_second_hand_on_the_bus_at_start_up_is_refused_before_anything_is_enabled(
    hand: HandConfig,
) -> None:
    """A node 1 twin (a second hand on the same bus, or a stream replayed from a log) sends
    Feedback of its own, counting on its own, from before the start-up: the host's view of
    node 1 rejects nearly every frame as a counter skip. Before, the start-up had heard one
    good frame and enabled the nodes, and the run stopped on FEEDBACK_TIMEOUT with them
    enabled; an enable on a bus with two hands reaches both."""
    disabled = int(NodeState.DISABLED)
    with rig(hand, None, max_seconds=1.0) as r, third_peer(r) as peer:
        counter = [100]

        def twin() -> None:
            counter[0] = (counter[0] + 1) % 256
            peer.send(twin_feedback(hand, counter[0]))

        r.sim.faults.add(Every(send=twin), 0.0)
        result = r.run()
    assert result.outcome is Outcome.STARTUP_FAILED, result.message
    assert [f.code for f in result.faults] == [FaultCode.REJECT_RATE]
    assert "node 1 (f1)" in result.message and "rejected" in result.message
    assert not [fid for fid, _ in r.wire if fid in HOST_IDS]  # the host sent nothing
    assert [n.state for n in r.sim.nodes] == [disabled] * 3


def test_a_few_rejected_frames_at_start_up_delay_the_enable_by_a_reject_window(
    hand: HandConfig,
) -> None:
    """Three frames of a node 1 twin in the first ticks cost a few rejects, within the
    allowance: the start-up listens on for a whole reject window after the first, and then
    enables the nodes as ever."""
    window = round(hand.safety.reject_window_s / hand.bus.period_s)
    with rig(hand, None, max_seconds=0.5) as r, third_peer(r) as peer:

        def twin() -> None:
            peer.send(twin_feedback(hand, 7))

        r.sim.faults.add(Every(send=twin), 0.0, 0.003)
        result = r.run()
        first_send = r.runtime.first_send_tick
    assert result.faults == [], result.message
    assert (
        0
        < result.node_rejects["counter_skip"] + result.node_rejects["counter_repeat"]
        <= (hand.safety.max_rejects_in_window)
    )
    assert window <= first_send <= window + 5


@pytest.mark.parametrize("transport", ["virtual", "unix"])
def test_a_run_on_a_bus_another_host_commands_is_refused_before_anything(
    hand: HandConfig, hold: Recipe, tmp_path: Path, transport: str
) -> None:
    """A second run or jog beside one took real-time priority on the first's CPU for its
    timing check before its driver heard the other host and refused: the first lost its ticks
    and latched every node's TIMEOUT (found by an outside audit). Now it listens first, and
    refuses as a bus in use: no timing check, nothing sent. On a unix bus too, where a sender
    lists a new participant only every 50 ms (a 20 ms listen missed one run in two)."""
    import uuid

    from handctl.errors import BusError
    from handctl.session import RunRequest, run_recipe

    spec = f"virtual:other-host-{uuid.uuid4().hex}"
    if transport == "unix":
        (tmp_path / "bus").mkdir()
        spec = f"unix:{tmp_path / 'bus'}"
    layout = protocol_for(hand).layout("TorqueCommand", 1)
    with commanding(spec, hand, layout, [0.0] * 3):  # a host's torque command every tick
        for _ in range(3):  # each time, not by luck
            with pytest.raises(BusError, match="another host is commanding this hand") as caught:
                run_recipe(RunRequest(hand=hand, recipe=hold, bus=spec))
            assert "TorqueCommand to node 1 (f1), id 0x101" in str(caught.value)


def test_a_node_that_goes_on_saying_enabled_after_the_disable_gets_the_e_stop(
    hand: HandConfig, hold: Recipe
) -> None:
    """A node whose firmware ignored the disable was only warned about, and left ENABLED for
    its watchdog (found by an outside audit): the host now sends the e-stop, which every node
    honours, once that node's Feedback still says ENABLED after it had the disable to act on.
    The nodes that obeyed are no reason for it: see the test above, where none is sent."""
    from handctl.sim.firmware import FaultBits as Bits

    with rig(hand, hold, max_seconds=0.5) as r:
        stubborn = r.sim.nodes[1]
        deaf_to(r, 2, "disable")
        result = r.run()
        r.sim.step()  # the nodes take the e-stop on their next tick
    assert result.outcome is Outcome.INTERRUPTED, result.message  # the rig's tick budget
    said = result.disable_unconfirmed
    assert said.startswith("node 2 (f2) not heard disabled"), said
    assert "node 2 (f2) went on saying ENABLED after the disable: the e-stop was sent" in said
    assert r.estops() == 1
    assert stubborn.state == int(NodeState.FAULT) and stubborn.fault_bits & Bits.ESTOP


def test_a_node_that_disobeys_the_disable_with_a_feedback_lost_is_still_said_to(
    hand: HandConfig, hold: Recipe
) -> None:
    """As above, with one of the deaf node's Feedback frames lost on the bus during the wait
    for its DISABLED: the one skipped counter made it read as a replayed or forged stream
    ("could not be confirmed disabled: frames of it were being rejected"), when it is a node
    that disobeyed (found by an outside audit). A lost frame costs one skip, nothing more."""
    from handctl.sim.faults import DropFeedback

    with rig(hand, hold, max_seconds=0.5) as r:
        deaf_to(r, 2, "disable")
        rt = r.runtime
        lost: list[int] = []

        def lose_one(tk: Tick) -> None:
            if rt.stop_requested and not lost:
                lost.append(tk.tick)
                # in the wait for DISABLED: the zero ticks, the disable, then some periods
                period = r.hand.bus.period_s
                at = tk.now_ns * 1e-9 + (ZERO_TICKS_BEFORE_DISABLE + 4) * period
                r.sim.faults.add(DropFeedback(node=2), at, at)

        rt.tick_hooks.append(lose_one)
        result = r.run()
        skipped = rt.driver.nodes[1].rejects.as_dict()["counter_skip"]
    assert lost and skipped == 1, (lost, skipped)
    said = result.disable_unconfirmed
    assert "node 2 (f2) went on saying ENABLED after the disable: the e-stop was sent" in said
    assert "could not be confirmed" not in said, said
    assert r.estops() == 1


def _sniffed(peer: can.BusABC, last: dict[int, int], heard: dict[int, bytes] | None = None) -> None:
    """The latest counter heard on each identifier in ``last`` (and the frame, in ``heard``):
    what a peer that can compute the CRC (no secret) needs to put a frame into a stream the
    host accepts."""
    while (msg := peer.recv(timeout=0)) is not None:
        if msg.arbitration_id in last:
            last[msg.arbitration_id] = msg.data[1]
            if heard is not None:
                heard[msg.arbitration_id] = bytes(msg.data)


def _uptime(layout: Layout, heard: dict[int, bytes]) -> int:
    """The uptime the node's own last Heartbeat said: a forged one that went back would be
    taken for a reboot, another fault than the one under test."""
    return int(layout.decode(heard[layout.frame_id])[1][1])


def _next(last: dict[int, int], frame_id: int) -> int:
    last[frame_id] = (last[frame_id] + 1) & 0xFF
    return last[frame_id]


def test_a_forged_heartbeat_does_not_arm_a_node_that_never_enabled(
    hand: HandConfig, hold: Recipe
) -> None:
    """Node 2 drops the enable (an interlock, say): its Feedback says DISABLED on every tick.
    A Heartbeat ENABLED after its frames each tick (a forgery, or firmware that reports the
    state asked for) armed the torque at once, and a zero-torque run completed on it (found
    by an outside audit). The torque is armed on each node's own Feedback now, and a
    DISABLED more than a node tick after the ENABLED is the node's present: nothing but zero
    reaches the bus, and the run stops on the contradiction."""
    heartbeat = protocol_for(hand).layout("Heartbeat", 2)
    with rig(hand, hold, max_seconds=1.0) as r, third_peer(r) as peer:
        deaf_to(r, 2, "enable")
        last = {heartbeat.frame_id: -1}
        heard: dict[int, bytes] = {}
        forged: list[tuple[int, bytes]] = []

        def forge() -> None:
            _sniffed(peer, last, heard)
            if r.runtime.first_send_tick < 0 or last[heartbeat.frame_id] < 0:
                return
            up = _uptime(heartbeat, heard)
            data = heartbeat.encode(_next(last, heartbeat.frame_id), (1, up))
            peer.send(frame(heartbeat.frame_id, data))
            forged.append((heartbeat.frame_id, data))

        r.sim.faults.add(Every(send=forge), 0.0)
        result = r.run()
    assert forged
    assert result.outcome is Outcome.SAFETY_STOP, result.message
    first = result.faults[0]
    assert first.code is FaultCode.NODE_CONTRADICTION, [str(f) for f in result.faults]
    assert "node 2 (f2): Heartbeat says ENABLED after DISABLED" in first.detail
    assert first.tick - r.runtime.first_send_tick <= 5
    assert [(a, b) for _, a, _, b in result.supervisor_history][:2] == [
        ("idle", "enabling"),
        ("enabling", "faulted"),
    ]
    assert not np.any(r.commands())


def test_a_forged_disabled_after_the_disable_does_not_hide_a_node_that_ignored_it(
    hand: HandConfig, hold: Recipe
) -> None:
    """Node 2 ignores the disable; one Heartbeat DISABLED after it (a forgery, or firmware
    that reports the state asked for) was taken as the node's word: the run said completed,
    no e-stop went, and the node latched TIMEOUT on its own (found by an outside audit). The
    disable is confirmed by each node's own Feedback now."""
    wire_protocol = protocol_for(hand)
    heartbeat = wire_protocol.layout("Heartbeat", 2)
    command = wire_protocol.layout("NodeCommand", 2)
    with rig(hand, hold, max_seconds=0.5) as r, third_peer(r) as peer:
        stubborn = r.sim.nodes[1]
        deaf_to(r, 2, "disable")
        last = {heartbeat.frame_id: -1, command.frame_id: -1}
        heard: dict[int, bytes] = {}
        forged: list[bytes] = []

        def forge_once() -> None:
            _sniffed(peer, last, heard)
            if forged or last[command.frame_id] < 0 or r.runtime.runner is None:
                return
            if not r.runtime.runner.done:
                return  # the enable's NodeCommand was heard; wait for the disable's
            if r.runtime.driver.nodes[1].state != int(NodeState.ENABLED):
                return
            up = _uptime(heartbeat, heard)
            data = heartbeat.encode(_next(last, heartbeat.frame_id), (0, up))
            peer.send(frame(heartbeat.frame_id, data))
            forged.append(data)

        r.sim.faults.add(Every(send=forge_once), 0.0)
        result = r.run()
        r.sim.step()  # the nodes take the e-stop on their next tick
    assert forged
    said = result.disable_unconfirmed
    assert said.startswith("node 2 (f2) not heard disabled"), said
    assert "node 2 (f2) went on saying ENABLED after the disable: the e-stop was sent" in said
    assert r.estops() == 1
    assert stubborn.state == int(NodeState.FAULT)


def test_a_state_the_protocol_does_not_define_does_not_hide_a_fault(
    hand: HandConfig, hold: Recipe
) -> None:
    """Node 2 latches FAULT (SENSOR); after its frames each tick, a Status of state 3 (which
    the protocol does not define) and a Heartbeat ENABLED. The undefined state took the
    FAULT's place and the ENABLED was then believed: the fault went unseen until the TDT
    check stopped the run 55 ms later on a ramp (found by an outside audit)."""
    wire_protocol = protocol_for(hand)
    status = wire_protocol.layout("Status", 2)
    heartbeat = wire_protocol.layout("Heartbeat", 2)
    with rig(hand, hold) as r, third_peer(r) as peer:
        node = r.sim.nodes[1]
        last = {status.frame_id: -1, heartbeat.frame_id: -1}
        heard: dict[int, bytes] = {}

        def fault_and_hide() -> None:
            _sniffed(peer, last, heard)
            if node.state != int(NodeState.FAULT):
                node._fault(int(FaultBits.SENSOR))  # said by its frames of the next tick
                return
            if min(last.values()) < 0:
                return
            hidden = (3, 0, 0, 0, 0, 0, wire_protocol.version, 1, 0, 0)
            peer.send(frame(status.frame_id, status.encode(_next(last, status.frame_id), hidden)))
            up = (1, _uptime(heartbeat, heard))
            peer.send(
                frame(heartbeat.frame_id, heartbeat.encode(_next(last, heartbeat.frame_id), up))
            )

        r.sim.faults.add(Every(send=fault_and_hide), INJECT_AT)
        result = r.run()
    # the FAULT and the undefined state are heard in the same tick: two immediate stops
    tick = stopped_at_once(r, result, FaultCode.NODE_CONTRADICTION)
    assert tick <= INJECT_TICK + 1
    assert "Status says state 3, which the protocol does not define" in result.faults[0].detail
    said = {f.code: f for f in result.faults}
    assert said[FaultCode.NODE_FAULT].tick == tick
    assert "SENSOR" in said[FaultCode.NODE_FAULT].detail


def test_a_forged_feedback_a_counter_ahead_is_a_second_sender(
    hand: HandConfig, hold: Recipe
) -> None:
    """One Feedback of node 1 every tenth tick, a counter ahead of the node, with f1_j1 at
    1.8 rad: the host believed it, rejected the node's own frame of that counter as a
    repeat, and stayed under the reject-rate limit, so the estimator, the exits and the
    guard read the forged angle on 380 ticks of a completed run (found by an outside audit).
    A counter with two contents is two senders: stopped at the node's next frame."""
    layout = protocol_for(hand).layout("Feedback", 1)
    joints = (len(layout.signals) - 2) // 2
    values = [0.0] * joints + [1.8] + [0.0] * (joints - 1) + [int(NodeState.ENABLED), 0]
    with rig(hand, hold) as r, third_peer(r) as peer:
        last = {layout.frame_id: -1}
        sent_at: list[int] = []

        def forge() -> None:
            _sniffed(peer, last)
            if last[layout.frame_id] < 0 or r.runtime.tick % 10:
                return
            data = layout.encode(_next(last, layout.frame_id), values)
            peer.send(frame(layout.frame_id, data))
            sent_at.append(r.runtime.tick)

        r.sim.faults.add(Every(send=forge), INJECT_AT)
        result = r.run()
    tick = stopped_at_once(r, result, FaultCode.NODE_CONTRADICTION)
    assert sent_at and tick == sent_at[0] + 1, (tick, sent_at)
    assert f"two Feedback frames (id 0x{layout.frame_id:03X})" in result.faults[0].detail


def test_a_forged_feedback_disabled_after_the_disable_does_not_hide_a_node_that_ignored_it(
    hand: HandConfig, hold: Recipe
) -> None:
    """Node 2 ignores the disable; one Feedback DISABLED with its next counter, right after
    the disable: the wait took it for the node's word at once and ended, the node's own
    frame of that counter (ENABLED) came a tick too late to contradict it, the run said
    completed, no e-stop went, and node 2 stayed ENABLED (found by an outside audit). A
    DISABLED is confirmed by a later Feedback now, and the contradiction is heard."""
    wire_protocol = protocol_for(hand)
    feedback = wire_protocol.layout("Feedback", 2)
    command = wire_protocol.layout("NodeCommand", 2)
    with rig(hand, hold, max_seconds=0.5) as r, third_peer(r) as peer:
        stubborn = r.sim.nodes[1]
        deaf_to(r, 2, "disable")
        last = {feedback.frame_id: -1, command.frame_id: -1}
        heard: dict[int, bytes] = {}
        commands: list[int] = []
        forged: list[bytes] = []

        def forge_once() -> None:
            before = last[command.frame_id]
            _sniffed(peer, last, heard)
            if last[command.frame_id] != before:
                commands.append(last[command.frame_id])
            if forged or len(commands) < 2 or feedback.frame_id not in heard:
                return  # the enable, then the disable
            values = list(feedback.decode(heard[feedback.frame_id])[1])
            values[-2] = int(NodeState.DISABLED)
            data = feedback.encode(_next(last, feedback.frame_id), values)
            peer.send(frame(feedback.frame_id, data))
            forged.append(data)

        r.sim.faults.add(Every(send=forge_once), 0.0)
        result = r.run()
        r.sim.step()  # the nodes take the e-stop on their next tick
    assert forged
    assert result.outcome is Outcome.SAFETY_STOP, result.message
    first = result.faults[0]
    assert first.code is FaultCode.NODE_CONTRADICTION, [str(f) for f in result.faults]
    assert first.detail.startswith("after this run's disable, node 2 (f2): two Feedback")
    said = result.disable_unconfirmed
    assert said.startswith("node 2 (f2) not heard disabled"), said
    assert "node 2 (f2) contradicted after the disable" in said
    assert r.estops() == 1
    assert stubborn.state == int(NodeState.FAULT)


def test_a_node_whose_stream_was_replayed_is_not_blamed_for_the_replay_s_enabled(
    hand: HandConfig, hold: Recipe
) -> None:
    """Node 1's Feedback replayed 50 ms late: the run stops on REJECT_RATE, and after the
    disable the replayed frames still say ENABLED. The e-stop is the safe answer, but the
    node that obeyed the disable was blamed for going on saying ENABLED, in frames the host
    had judged untrustworthy (found by an outside audit). It is said as what it is."""
    from handctl.sim import faults as inj

    with rig(hand, hold) as r:
        r.sim.faults.add(inj.ReplayFrames(node=1, delay=0.05), INJECT_AT)
        result = r.run()
    assert result.faults[0].code is FaultCode.REJECT_RATE, [str(f) for f in result.faults]
    said = result.disable_unconfirmed
    assert "went on saying ENABLED" not in said, said
    assert (
        "node 1 (f1) could not be confirmed disabled: frames of it were being rejected after "
        "the disable ("
    ) in said, said
    assert said.endswith(
        "so the ENABLED heard may be replayed or forged, not the node's own: the e-stop was sent"
    ), said
    assert r.estops() == 1


@pytest.mark.parametrize(("frame_id", "stops"), [(0x055, False), (0x101, True)])
def test_a_remote_frame_is_re_run_as_the_run_heard_it(
    hand: HandConfig, hold: Recipe, tmp_path: Path, frame_id: int, stops: bool
) -> None:
    """One remote frame (RTR) from a third peer, on a foreign id or on the host's
    TorqueCommand_1 id (FOREIGN_COMMAND, row 102). The log kept the event but not its id,
    so the re-run heard no frame: "unexpected_id rejects: logged 1, re-run 0", and a run
    stopped on FOREIGN_COMMAND re-ran as one that went on (found by an outside audit)."""
    from handctl.recording import channels as ch
    from handctl.recording.metadata import run_metadata, start_metadata
    from handctl.recording.reader import iter_decoded, open_recording
    from handctl.recording.recorder import Recorder
    from handctl.recording.rerun import rerun

    log = tmp_path / "remote.mcap"
    with rig(hand, hold, max_seconds=1.2) as r, third_peer(r) as peer:
        recorder = Recorder(
            log,
            hand,
            start_metadata(hand, hold, ["test", "remote frame"]),
            phase_names=[p.name for p in hold.phases],
        )
        r.runtime.recorder = recorder
        recorder.attach(r.runtime)
        recorder.add_metadata(
            ch.META_RUN,
            run_metadata(
                mode="lockstep",
                bus="virtual",
                seed=0,
                period_ns=round(hand.bus.period_s * 1e9),
                startup_ticks=r.runtime.startup_ticks,
                reset_node_faults=False,
                estimator=False,
                sim_faults="remote frame",
            ),
        )
        sent: list[int] = []

        def remote() -> None:
            if not sent:
                peer.send(
                    can.Message(arbitration_id=frame_id, is_remote_frame=True, is_extended_id=False)
                )
                sent.append(r.runtime.tick)

        r.sim.faults.add(Every(send=remote), INJECT_AT)
        with recorder:
            result = r.run()
            recorder.wait_ready()
            recorder.close({"outcome": result.outcome.value})
    assert sent and result.node_rejects["unexpected_id"] == 1
    assert (FaultCode.FOREIGN_COMMAND in {f.code for f in result.faults}) is stops
    recording = open_recording(log)
    bus = [m for _, _, m in iter_decoded(recording, [ch.EVENTS]) if m["kind"] == "bus"]
    assert [(m["name"], m.get("id")) for m in bus] == [("remote_frame", frame_id)]
    report = rerun(recording)
    assert report.ok, (report.mismatches[:3], report.frame_mismatches[:3])
    assert report.outcome == report.logged_outcome


def test_a_heartbeat_lost_to_a_second_sender_says_its_frames_came_and_were_rejected(
    hand: HandConfig, hold: Recipe
) -> None:
    """A second sender on Heartbeat_2 (another node 2, a bootloader), 10 Hz on its own
    counter: from then on every Heartbeat of node 2 is a counter skip, the node's and the
    other's alike, and the run stops on HEARTBEAT_LOST. The stop said only "last heartbeat
    351 ms ago" of a node whose Heartbeats never stopped, which sends the operator to its
    power and wiring; it says they came and were rejected, with the counts."""
    layout = protocol_for(hand).layout("Heartbeat", 2)
    with rig(hand, hold) as r, third_peer(r) as peer:
        calls = [0]

        def twin() -> None:
            calls[0] += 1
            if calls[0] % 100 == 37:
                data = layout.encode((90 + calls[0] // 100) % 256, [0, 1000 + calls[0]])
                peer.send(frame(layout.frame_id, data))

        r.sim.faults.add(Every(send=twin), INJECT_AT)
        result = r.run()
    first = result.faults[0]
    assert first.code is FaultCode.HEARTBEAT_LOST, [str(f) for f in result.faults]
    assert first.detail.startswith("node 2 (f2): last heartbeat "), first.detail
    said = re.search(
        r"; (\d+) Heartbeat frames heard since and rejected \(counter_skip \1\), none "
        r"accepted, the last [0-9.]+ ms ago: not a silent node; `handctl nodes` shows them$",
        first.detail,
    )
    assert said is not None, first.detail
    assert 4 <= int(said[1]) <= result.node_rejects["counter_skip"]


def test_a_node_silent_after_a_rejected_frame_is_said_to_have_fallen_silent(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """One corrupted Feedback, then none for 50 ms (a node browning out): the timeout said
    "not a silent node; `handctl nodes` shows them" of a node that had gone silent, sending
    the operator to look for a second sender (found by an outside audit)."""
    faults = tmp_path / "faults.yaml"
    faults.write_text(
        "faults:\n"
        "  - {kind: corrupt_crc, node: 2, message: feedback, start: 1.000, stop: 1.0015}\n"
        "  - {kind: drop_feedback, node: 2, start: 1.0015, stop: 1.05}\n"
    )
    argv = ["run", "recipe", str(ROOT / "config/recipes/swap_two_cylinders.yaml")]
    code = cli.main([*argv, "--max-seconds", "1.5", "--sim-faults", str(faults)])
    err = capsys.readouterr().err
    assert code == cli.EXIT_SAFETY_STOP, err
    said = re.search(
        r"FEEDBACK_TIMEOUT at tick \d+: node 2 \(f2\): last valid feedback [0-9.]+ ms ago; "
        r"1 Feedback frame heard since and rejected \(crc 1\), none accepted, the last "
        r"([0-9.]+) ms ago: the node fell silent after them",
        err,
    )
    assert said is not None, err
    assert float(said[1]) > 2.5  # half the stream's timeout: it had stopped coming
    assert "not a silent node" not in err


def test_an_e_stop_of_another_sender_is_said_with_every_node_it_stopped(
    hand: HandConfig, hold: Recipe
) -> None:
    """One e-stop frame (the operator's) from a third peer mid-run: every node latches FAULT
    (ESTOP) in the same node tick, yet the stop named "node 1 (f1) in FAULT (ESTOP)" alone
    (the supervisor latches a code once, and node 2's and 3's findings were dropped), and
    the frame itself showed only as `unexpected_id 1`. The stop names every node, and the
    run says the e-stop came from another sender."""
    from handctl.protocol import ESTOP_REASONS

    layout = protocol_for(hand).layout("EStop")
    with rig(hand, hold) as r, third_peer(r) as peer:
        sent: list[int] = []

        def press() -> None:
            if not sent:
                peer.send(frame(layout.frame_id, layout.encode(7, [ESTOP_REASONS["operator"]])))
                sent.append(r.runtime.tick)

        r.sim.faults.add(Every(send=press), INJECT_AT)
        result = r.run()
    first = result.faults[0]
    assert first.code is FaultCode.ESTOP, [str(f) for f in result.faults]
    assert first.detail == (
        "node 1 (f1) in FAULT (ESTOP); node 2 (f2) in FAULT (ESTOP); node 3 (f3) in FAULT (ESTOP)"
    )
    assert result.estop_heard == (
        "an e-stop frame (id 0x000, reason 1, operator) from another sender was heard: "
        "every node latches FAULT (ESTOP) on it, which the next run clears with "
        "--reset-node-faults"
    )
    assert result.node_rejects["unexpected_id"] == 1  # counted as before, never applied
    assert [n.state for n in r.sim.nodes] == [int(NodeState.FAULT)] * 3


def test_an_e_stop_sent_as_a_remote_frame_is_said_too(hand: HandConfig, hold: Recipe) -> None:
    """A remote frame (RTR) on the e-stop id: the nodes latch FAULT (ESTOP) on it as on a
    data frame, and the run did not say an e-stop was heard (found by an outside audit)."""
    with rig(hand, hold) as r, third_peer(r) as peer:
        sent: list[int] = []

        def press() -> None:
            if not sent:
                peer.send(
                    can.Message(arbitration_id=0x000, is_remote_frame=True, is_extended_id=False)
                )
                sent.append(r.runtime.tick)

        r.sim.faults.add(Every(send=press), INJECT_AT)
        result = r.run()
    assert result.faults[0].code is FaultCode.ESTOP, [str(f) for f in result.faults]
    assert result.estop_heard.startswith(
        "an e-stop frame (id 0x000, a remote frame (RTR)) from another sender was heard"
    )
