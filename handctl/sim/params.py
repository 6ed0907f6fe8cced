"""The ``sim:`` section of a hand config: every physical number of the simulated hand, with units.

The simulation is only worth something if a recipe that works in it has a chance on the robot,
so nothing physical is hidden in code: link radii and masses, joint friction, the tendon-drive
lag, contact friction per pair, sensor imperfections and the scene all come from the hand config
(SI units, written next to each key there). The section is read with the same strict ``Doc``
discipline as the rest of the config: unknown keys are refused, and every message names the file,
the key path (``sim.objects[1].radius``), what was expected and what was found.

Geometry that the host also needs (finger bases, link lengths, limits) stays in the main part of
the config and is not repeated here; this section only adds what the host never sees.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

from handctl.config import HandConfig, JointConfig, SafetyConfig
from handctl.convention import MAX_OBJECT_RADIUS, NAME_CHARS, OBJECT_NAME
from handctl.errors import ConfigError
from handctl.schema import Doc, description
from handctl.sim.placement import check_placement

#: The emulated nodes run on a 1 ms tick (the protocol's feedback period and watchdog unit).
NODE_TICK_S = 0.001
NODE_TICK_NS = 1_000_000
#: rad, how far inside its soft limits a joint must start: one placed on a limit settled
#: past it under gravity and stopped the run at tick 1 (ANGLE_LIMIT), one 1 mrad inside at
#: tick 6; 10 mrad held
START_MARGIN = 0.01
#: rad, what the start's margin forgives of a difference of two decimal angles in binary
_ROUNDING_RAD = 1e-9
#: m and kg, the thinnest and the lightest simulated link: MuJoCo refuses a body whose
#: inertia is below its mjMINVAL (a link of 1e-12 kg, or one 1e-9 m thick, ended a run in a
#: traceback, exit 1); no finger is thinner than 2 mm or lighter than the lightest object
MIN_LINK_RADIUS = 0.001
MIN_LINK_MASS = 0.001


@dataclass(frozen=True)
class LinkParams:
    radius: float  # m, capsule radius of the link (half the finger's thickness)
    mass: float  # kg


@dataclass(frozen=True)
class ObjectParams:
    name: str
    radius: float  # m
    length: float  # m, along z (the joint axes)
    mass: float  # kg
    x: float  # m, initial centre
    y: float  # m
    angle: float  # rad, initial rotation about z


@dataclass(frozen=True)
class FrictionParams:
    """Coulomb friction coefficient of each contact pair kind (dimensionless)."""

    finger_object: float
    object_object: float
    object_table: float
    object_palm: float
    finger_table: float
    finger_palm: float


@dataclass(frozen=True)
class TdtParams:
    noise: float  # N·m, standard deviation of white noise per sample
    bias: float  # N·m, standard deviation of the per-sensor constant bias drawn at start
    lag: float  # s, first-order time constant of the sensor and its filter
    resolution: float  # N·m, ADC step
    range: float  # N·m, a reading beyond this fails the node's self-check


@dataclass(frozen=True)
class EncoderParams:
    counts_per_rev: int  # encoder counts per joint revolution
    max_step: float  # rad, a change larger than this in one 1 ms tick fails the self-check


@dataclass(frozen=True)
class SimParams:
    seed: int
    timestep: float  # s, physics step; the 1 ms node tick is split into ``substeps`` of it
    gravity: float  # m/s², along -y
    table_height: float  # m, y of the table top
    palm_half_width: float  # m, half the palm's extent along x (the palm's face is y = 0)
    palm_thickness: float  # m, along +y above the face
    links: tuple[LinkParams, ...]  # per joint in config order (finger by finger)
    # per joint in config order (the config may give one number for every joint): no two
    # tendons run through the same sheaths, so no two joints have quite the same dynamics
    damping: tuple[float, ...]  # N·m·s/rad, viscous joint damping
    frictionloss: tuple[float, ...]  # N·m, dry joint friction
    armature: tuple[float, ...]  # kg·m², motor and pulley inertia reflected to the joint
    stop_margin: float  # rad, mechanical stops lie this far beyond the soft limits
    actuator_lag: tuple[float, ...]  # s, first-order time constant of each tendon drive
    motor_tau_max: tuple[float, ...]  # N·m, per joint in config order: the most a motor gives
    initial_angles: tuple[tuple[float, ...], ...]  # rad, per finger in config order
    objects: tuple[ObjectParams, ...]
    friction: FrictionParams
    contact_timeconst: float  # s, MuJoCo solref time constant of every contact
    contact_dampratio: float  # dimensionless, MuJoCo solref damping ratio
    # Links of different fingers collide (with this friction coefficient) when True; when
    # False they pass through one another, as fingers that cannot meet need no contact test.
    between_fingers: bool
    finger_finger_friction: float  # 0 when between_fingers is False
    tdt: TdtParams
    encoder: EncoderParams

    @property
    def substeps(self) -> int:
        """Physics steps per 1 ms node tick."""
        return round(NODE_TICK_S / self.timestep)


def check_scene_names(source: str, names: Sequence[str], hand: HandConfig) -> None:
    """A ``ConfigError`` naming ``source``'s first object (a recipe's or a template's
    ``objects[i].name``) that the simulated hand's scene does not have: the estimator's
    truth, the experiment and the planner's models all find an object by its name there, and
    a template planned on objects the scene lacks gave a recipe every run refused."""
    scene = [o.name for o in parse_sim(hand).objects]
    for i, name in enumerate(names):
        if name not in scene:
            raise ConfigError(
                source,
                f"objects[{i}].name",
                f"an object of the simulated hand ({', '.join(scene)}: sim.objects in "
                f"{hand.source})",
                name,
            )


def parse_sim(hand: HandConfig) -> SimParams:
    """Validate ``hand.sim``; raises ``ConfigError`` naming ``hand.source`` and the key path."""
    root = Doc({"sim": dict(hand.sim)} if hand.sim else {}, hand.source, "")
    doc = root.mapping("sim")
    seed = doc.integer("seed", min=0, max=2**32 - 1)
    timestep = doc.number("timestep", min=1e-5, max=NODE_TICK_S, unit="s")
    substeps = NODE_TICK_S / timestep
    if abs(substeps - round(substeps)) > 1e-9:
        doc.fail(
            "timestep", "a whole fraction of the 1 ms node tick (0.001, 0.0005, ...) s", timestep
        )
    gravity = doc.number("gravity", min=0.0, max=20.0, unit="m/s²")

    table = doc.mapping("table")
    table_height = table.number("height", min=-5.0, max=0.0, min_exclusive=False, unit="m")
    table.done()
    palm = doc.mapping("palm")
    palm_half_width = palm.number("half_width", min=0.0, max=0.5, min_exclusive=True, unit="m")
    palm_thickness = palm.number("thickness", min=0.0, max=0.5, min_exclusive=True, unit="m")
    palm.done()

    links = _parse_links(doc.mapping("links"), hand)

    joints = doc.mapping("joints")
    n = hand.n_joints
    damping = _per_joint(joints, "damping", n, min=0.0, max=10.0, unit="N·m·s/rad")
    frictionloss = _per_joint(joints, "frictionloss", n, min=0.0, max=1.0, unit="N·m")
    armature = _per_joint(joints, "armature", n, min=0.0, max=1.0, unit="kg·m²")
    stop_margin = joints.number("stop_margin", min=0.0, max=1.0, unit="rad")
    joints.done()

    actuator = doc.mapping("actuator")
    lag = _per_joint(actuator, "lag", n, min=0.0, max=1.0, min_exclusive=True, unit="s")
    motor_tau_max = _parse_motor_tau_max(actuator.mapping("motor_tau_max"), hand)
    actuator.done()

    initial_angles = _parse_initial_angles(doc.mapping("initial_angles"), hand)
    objects = tuple(_parse_object(d) for d in doc.mappings("objects", min_len=1, max_len=4))
    friction_doc = doc.mapping("friction")
    friction = _parse_friction(friction_doc)

    contact = doc.mapping("contact")
    # softer than ``MAX_CONTACT_TIMECONST_S`` the objects sink into what they rest on: at 0.5 s
    # the pair lay 25 mm into the table and the run stopped on a joint's limit, a config
    # `handctl check` had passed (found by an outside audit)
    timeconst = contact.number("timeconst", min=2 * timestep, max=MAX_CONTACT_TIMECONST_S, unit="s")
    dampratio = contact.number("dampratio", min=0.1, max=10.0)
    between_fingers = contact.boolean("between_fingers", default=False)
    contact.done()
    finger_finger = 0.0
    if between_fingers:
        finger_finger = coefficient(friction_doc, "finger_finger")
    elif friction_doc.has("finger_finger"):
        friction_doc.fail(
            "finger_finger",
            "no finger_finger friction while "
            "sim.contact.between_fingers is false (fingers do not touch)",
            friction_doc.raw("finger_finger"),
        )
    friction_doc.done()

    tdt_doc = doc.mapping("tdt")
    tdt = TdtParams(
        noise=tdt_doc.number("noise", min=0.0, max=1.0, unit="N·m"),
        bias=tdt_doc.number("bias", min=0.0, max=1.0, unit="N·m"),
        lag=tdt_doc.number("lag", min=0.0, max=1.0, unit="s"),
        resolution=tdt_doc.number("resolution", min=0.0, max=0.1, unit="N·m"),
        range=tdt_doc.number("range", min=0.1, max=3.2767, unit="N·m"),
    )
    _check_tdt_range(tdt_doc, tdt.range, hand)
    _check_tdt_noise(tdt_doc, tdt, hand)
    _check_tdt_within_tolerance(tdt_doc, tdt, hand)
    _check_drive_and_sensor_lag(actuator, lag, tdt, hand)
    tdt_doc.done()
    enc_doc = doc.mapping("encoder")
    encoder = EncoderParams(
        counts_per_rev=enc_doc.integer("counts_per_rev", min=16, max=2**24),
        max_step=enc_doc.number("max_step", min=0.0, max=3.0, min_exclusive=True, unit="rad"),
    )
    count = 2 * math.pi / encoder.counts_per_rev
    if encoder.max_step <= count:
        # every node latched SENSOR at the first count its joint moved, in the tick it was
        # enabled: the run stopped at tick 1 on NODE_CONTRADICTION, far from this key
        enc_doc.fail(
            "max_step",
            f"a step larger than one encoder count (2π/counts_per_rev = {count:.3g} rad): "
            "a joint that moves one count in a tick must not fail the node's self-check",
            encoder.max_step,
        )
    enc_doc.done()
    doc.done()

    params = SimParams(
        seed=seed,
        timestep=timestep,
        gravity=gravity,
        table_height=table_height,
        palm_half_width=palm_half_width,
        palm_thickness=palm_thickness,
        links=links,
        damping=damping,
        frictionloss=frictionloss,
        armature=armature,
        stop_margin=stop_margin,
        actuator_lag=lag,
        motor_tau_max=motor_tau_max,
        initial_angles=initial_angles,
        objects=objects,
        friction=friction,
        contact_timeconst=timeconst,
        contact_dampratio=dampratio,
        between_fingers=between_fingers,
        finger_finger_friction=finger_finger,
        tdt=tdt,
        encoder=encoder,
    )
    check_placement(hand, params, Doc({}, hand.source, "sim"))
    return params


def _per_joint(
    doc: Doc, key: str, n: int, *, min: float, max: float, min_exclusive: bool = False, unit: str
) -> tuple[float, ...]:
    """One number for every joint, or a list of ``n`` (one per joint, config order)."""
    value = doc.raw(key)
    if not isinstance(value, list):
        return (doc.number(key, min=min, max=max, min_exclusive=min_exclusive, unit=unit),) * n
    if len(value) != n:
        doc.fail(key, f"one number, or a list of {n} (one per joint)", f"{len(value)} numbers")
    sub = Doc({}, doc.file, doc.key_path(key))
    return tuple(
        sub.check_number(i, v, min=min, max=max, min_exclusive=min_exclusive, unit=unit)
        for i, v in enumerate(value)
    )


def _parse_links(doc: Doc, hand: HandConfig) -> tuple[LinkParams, ...]:
    """One list per finger, by finger name, of one ``{radius, mass}`` per joint (proximal
    first), flattened into config order.

    A joint that gives ``half_thickness`` (the estimator's link thickness) must be simulated
    with that radius: the two are one fact, and a simulation thicker or thinner than the
    estimator believes would fool every test of the estimator. A written 0 gives it too (a
    line link, which no simulated link is): taken for "not given", the estimator worked with
    line links beside 12 mm simulated ones and ``check`` said ok."""
    doc.expect(f.name for f in hand.fingers)
    links = []
    for i, finger in enumerate(hand.fingers):
        n = len(finger.joints)
        for k, (link_doc, joint) in enumerate(
            zip(doc.mappings(finger.name, min_len=n, max_len=n), finger.joints, strict=True)
        ):
            link = LinkParams(
                radius=link_doc.number("radius", min=MIN_LINK_RADIUS, max=0.2, unit="m"),
                mass=link_doc.number("mass", min=MIN_LINK_MASS, max=10.0, unit="kg"),
            )
            link_doc.done()
            given = joint.half_thickness_given or joint.half_thickness > 0
            if given and abs(link.radius - joint.half_thickness) > 1e-12:
                link_doc.fail(
                    "radius",
                    f"the half_thickness of {joint.name} "
                    f"({joint.half_thickness:g} m, fingers[{i}].joints[{k}]): the "
                    "estimator and the simulation must see one link"
                    + (
                        f" (a written 0 is a line link, and a simulated link's radius is "
                        f"at least {MIN_LINK_RADIUS:g} m: write the link's half thickness)"
                        if joint.half_thickness == 0
                        else ""
                    ),
                    link.radius,
                )
            links.append(link)
    doc.done()
    return tuple(links)


def _parse_motor_tau_max(doc: Doc, hand: HandConfig) -> tuple[float, ...]:
    """One list per finger, by finger name, of one limit per joint, flattened into config
    order; none below the joint's ``device_tau_max``: the node's saturation must be the one
    that binds (a weak motor is the motor_saturation fault)."""
    doc.expect(f.name for f in hand.fingers)
    limits: list[float] = []
    for finger in hand.fingers:
        values = doc.numbers(finger.name, length=len(finger.joints), min=0.0, max=100.0, unit="N·m")
        where = Doc({}, doc.file, doc.key_path(finger.name))
        for k, (value, joint) in enumerate(zip(values, finger.joints, strict=True)):
            if value < joint.device_tau_max:
                where.fail(
                    k,
                    f"a value >= device_tau_max of {joint.name} "
                    f"({joint.device_tau_max:g} N·m): the node's saturation must be "
                    "the one that binds (a weak motor is the motor_saturation fault)",
                    value,
                )
        limits += values
    doc.done()
    return tuple(limits)


def _check_tdt_range(doc: Doc, limit: float, hand: HandConfig) -> None:
    """The sensor's range at least every joint's reading of ±device_tau_max (in the node's
    factory calibration, as the self-check sees it): below it a torque the node applies
    latched SENSOR and every run stopped on NODE_FAULT, with no word of this key. As
    ``motor_tau_max`` below ``device_tau_max``: the node's saturation must be what binds."""

    def reading_of(joint: JointConfig) -> float:
        ends = (-joint.device_tau_max, joint.device_tau_max)
        return max(abs((end - joint.tdt.offset) / joint.tdt.scale) for end in ends)

    joint = max(hand.joints, key=reading_of)  # the first of the largest, in config order
    reading = reading_of(joint)
    if limit < reading:
        doc.fail(
            "range",
            f"a range >= {reading:g} N·m, the reading of device_tau_max of {joint.name} "
            f"({joint.device_tau_max:g} N·m through its tdt scale and offset): a torque the "
            "node applies must not fail the node's self-check (it latches SENSOR)",
            limit,
        )


def _check_tdt_noise(doc: Doc, tdt: TdtParams, hand: HandConfig) -> None:
    """Noise of at least half the step the host reads a joint's torque in, while the host
    stops on a reading that never moves (``safety.tdt_stuck_still_s``): that watchdog exists
    for a sensor whose reading is bit-identical that long, and a simulated one quieter than
    its steps is such a sensor (noise 0, or 1e-300, stopped every run on TDT_STUCK at the
    first half second of steady torque). The step is the coarser of the sensor's ADC step
    and the Feedback signal's, in N·m through the joint's tdt scale. At half a step a reading
    in the middle of a step stays on it with a chance of 0.68 a sample (P(|z| < 1)), so it
    moves within a few ticks; at a sixth of one, 0.997 a sample, it stays put for the 500
    ticks of the default window about one time in four. ``tdt_stuck_still_s: 0`` is how to
    simulate a noiseless sensor."""
    from handctl.hand_protocol import protocol_for

    still = hand.safety.tdt_stuck_still_s
    if still == 0:
        return
    protocol = protocol_for(hand)
    steps = []
    for finger in hand.fingers:
        feedback = protocol.layout("Feedback", finger.node_id)
        for k, joint in enumerate(finger.joints):
            wire = abs(feedback.signals[k].scale * joint.tdt.scale)
            steps.append((max(tdt.resolution, wire), joint.name, feedback.signals[k], feedback))
    step, name, signal, message = max(steps, key=lambda s: s[0])
    if tdt.noise < step / 2:
        doc.fail(
            "noise",
            f"a noise >= {step / 2:g} N·m, half the step the host reads {name}'s torque in "
            f"({step:g} N·m: sim.tdt.resolution, or {message.name}.{signal.name} through "
            f"its tdt scale), while safety.tdt_stuck_still_s is {still:g} s: a quieter "
            "sensor reads one value that long and every run stops on TDT_STUCK "
            "(safety.tdt_stuck_still_s: 0 turns that check off, for a noiseless sensor)",
            tdt.noise,
        )


def _check_tdt_within_tolerance(doc: Doc, tdt: TdtParams, hand: HandConfig) -> None:
    """A simulated sensor the host's TDT cross-check can live with: its bias and its noise
    (standard deviations) each below ``safety.tdt_tolerance`` (at one sigma a third of the
    sensors read beyond it, and nearly every run of a hand of several joints stops: a sensor
    model that says the sensor cannot be used; a model with some chance of a mismatch, a
    wider spread's, still runs and is judged by its runs), and its lag at most the host's
    model of it (``safety.tdt_lag_s``) plus half the window a mismatch must last
    (``safety.tdt_window_s``), beyond which a ramp of the torque reads wrong for longer than
    the window. Beyond either, every run stopped on TDT_MISMATCH in its first tenth of a
    second, on a config ``check`` passed."""
    safety = hand.safety
    for key, value in (("bias", tdt.bias), ("noise", tdt.noise)):
        if value >= safety.tdt_tolerance:
            doc.fail(
                key,
                f"a {key} (1 sigma) below safety.tdt_tolerance ({safety.tdt_tolerance:g} "
                "N·m): a sensor that far off stops nearly every run on TDT_MISMATCH",
                description(f"{value:g} N·m"),
            )
    slowest = _slowest_tdt(safety)
    fastest = safety.tdt_lag_s - safety.tdt_window_s / 2
    if tdt.lag < fastest:
        # the other way: a host that expects the sensor this much slower than it is reads
        # every ramp wrong for longer than the window (tdt_lag_s 1 s against a sensor of 2 ms
        # stopped every run on TDT_MISMATCH in its first tenth of a second)
        doc.fail(
            "lag",
            f"at least {fastest:g} s, safety.tdt_lag_s ({safety.tdt_lag_s:g} s, the host's "
            f"model of the sensor) less half safety.tdt_window_s ({safety.tdt_window_s:g} "
            "s): the host expects the sensor's reading to lag the command that much, and a "
            "faster sensor reads each torque ramp 'wrong' for longer than the window; make "
            "safety.tdt_lag_s the sensor's lag",
            description(f"{tdt.lag:g} s"),
        )
    if tdt.lag > slowest:
        doc.fail(
            "lag",
            f"at most {slowest:g} s, safety.tdt_lag_s ({safety.tdt_lag_s:g} s, the host's "
            f"model of the sensor) plus half safety.tdt_window_s ({safety.tdt_window_s:g} s): "
            "a slower sensor reads the recipe's torque ramps wrong for longer than the window "
            "and stops the run on TDT_MISMATCH (on the shipped hand a lag of 0.03 s runs the "
            "swap, 0.04 s stops it)",
            description(f"{tdt.lag:g} s"),
        )


def _slowest_tdt(safety: SafetyConfig) -> float:
    """s, the most the torque the sensor reads may lag the command: the host's model of it
    (``safety.tdt_lag_s``) plus half the window a mismatch must last."""
    return safety.tdt_lag_s + safety.tdt_window_s / 2


def _check_drive_and_sensor_lag(
    doc: Doc, lag: tuple[float, ...], tdt: TdtParams, hand: HandConfig
) -> None:
    """The sensor reads the torque the drive transmits, so the lag the host's TDT check
    meets is the drive's and the sensor's together: held to the bound the sensor's lag alone
    is held to (``safety.tdt_lag_s`` plus half ``safety.tdt_window_s``). A drive lag of 1 s
    passed ``check`` beside the sensor's 2 ms and stopped every run on TDT_MISMATCH in its
    first tenth of a second (an outside audit)."""
    safety = hand.safety
    slowest = _slowest_tdt(safety)
    worst = max(range(len(lag)), key=lambda i: lag[i])
    if lag[worst] + tdt.lag > slowest + 1e-12:
        doc.fail(
            "lag",
            f"at most {slowest - tdt.lag:g} s, so that with sim.tdt.lag ({tdt.lag:g} s) the "
            f"torque the sensor reads lags the command by no more than safety.tdt_lag_s "
            f"({safety.tdt_lag_s:g} s) plus half safety.tdt_window_s "
            f"({safety.tdt_window_s:g} s): more, and the recipe's torque ramps read wrong for "
            "longer than the window and stop the run on TDT_MISMATCH",
            description(f"{lag[worst]:g} s ({hand.joints[worst].name})"),
        )


def _parse_initial_angles(doc: Doc, hand: HandConfig) -> tuple[tuple[float, ...], ...]:
    """One list per finger, by finger name, inside the soft limits (by ``START_MARGIN``): a
    start outside them, or on one, would trip the host's soft-limit check before anything
    happened."""
    doc.expect(f.name for f in hand.fingers)
    angles = []
    for finger in hand.fingers:
        values = doc.numbers(
            finger.name, length=len(finger.joints), min=-2 * math.pi, max=2 * math.pi, unit="rad"
        )
        where = Doc({}, doc.file, doc.key_path(finger.name))
        for k, (value, joint) in enumerate(zip(values, finger.joints, strict=True)):
            if joint.angle_max - joint.angle_min < 2 * START_MARGIN - _ROUNDING_RAD:
                # asked for an angle "at least 0.01 rad inside" a range no angle is inside of
                # by that much (found by an outside audit)
                where.fail(
                    k,
                    f"a joint the simulated hand can start {START_MARGIN:g} rad inside both "
                    f"soft limits of: {joint.name}'s range [{joint.angle_min:g}, "
                    f"{joint.angle_max:g}] rad is narrower than {2 * START_MARGIN:g} rad "
                    "(widen it in the hand config)",
                    value,
                )
            inside = min(value - joint.angle_min, joint.angle_max - value)
            # to a nanoradian: 0.06 against a limit of 0.05 is 0.00999... in binary, and was
            # refused where 0.51 against 0.50 was taken
            if not inside >= START_MARGIN - _ROUNDING_RAD:
                where.fail(
                    k,
                    f"an angle within the soft limits of {joint.name} "
                    f"[{joint.angle_min:g}, {joint.angle_max:g}] rad, at least "
                    f"{START_MARGIN:g} rad inside (a joint that starts on a limit settles "
                    "past it: ANGLE_LIMIT at tick 1)",
                    value,
                )
        angles.append(values)
    doc.done()
    return tuple(angles)


def _parse_object(doc: Doc) -> ObjectParams:
    name = doc.string("name")
    if not OBJECT_NAME.match(name):
        # a recipe finds an object by this name and names its estimates after it: an
        # underscore passed check, and then no recipe could name the object at all
        doc.fail(
            "name",
            f"a name of letters and digits, starting with a letter, at most {NAME_CHARS} "
            "characters (recipes name the "
            "object's estimates after it: estimate.NAME_x)",
            name,
        )
    obj = ObjectParams(
        name=name,
        radius=doc.number("radius", min=0.005, max=MAX_OBJECT_RADIUS, unit="m"),
        length=doc.number("length", min=0.01, max=2.0, unit="m"),
        mass=doc.number("mass", min=0.001, max=20.0, unit="kg"),
        x=doc.number("x", min=-5.0, max=5.0, unit="m"),
        y=doc.number("y", min=-5.0, max=5.0, unit="m"),
        angle=doc.number("angle", default=0.0, min=-2 * math.pi, max=2 * math.pi, unit="rad"),
    )
    doc.done()
    return obj


#: The least Coulomb coefficient of a contact the simulated hand takes. At 1e-5 and below
#: (MuJoCo's own floor, ``mjMINMU``) a frictionless contact made the solver's answer jump: a
#: finger's joints leapt half a radian past their stops in one tick under 0.07 N·m, the run
#: ended on a node's SENSOR fault, and a pair was flung 45 cm in 10 ms (found by an outside
#: audit; 1e-4 ran). 0.001 is as slippery as a real contact gets, and every pair ran the
#: experiment with it.
MIN_FRICTION = 0.001


#: s, the softest contact the simulated hand takes (MuJoCo's default is 0.02 s): a contact's
#: sag under a load goes as the square of its time constant, a quarter of a millimetre here
#: for a cylinder on the table.
MAX_CONTACT_TIMECONST_S = 0.05


def _parse_friction(doc: Doc) -> FrictionParams:
    values = {name: coefficient(doc, name) for name in FrictionParams.__dataclass_fields__}
    return FrictionParams(**values)


def coefficient(doc: Doc, name: str) -> float:
    """A contact's Coulomb coefficient, ``MIN_FRICTION`` at the least."""
    value = doc.number(name, min=0.0, max=3.0)
    if value < MIN_FRICTION:
        doc.fail(
            name,
            f"at least {MIN_FRICTION:g}: the simulator's contacts come apart with no friction "
            f"at all (write {MIN_FRICTION:g} for a frictionless contact)",
            f"{value:g}",
        )
    return value
