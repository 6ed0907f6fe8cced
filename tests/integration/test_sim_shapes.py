"""The simulated hand follows the hand config for any shape: fingers of 1..6 joints and of
different lengths, links of their own radius and mass, finger-finger contact when asked for,
one to four objects; the shipped planar two-finger hand end to end over the bus."""

from __future__ import annotations

import copy
import dataclasses
import json
import math
from pathlib import Path
from typing import Any

import mujoco
import numpy as np
import pytest

from handctl.config import HandConfig, load_hand, parse_hand
from handctl.foxglove.scene import HandScene
from handctl.schema import Doc, load_yaml
from handctl.sim.params import SimParams, parse_sim
from handctl.sim.placement import link_segments
from handctl.sim.plant import Plant, gravity_torques
from handctl.sim.render import draw_scene, scene_half_width

from ..conftest import ROOT, handctl

HANDS = ROOT / "config" / "hands"
PLANAR = HANDS / "planar_2f2j.yaml"
FOUR_BY_FOUR = HANDS / "four_fingers_four_joints.yaml"


def _flexion(hand: HandConfig) -> list[float]:
    """+1 for a joint whose positive torque curls its finger towards the hand's middle."""
    return [1.0 if finger.base_x < 0 else -1.0 for finger in hand.fingers for _ in finger.joints]


def _geom(plant: Plant, gid: int) -> str:
    return str(mujoco.mj_id2name(plant.model, mujoco.mjtObj.mjOBJ_GEOM, gid))


# -- four fingers of four joints ------------------------------------------------------------


@pytest.fixture
def four() -> HandConfig:
    return load_hand(FOUR_BY_FOUR)


def test_four_by_four_hand_is_built_from_its_config(four: HandConfig) -> None:
    params = parse_sim(four)
    plant = Plant(four, params)
    assert plant.model.nu == 16 and len(four.fingers) == 4
    for finger in four.fingers:
        for k, joint in enumerate(finger.joints):
            gid = mujoco.mj_name2id(plant.model, mujoco.mjtObj.mjOBJ_GEOM, joint.name)
            link = params.links[four.joint_names.index(joint.name)]
            assert plant.model.geom_size[gid][0] == pytest.approx(link.radius)
            assert plant.model.geom_size[gid][0] == pytest.approx(joint.half_thickness)
            # the capsule spans its own link length: the next body sits at its end
            if k + 1 < len(finger.joints):
                bid = mujoco.mj_name2id(
                    plant.model, mujoco.mjtObj.mjOBJ_BODY, finger.joints[k + 1].name
                )
                assert plant.model.body_pos[bid][0] == pytest.approx(joint.link_length)
    limits = plant.model.actuator_forcerange[:, 1]
    assert list(limits) == pytest.approx(params.motor_tau_max)
    assert len(set(params.motor_tau_max[:4])) == 4  # a limit per joint, not per level


def test_each_joint_of_the_four_by_four_hand_turns_with_its_torque(four: HandConfig) -> None:
    """A torque on one joint turns that joint its own way, against the same run without it
    (gravity and the other joints move alike in both)."""
    params = parse_sim(four)
    plant = Plant(four, params)
    for joint in range(four.n_joints):
        moved = []
        for tau in (0.0, 0.1):
            plant.reset()
            command = np.zeros(four.n_joints)
            command[joint] = tau
            plant.set_torque_commands(command)
            for _ in range(60):
                plant.step()
            moved.append(float(plant.joint_angles[joint]))
        assert moved[1] - moved[0] > 0.01, four.joint_names[joint]


