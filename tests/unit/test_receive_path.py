"""The host's receive path with real frames on real buses: a frame's age counts from its
arrival, a drain never takes more than the bus can carry, 29-bit ids are not the protocol's,
a node's reports must agree, and a rate of rejected frames is a fault."""

from __future__ import annotations

import asyncio
import time
from collections.abc import Callable, Iterator
from dataclasses import replace
from pathlib import Path

import can
import numpy as np
import pytest

from handctl.busload import frames_per_period, shortest_frame_time_s
from handctl.config import HandConfig
from handctl.online.bus import EXTENDED_ID_FLAG, BusEventKind, Frame, HandBus, open_bus
from handctl.online.busspec import BusSpec
from handctl.online.clock import LockstepClock
from handctl.online.drivers.hand import AppliedTorques, HandDriver
from handctl.online.safety.faults import FaultCode
from handctl.online.safety.supervisor import State, Supervisor
from handctl.online.safety.watchdog import ReceiveWatch
from handctl.protocol import Protocol

MS = 1_000_000


class Clock:
    """The loop's clock as a test drives it (ns)."""

    def __init__(self) -> None:
        self.now = 5_000 * MS

    def __call__(self) -> int:
        return self.now


@pytest.fixture
def clock() -> Clock:
    return Clock()


@pytest.fixture
def driver(
    hand: HandConfig, protocol: Protocol, bus_pair: tuple[HandBus, HandBus], clock: Clock
) -> Iterator[HandDriver]:
    yield HandDriver(hand, protocol, bus_pair[0], clock_ns=clock)


def feedback(
    protocol: Protocol, node: int, counter: int, state: int = 1, faults: int = 0, angle: float = 0.1
) -> bytes:
    return protocol.layout("Feedback", node).encode(
        counter, (0.0, 0.0, 0.0, angle, 0.0, 0.0, state, faults)
    )


# -- receive times ---------------------------------------------------------------------------
def test_feedback_age_counts_from_arrival_not_from_the_drain(
    driver: HandDriver, protocol: Protocol, bus_pair: tuple[HandBus, HandBus], clock: Clock
) -> None:
    arrived = clock.now
    bus_pair[1].send(0x181, feedback(protocol, 1, 0))
    clock.now += 3 * MS  # the host reads it three periods later
    state = driver.poll()
    assert driver.nodes[0].feedback_ns == arrived
    assert state.age_s(clock.now)[0] == pytest.approx(0.003)


def test_the_unix_bus_stamps_frames_when_they_arrive(hand: HandConfig, tmp_path: Path) -> None:
    with (
        open_bus(f"unix:{tmp_path / 'bus'}", hand.bus) as rx,
        open_bus(f"unix:{tmp_path / 'bus'}", hand.bus) as tx,
    ):
        time.sleep(0.06)  # both sockets listed by each other
        before = time.monotonic_ns()
        assert tx.send(0x181, bytes(16))
        after = time.monotonic_ns()
        time.sleep(0.03)
        frames = rx.drain()
        drained = time.monotonic_ns()
    assert len(frames) == 1
    # On the host's clock, between the send and the drain, and the wait shows as age.
    assert before <= frames[0].timestamp_ns <= after
    assert drained - frames[0].timestamp_ns >= 25 * MS


class StampingAdapter(can.BusABC):
    """An adapter's receive stamps (s), over python-can's virtual bus: a test double of the
    stamps only, because none of this machine's buses stamps on another clock or lives
    through a wall-clock step (the kernel's and the virtual bus's stamps are right).
    ``stamp(sent)`` is the frame's stamp, given the wall-clock time it was sent."""

    def __init__(self, channel: str, stamp: Callable[[float], float]) -> None:
        self._wire = can.Bus(interface="virtual", channel=channel, receive_own_messages=False)
        self._stamp = stamp
        super().__init__(channel=channel)

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        msg = self._wire.recv(timeout=timeout)
        if msg is not None:
            msg.timestamp = self._stamp(msg.timestamp)  # python-can's virtual: time.time()
        return msg, False

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        self._wire.send(msg, timeout=timeout)

    def shutdown(self) -> None:
        self._wire.shutdown()
        super().shutdown()


