"""Runs a recipe tick by tick: the desired torques of the current phase, ramps, exits, aborts,
and the feedback a phase asks for.

The runner only proposes torques; the supervisor decides what is applied. It is a pure function
of time and the observed state (no clock of its own, no I/O), which is what lets a replay feed
logged feedback through it and get the very same torques.

A tick is two steps (``step`` does both): ``advance`` (exits, aborts, the phase's ramp) and
``feedback`` (what the hand measures moves the torque within what the phase allows, then the
soft-limit guard). The loop times them apart, so the feedback's cost shows as its own stage.
Feedback, all of it from the angles and the estimates computed from them:

- ``turn_rate``: the phase's torque times a scale in ``[scale_min, scale_max]``, set by a
  proportional-integral loop on the estimated centre-line rate (the derivative of the first
  pair's ``line_turn``, low-passed over ``RATE_TIME_CONSTANT``). While the estimate is invalid
  the scale holds. The loop starts at the plan's own torque (scale 1).
- ``pose``: a joint-space spring and damper towards the phase's pose, ramped in with the
  phase's torques; with ``integral``, once the ramp is done, a bounded integral of each
  stopped joint's distance from the pose the nominal hand rests in (``_pose_integrate``), so
  friction the model does not know cannot hold a finger short of it.
- ``brake``: more injected damping while the pair tumbles: none while the estimated
  centre-line rate is at most the brake's rate, rising to its ``joint_damping`` at twice
  that rate, on top of the phase's own ``joint_damping``; with a ``joint_rate``, the same
  while the fastest joint moves faster than that, whichever is the further over (the
  joints are measured every tick, the pair only while its cage is closed, and a pair
  swept along the palm opens it). A damper that acts only on a
  tumble slows the roll-over of a lightly damped hand and leaves alone a heavily damped one,
  whose pair a fixed damper would let fall back.
- ``paced_ramp``: the ramp into the phase moves along the segment from the previous
  phase's torque to this one's at a pace set by the pair (``_pace_step``): on while it
  turns slower than wanted, back while faster. The previous phase's torque brought the
  pair to where this phase begins, so between the two lies a torque that turns it slowly.
- ``blind_joint_rate`` (of a ``paced_ramp`` or a ``brake``): while the pair's estimate is
  invalid, the fastest joint against that rate in place of the pair's last rate, which
  says nothing about a pair swept along the palm with its cage open.
- ``turn_from``: a phase's exits read the turn from where the pair was when an earlier
  phase began (the paper switches on where the pair is, so what one phase left undone
  the next takes up); ``exit_share``: a phase's exit on that turn moves, once the phase
  measures the pair, to an even share of what is left to it among this phase and the next
  ones (``_threshold``); ``stall``: a phase ends once its torque is fully in and the turn
  has stopped moving (``_stalled``).
- ``reanalyse``: on the phase's first tick with a valid estimate the runner asks its
  ``Reanalyser`` for the analysis' torque at the measured configuration, and ``delay_s``
  later takes the answer: the phase's ramp starts again, from the torque proposed then to
  the answer (``_reanalyse``); no answer, or none robust, keeps the planned torque.
- ``joint_damping``: ``-joint_damping * velocity`` on each joint (the velocity is the
  slope of a line through the last eight angles, ``velocity.FittedVelocity``, as the
  guard's: a damper acts through the drive's lag plus the velocity's own, and on a lightly
  damped joint the most it may inject without ringing falls with that lag; the 10 ms
  low-pass it used before cost a third of the manipulation's successes at 0.06). The
  hand's own joint damping is what a real hand knows least (a tendon's losses are not
  measured to a factor of three), and in a turn it sets how fast the grasp rolls over: the
  fingers are torque-controlled, and what the analysis' margin puts into a roll only
  damping takes out. An injected term larger than that uncertainty makes the pace of the
  motion the recipe's. The coefficient moves from the previous phase's to this one's with
  the ramp, so a change of damping is no step in torque. Given per joint, each joint has
  its own: a light distal link tolerates far less through the lag than a proximal joint
  that carries the finger and the pair (docs/experiment.md, *The manipulation damped and
  ramped slowly*). With a ``RateBackoff`` (every run and every plan has one), a joint's
  injected damping, the brake's included, backs off while the supervisor's rate limit clips
  its command, where a damper pumps a light joint's ring instead of damping it
  (``backoff.py``; docs/experiment.md, *The injected damping backs off where the rate limit
  clips it*).
"""

from __future__ import annotations

import enum
import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from handctl.arrays import FloatArray
from handctl.online.recipes.backoff import RateBackoff
from handctl.online.recipes.guard import fitted_window
from handctl.online.recipes.reanalysis import Reanalyser
from handctl.online.recipes.schema import (
    FIRST_PAIR_TURN,
    Condition,
    MeasuredSizes,
    PacedRamp,
    Phase,
    PoseHold,
    PoseIntegral,
    Recipe,
    SignalKind,
    TimeoutAction,
)
from handctl.online.recipes.velocity import FittedVelocity, JointVelocity

