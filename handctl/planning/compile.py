"""``handctl plan``: from a template and a hand config to a compiled recipe with provenance.

Phase by phase, in order, because each phase's grasp is where the phases before it left the
hand:

1. the nominal model's state where the phase begins is the phase's grasp configuration;
2. the analysis (``handctl.analysis.plan_torques``) gives, for ``lift`` and ``turn`` phases,
   the torque within ±tau_max with the largest robust margin for the wanted motion, or says
   why there is none;
3. the search (``search.cem``) starts from that torque, the template's seed and the previous
   phase's torque, and scores candidates on every perturbed model still holding the objects;
4. every model runs the chosen phase to its exit, which gives the next phase's starting
   states; a model that fails (drop, soft limit) is left out of the later phases and
   counted.

With a ``replan.Base``, the phases before its ``start`` take their torques from that
compiled recipe instead of steps 2 and 3 (step 4 runs as ever), and keep its provenance.

Everything is deterministic given the template (its seed) and the hand config, so the
compiled recipe is reproducible with one command; the provenance of each phase records its
inputs (kind, wanted motion, grasp contacts), the analysis' margin or reason, the search's
score and where the chosen torque came from, and the hand-config hash.
"""

from __future__ import annotations

import math
from collections import Counter
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from handctl.analysis.model import AnalysisError
from handctl.analysis.planner import plan_torques
from handctl.config import HandConfig
from handctl.convention import HOLD_S, LIFT_HEIGHT, is_manipulation
from handctl.errors import ConfigError, escaped
from handctl.executor import WorkPool, open_pool
from handctl.online.recipes.loader import check_against_hand, joint_fingers, parse_recipe
from handctl.online.recipes.schema import (
    Condition,
    PacedRamp,
    PerJoint,
    Phase,
    PoseHold,
    PoseIntegral,
    ScheduledTorques,
    TimeoutAction,
    consecutive_pairs,
    parse_condition,
)
from handctl.planning.episode import Episode, PhaseOutcome, Snapshot
from handctl.planning.grasp import GraspSnapshot, fixed_directions, grasp_of, turn_directions
from handctl.planning.models import Model, model_set, sized_models
from handctl.planning.phase_task import PhaseTask, World, episode_of, run_phase_task, snapshot_of
from handctl.planning.replan import Base
from handctl.planning.search import (
    GUARDED_LIMIT_FAIL,
    GUARDED_LIMIT_MARGIN,
    LIMIT_FAIL,
    LIMIT_MARGIN,
    MIN_TURN_FRACTION,
    TUMBLE_FAIL_FACTOR,
    Budget,
    Candidate,
    SearchResult,
    cem,
    hold_scorer,
    turn_scorer,
    written_torques,
)
from handctl.planning.template import (
    PlannedSchedule,
    Template,
    TemplatePhase,
    no_ramp_left,
    ramp_intervals,
)
from handctl.progress import Progress
from handctl.schema import dump_yaml, parse_yaml
from handctl.sim.params import SimParams, parse_sim

#: how far into extension (a fraction of tau_max) a random seed may go
SEED_EXTENSION = 0.3


@dataclass
class AnalysisRecord:
    """The analysis of one phase, for the provenance and the plot."""

    snapshot: GraspSnapshot | None
    directions: dict[str, list[float]]
    found: bool
    torques: tuple[float, ...] | None
    margin: float
    reason: str

    def provenance(self) -> dict[str, Any]:
        out: dict[str, Any] = {"found": self.found}
        if self.snapshot is not None:
            out.update(self.snapshot.describe())
        if self.directions:
            out["directions"] = {k: [round(x, 4) for x in v] for k, v in self.directions.items()}
        if self.found and self.torques is not None:
            out["margin_N"] = round(self.margin, 4)
            out["torques"] = list(written_torques(self.torques))
        else:
            out["reason"] = self.reason
        return out


@dataclass
class PhasePlan:
    spec: TemplatePhase
    phase: Phase
    analysis: AnalysisRecord | None
    chosen: Candidate | None
    outcomes: list[PhaseOutcome]
    provenance: dict[str, Any] = field(default_factory=dict)
    #: per model, whether the phase did its job (``_jobs_done``); None: a free phase
    done: list[bool] | None = None
    #: what the phase left undone on every model (``_job_left_undone``); None: it did its
    #: job on one at least, or it has none
    undone: str | None = None
    #: where the template's ramps held the phase's search short of its seeds (``ramp_cuts``)
    ramp_cuts: tuple[RampCut, ...] = ()


@dataclass
class PlanResult:
    template: Template
    hand: HandConfig
    phases: list[PhasePlan]
    models: list[Model]
    template_digest: str
    base: Base | None = None

    def recipe_document(self) -> dict[str, Any]:
        """The compiled recipe as a YAML-ready mapping (the loader's format)."""
        t = self.template
        return {
            "recipe": t.recipe,
            "description": t.description,
            "compiled": True,
            "hand_config_hash": self.hand.config_hash,
            "planned_from": {
                "template": Path(t.source).name,
                "template_sha256": self.template_digest,
                "models": [
                    {"index": m.index, **{k: round(v, 4) for k, v in m.scales.items()}}
                    for m in self.models
                ],
                **(self.base.describe() if self.base is not None else {}),
                # a failed plan's recipe says so itself: `handctl run` warns of it
                **(
                    {"failed_phases": {p.phase.name: p.undone for p in failed}}
                    if (failed := [p for p in self.phases if p.undone is not None])
                    else {}
                ),
            },
            "objects": [{"name": o.name, "radius": o.radius} for o in t.objects],
            **(
                {"pairs": [[t.objects[a].name, t.objects[b].name] for a, b in t.pairs]}
                if t.pairs != consecutive_pairs(len(t.objects))
                else {}
            ),
            "end_ramp_s": t.end_ramp_s,
            **(t.limit_guard.document() if t.limit_guard is not None else {}),
            **({"min_total_turn_deg": t.min_total_turn_deg} if t.min_total_turn_deg > 0 else {}),
            **({"grasp_model": _grasp_model_document(t)} if t.grasp_model is not None else {}),
            "phases": [_phase_document(p, self.hand) for p in self.phases],
        }


