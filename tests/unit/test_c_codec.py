"""The firmware's C codec, the host's Python codec and the golden vectors must agree to the bit.

Host and finger controllers only interoperate if both sides pack, round and CRC every frame
identically, and the C side is generated code that nobody reads day to day: so the generated
files must be what the DBC yields today, the golden bytes must be what the host encodes, and the
compiled C must reproduce both, including the rounding ties and the frames it must refuse.
"""

from __future__ import annotations

import json
import math
import os
import random
import shutil
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

from handctl.errors import ProtocolError
from handctl.protocol import Layout, Protocol, crc8, load_protocol

ROOT = Path(__file__).resolve().parents[2]
TOOLS = ROOT / "tools"
DBC = ROOT / "firmware_protocol" / "handctl.dbc"
C_DIR = ROOT / "firmware_protocol" / "c"
VECTORS = ROOT / "firmware_protocol" / "vectors.json"
CFLAGS = ("-std=c99", "-Wall", "-Wextra", "-Werror", "-O2")
ERROR_NAMES = {"range": "RANGE", "crc": "CRC", "length": "LENGTH"}

Value = int | float


@pytest.fixture(scope="module")
def document() -> dict[str, Any]:
    loaded: dict[str, Any] = json.loads(VECTORS.read_text(encoding="utf-8"))
    return loaded


@pytest.fixture(scope="module")
def protocol() -> Protocol:
    return load_protocol(DBC)


