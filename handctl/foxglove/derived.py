"""Channels for Foxglove, derived in the writer process from the numbers it already records.

The loop records raw numbers (``handctl.recording``); here they become what Foxglove's panels
read without help: a ``foxglove.SceneUpdate`` of the hand and the objects, ``FrameTransforms``
of the finger links, ``foxglove.Log`` for events, the joint state and torques under the
joints' names, and the command and feedback frames decoded into their signals. None of it is
computed in the 1 kHz loop; the recorded channels a replay or re-run reads are unchanged.

The well-known schemas are the maintained SDK's (``foxglove-sdk``: its message classes and
their protobuf encoding); handctl's own derived channels are JSON with a JSON Schema, like the
recorded ones. The geometry comes from the hand config and the recipe in the recording's
metadata, so the writer needs nothing the loop does not already hand it.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Protocol

import orjson
from foxglove.messages import FrameTransforms, Log, LogLevel, SceneUpdate

from handctl.config import CAN_ID_KINDS, HandConfig, parse_hand
from handctl.foxglove.scene import DEFAULT_OBJECT_LENGTH, HandScene, ObjectShape, timestamp
from handctl.hand_protocol import ESTOP_ID, protocol_for
from handctl.online.estimator import ObjectEstimator
from handctl.protocol import Layout, parse_protocol
from handctl.protocol import Protocol as Wire
from handctl.recording import channels as ch
from handctl.schema import parse_yaml

SCENE = "/foxglove/scene"
TRANSFORMS = "/foxglove/tf"
LOG = "/foxglove/log"
JOINTS = "/hand/joints"
RX_DECODED = "/can/rx/decoded"
TX_DECODED = "/can/tx/decoded"
#: Scene and transforms every this many control ticks (50 Hz at 1 kHz): enough for the eye,
#: and a scene is some 3 kB.
SCENE_EVERY = 20

_KIND_MESSAGES = {
    "node_command": "NodeCommand",
    "torque_command": "TorqueCommand",
    "feedback": "Feedback",
    "status": "Status",
    "heartbeat": "Heartbeat",
}
#: Signals that carry one value per joint of the finger, numbered from 1, and the key they
#: get under the joint's name.
_PER_JOINT = {"Torque": "torque", "Angle": "angle"}


@dataclass(frozen=True)
class DerivedChannel:
    topic: str
    schema_name: str
    schema_encoding: str  # "protobuf" or "jsonschema"
    schema_data: bytes
    message_encoding: str  # "protobuf" or "json"


def _well_known(topic: str, message: type[SceneUpdate | FrameTransforms | Log]) -> DerivedChannel:
    schema = message.get_schema()
    return DerivedChannel(topic, schema.name, schema.encoding, bytes(schema.data), "protobuf")


def _json(topic: str, name: str, schema: dict[str, Any]) -> DerivedChannel:
    return DerivedChannel(
        topic,
        name,
        ch.SCHEMA_ENCODING,
        orjson.dumps({"title": name, **schema}),
        ch.MESSAGE_ENCODING,
    )


_NUMBER = {"type": ["number", "null"]}


def joints_schema(joints: Sequence[str]) -> dict[str, Any]:
    per_joint = {
        "type": "object",
        "properties": {
            "angle_rad": _NUMBER,
            "tdt_torque_nm": _NUMBER,
            "desired_nm": _NUMBER,
            "applied_nm": _NUMBER,
            "tau_max_nm": _NUMBER,
        },
    }
    return {
        "type": "object",
        "properties": {"tick": {"type": "integer"}, **{name: per_joint for name in joints}},
    }


_DECODED_SCHEMA = {
    "type": "object",
    "properties": {
        "tick": {"type": "integer"},
        "id": {"type": "integer"},
        "message": {"type": "string"},
        "finger": {"type": "string"},
        "counter": {"type": "integer"},
        "crc_ok": {"type": "boolean"},
        "signals": {"type": "object", "additionalProperties": _NUMBER},
        "joints": {
            "type": "object",
            "additionalProperties": {"type": "object", "additionalProperties": _NUMBER},
        },
    },
}


@dataclass(frozen=True)
class _FrameKind:
    layout: Layout
    finger: str
    #: (signal index, joint name, key) of each per-joint signal, worked out once
    slots: tuple[tuple[int, str, str], ...]
    others: tuple[tuple[int, str], ...]  # (index, name) of the rest


def _frame_kind(layout: Layout, finger: str, joints: Sequence[str]) -> _FrameKind:
    slots, others = [], []
    for i, signal in enumerate(layout.signal_names):
        stem = signal.rstrip("0123456789")
        number = signal[len(stem) :]
        if stem in _PER_JOINT and number and 0 < int(number) <= len(joints):
            slots.append((i, joints[int(number) - 1], _PER_JOINT[stem]))
        else:
            others.append((i, signal))
    return _FrameKind(layout, finger, tuple(slots), tuple(others))


class Emit(Protocol):
    """Where the derived messages go: ``key`` tells apart what the live view samples
    separately on one topic (a frame's id)."""

    def __call__(self, topic: str, log_time: int, data: bytes, key: int = 0) -> None: ...


class Derived:
    """Fed by the writer as it drains the rings; calls ``emit(topic, log_time, payload)``."""

    def __init__(
        self,
        hand: HandConfig,
        estimated: Sequence[ObjectShape],
        true_objects: Sequence[ObjectShape],
        estimator: ObjectEstimator | None,
        emit: Emit,
        protocol: Wire | None = None,
    ) -> None:
        self.hand = hand
        self.joints = hand.joint_names
        self.tau_max = [j.tau_max for j in hand.joints]
        self.scene = HandScene(hand, true_objects, estimated)
        self.estimator = estimator
        self.emit = emit
        self.channels = [
            _well_known(SCENE, SceneUpdate),
            _well_known(TRANSFORMS, FrameTransforms),
            _well_known(LOG, Log),
            _json(JOINTS, "handctl.Joints", joints_schema(self.joints)),
            _json(RX_DECODED, "handctl.DecodedFrame", _DECODED_SCHEMA),
            _json(TX_DECODED, "handctl.DecodedFrame", _DECODED_SCHEMA),
        ]
        protocol = protocol_for(hand) if protocol is None else protocol
        self.frames: dict[int, _FrameKind] = {}
        for finger in hand.fingers:
            ids = finger.can_ids.as_dict()
            for kind in CAN_ID_KINDS:
                layout = protocol.by_name.get(f"{_KIND_MESSAGES[kind]}_{finger.node_id}")
                if layout is not None:
                    self.frames[ids[kind]] = _frame_kind(
                        layout, finger.name, [j.name for j in finger.joints]
                    )
        estop = protocol.by_name.get("EStop")
        if estop is not None:
            self.frames[ESTOP_ID] = _frame_kind(estop, "", [])
        self.true_poses: list[tuple[float, float, float]] | None = None
        self._poses: deque[tuple[int, list[tuple[float, float, float]]]] = deque()
        self.estimates: list[tuple[float, float]] | None = None
        self.control_ticks = 0

    @classmethod
    def from_metadata(cls, metadata: dict[str, dict[str, Any]], emit: Emit) -> Derived:
        """From the recording's metadata records: the hand config, the recipe, the run."""
        from handctl.online.recipes.loader import parse_recipe

        hand_doc = metadata.get(ch.META_HAND, {}).get("yaml")
        if not hand_doc:
            raise ValueError(
                f"metadata {ch.META_HAND}.yaml: expected the hand config, found nothing"
            )
        # the DBC the run spoke: one given with --dbc numbers a hand's frames otherwise than
        # the generated one, and the hand read without it was refused (no channels at all)
        dbc = metadata.get(ch.META_HAND, {}).get("dbc")
        protocol = parse_protocol(str(dbc), "the recorded DBC") if dbc else None
        hand = parse_hand(parse_yaml(str(hand_doc), "the recorded hand config"), protocol)
        recipe_doc = metadata.get(ch.META_RECIPE, {}).get("yaml")
        recipe_objects = []
        if recipe_doc:
            recipe = parse_recipe(
                parse_yaml(str(recipe_doc), "the recorded recipe"), hand, as_recorded=True
            )
            recipe_objects = list(recipe.objects)
        lengths: dict[str, float] = {}
        true_objects: list[ObjectShape] = []
        if hand.sim:
            from handctl.errors import ConfigError
            from handctl.sim.params import parse_sim

            try:
                params = parse_sim(hand)
            except ConfigError:
                params = None
            if params is not None:
                true_objects = [ObjectShape(o.name, o.radius, o.length) for o in params.objects]
                lengths = {o.name: o.length for o in params.objects}
        estimated = [
            ObjectShape(o.name, o.radius, lengths.get(o.name, DEFAULT_OBJECT_LENGTH))
            for o in recipe_objects
        ]
        estimator = None
        if recipe_objects:
            # As the session sets one up for such a recipe. The estimator is a function of
            # the angles it was fed, tick by tick (the re-run relies on it): fed the same
            # recorded angles here, it gives the loop's estimates without the loop's cost.
            estimator = ObjectEstimator(hand, recipe_objects, recipe.pairs)
        return cls(hand, estimated, true_objects, estimator, emit, protocol)

    # -- what the writer feeds --------------------------------------------------------------
    def tick(
        self,
        t_ns: int,
        tick: int,
        angle: Sequence[float],
        tdt: Sequence[float],
        desired: Sequence[float],
        applied: Sequence[float],
        estimating: bool,
    ) -> None:
        """One control tick's numbers; ``estimating``: the loop ran its estimator this tick
        (the supervisor running and the recipe not done)."""
        message: dict[str, Any] = {"tick": tick}
        for i, name in enumerate(self.joints):
            message[name] = {
                "angle_rad": angle[i],
                "tdt_torque_nm": tdt[i],
                "desired_nm": desired[i],
                "applied_nm": applied[i],
                "tau_max_nm": self.tau_max[i],
            }
        self.emit(JOINTS, t_ns, orjson.dumps(message))
        if self.estimator is not None and estimating:
            est = self.estimator(angle)
            self.estimates = self.estimator.positions(est)
        if self.control_ticks % SCENE_EVERY == 0:
            self.emit(
                SCENE,
                t_ns,
                self.scene.update(t_ns, angle, self._truth_at(t_ns), self.estimates).encode(),
            )
            self.emit(TRANSFORMS, t_ns, self.scene.transforms(t_ns, angle).encode())
        self.control_ticks += 1

    def poses(self, t_ns: int, values: Sequence[float]) -> None:
        """The simulated objects' true poses, ``(x, y, angle)`` flattened. The writer may
        drain poses a few ticks ahead of the ticks' rows: they wait here for their tick."""
        self._poses.append(
            (
                t_ns,
                [(values[i], values[i + 1], values[i + 2]) for i in range(0, len(values) - 2, 3)],
            )
        )

    def _truth_at(self, t_ns: int) -> list[tuple[float, float, float]] | None:
        """The newest true poses not after ``t_ns``."""
        queue = self._poses
        while queue and queue[0][0] <= t_ns:
            self.true_poses = queue.popleft()[1]
        return self.true_poses

    def event(self, t_ns: int, payload: dict[str, Any]) -> None:
        kind, name = str(payload.get("kind", "")), str(payload.get("name", ""))
        detail = str(payload.get("detail", ""))
        level = LogLevel.Info
        if kind == "fault":
            level = LogLevel.Error
        elif (
            kind in ("bus", "rejected_frames", "recording")
            or (kind == "state" and name in ("fault_ramp", "faulted"))
            or (kind == "request" and name == "estop")
        ):
            level = LogLevel.Warning
        text = f"tick {payload.get('tick')}: {kind} {name}" + (f": {detail}" if detail else "")
        self.emit(
            LOG,
            t_ns,
            Log(
                timestamp=timestamp(t_ns), level=level, message=text, name=f"handctl.{kind}"
            ).encode(),
        )

    def frame(self, t_ns: int, tick: int, received: bool, frame_id: int, data: bytes) -> None:
        kind = self.frames.get(frame_id)
        if kind is None or len(data) != kind.layout.length:
            return
        layout = kind.layout
        counter, values = layout.decode(data)
        joints: dict[str, dict[str, float]] = {}
        for i, joint, key in kind.slots:
            slot = joints.get(joint)
            if slot is None:
                joints[joint] = slot = {}
            slot[key] = values[i]
        message = {
            "tick": tick,
            "id": frame_id,
            "message": layout.name,
            "finger": kind.finger,
            "counter": counter,
            "crc_ok": layout.crc_ok(data),
            "signals": {name: values[i] for i, name in kind.others},
            "joints": joints,
        }
        self.emit(RX_DECODED if received else TX_DECODED, t_ns, orjson.dumps(message), frame_id)
