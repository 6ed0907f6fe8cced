"""Choose joint torques that move each object the wanted way with the largest robust margin.

The margin of a torque τ is ``m(τ) = min_q v_q(τ)``, the smallest robust condition value (the
minimum over all admissible contact forces, as the LP oracle computes it), in N. We maximise it
within ``|τ| ≤ τ_max`` and, optionally, torque-ratio constraints such as eq. 25.

This is not a convex problem: each ``v_q`` is convex in τ (the value of a minimisation LP as a
function of its right-hand side), and maximising a minimum of convex functions can have many
local optima. It is solved exactly as a small mixed-integer LP. With the per-finger dual
vertices of ``exact`` (``v_q(τ) = d_q + Σ_j max_v τ_jᵀy_qjv`` on the realisable torques),
``t ≤ d_q + Σ_j z_qj`` with ``z_qj ≤ τ_jᵀy_qjv`` for *one chosen* vertex v per (q, j) is exactly
``t ≤ m(τ)`` once the choice is free, and the choice is a binary with a big-M bound that the
torque limit makes finite. The answer is then re-evaluated by the LP oracle, so the reported
margin never rests on the reformulation alone.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
from scipy.optimize import Bounds, LinearConstraint, OptimizeResult, milp

from handctl.analysis.conditions import Conditions, build_conditions
from handctl.analysis.exact import dual_polyhedron
from handctl.analysis.frames import Array, Vector
from handctl.analysis.model import AnalysisError, Grasp
from handctl.analysis.oracle import lp_values

MARGIN_TOLERANCE = 1e-9
"""N; a margin at or below this is no margin (the set is open: its boundary does not count)."""


@dataclass(frozen=True)
class TorquePlan:
    """The planner's answer. ``tau`` is the joint torque vector (N·m, finger by finger, joint
    by joint) when ``found``, else zeros; ``margin`` is the smallest robust condition value at
    ``tau`` (N) from the LP oracle; ``values`` gives each condition's robust value by label;
    ``reason`` says why nothing was found."""

    found: bool
    tau: tuple[float, ...]
    margin: float
    values: dict[str, float]
    reason: str = ""


def plan_torques(
    grasp: Grasp,
    directions: Mapping[str, Vector],
    tau_max: float | Vector,
    ratios: Sequence[Vector | None] | None = None,
) -> TorquePlan:
    """Torques with the largest robust margin for moving each named object along its direction.

    ``tau_max`` is one limit for all joints or one per joint (N·m). ``ratios[j]``, if given, is
    a vector ``κ_j`` that finger j's torques must be proportional to (``τ_j = u_j κ_j`` for some
    real ``u_j``, either sign); eq. 25 is ``κ_j = (1, k_j)``.
    """
    conditions = build_conditions(
        grasp, {k: np.asarray(v, dtype=float) for k, v in directions.items()}
    )
    return plan_for_conditions(conditions, tau_max, ratios)


def plan_for_conditions(
    conditions: Conditions,
    tau_max: float | Vector,
    ratios: Sequence[Vector | None] | None = None,
    nearest: Vector | None = None,
    min_margin: float = 0.0,
) -> TorquePlan:
    """``plan_torques`` for conditions already built. With ``nearest`` (a torque, N·m): not
    the largest margin but the torque nearest ``nearest`` (the sum of the joints' absolute
    differences) whose margin is at least ``min_margin`` (N, > 0): the smallest change to a
    torque that keeps the motion guaranteed by that much."""
    st = conditions.statics
    s = st.torque_map.shape[0]
    limits = np.broadcast_to(np.asarray(tau_max, dtype=float), (s,)).copy()
    if not np.all(np.isfinite(limits)) or np.any(limits <= 0.0):
        raise AnalysisError(f"tau_max must be finite and > 0 N·m, found {tau_max!r}")
    fingers = len(st.joint_blocks)
    if ratios is not None and len(ratios) != fingers:
        raise AnalysisError(f"expected {fingers} ratio vectors (or None), found {len(ratios)}")
    nothing = TorquePlan(False, tuple(0.0 for _ in range(s)), -np.inf, {}, "")
    duals = _duals(conditions)
    if isinstance(duals, str):
        return _replace(nothing, reason=duals)
    if nearest is not None and not min_margin > 0.0:
        raise AnalysisError(f"min_margin must be > 0 N with a nearest torque, found {min_margin!r}")
    program = _Program(s, conditions.count, fingers, duals.vertices, 0 if nearest is None else s)
    _add_margin_rows(program, conditions)
    z_bound = _add_vertex_rows(program, conditions, duals.vertices, limits)
    _add_realisable_rows(program, conditions, duals)
    if ratios is not None:
        _add_ratio_rows(program, conditions, ratios)
    if nearest is not None:
        _add_distance_rows(program, np.asarray(nearest, dtype=float))
    result = program.solve(limits, z_bound, None if nearest is None else min_margin)
    if result.status != 0 or result.x is None:
        return _replace(
            nothing, reason=f"the planning MILP ended with status {result.status}: {result.message}"
        )
    return _evaluate(conditions, np.clip(result.x[:s], -limits, limits), nothing)


@dataclass
class _Duals:
    """Per condition q and finger j, the vertices of the dual polyhedron; and the rays and
    lines of its recession cone (one cone for every q), which say which torques are
    realisable at all."""

    vertices: list[list[Array]]
    domain_rows: list[tuple[int, Array]]
    equality_rows: list[tuple[int, Array]]


def _duals(conditions: Conditions) -> _Duals | str:
    """The dual polyhedra of every (q, j), or why there is no plan: a condition that a
    finger's internal forces drive to -inf, whatever the torque."""
    st = conditions.statics
    duals = _Duals([], [], [])
    for q in range(conditions.count):
        row: list[Array] = []
        for j, (lam_block, joint_block) in enumerate(
            zip(st.lambda_blocks, st.joint_blocks, strict=True)
        ):
            dual = dual_polyhedron(
                st.torque_map[joint_block, lam_block], conditions.matrix[q, lam_block]
            )
            if dual.empty:
                return (
                    f"condition {conditions.labels[q]!r} can be driven to -inf by internal "
                    f"forces of finger {j + 1}"
                )
            if q == 0:
                duals.domain_rows += [(j, r) for r in dual.rays]
                duals.equality_rows += [(j, line) for line in dual.lineality]
            row.append(dual.vertices)
        duals.vertices.append(row)
    return duals