def _grasp_model_document(template: Template) -> dict[str, Any]:
    model = template.grasp_model
    assert model is not None
    return {
        "masses_kg": {o.name: m for o, m in zip(template.objects, model.masses, strict=True)},
        "friction": {
            "finger_object": model.finger_object_mu,
            "object_object": model.object_object_mu,
        },
        "gravity_m_s2": model.gravity,
        "contact_gap_m": model.contact_gap,
    }


def _paced_document(paced: PacedRamp) -> dict[str, Any]:
    """A phase's ``paced_ramp`` as a recipe writes it: the optional keys only when set."""
    doc: dict[str, Any] = {
        "rate_deg_s": round(math.degrees(paced.rate), 6),
        "reach": paced.reach,
        "back": paced.back,
    }
    if paced.joint_rate > 0.0:
        doc["joint_rate"] = paced.joint_rate
    if paced.blind_joint_rate > 0.0:
        doc["blind_joint_rate"] = paced.blind_joint_rate
    if paced.limit_depth > 0.0:
        doc["limit_depth"] = paced.limit_depth
    if paced.turn_back > 0.0:
        doc["turn_back_deg"] = round(math.degrees(paced.turn_back), 6)
    return doc


def _schedule_document(
    phase: Phase, hand: HandConfig, objects: Sequence[str]
) -> list[dict[str, Any]]:
    """A phase's ``schedule`` as a recipe writes it (``loader.parse_schedule`` reads it)."""
    out: list[dict[str, Any]] = []
    for entry in phase.schedule:
        ranges = [{"object": objects[r.object], "min": r.low, "max": r.high} for r in entry.when]
        out.append(
            {
                "when": {"radius_ratio": ranges},
                "torques": dict(zip(hand.joint_names, written_torques(entry.torques), strict=True)),
            }
        )
    return out


def _per_joint(value: PerJoint, hand: HandConfig) -> float | dict[str, float]:
    """A value given once for every joint or per joint, written back as it was given (a
    mapping of joint names in the config's order, or the one number)."""
    if isinstance(value, tuple):
        return dict(zip(hand.joint_names, value, strict=True))
    return value


def _pose_document(pose: PoseHold, hand: HandConfig) -> dict[str, Any]:
    doc: dict[str, Any] = {
        "angles": dict(zip(hand.joint_names, pose.angles, strict=True)),
        "stiffness": pose.stiffness,
        "damping": pose.damping,
    }
    if pose.integral is not None:
        doc["integral"] = {
            "rest": dict(zip(hand.joint_names, pose.integral.rest, strict=True)),
            "gain": pose.integral.gain,
            "max": pose.integral.max,
            "still_rate": pose.integral.still_rate,
        }
    return doc


def _switching(spec: TemplatePhase) -> dict[str, Any]:
    """A turn phase's switching on the pair's measured position, as the recipe carries it:
    the episodes exit on the phase's own turn, the recipe on the turn since ``turn_from``,
    shared out by the runner with an ``exit_share``."""
    doc: dict[str, Any] = {
        "turn_from": spec.turn_from,
        "exit": [spec.recipe_exit_condition()],
    }
    if spec.exit_share > 1:
        doc["exit_share"] = spec.exit_share
    return doc


def _phase_document(plan: PhasePlan, hand: HandConfig) -> dict[str, Any]:
    phase = plan.phase
    doc: dict[str, Any] = {
        "name": phase.name,
        "torques": dict(zip(hand.joint_names, written_torques(phase.torques), strict=True)),
        "ramp_s": phase.ramp_s,
        "max_s": phase.max_s,
        "on_timeout": phase.on_timeout.value,
    }
    if phase.exits:
        doc["exit"] = [c.text for c in phase.exits]
    if plan.spec.turn_from:
        doc.update(_switching(plan.spec))
    if phase.stall is not None:
        doc["stall"] = {
            "turn_deg": round(math.degrees(phase.stall.turn), 6),
            "window_s": phase.stall.window_s,
        }
    if phase.reanalyse is not None:
        doc["reanalyse"] = {
            "turn_deg": round(math.degrees(phase.reanalyse.turn), 6),
            "delay_s": phase.reanalyse.delay_s,
            "use": phase.reanalyse.use,
            "min_margin_N": phase.reanalyse.min_margin,
        }
    if phase.schedule:
        doc["schedule"] = _schedule_document(phase, hand, plan.spec.object_names)
    if phase.turn_rate is not None:
        loop = phase.turn_rate
        doc["turn_rate"] = {
            "rate_deg_s": round(math.degrees(loop.rate), 6),
            "scale": [loop.scale_min, loop.scale_max],
            "gain": loop.gain,
            "integral_per_s": loop.integral,
        }
    if phase.pose is not None:
        doc["pose"] = _pose_document(phase.pose, hand)
    if phase.joint_damping != 0.0:
        doc["joint_damping"] = _per_joint(phase.joint_damping, hand)
        if not phase.joint_damping_fades:
            doc["joint_damping_fades"] = False
    if phase.brake is not None:
        doc["brake"] = {
            "rate_deg_s": round(math.degrees(phase.brake.rate), 6),
            "joint_damping": phase.brake.damping,
        }
        if phase.brake.joint_rate > 0.0:
            doc["brake"]["joint_rate"] = phase.brake.joint_rate
        if phase.brake.blind_joint_rate > 0.0:
            doc["brake"]["blind_joint_rate"] = phase.brake.blind_joint_rate
    if phase.paced is not None:
        doc["paced_ramp"] = _paced_document(phase.paced)
    if phase.torque_margin != 1.0:
        doc["torque_margin"] = _per_joint(phase.torque_margin, hand)
    doc["provenance"] = plan.provenance
    return doc


