"""The Foxglove WebSocket server that shows a run while it goes on, or a log played back.

During a run it lives in the recording's writer process (``handctl.recording.writer``), which
hands it every message as it writes it to the MCAP file: the loop does not know it exists, and
a slow or stalled viewer costs the writer a bounded queue (the SDK drops the oldest message
per client), never the loop a microsecond of waiting. ``handctl replay RUN.mcap --live``
serves a finished (or truncated) file at the speed it was recorded.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path

import foxglove
from foxglove import Channel, Context, Schema

#: Bound to the loopback interface only: a live view of a robot is not for the network unless
#: someone chooses to tunnel it.
HOST = "127.0.0.1"
DEFAULT_PORT = 8765


class LiveServer:
    """A Foxglove WebSocket server with one channel per recorded topic, fed raw payloads."""

    def __init__(self, port: int, name: str = "handctl", host: str = HOST,
                 playback_range: tuple[int, int] | None = None) -> None:
        self.context = Context()
        self.server = foxglove.start_server(name=name, host=host, port=port,
                                            context=self.context,
                                            playback_time_range=playback_range)
        self.channels: dict[str, Channel] = {}

    @property
    def port(self) -> int:
        return self.server.port

    def add_channel(self, topic: str, schema_name: str, schema_encoding: str,
                    schema_data: bytes, message_encoding: str,
                    metadata: dict[str, str] | None = None) -> None:
        self.channels[topic] = Channel(
            topic, schema=Schema(name=schema_name, encoding=schema_encoding, data=schema_data),
            message_encoding=message_encoding, context=self.context, metadata=metadata)

    def log(self, topic: str, log_time: int, payload: bytes) -> None:
        channel = self.channels.get(topic)
        if channel is not None and channel.has_sinks():
            channel.log(payload, log_time=log_time)

    def close(self) -> None:
        self.server.stop()


def serve_recording(path: Path, port: int, speed: float = 1.0,
                    started: Callable[[LiveServer], None] | None = None) -> int:
    """Stream every message of ``path`` at its recorded spacing (divided by ``speed``);
    returns the number of messages sent. A truncated file plays up to where it stops."""
    from mcap.reader import make_reader

    with path.open("rb") as stream:
        reader = make_reader(stream)
        summary = None
        try:
            summary = reader.get_summary()
        except Exception:  # a truncated file has no summary: played from the records alone
            summary = None
        span = None
        if summary is not None and summary.statistics is not None:
            span = (summary.statistics.message_start_time, summary.statistics.message_end_time)
        server = LiveServer(port, name=f"handctl replay {path.name}", playback_range=span)
        try:
            if started is not None:
                started(server)
            sent = 0
            first_log: int | None = None
            wall0 = 0.0
            stream.seek(0)
            for schema, channel, message in make_reader(stream).iter_messages(
                    log_time_order=False):
                if channel.topic not in server.channels:
                    server.add_channel(channel.topic, schema.name if schema else "",
                                       schema.encoding if schema else "",
                                       bytes(schema.data) if schema else b"",
                                       channel.message_encoding, dict(channel.metadata))
                if first_log is None:
                    first_log, wall0 = message.log_time, time.monotonic()
                due = wall0 + (message.log_time - first_log) * 1e-9 / speed
                delay = due - time.monotonic()
                if delay > 0:
                    time.sleep(delay)
                server.log(channel.topic, message.log_time, message.data)
                sent += 1
        finally:
            server.close()
    return sent
