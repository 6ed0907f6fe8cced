"""A compiled recipe's header says how to plan it again: ``handctl plan`` with the options it
was planned with. That command must still be one ``handctl plan`` accepts, for the template
and the hand as they are now: the swap's header once named a ``--schedule-only`` re-plan
that a later change to the template left with nothing to search, which ``plan`` refuses.
Checked up to where ``plan`` begins to plan (the hand, the template, the base recipe and
the phase it re-plans from), not by planning, which takes minutes."""

from __future__ import annotations

import shlex
from pathlib import Path

import pytest
import yaml

from handctl.cli import build_parser
from handctl.config import load_hand
from handctl.planning.replan import load_base, load_kept_base
from handctl.planning.template import load_template

from ..conftest import ROOT

RECIPES = ROOT / "config" / "recipes"
PREFIX = "# Change the template and plan again: "
COMPILED = sorted(
    path
    for path in RECIPES.glob("*.yaml")
    if not path.name.endswith(".template.yaml") and yaml.safe_load(path.read_text()).get("compiled")
)


def test_the_shipped_recipes_compiled_by_plan_are_found() -> None:
    names = {path.name for path in COMPILED}
    assert {"swap_two_cylinders.yaml", "planar_lift_turn.yaml"} <= names


@pytest.mark.parametrize("recipe", COMPILED, ids=lambda p: p.name)
def test_the_header_names_a_plan_command_that_is_accepted(
    recipe: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    lines = recipe.read_text().splitlines()
    assert lines[1].startswith(PREFIX), lines[:2]
    argv = shlex.split(lines[1].removeprefix(PREFIX))
    assert argv[:2] == ["handctl", "plan"], argv
    monkeypatch.chdir(ROOT)  # the command is given from the project's root
    args = build_parser().parse_args(argv[1:])
    assert args.output.resolve() == recipe.resolve()
    hand = load_hand(args.hand)
    template = load_template(args.template, hand)
    assert template.recipe == yaml.safe_load(recipe.read_text())["recipe"]
    if args.keep_torques:
        load_kept_base(args.base, template, hand)
    elif args.start is not None:
        load_base(args.base, args.start, template, hand, args.schedule_only)
