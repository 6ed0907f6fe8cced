"""The input of ``handctl plan``: a recipe template (phases and the wanted motion of each).

A template says *what* each phase must do, not the torques that do it:

- ``free``: no contact to reason about (the approach); its torques are the template's own and
  are only simulated, so the phases after it start where the hand really is;
- ``lift``: the objects go up from the table by fingertip pushing (wanted direction ``move``
  per object) and end ``min_height`` above it, caged;
- ``hold``: the objects stay up and caged (no wanted motion);
- ``turn``: the line through the two centres turns by ``turn_deg`` (counter-clockwise
  positive); the compiled phase exits when the *estimated* turn reaches ``exit_fraction`` of
  it, held ``exit_hold_s``, and moves on at ``max_s`` otherwise (with ``turn_from``, on the
  turn since that phase began; with ``exit_share: N`` too, on an even share, among it and the
  N - 1 turn phases after it, of what is left to the last one's exit). Its ``schedule`` entries
  (alternative torques for the objects' measured sizes) either give their ``torques``,
  carried into the recipe as written, or ask for ``plan: {models: N}``: the plan searches
  that entry's torque on N models whose objects are of the sizes its ``when`` names.

``seed`` torques (optional) are where the search starts besides the analysis' answer and the
previous phase's torques. ``search`` sets the budget and the perturbed models. Loading is
strict (``handctl.schema``): unknown keys, wrong types and out-of-range values are errors that
name the file and key path.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from handctl.analysis.frames import moderate
from handctl.config import HandConfig
from handctl.errors import ConfigError, Description
from handctl.online.estimator import RADIUS_RANGE
from handctl.online.recipes.guard import GuardSettings
from handctl.online.recipes.loader import (
    MAX_JOINT_DAMPING,
    MAX_SCHEDULE,
    check_phase_ramp,
    check_ramp,
    check_unique_names,
    check_unshadowed,
    hold_outlasts,
    parse_brake,
    parse_damping_fades,
    parse_exit_share,
    parse_grasp_model,
    parse_integral_gains,
    parse_joint_damping,
    parse_limit_guard,
    parse_min_total_turn,
    parse_objects,
    parse_paced_ramp,
    parse_pairs,
    parse_reanalyse,
    parse_schedule_when,
    parse_stall,
    parse_torque_margin,
    parse_torques,
    parse_turn_rate,
    refuse_another_hands_joints,
)
from handctl.online.recipes.schema import (
    FIRST_PAIR_TURN,
    GraspModel,
    PacedRamp,
    Pair,
    PerJoint,
    RadiusRatio,
    Reanalyse,
    RecipeObject,
    ScheduledTorques,
    TurnBrake,
    TurnRate,
    TurnStall,
    estimate_names,
)
from handctl.planning.models import Spread
from handctl.planning.search import MAX_TURN_RATE_DEG_S, TORQUE_DECIMALS, Budget
from handctl.schema import Doc, load_yaml
from handctl.sim.params import check_scene_names, parse_sim

KINDS = ("free", "lift", "hold", "turn")
#: the most models a planned ``schedule`` entry may ask for
MAX_SCHEDULE_MODELS = 64


#: the most perturbed models a phase is searched on (``search.models``, ``plan --models``): a
#: search runs every candidate on each, and 100 is hours of planning on a workstation
MAX_MODELS = 100
#: deg, the smallest turn a turn phase may ask for: the pair's estimated centre line, which
#: its exit reads, is noisier than that
MIN_TURN_DEG = 1.0


@dataclass(frozen=True)
class PlannedSchedule:
    """A ``schedule`` entry of a template's turn phase whose torque the plan searches
    (``plan: {models: N}``), on ``models`` models of the template's spread whose objects'
    radii are drawn within ``when``'s ranges (``compile._plan_schedule``).

    Why planned: a torque found by hand for one size of object is tuned to the hands it was
    tried on; searched over models of that size (and every other uncertainty of the spread),
    it is chosen as the phase's own torque is, for what a hand of that size does."""

    when: tuple[RadiusRatio, ...]
    models: int


ScheduleEntry = ScheduledTorques | PlannedSchedule


