"""Issue-level check of the fault campaign: every injector in every kind of phase is caught
(or harmlessly absorbed), takes its stop, puts no unsafe frame on the wire, is in the MCAP log
at the tick it was detected, and comes back only through an explicit reset; docs/faults.md
shows exactly these results.

Every test runs twice over: on CI's cases (``[ci]``: one case of every injector, the kinds of
phase taken in turn) and, as a campaign, on the full matrix (``[full]``: every injector in
every kind of phase, 80 cases, several minutes):
``python -m pytest -m campaign tests/integration/test_fault_matrix.py``."""

from __future__ import annotations

import json
import shutil
from collections.abc import Callable, Iterator
from dataclasses import asdict
from pathlib import Path

import pytest
from mcap.reader import make_reader

from handctl.config import HandConfig
from handctl.executor import open_pool
from handctl.harness.campaign import (
    CASES,
    PHASES,
    CaseResult,
    CaseTask,
    run_case_task,
)
from handctl.online.safety.faults import FAULTS, FaultCode, StopCategory
from handctl.portable import portable_hand
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
    # one counter with other contents (the readings move): a second sender, as far as the
    # host can tell, at the first repeat
    "counter_repeat": dict.fromkeys(EVERY_PHASE, "NODE_CONTRADICTION"),
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


def ci_cases() -> list[tuple[str, str]]:
    """One case of every injector, CI's share of the matrix: the kinds of phase are taken in
    turn, so each is struck by several injectors, and an injector that a phase tolerates
    where another shows its fault (a torque fault while idle) is struck where it shows.

    What the full matrix adds is the same injector in the other kinds of phase: the runtime's
    detection does not depend on the phase, and the campaign runs the rest."""
    cases = []
    for number, injector in enumerate(CASES):
        turn = number % len(EVERY_PHASE)
        order = EVERY_PHASE[turn:] + EVERY_PHASE[:turn]
        shows = [p for p in order if EXPECTED[injector][p] is not None]
        cases.append((injector, (shows or order)[0]))
    return cases


def every_case() -> list[tuple[str, str]]:
    return [(injector, phase) for injector in CASES for phase in EVERY_PHASE]


@pytest.fixture(
    scope="module",
    params=[
        pytest.param(ci_cases, id="ci"),
        pytest.param(every_case, id="full", marks=pytest.mark.campaign),
    ],
)
def cases(request: pytest.FixtureRequest) -> list[tuple[str, str]]:
    """The (injector, phase) cases the tests judge: CI's share, or the full matrix."""
    choose: Callable[[], list[tuple[str, str]]] = request.param
    return choose()


@pytest.fixture(scope="module")
def logs(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Path]:
    """Where the campaign keeps each case's MCAP log (about 50 MB in all: removed after)."""
    directory = tmp_path_factory.mktemp("campaign-logs")
    yield directory
    shutil.rmtree(directory, ignore_errors=True)


@pytest.fixture(scope="module")
def results(hand: HandConfig, cases: list[tuple[str, str]], logs: Path) -> list[CaseResult]:
    # Every case is a lockstep run, so it gives the same result in a worker process as here
    # (test_campaign_pool.py holds that); two workers halve the suite's longest set-up.
    # The tasks are run_campaign's own, of the chosen cases only.
    tasks = [CaseTask(portable_hand(hand), i, p, keep_log=True) for i, p in cases]
    with open_pool(2) as pool:
        done = pool.map(run_case_task, tasks)
    for r, data in done:
        assert data is not None
        (logs / f"{r.injector}-{r.phase}.mcap").write_bytes(data)
    return [r for r, _ in done]


def test_every_injector_has_an_expectation() -> None:
    assert set(EXPECTED) == set(CASES)


def test_ci_strikes_every_injector_and_every_kind_of_phase() -> None:
    chosen = ci_cases()
    assert [i for i, _ in chosen] == list(CASES)
    assert {p for _, p in chosen} == set(EVERY_PHASE)
    # a case CI keeps shows the injector's fault wherever any phase does
    assert all(EXPECTED[i][p] is not None or not any(EXPECTED[i].values()) for i, p in chosen)


def test_detection_and_stop(cases: list[tuple[str, str]], results: list[CaseResult]) -> None:
    got = {(r.injector, r.phase): r.fault or None for r in results}
    want = {(i, p): EXPECTED[i][p] for i, p in cases}
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
    babble = [r.foreign_frames for r in results if r.injector == "babble"]
    errors = [r.bus_events for r in results if r.injector == "error_frames"]
    assert babble and all(n >= 5000 for n in babble)
    assert errors and all(n >= 500 for n in errors)


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


def test_fault_page_shows_this_campaign(
    cases: list[tuple[str, str]], results: list[CaseResult]
) -> None:
    """The page's results are these, case for case (CI's share: those of its cases)."""
    stored = json.loads((ROOT / "docs" / "fault_campaign.json").read_text())
    shown = [r for r in stored if (r["injector"], r["phase"]) in set(cases)]
    assert len(stored) == len(every_case())
    assert shown == [asdict(r) for r in results], (
        "docs/fault_campaign.json is stale: run python tools/gen_fault_table.py --campaign"
    )
