"""``handctl jog JOINT --torque X``: one joint under a small torque, to check its direction,
sign and scale before a recipe relies on them.

The jog is a recipe of one phase built in memory (the joint ramps to X N·m within its rate
limit, every other joint gets zero, then the end ramp back to zero) with the soft-limit guard,
run by the normal Runtime: every torque passes the supervisor with the hand's limits, exactly
as in a recipe run, and Ctrl-C is its controlled stop. A torque over half of the joint's
``tau_max`` (``JOG_SHARE``: the guard needs the rest) is refused before anything is opened or
sent; a recovery may ask the whole ``tau_max``.

The guard acts on every joint, not only the jogged one: a proximal joint's swing swings the
joints beyond it, and with zero torque a middle joint swung onto its soft limit would stop the
jog (``ANGLE_LIMIT``) at the small torques a bring-up starts with. Its push on another joint is
in the direction the hand config says, which is what a jog is there to check, so the command
names every other joint that got torque and how much; a sign that is wrong there pushes the
joint into its limit and the supervisor stops the jog.

With ``--recover`` the jog brings back a joint that rests outside its soft limits (after a
stop at speed, on its mechanical stop), which no other run can arm with. The supervisor then
allows that joint, and only it, outside its limits as long as it comes back in
(``handctl/online/safety/recovery.py``); the phase ends as soon as the joint is ``GUARD_BAND``
inside its range, so that the next run's soft-limit guard starts with it at rest outside its
band. The guard is off for a recovery but on one side of one joint: at and beyond the limit
the joint comes from it asks for the joint's whole ``tau_max``, a shove where a recovery wants
the small torque the user chose. The side the torque pushes the joint towards keeps it
(``recovery_guard``): the end ramp after the exit is ``MIN_RAMP_S`` at least, and under the
torque still in it a joint that came in at speed went on through its range into the other
soft limit (``ANGLE_LIMIT``, exit 3, on a range of 0.6 rad).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from handctl.bringup.zero_recipe import in_memory_recipe, phase
from handctl.config import HandConfig
from handctl.errors import ConfigError
from handctl.online.clock import Tick
from handctl.online.loop import TickRecord
from handctl.online.recipes.guard import LimitGuard, SpringBand
from handctl.online.recipes.schema import Condition, Recipe, TimeoutAction, parse_condition
from handctl.online.safety.chatter import Ringing
from handctl.online.safety.faults import FaultCode
from handctl.online.safety.recovery import Recovery
from handctl.session import RunReport, RunRequest, run_recipe
from handctl.stopsignals import StopSignals

#: The shortest ramp to and from the jog torque (s), however high the rate limit.
MIN_RAMP_S = 0.2
#: of a joint's ``tau_max``, the most a jog asks. The guard's spring, held to ``tau_max`` with
#: the jog, meets a torque of this share halfway into its band (a middle joint of the shipped
#: hand at its tau_max, 0.45 N·m, went past its limit; at 0.3 it stopped 0.16 rad inside),
#: and a proximal joint's swing flings the joints beyond it less hard (one at 0.4 of its
#: 0.6 N·m flung the middle joint past its limit). At half, every joint of the shipped hand,
#: both ways, ends inside its limits.
JOG_SHARE = 0.5
JOG_SHARE_TEXT = "half"
#: rad, the soft-limit guard's band (as the default recipe's ``limit_guard_band``).
GUARD_BAND = 0.15
#: s, the run-time table's line spacing: of the hand's loop, so that a slower loop does not
#: show its lines further apart (100 ticks was 0.5 s at 200 Hz).
TABLE_PERIOD_S = 0.1


def table_every_ticks(period_s: float) -> int:
    """Ticks between two lines of the run-time table at a loop period of ``period_s``."""
    return max(1, round(TABLE_PERIOD_S / period_s))


@dataclass(frozen=True)
class JogLine:
    """What the run-time table shows of one tick (SI units)."""

    t_s: float
    phase: str
    state: str
    desired: float  # N·m, what the jog asks of the joint (the guard's push-back included)
    applied: float  # N·m, what the supervisor let through
    angle: float  # rad
    tdt: float  # N·m


@dataclass
class JogReport:
    report: RunReport
    joint: str
    torque: float
    start_angle: float | None  # rad, when torque first flowed
    end_angle: float | None  # rad, at the end of the run (before its encoder failed, if it did)
    max_abs_tdt: float  # N·m
    recovery: Recovery | None = None  # with ``recover``: what the supervisor saw of it
    #: the jogged joint's node latched SENSOR: ``end_angle`` is the last reading before it
    encoder_failed: bool = False
    #: the TDT against the torque applied over the hold ("" if it followed, or the hold was
    #: too short to judge): ``tdt_problem``
    tdt_problem: str = ""

    @property
    def moved(self) -> float | None:
        if self.start_angle is None or self.end_angle is None:
            return None
        return self.end_angle - self.start_angle


class JogSink:
    """A ``RecordSink`` that keeps the jogged joint's line for ``show`` every ``every`` ticks
    (``TABLE_PERIOD_S`` of the loop by default) and at the first tick of every phase, and the
    angles a summary needs. The phase's first tick: a phase shorter than the spacing (the end
    ramp of a fast jog, or at a slow loop) had no line, and the table did not show the torque
    going back to zero."""

    def __init__(
        self,
        index: int,
        show: Callable[[JogLine], None] | None,
        period_s: float,
        every: int | None = None,
        *,
        node: str,
        torque: float = 0.0,
    ) -> None:
        self.index = index
        #: how the supervisor names the jogged joint's node (``node N (FINGER)``): its SENSOR
        #: fault freezes ``end_angle``, since the node's readings from that tick on are the
        #: jump it failed on (a saturated encoder read as tens of degrees the joint moved)
        self.node = node
        self.encoder_failed = False
        self.show = show
        self.period_s = period_s
        self.every = table_every_ticks(period_s) if every is None else every
        self._phase: str | None = None
        self.start_angle: float | None = None
        self.end_angle: float | None = None
        self.max_abs_tdt = 0.0
        #: over the ticks the jog's torque was applied whole (the hold): how many, and the
        #: sums of the applied torque and of the TDT's reading (``tdt_problem``)
        self.torque = torque
        self.held = 0
        self.held_applied = 0.0
        self.held_tdt = 0.0
        #: the ticks of the jog's phase its torque was not applied whole (the ramp, or the
        #: soft-limit guard holding it back), and the largest |applied| over them: a jog the
        #: guard held below its torque throughout had no hold, and was judged on nothing
        self.held_back = 0
        #: N·m, the least and the most torque applied while it was off the one asked: the
        #: guard's spring holds a joint below it, and its damper may push one past it
        self.held_back_low = math.inf
        self.held_back_high = -math.inf
        self._first_tick: int | None = None
        #: the last tick's line if it was not shown, as JogLine's fields (made a line only
        #: if it is: a frozen dataclass every tick was work in the tick): shown by ``finish``
        self._unshown: tuple[float, str, str, float, float, float, float] | None = None

    def begin_tick(self, tick: Tick) -> None:
        pass

    def note(self, kind: str, detail: str, tick: int) -> None:
        pass

    def push(self, record: TickRecord) -> None:
        j = self.index
        angle, tdt = float(record.angle[j]), float(record.tdt[j])
        if self._first_tick is None:
            self._first_tick = record.tick
            self.start_angle = angle
        if record.faults and not self.encoder_failed and self._sensor_failed(record):
            # the node fails in the tick its encoder jumped: ``end_angle`` stays the tick
            # before's, the last reading of the joint itself
            self.encoder_failed = True
        if not self.encoder_failed:
            self.end_angle = angle
        if np.isfinite(tdt):
            self.max_abs_tdt = max(self.max_abs_tdt, abs(tdt))
            applied = float(record.applied[j])
            whole = abs(applied - self.torque) <= 1e-3 * abs(self.torque)  # on the wire's grid
            if self.torque and whole and not self.encoder_failed:
                self.held += 1
                self.held_applied += applied
                self.held_tdt += tdt
            elif self.torque and record.phase == JOG_PHASE and not self.encoder_failed:
                self.held_back += 1
                self.held_back_low = min(self.held_back_low, applied)
                self.held_back_high = max(self.held_back_high, applied)
        new_phase = record.phase != self._phase
        self._phase = record.phase
        if self.show is None:
            return
        fields = (
            (record.tick - self._first_tick) * self.period_s,
            record.phase,
            record.state,
            float(record.desired[j]),
            float(record.applied[j]),
            angle,
            tdt,
        )
        if new_phase or (record.tick - self._first_tick) % self.every == 0:
            self._unshown = None
            self.show(JogLine(*fields))
        else:
            self._unshown = fields

    def _sensor_failed(self, record: TickRecord) -> bool:
        return any(
            f.code is FaultCode.NODE_FAULT
            and f.detail.startswith(self.node + " ")
            and "SENSOR" in f.detail
            for f in record.faults
        )

    def finish(self) -> None:
        """Show the last tick's line if it was not: a stop (Ctrl-C, a fault) ended the table
        on a line of the jog's torque, and never showed it back at zero."""
        if self.show is not None and self._unshown is not None:
            self.show(JogLine(*self._unshown))
            self._unshown = None


