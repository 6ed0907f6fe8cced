"""Perturbed models of the simulated hand: the set a plan is scored over and a bench runs on.

A torque plan that works on one model only is tuned to it, not planned: the contact forces of
an enveloping grasp are not unique (paper §4), so open-loop torques that turn the pair on one
model stall or slip on another. Each model here varies what a real tendon-driven hand does
not know, by family (``FAMILIES``; the defaults of ``Spread`` are the ranges below):

- ``contact``: every Coulomb coefficient on its own, ±50 % (rubber pads age, wood varies);
- ``joint_dynamics``: viscous damping and dry (tendon) friction, log-uniform ×0.3..×3, the
  range sim-to-real in-hand work randomises joint damping over, because nobody measures a
  tendon's friction to 10 %; armature and the drive's lag ×0.5..×2. One factor for the hand,
  and each joint a little off it (log-uniform ×0.8..×1.25, ``JOINT_SPREAD``): tendons share a
  design but not their sheaths;
- ``objects``: each cylinder's mass ±50 % and radius ±20 %, on its own (the recipe's nominal
  radius is then wrong for both, differently);
- ``placement``: the pair put down ±4 mm off its place along the table, with 0..6 mm between
  the cylinders when they are configured 2 mm apart, as the shipped hand's are (a gap
  configured otherwise moved by as much; one object shifted alone; three or more shifted as a
  row, each gap between neighbours moved as the pair's);
- ``start_pose``: every initial joint angle ±0.1 rad (within the soft limits);
- ``sensors``: the TDT's per-sensor bias and white noise ×0.5..×2 of the configured ones.

Cylinders are always put back as high above the table as configured (on it, where the
configured ones lie on it), side by side at their configured gaps, moved by the drawn one, and
one resting on others back on them, at its configured gaps from them, so the scene stays valid
(no start in collision between objects) and stays the hand's.
``Spread.only(family)`` varies one family and keeps the rest nominal, which is how a bench
tells which family a recipe is fragile to.
"""

from __future__ import annotations

import dataclasses
import itertools
import math
from collections.abc import Sequence
from dataclasses import dataclass
from types import MappingProxyType
from typing import Any, Protocol

import numpy as np

from handctl.config import HandConfig
from handctl.sim.params import (
    MIN_FRICTION,
    START_MARGIN,
    FrictionParams,
    ObjectParams,
    SimParams,
)
from handctl.sim.placement import resting_on

#: m, the gap of the shipped pair, from which a drawn gap moves any configured one.
SIDE_GAP = 0.002
#: each joint's own factor around the hand's, log-uniform within [1 / this, this]
JOINT_SPREAD = 1.25

Range = tuple[float, float]


@dataclass(frozen=True)
class Spread:
    """What the models vary and how far. ``±`` fields are relative half-ranges (0.5 = ±50 %)
    or absolute ones where a unit is given; ``Range`` fields are factors, drawn log-uniform
    between the two; ``gap`` is in m, None keeping the configured one."""

    friction: float = 0.5  # ± relative, each Coulomb coefficient on its own
    mass: float = 0.5  # ± relative, each cylinder on its own
    radius: float = 0.2  # ± relative, each cylinder on its own
    damping: Range = (0.3, 3.0)  # factor of the joints' viscous damping
    frictionloss: Range = (0.3, 3.0)  # factor of the joints' dry friction
    armature: Range = (0.5, 2.0)  # factor of the reflected motor inertia
    actuator_lag: Range = (0.5, 2.0)  # factor of the tendon drive's time constant
    placement: float = 0.004  # m, ± shift of the objects along the table
    # m, between the two cylinders of a pair configured SIDE_GAP apart (another configured
    # gap, or each of a row's, is moved by as much)
    gap: Range | None = (0.0, 0.006)
    initial_angles: float = 0.1  # rad, ± on every initial joint angle
    tdt_bias: Range = (0.5, 2.0)  # factor of the TDT bias's standard deviation
    tdt_noise: Range = (0.5, 2.0)  # factor of the TDT noise's standard deviation

    def as_dict(self) -> dict[str, Any]:
        return {
            k: (list(v) if isinstance(v, tuple) else v) for k, v in dataclasses.asdict(self).items()
        }

    @classmethod
    def nominal(cls) -> Spread:
        """No variation at all: every model is the configured hand."""
        return cls(
            0.0,
            0.0,
            0.0,
            (1.0, 1.0),
            (1.0, 1.0),
            (1.0, 1.0),
            (1.0, 1.0),
            0.0,
            None,
            0.0,
            (1.0, 1.0),
            (1.0, 1.0),
        )

    def only(self, family: str) -> Spread:
        """This spread in ``family`` (one of ``FAMILIES``), nothing elsewhere."""
        if family not in FAMILIES:
            raise ValueError(f"a family in {', '.join(FAMILIES)}, not {family!r}")
        keep = {k: getattr(self, k) for k in FAMILIES[family]}
        return dataclasses.replace(Spread.nominal(), **keep)


