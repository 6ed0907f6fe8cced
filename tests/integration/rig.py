"""A hardware-in-the-loop rig: the runtime and the simulated hand on one virtual bus, plus a
sniffer that hears every frame the host puts on the wire, the way a CAN analyser would."""

from __future__ import annotations

import asyncio
import os
import pty
import select
import signal
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from handctl.config import HandConfig
from handctl.harness.campaign import hil_bench
from handctl.online.bus import HandBus
from handctl.online.loop import Outcome, RunResult, Runtime
from handctl.online.recipes.loader import load_recipe
from handctl.online.recipes.schema import Recipe
from handctl.online.safety.faults import FaultCode
from handctl.sim.hand import SimulatedHand
from handctl.sim.params import SimParams

from ..conftest import ROOT
from ..dbc import decode


@dataclass
class Rig:
    hand: HandConfig
    sim: SimulatedHand
    runtime: Runtime
    sniffer: HandBus
    wire: list[tuple[int, bytes]] = field(default_factory=list)

    def run(self) -> RunResult:
        result = asyncio.run(self.runtime.run())
        self.wire += [(f.arbitration_id, f.data) for f in self.sniffer.drain(limit=10**7)]
        return result

    def commands(self) -> np.ndarray:
        """Every torque command on the wire so far, as rows of 9 joint torques (one per tick
        the host sent), decoded with cantools from the DBC, independently of handctl's codec."""
        per_node: dict[int, list[list[float]]] = {1: [], 2: [], 3: []}
        for frame_id, data in self.wire:
            if 0x101 <= frame_id <= 0x103:
                sig = decode(frame_id, data)
                per_node[frame_id - 0x100].append([sig["Torque1"], sig["Torque2"], sig["Torque3"]])
        n = min(len(v) for v in per_node.values())
        return np.hstack([np.array(per_node[k][:n]).reshape(n, 3) for k in (1, 2, 3)])

    def estops(self) -> int:
        return sum(1 for frame_id, _ in self.wire if frame_id == 0)


@contextmanager
def rig(
    hand: HandConfig,
    recipe: Recipe | None,
    *,
    seed: int = 0,
    max_seconds: float = 30.0,
    params: SimParams | None = None,
) -> Iterator[Rig]:
    max_ticks = round(max_seconds / hand.bus.period_s)
    with hil_bench(hand, recipe, seed, max_ticks, params) as (sim, runtime, sniffer):
        yield Rig(hand, sim, runtime, sniffer)


# -- recipes the integration tests share ---------------------------------------------------------
#: One phase that holds a light grasp for ten minutes: a run that goes until it is stopped.
HOLD_LONG = """
recipe: hold_long
phases:
  - name: hold
    torques: [0.06, 0.05, 0.03, 0.06, 0.05, 0.03, -0.06, -0.05, -0.03]
    ramp_s: 0.3
    max_s: 600
"""

#: Two short timed phases, the second holding until stopped: phase changes within a second.
TWO_PHASES = """
recipe: two_phases
phases:
  - name: first
    torques: [0.04, 0.03, 0.02, 0.04, 0.03, 0.02, -0.04, -0.03, -0.02]
    ramp_s: 0.1
    max_s: 0.4
    on_timeout: next
  - name: second
    torques: [0.06, 0.05, 0.03, 0.06, 0.05, 0.03, -0.06, -0.05, -0.03]
    ramp_s: 0.2
    max_s: 600
"""


#: Close, then hold: 0.4 + 1.6 s, each phase timed (the runtime's tests).
CLOSE_AND_HOLD_2S = """
recipe: hold
phases:
  - name: close
    torques: [0.06, 0.05, 0.03, 0.06, 0.05, 0.03, -0.06, -0.05, -0.03]
    ramp_s: 0.2
    max_s: 0.4
    on_timeout: next
  - name: hold
    torques: [0.07, 0.05, 0.03, 0.07, 0.05, 0.03, -0.07, -0.05, -0.03]
    ramp_s: 0.2
    max_s: 1.6
    on_timeout: next
"""

#: Close, then hold: 0.3 + 0.6 s, each phase timed (the tick-exception tests).
CLOSE_AND_HOLD_1S = """
recipe: hold
phases:
  - name: close
    torques: [0.06, 0.05, 0.03, 0.06, 0.05, 0.03, -0.06, -0.05, -0.03]
    ramp_s: 0.2
    max_s: 0.3
    on_timeout: next
  - name: hold
    torques: [0.07, 0.05, 0.03, 0.07, 0.05, 0.03, -0.07, -0.05, -0.03]
    ramp_s: 0.1
    max_s: 0.6
    on_timeout: next
"""

