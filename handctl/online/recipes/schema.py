"""What a recipe is: phases of joint torques with ramps, exits, aborts and a time limit.

Conditions are short strings, ``SIGNAL OP NUMBER [for SECONDS]``, because that is what an
engineer writes on a whiteboard and reads back in a log; they are parsed once at load time
into predicates over a fixed set of signals:

- ``time``: seconds since the phase began;
- ``angle.JOINT`` (rad), ``tdt.JOINT`` (N·m): the joint state from the nodes;
- ``estimate.NAME``: the object estimator's outputs, named by the recipe's own objects
  (``estimate_names``), which a recipe may use only if it declares its ``objects`` (the
  estimator needs their radii);
- ``for S`` makes the condition hold continuously for S seconds before it counts, so one noisy
  sample cannot end a phase.
"""

from __future__ import annotations

import enum
import math
import operator
import re
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Protocol

from handctl.convention import is_manipulation
from handctl.online.recipes.guard import LimitGuard

#: The most objects a recipe may grasp and the estimator tracks (the simulated hand's most).
MAX_OBJECTS = 4
#: What the estimator gives per object, as ``<object>_<suffix>``: its centre (m).
OBJECT_ESTIMATES = ("x", "y")
#: What it gives per pair of objects, as ``<a>_<b>_<suffix>``: ``line_angle`` is the direction
#: of the line from a's centre to b's, in (-π, π]; ``line_turn`` is how far that line has
#: turned since the phase began (counter-clockwise positive, unwrapped, so a phase can ask for
#: more than half a turn).
PAIR_ESTIMATES = ("line_angle", "line_turn")
#: The pair suffix a condition reads relative to its value when the phase began. The estimator
#: gives the turn as a running (unwrapped) value; only the runner knows where a phase starts.
PHASE_RELATIVE_SUFFIX = "_line_turn"
#: The index of the first pair's ``line_turn`` among the estimates (pairs come first): the
#: turn the turn-rate loop holds at its rate.
FIRST_PAIR_TURN = 1
#: The names estimates had when the estimator knew exactly two objects and no names. Recipes
#: written then (and the logs that carry them, which replay re-runs) say these; they read as
#: the first pair's and the first two objects' estimates.
LEGACY_ESTIMATES = {
    "centre_line_angle": 0,
    "centre_line_turn": 1,
    "object1_x": 2,
    "object1_y": 3,
    "object2_x": 4,
    "object2_y": 5,
}

OPERATORS: dict[str, Callable[[float, float], bool]] = {
    "<": operator.lt,
    "<=": operator.le,
    ">": operator.gt,
    ">=": operator.ge,
}

#: s, the longest a phase may last (its ``max_s``); a condition cannot hold for longer
MAX_PHASE_S = 3600.0

#: ASCII digits and spaces only, the whole text (``fullmatch``): ``\d`` took any script's
#: digits (an Arabic-Indic "٠.٤" was read as 0.4), and ``\s`` and ``$`` let a line break, a
#: form feed or a Unicode space through, which the summary then printed as they were
_CONDITION = re.compile(
    r" *(?P<signal>time|(?:angle|tdt|estimate)\.[A-Za-z0-9_]+) *(?P<op><=|>=|<|>) *"
    r"(?P<value>[-+]?(?:[0-9]+\.?[0-9]*|\.[0-9]+)(?:[eE][-+]?[0-9]+)?)"
    # a hold is written as a threshold is (exponent notation too), without a sign
    r"(?: +for +(?P<hold>(?:[0-9]+\.?[0-9]*|\.[0-9]+)(?:[eE][-+]?[0-9]+)?))? *"
)


class SignalKind(enum.Enum):
    TIME = "time"
    ANGLE = "angle"
    TDT = "tdt"
    ESTIMATE = "estimate"


@dataclass(frozen=True)
class Condition:
    text: str
    kind: SignalKind
    index: int  # joint index for ANGLE/TDT; index into the recipe's estimates for ESTIMATE
    op: str
    value: float
    hold_s: float
    relative: bool = False  # an estimate read relative to its value when the phase began

    def holds(self, value: float, threshold: float | None = None) -> bool:
        """Whether ``value`` meets the condition: against its own value, or against
        ``threshold`` in its place (a shared exit's, ``Phase.exit_share``; never NaN's)."""
        return OPERATORS[self.op](value, self.value if threshold is None else threshold)


class TimeoutAction(enum.Enum):
    NEXT = "next"
    ABORT = "abort"


