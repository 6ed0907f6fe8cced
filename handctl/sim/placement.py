"""Is the simulated scene one that can start? Names, reach and overlaps of the ``sim:`` section.

MuJoCo resolves bodies that start inside one another with a violent kick, and an object no
finger can reach makes a run that can only fail for a reason nobody sees. So the scene is
checked once, when the section is read, and refused with the key to change:

- every object's name is its own: MuJoCo names each body, geom and joint, and an object called
  like a link (or ``palm``) would be a model that does not build, or a contact on the wrong body;
  for the same reason no joint may be called ``palm``, ``table``, ``world`` or
  ``<finger>_base`` (``config.scene_names``, which the hand config refuses for every hand);
- objects lie between the table and the palm face, clear of one another;
- each object is within reach of at least one finger (its surface nearer to the finger's base
  than the finger is long, and the finger beside it along z);
- at the initial angles every link is out of the palm, clear of every object, and, where
  fingers collide (``contact.between_fingers``), clear of the other fingers' links.

A fingertip that starts a few millimetres into the table is not refused: the planning models
draw start poses around the configured one (``handctl/planning/models.py``), and a fifth of
them dip a fingertip that far; the table's contact lifts it out within a few ticks, a link
inside a cylinder or the palm is not so benign. A link deeper than its own diameter is
refused: one that deep is flung out, past a joint's limit or into a node's sensor fault (a
finger of five joints, 17 mm deep, passed its limit in 6 ticks). The planning models' start
poses (±0.1 rad) dip the shipped hands' fingertips at most 11 mm, under their diameters.

The scene is planar: links are capsules around segments in planes z = const (a finger's z),
objects capsules along z. The distance of two such shapes is the in-plane distance of their
axes combined with the gap along z between their extents.
"""

from __future__ import annotations

import math
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

from handctl.config import HandConfig, scene_names
from handctl.errors import ConfigError
from handctl.schema import Doc

if TYPE_CHECKING:
    from handctl.sim.params import ObjectParams, SimParams

#: Shapes closer than this (m) are touching, not overlapping: tolerance for numbers written
#: to the millimetre that meet exactly (a cylinder resting on the table).
_TOUCH = 1e-9
#: m, how far above what holds it an object may start and still rest on it (its place written
#: to the millimetre).
SUPPORT_GAP = 0.001
#: Object joints are named after the object with these suffixes (``handctl/sim/plant.py``).
OBJECT_JOINT_SUFFIXES = ("_x", "_y", "_rz")


@dataclass(frozen=True)
class LinkSegment:
    """One link at the initial angles: its axis from joint to joint in the hand plane (m)."""

    finger: int  # index in hand.fingers
    name: str  # the joint's name, which its MuJoCo body and geom carry
    x0: float
    y0: float
    x1: float
    y1: float
    radius: float  # m
    z: float  # m, the finger's offset along the joint axes


def link_segments(hand: HandConfig, params: SimParams) -> Iterator[LinkSegment]:
    """Every link at ``params.initial_angles``, finger by finger (planar forward kinematics)."""
    index = 0
    for f, (finger, angles) in enumerate(zip(hand.fingers, params.initial_angles, strict=True)):
        x, y, heading = finger.base_x, finger.base_y, finger.base_angle
        for joint, q in zip(finger.joints, angles, strict=True):
            heading += q
            x1 = x + math.cos(heading) * joint.link_length
            y1 = y + math.sin(heading) * joint.link_length
            yield LinkSegment(f, joint.name, x, y, x1, y1, params.links[index].radius, finger.z)
            x, y = x1, y1
            index += 1


