"""Strict loading of recipes, checked against the hand before any frame is sent.

A recipe can never raise a hardware limit: every phase torque is compared with the joint's
tau_max from the hand config, and every ramp (from zero into the first phase, between phases,
and back to zero at the end) with the joint's rate limit. A violation is a ``ConfigError`` that
names the phase, the joint, the value and the limit, so the fix is obvious.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from handctl.config import HandConfig
from handctl.convention import MAX_OBJECT_RADIUS, NAME_CHARS, OBJECT_NAME
from handctl.errors import ConfigError
from handctl.online.estimator import RADIUS_RANGE
from handctl.online.recipes.guard import SIDES, GuardSettings, SpringBand
from handctl.online.recipes.runner import RunStatus
from handctl.online.recipes.schema import (
    FIRST_PAIR_TURN,
    MAX_OBJECTS,
    MAX_PHASE_S,
    OBJECT_ESTIMATES,
    REANALYSIS_USES,
    Condition,
    GraspModel,
    PacedRamp,
    Pair,
    PerJoint,
    Phase,
    PoseHold,
    PoseIntegral,
    RadiusRatio,
    Reanalyse,
    Recipe,
    RecipeObject,
    ScheduledTorques,
    SignalKind,
    TimeoutAction,
    TurnBrake,
    TurnRate,
    TurnStall,
    consecutive_pairs,
    estimate_names,
    parse_condition,
)
from handctl.schema import Doc, description, load_yaml

MAX_PHASES = 64
#: m, the smallest nominal radius of a recipe's object: at 1e-12 m a recipe loaded and ran
#: with an estimator that never placed the object (it fits within ±40 % of the nominal), so
#: an exit on its estimates never came; the simulated hand's objects are as large or larger
MIN_OBJECT_RADIUS = 0.005
#: rad, the range of ``limit_guard_band``: narrower is a cliff again, wider fights the grasp.
#: The spring (tau_max / band) through the drive's lag rings on a light joint well above the
#: least (0.02 and 0.05 on the nominal hand's distal joints, not 0.08): a run whose command
#: rings says so (``safety.chatter``)
GUARD_BAND_MIN = 0.02
GUARD_BAND_MAX = 0.5


def fits_no_guard(span: float) -> bool:
    """Whether a joint's range of ``span`` (rad) is too narrow for the guard's two narrowest
    bands, so that no recipe with a guard can run on its hand."""
    return span - RANGE_ROUNDING_RAD <= 2 * GUARD_BAND_MIN


#: deg, the most ``min_total_turn_deg`` may ask for (a few turns of the pair)
MAX_TOTAL_TURN_DEG = 1440.0
#: deg/s, the fastest turn a turn-rate loop may ask for (a quasi-static analysis covers less)
MAX_TURN_RATE_DEG_S = 720.0
#: N·m·s/rad, the most damping a phase may inject: the drive's lag and the velocity filter
#: delay the damper by about 15 ms, and a damper much stiffer than the joints' inertia over
#: that delay oscillates instead of damping. Not a bound of stability (a distal link of the
#: nominal hand rings from about 0.01, a proximal one takes more; a hand config carries no
#: inertia): a run whose command rings says so (``safety.chatter``)
MAX_JOINT_DAMPING = 0.2
#: the largest ``torque_margin``: twice the planned torque is already a different plan
MAX_TORQUE_MARGIN = 2.0
#: the most a turn-rate loop may scale its phase's torque (tau_max still bounds it)
MAX_SCALE = 5.0
#: the furthest a paced ramp may go along its segment (1: the phase's torque; tau_max and
#: the supervisor still bound every joint)
MAX_REACH = 3.0
#: the most times its ramp's speed a paced ramp may go back at (the loader checked the ramp
#: against the joints' rate limit; the supervisor holds every step to it)
MAX_BACK = 10.0
#: rad/s, the largest joint speed a paced ramp or a brake may take as its threshold
MAX_JOINT_RATE = 100.0
#: s, the longest a phase's ``reanalyse`` may wait for its result (the planned torque acts
#: meanwhile; a result much later is for a pair that has moved on)
MAX_REANALYSIS_DELAY_S = 1.0
#: s, the default wait for a reanalysis: the analysis' one MILP takes 30..370 ms of CPU at
#: the configurations measured (docs/experiment.md), and a real-time run must have it then
DEFAULT_REANALYSIS_DELAY_S = 0.5
#: the deepest fraction of the guard's band a paced ramp's ``limit_depth`` may start at: it
#: needs room before the limit to go back in
MAX_LIMIT_DEPTH = 0.9
#: the most alternative torques a phase's ``schedule`` may carry
MAX_SCHEDULE = 8
#: the widest bounds of a ``radius_ratio``: the estimator fits a radius within ±40 % of the
#: recipe's (``RADIUS_RANGE``); a bound past that is an open end, a range past it is refused
RADIUS_RATIO_MIN = 0.5
RADIUS_RATIO_MAX = 1.5


def load_recipe(path: str | Path, hand: HandConfig) -> Recipe:
    """Load, validate and check a recipe for ``hand``; raises ``ConfigError``."""
    doc = load_yaml(path, "recipe")
    recipe = parse_recipe(doc, hand)
    check_against_hand(recipe, hand)
    return recipe


def parse_recipe(doc: Doc, hand: HandConfig, *, as_recorded: bool = False) -> Recipe:
    """The recipe in ``doc`` for ``hand``; ``as_recorded``: a recording's, read as it ran
    (a name the rules refuse now stays readable)."""
    name = doc.label("recipe", as_recorded=as_recorded)
    description = doc.text("description", default="")
    compiled = doc.boolean("compiled", default=False)
    digest = doc.raw("hand_config_hash", None)
    if digest is not None and not isinstance(digest, str):
        doc.fail("hand_config_hash", "a string like 'sha256:...'", digest)
    if compiled and digest is None:
        doc.fail(
            "hand_config_hash",
            "the hash of the hand config a compiled recipe was made for",
            "nothing",
        )
    # before anything that names a joint: on another hand the joints a recipe names are
    # not this hand's, and an unknown joint would hide that the whole recipe is another's
    if digest is not None and not hand.answers_to(digest):
        # which of the two it is the recipe cannot say: its hand's name is not in it
        raise ConfigError(
            doc.file,
            "hand_config_hash",
            f"{hand.config_hash}, the hash of {hand.source} (the recipe was compiled for "
            "another hand config: written for another hand? give its config with --hand; "
            "for this hand's config as it was before a change? recompile it for this one)",
            digest,
        )
    if not as_recorded:
        _refuse_another_hands_phases(doc, hand)
    end_ramp = doc.number("end_ramp_s", default=0.2, min=0.0, max=60.0, unit="s")
    objects = parse_objects(doc)
    pairs = parse_pairs(doc, objects)
    estimates = estimate_names(objects, pairs)
    settings = parse_limit_guard(doc, hand)
    guard = settings.guard(hand) if settings is not None else None
    min_turn = parse_min_total_turn(doc, bool(pairs))
    planned_from = doc.raw("planned_from", {})  # provenance of a planned recipe
    if not isinstance(planned_from, dict):
        doc.fail(
            "planned_from", "a mapping (what handctl plan planned the recipe from)", planned_from
        )
    plan_failed = _plan_failed(doc)
    phases = tuple(
        _parse_phase(p, hand, estimates, objects)
        for p in doc.mappings("phases", min_len=1, max_len=MAX_PHASES)
    )
    check_unique_names(doc, [p.name for p in phases])
    check_exit_shares(doc.file, phases)
    grasp_model = parse_grasp_model(
        doc, objects, [i for i, p in enumerate(phases) if p.reanalyse is not None]
    )
    for i, phase in enumerate(phases):
        earlier = [p.name for p in phases[: i + 1]]
        if phase.turn_from and phase.turn_from not in earlier:
            raise ConfigError(
                doc.file,
                f"phases[{i}].turn_from",
                "the name of this phase or an earlier one (" + ", ".join(earlier) + ")",
                phase.turn_from,
            )
        if phase.turn_from and not any(c.relative for c in phase.exits + phase.aborts):
            # it sets where a turn read in the phase's conditions counts from, and nothing
            # else: without one it did nothing, and a key that does nothing misleads
            raise ConfigError(
                doc.file,
                f"phases[{i}].turn_from",
                "a phase whose exit or abort reads a turn (estimate.<pair>_turn): turn_from "
                "sets where it counts from",
                phase.turn_from,
            )
        for key, loop in (
            ("turn_rate", phase.turn_rate),
            ("brake", phase.brake),
            ("paced_ramp", phase.paced),
            ("stall", phase.stall),
            ("reanalyse", phase.reanalyse),
        ):
            if loop is not None and not pairs:
                raise ConfigError(
                    doc.file,
                    f"phases[{i}].{key}",
                    "a recipe that declares two "
                    "objects or more ([{name, radius}, ...]): the " + key + " reads "
                    "the turn of the first pair",
                    f"{len(objects)} objects",
                )
        _check_rate_sense(doc.file, i, phase)
        if phase.paced is not None and phase.paced.limit_depth > 0.0 and guard is None:
            raise ConfigError(
                doc.file,
                f"phases[{i}].paced_ramp.limit_depth",
                "a recipe with a limit_guard_band (limit_depth is a fraction of its band)",
                "no limit_guard_band",
            )
    doc.done()
    return Recipe(
        name,
        doc.file,
        description,
        phases,
        end_ramp,
        digest,
        compiled,
        objects,
        guard,
        min_turn,
        pairs,
        grasp_model,
        plan_failed,
    )


#: The keys of a phase that ``handctl plan`` never writes into a phase's ``provenance`` (its
#: own ``schedule`` is there, what planned the phase's schedule): one found there is a phase
#: key indented a level too deep, which provenance swallowed unread.
PHASE_KEYS = frozenset(
    {
        "name", "torques", "ramp_s", "max_s", "on_timeout", "exit", "abort", "turn_rate",
        "pose", "joint_damping", "joint_damping_fades", "brake", "paced_ramp",
        "torque_margin", "turn_from", "stall", "exit_share", "reanalyse",
    }
)  # fmt: skip


def _refuse_another_hands_phases(doc: Doc, hand: HandConfig) -> None:
    """A phase whose provenance says it was planned for another hand config is refused as
    a recipe compiled for one is: deleting the recipe's own hash (or its ``compiled``) let
    the whole recipe run on another hand, every phase still saying it was planned for the
    first. And a phase key inside ``provenance`` is refused: it ran as if it were not there."""
    phases = doc.raw("phases", None)
    if not isinstance(phases, list):
        return  # said where the phases are read
    for i, phase in enumerate(phases):
        provenance = phase.get("provenance") if isinstance(phase, dict) else None
        if not isinstance(provenance, dict):
            continue
        key = f"phases[{i}].provenance"
        digest = provenance.get("hand_config_hash")
        if digest is not None and not (isinstance(digest, str) and hand.answers_to(digest)):
            raise ConfigError(
                doc.file,
                f"{key}.hand_config_hash",
                f"{hand.config_hash}, the hash of {hand.source} (the phase was planned for "
                "another hand config: plan the recipe again for this one)",
                digest,
            )
        stray = sorted(PHASE_KEYS.intersection(provenance))
        if stray:
            raise ConfigError(
                doc.file,
                f"{key}.{stray[0]}",
                "only what handctl plan wrote there: a phase's own keys go beside "
                "'provenance', not inside it (indented a level too deep?)",
                provenance[stray[0]],
            )


def _plan_failed(doc: Doc) -> tuple[tuple[str, str], ...]:
    """``planned_from.failed_phases`` (``phase: what it left undone``): what a plan that
    failed said of its recipe, which it wrote to be looked at. The rest of ``planned_from``
    is provenance, read by people, not by the runner."""
    planned = doc.mapping("planned_from", default={})
    if not planned.has("failed_phases"):
        return ()
    failed = planned.mapping("failed_phases")
    return tuple((str(name), failed.text(str(name))) for name in list(failed.keys()))


def parse_min_total_turn(doc: Doc, has_pair: bool) -> float:
    """``min_total_turn_deg`` of a recipe or a template: the least total turn of the first
    pair for the experiment to succeed (0, asking for no turn, when it is not set; only 0
    without a pair)."""
    turn = doc.number(
        "min_total_turn_deg", default=0.0, min=0.0, max=MAX_TOTAL_TURN_DEG, unit="deg"
    )
    if turn > 0 and not has_pair:
        doc.fail(
            "min_total_turn_deg",
            "0 (a turn is that of a pair of objects, and there is no pair)",
            turn,
        )
    return turn


#: rad: a joint's range as written (0.45 - 0.35 is 0.09999999999999998 or, the other way
#: round, 0.10000000000000003) is compared with bands this much short of it: bands of exactly
#: half of it each passed by rounding, and their two springs met
RANGE_ROUNDING_RAD = 1e-9


def parse_limit_guard(doc: Doc, hand: HandConfig) -> GuardSettings | None:
    """``limit_guard_band`` (rad) of a recipe or a template, with the spring bands of its own
    that ``limit_guard_spring_bands`` gives a side of a joint, or None when the guard is off.

    ``limit_guard_spring_bands`` is ``{joint: {lower: rad, upper: rad}}`` (either side may be
    left out). A joint's two springs must leave room between them, or the push-back of the one
    would start inside the other's band."""
    spring_key = "limit_guard_spring_bands"
    if not doc.has("limit_guard_band"):
        if doc.has(spring_key):
            doc.fail(
                spring_key,
                "nothing without a limit_guard_band (the spring bands are the guard's)",
                doc.raw(spring_key),
            )
        return None
    band = doc.number("limit_guard_band", min=GUARD_BAND_MIN, max=GUARD_BAND_MAX, unit="rad")
    springs: list[SpringBand] = []
    refuse_another_hands_joints(doc, spring_key, hand)
    bands = doc.mapping(spring_key, default={})
    joints = {j.name: j for j in hand.joints}
    bands.expect(joints)
    # an empty mapping, of joints or of a joint's sides, was taken and did nothing (a key
    # that does nothing misleads)
    if doc.has(spring_key) and not list(bands.keys()):
        doc.fail(spring_key, "a joint's spring bands ({JOINT: {lower: rad, upper: rad}})", {})
    for name in list(bands.keys()):
        sides = bands.mapping(name)
        sides.expect(SIDES)
        own = {
            side: sides.number(side, min=GUARD_BAND_MIN, max=GUARD_BAND_MAX, unit="rad")
            for side in SIDES
            if sides.has(side)
        }
        if not own:
            bands.fail(name, "a spring band for lower, upper or both (rad)", {})
        sides.done()
        springs.extend(SpringBand(name, side, width) for side, width in own.items())
        joint = joints[name]
        width = own.get("lower", band) + own.get("upper", band)
        if width >= joint.angle_max - joint.angle_min - RANGE_ROUNDING_RAD:
            bands.fail(
                name,
                f"spring bands that leave room between them: lower + upper below the joint's "
                f"range of {joint.angle_max - joint.angle_min:.4g} rad (the guard's band "
                f"{band:g} rad for a side not given)",
                f"{width:.4g} rad",
            )
    bands.done()
    # the narrowest joint the band is for, named: the first one too narrow in the config's
    # order was, and a band made narrow enough for it was refused again for the next
    shared = [j for j in hand.joints if not bands.has(j.name)]
    if shared:
        joint = min(shared, key=lambda j: j.angle_max - j.angle_min)
        span = joint.angle_max - joint.angle_min
        if 2 * band >= span - RANGE_ROUNDING_RAD:
            # the two springs overlapped: every angle of the joint was inside a band, pushed
            # back from one limit into the other (a narrow joint's every run stopped on
            # ANGLE_LIMIT, its recipe and hand config both passing their checks)
            remedy = (
                f"or give it bands of its own in {spring_key}"
                if not fits_no_guard(span)
                # where no two bands fit, the remedy offered was refused in its turn
                else f"no two bands of {GUARD_BAND_MIN:g} rad fit in it: a recipe for this "
                "hand has no limit_guard_band"
            )
            doc.fail(
                "limit_guard_band",
                f"a band whose two sides leave room in every joint's range: below half of "
                f"{joint.name}'s {span:.4g} rad, the narrowest (in {hand.source}; {remedy})",
                band,
            )
    return GuardSettings(band, tuple(springs))