#: the name of a jog's one phase (a recovery's is ``recover``)
JOG_PHASE = "jog"
#: ticks of the hold a TDT is judged on, at the least (a tenth of a second at 1 kHz): a jog
#: stopped sooner says nothing of its sensor
TDT_JUDGED_TICKS = 100
#: the range the TDT's mean over the hold may be in, as a fraction of the applied torque's:
#: a sensor of the other sign, of another scale, dead or stuck, or a joint that does not get
#: its torque (a saturated drive) is outside it
TDT_FOLLOWS = (0.5, 2.0)


def tdt_problem(joint: str, sink: JogSink, rang: Sequence[Ringing] = ()) -> str:
    """What is wrong with the TDT of the jogged joint over the hold ("" if nothing). The
    supervisor's own check allows 0.02 N·m and 15 %, as much as the small torques a jog is
    run at: a jog at 0.02 N·m whose TDT read 0.005 said "completed", exit 0, and the step
    of the bring-up meant to find a dead or mis-scaled sensor passed it.

    Not judged when the joint's command rang (``rang``, the run's ``chatter``): the mean of a
    command swinging by more than the jog's torque is not the torque the joint was held at,
    and a healthy sensor was said not to follow its joint (a hand of large tau_max, whose
    soft-limit guard is stiff for its links: found by an outside audit). Said as that.

    Nor when the torque asked was never held long enough because the soft-limit guard held
    the joint below it for as long (a jog run into the guard's band): said as that too. It
    passed in silence, exit 0, whatever the sensor read (found by an outside audit); a jog
    only stopped sooner than ``TDT_JUDGED_TICKS`` says nothing of its sensor."""
    if sink.held < TDT_JUDGED_TICKS:
        if sink.held_back < TDT_JUDGED_TICKS:
            return ""
        return (
            f"{joint}'s TDT cannot be judged: its applied torque was held off the "
            f"{sink.torque:+g} N·m asked for {sink.held_back} ticks of the jog (the soft-limit "
            f"guard acting on the joint: from {sink.held_back_low:+.4f} to "
            f"{sink.held_back_high:+.4f} N·m), so no steady torque was held; jog it with a "
            "smaller torque, or from further inside its range"
        )
    ringing = [r for r in rang if r.joint == joint]
    if ringing:
        return (
            f"{joint}'s TDT cannot be judged: its command rang (±{ringing[0].amplitude_nm:.3g} "
            f"N·m, {ringing[0].frequency_hz:.0f} Hz), the soft-limit guard pushing back "
            "against the jog, so no steady torque was held; jog it with a smaller torque, or "
            "from further inside its range"
        )
    applied, read = sink.held_applied / sink.held, sink.held_tdt / sink.held
    low, high = TDT_FOLLOWS
    if read * applied > 0 and low <= read / applied <= high:
        return ""
    return (
        f"{joint}'s TDT read {read:+.4f} N·m on average over the {sink.held} ticks "
        f"{applied:+.4f} N·m was applied (expected between {low:g} and {high:g} times it): "
        "a torque sensor that does not follow its joint (its sign, its scale, dead or "
        "stuck), or a drive that does not give the torque commanded"
    )