#: s, the low-pass of the estimated centre-line rate: the estimate moves in steps of the
#: encoder's resolution, and the rate loop must not chase them
RATE_TIME_CONSTANT = 0.03
_TURN = FIRST_PAIR_TURN


class RunStatus(enum.Enum):
    RUNNING = "running"
    END_RAMP = "end_ramp"  # the ramp back to zero after the last phase (recipe: end_ramp_s)
    COMPLETED = "completed"
    ABORTED = "aborted"


@dataclass
class PhaseRecord:
    name: str
    start_s: float
    end_s: float | None = None
    exit: str = ""  # the condition text, "timeout", "abort: ...", or "stopped"
    reanalysis: str = ""  # what a ``reanalyse`` phase's analysis answered ("": none asked)
    #: which of a ``schedule`` phase's torques ran and on what was measured ("": no schedule)
    schedule: str = ""
    #: each joint's least gain on its injected damping while the phase ran (``backoff.py``;
    #: the back-off's own list, filled as it goes); empty: no back-off
    least_damping_gain: list[float] = field(default_factory=list)


@dataclass
class Handover:
    """What one phase hands the next within a run: the torque the next ramp starts from (the
    last proposed, feedback included, before injected damping and the guard), the injected
    damping it fades from, and the velocity filters' history. The planner runs each phase on
    a runner of its own; starting that runner from the previous one's handover makes the
    phase begin as it does in a run of the whole recipe."""

    torques: FloatArray
    damping: FloatArray  # N·m·s/rad, per joint
    velocity: JointVelocity
    fitted_velocity: FittedVelocity
    #: the injected damping's back-off, whose mirror of the limiter goes on with the run
    backoff: RateBackoff | None = None