#: What the log's phase channel says when no phase of the recipe runs: the runner's status
#: (``RunStatus``) and the loop's ``NO_PHASE``. A phase of one of these names made its own
#: rows indistinguishable from them (a replay merged a phase 'end_ramp' with the end ramp and
#: lost phases 'running', 'aborted' and 'completed').
RESERVED_PHASE_NAMES = frozenset(status.value for status in RunStatus) | {"-"}


#: characters of a phase's name: it heads the status line, the summary's phase table and
#: the plots' phase bands
MAX_PHASE_NAME = 64


def check_unique_names(doc: Doc, names: list[str]) -> None:
    """Phase names are how logs, exits and provenance refer to phases: no two alike, and none
    that the log uses for something else."""
    seen: set[str] = set()
    for i, name in enumerate(names):
        if not name.strip() or name != name.strip() or len(name) > MAX_PHASE_NAME:
            # 'lift ' beside 'lift' were two phases no reader tells apart, a name of spaces
            # showed as nothing, and one of 10 000 characters filled the summary
            raise ConfigError(
                doc.file,
                f"phases[{i}].name",
                f"a phase name of 1 to {MAX_PHASE_NAME} characters, not beginning or ending "
                "with a space",
                name,
            )
        if name.strip() in RESERVED_PHASE_NAMES:
            raise ConfigError(
                doc.file,
                f"phases[{i}].name",
                "a phase name other than "
                + ", ".join(sorted(RESERVED_PHASE_NAMES))
                + " (the log says these where no phase runs)",
                name,
            )
        if name in seen:
            raise ConfigError(doc.file, f"phases[{i}].name", "a phase name not used before", name)
        seen.add(name)


