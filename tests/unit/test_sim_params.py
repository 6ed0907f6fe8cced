"""The ``sim:`` section: the shipped one is sound, and every mistake names file and key path."""

from __future__ import annotations

import copy
import dataclasses
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml

from handctl.config import HandConfig, load_hand
from handctl.errors import ConfigError
from handctl.planning.models import Spread, hand_with, perturb
from handctl.sim.params import parse_sim
from handctl.sim.plant import Plant

from ..conftest import HAND_YAML, ROOT

PLANAR = ROOT / "config" / "hands" / "planar_2f2j.yaml"


def _with_sim(hand: HandConfig, edit: Any) -> HandConfig:
    raw = copy.deepcopy(dict(hand.sim))
    edit(raw)
    return dataclasses.replace(hand, sim=raw)


def test_shipped_scene_is_the_documented_one(hand: HandConfig) -> None:
    p = parse_sim(hand)
    assert p.timestep == 0.001 and p.substeps == 1
    assert len(p.objects) == 2
    for obj in p.objects:
        assert 0.020 <= obj.radius <= 0.030
        assert 0.030 <= obj.mass <= 0.100
        assert obj.y - obj.radius == pytest.approx(p.table_height)  # resting on the table
        # long enough along z to span the side-by-side fingers (z = +-0.022) and finger 3
        assert obj.length / 2 > max(abs(f.z) for f in hand.fingers)
    for finger in hand.fingers:
        for joint in finger.joints:
            assert 0.040 <= joint.link_length <= 0.070


def test_missing_section_is_refused(hand: HandConfig) -> None:
    with pytest.raises(ConfigError) as err:
        parse_sim(dataclasses.replace(hand, sim={}))
    assert err.value.key == "sim"
    assert err.value.file == hand.source


def test_a_tdt_range_is_held_to_the_readings_of_device_tau_max(hand: HandConfig) -> None:
    """The node's self-check compares the reading in its factory calibration: a joint whose
    sensor reads half scale reads device_tau_max twice as large, and the range must hold it."""
    assert parse_sim(_with_sim(hand, lambda s: s["tdt"].update(range=0.8))).tdt.range == 0.8
    half = dataclasses.replace(
        hand.joints[4], tdt=dataclasses.replace(hand.joints[4].tdt, scale=0.5)
    )
    fingers = list(hand.fingers)
    fingers[1] = dataclasses.replace(
        fingers[1], joints=(fingers[1].joints[0], half, *fingers[1].joints[2:])
    )
    halved = dataclasses.replace(hand, fingers=tuple(fingers))
    with pytest.raises(ConfigError) as err:
        parse_sim(_with_sim(halved, lambda s: s["tdt"].update(range=1.0)))
    assert err.value.key == "sim.tdt.range"
    assert "a range >= 1.2 N·m, the reading of device_tau_max of f2_j2 (0.6 N·m" in (
        err.value.expected
    )


@pytest.mark.parametrize("noise", [0.0, 1e-300, 0.0002])
def test_a_tdt_quieter_than_its_steps_is_refused_while_stillness_is_a_fault(
    hand: HandConfig, noise: float
) -> None:
    """A reading that never moves for safety.tdt_stuck_still_s is TDT_STUCK: noise 0 (or
    1e-300) stopped every run there, at the first half second of steady torque."""
    with pytest.raises(ConfigError) as err:
        parse_sim(_with_sim(hand, lambda s: s["tdt"].update(noise=noise)))
    assert err.value.key == "sim.tdt.noise"
    assert err.value.found == noise
    assert "a noise >= 0.00025 N·m, half the step the host reads f1_j1's torque in" in (
        err.value.expected
    )
    assert "safety.tdt_stuck_still_s is 0.5 s" in err.value.expected
    # with the stillness check off, a noiseless sensor is what it says
    still_off = dataclasses.replace(
        hand, safety=dataclasses.replace(hand.safety, tdt_stuck_still_s=0.0)
    )
    assert parse_sim(_with_sim(still_off, lambda s: s["tdt"].update(noise=noise))).tdt.noise == (
        noise
    )


