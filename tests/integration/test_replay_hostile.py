"""``handctl replay`` on recordings altered after the run: a message that is not what its
channel says, metadata that does not parse, tick rows out of sequence, and command frames the
supervisor would never have let through. Each is bad input (exit 2) naming the file, the
message or record, the field, what was expected and what was found; never a traceback, never
a re-run that claims bit-exact on what it did not compare, and nothing onto a bus."""

from __future__ import annotations

import json
import struct
from collections.abc import Callable, Iterator
from dataclasses import replace
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import pytest
import yaml
from mcap.reader import make_reader
from mcap.writer import Writer

from handctl.config import HandConfig
from handctl.errors import ConfigError
from handctl.online.bus import open_bus
from handctl.protocol import NODE_COMMANDS, Protocol
from handctl.recording import channels as ch
from handctl.recording.frames import logged_frames, to_bus
from handctl.recording.reader import MAGIC, Recording, iter_decoded, open_recording
from handctl.recording.rerun import rerun
from handctl.recording.series import load_series

from ..conftest import ROOT, handctl
from .mcap_copy import Change, rewrite
from .rig import short_recipe
from .test_recording import Recorded, record_run


@pytest.fixture(scope="module")
def recorded(hand: HandConfig, tmp_path_factory: pytest.TempPathFactory) -> Recorded:
    directory = tmp_path_factory.mktemp("hostile")
    return record_run(hand, short_recipe(hand, directory), directory / "run.mcap", troubles=False)


def _refused_with_nothing_sent(
    recording: Recording, hand: HandConfig, channel: str, speed: float = 1.0
) -> str:
    """``to_bus`` of ``recording`` onto a virtual bus a listener is on: refused, nothing
    heard; the refusal's text."""
    with open_bus(f"virtual:{channel}", hand.bus) as listener:
        with pytest.raises(ConfigError) as caught:
            to_bus(recording, f"virtual:{channel}", speed=speed)
        heard = listener.drain(limit=10**6)
    assert heard == []
    return str(caught.value)


def one_message(topic: str, index: int, alter: Callable[[bytes], bytes]) -> Change:
    def change(t: str, i: int, raw: bytes) -> bytes:
        return alter(raw) if (t, i) == (topic, index) else raw

    return change


def field(key: str, value: object) -> Callable[[bytes], bytes]:
    def alter(raw: bytes) -> bytes:
        msg = json.loads(raw)
        if value is ...:
            del msg[key]
        else:
            msg[key] = value
        return json.dumps(msg).encode()

    return alter


# -- a message that is not what its channel says -------------------------------------------------
@pytest.mark.parametrize(
    ("topic", "alter", "key", "expected"),
    [
        (ch.TIMING, field("scheduled_ns", ...), "scheduled_ns", "expected an integer"),
        (ch.TIMING, field("stage_cpu_ns", "x"), "stage_cpu_ns", "expected an object"),
        (ch.TORQUE, field("applied_nm", None), "applied_nm", "expected an array"),
        (ch.TORQUE, field("desired_nm", [0.0, 1.0]), "desired_nm", "9 values, one per joint"),
        (ch.JOINT_STATE, field("angle_rad", ["x"] * 9), "angle_rad", "each item a number"),
        (ch.PHASE, field("phase", 7), "phase", "expected a string"),
        (ch.OBJECTS, field("objects", 1.5), "objects", "expected an array"),
        (ch.EVENTS, field("kind", "other"), "kind", "expected one of fault, state"),
        # counts and ticks a reader adds up or indexes by: a forged negative is refused
        (ch.EVENTS, field("count", -5), "count", "expected an integer, at least 0, found -5"),
        (ch.TIMING, field("missed", -3), "missed", "expected an integer, at least 0, found -3"),
        (ch.TIMING, field("tick", -1), "tick", "expected an integer, at least 0, found -1"),
        (ch.TORQUE, field("tick", 2.5), "tick", "expected an integer, at least 0, found 2.5"),
        (ch.CAN_RX, field("data", "zz"), "data", "a frame's payload as hex"),
        (ch.CAN_TX, field("id", 1 << 40), "id", "a CAN id"),
        (ch.TIMING, lambda raw: b"not json", "", "expected a JSON object"),
        (ch.TORQUE, lambda raw: b"[1, 2]", "", "expected a JSON object"),
        # nested deeper than Python's recursion limit: the message is bounded, not the value
        (ch.TORQUE, lambda raw: b"[" * 1000 + b"]" * 1000, "", "found [[[[[...]]]]]"),
        (ch.TIMING, lambda raw: b"[" * 5000 + b"]" * 5000, "", "expected a JSON object"),
        # frames too, in the summary: it counted a refusal by the raw bytes
        (ch.CAN_TX, lambda raw: b'garbage "ok":false', "", "expected a JSON object"),
        (ch.CAN_RX, field("data", "0"), "data", "a frame's payload as hex"),
        # more than the supervisor ever applies: the summary reported 1e40 N·m as a fact
        (ch.TORQUE, field("applied_nm", [1e40] * 9), "applied_nm[0] (f1_j1)", "tau_max"),
        # nor a NaN (the writer's null), which no comparison finds over the limit: it passed
        (ch.TORQUE, field("applied_nm", [0.0, None, *[0.0] * 7]), "applied_nm[1] (f1_j2)", "NaN"),
    ],
)
def test_a_message_not_of_its_channel_is_named(
    recorded: Recorded,
    tmp_path: Path,
    topic: str,
    alter: Callable[[bytes], bytes],
    key: str,
    expected: str,
) -> None:
    bad = tmp_path / "bad.mcap"
    index = {ch.EVENTS: 1, ch.OBJECTS: 5}.get(topic, 300)
    rewrite(recorded.path, bad, one_message(topic, index, alter))
    recording = open_recording(bad)
    assert recording.complete
    with pytest.raises(ConfigError) as caught:
        load_series(recording)
        rerun(recording)  # the summary does not read every channel; the re-run does
        to_bus(recording, "virtual:never-opened")  # nor the frames
    text = str(caught.value)
    assert text.startswith(f"{bad}: {topic} message at log time "), text
    assert (f": {key}: " in text) if key else True, text
    assert expected in text, text


def test_the_summary_counts_a_refused_frame_by_its_field(
    recorded: Recorded, tmp_path: Path
) -> None:
    """``"ok": false`` written with a space (as any JSON writer may) is a refusal: the count
    read the raw bytes for ``"ok":false`` and missed it."""
    spaced = tmp_path / "spaced.mcap"

    def refused(raw: bytes) -> bytes:
        msg = json.loads(raw)
        msg["ok"] = False
        return json.dumps(msg, separators=(", ", ": ")).encode()

    rewrite(recorded.path, spaced, one_message(ch.CAN_TX, 10, refused))
    frames = load_series(open_recording(spaced)).frames
    assert (
        frames["tx_refused"] == 1 + load_series(open_recording(recorded.path)).frames["tx_refused"]
    )


def test_the_cli_says_which_message_is_bad_and_exits_2(recorded: Recorded, tmp_path: Path) -> None:
    bad = tmp_path / "bad.mcap"
    rewrite(recorded.path, bad, one_message(ch.TIMING, 300, field("missed", None)))
    done = handctl("replay", str(bad), "--rerun")
    assert done.returncode == 2, done.stdout + done.stderr
    assert "Traceback" not in done.stderr
    assert f"{bad}: {ch.TIMING} message at log time" in done.stderr
    assert "(tick 300): missed: expected an integer, at least 0, found None" in done.stderr


@pytest.mark.parametrize("after_magic", ["random", "first record cut"])
def test_a_file_where_nothing_reads_is_bad_input(
    recorded: Recorded, tmp_path: Path, after_magic: str
) -> None:
    """An MCAP's first bytes and then nothing that reads (random bytes, or a log cut inside
    its first record) was summarised as a run of 0 ticks on '?', exit 0."""
    bad = tmp_path / "bad.mcap"
    if after_magic == "random":
        bad.write_bytes(MAGIC + bytes(range(7, 250)) * 40)
    else:
        bad.write_bytes(recorded.path.read_bytes()[:100])
    done = handctl("replay", str(bad))
    assert done.returncode == 2, done.stdout + done.stderr
    assert "Traceback" not in done.stderr
    assert f"{bad}: expected a recording with something in it to read" in done.stderr


def test_an_empty_log_beside_a_killed_run_s_recording_names_it(
    recorded: Recorded, tmp_path: Path
) -> None:
    """A run killed (SIGKILL) in its start-up leaves the path's empty placeholder and its
    recording in a hidden file beside it, which replay of the path did not name: "found an
    empty file" (found by an outside audit)."""
    log = tmp_path / "x.mcap"
    log.touch()
    done = handctl("replay", str(log))
    assert done.returncode == 2 and done.stderr.rstrip().endswith("found an empty file")
    beside = tmp_path / ".x.mcap.4321.handctl-partial"
    beside.write_bytes(recorded.path.read_bytes())
    done = handctl("replay", str(log))
    assert done.returncode == 2, done.stdout + done.stderr
    assert (
        f"found an empty file, beside the recording of a run killed before it began: {beside}"
        " (replay that one)" in done.stderr
    )
    assert handctl("replay", str(beside)).returncode == 0


@pytest.mark.parametrize(
    ("form", "found"),
    [
        (("cbor", "handctl.Torque", "jsonschema"), "found 'cbor messages of the jsonschema"),
        (("json", "handctl.Torque", "protobuf"), "found 'json messages of the protobuf schema"),
        (("json", "handctl.Foo", "jsonschema"), "jsonschema schema handctl.Foo'"),
    ],
    ids=["cbor messages", "protobuf schema", "another schema"],
)
@pytest.mark.parametrize("mode", [(), ("--rerun",), ("--json", "{out}")], ids=str)
def test_a_channel_that_is_not_handctls_json_is_refused(
    recorded: Recorded,
    tmp_path: Path,
    form: tuple[str, str, str],
    found: str,
    mode: tuple[str, ...],
) -> None:
    """Before, every mode decoded the channel as handctl's JSON whatever it declared, and a
    re-run of the file said bit-exact."""
    bad = tmp_path / "bad.mcap"
    rewrite(recorded.path, bad, formats={ch.TORQUE: form})
    out = str(tmp_path / "out.json")
    done = handctl("replay", str(bad), *(out if a == "{out}" else a for a in mode))
    assert done.returncode == 2, done.stdout + done.stderr
    assert f"handctl: error: {bad}: channel {ch.TORQUE}: expected json messages of the " in (
        done.stderr
    )
    assert found in done.stderr and "bit-exact" not in done.stdout