@dataclass(frozen=True)
class TemplatePhase:
    name: str
    kind: str
    ramp_s: float
    max_s: float
    seed: tuple[float, ...] | None  # N·m, config joint order
    move: dict[str, tuple[float, float]] = field(default_factory=dict)
    min_height: float = 0.0  # m
    turn: float = 0.0  # rad
    exit_fraction: float = 0.95
    exit_hold_s: float = 0.02
    turn_rate: TurnRate | None = None  # a turn phase's rate loop, carried into the recipe
    pose_stiffness: float | None = None  # N·m/rad: a free phase ends in the nominal's pose
    pose_damping: float = 0.0  # N·m·s/rad
    #: the names of the estimates of the template's objects (``schema.estimate_names``)
    estimates: tuple[str, ...] = ()
    #: N·m·s/rad, injected (one for every joint, or one per joint), carried into the recipe
    joint_damping: PerJoint = 0.0
    brake: TurnBrake | None = None  # more damping while the pair tumbles, carried likewise
    #: a turn phase's ramp paced by the pair's turn rate, carried likewise
    paced: PacedRamp | None = None
    #: the recipe's torques times this when run (one factor, or one per joint), carried likewise
    torque_margin: PerJoint = 1.0
    #: a turn phase whose recipe exit reads the turn from where this earlier phase began
    #: (``schema.Phase.turn_from``), carried likewise; "": its own start
    turn_from: str = ""
    #: rad, what the phases from ``turn_from`` up to this one (this one excluded) ask to turn
    from_turn: float = 0.0
    stall: TurnStall | None = None  # the end of a turn phase that stopped turning, carried
    #: this turn phase and the ``exit_share - 1`` turn phases after it share what is left of
    #: the turn to the last one's exit (``schema.Phase.exit_share``), carried into the recipe
    #: with that exit; 1: its own exit
    exit_share: int = 1
    #: rad, with an ``exit_share``: the last sharing phase's recipe exit (the turn since
    #: ``turn_from``), which this phase's compiled exit is written with
    share_to: float = 0.0
    #: the analysis again at the measured configuration when the phase begins, carried
    reanalyse: Reanalyse | None = None
    #: a turn phase's alternative torques for the objects' measured sizes: written ones are
    #: carried into the recipe as written, planned ones searched (``PlannedSchedule``)
    schedule: tuple[ScheduleEntry, ...] = ()
    #: the template's object names, by which a compiled ``schedule`` names its ranges
    object_names: tuple[str, ...] = ()
    #: whether ``joint_damping`` fades over the next phase's ramp or ends with the phase,
    #: carried into the recipe
    joint_damping_fades: bool = True
    #: the pose hold's integral: gain N·m/(rad·s), max N·m, still_rate rad/s; its rest pose
    #: is where the nominal hand settles under the hold (``compile._with_rest``)
    pose_integral: tuple[float, float, float] | None = None

    def exit_condition(self) -> str:
        """The exit of a turn phase in the planner's episodes: on the estimated turn of the
        first pair since the phase began (an episode runs one phase from where the last
        left the pair)."""
        op = "<" if self.turn < 0 else ">"
        return (
            f"estimate.{self.estimates[FIRST_PAIR_TURN]} {op} "
            f"{self.turn * self.exit_fraction:.4f} for {self.exit_hold_s:g}"
        )

    def recipe_exit_condition(self) -> str:
        """The compiled recipe's exit of a turn phase: with ``turn_from``, on the turn since
        that phase began, to ``exit_fraction`` of all the phases from there to this one
        ask; else as ``exit_condition``."""
        if not self.turn_from:
            return self.exit_condition()
        op = "<" if self.turn < 0 else ">"
        return (
            f"estimate.{self.estimates[FIRST_PAIR_TURN]} {op} "
            f"{self.recipe_exit_turn():.4f} for {self.exit_hold_s:g}"
        )

    def recipe_exit_turn(self) -> float:
        """rad, the turn since ``turn_from`` the compiled exit is written with: the phases'
        turns to here times ``exit_fraction``, or with an ``exit_share`` the last sharing
        phase's, which the runner shares out when this phase measures the pair."""
        if self.exit_share > 1:
            return self.share_to
        return (self.turn + self.from_turn) * self.exit_fraction


@dataclass(frozen=True)
class SearchSettings:
    models: int
    seed: int
    spread: Spread
    budget: Budget
    random_seeds: int = 0  # extra seeds per phase drawn uniformly from the flexion box
    #: deg/s, a turn phase's true centre-line rate above this at its peak is penalised
    max_turn_rate_deg_s: float = MAX_TURN_RATE_DEG_S


@dataclass(frozen=True)
class Template:
    source: str
    #: the SHA-256 (hex) of the bytes this template was parsed from: what the compiled recipe
    #: records (``template_sha256``). The file read again after the search named the
    #: template as it was then, edited meanwhile or not (an outside audit)
    sha256: str
    recipe: str
    description: str
    objects: tuple[RecipeObject, ...]
    end_ramp_s: float
    search: SearchSettings
    phases: tuple[TemplatePhase, ...]
    limit_guard: GuardSettings | None = None  # carried into the compiled recipe
    min_total_turn_deg: float = 0.0  # deg; carried into the compiled recipe
    grasp_model: GraspModel | None = None  # what ``reanalyse`` needs; carried likewise
    #: the pairs the estimator reports, by index into ``objects``; the first is the one the
    #: turn phases turn and the models are scored on (``pairs``; each object with the next
    #: when absent); carried into the compiled recipe
    pairs: tuple[Pair, ...] = ()