@dataclass(frozen=True)
class TurnRate:
    """Feedback of a turn phase (``runner.py``): the phase's torque is scaled within
    ``[scale_min, scale_max]`` so that the estimated centre line turns at ``rate``.

    Why a scale: the analysis' torque set of a quasi-static motion is a cone (its conditions
    are homogeneous in the torques, gravity aside), so the ray through the planned torque stays
    inside it, and along it the speed of the motion against the hand's damping grows with the
    torque. A hand damped three times as much needs about three times the torque for the same
    rate; a lighter one, less."""

    rate: float  # rad/s, signed: the wanted direction of the turn
    scale_min: float
    scale_max: float
    gain: float  # scale per unit of relative rate error (proportional)
    integral: float  # scale per second per unit of relative rate error


@dataclass(frozen=True)
class TurnBrake:
    """Joint damping a phase injects when the pair tumbles (``runner.py``): none while the
    estimated centre line turns at ``rate`` or slower (either way), rising to ``damping`` at
    twice that rate.

    Why on the rate and not always: a hand damped more than the plan's lets the pair fall
    back where a phase turns it by rolling it over its balance, and a hand damped less lets
    it tumble past the exit; a damper that acts only on the tumble slows the second and
    leaves the first alone."""

    rate: float  # rad/s, > 0
    damping: float  # N·m·s/rad, at twice ``rate``
    #: rad/s: also while the fastest joint moves faster than this (full at twice it); 0:
    #: on the pair's rate alone
    joint_rate: float = 0.0
    #: rad/s: while the pair's estimate is invalid (its cage open), the fastest joint
    #: against this in place of the pair's last rate; 0: the last rate holds
    blind_joint_rate: float = 0.0


@dataclass(frozen=True)
class PacedRamp:
    """A turn phase's ramp paced by the pair (``runner.py``): the torque moves along the
    segment from the previous phase's torque to this one's, forward at the ramp's speed
    while the estimated centre line turns slower than ``rate`` the wanted way, back while it
    turns faster, and never past ``reach`` (1: this phase's torque; more: on along the
    segment, beyond it).

    Why along the segment: the previous phase's torque brought the pair to where this
    phase begins and this phase's turns it on, so between them lies a torque that turns
    it slowly. Gravity makes the set of torques that turn the pair no cone (a smaller torque
    along its ray lets the pair fall back), so a scale of one torque is the wrong
    direction to give way in; the segment's other end is a torque that brought it here."""

    rate: float  # rad/s, signed: the wanted direction of the turn
    reach: float  # the furthest fraction along the segment, >= 1
    back: float  # how many times the ramp's speed the torque may go back at
    #: rad/s, the fastest any joint may move before the torque goes back as well; 0: the
    #: pair's rate alone
    joint_rate: float = 0.0
    #: rad/s: while the pair's estimate is invalid (its cage open), the fastest joint
    #: against this sets the pace instead of the pair's last rate; 0: the last rate holds
    blind_joint_rate: float = 0.0
    #: a fraction of the soft-limit guard's band: a joint deeper into its band than this
    #: holds the pace, and deeper still sends it back, at ``back`` once the joint is at its
    #: limit: the phase's torque is pushing the hand into its limit instead of turning the
    #: pair; 0: off (needs the recipe's ``limit_guard_band``)
    limit_depth: float = 0.0
    #: rad: once the pair is this far behind the furthest it got the wanted way in this
    #: phase (turned back), the pace holds, and further behind goes back, at ``back`` at
    #: twice it: a pair the torque turns the wrong way is not a slow pair; 0: off
    turn_back: float = 0.0


@dataclass(frozen=True)
class TurnStall:
    """A turn phase that ends when the pair has stopped turning (``runner.py``): once the
    phase's torque is fully in (its ramp done, a paced ramp at its ``reach``), the first
    pair's estimated turn moving less than ``turn`` either way for ``window_s``.

    Why: a torque that has stopped turning the pair will not start again by being held
    (the pair rests against what resists it), so holding it to the phase's ``max_s`` only
    spends time; the next phase, whose exit reads the turn from an earlier phase
    (``Phase.turn_from``), takes up what this one left."""

    turn: float  # rad, > 0
    window_s: float  # s, > 0


#: what a ``Reanalyse`` may apply: the analysis' own torque, a blend of it and the plan's, or
#: the robust torque nearest the plan's
REANALYSIS_USES = ("analysis", "blend", "nearest")