def test_four_by_four_cylinder_rests_then_is_closed_on_by_every_finger(
    four: HandConfig, tmp_path: Path
) -> None:
    params = parse_sim(four)
    plant = Plant(four, params)
    for _ in range(300):
        plant.step()
    (cylinder,) = plant.object_poses()
    start = params.objects[0]
    assert cylinder.y == pytest.approx(params.table_height + start.radius, abs=1e-3)
    assert cylinder.x == pytest.approx(start.x, abs=1e-3)
    # every finger curls in on it
    gains = [0.15, 0.10, 0.06, 0.04]
    plant.set_torque_commands([s * gains[k % 4] for k, s in enumerate(_flexion(four))])
    touching: set[str] = set()
    met: set[tuple[str, str]] = set()
    for _ in range(1500):
        plant.step()
        met |= set(plant.contact_pairs())
        touching |= {
            a if b == start.name else b for a, b in plant.contact_pairs() if start.name in (a, b)
        }
    fingers = {f.name for f in four.fingers if touching & {j.name for j in f.joints}}
    assert fingers == {f.name for f in four.fingers}
    # the fingers collide, and the two sides, interleaved along z, cross without touching
    assert params.between_fingers
    owner = {j.name: f.name for f in four.fingers for j in f.joints}
    assert not any(a in owner and b in owner for a, b in met)
    assert draw_scene(plant, tmp_path / "four.png").stat().st_size > 0


# -- fingers of any joint count and length --------------------------------------------------


def _odd_hand(counts: tuple[int, ...], between_fingers: bool = False) -> dict[str, Any]:
    """A hand config (as loaded YAML) with one finger per entry of ``counts`` joints, each
    link of its own length, radius and mass, fingers spread along x and z."""
    fingers: list[dict[str, Any]] = []
    sim_links: dict[str, list[dict[str, float]]] = {}
    motors: dict[str, list[float]] = {}
    initial: dict[str, list[float]] = {}
    for i, n in enumerate(counts):
        name = f"finger{i}"
        joints = []
        for k in range(n):
            joints.append(
                {
                    "name": f"{name}_joint{k}",
                    "link_length": 0.06 - 0.007 * k + 0.004 * i,
                    "tau_max": 0.5,
                    "device_tau_max": 0.6,
                    "rate_limit": 20.0,
                    "angle_min": -1.5,
                    "angle_max": 1.5,
                    "tdt": {"scale": 1.0, "offset": 0.0},
                }
            )
        n_id = i + 1
        fingers.append(
            {
                "name": name,
                "node_id": n_id,
                "can_ids": {
                    "node_command": 0x010 + n_id,
                    "torque_command": 0x100 + n_id,
                    "feedback": 0x180 + n_id,
                    "status": 0x280 + n_id,
                    "heartbeat": 0x700 + n_id,
                },
                "base": {"x": -0.06 + 0.04 * i, "y": 0.0, "angle": -math.pi / 2},
                "z": 0.03 * (i % 2) - 0.015,
                "joints": joints,
            }
        )
        sim_links[name] = [
            {"radius": 0.004 + 0.001 * k + 0.0005 * i, "mass": 0.01 + 0.005 * (k + i)}
            for k in range(n)
        ]
        motors[name] = [1.0] * n
        initial[name] = [0.3 * (-1) ** i] + [0.05 * (-1) ** i] * (n - 1)
    sim = copy.deepcopy(_SIM)
    sim["links"] = sim_links
    sim["actuator"]["motor_tau_max"] = motors
    sim["initial_angles"] = initial
    # a ball beside the last finger, within its reach (a scene must be), falling at t = 0
    sim["objects"][0].update(x=fingers[-1]["base"]["x"] + 0.1, y=-0.1)
    sim["contact"]["between_fingers"] = between_fingers
    if between_fingers:
        sim["friction"]["finger_finger"] = 0.6
    return {
        "name": "odd",
        "bus": {
            "interface": "virtual",
            "channel": "odd",
            "fd": True,
            "bitrate": 1_000_000,
            "data_bitrate": 5_000_000,
            "loop_rate_hz": 1000,
        },
        "fingers": fingers,
        # its sensors are noiseless (_SIM): a reading that never moves is no fault here
        "safety": {"tdt_stuck_still_s": 0.0},
        "sim": sim,
    }


