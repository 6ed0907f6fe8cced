"""Each watchdog on its own: node feedback, heartbeats, states and reboots; the TDT monitor;
late ticks and failed sends.

``NodeWatch`` watches the host's ``FingerNode`` objects, which hear the simulated nodes'
firmware frame by frame (``node_pair``): a lost frame, a reboot or a fault is the node's own.
Timeouts are checked to the nanosecond on both sides of the hand config's limit, and with a
config of longer timeouts too, so that the conversion to integer ns is exact in general.
"""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import numpy as np
import pytest

from handctl.config import HandConfig, SafetyConfig
from handctl.online.drivers.finger import FingerLayouts, FingerNode
from handctl.online.safety.faults import FaultCode
from handctl.online.safety.watchdog import NodeWatch, TdtMonitor, TickWatch
from handctl.protocol import Protocol
from handctl.sim.params import parse_sim

from .node_pair import MS, Link

LONG = {"feedback_timeout_s": 1.5, "heartbeat_timeout_s": 2.5}


def with_safety(hand: HandConfig, **changes: Any) -> HandConfig:
    return replace(hand, safety=replace(hand.safety, **changes))


@pytest.fixture
def link(hand: HandConfig, protocol: Protocol) -> Link:
    link = Link(hand, protocol)
    link.enable()
    return link


def codes(found: list[tuple[FaultCode, str]]) -> list[FaultCode]:
    return [code for code, _ in found]


# -- NodeWatch ---------------------------------------------------------------------------------


def test_live_enabled_nodes_raise_nothing(link: Link, hand: HandConfig) -> None:
    watch = NodeWatch(hand.safety)
    watch.arm(link.hosts)
    for _ in range(3 * round(hand.safety.heartbeat_timeout_s * 1e3)):
        assert watch.check(link.tick(), link.hosts, expect_enabled=True) == []


@pytest.mark.parametrize("safety", [{}, LONG], ids=["hand", "long"])
def test_feedback_older_than_the_timeout_by_one_ns_is_a_fault(
    hand: HandConfig, protocol: Protocol, safety: dict[str, float]
) -> None:
    hand = with_safety(hand, **safety)
    link = Link(hand, protocol)
    link.enable()
    watch = NodeWatch(hand.safety)
    watch.arm(link.hosts)
    heartbeats = {pair.host.layouts.heartbeat.frame_id for pair in link.pairs}
    feedback = {pair.host.layouts.feedback.frame_id for pair in link.pairs}
    timeout_ns = round(hand.safety.feedback_timeout_s * 1e9)
    last = link.tick(lose=heartbeats)  # the last feedback that arrives
    while link.now_ns <= last + timeout_ns:
        link.tick(lose=heartbeats | feedback)
    assert watch.check(last + timeout_ns, link.hosts, expect_enabled=True) == []
    found = watch.check(last + timeout_ns + 1, link.hosts, expect_enabled=True)
    age = f"{(timeout_ns + 1) / 1e6:.1f} ms ago"
    assert found == [
        (FaultCode.FEEDBACK_TIMEOUT, f"node {f.node_id} ({f.name}): last valid feedback {age}")
        for f in hand.fingers
    ]


@pytest.mark.parametrize("safety", [{}, LONG], ids=["hand", "long"])
def test_a_heartbeat_older_than_the_timeout_by_one_ns_is_a_fault(
    hand: HandConfig, protocol: Protocol, safety: dict[str, float]
) -> None:
    hand = with_safety(hand, **safety)
    link = Link(hand, protocol)
    link.enable()
    host = link.pairs[1].host
    while host.uptime_ms in (None, 0):  # the heartbeat after the one at boot
        link.tick()
    heard = host.heartbeat_ns
    assert heard is not None and heard > 0
    heartbeats = {host.layouts.heartbeat.frame_id}
    watch = NodeWatch(hand.safety)
    watch.arm(link.hosts)
    timeout_ns = round(hand.safety.heartbeat_timeout_s * 1e9)
    while link.now_ns <= heard + timeout_ns:
        link.tick(lose=heartbeats)  # only node 2's heartbeats are lost; feedback flows
    assert watch.check(heard + timeout_ns, link.hosts, expect_enabled=True) == []
    found = watch.check(heard + timeout_ns + 1, link.hosts, expect_enabled=True)
    f = hand.fingers[1]
    assert found == [
        (
            FaultCode.HEARTBEAT_LOST,
            f"node {f.node_id} ({f.name}): last heartbeat {(timeout_ns + 1) / 1e6:.0f} ms ago",
        )
    ]


