"""Perturbed models of the simulated hand: the set a plan is scored over and a bench runs on.

A torque plan that works on one model only is tuned to it, not planned: the contact forces of
an enveloping grasp are not unique (paper §4), so open-loop torques that turn the pair on one
friction coefficient may stall on another. Each model here scales what the real hand does not
know well: every Coulomb coefficient (independently, ±30 % by default: rubber pads age, wood
varies), the mass of the cylinders (±20 %) and their radius (±10 %, one draw for both, as two
cylinders cut from one rod). Cylinders that change size are put back on the table at rest and
side by side with the same 1 mm gap, so the scene stays valid (no start in collision).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from types import MappingProxyType
from typing import Any

import numpy as np

from handctl.config import HandConfig
from handctl.sim.params import FrictionParams, SimParams

#: m, the gap left between two cylinders put back side by side on the table.
SIDE_GAP = 0.002


@dataclass(frozen=True)
class Spread:
    """Relative half-ranges of the uniform perturbations (0.3 = ±30 %)."""

    friction: float = 0.3
    mass: float = 0.2
    radius: float = 0.1

    def as_dict(self) -> dict[str, float]:
        return dataclasses.asdict(self)


@dataclass(frozen=True)
class Model:
    """One perturbed model: its scale factors (for the record) and the parameters."""

    index: int
    params: SimParams
    scales: dict[str, float]


def perturb(params: SimParams, rng: np.random.Generator, spread: Spread) -> Model:
    """Draw one model around ``params``; the factors are kept for provenance."""
    fr = params.friction
    scales: dict[str, float] = {}
    values = {}
    for key in FrictionParams.__dataclass_fields__:
        factor = float(rng.uniform(1.0 - spread.friction, 1.0 + spread.friction))
        scales[f"friction.{key}"] = factor
        values[key] = getattr(fr, key) * factor
    mass = float(rng.uniform(1.0 - spread.mass, 1.0 + spread.mass))
    radius = float(rng.uniform(1.0 - spread.radius, 1.0 + spread.radius))
    scales["mass"] = mass
    scales["radius"] = radius
    return Model(-1, _with(params, FrictionParams(**values), mass, radius), scales)


def _with(params: SimParams, friction: FrictionParams, mass: float, radius: float) -> SimParams:
    objects = []
    mid = sum(o.x for o in params.objects) / len(params.objects)
    for obj in params.objects:
        r = obj.radius * radius
        side = math.copysign(1.0, obj.x - mid) if obj.x != mid else 0.0
        x = mid + side * (r + SIDE_GAP / 2) if len(params.objects) == 2 else obj.x
        objects.append(dataclasses.replace(obj, radius=r, mass=obj.mass * mass,
                                           x=x, y=params.table_height + r))
    return dataclasses.replace(params, friction=friction, objects=tuple(objects))


def model_set(params: SimParams, count: int, seed: int, spread: Spread,
              nominal: bool = True) -> list[Model]:
    """``count`` models: the nominal one first (if ``nominal``), then draws from ``seed``."""
    rng = np.random.default_rng(seed)
    out: list[Model] = []
    if nominal and count > 0:
        out.append(Model(0, params, {}))
    while len(out) < count:
        model = perturb(params, rng, spread)
        out.append(dataclasses.replace(model, index=len(out)))
    return out


def sim_section(params: SimParams) -> dict[str, Any]:
    """``params`` back as a ``sim:`` mapping of a hand config (for a run through the bus)."""
    p = params
    return {
        "seed": p.seed,
        "timestep": p.timestep,
        "gravity": p.gravity,
        "table": {"height": p.table_height},
        "palm": {"half_width": p.palm_half_width, "thickness": p.palm_thickness},
        "links": [{"radius": link.radius, "mass": link.mass} for link in p.links],
        "joints": {"damping": p.damping, "frictionloss": p.frictionloss,
                   "armature": p.armature, "stop_margin": p.stop_margin},
        "actuator": {"lag": p.actuator_lag, "motor_tau_max": list(p.motor_tau_max)},
        "initial_angles": {},  # filled by ``hand_with``: keyed by finger name
        "objects": [{"name": o.name, "radius": o.radius, "length": o.length, "mass": o.mass,
                     "x": o.x, "y": o.y, "angle": o.angle} for o in p.objects],
        "friction": dataclasses.asdict(p.friction),
        "contact": {"timeconst": p.contact_timeconst, "dampratio": p.contact_dampratio},
        "tdt": dataclasses.asdict(p.tdt),
        "encoder": dataclasses.asdict(p.encoder),
    }


def hand_with(hand: HandConfig, params: SimParams, *, tdt_noise_scale: float = 1.0,
              seed: int | None = None) -> HandConfig:
    """The same hand (same config hash: the sim section is not hashed) simulating ``params``,
    with the TDT noise scaled (sensor noise is one of the things a bench varies)."""
    section = sim_section(params)
    section["initial_angles"] = {f.name: list(a) for f, a in zip(hand.fingers,
                                                                  params.initial_angles,
                                                                  strict=True)}
    section["tdt"]["noise"] = params.tdt.noise * tdt_noise_scale
    if seed is not None:
        section["seed"] = seed
    return dataclasses.replace(hand, sim=MappingProxyType(section))