@pytest.mark.parametrize(
    "stamp",
    [
        # pcan without ``uptime``: seconds since the adapter's boot, decades before now
        pytest.param(lambda sent: time.clock_gettime(time.CLOCK_BOOTTIME), id="since-boot"),
        # stamped on the wall clock, which NTP then stepped forward (by 10 s) before the drain
        pytest.param(lambda sent: sent - 10.0, id="wall-clock-stepped-forward"),
        # and backwards: a frame that waited, stamped "later" than the drain
        pytest.param(lambda sent: sent + 10.0, id="wall-clock-stepped-back"),
        pytest.param(lambda sent: 0.0, id="no-stamp"),
    ],
)
def test_a_stamp_that_cannot_be_true_makes_a_frame_as_old_as_it_can_be(
    hand: HandConfig, channel: str, clock: Clock, stamp: Callable[[float], float]
) -> None:
    """A stamp before the last drain that emptied the queue, or after now, is not on the
    wall clock the drain converts from: an adapter stamping from its boot made every frame
    look ancient (the run refused to start, "no feedback"), a step of the wall clock
    mid-run made a fresh frame 0.5 s old (FEEDBACK_TIMEOUT) or a stale one fresh. Such a
    frame arrived after that drain: it is taken to have arrived then, never later."""
    adapter = StampingAdapter(channel, stamp)
    host = HandBus(adapter, BusSpec("pcan", "PCAN_USBBUS1"), fd=False, clock_ns=clock)
    peer = can.Bus(interface="virtual", channel=channel)
    try:
        assert host.drain() == []  # the queue emptied: what comes next arrived after this
        emptied = clock.now
        peer.send(can.Message(arbitration_id=0x181, data=bytes(8), is_extended_id=False))
        clock.now += 3 * MS  # the host reads it three periods later
        frames = host.drain()
        assert [f.timestamp_ns for f in frames] == [emptied]
        peer.send(can.Message(arbitration_id=0x181, data=bytes(8), is_extended_id=False))
        clock.now += MS
        assert [f.timestamp_ns for f in host.drain()] == [emptied + 3 * MS]
    finally:
        host.close()
        peer.shutdown()


def test_a_stamp_that_can_be_true_is_kept(hand: HandConfig, channel: str, clock: Clock) -> None:
    """A wall-clock stamp between the last drain that emptied the queue and now is the
    frame's arrival, as the kernel took it (a frame stamped before that drain, by a stamp
    that takes longer to be read than the drain takes, gets the drain's time)."""
    adapter = StampingAdapter(channel, lambda sent: sent)
    host = HandBus(adapter, BusSpec("pcan", "PCAN_USBBUS1"), fd=False, clock_ns=clock)
    peer = can.Bus(interface="virtual", channel=channel)
    try:
        host.drain()
        emptied = clock.now
        peer.send(can.Message(arbitration_id=0x181, data=bytes(8), is_extended_id=False))
        clock.now += 10_000 * MS  # the frame cannot wait as long in a test
        (frame,) = host.drain()
        assert emptied < frame.timestamp_ns <= clock.now
    finally:
        host.close()
        peer.shutdown()


class ArrivingWhileRead(StampingAdapter):
    """The adapter's queue gets one more frame (``late``, sent by ``peer``) while the host
    reads the first one: a frame that arrives during a drain, as the nodes' 1 ms Feedback
    does at any loop rate."""

    def __init__(self, channel: str, peer: can.BusABC, late: can.Message) -> None:
        super().__init__(channel, lambda sent: sent)
        self.peer, self.late = peer, late
        self.armed = False

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        if self.armed:
            self.armed = False
            self.peer.send(self.late)
        return super()._recv_internal(timeout)


