"""The spatial path (pyramidal cones, 6-D twists) against the planar one on the Fig. 3 grasp."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from handctl.analysis.conditions import build_conditions
from handctl.analysis.exact import exact_torque_set
from handctl.analysis.model import load_scenario
from handctl.analysis.oracle import lp_values
from handctl.analysis.slices import ratio_slice
from handctl.analysis.statics import statics

ROOT = Path(__file__).resolve().parents[2]
PLANAR = ROOT / "config" / "analysis" / "paper_fig3.yaml"
SPATIAL = ROOT / "config" / "analysis" / "paper_fig3_3d.yaml"


def test_spatial_statics_satisfy_eq14_and_eq19() -> None:
    grasp = dataclasses.replace(load_scenario(SPATIAL).grasp, gravity=np.array([0.0, -9.8, 0.3]))
    st = statics(grasp)
    assert st.v.shape == (12, 4 * 8) and st.d_o.shape == (3, 12)
    rng = np.random.default_rng(9)
    for _ in range(10):
        lam = rng.uniform(0.0, 3.0, size=st.v.shape[1])
        acc = st.acceleration(lam)
        np.testing.assert_allclose(st.d_o @ acc, 0.0, atol=1e-12)
        rhs = st.d_cb.T @ st.f_cb(lam) + st.d_o.T @ st.f_co(lam)
        np.testing.assert_allclose(st.m_b @ acc + st.h_b, rhs, atol=1e-12)


def test_spatial_exact_set_matches_its_lp_oracle() -> None:
    sc = load_scenario(SPATIAL)
    cond = build_conditions(sc.grasp, sc.directions)
    sl = ratio_slice(sc.grasp, (0.9, 0.1), sc.tau_max)
    ts = exact_torque_set(cond, sl)
    rng = np.random.default_rng(6)
    pts = np.vstack([rng.uniform(-3, 3, size=(25, 2))] + [p.mean(axis=0) for p in ts.region])
    for u in pts:
        lp = lp_values(cond, sl.torques(u))
        assert lp.realisable == bool(ts.realisable_mask(u)[0])
        if lp.realisable:
            np.testing.assert_allclose(lp.values, ts.margins(u)[0], atol=1e-7)


def test_outer_pyramids_contain_the_planar_cone() -> None:
    """The plane z = 0 is a symmetry plane, so out-of-plane forces do not couple into the
    in-plane conditions; what matters is the pyramid's shadow on the plane. It always contains
    the planar cone (set no larger than the planar one), equals it when a pair of edges
    projects exactly onto the planar cone's edges (6 edges: tangents at ±60° from z, with
    μ / cos 30° · sin 60° = μ), and approaches it as the edges get many."""
    planar = load_scenario(PLANAR)
    reference = exact_torque_set(
        build_conditions(planar.grasp, planar.directions),
        ratio_slice(planar.grasp, (0.9, 0.1), 3.0),
    ).area
    spatial = load_scenario(SPATIAL)
    areas = {}
    for edges in (5, 6, 8, 16, 64):
        grasp = dataclasses.replace(spatial.grasp, cone_edges=edges)
        cond = build_conditions(grasp, spatial.directions)
        areas[edges] = exact_torque_set(cond, ratio_slice(grasp, (0.9, 0.1), 3.0)).area
    assert all(a <= reference + 1e-12 for a in areas.values())
    assert areas[6] == pytest.approx(reference, rel=1e-9)
    assert areas[8] < reference - 0.1
    assert areas[64] == pytest.approx(reference, rel=0.01)
