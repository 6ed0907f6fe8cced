"""``torque_set_report``: the files the CLI writes and the summary it prints."""

from __future__ import annotations

import argparse
import errno
import json
import os
import resource
from pathlib import Path

import numpy as np
import pytest
import yaml

from handctl import cli
from handctl.analysis.commands import torque_set_report
from handctl.analysis.polygons import area
from handctl.errors import ConfigError

from ..conftest import handctl

ROOT = Path(__file__).resolve().parents[2]
FIG3 = ROOT / "config" / "analysis" / "paper_fig3.yaml"


@pytest.mark.parametrize("k", [(0.9, 0.1), (1.2, 0.5)])
def test_json_and_png(tmp_path: Path, k: tuple[float, float]) -> None:
    out_json, out_png = tmp_path / "a.json", tmp_path / "a.png"
    messages: list[str] = []
    text = torque_set_report(FIG3, k, out_json, out_png, messages.append)
    assert messages and "area" in text and str(out_png) in text
    assert out_png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    doc = json.loads(out_json.read_text(encoding="utf-8"))
    region = doc["region"]
    polys = [np.array(p) for p in region["polygons"]]
    assert polys and region["area"] == pytest.approx(sum(area(p) for p in polys), rel=1e-9)
    assert 0.0 < region["area"] < doc["realisable_area"]
    grid = doc["grid"]
    assert len(grid["tau11"]) == len(grid["tau21"]) == 121
    inside = grid["inside"]
    assert len(inside) == 121 and all(len(row) == 121 for row in inside)
    flat = [v for row in inside for v in row]
    assert {type(v) for v in flat} <= {bool, type(None)}
    assert any(v is True for v in flat) and any(v is None for v in flat)
    # the box is the torque limit of eq. 25: |k_i τ_i1| ≤ 3 N·m as well
    assert grid["tau11"][-1] == pytest.approx(3.0 / max(1.0, k[0]))
    # grid cells marked inside lie in the polygons; cells well outside them are not inside
    xs, ys = np.array(grid["tau11"]), np.array(grid["tau21"])
    for i in range(0, 121, 7):
        for j in range(0, 121, 7):
            point = np.array([xs[j], ys[i]])
            in_poly = any(_contains(p, point) for p in polys)
            if inside[i][j]:
                assert in_poly
    best = doc["best"]
    assert best is not None and any(
        _contains(p, np.array([best["tau11"], best["tau21"]])) for p in polys
    )


def _contains(poly: np.ndarray, point: np.ndarray) -> bool:
    step = np.roll(poly, -1, axis=0) - poly
    rel = point - poly
    return bool(np.all(step[:, 0] * rel[:, 1] - step[:, 1] * rel[:, 0] >= -1e-9))


def test_no_files_asked(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(tmp_path)
    text = torque_set_report(FIG3, (0.9, 0.1), None, None)
    assert "wrote" not in text and not list(tmp_path.iterdir())


def test_bad_scenario_and_unfit_grasp(tmp_path: Path) -> None:
    with pytest.raises(ConfigError):
        torque_set_report(tmp_path / "missing.yaml", (0.9, 0.1), None, None)
    data = yaml.safe_load(FIG3.read_text(encoding="utf-8"))
    data["fingers"][1]["links"] = [1.0, 1.0, 0.2]
    data["fingers"][1]["joints"] = data["fingers"][1]["joints"] + [0.0]
    path = tmp_path / "three.yaml"
    path.write_text(yaml.safe_dump(data), encoding="utf-8")
    # bad input (exit 2), naming the file and the key, not a failed analysis
    with pytest.raises(ConfigError, match="two fingers of two joints") as info:
        torque_set_report(path, (0.9, 0.1), None, None)
    assert info.value.file == str(path) and info.value.key == "fingers"
    assert "joint(s)" in str(info.value)


def test_a_json_the_disk_cannot_take_leaves_the_earlier_one_as_it_was(tmp_path: Path) -> None:
    """A full disk under ``--json`` (here a file size limit, ``ulimit -f``, which fails the
    write the same way): the JSON was written in place, so a cut-off file stood where the
    earlier one was, and the command ended in a bare traceback. Now one line, exit 1, the
    earlier file as it was and nothing left beside it."""
    out = tmp_path / "set.json"
    earlier = b'{"earlier": "region"}\n'
    out.write_bytes(earlier)
    limit = 16_000  # bytes: the document's grid alone is ten times this

    def small_files() -> None:
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))

    command = ["analyze", "torque-set", str(FIG3), "--k", "0.9", "0.1", "--json", str(out)]
    done = handctl(*command, timeout=300, preexec_fn=small_files)
    assert done.returncode == 1, done.stdout + done.stderr
    assert "Traceback" not in done.stderr
    assert done.stderr.strip().splitlines()[-1] == (
        f"handctl: error: --json: {out} could not be written (File too large); it is unchanged"
    )
    assert out.read_bytes() == earlier
    assert [p.name for p in tmp_path.iterdir()] == [out.name]


def test_a_json_the_disk_cannot_take_where_none_was_says_none_was_made(tmp_path: Path) -> None:
    """The same failure onto a path with no file: "it is unchanged" was said of a file that
    had never been there (found by an outside audit)."""
    out = tmp_path / "new.json"
    limit = 16_000

    def small_files() -> None:
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))

    command = ["analyze", "torque-set", str(FIG3), "--k", "0.9", "0.1", "--json", str(out)]
    done = handctl(*command, timeout=300, preexec_fn=small_files)
    assert done.returncode == 1, done.stdout + done.stderr
    assert done.stderr.strip().splitlines()[-1] == (
        f"handctl: error: --json: {out} could not be written (File too large); "
        "no file was made there"
    )
    assert list(tmp_path.iterdir()) == []


def test_a_system_refusal_without_a_file_name_is_said_not_raised(
    capsys: pytest.CaptureFixture[str],
) -> None:
    """An ``OSError`` the system raised with no file's name (a write to a file already open
    on a full disk) came out of the command line as a bare traceback. Now its reason and its
    errno's name, exit 1; an ``OSError`` no system call raised stays a bug, said as one."""

    def full(_args: argparse.Namespace) -> int:
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    def bug(_args: argparse.Namespace) -> int:
        raise OSError("no errno: raised by handctl's own code")

    assert cli._run(full, argparse.Namespace()) == cli.EXIT_FAILED
    err = capsys.readouterr().err
    assert err == (
        "handctl: error: the system refused a read or a write (No space left on device, ENOSPC)\n"
    )
    assert cli._run(bug, argparse.Namespace()) == cli.EXIT_FAILED
    err = capsys.readouterr().err
    assert err.startswith("handctl: internal error: OSError: no errno") and "Traceback" in err
