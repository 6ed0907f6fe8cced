"""The ``sim:`` section: the shipped one is sound, and every mistake names file and key path."""

from __future__ import annotations

import copy
import dataclasses
from typing import Any

import pytest

from handctl.config import HandConfig
from handctl.errors import ConfigError
from handctl.sim.params import parse_sim


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


@pytest.mark.parametrize(("edit", "key", "expected"), [
    (lambda s: s["objects"][1].update(radiuss=0.02), "sim.objects[1].radiuss", "unknown key"),
    (lambda s: s["tdt"].update(noise="much"), "sim.tdt.noise", "a number"),
    (lambda s: s.update(timestep=0.0003), "sim.timestep", "whole fraction"),
    (lambda s: s["objects"][0].update(y=-0.15), "sim.objects[0].y", "above the table"),
    (lambda s: s["objects"][1].update(x=-0.01), "sim.objects[1].x", "not overlapping"),
    (lambda s: s["initial_angles"].update(f3=[0.55, 1.2, 0.1]), "sim.initial_angles.f3[1]",
     "soft limits"),
    (lambda s: s["initial_angles"].pop("f2"), "sim.initial_angles.f2", "required"),
    (lambda s: s["actuator"]["motor_tau_max"].update(f2=[0.5, 0.75, 0.5]),
     "sim.actuator.motor_tau_max.f2[0]", "device_tau_max"),
    (lambda s: s["actuator"]["motor_tau_max"].update(f3=[1.0, 0.75]),
     "sim.actuator.motor_tau_max.f3", "a list of 3 numbers"),
    (lambda s: s["actuator"].update(motor_tau_max=[1.0, 0.75, 0.5]),
     "sim.actuator.motor_tau_max", "a mapping"),
    (lambda s: s["links"].update(f2=s["links"]["f2"][:2]), "sim.links.f2", "3 mappings"),
    (lambda s: s["links"].update(f4=s["links"]["f1"]), "sim.links.f4", "unknown key"),
    (lambda s: s["links"].pop("f3"), "sim.links.f3", "required"),
    (lambda s: s["links"].update(f1=[*s["links"]["f1"][:2], {"radius": 0.006, "mass": 0.015}]),
     "sim.links.f1[2].radius", "half_thickness of f1_j3"),
    (lambda s: s["friction"].update(object_object=-0.1), "sim.friction.object_object", ">= 0"),
    (lambda s: s["friction"].update(finger_finger=0.5), "sim.friction.finger_finger",
     "between_fingers is false"),
    (lambda s: s["contact"].update(between_fingers=True), "sim.friction.finger_finger",
     "required"),
    (lambda s: s["contact"].update(between_fingers="yes"), "sim.contact.between_fingers",
     "true or false"),
])
def test_mistakes_name_the_key(hand: HandConfig, edit: Any, key: str, expected: str) -> None:
    with pytest.raises(ConfigError) as err:
        parse_sim(_with_sim(hand, edit))
    assert err.value.key == key
    assert expected in err.value.expected
    assert err.value.file == hand.source