@pytest.mark.parametrize(
    ("key", "refused", "accepted", "expected"),
    [
        # safety.tdt_tolerance 0.02 N·m
        ("bias", 0.02, 0.0199, "a bias (1 sigma) below safety.tdt_tolerance (0.02 N·m)"),
        ("noise", 0.02, 0.0199, "a noise (1 sigma) below safety.tdt_tolerance (0.02 N·m)"),
        # safety.tdt_lag_s 0.01 s plus half tdt_window_s 0.05 s (0.04 s stopped the swap);
        # the drive's 5 ms comes on top (``test_the_drive_s_lag_counts_with_the_sensor_s``)
        ("lag", 0.0351, 0.030, "at most 0.035 s, safety.tdt_lag_s (0.01 s"),
    ],
)
def test_a_tdt_the_host_s_cross_check_cannot_live_with_is_refused(
    hand: HandConfig, key: str, refused: float, accepted: float, expected: str
) -> None:
    """A simulated sensor of bias or noise 1.0 N·m, or a lag of 1 s, passed ``check`` and
    every run on it stopped on TDT_MISMATCH within a tenth of a second (found by an outside
    audit)."""
    with pytest.raises(ConfigError) as err:
        parse_sim(_with_sim(hand, lambda s: s["tdt"].update({key: refused})))
    assert err.value.key == f"sim.tdt.{key}"
    assert expected in err.value.expected, err.value.expected
    parsed = parse_sim(_with_sim(hand, lambda s: s["tdt"].update({key: accepted})))
    assert getattr(parsed.tdt, key) == accepted


def test_the_drive_s_lag_counts_with_the_sensor_s(hand: HandConfig) -> None:
    """The sensor reads what the drive transmits: a drive lag of 1 s passed ``check`` beside
    the sensor's 2 ms and stopped every run on TDT_MISMATCH (an outside audit). The two
    together are held to the sensor's bound, 0.035 s on the shipped hand."""
    with pytest.raises(ConfigError) as err:
        parse_sim(_with_sim(hand, lambda s: s["actuator"].update({"lag": 1.0})))
    assert err.value.key == "sim.actuator.lag"
    assert "at most 0.033 s, so that with sim.tdt.lag (0.002 s)" in err.value.expected
    assert "1 s (f1_j1)" in str(err.value)
    assert parse_sim(_with_sim(hand, lambda s: s["actuator"].update({"lag": 0.033})))
    joints = hand.n_joints
    one_slow = [0.005] * (joints - 1) + [0.04]
    with pytest.raises(ConfigError) as err:
        parse_sim(_with_sim(hand, lambda s: s["actuator"].update({"lag": one_slow})))
    assert f"0.04 s ({hand.joints[-1].name})" in str(err.value)
    with pytest.raises(ConfigError) as err:
        parse_sim(_with_sim(hand, lambda s: s["tdt"].update({"lag": 0.033})))
    assert err.value.key == "sim.actuator.lag"  # 5 ms of the drive and 33 of the sensor


def test_a_host_that_expects_a_far_slower_sensor_is_refused(hand: HandConfig) -> None:
    """safety.tdt_lag_s of 1 s against the simulated sensor's 2 ms passed check, and every
    run stopped on TDT_MISMATCH: the host read each ramp 'wrong' for longer than its window."""
    slow_host = dataclasses.replace(hand, safety=dataclasses.replace(hand.safety, tdt_lag_s=1.0))
    with pytest.raises(ConfigError) as err:
        parse_sim(slow_host)
    assert err.value.key == "sim.tdt.lag"
    assert "at least 0.975 s, safety.tdt_lag_s (1 s" in err.value.expected
    assert "make safety.tdt_lag_s the sensor's lag" in err.value.expected
    parse_sim(_with_sim(slow_host, lambda s: s["tdt"].update({"lag": 0.975})))


