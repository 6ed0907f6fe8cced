"""The physical hand: a MuJoCo model built from the hand config and its ``sim:`` section.

Everything is planar by construction, as in the paper: all joint axes are +z, the cylinders lie
along z and may only slide in x and y and turn about z. The hand is fixed in the world; the
palm's face is y = 0, the fingers hang from it, and a table lies below.

Choices that matter for what a recipe sees:
- The tendon drive is a torque actuator behind a first-order lag (MuJoCo's exact filter
  dynamics), clipped to the motor's own limit. The force MuJoCo applies through it is the torque
  the tendon transmits to the joint, which is what a TDT sensor measures.
- Contacts are explicit pairs, each with the friction of its kind from the config. Links of
  different fingers collide only when ``sim.contact.between_fingers`` asks for it (fingers side
  by side, or opposing ones that never meet, need no contact test); links of one finger never
  do: neighbours share a joint, and a finger folding onto itself is beyond its stops.
- A cylinder collides as a capsule whose straight part is the cylinder's length, and has a solid
  cylinder's mass and inertia. In this planar scene the two give the same contacts (every finger
  and the palm lie within the straight part; on the table both rest on a line), and MuJoCo
  collides capsules analytically, where a true cylinder takes its general convex test: with a
  grasp in progress that is half the cost of a step.
- The integrator is ``implicitfast``, which treats joint damping implicitly and keeps the light
  distal links stable at a 1 ms step.

Object poses are ground truth, for evaluation and logs only: nothing on the bus carries them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any
from xml.sax.saxutils import quoteattr

import mujoco
import numpy as np

from handctl.arrays import FloatArray
from handctl.config import FingerConfig, HandConfig, JointConfig
from handctl.errors import ConfigError
from handctl.sim.params import LinkParams, SimParams

#: Along z, the palm reaches this far beyond the fingers and the cylinders it must stop (m).
_PALM_MARGIN = 0.005


@dataclass(frozen=True, slots=True)
class ObjectPose:
    """Ground truth of one cylinder: centre (m) and rotation about z (rad)."""

    name: str
    x: float
    y: float
    angle: float


def _f(value: float) -> str:
    return f"{value:.9g}"


def stop_range(joint: JointConfig, margin: float) -> tuple[float, float]:
    """The mechanical stops of a joint: its soft limits widened by ``margin`` on both sides."""
    return joint.angle_min - margin, joint.angle_max + margin


def build_mjcf(hand: HandConfig, params: SimParams) -> str:
    """The MJCF text of the scene; kept separate from ``Plant`` so it can be inspected."""
    p = params
    half_depth = (
        max(
            [
                abs(f.z) + max(link.radius for link in links)
                for f, links in zip(hand.fingers, finger_links(hand, p), strict=True)
            ]
            + [o.length / 2 for o in p.objects]
        )
        + _PALM_MARGIN
    )
    lines = [
        '<mujoco model="handctl_sim">',
        '  <compiler angle="radian" autolimits="true"/>',
        f'  <option timestep="{_f(p.timestep)}" gravity="0 {_f(-p.gravity)} 0" '
        'integrator="implicitfast"/>',
        '  <default><geom contype="0" conaffinity="0"/></default>',
        "  <worldbody>",
        f'    <geom name="table" type="plane" pos="0 {_f(p.table_height)} 0" zaxis="0 1 0" '
        'size="0.4 0.4 0.01"/>',
        '    <body name="palm">',
        f'      <geom name="palm" type="box" pos="0 {_f(p.palm_thickness / 2)} 0" '
        f'size="{_f(p.palm_half_width)} {_f(p.palm_thickness / 2)} {_f(half_depth)}"/>',
        "    </body>",
    ]
    first = 0
    for finger in hand.fingers:
        lines += _finger_xml(finger, params, first)
        first += len(finger.joints)
    for obj in p.objects:
        # A solid cylinder's inertia; the collision shape is a capsule (see the module doc).
        i_z = obj.mass * obj.radius**2 / 2
        i_xy = obj.mass * (3 * obj.radius**2 + obj.length**2) / 12
        lines += [
            f"    <body name={quoteattr(obj.name)}>",
            f'      <joint name={quoteattr(obj.name + "_x")} type="slide" axis="1 0 0"/>',
            f'      <joint name={quoteattr(obj.name + "_y")} type="slide" axis="0 1 0"/>',
            f'      <joint name={quoteattr(obj.name + "_rz")} type="hinge" axis="0 0 1"/>',
            f'      <inertial pos="0 0 0" mass="{_f(obj.mass)}" '
            f'diaginertia="{_f(i_xy)} {_f(i_xy)} {_f(i_z)}"/>',
            f'      <geom name={quoteattr(obj.name)} type="capsule" '
            f'size="{_f(obj.radius)} {_f(obj.length / 2)}"/>',
            "    </body>",
        ]
    lines.append("  </worldbody>")
    lines.append("  <contact>")
    lines += _pair_xml(hand, params)
    lines.append("  </contact>")
    lines.append("  <actuator>")
    for index, joint in enumerate(hand.joints):
        limit = p.motor_tau_max[index]
        lag = p.actuator_lag[index]
        lines.append(
            f"    <general name={quoteattr(joint.name)} joint={quoteattr(joint.name)} "
            f'dyntype="filterexact" dynprm="{_f(lag)}" gaintype="fixed" '
            f'gainprm="1" biastype="none" forcelimited="true" '
            f'forcerange="{_f(-limit)} {_f(limit)}"/>'
        )
    lines.append("  </actuator>")
    lines.append("</mujoco>")
    return "\n".join(lines)


def _finger_xml(finger: FingerConfig, params: SimParams, first: int) -> list[str]:
    """The finger's bodies; ``first`` is the index of its first joint in config order."""
    lines = [
        f"    <body name={quoteattr(finger.name + '_base')} "
        f'pos="{_f(finger.base_x)} {_f(finger.base_y)} {_f(finger.z)}" '
        f'euler="0 0 {_f(finger.base_angle)}">'
    ]
    indent = "      "
    for k, joint in enumerate(finger.joints):
        link = params.links[first + k]
        lo, hi = stop_range(joint, params.stop_margin)
        pos = "0 0 0" if k == 0 else f"{_f(finger.joints[k - 1].link_length)} 0 0"
        lines += [
            f'{indent}<body name={quoteattr(joint.name)} pos="{pos}">',
            f'{indent}  <joint name={quoteattr(joint.name)} type="hinge" axis="0 0 1" '
            f'range="{_f(lo)} {_f(hi)}" damping="{_f(params.damping[first + k])}" '
            f'frictionloss="{_f(params.frictionloss[first + k])}" '
            f'armature="{_f(params.armature[first + k])}"/>',
            f'{indent}  <geom name={quoteattr(joint.name)} type="capsule" '
            f'fromto="0 0 0 {_f(joint.link_length)} 0 0" size="{_f(link.radius)}" '
            f'mass="{_f(link.mass)}"/>',
        ]
        indent += "  "
    for _ in finger.joints:
        indent = indent[:-2]
        lines.append(f"{indent}</body>")
    lines.append("    </body>")
    return lines


