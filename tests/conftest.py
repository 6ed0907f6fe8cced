"""Shared fixtures: the default hand, the protocol, private virtual-bus channels, and one
run of the default recipe that many tests read."""

from __future__ import annotations

import importlib.util
import itertools
import json
import os
import signal
import subprocess
import sys
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from types import ModuleType
from typing import Any

import pytest

from handctl.config import HandConfig, load_hand
from handctl.online.bus import HandBus, open_bus
from handctl.protocol import Protocol, load_protocol

from .warm_start import WarmStart

ROOT = Path(__file__).resolve().parent.parent


def load_tool(name: str) -> ModuleType:
    """``tools/NAME.py`` as a module (the tools are scripts, not a package), with ``tools`` on
    the path while it loads, as when it runs, so its imports of sibling tools resolve."""
    tools = str(ROOT / "tools")
    sys.path.insert(0, tools)
    try:
        spec = importlib.util.spec_from_file_location(name, ROOT / "tools" / f"{name}.py")
        assert spec is not None and spec.loader is not None
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
        return module
    finally:
        sys.path.remove(tools)


HAND_YAML = ROOT / "config" / "hands" / "hiroshima_hand.yaml"
#: The main job's recipe, as the README names it (relative to the repository root)
DEFAULT_RECIPE = "config/recipes/swap_two_cylinders.yaml"
_channels = itertools.count()


def pytest_configure(config: pytest.Config) -> None:
    """The stop signals back to their defaults when the suite itself was started with them
    ignored (SIGHUP under ``nohup`` or a runner that ignores it): a run started so keeps
    ignoring them on purpose (``stopsignals.StopSignals``), so the tests of what a run does
    when its terminal goes away would test that branch instead, and fail. Every worker and
    every child inherits them."""
    from handctl.stopsignals import StopSignals

    for sig in set(StopSignals.SIGNALS) - set(StopSignals.HONOURED_IF_IGNORED):
        if signal.getsignal(sig) is signal.SIG_IGN:
            signal.signal(sig, signal.SIG_DFL)
    _compile_once()


def _compile_once() -> None:
    """Bytecode written for the suite's own Python processes, whatever the environment says
    (PYTHONDONTWRITEBYTECODE, set on many build machines and containers): the suite starts
    hundreds of them (every ``handctl`` a test runs, the simulated hand's process, the
    recorder's writer, the planner's workers), and without bytecode each compiles the handctl
    modules it imports anew, half a second of a short run's 1.6 s. Every worker and every child
    inherits the environment; ``__pycache__`` is ignored by git."""
    if os.environ.pop("PYTHONDONTWRITEBYTECODE", None) is not None:
        sys.dont_write_bytecode = False


@pytest.hookimpl(optionalhook=True)
def pytest_xdist_make_scheduler(config: pytest.Config, log: object) -> object | None:
    """The suite's work units (``tests/worker_units.py``) where pyproject.toml asks for
    ``--dist loadgroup``; any other ``--dist`` given on the command line is xdist's own."""
    if config.getvalue("dist") != "loadgroup":
        return None
    from .worker_units import ModuleOrGroupScheduling

    return ModuleOrGroupScheduling(config, log)


@pytest.hookimpl(tryfirst=True)
def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """Every reader of the session's run of the default recipe on one worker, so that it runs
    once (before xdist reads the groups: tryfirst)."""
    for item in items:
        if "default_run" in getattr(item, "fixturenames", ()):
            item.add_marker(pytest.mark.xdist_group("default_run"))


@pytest.fixture(scope="session")
def hand() -> HandConfig:
    return load_hand(HAND_YAML)


@pytest.fixture(scope="session")
def protocol() -> Protocol:
    return load_protocol()


@pytest.fixture
def channel() -> str:
    """A virtual-bus channel no other test uses, so tests never hear each other."""
    return f"handctl-test-{next(_channels)}"


