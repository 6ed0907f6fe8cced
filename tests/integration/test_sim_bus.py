"""The simulated hand as a bus peer: conformance to the DBC, the watchdog, both ways to run."""

from __future__ import annotations

import dataclasses
import math
import re
import signal as sig_module
import subprocess
import sys
import threading
import time
from collections import Counter
from pathlib import Path

import pytest

from handctl.config import HandConfig
from handctl.online.bus import open_bus
from handctl.sim.hand import SimulatedHand, standalone

from ..conftest import ROOT
from ..dbc import DB
from .test_sim_support import SimHost, crc8_autosar, crc_ok, enable_all, sim_and_host


def _session(host: SimHost) -> None:
    """A session that visits every state: boot, enable, torques, disable, e-stop, reset."""
    n = host.hand.n_joints
    host.run(5)
    enable_all(host)
    for k in range(250):
        host.tick([0.1 * math.sin(k / 20.0)] * n)
    host.command("disable", [2])
    host.run(20, [0.05] * n)
    host.send("EStop", None, (1,))
    host.run(10)
    host.command("fault_reset")
    host.run(20)


def test_crc_reference_value() -> None:
    assert crc8_autosar(b"123456789") == 0xDF  # the spec's check value


def test_every_frame_conforms_to_the_dbc(hand: HandConfig, channel: str) -> None:
    with sim_and_host(hand, channel) as (_, host):
        _session(host)
        ticks = host.sim.ticks
    assert host.heard
    last_counter: dict[int, int] = {}
    for h in host.heard:
        message = DB.get_message_by_frame_id(h.id)  # raises on an id outside the DBC
        assert message.senders and message.senders[0].startswith("FINGER"), message.name
        assert len(h.frame.data) == message.length, message.name
        assert crc_ok(h.frame), f"{message.name} at tick {h.tick}"
        counter = h.frame.data[1]
        if h.id in last_counter:
            assert counter == (last_counter[h.id] + 1) & 0xFF, f"{message.name} tick {h.tick}"
        last_counter[h.id] = counter
        signals = h.signals()
        for signal in message.signals:
            if signal.minimum is not None:
                assert signal.minimum <= signals[signal.name] <= signal.maximum
        if "State" in signals:
            assert signals["State"] in (0, 1, 2)
        if "FaultBits" in signals:
            assert signals["FaultBits"] & 0xE0 == 0  # reserved bits
    for tick in {h.tick for h in host.heard}:
        ids = [h.id for h in host.heard if h.tick == tick]
        assert ids == sorted(ids)  # frames queued together leave by arbitration order
    counts = Counter(h.id for h in host.heard)
    for finger in hand.fingers:
        can_ids = finger.can_ids
        assert counts[can_ids.feedback] == ticks  # every 1 ms, in every state
        assert counts[can_ids.heartbeat] == math.ceil(ticks / 100)
        uptimes = [h.signals()["Uptime"] for h in host.heard if h.id == can_ids.heartbeat]
        assert uptimes == list(range(0, ticks, 100))
        # periodic Status plus one per state change: boot 0, enable, (disable), e-stop, reset
        changes = 4 if finger.node_id == 2 else 3
        assert counts[can_ids.status] == math.ceil(ticks / 100) + changes


def test_states_seen_on_the_bus(hand: HandConfig, channel: str) -> None:
    with sim_and_host(hand, channel) as (_, host):
        _session(host)
    states = [h.signals()["State"] for h in host.of("Status", 2)]
    # boot DISABLED, ENABLED, DISABLED (disable), FAULT (e-stop), DISABLED (reset)
    assert [s for i, s in enumerate(states) if i == 0 or s != states[i - 1]] == [0, 1, 0, 2, 0]
    estop = [h.signals() for h in host.of("Feedback", 1) if h.signals()["State"] == 2]
    assert estop and all(s["FaultBits"] & 0x02 for s in estop)