def check_placement(hand: HandConfig, params: SimParams, doc: Doc) -> None:
    """Raise a ``ConfigError`` (``doc`` is the ``sim`` mapping) for a scene that cannot start."""
    _check_names(hand, params, doc)
    links = list(link_segments(hand, params))
    # first: no other overlap of the scene can be put right while a base is in the palm
    _check_bases_off_the_palm(hand, params, links)
    for i, obj in enumerate(params.objects):
        where = f"objects[{i}]"
        if obj.y - obj.radius < params.table_height - _TOUCH:
            doc.fail(
                f"{where}.y",
                f"a centre at least one radius ({obj.radius:g} m) above the "
                f"table top ({params.table_height:g} m)",
                obj.y,
            )
        if obj.y + obj.radius > _TOUCH:
            doc.fail(
                f"{where}.y",
                f"a centre at least one radius ({obj.radius:g} m) below the palm face (y = 0)",
                obj.y,
            )
        for j, other in enumerate(params.objects[:i]):
            gap = _object_gap(obj, other)
            if gap < -_TOUCH:
                doc.fail(
                    f"{where}.x",
                    f"a position not overlapping objects[{j}] "
                    f"({other.name}): {-gap:.4g} m too close",
                    obj.x,
                )
        _check_reach(hand, params, obj, doc, where)
        for link in links:
            gap = _object_link_distance(obj, link) - obj.radius - link.radius
            if gap < -_TOUCH:
                doc.fail(
                    f"{where}.x",
                    f"a position clear of link {link.name} at the initial "
                    f"angles: they overlap by {-gap:.4g} m",
                    obj.x,
                )
    for link in links:
        where = f"initial_angles.{hand.fingers[link.finger].name}"
        inside = link.radius - _segment_box_distance(
            link, params.palm_half_width, params.palm_thickness
        )
        if inside > _TOUCH:
            doc.fail(
                where,
                f"angles that keep every link out of the palm (x within "
                f"±{params.palm_half_width:g} m, y 0..{params.palm_thickness:g} m): "
                f"{link.name} is {inside:.4g} m inside it",
                list(params.initial_angles[link.finger]),
            )
        # a few millimetres are benign (see above); a link whose axis starts more than its
        # radius under the table top is flung out by the contact at the first step, past a
        # joint's limit or into a reading the node's self-check takes for a broken sensor: a
        # fault at tick 0 that says nothing of the scene
        below = params.table_height - min(link.y0, link.y1) - link.radius
        if below > _TOUCH:
            doc.fail(
                where,
                f"angles that keep every link's surface within its diameter "
                f"({2 * link.radius:g} m) of the table top (y = {params.table_height:g} m): "
                f"{link.name} reaches {below + 2 * link.radius:.4g} m into it",
                list(params.initial_angles[link.finger]),
            )
    if params.between_fingers:
        _check_fingers_apart(hand, params, links, doc)


def _check_names(hand: HandConfig, params: SimParams, doc: Doc) -> None:
    # the MuJoCo model names the scene's bodies and geoms so (``world`` is MuJoCo's own
    # body: a joint or object of that name clashed in its XML parser, an error naming a line
    # of XML the user never wrote). A hand config read to run refuses such a joint already
    # (``config.scene_names``); a recording's hand is read with the names it ran with
    taken = scene_names(hand.fingers)
    top = Doc({}, doc.file, "")
    for i, finger in enumerate(hand.fingers):
        for k, joint in enumerate(finger.joints):
            if joint.name in taken:  # the simulation names a link's body and geom after it
                top.fail(
                    f"fingers[{i}].joints[{k}].name",
                    f"a name the simulated hand does "
                    f"not use ({joint.name!r} is {taken[joint.name]})",
                    joint.name,
                )
    taken |= {j.name: f"a link of {f.name}" for f in hand.fingers for j in f.joints}
    for i, obj in enumerate(params.objects):
        for name in (obj.name, *(obj.name + s for s in OBJECT_JOINT_SUFFIXES)):
            if name in taken:
                doc.fail(
                    f"objects[{i}].name", f"a name of its own ({name!r} is {taken[name]})", obj.name
                )
        taken[obj.name] = f"objects[{i}]"
        taken |= {obj.name + s: f"a joint of objects[{i}]" for s in OBJECT_JOINT_SUFFIXES}


