"""Reading a recording back: streaming, and whole up to where a truncated file stops.

A recording is read front to back, record by record, so it needs no summary section: a file
whose writer died reads as far as it goes. At the first record the end of the file cuts short
the walk stops quietly and ``Recording.problem`` says where. A chunk is used only when it
decompresses and matches its CRC, so a chunk cut in the middle is dropped whole, never
half-read: what comes back is every complete chunk.

The record bodies (metadata, channels, statistics) are parsed by the mcap library. The walk
itself and the slicing of messages out of a decompressed chunk are done here: the library's
``StreamReader`` also parses every message index and builds an object per message, which
costs more than the rest of a replay's reading. ``mcap``'s own readers (``make_reader`` on a
whole file, ``StreamReader`` on a truncated one) read the same files; the tests check both.
"""

from __future__ import annotations

import os
import struct
import zlib
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from io import BytesIO
from pathlib import Path
from typing import Any, BinaryIO

import orjson
from mcap.data_stream import ReadDataStream
from mcap.exceptions import McapError
from mcap.opcode import Opcode
from mcap.records import Channel, Metadata, Statistics

from handctl.errors import ConfigError
from handctl.recording import channels as ch

MAGIC = b"\x89MCAP0\r\n"
_RECORD = struct.Struct("<BQ")
_MESSAGE = struct.Struct("<HIQQ")  # channel id, sequence, log time, publish time
_MESSAGE_HEADER = _MESSAGE.size
_CHUNK = struct.Struct("<QQQII")  # start, end, uncompressed size, CRC, compression name length
#: Larger than any record handctl writes: a length beyond it is garbage, not a record.
_RECORD_LIMIT = 1 << 32
#: Errors that mean "the file ends (or goes bad) here", not "handctl is broken".
_CUT_SHORT: tuple[type[BaseException], ...] = (McapError, struct.error, ValueError, EOFError,
                                               RuntimeError, UnicodeDecodeError)
try:
    import zstandard

    _CUT_SHORT += (zstandard.ZstdError,)
except ImportError:  # pragma: no cover - mcap depends on it
    zstandard = None  # type: ignore[assignment]


@dataclass
class Recording:
    """What a first pass over the file found: metadata, channels, and whether it is whole."""

    path: Path
    metadata: dict[str, dict[str, str]] = field(default_factory=dict)
    topics: dict[int, str] = field(default_factory=dict)  # channel id -> topic
    message_counts: dict[str, int] = field(default_factory=dict)  # complete files only
    chunks: int = 0
    complete: bool = False  # footer and closing magic read
    problem: str = ""  # why the walk stopped early ("" when complete)

    @property
    def truncated(self) -> bool:
        return not self.complete

    def meta(self, name: str, key: str, default: str = "") -> str:
        return self.metadata.get(name, {}).get(key, default)

    def json_meta(self, name: str, key: str = "json") -> Any:
        text = self.meta(name, key)
        return orjson.loads(text) if text else None


def _fail(path: Path, found: str) -> ConfigError:
    return ConfigError(str(path), "", "an MCAP file (a handctl recording, e.g. from "
                                      "'handctl run recipe --log RUN.mcap')", found)


