"""The robust torque set: LP oracle against the exact polygons, and the awkward cases."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from handctl.analysis.conditions import build_conditions
from handctl.analysis.exact import dual_polyhedron, exact_torque_set
from handctl.analysis.frames import rotation_2d
from handctl.analysis.model import Body, Finger, FingerContact, Grasp, load_scenario
from handctl.analysis.oracle import lp_grid, lp_values
from handctl.analysis.planner import plan_for_conditions
from handctl.analysis.polygons import area
from handctl.analysis.slices import TorqueSlice, ratio_slice

ROOT = Path(__file__).resolve().parents[2]
FIG3 = ROOT / "config" / "analysis" / "paper_fig3.yaml"
TOL = 1e-6  # N·m, boundary tolerance


@pytest.mark.parametrize("k", [(0.9, 0.1), (1.2, 0.5)])
def test_exact_set_agrees_with_the_lp_oracle_on_a_grid(k: tuple[float, float]) -> None:
    sc = load_scenario(FIG3)
    cond = build_conditions(sc.grasp, sc.directions)
    sl = ratio_slice(sc.grasp, k, sc.tau_max)
    ts = exact_torque_set(cond, sl)
    lo, hi = sl.bounds()
    xs, ys = np.linspace(lo[0], hi[0], 23), np.linspace(lo[1], hi[1], 23)
    real, inside = lp_grid(cond, sl, xs, ys)
    gx, gy = np.meshgrid(xs, ys)
    pts = np.column_stack([gx.ravel(), gy.ravel()])
    differ = (inside.ravel() != ts.inside_mask(pts)) & (ts.boundary_distance(pts) > TOL)
    assert not differ.any(), pts[differ]
    differ = (real.ravel() != ts.realisable_mask(pts)) & (
        ts.realisable_boundary_distance(pts) > TOL
    )
    assert not differ.any(), pts[differ]
    assert inside.any() and (~real).any() and (real & ~inside).any()  # all three kinds occur


@pytest.mark.parametrize("k", [(0.9, 0.1), (1.2, 0.5), (-0.4, 2.0)])
def test_exact_margins_equal_lp_minima(k: tuple[float, float]) -> None:
    sc = load_scenario(FIG3)
    cond = build_conditions(sc.grasp, sc.directions)
    sl = ratio_slice(sc.grasp, k, sc.tau_max)
    ts = exact_torque_set(cond, sl)
    rng = np.random.default_rng(2)
    lo, hi = sl.bounds()
    for u in rng.uniform(lo, hi, size=(40, 2)):
        result = lp_values(cond, sl.torques(u))
        assert result.realisable == bool(ts.realisable_mask(u)[0])
        if result.realisable:
            np.testing.assert_allclose(result.values, ts.margins(u)[0], atol=1e-7)


def test_region_lies_in_the_realisable_part_of_the_box() -> None:
    sc = load_scenario(FIG3)
    cond = build_conditions(sc.grasp, sc.directions)
    sl = ratio_slice(sc.grasp, (1.2, 0.5), sc.tau_max)
    ts = exact_torque_set(cond, sl)
    lo, hi = sl.bounds()
    np.testing.assert_allclose([lo, hi], [[-2.5, -3.0], [2.5, 3.0]])  # |1.2 τ_11| ≤ 3
    assert 0.0 < ts.area < ts.realisable_area <= area(ts.limit) + 1e-12
    for poly in ts.region:
        assert np.all(ts.realisable_mask(poly))
        assert np.all(sl.within_limits(poly))
        centroid = poly.mean(axis=0)
        assert ts.inside_mask(centroid)[0]
        assert lp_values(cond, sl.torques(centroid)).inside


def test_torque_that_no_contact_force_realises() -> None:
    sc = load_scenario(FIG3)
    cond = build_conditions(sc.grasp, sc.directions)
    sl = ratio_slice(sc.grasp, (0.9, 0.1), sc.tau_max)
    u = np.array([-1.0, -1.0])  # finger 1 pulling outward: contacts cannot pull
    result = lp_values(cond, sl.torques(u))
    assert not result.realisable and not result.inside
    assert not exact_torque_set(cond, sl).realisable_mask(u)[0]


def _squeeze_grasp() -> Grasp:
    """One link pushing a disc above it and a disc below it at different distances: the finger
    can push them apart with any force at zero torque, so the λ-set is unbounded."""
    r = 0.3
    finger = Finger("f", np.zeros(2), rotation_2d(0.0), (2.0, 0.5), (0.0, 0.5))
    bodies = (
        Body("a", np.array([0.5, r]), np.eye(2), r, 1.0, np.array([[0.045]])),
        Body("b", np.array([1.5, -r]), np.eye(2), r, 1.0, np.array([[0.045]])),
    )
    contacts = (
        FingerContact(0, 0, 0, 0.2, np.array([0.5, 0.0]), np.array([0.0, 1.0])),
        FingerContact(0, 0, 1, 0.2, np.array([1.5, 0.0]), np.array([0.0, -1.0])),
    )
    return Grasp(2, bodies, (finger,), contacts, (), np.zeros(2))


def test_unbounded_lambda_set_is_handled() -> None:
    grasp = _squeeze_grasp()
    down = build_conditions(grasp, {"a": np.array([0.0, -1.0])})
    up = build_conditions(grasp, {"a": np.array([0.0, 1.0])})
    tau = np.array([0.4, 0.0])
    result = lp_values(down, tau)
    assert result.realisable and result.values[0] == -np.inf and not result.inside
    finite = lp_values(up, tau)
    assert np.isfinite(finite.values[0])
    # joint 2 carries no contact, so only τ_2 = 0 is realisable: a lineality of the dual
    assert not lp_values(up, np.array([0.4, 0.1])).realisable
    sl = TorqueSlice(np.array([[1.0, 0.0], [0.0, 1.0]]), 3.0)
    ts_down = exact_torque_set(down, sl)
    assert ts_down.gradients[0] is None and ts_down.area == 0.0
    assert ts_down.margins(np.array([0.4, 0.0]))[0, 0] == -np.inf
    ts_up = exact_torque_set(up, sl)
    assert ts_up.realisable_area == pytest.approx(0.0, abs=1e-12)
    assert ts_up.realisable_mask(np.array([0.4, 0.0]))[0]
    assert not ts_up.realisable_mask(np.array([0.4, 0.1]))[0]
    np.testing.assert_allclose(ts_up.margins(np.array([0.4, 0.0]))[0], finite.values)
    plan = plan_for_conditions(down, 3.0)
    assert not plan.found and "-inf" in plan.reason


def test_dual_polyhedron_of_a_square() -> None:
    a = np.array([[1.0, -1.0, 0.0, 0.0], [0.0, 0.0, 1.0, -1.0]])
    dual = dual_polyhedron(a, np.ones(4))
    assert sorted(map(tuple, np.round(dual.vertices, 12))) == [
        (-1.0, -1.0),
        (-1.0, 1.0),
        (1.0, -1.0),
        (1.0, 1.0),
    ]
    assert len(dual.rays) == 0 and len(dual.lineality) == 0
    assert dual_polyhedron(a, np.array([1.0, -2.0, 1.0, 1.0])).empty  # y ≤ 1 and y ≥ 2
    cone = dual_polyhedron(np.array([[1.0, 0.0], [0.0, 1.0]]), np.zeros(2))
    assert sorted(map(tuple, cone.rays)) == [(-1.0, 0.0), (0.0, -1.0)]


def test_mirror_symmetry_of_the_both_down_task() -> None:
    """The grasp is mirror-symmetric; mirroring swaps the fingers and flips torque signs, so
    for 'both cylinders down' with k_1 = k_2 the set is invariant under (u1, u2) -> (-u2, -u1)."""
    sc = load_scenario(FIG3)
    cond = build_conditions(
        sc.grasp, {"cylinder1": np.array([0.0, -1.0]), "cylinder2": np.array([0.0, -1.0])}
    )
    sl = ratio_slice(sc.grasp, (0.5, 0.5), sc.tau_max)
    ts = exact_torque_set(cond, sl)
    assert 0.0 < ts.area < ts.realisable_area
    rng = np.random.default_rng(4)
    pts = rng.uniform(-3, 3, size=(400, 2))
    mirrored = np.column_stack([-pts[:, 1], -pts[:, 0]])
    far = ts.boundary_distance(pts) > TOL
    np.testing.assert_array_equal(ts.inside_mask(pts)[far], ts.inside_mask(mirrored)[far])


@pytest.mark.campaign
@pytest.mark.parametrize("k", [(0.9, 0.1), (1.2, 0.5)])
def test_full_121_grid_agreement(k: tuple[float, float]) -> None:
    """The benchmark's comparison as a test (about 20 s per setting, so a campaign)."""
    sc = load_scenario(FIG3)
    cond = build_conditions(sc.grasp, sc.directions)
    sl = ratio_slice(sc.grasp, k, sc.tau_max)
    ts = exact_torque_set(cond, sl)
    lo, hi = sl.bounds()
    xs, ys = np.linspace(lo[0], hi[0], 121), np.linspace(lo[1], hi[1], 121)
    real, inside = lp_grid(cond, sl, xs, ys)
    gx, gy = np.meshgrid(xs, ys)
    pts = np.column_stack([gx.ravel(), gy.ravel()])
    assert not ((inside.ravel() != ts.inside_mask(pts)) & (ts.boundary_distance(pts) > TOL)).any()
    assert not (
        (real.ravel() != ts.realisable_mask(pts)) & (ts.realisable_boundary_distance(pts) > TOL)
    ).any()
