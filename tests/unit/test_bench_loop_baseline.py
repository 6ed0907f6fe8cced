"""The loop bench's tick cost beside a baseline tree: ``tools/tick_cost.py`` runs with the
baseline's handctl first on the path, so everything it imports (through the tools it imports
too) must be in that tree. It imported the hold recipe from ``bench_loop``, whose own imports
had grown past the default baseline's handctl: both rounds failed with an ImportError kept
inside the figures, and the bench exited 0. A baseline that cannot run is refused before
anything is measured, on stderr, with exit 1."""

from __future__ import annotations

import argparse
import ast
import subprocess
from pathlib import Path
from typing import Any

import pytest

from ..conftest import HAND_YAML, ROOT, load_tool

TOOLS = ROOT / "tools"


def _defined(source: str) -> set[str]:
    """The names a module's source defines at its top level (in its ``if`` and ``try``
    blocks too), imported names included: what ``from it import NAME`` finds."""
    names: set[str] = set()
    body = list(ast.parse(source).body)
    while body:
        node = body.pop()
        if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef | ast.ClassDef):
            names.add(node.name)
        elif isinstance(node, ast.Assign):
            names.update(t.id for t in node.targets if isinstance(t, ast.Name))
        elif isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name):
            names.add(node.target.id)
        elif isinstance(node, ast.Import | ast.ImportFrom):
            names.update((a.asname or a.name).partition(".")[0] for a in node.names)
        elif isinstance(node, ast.If | ast.Try):
            body.extend([*node.body, *node.orelse])
            if isinstance(node, ast.Try):
                body.extend(n for h in node.handlers for n in h.body)
    return names


def _imports(tool: str, seen: set[str]) -> list[tuple[str, str]]:
    """``(handctl module, name)`` for every import of handctl in ``tools/TOOL.py`` and in the
    tools it imports, wherever in the file (``tick_cost.py`` imports inside ``main``)."""
    seen.add(tool)
    found: list[tuple[str, str]] = []
    for node in ast.walk(ast.parse((TOOLS / f"{tool}.py").read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            found += [(a.name, "") for a in node.names if a.name.startswith("handctl")]
        elif isinstance(node, ast.ImportFrom) and node.module:
            if node.module.split(".")[0] == "handctl":
                found += [(node.module, a.name) for a in node.names]
            elif (TOOLS / f"{node.module}.py").exists() and node.module not in seen:
                found += _imports(node.module, seen)
    return found


def _show(rev: str, path: str) -> str | None:
    done = subprocess.run(
        ["git", "-C", str(ROOT), "show", f"{rev}:{path}"],
        capture_output=True,
        text=True,
        check=False,
        timeout=60,
    )
    return done.stdout if done.returncode == 0 else None


def test_the_default_baseline_has_everything_tick_cost_imports() -> None:
    rev = load_tool("bench_loop").BASELINE_REV
    if _show(rev, "handctl/__init__.py") is None:
        pytest.skip(f"no git history with {rev} here")
    imports = _imports("tick_cost", set())
    assert ("handctl.handshape", "flexion_sign") in imports  # through hold_recipe.py
    missing = []
    for module, name in imports:
        path = module.replace(".", "/")
        source = _show(rev, f"{path}.py") or _show(rev, f"{path}/__init__.py")
        if source is None:
            missing.append(module)
        elif name and name not in _defined(source) and _show(rev, f"{path}/{name}.py") is None:
            missing.append(f"{module}.{name}")
    assert missing == [], f"{rev}'s handctl lacks what tools/tick_cost.py imports"


def test_the_check_sees_what_bench_loop_itself_imports() -> None:
    """The check above reads the tools ``tick_cost.py`` imports: had it still imported the
    recipe from ``bench_loop``, the check would have met ``hostcheck.work_figures``."""
    assert ("handctl.hostcheck", "work_figures") in _imports("bench_loop", set())
    assert not any(m == "handctl.hostcheck" for m, _ in _imports("tick_cost", set()))


def _old_tree(rev: str, into: Path) -> str:
    """``_extract``'s stand-in: a handctl too old for ``tick_cost.py`` (its config lacks
    ``load_hand``) under ``into``, and no problem getting it."""
    (into / "handctl").mkdir()
    (into / "handctl" / "__init__.py").write_text("")
    (into / "handctl" / "config.py").write_text("")
    return ""


def test_a_baseline_that_cannot_run_is_named_with_its_import_error(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    bench = load_tool("bench_loop")
    monkeypatch.setattr(bench, "_extract", _old_tree)
    problem = bench.baseline_problem("old", tmp_path, HAND_YAML)
    assert "unix bus:" in problem and "virtual bus:" in problem
    assert "cannot import name 'load_hand' from 'handctl.config'" in problem


def test_a_baseline_git_cannot_give_is_a_problem(tmp_path: Path) -> None:
    problem = load_tool("bench_loop").baseline_problem("no-such-rev", tmp_path, HAND_YAML)
    assert problem.startswith("git archive no-such-rev:")


def test_the_bench_refuses_a_baseline_that_cannot_run_before_measuring(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    bench = load_tool("bench_loop")
    measured: list[Any] = []
    monkeypatch.setattr(bench, "baseline_problem", lambda rev, into, hand: "ImportError: x")
    monkeypatch.setattr(bench, "_measure", lambda args, baseline: measured.append(args))
    args = argparse.Namespace(
        live=False, no_tick_cost=False, baseline="old", hand=HAND_YAML, record=False
    )
    with pytest.raises(SystemExit) as refused:
        bench.run(args)
    assert measured == []
    message = str(refused.value.code)
    assert message.startswith("bench.py loop: the baseline old cannot run tools/tick_cost.py")
    assert "ImportError: x" in message


def test_without_the_tick_cost_no_baseline_is_tried(monkeypatch: pytest.MonkeyPatch) -> None:
    bench = load_tool("bench_loop")

    def tried(*_: object) -> str:
        raise AssertionError("a baseline tried with --no-tick-cost")

    monkeypatch.setattr(bench, "baseline_problem", tried)
    monkeypatch.setattr(bench, "_measure", lambda args, baseline: {"baseline": baseline})
    args = argparse.Namespace(live=False, no_tick_cost=True, baseline="old", hand=HAND_YAML)
    assert bench.run(args) == {"baseline": None}
