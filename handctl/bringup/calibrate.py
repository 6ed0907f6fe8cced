"""``handctl calibrate tdt``: measure each TDT sensor's offset and noise at zero torque.

Every node is enabled and held at zero torque by the normal Runtime and its supervisor, as a
recipe of two zero-torque phases would be: ``settle`` (the fingers come to rest; not measured)
and ``measure``. Over ``measure`` each joint's TDT torque (with the hand config's current
calibration) is averaged: at zero torque it should read zero, so the new offset is the old one
minus the mean. The measurement is refused, naming the joint, when a joint moved (its angle
spanned more than ``max_span``: something pushed it, and the sensor read that push), when its
noise is implausible (above ``max_noise``, or exactly zero: a live sensor is never
bit-identical), or when the offset it would write is beyond ``max_offset`` or the joint's
``tau_max`` (a sensor that reads the joint's whole torque limit at zero torque is broken,
whatever ``max_offset`` allows). The offset written is judged, not the reading with the offset
configured: a hand config that already carries one would otherwise be moved by up to the bound
a run, without end.

The supervisor's TDT plausibility check compares the reading with the applied torque; an
uncalibrated sensor fails it by its very offset, which is what is being measured. For this run
only its tolerance is the largest ``device_tau_max`` of the hand (or ``max_offset``, if more):
at zero torque there is nothing for it to protect, and an offset just past ``max_offset`` is
the per-joint refusal this command exists to give (with ``max_offset`` as the tolerance, an
offset of 0.26 N·m stopped the run on TDT_MISMATCH, exit 3, with no table). Every other check
stays as the hand config has it.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from handctl.bringup.zero_recipe import in_memory_recipe, phase
from handctl.config import HandConfig
from handctl.online.clock import Tick
from handctl.online.loop import TickRecord
from handctl.online.recipes.schema import Recipe
from handctl.session import RunReport, RunRequest, run_recipe
from handctl.stopsignals import StopSignals

SETTLE = "settle"
MEASURE = "measure"


@dataclass(frozen=True)
class CalibrationLimits:
    """What a measurement must meet to be written."""

    # rad, a joint's angle range over the measurement: a finger hanging at zero torque still
    # creeps under gravity for seconds (on the simulated hand some 0.08 rad a second after
    # two seconds); a push or a swing moves it further
    max_span: float = 0.1
    max_noise: float = 0.02  # N·m, standard deviation of the TDT reading
    max_offset: float = 0.25  # N·m, the largest offset taken as a sensor's


class TdtSampler:
    """A ``RecordSink`` that accumulates the TDT readings and angles of the measure phase.

    Running sums (shifted by the first sample, so small differences keep their precision)
    rather than the samples: a tick adds a few vector operations, whatever the length."""

    def __init__(self, n: int) -> None:
        self.count = 0
        self._ref = np.zeros(n)
        self._sum = np.zeros(n)
        self._sumsq = np.zeros(n)
        self.angle_min = np.full(n, np.inf)
        self.angle_max = np.full(n, -np.inf)

    def begin_tick(self, tick: Tick) -> None:
        pass

    def note(self, kind: str, detail: str, tick: int) -> None:
        pass

    def push(self, record: TickRecord) -> None:
        if record.state != "running" or record.phase != MEASURE:
            return
        if self.count == 0:
            self._ref[:] = record.tdt
        d = record.tdt - self._ref
        self._sum += d
        self._sumsq += d * d
        np.minimum(self.angle_min, record.angle, out=self.angle_min)
        np.maximum(self.angle_max, record.angle, out=self.angle_max)
        self.count += 1

    def mean(self) -> np.ndarray:
        return self._ref + self._sum / max(self.count, 1)

    def std(self) -> np.ndarray:
        n = max(self.count, 1)
        var = self._sumsq / n - (self._sum / n) ** 2
        return np.sqrt(np.maximum(var, 0.0))


@dataclass(frozen=True)
class JointResult:
    name: str
    old_offset: float  # N·m
    new_offset: float  # N·m
    mean: float  # N·m, the reading at zero torque with the old offset
    noise: float  # N·m, standard deviation
    angle_span: float  # rad
    problem: str

    def as_dict(self) -> dict[str, Any]:
        return {
            "joint": self.name,
            "old_offset": self.old_offset,
            "new_offset": self.new_offset,
            "mean_nm": self.mean,
            "noise_nm": self.noise,
            "angle_span_rad": self.angle_span,
            "problem": self.problem,
        }


@dataclass
class Calibration:
    report: RunReport
    samples: int
    joints: list[JointResult]

    @property
    def problems(self) -> list[str]:
        return [f"{j.name}: {j.problem}" for j in self.joints if j.problem]

    @property
    def offsets(self) -> dict[str, float]:
        return {j.name: j.new_offset for j in self.joints}


def calibration_recipe(hand: HandConfig, settle_s: float, measure_s: float) -> Recipe:
    zero = [0.0] * hand.n_joints
    return in_memory_recipe(
        "calibrate_tdt",
        "zero torque on every joint: settle, then measure the TDT offsets",
        hand,
        [phase(SETTLE, zero, 0.0, settle_s), phase(MEASURE, zero, 0.0, measure_s)],
        0.0,
    )


def calibration_hand(hand: HandConfig, limits: CalibrationLimits) -> HandConfig:
    """The hand as the calibration run sees it: the TDT tolerance widened to the sensor's
    range (module docstring), nothing else changed."""
    widest = max(j.device_tau_max for j in hand.joints)
    tolerance = max(hand.safety.tdt_tolerance, limits.max_offset, widest)
    return dataclasses.replace(
        hand, safety=dataclasses.replace(hand.safety, tdt_tolerance=tolerance)
    )


def judge(hand: HandConfig, sampler: TdtSampler, limits: CalibrationLimits) -> list[JointResult]:
    """Each joint's new offset and what, if anything, makes the measurement unusable."""
    mean, std = sampler.mean(), sampler.std()
    span = sampler.angle_max - sampler.angle_min
    out = []
    for j, joint in enumerate(hand.joints):
        m, s, a = float(mean[j]), float(std[j]), float(span[j])
        problem = ""
        if sampler.count < 2 or not math.isfinite(a):
            problem = "no measurement (the run measured nothing)"
        elif a > limits.max_span:
            problem = (
                f"moved {a:.4f} rad during the measurement (at most "
                f"{limits.max_span:g}): keep the hand still and clear of anything"
            )
        elif s > limits.max_noise:
            problem = (
                f"noise {s:.4f} N·m is implausible (at most {limits.max_noise:g} N·m): "
                "check the sensor, its cable and its filter"
            )
        elif s == 0.0:
            problem = "the reading did not change at all: a live sensor is never so still"
        elif abs(joint.tdt.offset - m) > min(limits.max_offset, joint.tau_max):
            # the offset that would be written is judged, not this run's change to it: an
            # offset already in the config plus a reading within the bound would otherwise
            # ratchet it by up to the bound a run. At zero torque a sensor reading the joint's
            # whole torque limit is broken whatever --max-offset allows
            bound = min(limits.max_offset, joint.tau_max)
            why = "" if bound == limits.max_offset else ", the joint's tau_max"
            problem = (
                f"offset {joint.tdt.offset - m:+.4f} N·m (the sensor reads {m:+.4f} N·m with "
                f"the configured {joint.tdt.offset:+.4f}) is implausible (at most {bound:g} "
                f"N·m{why}): check the sensor's mounting and its factory calibration"
            )
        out.append(
            JointResult(joint.name, joint.tdt.offset, joint.tdt.offset - m, m, s, a, problem)
        )
    return out