_SIM: dict[str, Any] = {
    "seed": 0,
    "timestep": 0.001,
    "gravity": 9.81,
    "table": {"height": -0.5},
    "palm": {"half_width": 0.01, "thickness": 0.02},
    "joints": {"damping": 0.01, "frictionloss": 0.0, "armature": 5e-5, "stop_margin": 0.1},
    "actuator": {"lag": 0.005},
    "objects": [{"name": "ball", "radius": 0.03, "length": 0.1, "mass": 0.05, "x": 0.0, "y": -0.1}],
    "friction": {
        "finger_object": 0.8,
        "object_object": 0.3,
        "object_table": 0.4,
        "object_palm": 0.5,
        "finger_table": 0.5,
        "finger_palm": 0.5,
    },
    "contact": {"timeconst": 0.004, "dampratio": 1.0},
    "tdt": {"noise": 0.0, "bias": 0.0, "lag": 0.002, "resolution": 0.0005, "range": 3.0},
    "encoder": {"counts_per_rev": 16384, "max_step": 0.2},
}


def _load(data: dict[str, Any]) -> HandConfig:
    return parse_hand(Doc(data, "odd.yaml", ""))


@pytest.mark.parametrize("counts", [(1, 6), (2, 5, 3), (4, 1, 2, 6)])
def test_fingers_of_any_joint_count_hang_as_their_own_links_weigh(counts: tuple[int, ...]) -> None:
    """MuJoCo's gravity torques agree with planar statics written independently, link by link:
    each link's own mass and length reach the model, whatever the finger's joint count."""
    hand = _load(_odd_hand(counts))
    params = parse_sim(hand)
    assert [len(f.joints) for f in hand.fingers] == list(counts)
    plant = Plant(hand, params)
    expected = gravity_torques(hand, params, plant.joint_angles.copy())
    assert -plant.data.qfrc_bias[: hand.n_joints] == pytest.approx(expected, abs=1e-6)
    # the same hand with every link alike would weigh differently: the masses are per link
    alike = dataclasses.replace(params, links=(params.links[0],) * hand.n_joints)
    assert gravity_torques(hand, alike, plant.joint_angles.copy()) != pytest.approx(expected)


# -- finger-finger contact ------------------------------------------------------------------


def _aside(params: SimParams) -> SimParams:
    """The objects moved far along the table, out of the fingers' way (past the checks)."""
    objects = tuple(dataclasses.replace(o, x=math.copysign(0.5, o.x)) for o in params.objects)
    return dataclasses.replace(params, objects=objects)


@pytest.mark.parametrize("between_fingers", [True, False])
def test_opposing_fingers_meet_only_where_contact_is_asked_for(between_fingers: bool) -> None:
    hand = load_hand(PLANAR)
    params = _aside(
        dataclasses.replace(
            parse_sim(hand), between_fingers=between_fingers, finger_finger_friction=0.5
        )
    )
    plant = Plant(hand, params)
    left = {j.name for j in hand.fingers[0].joints}
    right = {j.name for j in hand.fingers[1].joints}
    pairs = {
        frozenset((_geom(plant, int(a)), _geom(plant, int(b))))
        for a, b in zip(plant.model.pair_geom1, plant.model.pair_geom2, strict=True)
    }
    between = {p for p in pairs if p & left and p & right}
    assert len(between) == (len(left) * len(right) if between_fingers else 0)
    # both fingers curl in hard: their distal links reach the middle together
    plant.set_torque_commands([0.4 * s for s in _flexion(hand)])
    met = False
    crossed = False
    for _ in range(1500):
        plant.step()
        met |= any(bool({a, b} & left and {a, b} & right) for a, b in plant.contact_pairs())
        crossed |= plant.fingertip(0)[0] > plant.fingertip(1)[0]
    assert met is between_fingers
    assert crossed is not between_fingers  # without contact the fingers pass through


# -- the planar hand of the paper over the bus ----------------------------------------------

CLOSE = """
recipe: close_planar
description: close both fingers of the planar hand on the two cylinders
phases:
  - name: close
    torques: [0.12, 0.06, -0.12, -0.06]
    ramp_s: 0.2
    max_s: 1.0
    on_timeout: next
"""


