"""Each fault injector, switched on and off at set times, observed where the host sees it: on the
bus."""

from __future__ import annotations

import itertools
import math
from collections.abc import Iterator
from pathlib import Path

import pytest

from handctl.config import HandConfig
from handctl.online.bus import BusEventKind
from handctl.protocol import NodeState
from handctl.sim.faults import (
    Babble,
    BusOff,
    CorruptCrc,
    CounterRepeat,
    CounterSkip,
    DelayFeedback,
    DropCommands,
    DropFeedback,
    EncoderJump,
    ErrorFrames,
    Injector,
    MotorSaturation,
    NodeReboot,
    NodeSilent,
    TdtOffset,
    TdtSpike,
    TdtStuck,
    TendonSlack,
)
from handctl.sim.hand import SimulatedHand

from .test_sim_support import Heard, SimHost, crc_ok, enable_all, sim_and_host

# Moderate torques, flexing every finger (finger 3 flexes with negative torques).
TAU = [0.2, 0.1, 0.05, 0.15, 0.1, 0.05, -0.2, -0.1, -0.05]
SCENARIOS = Path(__file__).resolve().parents[2] / "config" / "sim"
Window = tuple[list[Heard], list[Heard], list[Heard]]


@pytest.fixture
def running(hand: HandConfig, channel: str) -> Iterator[tuple[SimulatedHand, SimHost]]:
    with sim_and_host(hand, channel) as (sim, host):
        sim.plant.hold_objects(True)
        enable_all(host)
        host.run(30, TAU)
        yield sim, host


def window(
    host: SimHost,
    injector: Injector,
    before: int = 10,
    during: int = 20,
    after: int = 20,
    tau: list[float] | None = TAU,
) -> Window:
    """Schedule ``injector`` for ``during`` ticks starting ``before`` ticks from now; return
    what the host heard before, during and after."""
    k0 = host.sim.ticks + before
    host.sim.faults.add(injector, start=k0 / 1000, stop=(k0 + during) / 1000)
    heard = host.run(before + during + after, tau)
    return (
        [h for h in heard if h.tick <= k0],
        [h for h in heard if k0 < h.tick <= k0 + during],
        [h for h in heard if h.tick > k0 + during],
    )


def counters(frames: list[Heard]) -> list[int]:
    return [h.frame.data[1] for h in frames]


def torque(frames: list[Heard], joint: int) -> list[float]:
    return [h.signals()[f"Torque{joint}"] for h in frames]


def test_drop_commands_starves_the_watchdog(running: tuple[SimulatedHand, SimHost]) -> None:
    _, host = running
    _, mid, _ = window(host, DropCommands(node=1, count=12), during=15)
    states = {n: [h.signals()["State"] for h in host.of("Feedback", n, mid)] for n in (1, 2, 3)}
    assert states[1][-1] == 2 and host.last("Feedback", 1)["FaultBits"] & 0x01
    assert set(states[2]) == set(states[3]) == {1}


def test_a_few_dropped_commands_cost_one_counter_reject(
    running: tuple[SimulatedHand, SimHost],
) -> None:
    sim, host = running
    window(host, DropCommands(node=2, count=3), during=5)
    node = sim.nodes[1]
    assert node.state == NodeState.ENABLED  # 3 ms without commands is within the watchdog
    assert (node.reject_counter, node.reject_crc) == (1, 0)  # the frame after the gap


def test_drop_feedback(running: tuple[SimulatedHand, SimHost]) -> None:
    _, host = running
    pre, mid, post = window(host, DropFeedback(node=2))
    assert host.of("Feedback", 2, mid) == []
    assert len(host.of("Feedback", 1, mid)) == 20
    gap = counters(host.of("Feedback", 2, post))[0] - counters(host.of("Feedback", 2, pre))[-1]
    assert gap & 0xFF == 21  # the node went on counting: the host sees a skip


def test_delay_feedback(running: tuple[SimulatedHand, SimHost]) -> None:
    _, host = running
    pre, mid, post = window(host, DelayFeedback(node=3, delay=0.005))
    first_tick = mid[0].tick
    late = host.of("Feedback", 3, mid)
    assert late[0].tick == first_tick + 5  # held back five ticks
    assert len(host.of("Feedback", 1, mid)) == 20
    every = counters(host.of("Feedback", 3, pre + mid + post))
    assert every == [(every[0] + k) & 0xFF for k in range(len(every))]  # late, none lost


