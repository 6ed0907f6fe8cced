"""Recipe templates for ``handctl plan``: strict loading, and the exits they compile to."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml

from handctl.config import HandConfig
from handctl.errors import ConfigError
from handctl.planning.template import load_template

from ..conftest import HAND_YAML, ROOT

TEMPLATE = ROOT / "config" / "recipes" / "swap_two_cylinders.template.yaml"


def base() -> dict[str, Any]:
    data: dict[str, Any] = yaml.safe_load(TEMPLATE.read_text())
    return data


def write(tmp_path: Path, data: dict[str, Any]) -> Path:
    path = tmp_path / "t.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def test_the_shipped_template_loads(hand: HandConfig) -> None:
    t = load_template(TEMPLATE, hand)
    assert [p.kind for p in t.phases] == ["free", "lift", "hold"] + ["turn"] * 4
    turns = [p for p in t.phases if p.kind == "turn"]
    assert all(p.turn == pytest.approx(math.radians(-45)) for p in turns)
    # manipulate_1 ends at 90 % of its 45 deg, to leave manipulate_2 its share
    assert turns[0].exit_condition() == "estimate.cyl1_cyl2_line_turn < -0.7069 for 0.02"
    assert t.objects[0].name == "cyl1" and t.objects[1].radius == 0.02
    # a turn's paced ramp gives the rate's magnitude; it is signed as the turn
    assert all(p.paced is not None and p.paced.rate < 0 for p in turns)


def test_the_shipped_recipe_carries_the_template_s_feedback(hand: HandConfig) -> None:
    """What ``handctl plan`` carries from a template phase into the recipe it compiles (the
    pose hold's gains, the injected damping, the brake, the torque margin) is in the shipped
    recipe as the template says, so that planning the template again gives the same keys."""
    from handctl.online.recipes.loader import load_recipe

    template = load_template(TEMPLATE, hand)
    recipe = load_recipe(TEMPLATE.with_name("swap_two_cylinders.yaml"), hand)
    compiled = {p.name: p for p in recipe.phases}
    assert [p.name for p in template.phases] == list(compiled)
    for spec in template.phases:
        phase = compiled[spec.name]
        assert phase.torque_margin == spec.torque_margin, spec.name
        assert phase.joint_damping == spec.joint_damping, spec.name
        assert phase.brake == spec.brake, spec.name
        assert (phase.pose is None) == (spec.pose_stiffness is None), spec.name
        if phase.pose is not None:
            assert phase.pose.stiffness == spec.pose_stiffness, spec.name
            assert phase.pose.damping == spec.pose_damping, spec.name


def _schedule(data: dict[str, Any], *entries: dict[str, Any]) -> None:
    data["phases"][3]["schedule"] = list(entries)


_WHEN = {"radius_ratio": {"object": "cyl1", "min": 1.1}}
_TORQUES = {f"f{f}_j{j}": 0.1 for f in (1, 2, 3) for j in (1, 2, 3)}


def test_an_exit_share_compiles_to_the_last_sharing_phase_s_exit(
    tmp_path: Path, hand: HandConfig
) -> None:
    """``exit_share: N`` writes the exit of the turn phase N - 1 later (what the runner shares
    out), whatever that phase's own ``exit_fraction``; 3 spans manipulate_2 to _4."""
    data = base()
    turns = [p for p in data["phases"] if p.get("kind") == "turn"]
    for phase in turns:
        phase.pop("exit_share", None)
    turns[1]["exit_share"] = 3
    turns[3]["exit_fraction"] = 0.9
    t = load_template(write(tmp_path, data), hand)
    specs = [p for p in t.phases if p.kind == "turn"]
    assert specs[1].recipe_exit_turn() == pytest.approx(math.radians(-180.0) * 0.9)
    assert specs[1].recipe_exit_condition() == specs[3].recipe_exit_condition()
    assert specs[2].recipe_exit_turn() == pytest.approx(math.radians(-135.0) * 0.95)
    # the planner's own episode of the phase still exits on its own turn
    assert specs[1].exit_condition() == "estimate.cyl1_cyl2_line_turn < -0.7461 for 0.02"


@pytest.mark.parametrize(
    ("edit", "found"),
    [
        (lambda turns: turns[3].update(exit_share=2), "1 phase(s) short"),  # the last
        (lambda turns: turns[2].update(exit_share=3), "1 phase(s) short of the end"),
        (
            lambda turns: turns[1].update(exit_share=2) or turns[2].update(exit_share=2),
            "found 'manipulate_3 (exit_share 2 of its own)'",
        ),
        (lambda turns: turns[0].update(exit_share=2), "2"),  # no turn_from
        (
            lambda turns: turns[2].update(exit_share=2) or turns[3].pop("turn_from"),
            "manipulate_4 (turn_from none)",
        ),
        (
            lambda turns: turns[2].update(exit_share=2) or turns[3].update(turn_deg=45),
            "manipulate_4 (turn_deg 45, the other way)",
        ),
        (lambda turns: turns[2].update(exit_share=1.5), "float"),
    ],
)
def test_a_bad_exit_share_is_refused_naming_the_key(
    tmp_path: Path, hand: HandConfig, edit: Any, found: str
) -> None:
    data = base()
    turns = [p for p in data["phases"] if p.get("kind") == "turn"]
    for phase in turns:
        phase.pop("exit_share", None)
        phase.pop("exit_fraction", None)
    edit(turns)
    with pytest.raises(ConfigError) as info:
        load_template(write(tmp_path, data), hand)
    assert info.value.key.endswith("exit_share"), info.value
    assert found in str(info.value)


def test_an_exit_fraction_beside_an_exit_share_is_refused(tmp_path: Path, hand: HandConfig) -> None:
    """A sharing phase's exit is the last sharing phase's, so its own fraction is not read:
    a key that does nothing is refused rather than left to mislead."""
    data = base()
    turns = [p for p in data["phases"] if p.get("kind") == "turn"]
    turns[2]["exit_fraction"] = 0.5
    with pytest.raises(ConfigError) as info:
        load_template(write(tmp_path, data), hand)
    assert info.value.key == "phases[5].exit_fraction"


def test_a_schedule_entry_is_written_or_planned(tmp_path: Path, hand: HandConfig) -> None:
    """A template's schedule entry gives its torques (carried as written) or asks the plan
    to search them (``plan: {models: N}``), in the order the runner tries them."""
    from handctl.online.recipes.schema import ScheduledTorques
    from handctl.planning.template import PlannedSchedule

    data = base()
    _schedule(
        data,
        {"when": _WHEN, "plan": {"models": 5}},
        {"when": {"radius_ratio": {"object": "cyl1", "max": 0.9}}, "torques": _TORQUES},
    )
    planned, written = load_template(write(tmp_path, data), hand).phases[3].schedule
    assert isinstance(planned, PlannedSchedule) and planned.models == 5
    assert planned.when[0].object == 0 and planned.when[0].low == 1.1
    assert isinstance(written, ScheduledTorques) and written.torques == (0.1,) * 9


@pytest.mark.parametrize(
    ("entry", "key", "expected"),
    [
        ({"when": _WHEN, "plan": {"models": 5}, "torques": _TORQUES}, "torques", "both"),
        ({"when": _WHEN}, "torques", "neither"),
        ({"when": _WHEN, "plan": {"models": 1}}, "plan.models", "an integer"),
        ({"when": _WHEN, "plan": {"models": 4, "seed": 3}}, "plan.seed", "unknown key"),
    ],
)
def test_a_bad_schedule_entry_is_refused_naming_the_key(
    tmp_path: Path, hand: HandConfig, entry: dict[str, Any], key: str, expected: str
) -> None:
    data = base()
    _schedule(data, entry)
    with pytest.raises(ConfigError) as info:
        load_template(write(tmp_path, data), hand)
    assert info.value.key == f"phases[3].schedule[0].{key}"
    assert expected in str(info.value)


@pytest.mark.parametrize(
    ("change", "key", "expected"),
    [
        (lambda d: d["phases"][1].update(torque_margin=3), "phases[1].torque_margin", "2"),
        (lambda d: d["phases"][3].update(kind="spin"), "phases[3].kind", "one of"),
        (lambda d: d["phases"][3].update(turn_deg=0), "phases[3].turn_deg", "at least 1 deg"),
        (lambda d: d["phases"][3].update(turn_deg=1e-9), "phases[3].turn_deg", "found 1e-09"),
        (lambda d: d["phases"][3].update(colour="red"), "phases[3]", "colour"),
        # the planner's models are the hand's scene: an object it lacks is refused up front
        (
            lambda d: d["objects"].append({"name": "cyl3", "radius": 0.02}),
            "objects[2].name",
            "an object of the simulated hand (cyl1, cyl2",
        ),
        (
            lambda d: d["phases"][0].update(
                torques={"left_j1": 0.1, "left_j2": 0.1, "right_j1": -0.1, "right_j2": -0.1}
            ),
            "phases[0].torques",
            "written for another hand? give its config with --hand",
        ),
        (lambda d: d["phases"][1]["move"].update(cyl9=[0, 1]), "phases[1].move.cyl9", "object"),
        # a lift whose objects move down (gravity is along -y) planned, and did "its job"
        (
            lambda d: d["phases"][1]["move"].update(cyl1=[0, -1]),
            "phases[1].move.cyl1",
            "a direction with an upward part (y > 0)",
        ),
        (lambda d: d["phases"][0].pop("torques"), "phases[0].torques", ""),
        (lambda d: d["search"].update(elite=99, population=4), "search.elite", "population"),
        (
            lambda d: d["search"].update(max_turn_rate_deg_s=0),
            "search.max_turn_rate_deg_s",
            "deg/s",
        ),
        (lambda d: d["phases"].append(dict(d["phases"][3])), "phases[7].name", "not used"),
        (
            lambda d: d["phases"][3]["paced_ramp"].update(rate_deg_s=-90),
            "phases[3].paced_ramp.rate_deg_s",
            "deg/s",
        ),
        (
            lambda d: d["phases"][2].update(paced_ramp={"rate_deg_s": 90}),
            "phases[2]",
            "paced_ramp",
        ),
        # refused in the recipe only once every phase had been planned; the first ended the
        # plan in a traceback (the pace divides by its ramp)
        (
            lambda d: d["phases"][3].update(ramp_s=0),
            "phases[3].ramp_s",
            "a ramp longer than 0 s (the paced_ramp moves at its speed)",
        ),
        (
            lambda d: d["phases"][0].update(ramp_s=d["phases"][0]["max_s"] + 1),
            "phases[0].ramp_s",
            "a ramp no longer than the phase's max_s",
        ),
    ],
)
def test_bad_templates_are_refused_naming_the_key(
    tmp_path: Path, hand: HandConfig, change: Any, key: str, expected: str
) -> None:
    data = base()
    change(data)
    with pytest.raises(ConfigError) as info:
        load_template(write(tmp_path, data), hand)
    assert info.value.key.startswith(key)
    assert expected in str(info.value)


def _set(path: tuple[Any, ...], value: Any) -> Any:
    def change(data: dict[str, Any]) -> None:
        for key in path[:-1]:
            data = data[key]
        data[path[-1]] = value

    return change


@pytest.mark.parametrize(
    ("change", "key"),
    [
        (_set(("phases", 0, "torques", "f1_j1"), 0.61), "phases[0].torques.f1_j1"),
        (_set(("phases", 0, "torques", "f3_j3"), -50.0), "phases[0].torques.f3_j3"),
        (_set(("phases", 0, "torques", "f2_j2"), 1e30), "phases[0].torques.f2_j2"),
        (_set(("phases", 0, "torques"), [0.1] * 8 + [0.31]), "phases[0].torques.f3_j3"),
        (_set(("phases", 1, "seed", "f1_j1"), 1e30), "phases[1].seed.f1_j1"),
        (_set(("phases", 3, "seed", "f2_j3"), -0.5), "phases[3].seed.f2_j3"),
    ],
)
def test_a_torque_beyond_tau_max_is_refused_when_the_template_loads(
    tmp_path: Path, hand: HandConfig, change: Any, key: str
) -> None:
    """A free phase's torques go into the recipe as written, which ``run`` refused only after
    a whole plan (or the plan failed with 'an object left the hand'); a seed was clipped to
    tau_max without a word."""
    data = base()
    change(data)
    with pytest.raises(ConfigError) as info:
        load_template(write(tmp_path, data), hand)
    assert info.value.key == key
    assert "tau_max" in info.value.expected


def test_a_schedule_torque_beyond_tau_max_is_refused(tmp_path: Path, hand: HandConfig) -> None:
    data = base()
    _schedule(data, {"when": _WHEN, "torques": [0.1] * 4 + [0.7] + [0.1] * 4})
    with pytest.raises(ConfigError) as info:
        load_template(write(tmp_path, data), hand)
    assert info.value.key == "phases[3].schedule[0].torques.f2_j2"
    assert info.value.found == 0.7


def one_object(data: dict[str, Any]) -> None:
    data["objects"] = data["objects"][:1]
    data["phases"][1]["move"].pop("cyl2")
    data.pop("min_total_turn_deg")


def one_object_turning(data: dict[str, Any]) -> None:
    one_object(data)
    del data["phases"][4:]


@pytest.mark.parametrize(
    ("change", "key", "expected"),
    [
        (one_object_turning, "phases[3].kind", "a turn is that of a pair"),
        (lambda d: d.update(objects=d["objects"][:1]), "min_total_turn_deg", "there is no pair"),
        (
            lambda d: d.update(objects=[{"name": f"c{i}", "radius": 0.01} for i in range(5)]),
            "objects",
            "1 to 4",
        ),
    ],
)
def test_a_turn_needs_two_objects_and_there_are_four_at_most(
    tmp_path: Path, hand: HandConfig, change: Any, key: str, expected: str
) -> None:
    data = base()
    change(data)
    with pytest.raises(ConfigError) as info:
        load_template(write(tmp_path, data), hand)
    assert info.value.key == key
    assert expected in str(info.value)


def test_a_template_of_one_object_lifts_and_holds(tmp_path: Path, hand: HandConfig) -> None:
    data = base()
    one_object(data)
    data["phases"] = data["phases"][:3]
    t = load_template(write(tmp_path, data), hand)
    assert [o.name for o in t.objects] == ["cyl1"]
    assert [p.kind for p in t.phases] == ["free", "lift", "hold"]


@pytest.mark.parametrize(
    ("path", "key"),
    [(("phases", 0, "ramp_s"), "phases[0].ramp_s"), (("end_ramp_s",), "end_ramp_s")],
)
def test_a_plan_whose_recipe_run_would_refuse_is_refused_naming_the_template_key(
    path: tuple[Any, ...], key: str
) -> None:
    """A template's ramp_s: 0 was planned into a recipe that every run refused (exit 0 from
    plan, exit 2 from run): the ramps are known only once the torques are planned."""
    from handctl.config import load_hand
    from handctl.planning.compile import check_runnable

    hand = load_hand(ROOT / "config" / "hands" / "planar_2f2j.yaml")
    recipe = ROOT / "config" / "recipes" / "planar_lift_turn.yaml"
    check_runnable(recipe.read_text(), "t.template.yaml", hand)
    data = yaml.safe_load(recipe.read_text())
    target = data
    for part in path[:-1]:
        target = target[part]
    target[path[-1]] = 0.0
    with pytest.raises(ConfigError) as info:
        check_runnable(yaml.safe_dump(data, sort_keys=False), "t.template.yaml", hand)
    assert info.value.file == "t.template.yaml"
    assert info.value.key == key
    assert "rate limit" in info.value.expected and info.value.found == 0.0


def test_a_ramp_into_the_template_s_own_torques_is_checked_before_any_search(
    tmp_path: Path, hand: HandConfig
) -> None:
    """A ramp_s of 0 into the first (free) phase was refused only in the recipe planned from
    the template, once every phase had been searched."""
    data = base()
    data["phases"][0]["ramp_s"] = 0.0
    with pytest.raises(ConfigError) as info:
        load_template(write(tmp_path, data), hand)
    assert info.value.key == "phases[0].ramp_s"
    assert "expected a ramp of at least" in str(info.value)
    assert f"into phase '{data['phases'][0]['name']}'" in str(info.value)


def test_an_end_ramp_of_zero_is_refused_before_any_search(tmp_path: Path, hand: HandConfig) -> None:
    """end_ramp_s: 0 was refused only in the recipe planned from the template, once every
    phase had been searched (2 min 48 s of a quick plan of the swap, lost; found by an
    outside audit). The last phase's planned torques are not zero: its end ramp takes time."""
    data = base()
    data["end_ramp_s"] = 0.0
    with pytest.raises(ConfigError) as info:
        load_template(write(tmp_path, data), hand)
    assert info.value.key == "end_ramp_s"
    assert "a ramp back to zero longer than 0 s" in info.value.expected
    data["end_ramp_s"] = 0.3
    assert load_template(write(tmp_path, data), hand).end_ramp_s == 0.3


@pytest.mark.parametrize(
    ("phase", "ramp", "key"),
    [
        (1, 0.0, "phases[1].ramp_s"),  # a lift from the free approach's torques
        (2, 0.0, "phases[2].ramp_s"),  # a hold after the searched lift
        (3, 0.0, "phases[3].ramp_s or end_ramp_s"),  # the last phase, after a searched one
        (2, 1e-6, "phases[2].ramp_s"),  # too short to leave a written torque's last digit
    ],
)
def test_a_searched_phase_s_ramp_that_leaves_no_torque_is_refused_before_any_search(
    tmp_path: Path, phase: int, ramp: float, key: str
) -> None:
    """A ramp_s of 0 into a phase the plan searches, after another searched phase, was
    refused by the search's bounds only once the phases before it had been planned (12 to
    17 minutes of the swap's lift; found by an outside audit). Refused as the template
    loads, with the message the search gives (``compile.ramp_bounds``)."""
    from handctl.config import load_hand

    planar = load_hand(ROOT / "config" / "hands" / "planar_2f2j.yaml")
    data = yaml.safe_load(
        (ROOT / "config" / "recipes" / "planar_lift_turn.template.yaml").read_text()
    )
    assert load_template(write(tmp_path, data), planar)  # the shipped ramps leave room
    data["phases"][phase]["ramp_s"] = ramp
    with pytest.raises(ConfigError) as info:
        load_template(write(tmp_path, data), planar)
    assert info.value.key == key
    name = data["phases"][phase]["name"]
    assert str(info.value).endswith(
        "expected ramps the rate limit of left_j1 (20 N·m/s) can make between the phases' "
        f"torques within tau_max, found none leaves a torque for phase '{name}'"
    )


def test_the_search_box_leaves_room_for_what_the_feedback_adds(hand: HandConfig) -> None:
    """The search gives a phase no torque its own feedback takes past tau_max when it runs
    (the loader refuses that recipe): the lift's torque_margin, a turn-rate loop's largest
    scale, a paced ramp's reach beyond the phase's torque."""
    from dataclasses import replace

    from handctl.online.recipes.schema import PacedRamp, TurnRate
    from handctl.planning.compile import search_box

    template = load_template(ROOT / "config" / "recipes" / "swap_two_cylinders.template.yaml", hand)
    tau = [j.tau_max for j in hand.joints]
    zero = [0.0] * hand.n_joints
    lift = next(p for p in template.phases if p.name == "lift")
    margin = (
        [lift.torque_margin] * len(tau)
        if isinstance(lift.torque_margin, float)
        else list(lift.torque_margin)
    )
    assert search_box(lift, hand, zero) == pytest.approx(
        [t / max(m, 1.0) for t, m in zip(tau, margin, strict=True)]
    )
    turn = next(p for p in template.phases if p.kind == "turn")
    plain = replace(turn, turn_rate=None, paced=None, torque_margin=1.0)
    assert search_box(plain, hand, zero) == pytest.approx(tau)
    scaled = replace(
        plain, turn_rate=TurnRate(rate=-0.8, scale_min=0.5, scale_max=2.0, gain=1.0, integral=0.0)
    )
    assert search_box(scaled, hand, zero) == pytest.approx([t / 2 for t in tau])
    # both: the loop scales the margined torque, so the box is tau_max over their product
    # (over the larger of the two, a plan was refused by its own recipe's loader)
    both = replace(scaled, torque_margin=1.2)
    assert search_box(both, hand, zero) == pytest.approx([t / 2.4 for t in tau])
    paced = replace(plain, paced=PacedRamp(rate=-1.5, reach=1.5, back=2.0))
    previous = [0.1] * hand.n_joints
    box = search_box(paced, hand, previous)
    # the furthest the ramp goes, previous + 1.5 (torque - previous), stays within tau_max
    for b, t in zip(box, tau, strict=True):
        assert abs(0.1 + 1.5 * (b - 0.1)) <= t + 1e-12
        assert abs(0.1 + 1.5 * (-b - 0.1)) <= t + 1e-12


def test_a_template_names_its_pairs_as_a_recipe_does_and_the_plan_carries_them(
    tmp_path: Path, hand: HandConfig
) -> None:
    """A template refused ``pairs``, which a recipe takes: a planned recipe of three or four
    objects could turn only each object with the next (an outside audit)."""
    from handctl.planning.compile import PlanResult

    data = base()
    data["pairs"] = [["cyl2", "cyl1"]]
    template = load_template(write(tmp_path, data), hand)
    assert template.pairs == ((1, 0),)
    turns = [p for p in template.phases if p.kind == "turn"]
    assert turns[0].exit_condition().startswith("estimate.cyl2_cyl1_line_turn < ")
    document = PlanResult(template, hand, [], [], "sha256:0").recipe_document()
    assert document["pairs"] == [["cyl2", "cyl1"]]
    shipped = PlanResult(load_template(TEMPLATE, hand), hand, [], [], "")
    assert "pairs" not in shipped.recipe_document()
    data["pairs"] = [["cyl1", "cyl3"]]
    with pytest.raises(ConfigError, match=r"pairs\[0\]: expected two names of the recipe's"):
        load_template(write(tmp_path, data), hand)


def test_a_joint_of_another_hand_in_a_template_s_torques_is_named(tmp_path: Path) -> None:
    """``f1_j1`` written where the planar hand's ``left_j1`` goes: the refusal named the
    missing ``left_j1`` and guessed ``left_j2``, a joint that was there, as its misspelling."""
    from handctl.config import load_hand

    planar = load_hand(ROOT / "config" / "hands" / "planar_2f2j.yaml")
    template = ROOT / "config" / "recipes" / "planar_lift_turn.template.yaml"
    data: dict[str, Any] = yaml.safe_load(template.read_text())
    torques = data["phases"][0]["torques"]
    torques["f1_j1"] = torques.pop("left_j1")
    path = tmp_path / "t.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    with pytest.raises(ConfigError) as err:
        load_template(path, planar)
    assert err.value.key == "phases[0].torques.f1_j1"
    assert "unknown key; did you mean 'left_j1'?" in err.value.expected


@pytest.mark.parametrize(
    ("template", "hand_file"),
    [
        ("planar_lift_turn.template.yaml", None),
        ("swap_two_cylinders.template.yaml", "four_fingers_four_joints.yaml"),
        ("swap_two_cylinders.template.yaml", "planar_2f2j.yaml"),
    ],
)
def test_a_template_for_another_hand_is_said_as_such_before_its_objects(
    hand: HandConfig, template: str, hand_file: str | None
) -> None:
    """The planar template planned with the default hand was refused on an object's radius,
    and the default template with the four-fingered hand on an object's name: the user was
    sent to tune a size (found by an outside audit). Said as run recipe says it now."""
    from handctl.config import load_hand

    other = hand if hand_file is None else load_hand(ROOT / "config" / "hands" / hand_file)
    with pytest.raises(ConfigError) as info:
        load_template(ROOT / "config" / "recipes" / template, other)
    assert info.value.key == "phases[0].torques"
    assert f"keys that are joints of the hand {other.name} (" in info.value.expected
    assert "written for another hand? give its config with --hand" in info.value.expected


def test_objects_the_scene_has_otherwise_are_refused_before_the_plan(
    tmp_path: Path, hand: HandConfig
) -> None:
    """A template whose cylinders the estimator cannot measure on the scene the plan's models
    are drawn from (12 mm against 45 mm) planned "2/2 did its job" and its runs had no
    estimate; one listing the scene's pair right to left ran with every estimate of the
    pair 180° off (an outside probe). Both are refused as the template loads."""
    data = base()
    scene = {o["name"]: o for o in yaml.safe_load(HAND_YAML.read_text())["sim"]["objects"]}
    first = data["objects"][0]
    actual = scene[first["name"]]["radius"]
    first["radius"] = actual / 2  # its scene's is twice it: past the estimator's +40 %
    with pytest.raises(ConfigError) as info:
        load_template(write(tmp_path, data), hand)
    assert info.value.key == "objects[0].radius"
    assert f"({actual * 1e3:g} mm in sim.objects in" in info.value.expected
    data = base()
    data["objects"].reverse()
    with pytest.raises(ConfigError) as info:
        load_template(write(tmp_path, data), hand)
    assert info.value.key == "objects"
    names = [o["name"] for o in base()["objects"]]
    assert f"in the scene ({', '.join(names)}, by their x" in info.value.expected


def test_a_reanalysis_asked_against_its_phase_s_turn_is_refused(
    tmp_path: Path, hand: HandConfig
) -> None:
    """``reanalyse.turn_deg: +8`` in a phase that turns -8 asked the analysis for torques
    that turn the pair back, and was accepted (an outside probe)."""
    data = base()
    turn = next(p for p in data["phases"] if p["kind"] == "turn")
    turn["reanalyse"] = {"turn_deg": -turn["turn_deg"]}
    with pytest.raises(ConfigError) as info:
        load_template(write(tmp_path, data), hand)
    assert info.value.key.endswith(".reanalyse.turn_deg")
    assert "a turn the phase's way" in info.value.expected


def test_the_search_is_held_to_ramps_the_rate_limits_can_make(hand: HandConfig) -> None:
    """An ``end_ramp_s`` (or a phase's ``ramp_s``) too short for the torques the search
    found: the plan ran whole and its recipe was refused by its own loader, all of it lost
    (an outside probe, 10 s of a small plan; a shipped plan takes an hour). The search is
    held to what the rate limits can ramp from the torque before the phase and to what
    follows it; where no ramp binds, its box is the plan's as before."""
    from dataclasses import replace

    from handctl.planning.compile import ramp_bounds, search_box
    from handctl.planning.template import RAMP_BOUND_SLACK

    template = load_template(TEMPLATE, hand)
    turn = replace(next(p for p in template.phases if p.kind == "turn"), paced=None)
    zero = np.zeros(hand.n_joints)
    box = search_box(turn, hand, list(zero))
    named = ("t.yaml", "phases[3].ramp_s")
    # the shipped ramps bind nothing: the box itself, the plan unchanged
    assert ramp_bounds(turn, hand, box, zero, (zero, 0.3, "end_ramp_s"), named) == box
    # an end ramp of 5 ms at 20 N·m/s leaves ±0.1 N·m to the last phase
    rate = np.array([j.rate_limit for j in hand.joints])
    low, high = ramp_bounds(turn, hand, box, zero, (zero, 0.005, "end_ramp_s"), named)
    np.testing.assert_allclose(high, rate * 0.005 - RAMP_BOUND_SLACK)
    np.testing.assert_allclose(low, -(rate * 0.005 - RAMP_BOUND_SLACK))
    # from the torque before it, over its own short ramp: around that torque
    before = np.full(hand.n_joints, 0.2)
    low, high = ramp_bounds(replace(turn, ramp_s=0.005), hand, box, before, None, named)
    np.testing.assert_allclose(high, np.minimum(box, 0.2 + rate * 0.005 - RAMP_BOUND_SLACK))
    np.testing.assert_allclose(low, 0.2 - rate * 0.005 + RAMP_BOUND_SLACK)
    # neither ramp can be made by any torque: refused, naming both keys
    far = np.full(hand.n_joints, 0.3)
    with pytest.raises(ConfigError) as info:
        ramp_bounds(replace(turn, ramp_s=0.001), hand, box, far, (-far, 0.001, "end_ramp_s"), named)
    assert info.value.key == "phases[3].ramp_s or end_ramp_s"


def test_a_ramp_that_holds_the_search_short_of_its_seeds_is_named(hand: HandConfig) -> None:
    """The bounds ``ramp_bounds`` sets were never said: a short end_ramp_s failed a plan
    whose advice named the search, not the key (found by an outside audit). Each joint a
    ramp holds short of a seed is named with the key, the ramp and the bound; the shipped
    ramps hold none."""
    from dataclasses import replace

    from handctl.planning.compile import ramp_cuts

    template = load_template(TEMPLATE, hand)
    turn = replace(next(p for p in template.phases if p.kind == "turn"), paced=None)
    zero = np.zeros(hand.n_joints)
    seed = np.full(hand.n_joints, 0.05)
    seed[1] = 0.4
    starts = [("template", list(seed))]
    assert ramp_cuts(turn, hand, zero, (zero, 0.3, "end_ramp_s"), "phases[3].ramp_s", starts) == []
    cuts = ramp_cuts(turn, hand, zero, (zero, 0.005, "end_ramp_s"), "phases[3].ramp_s", starts)
    rate = hand.joints[1].rate_limit
    assert [c.joint for c in cuts] == [hand.joint_names[1]]  # 0.05 N·m is within the ramp
    assert cuts[0].key == "end_ramp_s" and cuts[0].high == pytest.approx(rate * 0.005 - 1e-4)
    assert cuts[0].text().startswith(f"end_ramp_s (0.005 s) holds {hand.joint_names[1]} within")
    assert "short of 0.4 N·m, the template seed" in cuts[0].text()
    # the phase's own ramp from the torque before it
    own = ramp_cuts(replace(turn, ramp_s=0.005), hand, zero, None, "phases[3].ramp_s", starts)
    assert [(c.key, c.joint) for c in own] == [("phases[3].ramp_s", hand.joint_names[1])]