def load_template(path: str | Path, hand: HandConfig) -> Template:
    """Read and check a template against ``hand``; every problem is a ``ConfigError``."""
    doc = load_yaml(path, "recipe template")
    doc.string("template")
    recipe = doc.label("recipe")
    description = doc.text("description", default="")
    if not doc.has("objects"):
        doc.fail("objects", "the objects the template grasps ([{name, radius}, ...])", "nothing")
    _refuse_another_hands_template(doc, hand)
    objects = list(parse_objects(doc))
    # every model the phases are planned on is the simulated hand's scene: objects it lacks
    # were planned on as nothing, and the recipe was refused by every run after the search
    check_scene_names(doc.file, [o.name for o in objects], hand)
    _check_scene_objects(doc.file, objects, hand)
    end_ramp = doc.number("end_ramp_s", default=0.3, min=0.0, max=60.0, unit="s")
    search = _search(doc.mapping("search", default={}))
    guard = parse_limit_guard(doc, hand)
    names = [o.name for o in objects]
    pairs = parse_pairs(doc, tuple(objects))
    min_turn = parse_min_total_turn(doc, bool(pairs))
    estimates = estimate_names(objects, pairs)
    phases = tuple(
        _phase(p, hand, names, estimates) for p in doc.mappings("phases", min_len=1, max_len=32)
    )
    check_unique_names(doc, [p.name for p in phases])
    _check_free_ramps(doc.file, phases, hand, end_ramp)
    _check_searched_ramps(doc.file, phases, hand, end_ramp)
    phases = _resolve_turn_from(doc, phases)
    grasp_model = parse_grasp_model(
        doc, objects, [i for i, p in enumerate(phases) if p.reanalyse is not None]
    )
    doc.done()
    return Template(
        doc.file,
        doc.sha256,
        recipe,
        description,
        tuple(objects),
        end_ramp,
        search,
        phases,
        guard,
        min_turn,
        grasp_model,
        pairs,
    )


#: The keys of a template's phase that map joint names to values.
_JOINT_KEYED = ("seed", "torques", "joint_damping")


def _refuse_another_hands_template(doc: Doc, hand: HandConfig) -> None:
    """A template written for another hand is said as such, before its objects are held to
    the hand's scene: a planar template planned with the default hand was refused on its
    objects' radius ("a radius the estimator can measure the scene's ... against"), and
    the user sent to tune a size, where ``run recipe`` says "written for another hand? give
    its config with --hand" (found by an outside audit)."""
    raw = doc.raw("phases", None)
    if not isinstance(raw, list):
        return  # said where the phases are read
    for i, phase in enumerate(raw):
        if not isinstance(phase, dict):
            continue
        keyed = {k: v for k, v in phase.items() if isinstance(k, str)}
        sub = Doc(keyed, doc.file, f"{doc.key_path('phases')}[{i}]")
        for key in _JOINT_KEYED:
            refuse_another_hands_joints(sub, key, hand)  # a mapping by joint names only


def _check_scene_objects(source: str, objects: Sequence[RecipeObject], hand: HandConfig) -> None:
    """The template's objects as the scene the plan's models are drawn from has them: each
    radius within what the estimator fits of the template's (it measures none outside
    ±``RADIUS_RANGE``), and in their order along the palm (the estimator names them so when
    it first locates them). A template of 12 mm cylinders on a scene of 45 mm ones planned
    "2/2 did its job" and its runs had no estimate; one listing the scene's pair right to
    left ran with every estimate of the pair 180° off."""
    scene = {o.name: o for o in parse_sim(hand).objects}
    where = f"sim.objects in {hand.source}"
    for i, obj in enumerate(objects):
        actual = scene[obj.name].radius
        low, high = obj.radius * (1.0 - RADIUS_RANGE), obj.radius * (1.0 + RADIUS_RANGE)
        if not low <= actual <= high:
            raise ConfigError(
                source,
                f"objects[{i}].radius",
                f"a radius the estimator can measure the scene's {obj.name} against "
                f"({actual * 1e3:g} mm in {where}: its fit stays within ±"
                f"{RADIUS_RANGE * 100:g} % of the template's)",
                obj.radius,
            )
    along = [o.name for o in sorted(objects, key=lambda o: scene[o.name].x)]
    if along != [o.name for o in objects]:
        raise ConfigError(
            source,
            "objects",
            f"the objects in their order along the palm in the scene ({', '.join(along)}, by "
            f"their x in {where}): the estimator names them in that order",
            Description(", ".join(o.name for o in objects)),
        )