def parse_objects(doc: Doc) -> tuple[RecipeObject, ...]:
    """``objects`` of a recipe or a template: 1..4 ``{name, radius}`` with distinct names that
    can prefix an estimate (letters and digits); none when the key is absent."""
    if not doc.has("objects"):
        return ()
    out: list[RecipeObject] = []
    for i, sub in enumerate(doc.mappings("objects", min_len=1, max_len=MAX_OBJECTS)):
        name = sub.string("name")
        if not OBJECT_NAME.match(name):
            sub.fail(
                "name",
                f"a name of letters and digits, starting with a letter, at most {NAME_CHARS} "
                "characters (it "
                "prefixes the object's estimates, e.g. estimate.NAME_x; the simulated "
                "scene's objects go by the same names)",
                name,
            )
        radius = sub.number("radius", min=0.0, max=MAX_OBJECT_RADIUS, min_exclusive=True, unit="m")
        if radius < MIN_OBJECT_RADIUS:
            sub.fail(
                "radius",
                f"a radius >= {MIN_OBJECT_RADIUS:g} m (the smallest object the simulated hand "
                "has; the estimator fits a radius only within ±40 % of this one)",
                radius,
            )
        sub.done()
        if any(o.name == name for o in out):
            raise ConfigError(
                doc.file, f"objects[{i}].name", "a name not used by another object", name
            )
        out.append(RecipeObject(name, radius))
    return tuple(out)


def parse_pairs(doc: Doc, objects: tuple[RecipeObject, ...]) -> tuple[Pair, ...]:
    """``pairs`` of a recipe or a template: ``[[a, b], ...]``, the pairs of objects (by name)
    whose centre line the estimator reports; each object with the next when absent. The first
    pair is the one a turn phase turns and the experiment's turn is measured on."""
    if not doc.has("pairs"):
        return consecutive_pairs(len(objects))
    names = [o.name for o in objects]
    raw = doc.raw("pairs")
    if not isinstance(raw, list) or not raw:
        doc.fail("pairs", "a non-empty list of [object, object] (names from objects)", raw)
    out: list[Pair] = []
    for i, item in enumerate(raw):
        key = f"pairs[{i}]"
        if (
            not isinstance(item, list)
            or len(item) != 2
            or not all(isinstance(n, str) and n in names for n in item)
        ):
            raise ConfigError(
                doc.file,
                key,
                f"two names of the recipe's objects ({', '.join(names) or 'none declared'})",
                item,
            )
        pair = (names.index(item[0]), names.index(item[1]))
        if pair[0] == pair[1]:
            raise ConfigError(doc.file, key, "two different objects", item)
        if pair in out or pair[::-1] in out:
            raise ConfigError(doc.file, key, "a pair not listed before", item)
        out.append(pair)
    return tuple(out)


def _parse_phase(
    doc: Doc, hand: HandConfig, estimates: tuple[str, ...], objects: tuple[RecipeObject, ...]
) -> Phase:
    name = doc.label("name")
    torques = parse_torques(doc, hand)
    # a phase lasts a loop period at least: 1e-9 s ran one tick of it, as if it had not been
    max_s = doc.number("max_s", min=hand.bus.period_s, max=MAX_PHASE_S, unit="s")
    # unsaid, the ramp fits the phase
    ramp = doc.number("ramp_s", default=min(0.1, max_s), min=0.0, max=60.0, unit="s")
    check_phase_ramp(doc, ramp, max_s, paced=False)
    on_timeout = TimeoutAction(
        doc.string("on_timeout", default="abort", choices=[a.value for a in TimeoutAction])
    )
    exits = _parse_conditions(doc, "exit", hand, estimates)
    aborts = _parse_conditions(doc, "abort", hand, estimates)
    reach = estimate_reach(hand, objects)
    for key, conditions in (("exit", exits), ("abort", aborts)):
        _refuse_never_holding(doc, key, conditions, max_s, hand, reach)
    turn_rate = parse_turn_rate(doc.mapping("turn_rate")) if doc.has("turn_rate") else None
    pose = _parse_pose(doc.mapping("pose"), hand) if doc.has("pose") else None
    joint_damping = parse_joint_damping(doc, hand.joint_names)
    fades = parse_damping_fades(doc)
    brake = parse_brake(doc.mapping("brake")) if doc.has("brake") else None
    paced = parse_paced_ramp(doc.mapping("paced_ramp")) if doc.has("paced_ramp") else None
    check_phase_ramp(doc, ramp, max_s, paced=paced is not None)
    margin = parse_torque_margin(doc, hand.joint_names)
    turn_from = doc.string("turn_from") if doc.has("turn_from") else ""
    stall = parse_stall(doc.mapping("stall")) if doc.has("stall") else None
    share = parse_exit_share(doc)
    if doc.has("exit_share") and not any(c.relative for c in exits):
        # a key that does nothing misleads, 1 too
        doc.fail(
            "exit_share",
            "a phase whose exit reads a turn (estimate.<pair>_turn): exit_share moves that "
            "exit's threshold",
            share,
        )
    reanalyse = parse_reanalyse(doc.mapping("reanalyse")) if doc.has("reanalyse") else None
    schedule = parse_schedule(doc, hand, [o.name for o in objects])
    if schedule and reanalyse is not None:
        doc.fail(
            "schedule",
            "no schedule in a phase with reanalyse (the analysis replaces the phase's torque "
            "itself)",
            f"{len(schedule)} entries",
        )
    provenance = doc.raw("provenance", {})
    if not isinstance(provenance, dict):
        doc.fail("provenance", "a mapping", provenance)
    doc.done()
    return Phase(
        name,
        torques,
        ramp,
        max_s,
        on_timeout,
        exits,
        aborts,
        provenance,
        turn_rate,
        pose,
        joint_damping,
        brake,
        paced,
        margin,
        turn_from,
        stall,
        reanalyse,
        schedule,
        joint_damping_fades=fades,
        exit_share=share,
    )


