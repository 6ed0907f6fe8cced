"""``handctl replay``: the re-run is bit-exact on real recordings (lockstep with faults and an
e-stop, real time, a SIGTERM'd run) and catches a one-ulp difference; the summary, the plot,
the export to python-can's formats and the replay onto a bus; bad input is exit 2."""

from __future__ import annotations

import itertools
import json
import math
import os
import re
import resource
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import can
import pytest
import yaml
from mcap.reader import make_reader
from mcap.writer import Writer

from handctl.config import HandConfig, load_hand
from handctl.hand_protocol import protocol_for
from handctl.online.bus import BusEvent, BusEventKind, Frame, FrameBus, open_bus
from handctl.online.clock import Tick
from handctl.online.loop import Outcome
from handctl.online.taps import TAP_TX, TAP_TX_FAILED
from handctl.protocol import load_protocol
from handctl.recording import channels as ch
from handctl.recording.frames import ReplayInterrupted, logged_frames, to_bus
from handctl.recording.metadata import run_metadata, start_metadata
from handctl.recording.reader import iter_decoded, iter_messages, open_recording
from handctl.recording.recorder import Recorder
from handctl.recording.replay import summarise_recording
from handctl.recording.rerun import rerun
from handctl.recording.series import load_series
from handctl.stopsignals import ctrl_c_at_once, interruption, noted_stops, working

from ..conftest import HAND_YAML, ROOT, handctl
from .another_host import commanding
from .bringup_peer import HOST_IDS, running_hand
from .mcap_copy import rewrite as copy_recording
from .realtime import REALTIME
from .rig import SHORT, TWO_PHASES, short_recipe, sim_on_unix_bus, write_recipe
from .test_recording import ESTOP_TICK, Recorded, record_run


@pytest.fixture(scope="module")
def recorded(hand: HandConfig, tmp_path_factory: pytest.TempPathFactory) -> Recorded:
    directory = tmp_path_factory.mktemp("replay")
    return record_run(hand, short_recipe(hand, directory), directory / "run.mcap")


#: the logged frames' channels
FRAMES = (ch.CAN_RX, ch.CAN_TX)


def rewrite(source: Path, target: Path, change: Any) -> None:
    """Copy a recording message by message, each JSON message through ``change(topic,
    message) -> message`` (the Foxglove protobuf ones as they are)."""

    def json_only(topic: str, index: int, raw: bytes) -> bytes:
        if topic.startswith("/foxglove/"):
            return raw
        return json.dumps(change(topic, json.loads(raw))).encode()

    copy_recording(source, target, json_only)


def test_a_plot_the_disk_cannot_take_is_said_and_the_rest_is_written(
    recorded: Recorded, tmp_path: Path
) -> None:
    """A full disk at the plot (here a file size limit, ``ulimit -f``, which fails the write
    the same way): a traceback, and the ``--json`` asked for never written. Now one line,
    exit 1, the report written with why the plot is not."""
    out, plot = tmp_path / "report.json", tmp_path / "replay.png"
    limit = 32_000  # bytes: the report fits, the picture does not

    def small_files() -> None:
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))

    command = ["replay", str(recorded.path), "--plot", str(plot), "--json", str(out)]
    done = handctl(*command, timeout=300, preexec_fn=small_files)
    assert done.returncode == 1, done.stdout + done.stderr
    assert "Traceback" not in done.stderr
    assert f"handctl: error: --plot: {plot}: no plot written (File too large)" in done.stderr
    assert json.loads(out.read_text())["plot"] == {"path": str(plot), "error": "File too large"}
    assert not plot.exists() and [p.name for p in tmp_path.iterdir()] == [out.name]


@pytest.mark.parametrize("fmt", ["candump", "blf"])
def test_an_export_the_disk_cannot_take_leaves_the_earlier_one_as_it_was(
    recorded: Recorded, tmp_path: Path, fmt: str
) -> None:
    """A full disk during ``--export`` (here a file size limit, which fails the write the
    same way): the export was written in place, so the earlier export the command replaces
    was gone and half of the new one stood under its name, and the command said bad input
    (exit 2). Now the earlier file is as it was, nothing is left beside it, exit 1."""
    out = tmp_path / f"frames.{fmt}"
    first = handctl("replay", str(recorded.path), "--export", fmt, str(out), timeout=300)
    assert first.returncode == 0, first.stderr
    earlier = out.read_bytes()
    limit = 4096  # bytes: far less than the run's frames
    assert len(earlier) > limit

    def small_files() -> None:
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))

    done = handctl(
        "replay", str(recorded.path), "--export", fmt, str(out), timeout=300, preexec_fn=small_files
    )
    assert done.returncode == 1, done.stdout + done.stderr
    assert "Traceback" not in done.stderr
    assert done.stderr.strip().splitlines()[-1] == (
        f"handctl: error: --export: {out} could not be written (File too large); it is unchanged"
    )
    assert out.read_bytes() == earlier
    assert [p.name for p in tmp_path.iterdir()] == [out.name]


# -- re-run -----------------------------------------------------------------------------------
def test_rerun_is_bit_exact_through_faults_and_an_estop(recorded: Recorded) -> None:
    recording = open_recording(recorded.path)
    report = rerun(recording)
    assert report.ok, (report.mismatches[:3], report.frame_mismatches[:3])
    logged_ticks = sum(1 for _ in iter_messages(recording, (ch.TORQUE,)))
    assert report.compared == logged_ticks > ESTOP_TICK
    sent = sum(1 for *_, is_rx in logged_frames(recording) if not is_rx)
    assert report.frames_compared == sent
    assert report.outcome == report.logged_outcome == "safety_stop"


def test_the_phase_a_stop_ended_is_the_same_in_the_run_and_its_replay(
    recorded: Recorded,
) -> None:
    """The run's operator e-stop ends the phase under way: its end and exit in the run's own
    summary (before: no end, no exit) and in the replay's (before: the log's last tick, no
    exit)."""
    run_phases = recorded.result.phases
    assert run_phases[-1]["exit"] == "safety stop: ESTOP"
    assert run_phases[-1]["end_s"] == pytest.approx(ESTOP_TICK * 1e-3)
    recording = open_recording(recorded.path)
    replayed = summarise_recording(recording, load_series(recording))["phases"]
    assert [(p["name"], p["start_s"], p["end_s"], p["exit"]) for p in replayed] == [
        (p["name"], p["start_s"], p["end_s"], p["exit"]) for p in run_phases
    ]


def test_a_stop_after_missed_ticks_ends_the_phase_at_its_tick_s_scheduled_time(
    recorded: Recorded, tmp_path: Path
) -> None:
    """After missed ticks (real time) a tick's scheduled time is later than its number of
    periods, and the run's clock is the schedule's: the replay ended a stopped phase at the
    number of periods, as many ticks early as were missed."""
    late = tmp_path / "late.mcap"

    def missed_five(topic: str, message: dict[str, Any]) -> dict[str, Any]:
        if topic == ch.TIMING and message["tick"] >= 500:
            message["scheduled_ns"] += 5_000_000  # five ticks missed before tick 500
        return message

    rewrite(recorded.path, late, missed_five)
    recording = open_recording(late)
    phases = summarise_recording(recording, load_series(recording))["phases"]
    assert phases[-1]["exit"] == "safety stop: ESTOP"
    assert phases[-1]["end_s"] == pytest.approx(ESTOP_TICK * 1e-3 + 0.005)


def test_a_time_budget_ends_the_phase_where_the_run_said_in_the_replay_too(
    hand: HandConfig, tmp_path: Path
) -> None:
    log = tmp_path / "budget.mcap"
    summary = tmp_path / "budget.json"
    done = handctl(
        "run",
        "recipe",
        str(write_recipe(tmp_path, TWO_PHASES)),
        "--max-seconds",
        "0.75",
        "--log",
        str(log),
        "--summary-json",
        str(summary),
    )
    assert done.returncode == 0, done.stderr
    run = json.loads(summary.read_text())
    run_phases = run["phases"]
    assert run_phases[-1]["exit"] == "stopped: time budget of 0.75 s reached"
    recording = open_recording(log)
    replay = summarise_recording(recording, load_series(recording))
    replayed = replay["phases"]
    assert [(p["name"], p["start_s"], p["end_s"], p["exit"]) for p in replayed] == [
        (p["name"], p["start_s"], p["end_s"], p["exit"]) for p in run_phases
    ]
    # the stages' CPU percentiles as the run's summary has them, from the same 1 µs bins
    # (numpy's interpolation gave other figures; lockstep has no lateness to compare)
    stages = replay["timing"]["stage_cpu_us_p99"]
    assert stages == {k: run["stage_cpu_us_p99"][k] for k in stages}
    assert replay["timing"]["lateness_us"] == run["lateness_us"]