def unreachable_turn(template: Template) -> str | None:
    """What is wrong with a ``min_total_turn_deg`` above the turn the template's phases ask
    for in all, or None. A warning, not a refusal: a turn phase may turn further than it asks
    (a tumble), and a template cut short of its turns is planned phase by phase all the same;
    but a recipe of it that turns as asked fails every run (``experiment.success``)."""
    asked = sum(abs(math.degrees(p.turn)) for p in template.phases if p.kind == "turn")
    if template.min_total_turn_deg <= asked:
        return None
    return (
        f"{template.source}: min_total_turn_deg {template.min_total_turn_deg:g} is more than "
        f"its turn phases ask for in all ({asked:.4g} deg): every run of the recipe that turns "
        "as asked fails (experiment.success false, exit 1)"
    )


def _check_free_ramps(
    source: str, phases: Sequence[TemplatePhase], hand: HandConfig, end_ramp_s: float
) -> None:
    """The ramps between torques the template gives itself (its free phases', from zero at
    the start, and back to zero at the end), held to the rate limits now, as the planned
    recipe's are: a ramp_s of 0 into the first phase, or an end_ramp_s of 0, was refused only
    once every phase had been planned (minutes of planning lost). A last phase the search
    plans ends on torques not known yet, but not zero: its end ramp must take time."""
    rate = np.array([j.rate_limit for j in hand.joints])
    before: np.ndarray | None = np.zeros(hand.n_joints)
    for i, phase in enumerate(phases):
        if phase.kind != "free" or phase.seed is None:
            before = None  # what the search finds, checked in the recipe
            continue
        margin = np.broadcast_to(np.asarray(phase.torque_margin, dtype=float), rate.shape)
        torques = np.asarray(phase.seed) * margin
        if before is not None:
            check_ramp(
                source,
                hand,
                f"phases[{i}].ramp_s",
                f"into phase '{phase.name}'",
                before,
                torques,
                phase.ramp_s,
                rate,
            )
        before = torques
    if before is not None:
        check_ramp(
            source,
            hand,
            "end_ramp_s",
            "back to zero after the last phase",
            before,
            np.zeros(hand.n_joints),
            end_ramp_s,
            rate,
        )
    elif end_ramp_s == 0:
        raise ConfigError(
            source,
            "end_ramp_s",
            "a ramp back to zero longer than 0 s: the last phase's planned torques are not "
            "zero, and a step to zero is beyond every rate limit",
            end_ramp_s,
        )


#: N·m, a ramp bound is kept this far inside: a torque is written to ``TORQUE_DECIMALS``,
#: and one rounded up past the bound was refused by the recipe's loader
RAMP_BOUND_SLACK = 10.0**-TORQUE_DECIMALS


def ramp_intervals(
    spec: TemplatePhase,
    hand: HandConfig,
    before: np.ndarray,
    after: tuple[np.ndarray, float, str] | None,
    into: str,
) -> list[tuple[str, float, np.ndarray, np.ndarray]]:
    """Per ramp that binds ``spec``'s torques (its own ``ramp_s`` from ``before``, and the
    one to ``after``): its key, its length (s, as written) and the torques (N·m, low and
    high per joint) the rate limits can ramp over it (``compile.ramp_bounds``)."""
    rate = np.array([j.rate_limit for j in hand.joints])
    margin = np.broadcast_to(np.asarray(spec.torque_margin, dtype=float), rate.shape)
    back = spec.paced.back if spec.paced is not None and spec.paced.back > 1.0 else 1.0
    ramps = [(into, spec.ramp_s, before, spec.ramp_s / back)]
    if after is not None:
        ramps.append((after[2], after[1], after[0], after[1]))
    out = []
    for key, written, other, ramp_s in ramps:
        reach = rate * ramp_s
        low = (other - reach) / margin + RAMP_BOUND_SLACK
        high = (other + reach) / margin - RAMP_BOUND_SLACK
        out.append((key, written, low, high))
    return out


def no_ramp_left(
    source: str, into: str, then: str | None, hand: HandConfig, joint: int, phase: str
) -> ConfigError:
    """The refusal of ramps that leave phase ``phase`` no torque on ``joint``: its own
    (``into``, the key of its ramp_s) and the one after it (``then``'s key, None: not known
    yet), as the template's load and the plan's search (``compile.ramp_bounds``) say it."""
    rate = hand.joints[joint].rate_limit
    return ConfigError(
        source,
        into if then is None else f"{into} or {then}",
        f"ramps the rate limit of {hand.joint_names[joint]} ({rate:g} N·m/s) can make "
        "between the phases' torques within tau_max",
        Description(f"none leaves a torque for phase '{phase}'"),
    )