def _pair_xml(hand: HandConfig, params: SimParams) -> list[str]:
    fr = params.friction
    solref = f'solref="{_f(params.contact_timeconst)} {_f(params.contact_dampratio)}"'

    def pair(a: str, b: str, mu: float) -> str:
        # condim 3: Coulomb friction in the contact plane only; in a planar scene there is no
        # spin about the normal to resist, and rolling is free, as the paper's model has it.
        return (
            f'    <pair geom1={quoteattr(a)} geom2={quoteattr(b)} condim="3" '
            f'friction="{_f(mu)} {_f(mu)} 0 0 0" {solref}/>'
        )

    links = [j.name for j in hand.joints]
    objects = [o.name for o in params.objects]
    lines = []
    for i, obj in enumerate(objects):
        lines += [pair(link, obj, fr.finger_object) for link in links]
        lines += [pair(obj, other, fr.object_object) for other in objects[i + 1 :]]
        lines.append(pair(obj, "table", fr.object_table))
        lines.append(pair(obj, "palm", fr.object_palm))
    lines += [pair(link, "table", fr.finger_table) for link in links]
    lines += [pair(link, "palm", fr.finger_palm) for link in links]
    if params.between_fingers:
        for f, finger in enumerate(hand.fingers):
            lines += [
                pair(a.name, b.name, params.finger_finger_friction)
                for a in finger.joints
                for other in hand.fingers[f + 1 :]
                for b in other.joints
            ]
    return lines