def test_a_run_stopped_in_its_start_up_re_runs_to_the_same_end(
    hand: HandConfig, tmp_path: Path
) -> None:
    """A stop met before the nodes were enabled is an interrupt, in the run and in its
    re-run alike: the re-run of such a log said "NOTHING COMPARED", exit 1, where the run
    had been interrupted (its signal handling alone made the failed start-up an interrupt)."""
    run = record_run(
        hand, short_recipe(hand, tmp_path), tmp_path / "early.mcap", troubles=False,
        stop_at_start=True,
    )  # fmt: skip
    assert run.result.outcome is Outcome.INTERRUPTED, run.result.message
    assert run.result.message.endswith(" during start-up, no node enabled")
    done = handctl("replay", str(run.path), "--rerun")
    assert done.returncode == 0, done.stdout + done.stderr
    assert "rerun: the start-up re-run to the same end (interrupted)" in done.stdout


def test_a_log_with_its_runtime_and_no_tick_has_nothing_to_re_run(
    hand: HandConfig, tmp_path: Path
) -> None:
    """Killed after its runtime was set up and before its first tick, a run leaves a file
    the writer finished with no tick: the re-run said "NOTHING COMPARED", exit 1."""
    log = tmp_path / "no_tick.mcap"
    recorder = Recorder(log, hand, start_metadata(hand, None, ["test"]))
    recorder.wait_ready()
    recorder.add_metadata(
        ch.META_RUN,
        run_metadata(
            mode="lockstep", bus="virtual", seed=0, period_ns=1_000_000, startup_ticks=500,
            reset_node_faults=False, estimator=False,
        ),
    )  # fmt: skip
    recorder.close({"outcome": "interrupted"})
    done = handctl("replay", str(log), "--rerun")
    assert done.returncode == 0, done.stdout + done.stderr
    assert "rerun: nothing to re-run: the run ended before its first tick" in done.stdout


def test_a_log_with_no_tick_and_no_runtime_has_nothing_to_re_run(
    hand: HandConfig, tmp_path: Path
) -> None:
    """A run stopped before its runtime was set up (a signal while it started) leaves a
    closed log with its start and no tick: the re-run said exit 2, as for bad input."""
    log = tmp_path / "unstarted.mcap"
    recorder = Recorder(log, hand, start_metadata(hand, None, ["test"]))
    recorder.wait_ready()
    recorder.close({"outcome": "interrupted"})
    done = handctl("replay", str(log), "--rerun")
    assert done.returncode == 0, done.stdout + done.stderr
    assert "rerun: nothing to re-run: the run ended before its runtime was set up" in done.stdout


@pytest.mark.parametrize(
    ("topic", "key", "value", "said"),
    [
        (ch.PHASE, "phase", "bogus", "phase: logged 'bogus', re-run "),
        (ch.SAFETY, "state", "faulted", "safety state: logged 'faulted', re-run 'running'"),
        (ch.TORQUE, "desired_nm", 0.125, "desired torque of f1_j1 (N·m): logged 0.125, re-run "),
        (ch.SAFETY, "faults_latched", 1, "faults latched: logged 1, re-run 0"),
        # a record moved off its tick leaves the tick without one: no record re-ran "as logged"
        (ch.PHASE, "tick", 10**6, "phase: logged None, re-run "),
        (ch.SAFETY, "tick", 10**6, "safety state: logged None, re-run 'running'"),
    ],
)
def test_rerun_finds_a_tick_whose_phase_state_or_desired_torques_were_rewritten(
    recorded: Recorded, tmp_path: Path, topic: str, key: str, value: object, said: str
) -> None:
    """The applied torques and the frames were compared, not what the tick decided: a log
    whose phase or safety state was rewritten re-ran "bit-exact" while replay's phase table
    showed the rewritten phase."""
    tampered = tmp_path / "decided.mcap"
    target = 300

    def change(t: str, message: dict[str, Any]) -> dict[str, Any]:
        if t == topic and message["tick"] == target:
            if key == "desired_nm":
                message[key][0] = value
            elif key == "tick":
                message[key] = target + 1
            else:
                message[key] = value
        return message

    rewrite(recorded.path, tampered, change)
    report = rerun(open_recording(tampered))
    assert not report.ok and report.mismatched_ticks == 1
    assert len(report.decision_mismatches) == 1
    assert report.decision_mismatches[0].startswith(f"tick {target}: {said}")
    done = handctl("replay", str(tampered), "--rerun")
    assert done.returncode == 1, done.stderr
    assert f"tick {target}: {said}" in done.stdout and "MISMATCH" in done.stdout
    # a phase the recipe does not have: the summary says so too (it split a phase in two
    # without a word, exit 0)
    unknown = "the phase channel says 'bogus' at tick 300, neither a phase of the recorded"
    assert (unknown in done.stderr) == (value == "bogus"), done.stderr


def test_rerun_finds_a_one_ulp_difference(recorded: Recorded, tmp_path: Path) -> None:
    tampered = tmp_path / "tampered.mcap"
    target = 400

    def nudge(topic: str, message: dict[str, Any]) -> dict[str, Any]:
        if topic == ch.TORQUE and message["tick"] == target:
            message["applied_nm"][4] = math.nextafter(message["applied_nm"][4], math.inf)
        return message

    rewrite(recorded.path, tampered, nudge)
    report = rerun(open_recording(tampered))
    assert not report.ok
    assert report.mismatched_ticks == 1
    assert [(m["tick"], m["joint"]) for m in report.mismatches] == [(target, "f2_j2")]
    done = handctl("replay", str(tampered), "--rerun")
    assert done.returncode == 1, done.stderr
    assert f"tick {target} f2_j2" in done.stdout and "MISMATCH" in done.stdout


def test_rerun_finds_a_command_frame_that_differs(recorded: Recorded, tmp_path: Path) -> None:
    tampered = tmp_path / "frame.mcap"
    first_command: list[int] = []

    def flip(topic: str, message: dict[str, Any]) -> dict[str, Any]:
        if topic == ch.CAN_TX and message["id"] == 0x101 and not first_command:
            first_command.append(message["tick"])
            data = bytearray.fromhex(message["data"])
            data[2] ^= 0x01
            message["data"] = data.hex()
        return message

    rewrite(recorded.path, tampered, flip)
    report = rerun(open_recording(tampered))
    assert report.mismatched_ticks == 0  # the torques agree ...
    assert len(report.frame_mismatches) == 1  # ... the frame on the wire does not
    assert f"tick {first_command[0]}" in report.frame_mismatches[0]


