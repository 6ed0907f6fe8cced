"""A lean MCAP writer for many small messages: the recorder writes about a dozen per tick.

The mcap library's ``Writer`` builds each message record field by field through a
``BytesIO`` and an index object, about 6 µs a message, which is most of the writer process's
time. Here a message is one ``struct.pack`` onto the chunk's ``bytearray`` and two integers
onto its channel's index. Every other record (header, schemas, channels, metadata, chunk,
statistics, indexes, footer) is built with the library's own record classes, and the summary
section is laid out as the library lays it out, so the files are what the library writes,
and its readers (and Foxglove) read them; the tests check with the library's readers.

Schemas and channels are written before the first chunk, outside it, so a file cut anywhere
after them still says what every channel is.
"""

from __future__ import annotations

import struct
import zlib
from collections import defaultdict
from typing import IO

import zstandard
from mcap.data_stream import RecordBuilder
from mcap.opcode import Opcode
from mcap.records import (
    Channel,
    Chunk,
    ChunkIndex,
    DataEnd,
    Footer,
    Header,
    McapRecord,
    Metadata,
    MetadataIndex,
    Schema,
    Statistics,
    SummaryOffset,
)

MAGIC = b"\x89MCAP0\r\n"
_MESSAGE = struct.Struct("<BQHIQQ")  # opcode, record length, channel, sequence, times
_MESSAGE_FIELDS = 22  # channel, sequence, log time, publish time
_INDEX_HEAD = struct.Struct("<BQHI")  # opcode, record length, channel, entries' byte length


def _bytes(record: McapRecord) -> bytes:
    builder = RecordBuilder()
    record.write(builder)
    data: bytes = builder.end()  # type: ignore[no-untyped-call]
    return data