class RecipeRunner:
    """The state of one execution of a recipe."""

    def __init__(
        self,
        recipe: Recipe,
        n_joints: int,
        after: Handover | None = None,
        reanalyser: Reanalyser | None = None,
        sizes: MeasuredSizes | None = None,
        backoff: RateBackoff | None = None,
        period_s: float = 0.001,
    ) -> None:
        """``period_s`` (s) is the period of the loop that feeds it, on which the dampers'
        velocity is a line spanning ``GUARD_VELOCITY_SPAN_S``."""
        self.recipe = recipe
        # the injected damping's gains against the supervisor's rate limit (backoff.py);
        # None: the recipe's damping as it is (a runner driving no supervisor)
        self.backoff = backoff
        # this runner's last proposal, which the back-off takes in on the next tick
        self._last_proposal = np.zeros(n_joints)
        self._proposals = False
        # the objects' measured sizes (the estimator), for ``schedule`` phases; None: their
        # own torques
        self.sizes = sizes
        self._scheduled = True  # whether this phase's schedule is settled
        # the analysis at the measured configuration (``reanalyse`` phases); None: their
        # planned torques
        self.reanalyser = reanalyser
        self.n = n_joints
        self.status = RunStatus.RUNNING
        self.index = -1
        self.phase_start = 0.0
        self.records: list[PhaseRecord] = []
        self.abort_reason = ""
        self._from = np.zeros(n_joints)
        self._target = np.zeros(n_joints)
        self._desired = np.zeros(n_joints)
        self._ramp_s = 0.0
        self._ramp_start = 0.0  # s, where the ramp began: the phase's start, or a reanalysis
        self._asked_at = math.nan  # s, when this phase asked for its reanalysis
        self._answered = False  # whether this phase's reanalysis is settled
        self._held_since: dict[int, float] = {}
        # per phase, the first finite value of each phase-relative estimate while it ran, by
        # index: a phase's exits read the turn from its own start or an earlier phase's
        self._refs: list[dict[int, float]] = [{} for _ in recipe.phases]
        self._relative = sorted(
            {c.index for p in recipe.phases for c in (*p.exits, *p.aborts) if c.relative}
        )
        names = [p.name for p in recipe.phases]
        self._turn_from = [
            names.index(p.turn_from) if p.turn_from else k for k, p in enumerate(recipe.phases)
        ]
        # the stall detector: the turn and the time it last moved by more than its ``turn``
        self._stall_turn = math.nan
        self._stall_t = math.nan
        self._started = False
        self._guard = recipe.limit_guard
        self._guarded = np.zeros(n_joints)
        # from the angles it is fed, so a re-run of the logged feedback gets the same values
        self.velocity = JointVelocity(n_joints)
        # less smoothed, for every damper that acts through the drive's lag (the guard's, the
        # injected damping and the brake): a damper's stable gain on a light link falls with
        # the lag around it, and this one adds 3.5 ms where the low-pass adds 10. Kept for
        # every recipe (about 4 µs a tick): a phase's damping may come in through a handover
        self._fitted_velocity = FittedVelocity(n_joints, fitted_window(period_s))
        self._fraction = 1.0  # of the current ramp
        # the turn-rate loop of the current phase: scale, its integral part, the rate
        self.scale = 1.0
        self._scale_i = 1.0
        self.turn_rate = 0.0  # rad/s, estimated, low-passed
        # whether the pair's estimate was invalid this tick (its cage open): ``turn_rate``
        # is then the last one seen, not the pair's present rate
        self.blind = False
        self._turn_last = math.nan
        self._turn_t = math.nan
        self._turn_dt = 0.0
        self._proposed = np.zeros(n_joints)
        self._delta = np.zeros(n_joints)
        self._fed = False  # whether ``_proposed`` holds this phase's last proposal
        # injected joint damping (N·m·s/rad): the previous phase's, this one's, and between
        # them as the ramp goes, so a change of damping is no step in torque
        self._damping_from = np.zeros(n_joints)
        self._damping_to = np.zeros(n_joints)
        self.damping = np.zeros(n_joints)
        self._damped = np.zeros(n_joints)
        # whether that ramp has work (a coefficient not zero), and whether ``damping`` holds
        # what the ramp alone would not (the brake's, or a phase's before): most phases have
        # no injected damping, and the ramp's array operations cost 3 µs a tick
        self._damping_ramped = False
        self._damping_stale = False
        # a paced ramp's fraction along its segment, and when it last moved
        self.pace = 0.0
        self._pace_t = math.nan
        # a paced ramp's furthest turn the wanted way in this phase (rad) and how far the
        # pair is behind it now
        self._furthest = math.nan
        self._behind = 0.0
        # each joint's depth into its guard's band now, and where a paced ramp's
        # ``limit_depth`` starts for it in this phase (``_limit_cap``)
        self._depth = np.zeros(n_joints)
        self._depth_from = np.zeros(n_joints)
        self._depth_known = False
        # a pose hold's integral (N·m per joint) and when it last grew
        self._pose_i = np.zeros(n_joints)
        self._pose_i_t = math.nan
        # per finger: whether a joint of it is past the integral's rest pose this tick
        self._finger_past = np.zeros(n_joints, dtype=bool)
        if after is not None:  # the first phase is entered from the handed-over state
            self._desired[:] = after.torques
            self.damping[:] = after.damping
            self.velocity = after.velocity
            self._fitted_velocity = after.fitted_velocity
            if after.backoff is not None:
                self.backoff = after.backoff

    def handover(self) -> Handover:
        """What the next phase would start from now (its filters are this runner's own)."""
        torques = (self._proposed if self._fed else self._desired).copy()
        damping = np.zeros(self.n) if self._damping_ends() else self.damping.copy()
        return Handover(torques, damping, self.velocity, self._fitted_velocity, self.backoff)

    def damping_backoff(self, k: int) -> list[tuple[int, float]]:
        """The joints whose injected damping backed off while record ``k``'s phase ran, and
        the least gain each had: joints the phase damped (its ``joint_damping``, or every
        joint under a brake), not those whose command the rate limit clipped undamped."""
        record = self.records[k]
        phase = next((p for p in self.recipe.phases if p.name == record.name), None)
        if phase is None or not record.least_damping_gain:
            return []
        damped = np.broadcast_to(np.asarray(phase.joint_damping, dtype=float), (self.n,))
        return [
            (j, g)
            for j, g in enumerate(record.least_damping_gain)
            if g < 1.0 and (damped[j] > 0.0 or phase.brake is not None)
        ]

    def _damping_ends(self) -> bool:
        """Whether the current phase's injected damping ends with it instead of fading over
        the next phase's ramp (``joint_damping_fades``)."""
        return 0 <= self.index < len(self.recipe.phases) and (
            not self.recipe.phases[self.index].joint_damping_fades
        )

    @property
    def phase_name(self) -> str:
        """The current phase, or else the runner's status (``end_ramp`` during the final ramp):
        what the log records as the phase."""
        if 0 <= self.index < len(self.recipe.phases):
            return self.recipe.phases[self.index].name
        return str(self.status.value)

    @property
    def done(self) -> bool:
        return self.status in (RunStatus.COMPLETED, RunStatus.ABORTED)

    @property
    def in_phase(self) -> bool:
        """Whether one of the recipe's phases is under way (not the end ramp, not done)."""
        return not self.done and bool(self.records) and self.records[-1].end_s is None

    def _enter(self, index: int, t: float, reason: str) -> None:
        if self.records:
            self.records[-1].end_s = t
            self.records[-1].exit = reason
        # the next ramp starts from what was proposed, feedback included, so that leaving a
        # phase with feedback is no step in torque
        self._from = (self._proposed if self._fed else self._desired).copy()
        self._fed = False
        self.phase_start = t
        self._ramp_start = t
        self._asked_at = math.nan
        self._answered = False
        self._settle_unmeasured()
        if self._damping_ends():
            self._damping_from[:] = 0.0
        else:
            self._damping_from[:] = self.damping
        self._held_since.clear()
        self._stall_turn = self._stall_t = math.nan
        self._pose_i[:] = 0.0
        self._pose_i_t = math.nan
        self.scale = self._scale_i = 1.0
        self.turn_rate = 0.0
        self.blind = False
        self._turn_last = self._turn_t = math.nan
        self.pace = 0.0
        self._pace_t = t
        self._furthest = math.nan
        self._behind = 0.0
        self._depth_known = False
        if index < len(self.recipe.phases):
            phase = self.recipe.phases[index]
            self.index = index
            self._target = np.array(phase.torques) * np.asarray(phase.torque_margin)
            self._ramp_s = phase.ramp_s
            self._damping_to[:] = phase.joint_damping
            self.records.append(PhaseRecord(phase.name, t))
            if self.backoff is not None:
                self.backoff.least = self.records[-1].least_damping_gain = [1.0] * self.n
            self._scheduled = not phase.schedule
        else:
            self.index = len(self.recipe.phases)
            self.status = RunStatus.END_RAMP
            self._target = np.zeros(self.n)
            self._ramp_s = self.recipe.end_ramp_s
            self._damping_to[:] = 0.0
        self._note_damping_ramp()

    def _ramp_damping(self, fraction: float) -> None:
        """``damping`` at ``fraction`` of the phase's ramp, from the previous phase's to this
        one's (left at zero without a coefficient to ramp)."""
        if self._damping_ramped:
            np.subtract(self._damping_to, self._damping_from, out=self.damping)
            self.damping *= fraction
            self.damping += self._damping_from
        elif self._damping_stale:
            self.damping.fill(0.0)
        self._damping_stale = False

    def _note_damping_ramp(self) -> None:
        """After the damping's ramp was set: whether it has work, and that ``damping`` is to
        be recomputed or cleared on the next ``advance``."""
        self._damping_ramped = bool(self._damping_from.any() or self._damping_to.any())
        self._damping_stale = True

    def step(
        self, t: float, angle: FloatArray, tdt: FloatArray, estimates: Sequence[float] | None = None
    ) -> FloatArray:
        """Desired torques at time ``t`` (s since the recipe started): ``advance`` then
        ``feedback``."""
        self.advance(t, angle, tdt, estimates)
        return self.feedback(t, angle, estimates)

    def advance(
        self, t: float, angle: FloatArray, tdt: FloatArray, estimates: Sequence[float] | None = None
    ) -> None:
        """Exits, aborts and the ramp of the current phase at ``t``: the recipe's own torque,
        before any feedback."""
        # Every phase is judged from the tick after the one it was entered on, the first one
        # too: checked on its first tick, a first phase whose exit held at once ended in the
        # tick it began, so no tick of the log ran it, and its holds counted a tick less than
        # every later phase's.
        entering = not self._started
        if entering:
            self._started = True
            self._enter(0, t, "")
        if self.done:
            self._desired[:] = 0.0
            return
        self.velocity.update(t, angle)
        self._fitted_velocity.update(t, angle)
        # to the microsecond: a bare difference of two tick times is a hair under or over a
        # phase's max_s (or a time condition's value) by where the phase began, and a max_s of
        # 0.01 s ran 10 ticks or 11; at 300 Hz a period of whole nanoseconds (3 333 333) is
        # short by a third of one, and three ticks were 9 999 999 ns, a tick too few for 0.01 s
        elapsed = round(t - self.phase_start, 6)
        if self.status is RunStatus.RUNNING:
            phase = self.recipe.phases[self.index]
            if estimates is not None:
                self._note_references(estimates)
            if not entering:
                self._judge(phase, t, elapsed, angle, tdt, estimates)
                if self.done:
                    return  # aborted: its torque is zero from this tick on (``abort``)
            if self.status is RunStatus.RUNNING and not self._scheduled:
                self._schedule(t)
            if self.status is RunStatus.RUNNING and not self._answered:
                self._reanalyse(t, angle, estimates)
        ramped = t - self._ramp_start
        fraction = 1.0 if self._ramp_s <= 0 else min(1.0, ramped / self._ramp_s)
        self._fraction = fraction
        self._ramp_damping(fraction)
        np.subtract(self._target, self._from, out=self._desired)
        self._desired *= fraction
        self._desired += self._from
        if self.status is RunStatus.END_RAMP and fraction >= 1.0:
            self.status = RunStatus.COMPLETED

    def _judge(
        self,
        phase: Phase,
        t: float,
        elapsed: float,
        angle: FloatArray,
        tdt: FloatArray,
        estimates: Sequence[float] | None,
    ) -> None:
        """The phase's aborts, exits, stall and timeout at ``t``: abort, or go on to the next
        phase, or nothing."""
        for k, cond in enumerate(phase.aborts):
            if self._held(1000 + k, cond, t, elapsed, angle, tdt, estimates):
                self.abort(t, f"abort: {cond.text}")
                return
        reason = next(
            (
                self._exit_text(phase, c)
                for k, c in enumerate(phase.exits)
                if self._held(k, c, t, elapsed, angle, tdt, estimates, self._threshold(phase, c))
            ),
            None,
        )
        if reason is None and phase.stall is not None and self._stalled(t, elapsed, estimates):
            reason = (
                f"stalled: turned less than {math.degrees(phase.stall.turn):g} deg"
                f" in {phase.stall.window_s:g} s"
            )
        if reason is None and elapsed >= phase.max_s:
            if phase.on_timeout is TimeoutAction.ABORT:
                self.abort(t, f"timeout: phase '{phase.name}' ran {phase.max_s:g} s")
                return
            reason = "timeout"
        if reason is not None:
            self._enter(self.index + 1, t, reason)

    def feedback(
        self, t: float, angle: FloatArray, estimates: Sequence[float] | None = None
    ) -> FloatArray:
        """The torque to propose: the phase's, moved by its feedback from what the hand
        measures, then guarded. Bounded work: a few operations per joint."""
        if self.done:
            self._desired[:] = 0.0
            return self._desired
        if self.backoff is not None and self._proposals:
            # the last tick's proposal, now that it is known to have been sent: the planner
            # drops the proposal of the tick a phase is left on, which the next phase's
            # runner proposes again
            self.backoff.observe(self._last_proposal)
        phase = self.recipe.phases[self.index] if self.status is RunStatus.RUNNING else None
        out = self._desired
        fresh = False  # whether the turn-rate estimate took a new sample this tick
        if phase is not None and (
            phase.turn_rate is not None or phase.brake is not None or phase.paced is not None
        ):
            fresh = self._follow_turn(t, estimates)
        if phase is not None and phase.brake is not None:
            brake = phase.brake
            if self.blind and brake.blind_joint_rate > 0.0:
                blind = brake.blind_joint_rate
                over = (self._fastest_joint() - blind) / blind
            else:
                over = (abs(self.turn_rate) - brake.rate) / brake.rate
            if brake.joint_rate > 0.0:
                fastest = self._fastest_joint()
                over = max(over, (fastest - brake.joint_rate) / brake.joint_rate)
            braked = self._fraction * brake.damping * min(1.0, max(0.0, over))
            if braked > 0.0:
                self.damping += braked
                self._damping_stale = True
        if phase is not None and (
            phase.turn_rate is not None or phase.pose is not None or phase.paced is not None
        ):
            # the ramp state stays the recipe's own torque; only what is proposed moves
            out = self._proposed
            out[:] = self._desired
            self._fed = True
            if phase.paced is not None:
                self._pace_step(t, phase.paced, phase.ramp_s, angle)
                # from + pace * (target - from), where the ramp put from + fraction * (...)
                np.subtract(self._target, self._from, out=self._delta)
                self._delta *= self.pace - self._fraction
                out += self._delta
            if phase.turn_rate is not None:
                if fresh:
                    self._turn_loop()
                # from + fraction * (scale * target - from)
                np.multiply(self._target, (self.scale - 1.0) * self._fraction, out=self._delta)
                out += self._delta
            if phase.pose is not None:
                self._pose_hold(t, phase.pose, angle, out)
        out = self._damp(out)
        if self._guard is not None:
            out = self._guard.apply(angle, out, self._guarded, self._fitted_velocity.value)
        self._last_proposal[:] = out
        self._proposals = True
        return out

    def _damp(self, out: FloatArray) -> FloatArray:
        """``out`` less the injected damping, backed off on a joint whose command the rate
        limit clips (``backoff.py``): apart from ``_proposed``, which the next phase's ramp
        starts from, as the damping carries over through ``self.damping`` instead."""
        if not (self._damping_ramped or self._damping_stale):
            return out
        np.multiply(self._fitted_velocity.value, self.damping, out=self._damped)
        if self.backoff is not None:
            self._damped *= self.backoff.gain
        np.subtract(out, self._damped, out=self._damped)
        return self._damped

    def _pose_hold(self, t: float, pose: PoseHold, angle: FloatArray, out: FloatArray) -> None:
        """Add a pose hold's spring and damper, ramped in with the phase, and its integral."""
        v = self.velocity.value
        for j, q_ref in enumerate(pose.angles):
            out[j] += self._fraction * (
                pose.stiffness * (q_ref - float(angle[j])) - pose.damping * float(v[j])
            )
        if pose.integral is not None:
            self._pose_integrate(t, pose.integral, angle)
            out += self._pose_i

    def _pose_integrate(self, t: float, integral: PoseIntegral, angle: FloatArray) -> None:
        """One step of a pose hold's integral: only once the phase's ramp is done and only on
        a joint that has stopped, so that it makes up for what friction holds back, never
        for a joint still on its way (which would wind it up and overshoot). It only adds to
        what the phase's torque asks of a joint (none on a joint it asks nothing of), and it
        grows only while every joint of the finger is short of the rest pose the way the
        torque pushes it: it pushes a finger that friction holds back on, and leaves alone
        one that a hand with less friction let go further (a start phase closes the fingers
        towards the objects, and the objects are what stops them there)."""
        dt = t - self._pose_i_t
        self._pose_i_t = t
        if not dt > 0.0 or self._fraction < 1.0:
            return
        v = self.velocity.value
        bound = integral.max
        target = self._target
        past = self._finger_past
        past[:] = False
        for j, q_rest in enumerate(integral.rest):
            if float(target[j]) * (float(angle[j]) - q_rest) > 0.0:
                past[integral.finger_of[j]] = True
        for j, q_rest in enumerate(integral.rest):
            if abs(float(v[j])) >= integral.still_rate:
                continue
            now = float(self._pose_i[j])
            grown = now + integral.gain * (q_rest - float(angle[j])) * dt
            if past[integral.finger_of[j]] and abs(grown) > abs(now):
                continue  # the finger went further: only unwind
            way = float(target[j])
            low, high = (0.0, bound) if way > 0.0 else (-bound, 0.0) if way < 0.0 else (0.0, 0.0)
            self._pose_i[j] = max(low, min(high, grown))

    def _follow_turn(self, t: float, estimates: Sequence[float] | None) -> bool:
        """One step of the estimated centre-line rate (``turn_rate``, rad/s); False when there
        was no new valid sample to take."""
        turn = float(estimates[_TURN]) if estimates is not None else math.nan
        self.blind = not math.isfinite(turn)
        if self.blind:
            self._turn_last = math.nan  # the rate restarts from the next valid estimate
            return False
        dt = t - self._turn_t
        if math.isnan(self._turn_last) or not dt > 0.0:
            self._turn_last, self._turn_t = turn, t
            return False
        raw = (turn - self._turn_last) / dt
        self.turn_rate += (raw - self.turn_rate) * dt / (RATE_TIME_CONSTANT + dt)
        self._turn_last, self._turn_t = turn, t
        self._turn_dt = dt
        return True

    def _reanalyse(self, t: float, angle: FloatArray, estimates: Sequence[float] | None) -> None:
        """Ask for the analysis at the configuration the pair is measured in (the phase's
        first tick with a valid estimate), and ``delay_s`` later take the answer: the ramp
        starts again from the torque proposed last to the answer's, so taking it is no step
        in torque. Work on the tick: a copy of the angles and estimates, once a phase."""
        phase = self.recipe.phases[self.index]
        wanted = phase.reanalyse
        if wanted is None:
            self._answered = True
            return
        record = self.records[-1]
        if math.isnan(self._asked_at):
            if self.reanalyser is None:
                self._answered = True
                record.reanalysis = "not run: no analysis in this run; the planned torque"
                return
            if estimates is None or not math.isfinite(float(estimates[_TURN])):
                return  # the pair is not measured yet: ask once it is
            self.reanalyser.submit(self.index, angle.tolist(), tuple(estimates))
            self._asked_at = t
            return
        if t - self._asked_at < wanted.delay_s - 1e-12:
            return
        self._answered = True
        result = self.reanalyser.collect(self.index) if self.reanalyser is not None else None
        if result is None:
            record.reanalysis = (
                f"late: no answer {wanted.delay_s:g} s after the request; the planned torque"
            )
            return
        record.reanalysis = result.note
        if result.torques is None:
            return
        self._ramp_again(t)
        self._target = np.array(result.torques, dtype=float)

    def _ramp_again(self, t: float) -> None:
        """Start the phase's ramp (and its paced ramp) again at ``t``, from the torque
        proposed last and the injected damping reached, towards a target set now: a new
        target within a phase is then no step in torque."""
        self._from = (self._proposed if self._fed else self._desired).copy()
        self._damping_from += self._fraction * (self._damping_to - self._damping_from)
        self._note_damping_ramp()
        self._ramp_start = t
        self.pace = 0.0
        self._pace_t = t

    def _settle_unmeasured(self) -> None:
        """The phase ends with its schedule still waiting for a measured radius: it ran its
        own torques, and its record says so."""
        if self.records and not self._scheduled:
            self.records[-1].schedule = "not measured while the phase ran: its own torques"
        self._scheduled = True

    def _schedule(self, t: float) -> None:
        """Choose the phase's torque from its ``schedule`` on the objects' measured radii,
        once: on its first tick if they are measured by then (the ramp into the phase then
        goes to the chosen torque), else on the first tick they are (the ramp starts again,
        from the torque proposed last to the chosen one, so the choice is no step in
        torque). The first entry whose every range holds; none: the phase's own torques.
        Work on the tick: a comparison per range, once a phase."""
        phase = self.recipe.phases[self.index]
        record = self.records[-1]
        if self.sizes is None:
            self._scheduled = True
            record.schedule = "not measured: no estimator in this run; its own torques"
            return
        wanted = sorted({r.object for s in phase.schedule for r in s.when})
        ratios: dict[int, float] = {}
        for k in wanted:
            radius = self.sizes.measured_radius(k)
            if radius is None:
                return  # not measured yet: choose once it is
            ratios[k] = radius / self.recipe.objects[k].radius
        self._scheduled = True
        measured = ", ".join(
            f"{self.recipe.objects[k].name} radius x{ratios[k]:.3f}" for k in wanted
        )
        chosen = next(
            (
                k
                for k, entry in enumerate(phase.schedule)
                if all(r.holds(ratios[r.object]) for r in entry.when)
            ),
            None,
        )
        if chosen is None:
            record.schedule = f"{measured}: its own torques"
            return
        late = t > self.phase_start
        record.schedule = f"{measured}: schedule[{chosen}]" + (
            f" from {t - self.phase_start:.3f} s into the phase" if late else ""
        )
        if late:  # chosen after the phase began: ramp again from what is proposed now
            self._ramp_again(t)
        self._target = np.array(phase.schedule[chosen].torques) * np.asarray(phase.torque_margin)

    def _note_references(self, estimates: Sequence[float]) -> None:
        """Keep the first finite value of every phase-relative estimate in this phase, for
        its own exits and for those of later phases that read the turn from it."""
        refs = self._refs[self.index]
        for i in self._relative:
            if i not in refs:
                value = float(estimates[i])
                if math.isfinite(value):
                    refs[i] = value

    def _reference(self, index: int) -> float | None:
        """Where a phase-relative estimate is read from: its first finite value since the
        phase ``turn_from`` names began (this phase's own start by default)."""
        for k in range(self._turn_from[self.index], self.index + 1):
            ref = self._refs[k].get(index)
            if ref is not None:
                return ref
        return None

    def _threshold(self, phase: Phase, cond: Condition) -> float:
        """Where an exit of the current phase holds: its written value, or with an
        ``exit_share`` of N and a turn read relative to a phase's start, where the pair was
        when this phase first measured it plus 1/N of the way from there to the written value
        (NaN, which nothing holds against, until it is measured: never guessed)."""
        if phase.exit_share == 1 or not cond.relative:
            return cond.value
        start = self._refs[self.index].get(cond.index)
        ref = self._reference(cond.index)
        if start is None or ref is None:
            return math.nan
        began = start - ref
        return began + (cond.value - began) / phase.exit_share

    def _exit_text(self, phase: Phase, cond: Condition) -> str:
        """What the phase record says of an exit that held: its text, and with a shared
        threshold, where that was (the text's value is the whole turn, not this phase's)."""
        threshold = self._threshold(phase, cond)
        if threshold == cond.value or not math.isfinite(threshold):
            return cond.text
        return f"{cond.text}, 1/{phase.exit_share} of the rest: at {threshold:.4f}"

    def _stalled(self, t: float, elapsed: float, estimates: Sequence[float] | None) -> bool:
        """Whether the pair has turned less than the phase's ``stall.turn`` for its
        ``window_s`` with the phase's torque fully in. A tick without a valid estimate, or
        with the torque still coming in, starts the window again: a stall is measured, never
        assumed."""
        phase = self.recipe.phases[self.index]
        stall = phase.stall
        assert stall is not None
        turn = float(estimates[_TURN]) if estimates is not None else math.nan
        full = elapsed >= self._ramp_s and (phase.paced is None or self.pace >= phase.paced.reach)
        if not (full and math.isfinite(turn)) or not abs(turn - self._stall_turn) <= stall.turn:
            self._stall_turn, self._stall_t = turn, t
            return False
        return t - self._stall_t >= stall.window_s - 1e-12

    def _fastest_joint(self) -> float:
        """rad/s, the speed of the fastest joint: what a brake's or a paced ramp's
        ``joint_rate`` is compared with."""
        return float(np.max(np.abs(self.velocity.value)))

    def _pace_step(self, t: float, paced: PacedRamp, ramp_s: float, angle: FloatArray) -> None:
        """Move the paced ramp's fraction along its segment by the relative rate error: at
        the ramp's own speed while the pair turns slower than the wanted rate (or the wrong
        way), back at up to ``back`` times that while it turns faster, in proportion
        between. The pair's rate is the last one estimated (it holds while the estimate is
        invalid). With ``joint_rate`` the fastest joint counts as well, whichever is the
        further over: the joints are measured every tick, also while the cage is open.
        With ``blind_joint_rate``, while the estimate is invalid the fastest joint against
        that rate replaces the pair's last rate: a pair swept along the palm opens its
        cage, and the rate seen before (often a small turn the wrong way, which reads as
        slow) says nothing about the sweep."""
        dt = t - self._pace_t
        self._pace_t = t
        if not dt > 0.0:
            return
        if self.blind and paced.blind_joint_rate > 0.0:
            error = (paced.blind_joint_rate - self._fastest_joint()) / paced.blind_joint_rate
        else:
            wanted = abs(paced.rate)
            along = self.turn_rate if paced.rate > 0 else -self.turn_rate
            error = (wanted - along) / wanted
        if paced.joint_rate > 0.0:
            fastest = self._fastest_joint()
            error = min(error, (paced.joint_rate - fastest) / paced.joint_rate)
        if paced.limit_depth > 0.0:
            error = min(error, self._limit_cap(paced, angle))
        if paced.turn_back > 0.0:
            error = min(error, self._turn_back_cap(paced))
        speed = min(1.0, max(-paced.back, error)) / ramp_s
        self.pace = min(paced.reach, max(0.0, self.pace + speed * dt))

    def _turn_back_cap(self, paced: PacedRamp) -> float:
        """The most a paced ramp may go forward (as its relative error) with the pair where
        it is against the furthest it got the wanted way in this phase: on at full speed
        until it is ``turn_back`` behind, back at ``back`` at twice that, in proportion
        between (it holds ``1 / (1 + back)`` of the way: a third with ``back`` 2). The
        pair's last valid estimate counts while its cage is open."""
        turn = self._turn_last
        if math.isfinite(turn):
            along = turn if paced.rate > 0 else -turn
            if not along <= self._furthest:  # NaN at the phase's start
                self._furthest = along
            self._behind = self._furthest - along
        over = (self._behind - paced.turn_back) / paced.turn_back
        if over <= 0.0:
            return 1.0
        return 1.0 - (1.0 + paced.back) * min(1.0, over)

    def _limit_cap(self, paced: PacedRamp, angle: FloatArray) -> float:
        """The most a paced ramp may go forward (as its relative error) with its joints
        where they are in their soft-limit guard's bands: on at full speed while every
        joint is at most ``limit_depth`` of its band in, or no deeper than it was when the
        phase began, back at ``back`` at the limit, in proportion between (it holds
        ``1 / (1 + back)`` of the way). A joint the phase pushes that deep is its torque
        driving the hand into a limit rather than turning the pair, and pushing on ends in
        a safety stop; going back along the segment eases towards the torque that held the
        pair. Why from where it began: a grasp may lean a joint into its band on purpose
        (the lift's distal joints), and that is not this phase's doing."""
        guard = self._guard
        if guard is None:
            return 1.0
        band = guard.band
        depth = self._depth
        for j in range(self.n):
            q = float(angle[j])
            if q < guard.lower[j]:
                depth[j] = (guard.lower[j] - q) / band
            elif q > guard.upper[j]:
                depth[j] = (q - guard.upper[j]) / band
            else:
                depth[j] = 0.0
        if not self._depth_known:
            np.maximum(depth, paced.limit_depth, out=self._depth_from)
            self._depth_known = True
        cap = 1.0
        for j in range(self.n):
            start = float(self._depth_from[j])
            if depth[j] > start and start < 1.0:
                over = min(1.0, (float(depth[j]) - start) / (1.0 - start))
                cap = min(cap, 1.0 - (1.0 + paced.back) * over)
        return cap

    def _turn_loop(self) -> None:
        """One step of the proportional-integral loop of the scale on the turn rate."""
        loop = self.recipe.phases[self.index].turn_rate
        assert loop is not None
        dt = self._turn_dt
        wanted = abs(loop.rate)
        along = self.turn_rate if loop.rate > 0 else -self.turn_rate
        error = (wanted - along) / wanted
        lo, hi = loop.scale_min, loop.scale_max
        if self._fraction >= 1.0:  # no integral while the phase's torque still ramps in
            self._scale_i = min(hi, max(lo, self._scale_i + loop.integral * error * dt))
        self.scale = min(hi, max(lo, self._scale_i + loop.gain * error))

    def abort(self, t: float, reason: str) -> None:
        """Stop proposing torque; the supervisor takes the hand to zero."""
        if self.done:
            return
        if self.records and self.records[-1].end_s is None:
            self.records[-1].end_s = t
            self.records[-1].exit = reason
            self._settle_unmeasured()
        self.abort_reason = reason
        self.status = RunStatus.ABORTED
        self._desired[:] = 0.0

    def _held(
        self,
        key: int,
        cond: Condition,
        t: float,
        elapsed: float,
        angle: FloatArray,
        tdt: FloatArray,
        estimates: Sequence[float] | None,
        threshold: float | None = None,
    ) -> bool:
        """Whether ``cond`` has held for its ``hold_s`` at ``t``; ``threshold`` in place of
        its written value when given (an ``exit_share``'s), and never while that is unknown
        (NaN)."""
        if cond.kind is SignalKind.TIME:
            value = elapsed
        elif cond.kind is SignalKind.ANGLE:
            value = float(angle[cond.index])
        elif cond.kind is SignalKind.TDT:
            value = float(tdt[cond.index])
        else:
            if estimates is None:
                return False
            value = float(estimates[cond.index])
            if cond.relative:
                ref = self._reference(cond.index)
                if ref is None:
                    return False
                value -= ref
        if not cond.holds(value, threshold):
            self._held_since.pop(key, None)
            return False
        since = self._held_since.setdefault(key, t)
        return t - since >= cond.hold_s - 1e-12
