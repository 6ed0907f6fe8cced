"""The LP oracle: is one torque vector in the robust torque set?

For a torque τ the admissible friction-cone coordinates are ``Λ(τ) = {λ ≥ 0 : JᵀVλ = τ}``
(eqs. 11–12; eq. 13's arbitrary ``k`` is exactly the freedom inside Λ(τ), and λ ≥ 0 is what
restricts it). The torque is in the set only if every condition ``g_q`` is positive for every
λ in Λ(τ), so each condition is minimised by a linear program (HiGHS):

* infeasible LP → no λ ≥ 0 realises τ: **not realisable**;
* unbounded LP → Λ(τ) is unbounded (internal forces that load no joint) and some direction of
  it drives ``g_q`` to -∞: the condition fails (value ``-inf``), nothing crashes;
* otherwise the minimum is the robust value of the condition, in N.

This is the direct formulation and deliberately shares nothing with ``exact`` beyond the
matrices, so that each checks the other. HiGHS runs with feasibility tolerances of 1e-9 instead
of its default 1e-7: with the default, a torque up to ~1e-7 N·m outside the realisable cone is
reported realisable, which near a nearly degenerate slice (a ratio k close to 0) is a visible
error in the torque plane.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import linprog

from handctl.analysis.conditions import Conditions
from handctl.analysis.frames import Array, Mask
from handctl.analysis.model import AnalysisError
from handctl.analysis.slices import TorqueSlice
from handctl.executor import WorkPool, open_pool
from handctl.progress import Progress

HIGHS_OPTIONS = {"primal_feasibility_tolerance": 1e-9, "dual_feasibility_tolerance": 1e-9}


@dataclass(frozen=True)
class OracleResult:
    """``values[q]`` = min over Λ(τ) of ``g_q`` (``-inf`` if unbounded, ``nan`` if skipped
    because an earlier condition already failed, all ``nan`` if not realisable)."""

    realisable: bool
    values: Array

    @property
    def inside(self) -> bool:
        return self.realisable and bool(np.all(self.values > 0.0))

    @property
    def margin(self) -> float:
        """The smallest robust condition value (N); ``nan`` when not realisable."""
        return float(np.min(self.values)) if self.realisable else float("nan")


def lp_values(conditions: Conditions, tau: Array, *, stop_early: bool = False) -> OracleResult:
    """Robust value of every condition at ``tau`` by one LP per condition."""
    a_eq = conditions.statics.torque_map
    values = np.full(conditions.count, np.nan)
    for q in range(conditions.count):
        res = linprog(
            conditions.matrix[q],
            A_eq=a_eq,
            b_eq=np.asarray(tau, dtype=float),
            bounds=(0.0, None),
            method="highs",
            options=HIGHS_OPTIONS,
        )
        if res.status == 2:
            return OracleResult(False, np.full(conditions.count, np.nan))
        if res.status == 3:
            values[q] = -np.inf
        elif res.status == 0:
            values[q] = float(res.fun) + float(conditions.offset[q])
        else:
            raise AnalysisError(
                f"LP for condition {conditions.labels[q]!r} at tau={tau!r} "
                f"ended with status {res.status}: {res.message}"
            )
        if stop_early and values[q] <= 0.0:
            break
    return OracleResult(True, values)


@dataclass(frozen=True)
class GridRow:
    """One row of an LP grid, as a task any worker can run (``handctl.executor``)."""

    conditions: Conditions
    torque_slice: TorqueSlice
    xs: Array
    y: float


def lp_row(row: GridRow) -> tuple[Mask, Mask]:
    """``(realisable, inside)`` along one row of the grid (see ``lp_grid``)."""
    realisable = np.zeros(len(row.xs), dtype=bool)
    inside = np.zeros(len(row.xs), dtype=bool)
    for j, x in enumerate(row.xs):
        u = np.array([x, row.y])
        result = lp_values(row.conditions, row.torque_slice.torques(u), stop_early=True)
        realisable[j] = result.realisable
        inside[j] = result.inside and bool(row.torque_slice.within_limits(u)[0])
    return realisable, inside


def lp_grid(
    conditions: Conditions,
    torque_slice: TorqueSlice,
    xs: Array,
    ys: Array,
    executor: WorkPool | None = None,
    bar: Progress | None = None,
) -> tuple[Mask, Mask]:
    """Classify the grid ``(xs[j], ys[i])`` by LPs: ``(realisable, inside)`` masks of shape
    ``(len(ys), len(xs))``. Points beyond the torque limit are realisable-or-not as usual but
    never inside. Stops evaluating a point at its first failed condition. The rows are tasks
    of ``executor`` (default: here, one after another); ``bar`` counts them."""
    if executor is None:
        with open_pool(workers=1) as inline:
            return lp_grid(conditions, torque_slice, xs, ys, inline, bar)
    rows = executor.map(
        lp_row, [GridRow(conditions, torque_slice, np.asarray(xs), float(y)) for y in ys], bar
    )
    realisable = np.array([r for r, _ in rows], dtype=bool).reshape(len(ys), len(xs))
    inside = np.array([i for _, i in rows], dtype=bool).reshape(len(ys), len(xs))
    return realisable, inside
