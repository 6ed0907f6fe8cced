"""What a host is, as far as real time goes: kernel, limits, CPUs, frequency scaling, and
which CPUs a real-time run takes. Read once, as found; ``handctl.hostcheck`` turns it into
advice beside the timing check's verdict.
"""

from __future__ import annotations

import os
import platform
import resource
from contextlib import suppress
from dataclasses import dataclass
from pathlib import Path
from typing import Any


@dataclass(frozen=True)
class HostFacts:
    """What the kernel and the limits of this process say about real time, as found."""

    realtime_kernel: bool | None  # /sys/kernel/realtime == 1 (None: the file is absent)
    preemption: str  # from uname -v: PREEMPT_RT, PREEMPT_DYNAMIC, PREEMPT, or none
    cmdline_preempt: str  # preempt= on the kernel command line, "" if not given
    rtprio_limit: int  # RLIMIT_RTPRIO soft limit (ulimit -r); -1 unlimited
    memlock_limit_kb: int  # RLIMIT_MEMLOCK soft limit (ulimit -l); -1 unlimited
    privileged: bool  # CAP_SYS_NICE in the effective set (root has it)
    cpus: tuple[int, ...]  # CPUs this process may run on
    isolated: tuple[int, ...]  # /sys/devices/system/cpu/isolated
    governors: dict[int, str]  # cpufreq scaling_governor per CPU ({} if no cpufreq)
    virtual_machine: bool  # the CPU says it runs under a hypervisor
    #: cgroup v1: this process's cpu group's real-time budget, (its cpu.rt_runtime_us file,
    #: µs per period); None where there is none (cgroup v2 has no real-time groups)
    rt_runtime: tuple[str, int] | None = None

    def as_json(self) -> dict[str, Any]:
        return {
            "realtime_kernel": self.realtime_kernel,
            "preemption": self.preemption,
            "cmdline_preempt": self.cmdline_preempt,
            "rtprio_limit": self.rtprio_limit,
            "memlock_limit_kb": self.memlock_limit_kb,
            "privileged": self.privileged,
            "cpus": list(self.cpus),
            "isolated": list(self.isolated),
            "governors": {str(k): v for k, v in self.governors.items()},
            "virtual_machine": self.virtual_machine,
            "rt_runtime_us": None if self.rt_runtime is None else list(self.rt_runtime),
        }


def preemption_model(uname_version: str) -> str:
    """The preemption model a kernel's version string names (``uname -v``)."""
    words = uname_version.replace("_", " ").upper().split()
    text = " " + " ".join(words) + " "
    if " PREEMPT RT " in text:
        return "PREEMPT_RT"
    if " PREEMPT DYNAMIC " in text:
        return "PREEMPT_DYNAMIC"
    if " PREEMPT " in text:
        return "PREEMPT"
    return "none"


def parse_cpu_list(text: str) -> tuple[int, ...]:
    """A kernel CPU list ("0-2,5") as numbers; "" is none."""
    cpus: list[int] = []
    for part in text.strip().split(","):
        if not part:
            continue
        lo, _, hi = part.partition("-")
        cpus += range(int(lo), int(hi or lo) + 1)
    return tuple(cpus)


def _read(path: str) -> str | None:
    try:
        return Path(path).read_text().strip()
    except OSError:
        return None


def _limit(which: int, unit: int = 1) -> int:
    soft = resource.getrlimit(which)[0]
    return -1 if soft == resource.RLIM_INFINITY else soft // unit


def gather_facts() -> HostFacts:
    realtime = _read("/sys/kernel/realtime")
    cpus = tuple(sorted(os.sched_getaffinity(0)))
    governors = {}
    for cpu in cpus:
        gov = _read(f"/sys/devices/system/cpu/cpu{cpu}/cpufreq/scaling_governor")
        if gov:
            governors[cpu] = gov
    cmdline = _read("/proc/cmdline") or ""
    preempt = next((w.partition("=")[2] for w in cmdline.split() if w.startswith("preempt=")), "")
    status = _read("/proc/self/status") or ""
    cap_eff = next(
        (int(line.split()[1], 16) for line in status.splitlines() if line.startswith("CapEff:")), 0
    )
    cpuinfo = _read("/proc/cpuinfo") or ""
    return HostFacts(
        realtime_kernel=None if realtime is None else realtime == "1",
        preemption=preemption_model(platform.uname().version),
        cmdline_preempt=preempt,
        rtprio_limit=_limit(resource.RLIMIT_RTPRIO),
        memlock_limit_kb=_limit(resource.RLIMIT_MEMLOCK, 1024),
        privileged=bool(cap_eff & (1 << 23)),  # CAP_SYS_NICE
        cpus=cpus,
        isolated=parse_cpu_list(_read("/sys/devices/system/cpu/isolated") or ""),
        governors=governors,
        virtual_machine=" hypervisor" in cpuinfo,
        rt_runtime=rt_runtime(),
    )