@pytest.fixture(scope="module")
def harness(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The generated codec and the hand-written harness, compiled as strictly as the brief asks."""
    compiler = shutil.which("gcc") or shutil.which("cc")
    if compiler is None:
        pytest.skip(
            "no C compiler: neither gcc nor cc is on PATH, so the generated C codec "
            "cannot be compiled and compared with the Python codec here"
        )
    exe = tmp_path_factory.mktemp("c_codec") / (
        "vector_harness.exe" if os.name == "nt" else "vector_harness"
    )
    command = [
        compiler,
        *CFLAGS,
        f"-I{C_DIR}",
        str(C_DIR / "handctl_protocol.c"),
        str(C_DIR / "vector_harness.c"),
        "-o",
        str(exe),
        "-lm",
    ]
    built = subprocess.run(command, capture_output=True, text=True, timeout=120, check=False)
    assert built.returncode == 0, f"{' '.join(command)}\n{built.stdout}{built.stderr}"
    return exe


def run_harness(exe: Path, lines: list[str]) -> list[str]:
    """One harness process for a whole batch: answers come back in order, one per line."""
    result = subprocess.run(
        [str(exe)],
        input="\n".join(lines) + "\n",
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )
    answers = result.stdout.splitlines()
    assert result.returncode == 0, "\n".join(a for a in answers if a.startswith("BAD"))
    assert len(answers) == len(lines)
    return answers


def text(value: Value) -> str:
    """repr() is the shortest text that strtod reads back as the same double."""
    return repr(float(value)) if isinstance(value, float) else str(value)


def encode_line(layout: Layout, counter: int, values: list[Value]) -> str:
    return f"E {layout.frame_id} {counter} {' '.join(text(v) for v in values)}"


def ordered(layout: Layout, signals: dict[str, Value]) -> list[Value]:
    assert list(signals) == list(layout.signal_names)
    return [signals[name] for name in layout.signal_names]


def same(a: Value, b: Value) -> bool:
    """Exact equality that also tells 0.0 from -0.0 and 1 from 1.0."""
    if isinstance(a, float) or isinstance(b, float):
        return isinstance(a, float) and isinstance(b, float) and a.hex() == b.hex()
    return type(a) is type(b) and a == b


def parse_decoded(answer: str, python_values: tuple[Value, ...]) -> tuple[int, list[Value]]:
    """C prints every value with %.17g; read each back as the kind Python gives for it."""
    status, counter, *tokens = answer.split()
    assert status == "OK", answer
    assert len(tokens) == len(python_values), answer
    values: list[Value] = [
        int(t) if isinstance(p, int) else float(t)
        for t, p in zip(tokens, python_values, strict=True)
    ]
    return int(counter), values


# --- the generated files are what the DBC yields -------------------------------------------------


@pytest.mark.parametrize("tool", ["gen_c_codec.py", "gen_vectors.py", "gen_dbc.py"])
def test_generated_files_are_up_to_date(tool: str) -> None:
    result = subprocess.run(
        [sys.executable, str(TOOLS / tool), "--check"],
        capture_output=True,
        text=True,
        cwd=ROOT,
        timeout=120,
        check=False,
    )
    assert result.returncode == 0, result.stderr


@pytest.mark.parametrize(
    ("tool", "target"), [("gen_c_codec.py", "c"), ("gen_vectors.py", "vectors.json")]
)
def test_check_mode_notices_stale_files(tool: str, target: str, tmp_path: Path) -> None:
    """The up-to-date test is only worth something if --check can fail."""
    out = tmp_path / target
    if target == "c":
        out.mkdir()
        for name in ("handctl_protocol.h", "handctl_protocol.c"):
            (out / name).write_text(
                (C_DIR / name).read_text(encoding="utf-8").replace("nearbyint(", "round("),
                encoding="utf-8",
            )
    else:
        out.write_text(
            VECTORS.read_text(encoding="utf-8").replace('"counter": 255', '"counter": 0'),
            encoding="utf-8",
        )
    result = subprocess.run(
        [sys.executable, str(TOOLS / tool), "--check", "--out", str(out)],
        capture_output=True,
        text=True,
        cwd=ROOT,
        timeout=120,
        check=False,
    )
    assert result.returncode == 1, result.stderr
    assert "run: python tools/" in result.stderr


# --- golden bytes against the Python codec -------------------------------------------------------


def test_every_dbc_message_has_golden_vectors(document: dict[str, Any], protocol: Protocol) -> None:
    cases: dict[str, set[str]] = {layout.name: set() for layout in protocol.layouts}
    for vector in document["vectors"]:
        layout = protocol.by_name[vector["message"]]
        assert vector["frame_id"] == layout.frame_id
        cases[layout.name].add(vector["case"])
    for layout in protocol.layouts:
        wanted = {"zero", "minimum", "maximum", "counter_wrap", "random_0"}
        if any(not s.is_integer for s in layout.signals):
            wanted |= {"tie_even", "tie_odd", "tie_negative_even", "tie_negative_odd"}
        assert wanted <= cases[layout.name], f"{layout.name}: missing {wanted - cases[layout.name]}"
    assert any(v["counter"] == 255 for v in document["vectors"])


def test_golden_bytes_are_what_python_encodes(document: dict[str, Any], protocol: Protocol) -> None:
    for vector in document["vectors"]:
        layout = protocol.by_name[vector["message"]]
        where = f"{layout.name}/{vector['case']}"
        golden = bytes.fromhex(vector["bytes"])
        assert layout.encode(vector["counter"], ordered(layout, vector["signals"])) == golden, where
        assert layout.crc_ok(golden), where
        counter, values = layout.decode(golden)
        assert counter == vector["counter"], where
        expected = ordered(layout, vector["decoded"])
        assert all(same(a, b) for a, b in zip(values, expected, strict=True)), where


def test_tie_vectors_sit_exactly_on_ties(document: dict[str, Any], protocol: Protocol) -> None:
    """Without exact ties, half-even and half-away codecs would pass the vectors alike."""
    even_ties = 0
    for vector in document["vectors"]:
        if not vector["case"].startswith("tie"):
            continue
        layout = protocol.by_name[vector["message"]]
        for spec in layout.signals:
            if spec.is_integer:
                continue
            q = (vector["signals"][spec.name] - spec.offset) / spec.scale
            if q - math.floor(q) == 0.5 and math.floor(q) % 2 == 0 and q > 0:
                even_ties += 1
    assert even_ties >= len(
        [lay for lay in protocol.layouts if any(not s.is_integer for s in lay.signals)]
    )


def test_python_refuses_the_rejects(document: dict[str, Any], protocol: Protocol) -> None:
    for reject in document["encode_rejects"]:
        layout = protocol.by_name[reject["message"]]
        with pytest.raises(ProtocolError):
            layout.encode(reject["counter"], ordered(layout, reject["signals"]))
    for reject in document["decode_rejects"]:
        layout = protocol.by_name[reject["message"]]
        assert not layout.crc_ok(bytes.fromhex(reject["bytes"])), reject["case"]


def test_python_crc_is_crc8_autosar(document: dict[str, Any]) -> None:
    check = document["crc_check"]
    assert crc8(bytes.fromhex(check["bytes"])) == check["crc8"] == 0xDF


# --- the compiled C codec against vectors and Python ---------------------------------------------


def test_c_encodes_every_vector_like_python(
    harness: Path, document: dict[str, Any], protocol: Protocol
) -> None:
    vectors = document["vectors"]
    lines = [
        encode_line(
            protocol.by_name[v["message"]],
            v["counter"],
            ordered(protocol.by_name[v["message"]], v["signals"]),
        )
        for v in vectors
    ]
    for vector, answer in zip(vectors, run_harness(harness, lines), strict=True):
        layout = protocol.by_name[vector["message"]]
        python = layout.encode(vector["counter"], ordered(layout, vector["signals"])).hex()
        assert answer == f"OK {vector['bytes']}" == f"OK {python}", (
            f"{layout.name}/{vector['case']}: C {answer}, vector {vector['bytes']}, Python {python}"
        )


def test_c_decodes_every_vector_like_python(
    harness: Path, document: dict[str, Any], protocol: Protocol
) -> None:
    vectors = document["vectors"]
    lines = [f"D {v['frame_id']} {v['bytes']}" for v in vectors]
    for vector, answer in zip(vectors, run_harness(harness, lines), strict=True):
        layout = protocol.by_name[vector["message"]]
        py_counter, py_values = layout.decode(bytes.fromhex(vector["bytes"]))
        c_counter, c_values = parse_decoded(answer, py_values)
        where = f"{layout.name}/{vector['case']}: C {answer}, Python {py_values}"
        assert c_counter == py_counter == vector["counter"], where
        assert all(same(c, p) for c, p in zip(c_values, py_values, strict=True)), where


def test_c_refuses_what_python_refuses(
    harness: Path, document: dict[str, Any], protocol: Protocol
) -> None:
    lines, expected = [], []
    for reject in document["encode_rejects"]:
        layout = protocol.by_name[reject["message"]]
        lines.append(encode_line(layout, reject["counter"], ordered(layout, reject["signals"])))
        expected.append(f"ERR {ERROR_NAMES[reject['error']]}")
    for reject in document["decode_rejects"]:
        lines.append(f"D {reject['frame_id']} {reject['bytes']}")
        expected.append(f"ERR {ERROR_NAMES[reject['error']]}")
    assert {r["error"] for r in document["decode_rejects"]} == {"crc", "length"}
    answers = run_harness(harness, lines)
    mismatches = [
        (line, want, got)
        for line, want, got in zip(lines, expected, answers, strict=True)
        if want != got
    ]
    assert not mismatches, mismatches[:5]


def test_c_refuses_non_finite_values(harness: Path, protocol: Protocol) -> None:
    """NaN compares false with everything: a careless range check would let it through."""
    lines = []
    for layout in protocol.layouts:  # every signal, scaled or integer, must refuse them
        for i in range(len(layout.signals)):
            for bad in ("nan", "inf", "-inf"):
                values = ["0"] * len(layout.signals)
                values[i] = bad
                lines.append(f"E {layout.frame_id} 0 {' '.join(values)}")
    assert set(run_harness(harness, lines)) == {"ERR RANGE"}


def test_c_by_id_api_refuses_unknown_ids_and_wrong_counts(
    harness: Path, protocol: Protocol
) -> None:
    unknown = max(layout.frame_id for layout in protocol.layouts) + 1
    torque = protocol.by_name["TorqueCommand_1"]
    answers = run_harness(
        harness,
        [
            f"D {unknown} 000000",
            f"E {unknown} 0 0",
            f"E {torque.frame_id} 0 0 0",
            f"E {torque.frame_id} 0 0 0 0 0",
        ],
    )
    assert answers == ["ERR ID", "ERR ID", "ERR ARG", "ERR ARG"]


def test_c_crc8_matches_python(harness: Path, document: dict[str, Any]) -> None:
    rng = random.Random(8)
    blobs = [bytes.fromhex(document["crc_check"]["bytes"]), b""]
    blobs += [rng.randbytes(rng.randrange(1, 40)) for _ in range(50)]
    answers = run_harness(harness, [f"C {blob.hex()}" for blob in blobs])
    assert answers[0] == "OK 223"
    assert answers == [f"OK {crc8(blob)}" for blob in blobs]


def test_c_matches_python_off_the_vectors(harness: Path, protocol: Protocol) -> None:
    """Seeded values around ties and range ends, beyond the committed vectors."""
    rng = random.Random(20)
    cases: list[tuple[Layout, int, list[Value]]] = []
    for layout in protocol.layouts:
        for _ in range(60):
            values: list[Value] = []
            for spec in layout.signals:
                if spec.is_integer:
                    values.append(rng.randint(-2, (1 << spec.size_bits) + 1))
                    continue
                span = (1 << (spec.size_bits - 1 if spec.signed else spec.size_bits)) + 2
                k = rng.randint(-span, span) if spec.signed else rng.randint(-2, span)
                step = rng.choice((0.5, 0.0, 0.25, rng.random()))
                values.append((k + step) * spec.scale + spec.offset)
            cases.append((layout, rng.randrange(256), values))
    answers = run_harness(harness, [encode_line(lay, c, v) for lay, c, v in cases])
    decode_lines: list[str] = []
    decode_of: list[tuple[int, tuple[Value, ...]]] = []
    for (layout, counter, values), answer in zip(cases, answers, strict=True):
        try:
            python = f"OK {layout.encode(counter, values).hex()}"
        except ProtocolError:
            python = "ERR RANGE"
        assert answer == python, f"{layout.name} counter {counter} values {values!r}"
        if python.startswith("OK"):
            decode_lines.append(f"D {layout.frame_id} {python[3:]}")
            decode_of.append(layout.decode(bytes.fromhex(python[3:])))
    assert len(decode_lines) > len(cases) // 4
    for answer, (counter, decoded) in zip(
        run_harness(harness, decode_lines), decode_of, strict=True
    ):
        c_counter, c_values = parse_decoded(answer, decoded)
        assert c_counter == counter
        assert all(same(c, p) for c, p in zip(c_values, decoded, strict=True)), answer


@pytest.mark.parametrize("tool", ["gen_c_codec.py", "gen_vectors.py", "gen_dbc.py"])
def test_an_out_that_cannot_be_written_is_said_with_exit_2(tool: str, tmp_path: Path) -> None:
    """A directory given as a file's --out (or a file as the C codec's directory) was an
    IsADirectoryError or FileExistsError traceback, exit 1."""
    out = tmp_path / "taken"
    if tool == "gen_c_codec.py":
        out.write_text("a file where the codec's directory goes")
    else:
        out.mkdir()
    result = subprocess.run(
        [sys.executable, str(TOOLS / tool), "--out", str(out)],
        capture_output=True,
        text=True,
        cwd=ROOT,
        timeout=120,
        check=False,
    )
    assert result.returncode == 2, result.stderr
    assert "Traceback" not in result.stderr and f"{tool}: --out" in result.stderr