# -- metadata -------------------------------------------------------------------------------------
@pytest.mark.parametrize(
    ("record", "key", "value", "expected"),
    [
        (ch.META_SUMMARY, "json", "{", "expected a JSON object"),
        (ch.META_SUMMARY, "json", "[1]", "expected a JSON object, found [1]"),
        (ch.META_RUN, "period_ns", "garbage", "expected a whole number >= 1, found 'garbage'"),
        (ch.META_RUN, "startup_ticks", "-5", "expected a whole number >= 0, found '-5'"),
        (ch.META_END, "dropped_ticks", "nan", "expected a whole number >= 0, found 'nan'"),
        ("handctl.command", "started_unix_ns", "1e9", "expected a whole number >= 0, found '1e9'"),
        # what a run never writes: summarised and re-run "bit-exact" as it was
        (ch.META_RUN, "seed", "abc", "expected a whole number >= 0, found 'abc'"),
        (ch.META_RUN, "mode", "bogus", "expected lockstep or realtime, found 'bogus'"),
        (ch.META_RUN, "period_ns", "500000", "expected 1000000 (the period of the recorded"),
        (ch.META_RUN, "estimator", "maybe", "expected True or False, found 'maybe'"),
    ],
)
def test_metadata_that_does_not_parse_is_exit_2(
    recorded: Recorded, tmp_path: Path, record: str, key: str, value: str, expected: str
) -> None:
    bad = tmp_path / "meta.mcap"
    rewrite(
        recorded.path,
        bad,
        metadata=lambda name, values: values | {key: value} if name == record else values,
    )
    done = handctl(
        "replay", str(bad), "--rerun", "--export", "candump", str(tmp_path / "frames.log")
    )
    assert done.returncode == 2, done.stdout + done.stderr
    assert "Traceback" not in done.stderr
    assert f"{bad}: metadata {record}.{key}: {expected}" in done.stderr, done.stderr


@pytest.mark.parametrize(
    ("key", "edit"),
    [
        # a joint's limit raised tenfold: a re-run and a replay onto a bus would check the
        # log's commands against it
        ("yaml", lambda text: text.replace("tau_max: 0.60", "tau_max: 6.00", 1)),
        ("dbc", lambda text: text + "\n"),
    ],
)
def test_a_hand_or_protocol_edited_in_the_log_is_refused(
    recorded: Recorded, tmp_path: Path, key: str, edit: Callable[[str], str]
) -> None:
    bad = tmp_path / "edited.mcap"

    def metadata(name: str, values: dict[str, str]) -> dict[str, str]:
        if name != ch.META_HAND:
            return values
        edited = edit(values[key])
        assert edited != values[key]
        return values | {key: edited}

    rewrite(recorded.path, bad, metadata=metadata)
    done = handctl("replay", str(bad), "--rerun")
    assert done.returncode == 2, done.stdout + done.stderr
    assert "Traceback" not in done.stderr
    assert f"{bad}: metadata {ch.META_HAND}.{key}: expected the text whose sha256" in done.stderr


@pytest.mark.parametrize(("key", "digest"), [("yaml", "sha256"), ("dbc", "dbc_sha256")])
def test_a_hand_or_protocol_edited_with_its_digest_taken_out_is_refused(
    recorded: Recorded, tmp_path: Path, key: str, digest: str
) -> None:
    """The digest deleted and tau_max raised: the log was read as one from before the digest
    was recorded, and the edited hand accepted by the summary and the re-run alike. No
    handctl log has the text without its digest."""
    bad = tmp_path / "undigested.mcap"

    def metadata(name: str, values: dict[str, str]) -> dict[str, str]:
        if name != ch.META_HAND:
            return values
        edited = values[key].replace("tau_max: 0.60", "tau_max: 0.70", 1) + "\n"
        return {k: v for k, v in values.items() if k != digest} | {key: edited}

    rewrite(recorded.path, bad, metadata=metadata)
    for extra in ((), ("--rerun",)):
        done = handctl("replay", str(bad), *extra)
        assert done.returncode == 2, done.stdout + done.stderr
        assert (
            f"{bad}: metadata {ch.META_HAND}.{digest}: expected the sha256 of {key} the run "
            "recorded beside it (every handctl log has it), found none: the record was edited "
            "after the run"
        ) in done.stderr


def test_a_recipe_recorded_for_another_hand_is_refused_by_the_summary_and_the_plot(
    recorded: Recorded, tmp_path: Path
) -> None:
    """The recorded recipe given another hand config's hash: the re-run refuses it, but the
    summary and the plot caught that refusal and went on as for a log without a recipe (its
    phases held to nothing, its pairs guessed), exit 0. Bad input, naming the file."""
    bad = tmp_path / "other_hand.mcap"
    other = "sha256:" + "0" * 64

    def metadata(name: str, values: dict[str, str]) -> dict[str, str]:
        if name != ch.META_RECIPE:
            return values
        return values | {"yaml": values["yaml"] + f"hand_config_hash: '{other}'\n"}

    rewrite(recorded.path, bad, metadata=metadata)
    plot = tmp_path / "other_hand.png"
    done = handctl("replay", str(bad), "--plot", str(plot))
    assert done.returncode == 2, done.stdout + done.stderr
    assert "Traceback" not in done.stderr
    assert f"handctl: error: {bad} (its recorded recipe): hand_config_hash: expected " in (
        done.stderr
    )
    assert f"found '{other}'" in done.stderr
    assert not plot.exists()


def test_a_recipe_today_s_rules_no_longer_read_leaves_the_summary_and_the_plot_readable(
    recorded: Recorded, tmp_path: Path
) -> None:
    """A log of an earlier handctl whose recipe today's rules refuse (an empty
    ``limit_guard_spring_bands``, accepted then): refusing every recorded recipe that did
    not read made such a log's summary, plot and export exit 2 (an audit of the fix above).
    Its frames and summary stay readable, as for a log without a recipe; the re-run, which
    needs the recipe, refuses it."""
    old = tmp_path / "old_rules.mcap"

    def metadata(name: str, values: dict[str, str]) -> dict[str, str]:
        if name != ch.META_RECIPE:
            return values
        return values | {"yaml": values["yaml"] + "limit_guard_spring_bands: {}\n"}

    rewrite(recorded.path, old, metadata=metadata)
    plot = tmp_path / "old_rules.png"
    done = handctl("replay", str(old), "--plot", str(plot))
    assert done.returncode == 0, done.stdout + done.stderr
    assert plot.exists()
    again = handctl("replay", str(old), "--rerun")
    assert again.returncode == 2, again.stdout + again.stderr
    assert "limit_guard_spring_bands" in again.stderr


# -- tick rows out of sequence ----------------------------------------------------------------
@pytest.mark.parametrize("tick", [299, 400])  # a negative tick: the message check above
def test_a_tick_row_out_of_sequence_in_a_whole_log_is_refused(
    recorded: Recorded, tmp_path: Path, tick: int
) -> None:
    """Only a damaged chunk can leave a gap in the ticks; in a log without one, a row out of
    sequence was altered, and a re-run that stopped there and said bit-exact would have
    compared a part of the log and vouched for the whole."""
    bad = tmp_path / "ticks.mcap"
    rewrite(recorded.path, bad, one_message(ch.TIMING, 300, field("tick", tick)))
    recording = open_recording(bad)
    assert recording.complete and not recording.damaged
    with pytest.raises(ConfigError) as caught:
        rerun(recording)
    assert str(caught.value) == (
        f"{bad}: {ch.TIMING} message: tick: expected tick 300, the row after tick 299 (ticks "
        f"follow one another; only a damaged chunk leaves a gap), found {tick}"
    )


# -- frames onto a bus ---------------------------------------------------------------------------
def _torque_command(
    protocol: Protocol, finger: int, joint: int, torque: Callable[[float], float]
) -> Callable[[bytes], bytes]:
    """A logged TorqueCommand with one joint's torque changed to ``torque(logged torque)``."""
    layout = protocol.layout("TorqueCommand", finger)

    def alter(raw: bytes) -> bytes:
        msg = json.loads(raw)
        assert msg["id"] == layout.frame_id
        counter, values = layout.decode(bytes.fromhex(msg["data"]))
        changed = list(values)
        changed[joint] = torque(values[joint])
        msg["data"] = layout.encode(counter, changed).hex()  # a good CRC: a re-sealed frame
        return json.dumps(msg).encode()

    return alter


def _nth_command(recorded: Recorded, frame_id: int, nth: int) -> int:
    """The index within ``/can/tx`` of the ``nth`` frame of ``frame_id``."""
    with recorded.path.open("rb") as handle:
        frames = [
            json.loads(m.data)["id"]
            for _, c, m in make_reader(handle).iter_messages(topics=[ch.CAN_TX])
        ]
    return [i for i, f in enumerate(frames) if f == frame_id][nth]


@pytest.mark.parametrize(
    ("case", "torque", "expected"),
    [
        ("over_tau_max", lambda logged: 2.0, "expected a torque within ±0.6 N·m (its tau_max)"),
        ("wire_maximum", lambda logged: 3.2767, "expected a torque within ±0.6 N·m"),
        # across zero, 0.3 N·m in one tick: never towards zero, 15 times the rate limit's step
        ("too_fast", lambda logged: -0.3 if logged >= 0 else 0.3, "expected a change of at most"),
    ],
)
def test_to_bus_sends_nothing_from_a_log_with_a_command_the_supervisor_would_refuse(
    recorded: Recorded,
    tmp_path: Path,
    hand: HandConfig,
    protocol: Protocol,
    case: str,
    torque: Callable[[float], float],
    expected: str,
) -> None:
    """The log's command frames are what the supervisor let through; a replay onto a bus
    where a hand may listen sends none of a log whose commands were altered (a re-sealed
    TorqueCommand over tau_max, or a step faster than the rate limit)."""
    layout = protocol.layout("TorqueCommand", 1)
    index = _nth_command(recorded, layout.frame_id, 200)
    bad = tmp_path / "commands.mcap"
    alter = _torque_command(protocol, 1, 0, torque)
    rewrite(recorded.path, bad, one_message(ch.CAN_TX, index, alter))
    recording = open_recording(bad)
    channel = f"hostile-{case}"
    with open_bus(f"virtual:{channel}", hand.bus) as listener:
        with pytest.raises(ConfigError) as caught:
            to_bus(recording, f"virtual:{channel}")
        heard = listener.drain(limit=10**6)
    assert heard == []
    text = str(caught.value)
    assert text.startswith(f"{bad}: {ch.CAN_TX} frame 0x101 "), text
    assert "Torque1 (f1_j1): " + expected in text and "nothing was sent" in text, text


def test_to_bus_sends_nothing_when_the_rerun_asked_with_it_finds_a_mismatch(
    recorded: Recorded, tmp_path: Path, hand: HandConfig, protocol: Protocol
) -> None:
    """A command altered within every bound the checks know (a tenth of a rate-limit step,
    re-sealed): the re-run said MISMATCH, and every frame went onto the bus all the same."""
    layout = protocol.layout("TorqueCommand", 1)
    index = _nth_command(recorded, layout.frame_id, 200)
    bad = tmp_path / "nudged.mcap"
    rewrite(recorded.path, bad, one_message(ch.CAN_TX, index, _torque_command(
        protocol, 1, 0, lambda logged: logged + 0.002 * (1 if logged < 0 else -1)
    )))  # fmt: skip
    directory = tmp_path / "bus"
    with open_bus(f"unix:{directory}", hand.bus) as listener:
        done = handctl("replay", str(bad), "--rerun", "--to-bus", f"unix:{directory}")
        heard = listener.drain(limit=10**6)
    assert done.returncode == 1, done.stdout + done.stderr
    assert "rerun: MISMATCH" in done.stdout, done.stdout
    assert "to-bus: nothing sent: the re-run found this log does not repeat its run" in (
        done.stderr
    )
    assert heard == []