@dataclass(frozen=True)
class Reanalyse:
    """A turn phase whose torque is computed again for the configuration the pair is in
    when the phase begins (``runner.py``, the paper's §4-5 torque sets at the measured
    relative position): the analysis runs off the tick on the measured joint angles, the
    estimated centres and the measured radii, and its torque replaces the planned one
    ``delay_s`` after the first valid estimate of the phase, in every mode (lockstep, real
    time, a re-run), so a run and its re-run apply it on the same tick.

    Why: the planned torque was computed for the pair where the nominal hand leaves it;
    on a hand whose pair is elsewhere (turned less, other radii) it can turn it back.
    Where the analysis finds no robust torque, the planned one is kept."""

    turn: float  # rad, signed: the sense of the turn the analysis is asked for
    delay_s: float  # s, from the request to the tick the result is applied
    #: "analysis": the analysis' torque of the largest margin; "blend": the point nearest the
    #: planned torque on the segment from it to the analysis' torque whose margin is at least
    #: ``min_margin``; "nearest": the torque nearest the planned one (the sum of the joints'
    #: differences) whose margin is at least ``min_margin``
    use: str
    min_margin: float  # N


@dataclass(frozen=True)
class GraspModel:
    """What the analysis of a measured grasp needs and the hand cannot measure: each
    object's mass (kg, the recipe's objects' order), the Coulomb coefficients of a finger
    on an object and of two objects, gravity (m/s², along -y of the hand's plane), and how
    much looser than an object's tightest wall another wall may be and still count as a
    contact (m: the estimator places an object equally far from every wall of its cage)."""

    masses: tuple[float, ...]
    finger_object_mu: float
    object_object_mu: float
    gravity: float
    contact_gap: float


#: A phase's value that may differ per joint (``torque_margin``, ``joint_damping``): one for
#: every joint, or one per joint in the config's order; either is used as it is (``numpy``
#: broadcasts the one).
PerJoint = float | tuple[float, ...]


@dataclass(frozen=True)
class PoseIntegral:
    """Integral action of a pose hold towards ``rest``, the pose the nominal hand settles in
    under the hold. Why: the spring alone leaves a finger where its torque, the spring and the
    friction the model does not know (the tendons', the tips' on the table) balance, so a hand
    with more friction than the nominal's stops short of the nominal's pose, and the lift
    begins from there. The integral grows only on a joint that has stopped (slower than
    ``still_rate``) once the phase's ramp is done, so a joint on its way is never wound up,
    only while no joint of its finger has gone past ``rest``, and it is bounded by ``max``.
    On the nominal hand it stays near zero: the hand rests where ``rest`` says."""

    rest: tuple[float, ...]  # rad, config joint order
    gain: float  # N·m/(rad·s)
    max: float  # N·m, per joint, either way
    still_rate: float  # rad/s
    #: each joint's finger (index in the hand config), config joint order: the finger's rule
    #: needs it and the runner has no hand config (``loader.joint_fingers``)
    finger_of: tuple[int, ...]


@dataclass(frozen=True)
class PoseHold:
    """Joint-space impedance of a phase: ``stiffness * (angle - q) - damping * velocity`` is
    added to the phase's torques, so the fingers end in a known pose whatever pose they began
    in and whatever their joints' friction (a start phase)."""

    angles: tuple[float, ...]  # rad, config joint order
    stiffness: float  # N·m/rad
    damping: float  # N·m·s/rad
    integral: PoseIntegral | None = None


@dataclass(frozen=True)
class RadiusRatio:
    """A range of one object's measured radius relative to the recipe's (measured / recipe),
    ``low <= ratio <= high``: what a scheduled torque of a phase is for."""

    object: int  # index into the recipe's ``objects``
    low: float
    high: float

    def holds(self, ratio: float) -> bool:
        return self.low <= ratio <= self.high


@dataclass(frozen=True)
class ScheduledTorques:
    """An alternative torque of a phase (``schedule``), for the grasp it meets when every
    range of ``when`` holds (``runner.py``, ``_schedule``).

    Why: the grasp's configuration, and so the torque that turns it, depends on the objects'
    size, which the estimator measures in the hold; one torque planned around the recipe's
    radii turns a much larger object the wrong way (docs/experiment.md)."""

    when: tuple[RadiusRatio, ...]
    torques: tuple[float, ...]  # N·m, config joint order


class MeasuredSizes(Protocol):
    """What the runner reads of the objects' sizes (the object estimator): an object's radius
    (m) once it is measured, else None."""

    def measured_radius(self, index: int) -> float | None: ...


