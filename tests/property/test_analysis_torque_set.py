"""Exact torque set against the LP oracle for random torque ratios, tasks and gravity; and the
polygon operations it is built from."""

from __future__ import annotations

import dataclasses
from functools import cache
from pathlib import Path

import numpy as np
from hypothesis import example, given, settings
from hypothesis import strategies as st

from handctl.analysis.conditions import Conditions, build_conditions
from handctl.analysis.exact import ExactTorqueSet, exact_torque_set
from handctl.analysis.model import load_scenario
from handctl.analysis.oracle import lp_values
from handctl.analysis.polygons import area, clip, difference, distance, hull, intersect
from handctl.analysis.slices import TorqueSlice, ratio_slice

ROOT = Path(__file__).resolve().parents[2]
FIG3 = ROOT / "config" / "analysis" / "paper_fig3.yaml"
TOL = 1e-6  # N·m, distance in the torque plane
SOLVER_TOL = 1e-7  # N·m or N: ties closer than this are for the LP solver's tolerances to break


@cache
def _conditions(angle1: float, angle2: float, reading: str, g: float) -> Conditions:
    grasp = load_scenario(FIG3).grasp
    grasp = dataclasses.replace(grasp, reading=reading, gravity=np.array([0.0, -g]))
    return build_conditions(
        grasp,
        {
            "cylinder1": np.array([np.cos(angle1), np.sin(angle1)]),
            "cylinder2": np.array([np.cos(angle2), np.sin(angle2)]),
        },
    )


def _check_point(cond: Conditions, sl: TorqueSlice, ts: ExactTorqueSet, u: np.ndarray) -> None:
    """LP oracle against the exact set at one point, unless the point is a tie: on the
    boundary in the plane, or within the solver's tolerance of it in torque or force."""
    lp = lp_values(cond, sl.torques(u))
    residual = abs(float(ts.realisability_residual(u)[0]))
    if ts.realisable_boundary_distance(u)[0] <= TOL or residual <= SOLVER_TOL:
        return
    assert lp.realisable == bool(ts.realisable_mask(u)[0])
    if not lp.realisable:
        return
    np.testing.assert_allclose(lp.values, ts.margins(u)[0], atol=1e-6)
    tie = float(np.min(np.abs(ts.margins(u)[0]))) <= SOLVER_TOL
    if ts.boundary_distance(u)[0] > TOL and not tie:
        # the oracle knows no torque limit; the set is cut by it
        assert (lp.inside and sl.within_limits(u)[0]) == bool(ts.inside_mask(u)[0])


@settings(max_examples=30, deadline=None)
@given(
    k1=st.floats(-2.0, 2.0),
    k2=st.floats(-2.0, 2.0),
    a1=st.sampled_from([np.pi / 2, 0.0, 2.0]),
    a2=st.sampled_from([-np.pi / 2, np.pi, -1.0]),
    reading=st.sampled_from(["paper", "net"]),
    g=st.sampled_from([0.0, 0.5]),
    seed=st.integers(0, 2**31 - 1),
)
def test_exact_matches_lp_at_random_points(
    k1: float, k2: float, a1: float, a2: float, reading: str, g: float, seed: int
) -> None:
    cond = _conditions(a1, a2, reading, g)
    grasp = load_scenario(FIG3).grasp
    sl = ratio_slice(grasp, (k1, k2), 3.0)
    ts = exact_torque_set(cond, sl)
    rng = np.random.default_rng(seed)
    lo, hi = sl.bounds()
    pts = rng.uniform(lo, hi, size=(6, 2))
    # also points inside the region, where a wrong 'inside' would be most costly
    for poly in ts.region[:2]:
        pts = np.vstack([pts, poly.mean(axis=0)])
    for u in pts:
        _check_point(cond, sl, ts, u)


@settings(max_examples=20, deadline=None)
@given(seed=st.integers(0, 2**31 - 1))
def test_general_plane_of_torques(seed: int) -> None:
    """A slice that is not eq. 25 (all four torques vary): same agreement."""
    rng = np.random.default_rng(seed)
    cond = _conditions(np.pi / 2, -np.pi / 2, "paper", 0.0)
    sl = TorqueSlice(rng.normal(size=(4, 2)), 3.0)
    ts = exact_torque_set(cond, sl)
    lo, hi = sl.bounds()
    for u in rng.uniform(lo, hi, size=(6, 2)):
        _check_point(cond, sl, ts, u)


points = st.lists(st.tuples(st.floats(-5, 5), st.floats(-5, 5)), min_size=3, max_size=12)
planes = st.lists(
    st.tuples(st.floats(-1, 1), st.floats(-1, 1), st.floats(-2, 2)), min_size=0, max_size=5
)


@settings(max_examples=150, deadline=None)
@given(points, planes, st.integers(0, 2**31 - 1))
@example(
    pts=[(0.0, 0.0), (0.0, -1.0), (1.0, 0.0)], hps=[(-1.0, -0.125, -3.8906318096990296e-13)], seed=0
)  # a vertex on the line
def test_difference_and_intersection_partition_a_polygon(
    pts: list[tuple[float, float]], hps: list[tuple[float, float, float]], seed: int
) -> None:
    poly = hull(np.array(pts))
    halfplanes = [(np.array([a, b]), c) for a, b, c in hps]
    pieces = difference(poly, halfplanes)
    kept = intersect(poly, halfplanes)
    total = sum(area(p) for p in pieces) + area(kept)
    assert abs(total - area(poly)) <= 1e-7 * max(1.0, area(poly))
    # sample: a point of the polygon is in the kept part or in a piece, never in two pieces
    rng = np.random.default_rng(seed)
    lo, hi = poly.min(axis=0), poly.max(axis=0)
    sample = rng.uniform(lo, hi, size=(50, 2))
    inside = distance(poly, sample) == 0.0
    satisfied = np.ones(len(sample), dtype=bool)
    for a, b in halfplanes:
        satisfied &= sample @ a <= b
    in_piece = np.array([distance(p, sample) <= 1e-9 for p in pieces]).reshape(-1, 50)
    in_kept = distance(kept, sample) <= 1e-9 if len(kept) else np.zeros(50, dtype=bool)
    margin = np.ones(len(sample), dtype=bool)
    for a, b in halfplanes:  # points on a boundary line may go either way
        if np.linalg.norm(a) > 1e-9:
            margin &= np.abs(sample @ a - b) / np.linalg.norm(a) > 1e-6
        else:
            margin &= abs(b) > 1e-6
    for i in np.flatnonzero(inside & margin):
        assert in_kept[i] == satisfied[i]
        assert int(in_piece[:, i].sum()) == (0 if satisfied[i] else 1)


@settings(max_examples=100, deadline=None)
@given(points, st.floats(-1, 1), st.floats(-1, 1), st.floats(-3, 3))
def test_clip_keeps_exactly_the_half_plane(
    pts: list[tuple[float, float]], a0: float, a1: float, b: float
) -> None:
    poly = hull(np.array(pts))
    a = np.array([a0, a1])
    out = clip(poly, a, b)
    if len(out):
        assert np.all(out @ a <= b + 1e-9)
        assert np.all(distance(poly, out) <= 1e-9)
    assert area(out) <= area(poly) + 1e-12
