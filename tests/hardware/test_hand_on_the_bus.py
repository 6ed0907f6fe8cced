"""A real hand on a real bus: opt in with ``HANDCTL_HARDWARE_BUS=SPEC`` (e.g. ``socketcan:can0``)
and ``pytest -m hardware tests/hardware``; ``HANDCTL_HARDWARE_HAND=HAND.yaml`` names the hand
(default: the packaged one). Without the variable every test here is skipped. A run on a
host that fails the timing check is refused, as ``handctl run`` refuses it;
``HANDCTL_HARDWARE_ACCEPT_MISSED_DEADLINES=1`` runs the zero-torque hold anyway, and
``HANDCTL_HARDWARE_RT=1`` runs it at real-time priority, as ``handctl run recipe --rt``.

Nothing here moves the hand: the first test only listens, the second commands zero torque.
The same tests run against the simulated hand as a peer on any bus
(``handctl sim --bus unix:DIR`` beside ``HANDCTL_HARDWARE_BUS=unix:DIR``).
"""

from __future__ import annotations

import os
import time
from pathlib import Path

import pytest

from handctl.cli import DEFAULT_HAND
from handctl.config import HandConfig, load_hand
from handctl.online.bus import open_bus
from handctl.online.drivers.hand import HandDriver
from handctl.online.loop import Outcome
from handctl.online.recipes.loader import load_recipe
from handctl.protocol import load_protocol
from handctl.session import RunRequest, run_recipe

BUS = os.environ.get("HANDCTL_HARDWARE_BUS", "")
#: How long the nodes get to be heard: their feedback comes every 1 ms, heartbeats slower.
LISTEN_S = 2.0

pytestmark = [
    pytest.mark.hardware,
    pytest.mark.skipif(not BUS, reason="needs a hand on a bus: set HANDCTL_HARDWARE_BUS"),
]


@pytest.fixture(scope="module")
def hand() -> HandConfig:
    return load_hand(os.environ.get("HANDCTL_HARDWARE_HAND", str(DEFAULT_HAND)))


def test_every_node_answers_while_the_host_only_listens(hand: HandConfig) -> None:
    with open_bus(BUS, hand.bus) as bus:
        driver = HandDriver(hand, load_protocol(), bus)
        deadline = time.monotonic() + LISTEN_S
        state = driver.poll()
        while time.monotonic() < deadline and (
            (state.feedback_ns < 0).any() or -1 in state.node_state
        ):
            time.sleep(hand.bus.period_s)
            state = driver.poll()
    silent = [f.name for f, s in zip(hand.fingers, state.node_state, strict=True) if s == -1]
    assert not silent, f"no feedback within {LISTEN_S} s from {silent}"
    assert (state.feedback_ns >= 0).all()
    rejects = {k: v for k, v in driver.reject_counts().items() if v}
    assert not {k: v for k, v in rejects.items() if k != "unexpected_id"}, rejects


def test_a_zero_torque_hold_ends_clean(hand: HandConfig, tmp_path: Path) -> None:
    recipe_path = tmp_path / "zero_hold.yaml"
    zeros = ", ".join(["0.0"] * hand.n_joints)
    recipe_path.write_text(
        f"recipe: zero_hold\nphases:\n  - name: hold\n"
        f"    torques: [{zeros}]\n    ramp_s: 0.1\n    max_s: 2.0\n"
        f"    on_timeout: next\n"
    )
    accept = os.environ.get("HANDCTL_HARDWARE_ACCEPT_MISSED_DEADLINES") == "1"
    report = run_recipe(
        RunRequest(
            hand=hand,
            recipe=load_recipe(recipe_path, hand),
            bus=BUS,
            accept_missed_deadlines=accept,
            # as `handctl run recipe --rt`: the hold without it lost ticks to an ordinary
            # host's scheduling, and nothing asked for it (an outside audit)
            realtime_priority=os.environ.get("HANDCTL_HARDWARE_RT") == "1",
        )
    )
    assert report.result.outcome is Outcome.COMPLETED, report.result.message
    assert report.result.faults == []
    assert report.summary["max_abs_tau_nm"] == dict.fromkeys(hand.joint_names, 0.0)