@dataclass(frozen=True)
class Phase:
    name: str
    torques: tuple[float, ...]  # N·m, config joint order
    ramp_s: float
    max_s: float
    on_timeout: TimeoutAction
    exits: tuple[Condition, ...]
    aborts: tuple[Condition, ...]
    provenance: Mapping[str, Any] = field(default_factory=dict)
    turn_rate: TurnRate | None = None
    pose: PoseHold | None = None
    #: N·m·s/rad, joint-velocity damping the runner adds (runner.py; one for every joint, or
    #: one per joint): the hand's own damping is the least known of its dynamics, and an
    #: added term it cannot change makes the motion's pace less its own; 0: none
    joint_damping: PerJoint = 0.0
    brake: TurnBrake | None = None
    paced: PacedRamp | None = None
    #: the runner applies ``torques`` times this (>= 1; one factor, or one per joint in the
    #: config's order): headroom in the lift for objects heavier than the plan's models
    #: (docs/experiment.md); 1: the plan's own
    torque_margin: PerJoint = 1.0
    #: the name of this or an earlier phase: the phase's exits read a ``line_turn`` from
    #: where the pair was when that phase began, not this one (the paper's switching on the
    #: pair's measured position, whatever an earlier phase left undone); "": this phase
    turn_from: str = ""
    stall: TurnStall | None = None
    #: the analysis again at the measured configuration when the phase begins; None: the
    #: planned torque throughout
    reanalyse: Reanalyse | None = None
    #: alternative torques for ranges of the objects' measured sizes, the first that holds
    #: chosen once the sizes are measured; none holding: ``torques``
    schedule: tuple[ScheduledTorques, ...] = ()
    #: whether this phase's ``joint_damping`` fades out over the next phase's ramp (no step
    #: in torque) or ends with the phase, so that damping meant for this phase's grasp does
    #: not reach into the next phase's motion (the step is the damping times the joints'
    #: speed at the switch, which the supervisor's rate limit spreads out)
    joint_damping_fades: bool = True
    #: this phase and the ``exit_share - 1`` after it share what is left of the turn: when
    #: the phase first measures the pair, each exit on a turn (``Condition.relative``) moves
    #: from its written threshold to where the pair is plus ``1/exit_share`` of the way
    #: there (``runner.py``, ``_threshold``). Why: how far an earlier phase's grasp
    #: could turn the pair differs from hand to hand (its fingers reach their limits), and a
    #: fixed threshold left the whole difference to this phase and none to the next; 1: the
    #: written threshold
    exit_share: int = 1

    @property
    def manipulates(self) -> bool:
        """Whether this is one of the recipe's manipulation phases, whose turn of the pair
        the experiment measures (each one's turn, the peak rate over them, the hold before
        the first): named so (``manipulate...``, the paper's experiment's names), planned as
        a turn phase (``provenance.kind: turn``), or ending on a pair's turn (an exit on a
        ``line_turn``). By the name alone, a turn phase named for what it does ('turn',
        'swap') was one the summary said turned the pair nothing, without a word."""
        return (
            is_manipulation(self.name)
            or self.provenance.get("kind") == "turn"
            or self.turn_sense() is not None
        )

    def turn_sense(self) -> float | None:
        """-1 when the phase's first exit on a turn waits for it to fall below its value (a
        clockwise turn), +1 when for it to rise above; None without such an exit."""
        cond = next((c for c in self.exits if c.relative), None)
        if cond is None:
            return None
        return -1.0 if cond.op.startswith("<") else 1.0


@dataclass(frozen=True)
class RecipeObject:
    """An object the recipe grasps, as the estimator needs it: a cylinder of nominal radius (m)
    lying along the joint axes. Its name is the simulated hand's name for it and the prefix of
    its estimates."""

    name: str
    radius: float


Pair = tuple[int, int]
"""Two objects by index in the recipe's ``objects``: the line from the first to the second."""


def consecutive_pairs(count: int) -> tuple[Pair, ...]:
    """The pairs a recipe gets when it names none: each object with the next (none for one)."""
    return tuple((i, i + 1) for i in range(count - 1))


def estimate_names(objects: Sequence[RecipeObject], pairs: Sequence[Pair]) -> tuple[str, ...]:
    """The estimator's outputs in its order: each pair's (``PAIR_ESTIMATES``), then each
    object's (``OBJECT_ESTIMATES``). Pairs come first so that the first pair's turn sits at
    ``FIRST_PAIR_TURN`` whatever the number of objects."""
    out: list[str] = []
    for a, b in pairs:
        out += [f"{objects[a].name}_{objects[b].name}_{s}" for s in PAIR_ESTIMATES]
    for o in objects:
        out += [f"{o.name}_{s}" for s in OBJECT_ESTIMATES]
    return tuple(out)