def _analyse(episode: Episode, spec: TemplatePhase, hand: HandConfig) -> AnalysisRecord | None:
    if spec.kind not in ("lift", "turn"):
        return None
    snap = grasp_of(episode.plant, hand)
    grasp = snap.grasp
    if not grasp.finger_contacts:
        return AnalysisRecord(
            snap, {}, False, None, -math.inf, "no finger touches an object in this configuration"
        )
    directions = (
        fixed_directions(grasp, spec.move)
        if spec.kind == "lift"
        else turn_directions(grasp, spec.turn)
    )
    listed = {k: [float(x) for x in v] for k, v in directions.items()}
    try:
        plan = plan_torques(grasp, directions, [j.tau_max for j in hand.joints])
    except AnalysisError as exc:
        return AnalysisRecord(snap, listed, False, None, -math.inf, str(exc))
    if not plan.found:
        return AnalysisRecord(snap, listed, False, None, plan.margin, plan.reason)
    return AnalysisRecord(snap, listed, True, plan.tau, plan.margin, "")


def _flexion_seed(hand: HandConfig, rng: np.random.Generator) -> tuple[float, ...]:
    """A torque drawn uniformly from the flexion box: every joint between ``-SEED_EXTENSION``
    and 1 times its tau_max in the direction that curls its finger inward (the sign of the
    finger's base side: fingers left of the palm's middle flex counter-clockwise). Mostly
    flexion, because an enveloping grasp is held by flexion; some extension, because a finger
    that gives way is how room is made for the pair to turn. Seeds that explore the grasp's
    own family of motions, with no knowledge of the task."""
    xs = [f.base_x for f in hand.fingers]
    mid = (min(xs) + max(xs)) / 2
    out: list[float] = []
    for finger in hand.fingers:
        sign = 1.0 if finger.base_x <= mid else -1.0
        out += [sign * float(rng.uniform(-SEED_EXTENSION, 1.0)) * j.tau_max for j in finger.joints]
    return tuple(out)


def _advance_to_contact(episode: Episode, phase: Phase) -> None:
    """Run ``phase`` on ``episode`` until some finger touches an object (or it ends)."""

    def touching() -> bool:
        return bool(grasp_of(episode.plant, episode.hand).grasp.finger_contacts)

    episode.run_phase(phase, stop=touching)


def _written_schedule(spec: TemplatePhase) -> tuple[ScheduledTorques, ...]:
    """The entries of ``spec``'s schedule that give their torques (the planned ones are the
    plan's to fill in)."""
    return tuple(e for e in spec.schedule if isinstance(e, ScheduledTorques))


def _compiled_phase(
    spec: TemplatePhase,
    torques: tuple[float, ...],
    hand: HandConfig,
    pose: PoseHold | None = None,
    schedule: tuple[ScheduledTorques, ...] | None = None,
) -> Phase:
    exits: tuple[Condition, ...] = ()
    if spec.kind == "turn":
        parsed = parse_condition(spec.exit_condition(), hand.joint_names, spec.estimates)
        assert not isinstance(parsed, str), parsed
        exits = (parsed,)
    rounded = written_torques(torques)
    return Phase(
        spec.name,
        rounded,
        spec.ramp_s,
        spec.max_s,
        TimeoutAction.NEXT,
        exits,
        (),
        turn_rate=spec.turn_rate,
        pose=pose,
        joint_damping=spec.joint_damping,
        joint_damping_fades=spec.joint_damping_fades,
        brake=spec.brake,
        paced=spec.paced,
        torque_margin=spec.torque_margin,
        stall=spec.stall,
        reanalyse=spec.reanalyse,
        schedule=_written_schedule(spec) if schedule is None else schedule,
    )


def _pose_of(episode: Episode, spec: TemplatePhase, hand: HandConfig) -> PoseHold:
    """The pose a free phase with a pose hold ends in: where its torques alone leave the
    nominal hand (rounded to 0.1 mrad), so the hold brings every hand to the nominal's pose."""
    assert spec.seed is not None and spec.pose_stiffness is not None
    episode.run_phase(_compiled_phase(spec, spec.seed, hand))
    return PoseHold(_rounded_angles(episode), spec.pose_stiffness, spec.pose_damping)


def _with_rest(episode: Episode, spec: TemplatePhase, hand: HandConfig, hold: PoseHold) -> PoseHold:
    """``hold`` with the template's integral, whose rest pose is where the nominal hand
    settles under the hold (spring and torques). Why not the spring's own pose: through the
    tips' friction on the table, where the hand comes to rest depends on the path, and the
    hold's path is not the torques' alone. The next phase is planned from where the nominal
    hand rests, so the integral brings every hand to the pose that phase was planned from.
    The episode is left where the phase ended."""
    assert spec.seed is not None and spec.pose_integral is not None
    episode.run_phase(_compiled_phase(spec, spec.seed, hand, replace(hold, integral=None)))
    gain, bound, still = spec.pose_integral
    rest = _rounded_angles(episode)
    integral = PoseIntegral(rest, gain, bound, still, joint_fingers(hand))
    return replace(hold, integral=integral)


def _rounded_angles(episode: Episode) -> tuple[float, ...]:
    return tuple(round(float(q), 4) + 0.0 for q in episode.plant.joint_angles)