def open_recording(path: str | Path) -> Recording:
    """First pass: metadata, channels, chunk count, completeness. Bad input is a ConfigError
    naming the file; a truncated file is not an error, it is a ``Recording`` that says so."""
    path = Path(path)
    if not path.is_file():
        raise _fail(path, "no such file" if not path.exists() else "not a regular file")
    with path.open("rb") as handle:
        head = handle.read(len(MAGIC))
        if head != MAGIC:
            raise _fail(path, f"a file starting with {head[:8]!r}" if head else "an empty file")
        recording = Recording(path)
        first_chunk: bytes | None = None
        walk = _Walk(handle)
        try:
            for op, body in walk.records((Opcode.CHUNK, Opcode.METADATA, Opcode.CHANNEL,
                                          Opcode.STATISTICS, Opcode.FOOTER)):
                if op == Opcode.CHUNK:
                    data = _chunk_data(body)  # a chunk cut short raises here: the walk ends
                    recording.chunks += 1
                    if first_chunk is None:
                        first_chunk = data
                elif op == Opcode.METADATA:
                    meta = Metadata.read(_stream(body))
                    recording.metadata[meta.name] = dict(meta.metadata)
                elif op == Opcode.CHANNEL:
                    channel = Channel.read(_stream(body))
                    recording.topics[channel.id] = channel.topic
                elif op == Opcode.STATISTICS:
                    stats = Statistics.read(_stream(body))
                    counts = dict(stats.channel_message_counts)
                    recording.message_counts = {str(k): v for k, v in counts.items()}
                elif op == Opcode.FOOTER:
                    recording.complete = handle.read(len(MAGIC)) == MAGIC
                    break
        except _CUT_SHORT as exc:
            recording.problem = (f"reading stopped at byte {walk.offset} after "
                                 f"{recording.chunks} complete chunks "
                                 f"({type(exc).__name__}{': ' + str(exc) if str(exc) else ''})")
        if recording.message_counts:
            recording.message_counts = {recording.topics.get(int(cid), cid): n
                                        for cid, n in recording.message_counts.items()}
        if not recording.topics and first_chunk is not None:
            for op, body in _records(first_chunk):
                if op == Opcode.CHANNEL:
                    channel = Channel.read(_stream(body))
                    recording.topics[channel.id] = channel.topic
    if not recording.complete and not recording.problem:
        recording.problem = (f"the file ends at byte {walk.offset} after {recording.chunks} "
                             "complete chunks, without its summary")
    return recording


def _stream(body: bytes) -> ReadDataStream:
    return ReadDataStream(BytesIO(body))


class _Walk:
    """The top-level records of an MCAP file, in order, from just after the magic."""

    def __init__(self, handle: BinaryIO) -> None:
        self.handle = handle
        self.offset = len(MAGIC)
        self.size = os.fstat(handle.fileno()).st_size

    def records(self, wanted: Iterable[int]) -> Iterator[tuple[int, bytes]]:
        """``(opcode, body)`` of the wanted records; others are skipped unread. Ends quietly
        at the end of the file; raises EOFError inside a record."""
        keep = {int(op) for op in wanted}
        handle = self.handle
        handle.seek(self.offset)
        while True:
            head = handle.read(9)
            if not head:
                return
            if len(head) < 9:
                raise EOFError("the file ends inside a record header")
            op, length = _RECORD.unpack(head)
            if length > _RECORD_LIMIT:
                raise ValueError(f"a record of {length} bytes: not a record boundary")
            if op in keep:
                body = handle.read(length)
                if len(body) < length:
                    raise EOFError(f"the file ends inside a record ({len(body)} of {length} "
                                   "bytes)")
                yield op, body
            else:
                if self.offset + 9 + length > self.size:
                    raise EOFError("the file ends inside a record")
                handle.seek(length, 1)
            self.offset += 9 + length


def _chunk_data(body: bytes) -> bytes:
    """The records of a chunk record's body, decompressed and checked against its CRC."""
    _, _, size, crc, name_length = _CHUNK.unpack_from(body)
    compression = body[_CHUNK.size:_CHUNK.size + name_length].decode()
    at = _CHUNK.size + name_length
    (data_length,) = struct.unpack_from("<Q", body, at)
    packed = body[at + 8:at + 8 + data_length]
    if len(packed) != data_length:
        raise EOFError("a chunk cut short")
    if compression == "zstd":
        if zstandard is None:  # pragma: no cover
            raise ValueError("zstd chunks need the zstandard package")
        data: bytes = zstandard.ZstdDecompressor().decompress(packed, max_output_size=size)
    elif compression == "lz4":
        import lz4.frame  # type: ignore[import-not-found, import-untyped, unused-ignore]

        data = lz4.frame.decompress(packed)
    elif compression == "":
        data = packed
    else:
        raise ValueError(f"unknown chunk compression {compression!r}")
    if len(data) != size:
        raise ValueError(f"chunk holds {len(data)} bytes, expected {size}")
    if crc and zlib.crc32(data) != crc:
        raise ValueError("chunk CRC mismatch")
    return data


