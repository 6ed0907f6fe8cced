"""``handctl replay --to-bus`` onto a hand that does not follow the log: another host that
begins commanding it during the replay, a node that ignores the disable, a node that reboots,
a peer's frames on a node's Feedback id. The simulated hand steps in lockstep with the
replay's clock (its ``sleep``), so what it hears and says is the same on a loaded machine."""

from __future__ import annotations

import errno
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any

import can
import pytest

from handctl.config import HandConfig
from handctl.hand_protocol import protocol_for
from handctl.online.bus import Frame, HandBus, open_bus
from handctl.protocol import NODE_COMMANDS, Layout, NodeState
from handctl.recording.frames import logged_frames, to_bus
from handctl.recording.reader import Recording, open_recording
from handctl.sim.firmware import FaultBits
from handctl.sim.hand import SimulatedHand

from .rig import short_recipe
from .test_recording import Recorded, record_run

#: what a peer does on each of the hand's ticks: (the hand, its tick since the replay
#: began, the peer's bus, every frame the peer has heard so far)
EachTick = Callable[[SimulatedHand, int, HandBus, list[Frame]], None]


@pytest.fixture(scope="module")
def recorded(hand: HandConfig, tmp_path_factory: pytest.TempPathFactory) -> Recorded:
    directory = tmp_path_factory.mktemp("live")
    return record_run(hand, short_recipe(hand, directory), directory / "run.mcap", troubles=False)


class Lockstep:
    """The simulated hand on ``spec``, stepped as the replay's clock goes, and a peer on the
    same bus that acts on each of its ticks."""

    def __init__(self, sim: SimulatedHand, peer: HandBus, each_tick: EachTick | None) -> None:
        self.sim = sim
        self.peer = peer
        self.heard: list[Frame] = []  # by the peer: the replay's frames and the hand's
        self.each_tick = each_tick
        self.now = sim.ticks * 1e-3  # s, the hand's time
        self.began = sim.ticks

    def clock(self) -> float:
        return self.now

    def sleep(self, seconds: float) -> None:
        self.now += seconds
        while self.sim.ticks * 1e-3 < self.now:
            self.sim.step()
            self.heard += self.peer.drain(limit=10**6)
            if self.each_tick is not None:
                self.each_tick(self.sim, self.sim.ticks - self.began, self.peer, self.heard)

    def settle(self) -> None:
        """One more tick of the hand (the nodes take what the replay sent last), and what
        the peer heard meanwhile."""
        self.sleep(1e-3)

    def replay(self, recording: Recording, spec: str) -> dict[str, Any]:
        """The log's host frames onto ``spec``, paced by the hand's time."""
        return to_bus(recording, spec, direction="tx", sleep=self.sleep, clock=self.clock)


@contextmanager
def lockstep(
    hand: HandConfig,
    spec: str,
    each_tick: EachTick | None = None,
    prepare: Callable[[SimulatedHand], None] | None = None,
) -> Iterator[Lockstep]:
    """The hand under way (a few ticks: its nodes speaking) and its peer, on ``spec``."""
    with open_bus(spec, hand.bus) as its_bus, open_bus(spec, hand.bus) as peer:
        sim = SimulatedHand(hand, its_bus)
        if prepare is not None:
            prepare(sim)
        for _ in range(20):
            sim.step()
        peer.drain(limit=10**6)
        yield Lockstep(sim, peer, each_tick)


def _after(frames: list[Frame], frame_id: int) -> int:
    """The counter after the last frame of ``frame_id`` among ``frames`` (0: none yet)."""
    last = next((f for f in reversed(frames) if f.arbitration_id == frame_id), None)
    return 0 if last is None else (last.data[1] + 1) & 0xFF