def test_at_exactly_its_timeout_a_message_is_fresh_even_beside_another_fault(
    link: Link, hand: HandConfig
) -> None:
    watch = NodeWatch(hand.safety)
    watch.arm(link.hosts)
    pair = link.pairs[2]
    pair.command("disable", link.now_ns)
    link.tick()
    f = hand.fingers[2]
    state = (FaultCode.NODE_STATE, f"node {f.node_id} ({f.name}) is DISABLED, expected ENABLED")
    assert pair.host.feedback_ns is not None and pair.host.heartbeat_ns is not None
    at_feedback_timeout = pair.host.feedback_ns + round(hand.safety.feedback_timeout_s * 1e9)
    assert watch.check(at_feedback_timeout, [pair.host], expect_enabled=True) == [state]
    at_heartbeat_timeout = pair.host.heartbeat_ns + round(hand.safety.heartbeat_timeout_s * 1e9)
    found = watch.check(at_heartbeat_timeout, [pair.host], expect_enabled=True)
    assert codes(found) == [FaultCode.FEEDBACK_TIMEOUT, FaultCode.NODE_STATE]


def test_a_long_silence_is_reported_in_milliseconds(link: Link, hand: HandConfig) -> None:
    host = link.pairs[0].host
    assert host.feedback_ns is not None and host.heartbeat_ns is not None
    silence = 1000 * 10**9  # ns
    f = hand.fingers[0]
    found = NodeWatch(hand.safety).check(host.feedback_ns + silence, [host], expect_enabled=True)
    assert found[0] == (
        FaultCode.FEEDBACK_TIMEOUT,
        f"node {f.node_id} ({f.name}): last valid feedback 1000000.0 ms ago",
    )
    found = NodeWatch(hand.safety).check(host.heartbeat_ns + silence, [host], expect_enabled=True)
    assert found[1] == (
        FaultCode.HEARTBEAT_LOST,
        f"node {f.node_id} ({f.name}): last heartbeat 1000000 ms ago",
    )


def test_an_unarmed_watch_checks_all_but_reboots(link: Link, hand: HandConfig) -> None:
    watch = NodeWatch(hand.safety)
    now = link.tick()
    assert watch.check(now, link.hosts, expect_enabled=True) == []
    link.pairs[1].command("disable", link.now_ns)
    now = link.tick()
    assert codes(watch.check(now, link.hosts, expect_enabled=True)) == [FaultCode.NODE_STATE]


def test_nodes_never_heard_are_reported_as_never(hand: HandConfig, protocol: Protocol) -> None:
    link = Link(hand, protocol)  # nothing has been received yet
    found = NodeWatch(hand.safety).check(0, link.hosts, expect_enabled=False)
    expected = []
    for f in hand.fingers:
        who = f"node {f.node_id} ({f.name})"
        expected += [
            (FaultCode.FEEDBACK_TIMEOUT, f"{who}: last valid feedback never"),
            (FaultCode.HEARTBEAT_LOST, f"{who}: last heartbeat never"),
        ]
    assert found == expected


def test_a_node_disabled_while_torque_flows_is_a_node_state_fault(
    link: Link, hand: HandConfig
) -> None:
    watch = NodeWatch(hand.safety)
    watch.arm(link.hosts)
    link.pairs[2].command("disable", link.now_ns)
    now = link.tick()
    f = hand.fingers[2]
    assert watch.check(now, link.hosts, expect_enabled=True) == [
        (FaultCode.NODE_STATE, f"node {f.node_id} ({f.name}) is DISABLED, expected ENABLED")
    ]
    assert watch.check(now, link.hosts, expect_enabled=False) == []