def joint_index(hand: HandConfig, joint: str) -> int:
    names = hand.joint_names
    if joint not in names:
        raise ConfigError("JOINT", "", f"a joint of {hand.source} ({', '.join(names)})", joint)
    return names.index(joint)


def jog_recipe(
    hand: HandConfig, joint: str, torque: float, seconds: float, recover: bool = False
) -> Recipe:
    """The one-phase jog; refused (``ConfigError``) over ``tau_max``, naming the limit. With
    ``recover``: the phase ``recover``, which ends once the joint is ``GUARD_BAND`` inside its
    range on the side the torque pushes towards, guarded only from the limit the torque
    pushes it towards (``recovery_guard``)."""
    j = joint_index(hand, joint)
    spec = hand.joints[j]
    most = JOG_SHARE * spec.tau_max
    # the bound that applies, first: a jog over tau_max was told tau_max, and then refused
    # at tau_max for the jog's own share of it (found by an outside audit)
    if recover and not abs(torque) <= spec.tau_max:  # NaN too
        raise ConfigError(
            "--torque",
            "",
            f"|τ| <= {spec.tau_max:g} N·m (tau_max of {joint} in {hand.source})",
            torque,
        )
    if not recover and not abs(torque) <= most + 1e-9:  # to a nN·m: 2/3 of 0.3 is 0.19999...
        # every command is held to tau_max, so the guard's push-back against a jog at
        # tau_max is the jog's own size only at the limit itself: the joint came onto it at
        # speed, past it, and the jog ended in a latched ANGLE_LIMIT
        raise ConfigError(
            "--torque",
            "",
            f"|τ| <= {most:.4g} N·m ({JOG_SHARE_TEXT} of {joint}'s tau_max, "
            f"{spec.tau_max:g} N·m in {hand.source}: the soft-limit guard needs the rest to "
            "push back from the limit; a heavy or long link may still reach it, and the "
            "supervisor then stops the jog)",
            torque,
        )
    if recover and torque == 0.0:
        raise ConfigError(
            "--torque",
            "",
            f"with --recover, a torque that pushes {joint} back in: negative from above its "
            f"upper limit {spec.angle_max:+g} rad, positive from below its lower limit "
            f"{spec.angle_min:+g} rad",
            torque,
        )
    ramp = max(MIN_RAMP_S, abs(torque) / spec.rate_limit)
    torques = [0.0] * hand.n_joints
    torques[j] = torque
    if not recover:
        return in_memory_recipe(
            f"jog_{joint}",
            f"{torque:+g} N·m on {joint}, zero elsewhere",
            hand,
            [phase(JOG_PHASE, torques, ramp, ramp + seconds)],
            ramp,
            guard=jog_guard(hand, torque),
        )
    back = phase("recover", torques, ramp, ramp + seconds)
    back = dataclasses.replace(
        back, exits=(recovered_condition(hand, joint, torque),), on_timeout=TimeoutAction.NEXT
    )
    return in_memory_recipe(
        f"recover_{joint}",
        f"{torque:+g} N·m on {joint} until it is back inside its soft limits, zero elsewhere",
        hand,
        [back],
        ramp,
        guard=recovery_guard(hand, joint, torque),
    )