#: the most phases an ``exit_share`` may share the rest of a turn among
MAX_EXIT_SHARE = 16


def _check_rate_sense(file: str, i: int, phase: Phase) -> None:
    """A turn-rate loop's or a paced ramp's rate is signed as the wanted turn, and a phase
    whose exit waits for the first pair's turn one way wants that way: a rate signed the
    other way read the pair's turn towards the exit as going back (the loop pushed harder,
    the pace never held the ramp back), and nothing said so."""
    cond = next((c for c in phase.exits if c.relative), None)
    if cond is None or cond.index != FIRST_PAIR_TURN:
        return
    sense = phase.turn_sense()
    way = "negative" if sense is not None and sense < 0 else "positive"
    for key, loop in (("turn_rate", phase.turn_rate), ("paced_ramp", phase.paced)):
        if loop is not None and math.copysign(1.0, loop.rate) != sense:
            raise ConfigError(
                file,
                f"phases[{i}].{key}.rate_deg_s",
                f"a rate signed as the turn the phase's exit waits for ({cond.text}: {way})",
                round(math.degrees(loop.rate), 9),
            )
    if phase.reanalyse is not None and math.copysign(1.0, phase.reanalyse.turn) != sense:
        # the analysis asked for torques that turn the pair away from the phase's exit
        raise ConfigError(
            file,
            f"phases[{i}].reanalyse.turn_deg",
            f"a turn the way the phase's exit waits for ({cond.text}: {way})",
            round(math.degrees(phase.reanalyse.turn), 9),
        )


def check_exit_shares(file: str, phases: Sequence[Phase]) -> None:
    """A phase's ``exit_share`` of N needs the N - 1 phases after it to take the rest: each
    with an exit on a turn read from the same phase's start (``turn_from``, or its own start
    for a phase without one) and no share of its own. Without them the phase ended after
    1/N of the turn and nothing took up the rest (``exit_share: 16`` on the last phase
    turned it 4 degrees). From the last phase back, so that a later phase's own share is
    named at its own key, not as what an earlier one found."""
    for i, phase in reversed(list(enumerate(phases))):
        if phase.exit_share == 1:
            continue
        origin = phase.turn_from or phase.name
        sharing = phases[i + 1 : i + phase.exit_share]
        unfit = [
            f"{p.name} ({why})"
            for p, why in ((p, _why_not_sharing(p, origin, phase.turn_sense())) for p in sharing)
            if why
        ]
        missing = phase.exit_share - 1 - len(sharing)
        if missing:
            unfit.append(f"{missing} phase(s) short of the end")
        if unfit:
            raise ConfigError(
                file,
                f"phases[{i}].exit_share",
                f"{phase.exit_share - 1} phase(s) after it, each exiting on the turn since "
                f"'{origin}' began and with no exit_share of its own",
                "; ".join(unfit),
            )


def _why_not_sharing(phase: Phase, origin: str, sense: float | None) -> str:
    """Why ``phase`` cannot take a share of a turn read from ``origin``'s start, turning
    the ``sense`` way (``Phase.turn_sense``) ("": it can)."""
    if not any(c.relative for c in phase.exits):
        return "no exit on a turn"
    if (phase.turn_from or phase.name) != origin:
        return f"its turn is read from '{phase.turn_from or phase.name}'"
    if phase.exit_share > 1:
        return f"exit_share {phase.exit_share} of its own"
    if phase.turn_sense() != sense:
        return "its exit waits for the turn the other way"
    return ""


def parse_exit_share(doc: Doc) -> int:
    """``exit_share`` of a recipe's or a template's phase: how many phases, this one and
    those after it, share what is left of the turn when it begins (1, the written threshold,
    when not set)."""
    return doc.integer("exit_share", default=1, min=1, max=MAX_EXIT_SHARE)


def parse_damping_fades(doc: Doc) -> bool:
    """``joint_damping_fades`` of a recipe's or a template's phase (true when not set):
    whether the phase's injected damping fades out over the next phase's ramp or ends with
    the phase. Refused without a ``joint_damping`` to end (a key that does nothing
    misleads)."""
    if not doc.has("joint_damping_fades"):
        return True
    fades = doc.boolean("joint_damping_fades")
    if not doc.has("joint_damping"):
        doc.fail("joint_damping_fades", "a phase with joint_damping", "no joint_damping")
    return fades


def parse_schedule(
    doc: Doc, hand: HandConfig, names: Sequence[str]
) -> tuple[ScheduledTorques, ...]:
    """``schedule`` of a recipe's or a template's phase (``schema.ScheduledTorques``): a list
    of ``{when: {radius_ratio: RANGE or [RANGE, ...]}, torques: {joint: N·m}}``, a RANGE
    ``{object: NAME, min: RATIO, max: RATIO}`` (measured radius over the recipe's; either
    bound may be left out); none when the key is absent."""
    if not doc.has("schedule"):
        return ()
    out: list[ScheduledTorques] = []
    for k, entry in enumerate(doc.mappings("schedule", min_len=1, max_len=MAX_SCHEDULE)):
        when = parse_schedule_when(entry, names)
        torques = parse_torques(entry, hand)
        entry.done()
        check_unshadowed(doc, k, when, [e.when for e in out], names)
        out.append(ScheduledTorques(when, torques))
    return tuple(out)


def check_unshadowed(
    doc: Doc,
    k: int,
    when: Sequence[RadiusRatio],
    earlier: Sequence[Sequence[RadiusRatio]],
    names: Sequence[str],
) -> None:
    """Refuse ``schedule[k]`` when an earlier entry holds wherever it does: the first entry
    that holds is chosen, so it would never be (a key that does nothing misleads). A recipe's
    and a template's schedule alike, a template's before its plan runs."""
    shadow = next((j for j, e in enumerate(earlier) if _within(when, e)), None)
    if shadow is not None:
        doc.fail(
            f"schedule[{k}].when",
            f"ranges not all within schedule[{shadow}]'s (the first entry that holds is "
            f"chosen, and schedule[{shadow}] holds wherever this one does: it is never "
            "chosen)",
            description(_ranges_text(when, names)),
        )


def _within(inner: Sequence[RadiusRatio], outer: Sequence[RadiusRatio]) -> bool:
    """Whether every radius ``inner`` holds for, ``outer`` holds for too: each range of
    ``outer`` contains one of ``inner`` on the same object."""
    return all(
        any(b.object == a.object and a.low <= b.low and b.high <= a.high for b in inner)
        for a in outer
    )


def _ranges_text(ranges: Sequence[RadiusRatio], names: Sequence[str]) -> str:
    return ", ".join(f"{names[r.object]} x{r.low:g}..x{r.high:g}" for r in ranges)


def parse_schedule_when(entry: Doc, names: Sequence[str]) -> tuple[RadiusRatio, ...]:
    """The ``when`` of one ``schedule`` entry: the ranges of measured radius it is for."""
    when = entry.mapping("when")
    when.expect(["radius_ratio"])  # what a torque may be scheduled on
    raw = when.raw("radius_ratio")
    single = isinstance(raw, dict)
    items = [raw] if single else raw
    if not isinstance(items, list) or not items:
        when.fail(
            "radius_ratio",
            "a range {object: NAME, min: RATIO, max: RATIO} or a non-empty list of them",
            raw,
        )
    ranges: list[RadiusRatio] = []
    for i, item in enumerate(items):
        path = when.key_path("radius_ratio") + ("" if single else f"[{i}]")
        if not isinstance(item, dict):
            raise ConfigError(entry.file, path, "a mapping {object, min, max}", item)
        ranges.append(_parse_radius_ratio(Doc(item, entry.file, path), names, ranges))
    when.done()
    return tuple(ranges)


