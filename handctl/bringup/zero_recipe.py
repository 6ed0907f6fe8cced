"""Recipes the bring-up commands build in memory and run with the normal Runtime.

They are checked against the hand like any recipe read from a file (``check_against_hand``):
a torque over ``tau_max`` or a ramp faster than the rate limit is refused before a frame is
sent.
"""

from __future__ import annotations

from collections.abc import Sequence

from handctl.config import HandConfig
from handctl.online.recipes.guard import LimitGuard
from handctl.online.recipes.loader import check_against_hand
from handctl.online.recipes.schema import Phase, Recipe, TimeoutAction


def phase(name: str, torques: Sequence[float], ramp_s: float, max_s: float) -> Phase:
    """A phase that holds ``torques`` (N·m) for ``max_s`` and then hands over to the next."""
    return Phase(name, tuple(float(t) for t in torques), ramp_s, max_s, TimeoutAction.NEXT, (), ())


def in_memory_recipe(
    name: str,
    description: str,
    hand: HandConfig,
    phases: Sequence[Phase],
    end_ramp_s: float,
    guard: LimitGuard | None = None,
) -> Recipe:
    """A recipe for ``hand``, refused (``ConfigError``) where a file's would be."""
    recipe = Recipe(
        name, f"<{name}>", description, tuple(phases), end_ramp_s, None, False, (), guard
    )
    check_against_hand(recipe, hand)
    return recipe
