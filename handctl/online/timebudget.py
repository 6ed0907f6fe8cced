"""A run's time budget (``--max-seconds``): the controlled stop when it is spent, and the
outcome of a run that ended so, ``TIME_BUDGET`` rather than an interrupt.

The stop goes through ``Runtime.request_stop`` with a reason of its own, which the recording
keeps with the stop; a re-run that repeats the stop (``handctl replay --rerun``) recognises the
same reason and reaches the same outcome.
"""

from __future__ import annotations

import dataclasses

from handctl.errors import ConfigError
from handctl.online.clock import Tick
from handctl.online.loop import Outcome, RunResult, Runtime

#: s, the longest budget: about 115 days, far beyond any run, and few enough ticks to count
#: (1e308 s overflowed the count of ticks)
MAX_BUDGET_S = 1e7
#: The start of the stop's reason; what follows is the budget.
REASON_PREFIX = "time budget of "


def check(max_seconds: float | None) -> None:
    """None is no limit; anything else must be a number of seconds > 0, at most
    ``MAX_BUDGET_S``."""
    if max_seconds is not None and not 0 < max_seconds <= MAX_BUDGET_S:
        raise ConfigError(
            "max_seconds",
            "",
            f"a time budget in seconds > 0 and <= {MAX_BUDGET_S:g} (None: no limit)",
            max_seconds,
        )


def install(runtime: Runtime, max_seconds: float) -> None:
    """Stop ``runtime`` (the controlled stop) once ``max_seconds`` of ticks have gone by,
    start-up included."""
    check(max_seconds)
    ticks = max(1, round(max_seconds / runtime.hand.bus.period_s))
    reason = f"{REASON_PREFIX}{max_seconds:g} s reached"

    def spent(tk: Tick) -> None:
        if tk.tick >= ticks:
            runtime.request_stop(reason)

    runtime.tick_hooks.append(spent)


def outcome(result: RunResult, stop_reason: str) -> RunResult:
    """``result`` as ``TIME_BUDGET`` if the stop that ended it was the budget's."""
    if result.outcome is Outcome.INTERRUPTED and stop_reason.startswith(REASON_PREFIX):
        return dataclasses.replace(result, outcome=Outcome.TIME_BUDGET)
    return result
