"""Issue-level check of the fault campaign: every injector in every kind of phase is caught
(or harmlessly absorbed), takes its stop, puts no unsafe frame on the wire, is in the MCAP log
at the tick it was detected, and comes back only through an explicit reset; docs/faults.md
shows exactly these results."""

from __future__ import annotations

import json
import shutil
from collections.abc import Iterator
from dataclasses import asdict
from pathlib import Path

import pytest
from mcap.reader import make_reader

from handctl.config import HandConfig
from handctl.executor import open_pool
from handctl.harness.campaign import CASES, PHASES, CaseResult, run_campaign
from handctl.online.safety.faults import FAULTS, FaultCode, StopCategory
from handctl.recording import channels as ch

from ..conftest import ROOT

EVERY_PHASE = [p for p, _ in PHASES]
TIMEOUT = "FEEDBACK_TIMEOUT"
#: What each injector must cause, per phase (None: tolerated, no fault).
EXPECTED: dict[str, dict[str, str | None]] = {
    **{
        name: dict.fromkeys(EVERY_PHASE, TIMEOUT)
        for name in (
            "drop_feedback",
            "delay_feedback",
            "corrupt_crc",
            "counter_repeat",
            "counter_skip",
            "node_reboot",
            "node_silent",
        )
    },
    "drop_commands": dict.fromkeys(EVERY_PHASE, "NODE_FAULT"),  # the node's own watchdog
    "encoder_jump": dict.fromkeys(EVERY_PHASE, "NODE_FAULT"),  # the node's self-check
    "tdt_stuck": dict.fromkeys(EVERY_PHASE, "TDT_STUCK"),
    "tdt_offset": dict.fromkeys(EVERY_PHASE, "TDT_MISMATCH"),
    "bus_off": dict.fromkeys(EVERY_PHASE, "BUS_ERROR"),
    "tdt_spike": dict.fromkeys(EVERY_PHASE, None),  # 2 ms, inside the 50 ms window
    "error_frames": dict.fromkeys(EVERY_PHASE, None),  # counted as bus events
    "babble": dict.fromkeys(EVERY_PHASE, None),  # foreign ids, counted and dropped
    "extended_twin": dict.fromkeys(EVERY_PHASE, None),  # 29-bit twins, counted and dropped
    "contradict": dict.fromkeys(EVERY_PHASE, "NODE_CONTRADICTION"),  # fault bits, ENABLED
    "replay_frames": dict.fromkeys(EVERY_PHASE, "REJECT_RATE"),  # 50 ms old, two a tick
    **{
        name: {
            "idle": None,
            "approach": "TDT_MISMATCH",
            "holding": "TDT_MISMATCH",
            "manipulating": "TDT_MISMATCH",
        }
        for name in ("tendon_slack", "motor_saturation")
    },
}


@pytest.fixture(scope="module")
def logs(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Path]:
    """Where the campaign keeps each case's MCAP log (about 50 MB in all: removed after)."""
    directory = tmp_path_factory.mktemp("campaign-logs")
    yield directory
    shutil.rmtree(directory, ignore_errors=True)


@pytest.fixture(scope="module")
def results(hand: HandConfig, logs: Path) -> list[CaseResult]:
    # Every case is a lockstep run, so it gives the same result in a worker process as here
    # (test_campaign_pool.py holds that); two workers halve the suite's longest set-up.
    with open_pool(2) as pool:
        return run_campaign(hand, log_dir=logs, executor=pool)


def test_every_injector_has_an_expectation() -> None:
    assert set(EXPECTED) == set(CASES)


def test_detection_and_stop(results: list[CaseResult]) -> None:
    got = {(r.injector, r.phase): r.fault or None for r in results}
    want = {(i, p): code for i, phases in EXPECTED.items() for p, code in phases.items()}
    assert got == want
    for r in results:
        if r.fault:
            category = FAULTS[FaultCode[r.fault]].category
            assert r.category == ("immediate" if category is StopCategory.IMMEDIATE else "ramp")
            assert r.latency_ms is not None and -1 <= r.latency_ms < 600


def test_nothing_unsafe_on_the_bus(results: list[CaseResult]) -> None:
    assert [(r.injector, r.phase) for r in results if r.unsafe_frames] == []
    assert all(r.frames > 100 for r in results)  # torque was flowing when it struck


def test_recovery_only_through_explicit_reset(results: list[CaseResult]) -> None:
    assert [(r.injector, r.phase) for r in results if r.fault and not r.recovered] == []


def test_disturbances_are_counted(results: list[CaseResult]) -> None:
    by = {(r.injector, r.phase): r for r in results}
    assert all(by["babble", p].foreign_frames >= 5000 for p in EVERY_PHASE)
    assert all(by["error_frames", p].bus_events >= 500 for p in EVERY_PHASE)


def test_every_case_is_in_its_log(results: list[CaseResult]) -> None:
    """The campaign's own judgement, read back with handctl's reader (``judge_log``): the
    fault with its stop at the detecting tick and the reset after it, or the disturbance
    counted as the runtime counted it; the file whole, nothing dropped."""
    assert [(r.injector, r.phase) for r in results if not r.logged] == []
    assert all((r.fault_tick is None) == (not r.fault) for r in results)


def test_the_mcap_library_reads_each_fault_at_its_tick(
    hand: HandConfig, results: list[CaseResult], logs: Path
) -> None:
    """Independently of handctl's reader: the mcap library's own reader finds on /events the
    fault code and stop, stamped with the detecting tick's number and time (tick k is at
    (k + 1) periods in lockstep), the supervisor's move into a fault state at that tick, and
    the explicit reset after it; a tolerated babble's foreign frames are all counted there."""
    period_ns = round(hand.bus.period_s * 1e9)
    for r in results:
        case = (r.injector, r.phase)
        events = []
        with (logs / f"{r.injector}-{r.phase}.mcap").open("rb") as handle:
            for _, _, message in make_reader(handle).iter_messages(topics=[ch.EVENTS]):
                events.append((message.log_time, json.loads(message.data)))
        faults = [(t, e) for t, e in events if e["kind"] == "fault"]
        if not r.fault:
            assert faults == [], case
            foreign = sum(
                e["count"]
                for _, e in events
                if e["kind"] == "rejected_frames" and e["name"] == "unexpected_id"
            )
            assert foreign == r.foreign_frames, case
            continue
        log_time, first = faults[0]
        assert (first["name"], first["category"], first["tick"]) == (
            r.fault,
            r.category,
            r.fault_tick,
        ), case
        assert log_time == (first["tick"] + 1) * period_ns, case
        assert any(
            e["kind"] == "state"
            and e["tick"] == r.fault_tick
            and e["name"] in ("fault_ramp", "faulted")
            for _, e in events
        ), case
        resets = [e["tick"] for _, e in events if e["kind"] == "request" and e["name"] == "reset"]
        assert len(resets) == 1 and resets[0] > first["tick"], case


def test_fault_page_shows_this_campaign(results: list[CaseResult]) -> None:
    stored = json.loads((ROOT / "docs" / "fault_campaign.json").read_text())
    assert stored == [asdict(r) for r in results], (
        "docs/fault_campaign.json is stale: run python tools/gen_fault_table.py --campaign"
    )
