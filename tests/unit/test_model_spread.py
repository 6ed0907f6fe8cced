"""The set of perturbed hands: every family of what a real hand does not know is varied
within its documented range, one family at a time or all at once, and every drawn model is a
valid scene that the simulated hand loads (per-joint dynamics included)."""

from __future__ import annotations

import dataclasses
import itertools
import math

import numpy as np
import pytest

from handctl.config import HandConfig
from handctl.errors import ConfigError
from handctl.planning.models import (
    FAMILIES,
    Spread,
    hand_with,
    model_set,
    perturb,
    sized_models,
)
from handctl.sim.params import ObjectParams, SimParams, parse_sim
from handctl.sim.placement import resting_on, unsupported
from handctl.sim.plant import Plant


@pytest.fixture(scope="module")
def params(hand: HandConfig) -> SimParams:
    return parse_sim(hand)


def _gap(p: SimParams) -> float:
    """Along the table (cylinders of two radii touch the table at two heights of centre)."""
    a, b = p.objects
    return abs(b.x - a.x) - a.radius - b.radius


def test_the_default_spread_draws_within_every_range(hand: HandConfig, params: SimParams) -> None:
    spread = Spread()
    models = model_set(params, 40, 5, spread, nominal=False, hand=hand)
    damping = np.array([m.params.damping for m in models]) / np.array(params.damping)
    # one factor for the hand in 0.3..3, each joint within x1.25 of it
    assert damping.min() >= 0.3 / 1.25 - 1e-9 and damping.max() <= 3.0 * 1.25 + 1e-9
    assert damping.max() > 1.5 and damping.min() < 0.6  # the range is used, not a corner
    assert any(len(set(np.round(row, 9))) > 1 for row in damping)  # joints differ
    lags = np.array([m.params.actuator_lag for m in models]) / np.array(params.actuator_lag)
    assert lags.min() >= 0.5 / 1.25 - 1e-9 and lags.max() <= 2.0 * 1.25 + 1e-9
    mid0 = sum(o.x for o in params.objects) / 2
    for m in models:
        p = m.params
        a, b = p.objects
        # each cylinder on its own: different radii and masses
        assert a.radius != b.radius and a.mass != b.mass
        for obj, nominal in zip(p.objects, params.objects, strict=True):
            assert 0.8 - 1e-9 <= obj.radius / nominal.radius <= 1.2 + 1e-9
            assert 0.5 - 1e-9 <= obj.mass / nominal.mass <= 1.5 + 1e-9
            assert obj.y == pytest.approx(p.table_height + obj.radius)  # resting
        assert -1e-9 <= _gap(p) <= 0.006 + 1e-9
        assert abs((a.x + b.x) / 2 - mid0) <= 0.004 + abs(a.radius - b.radius) / 2 + 1e-9
        assert a.x < b.x  # object 1 stays on the first finger's side
        for finger, angles, start in zip(
            hand.fingers, p.initial_angles, params.initial_angles, strict=True
        ):
            for q, q0, joint in zip(angles, start, finger.joints, strict=True):
                assert abs(q - q0) <= 0.1 + 1e-9
                assert joint.angle_min <= q <= joint.angle_max
        assert 0.5 - 1e-9 <= p.tdt.noise / params.tdt.noise <= 2.0 + 1e-9
        assert 0.5 - 1e-9 <= p.tdt.bias / params.tdt.bias <= 2.0 + 1e-9


@pytest.mark.parametrize("family", sorted(FAMILIES))
def test_one_family_varies_only_its_own_parameters(
    hand: HandConfig, params: SimParams, family: str
) -> None:
    model = perturb(params, np.random.default_rng(11), Spread().only(family), hand)
    p = model.params
    changed = {
        "contact": p.friction != params.friction,
        "joint_dynamics": (p.damping, p.frictionloss, p.armature, p.actuator_lag)
        != (params.damping, params.frictionloss, params.armature, params.actuator_lag),
        "objects": [(o.radius, o.mass) for o in p.objects]
        != [(o.radius, o.mass) for o in params.objects],
        "placement": [o.x for o in p.objects] != [o.x for o in params.objects]
        and [(o.radius, o.mass) for o in p.objects] == [(o.radius, o.mass) for o in params.objects],
        "start_pose": p.initial_angles != params.initial_angles,
        "sensors": p.tdt != params.tdt,
    }
    assert changed[family]
    assert not any(v for k, v in changed.items() if k != family)