#: The families of what a model varies, by the fields of ``Spread`` they draw.
FAMILIES: dict[str, tuple[str, ...]] = {
    "contact": ("friction",),
    "joint_dynamics": ("damping", "frictionloss", "armature", "actuator_lag"),
    "objects": ("mass", "radius"),
    "placement": ("placement", "gap"),
    "start_pose": ("initial_angles",),
    "sensors": ("tdt_bias", "tdt_noise"),
}


@dataclass(frozen=True)
class Model:
    """One perturbed model: its scale factors (for the record) and the parameters."""

    index: int
    params: SimParams
    scales: dict[str, float]


class Draws(Protocol):
    """Where a model's numbers come from: a ``numpy`` generator, or ``Strata``."""

    def uniform(self, low: float, high: float) -> float: ...


class Strata:
    """Latin-hypercube draws for ``count`` models: the k-th number each model draws (the same
    parameter for every model, since ``perturb`` draws in a fixed order) comes from its own
    1/count-th of the range, the strata shuffled per parameter. Why: a plan scores every
    candidate on a handful of models, and a handful of independent draws over a dozen ranges
    leaves some end of some range out by chance (five draws miss the lightest third of the
    joint damping about one time in eight); stratified, every range is covered end to end, and each
    model is still one draw from the spread. ``start(i)`` before drawing model ``i``."""

    def __init__(self, rng: np.random.Generator, count: int) -> None:
        self._rng = rng
        self._count = count
        self._order: list[np.ndarray] = []  # per parameter, the models' strata
        self._model = 0
        self._k = 0

    def start(self, model: int) -> None:
        self._model, self._k = model, 0

    def uniform(self, low: float, high: float) -> float:
        if self._k == len(self._order):
            self._order.append(self._rng.permutation(self._count))
        stratum = int(self._order[self._k][self._model])
        self._k += 1
        u = (stratum + float(self._rng.random())) / self._count
        return float(low + u * (high - low))


def _log_uniform(rng: Draws, bounds: Range) -> float:
    low, high = bounds
    if low == high:
        return float(low)
    return float(math.exp(rng.uniform(math.log(low), math.log(high))))


def _per_joint(
    rng: Draws, values: tuple[float, ...], bounds: Range
) -> tuple[float, tuple[float, ...]]:
    """The hand's factor from ``bounds`` and each joint's value a little off it."""
    factor = _log_uniform(rng, bounds)
    if bounds[0] == bounds[1]:
        return factor, tuple(v * factor for v in values)
    own = (1 / JOINT_SPREAD, JOINT_SPREAD)
    return factor, tuple(v * factor * _log_uniform(rng, own) for v in values)


