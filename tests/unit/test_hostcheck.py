"""The timing check's verdict, judged on recorded stall sequences (never on this machine's
timing), the host's facts and advice, and the attribution of missed ticks."""

from __future__ import annotations

import dataclasses
import json
import math
import os
from pathlib import Path
from typing import Any

import pytest

from handctl.cli import _own_miss_text
from handctl.config import HandConfig
from handctl.errors import ConfigError
from handctl.hostcheck import (
    CATCH_UP_CPU_FACTOR,
    Deadlines,
    LoopWork,
    ProbeRecord,
    advice,
    attribute,
    judge,
    stop_warning,
    work_figures,
)
from handctl.hostfacts import HostFacts, parse_cpu_list, plan_cpus, preemption_model
from handctl.online.misstrace import (
    NOTE_COLLECT,
    NOTE_PHASE,
)

MS = 1_000_000
START = 10_000 * MS
DATA = Path(__file__).resolve().parent.parent / "data"


def record(
    stalls: list[tuple[int, float, float]],
    *,
    seconds: float = 10.0,
    period_ns: int = MS,
    hist: dict[int, int] | None = None,
    **extra: Any,
) -> ProbeRecord:
    """A probe record of ``seconds`` whose stalls are (wake-up index, due ms, length ms),
    times counted from the start; missed ticks follow from the length."""
    wakeups = round(seconds * 1e9 / period_ns)
    rows = []
    for index, due_ms, length_ms in stalls:
        due = START + round(due_ms * MS)
        length = round(length_ms * MS)
        rows.append([index, due, due + length, length // period_ns])
    data = {
        "period_ns": period_ns,
        "start_ns": START,
        "end_ns": START + round(seconds * 1e9),
        "wakeups": wakeups,
        "lateness_hist_us": {str(k): v for k, v in (hist or {20: wakeups}).items()},
        "lateness_max_ns": max([r[2] - r[1] for r in rows], default=20_000),
        "stalls": rows,
        **extra,
    }
    return ProbeRecord.from_json(data, "recorded")


@pytest.fixture
def deadlines(hand: HandConfig) -> Deadlines:
    return Deadlines.of(hand)


def test_the_deadlines_are_the_hand_configs(hand: HandConfig) -> None:
    d = Deadlines.of(hand)
    assert d.period_ns == round(hand.bus.period_s * 1e9)
    assert d.overrun_tolerance_ticks == hand.safety.max_consecutive_misses
    assert d.feedback_timeout_ns == round(hand.safety.feedback_timeout_s * 1e9)


def test_a_quiet_host_passes(deadlines: Deadlines) -> None:
    verdict = judge(record([(400, 400.0, 0.6)]), deadlines)  # half a period late, no miss
    assert verdict.level == "pass", verdict.reasons
    assert verdict.figures["stalls_over_period"] == 0
    assert verdict.figures["lateness_us"] == {"p50": 20.0, "p99": 20.0, "max": 600.0}


def test_a_missed_tick_short_of_the_tolerance_is_marginal(deadlines: Deadlines) -> None:
    verdict = judge(record([(100, 100.0, 1.4), (5000, 5000.0, 2.5)]), deadlines)
    assert verdict.level == "marginal"
    assert verdict.figures["stalls_over_period"] == 2
    assert verdict.figures["stalls_over_overrun_tolerance"] == 0
    assert verdict.figures["loop_overrun_trips"] == 0
    assert "none as long as the overrun tolerance" in verdict.reasons[0]


def test_one_stall_as_long_as_the_tolerance_fails(deadlines: Deadlines) -> None:
    tolerance_ms = deadlines.overrun_tolerance_ticks * deadlines.period_ns / MS
    verdict = judge(record([(100, 100.0, tolerance_ms + 0.2)]), deadlines)
    assert verdict.fails
    assert verdict.figures["stalls_over_overrun_tolerance"] == 1
    assert verdict.figures["loop_overrun_trips"] == 1
    assert "LOOP_OVERRUN" in verdict.reasons[0]


def test_short_stalls_in_consecutive_wakeups_add_up_as_the_supervisor_counts(
    deadlines: Deadlines,
) -> None:
    # Each misses one tick; in consecutive wake-ups the supervisor adds them up to a stop...
    n = deadlines.overrun_tolerance_ticks
    back_to_back = [(100 + i, 100.0 + 2.2 * i, 2.2) for i in range(n)]
    assert judge(record(back_to_back), deadlines).fails
    # ...with an on-time wake-up between them, it starts counting again.
    apart = [(100 + 2 * i, 100.0 + 5 * i, 2.2) for i in range(n)]
    verdict = judge(record(apart), deadlines)
    assert verdict.level == "marginal"
    assert verdict.figures["loop_overrun_trips"] == 0


def test_a_stall_longer_than_the_feedback_timeout_fails(hand: HandConfig) -> None:
    # A hand that tolerates long overruns still fails on its feedback timeout.
    safety = dataclasses.replace(hand.safety, max_consecutive_misses=50, feedback_timeout_s=0.008)
    tolerant = Deadlines.of(dataclasses.replace(hand, safety=safety))
    assert judge(record([(100, 100.0, 7.5)]), tolerant).level == "marginal"
    verdict = judge(record([(100, 100.0, 8.5)]), tolerant)
    assert verdict.fails
    assert verdict.figures["stalls_over_feedback_timeout"] == 1
    assert "feedback timeout (8 ms)" in verdict.reasons[0]


def test_the_same_stalls_are_judged_against_each_hands_deadlines(hand: HandConfig) -> None:
    stalls = [(100, 100.0, 3.4)]
    strict = Deadlines.of(hand)  # 3 ticks: a 3.4 ms stall stops the loop
    loose = Deadlines.of(
        dataclasses.replace(hand, safety=dataclasses.replace(hand.safety, max_consecutive_misses=4))
    )
    assert judge(record(stalls), strict).fails
    assert judge(record(stalls), loose).level == "marginal"


def test_a_late_p99_is_marginal(deadlines: Deadlines) -> None:
    verdict = judge(record([], hist={30: 900, 700: 100}), deadlines)
    assert verdict.level == "marginal"
    assert verdict.figures["lateness_us"]["p99"] == 700.0
    assert "p99" in verdict.reasons[0]


def test_a_record_too_full_to_judge_fails(deadlines: Deadlines) -> None:
    assert judge(record([], stalls_overflow=3), deadlines).fails


def test_a_bad_record_is_refused_with_the_key_expected_and_found() -> None:
    good = record([(1, 1.0, 2.0)]).as_json()
    bad = {**good, "stalls": [[1, 5, 4, 0]]}  # woke before it was due
    with pytest.raises(ConfigError) as info:
        ProbeRecord.from_json({"probe": bad}, "old.json")
    assert info.value.file == "old.json" and info.value.key == "probe.stalls[0]"
    with pytest.raises(ConfigError) as info:
        ProbeRecord.from_json({**good, "period_ns": 0}, "old.json")
    assert info.value.key == "period_ns" and info.value.found == 0
    with pytest.raises(ConfigError) as info:
        ProbeRecord.from_json({**good, "steal_ms": "a lot"}, "old.json")
    assert info.value.key == "steal_ms"
    with pytest.raises(ConfigError) as info:
        ProbeRecord.from_json({**good, "stalls_overflow": -1}, "old.json")
    assert info.value.key == "stalls_overflow"
    with pytest.raises(ConfigError) as info:
        ProbeRecord.from_json([1, 2], "old.json")
    assert "JSON object" in info.value.expected


def test_a_check_report_reads_back_as_the_record_it_holds() -> None:
    original = record([(7, 7.0, 4.0)])
    again = ProbeRecord.from_json({"verdict": "fail", "probe": original.as_json()}, "r.json")
    assert again.stalls == original.stalls
    assert again.lateness_hist_us == original.lateness_hist_us


# -- attribution ----------------------------------------------------------------------------------
def test_a_missed_tick_is_the_hosts_only_if_the_bare_loop_stalled_with_it() -> None:
    host = record([(500, 500.0, 4.0)], period_ns=MS // 2)  # 500..504 ms
    at = START
    loop = [
        (10, at + 501 * MS, at + 503 * MS, 2),  # inside the host's stall
        (20, at + 504 * MS + 500_000, at + 506 * MS, 1),  # a period after its first miss
        (30, at + 800 * MS, at + 802 * MS, 2),  # the host ran fine then
        (40, at + 20_000 * MS, at + 20_002 * MS, 2),  # after the probe stopped
    ]
    own: list[int] = []
    assert attribute(loop, host, MS, own) == {
        "missed_host": 3,
        "missed_host_slow_cpu": 0,
        "missed_rival": 0,
        "missed_host_catch_up": 0,
        "missed_host_off_cpu": 0,
        "missed_handctl": 2,
        "missed_handctl_after_host": 0,
        "missed_unobserved": 2,
    }
    assert own == [30]


def test_a_stop_before_the_bare_loop_ran_says_whose_misses_no_one_judged() -> None:
    """A stop in a run's first ticks (a jog stopped on LOOP_OVERRUN at tick 31) comes before
    the bare loop's first wake-ups: its warning said "0 the host's, 0 handctl's", as if the
    stop had missed no tick."""
    host = record([], period_ns=MS // 2)
    early = [(31, START - 10 * MS, START - 3 * MS, 7)]  # before the probe began
    shares = attribute(early, host, MS)
    assert shares["missed_unobserved"] == 7 and shares["missed_host"] == 0
    verdict = judge(host, Deadlines(MS, 5, 20 * MS))
    text = stop_warning(["LOOP_OVERRUN"], verdict, shares, [])
    assert "0 the host's, 0 handctl's, 7 while the bare loop was not running" in text
    assert "not running" not in stop_warning(
        ["LOOP_OVERRUN"], verdict, dict(shares, missed_unobserved=0), []
    )


def test_a_short_host_stall_does_not_explain_a_long_miss() -> None:
    # Seen on the two-CPU machine: the loop 13 ms late, the bare loop beside it 0.9 ms.
    host = record([(500, 505.0, 0.9), (900, 900.0, 9.0)], period_ns=MS // 2)
    at = START
    loop = [
        (10, at + 500 * MS, at + 513 * MS, 13),  # 0.9 ms of host stall inside: handctl's
        (20, at + 900 * MS, at + 909 * MS + 400_000, 9),  # 9 ms of 9.4: the host's
    ]
    own: list[int] = []
    shares = attribute(loop, host, MS, own)
    assert (shares["missed_host"], shares["missed_handctl"]) == (9, 13)
    assert own == [10]


def test_a_miss_right_after_a_host_stall_is_handctls_catching_up() -> None:
    host = record([(500, 500.0, 4.0)], period_ns=MS // 2)  # 500..504 ms
    at = START
    loop = [
        (10, at + 501 * MS, at + 503 * MS, 2),  # the host's
        (11, at + 505 * MS, at + 506 * MS + 300_000, 1),  # the next tick, catching up
        (12, at + 507 * MS, at + 508 * MS + 100_000, 1),  # and the one after
        (20, at + 515 * MS, at + 516 * MS + 100_000, 1),
    ]  # on-time ticks between
    shares = attribute(loop, host, MS)
    assert (shares["missed_host"], shares["missed_handctl"]) == (2, 3)
    assert shares["missed_handctl_after_host"] == 2


USUAL_NS = 250_000  # a tick's usual thread CPU time in the catch-up cases below


def _catch_up_chain() -> tuple[ProbeRecord, list[tuple[int, int, int, int]]]:
    """A host stall the bare loop shared (wake-up 10), two misses in the next wake-ups that it
    did not share (11, 12), and one long after (20)."""
    host = record([(500, 500.0, 4.0)], period_ns=MS // 2)  # 500..504 ms
    at = START
    return host, [
        (10, at + 501 * MS, at + 503 * MS, 2),
        (11, at + 505 * MS, at + 506 * MS + 300_000, 1),
        (12, at + 507 * MS, at + 508 * MS + 100_000, 1),
        (20, at + 515 * MS, at + 516 * MS + 100_000, 1),
    ]


def test_a_catch_up_tick_of_its_usual_cpu_time_was_held_with_the_host() -> None:
    # Ticks 10 and 11 ran 300 and 450 µs of CPU where a tick usually runs 250: they did not
    # miss on their own work, they were held.
    host, loop = _catch_up_chain()
    work = LoopWork({11: 300_000, 12: 450_000, 20: 100_000}, USUAL_NS)
    own: list[int] = []
    shares = attribute(loop, host, MS, own, work=work)
    assert (shares["missed_host"], shares["missed_host_catch_up"]) == (2, 2)
    assert (shares["missed_handctl"], shares["missed_handctl_after_host"]) == (1, 0)
    assert own == [20]  # not right after the host's: handctl's, however cheap its tick


def test_a_slow_catch_up_tick_stays_handctls_and_ends_the_hosts_chain() -> None:
    host, loop = _catch_up_chain()
    limit = round(CATCH_UP_CPU_FACTOR * USUAL_NS)
    own: list[int] = []
    shares = attribute(loop, host, MS, own, work=LoopWork({11: limit + 1, 12: 1}, USUAL_NS))
    assert (shares["missed_host_catch_up"], shares["missed_handctl"]) == (0, 3)
    assert shares["missed_handctl_after_host"] == 2
    assert own == [11, 12, 20]  # 12 came after handctl's slow 11, not after the host's
    at_limit = attribute(loop, host, MS, work=LoopWork({11: limit}, USUAL_NS))
    assert at_limit["missed_host_catch_up"] == 1


def test_a_catch_up_tick_is_judged_only_when_it_was_measured_against_a_usual() -> None:
    host, loop = _catch_up_chain()
    for work in (LoopWork({}, USUAL_NS), LoopWork({11: 1, 12: 1}, 0), None):
        shares = attribute(loop, host, MS, work=work)
        assert (shares["missed_host_catch_up"], shares["missed_handctl"]) == (0, 3)


def test_a_catch_up_tick_of_a_whole_period_is_never_held() -> None:
    # A tick whose usual cost is most of a period: twice it is more than a period, and a tick
    # that needs a whole period of CPU misses on its own.
    host, loop = _catch_up_chain()
    shares = attribute(loop, host, MS, work=LoopWork({11: MS, 12: 1}, 600_000))
    assert (shares["missed_host_catch_up"], shares["missed_handctl"]) == (0, 3)
    shares = attribute(loop, host, MS, work=LoopWork({11: MS - 1}, 600_000))
    assert (shares["missed_host_catch_up"], shares["missed_handctl"]) == (1, 2)


def _late_start_chain(next_wake_ms: float, missed: int) -> list[tuple[int, int, int, int]]:
    """The host's stall of ``_catch_up_chain`` waking the loop 0.1 ms before its next
    deadline (505 ms), and the wake-up after that catch-up tick missing ``missed`` ticks."""
    at = START
    return [
        (10, at + 501 * MS, at + 504 * MS + 900_000, 3),
        (11, at + 505 * MS, at + round(next_wake_ms * MS), missed),
    ]


def test_a_catch_up_tick_begun_too_late_for_the_next_deadline_missed_it_with_the_host() -> None:
    # The host woke the loop 0.1 ms before the next deadline: a tick of the usual 250 µs could
    # not have met it, so that miss is the host's however long the tick took (here 1.3 ms
    # of CPU, more than a period: its caches were cold, or it was slow on its own).
    host, _ = _catch_up_chain()
    work = LoopWork({11: 1_300_000}, USUAL_NS)
    own: list[int] = []
    shares = attribute(_late_start_chain(506.4, 1), host, MS, own, work=work)
    assert (shares["missed_host"], shares["missed_host_catch_up"]) == (3, 1)
    assert (shares["missed_handctl"], own) == (0, [])
    # Without the loop's measure of its usual tick there is no late start to judge.
    shares = attribute(_late_start_chain(506.4, 1), host, MS, work=LoopWork({}, 0))
    assert (shares["missed_host_catch_up"], shares["missed_handctl"]) == (0, 1)


def test_what_a_late_catch_up_tick_missed_beyond_a_usual_ticks_share_stays_handctls() -> None:
    # The same late start, but the tick ran 3.3 ms: a usual tick would have missed the deadline
    # at 505 ms only; those at 506 and 507 are handctl's.
    host, _ = _catch_up_chain()
    work = LoopWork({11: 3_300_000}, USUAL_NS)
    own: list[int] = []
    shares = attribute(_late_start_chain(508.2, 3), host, MS, own, work=work)
    assert (shares["missed_host_catch_up"], shares["missed_handctl"]) == (1, 2)
    assert (shares["missed_handctl_after_host"], own) == (2, [11])


def test_a_catch_up_tick_begun_in_time_for_a_usual_tick_is_judged_by_its_cpu_time() -> None:
    # Begun 0.3 ms before the deadline, a 250 µs tick would have met it: no late start, and
    # its 1.3 ms of CPU time make the miss handctl's.
    host, _ = _catch_up_chain()
    rows = _late_start_chain(506.4, 1)
    rows[0] = (10, START + 501 * MS, START + 504 * MS + 700_000, 3)
    shares = attribute(rows, host, MS, work=LoopWork({11: 1_300_000}, USUAL_NS))
    assert (shares["missed_host_catch_up"], shares["missed_handctl"]) == (0, 1)
    late = attribute(rows, host, MS, work=LoopWork({11: 1_300_000}, 300_001))
    assert (late["missed_host_catch_up"], late["missed_handctl"]) == (1, 0)


def test_a_late_start_after_handctls_own_miss_is_handctls() -> None:
    # Wake-up 10 late on handctl's own (no host stall near it): wake-up 11's catch-up tick
    # began late because of handctl, so its miss is handctl's, however late it began.
    host = record([(100, 100.0, 4.0)], period_ns=MS // 2)
    shares = attribute(
        _late_start_chain(506.4, 1), host, MS, work=LoopWork({11: 200_000}, USUAL_NS)
    )
    assert (shares["missed_host_catch_up"], shares["missed_handctl"]) == (0, 4)


def test_recorded_slow_catch_up_ticks_of_handctls_stay_handctls() -> None:
    # Real-time runs of the shipped recipe with host stalls injected (a SCHED_FIFO task above
    # the bare loop, 1.6 ms busy on the loop's CPU) and a 2 ms busy loop of thread CPU time
    # in the tick right after each stalled wake-up: every miss that slow catch-up made is
    # handctl's, measured work or not (docs/timing.md, "Catch-up ticks").
    data = json.loads((DATA / "host_catch_up.json").read_text())
    for case in data["cases"]:
        loop = [(r[0], r[1], r[2], r[3]) for r in case["loop_stalls"]]
        host = ProbeRecord.from_json(case["probe"], case["kind"])
        work = LoopWork({int(k): v for k, v in case["work_ns"].items()}, case["usual_cpu_ns"])
        assert work.between_stalls_ns and min(work.between_stalls_ns.values()) > MS
        without = attribute(loop, host, MS)
        shares = attribute(loop, host, MS, work=work)
        assert shares == without and shares["missed_host_catch_up"] == 0
        assert shares["missed_handctl_after_host"] == shares["missed_handctl"] > 0


def test_recorded_busy_catch_up_ticks_are_the_hosts_only_as_far_as_a_late_start() -> None:
    # Real-time runs of the shipped recipe (load 1.4-1.8), 0.6 ms of busy thread CPU time in
    # the tick right after each stalled wake-up past the start (``busy_ticks``: those whose
    # next wake-up was stalled too), the usual measured from wake-up to wake-up; one run
    # (``host_catch_up``) had no busy tick in a catch-up. The CPU rule holds no busy catch-up,
    # and what the rules take from handctl are the deadlines of late starts alone: a busy
    # tick that began in time for the next deadline keeps its misses handctl's.
    data = json.loads((DATA / "host_late_start.json").read_text())
    moved_in_all = own_in_all = 0
    for case in data["cases"]:
        loop = [(r[0], r[1], r[2], r[3]) for r in case["loop_stalls"]]
        host = ProbeRecord.from_json(case["probe"], case["kind"])
        work = LoopWork({int(k): v for k, v in case["work_ns"].items()}, case["usual_cpu_ns"])
        for tick in case["busy_ticks"]:
            assert work.between_stalls_ns[tick + 1] > CATCH_UP_CPU_FACTOR * work.usual_ns
            assert not work.held(tick + 1, MS)
        without = attribute(loop, host, MS)
        shares = attribute(loop, host, MS, work=work)
        moved = without["missed_handctl"] - shares["missed_handctl"]
        assert moved == shares["missed_host_catch_up"] - without["missed_host_catch_up"]
        # catch-up ticks that began less than a usual tick before the next deadline
        woke = {r[0]: r[2] for r in loop}
        late = [r for r in loop if r[0] - 1 in woke and woke[r[0] - 1] + work.usual_ns > r[1]]
        assert moved <= len(late)
        moved_in_all += moved
        own_in_all += shares["missed_handctl"]
    assert moved_in_all > 0 and own_in_all > 0


# -- held off the CPU: the loop thread's own account of the tick before a miss ------------------
USUAL_DELAY_NS = 50_000  # what the bare loop's two preemptions a period usually cost the loop


def _traced(tick: int, *, wall: int, cpu: int, delay: int, voluntary: int = 0) -> dict[str, int]:
    """A ``MissTrace`` row of wake-up ``tick``: the tick before it, from its start to this
    one's, ran ``cpu``, waited ``delay`` runnable, and blocked ``voluntary`` times."""
    return {
        "tick": tick,
        "missed": 1,
        "late_ns": 0,
        "before_late_ns": 30_000,
        "wall_ns": wall,
        "cpu_ns": cpu,
        "stages_ns": cpu * 3 // 4,
        "run_delay_ns": delay,
        "voluntary": voluntary,
        "involuntary": 2,
        "faults": 0,
        "notes": 0,
    }


def _one_miss(late_ms: float) -> list[tuple[int, int, int, int]]:
    """Wake-up 50 came ``late_ms`` after its oldest missed deadline (at 800 ms); the one before
    it (49) was on time, so no catch-up rule applies. The bare loop saw nothing then."""
    due = START + 800 * MS
    missed = int(late_ms)
    return [(50, due, due + round(late_ms * MS), missed)]


def _held_work(row: dict[str, int], realtime: bool = True) -> LoopWork:
    return LoopWork({}, USUAL_NS, {50: row}, USUAL_DELAY_NS, realtime)


def test_a_miss_whose_tick_waited_runnable_for_the_cpu_is_the_hosts() -> None:
    # The tick before ran its usual 250 µs of CPU but waited 1.5 ms runnable while another
    # task ran on its CPU (run_delay; three times the usual for its 2.15 ms is 0.32): the bare
    # loop, which looked at other moments, saw nothing. Without that wait it would have met
    # its deadline.
    loop = _one_miss(1.2)
    row = _traced(50, wall=2_150_000, cpu=USUAL_NS, delay=1_500_000, voluntary=1)
    own: list[int] = []
    shares = attribute(loop, record([]), MS, own, work=_held_work(row))
    assert (shares["missed_host_off_cpu"], shares["missed_handctl"], own) == (1, 0, [])
    # the same figures, the loop not at a real-time priority: anything of the run's own (the
    # simulated hand's process, the recording's writer) may have held it
    shares = attribute(loop, record([]), MS, work=_held_work(row, realtime=False))
    assert (shares["missed_host_off_cpu"], shares["missed_handctl"]) == (0, 1)


def test_a_miss_whose_tick_never_blocked_and_was_off_the_cpu_is_the_hosts() -> None:
    # No voluntary switch: the thread never slept, yet of 3.1 ms it ran 0.4 and waited 0.1
    # runnable: 2.6 ms were taken from under it (a hypervisor's steal is not its CPU time).
    loop = _one_miss(2.2)
    row = _traced(50, wall=3_100_000, cpu=400_000, delay=100_000)
    shares = attribute(loop, record([]), MS, work=_held_work(row))
    assert (shares["missed_host_off_cpu"], shares["missed_handctl"]) == (2, 0)


def test_a_tick_that_blocked_or_ran_long_keeps_its_misses_handctls() -> None:
    # Off the CPU for 2 ms having blocked (a voluntary switch besides none for the timer:
    # the tick overran, so it never waited for it): not the host's to have taken.
    loop = _one_miss(1.3)
    blocked = _traced(50, wall=2_300_000, cpu=250_000, delay=50_000, voluntary=1)
    shares = attribute(loop, record([]), MS, work=_held_work(blocked))
    assert (shares["missed_host_off_cpu"], shares["missed_handctl"]) == (0, 1)
    # Busy: 2.2 ms of its own CPU time, the usual wait for the CPU. Its CPU time is never
    # taken off, however slow.
    busy = _traced(50, wall=2_300_000, cpu=2_200_000, delay=60_000)
    shares = attribute(loop, record([]), MS, work=_held_work(busy))
    assert (shares["missed_host_off_cpu"], shares["missed_handctl"]) == (0, 1)


def test_only_the_deadlines_the_held_time_cost_are_the_hosts() -> None:
    # 3.4 ms late, 3 deadlines missed; the tick before ran 2.3 ms of its own and waited 1.5 ms
    # runnable (0.84 beyond three times the usual for its 4.4 ms): without the wait it would
    # have been 2.56 ms late, two deadlines. One is the host's, two handctl's.
    loop = _one_miss(3.4)
    row = _traced(50, wall=4_400_000, cpu=2_300_000, delay=1_500_000, voluntary=1)
    own: list[int] = []
    shares = attribute(loop, record([]), MS, own, work=_held_work(row))
    assert (shares["missed_host_off_cpu"], shares["missed_handctl"], own) == (1, 2, [50])


def test_a_late_start_and_a_held_tick_together_take_only_what_each_explains() -> None:
    # The catch-up tick of the host's stall began 0.1 ms before the next deadline (a late
    # start: one deadline), ran 1.4 ms of CPU and waited 1.0 ms runnable (0.64 beyond three
    # times the usual for its 2.4 ms); its wake-up came 2.3 ms after that deadline. Without the
    # wait, 1.66 ms late: the one deadline a usual tick begun then would have missed too. So
    # both misses are the host's: one a late start, one held.
    host, _ = _catch_up_chain()
    loop = _late_start_chain(507.3, 2)
    row = _traced(11, wall=2_400_000, cpu=1_400_000, delay=1_000_000)
    work = LoopWork({11: 1_400_000}, USUAL_NS, {11: row}, USUAL_DELAY_NS, True)
    shares = attribute(loop, host, MS, work=work)
    assert (shares["missed_host_catch_up"], shares["missed_host_off_cpu"]) == (1, 1)
    assert shares["missed_handctl"] == 0
    # without the trace: the late start alone
    shares = attribute(loop, host, MS, work=LoopWork({11: 1_400_000}, USUAL_NS))
    assert (shares["missed_host_catch_up"], shares["missed_handctl"]) == (1, 1)


def _recorded_off_cpu() -> list[
    tuple[dict[str, Any], list[tuple[int, int, int, int]], ProbeRecord]
]:
    data = json.loads((DATA / "host_off_cpu.json").read_text())
    return [
        (
            case,
            [(r[0], r[1], r[2], r[3]) for r in case["loop_stalls"]],
            ProbeRecord.from_json(case["probe"], case["run"]),
        )
        for case in data["cases"]
    ]


def _recorded_work(case: dict[str, Any], realtime: bool) -> LoopWork:
    return LoopWork(
        {int(k): v for k, v in case["work_ns"].items()},
        case["usual_cpu_ns"],
        {int(k): v for k, v in case["late_wakeups"].items()},
        case["usual_run_delay_ns"],
        realtime,
    )


def test_recorded_misses_of_a_loop_held_off_its_cpu_are_the_hosts() -> None:
    # Two quiet real-time runs (the loop bench's, a recipe's) in which the bare loop's stalls
    # and hits did not cover four misses of one wake-up and one of another: in the tick before
    # each, the loop's thread, slow in every stage (4.3 and 2.6 times its usual CPU time: the
    # host's slow CPU), was off its CPU without blocking for 2.4 and 0.8 ms and waited
    # runnable for 1.75 and 0.23 ms.
    for case, loop, host in _recorded_off_cpu():
        if case["kind"] != "held":
            continue
        own: list[int] = []
        without = attribute(loop, host, MS, work=_recorded_work(case, realtime=False))
        shares = attribute(loop, host, MS, own, work=_recorded_work(case, realtime=True))
        assert without["missed_handctl"] > 0 and without["missed_host_off_cpu"] == 0
        assert shares["missed_handctl"] == 0 and own == []
        assert shares["missed_host_off_cpu"] == without["missed_handctl"]
        # the other rules' shares as they were
        ours = ("missed_host_off_cpu", "missed_handctl", "missed_handctl_after_host")
        assert {k: v for k, v in shares.items() if k not in ours} == {
            k: v for k, v in without.items() if k not in ours
        }


def test_recorded_busy_and_blocked_ticks_stay_handctls() -> None:
    # The same runs with work of handctl's own injected: 2 ms of busy CPU time, or a 2 ms
    # sleep, in the send stage of every 80th tick. A blocked tick's time off the CPU is never
    # the host's; a busy tick's CPU time never is. One busy tick (2.9 ms of CPU) was also off
    # its CPU 0.6 ms without blocking and missed three deadlines: the one that time cost is
    # the host's, the two its work cost stay handctl's.
    moved_in_all = 0
    for case, loop, host in _recorded_off_cpu():
        if case["kind"] == "held":
            continue
        work = _recorded_work(case, realtime=True)
        without = attribute(loop, host, MS, work=_recorded_work(case, realtime=False))
        shares = attribute(loop, host, MS, work=work)
        moved = without["missed_handctl"] - shares["missed_handctl"]
        assert moved == shares["missed_host_off_cpu"]
        if case["kind"] == "blocked":
            assert moved == 0
        busy = case["busy_ticks"]
        assert len(busy) >= 5
        for tick in busy:  # each busy or blocked tick keeps a miss of its own
            one = [r for r in loop if r[0] in (tick, tick + 1)]
            kept = attribute(one, host, MS, work=work)["missed_handctl"]
            before = attribute(one, host, MS, work=_recorded_work(case, realtime=False))
            assert kept >= min(1, before["missed_handctl"])
        moved_in_all += moved
    assert moved_in_all == 1


# -- the host -------------------------------------------------------------------------------------
@pytest.mark.parametrize(
    ("version", "model"),
    [
        ("#1 SMP PREEMPT_RT Thu Jan 1 00:00:00 UTC 2026", "PREEMPT_RT"),
        ("#1 SMP PREEMPT RT Thu Jan 1", "PREEMPT_RT"),
        ("#1 SMP PREEMPT_DYNAMIC @0", "PREEMPT_DYNAMIC"),
        ("#1 SMP PREEMPT Mon", "PREEMPT"),
        ("#1 SMP Mon Jan 1", "none"),
    ],
)
def test_the_preemption_model_is_read_from_uname(version: str, model: str) -> None:
    assert preemption_model(version) == model


def test_cpu_lists_and_the_cpus_of_loop_and_hand() -> None:
    assert parse_cpu_list("0-2,5\n") == (0, 1, 2, 5)
    assert parse_cpu_list("") == ()
    assert plan_cpus({0, 1, 2, 3}, set()) == (3, 0)
    assert plan_cpus({0, 1, 2, 3}, {1, 2}) == (2, 0)
    assert plan_cpus({4, 6}, {9}) == (6, 4)  # an isolated CPU this process may not use
    assert plan_cpus({0}, set()) == (None, None)


def facts(**changes: Any) -> HostFacts:
    base = HostFacts(
        realtime_kernel=None,
        preemption="PREEMPT_DYNAMIC",
        cmdline_preempt="",
        rtprio_limit=0,
        memlock_limit_kb=8192,
        privileged=False,
        cpus=(0, 1),
        isolated=(),
        governors={0: "powersave", 1: "performance"},
        virtual_machine=True,
    )
    return dataclasses.replace(base, **changes)


def test_the_advice_names_what_it_found() -> None:
    refused = record(
        [],
        scheduler={"policy": "SCHED_OTHER", "priority": 0},
        refused=["locking memory refused (Cannot allocate memory); ..."],
        steal_ms=12.0,
    )
    tips = "\n".join(advice(facts(), refused, realtime=True))
    assert "PREEMPT_RT kernel (found PREEMPT_DYNAMIC; /sys/kernel/realtime absent)" in tips
    assert "preempt=full" in tips
    assert "got SCHED_OTHER; RLIMIT_RTPRIO is 0" in tips
    assert "RLIMIT_MEMLOCK is 8192 KiB" in tips
    assert "isolcpus=1" in tips
    assert "governor powersave" in tips
    assert "12 ms stolen" in tips


def test_a_real_time_host_gets_no_advice() -> None:
    good = facts(
        realtime_kernel=True,
        preemption="PREEMPT_RT",
        isolated=(1,),
        governors={0: "performance", 1: "performance"},
        virtual_machine=False,
        rtprio_limit=-1,
        memlock_limit_kb=-1,
    )
    got = record([], scheduler={"policy": "SCHED_FIFO", "priority": 80})
    assert advice(good, got, realtime=True) == []
    assert "run with --rt" in advice(good, got, realtime=False)[0]


# -- a slow CPU: hiccups and slow pieces of work ------------------------------------------------
REF_NS = 6_000  # the usual wall time of the bare loop's piece of work


def slow_pieces(first_index: int, from_ms: float, count: int, factor: float) -> list[list[int]]:
    """``count`` slow pieces on consecutive wake-ups of a bare loop ticking every 0.5 ms, the
    first at ``from_ms``, each ``factor`` times the usual (as the probe writes them)."""
    rows = []
    for k in range(count):
        start = START + round((from_ms + 0.5 * k) * MS) + 20_000
        wall = round(factor * REF_NS)
        rows.append([first_index + k, start, start + wall, wall])
    return rows


def hiccups(first_index: int, from_ms: float, late_us: list[float]) -> list[list[int]]:
    """Wake-ups of the bare loop late by ``late_us`` each (less than a stall), one every
    0.5 ms from ``from_ms``."""
    rows = []
    for k, late in enumerate(late_us):
        due = START + round((from_ms + 0.5 * k) * MS)
        rows.append([first_index + k, due, due + round(late * 1e3)])
    return rows


def slow_record(
    pieces: list[list[int]],
    late: list[list[int]],
    stalls: tuple[tuple[int, float, float], ...] = (),
) -> ProbeRecord:
    return record(
        list(stalls),
        period_ns=MS // 2,
        hiccup_ns=100_000,
        hiccups=late,
        work={"reference_ns": REF_NS, "slow": pieces, "slow_overflow": 0},
    )


#: A tick of the control loop 2.5 ms late: due at 801 ms, it woke at 803.5 ms, two missed.
BUSY_TICK = (800, START + 801 * MS, START + 803 * MS + 500_000, 2)


def test_a_tick_handctl_made_slow_on_a_cpu_that_was_not_is_handctls() -> None:
    # A busy loop in the tick: the bare loop above it on the same CPU woke on time (but for
    # one 120 µs hiccup, as happens) and its work ran at the usual speed; a slow CPU elsewhere.
    host = slow_record(slow_pieces(600, 300.0, 6, 5.0), hiccups(1603, 801.5, [120]))
    own: list[int] = []
    shares = attribute([BUSY_TICK], host, MS, own)
    assert (shares["missed_handctl"], shares["missed_host_slow_cpu"], shares["missed_host"]) == (
        2,
        0,
        0,
    )
    assert own == [800]


def test_a_slow_cpu_interval_over_a_miss_makes_it_the_hosts() -> None:
    # The work of the bare loop ran at 5x its usual time on every wake-up across the miss.
    host = slow_record(slow_pieces(1598, 799.0, 10, 5.0), [])
    shares = attribute([BUSY_TICK], host, MS)
    assert (shares["missed_host_slow_cpu"], shares["missed_handctl"]) == (2, 0)
    # Each hit stands for one of the bare loop's periods (0.5 ms): two are 1 ms of the 1.5 ms
    # the miss needs, three are enough.
    for count, host_share in ((2, 0), (3, 2)):
        host = slow_record(slow_pieces(1600, 801.0, count, 5.0), [])
        shares = attribute([BUSY_TICK], host, MS)
        assert (shares["missed_host_slow_cpu"], shares["missed_handctl"]) == (
            host_share,
            2 - host_share,
        )
    # A piece that itself took longer than a period counts what it took.
    host = slow_record([[1600, START + 801 * MS, START + 802 * MS + 600_000, 10]], [])
    assert attribute([BUSY_TICK], host, MS)["missed_host_slow_cpu"] == 2


def test_hiccups_short_of_a_stall_add_up_to_a_miss() -> None:
    # The CPU taken away on three wake-ups running, none a stall (>= 0.5 ms late).
    late = hiccups(1598, 800.0, [150, 300, 200])
    shares = attribute([BUSY_TICK], slow_record([], late), MS)
    assert (shares["missed_host_slow_cpu"], shares["missed_handctl"]) == (2, 0)
    # Two of them are not enough for 1.5 ms; a hiccup and a slow piece on one wake-up are one.
    assert attribute([BUSY_TICK], slow_record([], late[:2]), MS)["missed_handctl"] == 2
    both = slow_record(slow_pieces(1599, 800.5, 1, 5.0), late[:2])
    assert attribute([BUSY_TICK], both, MS)["missed_handctl"] == 2


def test_stalls_alone_still_make_a_miss_the_hosts_not_its_slow_cpus() -> None:
    host = slow_record(slow_pieces(1598, 799.0, 10, 5.0), [], stalls=((1600, 801.0, 2.0),))
    shares = attribute([BUSY_TICK], host, MS)
    assert (shares["missed_host"], shares["missed_host_slow_cpu"]) == (2, 0)


def test_consecutive_slow_pieces_are_one_interval_and_the_check_reports_it(
    deadlines: Deadlines,
) -> None:
    pieces = slow_pieces(10, 100.0, 4, 10.0) + slow_pieces(40, 400.0, 1, 4.0)
    host = slow_record(pieces, hiccups(12, 101.0, [200]) + hiccups(80, 900.0, [150]))
    assert len(host.slow_cpu_hits()) == 6  # the hiccup at 101 ms and a piece share a wake-up
    intervals = host.slow_cpu_intervals()
    assert len(intervals) == 3  # 100 ms (pieces and a hiccup), 400 ms, 900 ms
    assert intervals[0][2] == 4 * 9 * REF_NS + 200_000
    d = dataclasses.replace(deadlines, period_ns=MS)
    verdict = judge(host, d)
    f = verdict.figures
    assert (f["slow_cpu_intervals"], f["hiccups"], f["slow_pieces"]) == (3, 2, 5)
    assert f["longest_slow_cpu_ms"] == 1.56  # from 100.02 ms to the 4th piece's end, 101.58
    assert f["slow_cpu_intervals_over_half_period"] == 0  # 0.416 ms lost at most
    assert verdict.level == "pass"
    heavy = slow_record([], hiccups(12, 101.0, [300, 400]))  # 0.7 ms lost in a row
    verdict = judge(heavy, d)
    assert verdict.level == "marginal"
    assert any("slow CPU" in r for r in verdict.reasons)
    # The check's bare loop ticks at the loop's period, which the advice judges by.
    heavy, host = (dataclasses.replace(r, period_ns=MS) for r in (heavy, host))
    tips = "\n".join(advice(facts(), heavy, realtime=True))
    assert "a CPU that does not slow down" in tips
    assert "does not overcommit" in tips
    assert "a CPU that does not slow down" not in "\n".join(advice(facts(), host, True))


# -- slow switches: the bare loop's own passage through the kernel ------------------------------
SWITCH_NS = 25_000  # the usual CPU time of the bare loop's switch (asleep on its timer and back)


def slow_switches(first_index: int, from_ms: float, cpu_us: list[float]) -> list[list[int]]:
    """Wake-ups of the bare loop, one every 0.5 ms from ``from_ms``, each 40 µs late (no
    hiccup) after a switch that cost ``cpu_us`` of its thread CPU time (as the probe writes
    them: from the deadline to the wake-up)."""
    rows = []
    for k, cpu in enumerate(cpu_us):
        due = START + round((from_ms + 0.5 * k) * MS)
        rows.append([first_index + k, due, due + 40_000, round(cpu * 1e3)])
    return rows


def switch_record(switches: list[list[int]], late: list[list[int]] | None = None) -> ProbeRecord:
    return record(
        [],
        period_ns=MS // 2,
        hiccup_ns=100_000,
        hiccups=late or [],
        work={
            "reference_ns": REF_NS,
            "slow": [],
            "slow_overflow": 0,
            "switch_reference_ns": SWITCH_NS,
            "slow_switches": switches,
            "slow_switches_overflow": 0,
        },
    )


def test_slow_switches_add_up_to_a_miss_as_hiccups_do() -> None:
    # The CPU taken away while the bare loop itself went through the kernel, on three
    # wake-ups running, none of them late enough to be a hiccup.
    three = switch_record(slow_switches(1598, 800.0, [120, 90, 150]))
    shares = attribute([BUSY_TICK], three, MS)
    assert (shares["missed_host_slow_cpu"], shares["missed_handctl"]) == (2, 0)
    # Two are not enough for the 1.5 ms the miss needs; a hiccup on the same wake-up as a
    # slow switch is one hit, not two.
    two = slow_switches(1598, 800.0, [120, 90])
    assert attribute([BUSY_TICK], switch_record(two), MS)["missed_handctl"] == 2
    both = switch_record(two, hiccups(1599, 800.5, [150]))
    assert len(both.slow_cpu_hits()) == 2
    assert attribute([BUSY_TICK], both, MS)["missed_handctl"] == 2
    # What a hit saw is the switch's CPU time over the usual: one of 1.6 ms covers the miss.
    long = switch_record(slow_switches(1600, 801.0, [1_600]))
    assert long.slow_cpu_hits()[0][1] == 1_600_000 - SWITCH_NS
    assert attribute([BUSY_TICK], long, MS)["missed_host_slow_cpu"] == 2


def test_slow_switches_are_counted_and_reported_by_the_check(deadlines: Deadlines) -> None:
    host = switch_record(slow_switches(10, 100.0, [100, 200]) + slow_switches(40, 400.0, [90]))
    verdict = judge(host, dataclasses.replace(deadlines, period_ns=MS))
    f = verdict.figures
    assert (f["slow_switches"], f["slow_cpu_intervals"], f["hiccups"]) == (3, 2, 0)
    assert f["slow_cpu_lost_ms"] == round((75 + 175 + 65) / 1e3, 3)
    again = ProbeRecord.from_json(host.as_json(), "again")
    assert again.slow_switches == host.slow_switches
    assert again.switch_reference_ns == SWITCH_NS


def _recorded_cases(kind: str) -> list[tuple[list[tuple[int, int, int, int]], ProbeRecord]]:
    """Recorded real-time runs of the shipped recipe (``--realtime --rt``) on a two-vCPU
    virtual machine: the control loop's missed ticks and the bare loop beside it, around them
    (docs/timing.md, "Slow switches")."""
    data = json.loads((DATA / "host_slow_switches.json").read_text())
    cases = [c for c in data["cases"] if c["kind"] == kind]
    assert cases
    return [
        (
            [(r[0], r[1], r[2], r[3]) for r in c["loop_stalls"]],
            ProbeRecord.from_json(c["probe"], kind),
        )
        for c in cases
    ]


def test_recorded_busy_ticks_of_handctls_stay_handctls() -> None:
    # A 2 ms busy loop of thread CPU time in every 80th tick: every tick it made the loop miss
    # is handctl's, with the slow switches the bare loop recorded meanwhile counted.
    for loop_stalls, host in _recorded_cases("handctl_busy_tick"):
        shares = attribute(loop_stalls, host, MS)
        assert shares["missed_handctl"] == sum(r[3] for r in loop_stalls) > 0
        assert shares["missed_host"] == shares["missed_host_slow_cpu"] == 0


def test_recorded_slow_cpu_misses_are_the_hosts_with_the_slow_switches() -> None:
    # Ticks slowed in every stage at once (3-12x), no page fault, the loop preempted only by
    # the bare loop; the bare loop's hiccups and slow pieces alone did not cover the misses.
    for loop_stalls, host in _recorded_cases("host_slow_cpu"):
        missed = sum(r[3] for r in loop_stalls)
        shares = attribute(loop_stalls, host, MS)
        assert (shares["missed_host_slow_cpu"], shares["missed_handctl"]) == (missed, 0)
        without = dataclasses.replace(host, slow_switches=())
        assert attribute(loop_stalls, without, MS)["missed_handctl"] == missed


def test_a_record_without_work_or_hiccups_has_no_slow_cpu() -> None:
    plain = record([(7, 7.0, 4.0)])
    assert plain.slow_cpu_intervals() == [] and plain.slow_cpu_hits() == []
    again = ProbeRecord.from_json(slow_record(slow_pieces(1, 1.0, 2, 5.0), []).as_json(), "r")
    assert len(again.slow) == 2 and again.work_reference_ns == REF_NS


@pytest.mark.parametrize(
    ("key", "value", "expected"),
    [
        ("work", [1, 2], "a mapping"),
        ("work.reference_ns", -1, "an integer >= 0"),
        ("work.slow[0]", [[1, 10, 5, 0]], "end_ns >= start_ns"),
        ("hiccups[0]", [[1, 10, 5]], "wake_ns >= due_ns"),
        ("work.switch_reference_ns", 1.5, "an integer >= 0"),
        ("work.slow_switches[0]", [[1, 10, 20, -1]], "cpu_ns >= 0"),
    ],
)
def test_a_bad_work_or_hiccup_record_names_the_key(key: str, value: object, expected: str) -> None:
    data = record([]).as_json()
    if key.startswith("work."):
        data["work"][key.split(".")[1].split("[", maxsplit=1)[0]] = value
    else:
        data[key.split("[", maxsplit=1)[0]] = value
    with pytest.raises(ConfigError) as info:
        ProbeRecord.from_json(data, "old.json")
    assert info.value.key == key
    assert expected in info.value.expected


def test_the_work_figures_name_each_own_miss_s_catch_up_tick_beside_the_usual() -> None:
    """A run's (and the loop bench's) figures of its catch-up ticks: the CPU time of the tick
    before each of handctl's own misses where it was measured, in µs, and the usual tick's."""
    work = LoopWork({120: 2_500_000, 480: 310_000}, 300_000)
    figures = work_figures(work, [120, 300, 480])
    assert figures == {
        "usual_tick_cpu_us": 300.0,
        "handctl_catch_up_cpu_us": [[120, 2500.0], [480, 310.0]],
        "handctl_misses": [],
    }
    assert work_figures(None, [120]) == {
        "usual_tick_cpu_us": 0.0,
        "handctl_catch_up_cpu_us": [],
        "handctl_misses": [],
    }


def test_each_own_miss_says_what_the_tick_before_it_did_where_it_was_traced() -> None:
    """The loop's trace of a late wake-up (``MissTrace``) is shown for each of handctl's own
    misses, whatever the wake-up before it: its CPU time against the usual, its wait for the
    CPU against the usual, the time it was off the CPU, what happened in it."""
    traced = {
        "tick": 667,
        "missed": 1,
        "late_ns": 1_300_000,
        "before_late_ns": 40_000,
        "wall_ns": 2_260_000,
        "cpu_ns": 1_900_000,
        "stages_ns": 1_700_000,
        "run_delay_ns": 90_000,
        "voluntary": 0,
        "involuntary": 3,
        "faults": 0,
        "notes": NOTE_COLLECT | NOTE_PHASE,
    }
    work = LoopWork({}, 300_000, {667: traced, 900: {**traced, "tick": 900}}, 45_000)
    figures = work_figures(work, [300, 667])
    assert figures["handctl_misses"] == [
        {
            "tick": 667,
            "missed": 1,
            "late_us": 1300.0,
            "before_woke_late_us": 40.0,
            "wall_us": 2260.0,
            "cpu_us": 1900.0,
            "cpu_over_usual": 6.33,
            "stages_cpu_us": 1700.0,
            "run_delay_us": 90.0,
            "usual_run_delay_us": 45.0,
            "off_cpu_us": 270.0,
            "voluntary_switches": 0,
            "involuntary_switches": 3,
            "page_faults": 0,
            "notes": ["phase", "collection"],
        }
    ]
    # and as a run prints it beside its summary
    assert _own_miss_text(figures["handctl_misses"][0]) == (
        "handctl's miss at tick 667 (1 missed, 1300 µs late): the tick before ran 1900 µs of "
        "CPU (6.33x its usual), waited 90 µs for the CPU (usual 45.0 µs), 270 µs off it, 0 "
        "voluntary switch(es), 0 fault(s); in it: phase, collection"
    )
    # a process stopped for 3 s (SIGSTOP) in whole microseconds, not "3.00164e+06"
    stopped = {**figures["handctl_misses"][0], "late_us": 3001640.0, "off_cpu_us": 3000210.0}
    assert "(1 missed, 3001640 µs late)" in _own_miss_text(stopped)
    assert "3000210 µs off it" in _own_miss_text(stopped)
    # a tick never off the CPU whose CPU time and run_delay (two clocks' counts) add up to a
    # microsecond past its wall time: off it for 0 µs, not -1
    busy = {**traced, "cpu_ns": 2_160_500, "run_delay_ns": 100_300}
    shown = work_figures(LoopWork({}, 300_000, {667: busy}, 45_000), [667])["handctl_misses"][0]
    assert shown["off_cpu_us"] == 0.0
    assert "waited 100 µs for the CPU (usual 45.0 µs), 0 µs off it," in _own_miss_text(shown)
    # a usual wait not measured yet is left out, not said as "usual None"
    unknown = {**figures["handctl_misses"][0], "usual_run_delay_us": None}
    assert "waited 90 µs for the CPU, 270 µs off it," in _own_miss_text(unknown)


@pytest.mark.parametrize(
    ("change", "key", "found"),
    [
        # str.isdigit() took these, and int() refused them in a traceback (exit 1)
        ({"lateness_hist_us": {"²": 3}}, "lateness_hist_us", "²"),
        ({"lateness_hist_us": {"١٢": 3}}, "lateness_hist_us", "١٢"),
        ({"lateness_hist_us": {"9" * 30: 3}}, "lateness_hist_us", "9" * 30),
        ({"lateness_hist_us": {"20": 10**30}}, "lateness_hist_us", None),
        ({"lateness_hist_us": {"20": True}}, "lateness_hist_us.20", True),
        ({"end_ns": START - 1}, "end_ns", START - 1),
        ({"wakeups": 0}, "wakeups", 0),
        ({"steal_ms": math.inf}, "steal_ms", math.inf),
    ],
)
def test_a_record_that_no_probe_writes_is_refused(
    change: dict[str, Any], key: str, found: object
) -> None:
    """An injected sequence is what a probe wrote; nonsense passed without a word or ended in
    a traceback."""
    good = record([(1, 1.0, 2.0)]).as_json()
    with pytest.raises(ConfigError) as info:
        ProbeRecord.from_json({**good, **change}, "old.json")
    assert info.value.key == key
    if found is not None:
        assert info.value.found == found


def test_a_bare_loop_is_judged_beside_the_loop_only_when_above_it() -> None:
    """The attribution rests on the bare loop preempting a real-time loop; at or below its
    priority, or refused its own, it is void (``below_the_loop``)."""
    from handctl.hostcheck import below_the_loop

    work = LoopWork({}, USUAL_NS, realtime=True, priority=80)
    above = record([], scheduler={"policy": "SCHED_FIFO", "priority": 81})
    assert below_the_loop(above, work) == ""
    assert below_the_loop(above, None) == ""  # nothing measured of the loop: no claim
    refused = "SCHED_FIFO priority 81 refused ([Errno 1] Operation not permitted)"
    other = record([], scheduler={"policy": "SCHED_OTHER", "priority": 0}, refused=[refused])
    said = below_the_loop(other, work)
    assert said.startswith("the bare timer loop beside the run ran at SCHED_OTHER 0, not above")
    assert refused in said
    level = record([], scheduler={"policy": "SCHED_FIFO", "priority": 80})
    assert below_the_loop(level, work) != ""
    # a loop at the ordinary scheduler shares it with the bare loop: as documented, judged
    assert below_the_loop(other, LoopWork({}, USUAL_NS)) == ""


def test_the_check_asks_for_the_priority_of_the_bare_loop_beside_a_run() -> None:
    """The check's own bare loop runs at the loop's 80; a run's asks for 81. A host that
    refuses 81 passed the check and voided every run's attribution (``beside_refused``)."""
    from handctl.hostcheck import BESIDE_PRIORITY, beside_refused

    assert BESIDE_PRIORITY == 81
    said = beside_refused(100)  # beyond SCHED_FIFO's 1-99: refused on any host
    assert said.startswith("SCHED_FIFO priority 100 refused (") and "one above the loop" in said
    before = os.sched_getscheduler(0)
    beside_refused(1)
    assert os.sched_getscheduler(0) == before  # asked by a thread of its own


def test_a_rival_is_among_the_reasons_of_the_check_in_text_and_json(
    deadlines: Deadlines,
) -> None:
    """A check MARGINAL because of a real-time rival had no 'because' line (the text said the
    measured record's reasons only), and a measured MARGINAL lost the rival from the JSON's
    reasons too (``worse`` kept the first verdict on a tie)."""
    from handctl.hostcheck import CheckReport, rival_verdict, worse
    from handctl.rivals import Rival

    rival = Rival(7, 7, "spin", "SCHED_FIFO", 85, (1,), 0)
    for stalls in ([], [(100, 50.0, 1.5)]):  # a quiet host, then a marginal one
        measured = record(stalls, scheduler={"policy": "SCHED_FIFO", "priority": 80})
        judged = judge(measured, deadlines)
        verdict = worse(judged, rival_verdict([rival], judged.figures))
        report = CheckReport(verdict, ((measured, judged),), facts(), (), True)
        assert report.verdict.level == "marginal"
        said = "1 real-time task(s) at the loop's priority or above may run on its CPU: spin"
        assert any(said in r for r in report.as_json()["reasons"])
        because = [line for line in report.text().splitlines() if line.startswith("  because")]
        assert any(said in line for line in because), report.text()
        assert len(because) == len(set(because)) == len(verdict.reasons)


def test_a_wake_up_seen_late_and_slow_to_switch_loses_its_time_once(
    deadlines: Deadlines,
) -> None:
    """A hiccup and a slow switch of one wake-up look at the same interval, its deadline to
    the wake-up: summed, a wake-up 0.3 ms late whose switch cost 0.3 ms over the usual "lost"
    0.6 ms, more than the interval's wall time, and a PASS host read MARGINAL. The larger of
    the two; a slow piece of work after the wake-up is a time of its own, and adds."""
    due = START + 500 * MS
    work = {"reference_ns": 6_000, "switch_reference_ns": 30_000, "slow": []}
    both = record(
        [],
        hiccup_ns=100_000,
        hiccups=[[500, due, due + 300_000]],
        work={**work, "slow_switches": [[500, due, due + 300_000, 330_000]]},
    )
    assert both.slow_cpu_intervals() == [(due, due + 300_000, 300_000)]
    verdict = judge(both, deadlines)
    assert verdict.figures["slow_cpu_lost_ms"] == 0.3
    assert verdict.level == "pass", verdict.reasons
    piece = [500, due + 310_000, due + 420_000, 110_000]  # 104 µs over its usual 6 µs
    with_piece = record(
        [],
        hiccup_ns=100_000,
        hiccups=[[500, due, due + 300_000]],
        work={**work, "slow": [piece], "slow_switches": [[500, due, due + 300_000, 130_000]]},
    )
    assert with_piece.slow_cpu_intervals() == [(due, due + 420_000, 300_000 + 104_000)]


def test_a_verdict_on_a_small_share_of_a_run_is_not_called_one() -> None:
    """A run stopped at tick 134 said "the bare timer loop beside it says the host was PASS"
    on 14 ms of bare loop (27 wake-ups of a 145-tick run): how much of the run it saw is said,
    and too little of it is no verdict (``observed_text``)."""
    from handctl.hostcheck import MIN_OBSERVED_SHARE, observed_text

    host = record([], seconds=0.014, period_ns=MS // 2)
    verdict = judge(host, Deadlines(MS, 5, 20 * MS))
    short = observed_text(verdict.figures["seconds"], 0.145)
    assert short == (
        "the bare timer loop beside the run ran 0.014 s of the run's 0.145 s (10%): too "
        "little to say what the host was"
    )
    shares = attribute([], host, MS)
    text = stop_warning(["LOOP_OVERRUN"], verdict, shares, [], short=short)
    assert "says the host was" not in text
    assert f"{short} (it saw it PASS)" in text
    assert observed_text(MIN_OBSERVED_SHARE * 10.0, 10.0) == ""  # half the run or more
    assert observed_text(0.014, None) == ""  # nothing to compare with


def test_sched_fifo_refused_with_cap_sys_nice_names_the_cgroups_budget(tmp_path: Path) -> None:
    """In a cgroup v1 cpu group with cpu.rt_runtime_us = 0, SCHED_FIFO is refused even with
    CAP_SYS_NICE, and the advice said to grant it with 'ulimit -r' or CAP_SYS_NICE, which
    the process had: it names the group's real-time budget, as found from /proc/self/cgroup."""
    from handctl.hostfacts import rt_runtime

    cgroups = tmp_path / "cgroup"
    cgroups.write_text("12:pids:/user.slice\n4:cpu,cpuacct:/batch/rt0\n0::/user.slice\n")
    group = tmp_path / "fs" / "cpu,cpuacct" / "batch" / "rt0"
    group.mkdir(parents=True)
    (group / "cpu.rt_runtime_us").write_text("0\n")
    found = rt_runtime(cgroups, tmp_path / "fs")
    assert found == (str(group / "cpu.rt_runtime_us"), 0)
    assert rt_runtime(tmp_path / "absent", tmp_path / "fs") is None  # cgroup v2, or none

    refused = record([], scheduler={"policy": "SCHED_OTHER", "priority": 0})
    tips = "\n".join(advice(facts(privileged=True, rt_runtime=found), refused, realtime=True))
    assert f"{group / 'cpu.rt_runtime_us'} is 0 µs" in tips
    assert "with CAP_SYS_NICE" in tips and "ulimit -r" not in tips
    # without the privilege the limits are what to change, as before
    tips = "\n".join(advice(facts(rt_runtime=found), refused, realtime=True))
    assert "ulimit -r" in tips and "cpu.rt_runtime_us" not in tips
