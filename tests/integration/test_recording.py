"""Recording a run to MCAP against the simulated hand: every channel round-trips (checked
against what the bus and the runtime really did, and against the schemas), the files read with
the mcap library's own readers, a full ring drops and counts without blocking the loop, a
SIGKILL of the control process loses one tick, and a truncated file gives back every complete
chunk."""

from __future__ import annotations

import json
import math
import os
import signal
import subprocess
import sys
import time
from collections import Counter
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import jsonschema
import numpy as np
import pytest
from mcap.reader import make_reader
from mcap.records import Channel as McapChannel
from mcap.records import Message as McapMessage
from mcap.stream_reader import StreamReader

from handctl.config import HandConfig
from handctl.errors import HandctlError
from handctl.foxglove.derived import Derived
from handctl.online.bus import DRAIN_LIMIT, Frame, open_bus
from handctl.online.clock import Tick
from handctl.online.loop import Outcome, RunResult, TickRecord
from handctl.online.recipes.schema import Recipe
from handctl.online.safety.supervisor import State
from handctl.recording import channels as ch
from handctl.recording.metadata import run_metadata, start_metadata
from handctl.recording.reader import iter_decoded, iter_messages, open_recording
from handctl.recording.recorder import Recorder
from handctl.recording.ring import FRAME_HEAD, FRAME_TAIL, TICK_HEAD, TICK_TAIL, RingLayout
from handctl.sim import faults as inj

from ..conftest import ROOT, handctl
from .rig import rig, short_recipe

ESTOP_TICK = 700
#: The channels the writer derives for Foxglove, beside the recorded ones.
DERIVED = Derived.from_metadata(
    {ch.META_HAND: {"yaml": (ROOT / "config" / "hands" / "hiroshima_hand.yaml").read_text()}},
    lambda *_: None,
).channels
JSON_TOPICS = {c.topic for c in ch.CHANNELS} | {
    c.topic for c in DERIVED if c.message_encoding == "json"
}


@dataclass
class Recorded:
    path: Path
    result: RunResult
    wire: list[tuple[int, bytes]]  # every frame the sniffer heard, in bus order
    poses: dict[int, list[tuple[float, float, float]]] = field(default_factory=dict)
    final_angle: list[float] = field(default_factory=list)
    final_tdt: list[float] = field(default_factory=list)
    #: every frame the host's bus drained, in order (a frame the host's receive queue had no
    #: room for is on the wire but never drained)
    drained: list[tuple[int, bytes]] = field(default_factory=list)


def record_run(
    hand: HandConfig,
    recipe: Recipe,
    path: Path,
    *,
    troubles: bool = True,
    layout: RingLayout | None = None,
    pause_writer: bool = False,
    writer_between_ticks: bool = False,
    writer_every_tick: bool = False,
    babble: inj.Babble | None = None,
    babble_until_s: float = 0.36,
    stop_at_start: bool = False,
) -> Recorded:
    """A lockstep run on the simulated hand, recorded the way ``run_recipe`` records it.

    With ``troubles``: error frames (bus events), a babbling foreign node (unexpected ids)
    and skipped counters (rejects), then an operator e-stop (a request and a fault).
    With ``writer_between_ticks``: once the hand is being stopped, every tick waits before it
    begins until the writer has taken everything published, the timing a loaded machine
    gives now and then (the loop descheduled between one tick's push and the next tick).
    With ``writer_every_tick``: so does every tick of the run (a small ring that never fills).
    ``babble``: a babbling node from 0.35 s to ``babble_until_s`` of the run.
    ``stop_at_start``: a stop asked for before the run, met in its start-up.
    """
    with rig(hand, recipe) as r:
        drained: list[tuple[int, bytes]] = []
        bus = r.runtime.driver.bus
        real_drain = bus.drain

        def drain(limit: int = DRAIN_LIMIT) -> list[Frame]:
            frames = real_drain(limit)
            drained.extend((f.arbitration_id, f.data) for f in frames)
            return frames

        bus.drain = drain  # type: ignore[method-assign]
        recorder = Recorder(
            path,
            hand,
            start_metadata(hand, recipe, ["test"]),
            phase_names=[p.name for p in recipe.phases],
            object_names=[o.name for o in r.sim.params.objects],
            layout=layout,
        )
        with recorder:
            capture = _Capture(recorder)
            if writer_between_ticks:
                runtime = r.runtime
                capture.before_tick = lambda: (
                    runtime.first_send_tick >= 0
                    and runtime.supervisor.state not in (State.ENABLING, State.RUNNING)
                )
            if writer_every_tick:
                capture.before_tick = lambda: True
            r.runtime.recorder = capture
            recorder.attach(r.runtime)
            recorder.add_metadata(
                ch.META_RUN,
                run_metadata(
                    mode="lockstep",
                    bus="virtual",
                    seed=0,
                    period_ns=1_000_000,
                    startup_ticks=r.runtime.startup_ticks,
                    reset_node_faults=False,
                    estimator=False,
                ),
            )
            poses: dict[int, list[tuple[float, float, float]]] = {}

            def sample(tk: Tick) -> None:
                if tk.tick % 10 == 0:
                    truth = [(o.x, o.y, o.angle) for o in r.sim.ground_truth().objects]
                    poses[tk.tick] = truth
                    recorder.poses(truth)
                if troubles and tk.tick == ESTOP_TICK:
                    r.runtime.request_estop("test e-stop")

            r.runtime.tick_hooks.append(sample)
            if troubles:
                r.sim.faults.add(inj.ErrorFrames(per_tick=1), 0.30, 0.303)
                r.sim.faults.add(inj.Babble(id=0x050, per_tick=2, length=8), 0.40, 0.405)
                r.sim.faults.add(inj.CounterSkip(node=1, message="feedback"), 0.50, 0.502)
            if babble is not None:
                r.sim.faults.add(babble, 0.35, babble_until_s)
            recorder.wait_ready()
            if pause_writer:
                os.kill(recorder.process.pid, signal.SIGSTOP)
            if stop_at_start:
                r.runtime.request_stop("test stop")
            try:
                result = r.run()
            finally:
                if pause_writer:
                    os.kill(recorder.process.pid, signal.SIGCONT)
            recorded = Recorded(
                path, result, list(r.wire), poses, capture.angle, capture.tdt, drained
            )
            recorder.close({"outcome": result.outcome.value})
    return recorded


