"""``tools/bench.py``: a benchmark whose figures say what failed exits 1, saying it on
stderr, rather than 0 with the error inside the JSON."""

from __future__ import annotations

import json
import sys
import types

import pytest

from ..conftest import load_tool


def _fake(figures: dict[str, object]) -> types.ModuleType:
    module = types.ModuleType("bench_fake", "A benchmark of the test's.")
    module.add_arguments = lambda parser: None  # type: ignore[attr-defined]
    module.run = lambda args: figures  # type: ignore[attr-defined]
    return module


@pytest.mark.parametrize(
    ("figures", "code"),
    [({"x": 1}, 0), ({"x": 1, "failed": ["tick_cost.unix: exit 1"]}, 1)],
)
def test_figures_that_hold_failures_exit_1_and_say_each(
    figures: dict[str, object],
    code: int,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    bench = load_tool("bench")
    monkeypatch.setattr(sys, "path", list(sys.path))  # main puts the tools on it
    monkeypatch.setattr(bench, "available", lambda: ["fake"])
    monkeypatch.setitem(sys.modules, "bench_fake", _fake(figures))
    assert bench.main(["fake", "--json"]) == code
    out, err = capsys.readouterr()
    assert json.loads(out) == figures
    assert err == ("bench.py fake: failed: tick_cost.unix: exit 1\n" if code else "")
