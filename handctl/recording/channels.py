"""The channels of a handctl recording: topic names, their JSON Schemas, and the event kinds.

Every channel carries JSON messages described by a JSON Schema (MCAP ``jsonschema`` schema
encoding, ``json`` message encoding), the pair Foxglove opens without any plug-in and the mcap
Python library reads with nothing but ``json``. Times inside messages are integer nanoseconds on
the loop's clock (``CLOCK_MONOTONIC`` in real time, simulated time in lockstep), as are the MCAP
log times; angles are in rad and torques in N·m, as everywhere in handctl.

``docs/recording.md`` documents the same table for people; a test keeps the two in step.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

from handctl.protocol import NodeState

#: Bumped when a channel changes incompatibly; replay refuses a recording of another version.
FORMAT_VERSION = 1
PROFILE = ""  # no ROS profile: plain JSON channels
SCHEMA_ENCODING = "jsonschema"
MESSAGE_ENCODING = "json"

JOINT_STATE = "/hand/joint_state"
TORQUE = "/control/torque"
SAFETY = "/safety/state"
PHASE = "/recipe/phase"
TIMING = "/loop/timing"
EVENTS = "/events"
CAN_RX = "/can/rx"
CAN_TX = "/can/tx"
OBJECTS = "/sim/objects"
STATS = "/recording/stats"
#: the channels every run writes, whatever its bus and hand: a complete log without one was
#: altered, and its summary would say of it what a run without it would ("faults: none")
CORE_TOPICS = (JOINT_STATE, TORQUE, SAFETY, PHASE, TIMING, EVENTS, CAN_RX, CAN_TX)
#: the topics of which every tick with the hand running writes one message (``TIMING`` has
#: one for every tick)
ACTIVE_TICK_TOPICS = (JOINT_STATE, TORQUE, SAFETY, PHASE)

#: Metadata record names (MCAP metadata: string to string maps).
META_RUN = "handctl.run"
META_HAND = "handctl.hand"
META_RECIPE = "handctl.recipe"
META_VERSIONS = "handctl.versions"
META_SUMMARY = "handctl.summary"
META_END = "handctl.recording_end"
#: ``ended`` of ``META_END`` when the recorder closed the file (not a dead control process).
ENDED_CLOSED = "closed by the recorder"

#: The supervisor's states as ``/safety/state`` writes them (``supervisor.State``'s values; a
#: test keeps the two in step: the recording does not import the runtime)
SAFETY_STATES = ("idle", "enabling", "running", "stopping", "fault_ramp", "faulted")

#: Event kinds on ``/events``.
EVENT_KINDS = ("fault", "state", "phase", "bus", "rejected_frames", "request", "recording")

_INT = {"type": "integer"}
#: a count or a tick: a reader relies on it not being negative (a forged -5 would subtract)
_COUNT = {"type": "integer", "minimum": 0}
_NUM = {"type": "number"}
_STR = {"type": "string"}
_BOOL = {"type": "boolean"}


def _array(item: dict[str, str], description: str) -> dict[str, Any]:
    return {"type": "array", "items": item, "description": description}


def _tick() -> dict[str, Any]:
    return {**_COUNT, "description": "tick number, 0 first (start-up ticks included)"}


def _object(
    title: str, description: str, properties: dict[str, Any], required: list[str]
) -> dict[str, Any]:
    return {
        "$schema": "https://json-schema.org/draft/2020-12/schema",
        "title": title,
        "description": description,
        "type": "object",
        "properties": properties,
        "required": required,
    }


@dataclass(frozen=True)
class Channel:
    topic: str
    schema_name: str
    schema: dict[str, Any]
    rate: str  # for the documentation: how often a message comes


CHANNELS: tuple[Channel, ...] = (
    Channel(
        JOINT_STATE,
        "handctl.JointState",
        _object(
            "handctl.JointState",
            "What the host believed about the joints after the tick's poll.",
            {
                "tick": _tick(),
                "angle_rad": _array(_NUM, "joint angles, config order (rad)"),
                "tdt_torque_nm": _array(_NUM, "TDT joint torques after calibration (N·m)"),
                "feedback_age_ns": _array(
                    _INT, "age of each joint's last valid feedback (ns), -1 before the first"
                ),
                "node_state": _array(
                    _INT,
                    "device state per finger node: "
                    + "".join(f"{s.value} {s.name}, " for s in NodeState)
                    + "-1 unknown",
                ),
                "node_fault_bits": _array(_INT, "device fault bits per finger node"),
            },
            ["tick", "angle_rad", "tdt_torque_nm", "feedback_age_ns"],
        ),
        "every control tick",
    ),
    Channel(
        TORQUE,
        "handctl.Torque",
        _object(
            "handctl.Torque",
            "Torques of one tick: what the recipe asked, what safety let through.",
            {
                "tick": _tick(),
                "desired_nm": _array(_NUM, "recipe runner output (N·m)"),
                "applied_nm": _array(
                    _NUM, "supervisor output, encoded into the command frames (N·m)"
                ),
            },
            ["tick", "desired_nm", "applied_nm"],
        ),
        "every control tick",
    ),
    Channel(
        SAFETY,
        "handctl.SafetyState",
        _object(
            "handctl.SafetyState",
            "The safety supervisor's state after the tick.",
            {
                "tick": _tick(),
                "state": {
                    **_STR,
                    "enum": list(SAFETY_STATES),
                    "description": ", ".join(SAFETY_STATES[:-1]) + " or " + SAFETY_STATES[-1],
                },
                "faults_latched": {**_COUNT, "description": "faults latched so far"},
            },
            ["tick", "state"],
        ),
        "every control tick",
    ),
    Channel(
        PHASE,
        "handctl.RecipePhase",
        _object(
            "handctl.RecipePhase",
            "The recipe phase the tick's desired torques came from.",
            {
                "tick": _tick(),
                "phase": {**_STR, "description": "phase name, end_ramp, or the runner's status"},
            },
            ["tick", "phase"],
        ),
        "every control tick",
    ),
    Channel(
        TIMING,
        "handctl.LoopTiming",
        _object(
            "handctl.LoopTiming",
            "When the tick was due and ran, and what its stages cost.",
            {
                "tick": _tick(),
                "scheduled_ns": {**_INT, "description": "when the tick was due (ns)"},
                "now_ns": {**_INT, "description": "when the loop got it (ns)"},
                "lateness_ns": _INT,
                "missed": {**_COUNT, "description": "ticks missed just before it"},
                "active": {
                    **_BOOL,
                    "description": "false for start-up and shut-down ticks, which only poll",
                },
                "stage_cpu_ns": {
                    "type": "object",
                    "description": "CPU time of each stage (ns)",
                    "properties": {
                        "poll": _COUNT,
                        "recipe": _COUNT,
                        "safety": _COUNT,
                        "send": _COUNT,
                    },
                },
            },
            ["tick", "scheduled_ns", "now_ns", "missed", "active"],
        ),
        "every tick",
    ),
    Channel(
        EVENTS,
        "handctl.Event",
        _object(
            "handctl.Event",
            "Something that happened: a fault, a state or phase change, a bus "
            "event, rejected frames, an operator request, recording drops.",
            {
                "tick": _tick(),
                "kind": {**_STR, "enum": list(EVENT_KINDS)},
                "name": {
                    **_STR,
                    "description": "fault code, new state, new phase, bus event kind, "
                    "reject kind, request (stop, estop, reset)",
                },
                "detail": _STR,
                "category": {**_STR, "description": "fault stop category"},
                "previous": {**_STR, "description": "state or phase before the change"},
                "cause": {**_STR, "description": "supervisor event behind a state change"},
                "count": {
                    **_COUNT,
                    "description": "rejected or dropped records since the last event",
                },
                "bus_time_ns": {**_INT, "description": "when the bus layer saw a bus event (ns)"},
                "id": {
                    **_INT,
                    "description": "the frame id of a bus event of one frame (a remote frame); "
                    "a 29-bit one with 0x80000000 set",
                },
            },
            ["tick", "kind", "name", "detail"],
        ),
        "when something happens",
    ),
    Channel(
        CAN_RX,
        "handctl.CanFrame",
        _object(
            "handctl.CanFrame",
            "One CAN frame, as drained from or handed to the bus.",
            {
                "tick": {**_INT, "description": "the tick whose poll drained it or which sent it"},
                "id": {
                    **_INT,
                    "description": "arbitration id; a 29-bit one with 0x80000000 set",
                },
                "data": {**_STR, "description": "payload, lower-case hex"},
                "bus_time_ns": {
                    **_INT,
                    "description": "received: the adapter's time stamp (its own clock)",
                },
                "ok": {**_BOOL, "description": "sent: false when the bus refused the frame"},
            },
            ["tick", "id", "data"],
        ),
        "every frame received",
    ),
    Channel(CAN_TX, "handctl.CanFrame", {}, "every frame sent (or refused)"),
    Channel(
        OBJECTS,
        "handctl.ObjectPoses",
        _object(
            "handctl.ObjectPoses",
            "Ground truth of the simulated objects (never seen by control).",
            {
                "tick": _tick(),
                "objects": {
                    "type": "array",
                    "items": {
                        "type": "object",
                        "properties": {"name": _STR, "x_m": _NUM, "y_m": _NUM, "angle_rad": _NUM},
                    },
                },
                "line_angle_rad": {
                    **_NUM,
                    "description": "the first pair's line_angle_rad (pairs[0])",
                },
                "pairs": {
                    "type": "array",
                    "description": "the recipe's pairs of objects (each object with the next "
                    "for a recipe that names none)",
                    "items": {
                        "type": "object",
                        "properties": {
                            "name": {**_STR, "description": "first/second object's name"},
                            "line_angle_rad": {
                                **_NUM,
                                "description": "angle of the line from the first object's "
                                "centre to the second's",
                            },
                        },
                    },
                },
            },
            ["tick", "objects"],
        ),
        "every 10 ticks, lockstep simulation only",
    ),
    Channel(
        STATS,
        "handctl.RecordingStats",
        _object(
            "handctl.RecordingStats",
            "The recorder's own accounts: what it wrote and dropped.",
            {
                "tick": {**_INT, "description": "the last tick written"},
                "ticks": _COUNT,
                "frames": _COUNT,
                "events": _COUNT,
                "dropped_ticks": _COUNT,
                "dropped_frames": _COUNT,
                "dropped_events": _COUNT,
                "dropped_poses": _COUNT,
            },
            ["tick", "dropped_ticks", "dropped_frames", "dropped_events"],
        ),
        "every chunk (≤ 50 ms)",
    ),
)

#: The channels ``handctl replay --rerun`` needs.
#: the writer's counts of what it dropped, in ``/recording/stats`` and the end record alike
DROPPED_KEYS = ("dropped_ticks", "dropped_frames", "dropped_events", "dropped_poses")
#: those of the run's own records: not the poses, which a log may lack (the simulated hand's
#: truth, not the run's), so that a run's exit and replay's header count the same records
RUN_DROPPED_KEYS = tuple(key for key in DROPPED_KEYS if key != "dropped_poses")
RERUN_TOPICS = (TIMING, TORQUE, JOINT_STATE, SAFETY, PHASE, CAN_RX, CAN_TX, EVENTS)


def pair_name(first: str, second: str) -> str:
    """A pair of objects as the recording, its replay and the experiment summary name it."""
    return f"{first}/{second}"


def pose_pairs(names: Sequence[str], named: Sequence[tuple[str, str]]) -> list[tuple[int, int]]:
    """The pairs of ``named`` (a recipe's ``pairs``, by object name) as indices into
    ``names`` (the objects whose poses are logged); with none named, each object with the
    next, as a recipe that names no pairs gets them. A pair of an object not logged is left
    out: there is no pose to measure its line by."""
    if not named:
        return [(i, i + 1) for i in range(len(names) - 1)]
    return [(names.index(a), names.index(b)) for a, b in named if a in names and b in names]


def schema_of(channel: Channel) -> dict[str, Any]:
    """The JSON Schema of a channel (``/can/tx`` shares ``/can/rx``'s)."""
    if channel.schema:
        return channel.schema
    return next(c.schema for c in CHANNELS if c.schema_name == channel.schema_name and c.schema)