def rt_runtime(
    cgroups: Path = Path("/proc/self/cgroup"), root: Path = Path("/sys/fs/cgroup")
) -> tuple[str, int] | None:
    """This process's cgroup v1 cpu group's ``cpu.rt_runtime_us`` (the file, its value): a
    group with 0 refuses SCHED_FIFO even to a process with CAP_SYS_NICE, whose refusal was
    then said as 'ulimit -r' or CAP_SYS_NICE, which it had. None where not found."""
    for line in (_read(str(cgroups)) or "").splitlines():
        _, controllers, group = [*line.split(":", 2), "", ""][:3]
        if "cpu" not in controllers.split(","):
            continue
        for mount in dict.fromkeys((controllers, "cpu", "cpu,cpuacct", "cpuacct,cpu")):
            path = root / mount / group.strip("/") / "cpu.rt_runtime_us"
            value = _read(str(path))
            if value is not None and value.lstrip("-").isdigit():
                return str(path), int(value)
    return None


def plan_cpus(allowed: set[int], isolated: set[int]) -> tuple[int | None, int | None]:
    """The CPU of the control loop and the one of the simulated hand, on >= 2 CPUs.

    The loop takes an isolated CPU if there is one, else the highest CPU (CPU 0 usually takes
    the most interrupts and housekeeping); the simulated hand takes the lowest other one. On
    one CPU there is nothing to separate: (None, None).
    """
    if len(allowed) < 2:
        return None, None
    loop = max(isolated & allowed) if isolated & allowed else max(allowed)
    return loop, min(allowed - {loop})


def ordinary_scheduling(pid: int) -> None:
    """Put process ``pid`` (0: this thread) at the ordinary scheduler, SCHED_OTHER.

    A child inherits its parent's policy: under a caller's ``chrt -f 90`` (or a service unit's
    real-time policy) the helpers of a run (the simulated hand, the bare timer loop, the
    rivals' watcher) ran at SCHED_FIFO 90, above the control loop, and the watcher blamed the
    run's own simulated hand as a real-time rival. Each gets the scheduling handctl means it to
    have: this, unless handctl raises it itself (``--rt``, the bare loop's priority).
    Lowering one's own child needs no privilege; a process already gone is left alone.
    """
    with suppress(OSError, AttributeError):  # gone already, or no such call on this system
        os.sched_setscheduler(pid, os.SCHED_OTHER, os.sched_param(0))


def rttime_note() -> list[str]:
    """What a SIGXCPU means when this thread runs at a real-time policy: the soft
    ``RLIMIT_RTTIME`` (µs of CPU time at SCHED_FIFO or SCHED_RR without a blocking call),
    with its value; nothing otherwise (then it is ``ulimit -t``, or someone's ``kill``).
    Said, since "interrupted by SIGXCPU" points nowhere near ``prlimit --rttime``."""
    if os.sched_getscheduler(0) not in (os.SCHED_FIFO, os.SCHED_RR):
        return []
    soft, hard = resource.getrlimit(resource.RLIMIT_RTTIME)
    if soft == resource.RLIM_INFINITY:
        return []
    shown = "unlimited" if hard == resource.RLIM_INFINITY else f"{hard} µs"
    return [
        f"SIGXCPU at {'SCHED_FIFO' if os.sched_getscheduler(0) == os.SCHED_FIFO else 'SCHED_RR'}"
        f": the soft RLIMIT_RTTIME is {soft} µs ({soft / 1e3:g} ms; hard {shown}) of CPU "
        "time at a real-time priority without blocking, and the kernel sends SIGXCPU past "
        "it; raise it ('prlimit --rttime', LimitRTTIME= of a service unit) or run without --rt"
    ]


def affinity(pid: int) -> list[int] | None:
    """The CPUs a process (0: this thread) may run on; None if it is gone."""
    try:
        return sorted(os.sched_getaffinity(pid))
    except ProcessLookupError:
        return None