def _check_searched_ramps(
    source: str, phases: Sequence[TemplatePhase], hand: HandConfig, end_ramp_s: float
) -> None:
    """The ramps of the phases the plan searches, refused now where they leave no torque
    whatever the search finds (``no_ramp_left``): a ramp_s of 0 into a phase after a
    searched one, which no torque but the one before it ramps, was refused by the search's
    bounds only once the phases before it had been planned (12 to 17 minutes of the swap's
    lift; found by an outside audit). Held to what is known before any search: the torques
    before the phase where they are given (from zero into the first, a free phase's), what
    follows it where it is given (zero after the last, a free phase's), and a ramp too
    short to leave any torque around a torque not known yet."""
    n = hand.n_joints
    for i, phase in enumerate(phases):
        if phase.kind == "free":
            continue
        before = np.zeros(n) if i == 0 else _given(phases[i - 1], hand)
        after: tuple[np.ndarray, float, str] | None = None
        if i == len(phases) - 1:
            after = (np.zeros(n), end_ramp_s, "end_ramp_s")
        elif (given := _given(phases[i + 1], hand)) is not None:
            after = (given, phases[i + 1].ramp_s, f"phases[{i + 1}].ramp_s")
        into = f"phases[{i}].ramp_s"
        ramps = ramp_intervals(phase, hand, np.zeros(n) if before is None else before, after, into)
        # with the torque before it not known, each ramp on its own: its width is known
        groups = [ramps] if before is not None else [[r] for r in ramps]
        for group in groups:
            low = np.max([r[2] for r in group], axis=0)
            high = np.min([r[3] for r in group], axis=0)
            for j in np.flatnonzero(low > high):
                raise no_ramp_left(
                    source, into, after[2] if after else None, hand, int(j), phase.name
                )


def _given(phase: TemplatePhase, hand: HandConfig) -> np.ndarray | None:
    """N·m, what the runner holds of a free phase's torques (times its ``torque_margin``);
    None for a phase the plan searches."""
    if phase.kind != "free" or phase.seed is None:
        return None
    margin = np.broadcast_to(np.asarray(phase.torque_margin, dtype=float), (hand.n_joints,))
    held: np.ndarray = np.asarray(phase.seed, dtype=float) * margin
    return held


def _resolve_turn_from(doc: Doc, phases: tuple[TemplatePhase, ...]) -> tuple[TemplatePhase, ...]:
    """Each ``turn_from`` checked to name this or an earlier turn phase, and the turn the
    phases from there up to this one ask for (its exit's share of the way)."""
    out = list(phases)
    for i, phase in enumerate(phases):
        if not phase.turn_from:
            continue
        earlier = [p.name for p in phases[: i + 1] if p.kind == "turn"]
        if phase.turn_from not in earlier:
            doc.fail(
                f"phases[{i}].turn_from",
                "the name of this or an earlier turn phase (" + ", ".join(earlier) + ")",
                phase.turn_from,
            )
        start = next(k for k, p in enumerate(phases) if p.name == phase.turn_from)
        out[i] = replace(phase, from_turn=sum(p.turn for p in phases[start:i]))
    # from the last phase back, so that a later phase's own share is named at its own key
    for i in reversed(range(len(out))):
        if out[i].exit_share > 1:
            out[i] = replace(out[i], share_to=_share_to(doc, out, i))
    return tuple(out)


def _share_to(doc: Doc, phases: list[TemplatePhase], i: int) -> float:
    """rad, the recipe exit of the last of the turn phases phase ``i``'s ``exit_share``
    spans: they must follow it and read the turn from the same ``turn_from``, so that
    "what is left" is the same turn for each of them."""
    phase = phases[i]
    key = f"phases[{i}].exit_share"
    if not phase.turn_from:
        doc.fail(
            key,
            "a phase with turn_from (the shared turn is read from where that phase began)",
            phase.exit_share,
        )
    sharing = phases[i + 1 : i + phase.exit_share]
    unfit = [f"{p.name} ({why})" for p in sharing if (why := _why_not_sharing(p, phase))]
    missing = phase.exit_share - 1 - len(sharing)
    if missing:
        unfit.append(f"{missing} phase(s) short of the end")
    if unfit:
        doc.fail(
            key,
            f"{phase.exit_share - 1} turn phase(s) after it, each with turn_from "
            f"{phase.turn_from}, turning the same way and with no exit_share of its own",
            "; ".join(unfit),
        )
    return sharing[-1].recipe_exit_turn()


def _why_not_sharing(phase: TemplatePhase, sharer: TemplatePhase) -> str:
    """Why ``phase`` cannot take a share of ``sharer``'s turn ("": it can)."""
    if phase.kind != "turn":
        return f"a {phase.kind} phase"
    if phase.turn_from != sharer.turn_from:
        return f"turn_from {phase.turn_from or 'none'}"
    if phase.exit_share > 1:
        return f"exit_share {phase.exit_share} of its own"
    if (phase.turn < 0) != (sharer.turn < 0):
        return f"turn_deg {math.degrees(phase.turn):g}, the other way"
    return ""