def _parse_radius_ratio(
    doc: Doc, names: Sequence[str], before: Sequence[RadiusRatio]
) -> RadiusRatio:
    """One range of a ``schedule``'s ``radius_ratio``: ``object``, ``min``, ``max``."""
    name = doc.string("object")
    if name not in names:
        known = ", ".join(names) or "none declared"
        doc.fail("object", f"an object of the recipe ({known})", name)
    if not (doc.has("min") or doc.has("max")):
        doc.fail("min", "a bound of the range (min, max or both)", "neither")
    low = doc.number("min", default=RADIUS_RATIO_MIN, min=RADIUS_RATIO_MIN, max=RADIUS_RATIO_MAX)
    high = doc.number("max", default=RADIUS_RATIO_MAX, min=RADIUS_RATIO_MIN, max=RADIUS_RATIO_MAX)
    if high <= low:
        # blame the bound that was written: a lone ``min`` at the top leaves no range either
        if doc.has("max"):
            doc.fail("max", f"a ratio larger than min ({low:g})", high)
        doc.fail("min", f"a ratio smaller than {high:g} (max, not written)", low)
    # the bounds may reach past what the estimator measures (an open end), the range not
    fits = (1.0 - RADIUS_RANGE, 1.0 + RADIUS_RANGE)
    if low >= fits[1] or high <= fits[0]:
        doc.fail(
            "min" if low >= fits[1] else "max",
            f"a range that meets {fits[0]:g}..{fits[1]:g}, the ratios the estimator measures "
            f"(within ±{RADIUS_RANGE:g} of the recipe's radius): this one is never met",
            low if low >= fits[1] else high,
        )
    doc.done()
    index = list(names).index(name)
    if any(r.object == index for r in before):
        doc.fail("object", "an object not ranged before in this when", name)
    return RadiusRatio(index, low, high)


def parse_stall(doc: Doc) -> TurnStall:
    """``stall`` of a recipe's or a template's phase (``schema.TurnStall``): ``turn_deg``
    (deg, > 0), the least the pair must turn within ``window_s`` (s, > 0) once the
    phase's torque is fully in, or the phase ends."""
    turn = doc.number("turn_deg", min=0.0, max=45.0, min_exclusive=True, unit="deg")
    window = doc.number("window_s", min=0.0, max=60.0, min_exclusive=True, unit="s")
    doc.done()
    return TurnStall(math.radians(turn), window)


def parse_reanalyse(doc: Doc, turn: float | None = None) -> Reanalyse:
    """``reanalyse`` of a recipe's or a template's turn phase (``schema.Reanalyse``):
    ``turn_deg`` (deg, signed; only its sense is asked of the analysis; a template's phase
    gives its own ``turn`` (rad) as the default), ``delay_s`` (s,
    from the request to the tick its result is applied), ``use`` (``analysis``, ``blend``
    or ``nearest``) and ``min_margin_N`` (N, the margin a blend or the nearest torque must
    keep, > 0)."""
    if turn is None:
        turn_deg = doc.number("turn_deg", min=-180.0, max=180.0, unit="deg")
    else:
        turn_deg = doc.number(
            "turn_deg", default=math.degrees(turn), min=-180.0, max=180.0, unit="deg"
        )
    if turn_deg == 0.0:
        doc.fail("turn_deg", "a turn other than 0 deg (its sense is what is asked for)", turn_deg)
    if (
        turn is not None
        and turn != 0.0
        and math.copysign(1.0, turn) != math.copysign(1.0, turn_deg)
    ):
        # the analysis was asked for torques that turn the pair back against its own phase
        doc.fail(
            "turn_deg",
            f"a turn the phase's way ({'negative' if turn < 0 else 'positive'}, as its own "
            f"turn of {math.degrees(turn):g} deg)",
            turn_deg,
        )
    delay = doc.number(
        "delay_s",
        default=DEFAULT_REANALYSIS_DELAY_S,
        min=0.001,
        max=MAX_REANALYSIS_DELAY_S,
        unit="s",
    )
    use = doc.string("use", default="blend", choices=list(REANALYSIS_USES))
    margin = doc.number(
        "min_margin_N", default=0.05, min=0.0, max=100.0, min_exclusive=True, unit="N"
    )
    doc.done()
    return Reanalyse(math.radians(turn_deg), delay, use, margin)


def parse_grasp_model(
    doc: Doc, objects: Sequence[RecipeObject], wanted: Sequence[int]
) -> GraspModel | None:
    """``grasp_model`` of a recipe (``schema.GraspModel``): ``masses_kg`` (one per object,
    by name), ``friction: {finger_object, object_object}``, ``gravity_m_s2`` and
    ``contact_gap_m``. Required when a phase has ``reanalyse``, refused otherwise (a key
    that does nothing misleads). ``wanted``: the indices of the phases with ``reanalyse``."""
    if not doc.has("grasp_model"):
        if wanted:
            doc.fail(
                "grasp_model",
                f"the grasp model phases[{wanted[0]}].reanalyse needs (masses_kg, friction, "
                "gravity_m_s2, contact_gap_m)",
                "nothing",
            )
        return None
    if not wanted:
        doc.fail("grasp_model", "no grasp_model: no phase has reanalyse", "a grasp_model")
    model = doc.mapping("grasp_model")
    masses_doc = model.mapping("masses_kg")
    masses = tuple(
        masses_doc.number(o.name, min=0.0, max=100.0, min_exclusive=True, unit="kg")
        for o in objects
    )
    masses_doc.done()
    friction = model.mapping("friction")
    finger_object = friction.number("finger_object", min=0.0, max=10.0, unit="")
    object_object = friction.number("object_object", min=0.0, max=10.0, unit="")
    friction.done()
    gravity = model.number("gravity_m_s2", default=9.81, min=0.0, max=100.0, unit="m/s^2")
    gap = model.number("contact_gap_m", default=0.001, min=0.0, max=0.01, unit="m")
    model.done()
    return GraspModel(masses, finger_object, object_object, gravity, gap)


def parse_torque_margin(doc: Doc, joint_names: Sequence[str]) -> PerJoint:
    """``torque_margin`` of a recipe's or a template's phase: the factor (1 when it is not set)
    the runner applies to the phase's torques, one for every joint or a mapping of each joint's
    name to its own. Why per joint: a joint that ends the phase resting in its soft-limit
    guard's band is held there by the guard's spring, not by its torque, and headroom on its
    torque only pushes it into its limit (docs/experiment.md, "Torque margin")."""
    return _per_joint(doc, "torque_margin", joint_names, 1.0, 1.0, MAX_TORQUE_MARGIN, "")


def parse_joint_damping(doc: Doc, joint_names: Sequence[str]) -> PerJoint:
    """``joint_damping`` (N·m·s/rad) of a recipe's or a template's phase: the damping the
    runner injects (0 when it is not set), one for every joint or a mapping of each joint's
    name to its own. Why per joint: a joint pressed into its guard's band by the phase's
    torque is held by the guard's stiff spring, whose push through the drive's lag is a
    negative damping a lightly damped joint cannot pay for; the other joints need none, and
    damping them changes how the pair rolls (docs/experiment.md)."""
    return _per_joint(doc, "joint_damping", joint_names, 0.0, 0.0, MAX_JOINT_DAMPING, "N·m·s/rad")


