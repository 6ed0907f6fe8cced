"""The experiment bench's measure of the paper's controlled turn: every manipulation phase
its step (45 deg within 10 by default), and no tumble besides."""

from __future__ import annotations

from pathlib import Path
from types import ModuleType
from typing import Any

import pytest
import yaml

from handctl.config import HandConfig
from handctl.errors import ConfigError
from handctl.online.recipes.loader import load_recipe

from ..conftest import ROOT, load_tool

RECIPE = ROOT / "config" / "recipes" / "swap_two_cylinders.yaml"


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
        ([38.6, 39.7, 51.5, 50.2], False),  # turned back, each phase
        ([-40.97, -37.35, 0.0, 78.35], False),  # a phase that did nothing, one turned back
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
    assert _bench().in_band(_run(angles), -45.0, 10.0) is expected


def test_the_step_is_signed_as_the_recipe_turns(tmp_path: Path, hand: HandConfig) -> None:
    """The shipped swap turns clockwise (its exits wait for the turn to fall below them); a
    recipe whose manipulation exits wait for it to rise turns counter-clockwise."""
    recipe = load_recipe(RECIPE, hand)
    assert _bench().turn_sense(recipe) == -1.0
    data = yaml.safe_load(RECIPE.read_text())
    for phase in data["phases"]:
        phase["exit"] = [e.replace(" < -", " > ") for e in phase.get("exit", [])] or None
        if phase["exit"] is None:
            del phase["exit"]
        for key in ("turn_rate", "paced_ramp"):  # their rates signed as the turn wanted
            if key in phase:
                phase[key]["rate_deg_s"] *= -1
    path = tmp_path / "recipe.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    assert _bench().turn_sense(load_recipe(path, hand)) == 1.0


@pytest.mark.parametrize(("phase_deg", "tolerance_deg"), [(45.0, 45.0), (1e-300, 1e300)])
def test_a_band_that_reaches_zero_is_refused(phase_deg: float, tolerance_deg: float) -> None:
    with pytest.raises(ConfigError) as info:
        _bench()._check_band(phase_deg, tolerance_deg)
    assert info.value.file == "--phase-tolerance-deg"


def test_the_rates_count_the_band_and_the_band_with_no_tumble() -> None:
    runs = [
        _run([-45.0] * 4),
        _run([-45.0] * 4, peak=250.0),  # in band, but tumbled
        _run([-30.0, -60.0, -45.0, -45.0]),
        _run([-45.0] * 4, peak=180.0),  # the quasi-static limit itself counts
    ]
    figures = _bench()._figures(runs, -45.0, 10.0)
    assert figures["phase_band_rate"] == 0.75
    assert figures["controlled_turn_rate"] == 0.5
    assert _bench()._figures(runs, -45.0, 20.0)["phase_band_rate"] == 1.0


def test_the_ringing_rate_counts_the_runs_with_a_joint_that_rang() -> None:
    runs = [_run([-45.0] * 4) for _ in range(4)]
    runs[1]["ringing_joints"] = ["f1_j3", "f2_j3"]
    runs[2]["ringing_joints"] = []
    assert _bench()._figures(runs, -45.0, 10.0)["ringing_rate"] == 0.25