def test_the_quietest_tdt_accepted_never_reads_still_long_enough_to_be_stuck(
    hand: HandConfig,
) -> None:
    """The sensor model at the least noise parse_sim takes, on the wire's grid, through the
    host's own stuck check for four of its windows at a steady torque: not one finding."""
    from handctl.hand_protocol import protocol_for
    from handctl.online.safety.watchdog import TdtMonitor
    from handctl.sim.sensors import TdtModel

    params = parse_sim(_with_sim(hand, lambda s: s["tdt"].update(noise=0.00025)))
    model = TdtModel(hand, params.tdt, np.random.default_rng(0))
    monitor = TdtMonitor(hand.safety, hand.n_joints, 0.001, [j.name for j in hand.joints])
    applied = np.full(hand.n_joints, 0.1234567)
    monitor.reset(applied)
    step = protocol_for(hand).layout("Feedback", 1).signals[0].scale  # every joint's, here
    for _ in range(2000):
        reading = np.round(np.asarray(model.sample(applied.tolist())) / step) * step
        assert monitor.update(applied, reading) == []


@pytest.mark.parametrize(
    ("edit", "key", "expected"),
    [
        (lambda s: s["objects"][1].update(radiuss=0.02), "sim.objects[1].radiuss", "unknown key"),
        (lambda s: s["tdt"].update(noise="much"), "sim.tdt.noise", "a number"),
        (lambda s: s.update(timestep=0.0003), "sim.timestep", "whole fraction"),
        (lambda s: s["objects"][0].update(y=-0.15), "sim.objects[0].y", "above the table"),
        (lambda s: s["objects"][1].update(x=-0.01), "sim.objects[1].x", "not overlapping"),
        (
            lambda s: s["initial_angles"].update(f3=[0.55, 1.2, 0.1]),
            "sim.initial_angles.f3[1]",
            "soft limits",
        ),
        # on a soft limit (f3_j2's angle_max is 0.9): ANGLE_LIMIT at tick 1 of every run
        (
            lambda s: s["initial_angles"].update(f3=[0.55, 0.9, 0.1]),
            "sim.initial_angles.f3[1]",
            "0.01 rad inside",
        ),
        (
            lambda s: s["initial_angles"].update(f3=[0.55, 0.895, 0.1]),
            "sim.initial_angles.f3[1]",
            "0.01 rad inside",
        ),
        (lambda s: s["initial_angles"].pop("f2"), "sim.initial_angles.f2", "required"),
        (
            lambda s: s["actuator"]["motor_tau_max"].update(f2=[0.5, 0.75, 0.5]),
            "sim.actuator.motor_tau_max.f2[0]",
            "device_tau_max",
        ),
        (
            lambda s: s["actuator"]["motor_tau_max"].update(f3=[1.0, 0.75]),
            "sim.actuator.motor_tau_max.f3",
            "a list of 3 numbers",
        ),
        (
            lambda s: s["actuator"].update(motor_tau_max=[1.0, 0.75, 0.5]),
            "sim.actuator.motor_tau_max",
            "a mapping",
        ),
        (lambda s: s["links"].update(f2=s["links"]["f2"][:2]), "sim.links.f2", "3 mappings"),
        (lambda s: s["links"].update(f4=s["links"]["f1"]), "sim.links.f4", "unknown key"),
        (lambda s: s["links"].pop("f3"), "sim.links.f3", "required"),
        (
            lambda s: s["links"].update(
                f1=[*s["links"]["f1"][:2], {"radius": 0.006, "mass": 0.015}]
            ),
            "sim.links.f1[2].radius",
            "half_thickness of f1_j3",
        ),
        (lambda s: s["friction"].update(object_object=-0.1), "sim.friction.object_object", ">= 0"),
        # the pair sank 25 mm into a table this soft, and the run stopped on a joint's limit
        (lambda s: s["contact"].update(timeconst=0.5), "sim.contact.timeconst", "<= 0.05"),
        # a frictionless contact came apart in the solver: a finger's joints leapt half a
        # radian past their stops in one tick, said as a node's SENSOR fault
        (
            lambda s: s["friction"].update(finger_object=0.0),
            "sim.friction.finger_object",
            "at least 0.001",
        ),
        (
            lambda s: (
                s["contact"].update(between_fingers=True),
                s["friction"].update(finger_finger=1e-5),
            ),
            "sim.friction.finger_finger",
            "at least 0.001",
        ),
        # the node latched SENSOR at the first count its joint moved (NODE_CONTRADICTION)
        (lambda s: s["encoder"].update(max_step=1e-12), "sim.encoder.max_step", "encoder count"),
        (
            lambda s: s["encoder"].update(counts_per_rev=16, max_step=0.3),
            "sim.encoder.max_step",
            "0.393 rad",
        ),
        # every run stopped on NODE_FAULT (SENSOR) the first time a joint pulled hard
        (
            lambda s: s["tdt"].update(range=0.1),
            "sim.tdt.range",
            "a range >= 0.8 N·m, the reading of device_tau_max of f1_j1 (0.8 N·m",
        ),
        # MuJoCo refused to build these (a traceback, exit 1): too light or too thin a link
        (lambda s: s["links"]["f1"][0].update(mass=1e-12), "sim.links.f1[0].mass", ">= 0.001"),
        (lambda s: s["links"]["f1"][2].update(mass=0.0005), "sim.links.f1[2].mass", ">= 0.001"),
        (lambda s: s["links"]["f1"][1].update(radius=1e-9), "sim.links.f1[1].radius", ">= 0.001"),
        (
            lambda s: s["friction"].update(finger_finger=0.5),
            "sim.friction.finger_finger",
            "between_fingers is false",
        ),
        (
            lambda s: s["contact"].update(between_fingers=True),
            "sim.friction.finger_finger",
            "required",
        ),
        (
            lambda s: s["contact"].update(between_fingers="yes"),
            "sim.contact.between_fingers",
            "true or false",
        ),
    ],
)
def test_mistakes_name_the_key(hand: HandConfig, edit: Any, key: str, expected: str) -> None:
    with pytest.raises(ConfigError) as err:
        parse_sim(_with_sim(hand, edit))
    assert err.value.key == key
    assert expected in err.value.expected
    assert err.value.file == hand.source


