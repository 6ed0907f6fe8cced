"""The layout in docs/foxglove is the one handctl.foxglove.layout builds for the default hand,
and it names only paths the derived channels have."""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest

from handctl.cli import main
from handctl.config import HandConfig
from handctl.foxglove import derived as fx
from handctl.foxglove.layout import layout_json

from ..conftest import ROOT

LAYOUT = ROOT / "docs" / "foxglove" / "handctl_layout.json"


def test_the_committed_layout_is_the_built_one(hand: HandConfig) -> None:
    assert LAYOUT.read_text() == layout_json(hand), (
        "regenerate: handctl layout config/hands/hiroshima_hand.yaml "
        "-o docs/foxglove/handctl_layout.json"
    )


def test_every_plotted_path_is_a_field_of_the_joints_channel(hand: HandConfig) -> None:
    text = LAYOUT.read_text()
    fields = set(
        fx.joints_schema(hand.joint_names)["properties"][hand.joint_names[0]]["properties"]
    )
    paths = re.findall(r'"value": "(/hand/joints\.[^"]+)"', text)
    plotted = {p.split(".")[1] for p in paths}
    assert plotted == set(hand.joint_names)
    for path in paths:
        assert path.split(".")[2] in fields, path
    assert {"desired_nm", "applied_nm", "tdt_torque_nm", "tau_max_nm"} == {
        p.split(".")[2] for p in paths
    }
    doc = json.loads(text)
    assert fx.SCENE in json.dumps(doc) and fx.LOG in json.dumps(doc)


def test_the_layout_command_says_what_is_wrong_and_exits_2(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A hand config that does not load, a directory that does not exist, and the hand config
    itself as the output ended in tracebacks (and the last lost the hand)."""
    hand = tmp_path / "hand.yaml"
    hand.write_text((ROOT / "config" / "hands" / "planar_2f2j.yaml").read_text())
    bad = tmp_path / "bad.yaml"
    bad.write_text("fingers: 3\n")
    classic = ROOT / "config" / "hands" / "hiroshima_hand_classic.yaml"
    cases = [
        ([str(bad), "-o", str(tmp_path / "l.json")], f"{bad}: "),
        ([str(hand), "-o", str(tmp_path / "none" / "l.json")], "-o: expected a file in an"),
        ([str(hand), "-o", str(hand)], "-o: expected another file than HAND.yaml's"),
        # one config, one verdict: what check refuses (a bus that cannot carry the hand)
        (
            [
                str(classic),
                "-o",
                str(tmp_path / "c.json"),
            ],
            f"{classic}: bus.fd: expected true (CAN-FD)",
        ),
    ]
    for argv, said in cases:
        assert main(["layout", *argv]) == 2
        err = capsys.readouterr().err
        assert err.startswith(f"handctl: error: {said}"), err
    assert hand.read_text() == (ROOT / "config" / "hands" / "planar_2f2j.yaml").read_text()
    notes = tmp_path / "notes.txt"  # another file than the hand's: replaced, exit 0
    notes.write_text("bring-up notes\n")
    assert main(["layout", str(hand), "-o", str(notes)]) == 2
    assert "an existing file that is not JSON" in capsys.readouterr().err
    assert notes.read_text() == "bring-up notes\n"
    assert main(["layout", str(hand), "-o", str(tmp_path / "l.json")]) == 0
    assert main(["layout", str(hand), "-o", str(tmp_path / "l.json")]) == 0  # over its own
    assert '"/hand/joints.' in (tmp_path / "l.json").read_text()
    # JSON, but not a layout (a run's --summary-json): replaced by the layout, exit 0
    summary = tmp_path / "summary.json"
    summary.write_text('{"outcome": "completed"}\n')
    capsys.readouterr()
    assert main(["layout", str(hand), "-o", str(summary)]) == 2
    assert f"found {summary}, an existing JSON file that is not a layout" in (
        capsys.readouterr().err
    )
    assert summary.read_text() == '{"outcome": "completed"}\n'
