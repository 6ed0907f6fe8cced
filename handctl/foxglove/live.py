"""The Foxglove WebSocket server that shows a run while it goes on, or a log played back.

During a run it lives in the recording's writer process (``handctl.recording.writer``), which
hands it every message as it writes it to the MCAP file: the loop does not know it exists, and
a slow or stalled viewer costs the writer a bounded queue (the SDK drops the oldest message
per client), never the loop a microsecond of waiting. ``handctl replay RUN.mcap --live``
serves a finished (or truncated) file at the speed it was recorded.

A channel written every tick (1 kHz) is served sampled: at most one message per
``SAMPLE_PERIOD_NS`` of log time and key (a CAN frame's key is its id, so every kind of frame
is shown, each at most that often). A viewer draws at its screen's rate; a thousand messages
a second on each of a dozen channels would cost the viewer, the server and the machine the
loop runs on for nothing anyone sees. The MCAP file keeps every message; a replay serves it
sampled the same way.
"""

from __future__ import annotations

import logging
import re
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path

import foxglove
import orjson
from foxglove import Channel, Context, Schema
from foxglove.websocket import WebSocketServer

from handctl.errors import ConfigError, Description, escaped
from handctl.foxglove import HOST
from handctl.foxglove.derived import JOINTS, RX_DECODED, TX_DECODED
from handctl.recording import channels as ch

#: s, how long closing the live view waits for its clients to let go (``LiveServer.close``)
CLOSE_TIMEOUT_S = 1.0
#: s, how long closing the live view gives its clients' queues to be sent before it stops
#: the server (no client reading: not at all); the SDK says nothing of what is still queued,
#: so this is a wait, not a receipt: 0.25 s sufficed in 10 of 10 runs at a load of 8 on two
#: cores, and a second keeps a view's last state (idle, zero torque) well clear of a host's
#: stalls, at the cost of a second at the end of a run someone watches
SEND_GRACE_S = 1.0
#: Messages queued per client, the newest (the SDK drops the oldest; its default, 1024,
#: was some 0.9 MB a client in the writer, 176 MB for 200 local clients that stopped
#: reading): a tenth of a second of the view (some 2200 messages a second), enough for a
#: viewer that reads and keeps up. The SDK has no limit on the number of clients and no
#: timeout for a handshake never finished (docs/recording.md): each costs the writer this
#: much until the server closes.
LIVE_BACKLOG = 256
#: The live view's sampling of a per-tick channel: 100 Hz of log time, still a smooth plot
#: (the 3D scene is written at 50 Hz anyway).
SAMPLE_PERIOD_NS = 10_000_000
#: A log time no message reaches (nothing held is due)
_NEVER = 2**64
#: Keys remembered for the sampling before they are forgotten all at once (frame ids from a
#: bus that babbles ever new ones must not grow the writer without bound).
MAX_SAMPLED_KEYS = 4096
#: A channel sampled as one stream (at most one message per ``SAMPLE_PERIOD_NS``).
PER_TICK = "tick"
#: A channel sampled per frame id, so that every kind of frame shows.
PER_FRAME = "frame"
#: The channels written every tick or every frame (recorded and derived), and how the live
#: view samples each; every other channel is served whole. The one list a run's writer and
#: a replay's server both serve by (``LiveServer.add_channel``).
SAMPLING: dict[str, str] = {
    ch.TIMING: PER_TICK,
    ch.JOINT_STATE: PER_TICK,
    ch.TORQUE: PER_TICK,
    ch.SAFETY: PER_TICK,
    ch.PHASE: PER_TICK,
    JOINTS: PER_TICK,
    ch.CAN_RX: PER_FRAME,
    ch.CAN_TX: PER_FRAME,
    RX_DECODED: PER_FRAME,
    TX_DECODED: PER_FRAME,
}


#: lines of the SDK's own notes (a client's invalid message, an unknown channel) shown per
#: server: any local user may connect, and one sending junk put eleven thousand lines on the
#: operator's terminal and 800 kB into the run's summary (the writer's notes); the rest are
#: counted, and the count said when the server closes
NOTES_SHOWN = 5