#: Close, then hold: 0.3 + 0.6 s (the recording and replay tests; ``short_recipe``).
SHORT = """
recipe: short_hold
phases:
  - name: close
    torques: [0.06, 0.05, 0.03, 0.06, 0.05, 0.03, -0.06, -0.05, -0.03]
    ramp_s: 0.15
    max_s: 0.3
    on_timeout: next
  - name: hold
    torques: [0.07, 0.05, 0.03, 0.07, 0.05, 0.03, -0.07, -0.05, -0.03]
    ramp_s: 0.15
    max_s: 0.6
    on_timeout: next
"""


def short_recipe(hand: HandConfig, directory: Path, hold_s: float = 0.6) -> Recipe:
    """Close, then hold for ``hold_s``: a short run with torque flowing."""
    path = directory / "short_hold.yaml"
    hold = f"ramp_s: {min(0.15, hold_s):g}\n    max_s: {hold_s}"  # a ramp within its phase
    path.write_text(SHORT.replace("ramp_s: 0.15\n    max_s: 0.6", hold))
    return load_recipe(path, hand)


def write_recipe(directory: Path, text: str, name: str = "recipe.yaml") -> Path:
    """A recipe written where a test may leave it (its tmp_path), for a loader or the CLI."""
    path = directory / name
    path.write_text(text)
    return path


def stopped_at_once(r: Rig, result: RunResult, code: FaultCode) -> int:
    """The first fault is ``code``; torque was flowing before it and is zero two ticks on.
    Returns the tick that detected it."""
    assert result.outcome is Outcome.SAFETY_STOP
    first = result.faults[0]
    assert first.code is code, [str(f) for f in result.faults]
    wire = r.commands()
    row = first.tick - r.runtime.first_send_tick
    assert np.abs(wire[row - 1]).max() > 0.01
    assert not np.any(wire[row + 2 :])
    return first.tick


def read_until(fd: int, wanted: str | None, timeout_s: float = 120.0) -> str:
    """What a terminal showed until ``wanted`` appeared (``None``: until the process closed
    it)."""
    seen = ""
    deadline = time.monotonic() + timeout_s
    while (wanted is None or wanted not in seen) and time.monotonic() < deadline:
        ready, _, _ = select.select([fd], [], [], 0.5)
        if not ready:
            continue
        try:
            chunk = os.read(fd, 4096)
        except OSError:  # the other end closed: the process ended
            break
        if not chunk:
            break
        seen += chunk.decode(errors="replace")
    return seen


@contextmanager
def sim_on_unix_bus(bus: Path) -> Iterator[subprocess.Popen[bytes]]:
    """``handctl sim`` in its own process on the unix bus ``bus`` (made), once it is on the
    bus; stopped with Ctrl-C at the end (killed if it does not end in a minute)."""
    bus.mkdir()
    sim = subprocess.Popen(
        [sys.executable, "-m", "handctl", "sim", "--bus", f"unix:{bus}", "--seconds", "120"],
        cwd=Path(__file__).resolve().parents[2],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    try:
        while not any(bus.iterdir()):  # the hand is on the bus
            assert sim.poll() is None, "the simulated hand ended before it was on the bus"
            time.sleep(0.05)
        yield sim
    finally:
        stop_with_ctrl_c(sim, 60)


def stop_with_ctrl_c(process: subprocess.Popen[Any], timeout_s: float) -> None:
    """A simulated hand's process ended as a user ends it, killed if it has not within
    ``timeout_s``."""
    process.send_signal(signal.SIGINT)
    try:
        process.wait(timeout=timeout_s)
    except subprocess.TimeoutExpired:
        process.kill()
        process.wait()


def stopped_while_holding(
    tmp_path: Path, options: list[str], stop: Callable[[subprocess.Popen[str]], None]
) -> tuple[int, str, str]:
    """``handctl run recipe`` of a hold that goes on until stopped, its status line on a
    terminal; ``stop(process)`` once the line says the phase is under way (not after a guess
    at how long the imports and the start-up take). The exit code, stdout and what the
    terminal showed."""
    recipe = tmp_path / "hold.yaml"
    recipe.write_text(HOLD_LONG)
    terminal, stderr_end = pty.openpty()
    proc = subprocess.Popen(
        [sys.executable, "-m", "handctl", "run", "recipe", str(recipe), *options],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=stderr_end,
        text=True,
    )
    os.close(stderr_end)
    try:
        shown = read_until(terminal, "running")
        assert "running" in shown, shown
        stop(proc)
        stdout, _ = proc.communicate(timeout=60)
        stderr = shown + read_until(terminal, None, timeout_s=10.0)
    finally:
        proc.kill()
        os.close(terminal)
    return proc.returncode, stdout, stderr
