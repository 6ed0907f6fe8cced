"""The house rules of DESIGN.md, checked on the source so a change that breaks one fails CI."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

from ..conftest import ROOT

PACKAGE = ROOT / "handctl"
ONLINE = ["bus.py", "busspec.py", "unixcan.py", "virtualcan.py", "clock.py", "timerfd.py",
          "loop.py", "estimator.py", "drivers", "safety", "recipes"]


def sources(*names: str) -> list[Path]:
    paths: list[Path] = []
    for name in names or (".",):
        target = PACKAGE / name
        if target.is_dir():
            paths += sorted(target.rglob("*.py"))
        elif target.exists():
            paths.append(target)
    return paths


def imported_modules(path: Path) -> set[str]:
    tree = ast.parse(path.read_text(encoding="utf-8"))
    found: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found |= {alias.name for alias in node.names}
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:  # relative import: resolve against the file's package
                parts = path.relative_to(ROOT).with_suffix("").parts[:-node.level]
                base = ".".join([*parts, base] if base else parts)
            found.add(base)
    return found


#: The modules that speak python-can: the bus, its specs, the unix and the arrival-stamped
#: virtual interfaces, and log export.
PYTHON_CAN_MODULES = {"bus.py", "busspec.py", "unixcan.py", "virtualcan.py", "canlog.py"}


def test_only_bus_imports_python_can() -> None:
    offenders = [p.relative_to(ROOT) for p in sources() if p.name not in PYTHON_CAN_MODULES
                 and any(m == "can" or m.startswith("can.") for m in imported_modules(p))]
    assert offenders == []


def test_online_plane_never_imports_analysis_or_sim() -> None:
    offenders = [(p.relative_to(ROOT), m) for p in sources(*ONLINE)
                 for m in imported_modules(p)
                 if m.startswith(("handctl.analysis", "handctl.sim"))]
    assert offenders == []


def test_only_the_cli_prints() -> None:
    offenders = []
    for path in sources():
        if path.name == "cli.py":
            continue
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.Call) and getattr(node.func, "id", None) == "print":
                offenders.append(f"{path.relative_to(ROOT)}:{node.lineno}")
    assert offenders == []


def test_no_asyncio_sleep_on_the_online_plane() -> None:
    offenders = [p.relative_to(ROOT) for p in sources(*ONLINE)
                 if "asyncio.sleep(" in p.read_text(encoding="utf-8")]
    assert offenders == []


@pytest.mark.parametrize("path", sources(), ids=lambda p: str(p.relative_to(PACKAGE)))
def test_applied_torques_are_made_only_by_the_supervisor(path: Path) -> None:
    """``HandDriver.send`` takes ``AppliedTorques``; only the supervisor may make them."""
    allowed = {PACKAGE / "safety" / "supervisor.py", PACKAGE / "drivers" / "hand.py"}
    if path in allowed:
        return
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Call) and getattr(node.func, "id", None) == "AppliedTorques":
            pytest.fail(f"{path.relative_to(ROOT)}:{node.lineno} makes AppliedTorques")


def test_yaml_is_only_loaded_safely() -> None:
    offenders = [p.relative_to(ROOT) for p in sources()
                 if "yaml.load(" in p.read_text(encoding="utf-8")
                 or "yaml.unsafe_load" in p.read_text(encoding="utf-8")]
    assert offenders == []