def calibrate_tdt(
    hand: HandConfig,
    *,
    bus: str = "sim",
    settle_s: float = 2.0,
    measure_s: float = 1.0,
    limits: CalibrationLimits = CalibrationLimits(),
    lockstep: bool | None = None,
    seed: int = 0,
    sim_faults: Path | None = None,
    reset_node_faults: bool = False,
    accept_missed_deadlines: bool = False,
    realtime_priority: bool = False,
    signals: StopSignals | None = None,
) -> Calibration:
    """Run the zero-torque measurement on ``bus`` and judge it; writes nothing. ``signals``:
    the stop signals taken over by the caller, who must see the ones that came after the hand
    had stopped (``StopSignals.ignored``) before it writes; None: taken over here."""
    run_hand = calibration_hand(hand, limits)
    recipe = calibration_recipe(run_hand, settle_s, measure_s)
    sampler = TdtSampler(hand.n_joints)
    report = run_recipe(
        RunRequest(
            hand=run_hand,
            recipe=recipe,
            bus=bus,
            lockstep=lockstep,
            seed=seed,
            sim_faults=sim_faults,
            reset_node_faults=reset_node_faults,
            accept_missed_deadlines=accept_missed_deadlines,
            realtime_priority=realtime_priority,
        ),
        recorder=sampler,
        signals=signals,
    )
    return Calibration(report, sampler.count, judge(hand, sampler, limits))
