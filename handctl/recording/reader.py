"""Reading a recording back: through its index when it has one, else front to back up to
where a truncated file stops.

A finished file ends in a summary section (channels, statistics, chunk and metadata indexes)
and a footer. When the summary is there and matches its CRC, the chunks are read where the
index says they are, so a chunk damaged in the middle of the file is named (its place, its
log times, what is wrong with it) and skipped, and every chunk after it is still read.

A file without a summary (its writer died) is read front to back, record by record: it reads
as far as it goes. At the first record the end of the file cuts short the walk stops quietly
and ``Recording.problem`` says where. Either way a chunk is used only when it decompresses and
matches its CRC, so a damaged or cut chunk is dropped whole, never half-read.

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
from mcap.records import Channel, ChunkIndex, Metadata, MetadataIndex, Schema, Statistics

from handctl.errors import ConfigError, Description, absent
from handctl.recording import channels as ch
from handctl.recording.loglock import partials_beside
from handctl.recording.messages import MessageCheck

MAGIC = b"\x89MCAP0\r\n"
_RECORD = struct.Struct("<BQ")
_MESSAGE = struct.Struct("<HIQQ")  # channel id, sequence, log time, publish time
_MESSAGE_HEADER = _MESSAGE.size
_CHUNK = struct.Struct("<QQQII")  # start, end, uncompressed size, CRC, compression name length
#: Larger than any record handctl writes: a length beyond it is garbage, not a record.
_RECORD_LIMIT = 1 << 32
#: bytes, the most a chunk may hold once decompressed: handctl's own hold about 0.35 MB, and
#: a 49 KB chunk that declared 1.5 GiB of zeros (with a CRC to match) took 1.6 GB to read
MAX_CHUNK_BYTES = 64 << 20
#: The last opcode MCAP defines (0x0F, DataEnd); 0x80 and up are user records, which a
#: handctl log never holds.
_LAST_OPCODE = 0x0F
#: Errors that mean "the file ends (or goes bad) here", not "handctl is broken".
_CUT_SHORT: tuple[type[BaseException], ...] = (
    McapError,
    struct.error,
    ValueError,
    EOFError,
    RuntimeError,
    UnicodeDecodeError,
    OverflowError,
)
try:
    import zstandard

    _CUT_SHORT += (zstandard.ZstdError,)
except ImportError:  # pragma: no cover - mcap depends on it
    zstandard = None  # type: ignore[assignment]


@dataclass(frozen=True)
class BadChunk:
    """A chunk the index points to that cannot be read: where it is and what it held."""

    number: int  # 0 first, in file order
    offset: int  # byte offset of the chunk record
    length: int  # bytes
    start_ns: int  # log times of its first and last message, from the index
    end_ns: int
    reason: str

    def describe(self, first_ns: int) -> str:
        return (
            f"chunk {self.number} at byte {self.offset} ({self.length} bytes, log time "
            f"{self.start_ns}..{self.end_ns} ns, {(self.start_ns - first_ns) * 1e-9:.3f}.."
            f"{(self.end_ns - first_ns) * 1e-9:.3f} s into the file) is damaged "
            f"({self.reason})"
        )


@dataclass
class Recording:
    """What a first pass over the file found: metadata, channels, and whether it is whole."""

    path: Path
    metadata: dict[str, dict[str, str]] = field(default_factory=dict)
    message_counts: dict[str, int] = field(default_factory=dict)  # complete files only
    #: whether the file holds a statistics record (``message_counts`` is then its counts,
    #: of no message at all if it is empty)
    statistics: bool = False
    chunks: int = 0  # chunks that read
    complete: bool = False  # footer and closing magic read, and every chunk read
    problem: str = ""  # what is missing and why ("" when complete)
    #: ``(offset, length)`` of each chunk that reads, where the summary's index or the first
    #: pass front to back found it; every later read takes these. None: not opened yet.
    chunk_spans: list[tuple[int, int]] | None = None
    bad_chunks: list[BadChunk] = field(default_factory=list)
    bad_metadata: list[str] = field(default_factory=list)  # names of indexed records that fail
    #: the summary's index does not describe the chunks it lists (``_counts_disagree``)
    bad_index: bool = False
    #: each channel's record and each schema's, by id: the topics, and what ``check_format``
    #: holds a handctl topic's encoding and schema to
    channels: dict[int, Channel] = field(default_factory=dict)
    schemas: dict[int, Schema] = field(default_factory=dict)
    #: a run still writes the file (its writer holds the file's lock): not cut short, not
    #: yet finished, and each read of it finds more
    being_written: bool = False
    #: where the messages are read from, when not ``path`` (a private copy of it: ``replay
    #: --to-bus`` checks and sends from one reading of the file)
    read_from: Path | None = None

    @property
    def topics(self) -> dict[int, str]:
        """Channel id to topic."""
        return {cid: channel.topic for cid, channel in self.channels.items()}

    @property
    def damaged(self) -> bool:
        """Some chunks do not read (where the summary indexes them, or, without one, as whole
        records front to back), or metadata the summary indexes does not."""
        return bool(self.bad_chunks or self.bad_metadata or self.bad_index)

    @property
    def truncated(self) -> bool:
        """The file ends before its footer (or its summary is unreadable)."""
        return not self.complete and not self.damaged

    def meta(self, name: str, key: str, default: str = "") -> str:
        return self.metadata.get(name, {}).get(key, default)

    def json_meta(self, name: str, key: str = "json") -> dict[str, Any] | None:
        """A metadata value that is a JSON object (None when absent); anything else is a
        ConfigError naming the record and the key."""
        text = self.meta(name, key)
        if not text:
            return None
        try:
            value = orjson.loads(text)
        except orjson.JSONDecodeError as exc:
            raise ConfigError(
                str(self.path), f"metadata {name}.{key}", f"a JSON object ({exc})", text
            ) from None
        if not isinstance(value, dict):
            raise ConfigError(str(self.path), f"metadata {name}.{key}", "a JSON object", value)
        return value

    def meta_int(self, name: str, key: str, default: int, minimum: int = 0) -> int:
        """A metadata value that is a whole number of at least ``minimum`` (``default`` when
        absent or empty); anything else is a ConfigError naming the record and the key."""
        text = self.meta(name, key)
        if not text:
            return default
        body = text[1:] if text[:1] == "-" else text
        value = int(text) if body.isascii() and body.isdigit() and len(body) <= 19 else None
        if value is None or value < minimum:
            raise ConfigError(
                str(self.path), f"metadata {name}.{key}", f"a whole number >= {minimum}", text
            )
        return value


def _check_tick_count(recording: Recording) -> None:
    """A finished file holds the tick rows its end record counts, and as many rows of each
    channel every running tick writes: every message after a tick cut out and the file
    finished again read as a complete run of that many ticks, its re-run "bit-exact" on them;
    a file with a channel's every message taken out, or with none at all, as a complete run
    whose torques were none."""
    if not recording.complete or not recording.statistics:
        return
    _check_frame_count(recording)
    told = recording.meta(ch.META_END, "ticks")
    if not told:
        return
    counts = recording.message_counts
    rows = counts.get(ch.TIMING, 0)
    if recording.meta_int(ch.META_END, "ticks", 0) != rows:
        raise ConfigError(
            str(recording.path),
            f"channel {ch.TIMING}",
            f"the {told} tick rows the end record ({ch.META_END}.ticks) counts",
            f"{rows} rows",
        )
    held = {topic: counts.get(topic, 0) for topic in ch.ACTIVE_TICK_TOPICS}
    most = max(held, key=lambda topic: held[topic])
    for topic, n in held.items():
        # the channel short of the others is the one said: the others agree with each other
        if n != held[most] or n > rows:
            raise ConfigError(
                str(recording.path),
                f"channel {topic}",
                f"a message for each running tick, at most the {rows} tick rows and as many "
                f"as {most} holds ({held[most]})",
                Description(f"{n} messages"),
            )


def _check_frame_count(recording: Recording) -> None:
    """A finished file holds the frames its end record counts, on /can/rx and /can/tx between
    them: the writer counts every frame it writes, a refused one too (on /can/tx, ok false),
    and none it dropped (those are ``dropped_frames``), as it has since its first version. A
    file with every sent frame taken out, or each written twice, read as a complete run, and
    ``--export`` wrote the twice-written frames, exit 0. A file whose end record has no count
    (one its control process ended before the set-up) is not checked, nor one without either
    channel at all: ``require_topics`` names that one."""
    told = recording.meta(ch.META_END, "frames")
    have = set(recording.topics.values())
    if not told or ch.CAN_RX not in have or ch.CAN_TX not in have:
        return
    counts = recording.message_counts
    rx, tx = counts.get(ch.CAN_RX, 0), counts.get(ch.CAN_TX, 0)
    if recording.meta_int(ch.META_END, "frames", -1) != rx + tx:
        raise ConfigError(
            str(recording.path),
            f"channels {ch.CAN_RX} and {ch.CAN_TX}",
            f"the {told} frames the end record ({ch.META_END}.frames) counts, between them",
            Description(f"{rx} on {ch.CAN_RX} and {tx} on {ch.CAN_TX}, {rx + tx} in all"),
        )


def _fail(path: Path, found: str) -> ConfigError:
    return ConfigError(
        str(path),
        "",
        "an MCAP file (a handctl recording, e.g. from 'handctl run recipe --log RUN.mcap')",
        Description(found),
    )


def _empty_file(path: Path) -> str:
    """An empty file, and the recording a run killed in its start-up left beside it: the
    run's writer fills a hidden file next to the path (``.NAME.PID.handctl-partial``) and
    puts it at the path as the run begins, so a run killed (SIGKILL) before then leaves the
    path's empty placeholder and the recording beside it, which nothing named (an outside
    audit). Of several (runs killed one after another), the newest by its time of change:
    the last by name sorted PIDs as text, and named an older run's of PID 999 over 10000's."""
    beside = partials_beside(path)
    if not beside:
        return "an empty file"
    newest = max(beside, key=lambda p: (_mtime_ns(p), p.name))
    which = f"the newest of {len(beside)}: " if len(beside) > 1 else ""
    return (
        f"an empty file, beside the recording of a run killed before it began: {newest} "
        f"({which}replay that one)"
    )


def _mtime_ns(path: Path) -> int:
    """``path``'s time of last change, or -1 for one gone since it was listed."""
    try:
        return path.stat().st_mtime_ns
    except OSError:
        return -1


