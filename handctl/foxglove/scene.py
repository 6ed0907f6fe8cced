"""The hand, the table and the objects as a Foxglove 3D scene.

Everything handctl drives is planar (joint axes along +z, see ``handctl.sim.plant``), so the
scene is the hand plane seen in 3D: frame ``world`` has x to the right, y up and z out of the
hand plane, the palm's face at y = 0. A link is drawn as a capsule (a cylinder with a sphere at
each end) from its joint to the next; ``FrameTransforms`` give the same chain as a tree
(``world`` -> ``<finger>_base`` -> ``<joint>`` -> ...), each joint's frame at its axis with x along
its link, as RViz's TF tree would. The geometry comes from the hand config (and its ``sim:``
section when there is one), so any hand handctl can drive is drawn, not one built in.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

from foxglove.messages import (
    Color,
    CubePrimitive,
    CylinderPrimitive,
    FrameTransform,
    FrameTransforms,
    KeyValuePair,
    Pose,
    Quaternion,
    SceneEntity,
    SceneEntityDeletion,
    SceneEntityDeletionType,
    SceneUpdate,
    SpherePrimitive,
    Timestamp,
    Vector3,
)

from handctl.config import HandConfig
from handctl.errors import ConfigError

WORLD = "world"
#: Used for a link or an object the config gives no thickness or length for (m).
DEFAULT_LINK_RADIUS = 0.006
DEFAULT_OBJECT_LENGTH = 0.10

_LINK = Color(r=0.55, g=0.62, b=0.72, a=1.0)
_PALM = Color(r=0.40, g=0.40, b=0.45, a=1.0)
_TABLE = Color(r=0.55, g=0.45, b=0.35, a=1.0)
_TRUE = Color(r=0.95, g=0.55, b=0.15, a=1.0)
#: The estimate is drawn over the truth, translucent, so that both stay visible.
_ESTIMATE = Color(r=0.20, g=0.80, b=0.45, a=0.35)


@dataclass(frozen=True)
class ObjectShape:
    name: str
    radius: float  # m
    length: float  # m, along z


#: m, the least half side of the drawn table, and how many times the hand's reach (from the
#: palm's centre to the farthest fingertip or object at the start) it spans at least
TABLE_HALF_SIDE_MIN_M = 1.0
TABLE_REACHES = 10.0


@dataclass(frozen=True)
class Scenery:
    """What does not move: the palm box and the table top (absent for a hand without ``sim:``)."""

    palm_half_width: float  # m
    palm_thickness: float  # m
    palm_half_depth: float  # m, along z
    table_height: float | None  # m, y of the table top
    #: m, half the drawn table's side. The simulated table is a plane without end, and a
    #: fixed 0.4 m square left a long finger, or an object pushed away, over its edge and
    #: resting on nothing (found by an outside audit): the hand's reach many times over
    table_half_side: float = 0.2


def timestamp(ns: int) -> Timestamp:
    return Timestamp(sec=ns // 1_000_000_000, nsec=ns % 1_000_000_000)


def _yaw(angle: float) -> Quaternion:
    return Quaternion(x=0.0, y=0.0, z=math.sin(angle / 2), w=math.cos(angle / 2))


def _along(angle: float) -> Quaternion:
    """The rotation that turns a primitive's z axis (a cylinder's axis) into the in-plane
    direction ``angle``: a quarter turn about y (z onto x), then ``angle`` about z."""
    c, s = math.cos(angle / 2), math.sin(angle / 2)
    h = math.sqrt(0.5)
    # q_z(angle) * q_y(pi/2)
    return Quaternion(x=-s * h, y=c * h, z=s * h, w=c * h)


def _pose(x: float, y: float, z: float, orientation: Quaternion | None = None) -> Pose:
    return Pose(
        position=Vector3(x=x, y=y, z=z),
        orientation=orientation or Quaternion(x=0.0, y=0.0, z=0.0, w=1.0),
    )


class HandScene:
    """Builds the scene and the transforms of one hand from joint angles and object poses."""

    def __init__(
        self,
        hand: HandConfig,
        objects: Sequence[ObjectShape] = (),
        estimated: Sequence[ObjectShape] = (),
    ) -> None:
        self.hand = hand
        self.objects = tuple(objects)
        self.estimated = tuple(estimated)
        self.scenery: Scenery | None = None
        sim_radii: tuple[float, ...] = ()
        params = None
        if hand.sim:
            from handctl.sim.params import parse_sim

            try:
                params = parse_sim(hand)
            except ConfigError:  # a view is no place to refuse a config: drawn without it
                params = None
        if params is not None:
            sim_radii = tuple(link.radius for link in params.links)  # config order
        flat = [
            sim_radii[i] if sim_radii else (j.half_thickness or DEFAULT_LINK_RADIUS)
            for i, j in enumerate(hand.joints)
        ]
        self.link_radius: list[list[float]] = []
        for f in hand.fingers:
            self.link_radius.append(flat[: len(f.joints)])
            flat = flat[len(f.joints) :]
        if params is not None:
            widest = max((r for radii in self.link_radius for r in radii), default=0.0)
            half_depth = (
                max(
                    [abs(f.z) + widest for f in hand.fingers]
                    + [o.length / 2 for o in params.objects]
                )
                + 0.005
            )
            reach = max(
                [abs(f.base_x) + sum(j.link_length for j in f.joints) for f in hand.fingers]
                + [abs(o.x) + o.radius for o in params.objects]
            )
            self.scenery = Scenery(
                params.palm_half_width,
                params.palm_thickness,
                half_depth,
                params.table_height,
                max(TABLE_HALF_SIDE_MIN_M, TABLE_REACHES * reach),
            )

    # -- kinematics -----------------------------------------------------------------------
    def links(
        self, angles: Sequence[float]
    ) -> list[tuple[str, float, float, float, float, float, float]]:
        """Each link as ``(joint name, x, y, z, direction, length, radius)``: its joint axis
        in the hand plane and the direction it points (rad)."""
        out = []
        i = 0
        for f, finger in enumerate(self.hand.fingers):
            x, y, heading = finger.base_x, finger.base_y, finger.base_angle
            for k, joint in enumerate(finger.joints):
                heading += angles[i] if math.isfinite(angles[i]) else 0.0
                out.append(
                    (joint.name, x, y, finger.z, heading, joint.link_length, self.link_radius[f][k])
                )
                x += joint.link_length * math.cos(heading)
                y += joint.link_length * math.sin(heading)
                i += 1
        return out

    def transforms(self, t_ns: int, angles: Sequence[float]) -> FrameTransforms:
        stamp = timestamp(t_ns)
        out = []
        i = 0
        for finger in self.hand.fingers:
            base = f"{finger.name}_base"
            out.append(
                FrameTransform(
                    timestamp=stamp,
                    parent_frame_id=WORLD,
                    child_frame_id=base,
                    translation=Vector3(x=finger.base_x, y=finger.base_y, z=finger.z),
                    rotation=_yaw(finger.base_angle),
                )
            )
            parent, offset = base, 0.0
            for joint in finger.joints:
                q = angles[i] if math.isfinite(angles[i]) else 0.0
                out.append(
                    FrameTransform(
                        timestamp=stamp,
                        parent_frame_id=parent,
                        child_frame_id=joint.name,
                        translation=Vector3(x=offset, y=0.0, z=0.0),
                        rotation=_yaw(q),
                    )
                )
                parent, offset = joint.name, joint.link_length
                i += 1
        return FrameTransforms(transforms=out)

    # -- the scene ------------------------------------------------------------------------
    def update(
        self,
        t_ns: int,
        angles: Sequence[float],
        true_poses: Sequence[tuple[float, float, float]] | None,
        estimates: Sequence[tuple[float, float]] | None,
    ) -> SceneUpdate:
        """The whole scene at ``t_ns``; an estimate that is not valid (NaN) is deleted, so a
        lost track disappears instead of staying where it was last seen."""
        stamp = timestamp(t_ns)
        entities = [self._link(stamp, *link) for link in self.links(angles)]
        if self.scenery is not None:
            entities += self._scenery(stamp, self.scenery)
        deletions = []
        if true_poses is not None:
            for shape, (x, y, angle) in zip(self.objects, true_poses, strict=False):
                if math.isfinite(x) and math.isfinite(y):
                    entities.append(
                        self._object(
                            stamp,
                            f"object/{shape.name}",
                            shape,
                            x,
                            y,
                            angle,
                            _TRUE,
                            "simulated (true)",
                        )
                    )
        if estimates is not None:
            for shape, (x, y) in zip(self.estimated, estimates, strict=False):
                ident = f"estimate/{shape.name}"
                if math.isfinite(x) and math.isfinite(y):
                    entities.append(
                        self._object(
                            stamp,
                            ident,
                            shape,
                            x,
                            y,
                            0.0,
                            _ESTIMATE,
                            "estimated from the joint angles",
                        )
                    )
                else:
                    deletions.append(
                        SceneEntityDeletion(
                            timestamp=stamp, type=SceneEntityDeletionType.MatchingId, id=ident
                        )
                    )
        return SceneUpdate(deletions=deletions, entities=entities)

    def _link(
        self,
        stamp: Timestamp,
        name: str,
        x: float,
        y: float,
        z: float,
        heading: float,
        length: float,
        radius: float,
    ) -> SceneEntity:
        c, s = math.cos(heading), math.sin(heading)
        d = 2 * radius
        mid = _pose(x + c * length / 2, y + s * length / 2, z, _along(heading))
        return SceneEntity(
            timestamp=stamp,
            frame_id=WORLD,
            id=f"link/{name}",
            cylinders=[
                CylinderPrimitive(
                    pose=mid,
                    size=Vector3(x=d, y=d, z=length),
                    bottom_scale=1.0,
                    top_scale=1.0,
                    color=_LINK,
                )
            ],
            spheres=[
                SpherePrimitive(pose=_pose(px, py, z), size=Vector3(x=d, y=d, z=d), color=_LINK)
                for px, py in ((x, y), (x + c * length, y + s * length))
            ],
            metadata=[KeyValuePair(key="joint", value=name)],
        )

    def _scenery(self, stamp: Timestamp, sc: Scenery) -> list[SceneEntity]:
        out = [
            SceneEntity(
                timestamp=stamp,
                frame_id=WORLD,
                id="palm",
                cubes=[
                    CubePrimitive(
                        pose=_pose(0.0, sc.palm_thickness / 2, 0.0),
                        size=Vector3(
                            x=2 * sc.palm_half_width, y=sc.palm_thickness, z=2 * sc.palm_half_depth
                        ),
                        color=_PALM,
                    )
                ],
            )
        ]
        if sc.table_height is not None:
            thickness = 0.005
            out.append(
                SceneEntity(
                    timestamp=stamp,
                    frame_id=WORLD,
                    id="table",
                    cubes=[
                        CubePrimitive(
                            pose=_pose(0.0, sc.table_height - thickness / 2, 0.0),
                            size=Vector3(
                                x=2 * sc.table_half_side, y=thickness, z=2 * sc.table_half_side
                            ),
                            color=_TABLE,
                        )
                    ],
                )
            )
        return out

    def _object(
        self,
        stamp: Timestamp,
        ident: str,
        shape: ObjectShape,
        x: float,
        y: float,
        angle: float,
        color: Color,
        source: str,
    ) -> SceneEntity:
        d = 2 * shape.radius
        return SceneEntity(
            timestamp=stamp,
            frame_id=WORLD,
            id=ident,
            cylinders=[
                CylinderPrimitive(
                    pose=_pose(x, y, 0.0, _yaw(angle)),
                    size=Vector3(x=d, y=d, z=shape.length),
                    bottom_scale=1.0,
                    top_scale=1.0,
                    color=color,
                )
            ],
            metadata=[
                KeyValuePair(key="object", value=shape.name),
                KeyValuePair(key="source", value=source),
            ],
        )