def jog_guard(hand: HandConfig, torque: float) -> LimitGuard:
    """The jog's soft-limit guard: ``GUARD_BAND``, narrowed to a quarter of the range of a
    joint narrower than twice it, pushing no joint harder than twice the jog's ``torque``.

    A jog is a small torque on one joint. With the recipe's guard, a joint resting inside its
    band (near an asymmetric limit) got up to its whole ``tau_max`` while another was jogged
    at a seventh of it, and a joint of 0.1 rad anywhere on the hand, inside the band from both
    sides, was pushed onto a limit by the guard itself: every jog stopped on ``ANGLE_LIMIT``.
    Twice the torque still stops the jogged joint inside its band, the spring meeting it
    with the torque's own size halfway in."""
    springs = [
        SpringBand(j.name, side, (j.angle_max - j.angle_min) / 4)
        for j in hand.joints
        if j.angle_max - j.angle_min < 2 * GUARD_BAND
        for side in ("lower", "upper")
    ]
    return LimitGuard.for_hand(hand, GUARD_BAND, springs=springs, push_max=2 * abs(torque))


def recovery_guard(hand: HandConfig, joint: str, torque: float) -> LimitGuard:
    """The recovery's guard: the jog's (``jog_guard``) on the recovered joint's far side
    alone, the limit its ``torque`` pushes it towards; every other side of every joint is
    unguarded (its band at infinity).

    The phase ends ``GUARD_BAND`` inside, and the end ramp's torque, still pushing, carried a
    joint that came in at speed through a range of 0.6 rad into its other limit (found by an
    outside audit). Only that side: the near one would shove a joint still outside with up
    to twice the recovery's torque, and another joint resting outside (a sagging finger) is
    held by the supervisor's ratchet, not pushed."""
    full = jog_guard(hand, torque)
    j = joint_index(hand, joint)
    down = torque < 0  # towards the lower limit

    def kept(values: tuple[float, ...], side_kept: bool, off: float) -> tuple[float, ...]:
        return tuple(v if k == j and side_kept else off for k, v in enumerate(values))

    return dataclasses.replace(
        full,
        lower=kept(full.lower, down, -math.inf),
        spring_lower=kept(full.spring_lower, down, -math.inf),
        upper=kept(full.upper, not down, math.inf),
        spring_upper=kept(full.spring_upper, not down, math.inf),
    )


