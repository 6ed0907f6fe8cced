"""The experiment bench's measure of the paper's controlled turn: every manipulation phase
its step (45 deg within 10 by default), and no tumble besides."""

from __future__ import annotations

from types import ModuleType
from typing import Any

import pytest

from ..conftest import load_tool


def _bench() -> ModuleType:
    return load_tool("bench_experiment")


def _run(angles: list[float] | None, peak: float = 100.0) -> dict[str, Any]:
    return {
        "phase_angles_deg": angles,
        "peak_turn_rate_deg_s": peak,
        "success": True,
        "swap": True,
        "dropped": False,
        "outcome": "completed",
        "lifted": True,
        "total_rotation_deg": sum(abs(a) for a in angles or []),
    }


@pytest.mark.parametrize(
    ("angles", "expected"),
    [
        ([-38.6, -39.7, -51.5, -50.2], True),
        ([38.6, 39.7, 51.5, 50.2], True),  # a turn the other way round
        ([-35.0, -55.0, -45.0, -45.0], True),  # the band's edges count
        ([-43.1, -34.9, -51.0, -51.0], False),
        ([-43.1, -35.3, -44.0, -57.6], False),
        ([-40.0, -40.0], True),  # a recipe of two manipulation phases
        ([], False),  # stopped before the manipulation
        (None, False),
    ],
)
def test_a_run_is_in_band_only_with_every_phase_within_the_tolerance(
    angles: list[float] | None, expected: bool
) -> None:
    assert _bench().in_band(_run(angles), 45.0, 10.0) is expected


def test_the_rates_count_the_band_and_the_band_with_no_tumble() -> None:
    runs = [
        _run([-45.0] * 4),
        _run([-45.0] * 4, peak=250.0),  # in band, but tumbled
        _run([-30.0, -60.0, -45.0, -45.0]),
        _run([-45.0] * 4, peak=180.0),  # the quasi-static limit itself counts
    ]
    figures = _bench()._figures(runs, 45.0, 10.0)
    assert figures["phase_band_rate"] == 0.75
    assert figures["controlled_turn_rate"] == 0.5
    assert _bench()._figures(runs, 45.0, 20.0)["phase_band_rate"] == 1.0