def _search(doc: Doc) -> SearchSettings:
    spread = _spread(doc.mapping("spread", default={}))
    b = Budget()
    budget = Budget(
        generations=doc.integer("generations", default=b.generations, min=0, max=100),
        population=doc.integer("population", default=b.population, min=1, max=1000),
        elite=doc.integer("elite", default=b.elite, min=1, max=100),
        initial_spread=doc.number("initial_spread", default=b.initial_spread, min=0.0, max=2.0),
        min_spread=doc.number("min_spread", default=b.min_spread, min=0.0, max=1.0),
    )
    if budget.elite > budget.population:
        doc.fail("elite", f"at most the population ({budget.population})", budget.elite)
    settings = SearchSettings(
        doc.integer("models", default=6, min=1, max=MAX_MODELS),
        doc.integer("seed", default=0, min=0, max=2**32 - 1),
        spread,
        budget,
        doc.integer("random_seeds", default=0, min=0, max=1000),
        doc.number(
            "max_turn_rate_deg_s",
            default=MAX_TURN_RATE_DEG_S,
            min=1.0,
            max=100000.0,
            unit="deg/s",
        ),
    )
    doc.done()
    return settings


def _spread(doc: Doc) -> Spread:
    """``search.spread``: any field of ``Spread`` (models.py), the others at their defaults.
    ± fields are a number; factor ranges two positive numbers, low first."""
    d = Spread()

    def factors(
        key: str, default: tuple[float, float], low: float, high: float, unit: str = ""
    ) -> tuple[float, float]:
        if not doc.has(key):
            return default
        pair = doc.numbers(key, length=2, min=low, max=high, unit=unit)
        if pair[0] > pair[1]:
            doc.fail(key, "[low, high] with low <= high", list(pair))
        return (pair[0], pair[1])

    spread = Spread(
        friction=doc.number("friction", default=d.friction, min=0.0, max=0.9),
        mass=doc.number("mass", default=d.mass, min=0.0, max=0.9),
        radius=doc.number("radius", default=d.radius, min=0.0, max=0.5),
        damping=factors("damping", d.damping, 0.01, 100.0),
        frictionloss=factors("frictionloss", d.frictionloss, 0.01, 100.0),
        armature=factors("armature", d.armature, 0.01, 100.0),
        actuator_lag=factors("actuator_lag", d.actuator_lag, 0.01, 100.0),
        placement=doc.number("placement", default=d.placement, min=0.0, max=0.05, unit="m"),
        gap=factors("gap", d.gap or (0.0, 0.0), 0.0, 0.05, "m"),
        initial_angles=doc.number(
            "initial_angles", default=d.initial_angles, min=0.0, max=0.5, unit="rad"
        ),
        tdt_bias=factors("tdt_bias", d.tdt_bias, 0.01, 10.0),
        tdt_noise=factors("tdt_noise", d.tdt_noise, 0.01, 10.0),
    )
    doc.done()
    return spread


def _schedule(doc: Doc, hand: HandConfig, objects: list[str]) -> tuple[ScheduleEntry, ...]:
    """A template's ``schedule``: each entry a recipe's (``when`` and ``torques``) or
    ``when`` and ``plan: {models: N}``, never both."""
    if not doc.has("schedule"):
        return ()
    out: list[ScheduleEntry] = []
    for k, entry in enumerate(doc.mappings("schedule", min_len=1, max_len=MAX_SCHEDULE)):
        when = parse_schedule_when(entry, objects)
        check_unshadowed(doc, k, when, [e.when for e in out], objects)
        if entry.has("plan") == entry.has("torques"):
            entry.fail(
                "torques",
                "either torques (carried as written) or plan: {models: N} (searched)",
                "both" if entry.has("plan") else "neither",
            )
        if entry.has("plan"):
            plan = entry.mapping("plan")
            models = plan.integer("models", min=2, max=MAX_SCHEDULE_MODELS)
            plan.done()
            out.append(PlannedSchedule(when, models))
        else:
            torques = parse_torques(entry, hand)
            _check_tau_max(entry, "torques", torques, hand)
            out.append(ScheduledTorques(when, torques))
        entry.done()
    return tuple(out)


def _torques(doc: Doc, key: str, hand: HandConfig) -> tuple[float, ...]:
    raw = doc.raw(key)
    if isinstance(raw, list):
        return tuple(doc.numbers(key, length=hand.n_joints, unit="N·m"))
    refuse_another_hands_joints(doc, key, hand)
    sub = doc.mapping(key)
    # a joint of another hand beside the missing one is named as what it is; read one by
    # one, the missing left_j1 was said to be misspelt as left_j2, a joint that was there
    sub.expect(hand.joint_names)
    values = tuple(sub.number(n, unit="N·m") for n in hand.joint_names)
    sub.done()
    return values


