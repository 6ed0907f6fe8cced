"""The miss trace in the running loop (``handctl.online.misstrace``): for each late wake-up,
what the tick before it did, read from the loop's own stamps and the kernel's schedstat.

A hold recipe runs in lockstep on the simulated hand through a clock that reports every
wake-up one tick late (the hand config's overrun tolerance raised so that the run goes on),
so every tick of the run has its row. What each row must say is known from the runtime
itself, read by a tick hook at every wake-up: whether the collector ran, the phase or the
supervisor's state changed, the status line was due; and one tick is made busy in its send
stage, which its row must show as CPU time of its stages. The first running tick's row is the
last start-up tick's, with the nodes' enable.
"""

from __future__ import annotations

import asyncio
import dataclasses
import time
from pathlib import Path

import pytest

from handctl.config import HandConfig
from handctl.online.bus import open_bus
from handctl.online.clock import LockstepClock, Tick
from handctl.online.drivers.hand import AppliedTorques, HandDriver
from handctl.online.loop import STATUS_EVERY_TICKS, Runtime, StatusLine
from handctl.online.misstrace import MissTrace, describe
from handctl.online.recipes.loader import load_recipe
from handctl.protocol import load_protocol
from handctl.sim.hand import SimulatedHand

from .rig import CLOSE_AND_HOLD_1S

BUSY_NS = 3_000_000  # thread CPU time the busy tick burns in its send stage


class LateClock(LockstepClock):
    """Lockstep, but every wake-up reports one expiration slept through, 1.5 periods late."""

    async def wait_tick(self) -> Tick:
        tk = await super().wait_tick()
        return Tick(tk.tick, tk.scheduled_ns, tk.now_ns + 3 * self.period_ns // 2, 1)


def _burn(ns: int) -> None:
    start = time.thread_time_ns()
    while time.thread_time_ns() - start < ns:
        pass


def test_each_late_wake_up_says_what_the_tick_before_it_did(
    hand: HandConfig, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    tolerant = dataclasses.replace(
        hand, safety=dataclasses.replace(hand.safety, max_consecutive_misses=1_000_000)
    )
    path = tmp_path / "hold.yaml"
    path.write_text(CLOSE_AND_HOLD_1S)
    recipe = load_recipe(path, tolerant)
    with (
        open_bus("virtual:miss-trace", tolerant.bus) as peer,
        open_bus("virtual:miss-trace", tolerant.bus) as host,
    ):
        sim = SimulatedHand(tolerant, peer, seed=0)
        clock = LateClock(tolerant.bus.period_s, sim.step)
        driver = HandDriver(tolerant, load_protocol(), host, clock_ns=clock.now_ns)
        lines: list[StatusLine] = []
        rt = Runtime(tolerant, driver, clock, recipe, status=lines.append, max_ticks=3000)
        rt.trace = MissTrace(clock.period_ns)
        seen: dict[int, tuple[int, int, object]] = {}  # at each wake-up: after the tick before

        def look(tk: Tick) -> None:
            phase = rt.runner.index if rt.runner is not None else -1
            seen[tk.tick] = (sum(rt.collector.collections), phase, rt.supervisor.state)

        rt.tick_hooks.append(look)
        busy: list[int] = []
        real_send = driver.send

        def send(applied: AppliedTorques) -> bool:
            if not busy and rt.first_send_tick >= 0 and rt.tick >= rt.first_send_tick + 300:
                busy.append(rt.tick)
                _burn(BUSY_NS)
            return real_send(applied)

        monkeypatch.setattr(driver, "send", send)
        rt.collector.young_threshold = 50  # collections often enough to be seen in the run
        asyncio.run(rt.run())
        rt.trace.close()
    rows = rt.trace.rows()
    traced = sorted(t for t in seen if t - 1 in seen)
    assert busy and traced and len(rows) >= len(traced)
    for tick in traced:
        row = rows[tick]
        assert row["missed"] == 1 and row["wall_ns"] > 0
        assert 0 <= row["stages_ns"] <= row["cpu_ns"]
        assert row["run_delay_ns"] >= 0
        assert min(row["voluntary"], row["involuntary"], row["faults"]) >= 0
        notes = set(describe(row, 300_000)["notes"])
        before, now = seen[tick - 1], seen[tick]
        assert ("collection" in notes) == (now[0] > before[0]), tick
        assert ("phase" in notes) == (now[1] != before[1]), tick
        assert ("state" in notes) == (now[2] is not before[2]), tick
        assert ("status_line" in notes) == ((tick - 1) % STATUS_EVERY_TICKS == 0), tick
    assert any("collection" in describe(rows[t], 1)["notes"] for t in traced)
    assert any("phase" in describe(rows[t], 1)["notes"] for t in traced)
    # the first running tick's row: the last start-up tick (no stages) and the nodes' enable
    first = min(seen)
    assert rows[first]["stages_ns"] == 0 and "state" in describe(rows[first], 1)["notes"]
    slow = rows[busy[0] + 1]
    assert slow["stages_ns"] >= BUSY_NS
    shown = describe(slow, 300_000)
    assert shown["cpu_us"] >= BUSY_NS / 1e3 and shown["cpu_over_usual"] >= BUSY_NS / 300_000


@pytest.mark.parametrize("readable", [True, False], ids=["schedstat", "no_schedstat"])
def test_the_run_delay_is_the_schedstat_s_growth_over_the_tick_before(
    tmp_path: Path, readable: bool
) -> None:
    """Read from a file written as the kernel writes ``/proc/thread-self/schedstat``; without
    one the figures are unknown, never zero."""
    stat = tmp_path / "schedstat"
    stat.write_text("1000000 500000 10\n")
    trace = MissTrace(1_000_000, path=str(stat) if readable else str(tmp_path / "absent"))
    trace.woke(7, 20_000, 0, 2_000_000)
    trace.done(2_300_000, 0)
    stat.write_text("1400000 1900000 14\n")
    time.sleep(0.003)
    trace.woke(8, 600_000, 1, 2_500_000)
    trace.close()
    row = trace.rows()[8]
    shown = describe(row, 250_000)
    assert shown["late_us"] == 1600.0 and shown["before_woke_late_us"] == 20.0
    assert shown["wall_us"] >= 3000.0 and shown["cpu_us"] == 500.0
    assert shown["stages_cpu_us"] == 300.0 and shown["cpu_over_usual"] == 2.0
    assert shown["voluntary_switches"] >= 1 and shown["page_faults"] >= 0  # it slept
    if readable:
        assert shown["run_delay_us"] == 1400.0
        assert shown["off_cpu_us"] == pytest.approx(shown["wall_us"] - 1900.0, abs=0.11)
    else:
        assert shown["run_delay_us"] is None and shown["off_cpu_us"] is None