def _check_reach(
    hand: HandConfig, params: SimParams, obj: ObjectParams, doc: Doc, where: str
) -> None:
    """Some finger beside the object along z must reach its surface when stretched out."""
    best: tuple[float, str] | None = None
    index = 0
    for finger in hand.fingers:
        radii = [params.links[index + k].radius for k in range(len(finger.joints))]
        index += len(finger.joints)
        if abs(finger.z) > obj.length / 2 + obj.radius + max(radii):
            continue  # passes beside the object's end
        reach = sum(j.link_length for j in finger.joints) + max(radii)
        surface = math.hypot(obj.x - finger.base_x, obj.y - finger.base_y) - obj.radius
        if surface <= reach:
            return
        short = surface - reach
        if best is None or short < best[0]:
            best = (short, finger.name)
    nearest = (
        f"the nearest finger, {best[1]}, is {best[0]:.4g} m short of its surface"
        if best is not None
        else "no finger lies within its length along z"
    )
    doc.fail(f"{where}.x", f"a place within reach of a finger ({nearest})", obj.x)


def _check_fingers_apart(
    hand: HandConfig, params: SimParams, links: list[LinkSegment], doc: Doc
) -> None:
    for i, a in enumerate(links):
        for b in links[i + 1 :]:
            if a.finger == b.finger:
                continue
            planar = _segment_distance(a, b)
            gap = math.hypot(planar, a.z - b.z) - a.radius - b.radius
            if gap < -_TOUCH:
                doc.fail(
                    f"initial_angles.{hand.fingers[b.finger].name}",
                    f"angles that keep the fingers apart (contact.between_fingers is "
                    f"true): {b.name} overlaps {a.name} by {-gap:.4g} m",
                    list(params.initial_angles[b.finger]),
                )


def _point_segment(px: float, py: float, x0: float, y0: float, x1: float, y1: float) -> float:
    dx, dy = x1 - x0, y1 - y0
    length2 = dx * dx + dy * dy
    t = 0.0 if length2 == 0 else max(0.0, min(1.0, ((px - x0) * dx + (py - y0) * dy) / length2))
    return math.hypot(px - (x0 + t * dx), py - (y0 + t * dy))


def _cross(ax: float, ay: float, bx: float, by: float, cx: float, cy: float) -> float:
    return (bx - ax) * (cy - ay) - (by - ay) * (cx - ax)


def _segments_cross(
    a: tuple[float, float, float, float], b: tuple[float, float, float, float]
) -> bool:
    d1 = _cross(*b[:2], *b[2:], *a[:2])
    d2 = _cross(*b[:2], *b[2:], *a[2:])
    d3 = _cross(*a[:2], *a[2:], *b[:2])
    d4 = _cross(*a[:2], *a[2:], *b[2:])
    return d1 * d2 < 0 and d3 * d4 < 0


def _planar_distance(
    a: tuple[float, float, float, float], b: tuple[float, float, float, float]
) -> float:
    """Distance of two segments ``(x0, y0, x1, y1)`` in the plane (0 where they cross)."""
    if _segments_cross(a, b):
        return 0.0
    return min(
        _point_segment(*a[:2], *b),
        _point_segment(*a[2:], *b),
        _point_segment(*b[:2], *a),
        _point_segment(*b[2:], *a),
    )


def _segment_distance(a: LinkSegment, b: LinkSegment) -> float:
    return _planar_distance((a.x0, a.y0, a.x1, a.y1), (b.x0, b.y0, b.x1, b.y1))


def unsupported(hand: HandConfig, params: SimParams) -> list[tuple[int, float]]:
    """The objects that start above the table top with nothing under them, each with how far
    above it (m): under gravity, with no object below it and no link within ``SUPPORT_GAP``.
    Such an object falls at the first step (a scene may mean it to: a small gap keeps it
    from starting in contact), so it rests on the table, not where it was put."""
    if params.gravity == 0.0:  # it stays where it is
        return []
    links = list(link_segments(hand, params))
    on_another = resting_on(params.objects, params.table_height)
    found = []
    for i, obj in enumerate(params.objects):
        above = obj.y - obj.radius - params.table_height
        if above <= SUPPORT_GAP or i in on_another:
            continue
        on_a_link = any(
            _object_link_distance(obj, link) - obj.radius - link.radius <= SUPPORT_GAP
            for link in links
        )
        if not on_a_link:
            found.append((i, above))
    return found