def test_a_node_in_fault_is_a_node_fault_named_by_its_bits(link: Link, hand: HandConfig) -> None:
    watch = NodeWatch(hand.safety)
    watch.arm(link.hosts)
    pair = link.pairs[0]
    beyond = parse_sim(hand).tdt.range + 0.1  # beyond the sensor's range, within the wire's
    pair.tick(link.now_ns, tdt=[0.0, beyond, 0.0])  # the node's self-check: FAULT(SENSOR)
    f = hand.fingers[0]
    for expect_enabled in (True, False):
        assert watch.check(link.now_ns, link.hosts, expect_enabled=expect_enabled) == [
            (FaultCode.NODE_FAULT, f"node {f.node_id} ({f.name}) in FAULT (SENSOR)")
        ]


def test_every_fault_bit_is_named(link: Link, hand: HandConfig) -> None:
    watch = NodeWatch(hand.safety)
    watch.arm(link.hosts)
    pair = link.pairs[0]
    pair.estop(link.now_ns)
    link.tick()  # the node reports FAULT(ESTOP), in its feedback and a Status
    pair.tick(link.now_ns, tdt=[parse_sim(hand).tdt.range + 0.1, 0.0, 0.0])
    f = hand.fingers[0]
    assert watch.check(link.now_ns, link.hosts, expect_enabled=True) == [
        (FaultCode.ESTOP, f"node {f.node_id} ({f.name}) in FAULT (ESTOP, SENSOR)")
    ]


def test_a_node_in_fault_without_a_bit_is_a_node_fault(
    hand: HandConfig, protocol: Protocol
) -> None:
    """Firmware that reports FAULT and names no reason still stops the hand."""
    f = hand.fingers[1]
    layouts = FingerLayouts.for_node(protocol, f.node_id)
    node = FingerNode(f, layouts)
    node.receive(layouts.heartbeat.frame_id, layouts.heartbeat.encode(0, (2, 10)), 0)
    fault = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 2, 0)
    node.receive(layouts.feedback.frame_id, layouts.feedback.encode(0, fault), 0)
    assert NodeWatch(hand.safety).check(0, [node], expect_enabled=False) == [
        (FaultCode.NODE_FAULT, f"node {f.node_id} ({f.name}) in FAULT (no bits)")
    ]


def test_a_node_in_fault_by_estop_is_an_estop(link: Link, hand: HandConfig) -> None:
    watch = NodeWatch(hand.safety)
    watch.arm(link.hosts)
    link.pairs[1].estop(link.now_ns)
    now = link.tick()
    f = hand.fingers[1]
    assert watch.check(now, link.hosts, expect_enabled=True) == [
        (FaultCode.ESTOP, f"node {f.node_id} ({f.name}) in FAULT (ESTOP)")
    ]


def reboot_and_wait(link: Link, finger: int) -> None:
    """Reboot one node for 5 ms and run until the host has counted it.

    The host sees a reboot as the uptime going back between two heartbeats it accepted. The
    first heartbeat after the boot is lost to the counter check, the second says 100 ms: so
    the node first runs until it has said more than that.
    """
    pair = link.pairs[finger]
    while pair.host.uptime_ms is None or pair.host.uptime_ms <= 100:
        link.tick()
    before = pair.host.reboots
    pair.node.reboot(link.now_ns, 5 * MS)
    for _ in range(1000):
        link.tick()
        if pair.host.reboots > before:
            return
    raise AssertionError("the reboot was never seen")


def test_every_reboot_after_arming_is_a_fault(link: Link, hand: HandConfig) -> None:
    watch = NodeWatch(hand.safety)
    reboot_and_wait(link, 1)  # before torque flows: not a fault
    watch.arm(link.hosts)
    for pair in link.pairs:
        pair.command("enable", link.now_ns)
    now = link.tick()
    assert watch.check(now, link.hosts, expect_enabled=True) == []
    reboot_and_wait(link, 1)
    assert link.pairs[1].host.reboots == 2
    f = hand.fingers[1]
    found = watch.check(link.now_ns, link.hosts, expect_enabled=True)
    assert (FaultCode.NODE_REBOOT, f"node {f.node_id} ({f.name}) rebooted") in found
    assert set(codes(found)) == {FaultCode.NODE_REBOOT, FaultCode.NODE_STATE}


def test_an_unarmed_watch_reports_no_reboot(link: Link, hand: HandConfig) -> None:
    reboot_and_wait(link, 0)
    found = NodeWatch(hand.safety).check(link.now_ns, link.hosts, expect_enabled=False)
    assert found == []


