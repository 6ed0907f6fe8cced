"""Re-planning a recipe from one of its phases on: the phases before it keep an existing
compiled recipe's torques.

Why: the approach, the lift and the hold take most of a plan's time, and a change to the
manipulation (its scoring, its feedback keys) does not change them. The kept phases are not
skipped: every model still runs them, with the kept torques, so the re-planned phases start
where a run of the recipe would start them on each model.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from handctl.config import HandConfig
from handctl.errors import ConfigError, Description
from handctl.online.recipes.loader import check_against_hand, parse_recipe
from handctl.online.recipes.schema import Phase, Recipe
from handctl.planning.template import PlannedSchedule, Template, TemplatePhase
from handctl.schema import load_yaml


@dataclass(frozen=True)
class Base:
    """A compiled recipe whose phases before ``start`` a plan keeps."""

    recipe: Recipe
    start: str  # the first phase planned again
    #: keep every phase's own torques; plan only the planned ``schedule`` entries of the
    #: phases from ``start`` on (``handctl plan --schedule-only``)
    schedule_only: bool = False
    #: keep every phase's torques and schedule entries, search nothing (``handctl plan
    #: --keep-torques``): the template's other keys compiled onto the base's torques
    keep_torques: bool = False
    #: where ``start`` is among the template's phases: the base's phases before it are the
    #: template's (``_check_kept_phases``). ``start`` itself may be a phase the base lacks
    #: (one added to the template, or renamed), whose place in the base was looked up in
    #: vain (a traceback), or passed over (every base phase after it was kept)
    start_at: int = 0

    def kept(self, spec: TemplatePhase) -> Phase | None:
        """The base's phase of ``spec``'s name if the plan keeps its torques (it comes before
        ``start``, or the plan is of the schedules only, or of nothing). A free phase only
        while the template still writes what the base has (``_as_written``): its torques
        are the template's own, not searched, and kept they compiled an edit of them over
        with the old values without a word. Unedited, it is kept whole, pose included: the
        pose is where the nominal hand came to rest when the base was planned, and computed
        again on today's simulation it moves (the shipped approach's rest by up to 0.07 rad),
        and with it every phase planned from there."""
        if self.schedule_only or self.keep_torques:
            phase = self.phase(spec.name)
        else:
            phase = next(
                (p for p in self.recipe.phases[: self.start_at] if p.name == spec.name), None
            )
        if phase is not None and spec.kind == "free" and not _as_written(phase, spec):
            return None
        return phase

    def phase(self, name: str) -> Phase | None:
        """The base's phase ``name``, kept or not: a re-planned phase's search starts from it
        too, so the plan keeps the base's torque unless it finds one that ranks above it."""
        return next((p for p in self.recipe.phases if p.name == name), None)

    def plans_schedule(self, name: str) -> bool:
        """Whether the plan searches phase ``name``'s planned ``schedule`` entries (it is
        ``start`` or after it); a phase before it keeps the base's, and so does every phase
        with ``keep_torques``."""
        if self.keep_torques:
            return False
        names = [p.name for p in self.recipe.phases]
        return name not in names or names.index(name) >= self.start_at

    def describe(self) -> dict[str, str | bool]:
        """For the re-planned recipe's ``planned_from``."""
        base = Path(self.recipe.source).name
        if self.keep_torques:
            return {"base": base, "keep_torques": True}
        out: dict[str, str | bool] = {"from_phase": self.start, "base": base}
        if self.schedule_only:
            out["schedule_only"] = True
        return out


#: N·m, N·m/rad, N·m·s/rad: a compiled recipe's numbers are written to 4 decimals
WRITTEN_TOLERANCE = 5e-5


def _as_written(phase: Phase, spec: TemplatePhase) -> bool:
    """Whether the base's free ``phase`` is what the template writes for it now: the same
    torques and the same pose hold's gains (or none)."""

    def near(a: float, b: float) -> bool:
        return math.isclose(a, b, rel_tol=0.0, abs_tol=WRITTEN_TOLERANCE)

    if spec.seed is None or len(spec.seed) != len(phase.torques):
        return False
    if not all(near(a, b) for a, b in zip(spec.seed, phase.torques, strict=True)):
        return False
    if spec.pose_stiffness is None or phase.pose is None:
        return spec.pose_stiffness is None and phase.pose is None
    return near(spec.pose_stiffness, phase.pose.stiffness) and near(
        spec.pose_damping, phase.pose.damping
    )