def test_another_host_that_begins_commanding_during_the_replay_is_an_e_stop(
    recorded: Recorded, hand: HandConfig, channel: str
) -> None:
    """A second host that began sending TorqueCommands to node 1, each a counter ahead of
    the replay's, was never noticed: the replay listened for another host only before its
    first frame, and node 1 took the other host's torques and rejected the replay's for
    some 235 ticks, until its own reject limit latched it (an outside audit). A frame on one
    of the hand's command identifiers during the replay is another host, as in a run
    (FOREIGN_COMMAND, docs/safety.md row 45): the e-stop at once, the replay stopped there,
    and said (exit 1) naming the identifier."""
    protocol = protocol_for(hand)
    torque = protocol.layout("TorqueCommand", 1)
    estopped: list[bool] = []  # at each frame the other host sent: whether it heard an e-stop

    def other_host(sim: SimulatedHand, tick: int, peer: HandBus, heard: list[Frame]) -> None:
        if tick >= 300:  # the nodes enabled, under the log's torques
            peer.send(torque.frame_id, torque.encode(_after(heard, torque.frame_id), (0.05,) * 3))
            estopped.append(any(f.arbitration_id == 0 for f in heard))

    recording = open_recording(recorded.path)
    logged = list(logged_frames(recording, "tx"))
    spec = f"virtual:{channel}"
    with lockstep(hand, spec, other_host) as hand_on_bus:
        sent = hand_on_bus.replay(recording, spec)
        hand_on_bus.settle()  # the nodes take the e-stop on their tick
        nodes = hand_on_bus.sim.nodes
        estops = [f for f in hand_on_bus.heard if f.arbitration_id == 0]
    said = sent.get("node_fault", "")
    assert said.startswith(
        "another sender on the hand's TorqueCommand id 0x101 of node 1 (f1) while the replay "
        f"sent ({torque.length} bytes: "
    ), sent
    assert "as a run stops on FOREIGN_COMMAND; the e-stop was sent" in said
    assert estopped[:2] == [False, True]  # the e-stop came with the replay's next look
    assert sent["sent"] < len(logged)  # stopped there, not sent to its end
    assert len(estops) == 1
    for node in nodes:
        assert node.state == int(NodeState.FAULT) and node.fault_bits & FaultBits.ESTOP


@pytest.mark.parametrize("burst", [1, 11])
def test_a_peer_s_frames_of_another_length_on_a_feedback_id_are_rejects(
    recorded: Recorded, hand: HandConfig, channel: str, burst: int
) -> None:
    """One frame of 8 bytes on node 1's Feedback id, from any peer, stopped the replay
    blaming "a hand of another config on the bus" (an outside audit); a run counts it as a
    rejected frame against the hand's reject limit. So does the replay now: one goes by, and
    more than ``safety.max_rejects_in_window`` within ``reject_window_s`` stops it, said as
    the rejects they are. (Another config is a node whose own stream keeps that length:
    ``test_to_bus_onto_a_hand_of_another_config_sends_nothing``.)"""
    feedback = protocol_for(hand).layout("Feedback", 1)
    limit = hand.safety.max_rejects_in_window
    assert burst in (1, limit + 1)

    def peer_frames(sim: SimulatedHand, tick: int, peer: HandBus, heard: list[Frame]) -> None:
        if tick == 500:  # the nodes enabled, under the log's torques
            for _ in range(burst):
                peer.send(feedback.frame_id, bytes(8))

    recording = open_recording(recorded.path)
    logged = list(logged_frames(recording, "tx"))
    spec = f"virtual:{channel}"
    with lockstep(hand, spec, peer_frames) as hand_on_bus:
        sent = hand_on_bus.replay(recording, spec)
    if burst == 1:
        assert "node_fault" not in sent, sent
        assert sent["sent"] == len(logged)
        return
    said = sent["node_fault"]
    assert said.startswith(
        f"node 1 (f1): {burst} of its Feedback_1 frames rejected within "
        f"{hand.safety.reject_window_s:g} s (length {burst}; at most {limit}, "
    ), said
    assert "as a run stops on REJECT_RATE, and the replay stopped there" in said
    assert "another config" not in said
    assert sent["sent"] < len(logged)


