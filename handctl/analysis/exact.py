"""The exact torque set: its polygons in a torque plane, from the vertices of the dual LPs.

Why it is polyhedral, and how it is computed without a grid of LPs:

1. ``JᵀV`` is block diagonal by finger (a finger's contacts load only its own joints), so the
   admissible set is a product ``Λ(τ) = Π_j Λ_j(τ_j)`` with ``Λ_j(τ_j) = {λ_j ≥ 0 : A_jλ_j = τ_j}``,
   ``A_j = J_jᵀV_j``, and each robust condition value splits:
   ``v_q(τ) = d_q + Σ_j min{c_qjᵀλ_j : λ_j ∈ Λ_j(τ_j)}``.
2. By LP duality each finger term equals ``max{τ_jᵀy : A_jᵀy ≤ c_qj}`` whenever ``τ_j`` is
   realisable (primal feasible). The dual polyhedron ``D_qj = {y : A_jᵀy ≤ c_qj}`` lives in
   ``ℝ^{s_j}`` (``s_j`` = joints of finger j), so its vertices and extreme rays are enumerated
   directly (choose ``s_j`` or ``s_j - 1`` tight constraints). Then
   * ``D_qj`` empty ⇔ the primal is unbounded for every realisable τ: ``v_q = -∞`` and condition
     q never holds (the unbounded λ-set case of the oracle);
   * the extreme rays ``r`` of the recession cone ``{A_jᵀy ≤ 0}`` (common to all q) give the
     realisable torques ``τ_jᵀr ≤ 0`` (Farkas), and a lineality space ``null(A_jᵀ)`` adds
     equalities;
   * otherwise ``v_q(τ) = d_q + Σ_j max_v τ_jᵀy_qjv`` over the vertices, a convex piecewise-
     linear function.
3. In a plane ``τ = E u`` the vertices project to ``w = E_jᵀy`` and the finger terms add up to
   ``v_q(u) = d_q + max{wᵀu : w ∈ W_q}`` with ``W_q`` the Minkowski sum of the projected
   hulls. Hence ``{v_q ≤ 0} = K_q = {u : wᵀu ≤ -d_q ∀ w ∈ vert W_q}`` is a convex polygon, and
   the torque set is ``(limit ∩ realisable) \\ ∪_q K_q``: a finite union of convex polygons,
   computed by half-plane clipping. Note it need not be convex (``v_q`` is convex, so its
   super-level set is the complement of a convex set).

The whole computation is a few dozen tiny linear solves, against one LP per condition and per
point for the oracle.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass

import numpy as np

from handctl.analysis.conditions import Conditions
from handctl.analysis.frames import Array, Mask
from handctl.analysis.model import AnalysisError
from handctl.analysis.polygons import (
    HalfPlane,
    area,
    difference,
    hull,
    intersect,
    merge_convex,
    minkowski_sum,
    union_distance,
)
from handctl.analysis.slices import TorqueSlice

MAX_COMBINATIONS = 200_000


@dataclass(frozen=True)
class DualPolyhedron:
    """``{y : Aᵀy ≤ c}`` as vertices + extreme rays + a basis of its lineality space (rows)."""

    vertices: Array
    rays: Array
    lineality: Array

    @property
    def empty(self) -> bool:
        return len(self.vertices) == 0


def _unique_rows(rows: list[Array], width: int, scale: float) -> Array:
    out: list[Array] = []
    for row in rows:
        if all(float(np.max(np.abs(row - kept))) > 1e-9 * scale for kept in out):
            out.append(row)
    return np.array(out).reshape(-1, width)


def dual_polyhedron(a: Array, c: Array) -> DualPolyhedron:
    """Enumerate ``{y ∈ ℝ^s : aᵀy ≤ c}`` for ``a`` of shape ``(s, N)``.

    Works in coordinates of ``range(a)`` (where the polyhedron is pointed) and reports the rest
    as the lineality space.
    """
    s, n = a.shape
    if n:
        u_mat, sing, _ = np.linalg.svd(a)
        rank = int(np.sum(sing > 1e-10 * max(1.0, float(sing[0]))))
    else:
        u_mat, rank = np.eye(s), 0
    basis, lineality = u_mat[:, :rank], u_mat[:, rank:].T
    reduced = a.T @ basis  # (N, rank): constraint rows in range coordinates
    scale = 1.0 + float(np.max(np.abs(c))) if n else 1.0
    tol = 1e-9 * scale
    if math.comb(n, rank) > MAX_COMBINATIONS:
        raise AnalysisError(
            f"dual polyhedron too large to enumerate ({n} constraints in {rank} dimensions)"
        )
    if rank == 0:
        feasible = n == 0 or bool(np.all(c >= -tol))
        vertices = np.zeros((1 if feasible else 0, s))
        return DualPolyhedron(vertices, np.zeros((0, s)), lineality)

    combos = np.array(list(itertools.combinations(range(n), rank)))
    mats = reduced[combos]
    smallest = np.linalg.svd(mats, compute_uv=False)[:, -1]
    good = smallest > 1e-10 * max(1.0, float(np.max(np.abs(reduced))))
    found: list[Array] = []
    if np.any(good):
        z = np.linalg.solve(mats[good], c[combos[good]][..., None])[..., 0]
        slack = z @ reduced.T - c[None, :]
        ok = np.all(slack <= tol * (1.0 + np.max(np.abs(z), axis=1))[:, None], axis=1)
        found = list(z[ok])
    vertices = _unique_rows(found, rank, scale) @ basis.T

    directions: list[Array] = []
    if rank == 1:
        candidates = [np.array([1.0]), np.array([-1.0])]
    else:
        candidates = []
        for combo in itertools.combinations(range(n), rank - 1):
            _, sv, vt = np.linalg.svd(reduced[list(combo)])
            if len(sv) == rank - 1 and sv[-1] > 1e-10 * max(1.0, float(sv[0])):
                candidates += [vt[-1], -vt[-1]]
    for d in candidates:
        if np.all(reduced @ d <= 1e-10 * float(np.max(np.abs(reduced)))):
            directions.append(d / float(np.linalg.norm(d)))
    rays = _unique_rows(directions, rank, 1.0) @ basis.T
    return DualPolyhedron(vertices, rays, lineality)


@dataclass(frozen=True)
class ExactTorqueSet:
    """The torque set in one plane of torques, exactly.

    ``region`` holds the convex pieces (closures, merged where their union is convex) of the set
    of ``u`` within the torque limit where every condition holds robustly; ``realisable`` is the
    realisable part of the limit polygon. ``gradients[q]`` are the vertices of ``W_q`` (``None``
    when condition q can be driven to -∞), so ``margins`` evaluates the robust condition values
    exactly anywhere.
    """

    torque_slice: TorqueSlice
    labels: tuple[str, ...]
    offsets: Array
    gradients: tuple[Array | None, ...]
    domain: tuple[HalfPlane, ...]
    limit: Array
    realisable: tuple[Array, ...]
    unrealisable: tuple[Array, ...]
    region: tuple[Array, ...]
    region_pieces: tuple[Array, ...]
    complement: tuple[Array, ...]

    @property
    def area(self) -> float:
        """Area of the torque set (N²·m²)."""
        return float(sum(area(p) for p in self.region))

    @property
    def realisable_area(self) -> float:
        return float(sum(area(p) for p in self.realisable))

    def realisable_mask(self, points: Array) -> Mask:
        pts = np.atleast_2d(points)
        ok = np.ones(len(pts), dtype=bool)
        slack = 1e-9 * (1.0 + np.max(np.abs(pts), axis=1))
        for a, b in self.domain:
            ok &= pts @ a - b <= slack * (1.0 + float(np.linalg.norm(a)))
        return ok

    def realisability_residual(self, points: Array) -> Array:
        """How far (N·m, in joint-torque space) each point's torques are beyond the realisable
        cone: the largest ``rᵀτ_j`` over its unit facet normals (≤ 0 means realisable). Unlike a
        distance in the plane, this stays meaningful for nearly degenerate slices."""
        pts = np.atleast_2d(points)
        if not self.domain:
            return np.full(len(pts), -np.inf)
        return np.asarray(np.max([pts @ a - b for a, b in self.domain], axis=0))

    def margins(self, points: Array) -> Array:
        """Robust value of every condition at each point, ``(P, Q)``; meaningful where
        realisable (outside it the LP is infeasible and there is no value)."""
        pts = np.atleast_2d(points)
        out = np.empty((len(pts), len(self.labels)))
        for q, grads in enumerate(self.gradients):
            if grads is None:
                out[:, q] = -np.inf
            else:
                out[:, q] = self.offsets[q] + np.max(pts @ grads.T, axis=1)
        return out

    def inside_mask(self, points: Array) -> Mask:
        pts = np.atleast_2d(points)
        return np.asarray(
            self.realisable_mask(pts)
            & self.torque_slice.within_limits(pts)
            & np.all(self.margins(pts) > 0.0, axis=1)
        )

    def boundary_distance(self, points: Array) -> Array:
        """Distance of each point to the boundary between the set and the rest of the limit
        polygon (0 on it). Every point of the limit polygon is in the closure of one side, so
        this is the larger of the distances to the two sides."""
        pts = np.atleast_2d(points)
        outside = list(self.complement) + list(self.unrealisable)
        return np.maximum(
            union_distance(list(self.region_pieces), pts), union_distance(outside, pts)
        )

    def realisable_boundary_distance(self, points: Array) -> Array:
        pts = np.atleast_2d(points)
        return np.maximum(
            union_distance(list(self.realisable), pts), union_distance(list(self.unrealisable), pts)
        )


def exact_torque_set(conditions: Conditions, torque_slice: TorqueSlice) -> ExactTorqueSet:
    """Compute the torque set of ``conditions`` in the plane ``torque_slice``."""
    st = conditions.statics
    basis = torque_slice.basis
    if basis.shape != (st.torque_map.shape[0], 2):
        raise AnalysisError(f"slice basis must be {st.torque_map.shape[0]}×2, found {basis.shape}")
    domain: list[HalfPlane] = []
    per_condition: list[list[Array] | None] = [[] for _ in range(conditions.count)]
    for lam_block, joint_block in zip(st.lambda_blocks, st.joint_blocks, strict=True):
        a_j = st.torque_map[joint_block, lam_block]
        e_j = basis[joint_block]
        for q in range(conditions.count):
            dual = dual_polyhedron(a_j, conditions.matrix[q, lam_block])
            if q == 0:
                for r in dual.rays:
                    domain.append((e_j.T @ r, 0.0))
                for line in dual.lineality:
                    domain += [(e_j.T @ line, 0.0), (-(e_j.T @ line), 0.0)]
            hulls = per_condition[q]
            if hulls is None:
                continue
            if dual.empty:
                per_condition[q] = None
            else:
                hulls.append(hull(dual.vertices @ e_j))
    gradients: list[Array | None] = []
    for hulls in per_condition:
        if hulls is None:
            gradients.append(None)
            continue
        total = np.zeros((1, 2))
        for h in hulls:
            total = minkowski_sum(total, h)
        gradients.append(total)

    limit = torque_slice.limit_polygon()
    realisable = intersect(limit, domain)
    unrealisable = difference(limit, domain)
    pieces = [realisable] if len(realisable) else []
    complement: list[Array] = []
    for q, grads in enumerate(gradients):
        bad: list[HalfPlane] = (
            [] if grads is None else [(w, -float(conditions.offset[q])) for w in grads]
        )
        inside_bad = intersect(realisable, bad) if len(realisable) else realisable
        if len(inside_bad):
            complement.append(inside_bad)
        pieces = [p for piece in pieces for p in difference(piece, bad)]
    return ExactTorqueSet(
        torque_slice=torque_slice,
        labels=conditions.labels,
        offsets=conditions.offset.copy(),
        gradients=tuple(gradients),
        domain=tuple(domain),
        limit=limit,
        realisable=(realisable,) if len(realisable) else (),
        unrealisable=tuple(unrealisable),
        region=tuple(merge_convex(pieces)),
        region_pieces=tuple(pieces),
        complement=tuple(complement),
    )
