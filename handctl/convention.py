"""One convention for what the run summary, the replay summary and both plots show, so that
the same run reads the same everywhere.

- **Time**: seconds since tick 0's scheduled time, the recipe runner's own clock (its phase
  times and timeouts read it). A phase starts at the scheduled time of the first tick that
  ran it. Start-up ticks before tick 0 do not exist; nothing is measured from a log's first
  message.
- **Heights**: of an object's centre above where it rested at the start (the simulated scene's
  initial pose), in mm on the axes: 0 on the table, positive up.
- **Turn**: the change of the centre line's angle (from the first object's centre to the
  second's) since the start, unwrapped, in degrees, counter-clockwise positive about +z (the
  hand config's sign of angles and torques: x to the right, y up). A pair turned half a turn
  clockwise reads -180, never +180 or a wrapped +3.14 rad. A phase's turn is measured on the
  poses of every ``POSE_EVERY_TICKS``-th tick, the ones a log carries, taken at the start of
  the tick (before it runs): the run's summary and its log's measure the same samples. Such a
  sample belongs to the phase the previous tick ran.
"""

from __future__ import annotations

import math
import re
from collections.abc import Container, Sequence

import numpy as np
import numpy.typing as npt

#: The simulated objects' poses are logged (and a turn measured) every this many ticks.
POSE_EVERY_TICKS = 10
#: An object's name, in a hand config's scene and in a recipe alike: the prefix of its
#: estimates in conditions (``estimate.<name>_x``, a pair's ``<a>_<b>_line_turn``), so no
#: underscore
OBJECT_NAME = re.compile(r"^[A-Za-z][A-Za-z0-9]{0,31}\Z")  # \Z: "$" lets a trailing newline by
#: A finger's or a joint's name in a hand config: what a recipe condition names a joint by
#: (``angle.NAME``, ``tdt.NAME``: ``[A-Za-z0-9_]+``), and what check, nodes and a run's
#: summary print as it is (a name with a space or an accent passed check and no condition
#: could name it; one with an escape sequence or a newline was written to the terminal raw)
#: At most ``NAME_CHARS`` characters, objects' too: a name heads a table's column, a plot's
#: legend and a Foxglove panel, and a 300-character one (check took it) ran off the plot's
#: top and broke every table's columns.
PART_NAME = re.compile(r"^[A-Za-z][A-Za-z0-9_]{0,31}\Z")  # \Z: "$" lets a trailing newline by
NAME_CHARS = 32
#: m, the largest object's radius, in a hand config's scene and in a recipe alike: the scene
#: took 1 m and a recipe 0.2, so an object a hand config held could not be named by a recipe
#: (no estimator, no experiment)
MAX_OBJECT_RADIUS = 1.0
PART_NAME_RULE = (
    f"a name of letters, digits and underscores, starting with a letter, at most {NAME_CHARS} "
    "characters"
)
TIME_LABEL = "time since tick 0 [s]"
HEIGHT_LABEL = "height above rest [mm]"
#: m, an object's centre this far above rest is lifted: the experiment's judgement and the
#: line the plots draw are one number
LIFT_HEIGHT = 0.010
#: s, lifted and held: every object ``LIFT_HEIGHT`` up this long without a break before the
#: first manipulation phase. The experiment's judgement and the planner's job of the hold
#: before the turns are one number: a plan whose hold ended sooner passed, and its recipe
#: then failed every run's experiment
HOLD_S = 2.0
#: s, a centre-line rate is taken over this window, so that one contact impact of a
#: millisecond is not a peak: the summary's, the bench's and the planner's peak rate alike
RATE_WINDOW_S = 0.010
TURN_LABEL = "turn of the centre line [deg, ccw +]"


def run_time_s(scheduled_ns: int, tick0_scheduled_ns: int) -> float:
    return (scheduled_ns - tick0_scheduled_ns) * 1e-9


def heights_above_rest(y: npt.ArrayLike, rest_y: Sequence[float]) -> npt.NDArray[np.float64]:
    """Rows of centre heights (m) minus each object's resting height (m)."""
    out: npt.NDArray[np.float64] = np.asarray(y, dtype=float) - np.asarray(rest_y, dtype=float)
    return out


def turn_rad(line_angle: npt.ArrayLike) -> npt.NDArray[np.float64]:
    """The turn since the first finite sample of a wrapped centre-line angle series (rad);
    NaN where the angle is unknown."""
    a = np.asarray(line_angle, dtype=float)
    out = np.full(a.shape, math.nan)
    ok = np.isfinite(a)
    if ok.any():
        unwrapped = np.unwrap(a[ok])
        out[ok] = unwrapped - unwrapped[0]
    return out


def turn_deg(line_angle: npt.ArrayLike) -> npt.NDArray[np.float64]:
    return np.degrees(turn_rad(line_angle))


#: The names of the paper's experiment's turn phases (``manipulate_1`` .. ``_4``) begin so: a
#: phase so named is a manipulation phase (``Phase.manipulates``) whatever its exits.
MANIPULATE_PREFIX = "manipulate"


def is_manipulation(phase: str, counted: Container[str] | None = None) -> bool:
    """Whether ``phase`` is one of the manipulation phases ``counted`` names (a recipe's
    ``manipulation_phases``), or without them, one named ``manipulate...``."""
    return phase in counted if counted is not None else phase.startswith(MANIPULATE_PREFIX)


def phase_turns_deg(
    t: npt.ArrayLike,
    line_angle: npt.ArrayLike,
    phases: Sequence[tuple[str, float, float]],
    counted: Container[str] | None = None,
) -> list[float]:
    """The turn (deg, ccw +) in each manipulation phase, those ``counted`` names (the
    recipe's ``manipulation_phases``; without it, the phases named ``manipulate...``): the
    unwrapped centre-line angle at the first sample at or after the phase's end (the last
    sample if the run ends first) minus at the first sample at or after its start.
    Consecutive phases' turns add up to the turn over all of them, whatever the sampling."""
    times = np.asarray(t, dtype=float)
    turn = turn_deg(line_angle)
    finite = np.isfinite(turn)
    times, turn = times[finite], turn[finite]
    out = []
    for name, start, end in phases:
        if not is_manipulation(name, counted):
            continue
        first = int(np.searchsorted(times, start - 1e-9))
        last = min(int(np.searchsorted(times, end - 1e-9)), len(times) - 1)
        out.append(round(float(turn[last] - turn[first]), 2) if first < last else 0.0)
    return out
