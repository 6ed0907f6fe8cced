"""docs/your_hand.md walks a newcomer through a hand config, a recipe and a template of their
own: its files must stay ones handctl loads, and its links must lead somewhere, or the page
that says every key is checked strictly teaches a file that is refused."""

from __future__ import annotations

import re
from pathlib import Path

from handctl.config import load_hand
from handctl.online.recipes.loader import load_recipe
from handctl.planning.template import load_template
from handctl.sim.params import parse_sim

from ..conftest import ROOT

PAGE = ROOT / "docs" / "your_hand.md"
BLOCK = re.compile(r"```(\w+)\n(.*?)```", re.S)
LINK = re.compile(r"\]\(([\w.]+\.md)(?:#([\w-]+))?\)")


def _slug(heading: str) -> str:
    """GitHub's anchor of a heading: lower case, punctuation but hyphens gone, spaces to '-'."""
    return re.sub(r"[^\w\- ]", "", heading.strip().lower()).replace(" ", "-")


def test_the_pages_hand_recipe_and_template_load(tmp_path: Path) -> None:
    names = ("two3.yaml", "hold.yaml", "two3.template.yaml")
    blocks = [text for kind, text in BLOCK.findall(PAGE.read_text()) if kind == "yaml"]
    assert len(blocks) == len(names)
    for name, text in zip(names, blocks, strict=True):
        (tmp_path / name).write_text(text)
    hand = load_hand(tmp_path / "two3.yaml")
    assert [len(f.joints) for f in hand.fingers] == [3, 3]
    parse_sim(hand)  # the simulated hand the steps run on
    recipe = load_recipe(tmp_path / "hold.yaml", hand)
    assert [p.name for p in recipe.phases] == ["close", "hold"]
    template = load_template(tmp_path / "two3.template.yaml", hand)
    assert [p.kind for p in template.phases] == ["free", "lift", "hold"]


def test_the_pages_links_lead_to_a_page_and_heading() -> None:
    links = LINK.findall(PAGE.read_text())
    assert links
    for page, anchor in links:
        target = PAGE.parent / page
        assert target.is_file(), page
        if anchor:
            headings = re.findall(r"^#+ (.*)$", target.read_text(), re.M)
            assert anchor in {_slug(h) for h in headings}, f"{page}#{anchor}"