def perturb(params: SimParams, rng: Draws, spread: Spread, hand: HandConfig | None = None) -> Model:
    """Draw one model around ``params``; the factors are kept for provenance. ``hand`` (the
    soft limits) bounds the drawn initial angles; without it they are not varied."""
    fr = params.friction
    scales: dict[str, float] = {}
    values = {}
    for key in FrictionParams.__dataclass_fields__:
        factor = float(rng.uniform(1.0 - spread.friction, 1.0 + spread.friction))
        scales[f"friction.{key}"] = factor
        # never below the least coefficient the simulated hand takes: a hand whose contact is
        # as slippery as it may be (0.001) had half its models refused, in its own file's
        # name, and the planner simulated the others below it (found by an outside audit)
        values[key] = max(getattr(fr, key) * factor, MIN_FRICTION)
    masses = [float(rng.uniform(1.0 - spread.mass, 1.0 + spread.mass)) for _ in params.objects]
    radii = [float(rng.uniform(1.0 - spread.radius, 1.0 + spread.radius)) for _ in params.objects]
    for k, (m, r) in enumerate(zip(masses, radii, strict=True)):
        scales[f"mass.{k + 1}"] = m
        scales[f"radius.{k + 1}"] = r
    joints: dict[str, tuple[float, ...]] = {}
    for key in ("damping", "frictionloss", "armature", "actuator_lag"):
        scales[key], joints[key] = _per_joint(rng, getattr(params, key), getattr(spread, key))
    shift = float(rng.uniform(-spread.placement, spread.placement))
    gap = float(rng.uniform(*spread.gap)) if spread.gap is not None else None
    scales["placement_m"] = shift
    # one object on the table has no gap to vary (those on others follow what holds them)
    on_the_table = len(params.objects) - len(resting_on(params.objects, params.table_height))
    if gap is not None and on_the_table >= 2:
        scales["gap_m"] = gap
    initial = params.initial_angles
    if hand is not None and spread.initial_angles > 0:
        drawn = []
        for finger, angles in zip(hand.fingers, initial, strict=True):
            drawn.append(
                tuple(
                    float(
                        np.clip(
                            q + rng.uniform(-spread.initial_angles, spread.initial_angles),
                            j.angle_min + START_MARGIN,
                            j.angle_max - START_MARGIN,
                        )
                    )
                    for q, j in zip(angles, finger.joints, strict=True)
                )
            )
        initial = tuple(drawn)
    bias = _log_uniform(rng, spread.tdt_bias)
    noise = _log_uniform(rng, spread.tdt_noise)
    scales["tdt_bias"], scales["tdt_noise"] = bias, noise
    tdt = dataclasses.replace(
        params.tdt, bias=params.tdt.bias * bias, noise=params.tdt.noise * noise
    )
    out = _with(params, FrictionParams(**values), masses, radii, shift, gap)
    out = dataclasses.replace(
        out,
        initial_angles=initial,
        tdt=tdt,
        damping=joints["damping"],
        frictionloss=joints["frictionloss"],
        armature=joints["armature"],
        actuator_lag=joints["actuator_lag"],
    )
    return Model(-1, out, scales)


