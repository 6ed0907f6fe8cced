"""The grasp model of §3: objects, fingers, contacts and friction, read from a scenario file.

Everything downstream (kinematics, statics, torque sets, planner) works on a ``Grasp`` whose
contact points and normals are *derived* from the geometry here and checked against it, so a
scenario cannot declare a contact that the geometry does not have: a link that is not tangent
to its object, a contact point beyond the end of a link, two objects that do not touch — each is
a ``ConfigError`` naming the contact, as is every malformed value (same discipline as the hand
config, through ``handctl.schema``).

Geometry: objects are discs in the plane, spheres or cylinders in space (pose, radius, mass,
inertia); finger links are ideal lines (zero thickness), as in the paper's Fig. 2. In space, a
cylinder is treated as infinitely long along its body z axis; where a contact point is not
unique (a link or a second cylinder parallel to a cylinder's axis), the point nearest to the
other body's reference point is used.

Trap "diameter R = 0.45 m" (§4): two objects of diameter 0.45 m could not be enveloped by links
of 1 m the way Fig. 3 shows and touch each other on the symmetry axis between bases 1 m apart;
R is a radius (the usual symbol), and the scenario files give radii.

Units: m, rad, kg, kg·m², N·m; angles counter-clockwise positive.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from handctl.analysis.frames import (
    Array,
    moderate,
    rotation_2d,
    rotation_about,
    rotation_from_vector,
    unit,
)
from handctl.errors import HandctlError
from handctl.schema import Doc, load_yaml

READINGS = ("paper", "net")


class AnalysisError(HandctlError, ValueError):
    """A grasp or a request the analysis cannot treat (singular contact system, wrong shape)."""


@dataclass(frozen=True)
class Body:
    """A grasped object. ``rotation`` is world-from-body; ``inertia`` is about the centre of mass,
    in the body frame (1×1 in the plane, 3×3 in space); a cylinder's axis is body z."""

    name: str
    position: Array
    rotation: Array
    radius: float
    mass: float
    inertia: Array
    shape: str = "disc"

    @property
    def dim(self) -> int:
        return int(self.position.shape[0])

    def axis(self) -> Array | None:
        """World direction of a cylinder's axis; ``None`` for discs and spheres (a point core)."""
        return self.rotation[:, 2].copy() if self.shape == "cylinder" else None


@dataclass(frozen=True)
class Finger:
    """A serial chain of revolute joints with ideal line links along each link's local x axis.

    Link k's frame Σ_F has its origin at joint k and rotation ``R_{k-1} Rot(axis_k, θ_k)``,
    so ``p_F`` and ``R_F`` of eqs. 1 and 3 are this frame. Joint axes are given in the frame of
    the previous link (the base for joint 1); in the plane they are all z.
    """

    name: str
    base: Array
    base_rotation: Array
    lengths: tuple[float, ...]
    angles: tuple[float, ...]
    axes: tuple[Array, ...] = ()

    @property
    def dim(self) -> int:
        return int(self.base.shape[0])

    @property
    def joints(self) -> int:
        return len(self.lengths)

    def with_angles(self, angles: Sequence[float] | Array) -> Finger:
        """The same finger at other joint angles (for finite differences and sweeps)."""
        return Finger(
            self.name,
            self.base,
            self.base_rotation,
            self.lengths,
            tuple(float(a) for a in angles),
            self.axes,
        )

    def frames(self) -> list[tuple[Array, Array]]:
        """``(p_F, R_F)`` of every link, base first."""
        out: list[tuple[Array, Array]] = []
        position = self.base.astype(float)
        rotation = self.base_rotation.astype(float)
        for k, (length, angle) in enumerate(zip(self.lengths, self.angles, strict=True)):
            if self.dim == 2:
                rotation = rotation @ rotation_2d(angle)
            else:
                rotation = rotation @ rotation_about(self.axes[k], angle)
            out.append((position, rotation))
            position = position + rotation[:, 0] * length
        return out

    def joint_axes_world(self) -> list[Array]:
        """World direction of every joint axis (3D only)."""
        axes: list[Array] = []
        rotation = self.base_rotation.astype(float)
        for k, (_, link_rotation) in enumerate(self.frames()):
            axes.append(rotation @ self.axes[k])
            rotation = link_rotation
        return axes

    def link_segment(self, link: int) -> tuple[Array, Array]:
        """Start and end point of a link."""
        origin, rotation = self.frames()[link]
        return origin, origin + rotation[:, 0] * self.lengths[link]


