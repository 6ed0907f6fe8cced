"""``handctl nodes`` against the simulated hand, on the virtual bus (in this process) and on
the unix bus (the command in a process of its own): every node there, a node missing, a node in
FAULT, a node of another protocol version, a node the hand config does not have; and it never
sends a frame."""

from __future__ import annotations

import json
import re
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
import yaml

from handctl import cli
from handctl.config import HandConfig
from handctl.online.bus import open_bus
from handctl.protocol import NodeState
from handctl.sim import faults as inj
from handctl.sim.firmware import FaultBits
from handctl.sim.hand import SimulatedHand

from ..conftest import HAND_YAML, ROOT
from .bringup_peer import HOST_IDS, running_hand

SECONDS = "0.6"


def _nodes(capsys: pytest.CaptureFixture[str], *args: str) -> tuple[int, dict[str, Any]]:
    code = cli.main(["nodes", "--json", "--seconds", SECONDS, *args])
    return code, json.loads(capsys.readouterr().out)


def _rows(report: dict[str, Any]) -> dict[int, dict[str, Any]]:
    return {row["node_id"]: row for row in report["nodes"]}


def test_every_node_is_listed_and_nothing_is_sent(
    hand: HandConfig, channel: str, capsys: pytest.CaptureFixture[str]
) -> None:
    spec = f"virtual:{channel}"
    sniffer = open_bus(spec, hand.bus)
    try:
        with running_hand(hand, spec):
            code, report = _nodes(capsys, "--bus", spec)
        heard = sniffer.drain(limit=10**6)
    finally:
        sniffer.close()
    assert code == cli.EXIT_OK and report["ok"]
    for row in report["nodes"]:
        assert row["present"] and row["state"] == "DISABLED" and row["problem"] == ""
        assert row["protocol_version"] == 2 and row["firmware"] == "0.2.0"
        assert row["feedback_hz"] > 0 and row["heartbeats"] > 0 and row["statuses"] > 0
    assert heard, "the sniffer heard the hand"
    assert not [f for f in heard if f.arbitration_id in HOST_IDS]


def _silent_2(sim: SimulatedHand) -> None:
    sim.activate(inj.NodeSilent(node=2))


def _sensor_fault_3(sim: SimulatedHand) -> None:
    sim.activate(inj.TdtSpike(node=3, joint=1, amplitude=5.0, duration=0.01))


def _version_3_on_1(sim: SimulatedHand) -> None:
    sim.nodes[0].protocol_version = 3


def test_a_missing_node(hand: HandConfig, channel: str, capsys: pytest.CaptureFixture[str]) -> None:
    with running_hand(hand, f"virtual:{channel}", _silent_2):
        code, report = _nodes(capsys, "--bus", f"virtual:{channel}")
    rows = _rows(report)
    assert code == cli.EXIT_FAILED and not report["ok"]
    assert not rows[2]["present"] and rows[2]["problem"].startswith("missing")
    assert rows[1]["problem"] == rows[3]["problem"] == ""


def test_a_node_in_fault(
    hand: HandConfig, channel: str, capsys: pytest.CaptureFixture[str]
) -> None:
    with running_hand(hand, f"virtual:{channel}", _sensor_fault_3):
        code, report = _nodes(capsys, "--bus", f"virtual:{channel}")
    row = _rows(report)[3]
    assert code == cli.EXIT_FAILED
    assert row["state"] == "FAULT" and row["faults"] == ["SENSOR"]
    assert row["problem"] == "in FAULT (SENSOR)"


def test_a_node_of_another_protocol_version(
    hand: HandConfig, channel: str, capsys: pytest.CaptureFixture[str]
) -> None:
    with running_hand(hand, f"virtual:{channel}", _version_3_on_1):
        code, report = _nodes(capsys, "--bus", f"virtual:{channel}")
    row = _rows(report)[1]
    assert code == cli.EXIT_FAILED
    assert row["protocol_version"] == 3
    assert "node 1 (f1) speaks handctl protocol 3, this host protocol 2" in row["problem"]


def _two_finger_hand(tmp_path: Path) -> Path:
    data = yaml.safe_load(HAND_YAML.read_text())
    data["fingers"] = data["fingers"][:2]
    # the host's config of a hand that is never simulated: the three-finger peer on the bus
    # is the fixture's (its sim section, of three fingers, check would refuse here)
    del data["sim"]
    path = tmp_path / "two_fingers.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