# -- the scene: names, reach and overlaps ---------------------------------------------------


@pytest.mark.parametrize(
    ("edit", "key", "expected"),
    [
        (lambda s: s["objects"][1].update(name="palm"), "sim.objects[1].name", "a name of its own"),
        (lambda s: s["objects"][0].update(name="world"), "sim.objects[0].name", "is the scene"),
        # a link's, a base's or an object joint's name has an underscore, which no object's
        # may have: a recipe could not name it (its estimates are NAME_x, A_B_line_turn)
        (lambda s: s["objects"][0].update(name="f2_j3"), "sim.objects[0].name", "letters and"),
        (lambda s: s["objects"][0].update(name="f1_base"), "sim.objects[0].name", "letters and"),
        (lambda s: s["objects"][1].update(name="cyl1_x"), "sim.objects[1].name", "letters and"),
        (lambda s: s["objects"][1].update(x=0.6), "sim.objects[1].x", "within reach of a finger"),
        (
            lambda s: s["objects"][0].update(x=-0.075, y=-0.05, radius=0.01),
            "sim.objects[0].x",
            "clear of link f1_j1",
        ),
        (
            lambda s: s["initial_angles"].update(f1=[1.5, 0.0, 0.0]),
            "sim.initial_angles.f1",
            "out of the palm",
        ),
        # straight down, finger 3's tip starts 22 mm into the table (its diameter is 14 mm)
        (
            lambda s: s["initial_angles"].update(f3=[0.0, 0.0, 0.0]),
            "sim.initial_angles.f3",
            "within its diameter (0.014 m) of the table top",
        ),
    ],
)
def test_a_scene_that_cannot_start_is_refused(
    hand: HandConfig, edit: Any, key: str, expected: str
) -> None:
    with pytest.raises(ConfigError) as err:
        parse_sim(_with_sim(hand, edit))
    assert err.value.key == key
    assert expected in err.value.expected
    assert err.value.file == hand.source


