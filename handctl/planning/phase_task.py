"""A phase on one model as a task any worker can run: the unit of a plan's parallel work.

A task carries everything the episode needs as data (the hand config as parsed, the model's
simulation parameters, the objects, the guard's settings, the snapshot to start from), so a worker
on another machine needs nothing but the installed package: no file, no path, no state left by
earlier tasks that could change a result. A worker keeps the MuJoCo models it built (keyed by
the model's digest), because building one costs more than most phases; a kept episode is always
restored from the task's snapshot first, so reusing it cannot change the outcome.
"""

from __future__ import annotations

import hashlib
import pickle
import threading
from collections import OrderedDict
from dataclasses import dataclass

from handctl.config import HandConfig
from handctl.online.recipes.guard import GuardSettings
from handctl.online.recipes.schema import Pair, Phase, RecipeObject
from handctl.planning.episode import Episode, PhaseOutcome, Snapshot
from handctl.portable import local_hand, portable_hand
from handctl.sim.params import SimParams

#: episodes one worker keeps (a plan uses one per model; more are rebuilt when needed)
KEPT_EPISODES = 64


@dataclass(frozen=True)
class World:
    """One model of the hand, as data: what a worker rebuilds an ``Episode`` from."""

    hand: HandConfig  # a ``portable_hand``
    params: SimParams
    objects: tuple[RecipeObject, ...]
    guard: GuardSettings | None
    digest: str
    pairs: tuple[Pair, ...] = ()  # by index into ``objects``; (): each object with the next

    @classmethod
    def of(
        cls,
        hand: HandConfig,
        params: SimParams,
        objects: tuple[RecipeObject, ...],
        guard: GuardSettings | None,
        pairs: tuple[Pair, ...] = (),
    ) -> World:
        portable = portable_hand(hand)
        digest = hashlib.sha256(pickle.dumps((portable, params, objects, guard, pairs))).hexdigest()
        return cls(portable, params, objects, guard, digest, pairs)

    def episode(self) -> Episode:
        hand = local_hand(self.hand)
        guard = self.guard.guard(hand) if self.guard is not None else None
        return Episode(hand, self.params, self.objects, guard, self.pairs)


@dataclass(frozen=True)
class PhaseTask:
    """Run ``phase`` on ``world`` from ``snapshot``; ``keep_state`` returns where it ended."""

    world: World
    snapshot: Snapshot
    phase: Phase
    lifted: bool
    keep_state: bool = False


#: Each thread's kept episodes, by the thread's identifier. Per thread, not per process: a
#: Dask worker runs as many tasks at once as it has threads (``dask worker``'s default is
#: one per core), and two tasks of one model on one episode ran on one MuJoCo state at once:
#: plans that exited 0 with other scores than the same plan's on one thread, MuJoCo's
#: FatalErrors, segfaults, and a plan that waited for ever on a task lost that way (found
#: by an outside audit).
_caches: dict[int, OrderedDict[str, Episode]] = {}
_caches_lock = threading.Lock()


def _kept() -> OrderedDict[str, Episode]:
    """This thread's kept episodes."""
    ident = threading.get_ident()
    kept = _caches.get(ident)
    if kept is None:
        with _caches_lock:
            kept = _caches.setdefault(ident, OrderedDict())
    return kept


def kept_models() -> int:
    """How many episodes this process keeps, over all its threads."""
    with _caches_lock:
        return sum(len(kept) for kept in _caches.values())


def episode_of(world: World) -> Episode:
    """This thread's episode of ``world`` (built once, kept for its next tasks)."""
    kept = _kept()
    episode = kept.get(world.digest)
    if episode is None:
        episode = world.episode()
        kept[world.digest] = episode
        while len(kept) > KEPT_EPISODES:
            kept.popitem(last=False)
    else:
        kept.move_to_end(world.digest)
    return episode


def run_phase_task(task: PhaseTask) -> tuple[PhaseOutcome, Snapshot | None]:
    """The outcome of the task's phase, and the state it ended in if asked for."""
    episode = episode_of(task.world)
    episode.restore(task.snapshot)
    outcome = episode.run_phase(task.phase, lifted=task.lifted)
    return outcome, (episode.snapshot() if task.keep_state else None)


def snapshot_of(world: World) -> Snapshot:
    """Where ``world`` starts (its configured initial state): from a new episode, since a kept
    one is wherever its last task left it."""
    episode = world.episode()
    kept = _kept()
    kept[world.digest] = episode
    kept.move_to_end(world.digest)
    return episode.snapshot()