def test_planar_hand_closes_on_its_two_cylinders_in_lockstep(tmp_path: Path) -> None:
    recipe = tmp_path / "close.yaml"
    recipe.write_text(CLOSE)
    out = tmp_path / "out.json"
    done = handctl("run", "recipe", str(recipe), "--hand", str(PLANAR), "--summary-json", str(out))
    assert done.returncode == 0, done.stderr
    summary = json.loads(out.read_text())
    assert summary["completed"] is True and summary["hand"] == "planar_2f2j"
    assert set(summary["max_abs_tau_nm"]) == {"left_j1", "left_j2", "right_j1", "right_j2"}
    objects = summary["sim"]["objects"]
    assert set(objects) == {"cyl1", "cyl2"}
    # the fingers closed the 1 mm gap between the cylinders: they were pushed together
    assert objects["cyl2"]["x_m"] - objects["cyl1"]["x_m"] < 0.091 - 0.0005
    assert set(summary["sim"]["nodes"]) == {"left", "right"}


def test_a_scene_out_of_reach_is_bad_input_before_anything_runs(tmp_path: Path) -> None:
    done = handctl("check", str(PLANAR), timeout=120)
    assert done.returncode == 0, done.stderr
    assert "simulated hand: cyl1 (r 0.045 m), cyl2 (r 0.045 m); fingers collide" in done.stdout
    bad = tmp_path / "far.yaml"
    bad.write_text(PLANAR.read_text().replace("x: 0.0455, y: -0.105}", "x: 0.6, y: -0.105}"))
    recipe = tmp_path / "close.yaml"
    recipe.write_text(CLOSE)
    for args in (
        ["check", str(bad)],
        ["sim", "--bus", "virtual:far", "--seconds", "0.1", "--hand", str(bad)],
        ["run", "recipe", str(recipe), "--hand", str(bad)],
    ):
        done = handctl(*args, timeout=120)
        assert done.returncode == 2, done.stderr
        assert f"{bad}: sim.objects[1].x: expected a place within reach of a finger" in done.stderr
        assert "found 0.6" in done.stderr


def test_the_drawing_holds_every_finger_stretched_out() -> None:
    hand = _load(_odd_hand((6, 1, 6)))
    params = parse_sim(hand)
    straight = tuple((0.0,) * len(f.joints) for f in hand.fingers)
    stretched = dataclasses.replace(params, initial_angles=straight)
    for base_angle in (0.0, math.pi):  # every finger pointing sideways, out or in
        turned = dataclasses.replace(
            hand, fingers=tuple(dataclasses.replace(f, base_angle=base_angle) for f in hand.fingers)
        )
        ends = [
            abs(x) + link.radius
            for link in link_segments(turned, stretched)
            for x in (link.x0, link.x1)
        ]
        assert max(ends) > 0.2  # wider than a fixed frame would show
        assert scene_half_width(Plant(turned, stretched)) >= max(ends)


def test_the_foxglove_table_holds_every_finger_stretched_out() -> None:
    """The simulated table is a plane without end; the drawn one was a fixed 0.4 m square,
    and a long finger (six links, 0.25 m of them) or an object pushed along the table was
    drawn over its edge, on nothing (found by an outside audit). It spans the hand's reach
    many times over."""
    hand = _load(_odd_hand((6, 1, 6)))
    params = parse_sim(hand)
    straight = tuple((0.0,) * len(f.joints) for f in hand.fingers)
    stretched = dataclasses.replace(params, initial_angles=straight)
    # every finger pointing sideways, out: as far as the fingers reach along the table
    turned = dataclasses.replace(
        hand, fingers=tuple(dataclasses.replace(f, base_angle=0.0) for f in hand.fingers)
    )
    reach = max(abs(x) for link in link_segments(turned, stretched) for x in (link.x0, link.x1))
    scenery = HandScene(hand).scenery
    assert scenery is not None
    assert reach > 0.2  # past the fixed square's edge
    assert scenery.table_half_side >= 2 * reach