#: The WebSocket subprotocol the SDK's server speaks, the only one it takes
SUBPROTOCOL = "foxglove.sdk.v1"
#: The SDK's note of a client it refused before the WebSocket began ("Dropping client
#: 127.0.0.1:42002: handshake failed"), whatever the cause: a viewer offering only the
#: protocol's older name, a port probe, a connection closed before its request. The note
#: does not say which, so the refusals are counted and said once, at the end, with the
#: likeliest cause a viewer's operator can do something about (``HANDSHAKE_HINT``)
HANDSHAKE_FAILED = re.compile(r"^Dropping client \S+: handshake failed")
HANDSHAKE_HINT = (
    f"the live view speaks the WebSocket subprotocol {SUBPROTOCOL} only: a viewer that "
    "offers only foxglove.websocket.v1, such as Lichtblick before December 2025 or an older "
    "Foxglove, is refused, and so is a connection that sent no WebSocket request "
    "(docs/recording.md)"
)


class _BoundedNotes(logging.Handler):
    """The SDK's log (Python ``logging`` under ``foxglove``), warnings and errors only, the
    first ``NOTES_SHOWN`` on stderr, the rest counted. Refused handshakes are counted too,
    and said with their likely cause at the end (``LiveServer.close``): the SDK's note
    alone left the operator of a viewer that could not connect with nothing to go on, and
    the cause beside the first note went to whatever was refused first (a port probe, a
    connection closed at once), the viewer's own note left bare or among the uncounted."""

    def __init__(self) -> None:
        super().__init__(logging.WARNING)
        self.shown = 0
        self.more = 0
        self.refused = 0

    def emit(self, record: logging.LogRecord) -> None:
        message = record.getMessage()
        if HANDSHAKE_FAILED.match(message):
            self.refused += 1
        if self.shown < NOTES_SHOWN:
            self.shown += 1
            # escaped: the note quotes what the client sent, and an escape sequence there
            # retitled and recoloured the operator's terminal
            sys.stderr.write(f"live view: {escaped(message)}\n")
        else:
            self.more += 1


def _bounded_notes() -> _BoundedNotes:
    """The one handler of the SDK's logger in this process, put there once (not propagated:
    Python's last-resort handler printed every note)."""
    logger = logging.getLogger("foxglove")
    for handler in logger.handlers:
        if isinstance(handler, _BoundedNotes):
            # a server's own five (a replay's after a run's)
            handler.shown = handler.more = handler.refused = 0
            return handler
    handler = _BoundedNotes()
    logger.addHandler(handler)
    logger.setLevel(logging.WARNING)
    logger.propagate = False
    return handler


