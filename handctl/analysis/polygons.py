"""Convex polygons in a torque plane: clipping, differences, hulls, areas, distances.

The exact torque set is a finite union of convex polygons cut out by half-planes, so these few
operations are all it needs; no general polygon library is required. A polygon is a ``(k, 2)``
array of vertices in counter-clockwise order; degenerate polygons (a segment, a point) are
allowed, because a lower-dimensional piece of a set is still part of its boundary.
"""

from __future__ import annotations

import numpy as np

from handctl.analysis.frames import Array

HalfPlane = tuple[Array, float]
"""``(a, b)`` for the closed half-plane ``aᵀu ≤ b``."""

EPS = 1e-12


def area(poly: Array) -> float:
    """Signed shoelace area (positive for counter-clockwise order)."""
    if len(poly) < 3:
        return 0.0
    x, y = poly[:, 0], poly[:, 1]
    return 0.5 * float(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1)))


def _dedupe(poly: Array, scale: float) -> Array:
    if len(poly) < 2:
        return poly
    keep = [0]
    for i in range(1, len(poly)):
        if np.max(np.abs(poly[i] - poly[keep[-1]])) > EPS * scale:
            keep.append(i)
    if len(keep) > 1 and np.max(np.abs(poly[keep[-1]] - poly[keep[0]])) <= EPS * scale:
        keep.pop()
    return poly[keep]


def clip(poly: Array, a: Array, b: float) -> Array:
    """``poly ∩ {aᵀu ≤ b}`` (Sutherland–Hodgman on one edge; the result stays convex)."""
    if len(poly) == 0:
        return poly
    scale = 1.0 + float(np.max(np.abs(poly)))
    norm = float(np.linalg.norm(a))
    if norm < EPS:
        return poly if b >= -EPS else poly[:0]
    s = (poly @ a - b) / norm
    tol = EPS * scale
    if np.all(s <= tol):
        return poly
    if np.all(s > tol):
        return poly[:0]
    out: list[Array] = []
    k = len(poly)
    for i in range(k):
        p, q = poly[i], poly[(i + 1) % k]
        sp, sq = s[i], s[(i + 1) % k]
        if sp <= tol:
            out.append(p)
        if (sp <= tol) != (sq <= tol) and k > 1:
            # a vertex counted inside by the tolerance may lie a hair outside; clamping keeps
            # the crossing on the edge instead of just beyond its end
            t = min(1.0, max(0.0, sp / (sp - sq)))
            out.append(p + t * (q - p))
    return _dedupe(np.array(out), scale) if out else poly[:0]


def intersect(poly: Array, halfplanes: list[HalfPlane]) -> Array:
    for a, b in halfplanes:
        poly = clip(poly, a, b)
        if len(poly) == 0:
            break
    return poly


def difference(poly: Array, halfplanes: list[HalfPlane]) -> list[Array]:
    """Closures of disjoint convex pieces of ``poly`` minus ``{aᵀu ≤ b for all}``.

    Piece e is where the first e-1 half-planes hold and half-plane e is violated, so the pieces
    do not overlap and their union is the difference. An empty list of half-planes is the whole
    plane, whose complement is empty.
    """
    pieces: list[Array] = []
    rest = poly
    for a, b in halfplanes:
        if float(np.linalg.norm(a)) < EPS:
            # 0ᵀu ≤ b: the whole plane (nothing violates it) or, for b < 0, nothing at all
            if b >= -EPS:
                continue
            pieces.append(rest)
            break
        piece = clip(rest, -a, -b)
        if len(piece):
            pieces.append(piece)
        rest = clip(rest, a, b)
        if len(rest) == 0:
            break
    return pieces


def hull(points: Array) -> Array:
    """Convex hull, counter-clockwise (Andrew's monotone chain); 1 or 2 points if degenerate."""
    pts = np.unique(np.round(points, 14), axis=0)
    if len(pts) <= 2:
        return pts

    def half(seq: Array) -> list[Array]:
        chain: list[Array] = []
        for p in seq:
            while len(chain) >= 2:
                o, a = chain[-2], chain[-1]
                if (a[0] - o[0]) * (p[1] - o[1]) - (a[1] - o[1]) * (p[0] - o[0]) > EPS:
                    break
                chain.pop()
            chain.append(p)
        return chain

    lower = half(pts)
    upper = half(pts[::-1])
    ring = np.array(lower[:-1] + upper[:-1])
    return ring if len(ring) else pts[:1]


def minkowski_sum(a: Array, b: Array) -> Array:
    """Hull of ``{p + q}``: the Minkowski sum of two convex point sets."""
    return hull((a[:, None, :] + b[None, :, :]).reshape(-1, 2))


def merge_convex(pieces: list[Array], rel_tol: float = 1e-9) -> list[Array]:
    """Merge pieces pairwise wherever their union is itself convex (hull area = sum of areas),
    so that a convex region cut into slivers by the difference comes out as one polygon."""
    merged = [p for p in pieces if abs(area(p)) > 0.0]
    changed = True
    while changed:
        changed = False
        for i in range(len(merged)):
            for j in range(i + 1, len(merged)):
                joint = hull(np.vstack([merged[i], merged[j]]))
                total = area(merged[i]) + area(merged[j])
                if abs(area(joint) - total) <= rel_tol * max(1.0, total):
                    merged[i] = joint
                    del merged[j]
                    changed = True
                    break
            if changed:
                break
    return merged


def _segment_distance(p: Array, q: Array, pts: Array) -> Array:
    d = q - p
    length2 = float(d @ d)
    if length2 < EPS * EPS:
        return np.asarray(np.linalg.norm(pts - p, axis=1))
    t = np.clip((pts - p) @ d / length2, 0.0, 1.0)
    return np.asarray(np.linalg.norm(pts - (p + t[:, None] * d), axis=1))


def distance(poly: Array, pts: Array) -> Array:
    """Euclidean distance of each point to a closed convex polygon (0 inside)."""
    if len(poly) == 0:
        return np.full(len(pts), np.inf)
    if len(poly) == 1:
        return np.asarray(np.linalg.norm(pts - poly[0], axis=1))
    k = len(poly)
    edges = np.min([_segment_distance(poly[i], poly[(i + 1) % k], pts) for i in range(k)], axis=0)
    if k >= 3 and area(poly) > 0.0:
        rel = pts[:, None, :] - poly[None, :, :]
        step = np.roll(poly, -1, axis=0) - poly
        cross = step[None, :, 0] * rel[:, :, 1] - step[None, :, 1] * rel[:, :, 0]
        inside = np.all(cross >= 0.0, axis=1)
        edges = np.where(inside, 0.0, edges)
    return np.asarray(edges)


def union_distance(polys: list[Array], pts: Array) -> Array:
    """Distance of each point to the union of closed convex polygons (inf if none)."""
    if not polys:
        return np.full(len(pts), np.inf)
    return np.asarray(np.min([distance(p, pts) for p in polys], axis=0))


def rectangle(lo: Array, hi: Array) -> Array:
    return np.array([[lo[0], lo[1]], [hi[0], lo[1]], [hi[0], hi[1]], [lo[0], hi[1]]])
