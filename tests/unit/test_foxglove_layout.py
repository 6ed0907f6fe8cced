"""The layout in docs/foxglove is the one handctl.foxglove.layout builds for the default hand,
and it names only paths the derived channels have."""

from __future__ import annotations

import json
import re

from handctl.config import HandConfig
from handctl.foxglove import derived as fx
from handctl.foxglove.layout import layout_json

from ..conftest import ROOT

LAYOUT = ROOT / "docs" / "foxglove" / "handctl_layout.json"


def test_the_committed_layout_is_the_built_one(hand: HandConfig) -> None:
    assert LAYOUT.read_text() == layout_json(hand), (
        "regenerate: python -m handctl.foxglove.layout config/hands/hiroshima_hand.yaml "
        "docs/foxglove/handctl_layout.json"
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
