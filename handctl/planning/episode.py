"""A recipe phase on one model of the simulated hand, without the bus: what a plan is scored on.

The search tries hundreds of torque vectors per phase on several models, so it runs the plant
directly (about ten times faster than through the emulated nodes) but keeps everything that
decides what a phase does on the hand:

- the real ``RecipeRunner`` (ramps, exits, ``for`` holds, phase-relative estimates, and the
  phase's feedback: pose hold, injected damping, brake, paced ramp, turn-rate loop, torque
  margin, soft-limit guard), started from the previous phase's runner's handover (the torque
  its ramp starts from, the damping it fades from, the velocity filters), so a phase is judged
  with the entry it will really have in a run of the whole recipe;
- the real ``ObjectEstimator`` fed with encoder-quantised angles, so exits fire when the
  estimator (not the ground truth) says the pair has turned;
- the soft joint limits, checked every tick on the measured angles as the safety supervisor
  does (a lift that brushes a limit for a millisecond stops the real run);
- the supervisor's limiter (``limit_torque``: ±tau_max, then the rate limit), as in every run;
- the host's loop at the hand's own rate (each command held for its period on the plant's
  1 ms ticks), and the bus's one node tick between a command and the nodes applying it.

Ground truth (object poses) is read only to *score* a phase, never to decide anything in it.
Snapshots (MuJoCo's integration state plus the estimator's track) let a phase start again from
the same place for every candidate.
"""

from __future__ import annotations

import copy
import dataclasses
import math
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import mujoco
import numpy as np

from handctl.config import HandConfig
from handctl.convention import LIFT_HEIGHT, RATE_WINDOW_S
from handctl.handshape import hand_span
from handctl.online.estimator import ObjectEstimator
from handctl.online.recipes.backoff import RateBackoff
from handctl.online.recipes.guard import LimitGuard
from handctl.online.recipes.runner import Handover, RecipeRunner, RunStatus
from handctl.online.recipes.schema import Pair, Phase, Recipe, RecipeObject
from handctl.online.safety.limits import JointLimits, limit_torque
from handctl.sim.params import NODE_TICK_S, SimParams
from handctl.sim.placement import rest_heights
from handctl.sim.plant import ObjectPose, Plant

#: m, an object this far below its resting height plus this margin counts as back on the table.
DROP_MARGIN = 0.005
#: ticks between the (cheap but not free) checks of limits and object poses.
CHECK_EVERY = 10
_STATE = mujoco.mjtState.mjSTATE_INTEGRATION


@dataclass
class Snapshot:
    state: np.ndarray
    estimator: ObjectEstimator
    torques: tuple[float, ...]
    tick: int  # ticks since the start
    handover: Handover | None = None  # the runner's state the next phase starts from
    #: the estimator's output for ``tick`` when it already ran there (the tick a phase was left
    #: on, which the next phase runs again): the estimator takes one step a call
    estimates: tuple[float, ...] | None = None
    #: the tick since which every object has been ``LIFT_HEIGHT`` up (None: not up now)
    up_since: int | None = None


@dataclass
class PhaseOutcome:
    """What one phase did on one model. Angles in degrees; heights in m above the rest
    height of each object (its centre on the table)."""

    exit: str  # the exit condition's text, "timeout", or "fail: ..." (soft limit, dropped)
    duration_s: float
    true_turn_deg: float
    est_turn_deg: float
    min_height: float
    end_height: float
    limit_margin: float  # rad, the closest any joint came to its soft limits
    pair_gap: float  # m, between the two objects' surfaces at the end (0: touching)
    pair_blocked: bool  # a finger link lies across the line between the centres at the end
    in_hand: bool
    est_valid: bool
    est_error_deg: float
    errors_deg: list[float] = field(default_factory=list)
    #: deg/s, the largest true centre-line rate, each over ``RATE_WINDOW_S`` (the summary's
    #: ``peak_turn_rate_deg_s`` measures the same in a run)
    peak_rate_deg_s: float = 0.0
    #: s, how long every object has been ``LIFT_HEIGHT`` up without a break at the phase's end,
    #: across the phases before it: the experiment's "lifted and held" (``HOLD_S``)
    held_s: float = 0.0

    @property
    def failed(self) -> bool:
        return self.exit.startswith("fail")