def open_recording(path: str | Path) -> Recording:
    """First pass: metadata, channels, chunk count, completeness. Bad input is a ConfigError
    naming the file; a truncated or damaged file is not an error, it is a ``Recording`` that
    says so."""
    path = Path(path)
    if not path.is_file():
        raise _fail(path, absent(path) if not path.exists() else "not a regular file")
    try:
        return _open_recording(path)
    except OSError as exc:
        # a file that says it is regular and cannot be read (a disk's or a network file
        # system's read error, /proc/self/mem): bad input named, as the YAML loaders do
        expected = "a readable file (a handctl recording)"
        raise ConfigError(str(path), "", expected, str(exc)) from None


def _open_recording(path: Path) -> Recording:
    with path.open("rb") as handle:
        head = handle.read(len(MAGIC))
        if head != MAGIC:
            raise _fail(path, f"a file starting with {head[:8]!r}" if head else _empty_file(path))
        recording = Recording(path)
        unreadable = ""
        try:
            index = _read_index(handle)
        except _CUT_SHORT as exc:
            index, unreadable = None, f"its summary does not read ({_why(exc)})"
        if index is not None and index.chunks:
            _open_indexed(handle, recording, index)
        else:
            _open_walk(handle, recording)
            if unreadable:
                recording.complete = False
                recording.problem = f"{unreadable}, so it was read front to back: " + (
                    recording.problem or f"{recording.chunks} complete chunks"
                )
        if not recording.topics:
            _topics_from_first_chunk(handle, recording)
        recording.being_written = not recording.complete and _locked_by_a_writer(handle)
    return recording


