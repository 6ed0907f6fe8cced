"""The import rules of docs/architecture.md, checked on the source so that a change that
breaks one fails CI."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

from ..conftest import ROOT

PACKAGE = ROOT / "handctl"

# The planes of docs/architecture.md, by module: an entry stands for itself and everything
# below it, and a module belongs to the plane of its longest entry. Every module of handctl has
# a plane, so a new one must be given its plane here (and in the document) before it passes.

#: What the control process runs every tick, and the bus it runs on.
ONLINE = ("handctl.online",)
#: What every plane may import: errors, the one YAML reader, the hand config, the protocol and
#: what a config is checked against, and the convention the summaries and plots share.
#: (``handctl`` itself, which holds only the version, is the foundation too.)
FOUNDATION = (
    "handctl.errors",
    "handctl.schema",
    "handctl.config",
    "handctl.protocol",
    "handctl.busload",
    "handctl.wirelimits",
    "handctl.convention",
    "handctl.hand_protocol",
    "handctl.handshape",
    "handctl.arrays",
    "handctl.wholefile",
)
OFFLINE = (
    "handctl.analysis",
    "handctl.planning",
    "handctl.executor",
    "handctl.progress",
    "handctl.portable",
)
SIMULATED_HAND = ("handctl.sim",)
RECORDING = ("handctl.recording", "handctl.foxglove")
#: What puts the planes together for a command: the command line, a run, bring-up, the host
#: timing check, what a run adds for the experiment, and the harness of the fault campaign and
#: the experiment bench (the real runtime against the simulated hand).
COMPOSITION = (
    "handctl.__main__",
    "handctl.cli",
    "handctl.session",
    "handctl.summary_guard",
    "handctl.stopsignals",
    "handctl.bringup",
    "handctl.hostcheck",
    "handctl.hostprobe",
    "handctl.hostfacts",
    "handctl.rivals",
    "handctl.parent_death",
    "handctl.outfile",
    "handctl.lossyout",
    "handctl.experiment",
    "handctl.harness",
)
PLANES = {
    "online": ONLINE,
    "foundation": FOUNDATION,
    "offline": OFFLINE,
    "simulated hand": SIMULATED_HAND,
    "recording": RECORDING,
    "composition": COMPOSITION,
}
#: What the simulated hand may use of the host's side: the bus and the timer. A peer that
#: shared the host's drivers, safety or loop would share their mistakes, and hide them.
SIM_MAY_USE = (
    "handctl.online.bus",
    "handctl.online.taps",
    "handctl.online.clock",
    "handctl.online.timerfd",
)


def module_of(path: Path) -> str:
    parts = path.relative_to(ROOT).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


MODULES = {module_of(path): path for path in sorted(PACKAGE.rglob("*.py"))}


def plane_of(module: str) -> str | None:
    """The plane of ``module``: that of the longest entry it is or lies below."""
    if module == "handctl":
        return "foundation"
    best = max(
        (
            (len(entry), plane)
            for plane, entries in PLANES.items()
            for entry in entries
            if module == entry or module.startswith(entry + ".")
        ),
        default=None,
    )
    return best[1] if best is not None else None


def sources(*planes: str) -> list[Path]:
    """The files of the modules of ``planes`` (of every module when none is named)."""
    return [path for module, path in MODULES.items() if not planes or plane_of(module) in planes]


def imported_modules(path: Path) -> set[str]:
    tree = ast.parse(path.read_text(encoding="utf-8"))
    found: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found |= {alias.name for alias in node.names}
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:  # relative import: resolve against the file's package
                parts = path.relative_to(ROOT).with_suffix("").parts[: -node.level]
                base = ".".join([*parts, base] if base else parts)
            found.add(base)
            # ``from handctl import loop`` imports the module handctl.online.loop
            found |= {
                f"{base}.{alias.name}" for alias in node.names if f"{base}.{alias.name}" in MODULES
            }
    return found


def handctl_imports(path: Path) -> set[str]:
    return {m for m in imported_modules(path) if m in MODULES}


def test_every_module_has_a_plane() -> None:
    assert [m for m in MODULES if plane_of(m) is None] == []


def test_every_entry_of_a_plane_is_a_module_in_one_plane() -> None:
    entries = [entry for plane in PLANES.values() for entry in plane]
    assert [e for e in entries if e not in MODULES] == []
    assert sorted(e for e in set(entries) if entries.count(e) > 1) == []


@pytest.mark.parametrize(
    ("plane", "may_import"),
    [
        ("foundation", {"foundation"}),
        ("online", {"online", "foundation"}),
    ],
)
def test_a_plane_imports_only_what_lies_below_it(plane: str, may_import: set[str]) -> None:
    """The foundation stands alone; the online plane needs nothing but itself and the
    foundation (never the analysis, planning, the simulated hand, recording or a command)."""
    offenders = [
        (str(p.relative_to(ROOT)), m)
        for p in sources(plane)
        for m in handctl_imports(p)
        if plane_of(m) not in may_import
    ]
    assert offenders == []


def test_the_simulated_hand_uses_only_the_bus_and_the_timer_of_the_host_side() -> None:
    offenders = [
        (str(p.relative_to(ROOT)), m)
        for p in sources("simulated hand")
        for m in handctl_imports(p)
        if plane_of(m) not in ("simulated hand", "foundation")
        and not any(m == e or m.startswith(e + ".") for e in SIM_MAY_USE)
    ]
    assert offenders == []


def test_only_composition_imports_composition() -> None:
    """A command, a run, bring-up, the timing check, the experiment and the harness put the
    planes together; nothing they put together may reach back up to them."""
    offenders = [
        (str(p.relative_to(ROOT)), m)
        for p in sources()
        if plane_of(module_of(p)) != "composition"
        for m in handctl_imports(p)
        if plane_of(m) == "composition"
    ]
    assert offenders == []


#: The modules that speak python-can: the bus, its specs, the unix and the arrival-stamped
#: virtual interfaces, and log export.
PYTHON_CAN_MODULES = {"bus.py", "busspec.py", "unixcan.py", "virtualcan.py", "canlog.py"}


def test_only_bus_imports_python_can() -> None:
    offenders = [
        p.relative_to(ROOT)
        for p in sources()
        if p.name not in PYTHON_CAN_MODULES
        and any(m == "can" or m.startswith("can.") for m in imported_modules(p))
    ]
    assert offenders == []


def test_only_the_cli_prints() -> None:
    """``cli.py``, and ``__main__.py`` for an interrupt while ``cli.py`` is still loading."""
    offenders = []
    for path in sources():
        if module_of(path) in ("handctl.cli", "handctl.__main__"):
            continue
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.Call) and getattr(node.func, "id", None) == "print":
                offenders.append(f"{path.relative_to(ROOT)}:{node.lineno}")
    assert offenders == []


def test_no_asyncio_sleep_on_the_online_plane() -> None:
    offenders = [
        p.relative_to(ROOT)
        for p in sources("online")
        if "asyncio.sleep(" in p.read_text(encoding="utf-8")
    ]
    assert offenders == []


@pytest.mark.parametrize("path", sources(), ids=lambda p: str(p.relative_to(PACKAGE)))
def test_applied_torques_are_made_only_by_the_supervisor(path: Path) -> None:
    """``HandDriver.send`` takes ``AppliedTorques``; only the supervisor may make them."""
    if module_of(path) in ("handctl.online.safety.supervisor", "handctl.online.drivers.hand"):
        return
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Call) and getattr(node.func, "id", None) == "AppliedTorques":
            pytest.fail(f"{path.relative_to(ROOT)}:{node.lineno} makes AppliedTorques")


def test_yaml_is_only_loaded_safely() -> None:
    offenders = [
        p.relative_to(ROOT)
        for p in sources()
        if "yaml.load(" in p.read_text(encoding="utf-8")
        or "yaml.unsafe_load" in p.read_text(encoding="utf-8")
    ]
    assert offenders == []