def plan_recipe(  # noqa: C901 - the planning pipeline; to split (issue 16)
    template: Template,
    hand: HandConfig,
    *,
    progress: Callable[[str], None] | None = None,
    models: int | None = None,
    budget: Budget | None = None,
    executor: WorkPool | None = None,
    meter: Callable[[str, int], Progress] | None = None,
    base: Base | None = None,
) -> PlanResult:
    """Plan every phase of ``template`` for ``hand`` (see the module doc), or, with ``base``,
    the phases from its ``start`` on.

    The phases run on the models through ``executor`` (default: here, one after another);
    the recipe is the same wherever they run. ``meter`` makes a progress bar per phase."""
    if executor is None:
        with open_pool(workers=1) as inline:
            return plan_recipe(
                template,
                hand,
                progress=progress,
                models=models,
                budget=budget,
                executor=inline,
                meter=meter,
                base=base,
            )
    say = progress or (lambda _m: None)
    settings = template.search
    count = models if models is not None else settings.models
    budget = budget or settings.budget
    params = parse_sim(hand)
    model_list = model_set(params, count, settings.seed, settings.spread, hand=hand)
    worlds = [
        World.of(hand, m.params, template.objects, template.limit_guard, template.pairs)
        for m in model_list
    ]
    snaps: list[Snapshot] = [snapshot_of(w) for w in worlds]
    alive = list(range(len(worlds)))
    previous: tuple[float, ...] = (0.0,) * hand.n_joints
    lifted = False
    plans: list[PhasePlan] = []
    base_name = Path(base.recipe.source).name if base is not None else ""
    for index, spec in enumerate(template.phases):
        say(f"phase {spec.name} ({spec.kind}) on {len(alive)} model(s)")
        # each phase draws from its own stream, so a phase's search does not depend on how
        # the phases before it were chosen (searched, or kept from a base recipe)
        rng = np.random.default_rng((settings.seed, index))
        if not alive:
            raise AnalysisError(
                f"no model holds the objects any more when phase "
                f"'{spec.name}' begins: the phases before it fail (widen the "
                "search or change the template)"
            )
        kept = base.kept(spec) if base is not None else None
        nominal = episode_of(worlds[alive[0]])
        nominal.restore(snaps[alive[0]])
        if kept is not None:
            say(f"  torques kept from {base_name}")
        elif spec.kind == "lift" and spec.seed is not None:
            # fingertip pushing begins without contact: its grasp is where the seed's motion
            # first touches the objects
            _advance_to_contact(nominal, _compiled_phase(spec, spec.seed, hand))
        analysis = _analyse(nominal, spec, hand) if kept is None else None
        nominal.restore(snaps[alive[0]])
        if analysis is not None:
            say(
                f"  analysis: margin {analysis.margin:.3g} N"
                if analysis.found
                else f"  analysis: none ({analysis.reason})"
            )
        chosen: Candidate | None = None
        cuts: list[RampCut] = []
        search_doc: dict[str, Any] | None = None
        bar: Progress | None = None
        pose = None
        if kept is not None:
            bar = meter(f"phase {spec.name}", len(alive)) if meter is not None else None
            torques, pose = kept.torques, kept.pose
            origin = f"base recipe {base_name}"
        elif spec.kind == "free":
            bar = meter(f"phase {spec.name}", len(alive)) if meter is not None else None
            assert spec.seed is not None
            torques = spec.seed
            origin = "template"
            if spec.pose_stiffness is not None:
                pose = _pose_of(nominal, spec, hand)
                nominal.restore(snaps[alive[0]])
        else:
            seeds: list[tuple[str, tuple[float, ...]]] = []
            if analysis is not None and analysis.found and analysis.torques is not None:
                seeds.append(("analysis", analysis.torques))
            if spec.seed is not None:
                seeds.append(("template", spec.seed))
            if any(previous):
                seeds.append(("previous phase", previous))
            if not seeds:
                seeds.append(("zero", previous))
            starts = list(seeds)  # the random ones below are no measure of a ramp's cut
            for k in range(settings.random_seeds):
                seeds.append((f"random flexion {k + 1}", _flexion_seed(hand, rng)))
            replanned = base.phase(spec.name) if base is not None else None
            if replanned is not None:
                # last, so that the plan keeps the base's torque only if nothing else drawn
                # ranks as high
                seeds.append(("base recipe", replanned.torques))
                starts.append(seeds[-1])
            margin, fail = _limit_bounds(template)
            scorer = (
                turn_scorer(spec.turn, spec.max_s, margin, settings.max_turn_rate_deg_s)
                if spec.kind == "turn"
                else hold_scorer(spec.min_height, open_pair=True, limit_margin=margin)
            )
            held = _held(previous, template.phases[index - 1] if index else None, hand)
            follows = _what_follows(template, index, hand, base)
            into = f"phases[{index}].ramp_s"
            bounds = ramp_bounds(
                spec, hand, search_box(spec, hand, previous), held, follows, (template.source, into)
            )
            cuts = ramp_cuts(spec, hand, held, follows, into, starts)
            for cut in cuts:
                say(f"  warning: {cut.text()}")
            # the chosen torque runs once more on every model, on the same bar
            result, bar = _search(
                [worlds[i] for i in alive],
                [snaps[i] for i in alive],
                _compiled_phase(spec, seeds[0][1], hand),
                seeds,
                _as_bounds(bounds),
                scorer,
                rng,
                budget,
                executor,
                lifted=lifted,
                limit_fail=fail,
                wanted_turn_deg=math.degrees(spec.turn) if spec.kind == "turn" else None,
                tumble_deg_s=(
                    TUMBLE_FAIL_FACTOR * settings.max_turn_rate_deg_s
                    if spec.kind == "turn"
                    else None
                ),
                label=f"phase {spec.name}",
                meter=meter,
                say=say,
                after=1,
            )
            chosen = result.best
            torques = chosen.torques
            origin = chosen.origin
            if all(o.failed for o in chosen.outcomes) and spec.kind != "lift":
                # nothing found keeps the objects on any model: hold on to them with the
                # previous torques rather than compile a phase that drops them
                torques, origin = previous, "previous phase (no candidate kept the objects)"
            search_doc = {
                "score": round(chosen.score, 4),
                "seed_scores": {c.origin: round(c.score, 4) for c in result.seeds},
                "evaluated": result.evaluated,
                "models": len(alive),
                "successes": chosen.successes,
            }
            if cuts:
                search_doc["held_by_ramps"] = [cut.text() for cut in cuts]
        if pose is not None and spec.pose_integral is not None:
            # a kept hold gets its rest pose too: the template may add the integral to it
            nominal.restore(snaps[alive[0]])
            pose = _with_rest(nominal, spec, hand, pose)
            nominal.restore(snaps[alive[0]])
        schedule: tuple[ScheduledTorques, ...] | None = None
        schedule_doc: list[dict[str, Any]] = []
        if any(isinstance(e, PlannedSchedule) for e in spec.schedule):
            if kept is not None and base is not None and not base.plans_schedule(spec.name):
                schedule = _base_schedule(spec, kept)
            else:
                schedule, schedule_doc = _plan_schedule(
                    template,
                    hand,
                    params,
                    spec,
                    index,
                    torques,
                    previous,
                    plans,
                    budget=budget,
                    executor=executor,
                    meter=meter,
                    say=say,
                )
        phase = _compiled_phase(spec, torques, hand, pose, schedule)
        ran = executor.map(
            run_phase_task,
            [PhaseTask(worlds[i], snaps[i], phase, lifted, keep_state=True) for i in alive],
            bar,
        )
        if bar is not None:
            bar.close()
        outcomes = [outcome for outcome, _ in ran]
        for i, (_, snap) in zip(alive, ran, strict=True):
            assert snap is not None
            snaps[i] = snap
        survivors = [i for i, o in zip(alive, outcomes, strict=True) if not o.failed and o.in_hand]
        say(f"  chosen from {origin}: {_outcomes_text(spec, outcomes)}")
        provenance: dict[str, Any] = {
            "kind": spec.kind,
            "wanted": _wanted(spec),
            "chosen_from": origin,
            "hand_config_hash": hand.config_hash,
        }
        if analysis is not None:
            provenance["analysis"] = analysis.provenance()
        else:
            provenance["analysis"] = {
                "found": False,
                "reason": (
                    "no contact to reason about (free motion)"
                    if spec.kind == "free"
                    else "no wanted motion (hold)"
                ),
            }
        if search_doc is not None:
            provenance["search"] = search_doc
        if kept is not None:
            # what planned the kept torques; the models below are this plan's
            provenance = {**dict(kept.provenance), "kept_from": origin}
        if schedule_doc:
            provenance["schedule"] = schedule_doc
        provenance["models"] = {
            "ran": len(alive),
            "held": len(survivors),
            "exits": _exit_counts(outcomes),
        }
        if spec.kind == "turn":
            provenance["models"]["true_turn_deg"] = [round(o.true_turn_deg, 1) for o in outcomes]
            provenance["models"]["peak_rate_deg_s"] = [round(o.peak_rate_deg_s) for o in outcomes]
        done = _jobs_done(spec, outcomes, template)
        undone = _job_left_undone(spec, outcomes, template, done)
        plans.append(
            PhasePlan(
                spec, phase, analysis, chosen, outcomes, provenance, done, undone, tuple(cuts)
            )
        )
        alive = survivors
        previous = phase.torques
        if spec.kind == "lift":
            lifted = True
    # the bytes the template was parsed from, not the file as it is now: a plan takes
    # minutes, and the file may have been edited meanwhile
    digest = template.sha256[:16]
    return PlanResult(template, hand, plans, model_list, f"sha256:{digest}", base)