def test_a_frame_that_arrives_while_the_drain_reads_is_as_young_as_it_is(channel: str) -> None:
    """A frame that reached the host after its drain began (and before the queue ran empty)
    has a stamp after the drain's own time; it was taken for a bad stamp and given the last
    drain's time, a whole drain interval older than it is: at 250 Hz, one tick a
    millisecond late was a FEEDBACK_TIMEOUT (found by an outside audit). A stamp after the
    drain began and before the frame was read is as good as the drain's own time."""
    peer = can.Bus(interface="virtual", channel=channel)
    late = can.Message(arbitration_id=0x182, data=bytes(8), is_extended_id=False)
    adapter = ArrivingWhileRead(channel, peer, late)
    began: list[int] = []

    def clock() -> int:
        now = time.monotonic_ns()
        began.append(now)
        return now

    host = HandBus(adapter, BusSpec("pcan", "PCAN_USBBUS1"), fd=False, clock_ns=clock)
    try:
        assert host.drain() == []
        peer.send(can.Message(arbitration_id=0x181, data=bytes(8), is_extended_id=False))
        adapter.armed = True
        began.clear()
        first, second = host.drain()
        drain_began = began[0]
        assert first.arbitration_id == 0x181 and second.arbitration_id == 0x182
        # the drain's own time, as every frame it reads at the latest; not the last drain's
        assert second.timestamp_ns == drain_began
        assert first.timestamp_ns <= drain_began
    finally:
        host.close()
        peer.shutdown()


def test_a_lockstep_peer_steps_at_the_new_ticks_time() -> None:
    seen: list[int] = []
    lockstep = LockstepClock(0.001, lambda: seen.append(lockstep.now_ns()))

    async def two() -> list[int]:
        return [(await lockstep.wait_tick()).now_ns for _ in range(2)]

    assert asyncio.run(two()) == seen == [1 * MS, 2 * MS]


# -- the drain's budget ----------------------------------------------------------------------
def test_the_bus_budget_is_derived_from_its_bit_rates(hand: HandConfig) -> None:
    # 1 Mbit/s CAN-FD with a 5 Mbit/s data phase: 30 bits + 32 bits at least, 36.4 µs.
    assert shortest_frame_time_s(True, 1_000_000, 5_000_000) == pytest.approx(36.4e-6)
    assert shortest_frame_time_s(False, 1_000_000, None) == pytest.approx(47e-6)
    assert frames_per_period(hand.bus) == 27
    assert frames_per_period(replace(hand.bus, fd=False)) == 21
    assert frames_per_period(replace(hand.bus, loop_rate_hz=500.0)) == 54


def test_a_drain_takes_what_the_bus_can_carry_and_reports_the_rest(
    driver: HandDriver, bus_pair: tuple[HandBus, HandBus], clock: Clock
) -> None:
    driver.poll()
    budget = 2 * driver.frames_per_period  # one period since the last poll, plus one
    for i in range(budget + 6):
        bus_pair[1].send(0x050, bytes((i & 0xFF,)))
    clock.now += MS
    driver.poll()
    assert driver.reject_counts()["unexpected_id"] == budget
    events = driver.take_bus_events()
    assert [e.kind for e in events] == [BusEventKind.RX_BACKLOG]
    assert events[0].timestamp_ns == clock.now
    clock.now += MS
    driver.poll()  # the rest, in order, and nothing left behind
    assert driver.reject_counts()["unexpected_id"] == budget + 6
    assert driver.take_bus_events() == []


def test_a_late_poll_may_drain_what_the_bus_carried_meanwhile(
    driver: HandDriver, bus_pair: tuple[HandBus, HandBus], clock: Clock
) -> None:
    driver.poll()
    frames = 4 * driver.frames_per_period
    for _ in range(frames):
        bus_pair[1].send(0x050, bytes(8))
    clock.now += 3 * MS + 1  # four periods begun: four periods' worth and one more
    driver.poll()
    assert driver.reject_counts()["unexpected_id"] == frames
    assert driver.take_bus_events() == []


def test_discarding_at_start_up_is_no_backlog(
    driver: HandDriver, bus_pair: tuple[HandBus, HandBus]
) -> None:
    for _ in range(1500):
        bus_pair[1].send(0x050, bytes(8))
    bus_pair[1].send_error_frame()
    assert driver.discard_pending() == 1500
    kinds = [e.kind for e in driver.take_bus_events()]
    assert kinds == [BusEventKind.ERROR_FRAME]