class _Program:
    """The planning MILP as it is built: the variables are tau (s) | t | z (Q*n) | b (one per
    vertex of every (q, j) with more than one vertex) | e (``extra``: each joint's distance
    from a torque to stay near), and the rows are added in order."""

    def __init__(
        self, s: int, q_count: int, fingers: int, vertices: list[list[Array]], extra: int = 0
    ) -> None:
        self.s = s
        self.q_count = q_count
        self.fingers = fingers
        self.z0 = s + 1
        self.b0 = self.z0 + q_count * fingers
        self.binaries = [
            (q, j, v)
            for q in range(q_count)
            for j in range(fingers)
            if len(vertices[q][j]) > 1
            for v in range(len(vertices[q][j]))
        ]
        self.b_index = {key: self.b0 + i for i, key in enumerate(self.binaries)}
        self.e0 = self.b0 + len(self.binaries)
        self.extra = extra
        self.n_var = self.e0 + extra
        self.rows: list[Array] = []
        self.lower: list[float] = []
        self.upper: list[float] = []

    def z(self, q: int, j: int) -> int:
        """The index of z_qj."""
        return self.z0 + q * self.fingers + j

    def add(self, coeffs: dict[int, float], lo: float, hi: float) -> None:
        line = np.zeros(self.n_var)
        for k, value in coeffs.items():
            line[k] += value
        self.rows.append(line)
        self.lower.append(lo)
        self.upper.append(hi)

    def solve(
        self, limits: Array, z_bound: float, min_margin: float | None = None
    ) -> OptimizeResult:
        """Maximise t within the torque limits; each z within the bound its vertices allow.
        With ``min_margin``: t at least that, and the sum of the distances e the least."""
        z_count = self.q_count * self.fingers
        lb = np.concatenate(
            [
                -limits,
                [-np.inf if min_margin is None else min_margin],
                np.full(z_count, -z_bound - 1.0),
                np.zeros(len(self.binaries)),
                np.zeros(self.extra),
            ]
        )
        ub = np.concatenate(
            [
                limits,
                [np.inf],
                np.full(z_count, z_bound + 1.0),
                np.ones(len(self.binaries)),
                np.full(self.extra, np.inf),
            ]
        )
        cost = np.zeros(self.n_var)
        if min_margin is None:
            cost[self.s] = -1.0
        else:
            cost[self.e0 :] = 1.0
        integrality = np.concatenate(
            [np.zeros(self.b0), np.ones(len(self.binaries)), np.zeros(self.extra)]
        )
        return milp(
            cost,
            integrality=integrality,
            bounds=Bounds(lb, ub),
            constraints=LinearConstraint(
                np.array(self.rows), np.array(self.lower), np.array(self.upper)
            ),
        )


def _add_margin_rows(program: _Program, conditions: Conditions) -> None:
    """t - Σ_j z_qj ≤ d_q for every condition q: t is at most the smallest value."""
    for q in range(program.q_count):
        coeffs = {program.s: 1.0}
        coeffs.update({program.z(q, j): -1.0 for j in range(program.fingers)})
        program.add(coeffs, -np.inf, float(conditions.offset[q]))