def _jobs_done(
    spec: TemplatePhase, outcomes: Sequence[PhaseOutcome], template: Template
) -> list[bool] | None:
    """Per model, whether a lift, hold or turn phase did its job (None for a free phase,
    which has none to judge). A lift or hold has when the objects are up by its
    ``min_height`` and in the hand, without a failure; a turn when it failed on none of the
    search's counts (a drop, a soft limit, less than ``MIN_TURN_FRACTION`` of its wanted
    turn, a tumble): a turn that stops short but past half is finished by the next phases'
    exits on the turn, as the swap's ``manipulate_2`` is."""
    if spec.kind == "free":
        return None
    if spec.kind == "turn":
        judge = Candidate(
            (),
            0.0,
            [],
            "",
            limit_fail=_limit_bounds(template)[1],
            wanted_turn_deg=math.degrees(spec.turn),
            tumble_deg_s=TUMBLE_FAIL_FACTOR * template.search.max_turn_rate_deg_s,
        )
        return [replace(judge, outcomes=[o]).failures == 0 for o in outcomes]
    hold = HOLD_S if spec is _held_before_turns(template) else 0.0
    return [
        not o.failed and o.in_hand and o.end_height >= spec.min_height and o.held_s >= hold - 1e-9
        for o in outcomes
    ]


def _held_before_turns(template: Template) -> TemplatePhase | None:
    """The lift or hold that ends the experiment's "lifted and held": the last before the
    first manipulation phase (``convention.is_manipulation``, as the experiment counts
    them), or the last of all when none is one. Its job includes the objects up for
    ``HOLD_S`` by its end: a template whose hold is shorter was planned and passed, and
    every run of its recipe then failed the experiment."""
    phases = template.phases
    first = next((i for i, p in enumerate(phases) if is_manipulation(p.name)), len(phases))
    return next((p for p in reversed(phases[:first]) if p.kind in ("lift", "hold")), None)


def _job_left_undone(
    spec: TemplatePhase,
    outcomes: Sequence[PhaseOutcome],
    template: Template,
    done: Sequence[bool] | None,
) -> str | None:
    """What a phase left undone on *every* model (``done``, ``_jobs_done``), or None."""
    if done is None or not outcomes or any(done):
        return None
    if spec.kind == "turn":
        turns = _figures([o.true_turn_deg for o in outcomes], "{:+.1f}")
        tumble = TUMBLE_FAIL_FACTOR * template.search.max_turn_rate_deg_s
        return (
            f"the pair turned {turns} deg of the {math.degrees(spec.turn):+.0f} deg wanted "
            f"(its job: at least {MIN_TURN_FRACTION:.0%} of it, no tumble over "
            f"{tumble:.0f} deg/s, nothing dropped, no soft limit)"
        )
    heights = _figures([round(o.end_height * 1e3) + 0 for o in outcomes], "{:d}")
    exits = sorted({o.exit for o in outcomes})
    held = job = ""
    if spec is _held_before_turns(template):
        held_s = _figures([round(o.held_s, 2) for o in outcomes], "{:.2f}")
        held = f", every object {LIFT_HEIGHT * 1e3:.0f} mm up or more for the last {held_s} s"
        job = (
            f", and every object up {HOLD_S:g} s by its end: the experiment's lifted and held "
            "before the first manipulation phase"
        )
    return (
        f"the lowest object ended {heights} mm up, model by model{held} (its job: at least "
        f"{spec.min_height * 1e3:.0f} mm, in the hand{job}), exits: {'; '.join(exits)}"
    )