@dataclass(frozen=True)
class Recipe:
    name: str
    source: str
    description: str
    phases: tuple[Phase, ...]
    end_ramp_s: float
    hand_config_hash: str | None
    compiled: bool
    objects: tuple[RecipeObject, ...] = ()
    limit_guard: LimitGuard | None = None  # soft-limit push-back (guard.py); None: off
    #: deg, the least total turn of the first pair for the experiment to count as a success
    #: (the run's ``experiment.success``); 0 asks for none
    min_total_turn_deg: float = 0.0
    #: the pairs whose centre line the estimator reports (``consecutive_pairs`` by default)
    pairs: tuple[Pair, ...] = ()
    #: what a phase's ``reanalyse`` needs beyond what the hand measures; None: no phase does
    grasp_model: GraspModel | None = None
    #: the phases a failed plan left undone on every model, as ``phase: what``
    #: (``planned_from.failed_phases``); a recipe written to be looked at, not run
    plan_failed: tuple[tuple[str, str], ...] = ()

    @property
    def manipulation_phases(self) -> tuple[str, ...]:
        """The names of the manipulation phases (``Phase.manipulates``), in the recipe's order."""
        return tuple(p.name for p in self.phases if p.manipulates)

    @property
    def estimates(self) -> tuple[str, ...]:
        """The names of the estimator's outputs for this recipe, in its order."""
        return estimate_names(self.objects, self.pairs)

    @property
    def uses_estimates(self) -> bool:
        return any(
            p.turn_rate is not None
            or p.brake is not None
            or p.paced is not None
            or p.stall is not None
            or p.reanalyse is not None
            or bool(p.schedule)
            for p in self.phases
        ) or any(c.kind is SignalKind.ESTIMATE for p in self.phases for c in (*p.exits, *p.aborts))


def parse_condition(
    text: str, joint_names: tuple[str, ...], estimates: Sequence[str] = ()
) -> Condition | str:
    """A ``Condition``, or the reason the text is not one (for the loader's message).
    ``estimates``: the names of the recipe's estimates (``estimate_names``), in their order."""
    match = _CONDITION.fullmatch(text)
    if match is None:
        example = f"angle.{joint_names[0]} > 1.2 for 0.02" if joint_names else "time > 1.0"
        return (
            f"a condition 'SIGNAL OP NUMBER [for SECONDS]' in ASCII digits and plain spaces "
            f"(no tab, line break or other script's digits), e.g. '{example}'"
        )
    signal = match["signal"]
    hold = float(match["hold"]) if match["hold"] else 0.0
    value = float(match["value"])
    # the pattern admits only digits, but enough of them overflow to infinity: a threshold of
    # inf is always (or never) crossed, and a hold longer than any phase never ends
    if not math.isfinite(value):
        return f"a condition whose NUMBER is finite (it reads as {value})"
    if hold > MAX_PHASE_S:
        return f"a condition held for at most {MAX_PHASE_S:g} s, a phase's longest"
    if signal == "time":
        return Condition(text, SignalKind.TIME, 0, match["op"], value, hold)
    family, _, name = signal.partition(".")
    if family == "estimate":
        if name in estimates:
            index = estimates.index(name)
        elif name in LEGACY_ESTIMATES and _legacy_layout(estimates):
            index = LEGACY_ESTIMATES[name]
        else:
            known = ", ".join(estimates) if estimates else "none: the recipe declares no objects"
            if name in LEGACY_ESTIMATES and estimates:
                known += "; the legacy names read two objects' one pair, first to second"
            return f"an estimate of the recipe's objects ({known}) (in '{text}')"
        return Condition(
            text,
            SignalKind.ESTIMATE,
            index,
            match["op"],
            value,
            hold,
            relative=estimates[index].endswith(PHASE_RELATIVE_SUFFIX),
        )
    if name not in joint_names:
        return f"a joint of the hand ({', '.join(joint_names)}) in '{text}'"
    kind = SignalKind.ANGLE if family == "angle" else SignalKind.TDT
    return Condition(text, kind, joint_names.index(name), match["op"], value, hold)


def _legacy_layout(estimates: Sequence[str]) -> bool:
    """Whether the estimates are those of two objects and their one pair, from the first to
    the second: the only layout the legacy names described (a pair written the other way
    round read its line half a turn from what the legacy names meant)."""
    if len(estimates) != len(LEGACY_ESTIMATES) or not estimates[1].endswith(PHASE_RELATIVE_SUFFIX):
        return False
    first, second = estimates[2].removesuffix("_x"), estimates[4].removesuffix("_x")
    return estimates[0] == f"{first}_{second}_line_angle"
