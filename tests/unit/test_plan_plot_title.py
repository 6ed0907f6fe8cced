"""The title of a plan's region plot: what planned the phase, said as this plan's or as the
base recipe's."""

from __future__ import annotations

import math
from types import SimpleNamespace
from typing import Any

from handctl.experiment.plot import plan_plot_title


def _plan(kind: str, provenance: dict[str, Any]) -> SimpleNamespace:
    return SimpleNamespace(
        phase=SimpleNamespace(name="lift"),
        spec=SimpleNamespace(kind=kind, turn=math.radians(-45)),
        provenance=provenance,
    )


def test_a_searched_phase_s_title_is_its_own_plan_s() -> None:
    title, why = plan_plot_title(
        _plan("turn", {"analysis": {"margin_N": 1.35}, "search": {"score": 0.9}})
    )
    assert title == "lift (turn), analysis margin 1.35 N, search score 0.9, wanted turn -45 deg"
    assert why.startswith("no analysis for this phase")


def test_a_kept_phase_s_title_says_its_margin_is_the_base_s() -> None:
    """``plan --keep-torques --plot``: the lift's plot said "analysis margin 1.3462 N" over
    "no analysis for this phase (no wanted motion or no contact)", the region not drawn (an
    outside probe); its margin was the base's, and nothing was analysed in this plan."""
    kept = {"analysis": {"margin_N": 1.3462}, "kept_from": "base.yaml"}
    title, why = plan_plot_title(_plan("lift", kept))
    assert title == "lift (lift), kept from base.yaml, analysis margin 1.3462 N there"
    assert why == "torques kept from base.yaml: no analysis ran in this plan, no region drawn"
