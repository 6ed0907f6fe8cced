"""No hidden shape: outside the hand configs (``config/``, the packaged copy in
``handctl/hands/``) and the tests, no code or tool names a finger, a joint or an object of the
default hand. What depends on the hand's shape reads it from the config (``handctl.handshape``
and the config itself), so another hand is driven, planned and judged as this one is."""

from __future__ import annotations

import re

from handctl.config import HandConfig

from ..conftest import ROOT

SEARCHED = ("handctl", "tools")
#: the packaged copy of the default hand config: a config, not code
CONFIGS = ("handctl/hands/",)
#: (file, line fragment, why): where a name is genuinely not a shape. Keep it short.
ALLOWED = (
    (
        "handctl/cli.py",
        "handctl jog f",
        "jog's help examples run against the packaged default hand, whose joints they name",
    ),
)
SUFFIXES = {".py", ".md", ".yaml", ".yml", ".json", ".txt", ".toml", ".dbc", ".h", ".c"}


def shape_names(hand: HandConfig) -> set[str]:
    """The default hand's finger, joint and simulated object names."""
    names = {f.name for f in hand.fingers} | set(hand.joint_names)
    names |= {str(o["name"]) for o in hand.sim.get("objects", [])}
    return names


def hits(names: set[str]) -> list[str]:
    pattern = re.compile(r"\b(" + "|".join(sorted(map(re.escape, names))) + r")\b")
    found = []
    for top in SEARCHED:
        for path in sorted((ROOT / top).rglob("*")):
            rel = path.relative_to(ROOT).as_posix()
            if (
                not path.is_file()
                or path.suffix not in SUFFIXES
                or "__pycache__" in rel
                or rel.startswith(CONFIGS)
            ):
                continue
            for number, line in enumerate(path.read_text(errors="replace").splitlines(), 1):
                match = pattern.search(line)
                if match is None:
                    continue
                if any(rel == f and fragment in line for f, fragment, _ in ALLOWED):
                    continue
                found.append(f"{rel}:{number}: '{match[1]}' in {line.strip()}")
    return found


def test_the_default_hands_names_appear_only_in_configs_and_tests(hand: HandConfig) -> None:
    names = shape_names(hand)
    assert {"f1", "f3_j3", "cyl1", "cyl2"} <= names
    found = hits(names)
    assert not found, "the default hand's shape is written into code:\n" + "\n".join(found)


def test_the_search_finds_a_name_where_there_is_one(hand: HandConfig) -> None:
    """The search itself works: the packaged hand config, searched as code, is full of them."""
    pattern = re.compile(r"\bf2_j1\b")
    assert any(pattern.search(p.read_text()) for p in (ROOT / "handctl/hands").glob("*.yaml"))
    assert hits({"ObjectEstimator"})  # a name that is in the code
