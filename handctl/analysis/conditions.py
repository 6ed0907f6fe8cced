"""The sufficient condition of eqs. 23–24, as affine functions ``g_q(λ) = c_qᵀλ + d_q > 0``.

A torque τ is in the torque set when every ``g_q`` is positive for **every** λ ≥ 0 with
``τ = JᵀVλ`` (the contact forces of an enveloping grasp are not unique, eq. 13), so each
``g_q`` is minimised over that λ-set by a linear program (``oracle``) or in closed form
(``exact``).

Rows, in this order:

* **motion (eq. 23)** — for each object i with a wanted direction ``a_i``: ``a_iᵀ f_ti``.
* **compression at C (replacement of eq. 24)** — for each object–object contact:
  ``-n_1ᵀ f_CO`` with ``n_1`` the outward normal of the first object at C.
* **friction at C** — only if the scenario gives a friction coefficient at C: the rolling
  force of eq. 20 must lie in the friction cone, ``μ(-n_1ᵀf_CO) ∓ tᵀf_CO > 0`` (in space, an
  inscribed polygon of tangent directions, which keeps the condition sufficient).

**Eq. 24 cannot hold with eqs. 19–20 for two discs.** Eq. 20 is the force that enforces the
rolling constraint of eq. 19, so at rest ``D_O p̈_B = 0``: the contact-point accelerations of
the two discs are equal. Their normal components are ``nᵀp̈_1`` and ``nᵀp̈_2``, because the
angular accelerations add only a component along ``α × r_iC``, which is tangent (``r_iC ∥ n``
for discs). With ``f_ti = m_i p̈_i`` (net reading; in the paper's reading gravity shifts both
accelerations equally and the argument is the same), ``n_1ᵀf_t1 = m_1 nᵀp̈_1`` and
``n_2ᵀf_t2 = -m_2 nᵀp̈_1`` (``n_2 = -n_1``): they have opposite signs for every torque, so
eq. 24 for i = 1 and 2 is never satisfied and the torque set would be empty. What the paper
needs from eq. 24 is that the objects *stay in contact*, since eq. 20 treats C as a bilateral
constraint; the sound condition for that is that the constraint force is compressive, i.e. the
force of object 2 on object 1 points into object 1: ``n_1ᵀ f_CO < 0``. With it (and the friction
rows when C has a finite μ) the rolling solution is the physically consistent one, and eq. 23
then guarantees the motion.

**Gravity and f_ti.** Eqs. 21–22 sum the contact forces only; gravity enters through ``h_B``
in eq. 20. That is the *paper's reading* (``reading: paper``), sound when gravity does not act
in the plane of the hand (a horizontal hand, or the paper's Fig. 3, whose text gives no gravity;
its scenario sets ``gravity: [0, 0]`` so that ``h_B = 0`` at rest). For a hand in a vertical
plane the object's acceleration is set by the *net* force, ``m_i p̈_i = f_ti + m_i g``, and
``a_iᵀ(f_ti + m_i g) > 0`` is what guarantees the motion (``reading: net``). The scenario file
chooses; in both readings gravity is in ``h_B`` and hence in ``f_CO``.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from handctl.analysis.frames import Array, Vector, tangent_basis, unit
from handctl.analysis.model import AnalysisError, Grasp
from handctl.analysis.statics import Statics, statics


@dataclass(frozen=True)
class Conditions:
    """Rows ``g_q(λ) = matrix[q] @ λ + offset[q]``; the torque set is where all are > 0 for every
    λ ≥ 0 with ``statics.torque_map @ λ = τ``. Values are forces (N)."""

    matrix: Array
    offset: Array
    labels: tuple[str, ...]
    statics: Statics

    def values(self, lam: Array) -> Array:
        return self.matrix @ lam + self.offset

    @property
    def count(self) -> int:
        return len(self.labels)


def build_conditions(
    grasp: Grasp, directions: Mapping[str, Vector], friction_directions: int = 8
) -> Conditions:
    """Conditions for moving each named object along its direction (unit vectors by name)."""
    st = statics(grasp)
    dim = grasp.dim
    rows: list[Array] = []
    offsets: list[float] = []
    labels: list[str] = []
    names = [b.name for b in grasp.bodies]
    for name, direction in directions.items():
        if name not in names:
            raise AnalysisError(f"no object named {name!r} in the grasp")
        a = unit(np.asarray(direction, dtype=float))
        if a.shape != (dim,):
            raise AnalysisError(f"direction of {name!r} must have {dim} components")
        i = names.index(name)
        rows.append(a @ st.total_map[dim * i : dim * (i + 1)])
        offsets.append(float(a @ st.total_offset[dim * i : dim * (i + 1)]))
        labels.append(f"move {name}")
    if not rows:
        raise AnalysisError("no wanted motion: give a direction for at least one object")
    for t, contact in enumerate(grasp.body_contacts):
        block = st.f_co_map[dim * t : dim * (t + 1)]
        shift = st.f_co_offset[dim * t : dim * (t + 1)]
        pair = f"{names[contact.first]}/{names[contact.second]}"
        n = contact.normal
        rows.append(-n @ block)
        offsets.append(float(-n @ shift))
        labels.append(f"compression {pair}")
        if contact.mu is None:
            continue
        tangents = tangent_basis(n)
        if dim == 2:
            dirs = [tangents[:, 0], -tangents[:, 0]]
            mu = contact.mu
        else:
            phis = 2.0 * math.pi * np.arange(friction_directions) / friction_directions
            dirs = [math.cos(p) * tangents[:, 0] + math.sin(p) * tangents[:, 1] for p in phis]
            mu = contact.mu * math.cos(math.pi / friction_directions)
        for k, e in enumerate(dirs):
            rows.append(-mu * (n @ block) - e @ block)
            offsets.append(float(-mu * (n @ shift) - e @ shift))
            labels.append(f"friction {pair} #{k + 1}")
    return Conditions(np.array(rows), np.array(offsets), tuple(labels), st)
