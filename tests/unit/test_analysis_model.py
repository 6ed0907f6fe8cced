"""Scenario loading: the Fig. 3 geometry as the issue describes it, and the error discipline."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import yaml

from handctl.analysis.model import load_scenario
from handctl.errors import ConfigError

ROOT = Path(__file__).resolve().parents[2]
FIG3 = ROOT / "config" / "analysis" / "paper_fig3.yaml"


def _write(tmp_path: Path, data: dict[str, object]) -> Path:
    path = tmp_path / "scenario.yaml"
    path.write_text(yaml.safe_dump(data), encoding="utf-8")
    return path


def _fig3() -> dict[str, object]:
    data = yaml.safe_load(FIG3.read_text(encoding="utf-8"))
    assert isinstance(data, dict)
    return data


def test_fig3_geometry_matches_the_description() -> None:
    """Re-derive the figure's geometry from the words of the issue, independently of the file."""
    grasp = load_scenario(FIG3).grasp
    r = 0.45
    f1, f2 = grasp.fingers
    assert math.degrees(f1.angles[0]) == pytest.approx(-133.0, abs=1e-9)
    # link 1 of finger 1 slopes outward (-x) and down; cylinders touch on the symmetry axis
    start, end = f1.link_segment(0)
    assert end[0] < start[0] and end[1] < start[1]
    c1, c2 = (b.position for b in grasp.bodies)
    assert c1[0] == pytest.approx(-r) and c2[0] == pytest.approx(r)
    assert c1[1] == pytest.approx(c2[1]) and c1[1] < 0.0  # the hand is above the objects
    # both links tangent: distance from the centre to each link line is the radius
    for link in (0, 1):
        a, b = f1.link_segment(link)
        d = (b - a) / np.linalg.norm(b - a)
        w = c1 - a
        assert abs(d[0] * w[1] - d[1] * w[0]) == pytest.approx(r, abs=1e-9)
    # link 2 curls inward underneath: its contact is below the centre, tip inward of the base
    contact2 = next(c for c in grasp.finger_contacts if c.finger == 0 and c.link == 1)
    assert contact2.point[1] < c1[1]
    assert f1.link_segment(1)[1][0] > f1.link_segment(1)[0][0]
    # finger 2 is the mirror image of finger 1 (x -> -x)
    for link in (0, 1):
        a1, b1 = f1.link_segment(link)
        a2, b2 = f2.link_segment(link)
        np.testing.assert_allclose(a2, a1 * [-1, 1], atol=1e-12)
        np.testing.assert_allclose(b2, b1 * [-1, 1], atol=1e-12)
    # object-object contact on the symmetry axis with a horizontal normal
    (bc,) = grasp.body_contacts
    np.testing.assert_allclose(bc.normal, [1.0, 0.0], atol=1e-12)
    assert bc.point[0] == pytest.approx(0.0, abs=1e-12)
    assert bc.mu is None
    assert [c.mu for c in grasp.finger_contacts] == [0.1] * 4


def test_fig3_contacts_lie_on_links_and_normals_point_into_objects() -> None:
    grasp = load_scenario(FIG3).grasp
    for c in grasp.finger_contacts:
        a, b = grasp.fingers[c.finger].link_segment(c.link)
        t = float((c.point - a) @ (b - a) / ((b - a) @ (b - a)))
        assert 0.0 < t < 1.0
        centre = grasp.bodies[c.body].position
        np.testing.assert_allclose(c.point + 0.45 * c.normal, centre, atol=1e-9)


