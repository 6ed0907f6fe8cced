"""Real-time rivals: other tasks that can take the control loop's CPU away from it.

The bare timer loop beside a run (``handctl.hostprobe``) sits one priority above the control
loop, so that the loop's own ticks never delay it. That leaves one kind of host trouble it
cannot see: another task at SCHED_FIFO or SCHED_RR whose priority is at least the loop's and
which may run on the loop's CPU. While such a task runs, the loop waits (at an equal priority a
FIFO task is not preempted, it runs until it blocks) and the probe does not. On this project's
own machine two real-time runs started side by side held each other's loop for 13-59 ms with
the probe seeing nothing, and every one of those missed ticks was counted as handctl's.

So a small watcher process at the ordinary scheduler (``python -m handctl.rivals``) looks for
such tasks every ``interval`` and notes how much CPU time each used since the last look (from
``/proc/PID/task/TID/schedstat``). A missed tick that no host stall explains, but during which a
rival ran, is the rival's (``handctl.hostcheck.attribute``). Kernel threads are left out: the
kernel's per-CPU threads above any user priority (migration, the watchdog) run for
microseconds, and they are the host's in the probe's figures already.

handctl's own processes are never rivals: a run's simulated hand, bare loops, recording writer
and workers are its children (``--family``, the run's process id, and every process descended
from it, are left out), and what they cost the loop is the run's own. Under a caller's ``chrt -f
90`` the simulated hand inherited SCHED_FIFO 90 and was blamed as a rival of its own run.

``python -m handctl.rivals --cpu C --priority P [--interval S] [--exclude PID ...]
[--family PID] [--parent-pid PID]`` runs until SIGTERM, SIGINT or the parent's end, then writes
one JSON object to stdout (``RivalRecord.from_json`` reads it).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from handctl.errors import ConfigError
from handctl.hostfacts import ordinary_scheduling, parse_cpu_list
from handctl.parent_death import JsonHelper, die_with_parent, stop_on_signals

#: s: how often the watcher looks. A scan reads a few hundred small files (a few ms of CPU),
#: so twice a second costs well under 1 % of a CPU; a stall is matched to the interval it fell in.
INTERVAL_S = 0.5
#: s: a watcher that has not written its record this long after SIGTERM is killed (it may be
#: in the middle of a look, or importing handctl on a loaded machine).
_STOP_TIMEOUT_S = 30.0
_PF_KTHREAD = 0x00200000
#: Parents followed up from a task before giving up on finding ``family`` (a process tree is
#: rarely a dozen deep; this bounds a look at a /proc that changes under it).
_MAX_ANCESTRY = 64
_POLICIES = {1: "SCHED_FIFO", 2: "SCHED_RR"}


@dataclass(frozen=True)
class Rival:
    """One task that could hold the loop: its ids, name, policy, priority, CPUs, CPU time."""

    pid: int
    tid: int
    name: str
    policy: str
    priority: int
    cpus: tuple[int, ...]
    runtime_ns: int

    def label(self) -> str:
        return f"{self.name} (pid {self.pid}, tid {self.tid}, {self.policy} {self.priority})"


def _stat_fields(text: str) -> tuple[str, list[str]] | None:
    """The task's name and the fields after it (the name may hold spaces and parentheses)."""
    open_at, close_at = text.find("("), text.rfind(")")
    if open_at < 0 or close_at < open_at:
        return None
    return text[open_at + 1 : close_at], text[close_at + 2 :].split()


def _read(path: str) -> str | None:
    """A small file of /proc in one read (the task may have ended since it was listed)."""
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return None
    try:
        return os.read(fd, 4096).decode(errors="replace")
    except OSError:
        return None
    finally:
        os.close(fd)


def _listed(path: str) -> list[str]:
    try:
        return [name for name in os.listdir(path) if name.isdigit()]
    except OSError:
        return []


def descends_from(pid: str, family: int, proc: Path = Path("/proc")) -> bool:
    """Whether process ``pid`` is ``family`` or descended from it (its parents read from
    /proc; a process gone on the way is taken as not of the family)."""
    root, wanted, at = str(proc), str(family), pid
    for _ in range(_MAX_ANCESTRY):
        if at == wanted:
            return True
        stat = _read(f"{root}/{at}/task/{at}/stat")
        parsed = _stat_fields(stat) if stat is not None else None
        if parsed is None or len(parsed[1]) < 2 or parsed[1][1] in ("0", at):
            return False
        at = parsed[1][1]
    return False