def _check_tau_max(
    doc: Doc,
    key: str,
    torques: tuple[float, ...] | None,
    hand: HandConfig,
    margin: PerJoint = 1.0,
    scale: float = 1.0,
) -> None:
    """A template's torques (a free phase's, a schedule entry's) go into the recipe as they
    are written, and its seeds start the search: none beyond the joint's tau_max, which the
    recipe would refuse only after the whole plan (a seed would be clipped without a word).
    The runner holds them times the phase's ``torque_margin``, and the recipe's loader
    refuses that product past tau_max, so it is held so here too; and times a turn-rate
    loop's largest ``scale``, which scales the margined torque. Each factor is said once, by
    its key (the scale was said twice, "(1.2) (1.2)", and with a margin the second figure
    was the product, unnamed; found by an outside audit)."""
    if torques is None:  # a lift, hold or turn phase without a seed
        return
    margins = np.broadcast_to(np.asarray(margin, dtype=float), (hand.n_joints,))
    for joint, value, each in zip(hand.joints, torques, margins.tolist(), strict=True):
        factor = each * scale
        if abs(value * factor) > joint.tau_max:
            parts = [f"the phase's torque_margin ({each:g})"] if each != 1 else []
            parts += [f"turn_rate's largest scale ({scale:g})"] if scale != 1 else []
            by = f", the torque times {' and '.join(parts)}" if parts else ""
            doc.fail(
                f"{key}.{joint.name}",
                f"|τ| <= {joint.tau_max:g} N·m (tau_max of {joint.name} in {hand.source})"
                + (f"{by}: {value * factor:.4g} N·m" if by else ""),
                value,
            )


def _check_margined(
    doc: Doc,
    hand: HandConfig,
    margin: PerJoint,
    scale: float,
    key: str,
    torques: tuple[float, ...] | None,
    schedule: Sequence[ScheduleEntry],
) -> None:
    """A phase's torques (a free phase's ``torques``, a seed, its written schedule entries')
    times its ``torque_margin`` and its turn-rate loop's largest ``scale``, within tau_max
    (``_check_tau_max``), as the recipe's loader holds what the runner asks."""
    if margin == 1.0 and scale == 1.0:
        return
    _check_tau_max(doc, key, torques, hand, margin, scale)
    for k, entry in enumerate(schedule):
        if isinstance(entry, ScheduledTorques):
            _check_tau_max(doc, f"schedule[{k}].torques", entry.torques, hand, margin, scale)


def _lift_move(sub: Doc, objects: list[str]) -> dict[str, tuple[float, float]]:
    """A lift's ``move``: each object's direction, with an upward part (gravity is along -y;
    a lift whose objects were to move down was planned, and said it did its job)."""
    move: dict[str, tuple[float, float]] = {}
    for obj in list(sub.keys()):
        if obj not in objects:
            sub.fail(obj, "an object of the template (" + ", ".join(objects) + ")", obj)
        vec = sub.numbers(obj, length=2)
        if not any(vec):  # any other length is a direction (made unit where it is used)
            sub.fail(obj, "a non-zero direction", list(vec))
        if vec[1] <= 0:
            sub.fail(obj, "a direction with an upward part (y > 0): a lift raises it", list(vec))
        x, y = moderate(np.array(vec, dtype=float)).tolist()
        move[obj] = (x, y)
    sub.done()
    return move


def _turn_exit(doc: Doc, period_s: float, max_s: float) -> tuple[float, float, int]:
    """A turn phase's ``exit_fraction``, ``exit_hold_s`` (s) and ``exit_share``; a hold its
    ``max_s`` leaves no time for is refused now, where the plan's recipe was refused after the
    whole plan."""
    exit_fraction = doc.number("exit_fraction", default=0.95, min=0.1, max=1.5)
    exit_hold = doc.number("exit_hold_s", default=0.02, min=0.0, max=1.0, unit="s")
    if hold_outlasts(period_s, exit_hold, max_s):
        doc.fail(
            "exit_hold_s",
            f"a hold the phase's max_s ({max_s:g} s) leaves time for (its exit could never hold)",
            exit_hold,
        )
    share = parse_exit_share(doc)
    if share > 1 and doc.has("exit_fraction"):
        # the shared exit is the last sharing phase's, so this phase's fraction is not read
        doc.fail(
            "exit_fraction",
            "no exit_fraction on a phase with an exit_share (its exit is the last sharing "
            "phase's, shared out)",
            exit_fraction,
        )
    return exit_fraction, exit_hold, share


