"""What the runner asks of the analysis at a measured configuration, and what it gets back.

A phase with ``reanalyse`` (``schema.Reanalyse``) asks, on its first tick with a valid
estimate of the pair, for the torque the analysis finds for the configuration the hand
measures then, and applies the answer ``delay_s`` later. The analysis takes tens of ms
(docs/experiment.md, *A torque for the configuration the pair is in*), far more than a tick,
and it belongs to the offline plane, which the online plane never imports: so the runner sees
only this interface, and the command that builds the run gives it an implementation
(``handctl.planning.reanalysis``) that computes off the tick in real time and at once in
lockstep. Either way the answer is taken on the same tick, ``delay_s`` after the request, so
a run, its lockstep twin and its re-run apply it at the same moment.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Protocol


@dataclass(frozen=True)
class ReanalysisResult:
    """The analysis' answer: ``torques`` (N·m, the hand's joint order) to apply, or None to
    keep the planned ones; ``note`` says which and why (the phase's record keeps it)."""

    torques: tuple[float, ...] | None
    note: str


class Reanalyser(Protocol):
    def submit(self, phase: int, angles: Sequence[float], estimates: Sequence[float]) -> None:
        """Start the analysis of phase ``phase`` (the recipe's index) at the measured joint
        angles (rad) and the estimator's outputs of the same tick. Must return within a
        tick: the work is done elsewhere, or (lockstep) when it is collected."""
        ...

    def collect(self, phase: int) -> ReanalysisResult | None:
        """The answer to phase ``phase``'s request, or None if it is not there yet."""
        ...
