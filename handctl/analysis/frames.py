"""Rotations and the vector-product operators of eqs. 5–7, in 2D and 3D.

Trap of the paper (§3, last paragraph): for the planar case it redefines the skew matrix as the
*row* ``(a×) = [-a_y  a_x]``. That row is the right operator for the moment ``a × f`` (a scalar
in 2D), but ``D = [I  -(a×)]`` of eqs. 5–7 then does not even have a consistent shape (a 2×2
block beside a 1×2 row), and transposing it is not enough either: the velocity of a body-fixed
point is ``ṗ + ω ẑ × a = ṗ + ω (-a_y, a_x)ᵀ``, so with the paper's row the map would be
``[I  +(a×)ᵀ]``, with the sign flipped. We keep the 3D form ``D = [I  -(a×)]`` for both
dimensions and define the planar operator as the column ``(a×) = (a_y, -a_x)ᵀ``: it is the third
column of the 3D skew matrix restricted to the plane, i.e. exactly what the 3D operator does to
an angular velocity along z. Then ``D`` is 2×3, ``D [ṗ; ω]`` is the contact-point velocity and
``Dᵀ f = [f; a × f]`` is the wrench of a force ``f`` applied at ``a``, as in 3D.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]
Mask = NDArray[np.bool_]
Vector = Sequence[float] | NDArray[np.float64]
"""A vector given either way: a list or tuple of floats, or a numpy array."""


def twist_size(dim: int) -> int:
    """Number of velocity coordinates of a rigid body: 3 in the plane, 6 in space."""
    return 3 if dim == 2 else 6


def rotation_2d(angle: float) -> Array:
    """Rotation matrix of a counter-clockwise angle (rad)."""
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, -s], [s, c]])


def rotation_from_vector(rotvec: Array) -> Array:
    """Rotation matrix of a rotation vector (axis times angle, rad), by Rodrigues' formula."""
    v = np.asarray(rotvec, dtype=float)
    angle = float(np.linalg.norm(v))
    if angle < 1e-15:
        return np.eye(3)
    k = skew(v / angle)
    return np.eye(3) + math.sin(angle) * k + (1.0 - math.cos(angle)) * (k @ k)


def rotation_about(axis: Array, angle: float) -> Array:
    """Rotation by ``angle`` about a unit ``axis`` (3D)."""
    return rotation_from_vector(np.asarray(axis, dtype=float) * angle)


def skew(a: Array) -> Array:
    """The 3×3 matrix with ``skew(a) @ b == a × b``."""
    return np.array([[0.0, -a[2], a[1]], [a[2], 0.0, -a[0]], [-a[1], a[0], 0.0]])


def cross_operator(a: Array) -> Array:
    """``(a×)`` of eqs. 5–7: 3×3 skew matrix in 3D, the 2×1 column ``(a_y, -a_x)ᵀ`` in 2D.

    See the module docstring for why the planar operator is a column and not the paper's row.
    """
    if a.shape[0] == 3:
        return skew(a)
    return np.array([[a[1]], [-a[0]]])


def point_velocity_map(a: Array) -> Array:
    """``D = [I  -(a×)]``: maps a body twist ``[ṗ; ω]`` to the velocity of the point at offset
    ``a`` (world frame) from the body's reference point; ``Dᵀ`` maps a force there to a wrench."""
    dim = a.shape[0]
    return np.hstack([np.eye(dim), -cross_operator(a)])


def unit(v: Array) -> Array:
    """``v / |v|``; callers guarantee ``v`` is not zero."""
    return v / float(np.linalg.norm(v))


def moderate(v: Array) -> Array:
    """A non-zero direction as given, or scaled to a largest component of 1 where its length
    would overflow or vanish in ``unit``: [0, 1e200] squared to inf (an analysis found no
    torque, exit 0), and [0, 1e-100] was taken for no direction at all. Any other is left
    as it was, to the bit."""
    peak = float(np.max(np.abs(v)))
    return v if 1e-100 < peak < 1e100 else v / peak


def tangent_basis(normal: Array) -> Array:
    """Orthonormal tangent directions (columns) of a unit normal: 1 in 2D, 2 in 3D.

    In 2D the tangent is the normal turned by +90°, so ``(n, t)`` is right-handed.
    """
    if normal.shape[0] == 2:
        return np.array([[-normal[1]], [normal[0]]])
    helper = np.array([1.0, 0.0, 0.0]) if abs(normal[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    t1 = unit(np.cross(normal, helper))
    t2 = np.cross(normal, t1)
    return np.column_stack([t1, t2])