@pytest.mark.parametrize(
    ("change", "key", "expected_part"),
    [
        (lambda d: d.update(reading="both"), "reading", "one of"),
        (lambda d: d.update(colour="red"), "colour", "unknown key"),
        (lambda d: d["objects"][0].update(radius=-1.0), "objects[0].radius", "> 0"),
        (lambda d: d["objects"][1].pop("mass"), "objects[1].mass", "required"),
        (lambda d: d["fingers"][0].update(joints=[0.1]), "fingers[0].joints", "2 numbers"),
        (
            lambda d: d["fingers"][0]["joints"].__setitem__(1, 1.7),
            "contacts.fingers[1].object",
            "tangent",
        ),
        (
            lambda d: d["objects"][1]["position"].__setitem__(0, 0.5),
            "contacts.fingers[2].object",
            "tangent",
        ),
        (
            lambda d: d["contacts"]["fingers"][0].update(object="cup"),
            "contacts.fingers[0].object",
            "one of",
        ),
        (lambda d: d["contacts"]["fingers"][0].update(link=3), "contacts.fingers[0].link", "<= 2"),
        (
            lambda d: d["contacts"]["objects"][0].update(objects=["cylinder1", "cylinder1"]),
            "contacts.objects[0].objects",
            "two different",
        ),
        (
            lambda d: d["task"]["move"].update(cylinder1=[0.0, 0.0]),
            "task.move.cylinder1",
            "non-zero",
        ),
        (lambda d: d["task"]["move"].update(cup=[0.0, 1.0]), "task.move.cup", "object name"),
        # nothing to move was found only by the analysis: exit 1, naming no file or key
        (lambda d: d["task"]["move"].clear(), "task.move", "at least one object"),
        (lambda d: d.update(gravity=[0.0, "down"]), "gravity[1]", "number"),
        # a contact listed twice counted its force twice; a tau_max of 1e300 gave a torque box
        # of area inf and a mu of 1e300 no realisable torque, each reported as a result
        (
            lambda d: d["contacts"]["fingers"].append(dict(d["contacts"]["fingers"][1])),
            "contacts.fingers[4].object",
            "contacts.fingers[1]",
        ),
        (lambda d: d["task"].update(tau_max=1e300), "task.tau_max", "<= 10000"),
        (lambda d: d["contacts"]["fingers"][0].update(mu=1e300), "contacts.fingers[0].mu", "<="),
        (lambda d: d["contacts"]["objects"][0].update(mu=1e300), "contacts.objects[0].mu", "<="),
        (lambda d: d.update(gravity=[0.0, -1e300]), "gravity[1]", ">= -1000"),
        # a tolerance of a metre accepted contacts that touch nothing as touching
        (lambda d: d.update(geometry_tolerance=1.0), "geometry_tolerance", "<= 0.001"),
        # far below m r²: the contact equations' matrix was singular in floating point, said
        # as "the object-object contacts are not independent", naming no key
        (lambda d: d["objects"][0].update(inertia=1e-20), "objects[0].inertia", ">= 2.025e-10"),
    ],
)
def test_errors_name_file_key_expected_found(
    tmp_path: Path, change: object, key: str, expected_part: str
) -> None:
    data = _fig3()
    assert callable(change)
    change(data)
    path = _write(tmp_path, data)
    with pytest.raises(ConfigError) as info:
        load_scenario(path)
    err = info.value
    assert err.file == str(path)
    assert err.key == key
    assert expected_part in err.expected


def test_objects_that_do_not_touch_are_refused(tmp_path: Path) -> None:
    data = _fig3()
    objects = data["objects"]
    assert isinstance(objects, list)
    objects[1]["radius"] = 0.40
    with pytest.raises(ConfigError) as info:
        load_scenario(_write(tmp_path, data))
    # the finger contacts on cylinder2 fail first, so drop them to reach the pair check
    data = _fig3()
    contacts = data["contacts"]
    assert isinstance(contacts, dict)
    contacts["fingers"] = contacts["fingers"][:2]
    data["objects"][1]["radius"] = 0.40  # type: ignore[index]
    with pytest.raises(ConfigError) as info:
        load_scenario(_write(tmp_path, data))
    assert info.value.key == "contacts.objects[0].objects"
    assert "touching" in info.value.expected