def test_corrupt_crc(running: tuple[SimulatedHand, SimHost]) -> None:
    _, host = running
    pre, mid, post = window(host, CorruptCrc(node=1, message="feedback"))
    assert all(crc_ok(h.frame) for h in pre + post)
    assert not any(crc_ok(h.frame) for h in host.of("Feedback", 1, mid))
    assert all(crc_ok(h.frame) for h in host.of("Feedback", 2, mid))


def test_counter_repeat(running: tuple[SimulatedHand, SimHost]) -> None:
    _, host = running
    _, mid, _ = window(host, CounterRepeat(node=2))
    repeated = counters(host.of("Feedback", 2, mid))
    assert len(set(repeated)) == 1 and len(repeated) == 20
    ok = counters(host.of("Feedback", 1, mid))
    assert ok == [(ok[0] + k) & 0xFF for k in range(20)]


def test_counter_skip(running: tuple[SimulatedHand, SimHost]) -> None:
    _, host = running
    _, mid, _ = window(host, CounterSkip(node=3, message="all"))
    skipping = counters(host.of("Feedback", 3, mid))
    assert [(b - a) & 0xFF for a, b in itertools.pairwise(skipping)] == [2] * 19


def test_tdt_stuck(running: tuple[SimulatedHand, SimHost]) -> None:
    _, host = running
    ramp = [0.01 * k for k in range(10)]
    host.sim.activate(TdtStuck(node=1, joint=2))
    frames: list[Heard] = []
    for r in ramp:
        tau = list(TAU)
        tau[0] += r
        tau[1] += r
        frames += host.of("Feedback", 1, host.run(5, tau))
    assert len(set(torque(frames, 2))) == 1  # frozen while the torque changes
    assert len(set(torque(frames, 1))) > 10


def test_tdt_spike(running: tuple[SimulatedHand, SimHost]) -> None:
    sim, host = running
    pre, mid, _ = window(host, TdtSpike(node=2, joint=1, amplitude=0.5, duration=0.002), during=10)
    base = torque(host.of("Feedback", 2, pre), 1)[-1]
    during = torque(host.of("Feedback", 2, mid), 1)
    assert [abs(v - base) > 0.4 for v in during] == [True, True] + [False] * 8
    assert sim.nodes[1].state == NodeState.ENABLED  # within the sensor's range: not noticed
    window(host, TdtSpike(node=2, joint=1, amplitude=5.0), during=2)
    assert host.last("Feedback", 2)["FaultBits"] & 0x08  # out of range: SENSOR


def test_tdt_offset(running: tuple[SimulatedHand, SimHost]) -> None:
    _, host = running
    pre, mid, _ = window(host, TdtOffset(node=3, joint=3, offset=0.2), during=30)
    base = torque(host.of("Feedback", 3, pre), 3)
    shifted = torque(host.of("Feedback", 3, mid), 3)
    assert sum(shifted) / len(shifted) - sum(base) / len(base) == pytest.approx(0.2, abs=0.01)