def _objects(*specs: tuple[str, float, float, float]) -> Any:
    def edit(s: dict[str, Any]) -> None:
        s["objects"] = [
            {"name": n, "radius": r, "length": 0.08, "mass": 0.03, "x": x, "y": y}
            for n, r, x, y in specs
        ]

    return edit


@pytest.mark.parametrize(
    "specs",
    [
        [("theOne", 0.03, 0.0, -0.11)],
        [
            ("a", 0.01, -0.033, -0.13),
            ("b", 0.012, -0.011, -0.128),
            ("c", 0.01, 0.011, -0.13),
            ("d", 0.008, 0.030, -0.132),
        ],
    ],
)
def test_one_to_four_objects_of_any_radius_and_name_a_recipe_can_name(
    hand: HandConfig, specs: list[tuple[str, float, float, float]]
) -> None:
    p = parse_sim(_with_sim(hand, _objects(*specs)))
    assert [(o.name, o.radius) for o in p.objects] == [(n, r) for n, r, _, _ in specs]


@pytest.mark.parametrize("name", ["the one", "obj0_r15", "1st", "cyl-1", "cyl1\n"])
def test_an_object_a_recipe_could_not_name_is_refused(hand: HandConfig, name: str) -> None:
    """``obj0_r15`` passed check, and every recipe naming it was refused: as ``obj0r15`` not
    an object of the scene, as ``obj0_r15`` not letters and digits."""
    with pytest.raises(ConfigError) as err:
        parse_sim(_with_sim(hand, _objects((name, 0.03, 0.0, -0.11))))
    assert err.value.key == "sim.objects[0].name" and err.value.found == name
    assert "letters and digits" in err.value.expected


def test_five_objects_are_refused(hand: HandConfig) -> None:
    five = [(f"o{i}", 0.005, -0.04 + 0.02 * i, -0.135) for i in range(5)]
    with pytest.raises(ConfigError) as err:
        parse_sim(_with_sim(hand, _objects(*five)))
    assert err.value.key == "sim.objects" and "1 to 4" in err.value.expected


def test_fingers_side_by_side_may_collide_without_touching_at_the_start(hand: HandConfig) -> None:
    """f1 and f2 share their plane position but not their z: asking for finger contact is
    accepted (their links are 44 mm apart along z), with a friction of its own."""

    def edit(s: dict[str, Any]) -> None:
        s["contact"]["between_fingers"] = True
        s["friction"]["finger_finger"] = 0.7

    p = parse_sim(_with_sim(hand, edit))
    assert p.between_fingers and p.finger_finger_friction == 0.7


def test_crossed_fingers_are_refused_where_fingers_collide() -> None:
    planar = load_hand(PLANAR)

    def cross(s: dict[str, Any]) -> None:
        s["initial_angles"].update(left=[0.95, 0.0], right=[-0.95, 0.0])
        s["objects"][0].update(x=-0.18)  # out of the crossed fingers' way
        s["objects"][1].update(x=0.18)

    crossed = _with_sim(planar, cross)
    with pytest.raises(ConfigError) as err:
        parse_sim(crossed)
    assert err.value.key == "sim.initial_angles.right"
    assert "keep the fingers apart" in err.value.expected and "left_j" in err.value.expected
    # without finger contact the same start is one the fingers pass through
    apart = _with_sim(
        crossed,
        lambda s: (s["contact"].update(between_fingers=False), s["friction"].pop("finger_finger")),
    )
    assert parse_sim(apart).initial_angles == ((0.95, 0.0), (-0.95, 0.0))


def test_shipped_planar_hand_is_the_papers_shape() -> None:
    planar = load_hand(PLANAR)
    p = parse_sim(planar)
    assert [len(f.joints) for f in planar.fingers] == [2, 2]
    assert [f.base_x for f in planar.fingers] == [-0.05, 0.05]
    assert all(j.link_length == 0.1 for j in planar.joints)
    assert [o.radius for o in p.objects] == [0.045, 0.045]  # 0.45 of a link, as in the paper
    assert all(o.y - o.radius == pytest.approx(p.table_height) for o in p.objects)
    for finger in planar.fingers:
        n = finger.node_id
        assert finger.can_ids.as_dict() == {
            "node_command": 0x010 + n,
            "torque_command": 0x100 + n,
            "feedback": 0x180 + n,
            "status": 0x280 + n,
            "heartbeat": 0x700 + n,
        }