def find_rivals(
    cpu: int | None,
    priority: int,
    exclude: Iterable[int] = (),
    proc: Path = Path("/proc"),
    family: int | None = None,
) -> list[Rival]:
    """Every user task at SCHED_FIFO or SCHED_RR, priority >= ``priority``, allowed on ``cpu``
    (any CPU when None), whose process is not in ``exclude`` nor ``family`` or descended from
    it (handctl's own: a run and its children).

    Only each task's ``stat`` is read (plain ``os`` calls: a look at a few hundred tasks costs
    a few ms); ``status`` and ``schedstat`` only for the few at a real-time priority.
    """
    skip = {str(pid) for pid in exclude}
    root = str(proc)
    found: list[Rival] = []
    for pid in _listed(root):
        if pid in skip:
            continue
        tasks = f"{root}/{pid}/task"
        for tid in _listed(tasks):
            task = f"{tasks}/{tid}"
            stat = _read(task + "/stat")
            parsed = _stat_fields(stat) if stat is not None else None
            if parsed is None or len(parsed[1]) < 39:
                continue
            name, fields = parsed
            policy, rt_priority, flags = int(fields[38]), int(fields[37]), int(fields[6])
            if policy not in _POLICIES or rt_priority < priority or flags & _PF_KTHREAD:
                continue
            status = _read(task + "/status") or ""
            allowed = next(
                (
                    parse_cpu_list(line.split(":", 1)[1])
                    for line in status.splitlines()
                    if line.startswith("Cpus_allowed_list:")
                ),
                (),
            )
            if cpu is not None and allowed and cpu not in allowed:
                continue
            if family is not None and descends_from(pid, family, proc):
                skip.add(pid)  # every thread of it
                break
            schedstat = (_read(task + "/schedstat") or "0").split()
            found.append(
                Rival(
                    int(pid),
                    int(tid),
                    name,
                    _POLICIES[policy],
                    rt_priority,
                    allowed,
                    int(schedstat[0]) if schedstat and schedstat[0].isdigit() else 0,
                )
            )
    return found


@dataclass(frozen=True)
class RivalRecord:
    """What the watcher saw: per look, the rivals that ran since the one before.

    ``spans`` rows are (start_ns, end_ns, tid, ran_ns): the task ran ``ran_ns`` of CPU time
    between two looks. ``rivals`` names every task seen, by tid.
    """

    cpu: int | None
    priority: int
    start_ns: int
    end_ns: int
    spans: tuple[tuple[int, int, int, int], ...]
    rivals: dict[int, str]

    def active(self, start_ns: int, end_ns: int) -> list[str]:
        """The rivals that ran during a look overlapping ``[start_ns, end_ns]``."""
        return sorted(
            {
                self.rivals.get(tid, str(tid))
                for s, e, tid, ran in self.spans
                if ran > 0 and s < end_ns and e > start_ns
            }
        )

    def as_json(self) -> dict[str, Any]:
        return {
            "cpu": self.cpu,
            "priority": self.priority,
            "start_ns": self.start_ns,
            "end_ns": self.end_ns,
            "spans": [list(s) for s in self.spans],
            "rivals": {str(k): v for k, v in self.rivals.items()},
        }

    @classmethod
    def from_json(cls, data: Any, source: str) -> RivalRecord:
        """A watcher's record; a malformed one names the key, what was expected and found."""
        if not isinstance(data, dict):
            raise ConfigError(source, "", "a JSON object", type(data).__name__)
        for key in ("priority", "start_ns", "end_ns"):
            if not isinstance(data.get(key), int):
                raise ConfigError(source, key, "an integer", data.get(key))
        spans = data.get("spans")
        if not isinstance(spans, list) or not all(
            isinstance(row, list) and len(row) == 4 and all(isinstance(v, int) for v in row)
            for row in spans
        ):
            raise ConfigError(source, "spans", "a list of [start_ns, end_ns, tid, ran_ns]", spans)
        rivals = data.get("rivals")
        if not isinstance(rivals, dict) or not all(k.isdigit() for k in rivals):
            raise ConfigError(source, "rivals", "an object of tid -> name", rivals)
        cpu = data.get("cpu")
        if cpu is not None and not isinstance(cpu, int):
            raise ConfigError(source, "cpu", "an integer or null", cpu)
        return cls(
            cpu,
            data["priority"],
            data["start_ns"],
            data["end_ns"],
            tuple((r[0], r[1], r[2], r[3]) for r in spans),
            {int(k): str(v) for k, v in rivals.items()},
        )


