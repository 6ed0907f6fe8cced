"""One handctl host per bus on a machine (``handctl/online/buslock.py``): a second run or
jog started while a first is still in its own start-up was let through its listen (the first
had sent nothing to hear), ran its timing check at real-time priority on the first's CPU,
and the first lost its ticks and latched every node's TIMEOUT (found by an outside audit).
The holder here is another process, as the first run would be."""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest

from handctl.config import HandConfig
from handctl.errors import BusError
from handctl.online.bus import open_bus
from handctl.online.buslock import lock_name, take_bus
from handctl.online.busspec import BusSpec
from handctl.online.recipes.loader import load_recipe
from handctl.session import RunRequest, run_recipe

from ..conftest import ROOT
from .rig import CLOSE_AND_HOLD_2S


@contextmanager
def held_by_another_process(spec: BusSpec) -> Iterator[int]:
    """The bus's host lock held by another process until the block ends; yields its pid."""
    code = (
        "import sys, time\n"
        "from handctl.online.buslock import take_bus\n"
        "from handctl.online.busspec import BusSpec\n"
        f"lock = take_bus(BusSpec({spec.interface!r}, {spec.channel!r}), 'the holder')\n"
        "print('held', flush=True)\n"
        "sys.stdin.read()\n"
    )
    with subprocess.Popen(
        [sys.executable, "-c", code],
        cwd=ROOT,
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
    ) as holder:
        assert holder.stdout is not None and holder.stdin is not None
        assert holder.stdout.readline() == "held\n"
        try:
            yield holder.pid
        finally:
            holder.stdin.close()  # it ends, and the kernel drops its lock
            holder.wait(timeout=30)


def test_a_second_host_is_refused_naming_the_first_and_takes_the_bus_once_it_ends(
    tmp_path: Path,
) -> None:
    spec = BusSpec("unix", str(tmp_path))
    # by the directory, however written; and none in it: it holds the participants' sockets
    assert lock_name(spec) == lock_name(BusSpec("unix", f"{tmp_path}/./"))
    assert lock_name(spec) != lock_name(BusSpec("unix", str(tmp_path / "other")))
    with held_by_another_process(spec) as pid:
        assert list(tmp_path.iterdir()) == []
        for _ in range(2):  # each time, and the refusal leaves the holder's lock as it was
            with pytest.raises(BusError) as refused:
                take_bus(spec, "this run")
            said = str(refused.value)
            assert said.startswith(f"another handctl host holds unix:{tmp_path} on this ")
            assert f"(pid {pid}: {sys.executable} -c " in said
            assert said.endswith("stop it first, or wait for it to end; this run sent nothing")
    # the holder gone, however it ended: free, and held by this one now, against the next
    with take_bus(spec, "this run"), pytest.raises(BusError, match="another handctl host holds"):
        take_bus(spec, "this run")
    take_bus(spec, "this run").release()


def test_a_killed_holder_frees_the_bus_and_nothing_is_left_behind(tmp_path: Path) -> None:
    """The lock was a file in the temporary directory: one was left for every unix bus ever
    used (150 in a day of the suite), a killed holder's kept other users off the bus, and
    the file removed by hand while a run started let a second host in (found by outside
    audits). It is a name in the abstract socket namespace now: nothing on disk."""
    spec = BusSpec("unix", str(tmp_path))
    code = (
        "import os, signal\n"
        "from handctl.online.buslock import take_bus\n"
        "from handctl.online.busspec import BusSpec\n"
        f"lock = take_bus(BusSpec('unix', {str(tmp_path)!r}), 'the holder')\n"
        "os.kill(os.getpid(), signal.SIGKILL)\n"
    )
    killed = subprocess.run([sys.executable, "-c", code], cwd=ROOT, check=False)
    assert killed.returncode == -9
    with take_bus(spec, "this run"):
        name = lock_name(spec)
        assert name is not None
        assert not [f for f in os.listdir(tempfile.gettempdir()) if name in f]
        with pytest.raises(BusError, match="another handctl host holds"):
            take_bus(spec, "this run")
    assert list(tmp_path.iterdir()) == []


def test_a_link_at_the_old_lock_file_s_path_writes_nothing_through_it(tmp_path: Path) -> None:
    """A symbolic link planted at the lock file's predictable path was followed: the file it
    named was emptied and the holder's pid written into it, by a run as root (found by an
    outside audit). No file is opened now."""
    victim = tmp_path / "victim.txt"
    victim.write_text("mine\n")
    spec = BusSpec("socketcan", "can0")
    planted = Path(tempfile.gettempdir()) / "handctl-bus-socketcan-can0.lock"
    if not planted.exists() and not planted.is_symlink():
        planted.symlink_to(victim)
        try:
            take_bus(spec, "this run").release()
        finally:
            planted.unlink()
    else:
        take_bus(spec, "this run").release()
    assert victim.read_text() == "mine\n"


def test_lock_names_by_bus() -> None:
    assert lock_name(BusSpec("virtual", "x")) is None  # inside one process
    assert lock_name(BusSpec("sim", "")) is None
    assert lock_name(BusSpec("socketcan", "can0")) == "handctl-bus-socketcan-can0"
    assert lock_name(BusSpec("pcan", "PCAN_USBBUS1/x:y")) == "handctl-bus-pcan-PCAN_USBBUS1_x_y"
    long = lock_name(BusSpec("pcan", "x" * 300))
    assert long is not None and len(long) <= 107


def test_a_run_on_a_bus_another_handctl_host_holds_sends_nothing(
    hand: HandConfig, tmp_path: Path
) -> None:
    """The run is refused before its listen and its timing check, with nothing sent: a
    listener that was on the bus all along heard nothing."""
    recipe_file = tmp_path / "hold.yaml"
    recipe_file.write_text(CLOSE_AND_HOLD_2S)
    recipe = load_recipe(recipe_file, hand)
    bus_dir = tmp_path / "bus"
    bus_dir.mkdir()
    spec = BusSpec("unix", str(bus_dir))
    with open_bus(str(spec), hand.bus) as listener, held_by_another_process(spec) as pid:
        with pytest.raises(BusError, match=f"another handctl host holds .*pid {pid}"):
            run_recipe(RunRequest(hand=hand, recipe=recipe, bus=str(spec)))
        assert listener.drain(limit=10**6) == []


def test_a_replay_onto_a_bus_another_handctl_host_holds_sends_nothing(
    hand: HandConfig, tmp_path: Path
) -> None:
    """``replay --to-bus`` takes the same lock: it sent its frames beside a run that was
    still in its start-up, where the listen had nothing to hear."""
    from handctl.recording.frames import to_bus
    from handctl.recording.reader import open_recording

    from .rig import short_recipe
    from .test_recording import record_run

    recorded = record_run(hand, short_recipe(hand, tmp_path), tmp_path / "run.mcap")
    bus_dir = tmp_path / "bus"
    bus_dir.mkdir()
    spec = BusSpec("unix", str(bus_dir))
    with open_bus(str(spec), hand.bus) as listener, held_by_another_process(spec) as pid:
        with pytest.raises(BusError, match=f"another handctl host holds .*pid {pid}.*replay"):
            to_bus(open_recording(recorded.path), str(spec), sleep=lambda _s: None)
        assert listener.drain(limit=10**6) == []