def test_a_drawn_model_is_a_hand_config_the_simulation_loads(
    hand: HandConfig, params: SimParams
) -> None:
    model = model_set(params, 2, 3, Spread(), hand=hand)[1]
    again = parse_sim(hand_with(hand, model.params, seed=4))
    assert again.damping == pytest.approx(model.params.damping)
    assert again.actuator_lag == pytest.approx(model.params.actuator_lag)
    plant = Plant(hand, again)
    assert plant.model.dof_damping[:9] == pytest.approx(model.params.damping)
    assert plant.model.actuator_dynprm[:, 0] == pytest.approx(model.params.actuator_lag)


def test_per_joint_dynamics_must_give_one_value_per_joint(hand: HandConfig) -> None:
    section = dict(hand.sim)
    section["joints"] = {**section["joints"], "damping": [0.01] * 8}
    with pytest.raises(ConfigError) as info:
        parse_sim(dataclasses.replace(hand, sim=section))
    assert info.value.key == "sim.joints.damping" and "9" in info.value.expected


@pytest.mark.parametrize("seed", [0, 7, 11])
def test_a_plan_s_few_models_cover_every_range_end_to_end(
    hand: HandConfig, params: SimParams, seed: int
) -> None:
    """The planner draws its models stratified: of five, one lies in each fifth of every
    range (the joint damping's lightest fifth, ×0.3..×0.48, among them), where five
    independent draws leave some fifth of some range out almost always."""
    count = 5
    models = model_set(params, count + 1, seed, Spread(), hand=hand)[1:]  # nominal first
    spread = Spread()

    def fifths(values: list[float], low: float, high: float) -> list[int]:
        return sorted(int((v - low) / (high - low) * count) for v in values)

    every = list(range(count))
    scales = [m.scales for m in models]
    for key in ("damping", "frictionloss", "armature", "actuator_lag", "tdt_bias"):
        low, high = getattr(spread, key)
        logs = [np.log(s[key]) for s in scales]
        assert fifths(logs, np.log(low), np.log(high)) == every, key
    for key, half in (("mass.1", spread.mass), ("radius.2", spread.radius)):
        assert fifths([s[key] for s in scales], 1 - half, 1 + half) == every, key
    assert fifths([s["gap_m"] for s in scales], *(spread.gap or (0.0, 0.0))) == every


def test_a_schedule_entry_s_models_have_objects_of_its_sizes(
    hand: HandConfig, params: SimParams
) -> None:
    """``sized_models``: the ranged object's radius is drawn within its range (cut to the
    spread's ±), the other's within the spread's, every other factor as the spread draws
    it; the same seed gives the same models, and the scene stays a pair on the table."""
    from handctl.planning.models import sized_models

    spread = Spread()
    models = sized_models(params, 8, (7, 5, 0), spread, {0: (1.1, 1.4)}, hand)
    again = sized_models(params, 8, (7, 5, 0), spread, {0: (1.1, 1.4)}, hand)
    assert [m.scales for m in models] == [m.scales for m in again]
    first = [m.scales["radius.1"] for m in models]
    second = [m.scales["radius.2"] for m in models]
    assert all(1.1 <= f <= 1.0 + spread.radius for f in first)
    assert all(1.0 - spread.radius <= f <= 1.0 + spread.radius for f in second)
    # stratified: the eight cover the cut range end to end, a stratum each
    assert max(first) - min(first) > 0.7 * (1.0 + spread.radius - 1.1)
    assert len({round(m.scales["damping"], 6) for m in models}) == 8
    for m, f1, f2 in zip(models, first, second, strict=True):
        a, b = m.params.objects
        assert a.radius == pytest.approx(params.objects[0].radius * f1)
        assert b.radius == pytest.approx(params.objects[1].radius * f2)
        assert a.y == pytest.approx(m.params.table_height + a.radius)
        assert _gap(m.params) == pytest.approx(m.scales["gap_m"], abs=1e-9)


def _row(params: SimParams, count: int, gap: float) -> SimParams:
    """``params`` with ``count`` cylinders of the first's size in a row on the table,
    ``gap`` (m) between neighbours."""
    first = params.objects[0]
    objects = tuple(
        dataclasses.replace(first, name=f"rod{k}", x=k * (2 * first.radius + gap))
        for k in range(count)
    )
    return dataclasses.replace(params, objects=objects)


