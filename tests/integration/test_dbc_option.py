"""``--dbc``: every command that puts frames on a bus speaks the given DBC, refuses one that
does not carry the hand before anything is sent, and a recording keeps the DBC it spoke so
that its re-run speaks it too."""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest
import yaml

from handctl.config import load_hand
from handctl.foxglove import derived as fx
from handctl.hand_protocol import protocol_for
from handctl.protocol import DEFAULT_DBC
from handctl.recording import channels as ch
from handctl.recording.reader import iter_messages, open_recording

from ..conftest import ROOT, handctl
from ..shapes import shaped_hand

RECIPE = ROOT / "config" / "recipes" / "swap_two_cylinders.yaml"
HAND = ROOT / "config" / "hands" / "hiroshima_hand.yaml"


@pytest.mark.parametrize(
    "command",
    [
        ["check", "{hand}"],
        ["run", "recipe", str(RECIPE), "--hand", "{hand}"],
        ["sim", "--bus", "virtual:dbc-option", "--hand", "{hand}", "--seconds", "0.1"],
        ["nodes", "--hand", "{hand}"],
        ["jog", "finger0_joint0", "--torque", "0.01", "--hand", "{hand}"],
        ["calibrate", "tdt", "--hand", "{hand}", "-o", "{out}"],
        ["monitor", "--hand", "{hand}", "--seconds", "0.1"],
    ],
)
def test_a_dbc_without_the_hands_nodes_is_refused_before_anything_is_sent(
    tmp_path: Path, command: list[str]
) -> None:
    hand = shaped_hand(tmp_path, [3, 3, 3, 3])
    out = tmp_path / "calibrated.yaml"
    args = [part.format(hand=hand, out=out) for part in command]
    done = handctl(*args, "--dbc", str(DEFAULT_DBC))
    assert done.returncode == 2, done.stdout + done.stderr
    assert (
        f"{hand}: fingers[3].node_id: expected a node with a NodeCommand_4 message in {DEFAULT_DBC}"
    ) in done.stderr
    assert "Traceback" not in done.stderr
    assert not out.exists()


def test_a_missing_dbc_is_named_against_the_option(tmp_path: Path) -> None:
    done = handctl("check", str(HAND), "--dbc", str(tmp_path / "none.dbc"))
    assert done.returncode == 2
    assert "--dbc: expected an existing DBC file" in done.stderr


def other_data_ids(tmp_path: Path) -> Path:
    """The packaged DBC with other DataIDs for the torque commands: frames of the same layout
    whose CRC only a host and nodes of this very DBC agree on."""
    text = DEFAULT_DBC.read_text(encoding="cp1252")
    for node in (1, 2, 3):
        line = f'BA_ "DataID" BO_ {0x100 + node} {0x1020 + node};'
        assert line in text
        text = text.replace(line, f'BA_ "DataID" BO_ {0x100 + node} {0x1120 + node};')
    path = tmp_path / "other.dbc"
    path.write_text(text, encoding="cp1252")
    return path


def test_a_run_on_a_given_dbc_records_it_and_reruns_on_it(tmp_path: Path) -> None:
    dbc = other_data_ids(tmp_path)
    log = tmp_path / "run.mcap"
    run = handctl(
        "run",
        "recipe",
        str(RECIPE),
        "--hand",
        str(HAND),
        "--dbc",
        str(dbc),
        "--max-seconds",
        "0.3",
        "--log",
        str(log),
    )
    assert run.returncode == 0, run.stderr  # the simulated nodes spoke the same DBC
    recorded = open_recording(log).meta(ch.META_HAND, "dbc")
    assert recorded == dbc.read_text(encoding="cp1252")
    assert recorded != protocol_for(load_hand(HAND)).text  # not the generated one
    rerun = handctl("replay", str(log), "--rerun")
    assert rerun.returncode == 0, rerun.stdout + rerun.stderr
    assert "command frames identical" in rerun.stdout