def test_a_node_that_reboots_during_the_replay_ends_it(
    recorded: Recorded, hand: HandConfig, channel: str
) -> None:
    """A node that rebooted in the middle of a replay came back DISABLED and took none of
    the rest of the log's torques, and the replay sent it to its end and exited 0 (an outside
    audit). A node the replay had enabled, heard ENABLED, that says DISABLED (not after the
    log's own disable) ends the replay there, said (exit 1), with the replay's stop."""

    def reboot(sim: SimulatedHand, tick: int, peer: HandBus, heard: list[Frame]) -> None:
        if tick == 500:  # the nodes enabled, under the log's torques
            sim.nodes[1].reboot(sim.ticks * 1_000_000, 5_000_000)

    recording = open_recording(recorded.path)
    logged = list(logged_frames(recording, "tx"))
    spec = f"virtual:{channel}"
    with lockstep(hand, spec, reboot) as hand_on_bus:
        sent = hand_on_bus.replay(recording, spec)
        rebooted = hand_on_bus.sim.nodes[1].reboots
    assert rebooted == 1
    assert sent.get("node_fault", "").startswith(
        "node 2 (f2) said DISABLED while the replay had it enabled, after it had said "
        "ENABLED: it rebooted, or something else disabled it"
    ), sent
    assert sent["sent"] < len(logged)  # stopped there, not sent to its end
    assert "zero torque and a disable sent after them" in sent["stopped"]


def test_a_node_whose_uptime_goes_back_during_the_replay_rebooted(hand: HandConfig) -> None:
    """The other sign of a reboot, as a run reads it: a Heartbeat whose uptime went back
    (not by its wrap) from a node the replay had enabled."""
    from handctl.recording.frames import _FaultsHeard, _LeftEnabled

    protocol = protocol_for(hand)
    left = _LeftEnabled(hand, protocol)
    now = [0.0]
    heard = _FaultsHeard(hand, left, lambda: now[0])
    heartbeat = protocol.layout("Heartbeat", 3)
    torque = protocol.layout("TorqueCommand", 3)

    def uptime(counter: int, ms: int) -> Frame:
        return Frame(heartbeat.frame_id, heartbeat.encode(counter, (int(NodeState.ENABLED), ms)))

    assert not heard.hear([uptime(0, 900)])  # not enabled by the replay: its own business
    left.sent(torque.frame_id, torque.encode(0, (0.0,) * len(torque.signals)))
    now[0] = 0.1
    assert not heard.hear([uptime(1, 1000)])
    now[0] = 0.2
    assert heard.hear([uptime(2, 30)])
    assert heard.first.startswith(
        "node 3 (f3) rebooted while the replay had it enabled (its uptime went back from "
        "1000 ms to 30 ms)"
    )


def _deaf_to_the_disable(node_id: int) -> Callable[[SimulatedHand], None]:
    """Simulated node ``node_id`` drops every disable: firmware that ignores it."""

    def prepare(sim: SimulatedHand) -> None:
        node = sim.nodes[node_id - 1]
        layout = sim.protocol.layout("NodeCommand", node_id)
        obey = node._apply

        def deaf(lay: Layout, data: bytes, now_ns: int) -> None:
            if lay is layout and layout.decode(data)[1][0] == NODE_COMMANDS["disable"]:
                return
            obey(lay, data, now_ns)

        setattr(node, "_apply", deaf)  # noqa: B010 (a method replaced on one instance)

    return prepare