# -- TdtMonitor --------------------------------------------------------------------------------


def monitor(hand: HandConfig, **safety: float) -> TdtMonitor:
    hand = with_safety(hand, **safety)
    return TdtMonitor(hand.safety, hand.n_joints, hand.bus.period_s, hand.joint_names)


def window(hand: HandConfig) -> int:
    return round(hand.safety.tdt_window_s / hand.bus.period_s)


def test_a_new_monitor_expects_zero_torque_and_has_counted_nothing(hand: HandConfig) -> None:
    zero = np.zeros(hand.n_joints)
    mon = monitor(hand)  # no reset: what a monitor expects before it is told anything
    off = np.full(hand.n_joints, 1.01 * hand.safety.tdt_tolerance)
    for _ in range(window(hand) - 1):
        assert mon.update(zero, off) == []
    assert codes(mon.update(zero, off)) == [FaultCode.TDT_MISMATCH] * hand.n_joints
    quick = monitor(hand, tdt_window_s=hand.bus.period_s)  # any mismatch shows at once
    assert quick.update(zero, zero) == []


def test_a_mismatch_is_a_fault_once_it_has_held_for_the_window(hand: HandConfig) -> None:
    mon = monitor(hand)
    applied = np.full(hand.n_joints, 0.2)
    mon.reset(applied)
    tolerance = hand.safety.tdt_tolerance + hand.safety.tdt_tolerance_rel * 0.2
    reading = applied.copy()
    reading[4] = 0.2 + 1.01 * tolerance
    for k in range(1, window(hand)):
        assert mon.update(applied, reading) == [], f"tick {k}"
    found = mon.update(applied, reading)
    name = hand.joint_names[4]
    assert found == [
        (
            FaultCode.TDT_MISMATCH,
            f"{name}: TDT {reading[4]:+.4f} N·m, expected +0.2000 N·m for {window(hand)} ticks",
        )
    ]
    assert mon.update(applied, reading) != []  # it goes on while it holds


@pytest.mark.parametrize(
    ("rate_hz", "ticks"), [(250.0, 13), (750.0, 38), (1000.0, 50), (333.0, 17)]
)
def test_a_mismatch_window_is_never_shorter_than_its_seconds_at_any_loop_rate(
    hand: HandConfig, rate_hz: float, ticks: int
) -> None:
    """50 ms at 250 Hz is 12.5 ticks: a mismatch held for 12 (48 ms) is not yet a fault,
    the 13th (52 ms) is."""
    assert hand.safety.tdt_window_s == 0.05
    dt = 1.0 / rate_hz
    mon = TdtMonitor(hand.safety, hand.n_joints, dt, hand.joint_names)
    zero = np.zeros(hand.n_joints)
    mon.reset(zero)
    off = np.full(hand.n_joints, 1.01 * hand.safety.tdt_tolerance)
    for k in range(1, ticks):
        assert mon.update(zero, off) == [], f"tick {k} of {ticks}"
    assert (ticks - 1) * dt < hand.safety.tdt_window_s <= ticks * dt
    assert codes(mon.update(zero, off)) == [FaultCode.TDT_MISMATCH] * hand.n_joints


def test_a_reading_exactly_at_the_tolerance_is_within_it(hand: HandConfig) -> None:
    mon = monitor(hand, tdt_window_s=hand.bus.period_s)  # a window of one tick
    zero = np.zeros(hand.n_joints)
    mon.reset(zero)  # the expectation stays exactly 0: the tolerance is the absolute one
    edge = np.full(hand.n_joints, hand.safety.tdt_tolerance)
    for reading in (edge, -edge):
        assert mon.update(zero, reading) == []
    beyond = np.nextafter(edge, np.inf)
    assert len(mon.update(zero, beyond)) == hand.n_joints


def test_vectors_of_another_length_are_refused(hand: HandConfig) -> None:
    mon = monitor(hand)
    n = hand.n_joints
    with pytest.raises(ValueError, match="zip"):
        mon.update(np.zeros(n), np.zeros(n - 1))
    with pytest.raises(ValueError, match="zip"):
        mon.update(np.zeros(n - 1), np.zeros(n))