class _Capture:
    """Passes the runtime's records on to the recorder and keeps the last tick's state."""

    def __init__(self, inner: Recorder) -> None:
        self.inner = inner
        self.angle: list[float] = []
        self.tdt: list[float] = []
        #: When it says so, the tick waits for the writer to take everything published first.
        self.before_tick: Callable[[], bool] = lambda: False

    def begin_tick(self, tick: Tick) -> None:
        if self.before_tick():
            wait_for_writer(self.inner)
        self.inner.begin_tick(tick)

    def push(self, record: TickRecord) -> None:
        self.inner.push(record)
        self.angle, self.tdt = record.angle.tolist(), record.tdt.tolist()

    def note(self, kind: str, detail: str, tick: int) -> None:
        self.inner.note(kind, detail, tick)


def wait_for_writer(recorder: Recorder, timeout_s: float = 10.0) -> None:
    """Until the writer process has copied out every tick and frame published so far."""
    ctl = recorder._ctl_view
    deadline = time.monotonic() + timeout_s
    while ctl[TICK_TAIL] != ctl[TICK_HEAD] or ctl[FRAME_TAIL] != ctl[FRAME_HEAD]:
        assert time.monotonic() < deadline, "the writer did not catch up"
        time.sleep(0.001)


@pytest.fixture(scope="module")
def recorded(hand: HandConfig, tmp_path_factory: pytest.TempPathFactory) -> Recorded:
    directory = tmp_path_factory.mktemp("recording")
    return record_run(hand, short_recipe(hand, directory), directory / "run.mcap")


def library_messages(path: Path) -> Iterator[tuple[str, int, dict[str, Any]]]:
    """The JSON messages in file order through the mcap library's own reader, nothing of
    handctl's (the Foxglove channels in protobuf are tests/integration/test_foxglove.py's)."""
    with path.open("rb") as handle:
        for _, channel, message in make_reader(handle).iter_messages(log_time_order=False):
            if channel.message_encoding == "json":
                yield channel.topic, message.log_time, json.loads(message.data)


def test_every_channel_is_written_and_matches_its_schema(recorded: Recorded) -> None:
    with recorded.path.open("rb") as handle:
        reader = make_reader(handle)
        summary = reader.get_summary()
        assert summary is not None and summary.statistics is not None
        schemas = {s.id: s for s in summary.schemas.values()}
        validators = {}
        for channel in summary.channels.values():
            schema = schemas[channel.schema_id]
            if schema.name.startswith("foxglove."):  # Foxglove's own, in protobuf
                assert schema.encoding == "protobuf" and channel.message_encoding == "protobuf"
                continue
            assert schema.encoding == "jsonschema" and channel.message_encoding == "json"
            validators[channel.topic] = jsonschema.Draft202012Validator(json.loads(schema.data))
        counts = {
            summary.channels[cid].topic: n
            for cid, n in summary.statistics.channel_message_counts.items()
        }
    assert set(counts) == {c.topic for c in ch.CHANNELS} | {c.topic for c in DERIVED}
    assert all(counts[c.topic] > 0 for c in ch.CHANNELS), counts
    assert len(summary.chunk_indexes) > 1
    for topic, _, message in library_messages(recorded.path):
        validators[topic].validate(message)
    kinds = {m["kind"] for t, _, m in library_messages(recorded.path) if t == ch.EVENTS}
    assert kinds == {"fault", "state", "phase", "bus", "rejected_frames", "request"}


