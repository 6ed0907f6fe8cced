"""The planner: its answer is in the torque set and no grid point has a larger robust margin."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from handctl.analysis.conditions import build_conditions
from handctl.analysis.exact import ExactTorqueSet, exact_torque_set
from handctl.analysis.model import AnalysisError, load_scenario
from handctl.analysis.oracle import lp_values
from handctl.analysis.planner import plan_for_conditions, plan_torques
from handctl.analysis.slices import ratio_slice

ROOT = Path(__file__).resolve().parents[2]
FIG3 = ROOT / "config" / "analysis" / "paper_fig3.yaml"
VERTICAL = ROOT / "config" / "analysis" / "paper_fig3_vertical.yaml"


def _grid_best(ts: ExactTorqueSet, n: int = 161) -> float:
    """Best robust margin over a grid, from the exact closed-form margins."""
    lo, hi = ts.torque_slice.bounds()
    gx, gy = np.meshgrid(np.linspace(lo[0], hi[0], n), np.linspace(lo[1], hi[1], n))
    pts = np.column_stack([gx.ravel(), gy.ravel()])
    margins = ts.margins(pts).min(axis=1)
    margins[~ts.realisable_mask(pts)] = -np.inf
    return float(margins.max())


@pytest.mark.parametrize("k", [(0.9, 0.1), (1.2, 0.5), (0.3, 1.7)])
def test_ratio_constrained_plan_is_the_best_in_its_plane(k: tuple[float, float]) -> None:
    sc = load_scenario(FIG3)
    plan = plan_torques(sc.grasp, sc.directions, sc.tau_max, [(1.0, k[0]), (1.0, k[1])])
    cond = build_conditions(sc.grasp, sc.directions)
    ts = exact_torque_set(cond, ratio_slice(sc.grasp, k, sc.tau_max))
    best = _grid_best(ts)
    if not plan.found:
        assert best <= 1e-9
        return
    tau = np.array(plan.tau)
    assert np.all(np.abs(tau) <= sc.tau_max + 1e-9)
    np.testing.assert_allclose(tau[[1, 3]], np.array(k) * tau[[0, 2]], atol=1e-9)
    assert ts.inside_mask(tau[[0, 2]])[0]
    assert plan.margin >= best - 1e-9
    check = lp_values(cond, tau)
    assert check.inside and check.margin == pytest.approx(plan.margin)
    assert plan.values == pytest.approx(dict(zip(cond.labels, check.values, strict=True)))


def test_free_torques_do_at_least_as_well_as_any_ratio() -> None:
    sc = load_scenario(FIG3)
    free = plan_torques(sc.grasp, sc.directions, sc.tau_max)
    tied = plan_torques(sc.grasp, sc.directions, sc.tau_max, [(1.0, 0.9), (1.0, 0.1)])
    assert free.found and tied.found
    assert free.margin >= tied.margin - 1e-9
    # random feasible torques never beat the planner
    cond = build_conditions(sc.grasp, sc.directions)
    rng = np.random.default_rng(8)
    for tau in rng.uniform(-3, 3, size=(60, 4)):
        result = lp_values(cond, tau)
        if result.realisable:
            assert result.margin <= free.margin + 1e-9


def test_per_joint_limits_are_respected() -> None:
    sc = load_scenario(FIG3)
    limits = [3.0, 0.5, 3.0, 0.5]
    plan = plan_torques(sc.grasp, sc.directions, limits)
    if plan.found:
        assert np.all(np.abs(plan.tau) <= np.array(limits) + 1e-9)


def test_none_exists_in_a_vertical_plane_with_small_torques() -> None:
    """With gravity in the plane (net reading) 3 N·m cannot lift a 1 kg cylinder here."""
    sc = load_scenario(VERTICAL)
    plan = plan_torques(sc.grasp, sc.directions, 3.0)
    assert not plan.found
    assert plan.margin <= 0.0 and "move cylinder1" in plan.reason
    bigger = plan_torques(sc.grasp, sc.directions, sc.tau_max)
    assert bigger.found and bigger.margin > 0.0


def test_bad_requests_are_refused() -> None:
    sc = load_scenario(FIG3)
    cond = build_conditions(sc.grasp, sc.directions)
    with pytest.raises(AnalysisError):
        plan_for_conditions(cond, 0.0)
    with pytest.raises(AnalysisError):
        plan_for_conditions(cond, 3.0, [(1.0, 0.5)])
    with pytest.raises(AnalysisError):
        plan_for_conditions(cond, 3.0, [(1.0, 0.5, 2.0), None])
    with pytest.raises(AnalysisError):
        plan_torques(sc.grasp, {"cup": (0.0, 1.0)}, 3.0)
