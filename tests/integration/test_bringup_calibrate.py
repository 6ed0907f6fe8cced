"""``handctl calibrate tdt`` end to end against the simulated hand: in lockstep on the virtual
bus, and free-running in its own process on the unix bus. The bias of a TDT sensor comes out as
its offset within its noise; a joint that moves, a node missing or in FAULT is refused and
nothing is written."""

from __future__ import annotations

import json
import math
import shutil
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from handctl import cli
from handctl.bringup.hand_edit import with_tdt_offsets
from handctl.config import HandConfig, load_hand, parse_hand
from handctl.errors import ConfigError
from handctl.online.bus import open_bus
from handctl.outfile import write_atomically
from handctl.schema import parse_yaml
from handctl.sim.params import parse_sim
from handctl.sim.sensors import TdtModel

from ..conftest import HAND_YAML, ROOT
from .realtime import ATTEMPTS_UNDER_LOAD, REALTIME, give_up, stopped_by_load, tolerant_hand

#: A bias on top of the drawn ones: node 2 joint 3 (f2_j3), N·m, well above the noise.
ADDED = 0.1
ADDED_JOINT = "f2_j3"


def _scenario(tmp_path: Path, *entries: str) -> Path:
    path = tmp_path / "faults.yaml"
    path.write_text("faults:\n" + "".join(f"  - {e}\n" for e in entries))
    return path


def _true_bias(hand: HandConfig, seed: int = 0) -> dict[str, float]:
    """The simulated sensors' biases for ``seed``: drawn as the simulated hand draws them."""
    model = TdtModel(hand, parse_sim(hand).tdt, np.random.default_rng(seed))
    return {j.name: b for j, b in zip(hand.joints, model.bias, strict=True)}


def _check_offsets(hand: HandConfig, written: Path, report: dict[str, Any]) -> None:
    bias = _true_bias(hand)
    bias[ADDED_JOINT] += ADDED
    calibrated = load_hand(written)
    n = report["samples"]
    for joint, measured in zip(calibrated.joints, report["joints"], strict=True):
        within = 4 * measured["noise_nm"] / math.sqrt(n) + 1e-4  # 4 sigma of a mean, rounding
        assert abs(joint.tdt.offset + bias[joint.name]) <= within, (joint.name, within)


