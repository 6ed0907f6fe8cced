"""The account of a run made after its hand has stopped, kept whole when a part of it fails.

Every part of a run's summary (the simulated hand's account, the host's timing, the
experiment's merit, the plot) is made once the hand is stopped, and can fail only by a bug of
handctl's. Raised, such a bug took the whole account with it: a traceback and exit 1, no
summary file, and a log finished without its summary, though the run had gone as it went.
Here each part is made on its own; a part that fails is said (``summary_errors``: the part,
its exception and its traceback; a warning; exit 1 unless the run's own code says more), and
the rest is made as usual. If the summary itself cannot be made, ``least_summary`` stands in
for it with what the run result holds plainly.
"""

from __future__ import annotations

import traceback
from collections.abc import Callable
from typing import Any, TypeVar

from handctl.config import HandConfig
from handctl.online.loop import Outcome, RunResult
from handctl.online.recipes.schema import Recipe
from handctl.online.safety.faults import FAULTS

T = TypeVar("T")

#: how many frames of a failed part's traceback the summary keeps (the innermost)
TRACEBACK_FRAMES = 12


class SummaryParts:
    """Makes the parts of a run's account one by one; what failed is kept in ``errors``."""

    def __init__(self) -> None:
        self.errors: list[dict[str, str]] = []
        self._said = 0

    def make(self, part: str, make: Callable[[], T], instead: T) -> T:
        """``make()``, or ``instead`` if it raised an ``Exception`` (an interrupt goes on:
        the run's interrupt path says it)."""
        try:
            return make()
        except Exception as exc:
            self.errors.append(
                {
                    "part": part,
                    "error": f"{type(exc).__name__}: {exc}"[:400],
                    "traceback": "".join(
                        traceback.format_exception(exc, limit=-TRACEBACK_FRAMES)
                    ).rstrip(),
                }
            )
            return instead

    def said_in(self, summary: dict[str, Any], warnings: list[str]) -> None:
        """The failures so far into ``summary`` and, each once, into ``warnings``."""
        if not self.errors:
            return
        summary["summary_errors"] = list(self.errors)
        for error in self.errors[self._said :]:
            warnings.append(
                f"the run's {error['part']} could not be made: {error['error']} (a bug in "
                "handctl, not in the input; the hand had stopped; please report it with "
                "this traceback)\n" + error["traceback"]
            )
        self._said = len(self.errors)


def least_summary(
    result: RunResult,
    hand: HandConfig,
    recipe: Recipe,
    lockstep: bool,
    sim: dict[str, Any] | None,
) -> dict[str, Any]:
    """The summary's keys from what the run result holds as plain values, for a summary that
    could not be made: how the run ended, why, its faults and its ticks."""
    return {
        "completed": result.outcome is Outcome.COMPLETED,
        "outcome": result.outcome.value,
        "message": result.message,
        "recipe": recipe.name,
        "hand": hand.name,
        "hand_config_hash": hand.config_hash,
        "mode": "lockstep" if lockstep else "realtime",
        "phases": [],
        "timed_out_phases": [],
        "faults": [
            {
                "code": f.code.name,
                "category": FAULTS[f.code].category.name.lower(),
                "tick": f.tick,
                "detail": f.detail,
            }
            for f in result.faults
        ],
        "ticks": result.ticks,
        "missed_ticks": result.missed_ticks,
        "lateness_us": {"p50": None, "p99": None, "max": None},
        "stage_cpu_us_p99": {},
        "max_abs_tau_nm": {},
        "rejected_frames": dict(result.node_rejects),
        "bus_events": result.bus_events,
        **({"sim": sim} if sim is not None else {}),
    }
