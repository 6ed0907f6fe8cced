"""Foxglove views of a real run: a lockstep run of the default recipe, recorded and served live
(``handctl run recipe ... --log RUN.mcap --live PORT``) as a separate process. A WebSocket
client speaks the Foxglove protocol to the live server; the MCAP's well-known-schema channels
are decoded with the protobuf descriptors the file itself carries, and checked against the
recorded numbers they were derived from."""

from __future__ import annotations

import asyncio
import itertools
import json
import math
import os
import socket
import struct
import subprocess
import sys
import time
from collections import defaultdict
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import jsonschema
import pytest
import websockets
from google.protobuf import descriptor_pb2, descriptor_pool, message_factory
from google.protobuf.message import Message
from mcap.reader import make_reader
from websockets.typing import Subprotocol

from handctl.config import HandConfig
from handctl.foxglove import derived as fx
from handctl.recording import channels as ch
from handctl.sim.params import parse_sim

from ..conftest import HAND_YAML, ROOT

RECIPE = ROOT / "config" / "recipes" / "swap_two_cylinders.yaml"
#: The subprotocol foxglove-sdk 0.30 speaks (the successor of "foxglove.websocket.v1").
SUBPROTOCOL = Subprotocol("foxglove.sdk.v1")
WANTED = (fx.SCENE, fx.JOINTS, fx.TRANSFORMS, ch.JOINT_STATE)
#: Enough of a run for the estimator to find both cylinders in the hand.
RUN_S = "3"


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def decoder(schema_name: str, data: bytes) -> Any:
    """The message class a protobuf schema record describes, built from its descriptors."""
    files = descriptor_pb2.FileDescriptorSet.FromString(data)
    pool = descriptor_pool.DescriptorPool()
    pending = list(files.file)
    while pending:  # add each file after the files it imports
        added = [f for f in pending if all(pool_has(pool, d) for d in f.dependency)]
        assert added, "the descriptor set does not close over its imports"
        for f in added:
            pool.Add(f)
            pending.remove(f)
    return message_factory.GetMessageClass(pool.FindMessageTypeByName(schema_name))


def pool_has(pool: descriptor_pool.DescriptorPool, name: str) -> bool:
    try:
        pool.FindFileByName(name)
    except KeyError:
        return False
    return True


def test_every_frame_of_the_tree_but_the_joints_is_a_name_the_scene_takes(
    hand: HandConfig,
) -> None:
    """The frames ``HandScene.transforms`` puts in ``/foxglove/tf``, other than the joints',
    are the names the hand config keeps joints off (``config.scene_names``): a joint named
    like one made a cycle or a frame of two parents. A frame added to the tree is added
    there."""
    from handctl.config import scene_names
    from handctl.foxglove.scene import HandScene

    message = HandScene(hand).transforms(0, [0.0] * hand.n_joints)
    schema = message.get_schema()
    tree = decoder(schema.name, schema.data).FromString(message.encode()).transforms
    frames = {t.parent_frame_id for t in tree} | {t.child_frame_id for t in tree}
    assert frames - set(hand.joint_names) <= set(scene_names(hand.fingers))
    children = [t.child_frame_id for t in tree]
    assert len(children) == len(set(children))  # one parent each


@dataclass
class Live:
    advertised: dict[str, dict[str, Any]] = field(default_factory=dict)
    received: dict[str, list[bytes]] = field(default_factory=lambda: defaultdict(list))
    #: The log time of each message received, beside it
    log_times: dict[str, list[int]] = field(default_factory=lambda: defaultdict(list))


#: The topics a client subscribes to together. The server drops a slow client's oldest
#: messages (the writer never waits for a viewer), so one client of every topic, on a busy
#: machine, may lose each scene under a thousand joint messages a second; a viewer that shows
#: the scene takes only what it draws, and so do these clients.
CLIENTS = ((fx.SCENE, fx.TRANSFORMS), (fx.JOINTS, ch.JOINT_STATE))


async def listen(
    port: int,
    proc: subprocess.Popen[bytes],
    enough: int,
    clients: tuple[tuple[str, ...], ...] = CLIENTS,
) -> Live:
    """One client per group of topics at once, their messages in one ``Live``."""
    live = Live()
    await asyncio.gather(*(_client(port, proc, enough, topics, live) for topics in clients))
    return live


async def _client(
    port: int, proc: subprocess.Popen[bytes], enough: int, wanted: tuple[str, ...], live: Live
) -> None:
    """Connect (retrying while the run starts), subscribe to ``wanted``, collect messages."""
    while True:
        try:
            ws = await websockets.connect(
                f"ws://127.0.0.1:{port}", subprotocols=[SUBPROTOCOL], max_size=None
            )
            break
        except OSError:
            if proc.poll() is not None:
                _, err = proc.communicate()
                raise AssertionError(
                    f"ended before its live server accepted: {err.decode()}"
                ) from None
            await asyncio.sleep(0.05)
    async with ws:
        assert ws.subprotocol == SUBPROTOCOL
        topics: dict[int, str] = {}
        while any(len(live.received[t]) < enough for t in wanted):
            try:
                raw = await asyncio.wait_for(ws.recv(), 5.0)
            except (TimeoutError, websockets.ConnectionClosed):
                break
            if isinstance(raw, str):
                op = json.loads(raw)
                if op["op"] == "advertise":
                    subs = []
                    for channel in op["channels"]:
                        live.advertised[channel["topic"]] = channel
                        if channel["topic"] in wanted:
                            topics[channel["id"]] = channel["topic"]
                            subs.append({"id": channel["id"], "channelId": channel["id"]})
                    if subs:
                        await ws.send(json.dumps({"op": "subscribe", "subscriptions": subs}))
                continue
            assert raw[0] == 0x01  # message data: subscription id, log time, payload
            sub, log_time = struct.unpack_from("<IQ", raw, 1)
            live.received[topics[sub]].append(bytes(raw[13:]))
            live.log_times[topics[sub]].append(log_time)


@dataclass
class Run:
    path: Path
    live: Live
    returncode: int
    stderr: str


def served(
    args: list[str],
    cwd: Path,
    enough: int,
    clients: tuple[tuple[str, ...], ...] = CLIENTS,
    python_options: tuple[str, ...] = (),
) -> tuple[Live, subprocess.CompletedProcess[bytes]]:
    """``python -m handctl ARGS --live PORT`` on a free port, in a process of its own with the
    checkout first on its path, and ``listen``'s clients connected until each has ``enough``
    messages of its topics (or the server closed); then the command's end.
    ``python_options``: the interpreter's own, for the command's process alone."""
    port = free_port()
    command = [sys.executable, *python_options, "-m", "handctl", *args, "--live", str(port)]
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    with subprocess.Popen(
        command, cwd=cwd, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE
    ) as proc:
        try:
            live = asyncio.run(listen(port, proc, enough, clients))
            out, err = proc.communicate(timeout=300)
        finally:
            if proc.poll() is None:
                proc.kill()
    return live, subprocess.CompletedProcess(command, proc.returncode, out, err)


