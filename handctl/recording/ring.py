"""The shared-memory rings between the loop and the writer process.

The loop copies each tick's numbers into preallocated rows of a memory block both processes
map, and moves a head counter on; the writer copies rows out behind it and moves a tail
counter. Nothing is pickled, no thread runs in the control process, and a row is visible to
the writer the moment its head moves, so when the control process dies the writer still has
everything published up to that tick.

Four single-producer, single-consumer rings share the block: tick rows (integers and floats),
CAN frames, events (short UTF-8 texts) and object poses. A ring that is full drops the record
and counts it in the control words; the writer records the counts.

Each counter is an aligned 8-byte word written by one side only, so the other side never
sees it torn; on x86-64 stores are seen in program order, so a row is complete before its
head moves. The writer also re-reads nothing it has released.
"""

from __future__ import annotations

import mmap
import struct
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from handctl.arrays import FloatArray
from handctl.online.tickstats import STAGES

# Control words (int64).
TICK_HEAD, TICK_TAIL = 0, 1
FRAME_HEAD, FRAME_TAIL = 2, 3
EVENT_HEAD, EVENT_TAIL = 4, 5
POSE_HEAD, POSE_TAIL = 6, 7
DROPPED_TICKS, DROPPED_FRAMES, DROPPED_EVENTS, DROPPED_POSES = 8, 9, 10, 11
CLOSED = 12  # 1: the loop side closed the recorder on purpose
CTL_WORDS = 16
#: the writer's exit status when the live view's port cannot be bound, which the control
#: process says as bad input (``--live``), the previous log left as it was
LIVE_REFUSED = 3

# Tick row, integer part: these columns, then node state and node fault bits per node, then
# feedback_ns per joint. The columns and the node words are all plain ints, so the loop packs
# them with one ``struct.pack_into``; feedback_ns is a numpy vector, copied as a buffer.
I_TICK, I_SCHEDULED, I_NOW, I_MISSED, I_ACTIVE = 0, 1, 2, 3, 4
I_STAGES = 5  # poll, recipe, safety, send
N_STAGES = 4
#: The names of those columns: the first loop stages, whose places never change.
RECORDED_STAGES = STAGES[:N_STAGES]
I_STATE, I_PHASE, I_FAULTS = 9, 10, 11
I_NODES = 12
# Tick row, float part: angle, tdt, desired, applied, n_joints each.

# Frame rows, FRAME_ROW bytes each, in blocks that keep the order the frames were on the bus:
# - a drain's received frames: a head row (TAP_RX, t_ns, tick, count), then ``count`` rows laid
#   out as the bus's ``Frame`` tuple (arbitration id, data, bus time, is_fd), so that the loop
#   copies a tick's drains and sent frames with one ``struct.pack_into`` of their fields;
# - a sent frame: one row (direction: TAP_TX or TAP_TX_FAILED, t_ns, tick, arbitration id,
#   data), as the bus's tap notes it.
# Data is a Pascal string: its length byte, then up to FRAME_BYTES bytes.
FRAME_BYTES = 64  # CAN-FD's largest payload
FRAME_ROW = 104
_DATA = f"{FRAME_BYTES + 1}p"


def _frame_row(fields: str) -> str:
    """A frame row's ``struct`` format (little-endian, unaligned): ``fields`` padded to
    FRAME_ROW bytes."""
    return fields + f"{FRAME_ROW - struct.calcsize('<' + fields)}x"


RX_HEAD_ROW = _frame_row("qqqq")
RX_FRAME_ROW = _frame_row(f"q{_DATA}q?")
TX_FRAME_ROW = _frame_row(f"qqqq{_DATA}")

# Event row: t_ns, tick, kind, length of the text; the text apart.
E_T, E_TICK, E_KIND, E_LEN = 0, 1, 2, 3
EVENT_INTS = 4
EVENT_BYTES = 480
#: Fields of an event's text are joined with the ASCII unit separator.
SEP = "\x1f"

# Event kinds in the ring; INTERN tells the writer a new string id (phase names).
EV_FAULT, EV_STATE, EV_PHASE, EV_BUS, EV_REJECT, EV_REQUEST, EV_INTERN = 1, 2, 3, 4, 5, 6, 7
RING_EVENT_KINDS = {
    EV_FAULT: "fault",
    EV_STATE: "state",
    EV_PHASE: "phase",
    EV_BUS: "bus",
    EV_REJECT: "rejected_frames",
    EV_REQUEST: "request",
}

