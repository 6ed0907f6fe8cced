"""Where the enveloped objects are, from the joint angles alone (online plane).

A real hand without vision knows only its joint angles. What makes that enough is the
enveloping grasp itself: every object is caged by finger links, the palm and the other object,
and squeezed against them, so it is tangent to the links it touches and clear of all the others.
The estimator therefore places each object where it is *deepest inside its cage*: the centre
``c`` that maximises the smallest clearance ``s_k(c) = dist(c, segment_k) - r - h_k`` over
every link segment (radius ``r`` of the object, half-thickness ``h_k`` of the link), the palm
(the segment joining the finger bases) and every other object (``|c - c'| - r - r'``). This is
the Chebyshev centre of the free space, and it is the right estimate for three reasons:

- for a squeezed object the free space shrinks to a point and the maximiser is where the
  object really is, touching the links it touches, with no need to decide beforehand which
  links those are (the enveloping assumption is exactly that the cage is closed);
- the best clearance ``t`` is a free unknown, so a radius a little off the nominal one (the
  clearance is then the same small number at every contact) or soft contacts that sink in
  shift the fit very little, where a fit of "distance = r" would be pulled towards one link;
- an object that is *not* caged (on the table, the hand open) has no bounded maximiser: the
  clearance grows and the estimate is reported invalid (NaN), which no exit condition accepts.

The radius is measured as well as the centre. A real cylinder is seldom the recipe's: ±20 %
moves the clearance at each link by up to 4 mm, and by twice that between two cylinders, so
the deepest point is pulled off the object where a cylinder's cage is partly the other
cylinder, and the cage test fails on a clearance that is not the same at every wall. At the
deepest point of a closed cage every tight wall is the same clearance away, so a squeezed
object is that much larger than its radius says: each object's radius is moved towards it
(``_fit_radii``), slowly, within ±``RADIUS_RANGE`` of the recipe's (the recipe's kept
within ``RADIUS_TOLERANCE``), and only while every object's cage is closed and every
estimate is still (``STILL_SPEED``). A grasp held still is
squeezed into its cages; one moving through the hand is not, and a loose cage's deepest
point is not the object's size. The radii are kept when the grasp moves on, so the centres
and the centre line of a turn are placed with the radii the hold measured.

The maximisation is tracked rather than solved from scratch, because it must fit in a tick:
each tick takes one active-set step per object from the previous estimate, with the other
objects fixed (the three tightest distinct clearances, linearised; the step that equalises them
when they cage the object, an ascent along the two tightest when they do not), limited to
``MAX_STEP``. Objects move far less than that per millisecond, so the track never falls
behind; a lost track (clearance beyond ``RESET_CLEARANCE``) restarts from seeds under the palm,
inside every cage the hand can form: side by side and touching, in the recipe's order along
the palm from its end of the smaller x (``handshape.palm_ends``), centred on the palm's middle.

The names are settled when the objects are first located (every estimate valid for
``LOCATE_S`` in a row; no estimate is reported before): the tracks are named in the recipe's
order along the palm, the order a recipe lists its objects in (``session`` warns of a recipe
that does not). Continuity names them from then on, through a turn that swaps them and
through a stretch without a cage. Why not continuity from the seeds: until the cages close,
the tracks wander through the open hand (deep in a link, from one pocket to another), and on
a hand whose fingers close on objects apart from each other, which pocket each track ends in
depended on the tick the estimator started on, so the names came out swapped on some runs
and not on others.

One to four objects (the recipe's), and for each pair the recipe names (each object with the
next by default) the angle of the line from the first centre to the second and its running
turn (``handctl.online.recipes.schema.estimate_names``). The estimates are valid together or not at
all: every object is a wall of the others' cages, so one object off its track puts the others'
fits in doubt.

Pure Python on floats, no NumPy: for a dozen segments that is several times cheaper per tick
than array calls, and it allocates little. The online plane only: no import of the analysis
or the simulation.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence

import numpy as np
import numpy.typing as npt

from handctl.config import HandConfig
from handctl.handshape import palm_ends
from handctl.online.recipes.schema import (
    MAX_OBJECTS,
    Pair,
    RecipeObject,
    consecutive_pairs,
    estimate_names,
)

NAN = float("nan")
#: m, the most an estimate moves in one tick: a step of a linearised problem is trusted this far.
MAX_STEP = 0.002
#: m, an object whose best clearance is further from zero than this is not held by its cage
#: (too loose, or the estimate sits in a pocket too small for it): its estimate is invalid. It
#: covers a radius 20 % off before the fit has measured it and the few tenths of a millimetre
#: soft contacts sink in.
VALID_CLEARANCE = 0.004
#: the most a fitted radius moves towards the one the cage measures, per tick, as a fraction
#: of the difference: 50 ticks (50 ms at 1 kHz) to take up most of it, so the encoder's
#: counts and a contact's momentary slip average out.
RADIUS_GAIN = 0.02
#: m/s: the radii are fitted only while every estimated centre moves slower than this. A grasp
#: held still is squeezed into its cages; an object moving through the hand is not, and in a
#: loose cage the deepest point is not where the object is.
STILL_SPEED = 0.01
#: s, the low-pass of each estimated centre's speed that ``STILL_SPEED`` is compared with
STILL_TIME_CONSTANT = 0.02
#: m: a measured radius this close to the recipe's does not replace it. The measurement is
#: no better than that: soft contacts sink in a few tenths of a millimetre, and two cylinders
#: caged partly by each other leave the split of their sizes as uncertain. Within it the
#: recipe's radius is the better estimate.
RADIUS_TOLERANCE = 0.0005
#: relative: how far a fitted radius may go from the recipe's. Beyond this it is another
#: object, or a cage the object does not fill; the fit stops at the bound.
RADIUS_RANGE = 0.4
#: m: once an object's radius is measured, a cage this much larger than the object is loose,
#: and the object is not located by it (it lies anywhere in the slack, where the deepest point
#: is only the middle): its estimate is invalid. Soft contacts sink in; they do not open.
LOOSE_CLEARANCE = 0.0005
#: ticks of fitting after which an object's radius counts as measured (``LOOSE_CLEARANCE``):
#: a few of the fit's time constants
MEASURED_TICKS = 150
#: m, a track whose best clearance exceeds this has left every cage: restart from the seeds.
#: (A track deep in the links is not restarted: the seeds may be in the links themselves, and
#: the ascent takes it out of a pocket too small for it as soon as the pocket changes.)
RESET_CLEARANCE = 0.02
#: s: the objects count as located once every estimate has been valid this long in a row.
#: A track passing through a pocket of its size while the fingers close makes the estimate
#: valid for a few ticks (5-8 ms seen, the cages still 3-4 mm loose), somewhere the object
#: is not: names settled there would be a guess.
LOCATE_S = 0.02
#: s: before the objects are first located, tracks that have rested this long, one of them
#: deeper in a wall than a contact sinks (``VALID_CLEARANCE``), are stuck (two tracks in one
#: cage, or one inside a link that no longer moves): every track starts again from its seed.
STUCK_S = 0.2
#: m, seeds sit this far below the palm (plus the object's radius), between the fingers.
SEED_DEPTH = 0.010
#: rad: an object counts as caged when the directions from its nearly tight contacts (within
#: ``CAGE_BAND`` of the tightest) leave no open angle wider than half a turn less this: held
#: on one open side only by friction and gravity, it is not located by geometry, and an exit
#: must not fire on it.
CAGE_GAP = 0.15
#: m, contacts this close to the tightest one count as touching for the cage test.
CAGE_BAND = 0.001
#: gradients closer than this (cosine) with clearances within ``DUPLICATE_CLEARANCE`` are one
#: constraint seen twice (fingers 1 and 2 in the same posture; two links meeting at a joint).
DUPLICATE_COSINE = 0.995
DUPLICATE_CLEARANCE = 0.0005

Segment = tuple[float, float, float, float, float, float]
"""``(ax, ay, ux, uy, length, half_thickness)``: start point, unit direction, extent (m)."""


class ObjectEstimator:
    """Estimates of 1..4 enveloped cylinders, one call per tick: ``estimator(angles)`` returns
    the values named by ``estimates`` (NaN while the objects are not caged).

    ``objects`` gives the nominal radii in the recipe's order, ``pairs`` the pairs whose centre
    line is reported (``consecutive_pairs`` when None); the hand config gives the finger bases,
    link lengths and link half-thicknesses.
    """

    def __init__(
        self, hand: HandConfig, objects: Sequence[RecipeObject], pairs: Sequence[Pair] | None = None
    ) -> None:
        if not 1 <= len(objects) <= MAX_OBJECTS:
            raise ValueError(
                f"the estimator tracks 1 to {MAX_OBJECTS} objects, found {len(objects)}"
            )
        self.names = tuple(o.name for o in objects)
        #: m, the recipe's radii: where the fit starts and what bounds it
        self.nominal_radii = tuple(float(o.radius) for o in objects)
        self.pairs: tuple[Pair, ...] = (
            tuple(pairs) if pairs is not None else consecutive_pairs(len(objects))
        )
        self.estimates = estimate_names(objects, self.pairs)
        self._fingers = [
            (
                f.base_x,
                f.base_y,
                f.base_angle,
                tuple((j.link_length, j.half_thickness) for j in f.joints),
            )
            for f in hand.fingers
        ]
        self._n = hand.n_joints
        period = hand.bus.period_s
        self._speed_gain = period / (STILL_TIME_CONSTANT + period)
        self._per_tick = 1.0 / period
        # the two waits before the objects are located, in ticks of this hand's loop
        self._locate_ticks = math.ceil(LOCATE_S / period - 1e-9)
        self._stuck_ticks = math.ceil(STUCK_S / period - 1e-9)
        first, last = palm_ends(hand)
        length = math.dist(first, last)
        self._palm: Segment | None = None
        if length > 0.0:
            self._palm = (
                first[0],
                first[1],
                (last[0] - first[0]) / length,
                (last[1] - first[1]) / length,
                length,
                0.0,
            )
        mid_x, mid_y = (first[0] + last[0]) / 2, (first[1] + last[1]) / 2
        # "below the palm" is away from the palm towards the fingers' mean pointing direction
        down_x = sum(math.cos(f.base_angle) for f in hand.fingers)
        down_y = sum(math.sin(f.base_angle) for f in hand.fingers)
        norm = math.hypot(down_x, down_y) or 1.0
        down_x, down_y = down_x / norm, down_y / norm
        side_x, side_y = (self._palm[2], self._palm[3]) if self._palm else (1.0, 0.0)
        self._seeds = tuple(
            (
                mid_x + offset * side_x + (r + SEED_DEPTH) * down_x,
                mid_y + offset * side_y + (r + SEED_DEPTH) * down_y,
            )
            for offset, r in zip(_seed_offsets(self.nominal_radii), self.nominal_radii, strict=True)
        )
        reach = max(sum(j[0] for j in f[3]) for f in self._fingers) + length
        self._centre = (mid_x, mid_y)
        self._reach = reach
        self.reset()

    def reset(self) -> None:
        """Forget the track (a new grasp): back to the seeds, the turn counts restart."""
        m, p = len(self.nominal_radii), len(self.pairs)
        self.centres: list[tuple[float, float]] = list(self._seeds)
        #: m, each object's radius as its cages measure it (``_fit_radii``)
        self.radii: list[float] = list(self.nominal_radii)
        #: m, each object's radius as its cages measure it, before ``RADIUS_TOLERANCE``
        self.measured_radii: list[float] = list(self.nominal_radii)
        self.clearance = [NAN] * m  # m, each object's best clearance at its estimate
        self.caged = [False] * m
        #: whether each object's three tightest walls surround it (a closed cage)
        self.closed = [False] * m
        #: m/s, each estimated centre's speed, low-passed (``STILL_TIME_CONSTANT``)
        self.speed = [math.inf] * m
        self._fitted = [0] * m  # ticks each radius has been fitted, up to MEASURED_TICKS
        self.valid = False
        self._named = False  # whether the names are settled (the objects first located)
        self._stuck = 0  # ticks the tracks have rested stuck, before the names are settled
        self._located = 0  # ticks in a row every estimate has been valid, until the names settle
        self._turn = [NAN] * p  # rad, each pair's unwrapped centre-line angle (running)
        self._last_angle = [NAN] * p
        self.last: tuple[float, ...] = (NAN,) * len(self.estimates)

    def measured_radius(self, index: int) -> float | None:
        """m, object ``index``'s radius as the estimator places it, once its cages have
        measured it (``MEASURED_TICKS`` of fitting; the recipe's within ``RADIUS_TOLERANCE``),
        else None: what a phase's ``schedule`` chooses its torque on."""
        if self._fitted[index] < MEASURED_TICKS:
            return None
        return self.radii[index]

    def positions(self, values: Sequence[float]) -> list[tuple[float, float]]:
        """Each object's estimated centre ``(x, y)`` (m) in an output of this estimator."""
        start = 2 * len(self.pairs)
        return [
            (values[start + 2 * i], values[start + 2 * i + 1])
            for i in range(len(self.nominal_radii))
        ]

    # -- geometry ---------------------------------------------------------------------------
    def segments(self, angles: Sequence[float] | npt.NDArray[np.float64]) -> list[Segment]:
        """Every link as a segment (forward kinematics in the hand plane), then the palm."""
        if isinstance(angles, np.ndarray):
            angles = angles.tolist()
        out: list[Segment] = []
        i = 0
        cos, sin = math.cos, math.sin
        for bx, by, heading, links in self._fingers:
            x, y = bx, by
            for length, half in links:
                heading += angles[i]
                i += 1
                ux, uy = cos(heading), sin(heading)
                out.append((x, y, ux, uy, length, half))
                x += ux * length
                y += uy * length
        if self._palm is not None:
            out.append(self._palm)
        return out

    def clearances(
        self, index: int, centre: tuple[float, float], segments: Sequence[Segment]
    ) -> list[tuple[float, float, float]]:
        """``(clearance, gx, gy)`` of object ``index`` at ``centre`` against every segment and
        every other object; ``(gx, gy)`` is the clearance's gradient (a unit vector)."""
        cx, cy = centre
        r = self.radii[index]
        out: list[tuple[float, float, float]] = []
        append = out.append
        hypot = math.hypot
        for ax, ay, ux, uy, length, half in segments:
            vx = cx - ax
            vy = cy - ay
            u = vx * ux + vy * uy
            if u < 0.0:
                u = 0.0
            elif u > length:
                u = length
            wx = vx - u * ux
            wy = vy - u * uy
            d = hypot(wx, wy)
            if d < 1e-12:
                append((-r - half, -uy, ux))
            else:
                append((d - r - half, wx / d, wy / d))
        for other, (ox, oy) in enumerate(self.centres):
            if other == index:
                continue
            wx, wy = cx - ox, cy - oy
            d = hypot(wx, wy)
            other_r = self.radii[other]
            if d < 1e-12:
                append((-r - other_r, 0.0, 1.0))
            else:
                append((d - r - other_r, wx / d, wy / d))
        return out

    # -- the tick ---------------------------------------------------------------------------
    def __call__(self, angle: Sequence[float] | npt.NDArray[np.float64]) -> tuple[float, ...]:
        segs = self.segments(angle)
        m = len(self.radii)
        for index in range(m):
            self._track(index, segs)
        if all(self.closed) and max(self.speed) < STILL_SPEED:
            self._fit_radii()
        self.valid = all(self.caged) and all(
            abs(c) <= VALID_CLEARANCE
            and (c + r - measured <= LOOSE_CLEARANCE or n < MEASURED_TICKS)
            for c, r, measured, n in zip(
                self.clearance, self.radii, self.measured_radii, self._fitted, strict=True
            )
        )
        if not self._named:
            self._located = self._located + 1 if self.valid else 0
            if self._located >= self._locate_ticks:
                self._name_along_palm()
            else:
                self.valid = False  # not located yet: no name is known to be the object's
        if not self.valid:
            if not self._named:
                self._unstick()
            self.last = (NAN,) * len(self.estimates)
            return self.last
        out: list[float] = []
        centres = self.centres
        for k, (a, b) in enumerate(self.pairs):
            line = math.atan2(centres[b][1] - centres[a][1], centres[b][0] - centres[a][0])
            self._turn[k] = advance_turn(self._turn[k], self._last_angle[k], line)
            self._last_angle[k] = line
            out += (line, self._turn[k])
        for x, y in centres:
            out += (x, y)
        self.last = tuple(out)
        return self.last

    def _track(self, index: int, segs: Sequence[Segment]) -> None:
        centre = self.centres[index]
        found = self.clearances(index, centre, segs)
        found.sort()
        best = found[0][0]
        self.clearance[index] = best
        far = math.dist(centre, self._centre) > self._reach
        if best > RESET_CLEARANCE or far:
            self.centres[index] = self._seeds[index]
            self.caged[index] = self.closed[index] = False
            self.speed[index] = math.inf
            return
        chosen = [found[0]]
        for item in found[1:]:
            s, gx, gy = item
            for c in chosen:
                if gx * c[1] + gy * c[2] >= DUPLICATE_COSINE and s - c[0] <= DUPLICATE_CLEARANCE:
                    break
            else:
                chosen.append(item)
                if len(chosen) == 4:
                    break
        step, worst = _chebyshev_step(chosen[:3])
        if worst >= 0 and len(chosen) == 4:
            # with four contacts the three tightest need not surround the object: exchange
            # the one that does not hold it for the fourth (one active-set exchange a tick)
            trial = [c for k, c in enumerate(chosen[:3]) if k != worst] + [chosen[3]]
            retry, again = _chebyshev_step(trial)
            if again < 0:
                step, worst = retry, again
        self.closed[index] = worst < 0 and len(chosen) >= 3
        self.caged[index] = _surrounds([c for c in chosen if c[0] - best <= CAGE_BAND])
        dx, dy = step
        size = math.hypot(dx, dy)
        if size > MAX_STEP:
            dx, dy = dx * MAX_STEP / size, dy * MAX_STEP / size
        self.centres[index] = (centre[0] + dx, centre[1] + dy)
        speed = self.speed[index]
        moved = math.hypot(dx, dy) * self._per_tick
        self.speed[index] = (
            moved if math.isinf(speed) else speed + (moved - speed) * self._speed_gain
        )

    def _unstick(self) -> None:
        """Before the objects are first located: tracks at rest with one deep in a wall for
        ``STUCK_S`` start again from the seeds. The ascent takes a track out of a pocket too
        small for it when the pocket changes; in a grasp held still it never does, and on a
        hand that cages its objects apart both tracks could end in one cage, each inside the
        other, for the rest of the run (no estimate ever valid). Not once the objects have
        been located: continuity keeps their names from then on, which a restart would lose.
        Work on the tick: a comparison per object."""
        if max(self.speed) < STILL_SPEED and min(self.clearance) < -VALID_CLEARANCE:
            self._stuck += 1
        else:
            self._stuck = 0
        if self._stuck >= self._stuck_ticks:
            self._stuck = 0
            m = len(self.radii)
            self.centres = list(self._seeds)
            self.caged, self.closed = [False] * m, [False] * m
            self.speed = [math.inf] * m

    def _name_along_palm(self) -> None:
        """Settle the names, once: the tracks in their order along the palm take the recipe's
        names in its order (each track's state goes with it: its cage measured its radius), and
        a pair whose line changed starts its turn count again. Tracks closer along the palm
        than half the smaller radius have no order there (one above the other): then the
        names stay as continuity gave them."""
        self._named = True
        ux, uy = (self._palm[2], self._palm[3]) if self._palm is not None else (1.0, 0.0)
        along = [x * ux + y * uy for x, y in self.centres]
        order = sorted(range(len(along)), key=along.__getitem__)
        if order == list(range(len(along))):
            return
        for a, b in itertools.pairwise(order):
            if along[b] - along[a] < 0.5 * min(self.radii[a], self.radii[b]):
                return
        self.centres = [self.centres[k] for k in order]
        self.radii = [self.radii[k] for k in order]
        self.measured_radii = [self.measured_radii[k] for k in order]
        self.clearance = [self.clearance[k] for k in order]
        self.caged = [self.caged[k] for k in order]
        self.closed = [self.closed[k] for k in order]
        self.speed = [self.speed[k] for k in order]
        self._fitted = [self._fitted[k] for k in order]
        # each pair's line is another now: its turn counts from here, as after a reset
        self._turn = [NAN] * len(self.pairs)
        self._last_angle = [NAN] * len(self.pairs)

    def _fit_radii(self) -> None:
        """Move each object's radius towards the one its cage measures: at the deepest point
        of a closed cage every tight wall is the same clearance away, and an object that
        touches them is that much larger than its radius says. Only while every object's
        cage is closed: each object is a wall of the others', and one that is not located
        says nothing of their size."""
        for i, nominal in enumerate(self.nominal_radii):
            clearance = self.clearance[i]
            if not abs(clearance) <= RADIUS_RANGE * nominal:
                continue
            measured = self.measured_radii[i]
            measured += RADIUS_GAIN * (self.radii[i] + clearance - measured)
            low, high = nominal * (1.0 - RADIUS_RANGE), nominal * (1.0 + RADIUS_RANGE)
            measured = self.measured_radii[i] = min(high, max(low, measured))
            # the measurement replaces the recipe's once it is further off than its own
            # uncertainty, and gives way to it again only well within it (no flicker)
            off = abs(measured - nominal)
            if off > RADIUS_TOLERANCE or (self.radii[i] != nominal and off > RADIUS_TOLERANCE / 2):
                self.radii[i] = measured
            else:
                self.radii[i] = nominal
            self._fitted[i] = min(MEASURED_TICKS, self._fitted[i] + 1)


def _seed_offsets(radii: Sequence[float]) -> list[float]:
    """Where along the palm (m from its middle) each object's seed sits: side by side and
    touching, in order, with the middle object (odd count) or the middle contact (even count)
    at the palm's middle."""
    m = len(radii)
    k = m // 2
    offsets = [0.0] * m
    if m % 2 == 0:
        offsets[k - 1], offsets[k] = -radii[k - 1], radii[k]
    for i in range(k + 1, m):
        offsets[i] = offsets[i - 1] + radii[i - 1] + radii[i]
    for i in range(k - 2 + m % 2, -1, -1):
        offsets[i] = offsets[i + 1] - radii[i + 1] - radii[i]
    return offsets


def advance_turn(turn: float, last_angle: float, angle: float) -> float:
    """The running (unwrapped) turn after the wrapped angle moved from ``last_angle`` to
    ``angle``: the step is taken the short way round, so the count goes on past ±π. A NaN turn
    (no valid estimate yet) starts at ``angle``."""
    if math.isnan(turn):
        return angle
    delta = angle - last_angle
    if delta > math.pi:
        delta -= 2 * math.pi
    elif delta < -math.pi:
        delta += 2 * math.pi
    return turn + delta


def _surrounds(contacts: Sequence[tuple[float, float, float]]) -> bool:
    """Whether the contact directions leave no open side: the widest angle between
    neighbouring directions is less than half a turn (by ``CAGE_GAP``)."""
    if len(contacts) < 3:
        return False
    angles = sorted(math.atan2(gy, gx) for _, gx, gy in contacts)
    widest = angles[0] + 2 * math.pi - angles[-1]
    for a, b in itertools.pairwise(angles):
        widest = max(widest, b - a)
    return widest < math.pi - CAGE_GAP


def _chebyshev_step(cons: Sequence[tuple[float, float, float]]) -> tuple[tuple[float, float], int]:
    """One active-set step of ``max_c min_k s_k + g_k·Δ`` on the tightest constraints.

    Three constraints that surround the point (non-negative multipliers of
    ``Σ μ_k g_k = 0, Σ μ_k = 1``) have a finite maximiser, where all three are equal: the
    Newton step goes there, and the second value is -1. Otherwise the constraint whose
    multiplier is the most negative is not holding the object back: the second value is its
    index (the one to exchange), and the step ascends along the other two.
    """
    # fewer than three (a hand of one or two links in all): none surrounds the object, and the
    # index past the two given names the third, missing, one (the caller only exchanges among
    # four); it was unbound, and the estimator raised at the first tick on such a hand
    worst = 2
    if len(cons) == 3:
        (s1, a1, b1), (s2, a2, b2), (s3, a3, b3) = cons
        # A = [[a1, b1, -1], [a2, b2, -1], [a3, b3, -1]]; solve A [dx, dy, t] = -s and
        # A^T mu = (0, 0, -1) with the adjugate (cofactors) of A.
        c11 = -b2 + b3
        c12 = -(-a2 + a3)
        c13 = a2 * b3 - a3 * b2
        c21 = -(-b1 + b3)
        c22 = -a1 + a3
        c23 = -(a1 * b3 - a3 * b1)
        c31 = -b1 + b2
        c32 = -(-a1 + a2)
        c33 = a1 * b2 - a2 * b1
        det = a1 * c11 + b1 * c12 - c13
        if abs(det) > 1e-9:
            # A^-1 = adj(A) / det with adj(A) = C^T, so A^-T = C / det: mu_i = -C_i3 / det
            mu1, mu2, mu3 = -c13 / det, -c23 / det, -c33 / det
            if mu1 >= 0.0 and mu2 >= 0.0 and mu3 >= 0.0:
                r1, r2, r3 = -s1, -s2, -s3
                dx = (c11 * r1 + c21 * r2 + c31 * r3) / det
                dy = (c12 * r1 + c22 * r2 + c32 * r3) / det
                return (dx, dy), -1
            worst = 0 if mu1 <= mu2 and mu1 <= mu3 else (1 if mu2 <= mu3 else 2)
            cons = [c for k, c in enumerate(cons) if k != worst]
        else:
            cons = list(cons[:2])
    if len(cons) >= 2:
        (s1, a1, b1), (s2, a2, b2) = cons[0], cons[1]
        ex, ey = a1 - a2, b1 - b2
        e2 = ex * ex + ey * ey
        # equalise the two clearances (the least move along g1 - g2), then ascend on both
        k = (s2 - s1) / e2 if e2 > 1e-12 else 0.0
        dx, dy = k * ex, k * ey
        sx, sy = a1 + a2, b1 + b2
        norm = math.hypot(sx, sy)
        if norm < 1e-6:  # pinched between opposite walls: the object sinks along them
            sx, sy = (b1, -a1) if -a1 < 0.0 else (-b1, a1)
            norm = 1.0
        return (dx + MAX_STEP * sx / norm, dy + MAX_STEP * sy / norm), worst
    s1, a1, b1 = cons[0]
    return (MAX_STEP * a1, MAX_STEP * b1), 0