def _add_vertex_rows(
    program: _Program, conditions: Conditions, vertices: list[list[Array]], limits: Array
) -> float:
    """z_qj ≤ τ_jᵀy for one vertex y of (q, j), chosen by binaries with a big-M bound when
    there are several. Returns the bound of every |z_qj| the torque limits allow."""
    z_bound = 0.0
    for q in range(program.q_count):
        for j, joint_block in enumerate(conditions.statics.joint_blocks):
            ys = vertices[q][j]
            lim = limits[joint_block]
            z_bound = max(z_bound, float(np.max(np.abs(ys) @ lim)))
            for v, y in enumerate(ys):
                coeffs = {program.z(q, j): 1.0}
                coeffs.update({joint_block.start + i: -float(y[i]) for i in range(len(y))})
                if len(ys) == 1:
                    program.add(coeffs, -np.inf, 0.0)
                    continue
                big_m = float(np.max(np.abs(ys - y), axis=0) @ lim) + 1.0
                coeffs[program.b_index[(q, j, v)]] = big_m
                program.add(coeffs, -np.inf, big_m)
            if len(ys) > 1:
                program.add({program.b_index[(q, j, v)]: 1.0 for v in range(len(ys))}, 1.0, 1.0)
    return z_bound


def _add_realisable_rows(program: _Program, conditions: Conditions, duals: _Duals) -> None:
    """Each finger's torque within the dual cone's rays (≤ 0) and on its lines (= 0)."""
    blocks = conditions.statics.joint_blocks
    for j, r in duals.domain_rows:
        block = blocks[j]
        program.add({block.start + i: float(r[i]) for i in range(len(r))}, -np.inf, 0.0)
    for j, line in duals.equality_rows:
        block = blocks[j]
        program.add({block.start + i: float(line[i]) for i in range(len(line))}, 0.0, 0.0)


def _add_distance_rows(program: _Program, nearest: Array) -> None:
    """e_i at least |tau_i - nearest_i|: two rows a joint."""
    for i, value in enumerate(nearest):
        program.add({program.e0 + i: 1.0, i: -1.0}, -float(value), np.inf)
        program.add({program.e0 + i: 1.0, i: 1.0}, float(value), np.inf)


def _add_ratio_rows(
    program: _Program, conditions: Conditions, ratios: Sequence[Vector | None]
) -> None:
    """τ_j proportional to κ_j: its projection off κ_j is zero."""
    for j, kappa in enumerate(ratios):
        if kappa is None:
            continue
        block = conditions.statics.joint_blocks[j]
        k = np.asarray(kappa, dtype=float)
        if k.shape != (block.stop - block.start,) or float(np.linalg.norm(k)) == 0.0:
            raise AnalysisError(
                f"ratio vector of finger {j + 1} must have "
                f"{block.stop - block.start} components, not all zero; "
                f"found {list(kappa)}"
            )
        projector = np.eye(len(k)) - np.outer(k, k) / float(k @ k)
        for prow in projector:
            program.add({block.start + i: float(prow[i]) for i in range(len(k))}, 0.0, 0.0)


def _evaluate(conditions: Conditions, tau: Array, nothing: TorquePlan) -> TorquePlan:
    """The MILP's torque as the LP oracle values it: the margin reported never rests on the
    reformulation alone."""
    check = lp_values(conditions, tau)
    values = {label: float(v) for label, v in zip(conditions.labels, check.values, strict=True)}
    if not check.realisable:
        return _replace(nothing, reason="the best torque found is not realisable (numerical)")
    margin = check.margin
    if margin <= MARGIN_TOLERANCE:
        worst = conditions.labels[int(np.argmin(check.values))]
        return TorquePlan(
            False,
            nothing.tau,
            margin,
            values,
            f"no torque within the limits satisfies every condition robustly; "
            f"the best margin is {margin:.3g} N, limited by {worst!r}",
        )
    return TorquePlan(True, tuple(float(x) for x in tau), margin, values)


def _replace(plan: TorquePlan, *, reason: str) -> TorquePlan:
    return TorquePlan(plan.found, plan.tau, plan.margin, plan.values, reason)


#: points tried along a blend's segment, the planned torque's end first
BLEND_STEPS = 8


def blend_towards(
    conditions: Conditions, planned: Vector, robust: Vector, min_margin: float
) -> tuple[float, TorquePlan]:
    """The torque nearest ``planned`` on the segment from it to ``robust`` (a torque the
    planner found) whose robust margin is at least ``min_margin`` (or, if ``robust``'s own
    is less, ``robust``'s): the fraction along the segment and the torque, the oracle's
    margin with it.

    Why a segment and not the nearest point of the whole set: the planned torque is what
    the search found to work on the simulated models, and the analysis' torque is what is
    guaranteed at this configuration; a torque between them keeps as much of the first as
    the second allows. The margin along the segment is not monotone (a minimum of convex
    functions), so it is sampled at ``BLEND_STEPS + 1`` points from the planned end, not
    bisected."""
    start = np.asarray(planned, dtype=float)
    end = np.asarray(robust, dtype=float)
    nothing = TorquePlan(False, tuple(0.0 for _ in start), -np.inf, {}, "")
    best = _evaluate(conditions, end, nothing)
    if not best.found:
        return 1.0, best
    wanted = min(min_margin, best.margin)
    for k in range(BLEND_STEPS):
        fraction = k / BLEND_STEPS
        plan = _evaluate(conditions, start + fraction * (end - start), nothing)
        if plan.found and plan.margin >= wanted:
            return fraction, plan
    return 1.0, best