def _wrap(angle: float) -> float:
    return (angle + math.pi) % (2 * math.pi) - math.pi


class Episode:
    """One model of the hand, advanced phase by phase."""

    def __init__(
        self,
        hand: HandConfig,
        params: SimParams,
        objects: Sequence[RecipeObject],
        guard: LimitGuard | None = None,
        pairs: Sequence[Pair] = (),
    ) -> None:
        self.hand = hand
        self.guard = guard
        self.params = params
        self.plant = Plant(hand, params)
        self.estimator = ObjectEstimator(hand, objects, tuple(pairs) or None)
        # The template's objects, by their place in the scene, and its first pair's: a scene
        # may hold more objects than the template names (a third rod on the table), and every
        # lift was scored on the lowest of all of them (never lifted), every turn on the
        # scene's first two, whichever the template named
        scene = [o.name for o in params.objects]
        named = [o.name for o in objects]
        self._ours = (
            [scene.index(n) for n in named]
            if named and all(n in scene for n in named)
            else list(range(len(scene)))
        )
        first = tuple(pairs[0]) if pairs else (0, 1)
        self._pair: tuple[int, int] | None = (
            (self._ours[first[0]], self._ours[first[1]]) if len(self._ours) >= 2 else None
        )
        self.torques: tuple[float, ...] = (0.0,) * hand.n_joints
        self.tick = 0
        self.handover: Handover | None = None
        self._estimates: tuple[float, ...] | None = None
        self._up_since: int | None = None  # Snapshot.up_since
        self._limits = JointLimits.from_hand(hand)
        counts = params.encoder.counts_per_rev
        self._quantum = 2 * math.pi / counts
        self._lo = [j.angle_min for j in hand.joints]
        self._hi = [j.angle_max for j in hand.joints]
        # where each object rests: on the table for one put up with nothing under it
        self._rest = list(rest_heights(hand, params))
        self._radii = [o.radius for o in params.objects]
        # the palm's middle and the farthest finger base from it: out of the hand, as the
        # experiment summary judges it (``handshape.hand_span``)
        self._mid_x, self._half_span = hand_span(hand)

    # -- snapshots --------------------------------------------------------------------------
    def snapshot(self) -> Snapshot:
        m, d = self.plant.model, self.plant.data
        size = mujoco.mj_stateSize(m, _STATE)
        state = np.empty(size)
        mujoco.mj_getState(m, d, state, _STATE)
        return Snapshot(
            state,
            copy.deepcopy(self.estimator),
            self.torques,
            self.tick,
            copy.deepcopy(self.handover),
            self._estimates,
            self._up_since,
        )

    def restore(self, snap: Snapshot) -> None:
        m, d = self.plant.model, self.plant.data
        mujoco.mj_setState(m, d, snap.state, _STATE)
        mujoco.mj_forward(m, d)
        self.estimator = copy.deepcopy(snap.estimator)
        self.torques = snap.torques
        self.tick = snap.tick
        self.handover = copy.deepcopy(snap.handover)
        self._estimates = snap.estimates
        self._up_since = snap.up_since

    # -- truth (scoring only) ---------------------------------------------------------------
    def heights(self) -> list[float]:
        """Each of the template's objects' centre above its resting height on the table (m)."""
        poses = self.plant.object_poses()
        return [poses[i].y - self._rest[i] for i in self._ours]

    def _pair_poses(self) -> tuple[ObjectPose, ObjectPose]:
        assert self._pair is not None
        poses = self.plant.object_poses()
        return poses[self._pair[0]], poses[self._pair[1]]

    def pair_gap(self) -> float:
        """m, between the surfaces of the first pair; 0 for one object."""
        if self._pair is None:
            return 0.0
        a, b = self._pair_poses()
        return (
            math.hypot(b.x - a.x, b.y - a.y)
            - self._radii[self._pair[0]]
            - self._radii[self._pair[1]]
        )

    def pair_blocked(self) -> bool:
        """Whether a finger link lies across the segment between the two centres: a pair
        with a link between its objects cannot turn past it. One object is no pair, so
        nothing blocks it (the hold of a one-object recipe asks for an open pair too)."""
        if self._pair is None:
            return False
        a, b = self._pair_poses()
        p, q = (a.x, a.y), (b.x, b.y)
        for ax, ay, ux, uy, length, half in self.estimator.segments(self.plant.joint_angles):
            end = (ax + ux * length, ay + uy * length)
            if _segment_distance(p, q, (ax, ay), end) < half:
                return True
        return False

    def in_hand(self) -> bool:
        poses = self.plant.object_poses()
        return all(
            abs(poses[i].x - self._mid_x) <= self._half_span + self._radii[i] for i in self._ours
        )

    def true_angle(self) -> float:
        """rad, the first pair's centre line (0 with one object: nothing turns)."""
        if self._pair is None:
            return 0.0
        a, b = self._pair_poses()
        return math.atan2(b.y - a.y, b.x - a.x)

    def estimate_error_deg(self) -> float:
        """|estimated - true| centre-line angle (deg); NaN while the estimate is invalid."""
        if not self.estimator.valid or not self.estimator.pairs:
            return math.nan
        return abs(math.degrees(_wrap(self.estimator.last[0] - self.true_angle())))

    def _note_up(self, heights: Sequence[float], tick: int) -> None:
        """Since when every object has been ``LIFT_HEIGHT`` up, at ``tick``."""
        if min(heights) < LIFT_HEIGHT:
            self._up_since = None
        elif self._up_since is None:
            self._up_since = tick

    # -- running ----------------------------------------------------------------------------
    def run_phase(
        self,
        phase: Phase,
        *,
        lifted: bool = False,
        record_errors: bool = False,
        stop: Callable[[], bool] | None = None,
    ) -> PhaseOutcome:
        """Run ``phase`` from the current state, entered as the runner enters it from the
        previous phase (``self.handover``; from rest at the start), with ``self.torques``
        applied until the first command arrives.

        ``lifted`` says the objects are up already, so falling back counts as a drop; ``stop``
        (checked every few ticks) ends the phase early, with the exit "stopped".
        """
        # a final ramp of some length, so that on the tick the phase is left the runner still
        # holds, unramped, the torque and the damping it hands the next phase
        recipe = Recipe(
            "episode", "<episode>", "", (phase,), 1.0, None, False, limit_guard=self.guard
        )
        # the host's loop at the hand's own rate, the plant at the nodes' 1 ms tick: a plan
        # at 1 kHz for a hand at 250 Hz scored a controller that hand does not run
        period = self.hand.bus.period_s
        period_ns, node_ns = round(period * 1e9), round(NODE_TICK_S * 1e9)
        backoff = RateBackoff.for_hand(self.hand, period)  # unless handed over
        runner = RecipeRunner(
            recipe, self.hand.n_joints, self.handover, backoff=backoff, period_s=period
        )
        plant, est = self.plant, self.estimator
        quantum = self._quantum
        t0 = self.tick
        first = self.true_angle()
        previous = first
        turned = 0.0
        # the true centre line every tick, unwrapped, over the last window: the peak rate
        window = max(1, round(RATE_WINDOW_S / period))
        recent: deque[float] = deque(maxlen=window + 1)
        line, line_last = first, first
        peak = 0.0
        est_start = math.nan
        min_height = math.inf
        margin = math.inf
        errors: list[float] = []
        exit_reason = ""
        tick = 0
        steps = math.ceil((phase.max_s + 2 * period) / period)
        zeros = np.zeros(self.hand.n_joints)
        lo_list, hi_list = self._lo, self._hi
        applied = np.array(self.torques, dtype=float)
        limits = self._limits
        out: tuple[float, ...] = ()
        # an object already on the table as the phase begins was never lifted: the lift
        # before it failed, and "fell back" said it had been up (found by an outside audit)
        never_up = lifted and min(self.heights()) < DROP_MARGIN
        for tick in range(steps):
            now = self.true_angle()
            line += _wrap(now - line_last)
            line_last = now
            recent.append(line)
            if len(recent) > window:
                peak = max(peak, abs(recent[-1] - recent[0]))
            raw = plant.joint_angles
            angles = [round(float(q) / quantum) * quantum for q in raw]
            # the soft limits every tick, on the measured angles, as the supervisor checks them
            worst = min(
                min(q - lo, hi - q) for q, lo, hi in zip(angles, lo_list, hi_list, strict=True)
            )
            margin = min(margin, worst)
            if worst < 0.0:
                bad = next(j for j, q in enumerate(angles) if q < lo_list[j] or q > hi_list[j])
                exit_reason = f"fail: {self.hand.joint_names[bad]} outside its soft limits"
                break
            # the tick a phase was left on is this phase's first: its estimates are those
            out = self._estimates if tick == 0 and self._estimates is not None else est(angles)
            if math.isnan(est_start) and est.valid and est.pairs:
                est_start = out[1]
            desired = runner.step((t0 + tick) * period, np.asarray(angles), zeros, out)
            if runner.index > 0 or runner.status is not RunStatus.RUNNING:
                break
            # the nodes apply a command one of their ticks after the host computed it (the
            # bus), so the plant's first tick of this period gets the previous command and
            # the others this one (none at 1 kHz); the supervisor limits every command
            plant.set_torque_commands(applied)
            limit_torque(desired, applied, limits, period, applied)
            at = t0 + tick
            node_ticks = (at + 1) * period_ns // node_ns - at * period_ns // node_ns
            for k in range(node_ticks):
                if k == 1:
                    plant.set_torque_commands(applied)
                plant.step()
            if tick % CHECK_EVERY == 0:
                now = self.true_angle()
                turned += _wrap(now - previous)
                previous = now
                heights = self.heights()
                min_height = min(min_height, *heights)
                self._note_up(heights, t0 + tick)
                if record_errors:
                    err = self.estimate_error_deg()
                    if not math.isnan(err):
                        errors.append(err)
                if lifted and min(heights) < DROP_MARGIN:
                    exit_reason = (
                        "fail: an object was never lifted (the lift left it on the table)"
                        if never_up
                        else "fail: an object fell back to the table"
                    )
                    break
                if not self.in_hand():
                    exit_reason = "fail: an object left the hand"
                    break
                if stop is not None and stop():
                    exit_reason = "stopped"
                    break
        if not exit_reason:
            exit_reason = runner.records[0].exit if runner.records else "timeout"
        self.torques = tuple(float(x) for x in applied)
        self.handover = runner.handover()
        self.tick = t0 + tick
        # the phase was left on this tick, its plant not stepped: the next phase runs it again
        self._estimates = out if runner.index > 0 else None
        now = self.true_angle()
        turned += _wrap(now - previous)
        est_turn = (
            (est.last[1] - est_start) if est.valid and not math.isnan(est_start) else math.nan
        )
        return PhaseOutcome(
            exit=exit_reason,
            duration_s=tick * period,
            true_turn_deg=math.degrees(turned),
            est_turn_deg=math.degrees(est_turn),
            min_height=min_height if min_height < math.inf else min(self.heights()),
            end_height=min(self.heights()),
            limit_margin=margin,
            pair_gap=self.pair_gap(),
            pair_blocked=self.pair_blocked(),
            in_hand=self.in_hand(),
            est_valid=est.valid,
            est_error_deg=self.estimate_error_deg(),
            errors_deg=errors,
            peak_rate_deg_s=math.degrees(peak / (window * period)),
            held_s=0.0 if self._up_since is None else (self.tick - self._up_since) * period,
        )


def _segment_distance(
    p: tuple[float, float], q: tuple[float, float], r: tuple[float, float], s: tuple[float, float]
) -> float:
    """Distance between segments pq and rs in the plane."""

    def cross(o: tuple[float, float], a: tuple[float, float], b: tuple[float, float]) -> float:
        return (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0])

    if (cross(p, q, r) * cross(p, q, s) < 0) and (cross(r, s, p) * cross(r, s, q) < 0):
        return 0.0

    def point(x: tuple[float, float], a: tuple[float, float], b: tuple[float, float]) -> float:
        dx, dy = b[0] - a[0], b[1] - a[1]
        n = dx * dx + dy * dy
        t = 0.0 if n == 0 else max(0.0, min(1.0, ((x[0] - a[0]) * dx + (x[1] - a[1]) * dy) / n))
        return math.hypot(x[0] - a[0] - t * dx, x[1] - a[1] - t * dy)

    return min(point(p, r, s), point(q, r, s), point(r, p, q), point(s, p, q))


def with_torques(phase: Phase, torques: Sequence[float] | np.ndarray) -> Phase:
    """The phase with other torques (what the search varies)."""
    return dataclasses.replace(phase, torques=tuple(float(t) for t in torques))
