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
from scipy.optimize import Bounds, LinearConstraint, milp

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


def plan_torques(grasp: Grasp, directions: Mapping[str, Vector],
                 tau_max: float | Vector,
                 ratios: Sequence[Vector | None] | None = None) -> TorquePlan:
    """Torques with the largest robust margin for moving each named object along its direction.

    ``tau_max`` is one limit for all joints or one per joint (N·m). ``ratios[j]``, if given, is
    a vector ``κ_j`` that finger j's torques must be proportional to (``τ_j = u_j κ_j`` for some
    real ``u_j``, either sign); eq. 25 is ``κ_j = (1, k_j)``.
    """
    conditions = build_conditions(grasp, {k: np.asarray(v, dtype=float)
                                          for k, v in directions.items()})
    return plan_for_conditions(conditions, tau_max, ratios)


def plan_for_conditions(conditions: Conditions, tau_max: float | Vector,  # noqa: C901 - one pass over the cases; to split (issue 16)
                        ratios: Sequence[Vector | None] | None = None) -> TorquePlan:
    """``plan_torques`` for conditions already built."""
    st = conditions.statics
    s = st.torque_map.shape[0]
    limits = np.broadcast_to(np.asarray(tau_max, dtype=float), (s,)).copy()
    if not np.all(np.isfinite(limits)) or np.any(limits <= 0.0):
        raise AnalysisError(f"tau_max must be finite and > 0 N·m, found {tau_max!r}")
    fingers = len(st.joint_blocks)
    if ratios is not None and len(ratios) != fingers:
        raise AnalysisError(f"expected {fingers} ratio vectors (or None), found {len(ratios)}")
    nothing = TorquePlan(False, tuple(0.0 for _ in range(s)), -np.inf, {}, "")

    # per (q, j): the vertices of the dual polyhedron; realisability from its recession cone
    vertices: list[list[Array]] = []
    domain_rows: list[tuple[int, Array]] = []
    equality_rows: list[tuple[int, Array]] = []
    for q in range(conditions.count):
        row: list[Array] = []
        for j, (lam_block, joint_block) in enumerate(zip(st.lambda_blocks, st.joint_blocks,
                                                         strict=True)):
            dual = dual_polyhedron(st.torque_map[joint_block, lam_block],
                                   conditions.matrix[q, lam_block])
            if dual.empty:
                return _replace(nothing, reason=f"condition {conditions.labels[q]!r} can be "
                                f"driven to -inf by internal forces of finger {j + 1}")
            if q == 0:
                domain_rows += [(j, r) for r in dual.rays]
                equality_rows += [(j, line) for line in dual.lineality]
            row.append(dual.vertices)
        vertices.append(row)

    # variables: tau (s) | t | z (Q*n) | b (one per vertex of every (q, j) with >1 vertex)
    q_count = conditions.count
    z0 = s + 1
    b0 = z0 + q_count * fingers
    binaries: list[tuple[int, int, int]] = []
    for q in range(q_count):
        for j in range(fingers):
            if len(vertices[q][j]) > 1:
                binaries += [(q, j, v) for v in range(len(vertices[q][j]))]
    n_var = b0 + len(binaries)
    rows: list[Array] = []
    lower: list[float] = []
    upper: list[float] = []

    def add(coeffs: dict[int, float], lo: float, hi: float) -> None:
        line = np.zeros(n_var)
        for k, value in coeffs.items():
            line[k] += value
        rows.append(line)
        lower.append(lo)
        upper.append(hi)

    for q in range(q_count):  # t - Σ_j z_qj ≤ d_q
        coeffs = {s: 1.0}
        coeffs.update({z0 + q * fingers + j: -1.0 for j in range(fingers)})
        add(coeffs, -np.inf, float(conditions.offset[q]))
    b_index = {key: b0 + i for i, key in enumerate(binaries)}
    z_bound = 0.0
    for q in range(q_count):
        for j, joint_block in enumerate(st.joint_blocks):
            ys = vertices[q][j]
            lim = limits[joint_block]
            z_bound = max(z_bound, float(np.max(np.abs(ys) @ lim)))
            for v, y in enumerate(ys):
                coeffs = {z0 + q * fingers + j: 1.0}
                coeffs.update({joint_block.start + i: -float(y[i]) for i in range(len(y))})
                if len(ys) == 1:
                    add(coeffs, -np.inf, 0.0)
                    continue
                big_m = float(np.max(np.abs(ys - y), axis=0) @ lim) + 1.0
                coeffs[b_index[(q, j, v)]] = big_m
                add(coeffs, -np.inf, big_m)
            if len(ys) > 1:
                add({b_index[(q, j, v)]: 1.0 for v in range(len(ys))}, 1.0, 1.0)
    for j, r in domain_rows:
        block = st.joint_blocks[j]
        add({block.start + i: float(r[i]) for i in range(len(r))}, -np.inf, 0.0)
    for j, line in equality_rows:
        block = st.joint_blocks[j]
        add({block.start + i: float(line[i]) for i in range(len(line))}, 0.0, 0.0)
    if ratios is not None:
        for j, kappa in enumerate(ratios):
            if kappa is None:
                continue
            block = st.joint_blocks[j]
            k = np.asarray(kappa, dtype=float)
            if k.shape != (block.stop - block.start,) or float(np.linalg.norm(k)) == 0.0:
                raise AnalysisError(f"ratio vector of finger {j + 1} must have "
                                    f"{block.stop - block.start} components, not all zero; "
                                    f"found {list(kappa)}")
            projector = np.eye(len(k)) - np.outer(k, k) / float(k @ k)
            for prow in projector:
                add({block.start + i: float(prow[i]) for i in range(len(k))}, 0.0, 0.0)

    lb = np.concatenate([-limits, [-np.inf], np.full(q_count * fingers, -z_bound - 1.0),
                         np.zeros(len(binaries))])
    ub = np.concatenate([limits, [np.inf], np.full(q_count * fingers, z_bound + 1.0),
                         np.ones(len(binaries))])
    cost = np.zeros(n_var)
    cost[s] = -1.0
    integrality = np.concatenate([np.zeros(b0), np.ones(len(binaries))])
    result = milp(cost, integrality=integrality, bounds=Bounds(lb, ub),
                  constraints=LinearConstraint(np.array(rows), np.array(lower), np.array(upper)))
    if result.status != 0 or result.x is None:
        return _replace(nothing, reason=f"the planning MILP ended with status {result.status}: "
                        f"{result.message}")
    tau = np.clip(result.x[:s], -limits, limits)
    check = lp_values(conditions, tau)
    values = {label: float(v) for label, v in zip(conditions.labels, check.values, strict=True)}
    if not check.realisable:
        return _replace(nothing, reason="the best torque found is not realisable (numerical)")
    margin = check.margin
    if margin <= MARGIN_TOLERANCE:
        worst = conditions.labels[int(np.argmin(check.values))]
        return TorquePlan(False, tuple(0.0 for _ in range(s)), margin, values,
                          f"no torque within the limits satisfies every condition robustly; "
                          f"the best margin is {margin:.3g} N, limited by {worst!r}")
    return TorquePlan(True, tuple(float(x) for x in tau), margin, values)


def _replace(plan: TorquePlan, *, reason: str) -> TorquePlan:
    return TorquePlan(plan.found, plan.tau, plan.margin, plan.values, reason)
