"""One handctl host per bus on a machine (``handctl/online/buslock.py``): a second run or
jog started while a first is still in its own start-up was let through its listen (the first
had sent nothing to hear), ran its timing check at real-time priority on the first's CPU,
and the first lost its ticks and latched every node's TIMEOUT (found by an outside audit).
The holder here is another process, as the first run would be."""

from __future__ import annotations

import subprocess
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest

from handctl.config import HandConfig
from handctl.errors import BusError
from handctl.online.bus import open_bus
from handctl.online.buslock import lock_path, take_bus
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
    assert lock_path(spec) == lock_path(BusSpec("unix", f"{tmp_path}/./"))
    assert lock_path(spec) != lock_path(BusSpec("unix", str(tmp_path / "other")))
    with held_by_another_process(spec) as pid:
        assert list(tmp_path.iterdir()) == []
        for _ in range(2):  # each time, and the refusal leaves the holder's lock as it was
            with pytest.raises(BusError) as refused:
                take_bus(spec, "this run")
            said = str(refused.value)
            assert said.startswith(f"another handctl host holds unix:{tmp_path} on this ")
            assert f"(pid {pid}, since " in said
            assert said.endswith("stop it first, or wait for it to end; this run sent nothing")
    # the holder gone, however it ended: free, and held by this one now, against the next
    with take_bus(spec, "this run"), pytest.raises(BusError, match="another handctl host holds"):
        take_bus(spec, "this run")
    take_bus(spec, "this run").release()


def test_the_lock_file_goes_with_its_holder_and_a_killed_holders_is_taken_over(
    tmp_path: Path,
) -> None:
    """One file per bus ever used was left in the temporary directory (150 in a day of the
    suite's private unix buses)."""
    spec = BusSpec("unix", str(tmp_path))
    path = lock_path(spec)
    assert path is not None
    take_bus(spec, "this run").release()
    assert not path.exists()
    # a holder killed leaves its file; the next one takes it over and removes it
    code = (
        "import os, signal\n"
        "from handctl.online.buslock import take_bus\n"
        "from handctl.online.busspec import BusSpec\n"
        f"lock = take_bus(BusSpec('unix', {str(tmp_path)!r}), 'the holder')\n"
        "os.kill(os.getpid(), signal.SIGKILL)\n"
    )
    killed = subprocess.run([sys.executable, "-c", code], cwd=ROOT, check=False)
    assert killed.returncode == -9
    assert path.exists()
    with take_bus(spec, "this run"):
        pass
    assert not path.exists()


def test_a_lock_file_removed_between_open_and_lock_is_opened_again(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A taker that opened the file just before its holder removed it locks a file the path
    no longer names: a third would then create the path's file anew and hold the bus beside
    it. Here the holder lets go between this taker's open and its lock."""
    from handctl.online import buslock

    spec = BusSpec("unix", str(tmp_path))
    path = lock_path(spec)
    assert path is not None
    opened = buslock._open_lock
    opens: list[int] = []

    def opened_then_removed(spec: BusSpec, path: Path, who: str) -> int:
        fd = opened(spec, path, who)
        opens.append(fd)
        if len(opens) == 1:
            path.unlink()  # what a holder's release does
        return fd

    monkeypatch.setattr(buslock, "_open_lock", opened_then_removed)
    with take_bus(spec, "this run"):
        assert len(opens) == 2
        monkeypatch.setattr(buslock, "_open_lock", opened)
        with pytest.raises(BusError, match="another handctl host holds"):
            take_bus(spec, "this run")  # the path's file is the one held
    assert not path.exists()


def test_lock_files_by_bus() -> None:
    assert lock_path(BusSpec("virtual", "x")) is None  # inside one process
    assert lock_path(BusSpec("sim", "")) is None
    socketcan = lock_path(BusSpec("socketcan", "can0"))
    assert socketcan is not None and socketcan.name == "handctl-bus-socketcan-can0.lock"
    other = lock_path(BusSpec("pcan", "PCAN_USBBUS1/x:y"))
    assert other is not None and other.name == "handctl-bus-pcan-PCAN_USBBUS1_x_y.lock"


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