def load_base(
    path: Path, start: str, template: Template, hand: HandConfig, schedule_only: bool = False
) -> Base:
    """Load ``path`` as the base of a plan of ``template`` from phase ``start`` on, checking
    that it was compiled from this template's phases for this hand; every problem is a
    ``ConfigError`` naming the option or the file, the key, what was expected and found."""
    names = [p.name for p in template.phases]
    if start not in names:
        listed = ", ".join(names)
        where = Path(template.source).name
        raise ConfigError("--from", "", f"a phase of {where} ({listed})", start)
    recipe = _read_base(path, template, hand)
    if schedule_only:
        _check_something_to_search(template, start)
    base = Base(recipe, start, schedule_only, start_at=names.index(start))
    return _checked(base, template, hand)


def load_kept_base(path: Path, template: Template, hand: HandConfig) -> Base:
    """Load ``path`` as the base of a plan that keeps every phase's torques and searches
    nothing (``--keep-torques``): a change to a template's exits or feedback is compiled in a
    minute, where planning it again searches for the torques for tens of minutes. The base
    is checked as ``load_base`` checks it, each of the template's phases kept."""
    recipe = _read_base(path, template, hand)
    return _checked(Base(recipe, template.phases[0].name, keep_torques=True), template, hand)


def _read_base(path: Path, template: Template, hand: HandConfig) -> Recipe:
    """The recipe at ``path``, if it was compiled from ``template``'s recipe for ``hand``,
    with the template's objects."""
    doc = load_yaml(path, "recipe")
    # a recipe without the key was said to have ``compiled: False``, a value it does not hold
    given = doc.has("compiled")
    recipe = parse_recipe(doc, hand)
    check_against_hand(recipe, hand)
    source = str(path)
    if not recipe.compiled:
        raise ConfigError(
            source,
            "compiled",
            "a recipe compiled by handctl plan (true)",
            False if given else Description("nothing: the key is missing"),
        )
    if recipe.name != template.recipe:
        raise ConfigError(
            source,
            "recipe",
            f"'{template.recipe}', the recipe {Path(template.source).name} compiles",
            recipe.name,
        )
    if not hand.answers_to(recipe.hand_config_hash):
        raise ConfigError(
            source,
            "hand_config_hash",
            f"{hand.config_hash}, the hash of the hand planned for ({hand.source})",
            recipe.hand_config_hash,
        )
    wanted_objects = [(o.name, o.radius) for o in template.objects]
    found_objects = [(o.name, o.radius) for o in recipe.objects]
    if found_objects != wanted_objects:
        raise ConfigError(
            source,
            "objects",
            f"the template's objects {wanted_objects} (name, radius in m)",
            found_objects,
        )
    return recipe


def _checked(base: Base, template: Template, hand: HandConfig) -> Base:
    """``base``, once the phases it keeps are the template's (``_check_kept_phases``), every
    planned schedule entry it is to give is in it (``_check_kept_entries``) and the template's
    torque margins keep its torques within tau_max (``_check_kept_margins``)."""
    _check_kept_phases(base, template)
    _check_kept_entries(base, template)
    _check_kept_margins(base, template, hand)
    return base


def _check_kept_margins(base: Base, template: Template, hand: HandConfig) -> None:
    """A kept phase runs the base's torques (its own and its schedule's) times the
    template's ``torque_margin``, which the compiled recipe's loader holds to tau_max: a
    margin too large for them was refused only after every model had run, naming a
    ``torques`` key the template does not have. Refused before anything is planned, naming
    the template's margin and the base's torque."""
    tau_max = np.array([j.tau_max for j in hand.joints])
    for i, spec in enumerate(template.phases):
        kept = base.kept(spec)
        if kept is None or spec.torque_margin == 1.0:
            continue
        margin = np.broadcast_to(np.asarray(spec.torque_margin, dtype=float), tau_max.shape)
        at = [p.name for p in base.recipe.phases].index(spec.name)
        torques = [("torques", kept.torques)] + [
            (f"schedule[{k}].torques", e.torques)
            for k, e in enumerate(kept.schedule)
            if not base.plans_schedule(spec.name)
        ]
        for key, values in torques:
            held = np.abs(np.asarray(values, dtype=float)) * margin
            for j in np.flatnonzero(held > tau_max * (1 + 1e-9)):
                name = hand.joint_names[j]
                raise ConfigError(
                    template.source,
                    f"phases[{i}].torque_margin",
                    f"a margin that keeps the kept torques within tau_max ({tau_max[j]:g} N·m "
                    f"of {name} in {hand.source}): {Path(base.recipe.source).name}'s "
                    f"phases[{at}].{key}.{name} is {values[j]:g} N·m, {held[j]:.4g} N·m "
                    f"times the margin",
                    float(margin[j]),
                )


