"""Statics of §4 on the Fig. 3 grasp: cones, signs, eq. 14 with eq. 20, and the eq. 24 trap."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest

from handctl.analysis.conditions import build_conditions
from handctl.analysis.frames import point_velocity_map
from handctl.analysis.model import Grasp, load_scenario
from handctl.analysis.statics import statics

ROOT = Path(__file__).resolve().parents[2]
FIG3 = ROOT / "config" / "analysis" / "paper_fig3.yaml"


def _grasp(reading: str = "paper", gravity: tuple[float, float] = (0.0, 0.0)) -> Grasp:
    grasp = load_scenario(FIG3).grasp
    return dataclasses.replace(grasp, reading=reading, gravity=np.array(gravity))


def test_planar_point_map_has_the_3d_shape_and_sign() -> None:
    a = np.array([0.3, -0.7])
    d = point_velocity_map(a)
    assert d.shape == (2, 3)
    # pure rotation at rate w about z: the point at a moves with w ẑ × a = w (-a_y, a_x)
    np.testing.assert_allclose(d @ [0.0, 0.0, 2.0], 2.0 * np.array([-a[1], a[0]]))
    # the transpose maps a force at a to [f; a × f]
    f = np.array([1.5, 0.4])
    np.testing.assert_allclose(d.T @ f, [1.5, 0.4, a[0] * f[1] - a[1] * f[0]])
    # and it agrees with the 3D map restricted to the plane
    d3 = point_velocity_map(np.array([a[0], a[1], 0.0]))
    np.testing.assert_allclose(d3[:2, [0, 1, 5]], d)


def test_cone_edges_are_at_the_friction_angle() -> None:
    grasp = _grasp()
    st = statics(grasp)
    for k, contact in enumerate(grasp.finger_contacts):
        for edge in st.v[2 * k : 2 * k + 2, 2 * k : 2 * k + 2].T:
            angle = math.acos(edge @ contact.normal / np.linalg.norm(edge))
            assert angle == pytest.approx(math.atan(0.1))


def test_pushing_finger_one_inward_needs_positive_torque() -> None:
    """f_CB is the force on the object: a pure normal push of link 1 of finger 1 into cylinder 1
    (which lies counter-clockwise of that link) takes a positive τ_11."""
    grasp = _grasp()
    st = statics(grasp)
    contact = grasp.finger_contacts[0]
    force = np.zeros(st.jacobian.shape[0])
    force[:2] = contact.normal
    tau = st.jacobian.T @ force
    assert tau[0] > 0.0 and tau[1] == 0.0 and np.all(tau[2:] == 0.0)


@pytest.mark.parametrize("reading", ["paper", "net"])
def test_eq14_and_eq19_hold_for_the_force_of_eq20(reading: str) -> None:
    grasp = _grasp(reading, (0.0, -9.81))
    st = statics(grasp)
    rng = np.random.default_rng(3)
    for _ in range(20):
        lam = rng.uniform(0.0, 5.0, size=int(st.v.shape[1]))
        acc = st.acceleration(lam)
        # eq. 19 differentiated at rest: the contact point C does not accelerate apart
        np.testing.assert_allclose(st.d_o @ acc, 0.0, atol=1e-12)
        # eq. 14 with D_Oᵀ f_CO: M p̈ + h = D_CBᵀ f_CB + D_Oᵀ f_CO
        rhs = st.d_cb.T @ st.f_cb(lam) + st.d_o.T @ st.f_co(lam)
        np.testing.assert_allclose(st.m_b @ acc + st.h_b, rhs, atol=1e-12)
        totals = st.totals(lam)
        # eqs. 21-22: finger forces on object i plus/minus f_CO (plus m g in the net reading)
        f = st.f_cb(lam)
        weight = np.array([0.0, -9.81]) if reading == "net" else np.zeros(2)
        np.testing.assert_allclose(totals[:2], f[0:2] + f[2:4] + st.f_co(lam) + weight, atol=1e-12)
        np.testing.assert_allclose(totals[2:], f[4:6] + f[6:8] - st.f_co(lam) + weight, atol=1e-12)
        # the net reading is m p̈; the paper's reading leaves out gravity
        net = np.concatenate([acc[0:2], acc[3:5]])
        expected = net if reading == "net" else net - np.tile([0.0, -9.81], 2)
        np.testing.assert_allclose(totals, expected, atol=1e-12)


@pytest.mark.parametrize(
    ("reading", "gravity"), [("paper", (0.0, 0.0)), ("paper", (0.0, -9.81)), ("net", (0.0, -9.81))]
)
def test_eq24_as_printed_never_holds_for_two_discs(
    reading: str, gravity: tuple[float, float]
) -> None:
    """n_1ᵀf_t1 and n_2ᵀf_t2 (outward normals at C) have opposite signs for every λ."""
    grasp = _grasp(reading, gravity)
    st = statics(grasp)
    n1 = grasp.body_contacts[0].normal
    rng = np.random.default_rng(7)
    for _ in range(200):
        lam = rng.exponential(1.0, size=int(st.v.shape[1])) * (rng.uniform(size=8) < 0.7)
        totals = st.totals(lam)
        assert float(n1 @ totals[:2]) * float(-n1 @ totals[2:]) <= 1e-9


def test_condition_rows_evaluate_the_physics() -> None:
    grasp = _grasp()
    sc = load_scenario(FIG3)
    cond = build_conditions(grasp, sc.directions)
    assert cond.labels == ("move cylinder1", "move cylinder2", "compression cylinder1/cylinder2")
    st = cond.statics
    rng = np.random.default_rng(11)
    lam = rng.uniform(0.0, 2.0, size=int(st.v.shape[1]))
    values = cond.values(lam)
    totals = st.totals(lam)
    assert values[0] == pytest.approx(totals[1])
    assert values[1] == pytest.approx(-totals[3])
    # compression: the force of cylinder 2 on cylinder 1 points into cylinder 1 (-x)
    assert values[2] == pytest.approx(-st.f_co(lam)[0])


def test_friction_rows_at_c_when_mu_is_given() -> None:
    grasp = _grasp()
    contact = dataclasses.replace(grasp.body_contacts[0], mu=0.4)
    grasp = dataclasses.replace(grasp, body_contacts=(contact,))
    cond = build_conditions(grasp, {"cylinder1": np.array([0.0, 1.0])})
    assert cond.count == 4
    rng = np.random.default_rng(5)
    for _ in range(50):
        lam = rng.uniform(0.0, 2.0, size=int(cond.statics.v.shape[1]))
        f = cond.statics.f_co(lam)
        values = cond.values(lam)
        inside_cone = abs(f[1]) < 0.4 * -f[0]
        assert inside_cone == bool(values[2] > 0 and values[3] > 0)