def _with(
    params: SimParams,
    friction: FrictionParams,
    mass: list[float],
    radius: list[float],
    shift: float = 0.0,
    gap: float | None = None,
    configured: SimParams | None = None,
) -> SimParams:
    """The scene with the objects scaled and put back as high above the table as
    configured, ``shift`` (m) along it from their configured middle: a pair side by side at
    its configured gap moved by ``gap - SIDE_GAP``; one object where it was; three or more
    in their configured order along the table, each neighbour's
    configured gap between surfaces moved by what ``gap`` moves a pair's (``SIDE_GAP`` to
    ``gap``, never below touching), so that objects scaled larger never start inside each
    other (an outside audit found four rods overlapping by up to 2.3 mm and kicked apart
    in the first 20 ms, and one object never shifted). An object resting on others
    (``placement.resting_on``) is no part of that row: it is put back on what holds it
    (``_on_top``). The gaps and heights kept are those of ``configured`` (``params`` unless
    given): the hand's, where ``params`` is a model drawn from it already."""
    given = (configured or params).objects
    stacked = resting_on(given, params.table_height)
    scaled = []
    for k, (obj, placed) in enumerate(zip(params.objects, given, strict=True)):
        r = obj.radius * radius[k]
        # as high above the table as configured: on it for a hand under gravity, where the
        # configured object lay; a hand in a horizontal plane (gravity 0) held its objects
        # above the table, and each model set them down on it, beyond the fingers' reach
        # (found by an outside audit). In nanometres, so that an object on the table is on it
        # to the bit.
        above = round(max(0.0, placed.y - placed.radius - params.table_height), 9)
        y = params.table_height + r + above
        scaled.append(dataclasses.replace(obj, radius=r, mass=obj.mass * mass[k], y=y))
    row = [k for k in range(len(scaled)) if k not in stacked]
    objects = list(scaled)
    laid = _laid_out(
        [params.objects[k] for k in row],
        [scaled[k] for k in row],
        shift,
        gap,
        [given[k] for k in row],
    )
    for k, obj in zip(row, laid, strict=True):
        objects[k] = obj
    # from the bottom up: what holds an object lies lower, and is placed before it
    for k in sorted(stacked, key=lambda k: given[k].y):
        below = [(given[i], objects[i]) for i in stacked[k][:2]]
        objects[k] = _on_top(objects[k], given[k], below)
    return dataclasses.replace(params, friction=friction, objects=tuple(objects))


def _laid_out(
    current: Sequence[ObjectParams],
    objects: list[ObjectParams],
    shift: float,
    gap: float | None,
    given: Sequence[ObjectParams],
) -> list[ObjectParams]:
    """The objects on the table (or free), scaled (``objects``), laid out along it: from
    where they are (``current``), at the gaps and heights of ``given`` (``_with``)."""
    if not objects:
        return []
    mid = sum(o.x for o in current) / len(current) + shift
    if len(objects) == 2:
        # the configured gap, moved by what a drawn one moves ``SIDE_GAP``: a pair configured
        # 20 mm apart was pushed to 2 mm in every model, in families that vary no placement
        # (found by an outside audit); in nanometres, as the height
        a, b = given
        between = round(max(0.0, abs(b.x - a.x) - a.radius - b.radius), 9)
        gap = between if gap is None else max(0.0, gap + (between - SIDE_GAP))
        a, b = objects
        left, right = (a, b) if a.x <= b.x else (b, a)
        # about the middle of the gap, not of the centres: those of two radii are not the
        # same point, and a pair of two radii moved by half their difference in every
        # model, even one that drew nothing (found beside an outside audit's stack); of one
        # radius, it adds exactly zero, and the shipped hands' models are what they were
        was_left, was_right = (current[0], current[1]) if a.x <= b.x else (current[1], current[0])
        mid += (was_left.radius - was_right.radius) / 2
        left = dataclasses.replace(left, x=mid - gap / 2 - left.radius)
        right = dataclasses.replace(right, x=mid + gap / 2 + right.radius)
        return [left, right] if a.x <= b.x else [right, left]
    if len(objects) == 1:
        return [dataclasses.replace(objects[0], x=objects[0].x + shift)]
    return _in_a_row(current, objects, shift, gap, given)