def finger_links(hand: HandConfig, params: SimParams) -> list[tuple[LinkParams, ...]]:
    """``params.links`` (config order) split finger by finger."""
    out = []
    first = 0
    for finger in hand.fingers:
        out.append(params.links[first : first + len(finger.joints)])
        first += len(finger.joints)
    return out


class Plant:
    """The MuJoCo hand, stepped one 1 ms node tick at a time.

    Arrays handed out (``joint_angles``, ``joint_velocities``, ``transmitted_torques``) are views
    into MuJoCo's state: reading them costs no allocation, and they change on the next ``step``.
    Callers that keep a value must copy it.
    """

    def __init__(self, hand: HandConfig, params: SimParams) -> None:
        self.hand = hand
        self.params = params
        self.xml = build_mjcf(hand, params)
        try:
            self.model: Any = mujoco.MjModel.from_xml_string(self.xml)
        except ValueError as exc:
            if "allocate memory" in str(exc):
                # MuJoCo's own allocation failed (a memory limit on the process): the host's,
                # not the hand config's, which was blamed, exit 2 (found by an outside audit)
                raise MemoryError(f"MuJoCo: {' '.join(str(exc).split())}") from exc
            # parse_sim's bounds keep every scene it accepts buildable; should one still slip
            # through, it is the hand config's numbers, not a crash: MuJoCo's message names
            # the element (a link by its joint's name, an object by its own)
            raise ConfigError(
                hand.source,
                "sim",
                "numbers MuJoCo can build the simulated hand from",
                " ".join(str(exc).split()),
            ) from exc
        self.data: Any = mujoco.MjData(self.model)
        self.n_joints = hand.n_joints
        self._substeps = params.substeps
        m = self.model
        joint_ids = [mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, j.name) for j in hand.joints]
        qadr = [int(m.jnt_qposadr[i]) for i in joint_ids]
        vadr = [int(m.jnt_dofadr[i]) for i in joint_ids]
        # The fingers are built first, so their joints are the first entries of qpos and qvel;
        # relying on it gives contiguous views instead of a gather per read.
        if qadr != list(range(self.n_joints)) or vadr != list(range(self.n_joints)):
            raise RuntimeError("finger joints are expected first in the MuJoCo state")
        self._obj_qadr = [
            int(m.jnt_qposadr[mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, f"{o.name}_x")])
            for o in params.objects
        ]
        self._gain_nominal = m.actuator_gainprm[:, 0].copy()
        self._range_nominal = m.actuator_forcerange.copy()
        self._hold: FloatArray | None = None
        self.reset()

    # -- state ------------------------------------------------------------------------------
    def reset(self) -> None:
        """Back to the configured start: joints at their initial angles, objects at rest."""
        mujoco.mj_resetData(self.model, self.data)
        q = self.data.qpos
        angles = [a for finger in self.params.initial_angles for a in finger]
        q[: self.n_joints] = angles
        for adr, obj in zip(self._obj_qadr, self.params.objects, strict=True):
            q[adr : adr + 3] = (obj.x, obj.y, obj.angle)
        self.model.actuator_gainprm[:, 0] = self._gain_nominal
        self.model.actuator_forcerange[:] = self._range_nominal
        self._hold = None
        mujoco.mj_forward(self.model, self.data)
        self.joint_angles: FloatArray = self.data.qpos[: self.n_joints]
        self.joint_velocities: FloatArray = self.data.qvel[: self.n_joints]
        self.transmitted_torques: FloatArray = self.data.actuator_force
        self._ctrl: FloatArray = self.data.ctrl

    @property
    def time(self) -> float:
        """Simulated time since the last reset (s)."""
        return float(self.data.time)

    def set_torque_commands(self, tau: FloatArray | list[float]) -> None:
        """The torque each motor is asked for (N·m, one per joint in config order)."""
        self._ctrl[:] = tau

    def step(self) -> None:
        """Advance one 1 ms node tick (``params.substeps`` physics steps)."""
        mujoco.mj_step(self.model, self.data, self._substeps)
        if self._hold is not None:
            self._restore_objects()

    # -- objects ----------------------------------------------------------------------------
    def object_poses(self) -> tuple[ObjectPose, ...]:
        """Ground truth: where each cylinder is. For evaluation and logs only."""
        q = self.data.qpos
        return tuple(
            ObjectPose(o.name, float(q[a]), float(q[a + 1]), float(q[a + 2]))
            for o, a in zip(self.params.objects, self._obj_qadr, strict=True)
        )

    def hold_objects(self, hold: bool) -> None:
        """Pin the cylinders where they are (a fixture for tests), or release them."""
        if not hold:
            self._hold = None
            return
        self._hold = np.array([self.data.qpos[a : a + 3] for a in self._obj_qadr])
        self._restore_objects()

    def _restore_objects(self) -> None:
        assert self._hold is not None
        for row, adr in enumerate(self._obj_qadr):
            self.data.qpos[adr : adr + 3] = self._hold[row]
            self.data.qvel[adr : adr + 3] = 0.0

    # -- drive faults -----------------------------------------------------------------------
    def set_tendon_slack(self, joint: int, slack: bool) -> None:
        """A slack tendon transmits nothing: the motor turns, the joint feels no torque."""
        self.model.actuator_gainprm[joint, 0] = 0.0 if slack else self._gain_nominal[joint]

    def set_motor_limit(self, joint: int, limit: float | None) -> None:
        """Lower what the motor can give (N·m), or restore its configured limit with ``None``."""
        if limit is None:
            self.model.actuator_forcerange[joint] = self._range_nominal[joint]
        else:
            self.model.actuator_forcerange[joint] = (-abs(limit), abs(limit))

    # -- geometry helpers (tests, drawings) -------------------------------------------------
    def fingertip(self, finger: int) -> tuple[float, float]:
        """Centre of the rounded tip of a finger's distal link (m, x and y)."""
        last = self.hand.fingers[finger].joints[-1]
        bid = mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_BODY, last.name)
        origin = self.data.xpos[bid]
        axis = self.data.xmat[bid].reshape(3, 3)[:, 0]
        return (
            float(origin[0] + axis[0] * last.link_length),
            float(origin[1] + axis[1] * last.link_length),
        )

    def contact_pairs(self) -> list[tuple[str, str]]:
        """Names of the geoms in contact now (active contacts only)."""
        pairs = []
        for i in range(self.data.ncon):
            con = self.data.contact[i]
            a = mujoco.mj_id2name(self.model, mujoco.mjtObj.mjOBJ_GEOM, int(con.geom1))
            b = mujoco.mj_id2name(self.model, mujoco.mjtObj.mjOBJ_GEOM, int(con.geom2))
            pairs.append((str(a), str(b)))
        return pairs


