"""A re-plan's base (``--from PHASE --base RECIPE``): which of the base's phases the plan
keeps, when the phase it plans from is one the base lacks."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest
import yaml

from handctl.config import load_hand
from handctl.errors import ConfigError
from handctl.planning.replan import load_base, load_kept_base
from handctl.planning.template import load_template

from ..conftest import HAND_YAML, ROOT

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
    assert [base.kept(p) is not None for p in template.phases] == [
        k < at for k in range(len(template.phases))
    ]
    assert [base.plans_schedule(p.name) for p in template.phases] == [
        k >= at for k in range(len(template.phases))
    ]


def test_a_margin_the_kept_torques_cannot_take_is_refused_before_the_plan(
    tmp_path: Path,
) -> None:
    """``--keep-torques`` with a template whose ``torque_margin`` takes a kept torque past
    tau_max: every model ran, and then the compiled recipe was refused naming
    ``phases[1].torques``, a key the template does not have. Now refused when the base
    loads, naming the template's margin and the base's torque; a margin the torques can take
    still loads."""
    hand = load_hand(PLANAR)
    data: dict[str, Any] = yaml.safe_load(TEMPLATE.read_text())
    data["phases"][1]["torque_margin"] = 1.2  # the lift's 0.5123 N·m of left_j1: 0.615 > 0.6
    path = tmp_path / "planar_lift_turn.template.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    template = load_template(path, hand)
    with pytest.raises(ConfigError) as info:
        load_kept_base(RECIPE, template, hand)
    assert (info.value.file, info.value.key) == (str(path), "phases[1].torque_margin")
    assert "planar_lift_turn.yaml's phases[1].torques.left_j1 is 0.5123 N·m" in str(info.value)
    with pytest.raises(ConfigError):  # the phases before --from are kept as well
        load_base(RECIPE, "manipulate", template, hand)
    load_base(RECIPE, "lift", template, hand)  # planned again: searched within the margin
    # 0.564 N·m; left_j2's 0.45 is at its tau_max already
    data["phases"][1]["torque_margin"] = {
        "left_j1": 1.1,
        "left_j2": 1,
        "right_j1": 1.1,
        "right_j2": 1,
    }
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    load_kept_base(RECIPE, load_template(path, hand), hand)


def test_a_free_phase_s_torques_times_its_margin_past_tau_max_are_refused_when_it_loads(
    tmp_path: Path,
) -> None:
    """A free phase's torques go into the recipe as written, and the runner holds them times
    the margin: past tau_max, the plan ran and its recipe was refused. A seed times its
    phase's margin and its turn-rate loop's largest scale is refused as well: the search
    box is tau_max over both, and the seed was clipped there and said "from template" (an
    outside probe)."""
    hand = load_hand(PLANAR)
    data: dict[str, Any] = yaml.safe_load(TEMPLATE.read_text())
    data["phases"][0]["torques"]["left_j2"] = 0.4
    data["phases"][0]["torque_margin"] = 1.5  # 0.6 > 0.45 of left_j2
    path = tmp_path / "t.template.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    with pytest.raises(ConfigError) as info:
        load_template(path, hand)
    assert info.value.key == "phases[0].torques.left_j2"
    assert "times the phase's torque_margin (1.5): 0.6 N·m" in info.value.expected
    data["phases"][0]["torque_margin"] = 1.1
    seed = data["phases"][3]["seed"]
    seed["left_j2"] = 0.3
    data["phases"][3]["torque_margin"] = 1.2
    data["phases"][3]["turn_rate"] = {"rate_deg_s": 20, "scale": [0.5, 1.5]}  # 0.54 > 0.45
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    with pytest.raises(ConfigError) as info:
        load_template(path, hand)
    assert info.value.key == "phases[3].seed.left_j2"
    # each factor once, by its key (the scale was said twice, the product unnamed)
    assert (
        "the torque times the phase's torque_margin (1.2) and turn_rate's largest scale "
        "(1.5): 0.54 N·m" in info.value.expected
    )
    data["phases"][3]["torque_margin"] = 1.0
    data["phases"][3]["turn_rate"]["scale"] = [0.5, 1.2]
    seed["left_j2"] = 0.45  # 0.54 > 0.45
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    with pytest.raises(ConfigError) as info:
        load_template(path, hand)
    assert info.value.expected.endswith(
        "planar_2f2j.yaml), the torque times turn_rate's largest scale (1.2): 0.54 N·m"
    )
    data["phases"][3]["torque_margin"] = 1.2
    data["phases"][3]["turn_rate"]["scale"] = [0.5, 1.5]
    seed["left_j2"] = 0.25  # 0.45
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    load_template(path, hand)


def test_a_turn_exit_its_phase_leaves_no_time_to_hold_is_refused_when_it_loads(
    tmp_path: Path,
) -> None:
    """``exit_hold_s: 0.9`` in a phase of ``max_s: 0.5``: refused by the planned recipe's
    loader after the whole plan, naming ``exit[0]``, a key the template does not have (an
    outside probe). Refused now as the template loads, naming ``exit_hold_s``."""
    hand = load_hand(PLANAR)
    data: dict[str, Any] = yaml.safe_load(TEMPLATE.read_text())
    turn = data["phases"][3]
    turn["max_s"], turn["exit_hold_s"] = 0.5, 0.9
    turn["ramp_s"] = min(turn.get("ramp_s", 0.1), 0.5)
    path = tmp_path / "t.template.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    with pytest.raises(ConfigError) as info:
        load_template(path, hand)
    assert info.value.key == "phases[3].exit_hold_s"
    assert "a hold the phase's max_s (0.5 s) leaves time for" in info.value.expected
    turn["exit_hold_s"] = 0.4
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    load_template(path, hand)


def test_a_written_entry_times_the_loop_s_scale_past_tau_max_is_refused_when_it_loads(
    tmp_path: Path,
) -> None:
    """A written schedule torque of 0.42 N·m in a phase whose turn-rate loop scales it by up
    to 1.2: 0.504 N·m of a 0.45 N·m joint, refused after the whole plan (an outside probe)."""
    hand = load_hand(PLANAR)
    data: dict[str, Any] = yaml.safe_load(TEMPLATE.read_text())
    turn = data["phases"][3]
    turn["turn_rate"] = {"rate_deg_s": 20, "scale": [0.5, 1.2]}
    turn["seed"]["left_j2"] = 0.3  # within the loop's reach: the entry is what is refused
    torques = dict.fromkeys(turn["seed"], 0.1) | {"left_j2": 0.42}
    turn["schedule"] = [
        {"when": {"radius_ratio": {"object": data["objects"][0]["name"], "max": 0.9}},
         "torques": torques}
    ]  # fmt: skip
    path = tmp_path / "t.template.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    with pytest.raises(ConfigError) as info:
        load_template(path, hand)
    assert info.value.key == "phases[3].schedule[0].torques.left_j2"
    assert "(1.2): 0.504 N·m" in info.value.expected


def test_a_kept_phase_without_the_kind_its_plan_wrote_is_refused(tmp_path: Path) -> None:
    """A base whose kept phase has no ``provenance.kind`` (an edited recipe) skipped the kind
    check, so a hold's torques could be kept as a turn's: refused, naming the phase. A free
    phase keeps nothing of the base's, so its kind is not asked for."""
    hand = load_hand(PLANAR)
    template = load_template(TEMPLATE, hand)
    data: dict[str, Any] = yaml.safe_load(RECIPE.read_text())
    for phase in data["phases"]:
        assert phase["provenance"]["kind"]
    data["phases"][0]["provenance"].pop("kind")  # the approach, free
    base = tmp_path / "planar_lift_turn.yaml"
    base.write_text(yaml.safe_dump(data, sort_keys=False))
    load_kept_base(base, template, hand)
    data["phases"][2]["provenance"].pop("kind")  # the envelop, a hold
    base.write_text(yaml.safe_dump(data, sort_keys=False))
    with pytest.raises(ConfigError) as info:
        load_kept_base(base, template, hand)
    assert (info.value.file, info.value.key) == (str(base), "phases[2].provenance.kind")
    assert "expected 'hold', the kind of the template's 'envelop'" in str(info.value)
    assert "found 'no kind'" in str(info.value)
    with pytest.raises(ConfigError):  # kept before --from as well
        load_base(base, "manipulate", template, hand)
    load_base(base, "envelop", template, hand)  # planned again: nothing of it kept


