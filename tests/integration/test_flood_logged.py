"""Load: a babbling node floods the bus with a foreign id at full rate for a whole recorded
lockstep run. The run still completes with the same torques as without the flood, every
foreign frame is counted and dropped, and the MCAP log records the flood: the counts on
/events and the frames on /can/rx are exactly what a sniffer on the bus heard."""

from __future__ import annotations

import json
from collections import Counter
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader

from handctl.config import HandConfig
from handctl.online.loop import Outcome, RunResult
from handctl.online.recipes.schema import Recipe
from handctl.recording import channels as ch
from handctl.recording.metadata import run_metadata, start_metadata
from handctl.recording.reader import iter_decoded, open_recording
from handctl.recording.recorder import Recorder
from handctl.sim import faults as inj

from .rig import rig, short_recipe

FOREIGN_ID = 0x050
#: About all a CAN-FD bus carries besides the hand's own traffic (the loop benchmark's 20).
PER_TICK = 20


@dataclass
class FloodRun:
    result: RunResult
    applied: np.ndarray  # applied torques, one row per control tick, from the log
    heard: int  # foreign frames the sniffer heard on the bus
    sent: int  # foreign frames the babbling node sent
    log: Path


def _run(hand: HandConfig, recipe: Recipe, log: Path, flood: bool) -> FloodRun:
    """A lockstep run recorded the way ``handctl run recipe --log`` records one."""
    with rig(hand, recipe) as r:
        babble = inj.Babble(id=FOREIGN_ID, per_tick=PER_TICK, length=8)
        if flood:
            r.sim.faults.add(babble, 0.0, 1e9)
        recorder = Recorder(
            log,
            hand,
            start_metadata(hand, recipe, ["test", "flood"]),
            phase_names=[p.name for p in recipe.phases],
        )
        with recorder:
            r.runtime.recorder = recorder
            recorder.attach(r.runtime)
            recorder.add_metadata(
                ch.META_RUN,
                run_metadata(
                    mode="lockstep",
                    bus="virtual",
                    seed=0,
                    period_ns=1_000_000,
                    startup_ticks=r.runtime.startup_ticks,
                    reset_node_faults=False,
                    estimator=False,
                    sim_faults="babble" if flood else "",
                ),
            )
            recorder.wait_ready()
            result = r.run()
            recorder.close({"outcome": result.outcome.value})
        heard = sum(1 for frame_id, _ in r.wire if frame_id == FOREIGN_ID)
    recording = open_recording(log)
    applied = np.array([m["applied_nm"] for _, _, m in iter_decoded(recording, [ch.TORQUE])])
    return FloodRun(result, applied, heard, babble.sent, log)


@pytest.fixture(scope="module")
def runs(hand: HandConfig, tmp_path_factory: pytest.TempPathFactory) -> tuple[FloodRun, FloodRun]:
    directory = tmp_path_factory.mktemp("flood")
    recipe = short_recipe(hand, directory, hold_s=0.5)
    return (
        _run(hand, recipe, directory / "quiet.mcap", flood=False),
        _run(hand, recipe, directory / "flood.mcap", flood=True),
    )


def test_the_run_succeeds_unchanged_under_the_flood(runs: tuple[FloodRun, FloodRun]) -> None:
    quiet, flood = runs
    assert flood.result.outcome is Outcome.COMPLETED and flood.result.faults == []
    assert flood.result.ticks == quiet.result.ticks
    # Foreign frames are dropped, never applied: the torques are those of a quiet bus.
    assert flood.applied.shape == quiet.applied.shape
    assert np.array_equal(flood.applied, quiet.applied)


def test_every_foreign_frame_is_counted_and_dropped(runs: tuple[FloodRun, FloodRun]) -> None:
    _, flood = runs
    assert flood.sent >= PER_TICK * flood.result.ticks - PER_TICK
    assert flood.heard == flood.sent
    assert flood.result.node_rejects["unexpected_id"] == flood.heard
    assert flood.result.unexpected_ids == {FOREIGN_ID: flood.heard}
    assert sum(v for k, v in flood.result.node_rejects.items() if k != "unexpected_id") == 0


def test_the_log_records_the_flood(runs: tuple[FloodRun, FloodRun]) -> None:
    """Read with the mcap library's own reader: the reject counts on /events and the frames
    on /can/rx add up to what the sniffer heard, tick by tick as the host drained them, and
    the recorder kept up with the flood (nothing dropped)."""
    _, flood = runs
    counted: Counter[int] = Counter()  # tick -> foreign frames counted on /events
    received: Counter[int] = Counter()  # tick -> foreign frames on /can/rx
    ended: dict[str, str] = {}
    with flood.log.open("rb") as handle:
        reader = make_reader(handle)
        for _, channel, message in reader.iter_messages(topics=[ch.EVENTS, ch.CAN_RX]):
            body = json.loads(message.data)
            if channel.topic == ch.CAN_RX:
                if body["id"] == FOREIGN_ID:
                    received[body["tick"]] += 1
            elif body["kind"] == "rejected_frames":
                assert body["name"] == "unexpected_id"
                counted[body["tick"]] += body["count"]
            else:
                assert body["kind"] != "fault"
        for record in reader.iter_metadata():
            if record.name == ch.META_END:
                ended = dict(record.metadata)
    assert sum(counted.values()) == sum(received.values()) == flood.heard
    assert all(ended[k] == "0" for k in ("dropped_ticks", "dropped_frames", "dropped_events"))
    # The flood is continuous in the log: a full tick's worth in every tick's frames.
    assert sorted(received) == list(range(flood.result.ticks))
    assert set(received.values()) == {PER_TICK}
    # Each reject event counts exactly the foreign frames drained since the one before: those
    # of its own tick's poll, plus those of the start-up ticks, which only poll, before it.
    pending = 0
    for k in range(flood.result.ticks):
        pending += received[k]
        if counted[k]:
            assert counted[k] == pending, k
            pending = 0
    assert pending == 0