class ChunkWriter:
    """Header, schemas, channels and metadata as they come; messages into the open chunk,
    which ``flush`` compresses, writes with its message indexes and pushes to the file;
    ``finish`` writes the summary section and the footer."""

    def __init__(self, out: IO[bytes], profile: str, library: str, level: int = 3) -> None:
        self.out = out
        self.offset = 0
        self.schemas: dict[int, Schema] = {}
        self.channels: dict[int, Channel] = {}
        self.chunk_indexes: list[ChunkIndex] = []
        self.metadata_indexes: list[MetadataIndex] = []
        self.counts: defaultdict[int, int] = defaultdict(int)
        self.messages = 0
        self.first_time: int | None = None
        self.last_time = 0
        self._compress = zstandard.ZstdCompressor(level=level).compress
        self._chunk = bytearray()
        self._index: dict[int, list[int]] = {}
        self._chunk_first: int | None = None
        self._chunk_last = 0
        self._write(MAGIC)
        self._write(_bytes(Header(profile, library)))

    def _write(self, data: bytes | bytearray) -> None:
        self.out.write(data)
        self.offset += len(data)

    def add_metadata(self, name: str, data: dict[str, str]) -> None:
        record = _bytes(Metadata(name, data))
        self.metadata_indexes.append(MetadataIndex(self.offset, len(record), name))
        self._write(record)

    def register_schema(self, name: str, encoding: str, data: bytes) -> int:
        schema = Schema(len(self.schemas) + 1, data, encoding, name)
        self.schemas[schema.id] = schema
        self._write(_bytes(schema))
        return schema.id

    def register_channel(
        self, topic: str, message_encoding: str, schema_id: int, metadata: dict[str, str]
    ) -> int:
        channel = Channel(len(self.channels) + 1, topic, message_encoding, metadata, schema_id)
        self.channels[channel.id] = channel
        self._write(_bytes(channel))
        return channel.id

    def add_message(self, channel_id: int, log_time: int, data: bytes, sequence: int) -> None:
        chunk = self._chunk
        entries = self._index.get(channel_id)
        if entries is None:
            entries = self._index[channel_id] = []
        entries += (log_time, len(chunk))
        chunk += _MESSAGE.pack(
            Opcode.MESSAGE, _MESSAGE_FIELDS + len(data), channel_id, sequence, log_time, log_time
        )
        chunk += data
        if self._chunk_first is None or log_time < self._chunk_first:
            self._chunk_first = log_time
        self._chunk_last = max(self._chunk_last, log_time)

    @property
    def chunk_bytes(self) -> int:
        return len(self._chunk)

    def flush(self) -> None:
        """Close the open chunk (if it holds anything) and push it to the file."""
        if not self._chunk:
            self.out.flush()
            return
        raw = bytes(self._chunk)
        packed = self._compress(raw)
        first = self._chunk_first or 0
        last = self._chunk_last
        start = self.offset
        record = _bytes(
            Chunk(
                compression="zstd",
                data=packed,
                message_end_time=last,
                message_start_time=first,
                uncompressed_crc=zlib.crc32(raw),
                uncompressed_size=len(raw),
            )
        )
        self._write(record)
        index_start = self.offset
        offsets: dict[int, int] = {}
        for channel_id, entries in self._index.items():
            offsets[channel_id] = self.offset
            count = len(entries) // 2
            self.counts[channel_id] += count
            self.messages += count
            body = struct.pack(f"<{len(entries)}Q", *entries)
            self._write(
                _INDEX_HEAD.pack(Opcode.MESSAGE_INDEX, 6 + len(body), channel_id, len(body)) + body
            )
        self.chunk_indexes.append(
            ChunkIndex(
                chunk_length=len(record),
                chunk_start_offset=start,
                compression="zstd",
                compressed_size=len(packed),
                message_end_time=last,
                message_index_length=self.offset - index_start,
                message_index_offsets=offsets,
                message_start_time=first,
                uncompressed_size=len(raw),
            )
        )
        if self.first_time is None or first < self.first_time:
            self.first_time = first
        self.last_time = max(self.last_time, last)
        self._chunk = bytearray()
        self._index = {}
        self._chunk_first = None
        self._chunk_last = 0
        self.out.flush()

    def finish(self) -> None:
        """Data end, then the summary (schemas, channels, statistics, chunk and metadata
        indexes, offsets to each group) and the footer, as the library writes them."""
        self.flush()
        self._write(_bytes(DataEnd(0)))
        summary_start = self.offset
        groups: list[tuple[int, list[McapRecord]]] = [
            (Opcode.SCHEMA, list(self.schemas.values())),
            (Opcode.CHANNEL, list(self.channels.values())),
            (
                Opcode.STATISTICS,
                [
                    Statistics(
                        attachment_count=0,
                        channel_count=len(self.channels),
                        channel_message_counts=dict(self.counts),
                        chunk_count=len(self.chunk_indexes),
                        message_count=self.messages,
                        message_end_time=self.last_time,
                        message_start_time=self.first_time or 0,
                        metadata_count=len(self.metadata_indexes),
                        schema_count=len(self.schemas),
                    )
                ],
            ),
            (Opcode.CHUNK_INDEX, list(self.chunk_indexes)),
            (Opcode.METADATA_INDEX, list(self.metadata_indexes)),
        ]
        summary = bytearray()
        offsets: list[SummaryOffset] = []
        for opcode, records in groups:
            group_start = summary_start + len(summary)
            for record in records:
                summary += _bytes(record)
            offsets.append(
                SummaryOffset(opcode, group_start, summary_start + len(summary) - group_start)
            )
        offset_start = summary_start + len(summary)
        for offset in offsets:
            summary += _bytes(offset)
        crc = zlib.crc32(summary)
        crc = zlib.crc32(
            struct.pack("<BQQQ", Opcode.FOOTER, 8 + 8 + 4, summary_start, offset_start), crc
        )
        self._write(summary)
        self._write(_bytes(Footer(summary_start, offset_start, crc)))
        self._write(MAGIC)
        self.out.flush()