#: models up to which the plan's progress says each one's outcome; more are counted
OUTCOMES_LISTED = 8


def _figures(values: Sequence[float], form: str) -> str:
    """Each model's figure, or on more than ``OUTCOMES_LISTED`` models their range: a
    message (and a failed recipe's ``failed_phases``) of 48 figures says no more than two."""
    if len(values) <= OUTCOMES_LISTED:
        return ", ".join(form.format(v) for v in values)
    return f"{form.format(min(values))} to {form.format(max(values))}"


def _outcomes_text(spec: TemplatePhase, outcomes: Sequence[PhaseOutcome]) -> str:
    """How the chosen torque did on the models, for the plan's progress: each model's exit
    and turn or height, or, on more than ``OUTCOMES_LISTED`` models, the exits counted and
    the range (a line per model of 48 was 2,000 characters)."""
    if len(outcomes) <= OUTCOMES_LISTED:
        return ", ".join(
            f"{_exit_word(o)} ({o.true_turn_deg:+.0f} deg, peak {o.peak_rate_deg_s:.0f} deg/s)"
            if spec.kind == "turn"
            else f"{_exit_word(o)} (up {round(o.end_height * 1e3) + 0:d} mm)"
            for o in outcomes
        )
    counted = Counter(_exit_word(o) for o in outcomes)
    exits = ", ".join(f"{word} {n}" for word, n in counted.most_common())
    if spec.kind == "turn":
        turns = [o.true_turn_deg for o in outcomes]
        spread = (
            f"turn {min(turns):+.0f} to {max(turns):+.0f} deg, peak at most "
            f"{max(o.peak_rate_deg_s for o in outcomes):.0f} deg/s"
        )
    else:
        heights = [round(o.end_height * 1e3) + 0 for o in outcomes]
        spread = f"up {min(heights):d} to {max(heights):d} mm"
    return f"{len(outcomes)} models: {exits}; {spread}"


def _exit_word(o: PhaseOutcome) -> str:
    """How a phase ended on one model, for a line of the plan's progress: a failure's whole
    reason (cut, "an object left the han" said nothing), else its exit condition's kind."""
    if o.failed or o.exit == "timeout":
        return o.exit
    return "exit"


def _limit_bounds(template: Template) -> tuple[float, float]:
    """rad: how near a soft limit a phase is scored down, and counted as failing (the guard
    makes the approach to a limit a slope, so a guarded grasp may rest closer)."""
    if template.limit_guard is not None:
        return GUARDED_LIMIT_MARGIN, GUARDED_LIMIT_FAIL
    return LIMIT_MARGIN, LIMIT_FAIL


def search_box(spec: TemplatePhase, hand: HandConfig, previous: Sequence[float]) -> list[float]:
    """N·m, the largest |torque| per joint the search may give ``spec``: tau_max less what the
    phase's feedback adds when it runs (its ``torque_margin``, a turn-rate loop's largest
    scale, a paced ramp's ``reach`` beyond it along the segment from ``previous``), which the
    loader holds to tau_max as well; searched to tau_max, a plan ended refused by its own
    recipe's loader."""
    tau = np.array([j.tau_max for j in hand.joints])
    factor = np.maximum(
        np.broadcast_to(np.asarray(spec.torque_margin, dtype=float), tau.shape), 1.0
    )
    if spec.turn_rate is not None:
        # the loop scales the margined torque (``loader._check_feedback_reach``): the
        # product, not the larger of the two, which planned a recipe its loader refused
        factor = factor * max(spec.turn_rate.scale_max, 1.0)
    box = tau / factor
    if spec.paced is not None and spec.paced.reach > 1.0:
        reach = spec.paced.reach
        start = np.abs(np.asarray(previous, dtype=float))
        box = np.minimum(box, np.maximum(0.0, (tau - (reach - 1.0) * start) / reach))
    return [float(b) for b in box]


def _held(torques: Sequence[float], spec: TemplatePhase | None, hand: HandConfig) -> np.ndarray:
    """N·m, what the runner holds of ``spec``'s ``torques``: times its ``torque_margin``."""
    margin = 1.0 if spec is None else spec.torque_margin
    held: np.ndarray = np.asarray(torques, dtype=float) * np.broadcast_to(
        np.asarray(margin, dtype=float), (hand.n_joints,)
    )
    return held


def _what_follows(
    template: Template, index: int, hand: HandConfig, base: Base | None
) -> tuple[np.ndarray, float, str] | None:
    """What phase ``index``'s torque must ramp to, if it is known before its search: the
    end's zero over ``end_ramp_s`` after the last phase, or the next phase's held torque
    over its ``ramp_s`` where that phase's torques are written (a free phase's) or kept from
    ``base``; with the key that sets the ramp. None when the next phase is searched after."""
    if index == len(template.phases) - 1:
        return np.zeros(hand.n_joints), template.end_ramp_s, "end_ramp_s"
    spec = template.phases[index + 1]
    kept = base.kept(spec) if base is not None else None
    torques = kept.torques if kept is not None else spec.seed if spec.kind == "free" else None
    if torques is None:
        return None
    return _held(torques, spec, hand), spec.ramp_s, f"phases[{index + 1}].ramp_s"