def test_a_command_put_in_among_the_ticks_as_one_before_the_first_is_refused(
    recorded: Recorded, tmp_path: Path, hand: HandConfig, protocol: Protocol
) -> None:
    """A frame of tick -1 (the start-up's) put in at the 200th command, a step within every
    limit after the real one, re-sealed: the re-run never compared frames of a tick it had
    passed and said bit-exact, and ``--rerun --to-bus`` sent it (found by an outside
    audit). A run logs no frame of a tick after that tick's successor's row."""
    layout = protocol.layout("TorqueCommand", 1)
    index = _nth_command(recorded, layout.frame_id, 200)
    bad = tmp_path / "inserted.mcap"

    def one_more(topic: str, i: int, raw: bytes) -> list[bytes]:
        if (topic, i) != (ch.CAN_TX, index):
            return []
        msg = json.loads(raw)
        counter, values = layout.decode(bytes.fromhex(msg["data"]))
        nudged = [values[0] + 0.001, *values[1:]]
        msg.update(tick=-1, data=layout.encode((counter + 1) % 256, nudged).hex())
        return [json.dumps(msg).encode()]

    rewrite(recorded.path, bad, after=one_more)
    with pytest.raises(ConfigError) as caught:
        rerun(open_recording(bad))
    assert "a frame or event of tick -1: expected one logged before tick 0's row" in str(
        caught.value
    )
    text = _refused_with_nothing_sent(open_recording(bad), hand, "hostile-inserted")
    assert f"{ch.CAN_TX} frame 0x101 of tick -1: expected a frame logged at its tick" in text
    done = handctl("replay", str(bad), "--rerun", "--to-bus", "virtual:hostile-inserted-cli")
    assert done.returncode == 2, done.stdout + done.stderr
    assert "frames sent" not in done.stdout + done.stderr


def _one_frame_replaced(topic: str, index: int, frame_id: int, data: str) -> Change:
    """A change of a log that puts the frame ``frame_id`` ``data`` (hex) in place of message
    ``index`` of ``topic``, the rest as it was."""

    def change(at: str, i: int, raw: bytes) -> bytes:
        if (at, i) != (topic, index):
            return raw
        return json.dumps(json.loads(raw) | {"id": frame_id, "data": data}).encode()

    return change


def test_to_bus_refuses_a_command_hidden_among_the_received_frames(
    recorded: Recorded, tmp_path: Path, hand: HandConfig, protocol: Protocol
) -> None:
    """Whichever channel holds it, a frame with a command's id is checked as a command: the
    received frames go onto the bus too."""
    layout = protocol.layout("TorqueCommand", 2)
    sealed = layout.encode(0, [0.5, 0.0, 0.0]).hex()
    bad = tmp_path / "rx.mcap"
    rewrite(recorded.path, bad, _one_frame_replaced(ch.CAN_RX, 500, layout.frame_id, sealed))
    done = handctl("replay", str(bad), "--to-bus", "virtual:hostile-rx")
    assert done.returncode == 2, done.stdout + done.stderr
    assert f"{bad}: {ch.CAN_RX} frame 0x102 {sealed}" in done.stderr
    assert "Torque1 (f2_j1): expected a change of at most" in done.stderr
    assert "to-bus:" not in done.stdout


def test_to_bus_never_resets_a_node_s_faults(
    recorded: Recorded, tmp_path: Path, hand: HandConfig, protocol: Protocol
) -> None:
    """A NodeCommand's ``Command`` was never read: a fault reset written into a log (or
    recorded by a run with ``--reset-node-faults``) went onto the bus and cleared what the
    nodes had latched, unasked. Only enable and disable are replayed."""
    layout = protocol.layout("NodeCommand", 1)
    sealed = layout.encode(0, [NODE_COMMANDS["fault_reset"]]).hex()
    bad = tmp_path / "reset.mcap"
    rewrite(recorded.path, bad, _one_frame_replaced(ch.CAN_TX, 300, layout.frame_id, sealed))
    with open_bus("virtual:hostile-reset", hand.bus) as listener:
        with pytest.raises(ConfigError) as caught:
            to_bus(open_recording(bad), "virtual:hostile-reset")
        heard = listener.drain(limit=10**6)
    assert heard == []
    text = str(caught.value)
    assert f"{ch.CAN_TX} frame 0x{layout.frame_id:03X} {sealed}" in text, text
    assert "Command: expected enable (1) or disable (2) (nothing was sent)" in text, text
    assert "--reset-node-faults" in text and text.endswith("found a fault reset"), text
    assert "as the supervisor lets a command through" not in text  # the run's did


def test_an_unaltered_log_still_goes_onto_the_bus_whole(
    recorded: Recorded, hand: HandConfig
) -> None:
    recording = open_recording(recorded.path)
    with open_bus("virtual:hostile-whole", hand.bus) as listener:
        sent = to_bus(recording, "virtual:hostile-whole")
        heard = listener.drain(limit=10**7)
    assert sent["failed"] == 0 and sent["sent"] == len(heard) > 0


def test_a_replay_faster_than_the_log_is_held_to_the_rate_limit_as_it_is_sent(
    recorded: Recorded, hand: HandConfig
) -> None:
    """Judged on the logged time, a replay at --speed 4 put four times the rate limit on a
    bus where a hand may listen; it is judged on the time it is sent at."""
    refused = _refused_with_nothing_sent(
        open_recording(recorded.path), hand, "hostile-fast", speed=1000.0
    )
    assert "of the logged time at --speed 1000" in refused
    assert "nothing was sent" in refused


def test_a_bad_message_the_re_run_meets_while_running_is_still_bad_input(
    recorded: Recorded, tmp_path: Path
) -> None:
    """The re-run reads the log as it goes: a bad message late in the log is met inside a
    tick, where the runtime would take it for a failing tick and stop the hand. It is still
    bad input naming the message, not a mismatch (exit 1) nor a stop."""
    bad = tmp_path / "late.mcap"
    rewrite(recorded.path, bad, one_message(ch.CAN_TX, 3000, field("data", "zz")))
    recording = open_recording(bad)
    with pytest.raises(ConfigError) as caught:
        rerun(recording)
    text = str(caught.value)
    assert text.startswith(f"{bad}: {ch.CAN_TX} message at log time "), text
    assert ": data: expected a frame's payload as hex, at most 64 bytes, found 'zz'" in text


def test_one_resolution_a_frame_is_no_spare_at_any_speed(
    hand: HandConfig, protocol: Protocol
) -> None:
    """The one resolution a frame spared for a log whose encoder rounded to the nearest let
    0.0001 N·m a frame through: faster than logged, on a joint whose step a tick is about one
    resolution, a replay at --speed 50 put 50 times its rate limit on the wire; as logged,
    twice it (found by an outside audit). The supervisor keeps the grid: no frame needs it."""
    from handctl.recording.frames import _torque_problem

    layout = protocol.layout("TorqueCommand", 1)
    finger = hand.fingers[0]
    resolution = layout.signals[0].scale
    before, after = (0.0, 0.0, 0.0), (resolution, 0.0, 0.0)
    nothing_left = [0.0, 0.0, 0.0]
    assert _torque_problem(layout, finger, after, before, nothing_left, 1.0) is not None
    assert _torque_problem(layout, finger, after, before, nothing_left, 50.0) is not None
    assert _torque_problem(layout, finger, after, before, [1.0, 0.0, 0.0], 1.0) is None


def _commands(
    monkeypatch: pytest.MonkeyPatch,
    protocol: Protocol,
    hand: HandConfig,
    times_ns: list[int],
    torques: list[float],
    logged_hand: HandConfig | None = None,
    on_bus: bool = False,
    extra: dict[int, tuple[int, bytes]] | None = None,
    refused: frozenset[int] = frozenset(),
) -> int:
    """``check_commands`` on a log whose only frames are node 1's commands to f1_j1, at
    ``times_ns``: what the rate limit makes of their timing alone (the log's hand
    ``logged_hand``, ``hand`` by default; ``on_bus``: ``hand`` is --hand's), and the frames
    ``extra`` (log time: ``(id, data)``) put in before the commands of their time. The
    commands at the indices ``refused`` were refused by the bus (logged as not sent, their
    counters given back to the next)."""
    from handctl.recording import frames

    layout = protocol.layout("TorqueCommand", 1)
    logged: list[tuple[int, int, bytes, bool]] = []
    went: list[bool] = []
    counter = 0
    for k, (t, tau) in enumerate(zip(times_ns, torques, strict=True)):
        logged.append((t, layout.frame_id, layout.encode(counter % 256, [tau, 0.0, 0.0]), False))
        went.append(k not in refused)
        counter += k not in refused
    for at, (frame_id, data) in sorted((extra or {}).items(), reverse=True):
        where = next((i for i, f in enumerate(logged) if f[0] >= at), len(logged))
        logged.insert(where, (at, frame_id, data, False))
        went.insert(where, True)

    def logged_frames(
        recording: object, direction: str = "both", refused: Any = None
    ) -> Iterator[tuple[int, int, bytes, bool]]:
        for frame, sent in zip(logged, went, strict=True):
            if sent:
                yield frame
            elif refused is not None:
                refused(frame[0], frame[1])

    monkeypatch.setattr(frames, "logged_frames", logged_frames)
    monkeypatch.setattr(frames, "recorded_protocol", lambda recording: protocol)
    monkeypatch.setattr(frames, "recorded_hand", lambda recording: logged_hand or hand)
    log = SimpleNamespace(path=Path("commands.mcap"))  # all the refusal reads of it
    return frames.check_commands(log, hand, on_bus=on_bus)  # type: ignore[arg-type]


def test_commands_stacked_at_one_log_time_are_held_to_the_rate_limit_together(
    monkeypatch: pytest.MonkeyPatch, hand: HandConfig, protocol: Protocol
) -> None:
    """Each command was judged on the time since the one before, with one period at least:
    20 commands at one log time, each a step just under a period's, put 0.38 N·m on the wire
    at once. Together they have what the rate limit gives over two periods, no more."""
    step = 0.95 * hand.fingers[0].joints[0].rate_limit * hand.bus.period_s
    torques = [step * (k + 1) for k in range(20)]
    with pytest.raises(ConfigError) as caught:
        _commands(monkeypatch, protocol, hand, [10**8] * 20, torques)
    text = str(caught.value)
    assert f"{ch.CAN_TX} frame 0x101 {_encoded(protocol, 2, torques[2])} " in text, text
    assert "Torque1 (f1_j1): expected a change of at most" in text
    # the same steps a period apart are what the supervisor sends
    period_ns = round(hand.bus.period_s * 1e9)
    assert _commands(monkeypatch, protocol, hand, [k * period_ns for k in range(20)], torques)


def test_commands_the_bus_refused_give_the_next_that_went_their_steps(
    monkeypatch: pytest.MonkeyPatch, hand: HandConfig, protocol: Protocol
) -> None:
    """A run's bus refused two commands in a row while f1_j1 ramped at its rate limit: the
    supervisor took each for applied and stepped on from it, and the next that went carried
    three steps from the last the node had; the run ended "completed", and the replay
    refused its log for a frame the supervisor had let through (an outside audit). The steps
    of refused commands are the next sent one's; a log's own gap is not."""
    step = hand.fingers[0].joints[0].rate_limit * hand.bus.period_s
    period_ns = round(hand.bus.period_s * 1e9)
    times = [k * period_ns for k in range(8)]
    torques = [step * (k + 1) for k in range(8)]
    assert _commands(monkeypatch, protocol, hand, times, torques, refused=frozenset({3, 4})) == 6
    # the same torques with nothing refused between: three steps in a period are not
    ramp = [tau for k, tau in enumerate(torques) if k not in (3, 4)]
    with pytest.raises(ConfigError):
        _commands(monkeypatch, protocol, hand, [k * period_ns for k in range(6)], ramp)