def _records(data: bytes) -> Iterator[tuple[int, bytes]]:
    offset, end = 0, len(data)
    while offset + 9 <= end:
        op, length = _RECORD.unpack_from(data, offset)
        start = offset + 9
        yield op, data[start:start + length]
        offset = start + length


def iter_messages(recording: Recording, topics: Iterable[str] | None = None
                  ) -> Iterator[tuple[str, int, bytes]]:
    """``(topic, log_time_ns, json_bytes)`` in file order, up to the last complete chunk.

    File order is the writer's order, which is what a replay wants: a tick's frames and events
    come before the tick's own row (see ``writer.Encoder.drain``).
    """
    wanted = None if topics is None else set(topics)
    names: dict[int, str] = dict(recording.topics)
    keep = {cid for cid, topic in names.items() if wanted is None or topic in wanted}
    unpack_record = _RECORD.unpack_from
    unpack_message = _MESSAGE.unpack_from
    message_op, channel_op = int(Opcode.MESSAGE), int(Opcode.CHANNEL)
    with recording.path.open("rb") as handle:
        try:
            for _, body in _Walk(handle).records((Opcode.CHUNK,)):
                data = _chunk_data(body)
                offset, end = 0, len(data)
                while offset + 9 <= end:
                    op, length = unpack_record(data, offset)
                    start = offset + 9
                    offset = start + length
                    if op == message_op:
                        cid, _, log_time, _ = unpack_message(data, start)
                        if cid in keep:
                            yield names[cid], log_time, data[start + _MESSAGE_HEADER:offset]
                    elif op == channel_op:
                        channel = Channel.read(_stream(data[start:offset]))
                        if channel.id not in names:
                            names[channel.id] = channel.topic
                            if wanted is None or channel.topic in wanted:
                                keep.add(channel.id)
        except _CUT_SHORT:
            return  # open_recording has said where and why


def iter_chunks(recording: Recording, topics: Iterable[str]
                ) -> Iterator[tuple[list[str], list[Any]]]:
    """The topics and decoded messages of the wanted channels in file order, in batches of
    a few thousand, each batch decoded by one ``orjson.loads`` of a JSON array made of its
    messages: a re-run reads a dozen small messages per tick, and a call per message costs
    more than the parsing itself."""
    topics_: list[str] = []
    raw: list[bytes] = []
    for topic, _, data in iter_messages(recording, topics):
        topics_.append(topic)
        raw.append(data)
        if len(raw) >= 4096:
            yield topics_, orjson.loads(b"[" + b",".join(raw) + b"]")
            topics_, raw = [], []
    if raw:
        yield topics_, orjson.loads(b"[" + b",".join(raw) + b"]")


def iter_decoded(recording: Recording, topics: Iterable[str] | None = None
                 ) -> Iterator[tuple[str, int, dict[str, Any]]]:
    loads = orjson.loads
    for topic, log_time, data in iter_messages(recording, topics):
        yield topic, log_time, loads(data)


def require_topics(recording: Recording, topics: Iterable[str], what: str) -> None:
    """A ConfigError naming the file when channels ``what`` needs are not in it."""
    have = set(recording.topics.values())
    missing = [t for t in topics if t not in have]
    if missing:
        raise ConfigError(str(recording.path), "channels",
                          f"the channels {', '.join(missing)} for {what} (a recording made by "
                          "'handctl run recipe --log')",
                          ", ".join(sorted(have)) or "no channels")


def check_format(recording: Recording) -> None:
    """Refuse a handctl recording of another format version (a foreign MCAP passes: it has no
    version, and the channel checks say what it lacks)."""
    version = recording.meta("handctl.command", "format_version")
    if version and version != str(ch.FORMAT_VERSION):
        raise ConfigError(str(recording.path), "metadata handctl.command.format_version",
                          f"format version {ch.FORMAT_VERSION}", version)