def test_log_times_edited_within_a_channel_are_said(
    recorded: Recorded, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The command frames' log times reversed after the run: the re-run said "identical"
    (the frames' content is) and the summary nothing. The writer writes each channel in
    time order, so the replay says how many go back, for the channel."""
    from handctl import cli

    sent = [t for _, t, _ in iter_messages(open_recording(recorded.path), [ch.CAN_TX])]
    first, last = min(sent), max(sent)
    tampered = tmp_path / "times.mcap"
    copy_recording(
        recorded.path,
        tampered,
        times=lambda topic, t: first + last - t if topic == ch.CAN_TX else t,
    )
    report = tmp_path / "r.json"
    assert cli.main(["replay", str(tampered), "--json", str(report)]) == cli.EXIT_OK
    err = capsys.readouterr().err
    assert f"messages of {ch.CAN_TX} have log times earlier than one written before" in err
    back = json.loads(report.read_text())["summary"]["messages_back_in_time"]
    assert list(back) == [ch.CAN_TX] and back[ch.CAN_TX] > 100
    assert cli.main(["replay", str(recorded.path), "--json", str(report)]) == cli.EXIT_OK
    assert "log times earlier" not in capsys.readouterr().err
    assert json.loads(report.read_text())["summary"]["messages_back_in_time"] == {}


def _alter_feedback(
    recorded: Recorded, target: Path, frame_id: int, after_tick: int, change: Any
) -> int:
    """Copy the recording with the first logged frame ``frame_id`` of a tick from
    ``after_tick`` on replaced by ``change(data)``; returns that frame's tick."""
    altered: list[int] = []

    def alter(topic: str, message: dict[str, Any]) -> dict[str, Any]:
        if (
            topic == ch.CAN_RX
            and message["id"] == frame_id
            and message["tick"] >= after_tick
            and not altered
        ):
            altered.append(message["tick"])
            message["data"] = change(bytes.fromhex(message["data"])).hex()
        return message

    rewrite(recorded.path, target, alter)
    assert altered
    return altered[0]


def test_rerun_finds_one_flipped_bit_in_a_feedback_frame(
    recorded: Recorded, tmp_path: Path
) -> None:
    """The flipped frame fails its CRC in the re-run and is rejected; the open-loop torques do
    not change, but the rejects and the joint state of that tick differ from the log."""
    tampered = tmp_path / "flipped.mcap"

    def flip(data: bytes) -> bytes:
        flipped = bytearray(data)
        flipped[10] ^= 0x04  # a bit of Angle2
        return bytes(flipped)

    tick = _alter_feedback(recorded, tampered, 0x182, 400, flip)
    report = rerun(open_recording(tampered))
    assert report.mismatched_ticks == 0  # the torques agree ...
    assert not report.ok  # ... what the driver read does not
    assert report.feedback_compared == report.compared
    about = [m for m in report.frame_mismatches if m.startswith(f"tick {tick}:")]
    assert any("crc rejects: logged 0, re-run 1" in m and "0x182" in m for m in about), about
    assert any("Feedback_2 0x182" in m and "feedback_age_ns" in m for m in about), about
    done = handctl("replay", str(tampered), "--rerun")
    assert done.returncode == 1, done.stdout + done.stderr
    assert "MISMATCH" in done.stdout and f"tick {tick}: crc rejects" in done.stdout


def test_rerun_finds_a_feedback_frame_altered_with_a_good_crc(
    recorded: Recorded, tmp_path: Path
) -> None:
    """A frame changed and re-sealed (counter and CRC valid) is accepted by the re-run, which
    then reads another angle than the run did: named by tick, frame id, joint and values."""
    layout = load_protocol().layout("Feedback", 3)
    tampered = tmp_path / "resealed.mcap"

    def reseal(data: bytes) -> bytes:
        counter, values = layout.decode(data)
        changed = list(values)
        changed[3] += 0.0001  # Angle1 of finger 3 (f3_j1) by one step of the wire
        return layout.encode(counter, changed)

    tick = _alter_feedback(recorded, tampered, layout.frame_id, 300, reseal)
    report = rerun(open_recording(tampered))
    about = [m for m in report.frame_mismatches if m.startswith(f"tick {tick}:")]
    assert len(about) == 1 and "Feedback_3 0x183" in about[0], report.frame_mismatches[:3]
    assert "f3_j1 angle_rad" in about[0] and "rejects" not in about[0]


def test_the_disable_after_the_last_tick_reruns_whenever_the_writer_drains(
    hand: HandConfig, tmp_path: Path
) -> None:
    """The nodes are disabled after the last control tick's push, and those frames belong to
    that tick. A writer that drains between that push and the next tick (a loaded machine)
    writes the tick's row before them; the log must still give them to the tick."""
    run = record_run(
        hand,
        short_recipe(hand, tmp_path, hold_s=0.1),
        tmp_path / "late.mcap",
        troubles=False,
        writer_between_ticks=True,
    )
    assert run.result.outcome is Outcome.COMPLETED
    recording = open_recording(run.path)
    disables = [
        m["tick"] for t, _, m in iter_decoded(recording, (ch.CAN_TX,)) if 0x011 <= m["id"] <= 0x013
    ]
    last_control_tick = max(m["tick"] for _, _, m in iter_decoded(recording, (ch.TORQUE,)))
    assert disables[-3:] == [last_control_tick] * 3
    report = rerun(recording)
    assert report.ok, (report.mismatches[:3], report.frame_mismatches[:3])
    assert report.outcome == report.logged_outcome == "completed"
    sent = sum(1 for *_, is_rx in logged_frames(recording) if not is_rx)
    assert report.frames_compared == sent


@REALTIME
def test_realtime_recording_reruns_bit_exact(tmp_path: Path) -> None:
    """Real time, the simulated hand in its own process: frames arrive when they arrive, and
    the log holds what each poll drained, so the re-run still matches bit for bit."""
    log = tmp_path / "rt.mcap"
    done = handctl(
        "run",
        "recipe",
        str(short_recipe_path(tmp_path)),
        "--realtime",
        "--max-seconds",
        "0.6",
        "--log",
        str(log),
    )
    assert done.returncode in (0, 3, 130), done.stderr
    recording = open_recording(log)
    assert recording.complete
    assert recording.meta(ch.META_RUN, "mode") == "realtime"
    report = rerun(recording)
    assert report.ok, (report.mismatches[:3], report.frame_mismatches[:3])
    # On a busy machine the real-time run may end early in a loop-overrun stop; the re-run
    # must then reach the same stop from the logged missed ticks.
    assert report.compared > 0
    assert report.outcome == report.logged_outcome


def test_a_run_that_heard_29_bit_frames_replays_and_reruns(tmp_path: Path) -> None:
    """A 29-bit frame on the bus is counted and otherwise left alone by the host, and its log
    holds it with the id as the host held it (``EXTENDED_ID_FLAG`` set). The reader took that
    id for no CAN id, and every mode refused the log of a run that had gone well."""
    faults = tmp_path / "twins.yaml"
    faults.write_text(
        "description: 29-bit twins of node 1's feedback\n"
        "faults:\n"
        "  - {kind: extended_twin, node: 1, message: feedback, start: 0.3, stop: 0.31}\n"
    )
    log, out, dump = tmp_path / "run.mcap", tmp_path / "summary.json", tmp_path / "frames.log"
    done = handctl(
        "run",
        "recipe",
        str(short_recipe_path(tmp_path)),
        "--sim-faults",
        str(faults),
        "--max-seconds",
        "0.5",
        "--log",
        str(log),
        "--summary-json",
        str(out),
    )
    assert done.returncode == 0, done.stderr
    assert json.loads(out.read_text())["rejected_frames"]["extended_id"] > 0
    again = handctl("replay", str(log), "--rerun", "--export", "candump", str(dump))
    assert again.returncode == 0, again.stderr
    assert "applied torques bit-exact" in again.stdout
    extended = [line for line in dump.read_text().splitlines() if " can0 " in line]
    assert any(len(line.split()[2].split("#")[0]) == 8 for line in extended)  # a 29-bit id


def short_recipe_path(directory: Path) -> Path:
    path = directory / "short_hold.yaml"
    path.write_text(SHORT)
    return path


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGHUP])
def test_sigterm_leaves_a_complete_file_that_reruns(tmp_path: Path, sig: signal.Signals) -> None:
    """SIGHUP (the terminal or the SSH session gone) too: a controlled stop, not a death."""
    log = tmp_path / "term.mcap"
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "handctl",
            "run",
            "recipe",
            "config/recipes/swap_two_cylinders.yaml",
            "--log",
            str(log),
        ],
        cwd=ROOT,
        text=True,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
    )
    try:
        deadline = time.monotonic() + 60
        while not (log.exists() and log.stat().st_size > 300_000):  # chunks: ticking
            assert proc.poll() is None and time.monotonic() < deadline, proc.stderr
            time.sleep(0.02)
        proc.send_signal(sig)
        _, stderr = proc.communicate(timeout=60)
    finally:
        proc.kill()
    assert proc.returncode == 130, stderr
    with log.open("rb") as handle:
        summary = make_reader(handle).get_summary()
    assert summary is not None and summary.chunk_indexes and summary.statistics
    recording = open_recording(log)
    assert recording.complete
    assert (recording.json_meta(ch.META_SUMMARY) or {})["outcome"] == "interrupted"
    done = handctl("replay", str(log), "--rerun")
    assert done.returncode == 0, done.stdout + done.stderr
    assert "bit-exact" in done.stdout