@dataclass(frozen=True)
class FingerContact:
    """Contact of a finger link with an object. ``normal`` points from the link into the object,
    which is the direction of the normal force the finger exerts; ``point`` is in the world."""

    finger: int
    link: int
    body: int
    mu: float
    point: Array
    normal: Array


@dataclass(frozen=True)
class BodyContact:
    """Contact C between two objects. ``normal`` is the outward normal of ``first`` at C (from
    ``first`` towards ``second``); ``mu`` is ``None`` for the rolling constraint of eq. 19 with
    no friction bound (the paper's assumption), else the friction coefficient at C."""

    first: int
    second: int
    point: Array
    normal: Array
    mu: float | None = None


@dataclass(frozen=True)
class Grasp:
    """The whole system of Fig. 1. ``gravity`` is the acceleration of gravity in the world frame
    (m/s²); ``reading`` selects what the total force ``f_ti`` of eqs. 21–22 contains (see
    ``handctl.analysis.conditions``); ``cone_edges`` is the number of edges of the polyhedral
    friction cones in space (2 in the plane)."""

    dim: int
    bodies: tuple[Body, ...]
    fingers: tuple[Finger, ...]
    finger_contacts: tuple[FingerContact, ...]
    body_contacts: tuple[BodyContact, ...]
    gravity: Array
    reading: str = "paper"
    cone_edges: int = 2

    @property
    def joint_count(self) -> int:
        return sum(f.joints for f in self.fingers)

    def joint_offsets(self) -> list[int]:
        """Index of each finger's first joint in the stacked joint vector θ."""
        offsets, total = [], 0
        for finger in self.fingers:
            offsets.append(total)
            total += finger.joints
        return offsets

    def body_index(self, name: str) -> int:
        return [b.name for b in self.bodies].index(name)


@dataclass(frozen=True)
class Scenario:
    """A grasp plus the task of §4: the wanted direction ``a_i`` of each object (unit vectors,
    by object name) and the joint torque limit."""

    file: str
    grasp: Grasp
    directions: dict[str, Array] = field(default_factory=dict)
    tau_max: float = math.inf


# -- geometry of contacts --------------------------------------------------------------------

Core = tuple[Array, Array | None]
"""A body's core: a reference point and, for a line core, a unit direction."""


def closest_points(a: Core, b: Core) -> tuple[Array, Array]:
    """Closest points between two cores (points or infinite lines); for parallel lines, the
    point of ``a`` nearest to ``b``'s reference point and its foot on ``b``."""
    pa, da = a
    pb, db = b
    if da is None and db is None:
        return pa, pb
    if da is None:
        assert db is not None
        return pa, pb + db * float(db @ (pa - pb))
    if db is None:
        return pa + da * float(da @ (pb - pa)), pb
    w = pa - pb
    c = float(da @ db)
    denom = 1.0 - c * c
    if denom < 1e-12:
        qa = pa + da * float(da @ (pb - pa))
        return qa, pb + db * float(db @ (qa - pb))
    s = (c * float(db @ w) - float(da @ w)) / denom
    t = (float(db @ w) - c * float(da @ w)) / denom
    return pa + da * s, pb + db * t


def _finger_contact(
    grasp_bodies: Sequence[Body],
    fingers: Sequence[Finger],
    finger: int,
    link: int,
    body: int,
    mu: float,
    tol: float,
    doc: Doc,
) -> FingerContact:
    start, end = fingers[finger].link_segment(link)
    length = fingers[finger].lengths[link]
    direction = (end - start) / length
    obj = grasp_bodies[body]
    on_link, on_core = closest_points((start, direction), (obj.position, obj.axis()))
    along = float(direction @ (on_link - start))
    if along < -tol or along > length + tol:
        doc.fail(
            "link",
            f"the contact point within the link (0 to {length:g} m)",
            f"{along:.9g} m along the link",
        )
    gap = float(np.linalg.norm(on_core - on_link))
    if abs(gap - obj.radius) > tol:
        doc.fail(
            "object",
            f"the link tangent to {obj.name} (distance {obj.radius:g} m "
            f"to its {'axis' if obj.shape == 'cylinder' else 'centre'}, "
            f"within {tol:g} m)",
            f"{gap:.12g} m",
        )
    return FingerContact(finger, link, body, mu, on_link, unit(on_core - on_link))


