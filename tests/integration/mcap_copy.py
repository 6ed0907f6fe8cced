"""A recording copied record by record with the mcap library, its messages and metadata
through the caller's changes: the logs the replay tests alter after the run."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

from mcap.reader import make_reader
from mcap.writer import Writer

#: ``change(topic, index within the topic, raw message) -> raw message``
Change = Callable[[str, int, bytes], bytes]


def rewrite(
    source: Path,
    target: Path,
    change: Change | None = None,
    metadata: Callable[[str, dict[str, str]], dict[str, str]] | None = None,
    formats: dict[str, tuple[str, str, str]] | None = None,
    times: Callable[[str, int], int] | None = None,
    drop: tuple[str, ...] = (),
    empty: tuple[str, ...] = (),
    after: Callable[[str, int, bytes], list[bytes]] | None = None,
    keep: Callable[[str, bytes], bool] | None = None,
) -> None:
    """Copy a recording record by record with the mcap library, the messages through
    ``change``, the metadata through ``metadata``, the channels of the topics in ``formats``
    given another (message encoding, schema name, schema encoding), and each message's log
    time through ``times(topic, log_time) -> log_time``; the channels of the topics in
    ``drop`` are left out, with their messages, and the messages of those in ``empty``
    (their channels kept); ``after(topic, index, raw message)`` gives messages to put in
    after that one, on its channel at its log time; ``keep(topic, raw message)`` false leaves
    that message out."""
    with source.open("rb") as handle:
        reader = make_reader(handle)
        summary = reader.get_summary()
        assert summary is not None
        messages = list(reader.iter_messages(log_time_order=False))
        records = list(reader.iter_metadata())
    counts: dict[str, int] = {}
    with target.open("wb") as out:
        writer = Writer(out)
        writer.start()
        for meta in records:
            values = dict(meta.metadata)
            writer.add_metadata(meta.name, metadata(meta.name, values) if metadata else values)
        schema_ids = {
            s.id: writer.register_schema(s.name, s.encoding, s.data)
            for s in summary.schemas.values()
        }
        channel_ids = {}
        for c in summary.channels.values():
            if c.topic in drop:
                continue
            encoding, schema_id = c.message_encoding, schema_ids[c.schema_id]
            if formats and c.topic in formats:
                encoding, name, schema_encoding = formats[c.topic]
                old = summary.schemas[c.schema_id]
                schema_id = writer.register_schema(name, schema_encoding, old.data)
            channel_ids[c.id] = writer.register_channel(c.topic, encoding, schema_id, c.metadata)
        for _, channel, message in messages:
            if channel.topic in drop or channel.topic in empty:
                continue
            if keep is not None and not keep(channel.topic, message.data):
                continue
            index = counts.get(channel.topic, 0)
            counts[channel.topic] = index + 1
            raw = change(channel.topic, index, message.data) if change else message.data
            log_time = times(channel.topic, message.log_time) if times else message.log_time
            writer.add_message(channel_ids[channel.id], log_time, raw, message.publish_time)
            for extra in after(channel.topic, index, message.data) if after else ():
                writer.add_message(channel_ids[channel.id], log_time, extra, log_time)
        writer.finish()  # type: ignore[no-untyped-call]  # mcap's Writer is untyped