def test_watchdog_zeroes_torque_and_latches_timeout(hand: HandConfig, channel: str) -> None:
    tau = [0.15, 0.1, 0.05] * 3
    tau[6:] = [-t for t in tau[6:]]
    with sim_and_host(hand, channel) as (sim, host):
        enable_all(host)
        host.run(50, tau)
        assert abs(sim.ground_truth().joint_torques[0] - tau[0]) < 1e-3
        last = sim.ticks  # the last command was taken at tick last - 1
        for _ in range(9):
            host.tick()
            assert host.last("Feedback", 1)["State"] == 1, f"tripped early at {sim.ticks}"
        heard = host.tick()
        for finger in hand.fingers:
            feedback = host.of("Feedback", finger.node_id, heard)[0].signals()
            assert (feedback["State"], feedback["FaultBits"]) == (2, 0x01)
            status = host.of("Status", finger.node_id, heard)[0].signals()
            assert (status["State"], status["FaultBits"]) == (2, 0x01)  # at once, not at 100 ms
            assert status["CommandAge"] == 10
        assert sim.ticks - last == 10
        host.run(60)
        assert max(abs(t) for t in sim.ground_truth().joint_torques) < 1e-3


def test_lockstep_is_deterministic_per_seed(hand: HandConfig, channel: str) -> None:
    def frames(seed: int, suffix: str) -> list[tuple[int, bytes]]:
        with sim_and_host(hand, channel + suffix, seed=seed) as (_, host):
            _session(host)
        return [(h.id, h.frame.data) for h in host.heard]

    first, again, other = frames(7, "a"), frames(7, "b"), frames(8, "c")
    assert first == again
    assert first != other  # the noise is the seed's


def test_free_running_is_an_independent_peer(hand: HandConfig, channel: str) -> None:
    """On its own timer the hand sends feedback with nobody stepping it, and its watchdog
    stops a host that enabled it and then went quiet."""
    with sim_and_host(hand, channel) as (sim, host):
        sim.start()
        try:
            host.command("enable")
            deadline = time.monotonic() + 10.0  # a failure guard, not a timing assertion
            while time.monotonic() < deadline:
                host.poll()
                fb = host.of("Feedback", 1)
                if len(fb) > 50 and fb[-1].signals()["State"] == 2:
                    break
                threading.Event().wait(0.01)
        finally:
            sim.stop()
        assert sim.ticks > 50
        states = [h.signals()["State"] for h in host.of("Feedback", 1)]
        assert 1 in states  # it was enabled...
        assert states[-1] == 2 and host.last("Feedback", 1)["FaultBits"] == 0x01  # ...then TIMEOUT


def test_standalone_runs_for_the_given_time(hand: HandConfig, channel: str) -> None:
    """It runs for the wall time asked and puts every tick it simulated on the bus, node 1's
    feedback with consecutive counters. How many ticks fit in 0.3 s is the machine's business:
    a loaded machine may hold the timer thread back for most of it, so a run that simulated
    no tick at all is tried again."""
    for _ in range(5):
        listener = open_bus(f"virtual:{channel}", hand.bus)
        try:
            summary = standalone(hand, f"virtual:{channel}", seconds=0.3)
            frames = listener.drain(limit=100_000)
        finally:
            listener.close()
        assert summary.startswith(f"simulated hand on virtual:{channel}")
        simulated, wall = (float(v) for v in re.findall(r"([0-9.]+) s", summary)[:2])
        assert wall >= 0.3
        feedback = [f for f in frames if f.arbitration_id == 0x181]
        if simulated > 0:
            break
    assert len(feedback) == round(simulated / hand.bus.period_s) > 0
    assert all(f.data[1] == k & 0xFF for k, f in enumerate(feedback))


def test_ground_truth_is_not_on_the_bus(hand: HandConfig, channel: str) -> None:
    with sim_and_host(hand, channel) as (sim, host):
        host.run(10)
        truth = sim.ground_truth()
        summary = sim.ground_truth_summary()
    assert [o.name for o in truth.objects] == ["cyl1", "cyl2"]
    assert summary["objects"]["cyl1"]["moved_m"] < 1e-3  # nothing touched them
    ids = {h.id for h in host.heard}
    assert ids <= {m.frame_id for m in DB.messages if m.senders[0].startswith("FINGER")}


def test_lockstep_follows_the_loop_period(hand: HandConfig, channel: str) -> None:
    bus = open_bus(f"virtual:{channel}", hand.bus)
    try:
        sim = SimulatedHand(hand, bus)
        assert sim.seed == sim.params.seed
        sim.step()
        assert sim.ticks == 1  # 1 kHz: one node tick per loop period
        slow = dataclasses.replace(hand, bus=dataclasses.replace(hand.bus, loop_rate_hz=400.0))
        sim = SimulatedHand(slow, bus)
        ticks = []
        for _ in range(4):
            sim.step()
            ticks.append(sim.ticks)
        assert ticks == [3, 5, 8, 10]  # 2.5 ms periods: simulated time keeps up, no drift
    finally:
        bus.close()