def test_every_model_the_planning_draws_is_a_scene_that_can_start(hand: HandConfig) -> None:
    """The planning's perturbed models (start pose, radii, placement, gap) go through the same
    checks when they run on the bus (``hand_with``): none may be refused."""
    params = parse_sim(hand)
    for seed in range(300):
        model = perturb(params, np.random.default_rng(seed), Spread(), hand)
        again = parse_sim(hand_with(hand, model.params, seed=seed))
        assert again.initial_angles == model.params.initial_angles
        assert again.links == model.params.links
        assert again.motor_tau_max == model.params.motor_tau_max


@pytest.mark.parametrize("name", ["four_fingers_four_joints", "planar_2f2j"])
def test_every_model_the_planning_draws_of_the_other_shipped_hands_can_start(name: str) -> None:
    """The same for the other shapes: the four-by-four's long fingers dip their tips deepest
    into the table in a drawn start pose (up to 11 mm), still within a link's diameter."""
    hand = load_hand(ROOT / "config" / "hands" / f"{name}.yaml")
    params = parse_sim(hand)
    for seed in range(300):
        model = perturb(params, np.random.default_rng(seed), Spread(), hand)
        again = parse_sim(hand_with(hand, model.params, seed=seed))
        assert again.initial_angles == model.params.initial_angles


def test_a_drawn_start_pose_stays_inside_the_margin_a_scene_needs(hand: HandConfig) -> None:
    """A hand that starts near a limit: the drawn start poses are clipped inside the margin
    ``parse_sim`` asks of a start pose, so every model can still start (one clipped onto the
    limit itself was refused, and the bench stopped with it)."""
    raw = copy.deepcopy(dict(hand.sim))
    lower = hand.fingers[0].joints[0].angle_min
    raw["initial_angles"]["f1"] = [lower + 0.02, *raw["initial_angles"]["f1"][1:]]
    near = dataclasses.replace(hand, sim=raw)
    params = parse_sim(near)
    for seed in range(50):
        model = perturb(params, np.random.default_rng(seed), Spread(), near)
        again = parse_sim(hand_with(near, model.params, seed=seed))
        assert again.initial_angles[0][0] >= lower + 0.01


def test_a_joint_named_like_the_scene_is_refused(hand: HandConfig) -> None:
    fingers = list(hand.fingers)
    joints = list(fingers[1].joints)
    joints[2] = dataclasses.replace(joints[2], name="f1_base")
    fingers[1] = dataclasses.replace(fingers[1], joints=tuple(joints))
    with pytest.raises(ConfigError) as err:
        parse_sim(dataclasses.replace(hand, fingers=tuple(fingers)))
    assert err.value.key == "fingers[1].joints[2].name"
    assert "the base of f1" in err.value.expected


def test_a_model_of_a_hand_whose_fingers_collide_keeps_its_finger_contact() -> None:
    """``hand_with`` writes the section back for a run on the bus: finger contact and its
    friction survive, as do the per-finger links and motor limits."""
    planar = load_hand(PLANAR)
    params = parse_sim(planar)
    again = parse_sim(hand_with(planar, params))
    assert again == params
    assert again.between_fingers and again.finger_finger_friction == 0.5


@pytest.mark.parametrize(
    ("link", "problem"),
    [
        (dict(mass=1e-12), "mjMINVAL"),
        (dict(radius=1e-9), "mjMINVAL"),
    ],
)
def test_a_scene_mujoco_cannot_build_is_bad_input(
    hand: HandConfig, link: dict[str, float], problem: str
) -> None:
    """Numbers past parse_sim's bounds (as a perturbed model could give) that MuJoCo refuses
    are the hand config's fault, named as such, never a MuJoCo traceback."""
    params = parse_sim(hand)
    links = (dataclasses.replace(params.links[0], **link), *params.links[1:])
    with pytest.raises(ConfigError) as err:
        Plant(hand, dataclasses.replace(params, links=links))
    assert err.value.file == hand.source
    assert err.value.key == "sim"
    assert problem in str(err.value.found)


