"""The analysis' grasp model (``handctl.analysis.Grasp``) of a configuration of the simulated hand.

The analysis reasons about a grasp at one instant: objects as discs, finger links as lines,
the contacts between them. A phase's grasp is the simulated hand's state where the phase
begins, read off MuJoCo: object poses, joint angles, and the active contacts. Choices:

- **Contacts come from MuJoCo** (the pairs in contact now), not from a distance threshold: they
  are the contacts that carry force in the simulation the plan is checked on. A link touching
  an object twice (MuJoCo may report two points) is one contact, as the model has it.
- **Contact points are on the object's surface**, on the line from the link's axis to the
  object's centre; the normal is that line's direction (link towards object). The links of the
  hand have a thickness (``half_thickness``) where the paper's have none; the normal force
  still passes through the centre, so only the tangential force's moment arm changes, and the
  point where the object really is touched is the one that gives it right.
- **Palm and table are left out.** The paper's model has no contact with the environment: a
  rigid palm would add a reaction that no joint torque bounds, and every robust condition
  with a component into the palm would fail. Leaving it out makes the analysis optimistic
  for motions into the palm, which is one reason its answer is checked and refined on the
  simulated hand (``search``).
- Gravity acts in the hand's plane (``reading: net``): the object's acceleration is set by the
  net force, weight included.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import mujoco
import numpy as np

from handctl.analysis.frames import Array, rotation_2d, unit
from handctl.analysis.model import Body, BodyContact, Finger, FingerContact, Grasp
from handctl.config import HandConfig
from handctl.online.recipes.schema import GraspModel
from handctl.sim.plant import Plant


@dataclass(frozen=True)
class GraspSnapshot:
    """A grasp and what it left out, for provenance."""

    grasp: Grasp
    environment: tuple[str, ...]  # contacts with the palm or the table, left out
    contacts: tuple[str, ...]  # "JOINT/OBJECT" and "OBJECT/OBJECT": what the grasp has

    def describe(self) -> dict[str, object]:
        return {"contacts": list(self.contacts), "left_out": list(self.environment)}


def grasp_of(plant: Plant, hand: HandConfig) -> GraspSnapshot:
    """The grasp of the plant's current state (see the module doc for the choices)."""
    model, data = plant.model, plant.data
    params = plant.params
    joint_names = list(hand.joint_names)
    object_names = [o.name for o in params.objects]
    poses = plant.object_poses()
    bodies = tuple(
        Body(
            o.name,
            np.array([p.x, p.y]),
            rotation_2d(p.angle),
            o.radius,
            o.mass,
            np.array([[o.mass * o.radius**2 / 2]]),
        )
        for o, p in zip(params.objects, poses, strict=True)
    )
    fingers = _fingers(hand, plant.joint_angles.tolist())
    owner = {j.name: (fi, k) for fi, f in enumerate(hand.fingers) for k, j in enumerate(f.joints)}
    finger_contacts: dict[tuple[int, int, int], FingerContact] = {}
    body_contacts: dict[tuple[int, int], BodyContact] = {}
    environment: set[str] = set()
    for i in range(data.ncon):
        con = data.contact[i]
        a = mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_GEOM, int(con.geom1))
        b = mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_GEOM, int(con.geom2))
        if b in joint_names and a in object_names:
            a, b = b, a
        if a in joint_names and b in object_names:
            fi, k = owner[a]
            bi = object_names.index(b)
            key = (fi, k, bi)
            if key not in finger_contacts:
                finger_contacts[key] = _finger_contact(
                    fingers[fi], k, bodies[bi], fi, bi, params.friction.finger_object
                )
        elif a in object_names and b in object_names:
            first, second = sorted((object_names.index(a), object_names.index(b)))
            if (first, second) not in body_contacts:
                body_contacts[(first, second)] = _body_contact(
                    bodies, first, second, params.friction.object_object
                )
        elif a in object_names or b in object_names:
            environment.add(f"{a}/{b}")
    keys = sorted(finger_contacts)
    grasp = Grasp(
        2,
        bodies,
        tuple(fingers),
        tuple(finger_contacts[k] for k in keys),
        tuple(body_contacts[k] for k in sorted(body_contacts)),
        np.array([0.0, -params.gravity]),
        "net",
    )
    names = [f"{hand.fingers[fi].joints[k].name}/{object_names[bi]}" for fi, k, bi in keys]
    names += [f"{object_names[a]}/{object_names[b]}" for a, b in sorted(body_contacts)]
    return GraspSnapshot(grasp, tuple(sorted(environment)), tuple(names))


def _fingers(hand: HandConfig, angles: Sequence[float]) -> list[Finger]:
    """The analysis' fingers of ``hand`` at ``angles`` (rad, the hand's joint order)."""
    fingers: list[Finger] = []
    offset = 0
    for f in hand.fingers:
        n = len(f.joints)
        fingers.append(
            Finger(
                f.name,
                np.array([f.base_x, f.base_y]),
                rotation_2d(f.base_angle),
                tuple(j.link_length for j in f.joints),
                tuple(angles[offset : offset + n]),
            )
        )
        offset += n
    return fingers


