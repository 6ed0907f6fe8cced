"""What the recording reader makes of a file it cannot read."""

from __future__ import annotations

import os
import struct
import tracemalloc
from pathlib import Path

import pytest
from mcap.opcode import Opcode
from mcap.writer import CompressionType, Writer

from handctl.errors import ConfigError
from handctl.recording.reader import MAGIC, iter_messages, open_recording


@pytest.mark.parametrize(
    ("path", "found"),
    [("/proc/self/mem", "Input/output error"), ("/proc/self/clear_refs", "Invalid argument")],
)
def test_a_regular_file_that_cannot_be_read_is_bad_input_named(path: str, found: str) -> None:
    """A file that says it is a regular one and fails its read (a disk's or a network file
    system's read error; these two do it on any Linux) is refused by name, as the YAML
    loaders refuse one, where ``handctl replay`` printed a traceback and exited 1."""
    if not Path(path).is_file():
        pytest.skip(f"{path}: not on this system")
    with pytest.raises(ConfigError) as info:
        open_recording(path)
    assert info.value.file == path
    assert "a readable file" in info.value.expected
    assert found in str(info.value)


def _one_chunk_file(path: Path, compression: str, packed: bytes, declared: int) -> None:
    """An MCAP file of a header and one chunk record of ``compression`` that declares
    ``declared`` bytes decompressed and holds ``packed`` (no CRC, no summary)."""
    name = compression.encode()
    body = struct.pack("<QQQII", 0, 0, declared, 0, len(name)) + name
    body += struct.pack("<Q", len(packed)) + packed
    header = struct.pack("<I", 0) + struct.pack("<I", 4) + b"test"
    path.write_bytes(
        MAGIC
        + struct.pack("<BQ", Opcode.HEADER, len(header))
        + header
        + struct.pack("<BQ", Opcode.CHUNK, len(body))
        + body
    )


def test_an_lz4_chunk_is_decompressed_no_further_than_it_declares(tmp_path: Path) -> None:
    """6.7 MB of lz4 declaring 1000 bytes inflated to 1.5 GiB (3.2 GB of memory) before its
    length was compared: the bound on a chunk's declared size held for zstd alone. Here
    32 MiB of zeros declare 1000 bytes; the reading stops past the 1000th byte, so what it
    allocates stays far below the 32 MiB it would have inflated (tracemalloc counts every
    allocation, lz4's buffers among them)."""
    import lz4.frame  # type: ignore[import-not-found, import-untyped, unused-ignore]

    bomb = tmp_path / "bomb.mcap"
    _one_chunk_file(bomb, "lz4", lz4.frame.compress(bytes(32 << 20), store_size=False), 1000)
    tracemalloc.start()
    try:
        recording = open_recording(bomb)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert recording.bad_chunks and recording.chunks == 0
    assert "decompresses to more than the 1000 bytes it declares" in (
        recording.bad_chunks[0].reason
    )
    assert peak < 8 << 20, f"{peak} bytes allocated reading it"


def test_an_lz4_log_another_mcap_writer_made_reads(tmp_path: Path) -> None:
    """handctl writes zstd, the mcap CLI and libraries can write lz4: such a log still reads,
    its chunks' declared sizes exact."""
    path = tmp_path / "lz4.mcap"
    with path.open("wb") as handle:
        writer = Writer(handle, compression=CompressionType.LZ4)
        writer.start()
        schema = writer.register_schema("s", "jsonschema", b"{}")
        channel = writer.register_channel("/x", "json", schema)
        for i in range(3):
            writer.add_message(channel, i, b'{"i": %d}' % i, i)
        writer.finish()  # type: ignore[no-untyped-call]  # mcap's Writer is untyped
    recording = open_recording(path)
    assert recording.complete and recording.chunks == 1
    assert [data for _, _, data in iter_messages(recording)] == [b'{"i": %d}' % i for i in range(3)]


def test_a_zstd_chunk_whose_frame_says_more_than_the_chunk_is_not_decompressed(
    tmp_path: Path,
) -> None:
    """zstandard's ``max_output_size`` bounds only a frame that does not say its size: one
    that does is taken at its word, and a chunk declaring 1000 bytes whose frame said 32 MiB
    allocated 32 MiB before its length was compared."""
    import zstandard

    bomb = tmp_path / "bomb.mcap"
    _one_chunk_file(bomb, "zstd", zstandard.ZstdCompressor().compress(bytes(32 << 20)), 1000)
    tracemalloc.start()
    try:
        recording = open_recording(bomb)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert recording.bad_chunks and recording.chunks == 0
    assert f"frame declares {32 << 20} bytes, and the chunk 1000" in recording.bad_chunks[0].reason
    assert peak < 8 << 20, f"{peak} bytes allocated reading it"


def test_an_empty_log_beside_several_killed_runs_names_the_newest(tmp_path: Path) -> None:
    """Two runs killed in their start-up, PIDs 999 and then 10000: the last by name (PIDs
    sorted as text) named 999's, the older."""
    log = tmp_path / "x.mcap"
    log.touch()
    older = tmp_path / ".x.mcap.999.handctl-partial"
    newer = tmp_path / ".x.mcap.10000.handctl-partial"
    for at, partial in enumerate((older, newer)):
        partial.write_bytes(MAGIC)
        os.utime(partial, ns=(10**18 + at * 10**9, 10**18 + at * 10**9))
    with pytest.raises(ConfigError) as info:
        open_recording(log)
    assert f"a run killed before it began: {newer} (the newest of 2: replay that one)" in str(
        info.value
    )
