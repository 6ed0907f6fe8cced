"""Can this host hold this hand's deadlines? The timing check, its verdict, and the host's share
of a run's missed ticks.

The measurement is a bare timer loop (``handctl.hostprobe``) in a process of its own, at the
control loop's period, with the scheduling ``--rt`` asks for. What it records is judged against
the hand config's deadlines (``judge``): a stall of the bare loop is a stall any loop on this
host would have had. The verdict says what the host is (``handctl.hostfacts``: kernel, limits,
CPUs, frequency scaling) and what would help (``advice``).

The same probe runs beside every real-time run, on the control loop's CPU one priority step
above it, so that each missed tick of the run can be attributed: to the host when the probe
stalled at the same time, to handctl when it did not (``attribute``).

A recorded probe sequence (the ``probe`` of ``handctl check --timing --json``) can be judged
with the measurement through the environment variable ``HANDCTL_TIMING_INJECT``; the verdict
is then the worse of the two, so the seam can make a host fail a check but never pass one
(docs/timing.md).
"""

from __future__ import annotations

import json
import math
import os
import re
import threading
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

from handctl.config import HandConfig, SafetyConfig
from handctl.errors import ConfigError, Description, HandctlError
from handctl.hostfacts import HostFacts, gather_facts, ordinary_scheduling, plan_cpus
from handctl.online.clock import LOOP_PRIORITY, Hygiene, StallLog
from handctl.online.misstrace import describe, held_off_ns
from handctl.online.safety.faults import Fault, FaultCode
from handctl.online.safety.watchdog import TickWatch
from handctl.online.tickstats import HIST_RANGE_US
from handctl.parent_death import JsonHelper
from handctl.rivals import Rival, RivalRecord, RivalWatch, find_rivals

#: A catch-up tick (the one between a stalled wake-up of the host's and another stalled
#: wake-up right after it) that took at most this many times the run's usual tick CPU time,
#: both from a wake-up to the next, was held, not slow: its miss is the host's
#: (``attribute``). A catch-up drains the frames of the periods slept through, and after a
#: host stall it runs on caches the host's other work evicted: a tick whose caches were
#: flushed down to the last level took 2.6x its usual stages at the median (docs/timing.md,
#: "Catch-up ticks").
CATCH_UP_CPU_FACTOR = 2.0
#: Seconds of the check a run on a real bus makes before it opens the bus.
PRECHECK_S = 1.5
#: The environment variable that names a recorded probe sequence to judge with the measurement.
INJECT_ENV = "HANDCTL_TIMING_INJECT"
#: a lateness bin of a probe record: whole µs in ASCII digits
_BIN = re.compile(r"[0-9]{1,9}", re.ASCII)
#: Verdicts, best first.
LEVELS = ("pass", "marginal", "fail")
#: Share of the loop's period: a bare loop's wake-up this late, short of a stall, is a hiccup
#: (the CPU taken away for a while). The bare loop's median lateness is 30-80 µs on the hosts
#: measured (docs/timing.md), so at 1 kHz this is well above the usual.
HICCUP_SHARE = 0.1
#: A host whose bare loop is late by more than this share of the period at p99 is marginal:
#: the control loop's own tick (about 100 µs) must fit in what is left.
P99_SHARE = 0.5
_PROBE_START_S = 30.0  # generous: the probe imports handctl on a loaded machine


class HostTimingError(HandctlError):
    """The host failed the timing check before a run on a real bus; nothing was sent."""


@dataclass(frozen=True)
class Deadlines:
    """The deadlines of one hand, from its config."""

    period_ns: int
    overrun_tolerance_ticks: int  # safety.max_consecutive_misses: LOOP_OVERRUN at this many
    feedback_timeout_ns: int  # safety.feedback_timeout_s

    @classmethod
    def of(cls, hand: HandConfig) -> Deadlines:
        return cls(
            round(hand.bus.period_s * 1e9),
            hand.safety.max_consecutive_misses,
            round(hand.safety.feedback_timeout_s * 1e9),
        )