# -- summary and plot -------------------------------------------------------------------------
def test_summary_and_plot(recorded: Recorded, tmp_path: Path) -> None:
    plot, out = tmp_path / "run.png", tmp_path / "summary.json"
    done = handctl("replay", str(recorded.path), "--plot", str(plot), "--json", str(out))
    assert done.returncode == 0, done.stderr
    assert plot.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and plot.stat().st_size > 20_000
    summary = json.loads(out.read_text())["summary"]
    assert summary["complete"] and summary["outcome"] == "safety_stop"
    assert [p["name"] for p in summary["phases"]] == ["close", "hold"]
    assert summary["phases"][0]["exit"] == "timeout"
    assert summary["phases"][0]["duration_s"] == pytest.approx(0.3, abs=0.002)
    assert [(f["code"], f["tick"]) for f in summary["faults"]] == [("ESTOP", ESTOP_TICK)]
    peak = recorded.result.max_abs_tau.tolist()
    assert [abs(t["applied_nm"]) for t in summary["largest_torques"].values()] == pytest.approx(
        peak, abs=1e-5
    )
    assert summary["drops"] == dict.fromkeys(
        ("dropped_ticks", "dropped_frames", "dropped_events", "dropped_poses"), 0
    )
    assert summary["timing"]["missed_ticks"] == 0
    assert summary["rejected_frames"]["unexpected_id"] > 0
    assert set(summary["objects"]) == {"cyl1", "cyl2"}
    assert "ESTOP" in done.stdout and "close" in done.stdout


def test_truncated_file_is_summarised_and_rerun_as_far_as_it_goes(
    recorded: Recorded, tmp_path: Path
) -> None:
    data = recorded.path.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: len(data) * 2 // 3])
    recording = open_recording(cut)
    summary = summarise_recording(recording, load_series(recording))
    assert not summary["complete"] and summary["ticks"] > 0
    report = rerun(recording)
    assert report.ok and report.compared > 0
    assert any("where the log ends" in note for note in report.notes)
    # what it holds repeats, but its writer did not finish it: the run went on past the cut
    # (a full disk's RECORDING_LOST stop ramp, say) and that was never compared; it was
    # "verified", exit 0, with no word of the rest
    out = tmp_path / "cut.json"
    done = handctl("replay", str(cut), "--rerun", "--json", str(out))
    assert done.returncode == 1, done.stdout + done.stderr
    assert "TRUNCATED" in done.stdout and "bit-exact" in done.stdout
    assert "rerun: FAILED: not the whole log: it is TRUNCATED" in done.stderr
    assert json.loads(out.read_text())["rerun"]["whole_log"] is False
    whole = tmp_path / "whole.json"
    assert handctl("replay", str(recorded.path), "--rerun", "--json", str(whole)).returncode == 0
    assert json.loads(whole.read_text())["rerun"]["whole_log"] is True


# -- frames out -------------------------------------------------------------------------------
@pytest.mark.parametrize(
    ("fmt", "reader"),
    [("candump", can.CanutilsLogReader), ("asc", can.ASCReader), ("blf", can.BLFReader)],
)
def test_export_reads_back_with_python_can(
    recorded: Recorded, tmp_path: Path, fmt: str, reader: Any
) -> None:
    out = tmp_path / f"frames.{fmt if fmt != 'candump' else 'log'}"
    done = handctl("replay", str(recorded.path), "--export", fmt, str(out))
    assert done.returncode == 0, done.stderr
    logged = [(fid, data, rx) for _, fid, data, rx in logged_frames(open_recording(recorded.path))]
    back = [(m.arbitration_id, bytes(m.data), m.is_rx) for m in reader(str(out))]
    assert [(f, d) for f, d, _ in back] == [(f, d) for f, d, _ in logged]
    if fmt != "candump":  # candump -L keeps no direction
        assert [rx for *_, rx in back] == [rx for *_, rx in logged]
    # each frame at its time of day, as a reader with absolute times reads it: the ASC's
    # date was the export's moment, and its milliseconds lost their leading zeros
    recording = open_recording(recorded.path)
    started = int(recording.meta("handctl.command", "started_unix_ns")) * 1e-9
    options = {"relative_timestamp": False} if fmt == "asc" else {}
    with reader(str(out), **options) as frames:
        first = next(iter(frames))
    assert abs(first.timestamp - started) < 2e-3, (first.timestamp, started)


def test_an_export_replaces_only_an_earlier_export_of_its_format(
    recorded: Recorded, tmp_path: Path
) -> None:
    """``--export blf hand.yaml`` replaced the hand config with BLF data, exit 0, where
    ``--json hand.yaml`` refused: an export replaces a new or empty file, or an export."""
    config = tmp_path / "hand.yaml"
    config.write_text((ROOT / "config" / "hands" / "hiroshima_hand.yaml").read_text())
    kept = config.read_bytes()
    done = handctl("replay", str(recorded.path), "--export", "blf", str(config))
    assert done.returncode == 2, done.stderr
    assert "an existing file that is not a blf export" in done.stderr
    assert config.read_bytes() == kept
    for fmt in ("candump", "asc", "blf"):
        out = tmp_path / f"frames.{fmt}"
        for _ in range(2):  # written, then written again over itself
            done = handctl("replay", str(recorded.path), "--export", fmt, str(out))
            assert done.returncode == 0, done.stderr
    other = tmp_path / "frames.asc"
    done = handctl("replay", str(recorded.path), "--export", "candump", str(other))
    assert done.returncode == 2 and "not a candump export" in done.stderr


def test_to_bus_sends_every_frame_with_its_spacing(
    recorded: Recorded, hand: HandConfig, channel: str
) -> None:
    recording = open_recording(recorded.path)
    logged = list(logged_frames(recording))
    now = [0.0]
    waits: list[float] = []

    def clock() -> float:
        return now[0]

    def sleep(seconds: float) -> None:
        waits.append(seconds)
        now[0] += seconds

    with open_bus(f"virtual:{channel}", hand.bus) as listener:
        sent = to_bus(recording, f"virtual:{channel}", speed=4.0, sleep=sleep, clock=clock)
        heard = listener.drain(limit=10**7)
    assert sent["sent"] == len(logged) and sent["failed"] == 0
    # the run disabled the nodes at its end: nothing is sent after its frames
    assert [(f.arbitration_id, f.data) for f in heard] == [(fid, d) for _, fid, d, _ in logged]
    assert "stopped" not in sent
    span = (logged[-1][0] - logged[0][0]) * 1e-9
    assert now[0] == pytest.approx(span / 4.0, rel=1e-6)


def test_to_bus_slowed_past_the_nodes_watchdog_is_refused(
    recorded: Recorded, hand: HandConfig, channel: str
) -> None:
    """Below ``--speed 0.1`` the run's commands, 1 ms apart, went out more than the nodes'
    10 ms command watchdog apart: every node faulted (an outside audit). At 0.1 itself, the
    watchdog exactly, they faulted too (their own 1 ms tick and the bus take 2 ms of it: an
    outside audit of that refusal). Refused before anything is sent, naming the slowest speed
    the log allows, 8 ms apart (exit 2); that one goes."""
    from handctl.errors import ConfigError

    recording = open_recording(recorded.path)
    now = [0.0]

    def sleep(seconds: float) -> None:  # the spacing, without the wait
        now[0] += seconds

    with open_bus(f"virtual:{channel}", hand.bus) as listener:
        with pytest.raises(ConfigError) as refused:
            to_bus(recording, f"virtual:{channel}", speed=0.1, sleep=sleep, clock=lambda: now[0])
        assert not listener.drain(limit=10**7)
        sent = to_bus(
            recording, f"virtual:{channel}", speed=0.125, sleep=sleep, clock=lambda: now[0]
        )
    said = str(refused.value)
    assert said.startswith("--speed: expected 0.125 or faster (nothing was sent): the log's")
    assert "commands to a node it has enabled come up to 1 ms apart" in said
    assert "more than 8 ms apart, within 2 ms of their 10 ms command watchdog" in said
    assert said.endswith("found 0.1")
    assert sent["sent"] == len(list(logged_frames(recording)))