def test_a_tdt_bias_comes_out_within_its_noise(
    hand: HandConfig, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    faults = _scenario(
        tmp_path, f"{{kind: tdt_offset, node: 2, joint: 3, offset: {ADDED}, start: 0.0}}"
    )
    out = tmp_path / "calibrated.yaml"
    code = cli.main(
        [
            "calibrate",
            "tdt",
            "-o",
            str(out),
            "--sim-faults",
            str(faults),
            "--json",
            str(tmp_path / "m.json"),
        ]
    )
    printed = capsys.readouterr().out
    assert code == cli.EXIT_OK, printed
    report = json.loads((tmp_path / "m.json").read_text())
    _check_offsets(hand, out, report)
    text = out.read_text()
    assert "# The Hiroshima-Hand as handctl drives it" in text  # comments kept
    assert "&flexor" in text and "sim:" in text  # and the layout
    assert HAND_YAML.read_text() != text  # a copy; the original is untouched
    assert "f2_j3          +0.0000" in printed  # before and after, per joint


def test_write_overwrites_the_hand_config_itself(
    hand: HandConfig, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    copy = tmp_path / "hand.yaml"
    shutil.copy(HAND_YAML, copy)
    before = copy.read_text()
    assert (
        cli.main(["calibrate", "tdt", "--hand", str(copy), "-o", str(copy), "--seconds", "0.2"])
        == cli.EXIT_BAD_INPUT
    )
    assert copy.read_text() == before and "--write" in capsys.readouterr().err
    assert (
        cli.main(["calibrate", "tdt", "--hand", str(copy), "--write", "--seconds", "0.2"])
        == cli.EXIT_OK
    )
    assert copy.read_text() != before
    assert load_hand(copy).joints[0].tdt.offset != 0.0


def test_o_replaces_only_a_calibrated_copy_of_the_same_hand(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """-o over another hand's config or a recipe replaced it with this hand's, exit 0 (only
    --write is said to overwrite). Refused before any bus opens; a copy of this hand that
    exists is a calibration done again."""
    other = tmp_path / "planar.yaml"
    shutil.copy(ROOT / "config" / "hands" / "planar_2f2j.yaml", other)
    recipe = tmp_path / "recipe.yaml"
    recipe.write_text("recipe: mine\nphases: []\n")
    for victim, what in ((other, "the hand config of 'planar_2f2j'"), (recipe, "not a hand")):
        before = victim.read_text()
        args = ["calibrate", "tdt", "-o", str(victim), "--seconds", "0.2"]
        assert cli.main(args) == cli.EXIT_BAD_INPUT
        err = capsys.readouterr().err
        assert "-o: expected a new file, or a calibrated copy of 'hiroshima_hand'" in err
        assert what in err
        assert victim.read_text() == before
    # a working copy of the same name with a lowered limit: its tau_max went back up to the
    # hand's 0.60 N·m, exit 0 (found by an outside audit)
    working = tmp_path / "working.yaml"
    lowered = cli.DEFAULT_HAND.read_text().replace("tau_max: 0.60,", "tau_max: 0.20,", 1)
    assert lowered != cli.DEFAULT_HAND.read_text()
    working.write_text(lowered)
    args = ["calibrate", "tdt", "-o", str(working), "--seconds", "0.2"]
    assert cli.main(args) == cli.EXIT_BAD_INPUT
    err = capsys.readouterr().err
    assert "differs from it in TDT offsets alone" in err
    assert "fingers[0].joints[0].tau_max is 0.2, not 0.6" in err, err
    assert working.read_text() == lowered
    copy = tmp_path / "copy.yaml"
    args = ["calibrate", "tdt", "-o", str(copy), "--seconds", "0.2", "--settle", "0.2"]
    assert cli.main(args) == cli.EXIT_OK
    assert cli.main(args) == cli.EXIT_OK  # again, over its own copy
    assert load_hand(copy).name == "hiroshima_hand"


def test_write_refuses_the_hand_config_shipped_with_handctl(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    """Without --hand the hand config is the package's own copy (site-packages, once
    installed): not a hand's to overwrite. Refused before any bus opens. (The default is a
    copy here, so that a regression overwrites nothing of the checkout's.)"""
    shipped = tmp_path / "hiroshima_hand.yaml"
    shutil.copy(cli.DEFAULT_HAND, shipped)
    monkeypatch.setattr(cli, "DEFAULT_HAND", shipped)
    before = shipped.read_text()
    assert cli.main(["calibrate", "tdt", "--write", "--seconds", "0.2"]) == cli.EXIT_BAD_INPUT
    err = capsys.readouterr().err
    assert "--write: expected --hand with the hand config of your hand" in err
    assert shipped.read_text() == before
    # nor is --write offered for it when neither -o nor --write is given
    assert cli.main(["calibrate", "tdt", "--seconds", "0.2"]) == cli.EXIT_BAD_INPUT
    err = capsys.readouterr().err
    assert "the default hand config is the package's: give your hand's with --hand" in err
    assert "or --write to overwrite" not in err
    assert shipped.read_text() == before


def test_write_keeps_what_was_saved_into_the_hand_config_during_the_run(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    """The offsets are written into the text read before the run: written over a file edited
    since, they would undo the edit. The real calibration runs; the edit comes at its end."""
    from handctl.bringup import calibrate

    copy = tmp_path / "hand.yaml"
    shutil.copy(HAND_YAML, copy)
    measure = calibrate.calibrate_tdt

    def edited_meanwhile(*args: Any, **kwargs: Any) -> calibrate.Calibration:
        result = measure(*args, **kwargs)
        copy.write_text(copy.read_text() + "# saved during the calibration\n")
        return result

    monkeypatch.setattr(calibrate, "calibrate_tdt", edited_meanwhile)
    args = ["calibrate", "tdt", "--hand", str(copy), "--write", "--seconds", "0.2"]
    assert cli.main(args) == cli.EXIT_FAILED
    assert "changed while the calibration ran; nothing written" in capsys.readouterr().err
    assert copy.read_text().endswith("# saved during the calibration\n")
    assert load_hand(copy).joints[0].tdt.offset == 0.0


def test_a_hand_config_with_crlf_line_ends_keeps_them(tmp_path: Path) -> None:
    """Written from the text as read (its line ends made \\n), every line of the copy
    differed from the original's."""
    copy = tmp_path / "hand.yaml"
    copy.write_bytes(HAND_YAML.read_bytes().replace(b"\n", b"\r\n"))
    out = tmp_path / "calibrated.yaml"
    args = ["calibrate", "tdt", "--hand", str(copy), "-o", str(out), "--seconds", "0.2"]
    assert cli.main(args) == cli.EXIT_OK
    written = out.read_bytes()
    assert written.count(b"\n") == written.count(b"\r\n") > 100
    assert load_hand(out).joints[0].tdt.offset != 0.0


def test_a_hand_config_with_mixed_line_ends_keeps_each_line_s(tmp_path: Path) -> None:
    """CRLF on the first five lines only: every line of the copy was given CRLF, not byte for
    byte the original but for the offsets (found by an outside audit)."""
    lines = HAND_YAML.read_bytes().split(b"\n")
    copy = tmp_path / "hand.yaml"
    copy.write_bytes(b"\r\n".join(lines[:6]) + b"\n" + b"\n".join(lines[6:]))
    out = tmp_path / "calibrated.yaml"
    args = ["calibrate", "tdt", "--hand", str(copy), "-o", str(out), "--seconds", "0.2"]
    assert cli.main(args) == cli.EXIT_OK
    written = out.read_bytes()
    assert written.count(b"\r\n") == 5
    assert written.split(b"\n")[:5] == copy.read_bytes().split(b"\n")[:5]
    assert load_hand(out).joints[0].tdt.offset != 0.0


def _read_only_hand(tmp_path: Path) -> list[str]:
    copy = tmp_path / "hand.yaml"
    shutil.copy(HAND_YAML, copy)
    copy.chmod(0o444)
    return ["--hand", str(copy), "--write"]


def _into_read_only_dir(tmp_path: Path) -> list[str]:
    locked = tmp_path / "locked"
    locked.mkdir()
    locked.chmod(0o555)
    return ["-o", str(locked / "calibrated.yaml")]


@pytest.mark.parametrize(
    "make_args, says",
    [
        (_read_only_hand, "--write: expected a file that may be written (it is read-only)"),
        (_into_read_only_dir, "-o: expected a file in a directory that may be written"),
        (lambda t: ["-o", str(t / "gone" / "c.yaml")], "-o: expected a file in an existing"),
        (
            lambda t: ["-o", str(t)],
            "-o: expected a regular file (not a directory, a device or a FIFO)",
        ),
        (
            lambda t: ["-o", str(t / "c.yaml"), "--json", str(t / "gone" / "m.json")],
            "--json: expected a file in an existing directory",
        ),
        (
            lambda t: ["-o", str(t / "c.yaml"), "--json", str(t / "c.yaml")],
            "--json: expected another file than the hand config and its calibrated copy",
        ),
    ],
)
def test_a_result_that_cannot_be_written_is_refused_before_anything_starts(
    hand: HandConfig,
    channel: str,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    make_args: Any,
    says: str,
) -> None:
    # A read-only hand config was overwritten by --write (os.replace needs only the
    # directory), and a file that could not be written failed with a traceback after the
    # whole calibration had run.
    args = make_args(tmp_path)
    before = {p: p.read_bytes() for p in tmp_path.rglob("*") if p.is_file()}
    sniffer = open_bus(f"virtual:{channel}", hand.bus)
    try:
        code = cli.main(["calibrate", "tdt", *args, "--bus", f"virtual:{channel}"])
        heard = sniffer.drain(limit=1000)
    finally:
        sniffer.close()
        for p in tmp_path.rglob("*"):  # let pytest clean up
            p.chmod(0o755 if p.is_dir() else 0o644)
    assert code == cli.EXIT_BAD_INPUT
    assert says in capsys.readouterr().err
    assert heard == []
    assert {p: p.read_bytes() for p in tmp_path.rglob("*") if p.is_file()} == before


def test_write_replaces_the_file_whole_keeping_its_mode(tmp_path: Path) -> None:
    copy = tmp_path / "hand.yaml"
    shutil.copy(HAND_YAML, copy)
    copy.chmod(0o640)
    code = cli.main(["calibrate", "tdt", "--hand", str(copy), "--write", "--seconds", "0.2"])
    assert code == cli.EXIT_OK
    assert [p.name for p in tmp_path.iterdir()] == ["hand.yaml"]  # no temporary file left
    assert copy.stat().st_mode & 0o777 == 0o640
    assert load_hand(copy).joints[0].tdt.offset != 0.0


@pytest.mark.parametrize("moment", ["summarise_run", "with_tdt_offsets"])
def test_a_stop_signal_once_the_hand_has_stopped_writes_nothing(
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
    moment: str,
) -> None:
    """A SIGTERM after the hand had stopped, before the command's end (its run's summary
    being made; in real time, the simulated hand's process ending) was dropped inside the
    run: --write overwrote the hand config, exit 0, the stop unsaid (found by an outside
    audit). A calibration's result is the file it writes: a stop before it writes nothing,
    or, once --json is written (the edit of the hand config being made), not the hand
    config."""
    import signal

    from handctl import session
    from handctl.bringup import hand_edit

    owner: Any = session if moment == "summarise_run" else hand_edit
    original = getattr(owner, moment)

    def signalled(*args: Any, **kwargs: Any) -> Any:
        signal.raise_signal(signal.SIGTERM)
        return original(*args, **kwargs)

    monkeypatch.setattr(owner, moment, signalled)
    copy = tmp_path / "hand.yaml"
    shutil.copy(HAND_YAML, copy)
    before = copy.read_bytes()
    report = tmp_path / "m.json"
    args = ["calibrate", "tdt", "--hand", str(copy), "--write", "--seconds", "0.2"]
    assert cli.main([*args, "--json", str(report)]) == cli.EXIT_INTERRUPTED
    captured = capsys.readouterr()
    said = "nothing written" if moment == "summarise_run" else f"{copy} not written"
    assert (
        "handctl: SIGTERM came after the hand had stopped, before the calibration was "
        f"written: {said}" in captured.err
    ), captured.err
    assert "offset after" in captured.out  # what was measured is shown
    assert copy.read_bytes() == before
    assert report.exists() is (moment != "summarise_run")
    assert {p.name for p in tmp_path.iterdir()} <= {"hand.yaml", "m.json"}


@pytest.mark.parametrize("name", ["SIGINT", "SIGTERM"])
def test_a_stop_signal_once_the_calibration_is_written_changes_no_exit(
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
    name: str,
) -> None:
    """A stop signal once the calibrated copy was written, as the calibration's stop signals
    were put back, turned its exit 0 into 130 "interrupted" over a file written (found by an
    outside audit). It is said, and the result stands."""
    import signal

    from handctl import stopsignals

    original = stopsignals.StopSignals.__exit__

    def signalled(self: stopsignals.StopSignals, *exc: Any) -> None:
        original(self, *exc)
        signal.raise_signal(signal.Signals[name])

    monkeypatch.setattr(stopsignals.StopSignals, "__exit__", signalled)
    copy = tmp_path / "copy.yaml"
    args = ["calibrate", "tdt", "-o", str(copy), "--seconds", "0.2"]
    assert cli.main(args) == cli.EXIT_OK, capsys.readouterr().err
    assert f"written: {copy}" in capsys.readouterr().out
    assert load_hand(copy).name
    assert [name] == stopsignals.LATE


def test_a_write_that_fails_leaves_the_old_file_and_nothing_else(tmp_path: Path) -> None:
    target = tmp_path / "hand.yaml"
    target.write_text("old\n")
    with pytest.raises(UnicodeEncodeError):  # fails in the middle of writing the new text
        write_atomically(target, "new " * 10_000 + "\udc80")
    assert target.read_text() == "old\n"
    assert [p.name for p in tmp_path.iterdir()] == ["hand.yaml"]


def test_a_joint_that_moves_is_refused_by_name(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # 400 counts of a 14-bit encoder: 0.15 rad, during the measurement (settle is 2 s)
    faults = _scenario(tmp_path, "{kind: encoder_jump, node: 2, joint: 2, counts: 400, start: 2.5}")
    out = tmp_path / "calibrated.yaml"
    code = cli.main(["calibrate", "tdt", "-o", str(out), "--sim-faults", str(faults)])
    err = capsys.readouterr().err
    assert code == cli.EXIT_FAILED
    assert "calibration refused, nothing written: f2_j2: moved 0.15" in err
    assert "f1_" not in err and "f3_" not in err and "f2_j1" not in err
    assert not out.exists()


def test_a_refused_calibration_says_its_json_was_written(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Refused with --json: "nothing written", and the JSON was (found by an outside audit).
    Its measurements are kept, and said to be."""
    faults = _scenario(tmp_path, "{kind: encoder_jump, node: 2, joint: 2, counts: 400, start: 0.5}")
    out, report = tmp_path / "calibrated.yaml", tmp_path / "m.json"
    args = ["calibrate", "tdt", "-o", str(out), "--settle", "0.2", "--seconds", "0.5"]
    code = cli.main([*args, "--sim-faults", str(faults), "--json", str(report)])
    err = capsys.readouterr().err
    assert code == cli.EXIT_FAILED
    assert (
        f"calibration refused, {out} not written (the measurements are in {report}): "
        "f2_j2: moved 0.15" in err
    ), err
    assert not out.exists()
    joints = json.loads(report.read_text())["joints"]
    assert [j["joint"] for j in joints if j["problem"]] == ["f2_j2"]


def test_an_offset_beyond_the_joints_tau_max_is_refused_whatever_max_offset_says(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # --max-offset 0.5 let a sensor reading 0.4 N·m at zero torque on a joint of tau_max
    # 0.3 N·m be calibrated away, and --max-offset 5 one reading 1 N·m
    faults = _scenario(tmp_path, "{kind: tdt_offset, node: 2, joint: 3, offset: 0.4, start: 0.0}")
    out = tmp_path / "calibrated.yaml"
    args = ["calibrate", "tdt", "-o", str(out), "--sim-faults", str(faults), "--seconds", "0.3"]
    assert cli.main([*args, "--max-offset", "0.5"]) == cli.EXIT_FAILED
    err = capsys.readouterr().err
    assert "nothing written: f2_j3: offset -0.40" in err
    assert "(at most 0.3 N·m, the joint's tau_max)" in err
    assert not out.exists()
    assert cli.main([*args, "--max-offset", "5"]) == cli.EXIT_BAD_INPUT
    assert "--max-offset: expected at most 0.6 N·m (the largest tau_max" in (
        capsys.readouterr().err
    )
    assert not out.exists()


def test_an_offset_just_past_max_offset_is_the_joint_s_refusal_not_a_safety_stop(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """With max_offset (0.25 N·m) as the run's TDT tolerance, a sensor reading 0.26 N·m at
    zero torque stopped the calibration on TDT_MISMATCH (exit 3, no table): the refusal by
    joint the docs promise was out of reach for the offsets it is for."""
    faults = _scenario(tmp_path, "{kind: tdt_offset, node: 1, joint: 1, offset: 0.26, start: 0.0}")
    out = tmp_path / "calibrated.yaml"
    args = ["calibrate", "tdt", "-o", str(out), "--sim-faults", str(faults), "--seconds", "0.3"]
    assert cli.main(args) == cli.EXIT_FAILED
    err = capsys.readouterr().err
    assert "nothing written: f1_j1: offset -0.26" in err and "(at most 0.25 N·m)" in err
    assert "TDT_MISMATCH" not in err
    assert not out.exists()


def test_the_offset_written_is_judged_not_the_reading_with_the_configured_one(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A hand config that already carries an offset of -0.2 N·m on f2_j3, and a sensor that
    reads 0.2 N·m more at zero torque: each reading is within --max-offset (0.25), and judging
    it alone wrote -0.4, then -0.6 on the next run; the offset written is what is bounded."""
    copy = tmp_path / "hand.yaml"
    copy.write_text(
        HAND_YAML.read_text().replace(
            "name: f2_j3,", "name: f2_j3, tdt: {scale: 1.0, offset: -0.2},", 1
        )
    )
    assert load_hand(copy).joints[5].tdt.offset == -0.2
    faults = _scenario(tmp_path, "{kind: tdt_offset, node: 2, joint: 3, offset: 0.2, start: 0.0}")
    out = tmp_path / "calibrated.yaml"
    args = ["calibrate", "tdt", "--hand", str(copy), "-o", str(out), "--seconds", "0.3"]
    assert cli.main([*args, "--sim-faults", str(faults)]) == cli.EXIT_FAILED
    err = capsys.readouterr().err
    assert "nothing written: f2_j3: offset -0.4" in err
    assert "(the sensor reads +0.2" in err and "with the configured -0.2000)" in err
    assert not out.exists()
    # the same configured offset and a sensor that reads it back to zero is written
    assert cli.main(args) == cli.EXIT_OK
    assert abs(load_hand(out).joints[5].tdt.offset + 0.2) < 0.01


def test_fingers_that_have_not_settled_are_refused(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "calibrated.yaml"
    code = cli.main(["calibrate", "tdt", "-o", str(out), "--settle", "0"])
    assert code == cli.EXIT_FAILED
    assert "f1_j3: moved" in capsys.readouterr().err
    assert not out.exists()


@pytest.mark.parametrize(
    "entry, says",
    [
        ("{kind: node_silent, node: 2, start: 0.0}", "node 2 (f2): no feedback"),
        (
            "{kind: tdt_spike, node: 3, joint: 1, amplitude: 5.0, start: 0.0}",
            "node 3 (f3) in FAULT (SENSOR)",
        ),
    ],
)
def test_a_node_missing_or_in_fault_stops_it_before_torque(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], entry: str, says: str
) -> None:
    out = tmp_path / "calibrated.yaml"
    code = cli.main(
        ["calibrate", "tdt", "-o", str(out), "--sim-faults", str(_scenario(tmp_path, entry))]
    )
    assert code == cli.EXIT_SAFETY_STOP
    assert says in capsys.readouterr().err
    assert not out.exists()


def test_a_layout_it_cannot_edit_is_dumped_and_still_right(hand: HandConfig) -> None:
    offsets = {j.name: 0.001 * k for k, j in enumerate(hand.joints)}
    text = HAND_YAML.read_text().replace(
        "      - {<<: *flexor, name: f2_j1}", "      - {<<: *flexor, name: f2_j1}  # same"
    )
    tagged = text.replace("offset: 0.0}}", "offset: !!float 0.0}}")
    edited = with_tdt_offsets(tagged, hand, offsets)
    assert not edited.dumped and "# same" in edited.text
    # a flow mapping closed on a line of its own leaves no place to add a key on its line
    odd = text.replace("name: f2_j1}  # same", "name: f2_j1\n        }")
    dumped = with_tdt_offsets(odd, hand, offsets)
    assert dumped.dumped and "f2_j1: its flow mapping ends on a line of its own" in dumped.why
    path = Path(hand.source).parent / "unused"  # only for the name in messages
    back = parse_hand(parse_yaml(dumped.text, str(path)))
    assert [j.tdt.offset for j in back.joints] == pytest.approx(list(offsets.values()))


@REALTIME
def test_on_the_unix_bus_with_the_hand_in_its_own_process(hand: HandConfig, tmp_path: Path) -> None:
    faults = _scenario(
        tmp_path, f"{{kind: tdt_offset, node: 2, joint: 3, offset: {ADDED}, start: 0.0}}"
    )
    out = tmp_path / "calibrated.yaml"
    # Short, and with the fingers still sagging (the joints' span is not what this tests):
    # a loaded machine can starve a free-running hand, so a stop of the load's is retried, on
    # a hand ``tolerant_of_load`` so that fewer are.
    tolerant = tolerant_hand(HAND_YAML, tmp_path)
    stopped = []
    for _attempt in range(ATTEMPTS_UNDER_LOAD):
        result = subprocess.run(
            [
                sys.executable,
                "-m",
                "handctl",
                "calibrate",
                "tdt",
                "--hand",
                str(tolerant),
                "--realtime",
                "--rt",
                "-o",
                str(out),
                "--settle",
                "0.3",
                "--seconds",
                "0.5",
                "--max-span",
                "1.0",
                "--sim-faults",
                str(faults),
                "--json",
                str(tmp_path / "m.json"),
            ],
            capture_output=True,
            text=True,
            cwd=ROOT,
            timeout=300,
            check=False,
        )
        if not stopped_by_load(result.stderr):
            break
        stopped.append(result.stderr)
    else:
        give_up("every attempt was stopped by the machine's load", stopped)
    assert result.returncode == cli.EXIT_OK, result.stderr
    _check_offsets(hand, out, json.loads((tmp_path / "m.json").read_text()))


@REALTIME
@pytest.mark.parametrize(
    "entry, says",
    [
        ("{kind: node_silent, node: 1, start: 0.0}", "node 1 (f1): no feedback"),
        (
            "{kind: tdt_spike, node: 2, joint: 2, amplitude: 5.0, start: 0.0}",
            "node 2 (f2) in FAULT (SENSOR)",
        ),
    ],
)
def test_on_the_unix_bus_a_node_missing_or_in_fault(tmp_path: Path, entry: str, says: str) -> None:
    out = tmp_path / "calibrated.yaml"
    stopped = []
    for _attempt in range(ATTEMPTS_UNDER_LOAD):  # a start-up the load stopped is retried
        result = subprocess.run(
            [
                sys.executable,
                "-m",
                "handctl",
                "calibrate",
                "tdt",
                "--realtime",
                "--rt",
                "-o",
                str(out),
                "--sim-faults",
                str(_scenario(tmp_path, entry)),
            ],
            capture_output=True,
            text=True,
            cwd=ROOT,
            timeout=300,
            check=False,
        )
        assert result.returncode == cli.EXIT_SAFETY_STOP, result.stderr
        assert not out.exists()
        if says in result.stderr:
            return
        assert stopped_by_load(result.stderr), f"not refused for {says!r}: {result.stderr}"
        stopped.append(result.stderr)
    give_up(f"never refused for {says!r}: every attempt was stopped by the load", stopped)


def test_o_refuses_the_hand_config_itself_under_another_path_and_a_symlink(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A copy of the hand config with its offsets as they are is no calibrated copy (none
    wrote it): `-o` at the repository's copy of the shipped config replaced it, exit 0, and
    `-o` at a symlink wrote through it into whatever it pointed to."""
    same = tmp_path / "hiroshima_hand.yaml"
    shutil.copyfile(HAND_YAML, same)
    before = same.read_bytes()
    assert cli.main(["calibrate", "tdt", "-o", str(same)]) == cli.EXIT_BAD_INPUT
    err = capsys.readouterr().err
    assert "-o: expected a new file, or a calibrated copy of" in err
    assert "the same config as" in err and "its TDT offsets too" in err
    link = tmp_path / "link.yaml"
    link.symlink_to(same)
    assert cli.main(["calibrate", "tdt", "-o", str(link)]) == cli.EXIT_BAD_INPUT
    assert "-o: expected a file, not a symbolic link" in capsys.readouterr().err
    assert same.read_bytes() == before


@pytest.mark.parametrize(
    ("option", "value", "expected"),
    [
        ("--max-noise", "5", "--max-noise: expected at most 0.6 N·m (the largest tau_max"),
        ("--max-span", "100", "--max-span: expected at most 3.2 rad (the widest joint range"),
        ("--seconds", "0.0001", "--seconds: expected at least 0.01 s, 10 loop periods"),
    ],
)
def test_a_bound_that_turns_a_check_off_or_measures_nothing_is_refused(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], option: str, value: str, expected: str
) -> None:
    """--max-noise 5 N·m and --max-span 100 rad passed any sensor; --seconds 0.0001 enabled
    the hand and measured nothing (exit 1). Refused before anything starts."""
    out = tmp_path / "calibrated.yaml"
    assert cli.main(["calibrate", "tdt", "-o", str(out), option, value]) == cli.EXIT_BAD_INPUT
    assert expected in capsys.readouterr().err
    assert not out.exists()


def _joints_changed(hand: HandConfig, tau_max: float = 0.0, span: float = 0.0) -> HandConfig:
    """``hand`` with every joint's tau_max, or its range's width, changed."""
    import dataclasses

    def joint(j: Any) -> Any:
        if tau_max:
            j = dataclasses.replace(j, tau_max=tau_max)
        return dataclasses.replace(j, angle_max=j.angle_min + span) if span else j

    fingers = tuple(
        dataclasses.replace(f, joints=tuple(joint(j) for j in f.joints)) for f in hand.fingers
    )
    return dataclasses.replace(hand, fingers=fingers)


def test_the_defaults_are_scaled_down_to_a_smaller_hand(hand: HandConfig) -> None:
    """A hand of 0.2 N·m joints, or of joints 0.08 rad wide, was refused for --max-offset
    (0.25) or --max-span (0.1) that its user never gave; the defaults fit the hand now, and
    an option given is still held to it."""
    import argparse

    none = argparse.Namespace(max_span=None, max_noise=None, max_offset=None)
    shipped = cli._calibration_limits(none, hand)
    assert (shipped.max_offset, shipped.max_noise, shipped.max_span) == (0.25, 0.02, 0.1)
    weak = _joints_changed(hand, tau_max=0.2)
    limits = cli._calibration_limits(none, weak)
    assert (limits.max_offset, limits.max_noise) == (0.2, 0.02)
    weaker = _joints_changed(hand, tau_max=0.1)
    assert cli._calibration_limits(none, weaker).max_noise == pytest.approx(0.01)
    narrow = _joints_changed(hand, span=0.08)
    assert cli._calibration_limits(none, narrow).max_span == pytest.approx(0.04)
    with pytest.raises(ConfigError, match=r"--max-offset: expected at most 0\.2 N·m"):
        cli._calibration_limits(argparse.Namespace(**{**vars(none), "max_offset": 0.25}), weak)