def test_frames_are_the_bus_traffic_in_order(recorded: Recorded) -> None:
    """An independent sniffer on the same bus heard exactly the logged frames, in order."""
    logged = [
        (m["id"], bytes.fromhex(m["data"]))
        for t, _, m in library_messages(recorded.path)
        if t in (ch.CAN_RX, ch.CAN_TX)
    ]
    assert logged == recorded.wire


def test_frames_wrapping_round_a_small_ring_are_the_bus_traffic(
    hand: HandConfig, tmp_path: Path
) -> None:
    """A frame ring of 64 rows, the writer catching up before every tick so that nothing is
    dropped: a tick's frames are a block of rows that wraps round the ring's end every few
    ticks, and a babbling node's drains of some fifty frames (64 bytes each, zeros among
    them) wrap nearly every tick. Every frame is in the file, in the order the host drained
    and sent them, byte for byte."""
    layout = RingLayout(hand.n_joints, len(hand.fingers), 2, frame_capacity=64)
    run = record_run(
        hand,
        short_recipe(hand, tmp_path),
        tmp_path / "small.mcap",
        layout=layout,
        writer_every_tick=True,
        babble=inj.Babble(id=0x050, per_tick=70, length=64),
        # over before the stop it causes ends: a tick that only listens (the stop's last,
        # which waits for the nodes to say they are disabled) hands its frames to the ring
        # at the next tick's start, and 70 of them do not fit 64 rows whatever the writer does
        babble_until_s=0.354,
    )
    recording = open_recording(run.path)
    end = recording.metadata[ch.META_END]
    assert end["dropped_frames"] == "0"
    logged: dict[str, list[tuple[int, bytes]]] = {ch.CAN_RX: [], ch.CAN_TX: []}
    for t, _, m in library_messages(run.path):
        if t in logged:
            logged[t].append((m["id"], bytes.fromhex(m["data"])))
    babbled = Counter(m["tick"] for t, _, m in library_messages(run.path) if m.get("id") == 0x050)
    assert sum(1 for n in babbled.values() if n > 32) >= 3  # blocks of half the ring
    assert logged[ch.CAN_RX] == run.drained
    received = {frame_id for frame_id, _ in run.drained}
    assert logged[ch.CAN_TX] == [f for f in run.wire if f[0] not in received]


#: Per tick, what the bus does: ("rx", n) the peer sends n frames and the host drains them,
#: ("tx",) the host sends one, ("push",) the tick's push (a tick without one only polled).
#: Per tick: ("rx", n) n frames drained at once; ("tx", n) a burst of n frames sent (the
#: first n - 1 with ``more=True``); ("open", n) n frames sent with ``more=True`` and nothing
#: after them (a ``flush`` or the next drain ends the burst); ("flush",); ("push",).
BUS_SCRIPT: list[list[tuple[Any, ...]]] = [
    [("rx", 3), ("tx", 3), ("push",)],
    [("rx", 2)],
    [("rx", 1), ("rx", 2), ("tx", 1), ("push",), ("tx", 1)],
    [("rx", 4), ("tx", 1), ("tx", 1), ("push",)],
    [("rx", 5), ("push",)],
    [("rx", 3), ("tx", 2), ("push",)],
    [("tx", 1), ("rx", 6), ("push",)],
    [("rx", 2), ("tx", 1), ("tx", 1), ("tx", 1), ("push",)],
    [("rx", 7), ("tx", 3), ("push",)],
    [("rx", 1), ("tx", 1), ("push",)],
    [("open", 2), ("rx", 3), ("tx", 2), ("push",)],
    [("tx", 4), ("push",), ("open", 1), ("flush",)],
    [("rx", 3), ("tx", 1), ("tx", 1), ("push",)],
    [("tx", 9), ("push",)],
    [("rx", 2)],
]


