"""Two-parameter families of joint torques, ``τ = E u``, over which torque sets are drawn.

The paper reduces the four torques of Fig. 3 to two with ``τ_i2 = k_i τ_i1`` (eq. 25); that is
``ratio_slice``. Any other plane through zero works the same way (``TorqueSlice(basis=E)``).
The torque limit ``|τ_ij| ≤ τ_max`` becomes a convex polygon in ``u``; for eq. 25 it is the
rectangle ``|u_i| ≤ τ_max / max(1, |k_i|)``, e.g. ``|τ_11| ≤ 2.5 N·m`` for ``k_1 = 1.2``.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from handctl.analysis.frames import Array, Mask
from handctl.analysis.model import AnalysisError, Grasp
from handctl.analysis.polygons import HalfPlane, intersect, rectangle


@dataclass(frozen=True)
class TorqueSlice:
    """``τ = basis @ u`` with ``u ∈ ℝ²`` (N·m), limited to ``|τ| ≤ tau_max`` joint by joint."""

    basis: Array
    tau_max: float
    labels: tuple[str, str] = ("u1", "u2")

    def torques(self, u: Array) -> Array:
        """Joint torques of one point ``(2,)`` or of many ``(P, 2)`` (rows)."""
        return np.asarray(u @ self.basis.T)

    def limit_halfplanes(self) -> list[HalfPlane]:
        out: list[HalfPlane] = []
        for row in self.basis:
            if float(np.max(np.abs(row))) > 0.0:
                out.append((row, self.tau_max))
                out.append((-row, self.tau_max))
        return out

    def limit_polygon(self) -> Array:
        """The torque limit as a polygon in ``u``."""
        reach = self.tau_max * float(np.max(np.sum(np.abs(np.linalg.pinv(self.basis)), axis=1)))
        start = rectangle(np.array([-reach, -reach]), np.array([reach, reach]))
        return intersect(start, self.limit_halfplanes())

    def bounds(self) -> tuple[Array, Array]:
        """Bounding rectangle of the torque limit: the box a grid is laid over."""
        poly = self.limit_polygon()
        return poly.min(axis=0), poly.max(axis=0)

    def within_limits(self, u: Array) -> Mask:
        """Mask of points (rows of ``u``) whose torques respect the limit (1e-12 slack)."""
        tau = self.torques(np.atleast_2d(u))
        return np.asarray(np.all(np.abs(tau) <= self.tau_max * (1 + 1e-12), axis=1))


def ratio_slice(grasp: Grasp, ratios: Sequence[float], tau_max: float) -> TorqueSlice:
    """Eq. 25: ``τ_j2 = k_j τ_j1`` for two two-joint fingers; ``u = (τ_11, τ_21)``."""
    if len(grasp.fingers) != 2 or any(f.joints != 2 for f in grasp.fingers):
        raise AnalysisError(
            "eq. 25 needs two fingers of two joints each; this grasp has "
            + ", ".join(f"{f.name}: {f.joints}" for f in grasp.fingers)
        )
    if len(ratios) != 2 or not all(np.isfinite(ratios)):
        raise AnalysisError(f"expected two finite ratios k_1, k_2; found {list(ratios)}")
    basis = np.zeros((grasp.joint_count, 2))
    for j, offset in enumerate(grasp.joint_offsets()):
        basis[offset, j] = 1.0
        basis[offset + 1, j] = float(ratios[j])
    return TorqueSlice(basis, tau_max, ("tau11", "tau21"))