def moved_feedback_id(tmp_path: Path) -> tuple[Path, Path, Path]:
    """A hand whose finger 1 feedback is at 0x1A1, the DBC its firmware speaks (the packaged
    one with Feedback_1 moved there) and a short recipe for it: a hand that loads only with
    its --dbc."""
    hand = tmp_path / "moved.yaml"
    hand.write_text(HAND.read_text().replace("feedback: 0x181", "feedback: 0x1A1"))
    dbc = tmp_path / "moved.dbc"
    text = DEFAULT_DBC.read_text(encoding="cp1252")
    assert len(re.findall(r"\b385\b", text)) > 3 and not re.findall(r"\b417\b", text)
    dbc.write_text(re.sub(r"\b385\b", "417", text), encoding="cp1252")
    recipe = tmp_path / "hold.yaml"
    torques = {
        j: 0.02 if j.startswith(("f1", "f2")) else -0.02 for j in load_hand(HAND).joint_names
    }
    recipe.write_text(
        yaml.safe_dump(
            {
                "recipe": "moved_ids",
                "phases": [
                    {
                        "name": "hold",
                        "torques": torques,
                        "ramp_s": 0.1,
                        "max_s": 0.3,
                        "on_timeout": "next",
                    }
                ],
            }
        )
    )
    return hand, dbc, recipe


def test_every_command_of_a_hand_that_needs_its_dbc_takes_it(tmp_path: Path) -> None:
    """With a DBC that numbers a frame otherwise, a run's log had no Foxglove channels (the
    writer read the hand without the DBC, and said so nowhere), a calibration measured and then
    refused to write, and the log could not be replayed onto that hand's bus at all."""
    hand, dbc, recipe = moved_feedback_id(tmp_path)
    log = tmp_path / "run.mcap"
    run = handctl(
        "run", "recipe", str(recipe), "--hand", str(hand), "--dbc", str(dbc), "--log", str(log)
    )
    assert run.returncode == 0, run.stderr
    assert "no Foxglove channels" not in run.stderr
    recording = open_recording(log)
    decoded = [json.loads(raw) for _, _, raw in iter_messages(recording, (fx.RX_DECODED,))]
    assert {d["message"] for d in decoded} >= {"Feedback_1", "Feedback_2", "Status_1"}
    assert {d["id"] for d in decoded if d["message"] == "Feedback_1"} == {0x1A1}
    assert any(True for _ in iter_messages(recording, (fx.SCENE,)))

    sent = handctl(
        "replay", str(log), "--to-bus", "virtual:moved", "--hand", str(hand), "--dbc", str(dbc)
    )
    assert sent.returncode == 0, sent.stderr
    assert "frames sent to virtual:moved (0 failed" in sent.stdout
    without = handctl("replay", str(log), "--to-bus", "virtual:moved", "--hand", str(hand))
    assert without.returncode == 2
    assert f"{hand}: fingers[0].can_ids.feedback: expected 0x181" in without.stderr
    alone = handctl("replay", str(log), "--dbc", str(dbc))
    assert alone.returncode == 2
    assert "--dbc: expected --to-bus SPEC --hand HAND.yaml as well" in alone.stderr

    out = tmp_path / "calibrated.yaml"
    cal = handctl(
        "calibrate", "tdt", "--hand", str(hand), "--dbc", str(dbc), "-o", str(out),
        "--settle", "0.3", "--seconds", "0.3",
    )  # fmt: skip
    assert cal.returncode == 0, cal.stdout + cal.stderr
    assert load_hand(out, dbc).fingers[0].can_ids.feedback == 0x1A1


def test_monitor_reads_a_log_for_its_hand_in_the_dbc_the_log_keeps(tmp_path: Path) -> None:
    """monitor --log with --hand of a hand that only its DBC carries was refused against the
    DBC generated from it, though the log keeps that DBC (and --dbc of the same file was
    taken; found by an outside audit): the hand is read in the recorded DBC."""
    hand, dbc, recipe = moved_feedback_id(tmp_path)
    log = tmp_path / "run.mcap"
    run = handctl(
        "run", "recipe", str(recipe), "--hand", str(hand), "--dbc", str(dbc), "--log", str(log)
    )
    assert run.returncode == 0, run.stderr
    shown = handctl("monitor", "--log", str(log), "--hand", str(hand))
    assert shown.returncode == 0, shown.stderr
    last = json.loads(shown.stdout.splitlines()[-1])
    feedback = {m["message"]: m for m in last["messages"]}["Feedback_1"]
    assert feedback["id"] == "0x1A1" and feedback["frames"] > 100 and feedback["rejects"] == {}
    assert handctl("monitor", "--log", str(log), "--dbc", str(dbc)).stdout == shown.stdout

    # another hand in the same DBC is still not the recorded one
    other = tmp_path / "other.yaml"
    other.write_text(yaml.safe_dump({**yaml.safe_load(hand.read_text()), "name": "other"}))
    refused = handctl("monitor", "--log", str(log), "--hand", str(other))
    assert refused.returncode == 2
    assert f"--hand: expected the hand {log} was recorded with" in refused.stderr
    # and a hand the recorded DBC does not carry either is refused as before
    moved = tmp_path / "moved_again.yaml"
    moved.write_text(hand.read_text().replace("feedback: 0x1A1", "feedback: 0x1B1"))
    refused = handctl("monitor", "--log", str(log), "--hand", str(moved))
    assert refused.returncode == 2
    assert f"{moved}: fingers[0].can_ids.feedback: expected 0x181" in refused.stderr


