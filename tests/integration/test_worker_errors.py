"""An error raised in a worker process of a plan's or a bench's pool reaches the caller as
the error it was: a ``ConfigError`` with its file, key, expected and found, not a pool that
says a process "terminated abruptly" (a ``ConfigError`` could not be unpickled: its
``__init__`` takes four arguments, and the default rebuilds it from its message alone)."""

from __future__ import annotations

import pickle
from pathlib import Path

import pytest
import yaml

from handctl.analysis.model import AnalysisError
from handctl.config import load_hand
from handctl.errors import BusError, ConfigError, HandctlError, ProtocolError
from handctl.executor import ClusterLostError, SchedulerError, WorkerMemoryError, open_pool
from handctl.hostcheck import HostTimingError

from ..conftest import HAND_YAML


@pytest.mark.parametrize(
    "error",
    [
        ConfigError("hand.yaml", "fingers[0].joints[1].tau_max", "a number > 0", -1.0),
        SchedulerError("tcp://127.0.0.1:1", "a Dask scheduler", "connection refused"),
        ClusterLostError("tcp://127.0.0.1:1", "mid-plan", "nothing was written"),
        WorkerMemoryError("tcp://127.0.0.1:1", "tcp://127.0.0.1:2 (name 0)", "MemoryError"),
        AnalysisError("singular contact system"),
        BusError("no such interface"),
        ProtocolError("frame 0x101: 3 bytes"),
        HostTimingError("the host missed 3 ticks"),
    ],
    ids=lambda e: type(e).__name__,
)
def test_every_handctl_error_pickles_as_it_was(error: HandctlError) -> None:
    again = pickle.loads(pickle.dumps(error))
    assert type(again) is type(error)
    assert str(again) == str(error)
    assert again.__dict__ == error.__dict__


def test_a_config_error_in_a_worker_reaches_the_caller_whole(tmp_path: Path) -> None:
    data = yaml.safe_load(HAND_YAML.read_text())
    data["fingers"][0]["joints"][1]["tau_max"] = -1.0
    bad = tmp_path / "hand.yaml"
    bad.write_text(yaml.safe_dump(data, sort_keys=False))
    with pytest.raises(ConfigError) as here:
        load_hand(bad)
    with open_pool(2) as pool, pytest.raises(ConfigError) as there:
        pool.map(load_hand, [bad, bad])  # a loaded hand is not sent back whole (portable.py)
    assert (there.value.file, there.value.key) == (here.value.file, here.value.key)
    assert str(there.value) == str(here.value)