def ramp_bounds(
    spec: TemplatePhase,
    hand: HandConfig,
    box: Sequence[float],
    before: np.ndarray,
    after: tuple[np.ndarray, float, str] | None,
    named: tuple[str, str],
) -> list[float] | tuple[list[float], list[float]]:
    """The search's bounds on ``spec``'s torques: ``box`` (``search_box``), cut to what the
    rate limits can ramp to from ``before`` (N·m held before the phase) over its
    ``ramp_s`` (going back at ``paced_ramp.back`` times its speed, as the loader holds it),
    and from to ``after`` (what follows it, ``_what_follows``). A plan with an
    ``end_ramp_s`` or a ``ramp_s`` too short for the torques it searched was refused by its
    own recipe's loader after the whole plan; searched within them, it never is. ``box``
    itself when no ramp binds (the search, and so the plan, as before)."""
    high = np.asarray(box, dtype=float)
    low = -high
    source, into = named  # the template's file, and its phase's ramp_s key
    for _, _, ramp_low, ramp_high in ramp_intervals(spec, hand, before, after, into):
        low = np.maximum(low, ramp_low)
        high = np.minimum(high, ramp_high)
    if np.all(low <= -np.asarray(box)) and np.all(high >= np.asarray(box)):
        return list(box)
    for j in np.flatnonzero(low > high):  # no torque within tau_max ramps both ways
        raise no_ramp_left(source, into, after[2] if after else None, hand, int(j), spec.name)
    return [float(v) for v in low], [float(v) for v in high]


@dataclass(frozen=True)
class RampCut:
    """A joint whose torque a ramp (``ramp_bounds``) holds short of a torque the phase's
    search starts from. Why said: the bound is the template's ramp, not the search's; an
    ``end_ramp_s`` of 1 ms left the planar turn ±0.02 N·m, the plan failed, and its advice
    was to widen the search, never naming the key (found by an outside audit)."""

    key: str  # the template's key that sets the ramp
    ramp_s: float  # s, as the template writes it
    joint: str
    low: float  # N·m
    high: float  # N·m
    start: str  # the seed it holds out (``analysis``, ``template``, ...)
    value: float  # N·m, that seed's torque on ``joint``

    def text(self) -> str:
        return (
            f"{self.key} ({self.ramp_s:g} s) holds {self.joint} within "
            f"[{self.low:.4g}, {self.high:.4g}] N·m, short of {self.value:.4g} N·m, the "
            f"{self.start} seed"
        )


def ramp_cuts(
    spec: TemplatePhase,
    hand: HandConfig,
    before: np.ndarray,
    after: tuple[np.ndarray, float, str] | None,
    into: str,
    starts: Sequence[tuple[str, Sequence[float]]],
) -> list[RampCut]:
    """Where a ramp of ``ramp_bounds`` leaves a joint less than a torque the search starts
    from (``starts``: the analysis', the template's seed, the previous phase's, a base
    recipe's; the random ones are no measure), one per ramp and joint, the seed furthest
    out: where a bound below tau_max leaves the seeds, the ramps bind nothing the search
    would have tried."""
    cuts: list[RampCut] = []
    for key, written, low, high in ramp_intervals(spec, hand, before, after, into):
        for j, joint in enumerate(hand.joint_names):
            outside = [(o, float(t[j])) for o, t in starts if not low[j] <= t[j] <= high[j]]
            if outside:
                origin, value = max(outside, key=lambda s: abs(s[1]))
                cuts.append(
                    RampCut(key, written, joint, float(low[j]), float(high[j]), origin, value)
                )
    return cuts


def _as_bounds(
    box: list[float] | tuple[list[float], list[float]],
) -> tuple[list[float], list[float]]:
    """The search's ``(low, high)`` from a symmetric box (``search_box``, ``ramp_bounds``
    where no ramp binds) or from bounds already."""
    if isinstance(box, tuple):
        return box
    return [-b for b in box], box


def _search(
    worlds: Sequence[World],
    snapshots: Sequence[Snapshot],
    trial: Phase,
    seeds: Sequence[tuple[str, tuple[float, ...]]],
    bounds: tuple[Sequence[float], Sequence[float]],
    scorer: Callable[[PhaseOutcome], float],
    rng: np.random.Generator,
    budget: Budget,
    executor: WorkPool,
    *,
    lifted: bool,
    limit_fail: float,
    wanted_turn_deg: float | None,
    tumble_deg_s: float | None,
    label: str,
    meter: Callable[[str, int], Progress] | None,
    say: Callable[[str], None],
    after: int = 0,
) -> tuple[SearchResult, Progress | None]:
    """The search (``cem``) for ``trial``'s torques on the models, with its progress bar
    (counting ``after`` more runs per model that the caller makes on it; open)."""
    runs = (len(seeds) + budget.generations * budget.population + after) * len(worlds)
    bar = meter(label, runs) if meter is not None else None
    result = cem(
        worlds,
        snapshots,
        trial,
        seeds,
        bounds,
        scorer,
        rng,
        budget,
        executor,
        lifted=lifted,
        progress=say,
        limit_fail=limit_fail,
        wanted_turn_deg=wanted_turn_deg,
        tumble_deg_s=tumble_deg_s,
        bar=bar,
    )
    return result, bar


def _base_schedule(spec: TemplatePhase, kept: Phase) -> tuple[ScheduledTorques, ...]:
    """``spec``'s schedule for a phase the plan keeps: the written entries as the template
    writes them, each planned one with the torques the base recipe has for its ``when``
    (there: checked when the base was loaded, ``replan._check_kept_entries``)."""
    out: list[ScheduledTorques] = []
    for entry in spec.schedule:
        if isinstance(entry, ScheduledTorques):
            out.append(entry)
            continue
        found = next(e for e in kept.schedule if e.when == entry.when)
        out.append(ScheduledTorques(entry.when, found.torques))
    return tuple(out)