def _phase(
    doc: Doc, hand: HandConfig, objects: list[str], estimates: tuple[str, ...]
) -> TemplatePhase:
    name = doc.label("name")
    kind = doc.string("kind", choices=KINDS)
    ramp = doc.number("ramp_s", default=0.3, min=0.0, max=60.0, unit="s")
    # a loop period at least, as the recipe's (refused there only after the search)
    max_s = doc.number("max_s", min=hand.bus.period_s, max=600.0, unit="s")
    key = "torques" if kind == "free" else "seed"
    seed = _torques(doc, key, hand) if kind == "free" or doc.has("seed") else None
    _check_tau_max(doc, key, seed, hand)
    move: dict[str, tuple[float, float]] = {}
    min_height = 0.0
    turn = 0.0
    exit_fraction = 0.95
    exit_hold = 0.02
    if kind == "lift":
        move = _lift_move(doc.mapping("move"), objects)
    if kind in ("lift", "hold"):
        min_height = doc.number("min_height", min=0.0, max=0.2, unit="m")
    turn_rate = None
    paced = None
    turn_from = ""
    stall = None
    share = 1
    reanalyse = None
    schedule: tuple[ScheduleEntry, ...] = ()
    if kind == "turn":
        if len(objects) < 2:
            doc.fail(
                "kind",
                "lift, hold or free: a turn is that of a pair of objects, and the template has one",
                kind,
            )
        turn_deg = doc.number("turn_deg", min=-180.0, max=180.0, unit="deg")
        if abs(turn_deg) < MIN_TURN_DEG:
            doc.fail(
                "turn_deg",
                f"a turn of at least {MIN_TURN_DEG:g} deg either way (less is within what the "
                "estimate of the pair can tell)",
                turn_deg,
            )
        turn = math.radians(turn_deg)
        exit_fraction, exit_hold, share = _turn_exit(doc, hand.bus.period_s, max_s)
        if doc.has("turn_rate"):
            turn_rate = parse_turn_rate(doc.mapping("turn_rate"), math.copysign(1.0, turn))
        if doc.has("paced_ramp"):
            paced = parse_paced_ramp(doc.mapping("paced_ramp"), math.copysign(1.0, turn))
        turn_from = doc.string("turn_from") if doc.has("turn_from") else ""
        stall = parse_stall(doc.mapping("stall")) if doc.has("stall") else None
        if doc.has("reanalyse"):
            reanalyse = parse_reanalyse(doc.mapping("reanalyse"), turn)
        schedule = _schedule(doc, hand, objects)
        if schedule and reanalyse is not None:
            doc.fail(
                "schedule",
                "no schedule in a phase with reanalyse (the analysis replaces the phase's "
                "torque itself)",
                f"{len(schedule)} entries",
            )
    # as the recipe's ramp is held (refused there only once every phase had been planned, and
    # a paced phase's ramp of 0 ended the plan in a traceback)
    check_phase_ramp(doc, ramp, max_s, paced is not None)
    stiffness: float | None = None
    damping = 0.0
    integral: tuple[float, float, float] | None = None
    if kind == "free" and doc.has("pose"):
        pose = doc.mapping("pose")
        stiffness = pose.number("stiffness", min=0.0, max=100.0, min_exclusive=True, unit="N·m/rad")
        damping = pose.number(
            "damping", default=0.0, min=0.0, max=MAX_JOINT_DAMPING, unit="N·m·s/rad"
        )
        if pose.has("integral"):
            gains = pose.mapping("integral")
            integral = parse_integral_gains(gains, hand)
            gains.done()
        pose.done()
    joint_damping = parse_joint_damping(doc, hand.joint_names)
    fades = parse_damping_fades(doc)
    brake = parse_brake(doc.mapping("brake")) if doc.has("brake") else None
    margin = parse_torque_margin(doc, hand.joint_names)
    # a free phase's torques and a written entry's go into the recipe as written, and a seed
    # starts the search, whose box is tau_max over the margin and the loop's scale
    # (``compile.search_box``): one past it was clipped there, and said "from template"
    scale = max(turn_rate.scale_max, 1.0) if turn_rate is not None else 1.0
    _check_margined(doc, hand, margin, scale, key, seed, schedule)
    doc.done()
    return TemplatePhase(
        name,
        kind,
        ramp,
        max_s,
        seed,
        move,
        min_height,
        turn,
        exit_fraction,
        exit_hold,
        turn_rate,
        stiffness,
        damping,
        estimates,
        joint_damping,
        brake,
        paced,
        margin,
        turn_from,
        stall=stall,
        reanalyse=reanalyse,
        schedule=schedule,
        object_names=tuple(objects),
        joint_damping_fades=fades,
        pose_integral=integral,
        exit_share=share,
    )