def test_a_start_one_margin_inside_a_limit_is_taken_however_the_decimals_round(
    hand: HandConfig,
) -> None:
    """0.06 against a lower limit of 0.05 is 0.00999... rad in binary: it was refused as less
    than the 0.01 rad margin, where 0.51 against 0.50 was taken."""
    finger = hand.fingers[1]
    joint = dataclasses.replace(finger.joints[1], angle_min=0.05)
    fingers = list(hand.fingers)
    fingers[1] = dataclasses.replace(finger, joints=(finger.joints[0], joint, *finger.joints[2:]))
    moved = dataclasses.replace(hand, fingers=tuple(fingers))

    def start(value: float) -> Any:
        def edit(s: dict[str, Any]) -> None:
            angles = list(s["initial_angles"][finger.name])
            angles[1] = value
            s["initial_angles"] = {**s["initial_angles"], finger.name: angles}

        return edit

    p = parse_sim(_with_sim(moved, start(0.06)))
    assert p.initial_angles[1][1] == 0.06
    with pytest.raises(ConfigError) as err:
        parse_sim(_with_sim(moved, start(0.0599)))
    assert err.value.key == f"sim.initial_angles.{finger.name}[1]"


def test_an_object_with_nothing_under_it_rests_on_the_table(hand: HandConfig) -> None:
    """Put 15 mm up, it falls at the first step: its height above rest was measured from
    where it had been put, so a lift needed 25 mm to count 10. One laid on the pair, touching
    both, rests where it is put; without gravity every object stays where it is."""
    import math

    from handctl.sim.placement import rest_heights, unsupported

    def up(s: Any) -> None:
        s["objects"][0].update(y=s["objects"][0]["y"] + 0.015)

    def third(s: Any) -> None:
        a, b = s["objects"][0], s["objects"][1]
        half = (b["x"] - a["x"]) / 2
        rise = math.sqrt((2 * a["radius"]) ** 2 - half**2)
        s["objects"].append({**a, "name": "cyl3", "x": a["x"] + half, "y": a["y"] + rise})

    shipped = parse_sim(hand)
    raised = parse_sim(_with_sim(hand, up))
    assert [i for i, _ in unsupported(hand, raised)] == [0]
    assert unsupported(hand, raised)[0][1] == pytest.approx(0.015)
    assert rest_heights(hand, raised) == pytest.approx(rest_heights(hand, shipped))
    assert rest_heights(hand, shipped) == tuple(o.y for o in shipped.objects)
    stacked = parse_sim(_with_sim(hand, third))
    assert unsupported(hand, stacked) == []
    assert rest_heights(hand, stacked) == tuple(o.y for o in stacked.objects)
    weightless = dataclasses.replace(raised, gravity=0.0)
    assert rest_heights(hand, weightless) == tuple(o.y for o in raised.objects)


@pytest.mark.parametrize("angles", [[0.0, 0.0, 0.0], [0.3, 0.5, 0.5], [-0.3, 0.0, 0.0]])
def test_a_finger_based_on_the_palm_is_said_of_its_base(
    hand: HandConfig, angles: list[float]
) -> None:
    """A finger hung from the palm's face inside its width: its first link starts at the
    base, so it overlaps the palm at any angle. The refusal named the initial angles, which
    no angle could satisfy (found by an outside audit); it names the base, what to move."""
    fingers = list(hand.fingers)
    fingers[1] = dataclasses.replace(fingers[1], base_x=0.0, base_y=0.0)
    moved = dataclasses.replace(hand, fingers=tuple(fingers))

    def edit(s: dict[str, Any]) -> None:
        s["initial_angles"][fingers[1].name] = angles

    with pytest.raises(ConfigError) as err:
        parse_sim(_with_sim(moved, edit))
    assert err.value.key == "fingers[1].base"
    assert "from the palm" in err.value.expected
    assert err.value.file == hand.source