def test_missing_file_and_bad_yaml(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="no such file"):
        load_scenario(tmp_path / "none.yaml")
    bad = tmp_path / "bad.yaml"
    bad.write_text("dimension: [1,\n", encoding="utf-8")
    with pytest.raises(ConfigError, match="valid YAML"):
        load_scenario(bad)


def _scenario_3d() -> dict[str, object]:
    """A sphere pinched by a two-link spatial finger: link 1 along +x, bent about y."""
    r = 0.2
    return {
        "dimension": 3,
        "reading": "net",
        "gravity": [0.0, 0.0, -9.81],
        "cone_edges": 6,
        "objects": [
            {
                "name": "ball",
                "shape": "sphere",
                "position": [0.5, 0.0, -r],
                "rotation": [0.0, 0.0, 0.3],
                "radius": r,
                "mass": 0.5,
                "inertia": [0.008, 0.008, 0.008],
            },
            {
                "name": "can",
                "shape": "cylinder",
                "position": [0.5, 2 * r, -r],
                "rotation": [0.0, math.pi / 2, 0.0],
                "radius": r,
                "mass": 0.5,
                "inertia": [0.01, 0.01, 0.01],
            },
        ],
        "fingers": [
            {
                "name": "f",
                "base": [0.0, 0.0, 0.0],
                "links": [1.0, 0.5],
                "joints": [0.0, 0.4],
                "axes": [[0, 0, 1], [0, 1, 0]],
            }
        ],
        "contacts": {
            "fingers": [{"finger": "f", "link": 1, "object": "ball", "mu": 0.3}],
            "objects": [{"objects": ["ball", "can"], "mu": 0.5}],
        },
        "task": {"move": {"ball": [0.0, 0.0, 1.0]}, "tau_max": 2.0},
    }


def test_3d_scenario_loads_with_cylinder_axis_and_pyramid() -> None:
    import tempfile

    with tempfile.TemporaryDirectory() as tmp:
        path = _write(Path(tmp), _scenario_3d())
        sc = load_scenario(path)
    grasp = sc.grasp
    assert grasp.dim == 3 and grasp.cone_edges == 6
    (fc,) = grasp.finger_contacts
    np.testing.assert_allclose(fc.point, [0.5, 0.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(fc.normal, [0.0, 0.0, -1.0], atol=1e-12)
    (bc,) = grasp.body_contacts
    np.testing.assert_allclose(bc.normal, [0.0, 1.0, 0.0], atol=1e-12)
    assert bc.mu == 0.5
    # a rotation vector of pi/2 about y turns the cylinder's body z axis into +x
    axis = grasp.bodies[1].axis()
    assert axis is not None
    np.testing.assert_allclose(axis, [1.0, 0.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(bc.point, [0.5, 0.2, -0.2], atol=1e-12)


def test_3d_axes_are_checked(tmp_path: Path) -> None:
    data = _scenario_3d()
    data["fingers"][0]["axes"] = [[0, 0, 1]]  # type: ignore[index]
    with pytest.raises(ConfigError) as info:
        load_scenario(_write(tmp_path, data))
    assert info.value.key == "fingers[0].axes"


@pytest.mark.parametrize("size", [1e200, 1e-100, 2.0])
def test_a_direction_of_any_length_is_that_direction(tmp_path: Path, size: float) -> None:
    """[0, 1e200] squared to infinity, and the analysis found no torque (exit 0); [0, 1e-100]
    was refused as "a non-zero direction". Only the zero vector is none."""
    data = _fig3()
    task = data["task"]
    assert isinstance(task, dict)
    task["move"]["cylinder1"] = [0.0, size]
    scenario = load_scenario(_write(tmp_path, data))
    assert scenario.directions["cylinder1"].tolist() == [0.0, 1.0]
    task["move"]["cylinder1"] = [0.0, 0.0]
    with pytest.raises(ConfigError, match="a non-zero direction"):
        load_scenario(_write(tmp_path, data))