def _body_contact(
    bodies: Sequence[Body], first: int, second: int, mu: float | None, tol: float, doc: Doc
) -> BodyContact:
    a, b = bodies[first], bodies[second]
    pa, pb = closest_points((a.position, a.axis()), (b.position, b.axis()))
    gap = float(np.linalg.norm(pb - pa))
    if abs(gap - a.radius - b.radius) > tol or gap < 1e-12:
        doc.fail(
            "objects",
            f"touching objects (core distance {a.radius + b.radius:g} m within {tol:g} m)",
            f"{gap:.12g} m",
        )
    normal = unit(pb - pa)
    return BodyContact(first, second, pa + normal * a.radius, normal, mu)


# -- YAML ------------------------------------------------------------------------------------


#: Bounds far beyond any hand (the paper's scale is 1 m, 1 kg, a few N·m) that keep the
#: analysis' arithmetic finite: a torque box of 1e300 N·m had an area of inf, a friction
#: coefficient of 1e300 made every torque unrealisable, both reported as results.
MAX_TAU = 1e4  # N·m
MAX_MU = 100.0
MAX_GRAVITY = 1e3  # m/s²
#: of m r²: the smallest moment of inertia a body may have
MIN_INERTIA_FRACTION = 1e-9
#: m: the most a listed contact may miss touching. The analysis computes with the contact
#: where the geometry puts it, so a looser tolerance would accept a scenario whose contacts
#: are not the ones its file describes (a millimetre is already 5 % of a cylinder's radius)
MAX_GEOMETRY_TOLERANCE = 1e-3


def load_scenario(path: str | Path) -> Scenario:
    """Read and check a scenario file; every problem is a ``ConfigError``."""
    doc = load_yaml(path, "analysis scenario")
    dim = doc.integer("dimension", min=2, max=3)
    reading = doc.string("reading", choices=READINGS)
    gravity = np.array(
        doc.numbers("gravity", length=dim, min=-MAX_GRAVITY, max=MAX_GRAVITY, unit="m/s²")
    )
    tol = doc.number(
        "geometry_tolerance",
        default=1e-9,
        min=0.0,
        min_exclusive=True,
        max=MAX_GEOMETRY_TOLERANCE,
        unit="m",
    )
    cone_edges = 2 if dim == 2 else doc.integer("cone_edges", default=8, min=3, max=64)
    bodies = tuple(_read_body(d, dim) for d in doc.mappings("objects", min_len=1))
    names = [b.name for b in bodies]
    _unique(doc, "objects", names)
    fingers = tuple(_read_finger(d, dim) for d in doc.mappings("fingers", min_len=1))
    _unique(doc, "fingers", [f.name for f in fingers])

    contacts = doc.mapping("contacts")
    finger_contacts: list[FingerContact] = []
    touching: dict[tuple[int, int, int], int] = {}
    for k, d in enumerate(contacts.mappings("fingers", min_len=1)):
        fi = _choose(d, "finger", [f.name for f in fingers])
        link = d.integer("link", min=1, max=fingers[fi].joints) - 1
        bi = _choose(d, "object", names)
        if (fi, link, bi) in touching:
            # a contact listed twice would count its force twice in eq. 9
            d.fail(
                "object",
                "each link touching each object at most once (contacts.fingers"
                f"[{touching[fi, link, bi]}] is this finger, link and object)",
                names[bi],
            )
        touching[fi, link, bi] = k
        mu = d.number("mu", min=0.0, max=MAX_MU)
        finger_contacts.append(_finger_contact(bodies, fingers, fi, link, bi, mu, tol, d))
        d.done()
    body_contacts: list[BodyContact] = []
    seen: set[tuple[int, int]] = set()
    for d in contacts.mappings("objects", default=[]):
        pair = d.raw("objects")
        if (
            not isinstance(pair, list)
            or len(pair) != 2
            or pair[0] == pair[1]
            or any(p not in names for p in pair)
        ):
            d.fail("objects", "two different object names out of " + ", ".join(names), pair)
        first, second = names.index(pair[0]), names.index(pair[1])
        if (min(first, second), max(first, second)) in seen:
            d.fail("objects", "each pair of objects at most once", pair)
        seen.add((min(first, second), max(first, second)))
        mu_value = d.raw("mu", None)
        mu_c = None if mu_value is None else d.check_number("mu", mu_value, min=0.0, max=MAX_MU)
        body_contacts.append(_body_contact(bodies, first, second, mu_c, tol, d))
        d.done()
    contacts.done()
    # eq. 9 stacks the contacts finger by finger: keep the file's order within a finger
    finger_contacts.sort(key=lambda c: c.finger)

    task = doc.mapping("task")
    tau_max = task.number("tau_max", min=0.0, max=MAX_TAU, min_exclusive=True, unit="N·m")
    move = task.mapping("move")
    if not list(move.keys()):
        # the analysis found out only when it ran: "no wanted motion", exit 1, no file named
        task.fail("move", "a direction for at least one object (" + ", ".join(names) + ")", {})
    directions: dict[str, Array] = {}
    for name in list(move.keys()):
        if name not in names:
            move.fail(name, "an object name out of " + ", ".join(names), name)
        vector = np.array(move.numbers(name, length=dim))
        if not np.any(vector):
            move.fail(name, "a non-zero direction", [float(v) for v in vector])
        directions[name] = unit(moderate(vector))
    move.done()
    task.done()
    doc.done()
    grasp = Grasp(
        dim,
        bodies,
        fingers,
        tuple(finger_contacts),
        tuple(body_contacts),
        gravity,
        reading,
        cone_edges,
    )
    return Scenario(str(path), grasp, directions, tau_max)