# Pose row: tick, t_ns (int64); then x, y, angle per object (float64), side by side in one
# row of 8-byte words, so that the loop writes a row with one ``struct.pack_into``.
POSE_INTS = 2

IntArray = npt.NDArray[np.int64]
ByteArray = npt.NDArray[np.uint8]


@dataclass(frozen=True)
class RingLayout:
    """Sizes of the rings; capacities are powers of two so an index is a mask away."""

    n_joints: int
    n_nodes: int
    n_objects: int = 0
    tick_capacity: int = 1 << 13  # 8 s at 1 kHz
    frame_capacity: int = 1 << 16  # rows: about 10 s of a 9-joint hand's traffic
    event_capacity: int = 1 << 12
    pose_capacity: int = 1 << 10

    def __post_init__(self) -> None:
        for name in ("tick_capacity", "frame_capacity", "event_capacity", "pose_capacity"):
            value = getattr(self, name)
            if value <= 0 or value & (value - 1):
                raise ValueError(f"{name} must be a power of two, not {value}")

    @property
    def tick_ints(self) -> int:
        return I_NODES + 2 * self.n_nodes + self.n_joints

    @property
    def i_feedback(self) -> int:
        """Where a tick row's feedback_ns column starts (after the node words)."""
        return I_NODES + 2 * self.n_nodes

    @property
    def tick_floats(self) -> int:
        return 4 * self.n_joints

    @property
    def pose_words(self) -> int:
        """A pose row's 8-byte words: its integers, then three floats per object (at least
        one, so that a run without objects still has a well-formed ring)."""
        return POSE_INTS + max(1, 3 * self.n_objects)

    def _sizes(self) -> list[tuple[str, tuple[int, ...], type]]:
        return [
            ("ctl", (CTL_WORDS,), np.int64),
            ("tick_i", (self.tick_capacity, self.tick_ints), np.int64),
            ("tick_f", (self.tick_capacity, self.tick_floats), np.float64),
            ("frame", (self.frame_capacity, FRAME_ROW), np.uint8),
            ("event_i", (self.event_capacity, EVENT_INTS), np.int64),
            ("event_d", (self.event_capacity, EVENT_BYTES), np.uint8),
            ("pose", (self.pose_capacity, self.pose_words), np.int64),
        ]

    @property
    def size(self) -> int:
        return sum(_nbytes(shape, dtype) for _, shape, dtype in self._sizes())

    def as_dict(self) -> dict[str, int]:
        return asdict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> RingLayout:
        return cls(**{k: int(v) for k, v in data.items()})


def _nbytes(shape: tuple[int, ...], dtype: type) -> int:
    return int(np.prod(shape)) * np.dtype(dtype).itemsize


class Rings:
    """Numpy views of every part of the block; both sides build the same views."""

    def __init__(self, layout: RingLayout, buffer: mmap.mmap) -> None:
        self.layout = layout
        self.buffer = buffer
        views: dict[str, Any] = {}
        #: Byte offset of each part in the block, for ``struct.pack_into`` on the loop side.
        self.offsets: dict[str, int] = {}
        offset = 0
        for name, shape, dtype in layout._sizes():
            views[name] = np.ndarray(shape, dtype=dtype, buffer=buffer, offset=offset)
            self.offsets[name] = offset
            offset += _nbytes(shape, dtype)
        self.ctl: IntArray = views["ctl"]
        self.tick_i: IntArray = views["tick_i"]
        self.tick_f: FloatArray = views["tick_f"]
        self.frame: ByteArray = views["frame"]
        self.event_i: IntArray = views["event_i"]
        self.event_d: ByteArray = views["event_d"]
        # The pose rows' two parts, as strided views of the one block of rows.
        rows = views["pose"]
        self.pose: IntArray = rows
        self.pose_i: IntArray = rows[:, :POSE_INTS]
        self.pose_f: FloatArray = np.ndarray(
            (layout.pose_capacity, layout.pose_words - POSE_INTS),
            dtype=np.float64,
            buffer=buffer,
            offset=self.offsets["pose"] + POSE_INTS * 8,
            strides=(layout.pose_words * 8, 8),
        )

    def release(self) -> None:
        """Drop the views so the mapping can be closed."""
        for name in (
            "ctl",
            "tick_i",
            "tick_f",
            "frame",
            "event_i",
            "event_d",
            "pose",
            "pose_i",
            "pose_f",
        ):
            setattr(self, name, None)