def test_one_good_reading_restarts_the_mismatch_window(hand: HandConfig) -> None:
    mon = monitor(hand)
    applied = np.zeros(hand.n_joints)
    mon.reset(applied)
    bad = np.full(hand.n_joints, 1.01 * hand.safety.tdt_tolerance)
    for _ in range(window(hand) - 1):
        assert mon.update(applied, bad) == []
    assert mon.update(applied, applied) == []
    for _ in range(window(hand) - 1):
        assert mon.update(applied, -bad) == []
    assert len(mon.update(applied, -bad)) == hand.n_joints


@pytest.mark.parametrize("torque", [0.3, -0.3, 0.0])
def test_the_tolerance_is_absolute_plus_relative_to_the_expected_torque(
    hand: HandConfig, torque: float
) -> None:
    tolerance = hand.safety.tdt_tolerance + hand.safety.tdt_tolerance_rel * abs(torque)
    for margin, faults in ((0.99, False), (1.01, True)):
        for sign in (1.0, -1.0):
            mon = monitor(hand)
            applied = np.full(hand.n_joints, torque)
            mon.reset(applied)
            reading = applied + sign * margin * tolerance
            found = []
            for _ in range(window(hand)):
                found = mon.update(applied, reading)
            assert bool(found) is faults, (margin, sign)


def test_the_expected_torque_lags_the_command_by_the_configured_time_constant(
    hand: HandConfig,
) -> None:
    """After a step of the command, a reading that follows the step at once is a mismatch
    from the first tick the lagged expectation leaves the tolerance."""
    dt, lag = hand.bus.period_s, hand.safety.tdt_lag_s
    tol, rel = hand.safety.tdt_tolerance, hand.safety.tdt_tolerance_rel
    step = 2.0 * tol  # small, so the lag decides when the reading is off
    # Implicit Euler of lag · de/dt = a - e, from e = 0: e_k = step · (1 - (lag/(lag+dt))^k).
    first_off = next(
        k
        for k in range(1, 10_000)
        if abs(step - step * (1 - (lag / (lag + dt)) ** k))
        <= tol + rel * step * (1 - (lag / (lag + dt)) ** k)
    )
    assert first_off > 2  # the lag matters for this step
    mon = monitor(hand, tdt_window_s=dt)  # a window of one tick: a fault as soon as it is off
    mon.reset(np.zeros(hand.n_joints))
    applied = np.full(hand.n_joints, step)
    for k in range(1, first_off):
        assert len(mon.update(applied, applied)) == hand.n_joints, f"tick {k}"
    assert mon.update(applied, applied) == []


def test_a_window_shorter_than_a_tick_is_one_tick(hand: HandConfig) -> None:
    mon = monitor(hand, tdt_window_s=0.0, tdt_stuck_window_s=0.0, tdt_stuck_still_s=0.0)
    zero = np.zeros(hand.n_joints)
    mon.reset(zero)
    off = np.full(hand.n_joints, 1.0)
    assert codes(mon.update(zero, off)) == [FaultCode.TDT_MISMATCH] * hand.n_joints
    mon.reset(zero)
    moving = np.full(hand.n_joints, 2 * hand.safety.tdt_stuck_min_change)
    still = np.full(hand.n_joints, hand.safety.tdt_stuck_min_change / 4)
    mon2 = monitor(hand, tdt_stuck_window_s=0.0)
    mon2.reset(zero)
    assert mon2.update(zero, still) == []
    assert mon2.update(moving, still) == []  # one repeat: not yet two ticks the same
    assert codes(mon2.update(zero, still)) == [FaultCode.TDT_STUCK] * hand.n_joints
    mon3 = monitor(hand, tdt_stuck_still_s=hand.bus.period_s)  # still for one tick: stuck
    mon3.reset(zero)
    assert mon3.update(zero, still) == []
    assert codes(mon3.update(zero, still)) == [FaultCode.TDT_STUCK] * hand.n_joints


def stuck_run(
    hand: HandConfig, swing: float, ticks: int, **safety: float
) -> list[tuple[int, list[tuple[FaultCode, str]]]]:
    """A reading fixed at 0.1 N·m while the command swings by ``swing`` around it; the
    findings of each tick that had any."""
    mon = monitor(hand, **safety)
    base = 0.1
    mon.reset(np.full(hand.n_joints, base))
    reading = np.full(hand.n_joints, base)
    out = []
    for k in range(1, ticks + 1):
        applied = np.full(hand.n_joints, base + (swing if k % 2 else 0.0))
        found = mon.update(applied, reading)
        if found:
            out.append((k, found))
    return out