def _unique(doc: Doc, key: str, names: list[str]) -> None:
    for i, name in enumerate(names):
        if name in names[:i]:
            doc.fail(key, "unique names", f"{name!r} twice")


def _choose(d: Doc, key: str, names: list[str]) -> int:
    value = d.string(key, choices=names)
    return names.index(value)


def _rotation(d: Doc, dim: int, key2: str, key3: str) -> Array:
    if dim == 2:
        return rotation_2d(d.number(key2, default=0.0, unit="rad"))
    return rotation_from_vector(
        np.array(d.numbers(key3, length=3, default=[0.0, 0.0, 0.0], unit="rad"))
    )


def _read_body(d: Doc, dim: int) -> Body:
    name = d.label("name")
    position = np.array(d.numbers("position", length=dim, unit="m"))
    rotation = _rotation(d, dim, "angle", "rotation")
    radius = d.number("radius", min=0.0, min_exclusive=True, unit="m")
    mass = d.number("mass", min=0.0, min_exclusive=True, unit="kg")
    # a body's moments of inertia are some fraction of m r² (a disc's is 1/2); far below it
    # (1e-20 kg·m² on the paper's 1 kg cylinder) the contact equations' matrix is singular in
    # floating point, which the analysis would report as dependent contacts
    smallest = MIN_INERTIA_FRACTION * mass * radius**2
    if dim == 2:
        shape = "disc"
        inertia = np.array([[d.number("inertia", min=smallest, unit="kg·m²")]])
    else:
        shape = d.string("shape", choices=("sphere", "cylinder"))
        inertia = np.diag(d.numbers("inertia", length=3, min=0.0, unit="kg·m²"))
        if float(np.min(np.diag(inertia))) < smallest:
            d.fail(
                "inertia",
                f"three principal moments >= {smallest:.3g} kg·m² ({MIN_INERTIA_FRACTION:g} m r²)",
                list(np.diag(inertia)),
            )
    d.done()
    return Body(name, position, rotation, radius, mass, inertia, shape)


def _read_finger(d: Doc, dim: int) -> Finger:
    name = d.label("name")
    base = np.array(d.numbers("base", length=dim, unit="m"))
    rotation = _rotation(d, dim, "base_angle", "base_rotation")
    lengths = d.numbers("links", min=0.0, unit="m")
    if not lengths or min(lengths) <= 0.0:
        d.fail("links", "a non-empty list of link lengths > 0 m", list(lengths))
    angles = d.numbers("joints", length=len(lengths), unit="rad")
    axes: tuple[Array, ...] = ()
    if dim == 3:
        raw_axes = d.raw("axes")
        if not isinstance(raw_axes, list) or len(raw_axes) != len(lengths):
            d.fail("axes", f"a list of {len(lengths)} joint axes", raw_axes)
        sub = Doc({"axes": raw_axes}, d.file, d.path)
        vectors = []
        for i, item in enumerate(raw_axes):
            if not isinstance(item, list) or len(item) != 3:
                sub.fail("axes", "joint axes of 3 numbers", item)
            vec = np.array([sub.check_number(f"axes[{i}]", v) for v in item])
            if float(np.linalg.norm(vec)) < 1e-12:
                sub.fail("axes", "non-zero joint axes", item)
            vectors.append(unit(vec))
        axes = tuple(vectors)
    d.done()
    return Finger(name, base, rotation, lengths, angles, axes)