def _locked_by_a_writer(handle: BinaryIO) -> bool:
    """Whether a run's writer holds the file's lock (``recorder._open_log``): a shared lock
    of ours is refused while it does. A file system without locks says no."""
    import fcntl

    try:
        fcntl.flock(handle.fileno(), fcntl.LOCK_SH | fcntl.LOCK_NB)
    except BlockingIOError:
        return True
    except OSError:
        return False
    fcntl.flock(handle.fileno(), fcntl.LOCK_UN)
    return False


def _why(exc: BaseException) -> str:
    return f"{type(exc).__name__}{': ' + str(exc) if str(exc) else ''}"


@dataclass
class _Index:
    """What the summary section of a finished file holds."""

    counts: dict[int, int]
    chunks: list[ChunkIndex]
    metadata: list[MetadataIndex]
    channels: dict[int, Channel] = field(default_factory=dict)
    schemas: dict[int, Schema] = field(default_factory=dict)
    statistics: bool = False


_FOOTER_BODY = struct.Struct("<QQI")  # summary start, summary offset start, summary CRC


def _read_index(handle: BinaryIO) -> _Index | None:
    """The summary of a file that ends in a footer and the closing magic; None for a file
    that does not (cut short) or has no summary. Raises when the summary is there but does
    not read or does not match its CRC."""
    size = os.fstat(handle.fileno()).st_size
    footer_at = size - len(MAGIC) - 9 - _FOOTER_BODY.size
    if footer_at < len(MAGIC):
        return None
    handle.seek(footer_at)
    tail = handle.read(9 + _FOOTER_BODY.size + len(MAGIC))
    if tail[-len(MAGIC) :] != MAGIC:
        return None
    op, length = _RECORD.unpack_from(tail)
    if op != Opcode.FOOTER or length != _FOOTER_BODY.size:
        raise ValueError("no footer record before the closing magic")
    summary_start, _, crc = _FOOTER_BODY.unpack_from(tail, 9)
    if summary_start == 0:
        return None
    if not len(MAGIC) <= summary_start <= footer_at:
        raise ValueError(f"the footer puts the summary at byte {summary_start}")
    handle.seek(summary_start)
    summary = handle.read(footer_at - summary_start)
    if crc and zlib.crc32(tail[: 9 + 16], zlib.crc32(summary)) != crc:
        raise ValueError("summary CRC mismatch")
    index = _Index({}, [], [])
    for op, body in _records(summary):
        if op == Opcode.CHANNEL:
            channel = Channel.read(_stream(body))
            index.channels[channel.id] = channel
        elif op == Opcode.SCHEMA:
            schema = Schema.read(_stream(body))
            index.schemas[schema.id] = schema
        elif op == Opcode.STATISTICS:
            index.counts = dict(Statistics.read(_stream(body)).channel_message_counts)
            index.statistics = True
        elif op == Opcode.CHUNK_INDEX:
            index.chunks.append(ChunkIndex.read(_stream(body)))
        elif op == Opcode.METADATA_INDEX:
            index.metadata.append(MetadataIndex.read(_stream(body)))
    return index