# -- identifiers -----------------------------------------------------------------------------
def test_an_extended_id_twin_of_feedback_is_rejected_and_counted(
    driver: HandDriver, protocol: Protocol, bus_pair: tuple[HandBus, HandBus]
) -> None:
    bus_pair[1].send(EXTENDED_ID_FLAG | 0x181, feedback(protocol, 1, 0, angle=0.3))
    state = driver.poll()
    assert driver.nodes[0].feedback is None and state.angle[0] == 0.0
    assert driver.reject_counts()["extended_id"] == 1
    assert driver.reject_counts()["unexpected_id"] == 0
    assert driver.unexpected_ids == {EXTENDED_ID_FLAG | 0x181: 1}
    bus_pair[1].send(0x181, feedback(protocol, 1, 0, angle=0.3))  # the real one is taken
    assert driver.poll().angle[0] == pytest.approx(0.3)


def test_a_remote_frame_is_no_data_frame_and_on_a_command_id_is_another_sender(
    driver: HandDriver, protocol: Protocol, channel: str
) -> None:
    """A remote frame (RTR) came out of the bus as a data frame of 0 bytes (found by an
    outside audit). It is no node's frame now, but still counted, and on a node's command id
    another sender (safety.md row 45), as a data frame there is."""
    import can

    with can.Bus(interface="virtual", channel=channel) as other:
        other.send(can.Message(arbitration_id=0x181, is_remote_frame=True, is_extended_id=False))
        other.send(can.Message(arbitration_id=0x101, is_remote_frame=True, is_extended_id=False))
        driver.poll()
    assert driver.nodes[0].rejects.as_dict()["length"] == 0  # not a Feedback_1 of 0 bytes
    assert driver.reject_counts()["unexpected_id"] == 2
    assert [e.kind for e in driver.take_bus_events()] == [BusEventKind.REMOTE_FRAME] * 2
    said = driver.nodes[0].foreign_command
    assert said.startswith("another sender on this host's TorqueCommand id 0x101 (a remote frame")


def test_the_unix_bus_carries_the_extended_flag(hand: HandConfig, tmp_path: Path) -> None:
    with (
        open_bus(f"unix:{tmp_path / 'bus'}", hand.bus) as rx,
        open_bus(f"unix:{tmp_path / 'bus'}", hand.bus) as tx,
    ):
        time.sleep(0.06)
        assert tx.send(EXTENDED_ID_FLAG | 0x181, bytes(16))
        assert tx.send(0x181, bytes(16))
        deadline = time.monotonic() + 2
        frames: list[Frame] = []
        while len(frames) < 2 and time.monotonic() < deadline:
            frames += rx.drain()
    assert [f.arbitration_id for f in frames] == [EXTENDED_ID_FLAG | 0x181, 0x181]


# -- contradictions --------------------------------------------------------------------------
def test_enabled_with_latched_fault_bits_is_a_contradiction(
    driver: HandDriver, protocol: Protocol, bus_pair: tuple[HandBus, HandBus]
) -> None:
    bus_pair[1].send(0x182, feedback(protocol, 2, 0, state=1, faults=0x10))  # SATURATED: fine
    driver.poll()
    assert driver.nodes[1].contradiction == ""
    bus_pair[1].send(0x182, feedback(protocol, 2, 1, state=1, faults=0x01))
    driver.poll()
    assert "ENABLED with latched fault bits (TIMEOUT)" in driver.nodes[1].contradiction
    bus_pair[1].send(0x183, feedback(protocol, 3, 0, state=0, faults=0x40))
    driver.poll()
    assert "reserved fault bits 0x40" in driver.nodes[2].contradiction


def test_fault_then_enabled_in_one_tick_the_fault_stands(
    driver: HandDriver, protocol: Protocol, bus_pair: tuple[HandBus, HandBus]
) -> None:
    """The last report does not win. A Heartbeat ENABLED after a Feedback FAULT may have been
    sent before it (CAN keeps the order within an identifier, not across them): no
    contradiction until the Heartbeat stream has said FAULT itself."""
    peer = bus_pair[1]
    heartbeat = protocol.layout("Heartbeat", 1)
    peer.send(0x181, feedback(protocol, 1, 0, state=2, faults=0x01))
    peer.send(0x701, heartbeat.encode(0, (1, 500)))
    state = driver.poll()
    node = driver.nodes[0]
    assert node.contradiction == ""
    assert state.node_state[0] == 2 and state.node_faults[0] == 0x01  # the last did not win
    peer.send(0x701, heartbeat.encode(1, (2, 501)))
    peer.send(0x701, heartbeat.encode(2, (1, 502)))
    state = driver.poll()
    assert "Heartbeat says ENABLED after FAULT" in node.contradiction
    assert state.node_state[0] == 2 and state.node_faults[0] == 0x01