@dataclass(frozen=True)
class ProbeRecord:
    """What one run of the bare loop saw (the JSON ``handctl.hostprobe`` writes)."""

    period_ns: int
    start_ns: int
    end_ns: int
    wakeups: int
    lateness_hist_us: dict[int, int]
    lateness_max_ns: int
    stalls: tuple[tuple[int, int, int, int], ...]  # (wake-up index, due_ns, wake_ns, missed)
    stalls_overflow: int = 0
    steal_ms: float = 0.0
    scheduler: dict[str, Any] = field(default_factory=dict)
    refused: tuple[str, ...] = ()
    source: str = "measured"
    #: The piece of work on each wake-up (``hostprobe.WorkLog``): its usual wall time (0: the
    #: probe did none), and the slow pieces as (wake-up index, start_ns, end_ns, cpu_ns).
    work_reference_ns: int = 0
    slow: tuple[tuple[int, int, int, int], ...] = ()
    slow_overflow: int = 0
    #: Wake-ups late by ``hiccup_ns`` or more but no stall, as (wake-up index, due_ns, wake_ns)
    hiccup_ns: int = 0
    hiccups: tuple[tuple[int, int, int], ...] = ()
    hiccups_overflow: int = 0
    #: The bare loop's passage through the kernel between two pieces of work (asleep on its
    #: timer, switched out and in): its usual thread CPU time, and the wake-ups on which it
    #: took ``--slow-factor`` times that or more, as (wake-up index, due_ns, wake_ns, cpu_ns).
    switch_reference_ns: int = 0
    slow_switches: tuple[tuple[int, int, int, int], ...] = ()
    slow_switches_overflow: int = 0

    def _hits(self) -> list[tuple[int, int, int, int]]:
        """The wake-ups on which the bare loop found its CPU taken away or slow, in order, as
        ``(index, start_ns, end_ns, seen_ns)``: a hiccup or a slow switch from its deadline to
        its wake-up, a slow piece of work over its run, a wake-up with more than one of them
        one hit over all; seen is what it saw lost (the hiccup's lateness, the switch's CPU
        time and the piece's time over the usual).

        A hiccup and a slow switch of one wake-up are two looks at the same interval, from its
        deadline to the wake-up: what they saw is the larger, not the sum (summed, a wake-up
        0.3 ms late whose switch cost 0.3 ms more than usual "lost" 0.6 ms, more than its
        interval's wall time). The piece of work runs after the wake-up, a time of its own."""
        woke: dict[int, tuple[int, int, int]] = {}
        for index, due, wake in self.hiccups:
            woke[index] = (due, wake, wake - due)
        for index, due, wake, cpu in self.slow_switches:
            at, until, seen = woke.get(index, (due, wake, 0))
            woke[index] = (at, until, max(seen, cpu - self.switch_reference_ns))
        hits: dict[int, tuple[int, int, int]] = {}
        for index, (due, wake, seen) in woke.items():
            _add_hit(hits, index, due, wake, max(0, seen))
        for index, start, end, _ in self.slow:
            _add_hit(hits, index, start, end, max(0, end - start - self.work_reference_ns))
        return [(index, *hits[index]) for index in sorted(hits)]

    def slow_cpu_intervals(self) -> list[tuple[int, int, int]]:
        """Where the CPU was slow for a loop, as ``(start_ns, end_ns, lost_ns)``: hits on
        consecutive wake-ups are one interval, from the first's start to the last's end, and
        lost is what they saw lost."""
        out: list[tuple[int, int, int]] = []
        last = -2  # no wake-up yet: wake-up indices start at 0
        for index, start, end, seen in self._hits():
            if index - last <= 1:
                s0, e0, l0 = out[-1]
                out[-1] = (s0, max(e0, end), l0 + seen)
            else:
                out.append((start, end, seen))
            last = index
        return out

    def slow_cpu_hits(self) -> list[tuple[int, int]]:
        """The bare loop's hits as ``(time_ns, seen_ns)``: when (a hiccup's deadline, a slow
        piece's start) and how long it saw lost."""
        return sorted((start, seen) for _, start, _, seen in self._hits())

    @classmethod
    def from_json(cls, data: object, source: str) -> ProbeRecord:
        """Read a probe's output, or a check report that holds one under ``probe``; a file
        that is neither gets a ConfigError naming the key, what was expected and found."""
        if isinstance(data, dict) and isinstance(data.get("probe"), dict):
            data, prefix = data["probe"], "probe."
        else:
            prefix = ""
        if not isinstance(data, dict):
            raise ConfigError(
                source,
                "",
                "a JSON object (hostprobe output or a check report)",
                type(data).__name__,
            )

        def integer(key: str, minimum: int = 0, default: int | None = None) -> int:
            value = data.get(key, default)
            if not isinstance(value, int) or isinstance(value, bool) or value < minimum:
                raise ConfigError(source, prefix + key, f"an integer >= {minimum}", value)
            return value

        steal = data.get("steal_ms", 0.0)
        if (
            not isinstance(steal, int | float)
            or isinstance(steal, bool)
            or not 0 <= steal < math.inf
        ):
            raise ConfigError(source, prefix + "steal_ms", "a finite number of ms >= 0", steal)
        scheduler = data.get("scheduler", {})
        refused = data.get("refused", [])
        if not isinstance(scheduler, dict):
            raise ConfigError(source, prefix + "scheduler", "a mapping", scheduler)
        if not isinstance(refused, list) or not all(isinstance(r, str) for r in refused):
            raise ConfigError(source, prefix + "refused", "a list of strings", refused)

        period = integer("period_ns", 1)
        start, end = integer("start_ns"), integer("end_ns")
        if end < start:
            raise ConfigError(source, prefix + "end_ns", f"a time >= start_ns ({start})", end)
        wakeups = integer("wakeups", 1)
        hist_raw = data.get("lateness_hist_us")
        hist_key = prefix + "lateness_hist_us"
        if not isinstance(hist_raw, dict):
            raise ConfigError(source, hist_key, "a mapping of µs bins to counts", hist_raw)
        for k, v in hist_raw.items():
            # ASCII digits, in the probe's range: str.isdigit() took '²', which int() refused
            # in a traceback
            if _BIN.fullmatch(k) is None or int(k) > HIST_RANGE_US:
                raise ConfigError(
                    source, hist_key, f"bins of whole µs from 0 to {HIST_RANGE_US}", k
                )
            if not isinstance(v, int) or isinstance(v, bool) or v < 0:
                raise ConfigError(source, f"{hist_key}.{k}", "a count >= 0", v)
        counted = sum(hist_raw.values())
        if counted > wakeups:  # the probe bins every wake-up once (a record may hold fewer)
            raise ConfigError(
                source,
                hist_key,
                f"counts that add up to at most the wakeups ({wakeups})",
                Description(f"counts that add up to {counted}"),
            )
        stalls = [
            (r[0], r[1], r[2], r[3])
            for r in _interval_rows(
                data.get("stalls"),
                source,
                prefix + "stalls",
                ("index", "due_ns", "wake_ns", "missed"),
            )
        ]
        work = _work(data.get("work"), source, prefix + "work")
        hiccups = [
            (r[0], r[1], r[2])
            for r in _interval_rows(
                data.get("hiccups", []), source, prefix + "hiccups", ("index", "due_ns", "wake_ns")
            )
        ]
        return cls(
            period_ns=period,
            start_ns=start,
            end_ns=end,
            wakeups=wakeups,
            lateness_hist_us={int(k): v for k, v in hist_raw.items()},
            lateness_max_ns=integer("lateness_max_ns"),
            stalls=tuple(stalls),
            stalls_overflow=integer("stalls_overflow", default=0),
            steal_ms=float(steal),
            scheduler=dict(scheduler),
            refused=tuple(refused),
            source=source,
            work_reference_ns=work.reference_ns,
            slow=work.slow,
            slow_overflow=work.slow_overflow,
            switch_reference_ns=work.switch_reference_ns,
            slow_switches=work.slow_switches,
            slow_switches_overflow=work.slow_switches_overflow,
            hiccup_ns=integer("hiccup_ns", default=0),
            hiccups=tuple(hiccups),
            hiccups_overflow=integer("hiccups_overflow", default=0),
        )

    def as_json(self) -> dict[str, Any]:
        return {
            "period_ns": self.period_ns,
            "start_ns": self.start_ns,
            "end_ns": self.end_ns,
            "wakeups": self.wakeups,
            "lateness_hist_us": {str(k): v for k, v in sorted(self.lateness_hist_us.items())},
            "lateness_max_ns": self.lateness_max_ns,
            "stalls": [list(s) for s in self.stalls],
            "stalls_overflow": self.stalls_overflow,
            "steal_ms": self.steal_ms,
            "scheduler": self.scheduler,
            "refused": list(self.refused),
            "source": self.source,
            "hiccup_ns": self.hiccup_ns,
            "hiccups": [list(h) for h in self.hiccups],
            "hiccups_overflow": self.hiccups_overflow,
            "work": {
                "reference_ns": self.work_reference_ns,
                "slow": [list(s) for s in self.slow],
                "slow_overflow": self.slow_overflow,
                "switch_reference_ns": self.switch_reference_ns,
                "slow_switches": [list(s) for s in self.slow_switches],
                "slow_switches_overflow": self.slow_switches_overflow,
            },
        }

    def lateness_us(self, q: float) -> float:
        """The q-th percentile (0..100) of the wake-up lateness, µs (1 µs bins)."""
        total = sum(self.lateness_hist_us.values())
        if total == 0:
            return 0.0
        rank = max(1, -(-q * total // 100))
        seen = 0
        for b in sorted(self.lateness_hist_us):
            seen += self.lateness_hist_us[b]
            if seen >= rank:
                return float(b)
        return float(HIST_RANGE_US)


def _interval_rows(raw: object, source: str, key: str, fields: tuple[str, ...]) -> list[list[int]]:
    """A probe record's list of intervals: rows of ``fields`` integers, the third (an end)
    not before the second (its start) and a fourth, if any, not negative; a ``ConfigError``
    naming the row otherwise. One check for the stalls, the hiccups and the slow pieces."""
    shape = f"[{', '.join(fields)}]"
    if not isinstance(raw, list):
        raise ConfigError(source, key, f"a list of {shape}", raw)
    rule = f"{shape} with {fields[2]} >= {fields[1]}" + (
        f" and {fields[3]} >= 0" if len(fields) > 3 else ""
    )
    for i, row in enumerate(raw):
        if (
            not isinstance(row, list)
            or len(row) != len(fields)
            or not all(isinstance(v, int) and not isinstance(v, bool) for v in row)
            or row[2] < row[1]
            or any(v < 0 for v in row[3:])
        ):
            raise ConfigError(source, f"{key}[{i}]", rule, row)
    return raw


def _add_hit(
    hits: dict[int, tuple[int, int, int]], index: int, start: int, end: int, seen: int
) -> None:
    """One more sign of a slow CPU on wake-up ``index``: the wake-up's hit spans both, and
    saw what both saw."""
    at, until, before = hits.get(index, (start, end, 0))
    hits[index] = (min(at, start), max(until, end), before + seen)


@dataclass(frozen=True)
class _WorkRecord:
    """The probe's ``work`` record: the piece of work's usual wall time and its slow pieces,
    the switch's usual CPU time and its slow switches, and how many of each were not kept."""

    reference_ns: int = 0
    slow: tuple[tuple[int, int, int, int], ...] = ()
    slow_overflow: int = 0
    switch_reference_ns: int = 0
    slow_switches: tuple[tuple[int, int, int, int], ...] = ()
    slow_switches_overflow: int = 0


def _work(raw: object, source: str, key: str) -> _WorkRecord:
    """The probe's ``work`` record. A record without one (a probe that timed no work, or an
    older one) has no slow CPU intervals; one without switches (older) has no slow switches."""
    if raw is None:
        return _WorkRecord()
    if not isinstance(raw, dict):
        raise ConfigError(
            source,
            key,
            "a mapping (reference_ns, slow, slow_overflow, switch_reference_ns, "
            "slow_switches, slow_switches_overflow)",
            raw,
        )
    values = {}
    for name in (
        "reference_ns",
        "slow_overflow",
        "switch_reference_ns",
        "slow_switches_overflow",
    ):
        value = raw.get(name, 0)
        if not isinstance(value, int) or isinstance(value, bool) or value < 0:
            raise ConfigError(source, f"{key}.{name}", "an integer >= 0", value)
        values[name] = value
    slow = tuple(
        (r[0], r[1], r[2], r[3])
        for r in _interval_rows(
            raw.get("slow", []), source, f"{key}.slow", ("index", "start_ns", "end_ns", "cpu_ns")
        )
    )
    switches = tuple(
        (r[0], r[1], r[2], r[3])
        for r in _interval_rows(
            raw.get("slow_switches", []),
            source,
            f"{key}.slow_switches",
            ("index", "due_ns", "wake_ns", "cpu_ns"),
        )
    )
    return _WorkRecord(
        values["reference_ns"],
        slow,
        values["slow_overflow"],
        values["switch_reference_ns"],
        switches,
        values["slow_switches_overflow"],
    )


@dataclass(frozen=True)
class Verdict:
    """The judgement of one probe record against one hand's deadlines."""

    level: str  # one of LEVELS
    reasons: tuple[str, ...]
    figures: dict[str, Any]

    @property
    def fails(self) -> bool:
        return self.level == "fail"


def judge(record: ProbeRecord, deadlines: Deadlines) -> Verdict:
    """Would a loop that stalls as this one did keep this hand running?

    A stall's length runs from the oldest deadline it slept through to the wake-up. It fails the
    host when it alone is as long as the overrun tolerance (the control loop would stop on
    LOOP_OVERRUN), when stalls in consecutive wake-ups add up to it (the same count the safety
    supervisor keeps, ``TickWatch``), or when it is longer than the feedback timeout (the
    simulated hand, a peer on this host, would be silent that long; and a real hand's command
    watchdog is not much longer). Shorter stalls that still miss a tick, or a p99 lateness of
    more than half a period, make it marginal.
    """
    period = deadlines.period_ns
    tolerance_ns = deadlines.overrun_tolerance_ticks * period
    lengths = [wake - due for _, due, wake, _ in record.stalls]
    over_period = sum(1 for n in lengths if n > period)
    over_tolerance = sum(1 for n in lengths if n >= tolerance_ns)
    over_feedback = sum(1 for n in lengths if n > deadlines.feedback_timeout_ns)
    # The supervisor's own count of consecutive misses, wake-up by wake-up, on the loop's period
    # (a probe ticking faster than the loop has its misses scaled to the loop's ticks).
    watch = TickWatch(SafetyConfig(max_consecutive_misses=deadlines.overrun_tolerance_ticks))
    trips, last = 0, None
    for (index, _, _, _), length in zip(record.stalls, lengths, strict=True):
        if last is None or index != last + 1:
            watch.tick(0)
        if watch.tick(length // period):
            trips += 1
            watch.tick(0)
        last = index
    slow_cpu = record.slow_cpu_intervals()
    slow_cpu_lost = [lost for _, _, lost in slow_cpu]
    slow_cpu_heavy = sum(1 for lost in slow_cpu_lost if lost >= P99_SHARE * period)
    figures = {
        "seconds": round((record.end_ns - record.start_ns) / 1e9, 3),
        "wakeups": record.wakeups,
        "lateness_us": {
            "p50": record.lateness_us(50),
            "p99": record.lateness_us(99),
            "max": round(record.lateness_max_ns / 1e3, 1),
        },
        "longest_stall_ms": round(max(lengths, default=0) / 1e6, 3),
        "stalls_over_period": over_period,
        "stalls_over_overrun_tolerance": over_tolerance,
        "stalls_over_feedback_timeout": over_feedback,
        "loop_overrun_trips": trips,
        "stalls_unrecorded": record.stalls_overflow,
        "hiccups": len(record.hiccups) + record.hiccups_overflow,
        "slow_pieces": len(record.slow) + record.slow_overflow,
        "slow_switches": len(record.slow_switches) + record.slow_switches_overflow,
        "slow_cpu_intervals": len(slow_cpu),
        "slow_cpu_intervals_over_half_period": slow_cpu_heavy,
        "longest_slow_cpu_ms": round(max((e - s for s, e, _ in slow_cpu), default=0) / 1e6, 3),
        "slow_cpu_lost_ms": round(sum(slow_cpu_lost) / 1e6, 3),
        "steal_ms": record.steal_ms,
        "period_ms": period / 1e6,
        "overrun_tolerance_ms": tolerance_ns / 1e6,
        "feedback_timeout_ms": deadlines.feedback_timeout_ns / 1e6,
    }
    reasons: list[str] = []
    if trips:
        reasons.append(
            f"{trips} stall(s) as long as the overrun tolerance "
            f"({deadlines.overrun_tolerance_ticks} periods, {tolerance_ns / 1e6:g} "
            "ms, alone or in consecutive ticks): the control loop would stop on "
            "LOOP_OVERRUN"
        )
    if over_feedback:
        reasons.append(
            f"{over_feedback} stall(s) longer than the feedback timeout "
            f"({deadlines.feedback_timeout_ns / 1e6:g} ms)"
        )
    if record.stalls_overflow:
        reasons.append(f"{record.stalls_overflow} more stalls than the record holds")
    level = "fail" if reasons else "pass"
    if level == "pass":
        p99 = record.lateness_us(99)
        if over_period:
            reasons.append(
                f"{over_period} stall(s) longer than a period ({period / 1e6:g} ms), "
                "each a missed tick, but none as long as the overrun tolerance"
            )
        if p99 > P99_SHARE * period / 1e3:
            reasons.append(f"lateness p99 {p99:g} µs is more than {P99_SHARE:.0%} of the period")
        if slow_cpu_heavy:
            reasons.append(
                f"{slow_cpu_heavy} time(s) the CPU was taken away in hiccups or ran slow for "
                f"{P99_SHARE:.0%} of a period or more, which no stall shows (slow CPU)"
            )
        level = "marginal" if reasons else "pass"
    return Verdict(level, tuple(reasons), figures)


def worse(a: Verdict, b: Verdict) -> Verdict:
    """The worse of the two, with ``a``'s figures; on a tie with the reasons of both: a
    MARGINAL host with a real-time rival on the loop's CPU lost the rival from its reasons."""
    if a.level == b.level:
        return Verdict(a.level, tuple(dict.fromkeys(a.reasons + b.reasons)), a.figures)
    return a if LEVELS.index(a.level) > LEVELS.index(b.level) else b


def advice(
    facts: HostFacts, record: ProbeRecord, realtime: bool, rivals: Sequence[Rival] = ()
) -> list[str]:
    """What would help this host hold the deadlines, each naming what was found."""
    tips: list[str] = []
    for rival in rivals:
        tips.append(
            f"the loop's CPU to itself: {rival.label()} may run on CPU(s) "
            f"{list(rival.cpus)} at the loop's priority or above; move it "
            f"('taskset -p -c ... {rival.tid}'), lower it ('chrt -p ... {rival.tid}'), or give "
            "the loop another CPU with --loop-cpu"
        )
    if facts.preemption != "PREEMPT_RT" and facts.realtime_kernel is not True:
        found = "/sys/kernel/realtime " + ("absent" if facts.realtime_kernel is None else "0")
        model = facts.preemption + (
            f", preempt={facts.cmdline_preempt}" if facts.cmdline_preempt else ""
        )
        tip = f"a PREEMPT_RT kernel (found {model}; {found})"
        if facts.preemption == "PREEMPT_DYNAMIC" and facts.cmdline_preempt != "full":
            tip += "; at least boot this one with preempt=full"
        tips.append(tip)
    got = record.scheduler.get("policy", "?")
    if realtime and got != "SCHED_FIFO" and facts.privileged and facts.rt_runtime is not None:
        # CAP_SYS_NICE and still refused: not the limits, the cgroup's real-time budget
        where, budget = facts.rt_runtime
        tips.append(
            f"real-time time for this process's cgroup (got {got} with CAP_SYS_NICE; "
            f"{where} is {budget} µs): give the group a real-time budget (cpu.rt_runtime_us "
            "above 0, within its parent's), or run in a group that has one"
        )
    elif realtime and got != "SCHED_FIFO":
        tips.append(
            f"real-time priority for the loop (got {got}; RLIMIT_RTPRIO is "
            f"{_show_limit(facts.rtprio_limit)}): 'ulimit -r {LOOP_PRIORITY + 1}' via "
            "rtprio in /etc/security/limits.conf, or CAP_SYS_NICE"
        )
    elif not realtime:
        tips.append(
            "run with --rt (SCHED_FIFO, a pinned CPU, locked memory); this check ran "
            f"at {got} like the run would"
        )
    if realtime and any("locking memory" in r for r in record.refused):
        tips.append(
            f"locked memory (RLIMIT_MEMLOCK is {_show_limit(facts.memlock_limit_kb)} "
            "KiB): 'ulimit -l unlimited' via memlock in /etc/security/limits.conf, or "
            "CAP_IPC_LOCK"
        )
    if len(facts.cpus) >= 2 and not facts.isolated:
        loop_cpu, _ = plan_cpus(set(facts.cpus), set())
        tips.append(
            f"a CPU of its own for the loop (none isolated in "
            f"/sys/devices/system/cpu/isolated): boot with isolcpus={loop_cpu} "
            f"nohz_full={loop_cpu} rcu_nocbs={loop_cpu}; handctl pins the loop to an "
            "isolated CPU with --rt"
        )
    lost = record.slow_cpu_intervals()
    if any(lost_ns >= P99_SHARE * record.period_ns for _, _, lost_ns in lost):
        tips.append(
            f"a CPU that does not slow down: the bare loop's CPU was taken away in hiccups or "
            f"ran slow {len(lost)} time(s) (longest "
            f"{max(e - s for s, e, _ in lost) / 1e6:.3g} ms, "
            f"{sum(n for _, _, n in lost) / 1e6:.3g} ms lost in all); a dedicated or isolated "
            "CPU, no frequency scaling, a host that does not overcommit its CPUs (a VM's vCPU "
            "pinned to a core of its own)"
        )
    slow = sorted({g for g in facts.governors.values() if g != "performance"})
    if slow:
        tips.append(
            f"no frequency scaling (cpufreq governor {', '.join(slow)}): "
            "'cpupower frequency-set -g performance'"
        )
    if facts.virtual_machine:
        tips.append(
            "a real machine or a VM with dedicated, pinned vCPUs: this is a virtual "
            "machine, whose hypervisor can take a CPU away for milliseconds"
            + (f" ({record.steal_ms:g} ms stolen during the check)" if record.steal_ms else "")
        )
    return tips


def _show_limit(value: int) -> str:
    return "unlimited" if value < 0 else str(value)


# -- running the probe --------------------------------------------------------------------------
class Probe(JsonHelper):
    """The bare loop as a child process, from ``start`` to ``stop`` (or for ``seconds``)."""

    def __init__(
        self,
        period_ns: int,
        *,
        record_ns: int,
        seconds: float | None = None,
        priority: int | None = None,
        cpu: int | None = None,
        lock_memory: bool = True,
        work_ns: int | None = None,
        slow_factor: float | None = None,
        hiccup_ns: int | None = None,
    ) -> None:
        args = [
            "--period-ns",
            str(period_ns),
            "--record-ns",
            str(record_ns),
            "--parent-pid",
            str(os.getpid()),
        ]
        if seconds is not None:
            args += ["--seconds", str(seconds)]
        if priority is not None:
            args += ["--priority", str(priority)]
        if cpu is not None:
            args += ["--cpu", str(cpu)]
        if not lock_memory:
            args.append("--no-lock-memory")
        if work_ns is not None:
            args += ["--work-ns", str(work_ns)]
        if slow_factor is not None:
            args += ["--slow-factor", str(slow_factor)]
        if hiccup_ns is not None:
            args += ["--hiccup-ns", str(hiccup_ns)]
        self.seconds = seconds
        super().__init__("handctl.hostprobe", args, "the timing probe")
        if priority is None:
            # at once, not after its imports at a caller's SCHED_FIFO: it raises none itself
            # (and puts itself at SCHED_OTHER too, which covers a priority it was refused)
            ordinary_scheduling(self.proc.pid)

    def stop(self) -> ProbeRecord:
        """End the probe (if it still runs) and read what it saw."""
        data = self.finish(_PROBE_START_S + (self.seconds or 0.0), self.seconds is None)
        if isinstance(data, dict) and data.get("wakeups") == 0:
            # started up, and stopped before its timer's first expiry (a run that ended on
            # its first ticks): its record is of nothing, which the record's own check said
            # as "wakeups: expected an integer >= 1, found 0"
            raise HandctlError(
                f"{self.what} measured nothing: handctl stopped it when what it was beside "
                f"ended, {time.monotonic() - self.started:.1f} s after starting it, before "
                "its first wake-up"
            )
        return ProbeRecord.from_json(data, "the timing probe")


@dataclass(frozen=True)
class CheckReport:
    """A timing check: the verdict, each record judged, the host's facts and the advice."""

    verdict: Verdict
    records: tuple[tuple[ProbeRecord, Verdict], ...]
    facts: HostFacts
    advice: tuple[str, ...]
    realtime: bool

    def as_json(self) -> dict[str, Any]:
        measured = self.records[0]
        return {
            "verdict": self.verdict.level,
            "reasons": list(self.verdict.reasons),
            **measured[1].figures,
            "scheduler": measured[0].scheduler,
            "refused": list(measured[0].refused),
            "realtime": self.realtime,
            "facts": self.facts.as_json(),
            "advice": list(self.advice),
            "injected": [
                {"source": r.source, "verdict": v.level, "reasons": list(v.reasons), **v.figures}
                for r, v in self.records[1:]
            ],
            "probe": measured[0].as_json(),
        }

    def text(self) -> str:
        """The verdict as a user reads it: one headline, the figures, what would help."""
        f = self.records[0][1].figures
        late = f["lateness_us"]
        sched = self.records[0][0].scheduler
        lines = [
            f"timing check: {self.verdict.level.upper()} - "
            + ("this host held" if self.verdict.level != "fail" else "this host cannot hold")
            + f" the hand's deadlines in {f['seconds']:g} s of a bare {1e3 / f['period_ms']:g}"
            f" Hz timer loop at {sched.get('policy', '?')} {sched.get('priority', 0)} on "
            f"CPU(s) {sched.get('cpus', '?')}",
            f"  wake-up lateness p50 {late['p50']:g} us, p99 {late['p99']:g} us, max "
            f"{late['max']:g} us; longest stall {f['longest_stall_ms']:g} ms",
            f"  stalls longer than one period ({f['period_ms']:g} ms): "
            f"{f['stalls_over_period']}, than the overrun tolerance "
            f"({f['overrun_tolerance_ms']:g} ms): {f['stalls_over_overrun_tolerance']}, than "
            f"the feedback timeout ({f['feedback_timeout_ms']:g} ms): "
            f"{f['stalls_over_feedback_timeout']}; LOOP_OVERRUN trips: "
            f"{f['loop_overrun_trips']}",
            f"  slow CPU: {f['slow_cpu_intervals']} interval(s) of hiccups (wake-ups late "
            f"but no stall: {f['hiccups']}), slow work ({f['slow_pieces']}) or slow switches "
            f"({f['slow_switches']}), "
            f"{f['slow_cpu_intervals_over_half_period']} losing half a period or more; longest "
            f"{f['longest_slow_cpu_ms']:g} ms, {f['slow_cpu_lost_ms']:g} ms lost in all",
        ]
        lines += [f"  because {r}" for r in self.records[0][1].reasons]
        # and what the headline rests on besides the measurement (a real-time rival, the
        # bare loop's priority refused), said before only in the advice if at all; the
        # injected records' reasons have lines of their own below
        said = {r for _, verdict in self.records for r in verdict.reasons}
        lines += [f"  because {r}" for r in self.verdict.reasons if r not in said]
        for record, verdict in self.records[1:]:
            lines.append(
                f"  injected from {record.source} ({INJECT_ENV}): "
                f"{verdict.level.upper()}" + "".join(f"; {r}" for r in verdict.reasons)
            )
        lines += [f"  refused: {r}" for r in self.records[0][0].refused]
        if self.advice:
            lines.append("  what would help:")
            lines += [f"  - {tip}" for tip in self.advice]
        return "\n".join(lines)


def injected_records(period_ns: int) -> list[ProbeRecord]:
    """The recorded sequence named by ``HANDCTL_TIMING_INJECT``, if any, of a loop of
    ``period_ns``."""
    path = os.environ.get(INJECT_ENV)
    if not path:
        return []
    from handctl.schema import read_input

    # opened without blocking and refused unless a regular file: a FIFO held the check in its
    # open() for good; the variable named, as what set the file
    limit = 64 << 20
    raw = read_input(path, f"a readable JSON file ({INJECT_ENV})", limit)
    if len(raw) > limit:
        raise ConfigError(path, "", f"a JSON file of at most {limit} bytes ({INJECT_ENV})", "more")
    try:
        data = json.loads(raw)
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ConfigError(path, "", f"valid JSON ({INJECT_ENV})", str(exc)) from None
    except RecursionError:  # nested deeper than the decoder goes: no probe writes that
        raise ConfigError(
            path, "", f"valid JSON ({INJECT_ENV})", Description("arrays or objects nested too deep")
        ) from None
    record = ProbeRecord.from_json(data, path)
    if record.period_ns != period_ns:
        # judged against this hand's deadlines, a probe of another loop's period measured
        # another loop
        raise ConfigError(
            path,
            "period_ns" if "probe" not in data else "probe.period_ns",
            f"the hand's loop period, {period_ns} ns ({INJECT_ENV})",
            record.period_ns,
        )
    return [record]


def timing_check(
    hand: HandConfig, seconds: float, *, realtime: bool, cpu: int | None = None
) -> CheckReport:
    """Measure the host for ``seconds`` with the scheduling the run would have, and judge it.

    ``realtime``: what ``--rt`` asks (SCHED_FIFO at the loop's priority, locked memory) on
    ``cpu`` (None: what ``plan_cpus`` gives the loop); otherwise the default scheduler.
    """
    deadlines = Deadlines.of(hand)
    # a bad file is refused before the measurement
    injected = injected_records(deadlines.period_ns)
    facts = gather_facts()
    check_loop_cpu(cpu, facts.cpus)
    if realtime and cpu is None:
        cpu, _ = plan_cpus(set(facts.cpus), set(facts.isolated))
    rivals = find_rivals(cpu if realtime else None, LOOP_PRIORITY if realtime else 1, [os.getpid()])
    with Probe(
        deadlines.period_ns,
        record_ns=deadlines.period_ns // 2,
        hiccup_ns=round(HICCUP_SHARE * deadlines.period_ns),
        seconds=seconds,
        priority=LOOP_PRIORITY if realtime else None,
        cpu=cpu if realtime else None,
        lock_memory=realtime,
    ) as probe:
        measured = probe.stop()
    _check_measured_whole(measured, seconds)
    records = [(measured, judge(measured, deadlines))]
    records += [(r, judge(r, deadlines)) for r in injected]
    verdict = records[0][1]
    for _, v in records[1:]:
        verdict = worse(verdict, v)
    if rivals:
        verdict = worse(verdict, rival_verdict(rivals, verdict.figures))
    tips = advice(facts, measured, realtime, rivals)
    beside = beside_refused() if realtime and "SCHED_FIFO" in measured.scheduler.values() else ""
    if beside:
        # the check's bare loop got the loop's 80; a run's needs 81, and below the loop it
        # would make the run's verdict and attribution void (``below_the_loop``)
        verdict = worse(verdict, Verdict("marginal", (beside,), verdict.figures))
        tips.append(
            f"real-time priority {BESIDE_PRIORITY} for the bare loop beside a run: 'ulimit -r "
            f"{BESIDE_PRIORITY}' via rtprio in /etc/security/limits.conf, or CAP_SYS_NICE"
        )
    return CheckReport(verdict, tuple(records), facts, tuple(tips), realtime)


#: The bare loop beside a run: one above the control loop (``beside_probe``).
BESIDE_PRIORITY = LOOP_PRIORITY + 1


def beside_refused(priority: int = BESIDE_PRIORITY) -> str:
    """Why SCHED_FIFO ``priority`` would be refused to the bare loop beside a run, or "".

    Asked by a thread of its own that ends at once (``sched_setscheduler`` sets the calling
    thread), so this process's own scheduling is untouched: a check that got the loop's 80
    passed a host that refused the 81 the run's bare loop asks for, whose run then blamed
    handctl's misses on the host."""
    said: list[str] = []

    def ask() -> None:
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
        except (OSError, AttributeError) as exc:
            said.append(str(exc))

    asker = threading.Thread(target=ask, name="handctl-rtprio")
    asker.start()
    asker.join()
    if not said:
        return ""
    return (
        f"SCHED_FIFO priority {priority} refused ({said[0]}): a run's bare timer loop asks for "
        "it, one above the loop, to say whose its missed ticks were; below the loop it cannot"
    )


def _check_measured_whole(measured: ProbeRecord, seconds: float) -> None:
    """A ``HandctlError`` when the probe measured less than asked: a SIGTERM or SIGINT from
    outside ends it early and cleanly, as handctl's own stop does, and a check of 2 s of the
    20 asked gave its verdict as if whole. The loop stops at its first wake-up past its
    length, so a whole one is within a period of it; a hundredth (at least 50 ms) is slack."""
    got = (measured.end_ns - measured.start_ns) / 1e9
    if got < seconds - max(0.05, 0.01 * seconds):
        raise HandctlError(
            f"the timing probe was stopped after {got:.3g} s of the {seconds:g} s asked, by a "
            "signal handctl did not send: no verdict on a measurement cut short"
        )


def rival_verdict(rivals: Sequence[Rival], figures: dict[str, Any]) -> Verdict:
    """Marginal while another real-time task may take the loop's CPU: the bare loop, one
    priority above the loop, cannot feel it, and it can hold the loop for as long as it runs
    (an idle one costs nothing, so not a fail)."""
    names = ", ".join(r.label() for r in rivals)
    return Verdict(
        "marginal",
        (
            f"{len(rivals)} real-time task(s) at the loop's priority or above may run "
            f"on its CPU: {names}",
        ),
        figures,
    )


# -- the host's share of a run's missed ticks ----------------------------------------------------
@dataclass(frozen=True)
class LoopWork:
    """What the control loop measured of its own work, for ``attribute``: the thread CPU time
    of each tick that ran between two stalled wake-ups in a row, by the second's wake-up index
    (``StallLog.work_ns``), and the run's usual tick CPU time measured the same way, from a
    wake-up to the next (``UsualWork.median_ns``)."""

    between_stalls_ns: dict[int, int]
    usual_ns: int
    #: What the tick before each late wake-up did, by the wake-up's tick
    #: (``handctl.online.misstrace.MissTrace.rows``): shown for handctl's own misses.
    late_wakeups: dict[int, dict[str, int]] = field(default_factory=dict)
    #: The run_delay of a usual tick (``MissTrace.usual_run_delay_ns``; -1: unknown).
    usual_run_delay_ns: int = -1
    #: Whether the loop ran at a real-time priority (SCHED_FIFO), which only the bare loop
    #: beside it and the host's own real-time tasks can preempt: only then is the time it was
    #: held off the CPU the host's (``unheld_missed``).
    realtime: bool = False
    #: Its SCHED_FIFO or SCHED_RR priority (0: none), which the bare loop must be above
    #: (``below_the_loop``).
    priority: int = 0

    def late_start_missed(self, start_ns: int, due_ns: int, period_ns: int) -> int:
        """How many deadlines from ``due_ns`` on a tick of the usual CPU time begun at
        ``start_ns`` would have missed too: the host's, when the host made it begin then
        (0 without a usual to judge by)."""
        over = start_ns + self.usual_ns - due_ns
        if self.usual_ns <= 0 or over <= 0:
            return 0
        return -(-over // period_ns)

    def unheld_missed(
        self, tick: int, wake_ns: int, due_ns: int, missed: int, period_ns: int
    ) -> int:
        """How many of the ``missed`` deadlines from ``due_ns`` on the late wake-up ``tick``
        (at ``wake_ns``) would have missed too had the loop's thread not been held off the CPU
        (``misstrace.held_off_ns``) in the tick before it, and, if that tick never blocked, in
        the late ticks before it that led to its late start (``start_credit_ns``): the others
        are the host's. All of them without a trace of that tick, or when the loop was not
        real-time (then the processes of a run itself, the simulated hand or the recording's
        writer, can hold it)."""
        row = self.late_wakeups.get(tick)
        if row is None or not self.realtime:
            return missed
        held = held_off_ns(row, self.usual_run_delay_ns, period_ns)
        if row["voluntary"] == 0:
            held += self.start_credit_ns(tick - 1, period_ns)
        return min(missed, max(0, (wake_ns - due_ns - held) // period_ns))

    def start_credit_ns(self, tick: int, period_ns: int) -> int:
        """How much earlier tick ``tick`` would have begun had the loop's thread not been held
        off the CPU before it: 0 if it began on time (no trace of its wake-up). Otherwise its
        wake-up's own held time, and, if the tick before it never blocked (so this one began
        where that one's work ended), what that one would have gained too; never more than
        the tick was late. A tick that blocked cuts the chain: its end did not follow from
        its start."""
        chain = []
        while (row := self.late_wakeups.get(tick)) is not None:
            chain.append(row)
            if row["voluntary"] != 0:
                break
            tick -= 1
        credit = 0
        for row in reversed(chain):
            late = row["late_ns"] - row["missed"] * period_ns  # of its start, on its schedule
            held = held_off_ns(row, self.usual_run_delay_ns, period_ns)
            credit = min(late, held + (credit if row["voluntary"] == 0 else 0))
        return max(0, credit)

    def held(self, tick: int, period_ns: int) -> bool:
        """Whether the tick before wake-up ``tick`` took no more than a catch-up's usual CPU
        time (``CATCH_UP_CPU_FACTOR`` times the usual, and less than a period: a tick that
        needs a whole period misses on its own), so that its miss was time it did not run."""
        cpu = self.between_stalls_ns.get(tick)
        if cpu is None or self.usual_ns <= 0:
            return False
        return cpu <= CATCH_UP_CPU_FACTOR * self.usual_ns and cpu < period_ns


def attribute(
    loop_stalls: list[tuple[int, int, int, int]],
    host: ProbeRecord,
    period_ns: int,
    handctls: list[int] | None = None,
    rivals: RivalRecord | None = None,
    work: LoopWork | None = None,
) -> dict[str, int]:
    """Split the control loop's missed ticks between the host and handctl.

    A missed tick's interval runs from one period before the oldest deadline it slept through
    (the tick before it may have been the one held up) to its wake-up. If stalls of the bare
    loop beside it overlap that interval by as long as the loop was late, less one period
    (the loop's own tick may take up to a period), the host held both loops: ``missed_host``.
    A host stall of 0.9 ms does not explain a loop 13 ms late. If the stalls do not, but
    together with the bare loop's hits (its hiccups, wake-ups late by less than a stall, its
    slow pieces of work, and its slow switches, a passage through the kernel between two
    pieces that cost it several times the usual CPU time; ``_slowed``) they do, the host's
    CPU was taken away in pieces or ran slow: ``missed_host_slow_cpu``. A loop slow on its
    own does not slow the bare loop's wake-ups, work or switches, which run above it on the
    same CPU. If the host does not explain
    it but a real-time rival (``handctl.rivals``: a task at the loop's priority or above,
    allowed on its CPU, which the probe one priority up does not feel) ran during it, the
    rival held the loop: ``missed_rival``, the host's too (what else runs on the host).

    A wake-up that missed right after one of the host's (the next wake-up, in a chain that
    began with the host) comes after a catch-up tick: it started late because of the host and
    drained the frames of the periods slept through. If ``work`` shows that tick took no more
    thread CPU time than a catch-up usually does (``LoopWork.held``), it did not miss on its
    own work: it was held, for time it did not run, and the miss is the host's too
    (``missed_host_catch_up``). So are the deadlines a tick of the usual CPU time would have
    missed had it begun when the catch-up tick began (``LoopWork.late_start_missed``: a late
    start): the host woke it too late to meet them, whatever its own work. What a catch-up
    tick missed beyond that, with its CPU time high, stays handctl's, as does any miss not
    right after the host's, but for this:

    Whatever the wake-up before it, the deadlines the loop would have met had its thread not
    been held off the CPU in the tick before the miss are the host's too
    (``missed_host_off_cpu``, ``LoopWork.unheld_missed``): by the kernel's own account of that
    thread (``handctl.online.misstrace``), the time it was runnable while another task ran
    (``run_delay``, beyond the usual the bare loop's preemptions cost) and, in a tick that
    never blocked, the time it was neither running nor runnable. Its own CPU time, however
    slow, is never taken off; only with the loop at a real-time priority, which no process of
    handctl's but the bare loop can preempt on its CPU.

    If none of these, the host let a bare loop run at that time and handctl was late on its
    own: ``missed_handctl``. Of those, ``missed_handctl_after_host`` came in the very next
    wake-up after the host's miss, its catch-up tick slow (or not measured). Missed ticks
    outside the time the probe ran are ``missed_unobserved``. The ticks of handctl's own
    misses are appended to ``handctls`` if given.
    """
    host_stalls = sorted((due, wake) for _, due, wake, _ in host.stalls)
    hits = host.slow_cpu_hits()
    counts = {
        "missed_host": 0,
        "missed_host_slow_cpu": 0,
        "missed_rival": 0,
        "missed_host_catch_up": 0,
        "missed_host_off_cpu": 0,
        "missed_handctl": 0,
        "missed_handctl_after_host": 0,
        "missed_unobserved": 0,
    }
    after_host = -2  # the last wake-up of a chain of misses that began with the host's
    hosts = -2  # the last wake-up whose miss was the host's (a catch-up's included)
    begun = 0  # when the tick after the previous stalled wake-up began: that wake-up
    for tick, due, wake, missed in loop_stalls:
        catch_up_began, begun = begun, wake
        start = due - period_ns
        if wake < host.start_ns or start > host.end_ns:
            counts["missed_unobserved"] += missed
        elif (stalled := _held(host_stalls, start, wake)) >= wake - due - period_ns:
            counts["missed_host"] += missed
            after_host = hosts = tick
        elif stalled + _slowed(hits, host.period_ns, start, wake) >= wake - due - period_ns:
            counts["missed_host_slow_cpu"] += missed
            after_host = hosts = tick
        elif rivals is not None and rivals.active(start, wake):
            counts["missed_rival"] += missed
            after_host = hosts = tick
        elif tick == hosts + 1 and work is not None and work.held(tick, period_ns):
            counts["missed_host_catch_up"] += missed
            after_host = hosts = tick
        else:
            late = 0
            if tick == hosts + 1 and work is not None:
                late = min(missed, work.late_start_missed(catch_up_began, due, period_ns))
            unheld = (
                work.unheld_missed(tick, wake, due, missed, period_ns)
                if work is not None
                else missed
            )
            own = max(0, unheld - late)
            counts["missed_host_catch_up"] += late
            counts["missed_host_off_cpu"] += missed - late - own
            if own == 0:
                after_host = hosts = tick
                continue
            counts["missed_handctl"] += own
            if tick == after_host + 1:
                counts["missed_handctl_after_host"] += own
                after_host = tick
            if handctls is not None:
                handctls.append(tick)
    return counts


def below_the_loop(record: ProbeRecord, work: LoopWork | None) -> str:
    """Why the bare loop beside a run was not above the control loop on its CPU, or "" if it
    was (or the loop was not real-time either: then the two share the ordinary scheduler,
    docs/timing.md's "Limits").

    The attribution rests on the bare loop preempting the loop: below it, the loop's own
    ticks hold it, and handctl's misses read as the host's stalls. A host that grants the
    loop's SCHED_FIFO 80 but not the bare loop's 81 (rtprio 80 in limits.conf) showed
    "163 the host's, 0 handctl's" with the refusal only in the JSON's ``host.refused``.
    """
    if work is None or not work.realtime:
        return ""
    policy = record.scheduler.get("policy", "?")
    priority = record.scheduler.get("priority", 0)
    above = isinstance(priority, int) and priority > work.priority
    if policy in ("SCHED_FIFO", "SCHED_RR") and above:
        return ""
    refused = "".join(f"; {r}" for r in record.refused if "SCHED_FIFO" in r)
    return (
        f"the bare timer loop beside the run ran at {policy} {priority}, not above the "
        f"control loop's real-time priority {work.priority}{refused}: the loop's own ticks "
        "held it, so its stalls are not the host's alone and whose the missed ticks were "
        "cannot be said (all counted unobserved)"
    )


def _void(shares: dict[str, int]) -> dict[str, int]:
    """Every missed tick as judged by no one: a bare loop below the loop saw handctl's own."""
    total = sum(v for k, v in shares.items() if k != "missed_handctl_after_host")
    return {k: total if k == "missed_unobserved" else 0 for k in shares}


def _held(host_stalls: list[tuple[int, int]], start: int, end: int) -> int:
    """ns of ``[start, end]`` during which the bare loop was stalled."""
    return sum(max(0, min(end, h_wake) - max(start, h_due)) for h_due, h_wake in host_stalls)


def _slowed(hits: list[tuple[int, int]], look_ns: int, start: int, end: int) -> int:
    """ns of ``[start, end]`` the CPU was taken away or slow, estimated from the bare loop's
    hits in it: each stands for one of its periods (``look_ns``), or what it saw if more. A
    look every ``look_ns`` that finds the CPU gone, at a moment that is as good as random,
    finds it gone in the share of looks that the CPU was gone: so each hit is one period's
    worth (docs/timing.md: the loop lost a median 0.58 ms a hit, the bare loop looking every
    0.5 ms), where what the hit itself saw is only the end of it."""
    return sum(max(look_ns, seen) for at, seen in hits if start <= at <= end)


# -- a run's host: its CPUs, the check before it, the bare loop beside it -----------------------
#: The summary lists the ticks of at most this many of handctl's own misses.
MAX_LISTED_TICKS = 20
#: The bare loop beside a run, started with it, ran for less than this share of the run:
#: what it saw is no verdict on the host (it starts in a process of its own, and a run that
#: stopped on its first ticks was judged "PASS" on 14 ms of 145).
MIN_OBSERVED_SHARE = 0.5


def observed_text(observed_s: float, run_s: float | None) -> str:
    """Why the bare loop's figures are no verdict on a run's host (it ran too little of the
    run), or "" when they are."""
    if run_s is None or run_s <= 0 or observed_s >= MIN_OBSERVED_SHARE * run_s:
        return ""
    return (
        f"the bare timer loop beside the run ran {observed_s:.3g} s of the run's "
        f"{run_s:.3g} s ({observed_s / run_s:.0%}): too little to say what the host was"
    )


def check_loop_cpu(cpu: int | None, cpus: Sequence[int] | None = None) -> None:
    """Refuse a ``--loop-cpu`` this process may not run on (``cpus``: the ones it may,
    ``os.sched_getaffinity`` by default), before anything is measured or said."""
    allowed = sorted(os.sched_getaffinity(0) if cpus is None else cpus)
    if cpu is not None and cpu not in allowed:
        raise ConfigError("--loop-cpu", "", f"one of the CPUs this process may use {allowed}", cpu)


def run_cpus(hygiene: Hygiene) -> tuple[int | None, int | None]:
    """The CPUs of the loop and of the simulated hand for a real-time run: the user's, or
    ``plan_cpus``'s on a machine of two or more; (None, None) when not pinned."""
    if not hygiene.pin:
        return None, None
    facts = gather_facts()
    allowed = set(facts.cpus)
    loop_cpu, sim_cpu = plan_cpus(allowed, set(facts.isolated))
    for option, cpu in (("--loop-cpu", hygiene.loop_cpu), ("--sim-cpu", hygiene.sim_cpu)):
        if cpu is not None and cpu not in allowed:
            raise ConfigError(
                option, "", f"one of the CPUs this process may use {sorted(allowed)}", cpu
            )
    if hygiene.loop_cpu is not None:
        loop_cpu = hygiene.loop_cpu
        if sim_cpu == loop_cpu:
            sim_cpu = min(allowed - {loop_cpu}, default=None)
    if hygiene.sim_cpu is not None:
        sim_cpu = hygiene.sim_cpu
    if loop_cpu is not None and loop_cpu == sim_cpu:
        raise ConfigError("--sim-cpu", "", f"a CPU other than the loop's ({loop_cpu})", sim_cpu)
    return loop_cpu, sim_cpu


def precheck(
    hand: HandConfig, realtime: bool, loop_cpu: int | None, accept_missed_deadlines: bool
) -> tuple[dict[str, Any], list[str]]:
    """The timing check before a run on anything but the simulated hand: a host that fails
    it is refused unless the user accepts the risk by name. Returns the check for the run's
    summary (its figures, not the probe's record) and the warnings."""
    report = timing_check(hand, PRECHECK_S, realtime=realtime, cpu=loop_cpu)
    if report.verdict.fails and not accept_missed_deadlines:
        raise HostTimingError(
            report.text() + "\n  nothing was sent; to run anyway, pass --accept-missed-deadlines"
        )
    summary = {k: v for k, v in report.as_json().items() if k not in ("probe", "facts")}
    if report.verdict.fails:
        return summary, [
            f"running with --accept-missed-deadlines on a host that failed the "
            f"timing check: {'; '.join(report.verdict.reasons)}"
        ]
    if report.verdict.level == "marginal":
        return summary, [f"timing check marginal: {'; '.join(report.verdict.reasons)}"]
    return summary, []


def beside_probe(
    hand: HandConfig,
    realtime: bool,
    cpu: int | None,
    lock_memory: bool,
    priority: int = BESIDE_PRIORITY,
) -> Probe:
    """The bare timer loop beside a real-time run, on the loop's CPU one priority above it
    (or on the simulated hand's CPU, above the hand).

    Above it, so the loop's own lateness never delays it; on its CPU, so it shares the loop's
    host stalls. It ticks twice a loop period: any host stall of a whole period then shows as
    a probe wake-up at least half a period late, which is what it keeps.
    """
    period = round(hand.bus.period_s * 1e9)
    return Probe(
        period // 2,
        record_ns=period // 2,
        hiccup_ns=round(HICCUP_SHARE * period),
        priority=priority if realtime else None,
        cpu=cpu,
        lock_memory=realtime and lock_memory,
    )


def work_figures(work: LoopWork | None, own: Sequence[int]) -> dict[str, Any]:
    """What the catch-up ticks before handctl's own misses (``own``, their ticks) took, beside
    the usual tick, CPU time in µs (``attribute`` judges them against it): so a miss that
    stayed handctl's shows whether its tick was slow or started late. ``handctl_misses``: what
    the tick before each of them did (``misstrace.describe``), whatever its wake-up."""
    return {
        "usual_tick_cpu_us": round(work.usual_ns / 1e3, 1) if work is not None else 0.0,
        "handctl_catch_up_cpu_us": [
            [tick, round(work.between_stalls_ns[tick] / 1e3, 1)]
            for tick in own[:MAX_LISTED_TICKS]
            if work is not None and tick in work.between_stalls_ns
        ],
        "handctl_misses": [
            describe(work.late_wakeups[tick], work.usual_ns, work.usual_run_delay_ns)
            for tick in own[:MAX_LISTED_TICKS]
            if work is not None and tick in work.late_wakeups
        ],
    }


def host_summary(
    hand: HandConfig,
    probe: Probe,
    loop_stalls: StallLog,
    faults: Sequence[Fault],
    warnings: list[str],
    peer_probe: Probe | None = None,
    rival_watch: RivalWatch | None = None,
    work: LoopWork | None = None,
    run_s: float | None = None,
) -> tuple[ProbeRecord | None, RivalRecord | None, dict[str, Any]]:
    """What the bare loop beside a run saw, and whose the run's missed ticks were; a warning
    with the host's verdict when the run stopped on LOOP_OVERRUN or FEEDBACK_TIMEOUT.

    ``peer_probe`` is a bare loop on the simulated hand's CPU: its stalls are the host's part
    in a feedback that came late, which the loop's CPU does not see. ``rival_watch`` saw the
    real-time tasks that could hold the loop where the probe above it would not notice.
    ``work`` is what the loop measured of its catch-up ticks and its usual tick, against which
    a catch-up tick is judged (``attribute``); None judges none. ``run_s``: how long the run
    ran, against which the bare loop's share of it is said (``observed_text``).
    """
    try:
        record = probe.stop()
        peer = peer_probe.stop() if peer_probe is not None else None
        rivals = rival_watch.stop() if rival_watch is not None else None
    except HandctlError as exc:
        warnings.append(str(exc))
        return None, None, {"error": str(exc)}
    deadlines = Deadlines.of(hand)
    verdict = judge(record, deadlines)
    own: list[int] = []
    shares = attribute(loop_stalls.rows(), record, deadlines.period_ns, own, rivals, work)
    shares["missed_unobserved"] += loop_stalls.overflow_missed
    void = below_the_loop(record, work)
    if void:
        shares, own = _void(shares), []
        warnings.append(void)
    short = observed_text(verdict.figures["seconds"], run_s)
    summary = {
        "verdict": verdict.level,
        "reasons": list(verdict.reasons),
        **({"attribution_void": void} if void else {}),
        **({"run_s": round(run_s, 3)} if run_s is not None else {}),
        **({"too_short": short} if short else {}),
        **verdict.figures,
        **shares,
        "handctl_missed_at_ticks": own[:MAX_LISTED_TICKS],
        **work_figures(work, own),
        "probe_period_us": record.period_ns / 1e3,
        "scheduler": record.scheduler,
        "refused": list(record.refused),
        "rivals": sorted(set(rivals.rivals.values())) if rivals is not None else [],
    }
    peer_text = ""
    if peer is not None:
        peer_verdict = judge(peer, deadlines)
        f = peer_verdict.figures
        summary["sim_cpu"] = {
            "cpus": peer.scheduler.get("cpus"),
            "verdict": peer_verdict.level,
            "longest_stall_ms": f["longest_stall_ms"],
            "stalls_over_period": f["stalls_over_period"],
            "stalls_over_feedback_timeout": f["stalls_over_feedback_timeout"],
        }
        peer_text = (
            f"; on the simulated hand's CPU {peer.scheduler.get('cpus')} the host was "
            f"{peer_verdict.level.upper()} (longest stall {f['longest_stall_ms']:g} "
            f"ms, {f['stalls_over_feedback_timeout']} longer than the feedback "
            "timeout)"
        )
    stopped_on = sorted(
        {
            f.code.name
            for f in faults
            if f.code in (FaultCode.LOOP_OVERRUN, FaultCode.FEEDBACK_TIMEOUT)
        }
    )
    if stopped_on:
        warnings.append(
            stop_warning(
                stopped_on, verdict, shares, summary["rivals"], peer_text, bool(void), short
            )
        )
    return record, rivals, summary


def stop_warning(
    stopped_on: Sequence[str],
    verdict: Verdict,
    shares: Mapping[str, int],
    rivals: Sequence[str],
    peer_text: str = "",
    below: bool = False,
    short: str = "",
) -> str:
    """The warning of a run that stopped on ``stopped_on`` (LOOP_OVERRUN, FEEDBACK_TIMEOUT):
    the bare loop's verdict on the host beside it, and whose the missed ticks were
    (``attribute``'s ``shares``), every kind that has any said. ``below``: the bare loop ran
    below the loop (``below_the_loop``), so its verdict is no verdict on the host; nor is it
    when it ran too little of the run (``short``, ``observed_text``)."""
    if below:
        return (
            f"the run stopped on {', '.join(stopped_on)}; the bare timer loop beside it ran "
            f"below the loop, so it says nothing of the host (its own verdict "
            f"{verdict.level.upper()} includes the loop's ticks) nor of whose the "
            f"{shares['missed_unobserved']} missed ticks were"
            + peer_text
            + "; see 'handctl check --timing' and docs/timing.md"
        )
    said = (
        f"{short} (it saw it {verdict.level.upper()}"
        if short
        else f"the bare timer loop beside it says the host was {verdict.level.upper()}"
    )
    return (
        f"the run stopped on {', '.join(stopped_on)}; {said}"
        + "".join(f"; {r}" for r in verdict.reasons)
        + (")" if short else "")
        + f" (longest host stall {verdict.figures['longest_stall_ms']:g} ms; missed ticks: "
        f"{shares['missed_host']} the host's, "
        + (
            f"{shares['missed_host_slow_cpu']} its slow CPU's, "
            if shares["missed_host_slow_cpu"]
            else ""
        )
        + (
            f"{shares['missed_host_catch_up']} its catch-up ticks', "
            if shares["missed_host_catch_up"]
            else ""
        )
        + (
            f"{shares['missed_host_off_cpu']} with the loop held off its CPU, "
            if shares["missed_host_off_cpu"]
            else ""
        )
        + f"{shares['missed_handctl']} handctl's"
        + (
            f", {shares['missed_rival']} a real-time rival's: " + ", ".join(rivals)
            if shares["missed_rival"]
            else ""
        )
        + (
            # a stop in the first ticks comes before the bare loop's first wake-ups: said,
            # or the stop read as "0 the host's, 0 handctl's"
            f", {shares['missed_unobserved']} while the bare loop was not running "
            "(judged by no one)"
            if shares["missed_unobserved"]
            else ""
        )
        + ")"
        + peer_text
        + "; see 'handctl check --timing' and docs/timing.md"
    )