def _read_record(handle: BinaryIO, offset: int, length: int, opcode: int) -> bytes:
    """The body of the record an index says is at ``offset`` (``length`` bytes in all)."""
    size = os.fstat(handle.fileno()).st_size
    if not 9 <= length <= _RECORD_LIMIT or offset + length > size:
        # an index can say anything: a length of 2^63 raised OverflowError, a traceback
        raise ValueError(
            f"an index entry of {length} bytes at offset {offset}, past the file's {size} bytes"
        )
    handle.seek(offset)
    raw = handle.read(length)
    if len(raw) != length:
        raise EOFError(f"the file ends inside the record ({len(raw)} of {length} bytes)")
    op, body_length = _RECORD.unpack_from(raw)
    if op != opcode or 9 + body_length != length:
        raise ValueError(
            f"a record of opcode 0x{op:02X} and {body_length} bytes where the "
            f"index has opcode 0x{opcode:02X} and {length - 9} bytes"
        )
    return raw[9:]


def _open_indexed(handle: BinaryIO, recording: Recording, index: _Index) -> None:
    """The first pass through the index: every chunk checked, the bad ones named."""
    recording.channels = dict(index.channels)
    recording.schemas = dict(index.schemas)
    recording.chunk_spans = []
    chunks = sorted(index.chunks, key=lambda c: c.chunk_start_offset)
    held: dict[int, int] = {}  # messages per channel, in the chunks that read
    for number, chunk in enumerate(chunks):
        try:
            _count_messages(
                _chunk_data(
                    _read_record(handle, chunk.chunk_start_offset, chunk.chunk_length, Opcode.CHUNK)
                ),
                held,
            )
        except _CUT_SHORT as exc:
            recording.bad_chunks.append(
                BadChunk(
                    number,
                    chunk.chunk_start_offset,
                    chunk.chunk_length,
                    chunk.message_start_time,
                    chunk.message_end_time,
                    _why(exc),
                )
            )
            continue
        recording.chunk_spans.append((chunk.chunk_start_offset, chunk.chunk_length))
        recording.chunks += 1
    problems = []
    for meta_index in index.metadata:
        try:
            meta = Metadata.read(
                _stream(_read_record(handle, meta_index.offset, meta_index.length, Opcode.METADATA))
            )
        except _CUT_SHORT as exc:
            recording.bad_metadata.append(meta_index.name)
            problems.append(
                f"metadata record {meta_index.name!r} at byte {meta_index.offset} "
                f"is damaged ({_why(exc)})"
            )
            continue
        recording.metadata[meta.name] = dict(meta.metadata)
    if recording.bad_chunks:
        first = min(c.message_start_time for c in chunks)
        last = recording.bad_chunks[-1].number
        problems[:0] = [bad.describe(first) for bad in recording.bad_chunks]
        problems.append(
            f"its messages are left out; {recording.chunks} of {len(chunks)} "
            f"chunks read, {len(chunks) - 1 - last} of them after the last "
            "damaged one"
        )
    elif index.counts and held != {cid: n for cid, n in index.counts.items() if n}:
        # an index that leaves a chunk out, or lists one twice, was believed: "complete",
        # with a tenth of the ticks missing, or doubled, and --to-bus sent them so
        problems.append(_counts_disagree(recording.topics, index.counts, held))
        recording.bad_index = True
    recording.complete = not problems
    recording.problem = "; ".join(problems)
    if recording.complete:
        topics = recording.topics
        recording.message_counts = {topics.get(cid, str(cid)): n for cid, n in index.counts.items()}
        recording.statistics = index.statistics