def test_plan_takes_the_dbc_of_its_hand(tmp_path: Path) -> None:
    """plan had no --dbc: a hand whose can_ids only its DBC carries could not be planned for.
    (A template it then refuses shows the hand was read; the plan itself is the search's.)"""
    hand, dbc, _ = moved_feedback_id(tmp_path)
    template = tmp_path / "t.yaml"
    text = (ROOT / "config" / "recipes" / "swap_two_cylinders.template.yaml").read_text()
    assert "{name: cyl2," in text
    template.write_text(text.replace("{name: cyl2,", "{name: drum,", 1))
    args = ["plan", str(template), "--hand", str(hand), "-o", str(tmp_path / "r.yaml")]
    without = handctl(*args)
    assert without.returncode == 2
    assert f"{hand}: fingers[0].can_ids.feedback: expected 0x181" in without.stderr
    done = handctl(*args, "--dbc", str(dbc))
    assert done.returncode == 2
    assert done.stderr.startswith(f"handctl: error: {template}: objects[1].name"), done.stderr


def test_a_replay_stopped_midway_stops_the_nodes_in_the_dbc_it_recorded(tmp_path: Path) -> None:
    """A replay onto a bus stopped midway zeroes and disables the nodes it left enabled. That
    stop was built from the hand config alone, in the DBC generated from it, not in the one
    the log recorded: a node whose DataIDs were the recorded DBC's refused the zero torque
    and the disable by their CRC and held its last torque until its watchdog (found by an
    outside audit). And a log whose DBC numbers a frame otherwise was refused outright onto a
    simulated bus, against "the DBC generated" for its hand."""
    from handctl.online.bus import open_bus
    from handctl.protocol import load_protocol
    from handctl.recording.frames import logged_frames, to_bus

    dbc = other_data_ids(tmp_path)
    log = tmp_path / "run.mcap"
    run = handctl(
        "run", "recipe", str(RECIPE), "--hand", str(HAND), "--dbc", str(dbc),
        "--max-seconds", "0.3", "--log", str(log),
    )  # fmt: skip
    assert run.returncode == 0, run.stderr
    recording = open_recording(log)
    logged = list(logged_frames(recording))
    halfway = (logged[-1][0] - logged[0][0]) * 1e-9 / 2  # s: the nodes enabled, under torque
    now = [0.0]

    def sleep(seconds: float) -> None:
        before = now[0]
        now[0] += seconds
        if before < halfway <= now[0]:
            raise KeyboardInterrupt

    hand = load_hand(HAND, dbc)
    with open_bus("virtual:recorded-dbc-stop", hand.bus) as listener:
        with pytest.raises(KeyboardInterrupt):
            to_bus(recording, "virtual:recorded-dbc-stop", sleep=sleep, clock=lambda: now[0])
        heard = [(f.arbitration_id, f.data) for f in listener.drain(limit=10**7)]
    protocol = load_protocol(dbc)
    for finger in hand.fingers:
        command = protocol.layout("NodeCommand", finger.node_id)
        torque = protocol.layout("TorqueCommand", finger.node_id)
        mine = [d for fid, d in heard if fid == torque.frame_id]
        assert all(torque.crc_ok(d) for d in mine[-6:])  # the zero torques, in its CRC
        assert [v for _, v in map(torque.decode, mine[-6:])] == [(0.0,) * 3] * 6
        last = [d for fid, d in heard if fid == command.frame_id][-1]
        assert command.crc_ok(last) and command.decode(last)[1] == (2.0,)  # disable

    hand_path, moved, recipe = moved_feedback_id(tmp_path)
    moved_log = tmp_path / "moved.mcap"
    done = handctl(
        "run", "recipe", str(recipe), "--hand", str(hand_path), "--dbc", str(moved),
        "--log", str(moved_log),
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    sent = handctl("replay", str(moved_log), "--to-bus", "virtual:moved-own")
    assert sent.returncode == 0, sent.stderr
    assert "frames sent to virtual:moved-own (0 failed" in sent.stdout