SWAP_TEMPLATE = ROOT / "config" / "recipes" / "swap_two_cylinders.template.yaml"
SWAP_RECIPE = ROOT / "config" / "recipes" / "swap_two_cylinders.yaml"


@pytest.mark.parametrize(
    ("key", "value"),
    [("torques", {"f1_j1": 0.05}), ("pose", {"stiffness": 0.7}), ("pose", {"damping": 0.01})],
)
def test_a_free_phase_is_kept_only_as_the_template_still_writes_it(
    tmp_path: Path, key: str, value: dict[str, float]
) -> None:
    """A free phase's torques are written in the template, not searched: kept from the base
    (``--keep-torques``, the phases before ``--from``), an edit of them or of its pose
    hold's gains was compiled over with the base's old values. Unedited, it is kept whole
    (its pose is where the nominal hand rested when the base was planned)."""
    hand = load_hand(HAND_YAML)
    data: dict[str, Any] = yaml.safe_load(SWAP_TEMPLATE.read_text())
    approach = data["phases"][0]
    assert approach["kind"] == "free" and "pose" in approach
    path = tmp_path / "swap_two_cylinders.template.yaml"

    def kept(start: str | None) -> list[bool]:
        path.write_text(yaml.safe_dump(data, sort_keys=False))
        template = load_template(path, hand)
        base = (
            load_kept_base(SWAP_RECIPE, template, hand)
            if start is None
            else load_base(SWAP_RECIPE, start, template, hand)
        )
        return [base.kept(p) is not None for p in template.phases[:2]]

    assert kept(None) == kept("manipulate_1") == [True, True]
    approach[key] = {**approach[key], **value}
    # the edited free phase is the template's; the searched lift is kept as before
    assert kept(None) == kept("manipulate_1") == [False, True]


def test_a_base_without_the_compiled_key_is_said_to_lack_it(tmp_path: Path) -> None:
    """A base recipe whose ``compiled`` key was deleted was said to have ``compiled: False``
    ("found False"), a value it does not hold (found by an outside audit)."""
    hand = load_hand(PLANAR)
    template = load_template(TEMPLATE, hand)
    data: dict[str, Any] = yaml.safe_load(RECIPE.read_text())
    path = tmp_path / "base.yaml"
    for value, found in ((None, "found nothing: the key is missing"), (False, "found False")):
        if value is None:
            del data["compiled"]
        else:
            data["compiled"] = value
        path.write_text(yaml.safe_dump(data, sort_keys=False))
        with pytest.raises(ConfigError) as info:
            load_base(path, "manipulate", template, hand)
        assert info.value.key == "compiled"
        assert str(info.value).endswith(
            f"expected a recipe compiled by handctl plan (true), {found}"
        )