def test_a_simulated_hand_asked_to_join_the_sim_bus_is_bad_input(
    capsys: pytest.CaptureFixture[str],
) -> None:
    """``sim`` names the simulated hand to the commands that listen to it; as the bus the hand
    itself joins it is a mix-up of the user's (exit 2, saying what the hand takes), not a bus
    that failed to open (exit 4, an internal message)."""
    from handctl import cli

    assert cli.main(["sim", "--bus", "sim", "--seconds", "0.3"]) == cli.EXIT_BAD_INPUT
    err = capsys.readouterr().err
    assert "--bus" in err and "unix:DIRECTORY" in err and "found 'sim'" in err
    assert "resolved by the caller" not in err


@pytest.mark.parametrize("where", ["directory", "missing directory", "the hand config"])
def test_a_summary_the_hand_cannot_write_is_refused_before_it_runs(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], where: str
) -> None:
    """The ground truth is written after the whole run: a directory, a file in a directory
    that is not there, or the hand config it reads were found out only then (after the run,
    or never: the config was replaced), and ``/dev/full`` was a traceback."""
    from handctl import cli

    hand_file = tmp_path / "hand.yaml"
    original = (ROOT / "config" / "hands" / "hiroshima_hand.yaml").read_text()
    hand_file.write_text(original)
    target = {
        "directory": tmp_path,
        "missing directory": tmp_path / "nowhere" / "truth.json",
        "the hand config": hand_file,
    }[where]
    argv = ["sim", "--bus", "virtual:refused-summary", "--seconds", "0.3"]
    argv += ["--hand", str(hand_file), "--summary-json", str(target)]
    assert cli.main(argv) == cli.EXIT_BAD_INPUT
    out, err = capsys.readouterr()
    assert "--summary-json" in err and str(target) in err
    assert "simulated hand on" not in out  # nothing was run
    assert hand_file.read_text() == original


def test_a_standalone_hand_on_the_virtual_bus_says_no_other_process_hears_it(
    capsys: pytest.CaptureFixture[str],
) -> None:
    """`handctl sim --bus virtual:y` and then `handctl nodes --bus virtual:y`: every node
    missing, the hand sending 12000 frames to a queue inside its own process, and nothing
    said why. It still runs (a test in one process may want it)."""
    from handctl import cli

    assert cli.main(["sim", "--bus", "virtual:alone", "--seconds", "0.1"]) == cli.EXIT_OK
    err = capsys.readouterr().err
    assert "--bus virtual:alone lives inside this process: no other command or process" in err
    assert cli.main(["sim", "--bus", "sim", "--seconds", "0.1"]) == cli.EXIT_BAD_INPUT
    assert "lives inside this process" not in capsys.readouterr().err


@pytest.mark.parametrize(
    "sig", [sig_module.SIGTERM, sig_module.SIGUSR1, sig_module.SIGALRM, sig_module.SIGXCPU]
)
def test_a_standalone_hand_ends_cleanly_on_a_signal_that_would_kill_it(
    tmp_path: Path, sig: sig_module.Signals
) -> None:
    """SIGUSR1, SIGUSR2 and SIGALRM killed ``handctl sim`` by the signal: no summary, its
    socket left in the bus directory (found by an outside audit). They end it as SIGTERM
    does: its summary written, the directory left as it found it."""
    bus, summary = tmp_path / "bus", tmp_path / "truth.json"
    bus.mkdir()
    sim = subprocess.Popen(
        [
            *(sys.executable, "-m", "handctl", "sim", "--bus", f"unix:{bus}"),
            *("--seconds", "120", "--summary-json", str(summary)),
        ],
        cwd=ROOT,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        assert sim.stderr is not None
        first = sim.stderr.readline()  # its first status line: the hand runs
        assert first.startswith("t="), first + sim.communicate()[1]
        sim.send_signal(sig)
        _, err = sim.communicate(timeout=60)
    finally:
        sim.kill()
    assert sim.returncode in (0, 130), err
    assert summary.exists(), err
    assert not any(bus.iterdir())  # its socket gone with it