@pytest.fixture(scope="module")
def run(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Run]:
    directory = tmp_path_factory.mktemp("foxglove")
    path = directory / "run.mcap"
    live, done = served(
        [
            "run",
            "recipe",
            str(RECIPE),
            "--hand",
            str(HAND_YAML),
            "--lockstep",
            "--log",
            str(path),
            "--max-seconds",
            RUN_S,
        ],
        directory,
        enough=5,
        python_options=("-X", "importtime"),  # which modules the control process loads
    )
    yield Run(path, live, done.returncode, done.stderr.decode(errors="replace"))


def mcap_messages(path: Path) -> Iterator[tuple[Any, Any, Any]]:
    with path.open("rb") as handle:
        yield from make_reader(handle).iter_messages(log_time_order=False)


def test_the_control_process_of_a_live_run_does_not_load_the_foxglove_sdk(run: Run) -> None:
    """The live server is the writer process's: the loop's process serves nothing, so it
    loads none of the SDK (its code and objects, which the loop's garbage collections would
    walk). ``-X importtime`` lists what the command's process imported, not the writer's."""
    imported = [
        line.rsplit("|", 1)[-1].strip()
        for line in run.stderr.splitlines()
        if line.startswith("import time:")
    ]
    assert "handctl.recording.recorder" in imported  # the listing is there, and it records
    assert "handctl.foxglove" in imported  # the live server's address
    sdk = [name for name in imported if name.split(".")[0] == "foxglove"]
    assert sdk == [], sdk


def test_live_server_sends_scene_and_joint_messages(run: Run, hand: HandConfig) -> None:
    assert run.returncode in (0, 130, 3, 1) and "Traceback" not in run.stderr, run.stderr
    live = run.live
    scene_channel = live.advertised[fx.SCENE]
    assert scene_channel["encoding"] == "protobuf"
    assert scene_channel["schemaName"] == "foxglove.SceneUpdate"
    scene_type = decoder("foxglove.SceneUpdate", _schema_bytes(scene_channel))
    assert len(live.received[fx.SCENE]) >= 5, {t: len(v) for t, v in live.received.items()}
    scene = scene_type.FromString(live.received[fx.SCENE][-1])
    ids = {e.id for e in scene.entities}
    assert {f"link/{name}" for name in hand.joint_names} <= ids
    assert len(live.received[fx.JOINTS]) >= 5
    joints = json.loads(live.received[fx.JOINTS][-1])
    for joint in hand.joints:
        assert joints[joint.name]["tau_max_nm"] == joint.tau_max
        assert math.isfinite(joints[joint.name]["angle_rad"])
    assert len(live.received[ch.JOINT_STATE]) >= 5  # today's channels are served too


def test_the_live_view_advertises_each_channel_with_the_logs_metadata(run: Run) -> None:
    """``--live`` serves the log's channels, and a vector's entries are named by the channel
    metadata key ``joints`` (docs/recording.md): a run's live view advertised
    ``/hand/joint_state`` and ``/control/torque`` with no metadata at all (no ``joints``,
    ``nodes`` or ``handctl.format_version``), while the log and ``replay --live`` had it
    (found by an outside audit). What a WebSocket client is advertised is the log's."""
    with run.path.open("rb") as handle:
        summary = make_reader(handle).get_summary()
    assert summary is not None
    logged = {c.topic: dict(c.metadata) for c in summary.channels.values()}
    advertised = {topic: c.get("metadata", {}) for topic, c in run.live.advertised.items()}
    assert set(advertised) == set(logged)
    assert advertised == logged
    assert "joints" in advertised[ch.JOINT_STATE] and "nodes" in advertised[ch.JOINT_STATE]
    assert "joints" in advertised[ch.TORQUE]


def _schema_bytes(channel: dict[str, Any]) -> bytes:
    """The live protocol carries a binary schema base64-encoded."""
    import base64

    return base64.b64decode(channel["schema"])


def test_well_known_channels_decode_with_their_own_schemas(run: Run, hand: HandConfig) -> None:
    with run.path.open("rb") as handle:
        summary = make_reader(handle).get_summary()
    assert summary is not None
    by_topic = {c.topic: (c, summary.schemas[c.schema_id]) for c in summary.channels.values()}
    for recorded in ch.CHANNELS:  # the recorded channels are all still there
        assert recorded.topic in by_topic
    types: dict[str, Any] = {}
    validators = {}
    for topic, (channel, schema) in by_topic.items():
        if schema.encoding == "protobuf":
            assert channel.message_encoding == "protobuf"
            assert schema.name.startswith("foxglove.")
            types[topic] = decoder(schema.name, schema.data)
        else:
            assert (schema.encoding, channel.message_encoding) == ("jsonschema", "json")
            validators[topic] = jsonschema.Draft202012Validator(json.loads(schema.data))
    assert set(types) == {fx.SCENE, fx.TRANSFORMS, fx.LOG}
    decoded: dict[str, list[tuple[int, Any]]] = defaultdict(list)
    for _, channel, message in mcap_messages(run.path):
        if channel.topic in types:
            value: Message = types[channel.topic].FromString(message.data)
        else:
            value = json.loads(message.data)
            validators[channel.topic].validate(value)
        decoded[channel.topic].append((message.log_time, value))
    check_scene(decoded, hand)
    check_joints_and_frames(decoded, hand)
    check_log(decoded)


def _forward(hand: HandConfig, angles: list[float]) -> dict[str, list[tuple[float, float]]]:
    """Each joint's axis and the link's far end, in the hand plane, from the config."""
    out = {}
    i = 0
    for finger in hand.fingers:
        x, y, heading = finger.base_x, finger.base_y, finger.base_angle
        for joint in finger.joints:
            heading += angles[i]
            end = (
                x + joint.link_length * math.cos(heading),
                y + joint.link_length * math.sin(heading),
            )
            out[joint.name] = [(x, y), end]
            x, y = end
            i += 1
    return out


