"""The live view samples by one list (``handctl.foxglove.live.SAMPLING``), which a run's
writer and a replay's server both read: every channel written every tick or every frame,
recorded or derived, and no other."""

from __future__ import annotations

from handctl.foxglove import derived as fx
from handctl.foxglove.live import PER_FRAME, PER_TICK, SAMPLING, LiveServer
from handctl.recording import channels as ch


def _documented(rate: str) -> str | None:
    """The sampling a channel's documented rate calls for."""
    if rate.startswith(("every tick", "every control tick")):
        return PER_TICK
    if rate.startswith("every frame"):
        return PER_FRAME
    return None


def test_every_recorded_channel_written_every_tick_or_frame_is_sampled_and_no_other() -> None:
    for channel in ch.CHANNELS:
        assert SAMPLING.get(channel.topic) == _documented(channel.rate), channel


def test_the_derived_per_tick_and_per_frame_channels_are_sampled_as_their_sources() -> None:
    assert SAMPLING[fx.JOINTS] == SAMPLING[ch.TORQUE] == PER_TICK
    assert SAMPLING[fx.RX_DECODED] == SAMPLING[ch.CAN_RX] == PER_FRAME
    assert SAMPLING[fx.TX_DECODED] == SAMPLING[ch.CAN_TX] == PER_FRAME
    for topic in (fx.SCENE, fx.TRANSFORMS, fx.LOG):
        assert topic not in SAMPLING


def test_a_server_samples_the_channels_it_is_given_by_the_list() -> None:
    """The server takes the sampling from the list itself: no caller says it."""
    server = LiveServer(0)
    for topic in (*(c.topic for c in ch.CHANNELS), fx.JOINTS, fx.SCENE, fx.RX_DECODED):
        server.add_channel(topic, "", "", b"", "json")
    assert server.sampled == {t: s for t, s in SAMPLING.items() if t in server.channels}
    assert fx.SCENE not in server.sampled


def test_the_live_view_gives_way_while_the_writer_is_behind_and_comes_back_after() -> None:
    """Held back once the writer is a quarter of a ring behind, served again only once it
    is back under a sixteenth: between the two it stays as it was (no flapping at one
    share), and each time it is held back is counted."""
    from handctl.recording.writer import LIVE_PAUSE_SHARE, LIVE_RESUME_SHARE, LivePace

    pace = LivePace()
    seen = []
    resumed = []
    for backlog in (0.0, 0.2, LIVE_PAUSE_SHARE, 0.26, 0.9, 0.2, LIVE_RESUME_SHARE, 0.06, 0.2, 0.3):
        resumed.append(pace.update(backlog))
        seen.append(pace.paused)
    assert seen == [False, False, False, True, True, True, True, False, False, True]
    assert pace.pauses == 2
    # said once, when it is served again: the writer then serves what it held meanwhile,
    # the newest of each channel (``LiveServer.send_held``), which was never served
    assert resumed == [False] * 7 + [True, False, False]
