"""Statics and dynamics at rest of §4 (eqs. 10–22), for any number of fingers and objects.

Everything here is an affine function of the friction-cone coordinates λ ≥ 0 (eq. 11), because
that is what lets the torque set be computed with linear programs: ``τ = JᵀVλ`` (eq. 12),
``f_CO = F λ + f₀`` (eq. 20) and the total forces ``f_ti = T_i λ + t_i`` (eqs. 21–22).

Conventions and traps:

* ``f_CB`` is the force each finger exerts **on the object**; a massless finger in equilibrium
  then needs ``τ = Jᵀ f_CB`` with ``J`` the contact-point Jacobian ``D_Fjk J_jk`` (eq. 10).
* Eq. 14 as printed has ``D_O f_CO``; the dimensions (``D_O`` is ``dim·r × twist·m``) and the
  virtual-work pairing with eq. 19 require ``D_Oᵀ f_CO``, which is also what eq. 20 is the
  solution of. With ``D_O = [D_O11  -D_O21]`` (eq. 18), ``f_CO`` is the force of object 2 on
  object 1 (object 2 receives ``-f_CO``), matching eqs. 21–22.
* The analysis is at rest (torques applied to a grasp at rest): the centrifugal and Coriolis
  parts of ``h_B`` and the term ``Ḋ_O ṗ_B`` of eq. 20 vanish; ``h_B`` is gravity only,
  ``h_B = [-m_i g; 0]`` per object (eq. 14 is ``M p̈ + h = forces``).
* Friction cones in space are outer (circumscribed) pyramids: the torque-set condition must
  hold for *every* admissible contact force, so a cone that contains the true one keeps the
  condition sufficient; an inner pyramid would not.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from handctl.analysis.frames import Array, tangent_basis, twist_size
from handctl.analysis.kinematics import contact_kinematics
from handctl.analysis.model import AnalysisError, FingerContact, Grasp


def cone_edges(contact: FingerContact, edges: int) -> Array:
    """``V_jk`` of eq. 11: the edge directions (columns) of the friction cone at a contact."""
    n = contact.normal
    t = tangent_basis(n)
    if n.shape[0] == 2:
        return np.column_stack([n + contact.mu * t[:, 0], n - contact.mu * t[:, 0]])
    spread = contact.mu / math.cos(math.pi / edges)
    phis = 2.0 * math.pi * np.arange(edges) / edges
    return np.column_stack(
        [n + spread * (math.cos(p) * t[:, 0] + math.sin(p) * t[:, 1]) for p in phis]
    )


def block_diag(blocks: list[Array]) -> Array:
    """Block-diagonal matrix of 2D blocks (scipy-free so that shapes of empty lists work)."""
    rows = sum(b.shape[0] for b in blocks)
    cols = sum(b.shape[1] for b in blocks)
    out = np.zeros((rows, cols))
    r = c = 0
    for b in blocks:
        out[r : r + b.shape[0], c : c + b.shape[1]] = b
        r += b.shape[0]
        c += b.shape[1]
    return out


@dataclass(frozen=True)
class Statics:
    """The matrices of §4 for one grasp at rest, plus the affine maps of λ built from them.

    ``lambda_blocks[j]`` and ``joint_blocks[j]`` are finger j's slices of λ and θ: because
    each finger's contacts load only that finger's joints, ``JᵀV`` is block diagonal with
    blocks ``A_j = J_jᵀV_j``, which the exact torque-set method exploits.
    """

    v: Array
    jacobian: Array
    d_cb: Array
    d_o: Array
    m_b: Array
    h_b: Array
    torque_map: Array
    f_co_map: Array
    f_co_offset: Array
    total_map: Array
    total_offset: Array
    accel_map: Array
    accel_offset: Array
    lambda_blocks: tuple[slice, ...]
    joint_blocks: tuple[slice, ...]

    def f_cb(self, lam: Array) -> Array:
        """Finger contact forces on the objects (eq. 11)."""
        return self.v @ lam

    def f_co(self, lam: Array) -> Array:
        """Object–object contact forces on the first object of each pair (eq. 20)."""
        return self.f_co_map @ lam + self.f_co_offset

    def totals(self, lam: Array) -> Array:
        """Total forces ``f_ti`` of eqs. 21–22, stacked by object (reading of the grasp)."""
        return self.total_map @ lam + self.total_offset

    def acceleration(self, lam: Array) -> Array:
        """Object accelerations ``p̈_B`` from eq. 14 with eq. 20's ``f_CO``."""
        return self.accel_map @ lam + self.accel_offset