def test_frames_keep_their_bus_order_and_ticks_however_drains_and_sends_fall(
    hand: HandConfig, tmp_path: Path
) -> None:
    """Through a real virtual bus, a frame ring of 16 rows emptied by the writer before each
    tick: a drain and the sends after it (the drain's block goes in with the first burst),
    bursts of one frame and of several, a burst left open until a drain or a flush ends it,
    ticks that only drain, two drains with nothing sent between them, a send before the
    tick's drain, frames sent after a tick's push, blocks and bursts that wrap round the
    ring's end, and a drain still waiting when the recorder closes. Every frame is in the
    file with its tick, in the order the bus handed it over, byte for byte."""
    layout = RingLayout(hand.n_joints, len(hand.fingers), 0, tick_capacity=16, frame_capacity=16)
    channel = f"virtual:order-{os.getpid()}-{time.monotonic_ns()}"
    path = tmp_path / "order.mcap"
    expected: list[tuple[str, int, int, bytes]] = []
    zero = np.zeros(hand.n_joints)
    with open_bus(channel, hand.bus) as peer, open_bus(channel, hand.bus) as host:
        recorder = Recorder(path, hand, {}, layout=layout)
        host.tap, host.rx_tap = recorder._sent, recorder._drain
        recorder.wait_ready()
        n = 0
        for k, actions in enumerate(BUS_SCRIPT):
            wait_for_writer(recorder)
            recorder.begin_tick(Tick(k, 1000 * k, 1000 * k, 0))
            for action in actions:
                if action[0] == "rx":
                    for _ in range(action[1]):
                        n += 1
                        peer.send(0x100 + n % 7, n.to_bytes(2, "little") * 4)
                    drained = host.drain()
                    assert len(drained) == action[1]
                    expected += [(ch.CAN_RX, k, f.arbitration_id, f.data) for f in drained]
                elif action[0] in ("tx", "open"):
                    for i in range(action[1]):
                        n += 1
                        data = n.to_bytes(2, "little") * 3
                        more = action[0] == "open" or i < action[1] - 1
                        assert host.send(0x200 + n % 5, data, more=more)
                        expected.append((ch.CAN_TX, k, 0x200 + n % 5, data))
                elif action[0] == "flush":
                    assert host.flush()
                else:
                    recorder.push(
                        TickRecord(k, 0, 0, 0, zero, zero, zero, zero, "running", "-", (0,) * 6, [])
                    )
        stats = recorder.close()
    assert stats["frames"] == len(expected) and stats["dropped_frames"] == 0
    logged = [
        (t, m["tick"], m["id"], bytes.fromhex(m["data"]))
        for t, _, m in library_messages(path)
        if t in (ch.CAN_RX, ch.CAN_TX)
    ]
    assert logged == expected
    assert [m["tick"] for t, _, m in library_messages(path) if t == ch.TIMING] == list(
        range(len(BUS_SCRIPT))
    )


def test_per_tick_records_are_what_the_runtime_did(recorded: Recorded) -> None:
    result = recorded.result
    messages = list(library_messages(recorded.path))
    timing = [m for t, _, m in messages if t == ch.TIMING]
    assert [m["tick"] for m in timing] == list(range(result.ticks))
    assert [m["lateness_ns"] for m in timing] == result.lateness_ns.tolist()
    assert [m["missed"] for m in timing] == result.missed.tolist()
    active = [m for m in timing if m["active"]]
    for m in active[:50]:
        stages = result.stage_ns[m["tick"]]
        assert [m["stage_cpu_ns"][k] for k in ("poll", "recipe", "safety", "send")] == stages[
            :4
        ].tolist()
    torques = [m for t, _, m in messages if t == ch.TORQUE]
    assert [m["tick"] for m in torques] == [m["tick"] for m in active]
    for j, peak in enumerate(result.max_abs_tau.tolist()):
        assert max(abs(m["applied_nm"][j]) for m in torques) == peak
    joint = [m for t, _, m in messages if t == ch.JOINT_STATE]
    assert joint[-1]["angle_rad"] == recorded.final_angle
    assert joint[-1]["tdt_torque_nm"] == recorded.final_tdt
    states = [m["state"] for t, _, m in messages if t == ch.SAFETY]
    assert states[-1] == "faulted" and "running" in states
    faults = [
        (m["name"], m["tick"]) for t, _, m in messages if t == ch.EVENTS and m["kind"] == "fault"
    ]
    assert faults == [(f.code.name, f.tick) for f in result.faults]
    assert faults[0] == ("ESTOP", ESTOP_TICK)
    requests = [
        (m["name"], m["tick"]) for t, _, m in messages if t == ch.EVENTS and m["kind"] == "request"
    ]
    # the operator's e-stop, and the run's note of the phase it ended
    assert requests == [("estop", ESTOP_TICK), ("phase_end", ESTOP_TICK)]
    rejected: Counter[str] = Counter()
    for t, _, m in messages:
        if t == ch.EVENTS and m["kind"] == "rejected_frames":
            rejected[m["name"]] += m["count"]
    assert rejected == Counter({k: v for k, v in result.node_rejects.items() if v})
    assert rejected["unexpected_id"] > 0 and rejected["counter_skip"] > 0
    bus = [m for t, _, m in messages if t == ch.EVENTS and m["kind"] == "bus"]
    assert len(bus) >= result.bus_events > 0
    assert {m["name"] for m in bus} == {"error_frame"}
    phases = [m["phase"] for t, _, m in messages if t == ch.PHASE]
    assert [p for i, p in enumerate(phases) if i == 0 or p != phases[i - 1]] == [
        "running",
        "close",
        "hold",
    ]


def test_object_poses_are_the_ground_truth(recorded: Recorded) -> None:
    poses = {m["tick"]: m for t, _, m in library_messages(recorded.path) if t == ch.OBJECTS}
    assert set(poses) == set(recorded.poses)
    for tick, truth in recorded.poses.items():
        objects = poses[tick]["objects"]
        assert [(o["x_m"], o["y_m"], o["angle_rad"]) for o in objects] == truth
        (x1, y1, _), (x2, y2, _) = truth
        assert poses[tick]["line_angle_rad"] == math.atan2(y2 - y1, x2 - x1)