def test_a_node_not_in_the_config_is_flagged(
    hand: HandConfig, channel: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    with running_hand(hand, f"virtual:{channel}"):
        code, report = _nodes(
            capsys, "--bus", f"virtual:{channel}", "--hand", str(_two_finger_hand(tmp_path))
        )
    assert code == cli.EXIT_FAILED
    assert [row["problem"] for row in report["nodes"]] == ["", ""]
    foreign = {f["id"]: f["what"] for f in report["foreign_ids"]}
    assert foreign["0x183"] == "Feedback_3: node 3, not in the hand config"
    assert foreign["0x703"] == "Heartbeat_3: node 3, not in the hand config"


def test_the_table_keeps_its_columns_for_two_digit_node_ids(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    doc = yaml.safe_load(HAND_YAML.read_text(encoding="utf-8"))
    for finger, node in zip(doc["fingers"], [9, 10, 11], strict=True):
        finger["node_id"] = node
        finger.pop("can_ids", None)  # the protocol's, from the node id
    path = tmp_path / "ids.yaml"
    path.write_text(yaml.safe_dump(doc), encoding="utf-8")
    assert cli.main(["nodes", "--seconds", SECONDS, "--hand", str(path)]) == cli.EXIT_OK
    lines = capsys.readouterr().out.splitlines()
    header = next(line for line in lines if line.startswith("node "))
    rows = [line for line in lines if re.match(r" ?\d+ f\d ", line)]
    assert len(rows) == 3
    for column in ("state", "faults", "problem"):  # left-aligned: they start there
        at = header.index(column)
        assert {row[at - 1] for row in rows} == {" "} and all(row[at] != " " for row in rows)


def test_bad_seconds_are_refused(capsys: pytest.CaptureFixture[str]) -> None:
    assert cli.main(["nodes", "--seconds", "0"]) == cli.EXIT_BAD_INPUT
    assert "--seconds" in capsys.readouterr().err
    # shorter than two of the nodes' Status reports: every node was said missing, a typo
    # read as a wiring fault (an outside probe)
    assert cli.main(["nodes", "--seconds", "1e-9"]) == cli.EXIT_BAD_INPUT
    err = capsys.readouterr().err
    assert "--seconds: expected a survey of at least 0.2 s (twice the 100 ms" in err
    assert "missing" not in err


@pytest.mark.parametrize(
    "prepare, node, problem",
    [
        (None, None, ""),
        (_silent_2, 2, "missing"),
        (_sensor_fault_3, 3, "in FAULT (SENSOR)"),
        (_version_3_on_1, 1, "speaks handctl protocol 3"),
    ],
)
def test_on_the_unix_bus_from_another_process(
    hand: HandConfig, tmp_path: Path, prepare: Any, node: int | None, problem: str
) -> None:
    spec = f"unix:{tmp_path / 'bus'}"
    with running_hand(hand, spec, prepare):
        result = subprocess.run(
            [
                sys.executable,
                "-m",
                "handctl",
                "nodes",
                "--bus",
                spec,
                "--json",
                "--seconds",
                SECONDS,
            ],
            capture_output=True,
            text=True,
            cwd=ROOT,
            timeout=120,
            check=False,
        )
    report = json.loads(result.stdout)
    rows = _rows(report)
    if node is None:
        assert result.returncode == 0 and report["ok"], result.stdout
        return
    assert result.returncode == cli.EXIT_FAILED
    assert problem in rows[node]["problem"]
    assert all(row["problem"] == "" for n, row in rows.items() if n != node)


def _corrupt_feedback_1(sim: SimulatedHand) -> None:
    sim.activate(inj.CorruptCrc(node=1, message="feedback"))


def _skipping_feedback_2(sim: SimulatedHand) -> None:
    sim.activate(inj.CounterSkip(node=2, message="feedback"))


@pytest.mark.parametrize(
    "prepare, node, rejected",
    [(_corrupt_feedback_1, 1, "crc"), (_skipping_feedback_2, 2, "counter_skip")],
)
def test_a_node_whose_feedback_is_heard_and_rejected_is_a_problem(
    hand: HandConfig,
    channel: str,
    capsys: pytest.CaptureFixture[str],
    prepare: Any,
    node: int,
    rejected: str,
) -> None:
    """A thousand frames a second heard, none accepted: the row said "ok" and the exit was
    0, against the bring-up's own criteria (feedback near its rate, rejects 0)."""
    with running_hand(hand, f"virtual:{channel}", prepare):
        code, report = _nodes(capsys, "--bus", f"virtual:{channel}")
    rows = _rows(report)
    assert code == cli.EXIT_FAILED and not report["ok"]
    row = rows[node]
    # the first frame of a stream is taken with any counter: a skipping stream has one
    assert row["feedback_hz"] < 10 and row["feedback_expected_hz"] == 1000
    assert row["host_rejects"][rejected] > 10
    assert re.search(r"feedback \d Hz accepted, expected 1000 Hz", row["problem"])
    assert f"frames rejected: {rejected} " in row["problem"]
    assert all(r["problem"] == "" for n, r in rows.items() if n != node)


def test_two_senders_of_one_nodes_frames_are_a_problem(
    hand: HandConfig, channel: str, capsys: pytest.CaptureFixture[str]
) -> None:
    """Two hands on one bus: every node id twice, each stream's counters interleaved."""
    spec = f"virtual:{channel}"
    with running_hand(hand, spec), running_hand(hand, spec):
        code, report = _nodes(capsys, "--bus", spec)
    assert code == cli.EXIT_FAILED and not report["ok"]
    for row in report["nodes"]:
        assert "counter_skip" in row["host_rejects"] or "counter_repeat" in row["host_rejects"]
        assert "frames rejected: counter_" in row["problem"]


def test_two_senders_on_a_heartbeat_are_said_as_such_not_as_a_reboot(
    hand: HandConfig, channel: str
) -> None:
    """A second hand started 0.3 s after the first: each node's Heartbeat comes from two
    senders whose uptimes alternate. Every other one went back, and the survey said each node
    "rebooted during the survey (its uptime went back, 6x)" (found by an outside audit)."""
    from handctl.bringup.nodes import survey
    from handctl.hand_protocol import protocol_for

    spec = f"virtual:{channel}"
    with running_hand(hand, spec), open_bus(spec, hand.bus) as bus:
        time.sleep(0.3)
        with running_hand(hand, spec):
            found = survey(hand, protocol_for(hand), bus, 0.6)
    for row in found.rows:
        assert "rebooted" not in row.problem, row
        assert f"two senders on Heartbeat_{row.node_id} (0x70{row.node_id}):" in row.problem, row


def test_a_bus_with_error_frames_is_a_problem(
    hand: HandConfig, channel: str, capsys: pytest.CaptureFixture[str]
) -> None:
    with running_hand(
        hand, f"virtual:{channel}", lambda sim: sim.activate(inj.ErrorFrames(per_tick=1))
    ):
        code, report = _nodes(capsys, "--bus", f"virtual:{channel}")
    assert code == cli.EXIT_FAILED and not report["ok"]
    assert report["bus_events"]["error_frame"] > 10
    assert report["bus_problem"].startswith("bus events: error_frame ")
    assert all(row["problem"] == "" for row in report["nodes"])  # the nodes are fine


@pytest.mark.parametrize(
    ("frame_id", "what"),
    [(0x101, "TorqueCommand_1: sent by another host"), (0x555, "not in the DBC")],
)
def test_frames_on_other_ids_are_a_problem(
    hand: HandConfig,
    channel: str,
    capsys: pytest.CaptureFixture[str],
    frame_id: int,
    what: str,
) -> None:
    """Good is 'no line about other ids' (docs/bringup.md): another host's commands and ids
    the DBC does not have were listed, and the survey still said ok, exit 0."""
    code, report = _nodes_beside_a_sender(hand, channel, capsys, lambda k: [frame_id])
    assert code == cli.EXIT_FAILED and not report["ok"]
    assert [f["what"] for f in report["foreign_ids"]] == [what]


def _nodes_beside_a_sender(
    hand: HandConfig,
    channel: str,
    capsys: pytest.CaptureFixture[str],
    ids: Callable[[int], list[int]],
) -> tuple[int, dict[str, Any]]:
    """``handctl nodes`` on a simulated hand's virtual channel while another sender puts 8
    zero bytes on each of ``ids(k)`` every 2 ms (k counting its rounds)."""
    spec = f"virtual:{channel}"
    other = open_bus(spec, hand.bus)
    stop = threading.Event()

    def send() -> None:
        k = 0
        while not stop.is_set():
            for frame_id in ids(k):
                other.send(frame_id, bytes(8))
            k += 1
            time.sleep(0.002)

    sender = threading.Thread(target=send)
    try:
        with running_hand(hand, spec):
            sender.start()
            return _nodes(capsys, "--bus", spec)
    finally:
        stop.set()
        if sender.is_alive():
            sender.join()
        other.close()


def test_a_remote_frame_is_named_as_one_and_is_no_command_to_the_nodes(
    hand: HandConfig, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Remote frames (RTR) from a python-can program on the unix bus: they reached the nodes
    and the survey as data frames of 0 bytes, the survey said "NodeCommand_1: sent by another
    host", and the nodes counted length rejects (found by an outside audit). Now they are
    named as remote frames, and no node takes one as a frame of its protocol; on id 0x000
    every node still stops (PROTOCOL.md: any frame with that id is an e-stop)."""
    import can

    channel = tmp_path / "bus"
    spec = f"unix:{channel}"
    stop = threading.Event()

    def send(theirs: can.BusABC) -> None:
        while not stop.is_set():
            for frame_id in (0x011, 0x101):  # NodeCommand_1, TorqueCommand_1
                theirs.send(
                    can.Message(arbitration_id=frame_id, is_remote_frame=True, is_extended_id=False)
                )
            time.sleep(0.01)

    with (
        running_hand(hand, spec) as sim,
        can.Bus(interface="unix", channel=str(channel)) as theirs,
    ):
        sender = threading.Thread(target=send, args=(theirs,))
        sender.start()
        try:
            code, report = _nodes(capsys, "--bus", spec)
        finally:
            stop.set()
            sender.join()
        node = sim.nodes[0]
        assert node.reject_length == 0 and node.state == NodeState.DISABLED
        theirs.send(can.Message(arbitration_id=0x000, is_remote_frame=True, is_extended_id=False))
        for _ in range(500):
            if node.state == NodeState.FAULT:
                break
            time.sleep(0.01)
        assert all(n.state == NodeState.FAULT for n in sim.nodes)
        assert all(n.fault_bits == FaultBits.ESTOP for n in sim.nodes)
    assert code == cli.EXIT_FAILED and not report["ok"]
    assert report["foreign_ids"] == []  # no "NodeCommand_1: sent by another host"
    assert report["bus_events"]["remote_frame"] > 10
    assert "a remote frame (RTR) on id 0x" in report["last_event"]["remote_frame"]
    assert "bus events: remote_frame " in report["bus_problem"]
    assert all(row["host_rejects"] == {} for row in report["nodes"])


def test_a_flood_of_ids_is_counted_in_a_bounded_table(
    hand: HandConfig, channel: str, capsys: pytest.CaptureFixture[str]
) -> None:
    """A device babbling on thousands of ids grew the table without end (35 000 lines after
    10 s, 96 MB): the first MAX_IDS ids are counted one by one, the frames of the rest together;
    a 29-bit id is shown as the wire carries it (no 0x8000.... of handctl's own flag)."""
    from handctl.bringup.idcount import MAX_IDS
    from handctl.online.bus import EXTENDED_ID_FLAG

    code, report = _nodes_beside_a_sender(
        hand,
        channel,
        capsys,
        lambda k: [EXTENDED_ID_FLAG | (0x10000 + 50 * k + j) for j in range(50)],
    )
    assert code == cli.EXIT_FAILED and not report["ok"]
    assert len(report["foreign_ids"]) == MAX_IDS
    assert report["foreign_ids_more_frames"] > 0
    assert all(
        re.fullmatch(r"0x0001[0-9A-F]{4} \(29-bit\)", f["id"]) for f in report["foreign_ids"]
    )


@pytest.mark.parametrize(
    "argv",
    [
        ["nodes", "--seconds", "0.2"],
        ["jog", "f1_j1", "--torque", "0.05"],
        ["run", "recipe", str(ROOT / "config" / "recipes" / "swap_two_cylinders.yaml")],
    ],
    ids=["nodes", "jog", "run"],
)
def test_a_unix_bus_no_hand_is_on_is_said_and_not_made(
    tmp_path: Path, argv: list[str], capsys: pytest.CaptureFixture[str]
) -> None:
    """A mistyped bus directory was made by the command, which then said every node was
    missing (``nodes``, which only listens, left the directory behind; a run listened out
    its start-up). ``monitor`` may come first and wait for a hand: it makes the bus."""
    missing = tmp_path / "no_bus_here"
    assert cli.main([*argv, "--bus", f"unix:{missing}"]) == cli.EXIT_BAD_INPUT
    err = capsys.readouterr().err
    assert "--bus: channel: expected the directory of a unix bus a hand is on" in err
    assert f"found {missing}: no such directory" in err
    assert not missing.exists()


def test_a_node_that_faulted_and_rebooted_during_the_survey_is_no_ok(
    hand: HandConfig, channel: str
) -> None:
    """The table shows each node's last word: a node in FAULT that rebooted (and so came back
    DISABLED, its bits cleared, with no reset from any host) said "ok", exit 0 (an outside
    probe). The reboot comes once the survey has listened for 0.2 s, from its own sleep."""
    from handctl.bringup.nodes import survey
    from handctl.hand_protocol import protocol_for

    spec = f"virtual:{channel}"
    with running_hand(hand, spec, _sensor_fault_3) as sim, open_bus(spec, hand.bus) as bus:
        began = time.monotonic()
        rebooted: list[float] = []

        def sleep(seconds: float) -> None:
            time.sleep(seconds)
            if not rebooted and time.monotonic() - began > 0.2:
                sim.activate(inj.NodeReboot(node=3, downtime=0.02))
                rebooted.append(time.monotonic() - began)

        found = survey(hand, protocol_for(hand), bus, 1.0, sleep=sleep)
    row = {r.node_id: r for r in found.rows}[3]
    assert rebooted and not found.ok
    assert row.state == "DISABLED", row
    assert "was in FAULT (SENSOR) during the survey and left it" in row.problem, row
    assert "rebooted during the survey (its uptime went back, 1x)" in row.problem, row
    assert {r.node_id: r for r in found.rows}[1].problem == ""


def test_an_angle_past_its_joint_s_limits_is_no_ok(hand: HandConfig) -> None:
    """A node whose f1_j1 read 3.0 rad, outside its [-1.00, 1.90], was listed "ok"."""
    from handctl.bringup.nodes import _Heard
    from handctl.hand_protocol import protocol_for
    from handctl.online.drivers.finger import FingerLayouts, FingerNode
    from handctl.protocol import NodeState

    finger = hand.fingers[0]
    node = FingerNode(finger, FingerLayouts.for_node(protocol_for(hand), finger.node_id))
    layout = node.layouts.feedback
    k = len(finger.joints)
    heard = _Heard()
    for counter, angle in enumerate((0.5, 3.0)):
        angles = (angle,) + (0.0,) * (k - 1)
        data = layout.encode(counter, (0.0,) * k + angles + (int(NodeState.DISABLED), 0))
        node.receive(layout.frame_id, data, counter * 1_000_000)
        heard.hear(node, layout.frame_id, data, counter * 1_000_000)
    assert heard.problems(node) == [
        f"{finger.joints[0].name} read +3.000 rad, past its limits "
        f"[{finger.joints[0].angle_min:+.2f}, {finger.joints[0].angle_max:+.2f}]"
    ]


def test_an_uptime_that_wraps_is_no_reboot_in_the_survey(hand: HandConfig) -> None:
    """A node 49.7 days up: its uint32 uptime of ms wraps to 0, which the survey said as a
    reboot (found by an outside audit). A drop the host's clock accounts for is the wrap."""
    from handctl.bringup.nodes import _Heard
    from handctl.hand_protocol import protocol_for
    from handctl.online.drivers.finger import FingerLayouts, FingerNode

    finger = hand.fingers[0]
    node = FingerNode(finger, FingerLayouts.for_node(protocol_for(hand), finger.node_id))
    layout = node.layouts.heartbeat
    heard = _Heard()
    top = (1 << 32) - 50
    for counter, (uptime, at_ms) in enumerate(((top, 1000), (50, 1100), (150, 1200))):
        heard.hear(node, layout.frame_id, layout.encode(counter, (1, uptime)), at_ms * 1_000_000)
    assert heard.reboots == 0 and heard.interleaved == 0
    heard.hear(node, layout.frame_id, layout.encode(0, (0, 40)), 1300 * 1_000_000)
    assert heard.reboots == 1