def _per_joint(
    doc: Doc,
    key: str,
    joint_names: Sequence[str],
    default: float,
    low: float,
    high: float,
    unit: str,
) -> PerJoint:
    """``key``: one number for every joint, or a mapping of each joint's name to its own (in
    the config's order), each within ``[low, high]``; ``default`` when it is not set."""
    if not isinstance(doc.raw(key, default), dict):
        return doc.number(key, default=default, min=low, max=high, unit=unit)
    _refuse_other_joints(doc, key, joint_names)
    sub = doc.mapping(key)
    sub.expect(joint_names)
    values = tuple(sub.number(n, min=low, max=high, unit=unit) for n in joint_names)
    sub.done()
    return values


def parse_brake(doc: Doc) -> TurnBrake:
    """``brake`` of a recipe's or a template's phase (``schema.TurnBrake``): ``rate_deg_s``,
    the turn rate above which it acts, and ``joint_damping`` (N·m·s/rad), reached at twice
    that rate; ``joint_rate`` (rad/s, optional), the joint speed above which it acts as
    well; ``blind_joint_rate`` (rad/s, optional), the joint speed above which it acts while
    the pair's estimate is invalid, in place of the pair's last rate."""
    rate = doc.number(
        "rate_deg_s", min=0.0, max=MAX_TURN_RATE_DEG_S, min_exclusive=True, unit="deg/s"
    )
    damping = doc.number(
        "joint_damping", min=0.0, max=MAX_JOINT_DAMPING, min_exclusive=True, unit="N·m·s/rad"
    )
    joint_rate = doc.number("joint_rate", default=0.0, min=0.0, max=MAX_JOINT_RATE, unit="rad/s")
    blind = doc.number("blind_joint_rate", default=0.0, min=0.0, max=MAX_JOINT_RATE, unit="rad/s")
    doc.done()
    return TurnBrake(math.radians(rate), damping, joint_rate, blind)


def _signed_rate(doc: Doc, sign: float | None) -> float:
    """A feedback's ``rate_deg_s`` (deg/s): a recipe writes it signed as the wanted turn; a
    template writes its magnitude, and the turn it belongs to gives the ``sign``."""
    if sign is None:
        rate = doc.number(
            "rate_deg_s", min=-MAX_TURN_RATE_DEG_S, max=MAX_TURN_RATE_DEG_S, unit="deg/s"
        )
        if rate == 0:
            doc.fail("rate_deg_s", "a non-zero rate, signed as the wanted turn", rate)
        return rate
    return sign * doc.number(
        "rate_deg_s", min=0.0, max=MAX_TURN_RATE_DEG_S, min_exclusive=True, unit="deg/s"
    )


def check_phase_ramp(doc: Doc, ramp: float, max_s: float, paced: bool) -> None:
    """A phase's ``ramp_s`` (a recipe's, a template's: ``handctl.planning.template``) fits
    it: no longer than its ``max_s`` (the phase ended, on its timeout at the latest, before
    its torques were in: a recipe that said 0.5 N·m sent 0.004 and completed), and, on a
    ``paced`` phase, longer than 0 (the pace moves at the ramp's speed)."""
    if ramp > max_s + 1e-9:
        doc.fail(
            "ramp_s",
            f"a ramp no longer than the phase's max_s ({max_s:g} s): the phase never reaches "
            "its torques",
            ramp,
        )
    if paced and ramp <= 0:
        doc.fail("ramp_s", "a ramp longer than 0 s (the paced_ramp moves at its speed)", ramp)


def parse_paced_ramp(doc: Doc, sign: float | None = None) -> PacedRamp:
    """``paced_ramp`` of a phase (``schema.PacedRamp``): ``rate_deg_s`` (signed, the wanted
    direction; a template gives its magnitude and the turn's sign as ``sign``), ``reach``
    (the furthest fraction along the segment, 1 by default) and ``back`` (how many times the
    ramp's speed it may go back at, 2 by default), ``joint_rate`` (rad/s, the fastest a
    joint may move before the torque goes back as well; 0, the default: the pair's rate
    alone) and ``blind_joint_rate`` (rad/s, the same while the pair's estimate is invalid,
    in place of the pair's last rate; 0, the default: the last rate holds)."""
    rate = _signed_rate(doc, sign)
    reach = doc.number("reach", default=1.0, min=1.0, max=MAX_REACH)
    back = doc.number("back", default=2.0, min=0.0, max=MAX_BACK, min_exclusive=True)
    joint_rate = doc.number("joint_rate", default=0.0, min=0.0, max=MAX_JOINT_RATE, unit="rad/s")
    blind = doc.number("blind_joint_rate", default=0.0, min=0.0, max=MAX_JOINT_RATE, unit="rad/s")
    depth = doc.number("limit_depth", default=0.0, min=0.0, max=MAX_LIMIT_DEPTH)
    turn_back = doc.number("turn_back_deg", default=0.0, min=0.0, max=90.0, unit="deg")
    doc.done()
    return PacedRamp(
        math.radians(rate), reach, back, joint_rate, blind, depth, math.radians(turn_back)
    )


def parse_turn_rate(doc: Doc, sign: float | None = None) -> TurnRate:
    """``turn_rate`` of a phase (``schema.TurnRate``): ``rate_deg_s`` (signed, the wanted
    direction; a template gives its magnitude and the turn's sign as ``sign``), ``scale``
    ``[min, max]``, ``gain`` and ``integral_per_s``."""
    rate = _signed_rate(doc, sign)
    scale = doc.numbers("scale", length=2, min=0.0, max=MAX_SCALE)
    if not 0 < scale[0] <= 1.0 <= scale[1]:
        doc.fail(
            "scale", "[min, max] with 0 < min <= 1 <= max (1 is the planned torque)", list(scale)
        )
    gain = doc.number("gain", default=0.5, min=0.0, max=10.0)
    integral = doc.number("integral_per_s", default=2.0, min=0.0, max=100.0, unit="1/s")
    doc.done()
    return TurnRate(math.radians(rate), scale[0], scale[1], gain, integral)


def _parse_pose(doc: Doc, hand: HandConfig) -> PoseHold:
    refuse_another_hands_joints(doc, "angles", hand)
    angles = _joint_angles(doc.mapping("angles"), hand)
    stiffness = doc.number("stiffness", min=0.0, max=100.0, unit="N·m/rad")
    # bounded as injected joint_damping is (10 N·m·s/rad was taken, and 0.5 already drove a
    # joint onto its limit); it acts on the 10 ms low-passed velocity, more lag than the
    # fitted one injected damping uses, so it rings at less (0.1 on the nominal hand's
    # distal joints): no bound is one of stability without the joints' inertia, which a hand
    # config does not carry, and a run whose command rings says so (``safety.chatter``)
    damping = doc.number("damping", default=0.0, min=0.0, max=MAX_JOINT_DAMPING, unit="N·m·s/rad")
    integral = _parse_integral(doc.mapping("integral"), hand) if doc.has("integral") else None
    doc.done()
    return PoseHold(angles, stiffness, damping, integral)


def _joint_angles(sub: Doc, hand: HandConfig) -> tuple[float, ...]:
    """Every joint's angle by name, within its limits (a pose). A misspelt joint is named as
    such: the first joint not read yet was said to be missing instead."""
    sub.expect(hand.joint_names)
    angles = [
        sub.number(joint.name, min=joint.angle_min, max=joint.angle_max, unit="rad")
        for joint in hand.joints
    ]
    sub.done()
    return tuple(angles)


def _parse_integral(doc: Doc, hand: HandConfig) -> PoseIntegral:
    refuse_another_hands_joints(doc, "rest", hand)
    rest = _joint_angles(doc.mapping("rest"), hand)
    gain, bound, still = parse_integral_gains(doc, hand)
    doc.done()
    return PoseIntegral(rest, gain, bound, still, joint_fingers(hand))