def recovered_condition(hand: HandConfig, joint: str, torque: float) -> Condition:
    """The recovery's exit: the joint ``GUARD_BAND`` inside the limit it is pushed away from."""
    spec = hand.joints[joint_index(hand, joint)]
    if torque < 0:
        text = f"angle.{joint} < {spec.angle_max - GUARD_BAND:.6f}"
    else:
        text = f"angle.{joint} > {spec.angle_min + GUARD_BAND:.6f}"
    cond = parse_condition(text, hand.joint_names)
    assert isinstance(cond, Condition), cond  # built here from a joint of the hand
    return cond


def jog(
    hand: HandConfig,
    joint: str,
    torque: float,
    *,
    seconds: float = 2.0,
    bus: str = "sim",
    lockstep: bool | None = None,
    realtime_priority: bool = False,
    seed: int = 0,
    sim_faults: Path | None = None,
    reset_node_faults: bool = False,
    accept_missed_deadlines: bool = False,
    recover: bool = False,
    show: Callable[[JogLine], None] | None = None,
    signals: StopSignals | None = None,
) -> JogReport:
    """Jog ``joint`` with ``torque`` N·m for ``seconds`` after the ramp, on ``bus``; with
    ``recover``, until it is back inside its soft limits (at most as long). ``signals``: the
    stop signals taken over by the caller, who says the ones that came after the hand had
    stopped (``StopSignals.ignored``); None: taken over, and those dropped, here."""
    recipe = jog_recipe(hand, joint, torque, seconds, recover)
    j = joint_index(hand, joint)
    recovery = Recovery(j, 1 if torque > 0 else -1) if recover else None
    finger = next(f for f in hand.fingers if joint in {k.name for k in f.joints})
    sink = JogSink(
        j, show, hand.bus.period_s, node=f"node {finger.node_id} ({finger.name})", torque=torque
    )
    report = run_recipe(
        RunRequest(
            hand=hand,
            recipe=recipe,
            bus=bus,
            lockstep=lockstep,
            realtime_priority=realtime_priority,
            seed=seed,
            sim_faults=sim_faults,
            reset_node_faults=reset_node_faults,
            accept_missed_deadlines=accept_missed_deadlines,
            recovery=recovery,
        ),
        recorder=sink,
        signals=signals,
    )
    sink.finish()
    return JogReport(
        report,
        joint,
        torque,
        sink.start_angle,
        sink.end_angle,
        sink.max_abs_tdt,
        recovery,
        sink.encoder_failed,
        "" if recover else tdt_problem(joint, sink, report.result.chatter),
    )