def test_a_reading_that_never_moves_while_the_command_does_is_stuck(hand: HandConfig) -> None:
    n = round(hand.safety.tdt_stuck_window_s / hand.bus.period_s)
    swing = 1.25 * hand.safety.tdt_stuck_min_change
    found = stuck_run(hand, swing, n + 1)
    # The first reading is the reference; each of the next n that repeats it counts.
    assert [k for k, _ in found] == [n + 1]
    assert found[0][1][0] == (
        FaultCode.TDT_STUCK,
        f"{hand.joint_names[0]}: TDT fixed at +0.1000 N·m for {n} ticks "
        f"while the command moved {swing:.4f} N·m",
    )
    assert codes(found[0][1]) == [FaultCode.TDT_STUCK] * hand.n_joints


def test_a_command_moving_exactly_the_minimum_change_is_enough(hand: HandConfig) -> None:
    n = round(hand.safety.tdt_stuck_window_s / hand.bus.period_s)
    change = hand.safety.tdt_stuck_min_change
    mon = monitor(hand)
    mon.reset(np.zeros(hand.n_joints))
    reading = np.full(hand.n_joints, change / 2)  # within the tolerance of either command
    found = []
    for k in range(1, n + 2):
        applied = np.full(hand.n_joints, change if k % 2 else 0.0)
        found = mon.update(applied, reading)
        assert bool(found) is (k == n + 1), f"tick {k}"
    assert codes(found) == [FaultCode.TDT_STUCK] * hand.n_joints


def test_a_still_reading_under_a_command_that_barely_moves_is_stuck_only_after_the_still_time(
    hand: HandConfig,
) -> None:
    still = round(hand.safety.tdt_stuck_still_s / hand.bus.period_s)
    found = stuck_run(hand, 0.75 * hand.safety.tdt_stuck_min_change, still + 1)
    assert [k for k, _ in found] == [still + 1]
    assert stuck_run(hand, 0.0, 3 * still, tdt_stuck_still_s=0.0) == []


def test_a_moving_reading_is_never_stuck(hand: HandConfig) -> None:
    mon = monitor(hand)
    applied = np.full(hand.n_joints, 0.1)
    mon.reset(applied)
    n = round(hand.safety.tdt_stuck_still_s / hand.bus.period_s)
    for k in range(2 * n):
        reading = applied + (1e-4 if k % 2 else -1e-4)
        assert mon.update(applied, reading) == []


def test_reset_starts_afresh_from_the_applied_torque(hand: HandConfig) -> None:
    mon = monitor(hand)
    applied = np.full(hand.n_joints, 0.25)
    mon.reset(np.zeros(hand.n_joints))
    for _ in range(window(hand) - 1):  # one tick short of a mismatch, and of nothing else
        mon.update(applied, np.zeros(hand.n_joints))
    mon.reset(applied)
    assert mon.expected == applied.tolist()
    # Expectation at the applied torque, the mismatch count back to zero, and no reading kept
    # to compare with: a full window of readings at the applied torque finds nothing.
    for _ in range(window(hand)):
        assert mon.update(applied, applied) == []
    for _ in range(window(hand) - 1):
        assert mon.update(applied, np.zeros(hand.n_joints)) == []


def test_a_reset_forgets_the_last_reading(hand: HandConfig) -> None:
    n = round(hand.safety.tdt_stuck_window_s / hand.bus.period_s)
    mon = monitor(hand)
    base = np.full(hand.n_joints, 0.1)
    mon.reset(base)
    swing = base + 1.25 * hand.safety.tdt_stuck_min_change
    for k in range(n):
        assert mon.update(swing if k % 2 else base, base) == []
    mon.reset(base)
    assert mon.update(swing, base) == []  # would have been the n-th repeat without the reset


# -- TickWatch ---------------------------------------------------------------------------------