def test_to_bus_refuses_command_frames_without_tick_rows(
    recorded: Recorded, hand: HandConfig, channel: str, tmp_path: Path
) -> None:
    """The pacing checks (safety.md #88, #99) read the tick rows, and a log with none was not
    checked at all: its ``/loop/timing`` channel dropped, with the end record's tick count,
    and its frames moved 30 s on halfway, it went out, enabled the nodes and then sent
    nothing for 30 s (an outside audit). A run logs a row for every tick it commands on:
    refused, exit 2, nothing sent."""
    from handctl.errors import ConfigError

    with recorded.path.open("rb") as handle:
        stamps = [m.log_time for _, _, m in make_reader(handle).iter_messages(topics=[ch.TIMING])]
    cut = sorted(stamps)[len(stamps) // 2]

    def no_ticks(name: str, values: dict[str, str]) -> dict[str, str]:
        return {k: v for k, v in values.items() if not (name == ch.META_END and k == "ticks")}

    bad = tmp_path / "no_ticks.mcap"
    copy_recording(
        recorded.path,
        bad,
        metadata=no_ticks,
        drop=(ch.TIMING,),
        times=lambda topic, t: t + 30 * 10**9 if t > cut and topic in FRAMES else t,
    )
    now = [0.0]

    def sleep(seconds: float) -> None:  # the spacing, without the wait
        now[0] += seconds

    with open_bus(f"virtual:{channel}", hand.bus) as listener:
        with pytest.raises(ConfigError) as refused:
            to_bus(open_recording(bad), f"virtual:{channel}", sleep=sleep, clock=lambda: now[0])
        assert not listener.drain(limit=10**7)
    said = str(refused.value)
    assert said.startswith(f"{bad}: channel {ch.TIMING}: expected a tick row for every tick")
    assert "found none, and the /can/tx frame 0x011 " in said  # the first enable


def test_to_bus_refuses_a_node_left_without_commands_past_its_watchdog(
    recorded: Recorded, hand: HandConfig, tmp_path: Path
) -> None:
    """Node 1's TorqueCommands of 20 ticks taken out, every tick row and every other frame
    as logged, the end record counting the frames left: each frame left is at its tick's
    time, and every check passed, but node 1 would go 21 ms without a command, past its
    10 ms watchdog (the counters after the gap renumbered, in sequence as a node takes
    them). The gap between a node's commands is read from the frames themselves: refused,
    exit 2, nothing sent."""
    layout = protocol_for(hand).layout("TorqueCommand", 1)
    torque = layout.frame_id

    def keep(topic: str, raw: bytes) -> bool:
        msg = json.loads(raw) if topic == ch.CAN_TX else {}
        return not (msg.get("id") == torque and 300 <= msg["tick"] < 320)

    def renumbered(topic: str, index: int, raw: bytes) -> bytes:
        msg = json.loads(raw) if topic == ch.CAN_TX else {}
        if msg.get("id") != torque or msg["tick"] < 320:
            return raw
        counter, values = layout.decode(bytes.fromhex(msg["data"]))
        return json.dumps(
            msg | {"data": layout.encode((counter - 20) % 256, values).hex()}
        ).encode()

    def counted(name: str, values: dict[str, str]) -> dict[str, str]:
        # the end record counts the frames left, as the run's writer would have
        if name != ch.META_END:
            return values
        return values | {"frames": str(int(values["frames"]) - 20)}

    bad = tmp_path / "gap.mcap"
    copy_recording(recorded.path, bad, renumbered, metadata=counted, keep=keep)
    done = handctl("replay", str(bad), "--to-bus", "virtual:gap")
    assert done.returncode == 2, done.stdout + done.stderr
    assert "frames sent" not in done.stdout + done.stderr
    assert f"/can/tx frame 0x{torque:03X} " in done.stderr
    assert "expected a command to node 1 within the nodes' 10 ms command watchdog" in done.stderr
    assert "found 0.021 s after the one before" in done.stderr


def test_to_bus_stopped_midway_zeroes_and_disables_the_nodes_it_enabled(
    recorded: Recorded, hand: HandConfig, channel: str
) -> None:
    """Ctrl-C in a replay onto a bus (or a log that ends with the nodes enabled, a run
    killed) left the hand under the last torques sent, near tau_max, until the nodes'
    watchdog faulted them. The replay ends as a run's stop does: zero torque to every node
    it left enabled for six periods, then a disable, each on the node's next counter."""
    recording = open_recording(recorded.path)
    logged = list(logged_frames(recording))
    halfway = (logged[-1][0] - logged[0][0]) * 1e-9 / 2  # s, the nodes enabled, under torque
    now = [0.0]

    def sleep(seconds: float) -> None:
        before = now[0]
        now[0] += seconds
        if before < halfway <= now[0]:
            raise KeyboardInterrupt

    with open_bus(f"virtual:{channel}", hand.bus) as listener:
        with pytest.raises(KeyboardInterrupt):
            to_bus(recording, f"virtual:{channel}", sleep=sleep, clock=lambda: now[0])
        heard = [(f.arbitration_id, f.data) for f in listener.drain(limit=10**7)]
    _ends_with_the_stop(hand, heard)


def _ends_with_the_stop(hand: HandConfig, heard: list[tuple[int, bytes]]) -> None:
    """``heard`` ends with a run's stop of every node the replay had under torque: six
    periods of zero torque, then a disable, each on the node's next counter."""
    protocol = protocol_for(hand)
    nodes = [f.node_id for f in hand.fingers]
    torque = {n: protocol.layout("TorqueCommand", n) for n in nodes}
    command = {n: protocol.layout("NodeCommand", n) for n in nodes}
    tail = heard[-7 * len(nodes) :]
    assert [fid for fid, _ in tail] == [torque[n].frame_id for n in nodes] * 6 + [
        command[n].frame_id for n in nodes
    ]
    for n in nodes:
        sent = [torque[n].decode(d) for fid, d in heard if fid == torque[n].frame_id]
        assert any(any(v != 0.0 for v in values) for _, values in sent[:-6])  # was under torque
        assert all(values == (0.0,) * len(values) for _, values in sent[-6:])
        counters = [c for c, _ in sent]
        assert all(b == (a + 1) & 0xFF for a, b in itertools.pairwise(counters))
        last = [command[n].decode(d) for fid, d in heard if fid == command[n].frame_id][-1]
        assert last[1] == (2.0,)  # disable


@pytest.mark.parametrize(
    ("first", "second"),
    [(signal.SIGINT, signal.SIGINT), (signal.SIGTSTP, signal.SIGTERM)],
    ids=["ctrl-c-twice", "ctrl-z-then-sigterm"],
)
def test_to_bus_sends_its_stop_whole_whatever_signals_follow(
    recorded: Recorded, hand: HandConfig, channel: str, first: int, second: int
) -> None:
    """A second Ctrl-C (or a SIGTERM) 5 ms after the first cut the replay's stop short: the
    hand left under the last torques sent, no zero, no disable (an outside probe, 4 runs in
    4). Ctrl-Z suspended the replay mid-stream, its torque on. Each stop signal is noted
    now and looked at between two frames; the stop is sent whole, and the ones that came
    during it are said."""
    recording = open_recording(recorded.path)
    logged = list(logged_frames(recording))
    halfway = (logged[-1][0] - logged[0][0]) * 1e-9 / 2
    now = [0.0]
    kills: list[int] = []

    def sleep(seconds: float) -> None:
        before = now[0]
        now[0] += seconds
        if before < halfway <= now[0]:
            kills.append(first)
            os.kill(os.getpid(), first)
        elif now[0] > halfway and len(kills) == 1:  # the stop's first sleep
            kills.append(second)
            os.kill(os.getpid(), second)

    class SuspendedError(Exception):
        pass

    def suspended(signum: int, frame: object) -> None:  # not the worker's own stop
        raise SuspendedError

    before = signal.signal(signal.SIGTSTP, suspended)
    working()  # a command begins: no signal yet
    try:
        with open_bus(f"virtual:{channel}", hand.bus) as listener:
            with pytest.raises(ReplayInterrupted) as stopped, noted_stops() as stops:
                to_bus(
                    recording,
                    f"virtual:{channel}",
                    sleep=sleep,
                    clock=lambda: now[0],
                    stops=stops,
                )
            heard = [(f.arbitration_id, f.data) for f in listener.drain(limit=10**7)]
        assert signal.getsignal(signal.SIGTSTP) is suspended  # put back as it was
    finally:
        signal.signal(signal.SIGTSTP, before)
    assert kills == [first, second]
    assert stopped.value.why.startswith(signal.Signals(first).name)
    assert stopped.value.ignored == [signal.Signals(second).name]
    # the command's last line names the signal but Ctrl-C's (a bare "interrupted" after a
    # SIGTERM: an outside audit)
    name = signal.Signals(first).name
    assert interruption() == ("interrupted" if first == signal.SIGINT else f"interrupted by {name}")
    assert "left enabled by the frames sent: zero torque and a disable" in stopped.value.stopped
    _ends_with_the_stop(hand, heard)


def test_a_fault_is_heard_only_from_a_node_the_replay_had_enabled(hand: HandConfig) -> None:
    """What the replay listens for: a node's Feedback saying FAULT while the replay had it
    enabled. A node still in FAULT from before (the log's own fault reset comes later), a
    Feedback that fails its CRC and a node ENABLED are not the hand stopping under it."""
    from handctl.online.drivers.finger import FingerLayouts
    from handctl.protocol import NodeState
    from handctl.recording.frames import _FaultsHeard, _LeftEnabled

    protocol = protocol_for(hand)
    left = _LeftEnabled(hand, protocol)
    heard = _FaultsHeard(hand, left)
    node = hand.fingers[0].node_id
    layouts = FingerLayouts.for_node(protocol, node)
    k = len(hand.fingers[0].joints)

    def feedback(state: NodeState, bits: int = 0) -> Frame:
        values = (0.0,) * (2 * k) + (int(state), bits)
        return Frame(layouts.feedback.frame_id, layouts.feedback.encode(0, values))

    timeout = 1  # the TIMEOUT bit (``fault_names``)
    assert not heard.hear([feedback(NodeState.FAULT, timeout)])  # not enabled by the replay
    torque = layouts.command
    left.sent(torque.frame_id, torque.encode(0, (0.0,) * k))  # under the replay's command now
    bad = feedback(NodeState.FAULT, timeout)
    assert not heard.hear([bad._replace(data=bad.data[:-1] + bytes([bad.data[-1] ^ 1]))])
    assert not heard.hear([feedback(NodeState.ENABLED)])
    assert heard.hear([feedback(NodeState.ENABLED), feedback(NodeState.FAULT, timeout)])
    assert heard.first.startswith(f"node {node} ({hand.fingers[0].name}) went into FAULT (")
    # a node of another hand config: a Feedback of another length on the same id, which
    # never decoded, so that hand's FAULT went unheard (an outside probe: exit 0). Its own
    # stream, each at the next counter; one such frame alone is a reject, any peer's
    other = _FaultsHeard(hand, left)
    values = (0.0,) * (2 * k) + (int(NodeState.ENABLED), 0)
    stream = [
        Frame(layouts.feedback.frame_id, layouts.feedback.encode(c, values)[:-2]) for c in range(5)
    ]
    assert not other.hear(stream[:1]) and not other.hear(stream[2:])  # a skip: not its own
    assert other.hear(stream)
    assert other.first == (
        f"node {node} ({hand.fingers[0].name}) answers with a {layouts.feedback.name} of "
        f"{layouts.feedback.length - 2} bytes where the recorded hand's is "
        f"{layouts.feedback.length}: a hand of another config is on the bus, and the replay "
        "stopped there"
    )


def test_a_joint_outside_is_the_replay_s_to_stop_only_under_its_torque_outwards(
    hand: HandConfig,
) -> None:
    """A replay stopped on any joint outside its soft limits, where a run's controlled stop
    does not fault a joint that sinks out while its torques ramp out (row 64): the replay of
    a run's end onto a hand that sags ended in a stop, exit 1, where the run had ended well
    (an outside audit). A joint outside is the replay's to stop when the torque it last sent
    that joint pushes it further out; under none, or one towards its range, it is not."""
    from handctl.online.drivers.finger import FingerLayouts
    from handctl.protocol import NodeState
    from handctl.recording.frames import _FaultsHeard, _LeftEnabled

    protocol = protocol_for(hand)
    left = _LeftEnabled(hand, protocol)
    heard = _FaultsHeard(hand, left)
    finger = hand.fingers[0]
    joint = finger.joints[0]
    layouts = FingerLayouts.for_node(protocol, finger.node_id)
    k = len(finger.joints)
    below = joint.angle_min - 0.05  # rad: sunk out past its lower limit

    def feedback() -> Frame:
        angles = (below,) + (0.0,) * (k - 1)  # after the TDT torques, as the layout has them
        values = (0.0,) * k + angles + (int(NodeState.ENABLED), 0)
        return Frame(layouts.feedback.frame_id, layouts.feedback.encode(0, values))

    def torque(first: float) -> None:
        command = layouts.command
        left.sent(command.frame_id, command.encode(0, (first,) + (0.0,) * (k - 1)))

    torque(0.0)  # enabled, its torques ramped out
    assert not heard.hear([feedback()])
    torque(abs(joint.tau_max) / 4)  # towards its range
    assert not heard.hear([feedback()])
    torque(-abs(joint.tau_max) / 4)  # further out: the replay drives it there
    assert heard.hear([feedback()])
    assert heard.first.startswith(f"{joint.name} at ")
    assert "with the replay's torque (-" in heard.first


def test_the_replay_s_stop_imports_nothing(
    hand: HandConfig, channel: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The replay's stop imported the run's loop (for how many zero ticks) when it began,
    some 25 ms, and the zero torque reached the hand 25-100 ms after the last command: the
    nodes' 10 ms watchdog had faulted them first, and the replay said it had stopped them
    (an outside probe, 6 runs in 6). What it needs is there before the first frame goes."""
    import builtins

    from handctl.recording.frames import _LeftEnabled

    left = _LeftEnabled(hand, protocol_for(hand))
    layout = protocol_for(hand).layout("TorqueCommand", hand.fingers[0].node_id)
    left.sent(layout.frame_id, layout.encode(0, (0.1,) * len(hand.fingers[0].joints)))

    def no_import(*args: Any, **kwargs: Any) -> Any:
        raise AssertionError(f"the stop imported {args[0]}")

    with (
        open_bus(f"virtual:{channel}", hand.bus) as bus,
        open_bus(f"virtual:{channel}", hand.bus) as listener,
    ):
        monkeypatch.setattr(builtins, "__import__", no_import)
        said = left.stop(bus, hand.bus.period_s, lambda seconds: None)
        monkeypatch.undo()
        heard = listener.drain(limit=10**6)
    assert said.startswith(f"node(s) {hand.fingers[0].node_id} left enabled")
    assert [f.arbitration_id for f in heard][-1] == protocol_for(hand).layout(
        "NodeCommand", hand.fingers[0].node_id
    ).frame_id  # zeros, then the disable


def test_to_bus_onto_a_hand_resting_outside_its_soft_limits_sends_nothing(
    recorded: Recorded, hand: HandConfig, channel: str
) -> None:
    """A joint resting outside its soft limits stops any run before any torque (safety.md
    #19); a replay onto such a hand (a simulated hand whose fingers had sagged past a limit)
    enabled every node and sent its torques, exit 0 (an outside audit). It refuses as a run
    does, naming the joint, its angle and limits and how to bring it back: nothing sent."""
    from handctl.errors import ConfigError, HandctlError

    from .test_bringup_jog import resting_outside

    spec = f"virtual:{channel}"
    recording = open_recording(recorded.path)
    with (
        running_hand(hand, spec, params=resting_outside(hand)),
        open_bus(spec, hand.bus) as listener,
    ):
        with pytest.raises(HandctlError) as refused:
            to_bus(recording, spec, direction="tx")
        heard = listener.drain(limit=10**6)
    assert not isinstance(refused.value, ConfigError)  # exit 1, as a node in FAULT before
    said = str(refused.value)
    assert said.startswith(f"{spec}: a joint of the hand on the bus rests outside its soft")
    assert "f1_j3 at -0.9" in said and "limits [-0.900, +2.300]" in said
    assert "bring it back with `handctl jog f1_j3 --torque +X --recover`" in said
    assert said.endswith("(nothing was sent)")
    assert heard and not [f for f in heard if f.arbitration_id in HOST_IDS]


def test_to_bus_onto_a_hand_of_another_config_sends_nothing(
    recorded: Recorded, hand: HandConfig, channel: str
) -> None:
    """A hand of another config on the bus (two joints a node where the log's had three): the
    replay skipped its Feedback, of another length, while it listened, and noticed only
    from the nodes it had enabled, once the enable and some torques had gone (an outside
    probe: node 1 ENABLED, 7 TorqueCommands). Heard before the first frame, it refuses:
    nothing sent, exit 1."""
    from handctl.errors import ConfigError, HandctlError

    other = load_hand(ROOT / "config" / "hands" / "planar_2f2j.yaml")
    spec = f"virtual:{channel}"
    recording = open_recording(recorded.path)
    with running_hand(other, spec), open_bus(spec, hand.bus) as listener:
        with pytest.raises(HandctlError) as refused:
            to_bus(recording, spec, direction="tx")
        heard = listener.drain(limit=10**6)
    assert not isinstance(refused.value, ConfigError)  # exit 1, as a node in FAULT before
    # node 1's or node 2's, whichever the replay heard first
    said = re.sub(r"node ([12]) \(f\1\) answers with a Feedback_\1 ", "node N ", str(refused.value))
    assert said == (
        f"{spec}: node N of 12 bytes where the recorded hand's is 16: a hand of another "
        "config is on the bus, heard before the replay sent anything: its frames are not "
        "that hand's (nothing was sent)"
    )
    assert heard and not [f for f in heard if f.arbitration_id in HOST_IDS]


def test_to_bus_stops_when_a_joint_it_drives_leaves_its_soft_limits(
    hand: HandConfig, channel: str, tmp_path: Path
) -> None:
    """The replay watched no angle while it sent: a joint driven past its soft limit went on
    under the log's torques. The simulated hand steps in lockstep with the replay's clock;
    on the hand on the bus (``--hand``, its f1_j1 allowed 10 mrad above where it is when the
    replay begins, which it passes midway) the replay stops there as a run stops on
    ANGLE_LIMIT: the joint, its angle and limits said, zero torque and a disable to the nodes
    it had enabled, and the command's exit 1 (``node_fault``)."""
    from handctl.sim.hand import SimulatedHand

    clean = record_run(hand, short_recipe(hand, tmp_path), tmp_path / "run.mcap", troubles=False)
    recording = open_recording(clean.path)
    logged = list(logged_frames(recording, "tx"))
    spec = f"virtual:{channel}"
    with open_bus(spec, hand.bus) as its_bus, open_bus(spec, hand.bus) as listener:
        sim = SimulatedHand(hand, its_bus)
        for _ in range(500):  # under way: it sags from its initial angles as it starts
            sim.step()
        limit = round(float(sim.plant.joint_angles[0]) + 0.01, 4)  # rad
        doc = yaml.safe_load(HAND_YAML.read_text())
        doc["fingers"][0]["joints"][0]["angle_max"] = limit
        path = tmp_path / "narrow.yaml"
        path.write_text(yaml.safe_dump(doc))
        now = [sim.ticks * 1e-3]  # s, the hand's time

        def sleep(seconds: float) -> None:  # the hand's time goes as the replay's
            now[0] += seconds
            while sim.ticks * 1e-3 < now[0]:
                sim.step()

        listener.drain(limit=10**7)
        sent = to_bus(
            recording, spec, direction="tx", hand=load_hand(path), sleep=sleep, clock=lambda: now[0]
        )
        heard = [
            (f.arbitration_id, f.data)
            for f in listener.drain(limit=10**7)
            if f.arbitration_id in HOST_IDS
        ]
    assert sent["node_fault"].startswith("f1_j1 at -0.36"), sent
    assert (
        f", {limit:+.3f}]: a joint of node 1 (f1) left its soft limits with the replay's "
        "torque (+" in (sent["node_fault"])
    )
    assert sent["sent"] < len(logged)  # stopped there, not sent to its end
    assert "zero torque and a disable sent after them" in sent["stopped"]
    _ends_with_the_stop(hand, heard)


@REALTIME
def test_to_bus_onto_a_hand_that_faults_under_it_stops_and_says_so(
    recorded: Recorded, hand: HandConfig, tmp_path: Path
) -> None:
    """A replay onto a live hand that fell behind (a loaded host) let the nodes' 10 ms command
    watchdog time out, went on sending to the faulted hand and exited 0 (an outside probe, 2
    runs in 2). The simulated hand in its own process hears the replay's commands; the
    replay stalls once for 0.1 s with the nodes under torque: it hears a node's FAULT, stops
    the nodes it had enabled and says so, and the command exits 1."""
    bus = tmp_path / "bus"
    with sim_on_unix_bus(bus):
        recording = open_recording(recorded.path)
        logged = list(logged_frames(recording, "tx"))
        halfway = (logged[-1][0] - logged[0][0]) * 1e-9 / 2  # s, the nodes under torque
        began = time.perf_counter()
        stalled: list[float] = []

        def sleep(seconds: float) -> None:
            time.sleep(seconds)
            if not stalled and time.perf_counter() - began > halfway:
                stalled.append(time.perf_counter() - began)
                time.sleep(0.1)

        sent = to_bus(recording, f"unix:{bus}", direction="tx", sleep=sleep)
        done = handctl("replay", str(recorded.path), "--to-bus", f"unix:{bus}", "--direction", "tx")
    assert "went into FAULT (TIMEOUT" in sent["node_fault"], sent
    assert sent["sent"] < len(logged)  # stopped there, not sent to its end
    # the hand left as the nodes it still had enabled were: zero torque, then disabled
    assert "zero torque and a disable sent after them" in sent["stopped"]
    # the command on the same hand, now in FAULT from the first replay: refused before it
    # sends anything (it sent its frames, then said a node "went into FAULT while the replay
    # had it enabled" and left enabled by it, both untrue: an outside audit)
    assert done.returncode == 1, done.stderr
    assert "in FAULT before the replay sent anything: a replay clears no fault" in done.stderr
    assert "went into FAULT" not in done.stderr and "frames sent" not in done.stdout


def test_to_bus_says_when_nobody_was_on_the_unix_bus(
    recorded: Recorded, hand: HandConfig, tmp_path: Path
) -> None:
    """Sends onto a unix bus nobody is on succeed: to a mistyped directory the replay said
    "N frames sent, 0 failed" as if a listener had them. The command refuses a directory
    that is not there."""
    recording = open_recording(recorded.path)
    logged = list(logged_frames(recording))
    now = [0.0]

    def sleep(seconds: float) -> None:  # the recorded spacing, without the wait
        now[0] += seconds

    def send(spec: str) -> dict[str, Any]:
        return to_bus(recording, spec, sleep=sleep, clock=lambda: now[0])

    alone = send(f"unix:{tmp_path / 'nobody'}")
    assert alone["sent"] == len(logged)
    assert "nobody received the frames" in alone["warning"]
    directory = tmp_path / "bus"
    with open_bus(f"unix:{directory}", hand.bus) as listener:
        heard_by = send(f"unix:{directory}")
        heard = listener.drain(limit=10**7)
    assert "warning" not in heard_by
    # a listener that does not read while the replay sends loses what overflows its queue
    # (the unix bus's own rule), and what it has is the log's first frames, in order
    assert heard
    assert [(f.arbitration_id, f.data) for f in heard] == [
        (fid, d) for _, fid, d, _ in logged[: len(heard)]
    ]
    # the command refuses a bus directory nobody made: it made it, sent every frame to
    # nobody and exited 0, with only a warning, the directory left behind
    typo = tmp_path / "typo"
    done = handctl("replay", str(recorded.path), "--to-bus", f"unix:{typo}")
    assert done.returncode == 2, done.stderr
    assert "--to-bus: channel: expected the directory of a unix bus a hand is on" in done.stderr
    assert "no such directory" in done.stderr and not typo.exists()
    # nor a directory nobody is on (left by participants that ended, a killed one's socket
    # in it): it was sent to with a warning, and a run onto it listened out its start-up
    empty = tmp_path / "empty"
    empty.mkdir()
    with open_bus(f"unix:{empty}", hand.bus):
        pass  # a participant come and gone; a dead one's socket file, too
    (empty / "4321-0.sock").touch()
    done = handctl("replay", str(recorded.path), "--to-bus", f"unix:{empty}")
    assert done.returncode == 2, done.stderr
    assert f"{empty}: nobody is on it" in done.stderr and "frames sent" not in done.stdout


@pytest.mark.parametrize("transport", ["virtual", "unix"])
def test_to_bus_onto_a_hand_another_host_commands_is_refused_before_anything(
    recorded: Recorded, hand: HandConfig, channel: str, tmp_path: Path, transport: str
) -> None:
    """A replay onto a hand a run was driving sent its frames beside the run's, the nodes
    taking whichever came last and neither's limits holding for them (from s41's list). It
    now listens first, as a run does, and refuses as a bus in use: nothing sent, exit 4."""
    from handctl.errors import BusError

    spec = f"virtual:{channel}"
    if transport == "unix":
        (tmp_path / "bus").mkdir()
        spec = f"unix:{tmp_path / 'bus'}"
    layout = protocol_for(hand).layout("NodeCommand", 3)
    recording = open_recording(recorded.path)
    with commanding(spec, hand, layout, [0]):  # a host's node command every tick
        for _ in range(3):  # each time, not by luck
            with pytest.raises(BusError, match="another host is commanding this hand") as caught:
                to_bus(recording, spec, sleep=lambda _: None)  # the old code: no waits
            assert "NodeCommand to node 3 (f3)" in str(caught.value)
            assert "heard before this replay sent anything" in str(caught.value)
        if transport == "unix":  # the command, from another process
            done = handctl("replay", str(recorded.path), "--to-bus", spec)
            assert done.returncode == 4, done.stderr
            assert "bus error: another host is commanding this hand" in done.stderr


# -- bad input --------------------------------------------------------------------------------
def test_not_an_mcap_file_is_exit_2(tmp_path: Path) -> None:
    bad = tmp_path / "notes.txt"
    bad.write_text("not a recording\n")
    done = handctl("replay", str(bad))
    assert done.returncode == 2
    assert str(bad) in done.stderr and "expected an MCAP file" in done.stderr
    missing = tmp_path / "missing.mcap"
    done = handctl("replay", str(missing))
    assert done.returncode == 2 and str(missing) in done.stderr and "no such file" in done.stderr


def test_rerun_of_a_log_without_the_channels_is_exit_2(tmp_path: Path) -> None:
    foreign = tmp_path / "foreign.mcap"
    with foreign.open("wb") as out:
        writer = Writer(out)
        writer.start()
        schema = writer.register_schema("Other", "jsonschema", b"{}")
        channel = writer.register_channel("/other", "json", schema)
        writer.add_message(channel, 1, b"{}", 1)
        writer.finish()  # type: ignore[no-untyped-call]  # mcap's Writer is untyped
    done = handctl("replay", str(foreign), "--rerun")
    assert done.returncode == 2, done.stdout + done.stderr
    # no channel of handctl's at all: not a handctl recording (``require_content``)
    assert str(foreign) in done.stderr and "expected a handctl recording" in done.stderr


def test_rerun_refuses_a_log_with_drops(hand: HandConfig, tmp_path: Path) -> None:
    from handctl.recording.ring import RingLayout

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
        hand,
        short_recipe(hand, tmp_path),
        tmp_path / "tiny.mcap",
        troubles=False,
        layout=tiny,
        pause_writer=True,
    )
    done = handctl("replay", str(run.path), "--rerun")
    assert done.returncode == 2
    assert str(run.path) in done.stderr and "dropped" in done.stderr


def test_unwritable_log_is_exit_2_before_the_run(tmp_path: Path) -> None:
    log = tmp_path / "no" / "such" / "dir" / "run.mcap"
    done = handctl("run", "recipe", "config/recipes/swap_two_cylinders.yaml", "--log", str(log))
    assert done.returncode == 2
    # the whole path, however long: it is what the user must find again
    assert f"--log: expected a file in an existing directory, found '{log}'" in done.stderr
    assert "ticks" not in done.stdout  # no run happened


def test_rerun_of_a_run_with_the_object_estimator(tmp_path: Path) -> None:
    """A recipe with objects runs with the estimator: the re-run sets it up the same way and
    feeds it the same angles, so even its tracking state comes out the same."""
    recipe = tmp_path / "with_objects.yaml"
    recipe.write_text(
        SHORT.replace(
            "phases:",
            "objects:\n  - {name: cyl1, radius: 0.020}\n  - {name: cyl2, radius: 0.020}\nphases:",
        )
    )
    log = tmp_path / "objects.mcap"
    done = handctl("run", "recipe", str(recipe), "--log", str(log))
    # a short hold lifts nothing: with objects declared, that is a failed experiment (exit 1)
    assert done.returncode in (1, 3), done.stderr
    recording = open_recording(log)
    assert recording.meta(ch.META_RUN, "estimator") == "True"
    report = rerun(recording)
    assert report.ok and report.compared > 500, report.as_dict()


def test_the_replay_bus_is_a_frame_bus_whose_taps_hear_the_run(
    hand: HandConfig, channel: str
) -> None:
    """ReplayBus stands in for HandBus through the protocol the driver types against
    (``FrameBus``; mypy checks the signatures), without python-can, and a recorder's taps
    hear from it what they would hear from a HandBus."""
    from handctl.recording.rerun import ReplayBus, TickInput

    replay = ReplayBus()
    with open_bus(f"virtual:{channel}", hand.bus) as real:
        assert isinstance(real, FrameBus)
    assert isinstance(replay, FrameBus)
    heard: list[tuple[Any, ...]] = []
    replay.tap = lambda frames, direction: heard.append(("tx", [f for f, _ in frames], direction))
    replay.rx_tap = lambda frames: heard.append(("rx", [f.arbitration_id for f in frames]))
    replay.event_tap = lambda event: heard.append(("event", event.kind))
    replay.load(
        0,
        TickInput(
            0,
            0,
            0,
            0,
            rx=[Frame(0x181, bytes(8))],
            tx=[(0x201, b"\x01", True), (0x202, b"\x02", False)],
            bus_events=[BusEvent(BusEventKind.TX_QUEUE_FULL, "full", 0)],
        ),
    )
    assert [f.arbitration_id for f in replay.drain()] == [0x181]
    assert replay.send(0x201, b"\x01") is True
    assert replay.send(0x202, b"\x02") is False  # as the bus answered in the run
    assert [e.kind for e in replay.events()] == [BusEventKind.TX_QUEUE_FULL]
    assert heard == [
        ("rx", [0x181]),
        ("tx", [0x201], TAP_TX),
        ("tx", [0x202], TAP_TX_FAILED),
        ("event", BusEventKind.TX_QUEUE_FULL),
    ]
    assert replay.flush() is True
    assert (replay.sent, replay.tx_failed, replay.frame_mismatches) == (1, 1, [])


def test_ctrl_c_stops_a_rerun_at_once(recorded: Recorded, monkeypatch: pytest.MonkeyPatch) -> None:
    """With Python's own SIGINT handler in place, asyncio's took over for the re-run and only
    cancelled its task, which the lockstep ticks took at the end: a Ctrl-C waited out the
    whole re-run (minutes on a long log; SIGTERM ended it at once)."""
    import handctl.recording.rerun as rerun_module
    from handctl.online.loop import Runtime

    after: list[int] = []

    class Interrupted(Runtime):
        def __init__(self, *args: Any, **kwargs: Any) -> None:
            super().__init__(*args, **kwargs)
            self.tick_hooks.append(self._count)

        def _count(self, tk: Tick) -> None:
            if after:
                after.append(tk.tick)
            elif tk.tick == 100:
                after.append(tk.tick)
                os.kill(os.getpid(), signal.SIGINT)

    monkeypatch.setattr(rerun_module, "Runtime", Interrupted)
    working()  # as every command begins (``cli.main``): an earlier one here had finished
    before = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        with pytest.raises(KeyboardInterrupt), ctrl_c_at_once():  # as replay --rerun runs it
            rerun(open_recording(recorded.path))
        assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
    finally:
        signal.signal(signal.SIGINT, before)
    assert after == [100]  # not one tick more


@pytest.mark.parametrize("name", ["", "-"])
def test_an_export_to_no_file_name_is_refused(
    recorded: Recorded, tmp_path: Path, name: str
) -> None:
    """``--export candump -`` wrote a file named '-' in the current directory, where every
    other output option refuses it as standard output."""
    done = handctl("replay", str(recorded.path), "--export", "candump", name, cwd=tmp_path)
    assert done.returncode == 2, done.stderr
    assert "--export: FILE: expected a file name" in done.stderr
    assert list(tmp_path.iterdir()) == []


def test_the_replay_s_copy_of_the_log_has_no_name_to_leave_behind(
    recorded: Recorded, hand: HandConfig, channel: str
) -> None:
    """The log is copied before it is checked and sent; the copy was a named file in a
    private directory, which a replay killed (SIGKILL) left behind, some 50 MB a minute of
    run (found by an outside audit). It has no name now: the system frees it however the
    replay ends."""
    import tempfile

    seen: list[list[str]] = []

    def sleep(_seconds: float) -> None:  # while it sends, the recorded spacing unslept
        if not seen:
            seen.append([n for n in os.listdir(tempfile.gettempdir()) if "handctl-to-bus" in n])

    with open_bus(f"virtual:{channel}", hand.bus):
        sent = to_bus(open_recording(recorded.path), f"virtual:{channel}", sleep=sleep)
    assert sent["sent"] > 0 and seen == [[]]