def _count_messages(data: bytes, held: dict[int, int]) -> None:
    """Add the messages of a chunk's records ``data`` to ``held``, by channel."""
    offset, end = 0, len(data)
    unpack_record, message_op = _RECORD.unpack_from, int(Opcode.MESSAGE)
    while offset + 9 <= end:
        op, length = unpack_record(data, offset)
        if op == message_op:
            cid = int.from_bytes(data[offset + 9 : offset + 11], "little")
            held[cid] = held.get(cid, 0) + 1
        offset += 9 + length


def _counts_disagree(topics: dict[int, str], counted: dict[int, int], held: dict[int, int]) -> str:
    """What the summary's statistics count against what the indexed chunks hold."""
    cid = next(c for c in sorted(set(counted) | set(held)) if counted.get(c, 0) != held.get(c, 0))
    return (
        f"its summary counts {counted.get(cid, 0)} messages of {topics.get(cid, str(cid))} and "
        f"the chunks its index lists hold {held.get(cid, 0)}: the index does not describe the "
        "file (a chunk left out or listed twice)"
    )


def _open_walk(handle: BinaryIO, recording: Recording) -> None:
    """The first pass front to back, for a file without a (readable) summary."""
    walk = _Walk(handle)
    spans: list[tuple[int, int]] = []
    number = first_ns = 0  # chunks met; the log time of the first one's first message
    try:
        for op, body in walk.records(
            (
                Opcode.CHUNK,
                Opcode.METADATA,
                Opcode.CHANNEL,
                Opcode.SCHEMA,
                Opcode.STATISTICS,
                Opcode.FOOTER,
            )
        ):
            if op == Opcode.CHUNK:
                # a whole record whose chunk does not read is damage, not the file's end:
                # named and stepped over by its length, as the index steps over it. (Ended
                # here, one flipped bit left every chunk after it unread, and the log was
                # said to be only cut short.)
                start, end = _CHUNK.unpack_from(body)[:2] if len(body) >= _CHUNK.size else (0, 0)
                first_ns = first_ns if number else start
                try:
                    _chunk_data(body)
                except _CUT_SHORT as exc:
                    recording.bad_chunks.append(
                        BadChunk(number, walk.offset, 9 + len(body), start, end, _why(exc))
                    )
                else:
                    spans.append((walk.offset, 9 + len(body)))
                    recording.chunks += 1
                number += 1
            elif op == Opcode.METADATA:
                meta = Metadata.read(_stream(body))
                recording.metadata[meta.name] = dict(meta.metadata)
            elif op == Opcode.CHANNEL:
                channel = Channel.read(_stream(body))
                recording.channels[channel.id] = channel
            elif op == Opcode.SCHEMA:
                schema = Schema.read(_stream(body))
                recording.schemas[schema.id] = schema
            elif op == Opcode.STATISTICS:
                stats = Statistics.read(_stream(body))
                counts = dict(stats.channel_message_counts)
                recording.message_counts = {str(k): v for k, v in counts.items()}
                recording.statistics = True
            elif op == Opcode.FOOTER:
                recording.complete = handle.read(len(MAGIC)) == MAGIC
                break
    except _CUT_SHORT as exc:
        recording.problem = (
            f"reading stopped at byte {walk.offset} after "
            f"{recording.chunks} complete chunks ({_why(exc)})"
        )
    recording.chunk_spans = spans
    if recording.bad_chunks:
        recording.complete = False
        after = sum(1 for s in spans if s[0] > recording.bad_chunks[-1].offset)
        recording.problem = "; ".join(
            [bad.describe(first_ns) for bad in recording.bad_chunks]
            + [
                f"its messages are left out; {recording.chunks} of {number} chunks read, "
                f"{after} of them after the last damaged one"
            ]
            + ([recording.problem] if recording.problem else [])
        )
    if recording.message_counts:
        topics = recording.topics
        recording.message_counts = {
            topics.get(int(cid), cid): n for cid, n in recording.message_counts.items()
        }
    if not recording.complete and not recording.problem:
        recording.problem = (
            f"the file ends at byte {walk.offset} after {recording.chunks} "
            "complete chunks, without its summary"
        )