def test_late_ticks_fault_when_consecutive_misses_reach_the_limit(hand: HandConfig) -> None:
    limit = hand.safety.max_consecutive_misses
    watch = TickWatch(hand.safety)
    for _ in range(limit - 1):
        assert watch.tick(1) == []
    assert watch.tick(0) == []  # an on-time tick starts the count again
    for _ in range(limit - 1):
        assert watch.tick(1) == []
    assert watch.tick(1) == [(FaultCode.LOOP_OVERRUN, f"{limit} consecutive ticks missed")]
    watch = TickWatch(hand.safety)
    watch.tick(limit - 1)
    assert watch.tick(-1) == []  # a clock that went back is no late tick either
    assert watch.tick(1) == []
    assert TickWatch(hand.safety).tick(limit) == [
        (FaultCode.LOOP_OVERRUN, f"{limit} consecutive ticks missed")
    ]
    assert TickWatch(hand.safety).tick(limit - 1) == []


def test_failed_sends_fault_when_consecutive_failures_reach_the_limit(hand: HandConfig) -> None:
    limit = hand.safety.max_consecutive_send_failures
    watch = TickWatch(hand.safety)
    for _ in range(limit - 1):
        assert watch.sent(False) == []
    assert watch.sent(True) == []
    for _ in range(limit - 1):
        assert watch.sent(False) == []
    assert watch.sent(False) == [
        (
            FaultCode.BUS_ERROR,
            f"{limit} consecutive ticks with command frames that could not be sent",
        )
    ]


def test_the_limits_are_the_configs(hand: HandConfig) -> None:
    safety = SafetyConfig(max_consecutive_misses=5, max_consecutive_send_failures=7)
    watch = TickWatch(safety)
    assert watch.tick(4) == [] and watch.tick(1) != []
    for _ in range(6):
        assert watch.sent(False) == []
    assert watch.sent(False) != []


def test_a_reading_still_at_a_steady_torque_is_given_its_lag_once_the_command_moves(
    hand: HandConfig,
) -> None:
    """A sensor quieter than its resolution reads the same at a steady torque for longer than
    the stuck window; when the command then ramps, the sensor has three of its lags to answer
    before it is stuck (the first fast ramp stopped such a hand at once)."""
    dt = hand.bus.period_s
    window_ticks = round(hand.safety.tdt_stuck_window_s / dt)
    answer = round(3 * hand.safety.tdt_lag_s / dt)
    assert 1 < answer < window_ticks
    mon = monitor(hand)
    steady = np.full(hand.n_joints, 0.1)
    mon.reset(steady)
    for _ in range(window_ticks + 20):  # still, the command too: not stuck
        assert mon.update(steady, steady) == []
    ramp = 0.02  # N·m a tick, the supervisor's rate limit at 1 kHz
    ticks_to_move = 1 + round(hand.safety.tdt_stuck_min_change / ramp)
    found = []
    for k in range(1, ticks_to_move + answer + 1):
        found = mon.update(steady + ramp * k, steady)
        if k < ticks_to_move + answer - 1:
            assert found == [], f"tick {k} of the ramp"
    # and a reading that still has not moved by then is stuck
    assert codes(found) == [FaultCode.TDT_STUCK] * hand.n_joints


def test_a_node_s_own_watchdog_says_whose_its_timeout_is(link: Link, hand: HandConfig) -> None:
    """A node's TIMEOUT is its watchdog hearing no command: the host's stall or the bus's,
    not the node's. A host frozen within a tick read as the node's fault, said as one."""
    watch = NodeWatch(hand.safety)
    watch.arm(link.hosts)
    pair = link.pairs[0]
    now = link.now_ns
    for _ in range(30):  # 30 ms of the node's ticks with no command from the host
        now += 1_000_000
        pair.node.update(now)
        out: list[tuple[int, bytes]] = []
        pair.node.publish(now, [0.0] * pair.n, [0.0] * pair.n, out)
        for frame_id, data in out:
            pair.host.receive(frame_id, data, now)
    found = watch.check(now, link.hosts, expect_enabled=True)
    f = hand.fingers[0]
    assert (
        FaultCode.NODE_FAULT,
        f"node {f.node_id} ({f.name}) in FAULT (TIMEOUT): it heard no command for its 10 ms "
        "watchdog (the host stalled, or its commands did not reach it)",
    ) in found, found