def _check_kept_entries(base: Base, template: Template) -> None:
    """Every planned ``schedule`` entry the plan takes from the base (those of the phases
    whose schedule it does not search) must be in the base, for the same ranges: checked
    before anything is planned, where the plan found it out only when it reached the phase,
    after its models had run the phases before."""
    names = [p.name for p in base.recipe.phases]
    for spec in template.phases:
        if spec.name not in names or base.plans_schedule(spec.name):
            continue
        at = names.index(spec.name)
        have = [e.when for e in base.recipe.phases[at].schedule]
        for k, entry in enumerate(spec.schedule):
            if isinstance(entry, PlannedSchedule) and entry.when not in have:
                raise ConfigError(
                    base.recipe.source,
                    f"phases[{at}].schedule",
                    f"an entry for the template's schedule[{k}] (or plan it: --from {spec.name})",
                    "none with its ranges",
                )


def _check_kept_phases(base: Base, template: Template) -> None:
    """The phases whose torques are kept (those before ``start``, or every one with
    ``schedule_only`` or ``keep_torques``) must be the template's, in its order."""
    every = base.schedule_only or base.keep_torques
    names = [p.name for p in template.phases]
    kept = names if every else names[: names.index(base.start)]
    which = "every phase is kept" if every else f"the phases before '{base.start}' are kept"
    have = [p.name for p in base.recipe.phases]
    source = base.recipe.source
    # the phases in order first: a template without one of the base's phases was said as a
    # phase too many at the end, not as the phase that differs where it does
    _check_kept_names(base, template, kept, have, which)
    if every and len(have) > len(names):
        # a phase the template does not have would be dropped from the recipe without a word
        raise ConfigError(
            source,
            f"phases[{len(names)}].name",
            f"no phase after '{names[-1]}', the template's last ({which})",
            have[len(names)],
        )


def _check_kept_names(
    base: Base, template: Template, kept: list[str], have: list[str], which: str
) -> None:
    """Each kept phase the template's, by name and in order, and of its kind, as the plan
    that compiled the base wrote it (``provenance.kind``): a hold kept as a turn's torques
    ran every model and failed at the end. A phase without the kind is refused too: it was
    taken on trust. A free phase is kept only as the template writes it (``Base.kept``):
    its name is checked, its kind is not asked for."""
    source = base.recipe.source
    for i, name in enumerate(kept):
        if i >= len(have) or have[i] != name:
            raise ConfigError(
                source,
                f"phases[{i}].name",
                f"'{name}', the template's phase {i + 1} ({which})",
                have[i] if i < len(have) else "no such phase",
            )
        wanted = template.phases[i].kind
        if wanted == "free":  # kept only as the template writes it (Base.kept)
            continue
        kind = base.recipe.phases[i].provenance.get("kind")
        if kind is None:
            # a phase without the kind its plan wrote (an edited recipe) might be a hold's
            # torques kept as a turn's: refused, as a phase of another kind is, not trusted
            raise ConfigError(
                source,
                f"phases[{i}].provenance.kind",
                f"'{wanted}', the kind of the template's '{name}', as handctl plan writes it "
                f"({which}: without it the phase may be of any kind; plan it: --from it)",
                "no kind",
            )
        if kind != wanted:
            raise ConfigError(
                source,
                f"phases[{i}].provenance.kind",
                f"'{wanted}', the kind of the template's '{name}' ({which}: a phase of "
                "another kind is no torque for it; plan it: --from it)",
                kind,
            )


def _check_something_to_search(template: Template, start: str) -> None:
    """``--schedule-only`` searches the planned ``schedule`` entries of the phases from
    ``start`` on, and nothing else: with none, it searched nothing, exit 0, and wrote the base
    again with this run's (fewer) models in its provenance, over a recipe planned on more."""
    names = [p.name for p in template.phases]
    planned = [
        p.name
        for p in template.phases[names.index(start) :]
        if any(isinstance(e, PlannedSchedule) for e in p.schedule)
    ]
    if not planned:
        raise ConfigError(
            "--schedule-only",
            "",
            f"a phase from '{start}' on with a schedule entry to plan (plan: {{models: N}} in "
            f"{Path(template.source).name}): --schedule-only searches only those",
            "none",
        )