def _topics_from_first_chunk(handle: BinaryIO, recording: Recording) -> None:
    """Channels written inside the chunks only (as the mcap library's writer does)."""
    try:
        for body in _chunk_bodies(handle, recording):
            for op, record in _records(_chunk_data(body)):
                if op == Opcode.CHANNEL:
                    channel = Channel.read(_stream(record))
                    recording.channels[channel.id] = channel
                elif op == Opcode.SCHEMA:
                    schema = Schema.read(_stream(record))
                    recording.schemas[schema.id] = schema
            return
    except _CUT_SHORT:
        return


def _chunk_bodies(handle: BinaryIO, recording: Recording) -> Iterator[bytes]:
    """The body of every chunk record to read, in file order: those the index lists and that
    read, or every one up to where the file stops."""
    if recording.chunk_spans is None:
        for _, body in _Walk(handle).records((Opcode.CHUNK,)):
            yield body
        return
    for offset, length in recording.chunk_spans:
        yield _read_record(handle, offset, length, Opcode.CHUNK)


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
            if op == 0 or op > _LAST_OPCODE:
                # no record: zeros where a power loss left the file's tail unwritten, read
                # 9 bytes at a time (a 4 GiB tail of zeros took minutes for each pass)
                raise ValueError(f"no record here (opcode 0x{op:02X})")
            if op in keep:
                body = handle.read(length)
                if len(body) < length:
                    raise EOFError(f"the file ends inside a record ({len(body)} of {length} bytes)")
                yield op, body
            else:
                if self.offset + 9 + length > self.size:
                    raise EOFError("the file ends inside a record")
                handle.seek(length, 1)
            self.offset += 9 + length


def _chunk_data(body: bytes) -> bytes:
    """The records of a chunk record's body, decompressed and checked against its CRC."""
    _, _, size, crc, name_length = _CHUNK.unpack_from(body)
    if size > MAX_CHUNK_BYTES:
        raise ValueError(
            f"a chunk of {size} bytes decompressed, more than any log's ({MAX_CHUNK_BYTES} at most)"
        )
    compression = body[_CHUNK.size : _CHUNK.size + name_length].decode()
    at = _CHUNK.size + name_length
    (data_length,) = struct.unpack_from("<Q", body, at)
    packed = body[at + 8 : at + 8 + data_length]
    if len(packed) != data_length:
        raise EOFError("a chunk cut short")
    if compression == "zstd":
        if zstandard is None:  # pragma: no cover
            raise ValueError("zstd chunks need the zstandard package")
        framed = zstandard.frame_content_size(packed)
        if framed not in (-1, size):
            # max_output_size holds only a frame that does not say its size: one that says
            # it is taken at its word, and 8 KB declaring 256 MiB allocated 256 MiB
            raise ValueError(
                f"a zstd chunk whose frame declares {framed} bytes, and the chunk {size}"
            )
        data: bytes = zstandard.ZstdDecompressor().decompress(packed, max_output_size=size)
    elif compression == "lz4":
        data = _lz4(packed, size)
    elif compression == "":
        data = packed
    else:
        raise ValueError(f"unknown chunk compression {compression!r}")
    if len(data) != size:
        raise ValueError(f"chunk holds {len(data)} bytes, expected {size}")
    if crc and zlib.crc32(data) != crc:
        raise ValueError("chunk CRC mismatch")
    return data