def test_one_object_is_shifted_and_has_no_gap(params: SimParams) -> None:
    """``placement`` moved only a pair: on a hand of one object its models were the nominal
    hand, recorded as shifted (found by an outside audit)."""
    one = dataclasses.replace(params, objects=params.objects[:1])
    for m in model_set(one, 6, 7000, Spread().only("placement"))[1:]:
        assert "gap_m" not in m.scales
        (obj,) = m.params.objects
        assert obj.x == pytest.approx(one.objects[0].x + m.scales["placement_m"], abs=1e-12)


def test_a_row_of_objects_never_starts_inside_each_other(
    hand: HandConfig, params: SimParams
) -> None:
    """Three or more objects were scaled where they stood: four rods 1 mm apart overlapped by
    up to 2.3 mm and were kicked apart in the first 20 ms (found by an outside audit). They
    keep their order and gaps now, the gaps moved as a pair's, the row shifted."""
    row = _row(params, 4, 0.001)
    for family in ("objects", "placement", "all"):
        spread = Spread() if family == "all" else Spread().only(family)
        for m in model_set(row, 8, 7000, spread)[1:]:
            objects = m.params.objects
            assert [o.name for o in sorted(objects, key=lambda o: o.x)] == [
                o.name for o in row.objects
            ]
            drawn = m.scales.get("gap_m")
            for a, b in itertools.pairwise(objects):
                between = (b.x - b.radius) - (a.x + a.radius)
                moved = 0.001 if drawn is None else max(0.0, 0.001 + drawn - 0.002)
                assert between == pytest.approx(moved, abs=1e-12), (family, m.index)
            left = objects[0].x - objects[0].radius
            right = objects[-1].x + objects[-1].radius
            given = (
                row.objects[0].x
                - row.objects[0].radius
                + row.objects[-1].x
                + row.objects[-1].radius
            ) / 2
            assert (left + right) / 2 == pytest.approx(given + m.scales["placement_m"], abs=1e-12)
            for o in objects:
                assert o.y == pytest.approx(m.params.table_height + o.radius)


def test_a_pair_keeps_its_configured_gap_and_height(params: SimParams) -> None:
    """Every perturbed model pushed a pair to 2 mm apart, whatever the hand configured and in
    families that vary no placement, and set every object down on the table, also on a hand
    in a horizontal plane (gravity 0) that holds its objects above it, beyond the fingers'
    reach there (found by an outside audit): the models were scored on scenes not the
    hand's. The configured gap is kept, moved by the drawn one's offset from 2 mm, and each
    object's height above the table is kept."""
    a, b = params.objects
    apart = dataclasses.replace(
        params,
        gravity=0.0,
        objects=(
            dataclasses.replace(a, x=a.x - 0.009, y=a.y + 0.015),
            dataclasses.replace(b, x=b.x + 0.009),
        ),
    )
    configured = _gap(apart)
    assert configured == pytest.approx(0.020)
    heights = [o.y - o.radius - apart.table_height for o in apart.objects]
    for family in ("contact", "objects", "placement"):
        for m in model_set(apart, 6, 7100, Spread().only(family))[1:]:
            drawn = m.scales.get("gap_m")
            expected = configured if drawn is None else configured + drawn - 0.002
            assert _gap(m.params) == pytest.approx(expected, abs=1e-9), (family, m.index)
            for obj, height in zip(m.params.objects, heights, strict=True):
                assert obj.y - obj.radius - m.params.table_height == pytest.approx(height)
    # a schedule entry's models, sized again from models already drawn: the gap drawn once
    for m in sized_models(apart, 4, (7, 5, 0), Spread(), {0: (1.1, 1.2)}):
        expected = configured + m.scales["gap_m"] - 0.002
        assert _gap(m.params) == pytest.approx(expected, abs=1e-9), m.index
        for obj, height in zip(m.params.objects, heights, strict=True):
            assert obj.y - obj.radius - m.params.table_height == pytest.approx(height)


def test_a_pair_of_two_radii_is_where_it_was_in_a_model_that_draws_nothing(
    params: SimParams,
) -> None:
    """The pair was laid out about the middle of its centres, which for two radii is not the
    middle of its gap: a pair of 20 and 25 mm moved 2.5 mm in every model, even one that
    varied nothing, and a drawn shift or gap moved it from there."""
    a, b = params.objects
    big = dataclasses.replace(b, radius=0.025, x=b.x + 0.005, y=b.y + 0.005)
    pair = dataclasses.replace(params, objects=(a, big))
    for m in model_set(pair, 3, 7000, Spread.nominal())[1:]:
        for obj, given in zip(m.params.objects, pair.objects, strict=True):
            assert (obj.x, obj.y) == pytest.approx((given.x, given.y), abs=1e-12)
    for m in model_set(pair, 6, 7000, Spread().only("placement"))[1:]:
        left, right = m.params.objects
        middle = (left.x + left.radius + right.x - right.radius) / 2
        was = (a.x + a.radius + big.x - big.radius) / 2
        assert middle == pytest.approx(was + m.scales["placement_m"], abs=1e-12)


