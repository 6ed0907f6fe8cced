"""The torque set checked by an independent engine: MuJoCo simulates the planar Fig. 3 grasp.

The simulation shares only the geometry with the analysis (read from the same scenario file);
the dynamics, contact forces and friction are MuJoCo's. Model:

* the plane is xy (gravity from the scenario; zero in the plane for the paper's Fig. 3);
* each finger is a chain of hinges about z with capsule links of radius ``RC`` from joint to
  joint, light (``LINK_MASS``) because the analysis takes the fingers as massless; they start at
  the scenario's joint angles, at rest, and are driven by constant joint torques
  (``qfrc_applied``) from t = 0;
* each cylinder has slide x, slide y and a hinge about z, its mass and planar inertia from the
  scenario; it carries two collision cylinders: one of radius ``R - RC`` for the finger contacts
  (so the capsule's surface is tangent exactly where the ideal line link is), one of radius R for
  the other cylinder;
* contacts are explicit pairs (every other collision is off; no other pair can come within reach
  in 100 ms): finger–cylinder with the scenario's μ = 0.1, ``condim`` 3;
* the rolling constraint of eq. 19 at C is a *unilateral* contact with high friction
  (``MU_ROLLING``) rather than an equality: it rolls as long as it is compressed, and separates
  if the analysis were wrong about compression, so the replacement of eq. 24 is exercised too;
* elliptic friction cones, stiff contacts (2 ms time constant) and a 0.2 ms step.

The condition is sufficient: every sampled torque inside the exact region must move cylinder 1
up and cylinder 2 down within 100 ms; torques outside prove nothing and are not asserted, except
to show the simulation can tell the tasks apart.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from handctl.analysis.conditions import build_conditions
from handctl.analysis.exact import ExactTorqueSet, exact_torque_set
from handctl.analysis.frames import Array
from handctl.analysis.model import Grasp, load_scenario
from handctl.analysis.polygons import area
from handctl.analysis.slices import ratio_slice

mujoco = pytest.importorskip("mujoco")

ROOT = Path(__file__).resolve().parents[2]
FIG3 = ROOT / "config" / "analysis" / "paper_fig3.yaml"
VERTICAL = ROOT / "config" / "analysis" / "paper_fig3_vertical.yaml"
RC = 0.004  # m, capsule radius of the links
LINK_MASS = 0.02  # kg
MU_ROLLING = 5.0
TIMESTEP = 2e-4  # s
DURATION = 0.1  # s
SAMPLES = 40


def _mjcf(grasp: Grasp) -> str:
    def f(x: float) -> str:
        return repr(float(x))

    bodies = []
    for i, body in enumerate(grasp.bodies):
        x, y = body.position
        inertia = float(body.inertia[0, 0])
        bodies.append(
            f'<body name="obj{i}" pos="{f(x)} {f(y)} 0">'
            f'<joint type="slide" axis="1 0 0"/><joint type="slide" axis="0 1 0"/>'
            f'<joint type="hinge" axis="0 0 1"/>'
            f'<inertial pos="0 0 0" mass="{f(body.mass)}" '
            f'diaginertia="{f(inertia)} {f(inertia)} {f(inertia)}"/>'
            f'<geom name="touch{i}" type="cylinder" size="{f(body.radius - RC)} 0.05"/>'
            f'<geom name="side{i}" type="cylinder" size="{f(body.radius)} 0.05"/></body>'
        )
    fingers = []
    for j, finger in enumerate(grasp.fingers):
        xml = ""
        for k, (length, angle) in enumerate(zip(finger.lengths, finger.angles, strict=True)):
            if k == 0:
                bx, by = finger.base
                pos = f"{f(bx)} {f(by)} 0"
            else:
                pos = f"{f(finger.lengths[k - 1])} 0 0"
            xml += (
                f'<body pos="{pos}" euler="0 0 {f(angle)}">'
                f'<joint name="j{j}_{k}" type="hinge" axis="0 0 1"/>'
                f'<geom name="link{j}_{k}" type="capsule" fromto="0 0 0 {f(length)} 0 0" '
                f'size="{RC}" mass="{LINK_MASS}"/>'
            )
        fingers.append(xml + "</body>" * finger.joints)
    pairs = [
        f'<pair geom1="link{c.finger}_{c.link}" geom2="touch{c.body}" condim="3" '
        f'friction="{f(c.mu)} {f(c.mu)} 0.0001 0.0001 0.0001"/>'
        for c in grasp.finger_contacts
    ]
    pairs += [
        f'<pair geom1="side{c.first}" geom2="side{c.second}" condim="3" '
        f'friction="{MU_ROLLING} {MU_ROLLING} 0.0001 0.0001 0.0001"/>'
        for c in grasp.body_contacts
    ]
    gx, gy = grasp.gravity
    return (
        f'<mujoco><compiler angle="radian"/>'
        f'<option timestep="{TIMESTEP}" gravity="{f(gx)} {f(gy)} 0" cone="elliptic" '
        f'impratio="10"/>'
        f'<default><geom contype="0" conaffinity="0" solref="0.002 1" '
        f'solimp="0.95 0.99 0.0001"/>'
        f'<pair solref="0.002 1" solimp="0.95 0.99 0.0001"/></default>'
        f"<worldbody>{''.join(bodies)}{''.join(fingers)}</worldbody>"
        f"<contact>{''.join(pairs)}</contact></mujoco>"
    )


def _displacements(model: object, grasp: Grasp, tau: Array) -> Array:
    """Vertical displacement of each cylinder after DURATION under constant torques."""
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    start = np.array([data.qpos[3 * i + 1] for i in range(len(grasp.bodies))])
    first_joint = 3 * len(grasp.bodies)
    for _ in range(round(DURATION / TIMESTEP)):
        data.qfrc_applied[:] = 0.0
        data.qfrc_applied[first_joint : first_joint + len(tau)] = tau
        mujoco.mj_step(model, data)
    end = np.array([data.qpos[3 * i + 1] for i in range(len(grasp.bodies))])
    return np.asarray(end - start, dtype=np.float64)


def _sample(ts: ExactTorqueSet, count: int, seed: int) -> Array:
    """Uniform points in the exact region (fan triangulation of its convex polygons)."""
    rng = np.random.default_rng(seed)
    triangles = [np.array([p[0], p[i], p[i + 1]]) for p in ts.region for i in range(1, len(p) - 1)]
    weights = np.array([abs(area(t)) for t in triangles])
    picks = rng.choice(len(triangles), size=count, p=weights / weights.sum())
    r1, r2 = rng.uniform(size=count), rng.uniform(size=count)
    s = np.sqrt(r1)
    out = np.array(
        [
            (1 - a) * t[0] + a * (1 - b) * t[1] + a * b * t[2]
            for t, a, b in zip((triangles[i] for i in picks), s, r2, strict=True)
        ]
    )
    assert np.all(ts.inside_mask(out))
    return out


def _agreement(
    grasp: Grasp,
    directions: dict[str, Array],
    k: tuple[float, float],
    tau_max: float,
    want: tuple[float, float],
    seed: int,
) -> float:
    cond = build_conditions(grasp, directions)
    sl = ratio_slice(grasp, k, tau_max)
    ts = exact_torque_set(cond, sl)
    assert ts.area > 0.0
    model = mujoco.MjModel.from_xml_string(_mjcf(grasp))
    hits = 0
    for u in _sample(ts, SAMPLES, seed):
        dy = _displacements(model, grasp, sl.torques(u))
        hits += bool(dy[0] * want[0] > 0.0 and dy[1] * want[1] > 0.0)
    return hits / SAMPLES


@pytest.mark.parametrize("k", [(0.9, 0.1), (1.2, 0.5)])
def test_inside_torques_move_cylinder_1_up_and_2_down(k: tuple[float, float]) -> None:
    sc = load_scenario(FIG3)
    assert sc.grasp.reading == "paper"
    assert _agreement(sc.grasp, sc.directions, k, sc.tau_max, (1.0, -1.0), seed=1) >= 0.95


def test_the_opposite_task_moves_the_opposite_way() -> None:
    """Cylinder 1 down and 2 up (the mirror task, k swapped): the simulation tells them apart."""
    sc = load_scenario(FIG3)
    opposite = {"cylinder1": np.array([0.0, -1.0]), "cylinder2": np.array([0.0, 1.0])}
    assert _agreement(sc.grasp, opposite, (0.1, 0.9), sc.tau_max, (-1.0, 1.0), seed=2) >= 0.95


def test_no_torque_no_motion() -> None:
    grasp = load_scenario(FIG3).grasp
    model = mujoco.MjModel.from_xml_string(_mjcf(grasp))
    np.testing.assert_allclose(_displacements(model, grasp, np.zeros(4)), 0.0, atol=1e-9)


def test_vertical_plane_needs_the_net_reading() -> None:
    """With gravity in the plane, the net reading's set works in simulation; the paper's reading
    (gravity left out of f_ti) admits torques under which cylinder 1 falls."""
    sc = load_scenario(VERTICAL)
    assert sc.grasp.reading == "net"
    k = (1.2, 0.5)
    assert _agreement(sc.grasp, sc.directions, k, sc.tau_max, (1.0, -1.0), seed=3) >= 0.95
    paper = dataclasses.replace(sc.grasp, reading="paper")
    sl = ratio_slice(paper, k, sc.tau_max)
    net_set = exact_torque_set(build_conditions(sc.grasp, sc.directions), sl)
    paper_set = exact_torque_set(build_conditions(paper, sc.directions), sl)
    only_paper = [u for u in _sample(paper_set, 200, seed=4) if not net_set.inside_mask(u)[0]][:10]
    assert only_paper
    model = mujoco.MjModel.from_xml_string(_mjcf(sc.grasp))
    falls = [_displacements(model, sc.grasp, sl.torques(u))[0] < 0.0 for u in only_paper]
    assert any(falls)