def gravity_torques(hand: HandConfig, params: SimParams, angles: FloatArray) -> FloatArray:
    """Joint torques gravity exerts on the free-hanging fingers (N·m), from planar statics.

    Written independently of MuJoCo (point masses at the link centres) so that a test can
    check the simulated fingers fall the way this says.
    """
    out = np.zeros(hand.n_joints)
    g = params.gravity
    offset = 0
    for finger in hand.fingers:
        q = angles[offset : offset + len(finger.joints)]
        # positions of joints and link centres in the plane
        heading = finger.base_angle
        x, y = finger.base_x, finger.base_y
        joints_xy = []
        centres = []
        for k, joint in enumerate(finger.joints):
            heading += q[k]
            joints_xy.append((x, y))
            cx = x + math.cos(heading) * joint.link_length / 2
            cy = y + math.sin(heading) * joint.link_length / 2
            centres.append((cx, cy, params.links[offset + k].mass))
            x += math.cos(heading) * joint.link_length
            y += math.sin(heading) * joint.link_length
        for k in range(len(finger.joints)):
            jx, _ = joints_xy[k]
            # force (0, -m g) at each distal centre; torque about z = r_x * F_y
            out[offset + k] = sum(-(cx - jx) * m * g for cx, _, m in centres[k:])
        offset += len(finger.joints)
    return out