def test_a_fault_reset_sequence_is_no_contradiction(
    driver: HandDriver, protocol: Protocol, bus_pair: tuple[HandBus, HandBus]
) -> None:
    peer = bus_pair[1]
    status = protocol.layout("Status", 1)
    peer.send(0x181, feedback(protocol, 1, 0, state=2, faults=0x03))
    peer.send(0x281, status.encode(0, (0, 0, 0, 0, 0, 5, 2, 0, 2, 0)))  # fault reset: DISABLED
    peer.send(0x181, feedback(protocol, 1, 1, state=0))
    peer.send(0x281, status.encode(1, (1, 0, 0, 0, 0, 5, 2, 0, 2, 0)))  # enable
    peer.send(0x181, feedback(protocol, 1, 2, state=1))
    assert driver.poll().node_state[0] == 1
    assert driver.nodes[0].contradiction == "" and driver.nodes[0].contradictions == 0


def test_a_new_start_judges_the_nodes_afresh(
    driver: HandDriver, protocol: Protocol, bus_pair: tuple[HandBus, HandBus]
) -> None:
    bus_pair[1].send(0x181, feedback(protocol, 1, 0, state=1, faults=0x02))
    driver.poll()
    assert driver.nodes[0].contradiction
    driver.discard_pending()
    assert driver.nodes[0].contradiction == "" and driver.nodes[0].contradictions == 1


# -- the supervisor --------------------------------------------------------------------------
def _armed(
    hand: HandConfig, driver: HandDriver, protocol: Protocol, peer: HandBus, clock: Clock
) -> tuple[Supervisor, int]:
    """A supervisor that has seen every node ENABLED and is RUNNING at the tick returned."""
    sup = Supervisor(hand)
    sup.start(0)
    for node in (1, 2, 3):
        peer.send(0x180 + node, feedback(protocol, node, 0))
        peer.send(0x700 + node, protocol.layout("Heartbeat", node).encode(0, (1, 100)))
    driver.poll()
    zeros = np.zeros(hand.n_joints)
    assert sup.observe(1, clock.now, driver.nodes, zeros, zeros, 0) == []
    assert sup.state is State.RUNNING
    return sup, 1


def test_a_backlog_is_a_fault_that_zeroes_torque(
    hand: HandConfig,
    driver: HandDriver,
    protocol: Protocol,
    bus_pair: tuple[HandBus, HandBus],
    clock: Clock,
) -> None:
    sup, tick = _armed(hand, driver, protocol, bus_pair[1], clock)
    for _ in range(3 * driver.frames_per_period):
        bus_pair[1].send(0x050, bytes(8))
    for node in (1, 2, 3):
        bus_pair[1].send(0x180 + node, feedback(protocol, node, 1))
    clock.now += MS
    state = driver.poll()
    faults = sup.observe(
        tick + 1, clock.now, driver.nodes, state.angle, state.tdt, 0, driver.take_bus_events()
    )
    assert [f.code for f in faults] == [FaultCode.RX_BACKLOG]
    assert not np.any(sup.filter(tick + 1, np.full(hand.n_joints, 0.05)))


def test_a_contradiction_keeps_the_nodes_from_being_believed_enabled(
    hand: HandConfig,
    driver: HandDriver,
    protocol: Protocol,
    bus_pair: tuple[HandBus, HandBus],
    clock: Clock,
) -> None:
    sup = Supervisor(hand)
    sup.start(0)
    for node in (1, 2, 3):  # ENABLED everywhere, but node 2 also says TIMEOUT
        bus_pair[1].send(0x180 + node, feedback(protocol, node, 0, faults=0x01 if node == 2 else 0))
        bus_pair[1].send(0x700 + node, protocol.layout("Heartbeat", node).encode(0, (1, 9)))
    state = driver.poll()
    faults = sup.observe(1, clock.now, driver.nodes, state.angle, state.tdt, 0)
    assert faults[0].code is FaultCode.NODE_CONTRADICTION
    assert "node 2" in faults[0].detail
    assert sup.state is State.FAULTED
    assert not np.any(sup.filter(1, np.full(hand.n_joints, 0.05)))