class LiveServer:
    """A Foxglove WebSocket server with one channel per recorded topic, fed raw payloads.

    Its channels are added first and the server is started after them (``start``): a client
    that connected while channels were still being added could subscribe to one the SDK had
    advertised to it but not yet entered for it, and be told ``Unknown channel ID`` and get
    nothing of that channel for the whole session."""

    def __init__(self, port: int, name: str = "handctl", host: str = HOST) -> None:
        self.context = Context()
        self.name, self.host, self.requested_port = name, host, port
        self.server: WebSocketServer | None = None
        self.channels: dict[str, Channel] = {}
        #: Per sampled topic, its sampling (``SAMPLING``); per (topic, key) the log time of
        #: the message last served.
        self.sampled: dict[str, str] = {}
        self._served: dict[tuple[str, int], int] = {}
        #: Per topic and key, the newest message not served (its log time and payload); per
        #: topic, the log time from which one of them may be due (``_send_quiet``). Dropped,
        #: a run's last ticks were never served: the view stayed on 'stopping' and a torque
        #: that was not zero while the log ended idle, every torque zero.
        self._held: dict[str, dict[int, tuple[int, bytes]]] = {}
        self._due: dict[str, int] = {}
        self.notes = _bounded_notes()

    def start(self) -> None:
        """Bind the port and serve the channels added so far; a ``ConfigError`` naming
        ``--live`` if the port cannot be bound (free when the command began, and taken by
        another program since: a replay binds it after its summary and re-run, and that was
        the SDK's traceback)."""
        try:
            self.server = foxglove.start_server(
                name=self.name,
                host=self.host,
                port=self.requested_port,
                context=self.context,
                message_backlog_size=LIVE_BACKLOG,
            )
        except RuntimeError as exc:
            # the SDK's reason whole (a ``Description``): cut to a value's length, it lost
            # its end, the part that says why ("Failed to bind p... Address already in use")
            raise ConfigError(
                "--live",
                "",
                f"a port the live view can listen on at {self.host} (it was free when the "
                "command began: another program has taken it since)",
                Description(f"{self.requested_port} ({exc})"),
            ) from None

    @property
    def port(self) -> int:
        return self.server.port if self.server is not None else self.requested_port

    def add_channel(
        self,
        topic: str,
        schema_name: str,
        schema_encoding: str,
        schema_data: bytes,
        message_encoding: str,
        metadata: dict[str, str] | None = None,
    ) -> None:
        """A topic of ``SAMPLING`` is served at most once per ``SAMPLE_PERIOD_NS`` of log
        time (and frame id, on a frame channel; see ``log``)."""
        sampling = SAMPLING.get(topic)
        if sampling is not None:
            self.sampled[topic] = sampling
        self.channels[topic] = Channel(
            topic,
            schema=Schema(name=schema_name, encoding=schema_encoding, data=schema_data),
            message_encoding=message_encoding,
            context=self.context,
            metadata=metadata,
        )

    def log(self, topic: str, log_time: int, payload: bytes, key: int = 0) -> None:
        """Serve one message to the clients subscribed to ``topic``, if any. On a sampled
        topic, a message is served when it is ``SAMPLE_PERIOD_NS`` after the last one served
        with the same key (``key``, the frame id, on a frame channel), or at the same log
        time (a tick's messages stay together). One in between is held, the newest of each
        key: served when its key has been quiet for a period of its topic's log time (a
        frame no longer sent), or by ``send_held`` (the end, the view served again), so
        that the view ends where the log does."""
        # The sampling first, a dictionary's work, which turns away nine in ten messages of a
        # per-tick channel before the call into the SDK that asks for its subscribers.
        sampling = self.sampled.get(topic)
        if sampling is not None:
            if log_time >= self._due.get(topic, _NEVER):
                self._send_quiet(topic, log_time)
            if sampling != PER_FRAME:
                key = 0
            slot = (topic, key)
            last = self._served.get(slot)
            if last is not None and last < log_time < last + SAMPLE_PERIOD_NS:
                self.hold(topic, log_time, payload, key)
                return
            if len(self._served) >= MAX_SAMPLED_KEYS:  # a bus babbling ever new ids
                self._served.clear()
                self._held.clear()
                self._due.clear()
            self._served[slot] = log_time
            held = self._held.get(topic)
            if held:
                held.pop(key, None)  # this one is newer
        self._send(topic, log_time, payload)

    def hold(self, topic: str, log_time: int, payload: bytes, key: int = 0) -> None:
        """Keep the message, unserved, as the newest of its topic (and key, on a frame
        channel) until ``send_held``. The writer hands it every message this way while it
        holds the view back (``LivePace``), so that the view, served again, shows where the
        run is and not where it was."""
        if self.sampled.get(topic) != PER_FRAME:
            key = 0
        held = self._held.setdefault(topic, {})
        if len(held) >= MAX_SAMPLED_KEYS and key not in held:  # ever new ids, as ``_served``
            held.clear()
        held[key] = (log_time, payload)
        self._due[topic] = min(self._due.get(topic, _NEVER), log_time + SAMPLE_PERIOD_NS)

    def send_held(self) -> None:
        """Serve every message held, now, oldest first (a topic's last message is then its
        newest, which a viewer shows): when the view is served again, and before the server
        closes."""
        held = sorted(
            (log_time, topic, key, payload)
            for topic, by_key in self._held.items()
            for key, (log_time, payload) in by_key.items()
        )
        self._held.clear()
        self._due.clear()
        for log_time, topic, key, payload in held:
            if topic in self.sampled:
                self._served[(topic, key)] = log_time
            self._send(topic, log_time, payload)

    def _send_quiet(self, topic: str, now: int) -> None:
        """Serve each held message of ``topic`` whose key has sent nothing for a period up
        to ``now`` (a log time of the same topic, whose messages come in log-time order): it
        is the newest of its key there is. A key that goes on is never served from here:
        its next message, within the period, takes the held one's place."""
        held = self._held[topic]
        due = _NEVER
        for key, (log_time, payload) in list(held.items()):
            if log_time + SAMPLE_PERIOD_NS <= now:
                del held[key]
                self._served[(topic, key)] = log_time
                self._send(topic, log_time, payload)
            else:
                due = min(due, log_time + SAMPLE_PERIOD_NS)
        self._due[topic] = due

    def _send(self, topic: str, log_time: int, payload: bytes) -> None:
        channel = self.channels.get(topic)
        if channel is None or not channel.has_sinks():
            return
        channel.log(payload, log_time=log_time)

    def close(self, timeout_s: float = CLOSE_TIMEOUT_S) -> bool:
        """Stop serving; False if the server had not stopped within ``timeout_s`` (s).

        The SDK's stop waits for every client's connection to close, and a client that has
        stopped reading (a viewer frozen, a laptop asleep) never lets it: a run's writer then
        did not end for minutes after the hand had stopped, its log long finished. So the
        stop is waited for a bounded time and then left to the process's end."""
        if self.server is None:
            return True
        self.send_held()  # the newest of each channel: the view ends where the log ends
        if any(channel.has_sinks() for channel in self.channels.values()):
            # The SDK's stop closes each connection at once, what is queued for it unsent:
            # the run's last messages, just served, were lost one run in three.
            time.sleep(SEND_GRACE_S)
        stopper = threading.Thread(target=self.server.stop, name="live-stop", daemon=True)
        stopper.start()
        stopper.join(timeout_s)
        if self.notes.refused:
            sys.stderr.write(
                f"live view: {self.notes.refused} connection(s) refused at the WebSocket "
                f"handshake; {HANDSHAKE_HINT}\n"
            )
            self.notes.refused = 0
        if self.notes.more:
            sys.stderr.write(f"live view: {self.notes.more} more notes of its clients not shown\n")
            self.notes.more = 0
        return not stopper.is_alive()