def joint_fingers(hand: HandConfig) -> tuple[int, ...]:
    """Each joint's finger (its index in the config), in the config's joint order."""
    return tuple(k for k, finger in enumerate(hand.fingers) for _ in finger.joints)


def parse_integral_gains(doc: Doc, hand: HandConfig) -> tuple[float, float, float]:
    """A pose hold's ``integral``: ``gain`` (N·m/(rad·s)), ``max`` (N·m) and ``still_rate``
    (rad/s), shared by a recipe and a template (whose ``rest`` the plan computes)."""
    gain = doc.number("gain", min=0.0, max=100.0, min_exclusive=True, unit="N·m/(rad·s)")
    # no more than the weakest joint's tau_max, so the bound means the same on every joint
    cap = min(j.tau_max for j in hand.joints)
    bound = doc.number("max", min=0.0, max=cap, min_exclusive=True, unit="N·m")
    still = doc.number("still_rate", min=0.0, max=10.0, min_exclusive=True, unit="rad/s")
    return gain, bound, still


def parse_torques(doc: Doc, hand: HandConfig) -> tuple[float, ...]:
    """``torques`` of a phase or a ``schedule`` entry: joint name to N·m, or a list in the
    config's joint order."""
    names = hand.joint_names
    raw = doc.raw("torques")
    if isinstance(raw, list):
        return doc.numbers("torques", length=len(names), unit="N·m")
    if not isinstance(raw, dict):
        doc.fail(
            "torques", f"a mapping of joint name to N·m, or a list of {len(names)} numbers", raw
        )
    refuse_another_hands_joints(doc, "torques", hand)
    sub = doc.mapping("torques")
    sub.expect(names)
    values = tuple(sub.number(n, unit="N·m") for n in names)
    sub.done()
    return values


def refuse_another_hands_joints(doc: Doc, key: str, hand: HandConfig) -> None:
    """A ``ConfigError`` when ``key`` is a mapping by joint name of which not one is a joint
    of ``hand``: the file was written for another hand, which a "missing key" and a guessed
    misspelling of the hand's first joint did not say."""
    _refuse_other_joints(doc, key, hand.joint_names, f"the hand {hand.name}", f": {hand.source}")


def _refuse_other_joints(
    doc: Doc, key: str, names: Sequence[str], whose: str = "the hand", where: str = ""
) -> None:
    """``refuse_another_hands_joints`` for a mapping keyed by ``names``."""
    raw = doc.raw(key, None)
    if isinstance(raw, dict) and raw and not set(raw) & set(names):
        doc.fail(
            key,
            f"keys that are joints of {whose} ({_some(list(names))}{where}; written for "
            "another hand? give its config with --hand)",
            f"joints {_some([str(k) for k in raw])}",
        )


def _some(names: Sequence[str], shown: int = 4) -> str:
    """The first few of ``names`` and how many more: a hand of 15 fingers of 6 joints in a
    message is a screenful."""
    more = len(names) - shown
    return ", ".join(names[:shown]) + (f" and {more} more" if more > 0 else "")


def _parse_conditions(
    doc: Doc, key: str, hand: HandConfig, estimates: tuple[str, ...]
) -> tuple[Condition, ...]:
    raw = doc.raw(key, [])
    if isinstance(raw, str):
        raw = [raw]
    if not isinstance(raw, list):
        doc.fail(key, "a list of conditions", raw)
    out = []
    sub = Doc({}, doc.file, doc.key_path(key))
    for i, text in enumerate(raw):
        if not isinstance(text, str):
            sub.fail(i, "a condition string", text)
        parsed = parse_condition(text, hand.joint_names, estimates)
        if isinstance(parsed, str):
            sub.fail(i, parsed, text)
        out.append(parsed)
    return tuple(out)


#: rad, the most a phase's exit or abort may wait for the pair to turn: a whole revolution
MAX_PHASE_TURN = 2.0 * math.pi


def estimate_reach(hand: HandConfig, objects: Sequence[RecipeObject]) -> float:
    """m, how far from the palm frame's origin an object's estimated centre can be: the
    estimator places an object only where finger links (and the other objects) cage it, so
    within the farthest finger's reach, its link's thickness and the objects' diameters."""
    fingers = max(
        (
            math.hypot(f.base_x, f.base_y) + sum(j.link_length + j.half_thickness for j in f.joints)
            for f in hand.fingers
        ),
        default=0.0,
    )
    return fingers + 2.0 * sum(o.radius for o in objects)


def _refuse_never_holding(
    doc: Doc,
    key: str,
    conditions: Sequence[Condition],
    max_s: float,
    hand: HandConfig,
    reach: float = math.inf,
) -> None:
    """A condition that cannot hold before the phase ends is refused: it loaded and ran as
    nothing, the phase timing out as if the exit had not been written. ``reach`` (m): how
    far an object's estimated centre can be (``estimate_reach``)."""
    sub = Doc({}, doc.file, doc.key_path(key))
    for i, cond in enumerate(conditions):
        why = _never_holds(cond, max_s, hand, reach)
        if why:
            sub.fail(
                i,
                f"a condition that can hold within the phase's max_s ({max_s:g} s): {why}",
                cond.text,
            )


def _never_holds(cond: Condition, max_s: float, hand: HandConfig, reach: float) -> str:
    """Why ``cond`` never holds in a phase of ``max_s`` on ``hand`` ('' if it may), an
    object's estimated centre within ``reach`` (m) of the palm frame's origin."""
    # a phase is judged from the tick after it began: its time is a loop period at least
    first = hand.bus.period_s
    above = cond.op in (">", ">=")
    timeout = _phase_tick(first, max_s, strictly=False)  # exits are judged in it first
    if cond.kind is SignalKind.TIME and above:
        begins = _phase_tick(first, cond.value, strictly=cond.op == ">")
    else:
        begins = 1
    if _held_from(first, begins, cond.hold_s) > timeout:
        if begins > 1:  # a time that comes too late, not a hold too long
            return "the phase times out first"
        return (
            f"held for {cond.hold_s:g} s from its second tick ({first * 1e3:g} ms) at the "
            "earliest, it outlasts the phase"
        )
    if (
        cond.kind is SignalKind.TIME
        and not above
        and (cond.value < first or (cond.op == "<" and cond.value == first))
    ):
        return f"a phase's time is never below one loop period ({first * 1e3:g} ms)"
    signal = cond.text.split()[0]
    # a line's direction is in (-π, π] (its turn, ``_line_turn``, is the unwrapped one)
    past_pi = cond.value > math.pi or (cond.op == ">" and cond.value == math.pi)
    if (
        cond.kind is SignalKind.ESTIMATE
        and signal.endswith("_line_angle")
        and ((above and past_pi) or (not above and cond.value <= -math.pi))
    ):
        return (
            f"{signal} is a direction in (-π, π] rad; its turn, unwrapped, is "
            f"{signal.removesuffix('_angle')}_turn"
        )
    if (
        cond.relative
        and abs(cond.value) > MAX_PHASE_TURN
        and ((above and cond.value > 0) or (not above and cond.value < 0))
    ):
        # the unwrapped turn can pass π, and ``line_angle``'s check does not catch 45 or 180
        # written in degrees: 45 rad is seven turns of the pair in one phase
        return (
            f"{signal} is the pair's turn since the phase began, in rad: a phase that turns it "
            f"more than a whole revolution ({MAX_PHASE_TURN:.4g} rad) is a turn written in "
            "degrees (or a phase to split)"
        )
    if (
        cond.kind is SignalKind.ESTIMATE
        and signal.endswith(tuple(f"_{s}" for s in OBJECT_ESTIMATES))
        and ((above and cond.value >= reach) or (not above and cond.value <= -reach))
    ):
        return (
            f"{signal} is an object's centre in the palm's frame, never {reach:.3g} m or more "
            "from its origin (the fingers' reach and the objects' diameters)"
        )
    if cond.kind is SignalKind.TDT:
        joint = hand.joints[cond.index]
        most = joint.device_tau_max
        if (above and cond.value > most) or (not above and cond.value < -most):
            return f"{joint.name}'s torque never passes its device_tau_max ({most:g} N·m)"
    if cond.kind is SignalKind.ANGLE:
        # the soft limit itself is inside (a joint at it is allowed, ``angle_violations``):
        # '> limit' holds only past it, '>= limit' at it
        joint = hand.joints[cond.index]
        hi, lo = joint.angle_max, joint.angle_min
        if above and (cond.value > hi or (cond.op == ">" and cond.value == hi)):
            return f"{joint.name} past its soft limit {hi:g} rad is a safety stop"
        if not above and (cond.value < lo or (cond.op == "<" and cond.value == lo)):
            return f"{joint.name} past its soft limit {lo:g} rad is a safety stop"
    return ""