def test_a_node_that_ignores_the_log_s_disable_gets_the_e_stop(
    recorded: Recorded, hand: HandConfig, channel: str
) -> None:
    """A node that ignored the log's disable was left ENABLED, and the replay exited 0
    saying nothing, until the node's watchdog latched FAULT (TIMEOUT) (an outside audit).
    The replay now waits for every node it enabled to say DISABLED, as a run does (row 75):
    one that goes on saying ENABLED gets the e-stop, and the replay says so (exit 1)."""
    recording = open_recording(recorded.path)
    logged = list(logged_frames(recording, "tx"))
    spec = f"virtual:{channel}"
    with lockstep(hand, spec, prepare=_deaf_to_the_disable(2)) as hand_on_bus:
        sent = hand_on_bus.replay(recording, spec)
        hand_on_bus.settle()  # the nodes take the e-stop on their tick
        stubborn = hand_on_bus.sim.nodes[1]
        estops = [f for f in hand_on_bus.heard if f.arbitration_id == 0]
    assert sent["sent"] == len(logged)  # the whole log went
    assert sent.get("node_fault", "").startswith(
        "node 2 (f2) went on saying ENABLED after the disable; the e-stop was sent: every "
        "node latches FAULT (ESTOP)"
    ), sent
    assert "stopped" not in sent  # the log disabled the nodes itself
    assert len(estops) == 1
    assert stubborn.state == int(NodeState.FAULT) and stubborn.fault_bits & FaultBits.ESTOP


@pytest.mark.parametrize("refusals", [7, None], ids=["refused-then-taken", "never-taken"])
def test_a_disable_the_bus_refuses_is_sent_again(
    recorded: Recorded,
    hand: HandConfig,
    channel: str,
    monkeypatch: pytest.MonkeyPatch,
    refusals: int | None,
) -> None:
    """The replay's stop sent its disable without looking at what the bus did with it: a
    full transmit queue left the nodes ENABLED, and the replay said it had disabled them.
    The host's transport refuses the disables (the log's three, the stop's three) and the
    e-stop after them, as SocketCAN does with a full queue (ENOBUFS): the disable is sent
    again while the replay waits for the nodes' DISABLED, and goes; refused on every try,
    the replay says so (exit 1)."""
    import handctl.online.bus as bus_module

    commands = {protocol_for(hand).layout("NodeCommand", f.node_id).frame_id for f in hand.fingers}
    refused: list[int] = []
    real_open = bus_module.open_bus

    def open_full(spec: str, *args: Any, **kwargs: Any) -> HandBus:
        bus = real_open(spec, *args, **kwargs)
        send_frame = bus._send_frame
        assert send_frame is not None, "the virtual bus sends frame by frame"

        def full(frame_id: int, flags: int, data: bytes) -> None:
            disable = frame_id in commands and data[2] == NODE_COMMANDS["disable"]
            if (disable or frame_id == 0) and (refusals is None or len(refused) < refusals):
                refused.append(frame_id)
                raise can.CanOperationError("No buffer space available", errno.ENOBUFS)
            send_frame(frame_id, flags, data)

        bus._send_frame = full  # type: ignore[assignment]
        return bus

    recording = open_recording(recorded.path)
    spec = f"virtual:{channel}"
    with lockstep(hand, spec) as hand_on_bus:
        monkeypatch.setattr(bus_module, "open_bus", open_full)
        sent = hand_on_bus.replay(recording, spec)
        monkeypatch.undo()
        states = [node.state for node in hand_on_bus.sim.nodes]
    assert sent["failed"] == len(hand.fingers)  # the log's own disables
    assert "zero torque and a disable sent after them" in sent["stopped"]
    if refusals is not None:
        assert len(refused) == refusals
        assert "node_fault" not in sent, sent
        assert "the bus refused the stop's disable 1 time(s) before it went" in sent["warning"]
        assert states == [int(NodeState.DISABLED)] * len(hand.fingers)
        return
    assert len(refused) > refusals_of_one_try(hand)  # sent again while it waited
    assert sent["node_fault"].startswith("the bus refused the disable of node(s) 1, 2, 3 "), sent
    assert "and the e-stop after it: a node still ENABLED stops only when" in sent["node_fault"]


def refusals_of_one_try(hand: HandConfig) -> int:
    """The frames refused once the log's disables, the stop's and the e-stop were."""
    return 2 * len(hand.fingers) + 1