#: s of log time, the longest gap between two messages the live replay waits out: a run
#: records every tick, so a longer one is a log altered or a run stalled, and is played past
LIVE_GAP_S = 1.0


def serve_recording(
    path: Path, port: int, speed: float = 1.0, started: Callable[[LiveServer], None] | None = None
) -> int:
    """Stream every message of ``path`` in file order at its recorded spacing (divided by
    ``speed``); returns the number of messages played. The messages are read as ``handctl
    replay`` reads them (``handctl.recording.reader``): a truncated file plays up to its last
    complete chunk, a damaged chunk is left out."""
    from handctl.recording.reader import iter_messages, open_recording

    recording = open_recording(path)
    server = LiveServer(port, name=f"handctl replay {path.name}")
    try:
        # the channels the reader found (a damaged file's too: read here again with mcap's
        # own reader, a chunk that did not decompress was a traceback)
        for channel in recording.channels.values():
            schema = recording.schemas.get(channel.schema_id)
            server.add_channel(
                channel.topic,
                schema.name if schema else "",
                schema.encoding if schema else "",
                bytes(schema.data) if schema else b"",
                channel.message_encoding,
                dict(channel.metadata),
            )
        server.start()
        if started is not None:
            started(server)
        sent = 0
        first_log: int | None = None
        last_log = 0
        wall0 = 0.0
        longest = round(LIVE_GAP_S * 1e9)
        for topic, log_time, data in iter_messages(recording):
            if first_log is None:
                first_log, last_log, wall0 = log_time, log_time, time.monotonic()
            if log_time - last_log > longest:
                # a gap no run leaves (it records every tick): played past, the rest of the
                # log moved up. One message at log time 2**64 - 1 held the view for ever
                # (found by an outside audit)
                first_log += log_time - last_log - longest
            last_log = max(last_log, log_time)
            delay = wall0 + (log_time - first_log) * 1e-9 / speed - time.monotonic()
            if delay > 0:
                time.sleep(delay)
            per_frame = server.sampled.get(topic) == PER_FRAME
            server.log(topic, log_time, data, _frame_id(data) if per_frame else 0)
            sent += 1
        return sent
    finally:
        server.close()


def _frame_id(data: bytes) -> int:
    """The ``id`` of a recorded frame message (JSON); 0 when it has none."""
    try:
        frame_id = orjson.loads(data).get("id", 0)
    except (orjson.JSONDecodeError, AttributeError):
        return 0
    return frame_id if isinstance(frame_id, int) else 0