@pytest.fixture
def bus_pair(hand: HandConfig, channel: str) -> Iterator[tuple[HandBus, HandBus]]:
    """Two ends of one virtual bus: (host side, peer side)."""
    host = open_bus(f"virtual:{channel}", hand.bus)
    peer = open_bus(f"virtual:{channel}", hand.bus)
    yield host, peer
    host.close()
    peer.close()


def handctl(
    *args: str,
    cwd: Path = ROOT,
    env: Mapping[str, str] | None = None,
    timeout: float = 600,
    preexec_fn: Callable[[], Any] | None = None,
) -> subprocess.CompletedProcess[str]:
    """``python -m handctl ARGS`` as a user runs it, from the repository root unless ``cwd``
    says otherwise, its output captured and its exit left to the caller. The repository comes
    first on the path wherever it runs (from the root ``python -m`` puts it there; elsewhere
    PYTHONPATH does), so the code under test is this checkout's, whatever is installed;
    ``env`` adds to the environment the suite runs in; ``preexec_fn`` runs in the child
    before handctl does (limits of its own, ``resource.setrlimit``). A child with limits of
    its own writes no bytecode: Python writes a module's cached bytecode with one write and
    renames it into place whatever that write wrote, so under a file size limit
    (``RLIMIT_FSIZE``) it left a cut-off file in ``__pycache__`` that every later process of
    the suite failed to import ("marshal data too short").

    It starts warm (``tests/warm_start.py``): forked, a process of its own, from one that has
    already imported handctl's command line, which saves the half second of interpreter
    start-up most of the suite's commands are. A command with ``preexec_fn``, or an ``env``
    read as an interpreter starts (``PYTHON*``, the locale), starts cold, as does every
    command with ``HANDCTL_TESTS_COLD=1`` set."""
    path = os.pathsep.join(p for p in (str(ROOT), os.environ.get("PYTHONPATH", "")) if p)
    limited = {"PYTHONDONTWRITEBYTECODE": "1"} if preexec_fn is not None else {}
    argv = [sys.executable, "-m", "handctl", *args]
    full = {**os.environ, "PYTHONPATH": path, **limited, **(env or {})}
    if preexec_fn is None and os.environ.get("HANDCTL_TESTS_COLD") != "1":
        warm = _warm_start({**os.environ, "PYTHONPATH": path})
        if warm.takes(full):
            return warm.run(argv, cwd, full, timeout)
    return subprocess.run(
        argv,
        cwd=cwd,
        env=full,
        text=True,
        capture_output=True,
        timeout=timeout,
        check=False,
        preexec_fn=preexec_fn,
    )


_warm: list[WarmStart] = []


def _warm_start(env: Mapping[str, str]) -> WarmStart:
    """This process's warm-start server, started with the first command."""
    if not _warm:
        _warm.append(WarmStart(ROOT, env))
    return _warm[0]


@dataclass(frozen=True)
class DefaultRun:
    """The README's main job, run once as a user runs it, with its log and plot: ``handctl run
    recipe config/recipes/swap_two_cylinders.yaml --summary-json F --log F --plot F`` from the
    repository root, the simulated hand in lockstep (deterministic, so any number of tests can
    read one run). A run of the default recipe costs some 12 s of CPU; the tests that judge
    the summary, the experiment, the plot and the replay of the same run share this one."""

    done: subprocess.CompletedProcess[str]
    summary: dict[str, Any]
    log: Path
    plot: Path


@pytest.fixture(scope="session")
def default_run(tmp_path_factory: pytest.TempPathFactory) -> DefaultRun:
    directory = tmp_path_factory.mktemp("default-run")
    out, log, plot = directory / "out.json", directory / "run.mcap", directory / "run.png"
    done = handctl(
        "run",
        "recipe",
        DEFAULT_RECIPE,
        "--summary-json",
        str(out),
        "--log",
        str(log),
        "--plot",
        str(plot),
        timeout=900,
    )
    assert out.exists(), done.stderr
    return DefaultRun(done, json.loads(out.read_text()), log, plot)