def watch(
    cpu: int | None,
    priority: int,
    exclude: set[int],
    interval_s: float,
    stop: list[bool],
    seconds: float | None = None,
    proc: Path = Path("/proc"),
    family: int | None = None,
) -> RivalRecord:
    """Look every ``interval_s`` until ``stop[0]`` (or ``seconds``) and keep what ran."""
    start = last = time.monotonic_ns()
    seen: dict[int, int] = {
        r.tid: r.runtime_ns for r in find_rivals(cpu, priority, exclude, proc, family)
    }
    names: dict[int, str] = {}
    spans: list[tuple[int, int, int, int]] = []
    end = None if seconds is None else start + round(seconds * 1e9)
    while not stop[0] and (end is None or last < end):
        time.sleep(interval_s)
        now = time.monotonic_ns()
        current = find_rivals(cpu, priority, exclude, proc, family)
        for rival in current:
            names[rival.tid] = rival.label()
            before = seen.get(rival.tid)
            # A task first seen now ran at most what it has in all, within this interval.
            ran = rival.runtime_ns - before if before is not None else rival.runtime_ns
            if ran > 0:
                spans.append((last, now, rival.tid, ran))
        seen = {r.tid: r.runtime_ns for r in current}
        last = now
    return RivalRecord(cpu, priority, start, last, tuple(spans), names)


class RivalWatch(JsonHelper):
    """The watcher as a child process, at the ordinary scheduler, from start to ``stop``.

    ``family``: a process whose descendants are not rivals (a run passes its own id)."""

    def __init__(
        self,
        cpu: int | None,
        priority: int,
        exclude: Iterable[int],
        family: int | None = None,
    ) -> None:
        args = [
            "--priority",
            str(priority),
            "--parent-pid",
            str(os.getpid()),
            "--exclude",
            *(str(pid) for pid in sorted(set(exclude) | {os.getpid()})),
        ]
        if cpu is not None:
            args += ["--cpu", str(cpu)]
        if family is not None:
            args += ["--family", str(family)]
        super().__init__("handctl.rivals", args, "the real-time rivals' watcher")
        # at once, not after its imports at a caller's SCHED_FIFO (it does so itself as well)
        ordinary_scheduling(self.proc.pid)

    def stop(self) -> RivalRecord:
        """End the watcher and read what it saw."""
        return RivalRecord.from_json(self.finish(_STOP_TIMEOUT_S), self.what)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m handctl.rivals", description=__doc__.split("\n\n")[0]
    )
    parser.add_argument("--cpu", type=int, help="the control loop's CPU (default: any)")
    parser.add_argument(
        "--priority", type=int, required=True, help="the loop's SCHED_FIFO priority"
    )
    parser.add_argument("--interval", type=float, default=INTERVAL_S, help="s between looks")
    parser.add_argument("--seconds", type=float, help="default: until SIGTERM or SIGINT")
    parser.add_argument("--exclude", type=int, nargs="*", default=[], help="process ids to skip")
    parser.add_argument(
        "--family", type=int, help="skip this process and every process descended from it"
    )
    parser.add_argument("--parent-pid", type=int, help="end when this process ends")
    args = parser.parse_args(argv)
    stop = stop_on_signals()
    # at the ordinary scheduler whatever it inherited: a watcher at a caller's SCHED_FIFO 90
    # would itself hold the loop it watches for
    ordinary_scheduling(0)
    exclude = set(args.exclude) | {os.getpid()}
    if args.parent_pid is not None and not die_with_parent(args.parent_pid):
        return 0
    record = watch(
        args.cpu, args.priority, exclude, args.interval, stop, args.seconds, family=args.family
    )
    json.dump(record.as_json(), sys.stdout)
    sys.stdout.write("\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
