"""Physical sanity of the simulated hand: gravity, resting contact, the drive and the TDT lag."""

from __future__ import annotations

import dataclasses
import math

import mujoco
import numpy as np
import pytest

from handctl.config import HandConfig
from handctl.sim.params import SimParams, parse_sim
from handctl.sim.plant import Plant, gravity_torques

from .test_sim_support import enable_all, sim_and_host


@pytest.fixture(scope="module")
def params(hand: HandConfig) -> SimParams:
    return parse_sim(hand)


def _far_objects(params: SimParams, table: float) -> SimParams:
    """The cylinders moved aside onto a table at ``table``, out of the fingers' reach."""
    objects = tuple(
        dataclasses.replace(o, x=math.copysign(0.3, o.x), y=table + o.radius)
        for o in params.objects
    )
    return dataclasses.replace(params, table_height=table, objects=objects)


def test_scene_starts_without_finger_contact(hand: HandConfig, params: SimParams) -> None:
    plant = Plant(hand, params)
    links = set(hand.joint_names)
    assert all(not links & set(pair) for pair in plant.contact_pairs())
    # no contact pair between two finger links exists at all: fingers never collide
    names = [
        (
            mujoco.mj_id2name(plant.model, mujoco.mjtObj.mjOBJ_GEOM, int(a)),
            mujoco.mj_id2name(plant.model, mujoco.mjtObj.mjOBJ_GEOM, int(b)),
        )
        for a, b in zip(plant.model.pair_geom1, plant.model.pair_geom2, strict=True)
    ]
    assert not [p for p in names if p[0] in links and p[1] in links]
    # each pair carries the friction of its kind
    mu = {frozenset(p): float(f[0]) for p, f in zip(names, plant.model.pair_friction, strict=True)}
    assert mu[frozenset(("f1_j3", "cyl1"))] == params.friction.finger_object
    assert mu[frozenset(("cyl1", "cyl2"))] == params.friction.object_object
    assert mu[frozenset(("cyl2", "table"))] == params.friction.object_table
    assert mu[frozenset(("f3_j1", "palm"))] == params.friction.finger_palm


def test_dropped_cylinder_comes_to_rest_on_the_table(hand: HandConfig, params: SimParams) -> None:
    p = _far_objects(params, params.table_height)
    dropped = dataclasses.replace(p.objects[0], y=p.objects[0].y + 0.03)
    plant = Plant(hand, dataclasses.replace(p, objects=(dropped, *p.objects[1:])))
    for _ in range(1000):
        plant.step()
    pose = plant.object_poses()[0]
    assert pose.y == pytest.approx(p.table_height + dropped.radius, abs=1e-3)
    assert abs(pose.x - dropped.x) < 1e-3
    adr = plant.model.jnt_dofadr[
        mujoco.mj_name2id(plant.model, mujoco.mjtObj.mjOBJ_JOINT, "cyl1_x")
    ]
    assert np.abs(plant.data.qvel[adr : adr + 3]).max() < 1e-3


def test_fingers_fall_the_way_gravity_says(hand: HandConfig, params: SimParams) -> None:
    p = _far_objects(dataclasses.replace(params, frictionloss=(0.0,) * len(params.damping)), -0.5)
    plant = Plant(hand, p)
    q0 = plant.joint_angles.copy()
    expected = gravity_torques(hand, p, q0)
    # MuJoCo's gravity force at rest agrees with planar statics written independently
    assert -plant.data.qfrc_bias[: hand.n_joints] == pytest.approx(expected, abs=1e-6)
    assert np.abs(expected).max() > 0.01  # the open start pose is far from hanging
    for _ in range(30):
        plant.step()
    moved = plant.joint_angles - q0
    assert float(moved @ expected) > 0  # gravity does positive work: the fingers fall
    for _ in range(4000):
        plant.step()
    # they come to hang straight down from their bases (every joint angle 0); the distal
    # joints, whose gravity stiffness is small against the joint damping, creep in last
    assert np.abs(plant.joint_angles).max() < 0.05
    assert np.abs(gravity_torques(hand, p, plant.joint_angles)).max() < 5e-4


def test_tdt_follows_the_command_through_both_lags(
    hand: HandConfig, channel: str, params: SimParams
) -> None:
    clean = dataclasses.replace(
        params, tdt=dataclasses.replace(params.tdt, noise=0.0, bias=0.0, resolution=0.0)
    )
    tau = [0.2, 0.12, 0.06, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0]
    with sim_and_host(hand, channel, params=clean) as (sim, host):
        sim.plant.hold_objects(True)
        enable_all(host)
        readings: list[float] = []
        for _ in range(60):
            assert host.tick(tau)
            readings.append(host.last("Feedback", 1)["Torque1"])
    ta, ts = clean.actuator_lag[0], clean.tdt.lag

    def step_response(t: float) -> float:  # two first-order lags in series, unit step
        if t <= 0:
            return 0.0
        return 1 - (ta * math.exp(-t / ta) - ts * math.exp(-t / ts)) / (ta - ts)

    for k, reading in enumerate(readings, start=1):
        lo = tau[0] * step_response((k - 2) * 1e-3) - 2e-4
        hi = tau[0] * step_response(k * 1e-3) + 2e-4
        assert lo <= reading <= hi, f"tick {k}: {reading} not in [{lo}, {hi}]"
    assert readings[1] < 0.2 * tau[0]  # there is a lag...
    assert readings[-1] == pytest.approx(tau[0], abs=2e-4)  # ...and it settles on the torque


def test_noisy_tdt_matches_the_applied_torque(
    hand: HandConfig, channel: str, params: SimParams
) -> None:
    tau = [0.15, -0.1, 0.08, 0.1, 0.1, 0.1, -0.2, -0.1, -0.05]
    with sim_and_host(hand, channel) as (sim, host):
        sim.plant.hold_objects(True)
        enable_all(host)
        host.run(60, tau)
        heard = host.run(40, tau)
    bound = 4 * params.tdt.bias + params.tdt.resolution
    for finger, offset in zip(hand.fingers, (0, 3, 6), strict=True):
        frames = host.of("Feedback", finger.node_id, heard)
        for j, joint in enumerate(finger.joints):
            raw = [f.signals()[f"Torque{j + 1}"] for f in frames]
            calibrated = [joint.tdt.scale * r + joint.tdt.offset for r in raw]
            assert np.mean(calibrated) == pytest.approx(tau[offset + j], abs=bound)
            assert np.std(calibrated) < 2 * params.tdt.noise + params.tdt.resolution


def test_fingertip_pushing_lifts_the_pair(hand: HandConfig, params: SimParams) -> None:
    """Not a grasp (that is a recipe's job), only proof the scene allows one: fingertips placed
    low beside the cylinders and pushed inward lift both off the table."""
    plant = Plant(hand, params)
    plant.data.qpos[:9] = [-0.25, -0.05, 1.2, -0.25, -0.05, 1.2, 0.25, 0.05, -1.2]
    mujoco.mj_forward(plant.model, plant.data)
    tau = np.array([0.25, 0.15, 0.10] * 2 + [-0.25, -0.15, -0.10])
    for _ in range(1500):
        plant.set_torque_commands(tau)
        plant.step()
    for pose, obj in zip(plant.object_poses(), params.objects, strict=True):
        assert pose.y > params.table_height + obj.radius + 0.03, pose
        assert pose.y + obj.radius <= 1e-3  # held under the palm, not through it
