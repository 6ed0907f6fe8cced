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