def test_a_joint_too_narrow_to_start_inside_is_said_as_such(hand: HandConfig) -> None:
    """A joint of ±0.005 rad was asked for a start "at least 0.01 rad inside" its limits,
    which no angle can meet (found by an outside audit): the range is what is wrong."""
    finger = hand.fingers[0]
    narrow = dataclasses.replace(finger.joints[0], angle_min=-0.005, angle_max=0.005)
    fingers = (
        dataclasses.replace(finger, joints=(narrow, *finger.joints[1:])),
        *hand.fingers[1:],
    )

    def start_at_zero(s: dict[str, Any]) -> None:
        s["initial_angles"][finger.name][0] = 0.0

    with pytest.raises(ConfigError) as err:
        parse_sim(_with_sim(dataclasses.replace(hand, fingers=fingers), start_at_zero))
    assert err.value.key == f"sim.initial_angles.{finger.name}[0]"
    assert f"{narrow.name}'s range [-0.005, 0.005] rad is narrower than 0.02 rad" in (
        err.value.expected
    )


def _hand_with_first_joint(tmp_path: Path, edit: Any) -> HandConfig:
    """The shipped hand, its first joint edited as written in the file (not as read)."""
    data = yaml.safe_load(HAND_YAML.read_text())
    edit(data["fingers"][0]["joints"][0])
    path = tmp_path / "hand.yaml"
    path.write_text(yaml.safe_dump(data))
    return load_hand(path)


def test_a_written_half_thickness_of_0_is_held_to_the_simulated_link(tmp_path: Path) -> None:
    """``half_thickness: 0`` was taken for "not given" and never compared: ``check`` said ok
    of a hand whose estimator saw line links and whose simulation 12 mm ones (found by an
    outside audit). Written, a 0 is a claim like any other, and no simulated link meets it."""
    hand = _hand_with_first_joint(tmp_path, lambda j: j.update(half_thickness=0.0))
    finger, joint = hand.fingers[0], hand.fingers[0].joints[0]
    with pytest.raises(ConfigError) as err:
        parse_sim(hand)
    assert err.value.file == str(tmp_path / "hand.yaml")
    assert err.value.key == f"sim.links.{finger.name}[0].radius"
    expected = err.value.expected
    assert f"the half_thickness of {joint.name} (0 m, fingers[0].joints[0])" in expected
    assert "a written 0 is a line link" in expected
    assert err.value.found == hand.sim["links"][finger.name][0]["radius"] > 0


def test_a_recorded_hand_with_a_written_half_thickness_of_0_reads_as_it_ran() -> None:
    """A log recorded before that rule, of a hand writing ``half_thickness: 0`` beside its
    ``sim.links``: its recorded hand lost its simulated hand (no turn in its replay, no
    torque panels in its plot; found by an outside audit of the rule). It reads as it ran."""
    from handctl.config import parse_hand
    from handctl.recording.metadata import _parsed_hand
    from handctl.schema import parse_yaml

    data = yaml.safe_load(HAND_YAML.read_text())
    data["fingers"][0]["joints"][0]["half_thickness"] = 0.0
    text = yaml.safe_dump(data)
    with pytest.raises(ConfigError):  # today's rule, for a hand config given now
        parse_sim(parse_hand(parse_yaml(text, "hand.yaml"), None))
    recorded = _parsed_hand(text, None, "old.mcap")
    assert recorded.joints[0].half_thickness == 0.0
    assert parse_sim(recorded).links  # its simulated hand, as the run had it


def test_a_half_thickness_left_out_is_not_held_to_the_simulated_link(tmp_path: Path) -> None:
    """docs/simulation.md: the two must be equal "where the joint gives half_thickness"; a
    joint that leaves it out keeps the paper's line link for the estimator."""
    hand = _hand_with_first_joint(tmp_path, lambda j: j.pop("half_thickness"))
    assert hand.fingers[0].joints[0].half_thickness == 0.0
    parse_sim(hand)