def _lz4(packed: bytes, size: int) -> bytes:
    """An lz4 chunk's records, ``size`` bytes as the chunk declares, decompressed no further
    than one byte past that: ``lz4.frame.decompress`` has no bound, and 6.7 MB of lz4 that
    declared 1000 bytes inflated to 1.5 GiB, 3.2 GB of memory, before its length was
    compared (an outside audit). handctl writes zstd; lz4 is what ``mcap`` (the CLI and the
    libraries) can also write, so it is read, bounded as zstd is."""
    import lz4.frame  # type: ignore[import-not-found, import-untyped, unused-ignore]

    decompressor = lz4.frame.LZ4FrameDecompressor()
    data: bytes = decompressor.decompress(packed, max_length=size + 1)
    if len(data) > size:
        raise ValueError(
            f"an lz4 chunk that decompresses to more than the {size} bytes it declares "
            "(decompression stopped there)"
        )
    if not decompressor.eof:
        raise EOFError("an lz4 chunk whose frame is cut short")
    return data


def _records(data: bytes) -> Iterator[tuple[int, bytes]]:
    offset, end = 0, len(data)
    while offset + 9 <= end:
        op, length = _RECORD.unpack_from(data, offset)
        start = offset + 9
        yield op, data[start : start + length]
        offset = start + length


def iter_messages(
    recording: Recording, topics: Iterable[str] | None = None
) -> Iterator[tuple[str, int, bytes]]:
    """``(topic, log_time_ns, json_bytes)`` in file order: every chunk that reads (up to where
    a truncated file stops).

    File order is the writer's order, which is what a replay wants: a tick's frames and events
    come before the tick's own row (see ``writer.Encoder.drain``).
    """
    wanted = None if topics is None else set(topics)
    names: dict[int, str] = dict(recording.topics)
    keep = {cid for cid, topic in names.items() if wanted is None or topic in wanted}
    unpack_record = _RECORD.unpack_from
    unpack_message = _MESSAGE.unpack_from
    message_op, channel_op = int(Opcode.MESSAGE), int(Opcode.CHANNEL)
    with (recording.read_from or recording.path).open("rb") as handle:
        try:
            for body in _chunk_bodies(handle, recording):
                data = _chunk_data(body)
                offset, end = 0, len(data)
                while offset + 9 <= end:
                    op, length = unpack_record(data, offset)
                    start = offset + 9
                    offset = start + length
                    if op == message_op:
                        cid, _, log_time, _ = unpack_message(data, start)
                        if cid in keep:
                            yield names[cid], log_time, data[start + _MESSAGE_HEADER : offset]
                    elif op == channel_op:
                        channel = Channel.read(_stream(data[start:offset]))
                        if channel.id not in names:
                            names[channel.id] = channel.topic
                            if wanted is None or channel.topic in wanted:
                                keep.add(channel.id)
        except _CUT_SHORT:
            return  # open_recording has said where and why


def iter_chunks(
    recording: Recording, topics: Iterable[str], check: MessageCheck | None = None
) -> Iterator[tuple[list[str], list[Any]]]:
    """The topics and decoded messages of the wanted channels in file order, in batches of
    a few thousand, each batch decoded by one ``orjson.loads`` of a JSON array made of its
    messages: a re-run reads a dozen small messages per tick, and a call per message costs
    more than the parsing itself. Every message is checked (``MessageCheck``): one that is
    not what its channel says is a ConfigError naming it."""
    check = check or MessageCheck(str(recording.path))
    topics_: list[str] = []
    times: list[int] = []
    raw: list[bytes] = []
    for topic, log_time, data in iter_messages(recording, topics):
        topics_.append(topic)
        times.append(log_time)
        raw.append(data)
        if len(raw) >= 4096:
            yield topics_, _checked_batch(check, topics_, times, raw)
            topics_, times, raw = [], [], []
    if raw:
        yield topics_, _checked_batch(check, topics_, times, raw)


def _checked_batch(
    check: MessageCheck, topics: list[str], times: list[int], raw: list[bytes]
) -> list[Any]:
    try:
        messages = orjson.loads(b"[" + b",".join(raw) + b"]")
    except orjson.JSONDecodeError:
        messages = None
    if not isinstance(messages, list) or len(messages) != len(raw):
        # a message that is not one JSON value (the batch does not parse, or one message
        # is two): decoded one by one, so that the first bad one is named
        messages = [check.loads(t, lt, r) for t, lt, r in zip(topics, times, raw, strict=True)]
    test = check.check
    for topic, log_time, msg in zip(topics, times, messages, strict=True):
        test(topic, log_time, msg)
    return messages


def iter_decoded(
    recording: Recording, topics: Iterable[str] | None = None, check: MessageCheck | None = None
) -> Iterator[tuple[str, int, dict[str, Any]]]:
    """``(topic, log_time_ns, message)`` in file order, each message checked
    (``MessageCheck``)."""
    loads = (check or MessageCheck(str(recording.path))).loads
    for topic, log_time, data in iter_messages(recording, topics):
        yield topic, log_time, loads(topic, log_time, data)