def _in_a_row(
    current: Sequence[ObjectParams],
    scaled: list[ObjectParams],
    shift: float,
    gap: float | None,
    configured: Sequence[ObjectParams],
) -> list[ObjectParams]:
    """Three or more objects laid out along the table in their configured order, their
    configured gaps kept (moved by ``gap - SIDE_GAP`` when ``gap`` is drawn), the row's
    middle (``current``'s) moved by ``shift``; the gaps are ``configured``'s."""
    order = sorted(range(len(scaled)), key=lambda k: current[k].x)
    given = [current[k] for k in order]
    gaps = []
    for a, b in itertools.pairwise([configured[k] for k in order]):
        between = max(0.0, (b.x - b.radius) - (a.x + a.radius))
        gaps.append(between if gap is None else max(0.0, between + gap - SIDE_GAP))
    middle = ((given[0].x - given[0].radius) + (given[-1].x + given[-1].radius)) / 2 + shift
    width = sum(2 * scaled[k].radius for k in order) + sum(gaps)
    out = list(scaled)
    edge = middle - width / 2
    for n, k in enumerate(order):
        out[k] = dataclasses.replace(scaled[k], x=edge + scaled[k].radius)
        edge += 2 * scaled[k].radius + (gaps[n] if n < len(gaps) else 0.0)
    return out


def _on_top(
    obj: ObjectParams,
    placed: ObjectParams,
    below: Sequence[tuple[ObjectParams, ObjectParams]],
) -> ObjectParams:
    """``obj`` (scaled) put back on what holds it: ``below``, each as configured and as
    already put back in this model, nearest first. Laid out in the row along the table, an
    object stacked on another was set beside it, at its own height, over nothing: it fell at
    the first step, and every model but the nominal one was a scene not the hand's (found by
    an outside audit).

    Each contact keeps its configured gap between surfaces, so the object moves with what
    holds it, by the change of that one's radius and its own: along the line of their
    centres on one object, and where the two circles of such centres meet on two (the side
    it was configured on), or as on the nearest alone where they do not (two grown apart
    beyond its reach: then it clears the other one)."""

    def reach(conf: ObjectParams, now: ObjectParams) -> float:
        apart = math.hypot(placed.x - conf.x, placed.y - conf.y)
        return apart - conf.radius - placed.radius + now.radius + obj.radius

    (conf_a, a), *rest = below
    reach_a = reach(conf_a, a)
    if rest:
        conf_b, b = rest[0]
        side = (conf_b.x - conf_a.x) * (placed.y - conf_a.y) - (conf_b.y - conf_a.y) * (
            placed.x - conf_a.x
        )
        met = _circles_meet(a, reach_a, b, reach(conf_b, b), 1.0 if side >= 0 else -1.0)
        if met is not None:
            return dataclasses.replace(obj, x=met[0], y=met[1])
    apart = math.hypot(placed.x - conf_a.x, placed.y - conf_a.y)
    ux, uy = (placed.x - conf_a.x) / apart, (placed.y - conf_a.y) / apart
    return dataclasses.replace(obj, x=a.x + ux * reach_a, y=a.y + uy * reach_a)


def _circles_meet(
    a: ObjectParams, ra: float, b: ObjectParams, rb: float, side: float
) -> tuple[float, float] | None:
    """Where the circles of radius ``ra`` about ``a``'s centre and ``rb`` about ``b``'s meet,
    on the ``side`` (+1: left) of the line from ``a`` to ``b``; None where they do not."""
    dx, dy = b.x - a.x, b.y - a.y
    apart = math.hypot(dx, dy)
    if apart == 0.0 or apart > ra + rb or apart < abs(ra - rb):
        return None
    along = (ra * ra - rb * rb + apart * apart) / (2 * apart)
    across = side * math.sqrt(max(0.0, ra * ra - along * along))
    return (
        a.x + (along * dx - across * dy) / apart,
        a.y + (along * dy + across * dx) / apart,
    )


def model_set(
    params: SimParams,
    count: int,
    seed: int,
    spread: Spread,
    nominal: bool = True,
    hand: HandConfig | None = None,
) -> list[Model]:
    """``count`` models: the nominal one first (if ``nominal``), then draws from ``seed``,
    stratified over the spread (``Strata``)."""
    out: list[Model] = []
    if nominal and count > 0:
        out.append(Model(0, params, {}))
    strata = Strata(np.random.default_rng(seed), count - len(out))
    for k in range(count - len(out)):
        strata.start(k)
        model = perturb(params, strata, spread, hand)
        out.append(dataclasses.replace(model, index=len(out)))
    return out