def test_metadata_names_the_hand_the_recipe_and_the_versions(
    recorded: Recorded, hand: HandConfig
) -> None:
    with recorded.path.open("rb") as handle:
        meta = {m.name: m.metadata for m in make_reader(handle).iter_metadata()}
    assert meta[ch.META_HAND]["config_hash"] == hand.config_hash
    assert meta[ch.META_HAND]["yaml"] == Path(hand.source).read_text()
    assert "short_hold" in meta[ch.META_RECIPE]["yaml"]
    assert {"handctl", "python", "numpy", "mujoco", "python-can", "mcap"} <= set(
        meta[ch.META_VERSIONS]
    )
    assert json.loads(meta["handctl.command"]["command_line"]) == ["test"]
    assert meta[ch.META_RUN]["mode"] == "lockstep"
    end = meta[ch.META_END]
    assert end["ended"] == "closed by the recorder"
    assert end["dropped_ticks"] == end["dropped_frames"] == "0"
    assert json.loads(meta[ch.META_SUMMARY]["json"]) == {"outcome": "safety_stop"}


def test_handctl_reader_agrees_with_the_library(recorded: Recorded) -> None:
    recording = open_recording(recorded.path)
    assert recording.complete and not recording.problem
    ours = [(t, lt, json.loads(d)) for t, lt, d in iter_messages(recording, JSON_TOPICS)]
    assert ours == list(library_messages(recorded.path))


def test_a_full_ring_drops_and_counts_and_never_blocks(
    hand: HandConfig, tmp_path: Path, recorded: Recorded
) -> None:
    """The writer is stopped (SIGSTOP) for the whole run: the rings fill, the loop goes on."""
    tiny = RingLayout(
        hand.n_joints,
        len(hand.fingers),
        2,
        tick_capacity=16,
        frame_capacity=64,
        event_capacity=8,
        pose_capacity=4,
    )
    run = record_run(
        hand, short_recipe(hand, tmp_path), tmp_path / "tiny.mcap", layout=tiny, pause_writer=True
    )
    assert run.result.ticks == recorded.result.ticks  # same run, nothing held it up
    assert run.result.outcome is Outcome.SAFETY_STOP
    recording = open_recording(run.path)
    end = {k: int(v) for k, v in recording.metadata[ch.META_END].items() if v.isdigit()}
    # Every record is either in the file or counted as dropped. The rings hold their capacity;
    # what the recorder publishes at close, after the writer was let go, may find room.
    assert end["ticks"] + end["dropped_ticks"] == run.result.ticks
    assert end["frames"] + end["dropped_frames"] == len(run.wire)
    # The frame ring's 64 rows hold the frames and a head row per drain; here a drain brings
    # the three nodes' frames or more, so a head row to three frames at most.
    assert 16 <= end["ticks"] <= 17 and 64 - 64 // 4 <= end["frames"] <= 64 + 6
    assert end["dropped_poses"] > 0 and end["dropped_events"] > 0
    logged = list(iter_decoded(recording, (ch.TIMING, ch.CAN_RX, ch.CAN_TX)))
    assert sum(t == ch.TIMING for t, _, _ in logged) == end["ticks"]
    assert len(logged) - end["ticks"] == end["frames"]
    drops: Counter[str] = Counter()
    for _, _, m in iter_decoded(recording, (ch.EVENTS,)):
        if m["kind"] == "recording":
            drops[m["name"]] += m["count"]
    assert drops["dropped_ticks"] == end["dropped_ticks"]
    assert drops["dropped_frames"] == end["dropped_frames"]
    stats = [m for _, _, m in iter_decoded(recording, (ch.STATS,))]
    assert stats[-1]["dropped_ticks"] == end["dropped_ticks"]


def test_a_writer_that_catches_up_writes_chunks_of_50_ms_each(
    hand: HandConfig, tmp_path: Path, recorded: Recorded
) -> None:
    """The writer stopped (SIGSTOP) for the whole run, rings large enough to hold it, and let
    go at its end: its backlog went into the file as one chunk of the whole run (4 s, 19.7 MB
    after a 6 s stop of a default run), where a chunk holds at most ``CHUNK_NS`` of log time,
    and a CRC error or the writer's death then cost all of it. Now each slice of that much
    goes out a chunk, its frames and events before its rows: the log is the run's, and
    re-runs bit-exact."""
    from handctl.recording.rerun import rerun
    from handctl.recording.writer import CHUNK_NS

    run = record_run(hand, short_recipe(hand, tmp_path), tmp_path / "held.mcap", pause_writer=True)
    assert run.result.ticks == recorded.result.ticks
    with run.path.open("rb") as handle:
        summary = make_reader(handle).get_summary()
    assert summary is not None
    spans = [c.message_end_time - c.message_start_time for c in summary.chunk_indexes]
    assert len(spans) >= run.result.ticks * 1_000_000 // CHUNK_NS and max(spans) < CHUNK_NS
    recording = open_recording(run.path)
    assert recording.complete and recording.meta(ch.META_END, "dropped_ticks") == "0"
    report = rerun(recording)
    assert (
        report.ok
        and report.compared > 0
        and report.compared == rerun(open_recording(recorded.path)).compared
    ), report.as_dict()

    def by_topic(path: Path) -> dict[str, list[Any]]:
        found: dict[str, list[Any]] = {}
        for topic, log_time, message in iter_decoded(open_recording(path), JSON_TOPICS):
            message.pop("stage_cpu_ns", None)  # the run's CPU time, another each run
            if topic != ch.STATS:  # one a chunk
                found.setdefault(topic, []).append((log_time, message))
        return found

    assert by_topic(run.path) == by_topic(recorded.path)


