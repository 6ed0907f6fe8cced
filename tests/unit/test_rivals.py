"""Real-time rivals: found in a /proc tree, read back from the watcher, and blamed for the
missed ticks they caused (``handctl.rivals``, ``handctl.hostcheck.attribute``)."""

from __future__ import annotations

from pathlib import Path

import pytest

from handctl.errors import ConfigError
from handctl.hostcheck import ProbeRecord, attribute
from handctl.rivals import RivalRecord, find_rivals

MS = 1_000_000
START = 10_000 * MS
KTHREAD = 0x00200000


def task(
    proc: Path,
    pid: int,
    tid: int,
    name: str,
    *,
    policy: int,
    priority: int,
    cpus: str = "0-1",
    flags: int = 0x400000,
    runtime_ns: int = 5_000_000,
    ppid: int = 1,
) -> None:
    """A task as the kernel lays it out: stat (policy field 41, rt_priority 40, flags 9),
    status (Cpus_allowed_list) and schedstat (CPU time in ns first)."""
    d = proc / str(pid) / "task" / str(tid)
    d.mkdir(parents=True)
    after = ["S", str(ppid), str(pid), str(pid), "0", "-1", str(flags)] + ["0"] * 29
    after += ["1", str(priority), str(policy), "0", "0", "0"]  # processor, rt_priority, policy
    (d / "stat").write_text(f"{tid} ({name}) " + " ".join(after) + "\n")
    (d / "status").write_text(f"Name:\t{name}\nCpus_allowed_list:\t{cpus}\n")
    (d / "schedstat").write_text(f"{runtime_ns} 1000 7\n")


@pytest.fixture
def proc(tmp_path: Path) -> Path:
    root = tmp_path / "proc"
    task(root, 10, 10, "migration/1", policy=1, priority=99, flags=KTHREAD)
    task(root, 20, 20, "rt loop", policy=1, priority=80, cpus="0-1")  # a name with a space
    task(root, 20, 21, "worker (x)", policy=2, priority=90, cpus="1")
    task(root, 30, 30, "pinned", policy=1, priority=85, cpus="0")
    task(root, 40, 40, "low", policy=1, priority=50)
    task(root, 50, 50, "bash", policy=0, priority=0)
    task(root, 60, 60, "ours", policy=1, priority=81)
    (root / "self").mkdir()  # not a process
    return root


def test_rivals_are_user_tasks_at_the_loops_priority_or_above_allowed_on_its_cpu(
    proc: Path,
) -> None:
    found = find_rivals(1, 80, exclude=[60], proc=proc)
    assert sorted((r.pid, r.tid, r.name, r.policy, r.priority) for r in found) == [
        (20, 20, "rt loop", "SCHED_FIFO", 80),
        (20, 21, "worker (x)", "SCHED_RR", 90),
    ]
    assert {r.runtime_ns for r in found} == {5_000_000}
    # On CPU 0 the pinned one is a rival and the worker is not; without a CPU, all of them.
    assert sorted(r.tid for r in find_rivals(0, 80, exclude=[60], proc=proc)) == [20, 30]
    assert sorted(r.tid for r in find_rivals(None, 81, proc=proc)) == [21, 30, 60]


def test_a_task_that_ends_while_looked_at_is_passed_over(proc: Path) -> None:
    (proc / "20" / "task" / "21" / "stat").unlink()
    assert [r.tid for r in find_rivals(1, 80, exclude=[60], proc=proc)] == [20]


def test_a_runs_own_processes_are_never_its_rivals(proc: Path) -> None:
    """Under a caller's ``chrt -f 90`` a run's simulated hand inherited SCHED_FIFO 90 and was
    named as the run's own rival: the run (``family``) and all it started are left out, to any
    depth, and only they."""
    task(proc, 100, 100, "handctl run", policy=1, priority=90, ppid=50)
    task(proc, 101, 101, "handctl sim", policy=1, priority=90, ppid=100)
    task(proc, 101, 102, "node timer", policy=1, priority=90, ppid=100)
    task(proc, 103, 103, "pool worker", policy=1, priority=90, ppid=101)  # a grandchild
    task(proc, 104, 104, "stranger", policy=1, priority=90, ppid=50)  # the run's sibling
    found = find_rivals(1, 80, exclude=[60], proc=proc, family=100)
    assert sorted(r.tid for r in found) == [20, 21, 104]
    assert {101, 102, 103} <= {r.tid for r in find_rivals(1, 80, exclude=[60], proc=proc)}


def record(stall_ms: list[tuple[float, float]]) -> ProbeRecord:
    rows = [
        [i, START + round(due * MS), START + round((due + length) * MS), round(length)]
        for i, (due, length) in enumerate(stall_ms)
    ]
    return ProbeRecord.from_json(
        {
            "period_ns": MS // 2,
            "start_ns": START,
            "end_ns": START + 10_000 * MS,
            "wakeups": 20_000,
            "lateness_hist_us": {"20": 20_000},
            "lateness_max_ns": 20_000,
            "stalls": rows,
        },
        "test",
    )


def rivals(spans: list[tuple[float, float, int]]) -> RivalRecord:
    return RivalRecord.from_json(
        {
            "cpu": 1,
            "priority": 80,
            "start_ns": START,
            "end_ns": START + 10_000 * MS,
            "spans": [
                [START + round(a * MS), START + round(b * MS), 7, ran] for a, b, ran in spans
            ],
            "rivals": {"7": "spin (pid 7, tid 7, SCHED_FIFO 80)"},
        },
        "test",
    )


def test_a_miss_no_host_stall_explains_is_a_rivals_if_one_ran_then() -> None:
    host = record([(500.0, 4.0)])  # 500..504 ms
    loop = [
        (10, START + 501 * MS, START + 503 * MS, 2),  # the host's, whatever ran
        (20, START + 1_200 * MS, START + 1_213 * MS, 13),  # a rival ran 1000..1500 ms
        (30, START + 2_200 * MS, START + 2_202 * MS, 2),  # the rival idled 2000..2500 ms
        (40, START + 3_200 * MS, START + 3_202 * MS, 2),  # no look covers it
    ]
    watched = rivals([(1000.0, 1500.0, 40 * MS), (2000.0, 2500.0, 0)])
    own: list[int] = []
    shares = attribute(loop, host, MS, own, watched)
    assert (shares["missed_host"], shares["missed_rival"], shares["missed_handctl"]) == (2, 13, 4)
    assert own == [30, 40]
    # Without the watcher's record the same misses are handctl's, as before.
    assert attribute(loop, host, MS)["missed_handctl"] == 17
    assert watched.active(START + 1_100 * MS, START + 1_101 * MS) == [
        "spin (pid 7, tid 7, SCHED_FIFO 80)"
    ]


@pytest.mark.parametrize(
    ("key", "value", "expected"),
    [
        ("spans", [[1, 2, 3]], "a list of [start_ns, end_ns, tid, ran_ns]"),
        ("rivals", {"x": "y"}, "an object of tid -> name"),
        ("start_ns", "soon", "an integer"),
        ("cpu", "one", "an integer or null"),
    ],
)
def test_a_bad_watcher_record_names_the_key(key: str, value: object, expected: str) -> None:
    good = rivals([]).as_json()
    with pytest.raises(ConfigError) as info:
        RivalRecord.from_json({**good, key: value}, "w.json")
    assert key in str(info.value) and expected in str(info.value)
    assert RivalRecord.from_json(good, "w.json") == rivals([])