def require_topics(recording: Recording, topics: Iterable[str], what: str) -> None:
    """A ConfigError naming the file when channels ``what`` needs are not in it."""
    have = set(recording.topics.values())
    missing = [t for t in topics if t not in have]
    if missing:
        raise ConfigError(
            str(recording.path),
            "channels",
            f"the channels {', '.join(missing)} for {what} (a recording made by "
            "'handctl run recipe --log')",
            Description(", ".join(sorted(have)) or "no channels"),
        )


def require_content(recording: Recording) -> None:
    """Refuse a file in which nothing reads: no metadata, no channel, no chunk. It begins as
    an MCAP file does and is otherwise random or cut within its first record, and its summary
    was all zeros and question marks, exit 0, as if it were the log of a run that did
    nothing."""
    if recording.metadata or recording.channels or recording.chunks:
        handctl_topics = {c.topic for c in ch.CHANNELS}
        if not any(name.startswith("handctl.") for name in recording.metadata) and not any(
            topic in handctl_topics for topic in recording.topics.values()
        ):
            # an MCAP file of another tool was summarised as a run of '? on ?', exit 0
            topics = sorted(recording.topics.values())
            listed = ", ".join(topics[:8]) + (", ..." if len(topics) > 8 else "")
            raise ConfigError(
                str(recording.path),
                "",
                "a handctl recording (from 'handctl run recipe --log RUN.mcap')",
                Description(
                    "an MCAP file of another tool: no handctl metadata and no handctl channel"
                    + (f" (its channels: {listed})" if topics else "")
                ),
            )
        if recording.bad_chunks and not recording.chunks:
            # every chunk damaged: its summary was "0 ticks", a run that did nothing, exit 0
            raise ConfigError(
                str(recording.path),
                "",
                "a recording with at least one chunk of messages that reads",
                Description(
                    f"none: every one of its {len(recording.bad_chunks)} chunk(s) of "
                    f"messages is damaged ({recording.problem})"
                ),
            )
        counted = sum(recording.message_counts.values()) if recording.message_counts else 0
        if counted and not recording.chunks:
            # handctl writes its messages in chunks and reads them there: a log rewritten
            # without chunks (by another tool) read as empty, "0 ticks, complete", exit 0
            raise ConfigError(
                str(recording.path),
                "",
                "a recording with its messages in chunks, as handctl writes it",
                Description(
                    f"{counted} messages outside any chunk (a file rewritten by another tool "
                    "without chunks)"
                ),
            )
        return
    raise ConfigError(
        str(recording.path),
        "",
        "a recording with something in it to read (metadata, a channel or a chunk)",
        # told, not read: whole (cut to 80 characters, the part that said why went)
        Description(f"none: {recording.problem or 'nothing after the magic bytes'}"),
    )


def check_format(recording: Recording) -> None:
    """Refuse a handctl recording of another format version (a foreign MCAP passes: it has no
    version, and the channel checks say what it lacks), and a channel of a handctl topic
    whose messages are not what handctl writes there: JSON, of the topic's JSON Schema.
    Why the second: every reader decodes a handctl topic as that JSON, so a file whose
    channel says protobuf or CBOR was read as if it were handctl's, and a re-run of it
    claimed bit-exact."""
    version = recording.meta("handctl.command", "format_version")
    if version and version != str(ch.FORMAT_VERSION):
        raise ConfigError(
            str(recording.path),
            "metadata handctl.command.format_version",
            f"format version {ch.FORMAT_VERSION}",
            version,
        )
    _check_tick_count(recording)
    wanted = {c.topic: c.schema_name for c in ch.CHANNELS}
    for channel in recording.channels.values():
        name = wanted.get(channel.topic)
        if name is None:
            continue
        schema = recording.schemas.get(channel.schema_id)
        found = (
            channel.message_encoding,
            schema.encoding if schema is not None else "no schema",
            schema.name if schema is not None else "",
        )
        if found != (ch.MESSAGE_ENCODING, ch.SCHEMA_ENCODING, name):
            raise ConfigError(
                str(recording.path),
                f"channel {channel.topic}",
                f"{ch.MESSAGE_ENCODING} messages of the {ch.SCHEMA_ENCODING} schema {name}",
                f"{found[0]} messages of the {found[1]} schema {found[2] or '(none)'}",
            )