def mass_matrix(grasp: Grasp) -> Array:
    """``M_B = diag[m_1 I, H_1, …]`` with ``H_i`` in the world frame."""
    blocks = []
    for body in grasp.bodies:
        blocks.append(body.mass * np.eye(grasp.dim))
        if grasp.dim == 2:
            blocks.append(body.inertia)
        else:
            blocks.append(body.rotation @ body.inertia @ body.rotation.T)
    return block_diag(blocks)


def gravity_term(grasp: Grasp) -> Array:
    """``h_B`` at rest: ``[-m_i g; 0]`` per object."""
    tw = twist_size(grasp.dim)
    h = np.zeros(tw * len(grasp.bodies))
    for i, body in enumerate(grasp.bodies):
        h[tw * i : tw * i + grasp.dim] = -body.mass * grasp.gravity
    return h


def statics(grasp: Grasp) -> Statics:
    """Build eqs. 10–22 for the grasp at rest."""
    dim = grasp.dim
    tw = twist_size(dim)
    order = [c.finger for c in grasp.finger_contacts]
    if order != sorted(order):
        raise AnalysisError("finger contacts must be stacked finger by finger (eq. 9)")
    kin = contact_kinematics(grasp)
    cones = [cone_edges(c, grasp.cone_edges) for c in grasp.finger_contacts]
    v = block_diag(cones) if cones else np.zeros((0, 0))
    jac = kin.jacobian
    torque_map = jac.T @ v
    m_b = mass_matrix(grasp)
    h_b = gravity_term(grasp)
    m_inv = np.linalg.inv(m_b)
    wrench_map = kin.d_cb.T @ v
    d_o = kin.d_o
    if d_o.shape[0]:
        s = d_o @ m_inv @ d_o.T
        if np.linalg.matrix_rank(s) < s.shape[0]:
            raise AnalysisError(
                "the object–object contacts are not independent "
                "(D_O M_B⁻¹ D_Oᵀ of eq. 20 is singular)"
            )
        f_co_map = np.asarray(-np.linalg.solve(s, d_o @ m_inv @ wrench_map), dtype=np.float64)
        f_co_offset = np.asarray(np.linalg.solve(s, d_o @ m_inv @ h_b), dtype=np.float64)
    else:
        f_co_map = np.zeros((0, v.shape[1]))
        f_co_offset = np.zeros(0)
    wrench_total = wrench_map + d_o.T @ f_co_map
    wrench_offset = d_o.T @ f_co_offset
    select = np.zeros((dim * len(grasp.bodies), tw * len(grasp.bodies)))
    for i in range(len(grasp.bodies)):
        select[dim * i : dim * (i + 1), tw * i : tw * i + dim] = np.eye(dim)
    total_map = select @ wrench_total
    total_offset = select @ wrench_offset
    if grasp.reading == "net":
        total_offset = total_offset + np.concatenate([b.mass * grasp.gravity for b in grasp.bodies])
    accel_map = m_inv @ wrench_total
    accel_offset = m_inv @ (wrench_offset - h_b)

    lam_blocks: list[slice] = []
    joint_blocks: list[slice] = []
    lam_start = 0
    offsets = grasp.joint_offsets()
    for j, finger in enumerate(grasp.fingers):
        count = sum(cones[k].shape[1] for k, c in enumerate(grasp.finger_contacts) if c.finger == j)
        lam_blocks.append(slice(lam_start, lam_start + count))
        joint_blocks.append(slice(offsets[j], offsets[j] + finger.joints))
        lam_start += count
    return Statics(
        v,
        jac,
        kin.d_cb,
        d_o,
        m_b,
        h_b,
        torque_map,
        f_co_map,
        f_co_offset,
        total_map,
        total_offset,
        accel_map,
        accel_offset,
        tuple(lam_blocks),
        tuple(joint_blocks),
    )