def test_a_late_tick_and_the_one_after_it_are_what_a_real_time_run_sends(
    monkeypatch: pytest.MonkeyPatch, hand: HandConfig, protocol: Protocol
) -> None:
    """A tick 0.9 of a period late, then one on time: two full steps 0.1 of a period apart,
    as the supervisor sends them in real time. The slack for it is one period, once."""
    step = hand.fingers[0].joints[0].rate_limit * hand.bus.period_s
    period_ns = round(hand.bus.period_s * 1e9)
    times = [0, period_ns + 9 * period_ns // 10, 2 * period_ns, 3 * period_ns]
    assert _commands(monkeypatch, protocol, hand, times, [step * (k + 1) for k in range(4)])
    with pytest.raises(ConfigError):  # three full steps within a period are not
        _commands(monkeypatch, protocol, hand, [0, 1, 2], [step, 2 * step, 3 * step])


def _encoded(protocol: Protocol, counter: int, torque: float) -> str:
    return protocol.layout("TorqueCommand", 1).encode(counter, [torque, 0.0, 0.0]).hex()


def test_a_sender_that_fell_behind_shifts_the_rest_instead_of_sending_its_backlog(
    recorded: Recorded, hand: HandConfig
) -> None:
    """After a stall of the sender, the frames it owed went out back to back: the rate limit
    the commands were checked against on their logged spacing was broken on the wire. The
    rest of the replay is shifted by the stall instead."""
    recording = open_recording(recorded.path)
    logged = list(logged_frames(recording))
    span_s = (logged[-1][0] - logged[0][0]) * 1e-9
    now = [0.0]
    calls = [0]

    def clock() -> float:
        calls[0] += 1
        if calls[0] == 2000:  # the sender stalls for 20 ms, once
            now[0] += 0.020
        return now[0]

    def sleep(seconds: float) -> None:
        now[0] += seconds

    with open_bus("virtual:hostile-stall", hand.bus) as listener:
        sent = to_bus(recording, "virtual:hostile-stall", sleep=sleep, clock=clock)
        listener.drain(limit=10**7)
    assert sent["failed"] == 0
    assert sent["shifted_ms"] == pytest.approx(20.0, abs=1.0)
    assert sent["worst_late_ms"] == pytest.approx(20.0, abs=1.0)
    # the whole replay took its logged span and the stall: nothing was caught up
    assert now[0] == pytest.approx(span_s + 0.020, abs=0.002)


def test_the_hand_on_the_bus_bounds_what_goes_out_not_the_log_s_own_config(
    recorded: Recorded, hand: HandConfig, tmp_path: Path
) -> None:
    """The log carries its hand config, and its digest is no seal: a log whose tau_max was
    raised and its digest computed again passed every check against its own limits. With
    --hand, the commands are held to the config of the hand on the bus as well."""
    source = Path(hand.source)  # the recorded run's
    text = source.read_text()
    assert "tau_max: 0.60" in text
    weaker = tmp_path / "weaker_hand.yaml"
    weaker.write_text(text.replace("tau_max: 0.60", "tau_max: 0.05", 1))
    done = handctl(
        "replay", str(recorded.path), "--to-bus", "virtual:hostile-hand", "--hand", str(weaker)
    )
    assert done.returncode == 2, done.stdout + done.stderr
    assert "Torque1 (f1_j1): expected a torque within ±0.05 N·m (its tau_max) in --hand" in (
        done.stderr
    )
    assert str(weaker) in done.stderr and "nothing was sent" in done.stderr
    assert "to-bus:" not in done.stdout
    same = handctl(
        "replay", str(recorded.path), "--to-bus", "virtual:hostile-hand", "--hand", str(source)
    )
    assert same.returncode == 0, same.stderr


def test_a_bus_where_a_real_hand_may_listen_needs_the_operator_s_hand_config(
    recorded: Recorded,
) -> None:
    done = handctl("replay", str(recorded.path), "--to-bus", "socketcan:can0")
    assert done.returncode == 2, done.stdout + done.stderr
    assert "--hand: expected the config of the hand on socketcan:can0" in done.stderr
    assert "to-bus:" not in done.stdout
    alone = handctl("replay", str(recorded.path), "--hand", "hand.yaml")
    assert alone.returncode == 2 and "--hand: expected --to-bus SPEC as well" in alone.stderr


def test_a_log_holding_other_tick_rows_than_its_end_counts_is_refused(
    recorded: Recorded, tmp_path: Path
) -> None:
    """Every message after a tick cut out and the file finished again read as a complete
    run of that many ticks, re-run "bit-exact": the end record counts the rows there are."""
    bad = tmp_path / "rows.mcap"

    def fewer(name: str, values: dict[str, str]) -> dict[str, str]:
        return (
            values | {"ticks": str(int(values["ticks"]) + 158)} if name == ch.META_END else values
        )

    rewrite(recorded.path, bad, metadata=fewer)
    done = handctl("replay", str(bad), "--rerun")
    assert done.returncode == 2, done.stdout + done.stderr
    assert f"{bad}: channel {ch.TIMING}: expected the " in done.stderr
    assert "tick rows the end record (handctl.recording_end.ticks) counts" in done.stderr
    assert "bit-exact" not in done.stdout


def _twice(topic: str, index: int, raw: bytes) -> list[bytes]:
    return [raw] if topic == ch.CAN_TX else []


@pytest.mark.parametrize(
    ("how", "found"),
    [
        ({"keep": lambda topic, raw: topic != ch.CAN_TX}, "0 on /can/tx"),
        ({"after": _twice}, "on /can/tx"),
    ],
    ids=["sent-taken-out", "sent-twice"],
)
def test_a_log_holding_other_frames_than_its_end_counts_is_refused(
    recorded: Recorded, tmp_path: Path, how: dict[str, Any], found: str
) -> None:
    """Every sent frame taken out, or each written twice, and the file finished again: the
    summary said 'complete', exit 0, and ``--export`` wrote the twice-written frames. The
    end record counts the frames the writer wrote, refused ones too, on both channels."""
    told = open_recording(recorded.path).meta(ch.META_END, "frames")
    bad = tmp_path / "frames.mcap"
    rewrite(recorded.path, bad, **how)
    out = tmp_path / "frames.log"
    for extra in ((), ("--export", "candump", str(out))):
        done = handctl("replay", str(bad), *extra)
        assert done.returncode == 2, done.stdout + done.stderr
        assert (
            f"handctl: error: {bad}: channels /can/rx and /can/tx: expected the {told} frames "
            "the end record (handctl.recording_end.frames) counts, between them, found "
        ) in done.stderr
        assert found in done.stderr and "complete" not in done.stdout
    assert not out.exists()


def test_drops_the_writer_counted_on_the_way_cannot_vanish_from_its_end(
    recorded: Recorded, tmp_path: Path
) -> None:
    bad = tmp_path / "drops.mcap"

    def dropped(topic: str, index: int, raw: bytes) -> bytes:
        if topic != ch.STATS:
            return raw
        return json.dumps(json.loads(raw) | {"dropped_ticks": 3}).encode()

    rewrite(recorded.path, bad, dropped)
    done = handctl("replay", str(bad), "--rerun")
    assert done.returncode == 2, done.stdout + done.stderr
    assert (
        f"{bad}: metadata handctl.recording_end.dropped_ticks: expected at least the 3 that "
        f"{ch.STATS} counted, found '0'"
    ) in done.stderr


def _logged_tx(path: Path) -> list[tuple[int, int, bytes]]:
    """``(log time, id, data)`` of every frame of ``/can/tx``, in the log's order."""
    with path.open("rb") as handle:
        return [
            (m.log_time, (msg := json.loads(m.data))["id"], bytes.fromhex(msg["data"]))
            for _, c, m in make_reader(handle).iter_messages(topics=[ch.CAN_TX])
        ]


def _largest_step_applied(
    hand: HandConfig, protocol: Protocol, node: int, frames: list[tuple[int, int, bytes]]
) -> float:
    """N·m, the largest change of a joint's applied torque that one of ``frames`` makes in
    node ``node``'s firmware (the simulated hand's), fed them in order."""
    from handctl.sim.firmware import EmulatedNode

    finger = next(f for f in hand.fingers if f.node_id == node)
    emulated = EmulatedNode(finger, protocol, tdt_range=3.0, encoder_max_step=1.0)
    emulated.boot(0)
    largest = 0.0
    for log_time, frame_id, data in frames:
        before = list(emulated.applied)
        emulated.receive(frame_id, data, log_time)
        largest = max(largest, *(abs(a - b) for a, b in zip(emulated.applied, before, strict=True)))
    return largest


def test_a_disable_and_an_enable_put_in_a_log_start_the_node_again_from_zero(
    recorded: Recorded, tmp_path: Path, hand: HandConfig, protocol: Protocol
) -> None:
    """Each TorqueCommand was judged from the node's previous one whatever NodeCommands came
    between: two commands at node 3's largest torque replaced by a disable and an enable (the
    counters in sequence) went out, and the node, which applies zero once disabled and takes
    the first command after an enable as its stream's baseline, stepped from zero to that
    torque in one frame (found by an outside audit)."""
    torque, node = protocol.layout("TorqueCommand", 3), protocol.layout("NodeCommand", 3)
    tx = _logged_tx(recorded.path)
    commands = [i for i, (_, f, _) in enumerate(tx) if f == torque.frame_id]
    largest = [max(map(abs, torque.decode(tx[i][2])[1])) for i in commands[:-20]]
    k = largest.index(max(largest))
    ours = [i for i, (_, f, _) in enumerate(tx) if f == node.frame_id]
    first = node.decode(tx[ours[0]][2])[0]
    # the two in place of the commands, the run's NodeCommands after them renumbered
    commanded = {commands[k]: NODE_COMMANDS["disable"], commands[k + 1]: NODE_COMMANDS["enable"]}
    commanded |= {i: int(node.decode(tx[i][2])[1][0]) for i in ours[1:]}
    counters = {i: first + 1 + n for n, i in enumerate(sorted(commanded))}

    def reenabled(topic: str, index: int, raw: bytes) -> bytes:
        if topic != ch.CAN_TX or index not in commanded:
            return raw
        data = node.encode(counters[index] % 256, (commanded[index],)).hex()
        return json.dumps(json.loads(raw) | {"id": node.frame_id, "data": data}).encode()

    bad = tmp_path / "reenabled.mcap"
    rewrite(recorded.path, bad, reenabled)
    # what the log would do to the node: from zero to near its largest torque in one frame,
    # more than the two ticks' worth the check allows a node's first command
    step = hand.fingers[2].joints[0].rate_limit * hand.bus.period_s  # one tick's at most
    assert _largest_step_applied(hand, protocol, 3, _logged_tx(bad)) > 3 * step
    text = _refused_with_nothing_sent(open_recording(bad), hand, "hostile-reenabled")
    assert f"{ch.CAN_TX} frame 0x{torque.frame_id:03X} " in text, text
    assert "expected a change of at most" in text and "from the node's 0 N·m" in text, text
    # the log as the run wrote it: a tick's step at most, the enable's baseline too
    assert _largest_step_applied(hand, protocol, 3, tx) <= step + 1e-9


def test_commands_the_node_would_reject_for_their_counter_are_refused(
    recorded: Recorded, tmp_path: Path, hand: HandConfig, protocol: Protocol
) -> None:
    """The check took every logged command as applied, but a node rejects one whose counter
    does not follow the last it took, and keeps its torque: f1_j1 ramped a tick's step a
    command to 0.2 N·m with commands 101-109 two counters apart went out, and the node held
    zero through them, then took 0.2 N·m in one step at the tenth, at the next counter
    (found by an outside audit). A run logs its commands in sequence."""
    layout = protocol.layout("TorqueCommand", 1)
    step = hand.fingers[0].joints[0].rate_limit * hand.bus.period_s
    seen: list[int] = []

    def ramped(skip: bool) -> Change:
        def change(topic: str, index: int, raw: bytes) -> bytes:
            if topic != ch.CAN_TX or (msg := json.loads(raw))["id"] != layout.frame_id:
                return raw
            k = len(seen)
            seen.append(k)
            counter, values = layout.decode(bytes.fromhex(msg["data"]))
            up = max(0, min(k - 100, 120 - k))  # 0.2 N·m at the 110th command, zero again at 120
            if skip and 101 <= k <= 109:
                counter += k - 100  # two apart from the 100th's
            elif skip and k >= 110:
                counter += 9  # the 110th at the one after the 109th's
            data = layout.encode(counter % 256, [round(up * step, 4), *values[1:]])
            return json.dumps(msg | {"data": data.hex()}).encode()

        return change

    bad, good = tmp_path / "skipped.mcap", tmp_path / "in_sequence.mcap"
    rewrite(recorded.path, bad, ramped(skip=True))
    seen.clear()
    rewrite(recorded.path, good, ramped(skip=False))
    # what the logs do to the node: the skipped counters make the ramp one 0.2 N·m step
    assert _largest_step_applied(hand, protocol, 1, _logged_tx(bad)) > 9 * step
    assert _largest_step_applied(hand, protocol, 1, _logged_tx(good)) <= step + 1e-9
    text = _refused_with_nothing_sent(open_recording(bad), hand, "hostile-skipped")
    assert f"{ch.CAN_TX} frame 0x{layout.frame_id:03X} " in text, text
    assert ": Counter: expected " in text and "the one after the previous TorqueCommand_1's" in text
    with open_bus("virtual:hostile-in-sequence", hand.bus) as listener:
        sent = to_bus(open_recording(good), "virtual:hostile-in-sequence")
        assert sent["sent"] == len(listener.drain(limit=10**7)) > 0


def test_torques_sent_to_a_disabled_node_are_no_ramp_for_after_its_enable(
    monkeypatch: pytest.MonkeyPatch, hand: HandConfig, protocol: Protocol
) -> None:
    """A node ignores the TorqueCommands it gets while DISABLED: a log that ramped them up
    before the enable, each step within the rate limit, then sent the full torque twice
    after it, took the node from zero to it in one frame."""
    step = hand.fingers[0].joints[0].rate_limit * hand.bus.period_s
    period_ns = round(hand.bus.period_s * 1e9)
    node = protocol.layout("NodeCommand", 1)
    enable = (node.frame_id, node.encode(0, (NODE_COMMANDS["enable"],)))
    ramp = [step * (k + 1) for k in range(15)]
    times = [k * period_ns for k in range(17)]
    with pytest.raises(ConfigError, match="from the node's 0 N·m"):
        before = [*ramp, ramp[-1], ramp[-1]]
        _commands(monkeypatch, protocol, hand, times, before, extra={15 * period_ns: enable})
    # ramped after the enable, as a run does: the same torques go out
    after = [0.0, *ramp, ramp[-1]]
    assert _commands(monkeypatch, protocol, hand, times, after, extra={0: enable}) == 18


def _f1_j1_as(hand: HandConfig, tau_max: float, rate_limit: float) -> HandConfig:
    """``hand`` with f1_j1's ``tau_max`` (N·m) and ``rate_limit`` (N·m/s)."""
    first = hand.fingers[0]
    joint = replace(first.joints[0], tau_max=tau_max, rate_limit=rate_limit)
    finger = replace(first, joints=(joint, *first.joints[1:]))
    return replace(hand, fingers=(finger, *hand.fingers[1:]))


@pytest.mark.parametrize("rate_limit", [0.1, 0.15, 0.3, 1.0])
def test_the_commands_are_held_to_both_limits_on_the_signal_s_grid(
    monkeypatch: pytest.MonkeyPatch, hand: HandConfig, protocol: Protocol, rate_limit: float
) -> None:
    """Each frame had a resolution to spare over its rate limit's budget, and half a
    resolution over tau_max: on f1_j1 with a rate limit of 0.1 N·m/s (one resolution a tick
    at 1 kHz) and a tau_max of 0.04996 N·m, a log raised by the largest step the check took
    reached 0.0500 N·m in 318 commands where the supervisor takes 500 to 0.0499 (found by an
    outside audit). The supervisor keeps both limits on the grid; so does the check, with
    only floating-point rest to spare (a rate of 0.3 N·m/s is 2.9999999999999996 counts a
    tick, the supervisor's step 3)."""
    import numpy as np

    from handctl.online.safety.limits import JointLimits, limit_torque

    slow = _f1_j1_as(hand, tau_max=0.04996, rate_limit=rate_limit)
    limits = JointLimits.from_hand(slow, protocol)
    scale = protocol.layout("TorqueCommand", 1).signals[0].scale
    applied, desired = np.zeros(len(limits.names)), np.zeros(len(limits.names))
    desired[0] = 1.0  # N·m, past tau_max: the supervisor's ramp to it, on its grid
    ramp = []
    for _ in range(600):
        limit_torque(desired, applied, limits, slow.bus.period_s, applied)
        ramp.append(float(applied[0]))
    assert round(ramp[-1] / scale) == 499  # 0.0499 N·m, tau_max on the grid
    period_ns = round(slow.bus.period_s * 1e9)
    times = [k * period_ns for k in range(len(ramp))]
    assert _commands(monkeypatch, protocol, slow, times, ramp) == len(ramp)
    # a count a tick faster than the supervisor ramps
    steps = round(ramp[-1] / scale) // ramp.index(ramp[-1]) + 1
    faster = [min(499, steps * (k + 1)) * scale for k in range(len(ramp))]
    with pytest.raises(ConfigError, match="expected a change of at most"):
        _commands(monkeypatch, protocol, slow, times, faster)
    # one count over tau_max at the end of the supervisor's ramp
    with pytest.raises(ConfigError, match=r"expected a torque within ±0\.04996 N·m"):
        _commands(monkeypatch, protocol, slow, times, [*ramp[:-1], 500 * scale])


def test_a_command_dated_back_gives_the_next_no_more_time(
    monkeypatch: pytest.MonkeyPatch, hand: HandConfig, protocol: Protocol
) -> None:
    """After each tick's command, another dated 0.7 ms before it: measured from that earlier
    time, each tick was credited 1.7 ms, and up to 1.75 times the rate limit went out
    (here 1.68)."""
    step = hand.fingers[0].joints[0].rate_limit * hand.bus.period_s
    period_ns = round(hand.bus.period_s * 1e9)
    times, torques = [], []
    for k in range(12):
        times += [k * period_ns, k * period_ns - 7 * period_ns // 10]
        torques += [step * (2 * k + 1) * 0.84, step * (2 * k + 2) * 0.84]
    with pytest.raises(ConfigError, match="expected a change of at most"):
        _commands(monkeypatch, protocol, hand, times, torques)


def test_the_slack_is_the_faster_loop_s_the_log_s_or_the_hand_s_on_the_bus(
    monkeypatch: pytest.MonkeyPatch, hand: HandConfig, protocol: Protocol
) -> None:
    """A log that says 250 Hz (re-sealed, or honest) had two of its periods' slack onto a
    1 kHz hand: a jump of four of that hand's steps at once went out."""
    slow = replace(hand, bus=replace(hand.bus, loop_rate_hz=250.0))
    step = hand.fingers[0].joints[0].rate_limit * slow.bus.period_s  # one 4 ms tick's
    times = [k * 4_000_000 for k in range(6)]
    torques = [0.9 * step * (k + 1) for k in range(6)]
    assert _commands(monkeypatch, protocol, slow, times, torques)  # onto its own hand
    with pytest.raises(ConfigError, match="in --hand"):
        _commands(monkeypatch, protocol, hand, times, torques, logged_hand=slow, on_bus=True)


def test_an_mcap_file_of_another_tool_is_not_summarised_as_a_run(tmp_path: Path) -> None:
    """A complete MCAP file written by the mcap library with channels of its own was
    summarised as a run of '? on ?', 'complete (but the writer did not finish the file)',
    exit 0, and plotted empty."""
    foreign = tmp_path / "foreign.mcap"
    with foreign.open("wb") as handle:
        writer = Writer(handle)
        writer.start()
        schema = writer.register_schema("Chatter", "jsonschema", b"{}")
        for k in range(3):
            channel = writer.register_channel(f"/chatter/{k}", "json", schema)
            writer.add_message(channel, log_time=k, publish_time=k, data=b"{}")
        writer.finish()  # type: ignore[no-untyped-call]  # mcap's Writer is untyped
    done = handctl("replay", str(foreign), "--plot", str(tmp_path / "p.png"))
    assert done.returncode == 2, done.stdout + done.stderr
    assert "expected a handctl recording" in done.stderr
    assert "no handctl metadata and no handctl channel (its channels: /chatter/0, " in (done.stderr)
    assert not (tmp_path / "p.png").exists()


def test_a_recording_rewritten_without_chunks_is_refused_not_read_as_empty(
    recorded: Recorded, tmp_path: Path
) -> None:
    """handctl reads the messages in chunks, where it writes them: a log copied without
    chunks read as '0.000 s, 0 ticks, complete', exit 0, and its re-run compared nothing."""
    flat = tmp_path / "flat.mcap"
    with recorded.path.open("rb") as source, flat.open("wb") as handle:
        reader = make_reader(source)
        writer = Writer(handle, use_chunking=False)
        writer.start()
        schemas: dict[int, int] = {}
        channels: dict[int, int] = {}
        for schema, channel, message in reader.iter_messages():
            if channel.id not in channels:
                if schema is not None and schema.id not in schemas:
                    schemas[schema.id] = writer.register_schema(
                        schema.name, schema.encoding, schema.data
                    )
                channels[channel.id] = writer.register_channel(
                    channel.topic,
                    channel.message_encoding,
                    schemas[schema.id] if schema is not None else 0,
                )
            writer.add_message(
                channels[channel.id], message.log_time, message.data, message.publish_time
            )
        writer.finish()  # type: ignore[no-untyped-call]  # mcap's Writer is untyped
    done = handctl("replay", str(flat), "--rerun")
    assert done.returncode == 2, done.stdout + done.stderr
    assert "expected a recording with its messages in chunks, as handctl writes it" in (done.stderr)


@pytest.mark.parametrize("key", ["applied_nm", "desired_nm"])
def test_a_torque_column_without_a_number_is_summarised_and_its_json_is_json(
    recorded: Recorded, tmp_path: Path, key: str
) -> None:
    """Every ``/control/torque`` value of one column nulled: the applied one ended the
    summary in a numpy traceback, exit 1; the desired one wrote ``NaN`` into ``--json``,
    which is not JSON. The column has no largest value: it is left out, and what JSON
    cannot say is ``null``. An applied torque that is no number is one the supervisor never
    applies: refused as one over tau_max is, by name."""

    def change(topic: str, index: int, raw: bytes) -> bytes:
        if topic != ch.TORQUE:
            return raw
        msg = json.loads(raw)
        return json.dumps(msg | {key: [None] * len(msg[key])}).encode()

    bad = tmp_path / "nulled.mcap"
    rewrite(recorded.path, bad, change)
    out = tmp_path / "summary.json"
    done = handctl("replay", str(bad), "--json", str(out))
    assert "Traceback" not in done.stderr and "RuntimeWarning" not in done.stderr
    if key == "applied_nm":
        assert done.returncode == 2, done.stdout + done.stderr
        assert "): applied_nm[0] (f1_j1): expected a number, at most" in done.stderr
        assert "found null (NaN)" in done.stderr and not out.exists()
        return
    assert done.returncode == 0, done.stdout + done.stderr

    def refuse(constant: str) -> object:
        raise AssertionError(f"{constant} in the JSON output")

    largest = json.loads(out.read_text(), parse_constant=refuse)["summary"]["largest_torques"]
    assert all(key not in entry for entry in largest.values())
    assert all("tdt_nm" in entry for entry in largest.values())


def test_a_summary_whose_outcome_was_changed_does_not_rerun_bit_exact(
    recorded: Recorded, tmp_path: Path
) -> None:
    """The log's summary says the run completed; fed the same frames, the run ends as it
    really did: 'outcome X (logged completed)', bit-exact, exit 0, before."""
    logged = json.loads(open_recording(recorded.path).metadata[ch.META_SUMMARY]["json"])
    other = "completed" if logged["outcome"] != "completed" else "time_budget"

    def metadata(name: str, data: dict[str, str]) -> dict[str, str]:
        if name != ch.META_SUMMARY:
            return data
        return {"json": json.dumps(json.loads(data["json"]) | {"outcome": other})}

    bad = tmp_path / "outcome.mcap"
    rewrite(recorded.path, bad, metadata=metadata)
    done = handctl("replay", str(bad), "--rerun")
    assert done.returncode == 1, done.stdout + done.stderr
    assert f"outcome: logged '{other}', re-run '{logged['outcome']}'" in done.stdout


@pytest.mark.parametrize("topic", ch.CORE_TOPICS)
def test_a_complete_log_without_a_channel_every_run_writes_is_refused(
    recorded: Recorded, tmp_path: Path, topic: str
) -> None:
    """Every run writes these channels: a complete log without ``/events`` summarised a
    run that ended in a safety stop as 'faults: none', exit 0; without ``/recipe/phase``,
    with no phases."""
    bad = tmp_path / "without.mcap"
    rewrite(recorded.path, bad, drop=(topic,))
    done = handctl("replay", str(bad))
    assert done.returncode == 2, done.stdout + done.stderr
    assert (
        f"expected the channels {topic} for its summary" in done.stderr
        # the end record counts the tick rows the timing channel should hold
        or f"channel {topic}: expected the 1" in done.stderr
        # and every running tick writes one message to these
        or f"channel {topic}: expected a message for each running tick" in done.stderr
    ), done.stderr


@pytest.mark.parametrize("topic", [*ch.ACTIVE_TICK_TOPICS, ch.TIMING])
def test_a_complete_log_whose_channel_lost_its_messages_is_refused(
    recorded: Recorded, tmp_path: Path, topic: str
) -> None:
    """The channel kept, its messages taken out and the file finished again: the summary of
    a log without a torque message said 'complete', exit 0, its table of torques empty."""
    bad = tmp_path / "emptied.mcap"
    rewrite(recorded.path, bad, empty=(topic,))
    done = handctl("replay", str(bad))
    assert done.returncode == 2, done.stdout + done.stderr
    assert f"channel {topic}: expected " in done.stderr
    assert "found 0 messages" in done.stderr or "found '0 rows'" in done.stderr


@pytest.mark.parametrize(("value", "shown"), [(1e9, "1000000000.0"), (-3.3, "-3.3")])
def test_a_joint_angle_no_feedback_frame_can_carry_is_refused(
    recorded: Recorded, tmp_path: Path, value: float, shown: str
) -> None:
    """A joint's angle of 1e9 rad in one message (a garbled or edited log) was summarised and
    plotted as its angle, exit 0. The host reads its angles off the Feedback frames, so none
    a run logs is beyond what the angle signal's bits carry (here 16 bits of 0.0001 rad): bad
    input, naming the message, the joint and both values, before a re-run or anything sent."""
    bad = tmp_path / "angle.mcap"
    rewrite(recorded.path, bad, one_message(ch.JOINT_STATE, 300, angle_of(1, value)))
    done = handctl("replay", str(bad), "--rerun", "--to-bus", "virtual:angle")
    assert done.returncode == 2, done.stdout + done.stderr
    assert "Traceback" not in done.stderr
    assert f"handctl: error: {bad}: {ch.JOINT_STATE} message at log time " in done.stderr
    assert (
        "angle_rad[1] (f1_j2): expected an angle Feedback_1.Angle2 can carry, "
        f"-3.2768..3.2767 rad (a run reads it there), found {shown}"
    ) in done.stderr
    assert "frames sent" not in done.stdout + done.stderr and "rerun:" not in done.stdout


def angle_of(joint: int, value: float) -> Callable[[bytes], bytes]:
    def alter(raw: bytes) -> bytes:
        msg = json.loads(raw)
        msg["angle_rad"][joint] = value
        return json.dumps(msg).encode()

    return alter


def test_a_log_with_frames_and_no_tick_row_is_not_summarised_as_a_run(
    recorded: Recorded, tmp_path: Path
) -> None:
    """Its tick rows taken out, and the end record's count of them with them: the summary
    said '0 ticks, complete', exit 0, beside 3000 frames and a table of torques, as if
    nothing were missing, where ``--to-bus`` refuses the same log (safety.md #88). A run logs
    a row for every tick it polls or sends on: bad input, naming the file."""

    def no_count(name: str, values: dict[str, str]) -> dict[str, str]:
        return {k: v for k, v in values.items() if not (name == ch.META_END and k == "ticks")}

    bad = tmp_path / "no_ticks.mcap"
    rewrite(recorded.path, bad, metadata=no_count, empty=(ch.TIMING,))
    plot = tmp_path / "no_ticks.png"
    done = handctl("replay", str(bad), "--plot", str(plot))
    assert done.returncode == 2, done.stdout + done.stderr
    assert "Traceback" not in done.stderr
    said = f"handctl: error: {bad}: channel {ch.TIMING}: expected a tick row for every tick"
    assert said in done.stderr, done.stderr
    assert " frames received, " in done.stderr
    assert "0 ticks" not in done.stdout and not plot.exists()


def test_to_bus_sends_nothing_from_a_log_with_a_frame_moved_off_its_tick(
    recorded: Recorded, tmp_path: Path, hand: HandConfig
) -> None:
    """The last received frame moved an hour on, still of its tick: every earlier frame
    was sent, the nodes enabled, and the replay waited silent for the hour."""
    last = len(list(iter_decoded(open_recording(recorded.path), (ch.CAN_RX,)))) - 1
    seen = [0]

    def times(topic: str, log_time: int) -> int:
        if topic != ch.CAN_RX:
            return log_time
        seen[0] += 1
        return log_time + 3600 * 10**9 if seen[0] - 1 == last else log_time

    bad = tmp_path / "moved.mcap"
    rewrite(recorded.path, bad, times=times)
    refused = _refused_with_nothing_sent(open_recording(bad), hand, "hostile-moved")
    assert "expected a frame logged at its tick's time" in refused
    assert "(nothing was sent)" in refused


@pytest.mark.parametrize("jump_s", [1e8, 0.05])
def test_to_bus_sends_nothing_from_a_log_whose_times_jump_between_ticks(
    recorded: Recorded, tmp_path: Path, jump_s: float
) -> None:
    """Every message after a tick in the middle moved three years on (or 50 ms, past the
    nodes' watchdog), each frame still at its tick's time: the frames before the jump were
    sent, the nodes enabled, and the replay then sent nothing until it was killed (here: its
    timeout)."""
    with recorded.path.open("rb") as handle:
        stamps = sorted(
            (json.loads(m.data)["tick"], m.log_time)
            for _, _, m in make_reader(handle).iter_messages(topics=[ch.TIMING])
        )
    tick, cut = stamps[len(stamps) // 2]

    def times(topic: str, log_time: int) -> int:
        return log_time + round(jump_s * 1e9) if log_time > cut else log_time

    bad = tmp_path / "jump.mcap"
    rewrite(recorded.path, bad, times=times)
    done = handctl("replay", str(bad), "--to-bus", f"virtual:jump-{jump_s:g}", timeout=120)
    assert done.returncode == 2, done.stdout + done.stderr
    assert "frames sent" not in done.stdout + done.stderr
    assert f"{ch.TIMING} tick {tick + 1}" in done.stderr
    assert "within the nodes' 10 ms command watchdog after the one before" in done.stderr
    gap = jump_s + (stamps[1][1] - stamps[0][1]) * 1e-9
    assert f"found {gap:.9g} s after tick {tick}" in done.stderr


def test_a_stall_before_the_first_command_is_no_gap_the_nodes_hold_torque_through(
    recorded: Recorded, hand: HandConfig
) -> None:
    """A real-time run's start-up listens to its nodes before it enables them, and a loaded
    host stalls it past the nodes' 10 ms watchdog: no node is enabled and no torque is held
    through it, but the replay refused the log as one whose ticks jump (an outside audit).
    The same stall once a command went is refused, as above."""
    from handctl.recording import frames

    ms = 1_000_000
    ticks = {0: 0, 1: 1 * ms, 2: 15 * ms, 3: 16 * ms, 4: 17 * ms}  # 14 ms from tick 1 to 2
    order = sorted(ticks)
    frames._check_no_gap(open_recording(recorded.path), ticks, order, 15 * ms)  # enabled at 2
    with pytest.raises(ConfigError) as caught:
        frames._check_no_gap(open_recording(recorded.path), ticks, order, 1 * ms)
    assert caught.value.key == f"{ch.TIMING} tick 2"
    # the first command of a whole log is found where it was logged
    first = frames._first_command_ns(open_recording(recorded.path), hand, "both")
    with recorded.path.open("rb") as handle:
        sent = [m.log_time for _, _, m in make_reader(handle).iter_messages([ch.CAN_TX])]
    assert first == min(sent)


def test_ticks_moved_past_their_scheduled_times_are_refused(
    recorded: Recorded, tmp_path: Path
) -> None:
    """Every tick 2^62 on, times as they were: the summary said the run lasted 4.6e15 s and
    the plot raised OverflowError, a traceback. No run's tick comes sooner after the clock's
    zero than its number of periods."""

    def later(topic: str, index: int, raw: bytes) -> bytes:
        msg = json.loads(raw) if raw.startswith(b"{") else {}
        if "tick" not in msg:
            return raw
        msg["tick"] += 1 << 62
        return json.dumps(msg).encode()

    bad = tmp_path / "later.mcap"
    rewrite(recorded.path, bad, later)
    done = handctl("replay", str(bad), "--plot", str(tmp_path / "p.png"))
    assert done.returncode == 2, done.stdout + done.stderr
    assert "Traceback" not in done.stderr
    assert f"{ch.TIMING} message at log time" in done.stderr
    assert f"found 'tick {1 << 62}'" in done.stderr


def test_a_tick_scheduled_before_the_clock_s_zero_is_refused_by_its_time(
    recorded: Recorded, tmp_path: Path
) -> None:
    """A tick row whose scheduled_ns was made -1e18 was refused as a bad tick ("expected at
    most its scheduled_ns over the run's period ..., found 'tick 300'"): the field at fault
    is its time, below any run's clock."""
    bad = tmp_path / "negative.mcap"
    rewrite(recorded.path, bad, one_message(ch.TIMING, 300, field("scheduled_ns", -(10**18))))
    with pytest.raises(ConfigError) as caught:
        load_series(open_recording(bad))
    text = str(caught.value)
    assert f"{ch.TIMING} message at log time " in text
    assert "(tick 300): scheduled_ns: expected a time on the loop's clock, at least 0" in text
    assert f"found {-(10**18)}" in text
    assert not (tmp_path / "p.png").exists()


def test_a_hand_record_whose_config_is_gone_and_its_digest_kept_is_refused(
    recorded: Recorded, tmp_path: Path
) -> None:
    """Zeros over the hand's metadata record read as its other keys and one named '': the
    replay read it as a log of no hand, "complete", its phase and torque tables empty, exit
    0; --rerun said the run's hand config was "nothing"."""

    def without_yaml(name: str, values: dict[str, str]) -> dict[str, str]:
        if name != ch.META_HAND:
            return values
        return {**{k: v for k, v in values.items() if k != "yaml"}, "": "\x00" * 8}

    bad = tmp_path / "no_yaml.mcap"
    rewrite(recorded.path, bad, metadata=without_yaml)
    for extra in ((), ("--rerun",)):
        done = handctl("replay", str(bad), *extra)
        assert done.returncode == 2, done.stdout + done.stderr
        assert f"metadata {ch.META_HAND}.yaml: expected the hand config whose sha256" in (
            done.stderr
        )
        assert "the record is damaged or edited (its keys: 'name'" in done.stderr


def test_a_log_a_run_still_writes_is_said_so_and_not_re_run(
    recorded: Recorded, tmp_path: Path
) -> None:
    """A log read while its run wrote it was called TRUNCATED, and one ``--rerun`` read two
    lengths of it (the summary 9391 ticks, the re-run 11544). The writer holds the file's
    lock (``recorder._open_log``): held here as a writer holds it."""
    import fcntl

    cut = tmp_path / "live.mcap"
    data = recorded.path.read_bytes()
    cut.write_bytes(data[: len(data) // 2])
    with cut.open("ab") as writer:
        fcntl.flock(writer.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        done = handctl("replay", str(cut))
        assert done.returncode == 0, done.stderr
        assert "BEING WRITTEN by a run: what it holds so far" in done.stdout
        assert "TRUNCATED" not in done.stdout
        done = handctl("replay", str(cut), "--rerun")
        assert done.returncode == 2, done.stdout + done.stderr
        assert "found a log a run is still writing (its writer holds the file's lock)" in (
            done.stderr
        )
    done = handctl("replay", str(cut))  # the lock gone, and the file cut: cut short
    assert "TRUNCATED" in done.stdout


def test_monitor_says_a_log_a_run_still_writes_as_replay_says_it(
    recorded: Recorded, tmp_path: Path
) -> None:
    """``monitor --log`` called a log its run was still writing TRUNCATED, where ``replay``
    of the same file said BEING WRITTEN (an outside audit, a run stopped mid-run)."""
    import fcntl

    cut = tmp_path / "live.mcap"
    data = recorded.path.read_bytes()
    cut.write_bytes(data[: len(data) // 2])
    with cut.open("ab") as writer:
        fcntl.flock(writer.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        done = handctl("monitor", "--log", str(cut))
        assert done.returncode == 0, done.stderr
        assert json.loads(done.stdout.splitlines()[-1])["frames"] > 0
        assert (
            f"handctl: warning: {cut} is BEING WRITTEN by a run: the frames shown are what it "
            "holds so far" in done.stderr
        )
        assert "TRUNCATED" not in done.stderr
    done = handctl("monitor", "--log", str(cut))  # the lock gone, and the file cut
    assert f"handctl: warning: {cut} is TRUNCATED (" in done.stderr


def test_an_export_of_a_log_that_does_not_say_when_it_started_says_so(
    recorded: Recorded, tmp_path: Path
) -> None:
    """Without ``started_unix_ns`` the frames were stamped from 1970, without a word; the
    export is in ``--json`` now as well."""

    def metadata(name: str, data: dict[str, str]) -> dict[str, str]:
        return {k: v for k, v in data.items() if k != "started_unix_ns"}

    bad = tmp_path / "when.mcap"
    rewrite(recorded.path, bad, metadata=metadata)
    out, summary = tmp_path / "frames.log", tmp_path / "s.json"
    done = handctl("replay", str(bad), "--export", "candump", str(out), "--json", str(summary))
    assert done.returncode == 0, done.stderr
    assert "warning: export: the log does not say when its run started" in done.stderr
    exported = json.loads(summary.read_text())["export"]
    assert exported["format"] == "candump" and exported["frames"] > 0
    assert out.read_text().startswith("(0.000000) ")


# -- what reaches the bus: one reading of the log, ids as the wire carries them, a run's rate ----
def test_to_bus_sends_what_it_checked_not_what_the_file_became(
    recorded: Recorded, tmp_path: Path, hand: HandConfig, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The checks read the file and the sending read it again: the rest of a file still
    arriving (a copy finishing) between the two went onto the bus unchecked. Checked and sent
    from one copy, taken first."""
    from handctl.online.loop import ZERO_TICKS_BEFORE_DISABLE
    from handctl.recording import frames

    whole = recorded.path.read_bytes()
    full = open_recording(recorded.path)
    assert full.chunk_spans is not None and len(full.chunk_spans) > 4
    offset, length = full.chunk_spans[len(full.chunk_spans) // 2]
    cut = tmp_path / "arriving.mcap"
    cut.write_bytes(whole[: offset + length])  # the chunks so far, read front to back
    arriving = open_recording(cut)
    expected = sum(1 for _ in logged_frames(arriving))
    real_check = frames.check_commands

    def check_then_the_rest_arrives(*args: Any, **kwargs: Any) -> int:
        checked = real_check(*args, **kwargs)
        with cut.open("ab") as handle:
            handle.write(whole[offset + length :])
        return checked

    monkeypatch.setattr(frames, "check_commands", check_then_the_rest_arrives)
    channel = "hostile-arriving"
    with open_bus(f"virtual:{channel}", hand.bus) as listener:
        sent = to_bus(arriving, f"virtual:{channel}", sleep=lambda s: None)
        heard = listener.drain(limit=10**6)
    assert sum(1 for _ in logged_frames(open_recording(cut))) > expected  # the file grew
    # every frame checked, and those only (and the stop of the nodes it left enabled)
    stop = (ZERO_TICKS_BEFORE_DISABLE + 2) * len(hand.fingers) if "stopped" in sent else 0
    assert sent["sent"] == expected
    assert len(heard) == expected + stop


def test_a_logged_id_the_wire_cannot_carry_is_refused(recorded: Recorded, tmp_path: Path) -> None:
    """0x901 without the 29-bit flag is no frame a bus carried; a replay sent it, which a
    controller keeping 11 bits takes for 0x101, a TorqueCommand no check had seen."""
    bad = tmp_path / "id901.mcap"
    rewrite(recorded.path, bad, one_message(ch.CAN_TX, 300, field("id", 0x901)))
    with pytest.raises(ConfigError) as caught:
        to_bus(open_recording(bad), "virtual:never-opened")
    assert ": id: expected a CAN id, an integer 0..0x7FF, or a 29-bit one" in str(caught.value)


def test_to_bus_refuses_a_29_bit_frame_that_aliases_a_command(
    recorded: Recorded, tmp_path: Path, hand: HandConfig, protocol: Protocol
) -> None:
    layout = protocol.layout("TorqueCommand", 1)
    index = _nth_command(recorded, layout.frame_id, 200)
    bad = tmp_path / "ext101.mcap"
    rewrite(recorded.path, bad, one_message(ch.CAN_TX, index, field("id", 0x80000101)))
    text = _refused_with_nothing_sent(open_recording(bad), hand, "hostile-alias")
    assert "no 29-bit frame whose low 11 bits are a command id" in text
    assert "takes it for 0x101" in text


def test_to_bus_refuses_more_commands_than_a_run_sends(
    recorded: Recorded, tmp_path: Path, hand: HandConfig, protocol: Protocol
) -> None:
    """The same command twenty times a tick (or fifty enables) was sent 1 µs apart: a run
    sends one a loop period per node and message, a few at once in a stop at most."""
    layout = protocol.layout("TorqueCommand", 1)
    first = _nth_command(recorded, layout.frame_id, 300)
    with recorded.path.open("rb") as handle:
        at = [
            (json.loads(m.data)["tick"], m.log_time)
            for _, c, m in make_reader(handle).iter_messages(topics=[ch.CAN_TX])
        ][first]

    def same_tick(topic: str, index: int, raw: bytes) -> bytes:
        if topic != ch.CAN_TX or not first <= index < first + 40:
            return raw
        msg = json.loads(raw)
        msg["tick"] = at[0]
        return json.dumps(msg).encode()

    # the 40 frames after it (about 13 ticks of three nodes) all in its tick, at its time
    moved: dict[str, int] = {}

    def times(topic: str, log_time: int) -> int:
        if topic != ch.CAN_TX:
            return log_time
        k = moved[topic] = moved.get(topic, -1) + 1
        return at[1] if first <= k < first + 40 else log_time

    bad = tmp_path / "burst.mcap"
    rewrite(recorded.path, bad, same_tick, times=times)
    text = _refused_with_nothing_sent(open_recording(bad), hand, "hostile-burst")
    assert "expected at most one TorqueCommand_1 to its node a loop period" in text


# -- a file's structure at its limits: a summary that lies, zeros, a chunk that inflates ---------
def _with_summary(whole: bytes, edit: Callable[[list[bytes]], list[bytes]]) -> bytes:
    """``whole`` with its summary section's records through ``edit`` (each a whole record),
    and the footer's summary CRC cleared (0: none to check)."""
    footer_at = len(whole) - len(MAGIC) - 9 - 20
    summary_start = struct.unpack_from("<Q", whole, footer_at + 9)[0]
    summary = whole[summary_start:footer_at]
    records, at = [], 0
    while at < len(summary):
        length = struct.unpack_from("<Q", summary, at + 1)[0]
        records.append(summary[at : at + 9 + length])
        at += 9 + length
    footer = bytearray(whole[footer_at:])
    footer[9 + 16 : 9 + 20] = bytes(4)
    return whole[:summary_start] + b"".join(edit(records)) + bytes(footer)


@pytest.mark.parametrize("how", ["left out", "listed twice"])
def test_a_summary_whose_index_does_not_describe_the_file_is_damaged(
    recorded: Recorded, tmp_path: Path, how: str
) -> None:
    """An index that left a chunk out, or listed one twice, was believed: 'complete', with a
    tenth of the ticks missing or doubled."""
    chunk_index = 0x08

    def edit(records: list[bytes]) -> list[bytes]:
        k = next(i for i, r in enumerate(records) if r[0] == chunk_index)
        return (
            records[:k] + records[k + 1 :]
            if how == "left out"
            else records[:k] + records[k : k + 1] + records[k:]
        )

    bad = tmp_path / "index.mcap"
    bad.write_bytes(_with_summary(recorded.path.read_bytes(), edit))
    recording = open_recording(bad)
    assert not recording.complete and recording.damaged
    assert "the index does not describe the file (a chunk left out or listed twice)" in (
        recording.problem
    )
    done = handctl("replay", str(bad))
    assert "DAMAGED: its summary counts" in done.stdout, done.stdout + done.stderr


def test_an_index_entry_past_the_end_of_the_file_is_damaged(
    recorded: Recorded, tmp_path: Path
) -> None:
    """A chunk index entry of 2^63 - 1 bytes raised OverflowError: a traceback."""

    def edit(records: list[bytes]) -> list[bytes]:
        k = next(i for i, r in enumerate(records) if r[0] == 0x08)
        entry = bytearray(records[k])
        # ChunkIndex: message start and end times, chunk start offset, chunk length
        struct.pack_into("<Q", entry, 9 + 24, (1 << 63) - 1)
        return [*records[:k], bytes(entry), *records[k + 1 :]]

    bad = tmp_path / "huge.mcap"
    bad.write_bytes(_with_summary(recorded.path.read_bytes(), edit))
    recording = open_recording(bad)
    assert recording.damaged and recording.bad_chunks
    assert "past the file's" in recording.bad_chunks[0].reason
    done = handctl("replay", str(bad))
    assert "Traceback" not in done.stderr and "DAMAGED" in done.stdout


def _inflating(data: bytearray, offset: int) -> None:
    """The chunk record at ``offset`` of ``data`` made to declare 3 GiB uncompressed, more than
    any log's (Chunk: message start and end times, then the uncompressed size): damaged
    whatever its compression and CRC (a flipped bit in a chunk without either can read)."""
    struct.pack_into("<Q", data, offset + 9 + 16, 3 << 30)


def test_a_chunk_that_would_inflate_past_any_log_s_is_damaged(
    recorded: Recorded, tmp_path: Path
) -> None:
    """A 49 KB chunk that declared 1.5 GiB of zeros took 1.6 GB of memory to read: a chunk's
    size is bounded before it is decompressed."""
    whole = bytearray(recorded.path.read_bytes())
    full = open_recording(recorded.path)
    assert full.chunk_spans
    _inflating(whole, full.chunk_spans[0][0])
    bad = tmp_path / "inflating.mcap"
    bad.write_bytes(bytes(whole))
    recording = open_recording(bad)
    assert recording.bad_chunks and recording.bad_chunks[0].number == 0
    assert "more than any log's" in recording.bad_chunks[0].reason


def test_a_tail_of_zeros_ends_the_reading_at_once(recorded: Recorded, tmp_path: Path) -> None:
    """A power loss leaves a file's tail zeros; read as records of opcode 0 and length 0, nine
    bytes at a time, a 4 GiB tail took minutes for every pass over the file."""
    whole = recorded.path.read_bytes()
    full = open_recording(recorded.path)
    assert full.chunk_spans
    offset, length = full.chunk_spans[3]
    bad = tmp_path / "zeros.mcap"
    bad.write_bytes(whole[: offset + length] + bytes(8 << 20))
    recording = open_recording(bad)
    assert not recording.complete and recording.chunks == 4
    assert "no record here (opcode 0x00)" in recording.problem


def test_names_from_the_log_are_printed_escaped(recorded: Recorded, tmp_path: Path) -> None:
    """A phase name is the log's to say: an escape sequence in it set the terminal's title,
    cleared it and printed a line of its own."""
    forged = "lift\x1b]0;PWNED\x07\x1b[2J\nFAKE: all good"
    bad = tmp_path / "escapes.mcap"
    rewrite(recorded.path, bad, one_message(ch.PHASE, 0, field("phase", forged)))
    done = handctl("replay", str(bad))
    assert "\x1b" not in done.stdout and "\x07" not in done.stdout
    assert "\\x1b]0;PWNED\\x07" in done.stdout
    assert "\nFAKE: all good" not in done.stdout


def test_to_bus_refuses_a_hand_of_another_shape_than_the_recorded_one(tmp_path: Path) -> None:
    """A node recorded with 4 joints and one on the bus with 5 share a TorqueCommand's
    12 bytes (CAN-FD pads 10 to 12): each command went out whole, its fifth torque the
    padding the recorded node never used, and the log's Feedback frames, shorter than the
    node's on the bus, beside them (an outside audit, on a 5-joint thumb recorded and a
    4-joint one on the bus)."""
    four = ROOT / "config" / "hands" / "four_fingers_four_joints.yaml"
    log = tmp_path / "four.mcap"
    recipe = ROOT / "config" / "recipes" / "four_by_four_close.yaml"
    ran = handctl(
        *("run", "recipe", str(recipe), "--hand", str(four), "--max-seconds", "0.3"),
        *("--log", str(log)),
    )
    assert ran.returncode == 0, ran.stderr
    data = yaml.safe_load(four.read_text())
    data.pop("sim", None)
    joints = data["fingers"][0]["joints"]
    joints.append({**joints[-1], "name": joints[-1]["name"] + "_tip"})
    five = tmp_path / "five_joints_on_node_1.yaml"
    five.write_text(yaml.safe_dump(data, sort_keys=False))
    assert handctl("check", str(five)).returncode == 0
    done = handctl("replay", str(log), "--to-bus", "virtual:hostile-shape", "--hand", str(five))
    assert done.returncode == 2, done.stdout + done.stderr
    name = data["fingers"][0]["name"]
    node = data["fingers"][0]["node_id"]
    assert f"--hand: expected a hand of the recorded shape (node {node} ({name}) 4 joints" in (
        done.stderr
    )
    assert f"found {five}: node {node} ({name}) 5 joints" in done.stderr
    assert "to-bus:" not in done.stdout
    # first of the checks: faster, the log's own commands break its rate limit, and that was
    # said, of a joint of the log's, before the shape (found by an outside audit)
    fast = handctl(
        *("replay", str(log), "--to-bus", "virtual:hostile-shape", "--hand", str(five)),
        *("--speed", "100"),
    )
    assert fast.returncode == 2, fast.stdout + fast.stderr
    assert "--hand: expected a hand of the recorded shape" in fast.stderr, fast.stderr
    same = handctl("replay", str(log), "--to-bus", "virtual:hostile-shape", "--hand", str(four))
    assert same.returncode == 0, same.stderr


def test_a_fault_the_run_never_latched_written_into_its_events_does_not_rerun(
    recorded: Recorded, tmp_path: Path
) -> None:
    """The log's events rewritten to faults the run never had: the replay printed each, and
    the re-run said "bit-exact", exit 0, for it compared torques, state and phase only.
    The forged names are cut on their line."""
    forged = "ANGLE_LIMIT" + "X" * 500

    def fault(topic: str, index: int, raw: bytes) -> bytes:
        if topic != ch.EVENTS or index != 0:
            return raw
        event = json.loads(raw)
        return json.dumps(
            {"tick": event["tick"], "kind": "fault", "name": forged, "category": "ramp",
             "detail": "forged"}
        ).encode()  # fmt: skip

    bad = tmp_path / "forged.mcap"
    rewrite(recorded.path, bad, fault)
    done = handctl("replay", str(bad), "--rerun")
    assert done.returncode == 1, done.stdout + done.stderr
    line = next(x for x in done.stdout.splitlines() if "FAULT ANGLE_LIMIT" in x)
    assert len(line) < 200 and "XXX..." in line
    assert "  faults: logged ANGLE_LIMITXXX" in done.stdout and "; re-run none" in done.stdout
    assert rerun(open_recording(recorded.path)).fault_mismatch == ""


def _without_summary(recorded: Recorded) -> tuple[bytes, list[tuple[int, int]]]:
    """The recorded file up to the end of its last chunk (a writer killed there), and where
    its chunks are."""
    spans = open_recording(recorded.path).chunk_spans
    assert spans and len(spans) >= 5
    end = spans[-1][0] + spans[-1][1]
    return recorded.path.read_bytes()[:end], spans


def test_a_damaged_chunk_in_a_log_without_its_summary_is_stepped_over_and_named(
    recorded: Recorded, tmp_path: Path, channel: str
) -> None:
    """Read front to back, one flipped bit in a chunk ended the reading there: the log was
    said to be cut short (a killed run's, which goes onto a bus) and every chunk after it was
    left unread."""
    whole, spans = _without_summary(recorded)
    damaged = bytearray(whole)
    offset, length = spans[2]
    damaged[offset + length - 40] ^= 0x10  # inside the chunk's compressed records
    bad = tmp_path / "flipped.mcap"
    bad.write_bytes(bytes(damaged))
    recording = open_recording(bad)
    assert recording.damaged and not recording.complete
    assert [c.number for c in recording.bad_chunks] == [2]
    assert recording.chunks == len(spans) - 1
    assert f"{len(spans) - 3} of them after the last damaged one" in recording.problem
    _refused_nothing_sent_by_the_cli(bad, channel, "is DAMAGED (chunk 2 at byte")


@pytest.mark.parametrize("with_summary", [True, False], ids=["indexed", "walked"])
def test_a_log_whose_every_chunk_is_damaged_is_refused(
    recorded: Recorded, tmp_path: Path, with_summary: bool
) -> None:
    """Nothing of the run's messages reads: its summary was that of a run of no tick, exit 0,
    the damage said on a line of its own."""
    whole, spans = _without_summary(recorded)
    if with_summary:
        whole = recorded.path.read_bytes()
    damaged = bytearray(whole)
    for offset, _ in spans:
        _inflating(damaged, offset)
    bad = tmp_path / "all_damaged.mcap"
    bad.write_bytes(bytes(damaged))
    recording = open_recording(bad)
    assert recording.chunks == 0 and len(recording.bad_chunks) == len(spans)
    done = handctl("replay", str(bad))
    assert done.returncode == 2, done.stdout + done.stderr
    assert str(bad) in done.stderr
    assert f"every one of its {len(spans)} chunk(s) of messages is damaged" in done.stderr
    assert "chunk 0 at byte" in done.stderr and "Traceback" not in done.stderr


def _refused_nothing_sent_by_the_cli(log: Path, channel: str, why: str) -> None:
    done = handctl("replay", str(log), "--to-bus", f"virtual:{channel}")
    assert done.returncode != 0 and why in done.stderr, done.stderr
    assert "frames sent" not in done.stderr + done.stdout


def test_a_log_without_its_summary_and_with_a_chunk_taken_out_sends_nothing(
    recorded: Recorded, hand: HandConfig, tmp_path: Path, channel: str
) -> None:
    """Whole chunks and no summary to count them: the file reads as cut short, and its
    frames went onto the bus with a hole of 60 ms in them (exit 0). A run records every
    tick, so the ticks say where the hole is."""
    whole, spans = _without_summary(recorded)
    offset, length = spans[3]
    bad = tmp_path / "hole.mcap"
    bad.write_bytes(whole[:offset] + whole[offset + length :])
    recording = open_recording(bad)
    assert recording.truncated  # nothing in the file itself says a chunk is missing
    text = _refused_with_nothing_sent(recording, hand, channel)
    assert f"{ch.TIMING} tick " in text and "missing, the log goes on at" in text
    assert "expected every tick between the first and the last" in text


def test_a_damaged_hand_record_is_said_as_damaged_not_as_missing(
    recorded: Recorded, tmp_path: Path
) -> None:
    """One byte flipped in the hand config's metadata record: ``replay --rerun`` refused the
    log saying it had found "nothing" there, as if it had been recorded without a hand
    (found by an outside audit); the record is there and does not read."""
    data = bytearray(recorded.path.read_bytes())
    with recorded.path.open("rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None
    record = next(m for m in summary.metadata_indexes if m.name == ch.META_HAND)
    data[record.offset + record.length // 2] ^= 0xFF
    bad = tmp_path / "hand-flipped.mcap"
    bad.write_bytes(bytes(data))
    assert ch.META_HAND in open_recording(bad).bad_metadata
    done = handctl("replay", str(bad), "--rerun")
    assert done.returncode == 2, done.stdout + done.stderr
    assert (
        f"metadata {ch.META_HAND}.yaml: expected the hand config the run used (recorded by "
        f"handctl), found a damaged record '{ch.META_HAND}' (it does not read: handctl "
        "replay's header says where)"
    ) in done.stderr
