"""Rolling-contact kinematics of §3.1 (eqs. 1–9) for m objects, n fingers, in 2D and 3D.

Rows of eq. 9 are stacked as the paper does: the finger contacts finger by finger (``c_j``
contacts of finger j, ``dim`` rows each), then the ``r`` object–object contacts. Columns of
``D_F`` are the joints finger by finger (``s_j`` each); columns of ``D_B`` are the objects'
twists ``[ṗ_Bi; ω_Bi]`` (3 in the plane, 6 in space). So ``D_B`` is
``(Σ dim·c_j + dim·r) × twist·m`` and ``D_F`` is ``(Σ dim·c_j + dim·r) × Σ s_j``, the paper's
dimensions. The contact points are body-fixed at the instant of evaluation: these are velocity
relations (what a finite difference of eqs. 1–2 with the points frozen in their bodies gives).

The planar cross-product operator is the column ``(a_y, -a_x)ᵀ``; see ``frames`` for why the
paper's row ``[-a_y  a_x]`` cannot be used in ``D = [I  -(a×)]``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from handctl.analysis.frames import Array, point_velocity_map, twist_size
from handctl.analysis.model import BodyContact, Finger, FingerContact, Grasp


def link_jacobian(finger: Finger, link: int) -> Array:
    """``J_jk`` of eq. 8: twist ``[ṗ_F; ω_F]`` of link ``link``'s frame per joint rate.

    The frame origin is at the link's own joint, so joint ``link`` adds rotation only.
    """
    frames = finger.frames()
    origin = frames[link][0]
    dim = finger.dim
    jac = np.zeros((twist_size(dim), finger.joints))
    axes = finger.joint_axes_world() if dim == 3 else []
    for joint in range(link + 1):
        lever = origin - frames[joint][0]
        if dim == 2:
            jac[:2, joint] = [-lever[1], lever[0]]
            jac[2, joint] = 1.0
        else:
            jac[:3, joint] = np.cross(axes[joint], lever)
            jac[3:, joint] = axes[joint]
    return jac


def finger_contact_blocks(grasp: Grasp, contact: FingerContact) -> tuple[Array, Array]:
    """``(D_Fjk J_jk, D_Bjk)`` of eqs. 3, 5, 6 and 8 for one finger contact.

    The first maps finger j's joint rates to the velocity of the contact point as a point of
    the link, the second maps object i's twist to the velocity of the same point as a point of
    the object; rolling (no slip) makes them equal.
    """
    finger = grasp.fingers[contact.finger]
    origin = finger.frames()[contact.link][0]
    d_f = point_velocity_map(contact.point - origin)
    d_b = point_velocity_map(contact.point - grasp.bodies[contact.body].position)
    return d_f @ link_jacobian(finger, contact.link), d_b


def body_contact_blocks(grasp: Grasp, contact: BodyContact) -> tuple[Array, Array]:
    """``(D_Oit, D_Olt)`` of eqs. 4 and 7 for the common point of objects i and l."""
    first = grasp.bodies[contact.first]
    second = grasp.bodies[contact.second]
    return (
        point_velocity_map(contact.point - first.position),
        point_velocity_map(contact.point - second.position),
    )


@dataclass(frozen=True)
class ContactKinematics:
    """Eq. 9 and the blocks the statics of §4 reuse.

    ``d_f``/``d_b`` are ``D_F``/``D_B``; ``finger_rows`` is the number of rows that belong to
    finger contacts, so ``J = d_f[:finger_rows]`` (eq. 10, the contact-point Jacobian),
    ``D_CB = d_b[:finger_rows]`` (eq. 15) and ``D_O = d_b[finger_rows:]`` (eq. 18).
    """

    d_f: Array
    d_b: Array
    finger_rows: int

    @property
    def jacobian(self) -> Array:
        return self.d_f[: self.finger_rows]

    @property
    def d_cb(self) -> Array:
        return self.d_b[: self.finger_rows]

    @property
    def d_o(self) -> Array:
        return self.d_b[self.finger_rows :]


def contact_kinematics(grasp: Grasp) -> ContactKinematics:
    """Assemble ``D_F`` and ``D_B`` of eq. 9."""
    dim = grasp.dim
    tw = twist_size(dim)
    rows = dim * (len(grasp.finger_contacts) + len(grasp.body_contacts))
    d_f = np.zeros((rows, grasp.joint_count))
    d_b = np.zeros((rows, tw * len(grasp.bodies)))
    offsets = grasp.joint_offsets()
    row = 0
    for contact in grasp.finger_contacts:
        block_f, block_b = finger_contact_blocks(grasp, contact)
        j0 = offsets[contact.finger]
        d_f[row : row + dim, j0 : j0 + block_f.shape[1]] = block_f
        d_b[row : row + dim, tw * contact.body : tw * (contact.body + 1)] = block_b
        row += dim
    finger_rows = row
    for body_contact in grasp.body_contacts:
        d_first, d_second = body_contact_blocks(grasp, body_contact)
        d_b[row : row + dim, tw * body_contact.first : tw * (body_contact.first + 1)] = d_first
        d_b[row : row + dim, tw * body_contact.second : tw * (body_contact.second + 1)] = -d_second
        row += dim
    return ContactKinematics(d_f, d_b, finger_rows)
