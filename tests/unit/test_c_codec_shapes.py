"""The C codec and the golden vectors of other hands: generated from the same hand config,
compiled as strictly as the default hand's, and agreeing with each other and with Python.

The default hand's committed files are checked in ``test_c_codec.py``; here every shape is
generated afresh (``tools/gen_c_codec.py --hand``, ``tools/gen_vectors.py --hand``), as a
firmware author of that hand would.
"""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

from handctl.config import load_hand
from handctl.hand_protocol import protocol_for

from ..shapes import shaped_hand
from .test_c_codec import (
    C_DIR,
    CFLAGS,
    ERROR_NAMES,
    ROOT,
    TOOLS,
    encode_line,
    ordered,
    parse_decoded,
    run_harness,
    same,
)

SHAPES = {"3x3": [3, 3, 3], "2x2": [2, 2], "4x4": [4, 4, 4, 4], "1x6": [6], "mixed": [1, 5, 2]}


def generate(tool: str, hand: Path, out: Path) -> None:
    done = subprocess.run(
        [sys.executable, str(TOOLS / tool), "--hand", str(hand), "--out", str(out)],
        capture_output=True,
        text=True,
        cwd=ROOT,
        timeout=120,
        check=False,
    )
    assert done.returncode == 0, done.stderr


@pytest.mark.parametrize("shape", list(SHAPES))
def test_the_c_codec_of_a_hand_matches_its_vectors(shape: str, tmp_path: Path) -> None:
    compiler = shutil.which("gcc") or shutil.which("cc")
    if compiler is None:
        pytest.skip("no C compiler: neither gcc nor cc is on PATH")
    hand_path = shaped_hand(tmp_path, SHAPES[shape])
    protocol = protocol_for(load_hand(hand_path))
    c_dir = tmp_path / "c"
    vectors = tmp_path / "vectors.json"
    generate("gen_c_codec.py", hand_path, c_dir)
    generate("gen_vectors.py", hand_path, vectors)
    # Beside the generated header: a quoted #include looks in the includer's folder first,
    # which for the packaged harness is the default hand's header.
    shutil.copy(C_DIR / "vector_harness.c", c_dir)
    exe = tmp_path / "vector_harness"
    command = [
        compiler,
        *CFLAGS,
        f"-I{c_dir}",
        str(c_dir / "handctl_protocol.c"),
        str(c_dir / "vector_harness.c"),
        "-o",
        str(exe),
        "-lm",
    ]
    built = subprocess.run(command, capture_output=True, text=True, timeout=120, check=False)
    assert built.returncode == 0, f"{' '.join(command)}\n{built.stdout}{built.stderr}"

    document: dict[str, Any] = json.loads(vectors.read_text(encoding="utf-8"))
    names = {v["message"] for v in document["vectors"]}
    assert names == {layout.name for layout in protocol.layouts}
    good = document["vectors"]
    encoded = run_harness(
        exe,
        [
            encode_line(
                protocol.by_name[v["message"]],
                v["counter"],
                ordered(protocol.by_name[v["message"]], v["signals"]),
            )
            for v in good
        ],
    )
    for vector, answer in zip(good, encoded, strict=True):
        assert answer == f"OK {vector['bytes']}", (vector["message"], vector["case"])
    decoded = run_harness(exe, [f"D {v['frame_id']} {v['bytes']}" for v in good])
    for vector, answer in zip(good, decoded, strict=True):
        layout = protocol.by_name[vector["message"]]
        counter, values = layout.decode(bytes.fromhex(vector["bytes"]))
        c_counter, c_values = parse_decoded(answer, values)
        assert c_counter == counter == vector["counter"]
        assert all(same(c, p) for c, p in zip(c_values, values, strict=True)), answer

    lines, expected = [], []
    for reject in document["encode_rejects"]:
        layout = protocol.by_name[reject["message"]]
        lines.append(encode_line(layout, reject["counter"], ordered(layout, reject["signals"])))
        expected.append(f"ERR {ERROR_NAMES[reject['error']]}")
    for reject in document["decode_rejects"]:
        lines.append(f"D {reject['frame_id']} {reject['bytes']}")
        expected.append(f"ERR {ERROR_NAMES[reject['error']]}")
    assert run_harness(exe, lines) == expected