def resting_on(objects: Sequence[ObjectParams], table_height: float) -> dict[int, tuple[int, ...]]:
    """The objects that rest on others: each one's index, with the objects below it within
    ``SUPPORT_GAP`` of its surface, nearest first. One on the table (within ``SUPPORT_GAP``
    of its top) rests on the table, whatever touches it: two cylinders of two radii side by
    side on it are a row, not a stack."""
    out = {}
    for i, obj in enumerate(objects):
        if obj.y - obj.radius - table_height <= SUPPORT_GAP:
            continue
        below = sorted(
            (gap, k)
            for k, other in enumerate(objects)
            if other.y < obj.y and (gap := _object_gap(obj, other)) <= SUPPORT_GAP
        )
        if below:
            out[i] = tuple(k for _, k in below)
    return out


def rest_heights(hand: HandConfig, params: SimParams) -> tuple[float, ...]:
    """m, the centre height each object rests at, which its height above rest is measured
    from (the experiment's lift, replay's, the plan's): where it was put, but on the table
    for one with nothing under it (``unsupported``). Measured from where it had been put,
    an object placed 15 mm up fell at the first step and a lift needed 25 mm to count 10."""
    falling = {i for i, _ in unsupported(hand, params)}
    return tuple(
        params.table_height + o.radius if i in falling else o.y
        for i, o in enumerate(params.objects)
    )


def _object_gap(a: ObjectParams, b: ObjectParams) -> float:
    """m between the two objects' surfaces in the hand plane (negative: they overlap)."""
    return math.hypot(a.x - b.x, a.y - b.y) - a.radius - b.radius


def _object_link_distance(obj: ObjectParams, link: LinkSegment) -> float:
    """Distance of the object's axis (a segment along z) from the link's axis."""
    planar = _point_segment(obj.x, obj.y, link.x0, link.y0, link.x1, link.y1)
    along_z = max(0.0, abs(link.z) - obj.length / 2)
    return math.hypot(planar, along_z)


def _check_bases_off_the_palm(
    hand: HandConfig, params: SimParams, links: list[LinkSegment]
) -> None:
    """A finger whose base is nearer the palm than its first link's radius: the link starts at
    the base, so it overlaps the palm at every angle. Said of the base, which is what to
    move; it was said of the initial angles, which no angle could satisfy (found by an
    outside audit: a middle finger hung from the palm's face at x = 0)."""
    for f, finger in enumerate(hand.fingers):
        first = next((link for link in links if link.finger == f), None)
        if first is None:
            continue
        dx = max(abs(finger.base_x) - params.palm_half_width, 0.0)
        dy = max(-finger.base_y, finger.base_y - params.palm_thickness, 0.0)
        inside = first.radius - math.hypot(dx, dy)
        if inside > _TOUCH:
            raise ConfigError(
                hand.source,
                f"fingers[{f}].base",
                f"a base at least its first link's radius ({first.radius:g} m) from the "
                f"palm (x within ±{params.palm_half_width:g} m, y 0..{params.palm_thickness:g} "
                f"m), since the link starts there: {first.name} is {inside:.4g} m inside the "
                "palm at any angle (below the palm face, y <= "
                f"{-first.radius:g} m, or beside it)",
                f"x {finger.base_x:g} m, y {finger.base_y:g} m",
            )


def _segment_box_distance(link: LinkSegment, half_width: float, thickness: float) -> float:
    """Distance of the link's axis from the palm's cross-section (0 where it enters it)."""
    inside = [
        abs(x) <= half_width and 0.0 <= y <= thickness
        for x, y in ((link.x0, link.y0), (link.x1, link.y1))
    ]
    if any(inside):
        return 0.0
    seg = (link.x0, link.y0, link.x1, link.y1)
    corners = (
        (-half_width, 0.0),
        (half_width, 0.0),
        (half_width, thickness),
        (-half_width, thickness),
    )
    edges = [(*corners[k], *corners[(k + 1) % 4]) for k in range(4)]
    return min(_planar_distance(seg, edge) for edge in edges)