def check_scene(decoded: dict[str, list[tuple[int, Any]]], hand: HandConfig) -> None:
    angles = {t: m["angle_rad"] for t, m in decoded[ch.JOINT_STATE]}
    truths = sorted((t, m["objects"]) for t, m in decoded[ch.OBJECTS])
    sim = parse_sim(hand)
    line_errors: list[float] = []
    assert len(decoded[fx.SCENE]) >= 50
    for t, scene in decoded[fx.SCENE]:
        entities = {e.id: e for e in scene.entities}
        ends = _forward(hand, angles[t])
        for name, (start, end) in ends.items():
            spheres = entities[f"link/{name}"].spheres
            got = [(s.pose.position.x, s.pose.position.y) for s in spheres]
            assert got == pytest.approx([start, end], abs=1e-9)
            radius = sim.links[hand.joint_names.index(name)].radius
            assert spheres[0].size.x == pytest.approx(2 * radius)
        assert {"palm", "table"} <= set(entities)
        truth = [objs for tt, objs in truths if tt <= t]
        if truth:
            centres = []
            for obj in truth[-1]:
                cyl = entities[f"object/{obj['name']}"].cylinders[0]
                assert (cyl.pose.position.x, cyl.pose.position.y) == pytest.approx(
                    (obj["x_m"], obj["y_m"]), abs=1e-12
                )
                estimate = entities.get(f"estimate/{obj['name']}")
                if estimate is not None:
                    est = estimate.cylinders[0]
                    assert est.color.a < 1.0  # translucent over the truth
                    radius = est.size.x / 2
                    # the estimate overlaps the object it stands for
                    assert (
                        math.dist(
                            (est.pose.position.x, est.pose.position.y), (obj["x_m"], obj["y_m"])
                        )
                        < radius
                    )
                    centres.append(
                        ((est.pose.position.x, est.pose.position.y), (obj["x_m"], obj["y_m"]))
                    )
            if len(centres) == 2:
                (e1, t1), (e2, t2) = centres
                line_error = math.atan2(e2[1] - e1[1], e2[0] - e1[0]) - math.atan2(
                    t2[1] - t1[1], t2[0] - t1[0]
                )
                line_errors.append(abs(math.remainder(line_error, math.tau)))
    # the estimated pair lies along the true pair (the run summary's estimator error is
    # a few degrees at its 95th percentile)
    assert len(line_errors) > 10, "the estimator never placed the objects"
    assert sorted(line_errors)[len(line_errors) // 2] < math.radians(10)
    # the transforms are the same chain as the scene's links
    for t, tfs in decoded[fx.TRANSFORMS][::10]:
        ends = _forward(hand, angles[t])
        frames = {tf.child_frame_id: tf for tf in tfs.transforms}
        for finger in hand.fingers:
            x, y, heading = 0.0, 0.0, 0.0
            chain = [f"{finger.name}_base"] + [j.name for j in finger.joints]
            for name in chain:
                tf = frames[name]
                assert tf.parent_frame_id == (
                    "world" if name.endswith("_base") else chain[chain.index(name) - 1]
                )
                dx, dy = tf.translation.x, tf.translation.y
                x, y = (
                    x + dx * math.cos(heading) - dy * math.sin(heading),
                    y + dx * math.sin(heading) + dy * math.cos(heading),
                )
                heading += 2 * math.atan2(tf.rotation.z, tf.rotation.w)
                if name in ends:
                    assert (x, y) == pytest.approx(ends[name][0], abs=1e-9)


def check_joints_and_frames(decoded: dict[str, list[tuple[int, Any]]], hand: HandConfig) -> None:
    torque = {m["tick"]: m for _, m in decoded[ch.TORQUE]}
    state = {m["tick"]: m for _, m in decoded[ch.JOINT_STATE]}
    assert len(decoded[fx.JOINTS]) == len(torque)
    for _, m in decoded[fx.JOINTS]:
        for i, name in enumerate(hand.joint_names):
            assert m[name]["applied_nm"] == torque[m["tick"]]["applied_nm"][i]
            assert m[name]["desired_nm"] == torque[m["tick"]]["desired_nm"][i]
            assert m[name]["angle_rad"] == state[m["tick"]]["angle_rad"][i]
            assert m[name]["tdt_torque_nm"] == state[m["tick"]]["tdt_torque_nm"][i]
    # every recorded command frame has its decoded twin, with the applied torques in it
    sent = [m for _, m in decoded[ch.CAN_TX]]
    commands = [m for _, m in decoded[fx.TX_DECODED]]
    assert len(commands) == len(sent)
    ids = {f.can_ids.torque_command: f for f in hand.fingers}
    checked = 0
    for raw, dec in zip(sent, commands, strict=True):
        assert (dec["id"], dec["tick"]) == (raw["id"], raw["tick"]) and dec["crc_ok"]
        finger = ids.get(raw["id"])
        if finger is not None and raw["tick"] in torque:
            assert dec["message"].startswith("TorqueCommand")
            for joint in finger.joints:
                applied = torque[raw["tick"]]["applied_nm"][hand.joint_names.index(joint.name)]
                assert dec["joints"][joint.name]["torque"] == pytest.approx(applied, abs=1e-3)
            checked += 1
    assert checked > 1000
    feedback = [m for _, m in decoded[fx.RX_DECODED] if m["message"].startswith("Feedback")]
    assert feedback and all(
        set(m["joints"])
        == {j.name for f in hand.fingers if f.name == m["finger"] for j in f.joints}
        for m in feedback
    )


def check_log(decoded: dict[str, list[tuple[int, Any]]]) -> None:
    events = decoded[ch.EVENTS]
    logs = decoded[fx.LOG]
    assert len(logs) == len(events) > 0
    for (t_event, event), (t_log, log) in zip(events, logs, strict=True):
        assert t_log == t_event
        assert log.timestamp.seconds * 1_000_000_000 + log.timestamp.nanos == t_event
        assert f"{event['kind']} {event['name']}" in log.message
        if event["kind"] == "fault":
            assert log.level == 4  # ERROR
        elif event["kind"] == "phase":
            assert log.level == 2  # INFO


def replay_live(log: Path, cwd: Path, code: int = 0) -> tuple[Live, bytes]:
    """``handctl replay LOG --live PORT`` with the viewer-like clients listening; what they
    received and what the command printed, once it exited ``code``."""
    live, done = served(["replay", str(log)], cwd, enough=3)
    assert done.returncode == code, done.stderr.decode()
    return live, done.stdout


def test_replay_live_streams_a_recording(run: Run, tmp_path: Path) -> None:
    """``handctl replay RUN.mcap --live PORT`` serves the file's channels at its own pace
    (the recorded pace), the per-tick ones sampled as a run's live view serves them."""
    from handctl.foxglove.live import SAMPLE_PERIOD_NS

    live, out = replay_live(run.path, tmp_path)
    for topic in WANTED:
        assert len(live.received[topic]) >= 3, topic
    for topic in (ch.JOINT_STATE, fx.JOINTS):  # recorded every tick, 1 ms apart
        gaps = [b - a for a, b in itertools.pairwise(live.log_times[topic])]
        assert all(g >= SAMPLE_PERIOD_NS for g in gaps), (topic, gaps[:20])
    assert b"messages of the log played" in out


def test_live_refuses_bad_input_with_exit_2(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from handctl.cli import main

    for port in ("0", "65536", "http"):
        with pytest.raises(SystemExit) as stop:
            main(["run", "recipe", str(RECIPE), "--hand", str(HAND_YAML), "--live", port])
        assert stop.value.code == 2
        err = capsys.readouterr().err
        assert f"expected a TCP port 1..65535, found '{port}'" in err
        assert "loopback" not in err
    for address in ("0.0.0.0", "0.0.0.0:8765", "localhost", "[::1]:8765"):
        # an address: the view's is not a choice, and the message says how to reach it
        with pytest.raises(SystemExit) as stop:
            main(["run", "recipe", str(RECIPE), "--hand", str(HAND_YAML), "--live", address])
        assert stop.value.code == 2
        err = capsys.readouterr().err
        assert f"found '{address}' (the live view binds the loopback interface" in err
        assert "through an SSH tunnel" in err
    assert main(["run", "recipe", str(RECIPE), "--hand", str(HAND_YAML), "--live"]) == 2
    err = capsys.readouterr().err
    assert "--live" in err and "--log RUN.mcap" in err


@pytest.mark.parametrize("command", ["run", "replay"])
def test_a_port_in_use_is_bad_input_before_anything_starts(
    tmp_path: Path, run: Run, command: str
) -> None:
    """Found out by the writer it emptied an existing log of the --log name and said only
    that the writer was gone (exit 1); found out by a replay it was the SDK's traceback."""
    log = tmp_path / "run.mcap"
    log.write_bytes(run.path.read_bytes())
    args = {
        "run": ["run", "recipe", str(RECIPE), "--hand", str(HAND_YAML), "--log", str(log)],
        "replay": ["replay", str(log)],
    }[command]
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        done = subprocess.run(
            [sys.executable, "-m", "handctl", *args, "--live", str(port)],
            cwd=tmp_path,
            env={**os.environ, "PYTHONPATH": str(ROOT)},
            capture_output=True,
            text=True,
            timeout=300,
            check=False,
        )
    assert done.returncode == 2, done.stderr
    assert (
        f"--live: expected a port the live view can listen on at 127.0.0.1, found '{port} ("
        in done.stderr
    )
    assert "Traceback" not in done.stderr
    assert "live: Foxglove" not in done.stderr and "live: streaming" not in done.stderr
    assert log.read_bytes() == run.path.read_bytes()


def test_replay_live_plays_a_truncated_log_to_its_cut(run: Run, tmp_path: Path) -> None:
    cut = tmp_path / "cut.mcap"
    data = run.path.read_bytes()
    cut.write_bytes(data[: len(data) // 2])
    live, out = replay_live(cut, tmp_path)
    assert b"TRUNCATED" in out
    assert len(live.received[fx.SCENE]) >= 3


def test_replay_live_plays_past_a_message_dated_far_after_the_rest(
    run: Run, tmp_path: Path
) -> None:
    """One message of the log at log time 2**64 - 1 (a log written with the mcap library):
    the live replay waited for it, for ever (found by an outside audit). A gap no run leaves
    is played past."""
    from .mcap_copy import rewrite

    with run.path.open("rb") as handle:
        last = max(m.log_time for _, _, m in make_reader(handle).iter_messages())
    far = tmp_path / "far.mcap"
    rewrite(run.path, far, times=lambda _topic, t: 2**64 - 1 if t == last else t)
    live, done = served(["replay", str(far), "--speed", "20"], tmp_path, enough=3)
    assert done.returncode == 0, done.stderr.decode()
    assert b"messages of the log played" in done.stdout
    assert live.received  # and served while it played


def test_replay_live_plays_a_damaged_log_around_its_damage(run: Run, tmp_path: Path) -> None:
    """A chunk that does not decompress: the channels were read again with mcap's own reader,
    which decompressed it, a traceback before anything was served."""
    from handctl.recording.reader import open_recording

    spans = open_recording(run.path).chunk_spans
    assert spans and len(spans) >= 3
    offset, length = spans[1]
    data = bytearray(run.path.read_bytes())
    data[offset + length - 40] ^= 0x10
    damaged = tmp_path / "damaged.mcap"
    damaged.write_bytes(bytes(data))
    live, out = replay_live(damaged, tmp_path, code=1)  # played, and said not whole
    assert b"DAMAGED: chunk 1 at byte" in out
    assert len(live.received[fx.SCENE]) >= 3


#: A short recipe that completes: close gently and hold, no objects to find.
SHORT_RECIPE = """\
recipe: close_and_hold
description: close the hand gently and hold, for the live-view test
phases:
  - name: close
    torques: {f1_j1: 0.05, f1_j2: 0.03, f1_j3: 0.02, f2_j1: 0.05, f2_j2: 0.03, f2_j3: 0.02,
              f3_j1: -0.05, f3_j2: -0.03, f3_j3: -0.02}
    ramp_s: 0.2
    max_s: 0.8
    on_timeout: next
  - name: hold
    torques: {f1_j1: 0.05, f1_j2: 0.03, f1_j3: 0.02, f2_j1: 0.05, f2_j2: 0.03, f2_j3: 0.02,
              f3_j1: -0.05, f3_j2: -0.03, f3_j3: -0.02}
    max_s: 0.8
    on_timeout: next
"""
#: Per-tick channels the viewer listens to, recorded and derived, and the scene.
SAMPLED = (ch.JOINT_STATE, ch.CAN_RX, fx.JOINTS, fx.RX_DECODED)


def test_a_live_run_with_a_client_completes_and_records_every_tick(
    tmp_path: Path, hand: HandConfig
) -> None:
    """A lockstep recipe run to its end while a client listens to the live view: the run
    completes, the file holds every tick and drops nothing, and the client got the per-tick
    channels sampled (each frame id apart) while the file has them every tick."""
    from handctl.foxglove.live import SAMPLE_PERIOD_NS

    recipe = tmp_path / "close_and_hold.yaml"
    recipe.write_text(SHORT_RECIPE)
    path = tmp_path / "run.mcap"
    summary_path = tmp_path / "summary.json"
    # one client, listening until the server closes with the end of the run
    live, done = served(
        [
            "run",
            "recipe",
            str(recipe),
            "--hand",
            str(HAND_YAML),
            "--lockstep",
            "--log",
            str(path),
            "--summary-json",
            str(summary_path),
        ],
        tmp_path,
        enough=1 << 30,
        clients=((*SAMPLED, fx.SCENE),),
    )
    assert done.returncode == 0, done.stderr.decode()
    summary = json.loads(summary_path.read_text())
    assert summary["outcome"] == "completed"
    timing: list[int] = []
    recorded: dict[str, list[int]] = defaultdict(list)
    for _, channel, message in mcap_messages(path):
        if channel.topic == ch.TIMING:
            timing.append(json.loads(message.data)["tick"])
        recorded[channel.topic].append(message.log_time)
    assert timing == list(range(len(timing))) and len(timing) >= 1600
    with path.open("rb") as handle:
        metadata = {m.name: m.metadata for m in make_reader(handle).iter_metadata()}
    end = metadata[ch.META_END]
    assert end["ended"] == ch.ENDED_CLOSED
    assert int(end["ticks"]) == len(timing)
    for dropped in ("dropped_ticks", "dropped_frames", "dropped_events", "dropped_poses"):
        assert end[dropped] == "0", end
    # Every control tick's joint state is in the file, a tick (1 ms) apart.
    steps = {b - a for a, b in itertools.pairwise(recorded[ch.JOINT_STATE])}
    assert steps == {1_000_000}
    # The viewer got a scene, and the per-tick channels sampled: per frame id on the frame
    # channels, consecutive messages the same tick or a sampling period apart, but for the
    # newest of a key before it went quiet for a period (a frame no longer sent, the end).
    assert live.received[fx.SCENE], {t: len(v) for t, v in live.received.items()}
    for topic in SAMPLED:
        assert live.received[topic], topic
        quiet = _newest_before_quiet(path, topic, SAMPLE_PERIOD_NS)
        by_key: dict[int, list[int]] = defaultdict(list)
        for payload, log_time in zip(live.received[topic], live.log_times[topic], strict=True):
            by_key[_key(topic, payload)].append(log_time)
        for key, times in by_key.items():
            early = [
                (a, b)
                for a, b in itertools.pairwise(times)
                if 0 < b - a < SAMPLE_PERIOD_NS and b not in quiet[key]
            ]
            assert not early, (topic, key, early[:20])
    # Each kind of frame reaches the viewer: the 1 kHz feedback and the 10 Hz heartbeats.
    ids = {json.loads(m)["id"] for m in live.received[ch.CAN_RX]}
    for kind in ("feedback", "heartbeat"):
        assert {f.can_ids.as_dict()[kind] for f in hand.fingers} <= ids, (kind, sorted(ids))


#: Every channel a run's writer serves, recorded and derived.
EVERY_TOPIC = (
    *(c.topic for c in ch.CHANNELS),
    *(fx.SCENE, fx.TRANSFORMS, fx.LOG, fx.JOINTS, fx.RX_DECODED, fx.TX_DECODED),
)


def _newest(topic: str, pairs: Iterable[tuple[bytes, int]]) -> dict[int, tuple[int, bytes]]:
    """The newest (log time, payload) of each key of ``topic``: its frame id on a frame
    channel (as the live view samples it), else one."""
    newest: dict[int, tuple[int, bytes]] = {}
    for payload, log_time in pairs:
        key = _key(topic, payload)
        if key not in newest or log_time >= newest[key][0]:
            newest[key] = (log_time, payload)
    return newest


def test_the_live_view_ends_where_the_log_ends(tmp_path: Path) -> None:
    """The sampling dropped a message within a period of the last one served and never
    served the newest: the view of a run that had ended stayed on up to 9 ticks before its
    end, /safety/state 'stopping' and a torque that was not zero, while the log ended idle,
    every torque zero (found by an outside audit). A client of every channel, listening to
    the end of a lockstep run, last got of each channel (and frame id) what the log has
    last."""
    recipe = tmp_path / "close_and_hold.yaml"
    recipe.write_text(SHORT_RECIPE)
    path = tmp_path / "run.mcap"
    live, done = served(
        [
            *("run", "recipe", str(recipe), "--hand", str(HAND_YAML)),
            *("--lockstep", "--log", str(path)),
        ],
        tmp_path,
        enough=1 << 30,
        clients=(EVERY_TOPIC,),
    )
    assert done.returncode == 0, done.stderr.decode()
    states = [m for _, c, m in mcap_messages(path) if c.topic == ch.SAFETY]
    state = json.loads(max(states, key=lambda m: m.log_time).data)
    assert state["state"] == "idle", state
    _assert_ends_as(live, path)


def _assert_ends_as(live: Live, path: Path) -> None:
    """What the client got last of each sampled channel (and frame id) is the log's last."""
    from handctl.foxglove.live import SAMPLING

    logged: dict[str, list[tuple[bytes, int]]] = defaultdict(list)
    for _, channel, message in mcap_messages(path):
        logged[channel.topic].append((bytes(message.data), message.log_time))
    for topic in SAMPLING:
        shown = _newest(topic, zip(live.received[topic], live.log_times[topic], strict=True))
        assert shown == _newest(topic, logged[topic]), topic


def test_replay_live_ends_where_the_log_ends(run: Run, tmp_path: Path) -> None:
    """``replay --live`` held back the log's last messages of each sampled channel as a
    run's live view did, and ended the view before them (an outside audit)."""
    live, done = served(["replay", str(run.path)], tmp_path, enough=1 << 30, clients=(EVERY_TOPIC,))
    assert done.returncode == 0, done.stderr.decode()
    _assert_ends_as(live, run.path)


def _key(topic: str, payload: bytes) -> int:
    """The key the live view samples a message of ``topic`` by: its frame id on a frame
    channel, else one for all."""
    from handctl.foxglove.live import PER_FRAME, SAMPLING

    return int(json.loads(payload)["id"]) if SAMPLING.get(topic) == PER_FRAME else 0


def _newest_before_quiet(path: Path, topic: str, period_ns: int) -> dict[int, set[int]]:
    """Per key of ``topic`` in the log at ``path``, the log times of its messages after
    which the key sent nothing for ``period_ns`` (its last among them)."""
    times: dict[int, list[int]] = defaultdict(list)
    for _, channel, message in mcap_messages(path):
        if channel.topic == topic:
            times[_key(topic, message.data)].append(message.log_time)
    quiet: dict[int, set[int]] = defaultdict(set)
    for key, each in times.items():
        for a, b in itertools.pairwise([*each, each[-1] + period_ns]):
            if b - a >= period_ns:
                quiet[key].add(a)
    return quiet


async def _first_advertise(port: int) -> set[str]:
    async with websockets.connect(
        f"ws://127.0.0.1:{port}", subprotocols=[SUBPROTOCOL], max_size=None
    ) as ws:
        while True:
            raw = await asyncio.wait_for(ws.recv(), 5.0)
            if isinstance(raw, str) and json.loads(raw)["op"] == "advertise":
                return {c["topic"] for c in json.loads(raw)["channels"]}


def test_the_live_server_listens_only_once_its_channels_are_there() -> None:
    """A client that connects while channels are still being added can be told ``Unknown
    channel ID`` for one it was advertised, and get nothing of it (the SDK's race; the
    replay-live test lost the joint states to it one run in three). So the server binds its
    port only when every channel is there, and a client's first advertise names them all."""
    from handctl.foxglove.live import LiveServer

    port = free_port()
    server = LiveServer(port)
    try:
        with pytest.raises(OSError):
            socket.create_connection(("127.0.0.1", port), timeout=1.0).close()
        topics = {"/hand/joint_state", "/hand/joints", "/foxglove/scene"}
        for topic in sorted(topics):
            server.add_channel(topic, "handctl.Test", "jsonschema", b"{}", "json")
        server.start()
        assert asyncio.run(_first_advertise(port)) == topics
    finally:
        server.close()


#: The topic whose one message ends what ``_subscribed`` collects
END = "/end"


async def _subscribed(server: Any, feed: Any) -> list[tuple[str, int, bytes]]:
    """A client of every channel of ``server`` (a ``LiveServer``): once the server has it
    for each channel, ``feed(server)`` logs; what it received up to the message on ``END``,
    as (topic, log time, payload) in the order received."""
    async with websockets.connect(
        f"ws://127.0.0.1:{server.port}", subprotocols=[SUBPROTOCOL], max_size=None
    ) as ws:
        topics: dict[int, str] = {}
        while not topics:
            raw = await asyncio.wait_for(ws.recv(), 30.0)
            if isinstance(raw, str) and json.loads(raw)["op"] == "advertise":
                topics = {c["id"]: c["topic"] for c in json.loads(raw)["channels"]}
        subs = [{"id": i, "channelId": i} for i in topics]
        await ws.send(json.dumps({"op": "subscribe", "subscriptions": subs}))
        while not all(c.has_sinks() for c in server.channels.values()):
            await asyncio.sleep(0.01)  # the SDK takes the subscription on its own thread
        feed(server)
        got: list[tuple[str, int, bytes]] = []
        while not got or got[-1][0] != END:
            raw = await asyncio.wait_for(ws.recv(), 30.0)
            if isinstance(raw, bytes) and raw[0] == 0x01:
                sub, log_time = struct.unpack_from("<IQ", raw, 1)
                got.append((topics[sub], log_time, bytes(raw[13:])))
        return got


def test_a_frame_no_longer_sent_and_a_view_held_back_are_served_their_newest() -> None:
    """The newest message of a key the sampling held back is served once its key has been
    quiet for a period of its topic's log time (a frame id no longer sent, while others go
    on), and every message held while the writer held the view back (``hold``) is served,
    the newest of each topic and key, oldest first, when it is served again (``send_held``):
    both were lost, and the view stayed on older values for good (an outside audit)."""
    from handctl.foxglove.live import SAMPLE_PERIOD_NS, LiveServer

    ms = SAMPLE_PERIOD_NS // 10

    def frame(frame_id: int, t: int) -> bytes:
        return json.dumps({"id": frame_id, "t": t}).encode()

    def feed(server: LiveServer) -> None:
        for t in range(0, 40 * ms, ms):  # id 1 every tick; id 2 for 5 ticks only
            server.log(ch.CAN_RX, t, frame(1, t), 1)
            if t < 5 * ms:
                server.log(ch.CAN_RX, t, frame(2, t), 2)
        for t in range(40 * ms, 44 * ms, ms):  # the view held back
            server.hold(ch.CAN_RX, t, frame(1, t), 1)
            server.hold(ch.SAFETY, t, b'{"state": "%d"}' % t)
            server.hold(fx.SCENE, t, b"scene %d" % t)
        server.send_held()
        server.log(END, 44 * ms, b"end")

    server = LiveServer(free_port())
    for topic in (ch.CAN_RX, ch.SAFETY, fx.SCENE, END):
        server.add_channel(topic, "handctl.Test", "jsonschema", b"{}", "json")
    server.start()
    try:
        got = asyncio.run(_subscribed(server, feed))
    finally:
        server.close()
    frames = [(json.loads(p)["id"], t // ms) for topic, t, p in got if topic == ch.CAN_RX]
    # id 2's newest (tick 4), once id 1's ticks are a period past it; id 1's newest after
    # the view was held back (tick 43), and nothing of id 1 at 36..39 before it
    assert frames == [(1, 0), (2, 0), (1, 10), (2, 4), (1, 20), (1, 30), (1, 43)], frames
    held = [(topic, t // ms, p) for topic, t, p in got if topic != ch.CAN_RX]
    assert held[-1] == (END, 44, b"end")
    assert sorted(held[:-1]) == [
        (fx.SCENE, 43, b"scene %d" % (43 * ms)),
        (ch.SAFETY, 43, b'{"state": "%d"}' % (43 * ms)),
    ], held


#: The payload of each message of the backlog test: large, so that the kernel's socket
#: buffers hold few of them beside the server's queue
BIG = 1 << 16


async def _stalled_then_read(server: Any, count: int) -> list[int]:
    """A client of every channel of ``server`` that reads nothing while ``count`` messages
    of ``BIG`` bytes are served (its event loop is busy serving them), then reads up to the
    last; the numbers of the messages it got."""
    sock = socket.socket()
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
    sock.connect(("127.0.0.1", server.port))
    async with websockets.connect(
        f"ws://127.0.0.1:{server.port}",
        sock=sock,
        subprotocols=[SUBPROTOCOL],
        max_size=None,
        max_queue=1,
    ) as ws:
        while True:
            raw = await asyncio.wait_for(ws.recv(), 30.0)
            if isinstance(raw, str) and json.loads(raw)["op"] == "advertise":
                channels = json.loads(raw)["channels"]
                break
        subs = [{"id": c["id"], "channelId": c["id"]} for c in channels]
        await ws.send(json.dumps({"op": "subscribe", "subscriptions": subs}))
        while not all(c.has_sinks() for c in server.channels.values()):
            await asyncio.sleep(0.01)
        for k in range(count):  # nothing is read meanwhile: the loop is here
            server.log("/big", k, b"%08d" % k + bytes(BIG - 8))
        got: list[int] = []
        while not got or got[-1] != count - 1:
            raw = await asyncio.wait_for(ws.recv(), 30.0)
            if isinstance(raw, bytes) and raw[0] == 0x01:
                got.append(int(raw[13:21]))
        return got


def test_a_client_that_stops_reading_costs_the_writer_a_bounded_queue() -> None:
    """Each client that stopped reading cost the writer the SDK's default backlog, 1024
    messages (some 0.9 MB: 200 such clients, 176 MB), when the live view never needs more
    than a fraction of a second of it (an outside audit). A client's queue holds at most
    ``LIVE_BACKLOG`` messages, the newest, and the oldest are dropped: what a stalled client
    gets once it reads again is that many and what its socket buffers held, the last one
    served among them."""
    from handctl.foxglove.live import LIVE_BACKLOG, LiveServer

    server = LiveServer(free_port())
    server.add_channel("/big", "handctl.Test", "jsonschema", b"{}", "json")
    server.start()
    count = 3 * 1024
    try:
        got = asyncio.run(_stalled_then_read(server, count))
    finally:
        server.close()
    # what the kernel can hold of it (the server's send buffer at its most, the client's
    # receive buffer) and what is on its way in the SDK's and the client's hands
    wmem_max = int(Path("/proc/sys/net/ipv4/tcp_wmem").read_text().split()[2])
    in_buffers = (wmem_max + 4 * BIG) // BIG + 4
    assert got == sorted(got) and got[-1] == count - 1
    assert len(got) <= LIVE_BACKLOG + in_buffers, (len(got), in_buffers)


async def _junk(port: int, count: int) -> None:
    async with websockets.connect(
        f"ws://127.0.0.1:{port}", subprotocols=[SUBPROTOCOL], max_size=None
    ) as ws:
        await ws.send(json.dumps({"op": "\x1b]2;PWNED\x07\x1b[31mevil"}))  # shown first
        for k in range(count):
            await ws.send(f"junk {k}")
        await ws.send(
            json.dumps({"op": "subscribe", "subscriptions": [{"id": 1, "channelId": 999}]})
        )
        await asyncio.sleep(0.5)  # the server reads them all


def test_a_client_sending_junk_gets_a_few_lines_on_stderr_not_one_each(
    capfd: pytest.CaptureFixture[str],
) -> None:
    """Any local user may connect: a client sending 200 000 invalid messages put eleven
    thousand lines on the operator's terminal and 800 kB into the run's summary (found by an
    outside audit). The first few are said, the rest counted."""
    from handctl.foxglove.live import NOTES_SHOWN, LiveServer

    port = free_port()
    server = LiveServer(port)
    server.add_channel("/hand/joints", "handctl.Test", "jsonschema", b"{}", "json")
    server.start()
    try:
        asyncio.run(_junk(port, 50))
    finally:
        assert server.close()
    err = capfd.readouterr().err.splitlines()
    said = [line for line in err if line.startswith("live view: ")]
    assert len(said) == NOTES_SHOWN + 1, err
    assert "Invalid message" in said[0] and "PWNED" in said[0]
    more = said[-1].removeprefix("live view: ").split()
    assert more[1:] == ["more", "notes", "of", "its", "clients", "not", "shown"]
    assert int(more[0]) >= 51 - NOTES_SHOWN  # every junk message counted, none lost
    assert len(err) == len(said)  # nothing else printed of them
    assert "\x1b" not in capfd.readouterr().err + "\n".join(err)  # no escape reaches a terminal


async def _offer(port: int, subprotocol: str) -> int:
    """The HTTP status of a WebSocket handshake offering ``subprotocol`` alone."""
    try:
        async with websockets.connect(
            f"ws://127.0.0.1:{port}", subprotocols=[Subprotocol(subprotocol)]
        ):
            return 101
    except websockets.InvalidStatus as refused:
        return int(refused.response.status_code)


def test_a_viewer_offering_the_old_subprotocol_is_told_which_one_is_spoken(
    capfd: pytest.CaptureFixture[str],
) -> None:
    """The SDK's server takes only clients offering ``foxglove.sdk.v1``; one offering only
    ``foxglove.websocket.v1`` (older Foxglove, Lichtblick before December 2025) is refused
    with HTTP 400, and the operator saw only "Dropping client ...: handshake failed" (found
    by an outside audit). The SDK's note is the same whatever the cause, and the
    subprotocol said beside the first went to a connection that had sent nothing, the
    viewer's own note left bare (an outside audit): the refusals are counted and said once
    at the end, with the subprotocol spoken."""
    from handctl.foxglove.live import LiveServer

    port = free_port()
    server = LiveServer(port)
    server.add_channel("/hand/joints", "handctl.Test", "jsonschema", b"{}", "json")
    server.start()
    err = ""
    try:
        socket.create_connection(("127.0.0.1", port), timeout=10).close()  # sent nothing
        assert asyncio.run(_offer(port, "foxglove.websocket.v1")) == 400
        assert asyncio.run(_offer(port, "foxglove.websocket.v1")) == 400
        assert asyncio.run(_offer(port, SUBPROTOCOL)) == 101
        deadline = time.monotonic() + 60  # the SDK notes it from its own thread
        while err.count("handshake failed") < 3 and time.monotonic() < deadline:
            time.sleep(0.05)
            err += capfd.readouterr().err
    finally:
        assert server.close()
    err += capfd.readouterr().err
    said = [line for line in err.splitlines() if "handshake failed" in line]
    assert len(said) == 3, err
    for line in said:  # the SDK's note, as it is: it does not say why
        assert line.startswith("live view: Dropping client 127.0.0.1:"), line
        assert line.endswith("handshake failed"), line
    end = [line for line in err.splitlines() if "refused at the WebSocket handshake" in line]
    assert end == [err.splitlines()[-1]], err
    assert end[0].startswith("live view: 3 connection(s) refused at the WebSocket handshake")
    assert "speaks the WebSocket subprotocol foxglove.sdk.v1 only" in end[0]


def test_a_port_taken_after_the_check_is_said_against_live() -> None:
    """Free when the command began, taken by another program before the server bound it (a
    replay binds after its summary and re-run): that was the SDK's RuntimeError traceback."""
    from handctl.errors import ConfigError
    from handctl.foxglove.live import LiveServer

    port = free_port()
    server = LiveServer(port)
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as taker:
        taker.bind(("127.0.0.1", port))
        taker.listen()
        with pytest.raises(ConfigError) as err:
            server.start()
    assert err.value.file == "--live"
    assert "another program has taken it since" in err.value.expected
    # the SDK's reason whole: cut to a value's length, it was "Failed to bind p... Address"
    said = str(err.value)
    assert f"found {port} (" in said and "Address already in use" in said, said
    assert "..." not in said


class _StalledViewer:
    """A viewer that subscribes to every channel and then stops reading (frozen, asleep): a
    WebSocket client by hand on a plain socket, since a client library reads for its user."""

    def __init__(self, port: int, proc: subprocess.Popen[bytes]) -> None:
        self.sock = self._connect(port, proc)
        key = "dGhlIHNhbXBsZSBub25jZQ=="
        self.sock.sendall(
            (
                f"GET / HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nUpgrade: websocket\r\n"
                f"Connection: Upgrade\r\nSec-WebSocket-Key: {key}\r\n"
                f"Sec-WebSocket-Version: 13\r\nSec-WebSocket-Protocol: {SUBPROTOCOL}\r\n\r\n"
            ).encode()
        )
        head = b""
        while b"\r\n\r\n" not in head:
            head += self._exactly(1)
        assert head.startswith(b"HTTP/1.1 101"), head
        while True:
            opcode, payload = self._frame()
            if opcode == 1 and json.loads(payload).get("op") == "advertise":
                channels = json.loads(payload)["channels"]
                break
        subs = [{"id": c["id"], "channelId": c["id"]} for c in channels]
        self._send_text(json.dumps({"op": "subscribe", "subscriptions": subs}).encode())

    @staticmethod
    def _connect(port: int, proc: subprocess.Popen[bytes]) -> socket.socket:
        while True:
            sock = socket.socket()
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
            try:
                sock.connect(("127.0.0.1", port))
                return sock
            except OSError:
                sock.close()
                assert proc.poll() is None, "ended before its live server accepted"
                time.sleep(0.05)

    def _exactly(self, n: int) -> bytes:
        data = b""
        while len(data) < n:
            chunk = self.sock.recv(n - len(data))
            assert chunk, "the server closed"
            data += chunk
        return data

    def _frame(self) -> tuple[int, bytes]:
        first, second = self._exactly(2)
        n = second & 0x7F
        if n == 126:
            (n,) = struct.unpack(">H", self._exactly(2))
        elif n == 127:
            (n,) = struct.unpack(">Q", self._exactly(8))
        return first & 0x0F, self._exactly(n)

    def _send_text(self, payload: bytes) -> None:
        mask = os.urandom(4)
        header = bytes([0x81, 0x80 | 126]) + struct.pack(">H", len(payload))
        if len(payload) < 126:
            header = bytes([0x81, 0x80 | len(payload)])
        masked = bytes(b ^ mask[i % 4] for i, b in enumerate(payload))
        self.sock.sendall(header + mask + masked)


def test_a_viewer_that_stops_reading_does_not_hold_the_run_at_its_end(tmp_path: Path) -> None:
    """The SDK's stop waits for every connection to close, and a viewer that stopped
    reading never lets it: the writer, its log long finished, hung until it was killed 20 s
    later and the summary lost its recording. The live view is now left behind instead."""
    port = free_port()
    summary_path = tmp_path / "summary.json"
    command = [
        *(sys.executable, "-m", "handctl", "run", "recipe"),
        str(RECIPE),
        *("--lockstep", "--log", str(tmp_path / "run.mcap")),
        *("--summary-json", str(summary_path), "--live", str(port)),
    ]
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    with subprocess.Popen(
        command, cwd=tmp_path, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE
    ) as proc:
        try:
            viewer = _StalledViewer(port, proc)
            _, err = proc.communicate(timeout=300)
            viewer.sock.close()
        finally:
            if proc.poll() is None:
                proc.kill()
    assert proc.returncode == 0, err.decode()
    recording = json.loads(summary_path.read_text())["recording"]
    assert "error" not in recording, recording
    assert recording["ticks"] > 10_000 and recording["writer_exit"] == 0


def test_many_viewers_that_stop_reading_cost_the_log_nothing(tmp_path: Path) -> None:
    """Each message is queued for each client in the writer, so 200 local viewers that
    subscribed to everything and stopped reading held the writer back until its rings
    overflowed: a lockstep run lost its last 2084 ticks, exit 0 (an outside audit). The live
    view now gives way while the writer is behind: the log keeps every record."""
    port = free_port()
    summary_path = tmp_path / "summary.json"
    command = [
        *(sys.executable, "-m", "handctl", "run", "recipe"),
        str(RECIPE),
        *("--lockstep", "--log", str(tmp_path / "run.mcap")),
        *("--summary-json", str(summary_path), "--live", str(port)),
    ]
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    viewers = []
    with subprocess.Popen(
        command, cwd=tmp_path, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE
    ) as proc:
        try:
            viewers = [_StalledViewer(port, proc) for _ in range(200)]
            _, err = proc.communicate(timeout=600)
        finally:
            for viewer in viewers:
                viewer.sock.close()
            if proc.poll() is None:
                proc.kill()
    assert proc.returncode == 0, err.decode()
    recording = json.loads(summary_path.read_text())["recording"]
    assert "error" not in recording, recording
    dropped = {k: v for k, v in recording.items() if k.startswith("dropped_")}
    assert set(dropped.values()) == {0}, (dropped, recording.get("writer_notes"))


def test_a_port_taken_before_the_writer_binds_it_leaves_the_previous_log(
    tmp_path: Path, hand: HandConfig
) -> None:
    """Free when the run's options were checked, taken by another program before the
    recording's writer bound it: the run's previous log, given again as --log, was emptied
    (0 bytes) and the run exited 1 (an outside probe). Bad input now, naming --live, and
    the previous log as it was."""
    from handctl.errors import ConfigError
    from handctl.recording.metadata import start_metadata
    from handctl.recording.reader import open_recording
    from handctl.recording.recorder import Recorder

    log = tmp_path / "run.mcap"
    previous = b"the previous run's log " * 1000
    log.write_bytes(previous)
    port = free_port()
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as taker:
        taker.bind(("127.0.0.1", port))
        taker.listen()
        recorder = Recorder(log, hand, start_metadata(hand, None, ("t",)), live_port=port)
        # closed as a run's start-up closes it, the error in flight kept
        with pytest.raises(ConfigError) as err, recorder:
            recorder.wait_ready()
    assert err.value.file == "--live"
    assert "nothing was sent and the log is as it was" in err.value.expected
    # one message, the port and the SDK's reason: the server's own refusal was nested in it,
    # its reason cut ("found '8814 (FoxgloveError: Failed to bind p... Address already...")
    said = str(err.value)
    assert said.count("expected") == 1 and f"found {port} (" in said, said
    assert "Address already in use" in said and "..." not in said
    assert log.read_bytes() == previous
    # with the port free, the same log is replaced by the run's, whole
    recorder = Recorder(log, hand, start_metadata(hand, None, ("test",)), live_port=free_port())
    recorder.wait_ready()
    recorder.close({"outcome": "test"})
    assert open_recording(log).complete


def test_a_port_taken_before_the_writer_binds_it_leaves_no_file_at_a_new_path(
    tmp_path: Path, hand: HandConfig
) -> None:
    """The same refusal where --log named nothing: a 0-byte file was left at the path (the
    empty one made to hold it, put there as the run's), under "the log is as it was" (found
    by an outside audit). The path names nothing again, and nothing is left beside it. The
    port is taken before the recorder starts: the run's own check, which would have refused
    it, is not the recorder's."""
    from handctl.errors import ConfigError
    from handctl.recording.metadata import start_metadata
    from handctl.recording.recorder import Recorder

    log = tmp_path / "new.mcap"
    port = free_port()
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as taker:
        taker.bind(("127.0.0.1", port))
        taker.listen()
        recorder = Recorder(
            log, hand, start_metadata(hand, None, ("t",)), live_port=port, keep_previous=True
        )
        with pytest.raises(ConfigError) as err, recorder:  # as a run's start-up closes it
            recorder.wait_ready()
    assert err.value.file == "--live"
    assert not log.exists() and list(tmp_path.iterdir()) == []
    assert not recorder.stats.get("previous_kept")


def _served_when_said(proc: subprocess.Popen[bytes], line: bytes, port: int) -> None:
    """``proc``'s stderr read until ``line``, then ``port`` connected to at once (no
    retry: served when said); ``proc`` then ends with exit 0."""
    assert proc.stderr is not None
    said = b""
    while line not in said:
        got = proc.stderr.readline()
        assert got, said.decode()
        said += got
    with socket.create_connection(("127.0.0.1", port), timeout=10):
        pass
    proc.stderr.read()
    assert proc.wait(timeout=300) == 0


def test_the_live_line_is_said_once_the_port_is_served(tmp_path: Path) -> None:
    """The "live: Foxglove WebSocket on ws://..." line came as the command began, a second
    before the writer bound the port: a client that connected when told was refused (an
    outside probe). It is said once the port is served."""
    port = free_port()
    command = [
        *(sys.executable, "-m", "handctl", "run", "recipe", str(RECIPE), "--lockstep"),
        *("--log", str(tmp_path / "run.mcap"), "--live", str(port), "--max-seconds", "1"),
    ]
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    with subprocess.Popen(
        command, cwd=tmp_path, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE
    ) as proc:
        _served_when_said(proc, b"live: Foxglove WebSocket on", port)
    # and replay's, which was said before the recording was even read (seconds before)
    port = free_port()
    command = [sys.executable, "-m", "handctl", "replay", str(tmp_path / "run.mcap")]
    with subprocess.Popen(
        [*command, "--live", str(port), "--speed", "4"],
        cwd=tmp_path,
        env=env,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
    ) as proc:
        _served_when_said(proc, b"live: streaming", port)


def test_the_live_lines_show_no_control_character_of_a_file_name(tmp_path: Path) -> None:
    """A file name is the user's value: the live lines printed the hand's (quoted by
    ``shlex``, which leaves control characters as they are) and the replayed log's raw, and
    an escape sequence in either retitled or recoloured the terminal (found by an outside
    audit). The layout command stays one the user can paste: ``$'...'``, as bash reads it."""
    hand = tmp_path / "hand\x1b]0;PWNED\x07.yaml"
    hand.write_bytes(HAND_YAML.read_bytes())
    log = tmp_path / "evil\x1b[31mred.mcap"
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    said = []
    for args in (
        ["run", "recipe", str(RECIPE), "--hand", str(hand), "--lockstep", "--log", str(log)],
        ["replay", str(log), "--speed", "4"],
    ):
        if args[0] == "run":
            args += ["--max-seconds", "1"]
        done = subprocess.run(
            [sys.executable, "-m", "handctl", *args, "--live", str(free_port())],
            cwd=tmp_path,
            env=env,
            capture_output=True,
            text=True,
            timeout=300,
            check=False,
        )
        assert done.returncode == 0, done.stderr
        said.append(done.stdout + done.stderr)
    assert not any(c in "".join(said) for c in "\x1b\x07"), said
    folder = str(tmp_path)
    assert f"handctl layout $'{folder}/hand\\x1b]0;PWNED\\x07.yaml' -o LAYOUT.json" in said[0]
    assert f"live: streaming {folder}/evil\\x1b[31mred.mcap at 4x" in said[1]
