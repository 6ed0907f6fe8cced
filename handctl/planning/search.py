"""The search that refines one phase's torques on the simulated hand, over perturbed models.

Why a search at all: the analysis' condition is sufficient, not necessary. It holds the grasp
at rest, leaves out the palm and the table, and asks every admissible contact force to move the
objects the wanted way, so for many phases it is empty or it picks a torque that turns the pair
on paper and stalls in the hand. What decides is what the hand does: each candidate runs the
phase (ramp, exits on the *estimated* turn, soft limits) from where the previous phases left
every model, and is scored on all of them together.

The method is the cross-entropy method: a Gaussian over the nine torques, centred on the best
seed (the analysis' torque when it has one), sampled, clipped to ±tau_max, its mean and spread
re-fitted to the elite of each generation. It needs no gradient (contact makes the outcome a
step function of the torques) and a few hundred episodes per phase. The score of a candidate is
its mean score over the models minus a fraction of their spread, so a torque that works on most
models beats one that is brilliant on one and drops the pair on another; and candidates are
ranked by how many models they fail on first (a failure stops the hand or loses the objects,
and a turn phase that turns the pair less than ``MIN_TURN_FRACTION`` of its wanted turn on a
model has failed there too: it did not do its job), by score second.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from handctl.executor import WorkPool
from handctl.online.recipes.schema import Phase
from handctl.planning.episode import PhaseOutcome, Snapshot, with_torques
from handctl.planning.phase_task import PhaseTask, World, run_phase_task
from handctl.progress import Progress

#: weight of the spread over models in a candidate's score (robustness over luck)
SPREAD_WEIGHT = 0.5
#: rad, a phase that takes a joint closer than this to its soft limits is penalised: the next
#: phase, or another model, would cross it and stop the hand
LIMIT_MARGIN = 0.25
#: rad, closer than this to a soft limit on any model counts as failing there (ranking)
LIMIT_FAIL = 0.1
#: rad, the same two with the soft-limit guard on (``recipes/guard.py``): the guard makes a
#: joint's approach to its limit a slope rather than a cliff, so a grasp may rest inside the
#: guard's band, and only the last few hundredths of a radian are the danger
GUARDED_LIMIT_MARGIN = 0.06
GUARDED_LIMIT_FAIL = 0.02
#: deg/s, the true centre-line rate a manipulation phase should not exceed at its peak (the
#: template's ``search.max_turn_rate_deg_s``): faster is a tumble, dynamics the quasi-static
#: analysis does not cover and a real hand would likely drop
MAX_TURN_RATE_DEG_S = 180.0
#: what a peak rate above it costs, per multiple of it over, and at most
RATE_WEIGHT = 0.5
RATE_PENALTY_CAP = 1.0
#: a turn whose true centre line peaked above this many times ``max_turn_rate_deg_s`` on a
#: model failed there, for the ranking: the score charges a peak in proportion, so a torque
#: that snapped the pair over on one model and reached its exit on the others outranked one
#: that turns slowly everywhere and falls a little short on one; and a snap is what a real
#: hand would likely drop (docs/experiment.md)
TUMBLE_FAIL_FACTOR = 2.0
#: a turn phase that turned the pair less than this fraction of its wanted turn on a model
#: (or the other way) failed there, for the ranking: without it a torque that does not turn
#: the pair fails on no model, and "do nothing" ranks above any torque that turns the pair on
#: most models but drops it on one. Half: a phase that stops short of half its turn leaves
#: the next more than it was planned for, one past half is finished by the next phases'
#: exits on the turn since ``turn_from``
MIN_TURN_FRACTION = 0.5


def _limit_penalty(o: PhaseOutcome, margin: float = LIMIT_MARGIN) -> float:
    return 0.5 * max(0.0, margin - o.limit_margin) / margin


@dataclass(frozen=True)
class Budget:
    """How much simulated work one phase may take."""

    generations: int = 4
    population: int = 16
    elite: int = 4
    initial_spread: float = 0.25  # of tau_max, per joint
    min_spread: float = 0.02


@dataclass
class Candidate:
    torques: tuple[float, ...]
    score: float
    outcomes: list[PhaseOutcome]
    origin: str
    scores: list[float] = field(default_factory=list)  # per model
    limit_fail: float = LIMIT_FAIL  # rad, see ``failures``
    #: deg, a turn phase's wanted turn (signed), see ``failures``; None: not a turn phase
    wanted_turn_deg: float | None = None
    #: deg/s, a turn phase's peak rate that counts as failing, see ``failures``; None: none
    tumble_deg_s: float | None = None

    @property
    def failures(self) -> int:
        """Models on which the phase failed (a drop, a soft limit, an object out of hand),
        came within ``LIMIT_FAIL`` of a soft limit (contact makes the motion chaotic enough
        that a model which brushes a limit here crosses it on the real bus), or, in a turn
        phase, turned the pair less than ``MIN_TURN_FRACTION`` of its wanted turn or faster
        than ``tumble_deg_s`` at its peak."""
        return sum(
            1
            for o in self.outcomes
            if o.failed or o.limit_margin < self.limit_fail or self._short(o) or self._tumbled(o)
        )

    def _tumbled(self, o: PhaseOutcome) -> bool:
        return self.tumble_deg_s is not None and o.peak_rate_deg_s > self.tumble_deg_s

    def _short(self, o: PhaseOutcome) -> bool:
        wanted = self.wanted_turn_deg
        if not wanted:
            return False
        return o.true_turn_deg / wanted < MIN_TURN_FRACTION

    def rank(self) -> tuple[int, float]:
        """Larger is better: fewer failures first, then the score. A failure stops the real
        hand (the soft limits), loses the objects or leaves the turn undone, so no score makes
        up for one."""
        return (-self.failures, self.score)

    @property
    def successes(self) -> int:
        """Models on which the phase did what it is for (a score of 1 or more: the turn
        reached by its exit, or the objects up and caged)."""
        return sum(1 for s in self.scores if s >= 1.0)


def _tally(cand: Candidate, models: int) -> str:
    """What a candidate's line says beside its score: ranked on its failures first (``rank``),
    it read '(1/2)' beside one that was chosen over it with '(0/2)', which looked like the
    worse one chosen; the models it scored in full on (1 or more: ``successes``) and those it
    failed on, both named, in words of their own (the phase's line after the search counts
    the models it "did its job" on, none failed: ``compile._jobs_done``)."""
    return f"{cand.successes}/{models} scored in full, {cand.failures} failed"


@dataclass
class SearchResult:
    best: Candidate
    seeds: list[Candidate]
    evaluated: int
    history: list[float] = field(default_factory=list)  # best score after each generation


Scorer = Callable[[PhaseOutcome], float]

#: decimals of N·m kept in the compiled recipe (0.1 mN·m, far below the TDT resolution)
TORQUE_DECIMALS = 4


def written_torques(values: Sequence[float] | np.ndarray) -> tuple[float, ...]:
    """The torques as a compiled recipe writes them (``TORQUE_DECIMALS``; -0.0 as 0.0)."""
    return tuple(round(float(v), TORQUE_DECIMALS) + 0.0 for v in values)


def evaluate(
    worlds: Sequence[World],
    snapshots: Sequence[Snapshot],
    phase: Phase,
    candidates: Sequence[Sequence[float] | np.ndarray],
    scorer: Scorer,
    executor: WorkPool,
    *,
    lifted: bool,
    limit_fail: float = LIMIT_FAIL,
    wanted_turn_deg: float | None = None,
    tumble_deg_s: float | None = None,
    bar: Progress | None = None,
) -> list[Candidate]:
    """Run ``phase`` with each candidate's torques on every model from its snapshot, all of
    them as one batch of tasks for ``executor``; score each candidate over the models
    together (the scorer runs here: it is a closure, and cheap)."""
    # what is scored is what a recipe can carry: the torques as the compiled recipe writes
    # them. A score of the unrounded torques is not the written recipe's, and on a hand where
    # 0.05 mN·m moves the outcome a re-plan from that recipe scored it otherwise.
    candidates = [written_torques(torques) for torques in candidates]
    tasks = [
        PhaseTask(world, snap, with_torques(phase, torques), lifted)
        for torques in candidates
        for world, snap in zip(worlds, snapshots, strict=True)
    ]
    results = executor.map(run_phase_task, tasks, bar)
    out = []
    n = len(worlds)
    for k, torques in enumerate(candidates):
        outcomes = [outcome for outcome, _ in results[k * n : (k + 1) * n]]
        scores = np.array([scorer(o) for o in outcomes])
        score = float(scores.mean() - SPREAD_WEIGHT * scores.std())
        out.append(
            Candidate(
                tuple(float(t) for t in torques),
                score,
                outcomes,
                "",
                [float(s) for s in scores],
                limit_fail,
                wanted_turn_deg,
                tumble_deg_s,
            )
        )
    return out


def cem(
    worlds: Sequence[World],
    snapshots: Sequence[Snapshot],
    phase: Phase,
    seeds: Sequence[tuple[str, Sequence[float]]],
    bounds: tuple[Sequence[float], Sequence[float]],
    scorer: Scorer,
    rng: np.random.Generator,
    budget: Budget,
    executor: WorkPool,
    *,
    lifted: bool,
    progress: Callable[[str], None] | None = None,
    limit_fail: float = LIMIT_FAIL,
    wanted_turn_deg: float | None = None,
    tumble_deg_s: float | None = None,
    bar: Progress | None = None,
) -> SearchResult:
    """Cross-entropy search around the seeds; returns the best candidate ever evaluated.

    ``bounds`` are each joint's ``(low, high)`` torques (N·m): ``±tau_max`` less what the
    phase's feedback adds, cut to the ramps the rate limits can make
    (``compile.ramp_bounds``); the spread is half their width.

    A generation is drawn whole before any of it runs (the draws do not depend on the
    outcomes within it), so its candidates run in parallel and the result is the same on
    any executor."""
    low, high = (np.asarray(b, dtype=float) for b in bounds)
    limit = (high - low) / 2.0  # a symmetric box's own tau_max
    say = progress or (lambda _m: None)
    seeded = evaluate(
        worlds,
        snapshots,
        phase,
        [np.clip(t, low, high) for _, t in seeds],
        scorer,
        executor,
        lifted=lifted,
        limit_fail=limit_fail,
        wanted_turn_deg=wanted_turn_deg,
        tumble_deg_s=tumble_deg_s,
        bar=bar,
    )
    for (origin, _), cand in zip(seeds, seeded, strict=True):
        cand.origin = origin
        say(f"  seed {origin}: score {cand.score:+.3f} ({_tally(cand, len(worlds))})")
    best = max(seeded, key=Candidate.rank)
    mean = np.array(best.torques)
    spread = np.full(len(limit), budget.initial_spread) * limit
    evaluated = len(seeded)
    history = [best.score]
    pool = list(seeded)
    for gen in range(budget.generations):
        drawn = [
            np.clip(mean + spread * rng.standard_normal(len(limit)), low, high)
            for _ in range(budget.population)
        ]
        population = evaluate(
            worlds,
            snapshots,
            phase,
            drawn,
            scorer,
            executor,
            lifted=lifted,
            limit_fail=limit_fail,
            wanted_turn_deg=wanted_turn_deg,
            tumble_deg_s=tumble_deg_s,
            bar=bar,
        )
        for cand in population:
            cand.origin = f"search generation {gen + 1}"
        evaluated += len(population)
        pool = sorted(pool + population, key=Candidate.rank, reverse=True)
        elite = pool[: budget.elite]
        if elite[0].rank() > best.rank():
            best = elite[0]
        stack = np.array([c.torques for c in elite])
        mean = stack.mean(axis=0)
        spread = np.maximum(stack.std(axis=0), budget.min_spread * limit)
        history.append(best.score)
        say(f"  generation {gen + 1}: best {best.score:+.3f} ({_tally(best, len(worlds))})")
    return SearchResult(best, seeded, evaluated, history)


def _rate_penalty(o: PhaseOutcome, max_rate_deg_s: float) -> float:
    over = o.peak_rate_deg_s / max_rate_deg_s - 1.0
    return min(RATE_PENALTY_CAP, RATE_WEIGHT * max(0.0, over))


def turn_scorer(
    target_rad: float,
    max_s: float,
    limit_margin: float = LIMIT_MARGIN,
    max_rate_deg_s: float = MAX_TURN_RATE_DEG_S,
) -> Scorer:
    """Score of a manipulation phase: reaching the wanted turn (by its exit) is worth 1 plus a
    little for speed; a timeout is worth the fraction of the turn made; failing (soft limit,
    drop, an object out of the hand) costs 1; ending with a lost estimate costs half; a true
    centre-line rate peaking above ``max_rate_deg_s`` costs half per multiple of it over, up
    to 1, so a turn that tumbles to its exit ranks below a slow one that falls short: the
    speed the score rewards is that of a turn made at the pace the analysis covers."""
    target_deg = math.degrees(target_rad)

    def score(o: PhaseOutcome) -> float:
        if o.failed:
            return -1.0
        lost = (
            (0.0 if o.est_valid and o.in_hand else -0.5)
            - _limit_penalty(o, limit_margin)
            - _rate_penalty(o, max_rate_deg_s)
        )
        if o.exit != "timeout":
            return 1.0 + 0.25 * (1.0 - o.duration_s / max_s) + lost
        return 0.8 * float(np.clip(o.true_turn_deg / target_deg, -1.0, 1.0)) + lost

    return score


def hold_scorer(
    min_height: float, open_pair: bool = False, limit_margin: float = LIMIT_MARGIN
) -> Scorer:
    """Score of a lift or hold phase: both objects up by ``min_height`` and caged (the
    estimate valid) at its end; with ``open_pair``, no finger link between the two objects
    (a pair with a link between them cannot turn past it)."""

    def score(o: PhaseOutcome) -> float:
        if o.failed:
            return -1.0
        # (a min_height of 0, which a template may write, asks only that nothing sank: it
        # was a division by zero, a traceback at the end of the phase's search)
        if o.end_height >= min_height:
            up = 1.0
        else:
            up = 0.5 * max(0.0, o.end_height / min_height) if min_height > 0 else 0.0
        pair = -0.5 if open_pair and o.pair_blocked else 0.0
        caged = 0.25 if o.est_valid and o.in_hand else -0.5
        return up + pair + caged - _limit_penalty(o, limit_margin)

    return score
