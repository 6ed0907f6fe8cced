"""Eq. 9 against finite differences of eqs. 1–2, for random grasps in 2D and 3D.

The contact points are frozen in their bodies (link frame or object frame); moving the joints
and the objects by a small step along (θ̇, ṗ_B) and differencing the two copies of each contact
point (finger side minus object side, or object i minus object l) must give
``D_F θ̇ - D_B ṗ_B`` — zero for consistent (rolling) motions, which we draw from the null space
of ``[D_F, -D_B]``.
"""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from handctl.analysis.frames import Array, rotation_2d, rotation_from_vector, twist_size
from handctl.analysis.kinematics import contact_kinematics
from handctl.analysis.model import Body, BodyContact, Finger, FingerContact, Grasp

STEP = 1e-6


def _random_grasp(seed: int, dim: int, n_fingers: int, n_bodies: int) -> Grasp:
    rng = np.random.default_rng(seed)

    def rot() -> Array:
        if dim == 2:
            return rotation_2d(float(rng.uniform(-np.pi, np.pi)))
        return rotation_from_vector(rng.normal(size=3))

    bodies = tuple(
        Body(f"b{i}", rng.normal(size=dim), rot(), 0.3, 1.0 + i, np.eye(1 if dim == 2 else 3))
        for i in range(n_bodies)
    )
    fingers = []
    for j in range(n_fingers):
        joints = int(rng.integers(1, 4))
        axes = (
            tuple(v / np.linalg.norm(v) for v in rng.normal(size=(joints, 3))) if dim == 3 else ()
        )
        fingers.append(
            Finger(
                f"f{j}",
                rng.normal(size=dim),
                rot(),
                tuple(rng.uniform(0.3, 1.2, size=joints)),
                tuple(rng.uniform(-2, 2, size=joints)),
                axes,
            )
        )
    contacts = []
    for j, finger in enumerate(fingers):
        for _ in range(int(rng.integers(1, 3))):
            link = int(rng.integers(0, finger.joints))
            a, b = finger.link_segment(link)
            point = a + rng.uniform(0, 1) * (b - a) + 0.01 * rng.normal(size=dim)
            normal = rng.normal(size=dim)
            contacts.append(
                FingerContact(
                    j,
                    link,
                    int(rng.integers(0, n_bodies)),
                    0.2,
                    point,
                    normal / np.linalg.norm(normal),
                )
            )
    body_contacts = []
    for i in range(n_bodies - 1):
        normal = rng.normal(size=dim)
        body_contacts.append(
            BodyContact(i, i + 1, rng.normal(size=dim), normal / np.linalg.norm(normal))
        )
    return Grasp(dim, bodies, tuple(fingers), tuple(contacts), tuple(body_contacts), np.zeros(dim))


def _moved_rotation(rotation: Array, omega: Array, h: float) -> Array:
    if rotation.shape[0] == 2:
        return rotation_2d(float(omega[0]) * h) @ rotation
    return rotation_from_vector(omega * h) @ rotation


def _mismatch(grasp: Grasp, theta_dot: Array, p_dot: Array, h: float) -> Array:
    """Per contact, the gap between the two copies of the frozen contact point after a step h:
    finger side minus object side, and object l minus object i."""
    dim = grasp.dim
    tw = twist_size(dim)
    offsets = grasp.joint_offsets()
    moved_fingers = [
        f.with_angles(np.array(f.angles) + h * theta_dot[o : o + f.joints])
        for f, o in zip(grasp.fingers, offsets, strict=True)
    ]

    def body_point(i: int, world_point: Array) -> Array:
        body = grasp.bodies[i]
        local = body.rotation.T @ (world_point - body.position)
        v = p_dot[tw * i : tw * i + dim]
        w = p_dot[tw * i + dim : tw * (i + 1)]
        return body.position + h * v + _moved_rotation(body.rotation, w, h) @ local

    out = []
    for c in grasp.finger_contacts:
        origin, rotation = grasp.fingers[c.finger].frames()[c.link]
        local = rotation.T @ (c.point - origin)
        new_origin, new_rotation = moved_fingers[c.finger].frames()[c.link]
        out.append(new_origin + new_rotation @ local - body_point(c.body, c.point))
    for bc in grasp.body_contacts:
        # eq. 9's object rows read 0 = D_O ṗ_B (D_F is zero there): the residual is l minus i
        out.append(body_point(bc.second, bc.point) - body_point(bc.first, bc.point))
    return np.concatenate(out)


grasps = st.builds(
    _random_grasp,
    st.integers(0, 2**31 - 1),
    st.sampled_from([2, 3]),
    st.integers(1, 3),
    st.integers(1, 3),
)


@settings(max_examples=60, deadline=None)
@given(grasps, st.integers(0, 2**31 - 1))
def test_eq9_equals_finite_difference_of_eqs_1_2(grasp: Grasp, seed: int) -> None:
    rng = np.random.default_rng(seed)
    kin = contact_kinematics(grasp)
    theta_dot = rng.normal(size=grasp.joint_count)
    p_dot = rng.normal(size=int(kin.d_b.shape[1]))
    fd = (_mismatch(grasp, theta_dot, p_dot, STEP) - _mismatch(grasp, theta_dot, p_dot, -STEP)) / (
        2 * STEP
    )
    np.testing.assert_allclose(kin.d_f @ theta_dot - kin.d_b @ p_dot, fd, atol=1e-6)


@settings(max_examples=60, deadline=None)
@given(grasps, st.integers(0, 2**31 - 1))
def test_consistent_motions_keep_contact_points_together(grasp: Grasp, seed: int) -> None:
    rng = np.random.default_rng(seed)
    kin = contact_kinematics(grasp)
    stacked = np.hstack([kin.d_f, -kin.d_b])
    _, sing, vt = np.linalg.svd(stacked)
    rank = int(np.sum(sing > 1e-9))
    null = vt[rank:]
    if len(null) == 0:
        return
    motion = null.T @ rng.normal(size=len(null))
    theta_dot, p_dot = motion[: grasp.joint_count], motion[grasp.joint_count :]
    np.testing.assert_allclose(kin.d_f @ theta_dot, kin.d_b @ p_dot, atol=1e-9)
    fd = (_mismatch(grasp, theta_dot, p_dot, STEP) - _mismatch(grasp, theta_dot, p_dot, -STEP)) / (
        2 * STEP
    )
    np.testing.assert_allclose(fd, 0.0, atol=1e-6)


@settings(max_examples=40, deadline=None)
@given(grasps)
def test_shapes_are_the_papers(grasp: Grasp) -> None:
    kin = contact_kinematics(grasp)
    dim = grasp.dim
    rows = dim * len(grasp.finger_contacts) + dim * len(grasp.body_contacts)
    assert kin.d_b.shape == (rows, (3 if dim == 2 else 6) * len(grasp.bodies))
    assert kin.d_f.shape == (rows, sum(f.joints for f in grasp.fingers))
    # object-object rows have no joint part (the zero block row of D_F)
    assert np.all(kin.d_f[kin.finger_rows :] == 0.0)
