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
    fingers: list[Finger] = []
    owner: dict[str, tuple[int, int]] = {}
    angles = plant.joint_angles.tolist()
    offset = 0
    for fi, f in enumerate(hand.fingers):
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
        for k, j in enumerate(f.joints):
            owner[j.name] = (fi, k)
        offset += n
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


def turn_directions(grasp: Grasp, turn: float) -> dict[str, Array]:
    """Wanted directions for turning the line from object 1 to object 2 by ``turn`` (its
    sign; rad): both move tangentially about their midpoint, in opposite directions."""
    c1, c2 = grasp.bodies[0].position, grasp.bodies[1].position
    u = unit(c2 - c1)
    sense = math.copysign(1.0, turn)
    t2 = sense * np.array([-u[1], u[0]])
    return {grasp.bodies[0].name: -t2, grasp.bodies[1].name: t2}


def fixed_directions(grasp: Grasp, move: Mapping[str, Sequence[float]]) -> dict[str, Array]:
    """The template's directions, made unit, for the objects the grasp has."""
    names = {b.name for b in grasp.bodies}
    return {name: unit(np.asarray(v, dtype=float)) for name, v in move.items() if name in names}
