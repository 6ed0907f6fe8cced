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
from contextlib import suppress
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
                f"{_part_name(error['part'])} could not be made: {error['error']} (a bug in "
                "handctl, not in the input; the hand had stopped; please report it with "
                "this traceback)\n" + error["traceback"]
            )
        self._said = len(self.errors)


#: What the parts of a run's account are called where their failure is said.
PART_NAMES = {
    "warnings": "the run's warnings",
    "sim": "the simulated hand's account",
    "summary": "the summary itself",
    "frames_lost": "the frames the host lost",
    "loop_work": "the loop's own timing",
    "host": "the host's timing",
    "experiment": "the experiment's figures",
    "plot": "the plot",
}


def _part_name(part: str) -> str:
    return PART_NAMES.get(part, f"the run's {part}")


def failed_parts(summary: dict[str, Any]) -> str:
    """The parts of ``summary`` that could not be made, in words ("" if none)."""
    return "; ".join(_part_name(str(e.get("part"))) for e in summary.get("summary_errors", []))


def require_whole(summary: dict[str, Any], what: str) -> None:
    """For a tool that reads a run's summary as its result (the experiment bench, the soak
    and loop benchmarks): a summary short of a part is a bug of handctl's, raised with its
    tracebacks, never read as the run's result (a failed experiment, a missing figure)."""
    errors = summary.get("summary_errors")
    if errors:
        raise RuntimeError(
            f"{what}: the run's summary lacks {failed_parts(summary)}, by a bug of "
            "handctl's:\n" + "\n".join(e["traceback"] for e in errors)
        )


def summary_head(
    result: RunResult, hand: HandConfig, recipe: Recipe, lockstep: bool
) -> dict[str, Any]:
    """The keys every run summary begins with: how the run ended, what ran, and where."""
    return {
        "completed": result.outcome is Outcome.COMPLETED,
        "outcome": result.outcome.value,
        "message": result.message,
        "recipe": recipe.name,
        "hand": hand.name,
        "hand_config_hash": hand.config_hash,
        "mode": "lockstep" if lockstep else "realtime",
    }


def least_summary(
    result: RunResult,
    hand: HandConfig,
    recipe: Recipe,
    lockstep: bool,
    sim: dict[str, Any] | None,
) -> dict[str, Any]:
    """The summary's keys from what the run result holds as plain values, for a summary that
    could not be made: how the run ended, why, its phases, its faults, its ticks, its
    largest torques, and every note a script reads to know whether the hand may still be
    enabled or faulted. Each is taken on its own: one that fails is left out."""
    summary: dict[str, Any] = {
        **summary_head(result, hand, recipe, lockstep),
        "phases": [],
        "timed_out_phases": [],
        "faults": [],
        "ticks": result.ticks,
        "missed_ticks": result.missed_ticks,
        "lateness_us": {"p50": None, "p99": None, "max": None},
        "stage_cpu_us_p99": {},
        "max_abs_tau_nm": {},
        "rejected_frames": {},
        "bus_events": result.bus_events,
    }
    plain: dict[str, Callable[[], Any]] = {
        "phases": lambda: [
            {**p, "timed_out": str(p["exit"]).startswith("timeout")} for p in result.phases
        ],
        "timed_out_phases": lambda: [
            p["name"] for p in result.phases if str(p["exit"]).startswith("timeout")
        ],
        "faults": lambda: [
            {
                "code": f.code.name,
                "category": FAULTS[f.code].category.name.lower(),
                "tick": f.tick,
                "detail": f.detail,
            }
            for f in result.faults
        ],
        "max_abs_tau_nm": lambda: {
            name: round(float(v), 5)
            for name, v in zip(hand.joint_names, result.max_abs_tau, strict=True)
        },
        "rejected_frames": lambda: dict(result.node_rejects),
    }
    for key, make in plain.items():
        with suppress(Exception):  # left as it stands above: this is the summary of a failure
            summary[key] = make()
    notes = {
        "left_limits_in_stop": result.stop_notes,
        "nodes_reset": result.nodes_reset,
        "disable_unconfirmed": result.disable_unconfirmed,
        "ended_in_fault": result.ended_in_fault,
        "estop_heard": result.estop_heard,
        "rebooted": result.rebooted,
    }
    summary.update({key: note for key, note in notes.items() if note})
    if sim is not None:
        summary["sim"] = sim
    return summary
