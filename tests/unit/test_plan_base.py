"""A re-plan's base (``--from PHASE --base RECIPE``): which of the base's phases the plan
keeps, when the phase it plans from is one the base lacks."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest
import yaml

from handctl.config import load_hand
from handctl.planning.replan import load_base
from handctl.planning.template import load_template

from ..conftest import ROOT

PLANAR = ROOT / "config" / "hands" / "planar_2f2j.yaml"
TEMPLATE = ROOT / "config" / "recipes" / "planar_lift_turn.template.yaml"
RECIPE = ROOT / "config" / "recipes" / "planar_lift_turn.yaml"


@pytest.mark.parametrize("where", ["before manipulate", "at the end"])
def test_a_phase_added_to_the_template_is_planned_from_and_what_follows_it_too(
    tmp_path: Path, where: str
) -> None:
    """A phase added to the template, planned from with the earlier plan as the base: the
    base was searched for it (a traceback, exit 1), and every phase of the base after it
    was kept (the order of the base's phases read past where the new one goes)."""
    hand = load_hand(PLANAR)
    data: dict[str, Any] = yaml.safe_load(TEMPLATE.read_text())
    added = {"name": "extra", "kind": "hold", "min_height": 0.02, "ramp_s": 0.3, "max_s": 0.5}
    at = 3 if where == "before manipulate" else len(data["phases"])
    data["phases"].insert(at, added)
    path = tmp_path / "planar_lift_turn.template.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    template = load_template(path, hand)
    base = load_base(RECIPE, "extra", template, hand)
    assert [base.kept(p.name) is not None for p in template.phases] == [
        k < at for k in range(len(template.phases))
    ]
    assert [base.plans_schedule(p.name) for p in template.phases] == [
        k >= at for k in range(len(template.phases))
    ]
