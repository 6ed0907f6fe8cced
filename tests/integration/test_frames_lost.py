"""A run on the unix bus whose own receive queue lost frames says so: each lost frame shows
as a counter skip of the node whose frame it was, and the run said only "frames rejected by
the host's receive checks: counter_skip 3", as if the nodes had skipped them (found by an
outside audit of the first hour; ``handctl nodes`` and ``monitor`` said it).

The simulated hand is stepped on the unix bus while the host does not read, as a host
stopped or starved does, until the bus drops frames for it."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest

from handctl import cli
from handctl.config import HandConfig
from handctl.online.bus import open_bus
from handctl.online.drivers.hand import HandDriver
from handctl.protocol import Protocol
from handctl.session import _frames_lost
from handctl.sim.hand import SimulatedHand

from ..conftest import ROOT

#: node ticks the host does not read for: the hand sends some 3 frames a tick, and the unix
#: bus holds 64 for a receiver that does not read, past its socket's few datagrams
UNREAD_TICKS = 200


def test_frames_the_hosts_receive_queue_lost_are_in_the_summary(
    hand: HandConfig, protocol: Protocol, tmp_path: Path
) -> None:
    with (
        open_bus(f"unix:{tmp_path / 'bus'}", hand.bus) as host,
        open_bus(f"unix:{tmp_path / 'bus'}", hand.bus) as peer,
    ):
        sim = SimulatedHand(hand, peer, seed=0)
        driver = HandDriver(hand, protocol, host)
        summary: dict[str, Any] = {}
        driver.poll()
        _frames_lost(summary, driver)
        assert summary == {}  # nothing lost, nothing said
        for _ in range(UNREAD_TICKS):
            sim.step()
        for _ in range(UNREAD_TICKS):  # what its queue holds
            driver.poll()
        for _ in range(3):  # the frames held for the host, then the word of what it lost
            sim.step()
            driver.poll()
        _frames_lost(summary, driver)
        dropped = sim.ground_truth_summary()["transport"]["frames_dropped"]
    assert dropped > 0
    assert summary == {"frames_lost": dropped}
    skips = sum(n.rejects.as_dict()["counter_skip"] for n in driver.nodes)
    assert skips > 0  # what the run said alone, as if the nodes had skipped them


def test_frames_lost_are_printed_beside_the_rejects(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The printed summary says them, beside the counter skips they show as."""
    out = tmp_path / "summary.json"
    argv = ["run", "recipe", str(ROOT / "config/recipes/swap_two_cylinders.yaml")]
    assert cli.main([*argv, "--max-seconds", "0.05", "--summary-json", str(out)]) == 0
    summary = json.loads(out.read_text())
    capsys.readouterr()
    cli._print_run_summary(summary, None)
    assert "lost" not in capsys.readouterr().out
    cli._print_run_summary({**summary, "frames_lost": 7}, None)
    assert (
        "  frames the host's own receive queue lost (it read them too late): 7; they show "
        "among the counter skips (one skip for each run of frames lost of a node), which are "
        "then the host's, not the node's"
    ) in capsys.readouterr().out