def hold_outlasts(period_s: float, hold_s: float, max_s: float) -> bool:
    """Whether a condition held for ``hold_s`` from a phase's second tick at the earliest
    outlasts a phase of ``max_s`` (``_never_holds``): a template's turn exit is refused so
    before its plan, where its recipe was refused after it."""
    return _held_from(period_s, 1, hold_s) > _phase_tick(period_s, max_s, strictly=False)


def _elapsed(period_s: float, ticks: int) -> float:
    """s, a phase's time ``ticks`` ticks after it began, as the runner reads it: whole
    nanoseconds a period, rounded to the microsecond."""
    return round(ticks * round(period_s * 1e9) * 1e-9, 6)


def _phase_tick(period_s: float, seconds: float, *, strictly: bool) -> int:
    """The first tick of a phase (1: the first judged) whose time is at least ``seconds``
    (past it, ``strictly``)."""
    tick = max(1, math.floor(seconds / period_s) - 1)
    while not (
        _elapsed(period_s, tick) > seconds if strictly else _elapsed(period_s, tick) >= seconds
    ):
        tick += 1
    return tick


def _held_from(period_s: float, begins: int, hold_s: float) -> int:
    """The tick at which a condition true from tick ``begins`` on has held ``hold_s``."""
    tick = begins + max(0, math.floor(hold_s / period_s) - 1)
    while _elapsed(period_s, tick) - _elapsed(period_s, begins) < hold_s - 1e-12:
        tick += 1
    return tick


def check_against_hand(recipe: Recipe, hand: HandConfig) -> None:
    """Refuse torques over tau_max and ramps faster than the rate limit, naming everything."""
    names = hand.joint_names
    tau_max = np.array([j.tau_max for j in hand.joints])
    rate = np.array([j.rate_limit for j in hand.joints])
    # every torque a phase may hold (its own and its schedule's), and every ramp between one
    # of the previous phase's and one of this phase's: which one runs is chosen on the hand
    previous = [np.zeros(len(names))]
    for i, phase in enumerate(recipe.phases):
        keys = [f"phases[{i}].torques"] + [
            f"phases[{i}].schedule[{k}].torques" for k in range(len(phase.schedule))
        ]
        # what the runner holds: the torques times the phase's torque_margin (before, the
        # margin got around both checks and the supervisor clamped what it asked for)
        margin = np.broadcast_to(np.asarray(phase.torque_margin, dtype=float), tau_max.shape)
        candidates = [np.array(phase.torques) * margin] + [
            np.array(s.torques) * margin for s in phase.schedule
        ]
        for key, torques in zip(keys, candidates, strict=True):
            for j in np.flatnonzero(np.abs(torques) > tau_max):
                by = (
                    f", the torque times the phase's torque_margin ({margin[j]:g})"
                    if margin[j] != 1.0
                    else ""
                )
                raise ConfigError(
                    recipe.source,
                    f"{key}.{names[j]}",
                    f"|τ| <= {tau_max[j]:g} N·m (tau_max of {names[j]} in {hand.source}) in "
                    f"phase '{phase.name}'{by}",
                    round(float(torques[j]), 9),
                )
            _check_feedback_reach(recipe, hand, i, key, torques, previous, tau_max)
            # a schedule entry chosen once the phase has begun is ramped to again, from where
            # the phase's own ramp had got: anywhere between the previous torque and its own
            starts = [*previous, candidates[0]] if "schedule" in key else previous
            for start in starts:
                into = f"into phase '{phase.name}'" + (f" ({key})" if "schedule" in key else "")
                check_ramp(
                    recipe.source, hand, f"phases[{i}].ramp_s", into, start, torques,
                    phase.ramp_s, rate,
                )  # fmt: skip
                if phase.paced is not None and phase.paced.back > 1.0:
                    # going back along the segment at ``back`` times the ramp's speed
                    check_ramp(
                        recipe.source, hand, f"phases[{i}].paced_ramp.back",
                        f"{into}, going back at {phase.paced.back:g} times the ramp's speed",
                        start, torques, phase.ramp_s / phase.paced.back, rate,
                    )  # fmt: skip
        previous = candidates
    for start in previous:
        check_ramp(
            recipe.source,
            hand,
            "end_ramp_s",
            "back to zero after the last phase",
            start,
            np.zeros(len(names)),
            recipe.end_ramp_s,
            rate,
        )


def _check_feedback_reach(
    recipe: Recipe,
    hand: HandConfig,
    i: int,
    key: str,
    torques: np.ndarray,
    previous: Sequence[np.ndarray],
    tau_max: np.ndarray,
) -> None:
    """Refuse a feedback that takes a phase's torque past tau_max: a turn-rate loop's largest
    scale, a paced ramp's ``reach`` beyond the phase's torque along the segment from the
    previous phase's. The supervisor clamped such a torque joint by joint, which changed the
    direction of the torque the analysis planned, and nothing said so."""
    phase = recipe.phases[i]
    names = hand.joint_names
    reached: list[tuple[str, float, str, np.ndarray]] = []
    if phase.turn_rate is not None and phase.turn_rate.scale_max != 1.0:
        scale = phase.turn_rate.scale_max
        how = f"times turn_rate's largest scale ({scale:g})"
        reached.append(("turn_rate.scale", scale, how, torques * scale))
    if phase.paced is not None and phase.paced.reach > 1.0:
        reach = phase.paced.reach
        how = f"{reach:g} of the way along the segment from the previous phase's torque"
        reached += [
            ("paced_ramp.reach", reach, how, start + reach * (torques - start))
            for start in previous
        ]
    for what, value, how, values in reached:
        for j in np.flatnonzero(np.abs(values) > tau_max * (1 + 1e-9)):
            raise ConfigError(
                recipe.source,
                f"phases[{i}].{what}",
                f"a feedback that keeps |τ| <= {tau_max[j]:g} N·m (tau_max of {names[j]} in "
                f"{hand.source}) in phase '{phase.name}': {key}.{names[j]} {how} is "
                f"{float(values[j]):.4g} N·m",
                value,
            )


def check_ramp(
    source: str,
    hand: HandConfig,
    key: str,
    what: str,
    start: np.ndarray,
    end: np.ndarray,
    ramp_s: float,
    rate: np.ndarray,
) -> None:
    """Refuse (naming ``source`` and ``key``) a ramp from ``start`` to ``end`` (N·m) over
    ``ramp_s`` faster than a joint's rate limit ``rate`` (N·m/s)."""
    step = np.abs(end - start)
    for j in range(len(step)):
        if step[j] == 0:
            continue
        need = step[j] / ramp_s if ramp_s > 0 else float("inf")
        if need > rate[j] * (1 + 1e-9):
            name = hand.joint_names[j]
            raise ConfigError(
                source,
                key,
                f"a ramp of at least {step[j] / rate[j]:.3g} s {what}: {name} moves "
                f"{step[j]:.3g} N·m and its rate limit is {rate[j]:g} N·m/s",
                ramp_s,
            )