def _plan_schedule(
    template: Template,
    hand: HandConfig,
    params: SimParams,
    spec: TemplatePhase,
    index: int,
    own: tuple[float, ...],
    previous: tuple[float, ...],
    plans: Sequence[PhasePlan],
    *,
    budget: Budget,
    executor: WorkPool,
    meter: Callable[[str, int], Progress] | None,
    say: Callable[[str], None],
) -> tuple[tuple[ScheduledTorques, ...], list[dict[str, Any]]]:
    """``spec``'s schedule with each planned entry's torque searched (the written ones as
    written), and what each search found, for the provenance.

    Each planned entry gets models of its own: the template's spread with the objects' radii
    drawn within the entry's ranges (``models.sized_models``), run through the phases
    compiled so far (as every model of the plan is), and the search (``cem``) for the phase
    on those of them that still hold the objects, from the phase's own torque, the written
    entries', the previous phase's and random flexion seeds. Why its own models: the entry
    is the torque for hands with objects of that size, so it is chosen on such hands, with
    every other uncertainty of the spread."""
    settings = template.search
    written = _written_schedule(spec)
    margin, fail = _limit_bounds(template)
    scorer = turn_scorer(spec.turn, spec.max_s, margin, settings.max_turn_rate_deg_s)
    out: list[ScheduledTorques] = []
    docs: list[dict[str, Any]] = []
    for k, entry in enumerate(spec.schedule):
        if isinstance(entry, ScheduledTorques):
            out.append(entry)
            continue
        name = f"{spec.name}.schedule[{k}]"
        ranges = {r.object: (r.low, r.high) for r in entry.when}
        models = sized_models(
            params, entry.models, (settings.seed, index, k), settings.spread, ranges, hand
        )
        worlds = [
            World.of(hand, m.params, template.objects, template.limit_guard, template.pairs)
            for m in models
        ]
        snaps = [snapshot_of(w) for w in worlds]
        alive = list(range(len(worlds)))
        lifted = False
        say(f"  {name}: {len(worlds)} model(s) of its sizes through the phases before it")
        for before in plans:
            ran = executor.map(
                run_phase_task,
                [
                    PhaseTask(worlds[i], snaps[i], before.phase, lifted, keep_state=True)
                    for i in alive
                ],
            )
            held = []
            for i, (outcome, snap) in zip(alive, ran, strict=True):
                assert snap is not None
                snaps[i] = snap
                if not outcome.failed and outcome.in_hand:
                    held.append(i)
            alive = held
            lifted = lifted or before.spec.kind == "lift"
        if not alive:
            raise AnalysisError(
                f"no model of {name}'s sizes holds the objects when '{spec.name}' begins: "
                "the phases before it fail on objects of that size (narrow its ranges)"
            )
        rng = np.random.default_rng((settings.seed, index, 1 + k))
        seeds: list[tuple[str, tuple[float, ...]]] = [("phase's own", own)]
        seeds += [(f"schedule[{j}]", e.torques) for j, e in enumerate(written)]
        if any(previous):
            seeds.append(("previous phase", previous))
        seeds += [
            (f"random flexion {j + 1}", _flexion_seed(hand, rng))
            for j in range(settings.random_seeds)
        ]
        result, bar = _search(
            [worlds[i] for i in alive],
            [snaps[i] for i in alive],
            _compiled_phase(spec, own, hand, schedule=()),
            seeds,
            _as_bounds(search_box(spec, hand, previous)),
            scorer,
            rng,
            budget,
            executor,
            lifted=lifted,
            limit_fail=fail,
            wanted_turn_deg=math.degrees(spec.turn),
            tumble_deg_s=TUMBLE_FAIL_FACTOR * settings.max_turn_rate_deg_s,
            label=f"phase {name}",
            meter=meter,
            say=say,
        )
        if bar is not None:
            bar.close()
        best = result.best
        out.append(ScheduledTorques(entry.when, written_torques(best.torques)))
        objects = spec.object_names
        docs.append(
            {
                "entry": k,
                "radius_ratio": [
                    {"object": objects[r.object], "min": r.low, "max": r.high} for r in entry.when
                ],
                "models": len(worlds),
                "held": len(alive),
                "chosen_from": best.origin,
                "score": round(best.score, 4),
                "successes": best.successes,
                "failures": best.failures,
                "true_turn_deg": [round(o.true_turn_deg, 1) for o in best.outcomes],
                "peak_rate_deg_s": [round(o.peak_rate_deg_s) for o in best.outcomes],
            }
        )
        say(
            f"  {name}: chosen from {best.origin}, {best.successes}/{len(alive)} models turn, "
            f"{best.failures} fail"
        )
    return tuple(out), docs


def _wanted(spec: TemplatePhase) -> dict[str, Any]:
    if spec.kind == "turn":
        return {"turn_deg": round(math.degrees(spec.turn), 3), "exit": spec.exit_condition()}
    if spec.kind == "lift":
        return {"move": {k: list(v) for k, v in spec.move.items()}, "min_height_m": spec.min_height}
    if spec.kind == "hold":
        return {"min_height_m": spec.min_height}
    return {"torques": "from the template"}


def _exit_counts(outcomes: list[PhaseOutcome]) -> dict[str, int]:
    counts: dict[str, int] = {}
    for o in outcomes:
        key = "exit" if o.exit.startswith("estimate") else o.exit
        counts[key] = counts.get(key, 0) + 1
    return counts


def recipe_text(result: PlanResult, command: str) -> str:
    """The compiled recipe's YAML, with a header that says how to make it again."""
    # each a comment of one line: a newline in a file's name made the rest of it YAML, and
    # the recipe written did not load
    header = (
        f"# Compiled by handctl plan from {escaped(Path(result.template.source).name)}: do "
        "not edit by hand.\n"
        f"# Change the template and plan again: {escaped(command)}\n"
    )
    body = dump_yaml(result.recipe_document())
    check_runnable(body, result.template.source, result.hand)
    return header + body


def check_runnable(body: str, template_source: str, hand: HandConfig) -> None:
    """Refuse a compiled recipe (``body``) that ``handctl run`` would refuse, naming the
    template's key.

    The template's ramps can be checked against the rate limits only once the torques they
    lead to are planned: a ``ramp_s`` too short for the step into a phase (``ramp_s: 0``) made
    a recipe that every run refused. The compiled phases are the template's, in its order, so
    the recipe's key (``phases[2].ramp_s``, ``end_ramp_s``) is the template's key too."""
    try:
        recipe = parse_recipe(parse_yaml(body, template_source), hand)
        check_against_hand(recipe, hand)
    except ConfigError as exc:
        raise ConfigError(
            template_source, exc.key, f"{exc.expected} (in the recipe planned from it)", exc.found
        ) from None


def quick_budget() -> Budget:
    """The smallest search that still exercises every step (tests, smoke runs)."""
    return replace(Budget(), generations=1, population=2, elite=1)