# -- durability ------------------------------------------------------------------------------
CHILD = """
import os, signal, sys
from pathlib import Path
from handctl.config import load_hand
from handctl.online.recipes.loader import load_recipe
from handctl.session import RunRequest, run_recipe

hand = load_hand(sys.argv[1])
recipe = load_recipe(sys.argv[2], hand)
kill_at, kill_writer = int(sys.argv[4]), sys.argv[5] == "1"

def children():
    found = []
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            try:
                stat = Path(f"/proc/{entry}/stat").read_text()
            except OSError:
                continue
            if int(stat.rsplit(")", 1)[1].split()[1]) == os.getpid():
                found.append(int(entry))
    return found

def status(line):
    tick = round(line.t_s * 1000)
    if tick >= kill_at:
        print(tick, flush=True)
        if kill_writer:
            for pid in children():
                os.kill(pid, signal.SIGKILL)
        os.kill(os.getpid(), signal.SIGKILL)

run_recipe(RunRequest(hand=hand, recipe=recipe, log=Path(sys.argv[3])), status=status)
"""


def kill_mid_run(
    hand: HandConfig, recipe: Recipe, path: Path, kill_at: int, kill_writer: bool
) -> int:
    """Run a recorded lockstep run in a child that SIGKILLs itself (and, if asked, the writer)
    at the status line of tick ``kill_at``; returns the tick it died in."""
    done = subprocess.run(
        [
            sys.executable,
            "-c",
            CHILD,
            hand.source,
            recipe.source,
            str(path),
            str(kill_at),
            "1" if kill_writer else "0",
        ],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    assert done.returncode == -signal.SIGKILL, done.stderr
    return int(done.stdout.split()[-1])


def wait_complete(path: Path, timeout_s: float = 60.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not open_recording(path).complete:
        assert time.monotonic() < deadline, "the writer did not finish the file"
        time.sleep(0.1)


def test_sigkill_of_the_control_process_loses_no_finished_tick(
    hand: HandConfig, tmp_path: Path
) -> None:
    recipe = short_recipe(hand, tmp_path)
    path = tmp_path / "killed.mcap"
    died_in = kill_mid_run(hand, recipe, path, 600, kill_writer=False)
    wait_complete(path)  # the orphaned writer finishes the file on its own
    recording = open_recording(path)
    assert (
        recording.meta(ch.META_END, "ended")
        == "the control process ended without closing the recorder"
    )
    ticks = [m["tick"] for _, _, m in iter_decoded(recording, (ch.TIMING,))]
    assert ticks == list(range(len(ticks)))
    lost_ms = died_in - ticks[-1]
    assert lost_ms <= 100
    # It died at the status line, after the tick's push, which publishes the tick: nothing of
    # a finished tick is lost (a kill inside a tick would lose that tick alone).
    assert lost_ms == 0
    with path.open("rb") as handle:  # complete and indexed, for the library too
        summary = make_reader(handle).get_summary()
    assert summary is not None and summary.chunk_indexes


def test_sigkill_of_both_leaves_a_readable_prefix(hand: HandConfig, tmp_path: Path) -> None:
    recipe = short_recipe(hand, tmp_path)
    path = tmp_path / "both.mcap"
    kill_mid_run(hand, recipe, path, 600, kill_writer=True)
    recording = open_recording(path)
    assert not recording.complete and recording.problem
    ours = [(t, lt, json.loads(d)) for t, lt, d in iter_messages(recording, JSON_TOPICS)]
    assert [m for t, _, m in ours if t == ch.TIMING], "nothing of the run was on disk"
    # The library's streaming reader reads the same prefix before it stops at the cut.
    theirs: list[McapMessage] = []
    with path.open("rb") as handle, pytest.raises(Exception):  # noqa: B017 - whatever the library raises at the cut
        json_channels: set[int] = set()
        for record in StreamReader(handle, validate_crcs=True).records:
            if isinstance(record, McapChannel) and record.message_encoding == "json":
                json_channels.add(record.id)
            if isinstance(record, McapMessage) and record.channel_id in json_channels:
                theirs.append(record)
    assert [json.loads(m.data) for m in theirs] == [m for _, _, m in ours]


@pytest.mark.parametrize(
    "failure",
    [HandctlError("the recording writer is gone"), KeyboardInterrupt("signal SIGINT")],
    ids=["writer_gone", "interrupt"],
)
def test_a_writer_that_never_had_its_set_up_leaves_no_file(
    hand: HandConfig, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, failure: BaseException
) -> None:
    """Nothing was recorded: no file, rather than an empty one that no reader opens
    (``handctl replay``: "an empty file"). The set-up is bigger than a pipe holds, so handing
    it over waits for the writer to start, the longest wait of a run's start-up."""

    def fails(self: Recorder, message: dict[str, Any], stall_timeout_s: float = 0.0) -> None:
        raise failure

    monkeypatch.setattr(Recorder, "_send", fails)
    path = tmp_path / "run.mcap"
    with pytest.raises(type(failure)):
        Recorder(path, hand, {})
    assert not path.exists()


@pytest.mark.parametrize(
    "where", ["inside_a_chunk", "after_a_chunk", "in_the_summary", "in_the_header"]
)
def test_a_truncated_file_gives_back_every_complete_chunk(
    recorded: Recorded, tmp_path: Path, where: str
) -> None:
    data = recorded.path.read_bytes()
    with recorded.path.open("rb") as handle:
        reader = make_reader(handle)
        summary = reader.get_summary()
        assert summary is not None
        chunks = sorted(summary.chunk_indexes, key=lambda c: c.chunk_start_offset)
        all_messages = list(library_messages(recorded.path))
    middle = chunks[len(chunks) // 2]
    cut = {
        "inside_a_chunk": middle.chunk_start_offset + middle.chunk_length // 2,
        "after_a_chunk": middle.chunk_start_offset + middle.chunk_length,
        "in_the_summary": len(data) - 40,
        "in_the_header": 30,
    }[where]
    truncated = tmp_path / "cut.mcap"
    truncated.write_bytes(data[:cut])
    recording = open_recording(truncated)
    assert not recording.complete and recording.problem
    whole = [c for c in chunks if c.chunk_start_offset + c.chunk_length <= cut]
    expected = sum(_chunk_messages(recorded.path, c) for c in whole)
    got = [(t, lt, json.loads(d)) for t, lt, d in iter_messages(recording, JSON_TOPICS)]
    assert len(got) == expected
    assert got == all_messages[:expected]
    assert recording.chunks == len(whole)


@pytest.mark.parametrize("where", ["compressed_data", "record_header"])
def test_a_damaged_chunk_is_named_and_the_chunks_after_it_are_read(
    recorded: Recorded, tmp_path: Path, where: str
) -> None:
    """Bytes overwritten inside a chunk in the middle of a finished file: the index still says
    where every chunk is, so only that chunk's messages are lost."""
    data = bytearray(recorded.path.read_bytes())
    with recorded.path.open("rb") as handle:
        summary = make_reader(handle).get_summary()
    assert summary is not None
    chunks = sorted(summary.chunk_indexes, key=lambda c: c.chunk_start_offset)
    bad = len(chunks) // 2
    middle = chunks[bad]
    at = {
        "compressed_data": middle.chunk_start_offset + middle.chunk_length // 2,
        "record_header": middle.chunk_start_offset + 1,
    }[where]  # its length field
    data[at : at + 8] = bytes(b ^ 0x5A for b in data[at : at + 8])
    damaged = tmp_path / "damaged.mcap"
    damaged.write_bytes(bytes(data))

    recording = open_recording(damaged)
    assert recording.damaged and not recording.complete and not recording.truncated
    assert [(c.number, c.offset, c.start_ns, c.end_ns) for c in recording.bad_chunks] == [
        (bad, middle.chunk_start_offset, middle.message_start_time, middle.message_end_time)
    ]
    assert f"chunk {bad} at byte {middle.chunk_start_offset}" in recording.problem
    assert f"{middle.message_start_time}..{middle.message_end_time} ns" in recording.problem
    assert recording.chunks == len(chunks) - 1
    assert recording.meta(ch.META_END, "ended") == "closed by the recorder"  # metadata read
    counts = [_chunk_messages(recorded.path, c) for c in chunks]
    lost_from, lost_to = sum(counts[:bad]), sum(counts[: bad + 1])
    everything = list(library_messages(recorded.path))
    got = [(t, lt, json.loads(d)) for t, lt, d in iter_messages(recording, JSON_TOPICS)]
    assert got == everything[:lost_from] + everything[lost_to:]
    assert counts[bad + 1 :] and got[-1] == everything[-1]  # the chunks after it are kept

    done = handctl("replay", str(damaged), "--rerun")
    # what it compared repeats, and the rest was never compared: exit 1 (it was 0, which a
    # script took for the whole log verified)
    assert done.returncode == 1, done.stdout + done.stderr
    assert f"DAMAGED: chunk {bad} at byte {middle.chunk_start_offset}" in done.stdout
    assert "bit-exact" in done.stdout and "before a damaged chunk" in done.stdout
    assert "rerun: FAILED: not the whole log: it is DAMAGED" in done.stderr
    # nor does it go onto a bus: the frames either side of the hole would go out as one
    # stream the run never sent (it went, exit 0)
    done = handctl("replay", str(damaged), "--to-bus", f"virtual:damaged-{where}")
    assert done.returncode == 1, done.stdout + done.stderr
    assert f"to-bus: nothing sent: {damaged} is DAMAGED (chunk {bad} at byte" in done.stderr
    assert "frames sent" not in done.stdout
    # and what is read of it is no sound log: exit 0 from a summary or an export was read as
    # one, the export's hole unsaid (found by an outside audit)
    exported = damaged.with_suffix(".log")
    done = handctl("replay", str(damaged), "--export", "candump", str(exported))
    assert done.returncode == 1, done.stdout + done.stderr
    assert f"handctl: failed: {damaged} is DAMAGED (chunk {bad} at byte" in done.stderr
    assert "export: the log is DAMAGED (chunk" in done.stderr and "have a hole there" in (
        done.stderr
    )
    assert exported.stat().st_size > 0


def test_a_rerun_does_not_start_after_a_damaged_first_chunk(
    recorded: Recorded, tmp_path: Path
) -> None:
    """Without its first ticks a log has nothing a fresh runtime could follow."""
    from handctl.recording.rerun import rerun

    data = bytearray(recorded.path.read_bytes())
    with recorded.path.open("rb") as handle:
        summary = make_reader(handle).get_summary()
    assert summary is not None
    first = min(summary.chunk_indexes, key=lambda c: c.chunk_start_offset)
    at = first.chunk_start_offset + first.chunk_length // 2
    data[at : at + 8] = bytes(b ^ 0x5A for b in data[at : at + 8])
    damaged = tmp_path / "first.mcap"
    damaged.write_bytes(bytes(data))
    recording = open_recording(damaged)
    assert [c.number for c in recording.bad_chunks] == [0]
    report = rerun(recording)
    assert report.compared == 0 and report.frames_compared == 0, report.as_dict()
    assert any("before a damaged chunk" in note for note in report.notes)
    # and the command does not call nothing bit-exact
    done = handctl("replay", str(damaged), "--rerun")
    assert done.returncode == 1, done.stdout + done.stderr
    assert "rerun: NOTHING COMPARED" in done.stdout and "bit-exact" not in done.stdout


def test_a_damaged_metadata_record_is_named(recorded: Recorded, tmp_path: Path) -> None:
    """Metadata has no CRC, but a record that is not where and what its index says is named,
    and a re-run that needs it is refused (exit 2) rather than run on something else."""
    data = bytearray(recorded.path.read_bytes())
    with recorded.path.open("rb") as handle:
        summary = make_reader(handle).get_summary()
    assert summary is not None
    hand_index = next(m for m in summary.metadata_indexes if m.name == ch.META_HAND)
    data[hand_index.offset + 1] ^= 0xFF  # its length
    damaged = tmp_path / "meta.mcap"
    damaged.write_bytes(bytes(data))
    recording = open_recording(damaged)
    assert recording.damaged and recording.bad_metadata == [ch.META_HAND]
    assert f"metadata record '{ch.META_HAND}' at byte {hand_index.offset}" in recording.problem
    assert ch.META_RUN in recording.metadata and recording.chunks == len(summary.chunk_indexes)
    done = handctl("replay", str(damaged), "--rerun")
    assert done.returncode == 2, done.stdout + done.stderr
    assert str(damaged) in done.stderr and ch.META_HAND in done.stderr


def _chunk_messages(path: Path, chunk: Any) -> int:
    """How many JSON messages one chunk holds, through the library's own chunk parser."""
    from mcap.records import Chunk, Message
    from mcap.stream_reader import breakup_chunk

    with path.open("rb") as handle:
        summary = make_reader(handle).get_summary()
        assert summary is not None
        json_ids = {c.id for c in summary.channels.values() if c.message_encoding == "json"}
        handle.seek(chunk.chunk_start_offset)
        record = next(iter(StreamReader(handle, skip_magic=True, emit_chunks=True).records))
    assert isinstance(record, Chunk)
    return sum(isinstance(r, Message) and r.channel_id in json_ids for r in breakup_chunk(record))


def test_docs_name_every_channel_schema_and_field() -> None:
    """docs/recording.md is what a Foxglove user reads: it must not fall behind channels.py."""
    text = (ROOT / "docs" / "recording.md").read_text()
    for channel in ch.CHANNELS:
        assert f"`{channel.topic}`" in text and f"`{channel.schema_name}`" in text
        for name in ch.schema_of(channel)["properties"]:
            assert f"`{name}" in text or name == "tick", (channel.topic, name)
    for kind in ch.EVENT_KINDS:
        assert f"`{kind}`" in text
    for name in (
        ch.META_RUN,
        ch.META_HAND,
        ch.META_RECIPE,
        ch.META_VERSIONS,
        ch.META_SUMMARY,
        ch.META_END,
    ):
        assert f"`{name}`" in text


def test_the_safety_channel_s_states_are_the_supervisor_s() -> None:
    """The recording does not import the runtime, so its schema lists the states itself."""
    from handctl.online.safety.supervisor import State

    assert tuple(s.value for s in State) == ch.SAFETY_STATES