def test_encoder_jump(running: tuple[SimulatedHand, SimHost]) -> None:
    sim, host = running
    counts = 20
    step = 2 * math.pi / sim.params.encoder.counts_per_rev
    sim.activate(EncoderJump(node=1, joint=1, counts=counts))
    host.tick(TAU)
    reading = host.last("Feedback", 1)["Angle1"]
    true = sim.ground_truth().joint_angles[0]
    assert reading - true == pytest.approx(counts * step, abs=step)
    assert sim.nodes[0].state == NodeState.ENABLED  # small enough to pass the node's self-check
    sim.activate(EncoderJump(node=2, joint=3, counts=sim.params.encoder.counts_per_rev // 4))
    host.tick(TAU)
    assert host.last("Feedback", 2)["FaultBits"] & 0x08


def test_node_reboot(running: tuple[SimulatedHand, SimHost]) -> None:
    sim, host = running
    _, mid, post = window(host, NodeReboot(node=2, downtime=0.02), during=20, after=5)
    node2 = [h for h in mid if h.id in sim.nodes[1].tx_ids]
    assert node2 == []  # silent while down
    assert len(host.of("Feedback", 1, mid)) == 20
    first = host.of("Feedback", 2, post)
    assert first[0].frame.data[1] == 0 and first[0].signals()["State"] == 0
    assert host.of("Heartbeat", 2, post)[0].signals()["Uptime"] == 0
    # torque-free since the reboot, 25 ms ago: only the 5 ms drive lag still decays
    assert sim.ground_truth().joint_torques[3:6] == pytest.approx([0.0] * 3, abs=5e-3)


def test_node_silent(running: tuple[SimulatedHand, SimHost]) -> None:
    sim, host = running
    _, mid, post = window(host, NodeSilent(node=3))
    assert [h for h in mid if h.id in sim.nodes[2].tx_ids] == []
    assert host.of("Feedback", 3, post)[0].signals()["State"] == 1  # it heard all along


def test_error_frames(running: tuple[SimulatedHand, SimHost]) -> None:
    _, host = running
    host.events.clear()
    window(host, ErrorFrames(per_tick=2), during=5)
    kinds = [e.kind for e in host.events]
    assert kinds.count(BusEventKind.ERROR_FRAME) == 10


def test_bus_off(running: tuple[SimulatedHand, SimHost]) -> None:
    _, host = running
    host.events.clear()
    _, mid, post = window(host, BusOff(), during=10)
    assert mid == []  # no node can transmit
    kinds = [e.kind for e in host.events]
    assert kinds == [BusEventKind.BUS_OFF, BusEventKind.BUS_RESTARTED]
    assert len(host.of("Feedback", 1, post)) == 20


def test_babble(running: tuple[SimulatedHand, SimHost]) -> None:
    sim, host = running
    before = [n.reject_unexpected for n in sim.nodes]
    start = sim.ticks
    _, mid, _ = window(host, Babble(id=0x050, per_tick=5), during=10)
    assert len([h for h in mid if h.id == 0x050]) == 50
    # every node heard the 50 frames, besides the other nodes' TorqueCommands (2 per tick)
    grown = [n.reject_unexpected - b for n, b in zip(sim.nodes, before, strict=True)]
    assert grown == [50 + 2 * (sim.ticks - start)] * 3
    assert all(n.state == NodeState.ENABLED for n in sim.nodes)


def test_babble_on_the_estop_id_stops_every_node(running: tuple[SimulatedHand, SimHost]) -> None:
    sim, host = running
    window(host, Babble(id=0x000, per_tick=1, length=8), during=1, after=2)
    assert all(n.state == NodeState.FAULT and n.fault_bits & 0x02 for n in sim.nodes)
    assert host.last("Feedback", 3)["FaultBits"] & 0x02


def test_tendon_slack(running: tuple[SimulatedHand, SimHost]) -> None:
    sim, host = running
    pre, mid, post = window(host, TendonSlack(node=1, joint=1), during=40, after=40)
    assert torque(host.of("Feedback", 1, pre), 1)[-1] == pytest.approx(TAU[0], abs=0.02)
    assert abs(torque(host.of("Feedback", 1, mid), 1)[-1]) < 0.02  # nothing transmitted
    assert sim.nodes[0].applied[0] == pytest.approx(TAU[0])  # while the node drives it
    assert torque(host.of("Feedback", 1, post), 1)[-1] == pytest.approx(TAU[0], abs=0.02)


def test_motor_saturation(running: tuple[SimulatedHand, SimHost]) -> None:
    _, host = running
    _, mid, _ = window(host, MotorSaturation(node=3, joint=1, limit=0.05), during=40)
    last = host.of("Feedback", 3, mid)[-1].signals()
    assert last["Torque1"] == pytest.approx(-0.05, abs=0.015)
    assert last["FaultBits"] == 0  # the node does not know: only the TDT shows it


def test_every_injector_scenario_runs_to_the_end(hand: HandConfig, channel: str) -> None:
    with sim_and_host(hand, channel) as (sim, host):
        sim.load_faults(SCENARIOS / "every_injector.yaml")
        host.command("enable")
        host.run(1200, TAU)
        summary = sim.ground_truth_summary()
    assert len(summary["faults"]) == len(sim.faults)
    assert not sim.faults.pending
    assert {i.kind for i in sim.active} == {"tdt_spike", "node_reboot"}  # no stop time