#: m between the surfaces of an object and the one it rests on (``check`` allows 1 mm)
ON_TOP = 0.0005


def _surface_gap(a: ObjectParams, b: ObjectParams) -> float:
    return math.hypot(a.x - b.x, a.y - b.y) - a.radius - b.radius


def _stacked(params: SimParams, bottoms: int) -> SimParams:
    """``params`` with ``bottoms`` (1 or 2) cylinders on the table, 1 mm apart, and one more
    resting on them, ``ON_TOP`` from each: a stack, or a pyramid."""
    first = params.objects[0]
    r = first.radius
    pitch = (2 * r + 0.001) / 2 if bottoms == 2 else 0.0
    on = [dataclasses.replace(first, name=f"on{k}", x=x) for k, x in enumerate((-pitch, pitch))]
    rise = math.sqrt((2 * r + ON_TOP) ** 2 - pitch**2)
    top = dataclasses.replace(first, name="top", x=0.0, y=first.y + rise)
    return dataclasses.replace(params, objects=(*on[:bottoms], top))


@pytest.mark.parametrize("bottoms", [1, 2], ids=["stack", "pyramid"])
def test_an_object_resting_on_others_stays_on_them_in_every_model(
    hand: HandConfig, params: SimParams, bottoms: int
) -> None:
    """Every model laid the objects out in a row along the table, an object stacked on
    another too: set beside it at its own height, over nothing, it fell at the first step,
    even in models that varied nothing, and only the nominal one was the hand's scene (found
    by an outside audit). With nothing drawn a model is the configured scene; a drawn radius
    or gap moves the object on top with what holds it, each contact at its configured gap."""
    stack = _stacked(params, bottoms)
    assert resting_on(stack.objects, stack.table_height) == {bottoms: tuple(range(bottoms))}
    assert unsupported(hand, stack) == []
    for m in model_set(stack, 3, 7000, Spread.nominal())[1:]:
        for obj, given in zip(m.params.objects, stack.objects, strict=True):
            assert (obj.x, obj.y) == pytest.approx((given.x, given.y), abs=1e-12)
    models = [
        m
        for family in ("objects", "placement", "all")
        for m in model_set(stack, 8, 7000, Spread() if family == "all" else Spread().only(family))[
            1:
        ]
    ]
    models += sized_models(stack, 4, 7, Spread(), {0: (1.1, 1.2)})
    for m in models:
        *below, top = m.params.objects
        for obj in below:  # on the table, as configured
            assert obj.y - obj.radius == pytest.approx(m.params.table_height, abs=1e-9)
            assert _surface_gap(top, obj) == pytest.approx(ON_TOP, abs=1e-12), m.scales
        assert unsupported(hand, m.params) == [], m.scales
    if bottoms == 1:  # shifted with its bottom, straight above it
        for m in models:
            bottom, top = m.params.objects
            assert bottom.x == pytest.approx(m.scales["placement_m"], abs=1e-12)
            assert top.x == pytest.approx(bottom.x, abs=1e-12)
            assert "gap_m" not in m.scales  # one object on the table: no gap to vary


def test_a_contact_as_slippery_as_it_may_be_stays_so_in_every_model(
    hand: HandConfig, params: SimParams
) -> None:
    """A hand whose table is as slippery as the simulated hand takes (0.001) had half its
    models drawn below that, refused in its own file's name when run, and simulated so by
    the planner (found by an outside audit): every model's coefficient is at least it."""
    from handctl.sim.params import MIN_FRICTION, parse_sim

    slippery = dataclasses.replace(
        params, friction=dataclasses.replace(params.friction, object_table=MIN_FRICTION)
    )
    for m in model_set(slippery, 12, 7200, Spread().only("contact"), hand=hand)[1:]:
        assert m.params.friction.object_table >= MIN_FRICTION
        parse_sim(hand_with(hand, m.params, seed=m.index))  # the model runs