def measured_grasp(
    hand: HandConfig,
    angles: Sequence[float],
    centres: Sequence[tuple[float, float]],
    radii: Sequence[float],
    names: Sequence[str],
    model: GraspModel,
) -> GraspSnapshot:
    """The grasp of a configuration as the hand measures it: joint angles (rad), each
    object's estimated centre (m) and measured radius (m), in the recipe's order. What the
    hand cannot measure (masses, friction, gravity) is ``model``'s.

    The contacts are decided by geometry, as the estimator sees the cage: the estimator puts
    each object equally far from every wall that holds it (a clearance that is not zero where
    the measured radius or the soft contacts are off), so a link or another object counts as
    touching an object when its clearance is within ``model.contact_gap`` of that object's
    tightest one. Link clearances count the link's half-thickness, as the estimator's do; the
    contact point and normal are then placed as ``grasp_of`` places them. The palm is left out
    (see the module doc)."""
    fingers = _fingers(hand, [float(a) for a in angles])
    thickness = [tuple(j.half_thickness for j in f.joints) for f in hand.fingers]
    bodies = tuple(
        Body(
            name,
            np.array([float(c[0]), float(c[1])]),
            rotation_2d(0.0),
            float(r),
            m,
            np.array([[m * float(r) ** 2 / 2]]),
        )
        for name, c, r, m in zip(names, centres, radii, model.masses, strict=True)
    )
    segments = [
        (fi, k, *finger.link_segment(k))
        for fi, finger in enumerate(fingers)
        for k in range(finger.joints)
    ]
    link_clearance = {
        (fi, k, bi): _segment_distance(body.position, start, end) - body.radius - thickness[fi][k]
        for fi, k, start, end in segments
        for bi, body in enumerate(bodies)
    }
    pair_clearance = {
        (a, b): float(np.linalg.norm(bodies[b].position - bodies[a].position))
        - bodies[a].radius
        - bodies[b].radius
        for a in range(len(bodies))
        for b in range(a + 1, len(bodies))
    }
    tightest = [
        min(
            [c for (_, _, bi), c in link_clearance.items() if bi == i]
            + [c for pair, c in pair_clearance.items() if i in pair]
        )
        for i in range(len(bodies))
    ]
    keys = sorted(k for k, c in link_clearance.items() if c <= tightest[k[2]] + model.contact_gap)
    touching = sorted(
        pair
        for pair, c in pair_clearance.items()
        if c <= min(tightest[pair[0]], tightest[pair[1]]) + model.contact_gap
    )
    grasp = Grasp(
        2,
        bodies,
        tuple(fingers),
        tuple(
            _finger_contact(fingers[fi], k, bodies[bi], fi, bi, model.finger_object_mu)
            for fi, k, bi in keys
        ),
        tuple(_body_contact(bodies, a, b, model.object_object_mu) for a, b in touching),
        np.array([0.0, -model.gravity]),
        "net",
    )
    contacts = [f"{hand.fingers[fi].joints[k].name}/{names[bi]}" for fi, k, bi in keys]
    contacts += [f"{names[a]}/{names[b]}" for a, b in touching]
    return GraspSnapshot(grasp, (), tuple(contacts))


def _segment_distance(point: Array, start: Array, end: Array) -> float:
    """m, from ``point`` to the segment from ``start`` to ``end``."""
    span = end - start
    along = float(np.clip((point - start) @ span / float(span @ span), 0.0, 1.0))
    return float(np.linalg.norm(point - (start + along * span)))


def _finger_contact(
    finger: Finger, link: int, body: Body, fi: int, bi: int, mu: float
) -> FingerContact:
    start, end = finger.link_segment(link)
    direction = (end - start) / finger.lengths[link]
    along = float(np.clip((body.position - start) @ direction, 0.0, finger.lengths[link]))
    foot = start + along * direction
    normal = unit(body.position - foot)
    return FingerContact(fi, link, bi, mu, body.position - normal * body.radius, normal)


def _body_contact(bodies: Sequence[Body], first: int, second: int, mu: float) -> BodyContact:
    a, b = bodies[first], bodies[second]
    normal = unit(b.position - a.position)
    return BodyContact(first, second, a.position + normal * a.radius, normal, mu)


def turn_directions(grasp: Grasp, turn: float, pair: tuple[int, int] = (0, 1)) -> dict[str, Array]:
    """Wanted directions for turning the line from object ``pair[0]`` to ``pair[1]`` (the
    first two by default) by ``turn`` (its sign; rad): both move tangentially about their
    midpoint, in opposite directions."""
    first, second = grasp.bodies[pair[0]], grasp.bodies[pair[1]]
    u = unit(second.position - first.position)
    sense = math.copysign(1.0, turn)
    t2 = sense * np.array([-u[1], u[0]])
    return {first.name: -t2, second.name: t2}


def fixed_directions(grasp: Grasp, move: Mapping[str, Sequence[float]]) -> dict[str, Array]:
    """The template's directions, made unit, for the objects the grasp has."""
    names = {b.name for b in grasp.bodies}
    return {name: unit(np.asarray(v, dtype=float)) for name, v in move.items() if name in names}
