"""Watchdogs that turn what the nodes said (or did not say) into faults.

Each monitor keeps a few fixed-size arrays and is updated once per tick; none allocates per
joint per tick beyond small numpy temporaries, and none waits for anything.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from handctl.config import SafetyConfig
from handctl.drivers.finger import FingerNode, fault_names
from handctl.safety.faults import FaultCode
from handctl.safety.limits import FloatArray

ENABLED = 1
FAULT = 2
Finding = tuple[FaultCode, str]


class NodeWatch:
    """Feedback age, heartbeat age, device state and reboots of every node."""

    def __init__(self, safety: SafetyConfig) -> None:
        self.feedback_timeout_ns = int(safety.feedback_timeout_s * 1e9)
        self.heartbeat_timeout_ns = int(safety.heartbeat_timeout_s * 1e9)
        self._reboots: list[int] = []

    def arm(self, nodes: Sequence[FingerNode]) -> None:
        """Remember the reboot counts at the moment torque starts to flow."""
        self._reboots = [node.reboots for node in nodes]

    def check(self, now_ns: int, nodes: Sequence[FingerNode], expect_enabled: bool
              ) -> list[Finding]:
        found: list[Finding] = []
        for i, node in enumerate(nodes):
            who = f"node {node.node_id} ({node.finger.name})"
            if node.feedback_ns is None or now_ns - node.feedback_ns > self.feedback_timeout_ns:
                age = "never" if node.feedback_ns is None else \
                    f"{(now_ns - node.feedback_ns) / 1e6:.1f} ms ago"
                found.append((FaultCode.FEEDBACK_TIMEOUT, f"{who}: last valid feedback {age}"))
            if node.heartbeat_ns is None or \
                    now_ns - node.heartbeat_ns > self.heartbeat_timeout_ns:
                age = "never" if node.heartbeat_ns is None else \
                    f"{(now_ns - node.heartbeat_ns) / 1e6:.0f} ms ago"
                found.append((FaultCode.HEARTBEAT_LOST, f"{who}: last heartbeat {age}"))
            if i < len(self._reboots) and node.reboots > self._reboots[i]:
                found.append((FaultCode.NODE_REBOOT, f"{who} rebooted"))
            if node.state == FAULT:
                names = fault_names(node.fault_bits)
                code = FaultCode.ESTOP if "ESTOP" in names else FaultCode.NODE_FAULT
                found.append((code, f"{who} in FAULT ({', '.join(names) or 'no bits'})"))
            elif expect_enabled and node.state != ENABLED:
                found.append((FaultCode.NODE_STATE, f"{who} is {node.state_name}, "
                                                    "expected ENABLED"))
        return found


class TdtMonitor:
    """TDT torque against the applied command: a tolerance held over a window, and a sensor
    whose reading does not move at all while the command does (stuck)."""

    def __init__(self, safety: SafetyConfig, n_joints: int, dt: float,
                 names: Sequence[str]) -> None:
        self.names = tuple(names)
        self.tol = safety.tdt_tolerance
        self.rel = safety.tdt_tolerance_rel
        self.alpha = dt / (safety.tdt_lag_s + dt)
        self.window = max(1, round(safety.tdt_window_s / dt))
        self.stuck_window = max(2, round(safety.tdt_stuck_window_s / dt))
        self.min_change = safety.tdt_stuck_min_change
        self.expected = np.zeros(n_joints)
        self.mismatch_ticks = np.zeros(n_joints, dtype=np.int64)
        self.same_ticks = np.zeros(n_joints, dtype=np.int64)
        self.last_reading = np.full(n_joints, np.nan)
        self.cmd_lo = np.zeros(n_joints)
        self.cmd_hi = np.zeros(n_joints)

    def reset(self, applied: FloatArray) -> None:
        self.expected[:] = applied
        self.mismatch_ticks[:] = 0
        self.same_ticks[:] = 0
        self.last_reading[:] = np.nan

    def update(self, applied: FloatArray, reading: FloatArray) -> list[Finding]:
        """Fold one tick in: ``applied`` is what the nodes were last told, ``reading`` the TDT."""
        self.expected += (applied - self.expected) * self.alpha
        error = np.abs(reading - self.expected)
        over = error > self.tol + self.rel * np.abs(self.expected)
        self.mismatch_ticks = np.where(over, self.mismatch_ticks + 1, 0)
        same = reading == self.last_reading
        self.same_ticks = np.where(same, self.same_ticks + 1, 0)
        self.cmd_lo = np.where(same, np.minimum(self.cmd_lo, applied), applied)
        self.cmd_hi = np.where(same, np.maximum(self.cmd_hi, applied), applied)
        self.last_reading[:] = reading
        found: list[Finding] = []
        for j in np.flatnonzero(self.mismatch_ticks >= self.window):
            found.append((FaultCode.TDT_MISMATCH,
                          f"{self.names[j]}: TDT {reading[j]:+.3f} N·m, expected "
                          f"{self.expected[j]:+.3f} N·m for {self.window} ticks"))
        stuck = (self.same_ticks >= self.stuck_window) & (
            self.cmd_hi - self.cmd_lo >= self.min_change)
        for j in np.flatnonzero(stuck):
            found.append((FaultCode.TDT_STUCK,
                          f"{self.names[j]}: TDT fixed at {reading[j]:+.4f} N·m for "
                          f"{self.same_ticks[j]} ticks while the command moved "
                          f"{self.cmd_hi[j] - self.cmd_lo[j]:.3f} N·m"))
        return found


class TickWatch:
    """Late ticks and failed sends, counted consecutively."""

    def __init__(self, safety: SafetyConfig) -> None:
        self.max_misses = safety.max_consecutive_misses
        self.max_send_failures = safety.max_consecutive_send_failures
        self.consecutive_misses = 0
        self.consecutive_send_failures = 0

    def tick(self, missed: int) -> list[Finding]:
        """``missed``: ticks the clock skipped before this one (0 when on time)."""
        if missed <= 0:
            self.consecutive_misses = 0
            return []
        self.consecutive_misses += missed
        if self.consecutive_misses >= self.max_misses:
            return [(FaultCode.LOOP_OVERRUN,
                     f"{self.consecutive_misses} consecutive ticks missed")]
        return []

    def sent(self, ok: bool) -> list[Finding]:
        self.consecutive_send_failures = 0 if ok else self.consecutive_send_failures + 1
        if self.consecutive_send_failures >= self.max_send_failures:
            return [(FaultCode.BUS_ERROR,
                     f"{self.consecutive_send_failures} consecutive ticks with command frames "
                     "that could not be sent")]
        return []