def test_the_foxglove_scene_draws_each_link_with_its_own_radius() -> None:
    hand = _load(_odd_hand((2, 5, 3)))
    radii = [link.radius for link in parse_sim(hand).links]
    assert len(set(radii)) > 5  # fingers differ, not only joint levels
    drawn = HandScene(hand).link_radius
    assert [len(r) for r in drawn] == [2, 5, 3]
    assert [r for finger in drawn for r in finger] == pytest.approx(radii)


def test_objects_of_any_name_are_simulated_under_it(hand: HandConfig) -> None:
    """A hand config names its objects as a recipe can (letters and digits, parse_sim), but
    the scene's builder takes any name as it is, escaped for MuJoCo's XML: what it is given
    is not its to trust."""
    names = ['a "quoted" <cylinder> & co', "zylinder 2"]
    params = parse_sim(hand)
    objects = tuple(
        dataclasses.replace(obj, name=name) for obj, name in zip(params.objects, names, strict=True)
    )
    plant = Plant(hand, dataclasses.replace(params, objects=objects))
    plant.step()
    assert [pose.name for pose in plant.object_poses()] == names
    assert names[0] in {_geom(plant, int(g)) for g in plant.model.pair_geom1}


def test_planar_hand_envelops_and_lifts_its_two_cylinders() -> None:
    """The shipped planar hand can do what the paper's hand does: curled in with the distal
    joints leading, the fingers scoop both cylinders off the table into an enveloping grasp
    (distal links under the pair, near the paper's q_2 = 1.84 rad)."""
    hand = load_hand(PLANAR)
    params = parse_sim(hand)
    plant = Plant(hand, params)
    plant.set_torque_commands([0.1, 0.3, -0.1, -0.3])
    for _ in range(2000):
        plant.step()
    for pose, start in zip(plant.object_poses(), params.objects, strict=True):
        assert pose.y - start.y > 0.03, pose
    assert plant.joint_angles[1] > 1.5 and plant.joint_angles[3] < -1.5
    touching = {frozenset(p) for p in plant.contact_pairs()}
    assert frozenset(("left_j2", "cyl1")) in touching
    assert frozenset(("right_j2", "cyl2")) in touching


def test_the_papers_hand_at_its_own_scale_is_a_scene_too() -> None:
    """Objects of any radius: the paper's §4 example at its own size (links of 1 m, bases at
    -+0.5 m, cylinders of 0.45 m and 1 kg) in a horizontal plane, as its Fig. 3 has it."""
    data = copy.deepcopy(load_yaml(PLANAR).data)
    for finger in data["fingers"]:
        finger["base"] = {**finger["base"], "x": math.copysign(0.5, finger["base"]["x"])}
        finger["joints"] = [
            {**joint, "link_length": 1.0, "half_thickness": 0.08} for joint in finger["joints"]
        ]
    sim = data["sim"]
    sim.update(gravity=0.0, table={"height": -1.5}, palm={"half_width": 0.4, "thickness": 0.2})
    sim["links"] = {f["name"]: [{"radius": 0.08, "mass": 0.5}] * 2 for f in data["fingers"]}
    sim["objects"] = [
        {"name": name, "radius": 0.45, "length": 0.8, "mass": 1.0, "x": x, "y": -1.05}
        for name, x in (("cylinder1", -0.455), ("cylinder2", 0.455))
    ]
    hand = parse_hand(Doc(data, "paper_scale.yaml", ""))
    params = parse_sim(hand)
    plant = Plant(hand, params)
    radii = {_geom(plant, g): plant.model.geom_size[g][0] for g in range(plant.model.ngeom)}
    assert radii["cylinder1"] == radii["cylinder2"] == pytest.approx(0.45)
    # the fingers close on the cylinders, each on its own
    plant.set_torque_commands([0.5, 0.5, -0.5, -0.5])
    touching: set[frozenset[str]] = set()
    for _ in range(1500):
        plant.step()
        touching |= {frozenset(p) for p in plant.contact_pairs()}
    assert any({"cylinder1", "left_j2"} <= p or {"cylinder1", "left_j1"} <= p for p in touching)
    assert any({"cylinder2", "right_j2"} <= p or {"cylinder2", "right_j1"} <= p for p in touching)