def sized_models(
    params: SimParams,
    count: int,
    seed: int | tuple[int, ...],
    spread: Spread,
    radius: dict[int, Range],
    hand: HandConfig | None = None,
) -> list[Model]:
    """``count`` models of ``spread`` whose objects' radius factors are drawn within
    ``radius`` (object index to (low, high) factors of the configured radius; the other
    objects' within the spread's ±), stratified like ``model_set``'s. A range reaching out of
    the spread is cut to it where that leaves a range, so the models stay hands the spread
    covers. Why: a torque for objects of some size (a ``schedule`` entry) is planned on
    hands with objects of that size, and every other uncertainty of the spread."""
    # one stream for what the spread draws, one for the sizes
    spread_stream, size_stream = np.random.SeedSequence(seed).spawn(2)
    strata = Strata(np.random.default_rng(spread_stream), count)
    sizes = Strata(np.random.default_rng(size_stream), count)
    fixed = dataclasses.replace(spread, radius=0.0)
    lo_spread, hi_spread = 1.0 - spread.radius, 1.0 + spread.radius
    out: list[Model] = []
    for k in range(count):
        strata.start(k)
        sizes.start(k)
        model = perturb(params, strata, fixed, hand)
        factors = []
        for i in range(len(params.objects)):
            low, high = radius.get(i, (lo_spread, hi_spread))
            if max(low, lo_spread) < min(high, hi_spread):
                low, high = max(low, lo_spread), min(high, hi_spread)
            factors.append(sizes.uniform(low, high))
        sized = _with(
            model.params,
            model.params.friction,
            [1.0] * len(factors),
            factors,
            0.0,
            model.scales.get("gap_m"),
            params,
        )
        scales = dict(model.scales) | {f"radius.{i + 1}": f for i, f in enumerate(factors)}
        out.append(Model(k, sized, scales))
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
        "links": {},  # filled by ``hand_with``: keyed by finger name
        "joints": {
            "damping": list(p.damping),
            "frictionloss": list(p.frictionloss),
            "armature": list(p.armature),
            "stop_margin": p.stop_margin,
        },
        "actuator": {"lag": list(p.actuator_lag), "motor_tau_max": {}},  # as links
        "initial_angles": {},  # filled by ``hand_with``: keyed by finger name
        "objects": [
            {
                "name": o.name,
                "radius": o.radius,
                "length": o.length,
                "mass": o.mass,
                "x": o.x,
                "y": o.y,
                "angle": o.angle,
            }
            for o in p.objects
        ],
        "friction": dataclasses.asdict(p.friction)
        | ({"finger_finger": p.finger_finger_friction} if p.between_fingers else {}),
        "contact": {
            "timeconst": p.contact_timeconst,
            "dampratio": p.contact_dampratio,
            "between_fingers": p.between_fingers,
        },
        "tdt": dataclasses.asdict(p.tdt),
        "encoder": dataclasses.asdict(p.encoder),
    }


def hand_with(hand: HandConfig, params: SimParams, *, seed: int | None = None) -> HandConfig:
    """The same hand (same config hash: the sim section is not hashed) simulating ``params``,
    with ``seed`` for the sensors' noise and biases if given."""
    section = sim_section(params)
    section["initial_angles"] = {
        f.name: list(a) for f, a in zip(hand.fingers, params.initial_angles, strict=True)
    }
    first = 0
    for finger in hand.fingers:
        last = first + len(finger.joints)
        section["links"][finger.name] = [
            {"radius": link.radius, "mass": link.mass} for link in params.links[first:last]
        ]
        section["actuator"]["motor_tau_max"][finger.name] = list(params.motor_tau_max[first:last])
        first = last
    if seed is not None:
        section["seed"] = seed
    return dataclasses.replace(hand, sim=MappingProxyType(section))