def test_a_rate_of_rejected_frames_is_a_fault(
    hand: HandConfig,
    driver: HandDriver,
    protocol: Protocol,
    bus_pair: tuple[HandBus, HandBus],
    clock: Clock,
) -> None:
    limit = hand.safety.max_rejects_in_window
    watch = ReceiveWatch(hand.safety, hand.bus.period_s)
    assert watch.window == 100 and limit == 10
    peer = bus_pair[1]
    bad = bytes((feedback(protocol, 3, 0)[0] ^ 0xFF,)) + feedback(protocol, 3, 0)[1:]

    def tick(k: int, rejects: int) -> list[FaultCode]:
        for _ in range(rejects):
            peer.send(0x183, bad)
        clock.now += MS
        driver.poll()
        return [code for code, _ in watch.check(k, driver.nodes)]

    assert tick(0, 0) == []
    assert all(tick(k, 1) == [] for k in range(1, 1 + limit))  # ten in the window: allowed
    assert tick(11, 1) == [FaultCode.REJECT_RATE]  # the eleventh within 100 ticks
    # Until a hundred ticks on, when the first of them leave the window; a pause restarts it.
    later = {k: tick(k, 0) for k in range(12, 120)}
    assert all(later[k] == [FaultCode.REJECT_RATE] for k in range(12, 101))
    assert all(later[k] == [] for k in range(101, 120))
    assert tick(500, 5) == []
    assert driver.reject_counts()["crc"] == 16


def test_reject_rate_settings_come_from_the_safety_section(hand: HandConfig) -> None:
    safety = replace(hand.safety, reject_window_s=0.02, max_rejects_in_window=0)
    watch = ReceiveWatch(safety, hand.bus.period_s)
    assert (watch.window, watch.limit) == (20, 0)
    one_tick = ReceiveWatch(replace(safety, reject_window_s=hand.bus.period_s), hand.bus.period_s)
    assert one_tick.window == 1  # the shortest window the loader takes: one tick, not two


def test_commands_still_go_out_as_standard_frames(
    driver: HandDriver, bus_pair: tuple[HandBus, HandBus]
) -> None:
    driver.send(AppliedTorques(np.zeros(9)))
    assert [f.arbitration_id for f in bus_pair[1].drain()] == [0x101, 0x102, 0x103]


def test_reject_rate_settings_are_read_and_checked(tmp_path: Path) -> None:
    from handctl.config import load_hand
    from handctl.errors import ConfigError

    from ..conftest import HAND_YAML

    text = HAND_YAML.read_text()
    good = tmp_path / "good.yaml"
    good.write_text(text + "safety:\n  reject_window_s: 0.05\n  max_rejects_in_window: 4\n")
    safety = load_hand(good).safety
    assert (safety.reject_window_s, safety.max_rejects_in_window) == (0.05, 4)
    bad = tmp_path / "bad.yaml"
    bad.write_text(text + "safety:\n  max_rejects_in_window: -1\n")
    with pytest.raises(ConfigError) as info:
        load_hand(bad)
    assert info.value.key == "safety.max_rejects_in_window"
    assert str(bad) in str(info.value) and "-1" in str(info.value)


def test_an_exported_log_keeps_29_bit_ids_extended(tmp_path: Path) -> None:
    from handctl.recording.canlog import write_frames

    out = tmp_path / "rx.log"
    frames = [
        (1.0, EXTENDED_ID_FLAG | 0x181, bytes(16), True, True),
        (1.001, 0x181, bytes(16), True, True),
    ]
    assert write_frames(out, "candump", frames) == 2
    ids = [line.split()[2].split("#")[0] for line in out.read_text().splitlines()]
    assert ids == ["00000181", "181"]
