"""The ``handctl`` command: the one place in handctl that prints.

Exit codes (the same for every subcommand):

==== =====================================================================
0    done
1    finished, but the result is a failure (e.g. a replay mismatch, a run's log lost or
     possibly incomplete)
2    bad input: configuration, recipe, scenario, arguments; nothing was sent
3    safety stop: a fault stopped the hand
4    bus unavailable or failed
5    the host failed the timing check (``check --timing``, or before a run on a real bus);
     nothing was sent
130  interrupted (Ctrl-C, SIGTERM, SIGHUP, Ctrl-\\, SIGUSR1/2, SIGALRM, SIGXCPU or any other
     signal whose default would kill the process, and for a run Ctrl-Z), after a controlled
     stop
==== =====================================================================

A run that reaches its ``--max-seconds`` stops under control with the outcome ``time_budget``
and exit 0: it did what was asked. A reader that leaves early (``handctl check | head -1``)
does not change the exit code: the command finishes its work and says nothing more.
"""

from __future__ import annotations

import argparse
import contextlib
import difflib
import io
import math
import os
import re
import shlex
import shutil
import signal
import sys
import textwrap
import threading
from collections.abc import Callable, Iterator, Mapping, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import IO, TYPE_CHECKING, Any

from handctl import __version__, mujoco_opengl_off
from handctl.errors import (
    BusError,
    ConfigError,
    Description,
    HandctlError,
    absent,
    escaped,
    said_by,
    shown,
)
from handctl.lossyout import LossyOut

if TYPE_CHECKING:
    from handctl.bringup.calibrate import Calibration
    from handctl.bringup.jog import JogReport
    from handctl.config import HandConfig
    from handctl.online.loop import RunResult
    from handctl.online.recipes.reanalysis import Reanalyser
    from handctl.online.recipes.schema import Recipe
    from handctl.planning.replan import Base
    from handctl.planning.template import Template
    from handctl.recording.reader import Recording
    from handctl.recording.rerun import RerunReport
    from handctl.sim.params import SimParams
    from handctl.stopsignals import StopSignals

EXIT_OK = 0
EXIT_FAILED = 1
EXIT_BAD_INPUT = 2
EXIT_SAFETY_STOP = 3
EXIT_BUS = 4
EXIT_HOST = 5
EXIT_INTERRUPTED = 130

#: The hand a command drives unless told otherwise: shipped inside the package, so that the
#: default does not depend on the current directory. ``config/hands/hiroshima_hand.yaml`` is
#: the repository's copy, kept identical by a test (tests/unit/test_cli_defaults.py).
DEFAULT_HAND = Path(__file__).resolve().parent / "hands" / "hiroshima_hand.yaml"
DEFAULT_HAND_HELP = "default: the Hiroshima-Hand, shipped with handctl"
#: A simulated hand told to stop by SIGTERM waits this long (s) for its host to be gone:
#: SIGTERM is the parent-death signal, which comes when the host's first thread dies, and a
#: host killed with SIGKILL on a loaded machine took more than 2 s to take the rest down
#: (its bus directory was then left behind). The wait ends as soon as the host is gone; only
#: a SIGTERM sent to the hand alone, its host alive, waits it out.
ORPHAN_WAIT_S = 10.0
#: the largest |k| of ``analyze torque-set --k``: a second joint's torque a thousand times the
#: first's is already a slice along one axis; 1e308 overflowed the grid
MAX_TORQUE_RATIO = 1e3
#: the slowest and fastest ``replay --speed``: a log of a minute replays in 17 hours at the
#: slowest (1e-300 overflowed the clock's time stamps, 1e-9 waited for ever); at the fastest
#: the frames go out as fast as the bus takes them anyway
MIN_REPLAY_SPEED = 1e-3
MAX_REPLAY_SPEED = 1e3
#: s, the shortest timing check: ten ticks at 1 kHz (1e-300 s gave a verdict on no tick)
MIN_TIMING_CHECK_S = 0.01
#: the fewest loop periods a TDT calibration measures for (an offset and a noise need samples)
CALIBRATION_MIN_PERIODS = 10
#: s, the timing check's length when --seconds is not given
TIMING_CHECK_DEFAULT_S = 10.0


def _load_hand(path: Path, option: str, dbc: Path | None = None) -> HandConfig:
    """The hand config at ``path``, speaking the protocol of ``dbc`` (``--dbc``) or the one
    generated from it; a file that is not there is reported against the option (or
    argument) that named it, the first thing to check when it is the default."""
    from handctl.config import load_hand

    if not path.is_file():
        raise ConfigError(
            option,
            "",
            "an existing hand config file (HAND.yaml; " + DEFAULT_HAND_HELP + ")",
            Description(f"{escaped(str(path))}: {'not a file' if path.exists() else absent(path)}"),
        )
    _check_dbc_file(dbc)
    return load_hand(path) if dbc is None else load_hand(path, dbc)


def _check_dbc_file(dbc: Path | None) -> None:
    """A ``--dbc`` that names no file is refused against the option."""
    if dbc is not None and not dbc.is_file():
        raise ConfigError(
            "--dbc",
            "",
            "an existing DBC file (PROTOCOL.dbc)",
            Description(f"{escaped(str(dbc))}: {'not a file' if dbc.exists() else absent(dbc)}"),
        )


def _positive_seconds(option: str, value: float | None) -> None:
    """A duration option: > 0 and at most ``MAX_BUDGET_S`` (about 115 days: a budget is
    counted in ticks, and 1e308 s overflowed the count). Leaving the option out is how to ask
    for no limit."""
    from handctl.online.timebudget import MAX_BUDGET_S

    if value is not None and not 0 < value <= MAX_BUDGET_S:
        raise ConfigError(
            option,
            "",
            f"a number of seconds > 0 and <= {MAX_BUDGET_S:g} (leave the option out for no limit)",
            value,
        )


def _output_path(text: str) -> Path:
    """An option's file to write, as ``Path`` would take it, but for a name that ends in a
    separator: ``Path`` drops it, and ``--log y.mcap/`` wrote (or replaced) ``y.mcap`` where
    the system would have refused a file name that is a directory's."""
    if text.endswith(os.sep) or (os.altsep is not None and text.endswith(os.altsep)):
        raise argparse.ArgumentTypeError(f"expected a file name, found {text!r} (a directory's)")
    if text in ("", "-"):
        # '' was the current directory ('.'), '-' a file of that name where standard output
        # was meant: neither is written
        why = "an empty name" if not text else "standard output is not written to: give a file"
        raise argparse.ArgumentTypeError(f"expected a file name, found {text!r} ({why})")
    return Path(text)


def _output_dir(text: str) -> Path:
    """An option's directory to write files in: a trailing separator is how a directory is
    often named, unlike ``_output_path``'s files. An empty name was the current directory
    (``Path('')``), where the files were written unasked."""
    if not text:
        raise argparse.ArgumentTypeError("expected a directory name, found '' (nothing)")
    return Path(text)


def _json_text(value: Any, indent: int | None = 2) -> str:
    """``value`` as JSON that any reader takes: a NaN or an infinity (a value a log lacks, a
    figure of nothing) is written ``null``, where ``json.dumps`` wrote ``NaN``, which is not
    JSON and which strict readers (``jq``, browsers, most languages) refuse. A string that is
    not valid UTF-8 (a path with a byte of another encoding, which Python holds as a lone
    surrogate) has that byte as ``\\xNN``, as the recording's metadata has it: written as it
    was, ``"\\udcff"``, strict readers (orjson, Rust, Go) refused the whole file."""
    import json

    def finite(v: Any) -> Any:
        if isinstance(v, str):
            return _utf8_text(v)
        if isinstance(v, float):
            return v if math.isfinite(v) else None
        if isinstance(v, dict):
            return {finite(k): finite(x) for k, x in v.items()}
        if isinstance(v, (list, tuple)):
            return [finite(x) for x in v]
        return v

    return json.dumps(
        finite(value), indent=indent, default=lambda v: _utf8_text(str(v)), allow_nan=False
    )


def _utf8_text(text: str) -> str:
    """``text`` as ``metadata.valid_text`` makes it, imported only for the rare string that
    needs it (the module costs a command that never records 0.2 s)."""
    try:
        text.encode("utf-8")
    except UnicodeEncodeError:
        from handctl.recording.metadata import valid_text

        return valid_text(text)
    return text


def _output_file(
    option: str,
    path: Path | None,
    *,
    json_output: bool = False,
    json_kind: tuple[str, frozenset[str]] | None = None,
) -> None:
    """An option naming a file to write: refused before any work (a run, a plan) when it
    cannot be written (``outfile.check_writable``), rather than found out at the end."""
    from handctl.outfile import check_writable

    if path is not None:
        check_writable(path, option, json_output=json_output, json_kind=json_kind)


def _refuse_same_files(outputs: dict[str, Path | None], inputs: dict[str, Path | None]) -> None:
    """``outfile.refuse_same_files``: an output that names an input or another output is
    refused before the work (it replaced a DBC, a hand config or a recording, exit 0)."""
    from handctl.outfile import refuse_same_files

    refuse_same_files(outputs, inputs)


def _plot_file(option: str, path: Path | None) -> None:
    """An option naming a picture to draw: a file that can be written, in a format a plot can
    be written in (``outfile.check_image``), asked before the work."""
    from handctl.outfile import check_image

    if path is not None:
        check_image(path, option)


def _write_output(option: str, path: Path, text: str) -> None:
    """An output the options named, whole or not at all (``outfile.write_atomically``); a
    failure at the end (a full disk, a directory gone since it was checked) is said by name,
    exit 1: the work was done, its file was not written."""
    from handctl.outfile import write_atomically
    from handctl.wholefile import left_as_it_was

    existed = path.exists()
    try:
        write_atomically(path.resolve(), text)
    except OSError as exc:
        raise HandctlError(
            f"{option}: {path} could not be written ({exc}); {left_as_it_was(existed)}"
        ) from None


def _say_in_process_bus(option: str, spec: str | None) -> None:
    """A python-can ``virtual`` bus is a queue inside one process: a command on one hears
    and reaches nobody but itself. ``run`` waited out a timing check and its start-up to stop
    on 'no feedback' (exit 3), ``nodes`` listed every node missing, ``replay --to-bus`` sent
    its frames to nobody, each without saying why."""
    if spec is not None and spec.startswith("virtual:"):
        print(
            f"handctl: warning: {option} {escaped(spec)} lives inside this process: nothing "
            "in another process hears or answers it (a simulated hand in another process is "
            "on unix:DIRECTORY; the one this command starts is --bus sim)",
            file=sys.stderr,
        )


def _refuse_no_simulated_hand(hand: HandConfig, bus: str) -> None:
    """A hand config without a ``sim:`` section on the simulated hand's bus: said as the bus
    not given. It was "sim: expected this key (required)", which sent the user with a real
    hand's config to write a simulation, where ``--bus`` was forgotten (an outside audit)."""
    if not hand.sim:
        raise ConfigError(
            hand.source,
            "sim",
            f"a sim: section for --bus {bus}, the simulated hand (the default bus); for the "
            "hand itself give its bus: --bus hand (the interface in its config) or e.g. "
            "--bus socketcan:can0",
            "no sim: section",
        )


def _refuse_no_simulated_hand_on(hand: HandConfig, bus: str) -> None:
    """``_refuse_no_simulated_hand`` when ``bus`` is the simulated hand's."""
    from handctl.online.busspec import parse_spec

    if parse_spec(bus, hand.bus, hand.source).interface == "sim":
        _refuse_no_simulated_hand(hand, bus)


def _sim_seed(args: argparse.Namespace, hand: HandConfig) -> int:
    """``--seed`` (not given: the hand config's ``sim.seed``, as ``handctl sim`` takes it and
    docs/simulation.md says; it was 0 whatever the config said), once the options only the
    simulated hand takes are known to be for it: on another bus ``--seed`` and
    ``--sim-faults`` went unused without a word, and a run the user meant to disturb ran
    undisturbed (``--lockstep`` there was refused). ``--loop-cpu`` and ``--sim-cpu`` place the
    threads ``--rt`` makes real-time: without it they too did nothing. And ``--rt`` itself
    raises, pins and locks a real-time loop, which lockstep (the simulated hand's default)
    has none of: ``run recipe --rt --loop-cpu 0`` ran at SCHED_OTHER on every CPU, exit 0."""
    from handctl.online.busspec import parse_spec

    _say_in_process_bus("--bus", args.bus)  # run, calibrate and jog all come by here
    on_sim = parse_spec(args.bus, hand.bus, hand.source).interface == "sim"
    if on_sim:
        _refuse_no_simulated_hand(hand, args.bus)
    if not on_sim:
        sim_cpu = getattr(args, "sim_cpu", None)
        for option, value in (
            ("--seed", args.seed),
            ("--sim-faults", args.sim_faults),
            ("--sim-cpu", sim_cpu),  # no simulated hand's process to place
        ):
            if value is not None:
                raise ConfigError(
                    option,
                    "",
                    "the simulated hand (--bus sim): only it takes " + option,
                    f"{value} with --bus {args.bus}",
                )
    if on_sim and args.rt and not args.realtime:
        given = " ".join(
            f"{option} {value}" if value is not None else option
            for option, value in (
                ("--rt", None),
                ("--loop-cpu", getattr(args, "loop_cpu", None)),
                ("--sim-cpu", getattr(args, "sim_cpu", None)),
            )
            if option == "--rt" or value is not None
        )
        raise ConfigError(
            "--rt",
            "",
            "--realtime as well: on the simulated hand a run is stepped in lockstep unless "
            "--realtime, and lockstep has no real-time loop to raise, pin or lock",
            f"{given} in lockstep",
        )
    if not args.rt:
        for option in ("--loop-cpu", "--sim-cpu"):
            value = getattr(args, option[2:].replace("-", "_"), None)
            if value is not None:
                raise ConfigError(
                    option, "", "--rt as well (it places the real-time threads)", value
                )
    if args.seed is not None:
        return int(args.seed)
    if not on_sim:
        return 0  # no simulated hand to seed
    from handctl.sim.params import parse_sim

    return parse_sim(hand).seed


def _truth_to(path: Path) -> Callable[[dict[str, Any]], None]:
    """The simulated hand's ground truth into ``--summary-json`` at its end, whole or not at
    all (``_write_output``)."""

    def write(truth: dict[str, Any]) -> None:
        _write_output("--summary-json", path, _json_text(truth) + "\n")

    return write


def _progress(message: str) -> None:
    """Progress of long work goes to stderr, so stdout stays clean for results."""
    print(message, file=sys.stderr, flush=True)


# -- check ---------------------------------------------------------------------------------------
def _cmd_check_timing(args: argparse.Namespace) -> int:
    from handctl.hostcheck import check_loop_cpu, timing_check

    seconds = TIMING_CHECK_DEFAULT_S if args.seconds is None else args.seconds
    if not MIN_TIMING_CHECK_S <= seconds <= 3600:
        raise ConfigError(
            "--seconds",
            "",
            f"a number of seconds >= {MIN_TIMING_CHECK_S:g} and <= 3600",
            seconds,
        )
    if args.no_rt and args.loop_cpu is not None:
        # as a run refuses --loop-cpu without --rt: the CPU is where SCHED_FIFO pins the loop
        raise ConfigError(
            "--loop-cpu",
            "",
            "no --no-rt (the CPU is the one --rt pins the loop to; without it the loop runs "
            "where the scheduler puts it)",
            f"--loop-cpu {args.loop_cpu} --no-rt",
        )
    _refuse_same_files({"--json": args.json}, {args.hand_said: args.hand})
    _output_file("--json", args.json, json_output=True)
    hand = _load_checked_hand(args.hand, args.hand_said)
    check_loop_cpu(args.loop_cpu)  # before the line that says the check has begun
    _progress(
        f"timing check: a bare timer loop at {hand.bus.loop_rate_hz:g} Hz for {seconds:g} s ..."
    )
    report = timing_check(hand, seconds, realtime=not args.no_rt, cpu=args.loop_cpu)
    print(report.text())
    if args.json:
        _write_output("--json", args.json, _json_text(report.as_json()) + "\n")
    return EXIT_HOST if report.verdict.fails else EXIT_OK


#: s, the longest a joint's rate limit may take to slew its whole tau_max before ``check``
#: warns: the shipped hand takes 0.03 s; at 0.1 N·m/s (3-6 s) the guard's push-back reached
#: 7 % of what it asked before the joint met its limit
SLOW_SLEW_S = 0.25


def _scene_warnings(hand: HandConfig, scene: SimParams | None) -> list[str]:
    """What a hand config allows that no run of the experiment can do: the config is sound
    (bring-up, jog and any recipe without these parts run), but the user would otherwise
    learn it from every run's failure."""
    from handctl.convention import LIFT_HEIGHT
    from handctl.online.recipes.loader import GUARD_BAND_MIN, fits_no_guard

    out = []
    for joint in hand.joints:
        span = joint.angle_max - joint.angle_min
        if fits_no_guard(span):
            out.append(
                f"{escaped(joint.name)}'s range of {span:.4g} rad holds no two of the "
                f"soft-limit guard's narrowest bands ({GUARD_BAND_MIN:g} rad): every recipe "
                "with a limit_guard_band is refused on this hand"
            )
    if scene is not None:
        from handctl.sim.idle import IDLE_S, idle_excursions
        from handctl.sim.placement import unsupported

        for i, above in unsupported(hand, scene):
            out.append(
                f"sim.objects[{i}].y: {escaped(scene.objects[i].name)} starts "
                f"{above * 1e3:.1f} mm above the table with nothing under it: it falls at "
                "the first step, and its height above rest is measured from the table"
            )
        for e in idle_excursions(hand, scene):
            name = escaped(hand.joint_names[e.joint])
            out.append(
                f"with no torque on the simulated hand, {name} goes from its initial "
                f"{e.start:+.3f} rad past its soft limit {e.limit:+.3f} rad in {e.time_s:.3f} s "
                f"(idle for {IDLE_S:g} s, gravity and contacts only): a phase of zero torque "
                "(calibrate tdt's, a recipe's ramp from zero) stops on ANGLE_LIMIT; a start "
                "pose nearer where it hangs (sim.initial_angles) or a wider range avoids it"
            )
    for obj in scene.objects if scene is not None else ():
        # the palm's face is y = 0, the objects below it: the most a centre can rise
        room = -obj.radius - obj.y
        if room < LIFT_HEIGHT:
            out.append(
                f"sim.objects: {escaped(obj.name)} can rise {room * 1e3:.1f} mm before it "
                f"meets the palm, and the experiment counts an object lifted at "
                f"{LIFT_HEIGHT * 1e3:g} mm above its rest: no run on this scene succeeds"
            )
    return out


def _cmd_check(args: argparse.Namespace) -> int:
    args.hand = _hand_given(args)
    # an option of the other check did nothing, without a word: `check --json t.json` wrote
    # no file, `check --timing --dbc nosuch.dbc` never looked at it
    other = (
        [("--dbc", args.dbc)]
        if args.timing
        else [
            ("--seconds", args.seconds),
            ("--no-rt", args.no_rt or None),
            ("--loop-cpu", args.loop_cpu),
            ("--json", args.json),
        ]
    )
    for option, value in other:
        if value is not None:
            raise ConfigError(
                option,
                "",
                "the check it belongs to: "
                + ("the hand config's (without --timing)" if args.timing else "--timing"),
                value,
            )
    if args.timing:
        return _cmd_check_timing(args)
    from handctl.busload import MAX_LOAD, bus_refusals, hand_budget
    from handctl.hand_protocol import protocol_for
    from handctl.online.busspec import check_interface
    from handctl.sim.params import parse_sim

    hand = _load_hand(args.hand, args.hand_said, args.dbc)
    check_interface(hand.bus, hand.source)
    protocol = protocol_for(hand)

    # The simulated hand's section is in the same file: a mistake there is found here, before
    # `sim` or `run` meets it (the robot never reads it, so a config without one is fine).
    scene = parse_sim(hand) if hand.sim else None
    bus = hand.bus
    kind = (
        f"CAN-FD {bus.bitrate / 1e6:g}/{(bus.data_bitrate or 0) / 1e6:g} Mbit/s"
        if bus.fd
        else f"classic CAN {bus.bitrate / 1e6:g} Mbit/s"
    )
    print(f"hand {escaped(hand.name)} ({escaped(str(args.hand))}), config hash {hand.config_hash}")
    print(f"bus {escaped(f'{bus.interface}:{bus.channel}')}, {kind}, loop {bus.loop_rate_hz:g} Hz")
    # torques to the wire's resolution (0.0001 N·m: a tau_max of 0.0004 read 0.000), the
    # names' column as wide as the longest (up to 32 characters)
    width = max(8, *(len(j.name) for j in hand.joints))
    print(f"{'joint':<{width}} {'tau_max':>9} {'device':>9} {'rate':>10} {'angle range':>17}")
    for finger in hand.fingers:
        for joint in finger.joints:
            limits = f"[{joint.angle_min:+.2f}, {joint.angle_max:+.2f}] rad"
            print(
                f"{escaped(joint.name):<{width}} {joint.tau_max:>7.4f}Nm "
                f"{joint.device_tau_max:>7.4f}Nm {joint.rate_limit:>6.1f}N·m/s {limits}"
            )
    for finger in hand.fingers:
        ids = ", ".join(f"{k} 0x{v:03X}" for k, v in finger.can_ids.as_dict().items())
        print(f"node {finger.node_id} ({finger.name}): {ids}")
    if scene is not None:
        objects = ", ".join(f"{o.name} (r {o.radius:g} m)" for o in scene.objects)
        print(
            f"simulated hand: {objects}; "
            f"fingers {'collide' if scene.between_fingers else 'pass through each other'}"
        )
    budget = hand_budget(hand, protocol)
    print(f"\nworst-case bus budget ({kind}, {bus.loop_rate_hz:g} Hz loop):")
    print(
        f"{'message':<17} {'id':>6} {'bytes':>5} {'frames':>6} {'rate':>8} {'time':>9} {'load':>7}"
    )
    for m in budget.messages:
        rate = f"{m.rate_hz:g} Hz" if m.rate_hz else "event"
        print(
            f"{m.name:<17} 0x{m.frame_id:03X} {m.n_bytes:>5} {m.frames:>6} {rate:>8} "
            f"{m.frame_time_us:>7.1f}us {m.load * 100:>6.2f}%"
        )
    print(f"total {budget.load * 100:.1f} % (limit {MAX_LOAD * 100:.0f} %)")
    for joint in hand.joints:
        slew_s = joint.tau_max / joint.rate_limit
        if slew_s > SLOW_SLEW_S:
            print(
                f"handctl: warning: {escaped(str(args.hand))}: {escaped(joint.name)}.rate_limit "
                f"{joint.rate_limit:g} N·m/s takes {slew_s:.3g} s to reach its tau_max "
                f"({joint.tau_max:g} N·m): the soft-limit guard's push-back slews as slowly, "
                "and a joint at speed reaches its limit first (a safe stop, ANGLE_LIMIT, "
                "where the guard would have held it)",
                file=sys.stderr,
            )
    for warning in _scene_warnings(hand, scene):
        print(f"handctl: warning: {escaped(str(args.hand))}: {warning}", file=sys.stderr)
    refusals = bus_refusals(hand, protocol, budget)
    if not refusals:
        print("ok")
        return EXIT_OK
    for key, expected, found in refusals:
        print(
            f"handctl: error: {escaped(str(args.hand))}: {key}: expected {expected}, found {found}",
            file=sys.stderr,
        )
    return EXIT_BAD_INPUT


# -- analyze -------------------------------------------------------------------------------------
def _cmd_analyze_torque_set(args: argparse.Namespace) -> int:
    from handctl.analysis.commands import torque_set_report

    _plot_file("--plot", args.plot)
    _refuse_same_files({"--json": args.json, "--plot": args.plot}, {"SCENARIO.yaml": args.scenario})
    _output_file("--json", args.json, json_output=True)
    if not all(math.isfinite(k) and abs(k) <= MAX_TORQUE_RATIO for k in args.k):
        raise ConfigError(
            "--k", "", f"two finite ratios within ±{MAX_TORQUE_RATIO:g}", " ".join(map(str, args.k))
        )
    report = torque_set_report(
        args.scenario, (args.k[0], args.k[1]), args.json, args.plot, progress=_progress
    )
    print(report)
    return EXIT_OK


# -- run ---------------------------------------------------------------------------------------
class _StatusPrinter:
    """The live status line on a terminal, shown from inside the tick: a line the terminal
    cannot take now (Ctrl-S, a stalled SSH session) is dropped, never waited for
    (``handctl.lossyout``); ``finish`` once the run is over, before anything else is
    written to stderr."""

    def __init__(self) -> None:
        # a terminal that knows no escape sequences (TERM=dumb: an editor's shell, a serial
        # console) showed the erase as '^[[K' on every line: there, spaces erase instead
        self.dumb = os.environ.get("TERM") == "dumb"
        self.out = LossyOut(sys.stderr)

    def __call__(self, line: object) -> None:
        from handctl.online.loop import StatusLine

        assert isinstance(line, StatusLine)
        # stderr's terminal, where the line is drawn: stdout's (``shutil``'s first choice)
        # may be a file, and an 80-column line wrapped on a narrower terminal left a row
        # behind at every update (found by an outside audit)
        width = _stderr_columns()
        text = fit_width(status_text(line), width)
        # erased to the line's end: a shorter line leaves nothing of the one before
        end = " " * max(width - 1 - len(text), 0) if self.dumb else "\x1b[K"
        self.out.write("\r" + text + end)

    def finish(self) -> None:
        self.out.finish()


def _stderr_columns() -> int:
    """The width of stderr's terminal: ``COLUMNS`` if set, as ``shutil`` reads it, then
    stderr's own size, then ``shutil``'s answer (stdout's, or 80)."""
    try:
        given = int(os.environ.get("COLUMNS", ""))
    except ValueError:
        given = 0
    if given > 0:
        return given
    try:
        columns = os.get_terminal_size(sys.stderr.fileno()).columns
    except (OSError, ValueError):
        columns = 0
    return columns if columns > 0 else shutil.get_terminal_size().columns


def _status_printer() -> _StatusPrinter | None:
    """A live status line on a terminal; nothing when stderr is a file or a pipe."""
    if not sys.stderr.isatty():
        return None
    printer = _StatusPrinter()
    if printer.out.off:
        print(
            f"handctl: note: no live status line: stderr is {printer.out.off}, and a run "
            "never waits for its terminal",
            file=sys.stderr,
        )
    return printer


def fit_width(text: str, columns: int) -> str:
    """``text`` cut to fit a terminal ``columns`` wide, with room for the cursor: a status
    line that wraps is rewritten by ``\\r`` on its last row only, and the rows above pile up
    (132 characters with six phases timed out)."""
    room = max(columns - 1, 1)
    return text if len(text) <= room else text[: room - 1] + "…"


def status_text(line: object) -> str:
    """One status line: run time (marked as simulated in lockstep, which runs faster than
    the wall clock), phase k of n and the time in it, safety state, torque, lateness and the
    phases that ended on their timeout."""
    from handctl.online.loop import StatusLine

    assert isinstance(line, StatusLine)
    clock = "sim " if line.simulated else ""
    if 1 <= line.phase_number <= line.phase_count:
        where = (
            f"phase {line.phase_number}/{line.phase_count} {line.phase:<16} {line.phase_s:6.2f} s"
        )
    else:
        where = f"{line.phase:<28}"
    # the phases that ran out their max_s so far, which the docs promise the line says (it
    # carried them, and showed none)
    timed_out = f"  timed out: {', '.join(line.timed_out)}" if line.timed_out else ""
    return (
        f"{clock}{line.t_s:7.2f} s  {where}  {line.state:<10} "
        f"max|τ| {line.max_abs_tau:5.3f} N·m  late {line.lateness_us:7.1f} µs{timed_out}"
    )


def _own_miss_text(miss: dict[str, Any]) -> str:
    """One of handctl's own misses as its trace tells it (``misstrace.describe``); whole
    microseconds (a 3 s stop read "3.00164e+06 µs late")."""
    over = miss["cpu_over_usual"]
    text = (
        f"handctl's miss at tick {miss['tick']} ({miss['missed']} missed, "
        f"{miss['late_us']:.0f} µs late): the tick before ran {miss['cpu_us']:.0f} µs of CPU"
        + (f" ({over:g}x its usual)" if over is not None else "")
    )
    if miss["run_delay_us"] is not None:
        usual = miss["usual_run_delay_us"]
        text += (
            f", waited {miss['run_delay_us']:.0f} µs for the CPU"
            + (f" (usual {usual:.1f} µs)" if usual is not None else "")
            + f", {miss['off_cpu_us']:.0f} µs off it"
        )
    text += f", {miss['voluntary_switches']} voluntary switch(es), {miss['page_faults']} fault(s)"
    return text + (f"; in it: {', '.join(miss['notes'])}" if miss["notes"] else "")


def _load_checked_hand(path: Path, option: str, dbc: Path | None = None) -> HandConfig:
    """``_load_hand``, refusing what ``handctl check`` refuses: one config, one verdict, for
    every command that takes a hand config. A hand whose bus cannot carry it is bad input for
    any of them: at bus.loop_rate_hz 10000 a run began and stopped at tick 10 (RX_BACKLOG,
    exit 3), a classic-CAN hand was jogged and calibrated as fine, and ``handctl sim`` put
    16-byte frames on a classic bus. So is a ``bus.interface`` python-can does not know and
    a ``sim:`` section check refuses (a run on the robot never reads it, but the config that
    check turned away is the one the run would record as its hand)."""
    from handctl.busload import bus_refusals, hand_budget
    from handctl.hand_protocol import protocol_for
    from handctl.online.busspec import check_interface
    from handctl.sim.params import parse_sim

    hand = _load_hand(path, option, dbc)
    check_interface(hand.bus, hand.source)
    if hand.sim:
        parse_sim(hand)
    protocol = protocol_for(hand)
    refusals = bus_refusals(hand, protocol, hand_budget(hand, protocol))
    if refusals:
        raise ConfigError(str(path), *refusals[0])
    return hand


def _cmd_run_recipe(args: argparse.Namespace) -> int:
    from handctl.stopsignals import StopSignals, finished

    # The run's stop signals before anything else: a signal while the modules of a run load
    # (most of a second, more on a busy machine) is taken once they have, not inside one.
    with StopSignals() as signals:
        code = _run_recipe_under(args, signals)
        finished()  # the run's result stands from here (``stopsignals.finished``)
    if signals.ignored:
        # taken, not lost: a SIGTERM that exited 0 without a word looked unheard
        _came_after_the_stop(
            signals.ignored,
            ", while the run's log and summary were finished: they were finished first",
        )
    return code


def _came_after_the_stop(names: Sequence[str], then: str) -> None:
    """Say the stop signals ``names`` that came once the hand had stopped, and ``then``, what
    became of them: taken, not lost (a SIGTERM that exited without a word looked unheard)."""
    print(
        f"handctl: {', '.join(dict.fromkeys(names))} came after the hand had stopped{then}",
        file=sys.stderr,
    )


def _run_recipe_under(args: argparse.Namespace, signals: StopSignals) -> int:
    from handctl.online.clock import Hygiene
    from handctl.online.recipes.loader import load_recipe
    from handctl.outfile import check_log_target
    from handctl.session import RunInterrupted, RunRequest, interrupted_summary, run_recipe

    _positive_seconds("--max-seconds", args.max_seconds)
    _output_file("--summary-json", args.summary_json)
    _plot_file("--plot", args.plot)
    _refuse_same_files(
        {"--log": args.log, "--summary-json": args.summary_json, "--plot": args.plot},
        {
            "the recipe": args.recipe,
            "--hand": args.hand,
            "--dbc": args.dbc,
            "--sim-faults": args.sim_faults,
        },
    )
    _output_file("--summary-json", args.summary_json, json_output=True)
    # a FIFO blocked the run in open() for good, deaf to Ctrl-C; a device lost the log
    replaces_log = args.log is not None and check_log_target(args.log, "--log")
    hand = _load_checked_hand(args.hand, "--hand", args.dbc)
    recipe = load_recipe(args.recipe, hand)
    for name, undone in recipe.plan_failed:
        # run as asked (the engineer may mean to try it), but not as if it were a plan's
        print(
            f"handctl: warning: {args.recipe} is the recipe of a failed plan, written to be "
            f"looked at: its phase '{name}' left this undone on every model it was planned "
            f"on: {undone}",
            file=sys.stderr,
        )
    if args.live is not None and args.log is None:
        raise ConfigError(
            "--live",
            "",
            "--log RUN.mcap as well (the recording's writer serves the live view)",
            "no --log",
        )
    if args.live is not None:
        from handctl.foxglove import check_port_free

        check_port_free(args.live, "--live")
    lockstep = True if args.lockstep else (False if args.realtime else None)
    request = RunRequest(
        hand=hand,
        recipe=recipe,
        bus=args.bus,
        lockstep=lockstep,
        realtime_priority=args.rt,
        seed=_sim_seed(args, hand),
        reset_node_faults=args.reset_node_faults,
        sim_faults=args.sim_faults,
        max_seconds=args.max_seconds,
        log=args.log,
        command_line=tuple(sys.argv),
        plot=args.plot,
        hygiene=Hygiene(loop_cpu=args.loop_cpu, sim_cpu=args.sim_cpu),
        accept_missed_deadlines=args.accept_missed_deadlines,
        live_port=args.live,
    )
    status = _status_printer()
    if replaces_log:
        print(
            f"handctl: warning: --log: {escaped(str(args.log))} is a recording already; "
            "this run's replaces it once the run begins",
            file=sys.stderr,
        )
    try:
        try:
            report = run_recipe(request, status=status, signals=signals)
        finally:
            if status is not None:
                status.finish()
    except KeyboardInterrupt as exc:
        # a stop signal during the start-up, or an interrupt inside a tick (Ctrl-C without
        # the signal handler, a cancelled task): the summary asked for says what ran
        summary = (
            exc.summary
            if isinstance(exc, RunInterrupted)
            else interrupted_summary(request, said_by(exc))
        )
        if isinstance(exc, RunInterrupted) and summary.get("ticks"):
            print(f"handctl: {summary['message']}", file=sys.stderr)
        if args.summary_json:
            text = _json_text(summary) + "\n"
            with contextlib.suppress(HandctlError):  # said; the interrupt keeps its 130
                _write_summary(args.summary_json, text)
        raise
    if status is not None:
        print(file=sys.stderr)
    for warning in report.warnings:
        print(f"handctl: warning: {warning}", file=sys.stderr)
    summary = report.summary
    _print_run_summary(summary, args.plot)  # first: a summary file that fails still shows it
    code = _run_exit_code(report.result, summary)
    if args.summary_json:
        try:
            _write_summary(args.summary_json, _json_text(summary) + "\n")
        except HandctlError:
            # a run that stopped for a reason that says more keeps its code (3, 4, 130), as
            # with a lost log; its line above stays, this one is added
            return code if code != EXIT_OK else EXIT_FAILED
    return code


def _write_summary(path: Path, text: str) -> None:
    """``--summary-json`` at the end of a run: a failure to write it is said on stderr (and
    raised, for the exit code), after what the run said of itself."""
    try:
        _write_output("--summary-json", path, text)
    except HandctlError as exc:
        print(f"handctl: error: {exc}", file=sys.stderr)
        raise


def _print_run_summary(summary: dict[str, Any], plot: Path | None) -> None:
    print(
        f"recipe {summary['recipe']} on {summary['hand']} ({summary['mode']}): {summary['outcome']}"
    )
    for phase in summary["phases"]:
        end = "-" if phase["end_s"] is None else f"{phase['end_s']:.3f}"
        exit_text = f"TIMED OUT ({phase['exit']})" if phase.get("timed_out") else phase["exit"]
        print(f"  {phase['name']:<16} {phase['start_s']:8.3f} .. {end:>8} s  {exit_text}")
        backoff = phase.get("damping_backoff")
        if backoff:
            least = ", ".join(f"{name} x{gain:.2f}" for name, gain in backoff.items())
            print(f"  {'':<16} injected damping backed off (rate limit clipped): {least}")
    for fault in summary["faults"]:
        print(
            f"  FAULT {fault['code']} ({fault['category']}) at tick {fault['tick']}: "
            f"{fault['detail']}"
        )
    late = {k: "?" if v is None else v for k, v in summary["lateness_us"].items()}
    print(
        f"  {summary['ticks']} ticks, {summary['missed_ticks']} missed, lateness p50 "
        f"{late['p50']} µs p99 {late['p99']} µs max {late['max']} µs"
    )
    rejected = {k: n for k, n in summary["rejected_frames"].items() if n}
    if rejected:
        # in the JSON alone, a run with a second sender on a node's id ended exit 0 saying
        # nothing: a frame the host rejected is one it never applied, and someone sent it
        print(
            "  frames rejected by the host's receive checks (never applied): "
            + ", ".join(f"{k} {n}" for k, n in rejected.items())
        )
    lost = summary.get("frames_lost")
    if lost:
        print(
            f"  frames the host's own receive queue lost (it read them too late): {lost}; "
            "they show among the counter skips (one skip for each run of frames lost of a "
            "node), which are then the host's, not the node's"
        )
    events = summary.get("bus_events")
    if events:
        # the summary keeps their count alone (a log has each, on /events): an error-passive
        # flood of 42220 ended with nothing printed of it, where the log's replay said it
        rec = summary.get("recording")
        print(
            "  bus events (error frames, bus-state changes, refused, dropped and remote "
            f"frames): {events}"
            + ("; each is in the log's /events" if rec and "error" not in rec else "")
        )
    host = summary.get("host")
    if host and "error" not in host:
        print(
            f"  host (bare timer loop beside the run): {host['verdict'].upper()}, lateness "
            f"p99 {host['lateness_us']['p99']:g} µs, longest stall "
            f"{host['longest_stall_ms']:g} ms; missed ticks: {host['missed_host']} the "
            f"host's"
            + (
                f" (and {host['missed_host_slow_cpu']} its slow CPU's)"
                if host.get("missed_host_slow_cpu")
                else ""
            )
            + (
                f" (and {host['missed_host_catch_up']} its catch-up ticks')"
                if host.get("missed_host_catch_up")
                else ""
            )
            + (
                f" (and {host['missed_host_off_cpu']} with the loop held off its CPU)"
                if host.get("missed_host_off_cpu")
                else ""
            )
            + f", {host['missed_handctl']} handctl's"
            + (
                f", {host['missed_rival']} real-time rivals' ({', '.join(host['rivals'])})"
                if host.get("missed_rival")
                else ""
            )
        )
        for miss in host.get("handctl_misses", []):
            print("  " + _own_miss_text(miss))
    print(
        "  max |τ| [N·m] " + ", ".join(f"{k} {v:.4f}" for k, v in summary["max_abs_tau_nm"].items())
    )
    if "experiment" in summary:
        ex = summary["experiment"]
        if "turn_deg" in ex:  # the first pair's figures
            err = ex["estimator_error_deg"]
            turned = (
                f"turn per phase {ex['phase_angles_deg']} deg, turn "
                f"{ex['turn_deg']:+.2f} deg (ccw +), peak rate "
                f"{ex['peak_turn_rate_deg_s']} deg/s, "
            )
            estimated = "-" if err is None else f"{err} deg"
        else:  # no pair: how far off each object's estimated centre was
            turned = ""
            estimated = (
                ", ".join(
                    f"{name} {o['estimator_error_m'] * 1e3:.1f} mm"
                    for name, o in ex["objects"].items()
                    if o.get("estimator_error_m") is not None
                )
                or "-"
            )
        print(
            f"  experiment: lifted {ex['lifted']} (held {ex['held_s']:.2f} s), {turned}"
            f"dropped {ex['dropped']}, estimator p95 {estimated}"
        )
        print(f"  experiment: {_experiment_verdict(ex)}")
    if plot and "plot" in summary and "error" not in summary["plot"]:
        # a run without the experiment's summary (a recipe of no objects, a real-time run)
        # wrote its plot too, and did not say where
        print(f"  overview plot: {escaped(str(plot))}")
    if "recording" in summary and "error" not in summary["recording"]:
        rec = summary["recording"]
        dropped = _records_dropped(rec)
        print(
            f"  recorded {rec['ticks']} ticks, {rec['frames']} frames to "
            f"{escaped(str(rec['path']))}"
            + (f" ({dropped} records dropped: the writer fell behind)" if dropped else "")
        )


def _experiment_verdict(ex: dict[str, Any]) -> str:
    """Success with what it took, or FAILED with what was missing: the criteria alone after
    FAILED read as if they had been met."""
    wanted = ex["min_total_turn_deg"]
    if ex["success"]:
        turn = f", at least {wanted:g} deg turned" if wanted > 0 else ""  # a recipe asks none
        return f"success (lifted, held, nothing dropped{turn})"
    missing = []
    if not ex["lifted"]:
        missing.append(f"not lifted and held (held {ex['held_s']:.2f} s)")
    if ex["dropped"]:
        missing.append("an object dropped")
    turned = ex.get("total_rotation_deg")
    if wanted > 0 and turned is not None and turned < wanted:
        missing.append(f"turned {turned:.1f} deg of the {wanted:g} it needs")
    end = ex.get("end_from_table_deg")
    if end is not None and not missing and 90.0 < wanted <= 180.0 and abs(end) <= 90.0:
        missing.append(
            f"the pair ended {end:.1f} deg from how it lay on the table, not the other way "
            f"round (it had turned {ex['turn_before_manipulation_deg']:.1f} deg before the "
            "manipulation)"
        )
    if ex.get("stopped"):
        stopped = ex["stopped"]
        missing.append(_STOPPED_WORDS.get(stopped, f"the run ended ({stopped}) before its end"))
    return "FAILED: " + ("; ".join(missing) or "see above")


#: How an experiment's run that did not end as asked ended (its ``stopped``, a run's
#: ``Outcome``), in words: "the run ended in interrupted, not at its end" was the outcome's
#: name pasted into one sentence for all.
_STOPPED_WORDS = {
    "safety_stop": "the run ended in a safety stop, before its end",
    "interrupted": "the run was interrupted before its end",
    "startup_failed": "the run never started",
}


def _run_exit_code(result: RunResult, summary: dict[str, Any]) -> int:
    """The exit code of a run's outcome (module doc), with why it stopped on stderr.

    A log asked for and lost or possibly incomplete (its writer failed, hung and was killed,
    the file removed or replaced) is a failed result: a run that exited 0 was taken for one
    whose log could be trusted, by scripts that never read the warning; so is a ``--plot``
    not written because the run's recording failed. Neither makes another code 1: a safety
    stop, a bus error or an interrupt says more, and is kept."""
    code = _outcome_exit_code(result, summary)
    from handctl.summary_guard import failed_parts

    names = failed_parts(summary)
    if names:
        # a bug of handctl's in the account made after the hand stopped: said above with
        # its traceback; the outcome stands, the summary is short of those parts
        if code == EXIT_OK:
            print(
                f"handctl: failed: the run ended as asked, but its summary lacks {names} "
                "(a bug of handctl's: the warnings above say why)",
                file=sys.stderr,
            )
            code = EXIT_FAILED
        else:
            print(f"handctl: and its summary lacks {names}", file=sys.stderr)
    plotted = summary.get("plot", {})
    if "error" in plotted:
        # the run's own recording, which the plot is drawn from, failed, or the picture
        # could not be written (a full disk, its directory gone)
        if code == EXIT_OK:
            print(
                f"handctl: failed: the run ended as asked, but no plot was written to "
                f"{escaped(str(plotted['path']))} ({plotted['error']}: the warning above "
                "says why)",
                file=sys.stderr,
            )
            return EXIT_FAILED
        print(
            f"handctl: and no plot was written to {escaped(str(plotted['path']))}",
            file=sys.stderr,
        )
    recorded = summary.get("recording")
    if recorded is None:
        return code
    if "error" in recorded:
        why = "is lost or may be incomplete (the warning above says why)"
    else:
        # records the writer dropped (it fell behind by its rings' 8 s) are not in the log:
        # a log with a hole in it, which exited 0 with a parenthesis on the summary's line
        dropped = _records_dropped(recorded)
        if not dropped:
            return code
        why = f"lacks {dropped} records the writer dropped when it fell behind"
    if code == EXIT_OK:
        print(
            f"handctl: failed: the run ended as asked, but its log "
            f"{escaped(str(recorded['path']))} {why}",
            file=sys.stderr,
        )
        return EXIT_FAILED
    print(f"handctl: and the run's log {escaped(str(recorded['path']))} {why}", file=sys.stderr)
    return code


def _records_dropped(counts: dict[str, Any]) -> int:
    """The records of the run that the writer dropped and its log lacks, from a run's
    ``recording`` or a replay's ``drops``."""
    from handctl.recording.channels import RUN_DROPPED_KEYS

    return sum(int(counts.get(key, 0)) for key in RUN_DROPPED_KEYS)


def _outcome_exit_code(result: RunResult, summary: dict[str, Any]) -> int:
    """The exit code of how the run itself ended, its recording aside."""
    from handctl.online.loop import Outcome

    if result.outcome is Outcome.COMPLETED:
        if "experiment" in summary and not summary["experiment"]["success"]:
            # the hand is safe, but the run did not do what it was for (README: exit codes)
            print(
                "handctl: the experiment failed: see 'experiment' in the summary", file=sys.stderr
            )
            return EXIT_FAILED
        return EXIT_OK
    if result.outcome is Outcome.TIME_BUDGET:
        print(f"handctl: stopped: {result.message}", file=sys.stderr)
        return EXIT_OK
    if result.outcome is Outcome.INTERRUPTED:
        print(f"handctl: stopped: {result.message}", file=sys.stderr)
        return EXIT_INTERRUPTED
    print(f"handctl: safety stop: {result.message}", file=sys.stderr)
    return EXIT_SAFETY_STOP


# -- plan --------------------------------------------------------------------------------------
def _cmd_plan(args: argparse.Namespace) -> int:
    from handctl.executor import ClusterLostError, Stopwatch, check_pool_options, open_pool
    from handctl.planning.compile import plan_recipe, quick_budget, recipe_text
    from handctl.planning.template import load_template, unreachable_turn
    from handctl.progress import Progress, close_active, say
    from handctl.stopsignals import finished, held_back

    _output_file("-o", args.output)
    existing = _refuse_other_than_a_recipe(args.output)
    if args.plot is not None:
        from handctl.outfile import check_directory

        check_directory(args.plot, "--plot")
    # -o the --base is how a recipe is re-planned in place (the base is read first)
    _refuse_same_files(
        {"-o": args.output, "--plot": args.plot},
        {"the template": args.template, "--hand": args.hand, "--dbc": args.dbc},
    )
    from handctl.planning.template import MAX_MODELS

    if args.models is not None and not 1 <= args.models <= MAX_MODELS:
        raise ConfigError(
            "--models",
            "",
            f"1 to {MAX_MODELS} models (as the template's search.models)",
            args.models,
        )
    check_pool_options(args.workers, args.scheduler)  # before the template is loaded
    hand = _load_checked_hand(args.hand, "--hand", args.dbc)
    template = load_template(args.template, hand)
    if (short := unreachable_turn(template)) is not None:
        print(f"handctl: warning: {short}", file=sys.stderr)
    base = _plan_base(args, template, hand)
    if args.plot is not None:
        _check_plot_targets(args.plot, [phase.name for phase in template.phases])
    clock = Stopwatch()
    with open_pool(args.workers, args.scheduler) as pool:
        where, cpu_counted = pool.where, pool.cpu_counted
        say(f"planning on {where}")
        try:
            result = plan_recipe(
                template,
                hand,
                progress=say,
                models=args.models,
                budget=quick_budget() if args.quick else None,
                executor=pool,
                meter=Progress,
                base=base,
            )
        except ClusterLostError as exc:  # a failed result (exit 1), and the file is not written
            raise ClusterLostError(exc.address, "mid-plan", "nothing was written") from None
        finally:
            close_active()
    # quoted as a shell takes it back (a path with a space was two words in the header)
    command = shlex.join(
        ["handctl", "plan", str(args.template), "-o", str(args.output)]
        + (["--hand", str(args.hand)] if args.hand != DEFAULT_HAND else [])
        + (["--dbc", str(args.dbc)] if args.dbc is not None else [])
        + (["--models", str(args.models)] if args.models else [])
        + (["--quick"] if args.quick else [])
        + (["--from", args.start] if args.start is not None else [])
        + (["--base", str(args.base)] if base is not None else [])
        + (["--schedule-only"] if args.schedule_only else [])
        + (["--keep-torques"] if args.keep_torques else [])
    )
    # the plots first, drawn aside and moved in whole, the recipe last and whole: a Ctrl-C
    # while they were drawn left a recipe and a PNG cut short, where nothing was to be written
    plot_error: HandctlError | None = None
    try:
        plots = _plan_plots(result, args.plot) if args.plot else []
    except HandctlError as exc:  # the plan is not lost to a plot that cannot be placed
        plots, plot_error = [], exc
    text = recipe_text(result, command)
    # from the write on, a stop signal is noted and said, not raised: one that came as the
    # phases' lines were printed exited 130 after the recipe was written, skipping the lines
    # and a failed plan's exit 1 (and one just after the write, before the lines, said only
    # "interrupted"); README: a stop signal once the command has its result changes no exit
    with held_back() as late:
        output = _failed_plan_output(result, args.output, args.quick)
        _write_output("-o", output, text)
        wall_s, cpu_s = clock.read()  # the pool is closed: its local workers' CPU is counted
        print(f"recipe {template.recipe} planned for {hand.name} ({hand.config_hash}) -> {output}")
        print(f"  in {wall_s:.0f} s wall, {cpu_s:.0f} s CPU ({cpu_counted}) on {where}")
        for plan in result.phases:
            print(_planned_phase_line(plan))
        for path in plots:
            print(f"  plot {path}")
        replaced = _replaced_another(existing, template.recipe, hand)
        if replaced and output == args.output:
            print(
                f"handctl: warning: {escaped(str(output))} held another recipe ({replaced}); "
                "it is replaced",
                file=sys.stderr,
            )
        if plot_error is not None:
            print(f"handctl: error: {plot_error} (the recipe is written)", file=sys.stderr)
            # a directory whose files cannot be replaced is bad input; a disk that filled is not
            code = EXIT_BAD_INPUT if isinstance(plot_error, ConfigError) else EXIT_FAILED
        else:
            code = _plan_exit_code(result, output, args.quick)
        finished()  # the plan's result stands: a signal from here on is ``stopsignals.LATE``
    if late:
        print(
            f"handctl: {', '.join(late)} came once {escaped(str(output))} was being written: "
            f"ignored, the plan's exit ({code}) stands",
            file=sys.stderr,
        )
    return code


def _failed_plan_output(result: Any, output: Path, quick: bool) -> Path:
    """Where a plan is written: ``output``, but for a failed plan (``_plan_exit_code``) over a
    recipe that runs, which it never replaces: ``-o`` the ``--base`` (how a recipe is
    re-planned in place, as the README shows) lost the working recipe to the failed one. That
    one goes beside it, ``NAME.failed.yaml``. So does a ``--quick`` one's (which only warns,
    exit 0): it replaced the working recipe all the same."""
    failed = any(plan.undone is not None for plan in result.phases)
    if not failed or not output.is_file():
        return output
    data = _existing_yaml(output)
    if not data or _existing_kind(data) != "recipe":
        return output
    if "failed_phases" in (data.get("planned_from") or {}):
        return output  # a failed plan's recipe itself: nothing that runs is lost
    aside = _free_aside(output)
    what = "a phase of this --quick plan did nothing" if quick else "the plan failed"
    print(
        f"handctl: {what}: {output} is a recipe that runs and is kept; the failed plan is "
        f"written to {aside}",
        file=sys.stderr,
    )
    return aside


def _free_aside(output: Path) -> Path:
    """``NAME.failed.yaml`` beside ``output``, or ``NAME.failed.N.yaml`` for the first N free
    if that name holds anything but a failed plan's recipe: written without a look, it went
    through a symlink there into the very recipe it said it kept (or the template), and over a
    read-only file of anything."""
    longest = _longest_name(output.parent)
    for n in range(1, 1000):
        middle = ".failed" if n == 1 else f".failed.{n}"
        # the stem cut to fit the file system's longest name: a recipe named near it lost
        # the whole failed search to a bare "File name too long"
        room = max(1, longest - len(os.fsencode(f"{middle}{output.suffix}")))
        stem = os.fsencode(output.stem)[:room].decode(errors="ignore")  # no half a character
        aside = output.with_name(f"{stem}{middle}{output.suffix}")
        if not aside.exists() and not aside.is_symlink():
            return aside
        if aside.is_symlink() or not aside.is_file():
            continue
        data = _existing_yaml(aside)
        earlier = data is not None and "failed_phases" in (data.get("planned_from") or {})
        if earlier and os.access(aside, os.W_OK):
            return aside  # an earlier failed plan of it: replaced
    raise ConfigError("-o", "", "a name beside it for the failed plan", str(output))


def _longest_name(directory: Path) -> int:
    """The longest file name (bytes) ``directory``'s file system takes: 255 where it does not
    say."""
    try:
        return int(os.pathconf(directory, "PC_NAME_MAX"))
    except (OSError, ValueError):
        return 255


def _check_plot_targets(directory: Path, phases: Sequence[str]) -> None:
    """Refuse, before the search, a ``--plot`` directory where a plot's name is taken by
    anything but a picture (an earlier plan's, replaced): a directory in the way was found only
    after the whole search, and a file of any other kind (a link, a recipe, notes) that
    happened to bear the name was replaced without a word."""
    from handctl.experiment.plot import plan_plot_name
    from handctl.outfile import picture_or_nothing

    for k, phase in enumerate(phases):
        target = directory / plan_plot_name(k, phase)
        if not (target.exists() or target.is_symlink()):
            continue
        if target.is_symlink() or not target.is_file():
            kind = "a symbolic link" if target.is_symlink() else "not a regular file"
            found = Description(f"{target}: {kind}")
        elif picture_or_nothing(target):
            continue  # an earlier plot: replaced
        else:
            found = Description(f"{target}: a file that is not a picture")
        raise ConfigError(
            "--plot",
            "",
            "a directory where the plots' names are free or earlier plots (pictures, replaced)",
            found,
        )


def _plan_plots(result: Any, directory: Path) -> list[Path]:
    """The plan's region plots, drawn in a directory of their own inside ``directory`` and
    moved into it once all are drawn; an interrupt leaves none."""
    # the directories made for the plots, taken away again if none is placed: an interrupt
    # while they were drawn left an empty --plot tree behind
    made = [p for p in (directory, *directory.parents) if not p.exists()]
    directory.mkdir(parents=True, exist_ok=True)
    try:
        return _place_plots(result, directory)
    except BaseException:
        for path in made:  # deepest first
            with contextlib.suppress(OSError):  # not empty, or not ours: left
                path.rmdir()
        raise


def _place_plots(result: Any, directory: Path) -> list[Path]:
    """``_plan_plots``'s drawing and placing, into ``directory`` (made)."""
    import tempfile

    from handctl.experiment.plot import plot_plan

    with tempfile.TemporaryDirectory(dir=directory, prefix=".handctl-plot-") as aside:
        drawn = plot_plan(result, Path(aside))
        placed = []
        for path in drawn:
            target = directory / path.name
            try:
                os.replace(path, target)
            except OSError as exc:  # it named the temporary file, not the one in --plot
                raise ConfigError(
                    "--plot",
                    "",
                    "a directory whose plot files can be replaced",
                    Description(f"{target}: {exc.strerror}"),
                ) from None
            placed.append(target)
    return placed


def _plan_base(args: argparse.Namespace, template: Template, hand: HandConfig) -> Base | None:
    """The recipe a plan keeps torques from (``--base`` with ``--from``, or with
    ``--keep-torques``), checked against the template and the hand; None: plan every phase."""
    if args.keep_torques:
        if args.base is None:
            raise ConfigError("--keep-torques", "", "--keep-torques with --base", "no --base")
        # --quick sizes a search, and here there is none: it only turned a failed plan's
        # exit 1 into a smoke test's warning
        for option, given in (
            ("--from", args.start),
            ("--schedule-only", args.schedule_only),
            ("--quick", args.quick),
        ):
            if given:
                raise ConfigError(
                    option,
                    "",
                    f"no {option} with --keep-torques (every phase's torques are kept, "
                    "nothing is searched)",
                    given,
                )
    elif (args.start is None) != (args.base is None):
        given, missing = ("--from", "--base") if args.base is None else ("--base", "--from")
        raise ConfigError(missing, "", f"{missing} with {given} (both or neither)", "nothing")
    if args.schedule_only and args.start is None:
        raise ConfigError(
            "--schedule-only", "", "--schedule-only with --from and --base", "neither"
        )
    if args.base is not None and not args.base.is_file():
        # an empty --base is Path("."): the loader's own message named '.', not the option
        # the Path, shown whole: a string was cut to 80 characters, the file's name with it
        raise ConfigError("--base", "", "a compiled recipe file", args.base)
    if args.keep_torques:
        from handctl.planning.replan import load_kept_base

        return load_kept_base(args.base, template, hand)
    if args.start is not None:
        from handctl.planning.replan import load_base

        return load_base(args.base, args.start, template, hand, args.schedule_only)
    return None


def _plan_exit_code(result: Any, output: Path, quick: bool) -> int:
    """Exit 1 when a phase of the plan did nothing it is for on any model (said per phase):
    such a recipe said "N/N models hold", exit 0, and every run of it failed, wherever the
    phase sat. It is written all the same, to be looked at or re-planned from (--base);
    ``--quick``, the smallest search, is a smoke test of the pipeline, and only warns."""
    undone = [plan for plan in result.phases if plan.undone is not None]
    keys: list[str] = []  # the ramps that held a failed phase's search short of its seeds
    for plan in undone:
        print(
            f"handctl: {'warning' if quick else 'the plan failed'}: phase "
            f"'{plan.phase.name}' ({plan.spec.kind}): {plan.undone}, on every one of the "
            f"{len(plan.outcomes)} model(s)",
            file=sys.stderr,
        )
        for cut in plan.ramp_cuts:
            print(
                f"handctl: phase '{plan.phase.name}' was searched within its ramps: {cut.text()}",
                file=sys.stderr,
            )
            keys += [cut.key] if cut.key not in keys else []
    if undone and not quick:
        # a ramp that held the search is named first: the advice to widen the search alone
        # sent the user to search longer within ±0.02 N·m an end_ramp_s of 1 ms left
        ramps = f"lengthen {' and '.join(keys)}, " if keys else ""
        print(
            f"handctl: {output} is written to be looked at or re-planned from, not to be "
            f"run: {ramps}widen the search (search.models, generations, population), seed "
            "the phase's torques, or change the template",
            file=sys.stderr,
        )
        return EXIT_FAILED
    if undone:
        print("handctl: --quick is the smallest search, for a smoke test", file=sys.stderr)
    return EXIT_OK


def _planned_phase_line(plan: Any) -> str:
    """One line of a plan's report. A kept phase's provenance is copied from the base
    recipe, which is a file like any other: what it lacks is said, not a KeyError after
    the whole search (it has no bearing on the torques)."""
    prov = plan.provenance
    analysis = prov.get("analysis")
    if not isinstance(analysis, dict):
        ana = "analysis: not recorded"
    elif analysis.get("found"):
        ana = f"analysis margin {analysis.get('margin_N', '?')} N"
    else:
        ana = "analysis: none"
    search = prov.get("search")
    found = f", search score {search.get('score', '?')}" if isinstance(search, dict) else ""
    origin = f"from {prov.get('chosen_from') or '?'}"
    kept = prov.get("kept_from")
    if kept:  # nothing was searched here: the score and origin are the base's
        origin = f"kept from {kept} ({origin} there)"
    held = prov["models"]  # this plan's own run of the phase
    # "hold" is only that the objects are still in the hand; what the phase is for (up by
    # its height, turned) is said beside it, or a phase that did nothing read as done
    done = "" if plan.done is None else f", {sum(plan.done)}/{len(plan.done)} did its job"
    return (
        f"  {plan.phase.name:<16} {plan.spec.kind:<5} {ana}{found}; "
        f"{origin}; {held['held']}/{held['ran']} models hold{done}"
    )


# -- sim ---------------------------------------------------------------------------------------
def _cmd_sim(args: argparse.Namespace) -> int:
    from handctl.stopsignals import ENDING, interrupt, signal_name

    _positive_seconds("--seconds", args.seconds)
    # the ground truth is written after the whole run: a path that cannot take it is said
    # now, not found out at the end with the run done for nothing
    _refuse_same_files(
        {"--summary-json": args.summary_json},
        {"--hand": args.hand, "--dbc": args.dbc, "--faults": args.faults},
    )
    _output_file("--summary-json", args.summary_json, json_output=True)
    # Ctrl-C, the host's SIGINT and SIGTERM (also the parent-death signal) end the hand
    # cleanly with its summary, even when this process inherited them ignored or blocked, as
    # a script's background jobs do.
    signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT, signal.SIGTERM})
    signal.signal(signal.SIGINT, signal.default_int_handler)
    terminated: list[str] = []

    def terminate(signum: int, frame: object) -> None:
        # Only the first: a dying host can signal its hand more than once (once per thread),
        # and a second interrupt would cut short the clean-up the first one began.
        terminated.append(signal_name(signum))
        if len(terminated) == 1:
            # as every command's stop signal: the last line names it ("interrupted by
            # SIGXCPU"), not a bare "interrupted" as if Ctrl-C
            interrupt(signum, frame)

    signal.signal(signal.SIGTERM, terminate)
    # and the others whose default ends the process, as for a run (stopsignals.ENDING; SIGHUP
    # and SIGQUIT are ``main``'s already): SIGUSR1 killed the hand by the signal, no summary,
    # its socket left in the bus directory
    for other in ENDING:
        if other in (signal.SIGHUP, signal.SIGQUIT) or signal.getsignal(other) is signal.SIG_IGN:
            continue
        signal.signal(other, terminate)
    # whether --parent-pid named this hand's parent, alive or gone: only then is a bus
    # directory left when the parent is gone its to tidy (a live process that is not the
    # parent would have it tidy a bus others are on)
    adopted = False
    try:
        parent_alive: Callable[[], bool] | None = None
        if args.parent_pid is not None:
            from functools import partial

            from handctl.parent_death import die_with_parent, process_alive
            from handctl.parent_death import parent_alive as alive

            if args.parent_pid <= 0:
                raise ConfigError("--parent-pid", "", "a process id > 0", args.parent_pid)
            highest = _pid_max()
            if highest is not None and args.parent_pid > highest:
                # no process ever had it: not a parent that ended (exit 130), a mistake
                raise ConfigError(
                    "--parent-pid",
                    "",
                    f"a process id the system can give (at most {highest}, kernel.pid_max)",
                    args.parent_pid,
                )
            if not die_with_parent(args.parent_pid):
                if process_alive(args.parent_pid):
                    # a live process that is not this one's parent: its end would never be
                    # seen, and this hand would outlive it
                    raise ConfigError(
                        "--parent-pid",
                        "",
                        f"the id of this process's parent ({os.getppid()})",
                        args.parent_pid,
                    )
                # the host that started this hand is gone already: a stop, said as such
                adopted = True
                print(
                    f"handctl: process {args.parent_pid} ended before its simulated hand "
                    "started; nothing was run",
                    file=sys.stderr,
                )
                return EXIT_INTERRUPTED
            adopted = True
            parent_alive = partial(alive, args.parent_pid)
        from handctl.sim.faults import load_scenario
        from handctl.sim.hand import standalone

        hand = _load_checked_hand(args.hand, "--hand", args.dbc)
        faults = load_scenario(args.faults, hand) if args.faults else None
        if args.bus.startswith("virtual:"):
            # python-can's virtual bus is a queue inside one process: `handctl nodes` or a
            # host in another process heard nothing, and nothing said why
            print(
                f"handctl: warning: --bus {escaped(args.bus)} lives inside this process: no "
                "other command or process hears this hand (a unix:DIRECTORY bus crosses "
                "processes)",
                file=sys.stderr,
            )
        print(
            standalone(
                hand,
                args.bus,
                args.seconds,
                _progress,
                seed=args.seed,
                faults=faults,
                ground_truth=None if args.summary_json is None else _truth_to(args.summary_json),
                realtime=args.rt,
                keep_running=parent_alive,
            )
        )
    except Exception as exc:
        # An interrupt raised inside C code (MuJoCo's import, for one) comes out as that
        # code's own error: it is still an interrupt.
        if isinstance(exc.__cause__ or exc.__context__, KeyboardInterrupt):
            raise KeyboardInterrupt(str(exc)) from exc
        raise
    finally:
        _sim_ended(args, adopted, terminated[:1])
    return EXIT_OK


def _sim_ended(args: argparse.Namespace, adopted: bool, stopped_by: list[str]) -> None:
    """What a simulated hand says and tidies as it ends, ``stopped_by`` the first stop signal
    (if any): a SIGXCPU at a real-time limit is named as that limit, and a host gone for good
    leaves its bus directory to this hand."""
    from handctl.hostfacts import rttime_note
    from handctl.parent_death import parent_ends, remove_orphaned_bus

    if stopped_by == ["SIGXCPU"]:
        for line in rttime_note():  # the kernel's, at a real-time limit: which one
            print(f"handctl: {line}", file=sys.stderr)
    # SIGTERM is also the parent-death signal, which can come while the host is still going
    # down: then wait for it to be gone. Only SIGTERM: a hand ended by SIGXCPU waited 10 s
    # for a parent that was alive, and held the host's start-up that long.
    waited = ORPHAN_WAIT_S if stopped_by == ["SIGTERM"] else 0.0
    if adopted and parent_ends(args.parent_pid, waited):
        remove_orphaned_bus(args.bus, args.summary_json)


def _pid_max() -> int | None:
    """The largest process id this system gives (``kernel.pid_max``), or None if unknown."""
    try:
        return int(Path("/proc/sys/kernel/pid_max").read_text())
    except (OSError, ValueError):
        return None


# -- replay ------------------------------------------------------------------------------------
def _print_replay_summary(summary: dict[str, Any]) -> None:
    from handctl.recording.metadata import map_strings

    # every string of it as a terminal can show it: a log's phase names, event details and
    # metadata are the log's to say, and an escape sequence in one recoloured the terminal,
    # set its title or printed a line of its own
    raw, summary = summary, map_strings(summary, escaped)
    state = (
        "complete"
        if summary["complete"]
        else "BEING WRITTEN by a run: what it holds so far"
        if summary.get("being_written")
        else f"{'DAMAGED' if summary.get('damaged') else 'TRUNCATED'}: {summary['problem']}"
    )
    from handctl.recording.channels import ENDED_CLOSED

    if summary["complete"] and summary.get("ended") not in (None, ENDED_CLOSED):
        # finished by the writer alone: a killed control process, which only --json said
        state += f" (but {summary['ended']})"
    dropped = _records_dropped(summary["drops"])
    if dropped:
        # a whole file is not a whole run: the header said "complete" over a log without
        # the last 2 s of its run, and only the drops' line further down said otherwise
        state += f", but without {dropped} records the writer dropped during the run"
    print(
        f"{summary['file']}: {summary['recipe'] or '?'} on {summary['hand'] or '?'} "
        f"({summary['mode'] or '?'}), {summary['outcome']}; {summary['duration_s']:.3f} s, "
        f"{summary['ticks']} ticks, {summary['chunks']} chunks, {state}"
    )
    print("  phases:")
    for phase in summary["phases"]:
        print(
            f"    {phase['name']:<16} {phase['start_s']:8.3f} .. {phase['end_s']:8.3f} s "
            f"({phase['duration_s']:.3f} s)  {phase['exit']}"
        )
    print("  largest torques [N·m] (applied, when; |desired|; |TDT|):")
    for name, t in summary["largest_torques"].items():
        if "applied_nm" in t:
            desired, tdt = t.get("desired_nm"), t.get("tdt_nm")
            print(
                f"    {name:<8} {t['applied_nm']:+.4f} at {t['at_s']:.3f} s; "
                + ("-" if desired is None else f"{desired:.4f}")
                + "; "
                + ("-" if tdt is None else f"{tdt:.4f}")
            )
    for fault in summary["faults"]:
        # to a line's length: a log's events are the log's to say, and a forged one printed
        # 10 000 characters a fault
        print(
            f"  FAULT {_clipped(fault['code'], 40)} ({_clipped(fault['category'], 20)}) at "
            f"tick {fault['tick']} ({fault['t_s']:.3f} s): {_clipped(fault['detail'], 400)}"
        )
    if not summary["faults"]:
        print("  faults: none")
    timing = summary["timing"]
    late = timing["lateness_us"]
    stages = ", ".join(f"{k} {v}" for k, v in timing["stage_cpu_us_p99"].items())
    print(
        f"  timing: lateness p50 {late['p50']} µs, p99 {late['p99']} µs, max {late['max']} µs;"
        f" {timing['missed_ticks']} missed ticks; stage CPU p99 (µs) {stages}"
    )
    frames = summary["frames"]
    rejected = ", ".join(f"{k} {v}" for k, v in summary["rejected_frames"].items()) or "none"
    print(
        f"  frames: {frames['rx']} received, {frames['tx']} sent ({frames['tx_refused']} "
        f"refused); {summary['bus_events']} bus events; rejected: {rejected}"
    )
    drops = summary["drops"]
    print("  drops: " + (", ".join(f"{k} {v}" for k, v in drops.items() if v) or "none"))
    for topic, count in summary.get("messages_back_in_time", {}).items():
        print(
            f"handctl: warning: {summary['file']}: {count} messages of {topic} have log times "
            "earlier than one written before them: the writer writes each channel in time "
            "order, so the log's times were edited after the run (or the host's clock was "
            "stepped during it); a re-run compares the frames' content, not their times",
            file=sys.stderr,
        )
    for name, tick in raw.get("unknown_phases", {}).items():
        print(
            f"handctl: warning: {summary['file']}: the phase channel says {shown(name)} at "
            f"tick {tick}, neither a phase of the recorded recipe nor the runner's status: "
            "the log was edited after the run (`--rerun` finds where)",
            file=sys.stderr,
        )
    for name, pose in summary.get("objects", {}).items():
        print(_object_line(name, pose))
    for pair, figures in summary.get("pairs", {}).items():
        if not figures["phase_turns_deg"]:
            # no manipulation phase ran (a hold, a lift, a run stopped before one): there is
            # no turn to say, and "per phase [] deg, turn +0.00 deg" read as one measured
            continue
        print(
            f"  turn of the centre line {pair}: per phase {figures['phase_turns_deg']} deg, "
            f"turn {figures['turn_deg']:+.2f} deg (ccw +)"
        )


def _object_line(name: str, pose: Mapping[str, Any]) -> str:
    """An object's line of the replay's summary: where it started and ended (mm). A height a
    few µm below rest is "+0.0", not "-0.0" (``z``): an object that never left the table read
    as if it had sunk into it."""
    start, end = pose["start"], pose["end"]
    key = "height_above_rest_m" if "height_above_rest_m" in start else "y_m"
    return (
        f"  {name}: height {'above rest ' if key != 'y_m' else ''}"
        f"{start[key] * 1e3:+z.1f} -> {end[key] * 1e3:+z.1f} mm, "
        f"x {start['x_m'] * 1e3:+z.1f} -> {end['x_m'] * 1e3:+z.1f} mm"
    )


def _check_to_bus_option(args: argparse.Namespace) -> None:
    """``--to-bus``: a bus that may be replayed onto, and the hand config a real one needs."""
    from handctl.online.busspec import parse_spec, require_peers
    from handctl.recording.frames import SIMULATED_BUSES, hand_needed

    # before the summary and the re-run, as every other option (it was found after them,
    # and named '--bus', an option replay does not have); 'hand' is the hand config's own
    # bus, where the real hand is
    spec = None if args.to_bus == "hand" else parse_spec(args.to_bus, option="--to-bus")
    if spec is not None:
        # a mistyped unix bus was made by the replay, which sent every frame to nobody
        # and exited 0, the directory left behind
        require_peers(spec, "--to-bus")
    real = spec is None or spec.interface not in SIMULATED_BUSES
    if real and args.hand is None:
        raise hand_needed(args.to_bus)


def _check_replay_options(args: argparse.Namespace) -> None:
    """Every option of ``replay`` that needs another, or a range, said before the log is read:
    an option that would be ignored is refused rather than silently dropped."""
    _plot_file("--plot", args.plot)
    _output_file("--json", args.json)
    if args.live is not None:
        from handctl.foxglove import check_port_free

        check_port_free(args.live, "--live")
    if args.to_bus == "":  # taken for no --to-bus: nothing sent, exit 0
        raise ConfigError("--to-bus", "", "a bus (unix:DIRECTORY, or a CAN interface)", "")
    if args.export and args.export[1] in ("", "-"):
        # '' the directory '.'; '-' was written as a file of that name where standard
        # output was meant, as every other output option refuses it
        why = " (standard output is not written to: give a file)" if args.export[1] else ""
        raise ConfigError("--export", "FILE", f"a file name{why}", args.export[1])
    if args.speed is not None and not (args.to_bus or args.live is not None):
        raise ConfigError(
            "--speed",
            "",
            "--to-bus SPEC or --live as well (the speed is of "
            "the replay onto a bus or to Foxglove)",
            args.speed,
        )
    if args.to_bus == "sim":
        raise ConfigError(
            "--to-bus",
            "",
            "a bus other processes are on (unix:DIRECTORY, or a CAN interface): 'sim' is the "
            "simulated hand a run starts for itself; start one with 'handctl sim --bus "
            "unix:DIRECTORY' and replay onto unix:DIRECTORY",
            args.to_bus,
        )
    if args.to_bus:
        _check_to_bus_option(args)
    if args.direction is not None and not args.to_bus:
        raise ConfigError(
            "--direction",
            "",
            "--to-bus SPEC as well (the direction is of the frames sent onto a bus)",
            args.direction,
        )
    if args.hand is not None and not args.to_bus:
        raise ConfigError(
            "--hand",
            "",
            "--to-bus SPEC as well (the hand is the one on that bus, whose limits bound what "
            "is sent)",
            str(args.hand),
        )
    if args.dbc is not None and args.hand is None:
        raise ConfigError(
            "--dbc",
            "",
            "--to-bus SPEC --hand HAND.yaml as well (the DBC is the protocol of the hand on "
            "that bus; the recording's own is recorded in it)",
            str(args.dbc),
        )
    if args.speed is not None and not MIN_REPLAY_SPEED <= args.speed <= MAX_REPLAY_SPEED:
        raise ConfigError(
            "--speed",
            "",
            f"a factor of the recorded pace from {MIN_REPLAY_SPEED:g} to {MAX_REPLAY_SPEED:g}",
            args.speed,
        )
    if args.export:
        # here only: python-can, which the formats' module loads, costs a replay that
        # exports nothing a fifth of its start
        from handctl.recording.canlog import LOG_FORMATS

        if args.export[0] not in LOG_FORMATS:
            raise ConfigError(
                "--export", "FORMAT", "one of " + ", ".join(LOG_FORMATS), args.export[0]
            )
    export = Path(args.export[1]) if args.export else None
    # an export or a summary written over the recording it was read from emptied it, exit 0
    _refuse_same_files(
        {"--json": args.json, "--plot": args.plot, "--export": export},
        {"the recording": Path(args.log), "--hand": args.hand, "--dbc": args.dbc},
    )
    if export is not None:
        from handctl.outfile import check_writable

        check_writable(export, "--export", export=args.export[0])
    _output_file("--json", args.json, json_output=True)


def _startup_repeated(result: RerunReport) -> bool:
    """Whether a re-run with no control tick repeated a start-up that ended as logged: it
    failed, or it was stopped (a signal, the time budget) before the nodes were enabled."""
    return result.outcome == result.logged_outcome and result.outcome in (
        "startup_failed",
        "interrupted",
        "time_budget",
    )


def _clipped(text: str, most: int) -> str:
    """``text`` cut to ``most`` characters, the cut said."""
    return text if len(text) <= most else f"{text[: most - 3]}..."


def _print_rerun(result: RerunReport) -> int:
    """What a re-run found, said; its exit code (EXIT_FAILED when nothing was shown
    bit-exact or something differed)."""
    from handctl.recording import rerun

    for note in result.notes:
        print(f"rerun: note: {note}")
    if result.outcome in (rerun.NOT_STARTED, rerun.NO_TICK):
        print(f"rerun: nothing to re-run: {result.outcome} (no tick was logged)")
    elif result.ok and result.compared == 0 and _startup_repeated(result):
        # a run that never enabled its nodes has no control tick: what can be shown is
        # that the start-up, fed the same frames, ends the same way
        print(
            f"rerun: the start-up re-run to the same end ({result.outcome}), every frame "
            f"as logged ({result.frames_compared} sent); no control tick to compare: the "
            "nodes were never enabled"
        )
    elif (
        result.ok
        and result.compared == 0
        and result.logged_outcome == "startup_failed"
        and result.outcome == "log ended"
    ):
        # a start-up that failed on something outside the frames (the simulated hand's
        # process ending): the re-run, fed the same frames, listens to the log's end
        print(
            "rerun: the start-up re-run on every logged frame to the log's end, nothing "
            "sent; it failed on something the frames do not hold (its reason is in the "
            "summary: a peer process that ended, say); no control tick to compare"
        )
    elif result.ok and result.compared == 0:
        # a log whose first chunk is lost has no tick a fresh runtime could follow: the
        # re-run ran nothing, and nothing was shown to be bit-exact
        print(
            "rerun: NOTHING COMPARED: no tick of the log could be re-run"
            + (" (see the notes)" if result.notes else "")
        )
        return EXIT_FAILED
    elif result.ok:
        print(
            f"rerun: {result.compared} ticks compared, applied torques bit-exact "
            "(desired ones too, safety state and phase as logged); "
            f"{result.frames_compared} command frames identical; outcome "
            f"{result.outcome} (logged {result.logged_outcome or '?'}); "
            f"{result.wall_s:.2f} s"
        )
    else:
        print(
            f"rerun: MISMATCH in {result.mismatched_ticks} of {result.ticks} ticks, "
            f"{len(result.frame_mismatches)} frame mismatches; outcome {result.outcome} "
            f"(logged {result.logged_outcome or '?'})"
        )
        for m in result.mismatches[: rerun.MAX_LISTED]:
            print(
                f"  tick {m['tick']} {m['joint']}: logged {m['logged_nm']!r}, re-run "
                f"{m['rerun_nm']!r} {m['detail']}"
            )
        for text in result.frame_mismatches[: rerun.MAX_LISTED]:
            print(f"  {text}")
        for text in result.decision_mismatches[: rerun.MAX_LISTED]:
            print(f"  {text}")
        return EXIT_FAILED
    return EXIT_OK


def _replay_to_bus(
    args: argparse.Namespace, recording: Any, on_bus: HandConfig | None
) -> dict[str, Any]:
    """``replay --to-bus``: the frames onto the bus (held to the limits of ``on_bus``, the
    hand config given with ``--hand``, as well), and what became of them said."""
    from handctl.recording import frames

    _say_in_process_bus("--to-bus", args.to_bus)
    # said before the frames' checks, which may still refuse the whole log (nothing sent)
    _progress(
        f"to-bus: checking the logged commands, then replaying the frames onto {args.to_bus} "
        f"at {args.speed or 1.0:g}x ..."
    )
    direction = args.direction or _to_bus_direction(args.to_bus)
    try:
        from handctl.stopsignals import noted_stops

        # the stop signals noted, not raised, while frames go to a hand (``noted_stops``)
        with noted_stops() as stops:
            sent = frames.to_bus(
                recording,
                args.to_bus,
                args.speed or 1.0,
                direction,
                hand=on_bus,
                stops=stops,
            )
    except frames.ReplayInterrupted as exc:
        why = f" by {exc.why}" if exc.why else ""
        if exc.stopped:
            print(f"to-bus: interrupted{why}; {exc.stopped}", file=sys.stderr)
        if exc.ignored:
            print(
                f"to-bus: {', '.join(exc.ignored)} came while the stop was sent: ignored, so "
                "that it was sent whole",
                file=sys.stderr,
            )
        raise
    if "node_fault" in sent:
        print(f"to-bus: FAILED: {sent['node_fault']}", file=sys.stderr)
    if "stopped" in sent:
        ended = "the replay ended" if "node_fault" in sent else "the log ended"
        print(f"to-bus: {ended} with {sent['stopped']}", file=sys.stderr)
    shifted = sent["shifted_ms"]
    print(
        f"to-bus: {sent['sent']} frames sent to {sent['bus']} ({sent['failed']} failed, "
        f"worst lateness {sent['worst_late_ms']} ms"
        + (f"; fell behind and shifted the rest by {shifted} ms in all" if shifted else "")
        + ")"
    )
    if "warning" in sent:
        print(f"handctl: warning: to-bus: {sent['warning']}", file=sys.stderr)
    return sent


def _to_bus_direction(spec: str) -> str:
    """``--to-bus``'s frames when ``--direction`` is not given: both directions on a bus of
    this machine's own (virtual, unix: a simulated hand's, a tool's test), the host's alone
    on any other. There the nodes send their own Feedback, Status and Heartbeat, and the
    logged copies went out under the same identifiers beside them, without a word: two
    senders of one identifier with other data are bit errors on CAN, error counters rising
    towards error-passive and bus-off (found by an outside audit). Said when it applies."""
    if spec.split(":", 1)[0] in ("virtual", "unix"):
        return "both"
    print(
        "to-bus: the host's frames only (--direction tx, the default on a bus a hand may be "
        "on: its nodes send their own); --direction both sends the logged node frames too",
        file=sys.stderr,
    )
    return "tx"


def _reanalysis_on_tick(hand: HandConfig, recipe: Recipe, estimator: Any) -> Reanalyser:
    """The re-run's analysis at the measured configuration, imported only for a recipe that
    has ``reanalyse`` phases: the offline plane (scipy.optimize) costs a re-run of any other
    log 0.4 s of its 1.7 s."""
    from handctl.planning.reanalysis import ReanalysisOnTick

    return ReanalysisOnTick(hand, recipe, estimator)


def _replay_rerun(recording: Recording, report: dict[str, Any]) -> int:
    """``replay --rerun``: the re-run printed and put in ``report``; its exit code."""
    from handctl.recording import rerun
    from handctl.stopsignals import ctrl_c_at_once

    with ctrl_c_at_once():
        result = rerun.rerun(recording, _reanalysis_on_tick)
    report["rerun"] = result.as_dict()
    # a finished file that reads whole is all the run wrote (a SIGKILL of the control
    # process alone leaves one: its writer finishes the file); any other is not
    report["rerun"]["whole_log"] = recording.complete and not recording.damaged
    if _print_rerun(result) != EXIT_OK:
        return EXIT_FAILED
    if recording.damaged:
        # what it compared repeats, but a script that read exit 0 as "verified" took the
        # ticks past the hole as verified too
        print(
            "rerun: FAILED: not the whole log: it is DAMAGED, and the ticks from its first "
            "damaged chunk on were not compared",
            file=sys.stderr,
        )
        return EXIT_FAILED
    if not recording.complete:
        # the writer did not finish it (killed, a full disk): the run may have gone on past
        # its end (a fault, the stop ramp) that nothing compared; it was "verified", exit 0
        print(
            "rerun: FAILED: not the whole log: it is TRUNCATED (its writer did not finish "
            "it), and whatever the run did after its end was not compared",
            file=sys.stderr,
        )
        return EXIT_FAILED
    return EXIT_OK


def _cmd_replay(args: argparse.Namespace) -> int:
    from handctl.recording import channels as ch
    from handctl.recording import frames, replay
    from handctl.recording.metadata import check_run_metadata, recorded_hand
    from handctl.recording.reader import (
        check_format,
        open_recording,
        require_content,
        require_topics,
    )
    from handctl.recording.series import load_series

    _check_replay_options(args)
    # the bus's hand before the work: one check refuses was found only after the summary,
    # the plot and the re-run were done
    on_bus = _load_checked_hand(args.hand, "--hand", args.dbc) if args.hand is not None else None
    recording = open_recording(args.log)
    require_content(recording)
    if recording.being_written and (args.rerun or args.to_bus or args.export):
        # each read of it finds more: the summary said 9391 ticks and the re-run compared
        # 11544 of one invocation, and frames sent or exported would end wherever it had got
        raise ConfigError(
            str(args.log),
            "",
            "a finished recording for --rerun, --to-bus or --export (the run writing it "
            "ends it; its summary can be read now)",
            Description("a log a run is still writing (its writer holds the file's lock)"),
        )
    check_format(recording)
    # a run writes all these channels or, gone before its set-up, none; a log cut short may
    # end before some of them
    if recording.complete and set(ch.CORE_TOPICS) & set(recording.topics.values()):
        require_topics(recording, ch.CORE_TOPICS, "its summary")
    check_run_metadata(recording, recorded_hand(recording, required=False))
    series = load_series(recording)
    summary = replay.summarise_recording(recording, series)
    _print_replay_summary(summary)
    report: dict[str, Any] = {"summary": summary}
    status = EXIT_OK
    plot_error: HandctlError | None = None
    if args.plot:
        from handctl.recording.plot import plot_recording, title_of
        from handctl.wholefile import PictureNotWrittenError

        try:
            plot_recording(series, args.plot, title_of(summary), recording)
            print(f"plot: {args.plot}")
        except PictureNotWrittenError as exc:  # said at the end, the rest done and written
            plot_error = exc
            report["plot"] = {"path": str(args.plot), "error": exc.why}
    if args.rerun and _replay_rerun(recording, report) != EXIT_OK:
        status = EXIT_FAILED
    if args.export:
        fmt, out = args.export
        exported = frames.export(recording, fmt, out)
        report["export"] = exported
        print(f"export: {exported['frames']} frames to {out} ({fmt})")
        if "warning" in exported:
            print(f"handctl: warning: export: {exported['warning']}", file=sys.stderr)
    if args.to_bus and status != EXIT_OK:
        # the re-run proved the log does not repeat its run: a frame was altered, and the
        # command checks' bounds may have been re-sealed with it
        print(
            "to-bus: nothing sent: the re-run found this log does not repeat its run",
            file=sys.stderr,
        )
        report["to_bus"] = {"sent": 0, "refused": "the re-run found a mismatch"}
    elif args.to_bus and recording.damaged:
        # a chunk dropped whole from the middle: the frames around it would go out as if
        # one after the other, a gap of commands the run never sent (a log cut short at its
        # end, by a crash or a power loss, still goes: what it holds is what the run sent)
        print(
            f"to-bus: nothing sent: {args.log} is DAMAGED ({recording.problem}); the frames "
            "of a log with a hole in it are not the run's",
            file=sys.stderr,
        )
        report["to_bus"] = {"sent": 0, "refused": "the log is damaged"}
        status = EXIT_FAILED
    elif args.to_bus:
        report["to_bus"] = _replay_to_bus(args, recording, on_bus)
        if "node_fault" in report["to_bus"]:
            status = EXIT_FAILED  # the hand did not follow the log to its end
    if args.json:
        _write_output("--json", args.json, _json_text(report) + "\n")
    if plot_error is not None:
        print(f"handctl: error: --plot: {plot_error}", file=sys.stderr)
        status = EXIT_FAILED
    if args.live is not None:
        from handctl.foxglove import HOST
        from handctl.foxglove.live import serve_recording

        # said once the port is served: said before the recording was read, a client that
        # connected when told was refused for seconds
        streamed = serve_recording(
            Path(args.log),
            args.live,
            args.speed or 1.0,
            started=lambda _: _progress(
                f"live: streaming {escaped(str(args.log))} at {args.speed or 1.0:g}x to "
                f"Foxglove on ws://{HOST}:{args.live} ..."
            ),
        )
        # every message of the log at its pace; a viewer is sent what it subscribed to, the
        # per-tick channels sampled (docs/recording.md): not a count of what it was sent
        print(f"live: {streamed} messages of the log played")
    return _failed_if_damaged(args.log, recording, status)


def _failed_if_damaged(log: Path, recording: Any, status: int) -> int:
    """``status``, or a failed result for a log with a hole in its middle: what was read of
    it is said, but a summary, a plot, an export or a live view of it is not the run's whole
    (exit 0 was read as a sound log; found by an outside audit). A log cut short at its end
    holds all its run wrote, and keeps its 0."""
    if not recording.damaged or status != EXIT_OK:
        return status
    print(
        f"handctl: failed: {escaped(str(log))} is DAMAGED ({recording.problem}): what is said "
        "and written of it leaves out what was in the hole",
        file=sys.stderr,
    )
    return EXIT_FAILED


# -- bring-up ----------------------------------------------------------------------------------
def _seconds_or(value: float | None, default: float) -> float:
    """``--seconds`` of a bring-up command (``default`` when left out): a positive, finite
    time; bad input is refused before anything starts."""
    if value is None:
        return default
    if not 0 < value < MAX_BRING_UP_S:
        raise ConfigError(
            "--seconds", "", f"a time in seconds > 0 and < {MAX_BRING_UP_S:g} (11.6 days)", value
        )
    return value


#: s, the longest a bring-up command runs: its work is counted in ticks and seconds at once
MAX_BRING_UP_S = 1e6


def _cmd_nodes(args: argparse.Namespace) -> int:
    from handctl.bringup.idcount import MAX_IDS
    from handctl.bringup.nodes import id_text, survey
    from handctl.bringup.peer import listening_bus
    from handctl.hand_protocol import protocol_for
    from handctl.online.bus import BusEventKind

    hand = _load_checked_hand(args.hand, "--hand", args.dbc)
    protocol = protocol_for(hand)
    seconds = _seconds_or(args.seconds, 1.0)
    # two of the slowest report a node sends on its own: a survey of 1e-9 s heard nothing
    # and called every node missing, a typo read as a wiring fault
    slowest = max(
        protocol.layout(name, f.node_id).cycle_time_ms or 0
        for f in hand.fingers
        for name in ("Feedback", "Status", "Heartbeat")
    )
    if seconds < 2 * slowest * 1e-3:
        raise ConfigError(
            "--seconds",
            "",
            f"a survey of at least {2 * slowest * 1e-3:g} s (twice the {slowest} ms the nodes "
            "take between two of their Status or Heartbeat reports, in the protocol)",
            seconds,
        )
    _say_in_process_bus("--bus", args.bus)
    _refuse_no_simulated_hand_on(hand, args.bus)
    with listening_bus(args.bus, hand) as bus:
        result = survey(hand, protocol, bus, seconds)
    if args.json:
        print(_json_text(result.as_dict()))
        return EXIT_OK if result.ok else EXIT_FAILED
    where = (
        result.bus
        if args.bus != "sim"
        else f"sim (a simulated hand this command started on {result.bus})"
    )
    print(
        f"{hand.name} on {where}: listened {result.seconds:.2f} s, sent nothing; "
        f"host protocol {result.host_protocol}"
    )
    # the node column fits its widest id and name: ids 10-15 and names over 7 characters
    # pushed the rest of their row one column or more to the right of the header
    id_width = max((len(str(row.node_id)) for row in result.rows), default=1)
    labels = [f"{row.node_id:>{id_width}} {row.name}" for row in result.rows]
    node_width = max([9, *(len(label) for label in labels)])
    print(
        f"{'node':<{node_width}} {'state':<9} {'faults':<16} {'proto':>5} {'firmware':>8} "
        f"{'fb Hz':>6} {'hb':>3} {'st':>3} {'uptime s':>9} {'host rejects':<14} "
        f"{'node rejects':<13} problem"
    )
    for row, label in zip(result.rows, labels, strict=True):
        uptime = "-" if row.uptime_ms is None else f"{row.uptime_ms / 1e3:.1f}"
        host = ",".join(f"{k} {v}" for k, v in row.host_rejects.items()) or "0"
        theirs = (
            "-" if row.node_rejects is None else "/".join(str(v) for v in row.node_rejects.values())
        )
        proto = "-" if row.protocol_version is None else str(row.protocol_version)
        print(
            f"{label:<{node_width}} {row.state:<9} {','.join(row.faults) or '-':<16} "
            f"{proto:>5} {row.firmware:>8} {row.feedback_hz:>6.0f} {row.heartbeats:>3} "
            f"{row.statuses:>3} {uptime:>9} {host:<14} {theirs:<13} "
            f"{row.problem or 'ok'}"
        )
    for fid, (what, count) in sorted(result.foreign.items()):
        print(f"  id {id_text(fid)}: {count} frames, {what}")
    if result.foreign_more_frames:
        print(
            f"  and {result.foreign_more_frames} frames of more ids (only the first "
            f"{MAX_IDS} ids are counted one by one)"
        )
    if result.bus_events:
        print("  bus events: " + ", ".join(f"{k} {v}" for k, v in result.bus_events.items()))
        if BusEventKind.REMOTE_FRAME.value in result.last_event:
            # which id: on 0x000 the nodes take it as an e-stop
            print(f"    last remote frame: {result.last_event[BusEventKind.REMOTE_FRAME.value]}")
    if result.bus_problem:
        print(f"  problem: {result.bus_problem} (docs/bringup.md, step 2)")
    if result.frames_lost:
        print(
            f"  this listener lost {result.frames_lost} frames before it read them: as many "
            "counter skips are its own, not the nodes'"
        )
    print("  (node rejects: crc/counter/length, as the node's Status reports them)")
    return EXIT_OK if result.ok else EXIT_FAILED


def _positive(option: str, value: float | None, default: float, unit: str) -> float:
    if value is None:
        return default
    if not 0 < value < 1e6:
        # the bound too: "expected a value > 0 s, found 1000000.0" contradicted itself
        raise ConfigError(option, "", f"a value > 0 and < 1e+06 {unit}", value)
    return value


def _run_outcome(report: Any) -> int | None:
    """Exit code of a bring-up run that did not complete (None if it did), said on stderr."""
    from handctl.online.loop import Outcome

    for warning in report.warnings:
        print(f"handctl: warning: {warning}", file=sys.stderr)
    # a summary short of a part (a bug of handctl's, said above) is a failed result even
    # of a run that completed: it ended exit 0, or in a traceback where the bring-up read
    # a figure the part would have made (found by an outside audit)
    errors = {"summary_errors": report.summary.get("summary_errors", [])}
    if report.result.outcome is Outcome.COMPLETED and not errors["summary_errors"]:
        return None
    return _run_exit_code(report.result, errors)


def _existing_yaml(output: Path) -> dict[str, Any] | None:
    """The YAML mapping an output would replace; None when there is nothing there (or no
    regular file, which ``check_writable`` names); {} for a file that is not one."""
    from handctl.schema import load_yaml

    if not output.is_file():
        return None
    try:
        return dict(load_yaml(output).data)
    except ConfigError:
        return {}


def _replaced_another(existing: dict[str, Any] | None, name: str, hand: HandConfig) -> str:
    """What a plan's ``-o`` held, if it was a recipe of another name or another hand, said as
    a warning's part ("" otherwise). A plan is how a recipe is written again, so one is
    replaced; but a swap recipe of twenty minutes' planning went, replaced by another hand's
    quick plan, without a word (an outside probe)."""
    if not existing:
        return ""
    other = []
    if existing.get("recipe") != name:
        other.append(f"recipe {escaped(str(existing.get('recipe')))}")
    digest = existing.get("hand_config_hash")
    if not isinstance(digest, str):
        other.append("for no hand config (it has no hand_config_hash)")
    elif not hand.answers_to(digest):
        other.append(f"for another hand ({escaped(digest)})")
    return ", ".join(other)


def _existing_kind(data: dict[str, Any]) -> str | None:
    """What handctl file ``data`` (an existing output's YAML) is (``schema.FILE_KINDS``)."""
    from handctl.schema import file_kind

    found = file_kind(data)
    return None if found is None else found[0]


def _refuse_other_file(output: Path, hand: HandConfig, source: Path) -> None:
    """``-o`` names a new file, or a calibrated copy of this very hand (a calibration done
    again): another hand's config or a recipe there was replaced by this hand's, exit 0. A
    copy of the same name is this hand only if nothing but its TDT offsets differs from
    ``source``: a working copy with a lowered ``tau_max`` or a ``safety`` section of its own,
    named as the hand is, lost them without a word."""
    from handctl.schema import load_yaml

    if output.is_symlink():
        # written through, it replaced the file the link points to, wherever that was
        raise ConfigError(
            "-o",
            "",
            f"a file, not a symbolic link (the calibrated copy would replace {output.resolve()})",
            str(output),
        )
    data = _existing_yaml(output)
    if data is None:
        return
    is_hand = _existing_kind(data) == "hand config"
    if is_hand and data.get("name") == hand.name:
        original = dict(load_yaml(source).data)
        differs = _first_difference(data, original, "")
        if differs is None and data != original:
            return
        if differs is None:
            # the same config, offsets too: no calibration ever wrote it, so it is the hand
            # config itself under another path (the repository's copy of the shipped one was
            # replaced so, exit 0)
            raise ConfigError(
                "-o",
                "",
                f"a new file, or a calibrated copy of {source} (one whose TDT offsets a "
                "calibration wrote; --write overwrites the hand config itself)",
                Description(f"{output}, the same config as {source}, its TDT offsets too"),
            )
        raise ConfigError(
            "-o",
            "",
            f"a new file, or a calibrated copy of {source} that differs from it in TDT offsets "
            "alone (one that differs otherwise is another config, and is not replaced)",
            Description(f"{output}, whose {differs}"),
        )
    what = (
        f"the hand config of '{data['name']}'"
        if is_hand and "name" in data
        else "a file that is not a hand config"
    )
    raise ConfigError(
        "-o",
        "",
        f"a new file, or a calibrated copy of '{hand.name}' to write again (an existing "
        "file of anything else is not replaced)",
        f"{output}, {what}",
    )


def _first_difference(copy: Any, source: Any, path: str) -> str | None:
    """Where a calibrated copy's YAML data first differs from its source's, besides a joint's
    ``tdt.offset`` (what a calibration writes); None when nowhere."""
    if isinstance(copy, dict) and isinstance(source, dict):
        for key in sorted(set(copy) | set(source), key=str):
            here = f"{path}.{key}" if path else str(key)
            if key == "offset" and path.endswith(".tdt") and ".joints[" in path:
                continue
            if key not in copy or key not in source:
                side = "the copy" if key not in copy else "the hand config"
                return f"{here} is not in {side}"
            found = _first_difference(copy[key], source[key], here)
            if found is not None:
                return found
        return None
    if isinstance(copy, list) and isinstance(source, list):
        if len(copy) != len(source):
            return f"{path} has {len(copy)} entries, not {len(source)}"
        for k, (a, b) in enumerate(zip(copy, source, strict=True)):
            found = _first_difference(a, b, f"{path}[{k}]")
            if found is not None:
                return found
        return None
    numbers = all(isinstance(v, int | float) and not isinstance(v, bool) for v in (copy, source))
    if copy != source or (not numbers and type(copy) is not type(source)):
        return f"{path} is {shown(copy)}, not {shown(source)}"
    return None


def _refuse_other_than_a_recipe(output: Path) -> dict[str, Any] | None:
    """A plan's ``-o`` names a new file or a recipe (re-planned, or planned again): a hand
    config, a template or notes there were replaced by the recipe, exit 0. The recipe there,
    if any (``_replaced_another``)."""
    data = _existing_yaml(output)
    if data is not None and _existing_kind(data) == "recipe" and not data.get("compiled"):
        # a recipe written by hand is the user's work, not a plan to write again: a bring-up
        # hold recipe was replaced by a plan, with a warning of "another hand (None)" (found
        # by an outside audit)
        raise ConfigError(
            "-o",
            "",
            "a new file, or a recipe handctl plan compiled, to write again (a recipe written "
            "by hand, without compiled: true, is not replaced: give another -o)",
            # a Description, not a string cut to 80 characters: the file's name, at the end
            # of a long path, was the part left out (found by an outside audit)
            Description(
                f"recipe {escaped(str(data.get('recipe')))}, written by hand, in "
                f"{escaped(str(output))}"
            ),
        )
    if data is None or _existing_kind(data) == "recipe":
        return data
    raise ConfigError(
        "-o",
        "",
        "a new file, or a recipe to write again (an existing file of anything else, a hand "
        "config or a template say, is not replaced)",
        Description(f"{escaped(str(output))}, an existing file that is not a recipe"),
    )


def _calibration_limits(args: argparse.Namespace, hand: HandConfig) -> Any:
    """``calibrate tdt``'s plausibility bounds, each at most what leaves its check on: an
    offset or a noise past the largest tau_max, or a span past the widest joint range, passes
    any sensor. An option left out is its default scaled down to the hand where the hand is
    smaller (an offset up to the largest tau_max, a tenth of it for the noise, half the widest
    range for the span): the defaults are a hand of 0.6 N·m and 2 rad joints, and a hand of
    0.2 N·m or of 0.08 rad joints was refused for options its user never gave."""
    from handctl.bringup.calibrate import CalibrationLimits

    widest = max(hand.joints, key=lambda j: j.tau_max)
    roomiest = max(hand.joints, key=lambda j: j.angle_max - j.angle_min)
    room = roomiest.angle_max - roomiest.angle_min
    limits = CalibrationLimits(
        max_span=_positive(
            "--max-span", args.max_span, min(CalibrationLimits.max_span, room / 2), "rad"
        ),
        max_noise=_positive(
            "--max-noise",
            args.max_noise,
            min(CalibrationLimits.max_noise, widest.tau_max / 10),
            "N·m",
        ),
        max_offset=_positive(
            "--max-offset",
            args.max_offset,
            min(CalibrationLimits.max_offset, widest.tau_max),
            "N·m",
        ),
    )
    if limits.max_offset > widest.tau_max:
        raise ConfigError(
            "--max-offset",
            "",
            f"at most {widest.tau_max:g} N·m (the largest tau_max, {widest.name}'s: an offset "
            "beyond it is a broken sensor)",
            limits.max_offset,
        )
    if limits.max_noise > widest.tau_max:
        raise ConfigError(
            "--max-noise",
            "",
            f"at most {widest.tau_max:g} N·m (the largest tau_max, {widest.name}'s: a noise beyond "
            "it passes any sensor, the check is off)",
            limits.max_noise,
        )
    if limits.max_span > room:
        raise ConfigError(
            "--max-span",
            "",
            f"at most {room:g} rad (the widest joint range, "
            f"{roomiest.name}'s: a span beyond it passes any motion, the check is off)",
            limits.max_span,
        )
    return limits


def _cmd_calibrate_tdt(args: argparse.Namespace) -> int:
    from handctl.bringup.calibrate import calibrate_tdt
    from handctl.outfile import check_writable
    from handctl.stopsignals import StopSignals, finished

    # before the DBC is read: one that -o or --json names would be replaced at the end (the
    # two against each other and the hand config are asked below, with what --write means)
    for option, output in (("-o", args.output), ("--json", args.json)):
        _refuse_same_files({option: output}, {"--dbc": args.dbc, "--sim-faults": args.sim_faults})
    hand = _load_checked_hand(args.hand, "--hand", args.dbc)
    if args.output is None and not args.write:
        # --write only for a hand of the user's: offered for the shipped config, it was then
        # refused as the package's (found by an outside audit)
        instead = (
            "the default hand config is the package's: give your hand's with --hand to "
            "overwrite it with --write"
            if args.hand.resolve() == DEFAULT_HAND
            else f"or --write to overwrite {args.hand}"
        )
        raise ConfigError("-o", "", f"a file for the calibrated copy ({instead})", "nothing")
    if args.output is not None and args.write:
        raise ConfigError(
            "--write",
            "",
            f"either -o FILE (a calibrated copy) or --write (overwrite {args.hand}), not both",
            f"-o {args.output} --write",
        )
    if args.write and args.hand.resolve() == DEFAULT_HAND:
        raise ConfigError(
            "--write",
            "",
            "--hand with the hand config of your hand: the one shipped with handctl is the "
            "package's, not a hand's (-o FILE writes a calibrated copy of it)",
            str(args.hand),
        )
    target = args.hand if args.output is None else args.output
    if (
        args.output is not None
        and not args.write
        and args.output.exists()
        and args.output.resolve() == args.hand.resolve()
    ):
        raise ConfigError(
            "-o",
            "",
            f"another file than the hand config (--write overwrites {args.hand})",
            str(args.output),
        )
    if args.output is not None:
        _refuse_other_file(args.output, hand, args.hand)
    # before anything starts: a calibration whose result cannot be written is not begun
    written = check_writable(target, "-o" if args.output is not None else "--write")
    if args.json is not None and check_writable(args.json, "--json", json_output=True) in (
        written,
        args.hand.resolve(),
    ):
        raise ConfigError(
            "--json",
            "",
            "another file than the hand config and its calibrated copy",
            str(args.json),
        )
    limits = _calibration_limits(args, hand)
    measure = _seconds_or(args.seconds, 1.0)
    shortest = CALIBRATION_MIN_PERIODS * hand.bus.period_s
    if measure < shortest:
        raise ConfigError(
            "--seconds",
            "",
            f"at least {shortest:g} s, {CALIBRATION_MIN_PERIODS} loop periods (an offset and a "
            "noise need samples; a shorter one enabled the hand and measured nothing)",
            measure,
        )
    settle = 2.0 if args.settle is None else args.settle
    from handctl.online.recipes.schema import MAX_PHASE_S

    if not 0 <= settle <= MAX_PHASE_S:  # a phase of the calibration's recipe, as long as any
        raise ConfigError(
            "--settle",
            "",
            f"a time in seconds from 0 to {MAX_PHASE_S:g} (a phase's longest)",
            settle,
        )
    text = args.hand.read_text(encoding="utf-8")
    # The stop signals taken over here, up to the write, not inside the run: one that came
    # after the hand had stopped (the simulated hand's process ending, half a second) was
    # dropped there, and --write then overwrote the hand config, exit 0, the stop unsaid
    # (found by an outside audit). The calibration's result is the file it writes: a stop
    # before that write writes nothing (``_write_calibration``).
    with StopSignals() as signals:
        calibration = calibrate_tdt(
            hand,
            bus=args.bus,
            settle_s=settle,
            measure_s=measure,
            limits=limits,
            lockstep=False if args.realtime else None,
            seed=_sim_seed(args, hand),
            sim_faults=args.sim_faults,
            reset_node_faults=args.reset_node_faults,
            realtime_priority=args.rt,
            accept_missed_deadlines=args.accept_missed_deadlines,
            signals=signals,
        )
        code = _calibration_result(args, hand, text, calibration, written, signals, settle)
        # the result stands (the file written, or not): a stop signal from here on is said
        # and changes no exit; one in the gap before the command's end turned it into 130
        # (found by an outside audit)
        finished()
    return code


def _calibration_result(
    args: argparse.Namespace,
    hand: HandConfig,
    text: str,
    calibration: Calibration,
    written: Path,
    signals: StopSignals,
    settle: float,
) -> int:
    """What a calibration that ran (``settle`` s, then ``--seconds``) says and writes, and
    its exit code."""
    from handctl.bringup.hand_edit import format_offset

    stopped = _run_outcome(calibration.report)
    if stopped is not None:
        if signals.ignored:  # the run's own stop, or its fault, is the result
            _came_after_the_stop(signals.ignored, ": ignored")
        return stopped
    print(
        f"TDT offsets of {hand.name} at zero torque, {calibration.samples} samples "
        f"({_seconds_or(args.seconds, 1.0):g} s after {settle:g} s to settle):"
    )
    print(
        f"{'joint':<8} {'offset before':>13} {'offset after':>12} {'mean':>9} {'noise':>8} "
        f"{'moved':>10}  problem"
    )
    for j in calibration.joints:
        print(
            f"{j.name:<8} {j.old_offset:>+13.4f} {float(format_offset(j.new_offset)):>+12.4f} "
            f"{j.mean:>+9.4f} {j.noise:>8.4f} {j.angle_span:>6.4f} rad  {j.problem or 'ok'}"
        )
    if signals.ignored:
        return _stopped_before_written(signals.ignored, "nothing written")
    if args.json:
        _write_output(
            "--json",
            args.json,
            _json_text(
                {
                    "samples": calibration.samples,
                    "joints": [j.as_dict() for j in calibration.joints],
                }
            )
            + "\n",
        )
    if calibration.problems:
        # the measurements of a refused calibration are kept (--json): what was refused is
        # the hand config, and "nothing written" over a --json written was untrue (found by
        # an outside audit)
        target = args.hand if args.output is None else args.output
        written_what = (
            "nothing written"
            if not args.json
            else f"{escaped(str(target))} not written (the measurements are in "
            f"{escaped(str(args.json))})"
        )
        print(
            f"handctl: calibration refused, {written_what}: " + "; ".join(calibration.problems),
            file=sys.stderr,
        )
        return EXIT_FAILED
    return _write_calibration(args, hand, text, calibration.offsets, written, signals.ignored)


def _stopped_before_written(names: list[str], what: str) -> int:
    """Exit 130 for the stop signals ``names`` that came once the hand had stopped but before
    the calibration was written: its result is the file, so ``what`` (nothing, or the hand
    config) was not written."""
    _came_after_the_stop(
        names, f", before the calibration was written: {what} (the offsets measured are above)"
    )
    return EXIT_INTERRUPTED


def _write_calibration(
    args: argparse.Namespace,
    hand: HandConfig,
    text: str,
    offsets: dict[str, float],
    written: Path,
    stops: list[str],
) -> int:
    """The calibrated hand config written (``-o`` or ``--write``) from ``text``, the hand
    config as it was read before the run, with ``offsets`` (N·m by joint); not if a stop
    signal came before the write (``stops``, the calibration's ``StopSignals.ignored``, looked
    at once they are held back)."""
    from handctl.bringup.hand_edit import with_line_ends, with_tdt_offsets
    from handctl.config import load_hand
    from handctl.stopsignals import held_back

    target = args.hand if args.output is None else args.output
    try:
        edited = with_tdt_offsets(text, hand, offsets)
    except ValueError as exc:
        print(f"handctl: calibration refused, nothing written: {args.hand} {exc}", file=sys.stderr)
        return EXIT_FAILED
    if edited.dumped:
        print(
            f"handctl: warning: {args.hand} could not be edited in place ({edited.why}); "
            "written as a plain dump, without its comments and layout",
            file=sys.stderr,
        )
    with held_back() as late:
        if stops:
            return _stopped_before_written(stops, f"{target} not written")
        if args.write and _read_or_none(args.hand) != text:
            # written from the text read before the run, it would undo whatever was saved
            # into the file since
            raise HandctlError(
                f"--write: {args.hand} changed while the calibration ran; nothing written "
                "(the offsets measured are above; calibrate again)"
            )
        # read with its line ends made \n: each line's own put back (``with_line_ends``); a
        # dump has no lines of the original, and takes \r\n if the original had any
        raw = args.hand.read_bytes().decode("utf-8", errors="surrogateescape")
        out = edited.text
        if edited.dumped and "\r\n" in raw:
            out = out.replace("\n", "\r\n")
        elif not edited.dumped:
            out = with_line_ends(raw, out)
        _write_output("-o" if args.output is not None else "--write", written, out)
        new_hash = load_hand(target, args.dbc).config_hash
        print(f"written: {target}" + (" (the original, --write)" if target == args.hand else ""))
        if new_hash != hand.config_hash:
            print(
                f"  the config hash changes from {hand.config_hash} to {new_hash}: recipes "
                "compiled for the old one must be planned again (handctl plan)"
            )
    for name in late:
        print(f"handctl: {name} came once {target} was being written: ignored", file=sys.stderr)
    return EXIT_OK


def _read_or_none(path: Path) -> str | None:
    try:
        return path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError):
        return None


def _cmd_jog(args: argparse.Namespace) -> int:
    from handctl.bringup.jog import JogLine, jog, jog_recipe
    from handctl.stopsignals import StopSignals, finished

    hand = _load_checked_hand(args.hand, "--hand", args.dbc)
    seconds = _seconds_or(args.seconds, 2.0)
    # refused here, before any bus opens
    jog_recipe(hand, args.joint, args.torque, seconds, args.recover)
    _refuse_a_torque_the_wire_rounds_away(hand, args.joint, args.torque)
    if args.bus == "sim":
        from handctl.sim.params import parse_sim

        # a hand without a simulated one was refused under the table's header
        _refuse_no_simulated_hand(hand, args.bus)
        parse_sim(hand)
    until = " or until it is back inside its soft limits" if args.recover else ""
    banner = [
        f"jog {args.joint} with {args.torque:+g} N·m for {seconds:g} s{until} on "
        f"{escaped(args.bus)}, "
        + (
            "every other joint at zero (the soft-limit guard is off in a recovery, but "
            f"for the limit the torque pushes {args.joint} towards) "
            if args.recover
            else "every other joint at zero unless the soft-limit guard pushes it back "
        )
        + "(Ctrl-C: controlled stop)",
        f"{'t s':>7} {'phase':<9} {'state':<10} {'desired':>9} {'applied':>9} "
        f"{'angle rad':>10} {'TDT N·m':>9}",
    ]

    def say_banner() -> None:
        """Once the jog runs, not before: a jog refused (no bus, the timing check, another
        host) printed its banner and table header first, and read from a log or through a
        pipe it looked like a jog that had started."""
        if banner:
            print("\n".join(banner), flush=True)
            banner.clear()

    # the table is shown from inside the tick: a line stdout cannot take now (a pager at
    # its prompt, Ctrl-S) is dropped, never waited for (``handctl.lossyout``); the banner
    # waits for a line that goes out, or for the end
    table = LossyOut(sys.stdout)
    if table.off:
        print(
            f"handctl: note: the table is shown only at the end: stdout is {table.off}, and "
            "a jog never waits for it",
            file=sys.stderr,
        )

    def show(line: JogLine) -> None:
        row = (
            f"{line.t_s:>7.2f} {line.phase:<9} {line.state:<10} {line.desired:>+9.4f} "
            f"{line.applied:>+9.4f} {line.angle:>+10.4f} {line.tdt:>+9.4f}\n"
        )
        if table.write("\n".join([*banner, row]) if banner else row):
            banner.clear()

    # the jog's stop signals taken over here, not inside the run: one that came after the hand
    # had stopped (the simulated hand's process ending, half a second) was dropped there, and
    # the jog exited 0 without a word (found by an outside audit)
    try:
        with StopSignals() as signals:
            result = jog(
                hand,
                args.joint,
                args.torque,
                seconds=seconds,
                bus=args.bus,
                lockstep=False if args.realtime else None,
                realtime_priority=args.rt,
                seed=_sim_seed(args, hand),
                sim_faults=args.sim_faults,
                reset_node_faults=args.reset_node_faults,
                accept_missed_deadlines=args.accept_missed_deadlines,
                recover=args.recover,
                show=show,
                signals=signals,
            )
            # the jog's result is what it did, which stands once the hand has stopped: a stop
            # signal while it is said (a stopped terminal holds that for as long as it likes)
            # turned a jog's exit 0 or 1 into 130 "interrupted", its result lines lost (found
            # by an outside audit)
            finished()
    finally:
        table.finish()
    from handctl.online.loop import Outcome

    if result.report.result.outcome is not Outcome.STARTUP_FAILED:
        say_banner()  # a jog that ran (a failed start-up's error says it did not)
    if table.dropped and not table.gone:
        print(
            f"handctl: note: {table.dropped} of the table's {table.dropped + table.written} "
            "lines were not shown: stdout could not take them when they came (a stopped "
            "terminal, or a reader that fell behind), and the jog does not wait for it",
            file=sys.stderr,
        )
    if signals.ignored:
        # the jog's result is what it measured, which the stop could no longer change
        _came_after_the_stop(
            signals.ignored, ", while the jog was finished: ignored, the jog's result stands"
        )
    moved = result.moved
    if moved is not None:
        largest = result.report.summary["max_abs_tau_nm"][args.joint]
        # a recovery of a joint already inside applies nothing: "under +0.03 N·m" beside a
        # joint that sank the other way read as a joint that turns against its torque
        under = f"under {args.torque:+g} N·m" if largest else "with no torque applied"
        print(
            f"{args.joint}: {result.start_angle:+.4f} -> {result.end_angle:+.4f} rad "
            f"({moved:+.4f} rad"
            + (", to the last reading before its encoder failed" if result.encoder_failed else "")
            + f") {under}; largest |TDT| "
            f"{result.max_abs_tdt:.4f} N·m; largest |applied| {largest:.4f} N·m"
        )
    # the soft-limit guard pushes back any joint the jog swings towards a limit, by the sign
    # the hand config gives it: said, since a jog is where those signs are checked
    pushed = {
        name: tau
        for name, tau in result.report.summary["max_abs_tau_nm"].items()
        if name != args.joint and tau > 0.0
    }
    if pushed:
        print(
            "other joints pushed back from a soft limit by the guard (largest |applied|): "
            + ", ".join(f"{name} {tau:.4f} N·m" for name, tau in pushed.items())
        )
    stopped = _run_outcome(result.report)
    if stopped is None and result.recovery is not None:
        return _recovery_outcome(result, hand)
    if stopped is None and result.tdt_problem:
        print(f"handctl: FAILED: {result.tdt_problem}", file=sys.stderr)
        return EXIT_FAILED
    return EXIT_OK if stopped is None else stopped


def _refuse_a_torque_the_wire_rounds_away(hand: HandConfig, joint: str, torque: float) -> None:
    """A jog torque under the command signal's step travels as zero or as a whole step: the
    jog said it ran under 1e-05 N·m and the joint got none. Bad input, before any bus
    opens."""
    from handctl.bringup.jog import joint_index
    from handctl.hand_protocol import protocol_for

    j = joint_index(hand, joint)
    finger = next(f for f in hand.fingers if any(x.name == joint for x in f.joints))
    k = [x.name for x in finger.joints].index(joint)
    step = protocol_for(hand).layout("TorqueCommand", finger.node_id).signals[k].scale
    if torque != 0.0 and abs(torque) < step:
        raise ConfigError(
            "--torque",
            "",
            f"0 or |τ| >= {step:g} N·m (the command signal's step: less reaches "
            f"{hand.joints[j].name} as zero or as one step)",
            torque,
        )


def _recovery_outcome(result: JogReport, hand: HandConfig) -> int:
    """What a recovery jog that ran to its end did: back inside (0), or not (1, a failed
    result: the hand is safe, stopped, and still outside)."""
    recovery = result.recovery
    assert recovery is not None
    spec = hand.joints[recovery.joint]
    if not recovery.needed:
        print(
            f"{result.joint} was inside its soft limits [{spec.angle_min:+g}, "
            f"{spec.angle_max:+g}] rad when torque came on ({recovery.start_angle:+.4f} rad): "
            "nothing to recover"
        )
        return EXIT_OK
    end = result.end_angle
    back = end is not None and spec.angle_min <= end <= spec.angle_max
    if not back:
        print(
            f"{result.joint} still outside its soft limits [{spec.angle_min:+g}, "
            f"{spec.angle_max:+g}] rad at {end:+.4f} rad: jog it again with more torque or "
            "--seconds (it is stopped, torque off)",
            file=sys.stderr,
        )
        return EXIT_FAILED
    print(
        f"{result.joint} back inside its soft limits: {recovery.start_angle:+.4f} -> "
        f"{end:+.4f} rad (limits [{spec.angle_min:+g}, {spec.angle_max:+g}] rad)"
    )
    return EXIT_OK


def _cmd_monitor(args: argparse.Namespace) -> int:
    import time

    from handctl.bringup.monitor import BusView, listen, table
    from handctl.bringup.peer import listening_bus
    from handctl.hand_protocol import protocol_for

    if args.log is not None and args.bus is not None:
        raise ConfigError(
            "--log",
            "",
            "either --log or --bus: a log is read instead of a bus",
            f"--log {args.log} --bus {args.bus}",
        )
    seconds = None if args.seconds is None else _seconds_or(args.seconds, 0.0)
    every = _positive("--every", args.every, 1.0, "s")
    on_tty = sys.stdout.isatty()

    def emit(snapshot: dict[str, object]) -> None:
        print(_json_text(snapshot, indent=None), flush=True)

    if args.log is not None:
        return _monitor_log(args, seconds, every, on_tty, emit)
    hand_path = DEFAULT_HAND if args.hand is None else args.hand
    hand = _load_checked_hand(hand_path, "--hand", args.dbc)
    view = BusView(protocol_for(hand))
    bus_text = "sim" if args.bus is None else args.bus  # '' is a bad spec, not the default
    _say_in_process_bus("--bus", args.bus)
    _refuse_no_simulated_hand_on(hand, bus_text)
    try:
        with listening_bus(bus_text, hand, waits=True) as bus:
            title = f"handctl monitor {escaped(bus_text)} ({bus.spec}): listening, sending nothing"
            if on_tty:
                from rich.live import Live

                with Live(table(view.snapshot(), title), screen=True, auto_refresh=False) as live:
                    shown = time.monotonic()
                    for batch in listen(bus, seconds, view=view):
                        for frame_id, data, t_ns in batch:
                            view.observe(frame_id, data, t_ns)
                        if time.monotonic() - shown >= min(every, 0.25):
                            shown = time.monotonic()
                            live.update(
                                table(view.snapshot(time.monotonic_ns()), title), refresh=True
                            )
            else:
                emitted = time.monotonic()
                # a reader that left (``handctl monitor | head -1``) is told nothing more:
                # listening on would go on for ever, writing to no one
                for batch in listen(bus, seconds, keep_going=_reader_stays, view=view):
                    for frame_id, data, t_ns in batch:
                        view.observe(frame_id, data, t_ns)
                    if time.monotonic() - emitted >= every:
                        emitted = time.monotonic()
                        emit(view.snapshot(time.monotonic_ns()))
    except KeyboardInterrupt:
        pass  # Ctrl-C is how a monitor is ended: what was seen is still said below
    if not on_tty:
        # on the clock the snapshots before it took: at the last frame's time it was earlier
        # than the one before, and every rate came out as none
        emit(view.snapshot(time.monotonic_ns(), whole=True))
    return EXIT_OK


def _reader_stays() -> bool:
    """Whether stdout still has a reader (``_ReaderMayLeave`` notes when it left)."""
    return not getattr(sys.stdout, "reader_gone", False)


def _monitor_log(
    args: argparse.Namespace,
    seconds: float | None,
    every: float,
    on_tty: bool,
    emit: Callable[[dict[str, object]], None],
) -> int:
    """``handctl monitor --log``: a recording's raw frames through the same view, snapshots
    every ``every`` s of log time when piped, the whole at the end; with ``seconds``, the
    frames of that much log time from the first, as ``every`` is of log time (--seconds was
    ignored, and a log of 10 s shown whole after --seconds 1). The frames are decoded with the
    protocol the recording keeps (``log_protocol``): --hand and --dbc only matter for a
    recording that keeps none, and one that is not the recorded hand is refused."""
    from handctl.bringup.monitor import BusView, from_log, log_protocol, table
    from handctl.recording.reader import check_format, open_recording

    log: Path = args.log
    hand, refused = None, None
    if args.hand is not None:
        try:
            hand = _load_checked_hand(args.hand, "--hand", args.dbc)
        except ConfigError as exc:
            if args.dbc is not None:
                raise
            refused = exc  # perhaps a hand of the DBC the recording keeps (below)
    _check_dbc_file(args.dbc)
    try:
        recording = open_recording(log)  # a file that is no recording is refused by name
        check_format(recording)
    except HandctlError:
        if refused is not None:
            raise refused from None  # the hand first, as every command refuses it
        raise
    if refused is not None:
        hand = _monitor_log_hand(args.hand, refused, recording)
    protocol = log_protocol(
        recording, hand, args.dbc, lambda: _load_hand(DEFAULT_HAND, "--hand", args.dbc)
    )
    view = BusView(protocol)
    step = round(every * 1e9)
    next_ns: int | None = None
    first_ns: int | None = None
    span_ns = None if seconds is None else round(seconds * 1e9)
    for frame_id, data, t_ns in from_log(recording, view):
        first_ns = t_ns if first_ns is None else first_ns
        if span_ns is not None and t_ns - first_ns > span_ns:
            break
        view.observe(frame_id, data, t_ns)
        next_ns = t_ns + step if next_ns is None else next_ns
        if not on_tty and t_ns >= next_ns:
            emit(view.snapshot(t_ns))
            # the next moment after this frame: past a jump in the log's times (an edited
            # log's three years) one snapshot, not one for every frame until the steps
            # caught up (17 MB of them)
            next_ns += step * ((t_ns - next_ns) // step + 1)
    final = view.snapshot(whole=True)
    if on_tty:
        from rich.console import Console

        Console().print(table(final, f"{log}: {view.frames} frames"))
    else:
        emit(final)
    if not recording.complete:
        # as replay says it: a view of part of a run read as the whole of one. A log its run
        # still writes is neither cut short nor damaged (it was called TRUNCATED)
        state = (
            "BEING WRITTEN by a run"
            if recording.being_written
            else f"{'DAMAGED' if recording.damaged else 'TRUNCATED'} ({recording.problem})"
        )
        if not view.frames:
            # "frames: 0" and exit 0 read as a run with nothing on its bus
            print(
                f"handctl: error: {log} is {state}: no frame of it could be read"
                + (" yet" if recording.being_written else ""),
                file=sys.stderr,
            )
            return EXIT_FAILED
        print(
            f"handctl: warning: {log} is {state}: the frames shown are "
            + ("what it holds so far" if recording.being_written else "those that could be read"),
            file=sys.stderr,
        )
    return EXIT_OK


def _monitor_log_hand(path: Path, refused: ConfigError, recording: Recording) -> HandConfig:
    """``monitor --log``'s --hand that ``_load_checked_hand`` refused (``refused``), given no
    --dbc, for a recording whose run spoke a DBC of its own: a hand that only that DBC
    carries (can_ids of its own) was refused against the DBC generated from it, though the
    log keeps the DBC its frames were sent in, and --dbc of that very DBC was taken. Such a
    hand is read against the recorded DBC, as the recording's own hand is read. Nothing is
    decoded with it: the recorded DBC decodes, and ``log_protocol`` refuses any hand but the
    recorded one (by its config hash). Anything else keeps the first refusal."""
    from handctl.config import parse_hand
    from handctl.hand_protocol import generated_protocol
    from handctl.recording.metadata import recorded_hand, recorded_protocol
    from handctl.schema import load_yaml

    recorded = recorded_hand(recording, required=False)
    protocol = None if recorded is None else recorded_protocol(recording)
    if protocol is None or recorded is None or protocol.text == generated_protocol(recorded).text:
        raise refused  # the run spoke the generated DBC: the refusal stands
    try:
        return parse_hand(load_yaml(path, "hand config"), protocol)
    except ConfigError:
        raise refused from None  # not a hand of the recorded DBC either: as refused first


# -- parser --------------------------------------------------------------------------------------
DEFAULT_LIVE_PORT = 8765


#: An integer as a command line gives one: ASCII digits after an optional sign. ``int()``
#: also takes the digits of every script (a full-width '８７６５' was taken as port 8765),
#: underscores and surrounding white space, none of which a user types as a number here.
_INTEGER = re.compile(r"[+-]?[0-9]+")


def _integer_or_none(text: str) -> int | None:
    """``text`` as an integer (``_INTEGER``), None if it is none: the one rule of every
    integer option, so that no option takes what another refuses."""
    if not _INTEGER.fullmatch(text):
        return None
    try:
        return int(text)
    except ValueError:  # more digits than Python converts (sys.get_int_max_str_digits)
        return None


def _integer(text: str) -> int:
    """An integer option's argparse type: the error is a usage error (exit 2) naming what an
    integer is here, not argparse's "invalid _integer value"."""
    value = _integer_or_none(text)
    if value is None:
        raise argparse.ArgumentTypeError(
            f"expected an integer (ASCII digits 0-9, an optional sign), found {shown(text)}"
        )
    return value


def _real(text: str) -> float:
    """A signed number option's argparse type (a torque, a ratio): ``_number``."""
    return _number(text, "0.5, -1e-3")


def _amount(text: str) -> float:
    """The argparse type of a number option that is never below 0 (a time, a speed, a
    limit): ``_number``, its examples of such numbers. "--max-seconds 1s" was told "e.g.
    0.5, -1e-3", an example the option refuses (an outside audit). A negative number still
    reaches the option's own check, which says what it takes."""
    return _number(text, "0.5, 2")


def _number(text: str, examples: str) -> float:
    """``float`` but for the digits of other scripts, which it takes as ``int`` does (a
    full-width '０.５' was 0.5). Its other spellings (``nan``, ``inf``, ``1e-3``) are each
    option's own check to refuse or take."""
    try:
        if text.isascii():
            return float(text)
    except ValueError:
        pass
    raise argparse.ArgumentTypeError(
        f"expected a number (e.g. {examples}), found {shown(text)}{_not_ascii(text)}"
    )


def _not_ascii(text: str) -> str:
    """What to add to an error for ``text`` that a reader may take for digits but that are
    not ASCII (a full-width '８'): why it was refused."""
    return "" if text.isascii() else " (a number here is written in ASCII digits 0-9)"


def _seed(text: str) -> int:
    """A simulated hand's seed: numpy's generators take only a non-negative integer, and
    the hand config's ``sim.seed`` one below 2**32, so that a seed means the same hand given
    either way; argparse makes the error a usage error (exit 2)."""
    seed = _integer_or_none(text)
    if seed is None or not 0 <= seed <= 2**32 - 1:
        raise argparse.ArgumentTypeError(
            f"expected an integer from 0 to {2**32 - 1}, found {shown(text)}{_not_ascii(text)}"
        )
    return seed


def _port(text: str) -> int:
    """A TCP port for ``--live``; argparse makes the error a usage error (exit 2)."""
    port = _integer_or_none(text)
    if port is None or not 1 <= port <= 65535:
        if os.path.exists(text) or text.lower().endswith((".mcap", ".yaml", ".yml")):
            # the port is optional, and took the file the command was to be given
            # (``replay --live RUN.mcap``): said as an address before, for its dot
            where = (
                " (a file's name: the port of --live is optional, and took the argument "
                "after it; put --live after the file, or give the port as --live=PORT)"
            )
        elif any(c in text for c in ".:[]") or text.strip().lower() == "localhost":
            # an address given with it or instead of it: the view's address is not a choice
            where = (
                " (the live view binds the loopback interface, 127.0.0.1, only: give the "
                "port alone, and reach it from another machine through an SSH tunnel, "
                "docs/recording.md)"
            )
        else:
            where = ""
        raise argparse.ArgumentTypeError(
            f"expected a TCP port 1..65535, found {shown(text)}{_not_ascii(text)}{where}"
        )
    return port


#: A negative number as a value, in argparse's sense: an argument that looks like one is
#: a value, not an option. argparse's own (Python 3.11) knows no exponent, so
#: ``--torque -1e-3`` was "expected one argument" and had to be written ``--torque=-1e-3``;
#: ``--k -inf 0.1`` likewise, where the option's own check says what a value must be.
NEGATIVE_NUMBER = re.compile(
    r"^-(?:(?:[0-9]+(?:\.[0-9]*)?|\.[0-9]+)(?:[eE][+-]?[0-9]+)?|(?i:inf|infinity|nan))$"
)


class _Parser(argparse.ArgumentParser):
    """handctl's parser, and every subcommand's (``add_subparsers`` makes them of the
    parent's class): one place that makes a negative number in exponent form a value, that
    takes an option only as written in full, and that says an option it does not know with
    the command's own usage.

    In full: ``--acc`` ran as ``--accept-missed-deadlines``, ``--reset`` as
    ``--reset-node-faults`` and ``--rec`` as ``--recover``, switches a controller of a real
    hand should take only when they are spelled out (and an option added later would have
    changed what an abbreviation meant)."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        kwargs.setdefault("allow_abbrev", False)
        super().__init__(*args, **kwargs)
        # argparse reads this private attribute (3.11) where it tells a negative number from
        # an option; a later Python that matches more ("-" then a digit) still matches these
        self._negative_number_matcher = NEGATIVE_NUMBER
        self.register("action", None, _StoreOnce)  # an option without action=
        self.register("action", "store", _StoreOnce)
        self.given: set[str] = set()  # the destinations given a value in this parse

    def parse_known_args(  # type: ignore[override]
        self, args: Sequence[str] | None = None, namespace: argparse.Namespace | None = None
    ) -> tuple[argparse.Namespace, list[str]]:
        self.given = set()
        parsed, extras = super().parse_known_args(args, namespace)
        if extras and self._subparsers is None:
            # a command's own options: said here, with its usage, where argparse said them
            # at the top ("usage: handctl [-h] [--version] COMMAND ...")
            self.error(f"unrecognized arguments: {' '.join(map(self._hint, extras))}")
        return parsed, extras

    def _hint(self, extra: str) -> str:
        """``extra`` with the option it may have meant: the one it begins (options are taken
        only in full), or the one it is a slip of."""
        word = extra.split("=", 1)[0]
        if not word.startswith("-"):
            return extra
        known = [o for a in self._actions for o in a.option_strings]
        begun = [o for o in known if o.startswith(word)]
        close = begun or difflib.get_close_matches(word, known, 1, 0.75)
        if not close:
            return extra
        how = " options are taken only in full" if begun else ""
        return f"{extra} (did you mean {' or '.join(close)}?{how})"


class _StoreOnce(argparse._StoreAction):
    """An option of one value given twice with two values is refused: argparse kept the last
    without a word, so ``--bus sim ... --bus socketcan:can0`` drove whichever came last, and
    ``--max-seconds 5 ... --max-seconds 50`` ran ten times what the first said. Given twice
    with the same value it is one option.

    An optional value left out (``--live`` alone, ``nargs="?"``) is said as that, with the
    value it stands for: ``--live --live 8788`` was "given twice, as '8765' and then
    '8788'", a value the user never typed. argparse hands the action its ``const`` itself
    for a value left out, and a value typed is converted anew, so ``values is self.const``
    tells them apart."""

    #: how this option was first given (``_as_given``), and in which parse (its ``given``
    #: set, held here so that it is no other parse's): for the refusal
    first_given: tuple[set[str], str] | None = None

    def __call__(
        self,
        parser: argparse.ArgumentParser,
        namespace: argparse.Namespace,
        values: Any,
        option_string: str | None = None,
    ) -> None:
        given = parser.given if isinstance(parser, _Parser) else set()
        first = getattr(namespace, self.dest, None)
        if self.dest in given and first != values:
            earlier = self.first_given
            raise argparse.ArgumentError(
                self,
                f"given twice, as "
                f"{earlier[1] if earlier and earlier[0] is given else _shown_value(first)} "
                f"and then {self._as_given(values, option_string)}: give it once",
            )
        if self.dest not in given:
            self.first_given = (given, self._as_given(values, option_string))
        given.add(self.dest)
        super().__call__(parser, namespace, values, option_string)

    def _as_given(self, values: Any, option_string: str | None) -> str:
        if self.nargs == argparse.OPTIONAL and values is self.const and option_string:
            return f"{option_string} alone (its default, {values})"
        return _shown_value(values)


def _shown_value(value: Any) -> str:
    if value is None:
        return "no value"
    if isinstance(value, list):
        return " ".join(_shown_value(v) for v in value)
    return shown(str(value))


class _HelpFormatter(argparse.RawDescriptionHelpFormatter):
    """Descriptions and examples as written (``_command`` wraps the prose itself), so that
    example commands keep their lines."""


def _command(
    parent: argparse._SubParsersAction[argparse.ArgumentParser],
    name: str,
    *,
    help: str,
    description: str,
    examples: Sequence[str],
    notes: str = "",
) -> argparse.ArgumentParser:
    """A subcommand whose ``--help`` ends with examples (and notes, e.g. its exit codes).

    Every subcommand is made here, so that each one's help has the same shape; a test walks
    them all (tests/unit/test_cli_help.py), new ones included.
    """
    width = 88
    epilog = "examples:\n" + "\n".join(f"  {e}" for e in examples)
    if notes:
        epilog = textwrap.fill(notes, width) + "\n\n" + epilog
    return parent.add_parser(
        name,
        help=help,
        description=textwrap.fill(description, width),
        epilog=epilog,
        formatter_class=_HelpFormatter,
    )


def build_parser() -> argparse.ArgumentParser:
    parser: argparse.ArgumentParser = _Parser(
        prog="handctl",
        description="Grasp, lift and manipulate objects with a joint-torque-controlled robot "
        "hand over CAN: any hand its config describes, simulated or real.",
        epilog="examples:\n"
        "  handctl run recipe config/recipes/swap_two_cylinders.yaml --summary-json out.json\n"
        "  handctl replay run.mcap --plot run.png\n"
        "  handctl check config/hands/hiroshima_hand.yaml\n"
        "  handctl COMMAND --help   (every option of a command, with its examples)\n\n"
        + textwrap.fill(
            "Exit codes: 0 done (or stopped at --max-seconds), 1 failed result, 2 bad "
            "input, 3 safety stop, 4 bus error, 5 host failed the timing check, "
            "130 interrupted.",
            88,
        ),
        formatter_class=_HelpFormatter,
    )
    parser.add_argument("--version", action="version", version=f"handctl {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    _add_check(sub)
    _add_analyze(sub)
    _add_sim(sub)
    _add_run(sub)
    _add_plan(sub)
    _add_replay(sub)
    _add_layout(sub)
    _add_bringup(sub)
    _name_empty_paths(parser)
    return parser


class _NoName:
    """An empty file name given for ``option``: argparse made it the directory '.', said in
    a message naming neither the option nor what was given ("found .: not a file"). Refused
    when the command runs (``_refuse_empty_names``), with the option."""

    def __init__(self, option: str) -> None:
        self.option = option


def _name_empty_paths(parser: argparse.ArgumentParser) -> None:
    """Every file-name argument of ``parser`` and its commands takes an empty name as a
    ``_NoName`` of its option, not as the path '.'."""
    for action in parser._actions:  # argparse keeps no public list of them
        if isinstance(action, argparse._SubParsersAction):
            for command in dict.fromkeys(action.choices.values()):
                _name_empty_paths(command)
        elif action.type is Path:
            action.type = _path_or_none(
                action.option_strings[0] if action.option_strings else str(action.metavar)
            )


def _path_or_none(option: str) -> Callable[[str], Path | _NoName]:
    def convert(text: str) -> Path | _NoName:
        return Path(text) if text else _NoName(option)

    return convert


def _refuse_empty_names(args: argparse.Namespace) -> None:
    """A ``ConfigError`` for an empty file name on the command line (``_NoName``)."""
    for value in vars(args).values():
        if isinstance(value, _NoName):
            raise ConfigError(value.option, "", "a file name", "")


def _add_dbc(command: argparse.ArgumentParser, help: str = "") -> None:
    """``--dbc``, on every command that speaks a hand's protocol (``help``: what it is for
    there, where that is not the frames the command puts on a bus)."""
    command.add_argument(
        "--dbc",
        type=Path,
        metavar="PROTOCOL.dbc",
        help=help
        or "the CAN protocol (a DBC file) instead of the one generated from "
        "the hand config; checked against the hand's nodes, joints and "
        "can_ids",
    )


def _add_hand_argument(command: argparse.ArgumentParser) -> None:
    """The hand config as the command's argument (``check``, ``layout``), the default one if
    none is given; ``--hand`` too, as every other command that takes a hand spells it (the
    README says so: ``check --hand X.yaml`` was refused as an unknown option)."""
    command.add_argument(
        "hand",
        type=Path,
        nargs="?",
        default=None,
        metavar="HAND.yaml",
        help=f"hand config ({DEFAULT_HAND_HELP})",
    )
    command.add_argument(
        "--hand",
        dest="hand_option",
        type=Path,
        action=_StoreOnce,
        metavar="HAND.yaml",
        help="the same, as the other commands take it",
    )


def _hand_given(args: argparse.Namespace) -> Path:
    """The hand config of ``_add_hand_argument``: HAND.yaml or ``--hand``, not two. Sets
    ``args.hand_said``, what a message about it calls it (the one the user gave)."""
    given, option = args.hand, args.hand_option
    if given is not None and option is not None and given != option:
        raise ConfigError(
            "--hand",
            "",
            f"one hand config, as HAND.yaml or as --hand (HAND.yaml is {escaped(str(given))})",
            str(option),
        )
    args.hand_said = "--hand" if given is None and option is not None else "HAND.yaml"
    return given or option or DEFAULT_HAND


def _add_layout(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    layout = _command(
        sub,
        "layout",
        help="write the Foxglove layout of a hand",
        description="Write the Foxglove layout of a hand config: the 3D scene, one torque plot "
        "per finger, the phase, the safety state and the log (docs/recording.md). In "
        "Foxglove: Layouts, Import from file.",
        examples=[
            "handctl layout config/hands/four_fingers_four_joints.yaml -o four_by_four.json",
        ],
    )
    _add_hand_argument(layout)
    layout.add_argument(
        "-o", dest="output", type=_output_path, required=True, metavar="OUT.json",
        help="where to write the layout (JSON)",
    )  # fmt: skip
    _add_dbc(layout)
    layout.set_defaults(func=_cmd_layout)


def _cmd_layout(args: argparse.Namespace) -> int:
    from handctl.foxglove.layout import LAYOUT_KEYS, layout_json

    args.hand = _hand_given(args)
    # a layout written over the hand config lost the hand
    _refuse_same_files({"-o": args.output}, {args.hand_said: args.hand, "--dbc": args.dbc})
    # a layout is JSON: an existing file that is not (another hand's config, a recipe,
    # notes), or JSON of anything else (a run's summary), was replaced by it, exit 0
    _output_file("-o", args.output, json_kind=("layout", LAYOUT_KEYS))
    # checked as every command checks it: a hand check refuses was given a layout, exit 0
    hand = _load_checked_hand(args.hand, args.hand_said, args.dbc)
    _write_output("-o", args.output, layout_json(hand))
    print(f"written: {args.output} (the Foxglove layout of {hand.name})")
    return EXIT_OK


def _add_check(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    check = _command(
        sub,
        "check",
        help="validate a hand config and its bus-load budget",
        description="Validate a hand config against the protocol (DBC) and print its "
        "worst-case bus-load budget; exit 2 if over 50 %.",
        examples=[
            "handctl check",
            "handctl check config/hands/hiroshima_hand_classic.yaml",
            "handctl check --timing --seconds 600 --json timing.json",
        ],
    )
    _add_hand_argument(check)
    _add_dbc(check)
    timing = check.add_argument_group(
        "timing", "can this host hold the hand's deadlines? (docs/timing.md; exit 5 if not)"
    )
    timing.add_argument(
        "--timing",
        action="store_true",
        help="instead of the config: a bare timer loop at the hand's loop rate "
        "with the scheduling --rt asks for; wake-up lateness, stalls "
        "against the period, overrun tolerance and feedback timeout, a "
        "verdict and what would help",
    )
    timing.add_argument(
        "--seconds",
        type=_amount,
        metavar="S",
        help=f"length of the timing check [s], >= {MIN_TIMING_CHECK_S:g} and <= 3600 "
        f"(default {TIMING_CHECK_DEFAULT_S:g})",
    )
    timing.add_argument(
        "--no-rt", action="store_true", help="check at the default scheduler, as a run without --rt"
    )
    timing.add_argument(
        "--loop-cpu",
        type=_integer,
        metavar="N",
        help="the CPU to check (default: the one --rt gives the loop)",
    )
    timing.add_argument(
        "--json",
        type=_output_path,
        metavar="FILE.json",
        help="write the report, with the probe's record, as JSON",
    )
    check.set_defaults(func=_cmd_check)


def _add_analyze(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    example = (
        "handctl analyze torque-set config/analysis/paper_fig3.yaml --k 0.9 0.1 --plot fig3.png"
    )
    analyze = _command(
        sub,
        "analyze",
        help="offline grasp analysis (paper §3–§4)",
        description="Offline analysis of enveloping grasps.",
        examples=[example],
    )
    analyses = analyze.add_subparsers(dest="analysis", metavar="ANALYSIS", required=True)
    tset = _command(
        analyses,
        "torque-set",
        help="the torque set that moves two enveloped objects (Fig. 3)",
        description="Compute the robust torque set over (tau_11, tau_21) with "
        "tau_i2 = k_i tau_i1: exactly, and on a 121x121 grid of LPs.",
        examples=[example, "handctl analyze torque-set SCENARIO.yaml --k 1 0.5 --json region.json"],
    )
    tset.add_argument(
        "scenario", type=Path, metavar="SCENARIO.yaml", help="analysis scenario (config/analysis/)"
    )
    tset.add_argument(
        "--k",
        type=_real,
        nargs=2,
        metavar=("K1", "K2"),
        required=True,
        help="torque ratios k_1, k_2 (tau_i2 = k_i tau_i1) [N·m per N·m, dimensionless]",
    )
    tset.add_argument(
        "--json",
        type=_output_path,
        metavar="FILE.json",
        help="write the region and the grid as JSON",
    )
    tset.add_argument(
        "--plot", type=_output_path, metavar="OUT.png", help="write a PNG in the style of Fig. 3"
    )
    tset.set_defaults(func=_cmd_analyze_torque_set)


def _add_sim(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    sim = _command(
        sub,
        "sim",
        help="run the simulated hand as a standalone peer on a bus",
        description="Run the simulated hand (MuJoCo plant behind emulated finger nodes) free "
        "on its own 1 kHz timer, as a peer on any python-can bus.",
        examples=[
            "handctl sim --bus unix:/tmp/handctl-bus --seconds 60",
            "handctl sim --bus unix:/tmp/handctl-bus --faults config/sim/feedback_dropout.yaml",
        ],
    )
    sim.add_argument(
        "--bus",
        required=True,
        metavar="SPEC",
        help="INTERFACE:CHANNEL, e.g. unix:DIRECTORY, socketcan:vcan0 or "
        "udp_multicast:239.74.163.2 (virtual:NAME lives inside this process: no other "
        "command hears it)",
    )
    _add_dbc(sim)
    sim.add_argument(
        "--hand",
        type=Path,
        default=DEFAULT_HAND,
        metavar="HAND.yaml",
        help=f"hand config ({DEFAULT_HAND_HELP})",
    )
    sim.add_argument(
        "--seconds",
        type=_amount,
        metavar="S",
        help="stop after this long [s], > 0 (default: at Ctrl-C)",
    )
    sim.add_argument("--seed", type=_seed, help="sensor noise seed (default: the config's)")
    sim.add_argument(
        "--faults", type=Path, metavar="FAULTS.yaml", help="fault scenario (config/sim/)"
    )
    sim.add_argument(
        "--summary-json",
        type=_output_path,
        metavar="FILE.json",
        help="write the ground truth (object poses, node states) at the end",
    )
    sim.add_argument(
        "--rt",
        action="store_true",
        help="ask for SCHED_FIFO (below the control loop's priority) and locked "
        "memory for the node timer (says so when refused)",
    )
    sim.add_argument(
        "--parent-pid",
        type=_integer,
        metavar="PID",
        help="run as the simulated hand of process PID (what handctl run "
        "--realtime does): stop when PID ends, and then remove the unix bus "
        "directory, which nobody else is left to remove",
    )
    sim.set_defaults(func=_cmd_sim)


def _add_run(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    example = "handctl run recipe config/recipes/swap_two_cylinders.yaml --summary-json out.json"
    run = _command(
        sub, "run", help="drive the hand", description="Drive the hand.", examples=[example]
    )
    runs = run.add_subparsers(dest="what", metavar="WHAT", required=True)
    rec = _command(
        runs,
        "recipe",
        help="run a grasp recipe",
        description="Run a recipe phase by phase at the hand's loop rate, every torque through "
        "the safety supervisor. Default bus: the simulated hand, in lockstep.",
        notes="Ctrl-C, SIGTERM, SIGHUP, Ctrl-\\ (SIGQUIT), Ctrl-Z, SIGUSR1/2, SIGALRM, SIGXCPU "
        "or any other signal whose default would kill it: a controlled stop (torque to zero, "
        "nodes disabled), exit 130. At --max-seconds: the "
        "same stop, outcome time_budget, exit 0. A safety stop exits 3.",
        examples=[
            example,
            "handctl run recipe RECIPE.yaml --bus socketcan:can0 --rt --log RUN.mcap",
        ],
    )
    rec.add_argument("recipe", type=Path, metavar="RECIPE.yaml", help="the recipe")
    _add_dbc(rec)
    rec.add_argument(
        "--hand",
        type=Path,
        default=DEFAULT_HAND,
        metavar="HAND.yaml",
        help=f"hand config ({DEFAULT_HAND_HELP})",
    )
    rec.add_argument(
        "--bus",
        default="sim",
        metavar="SPEC",
        help="sim (default), hand (the config's bus), virtual:NAME, socketcan:can0, "
        "unix:DIRECTORY, INTERFACE:CHANNEL",
    )
    mode = rec.add_mutually_exclusive_group()
    mode.add_argument(
        "--lockstep",
        action="store_true",
        help="step the simulated hand once per tick (default with --bus sim)",
    )
    mode.add_argument(
        "--realtime", action="store_true", help="tick from a 1 kHz timer (default on a real bus)"
    )
    rec.add_argument(
        "--rt",
        action="store_true",
        help="ask for SCHED_FIFO, locked and prefaulted memory, and on >= 2 CPUs "
        "separate CPUs for the loop and the simulated hand (says so when "
        "refused); on the simulated hand with --realtime only",
    )
    rec.add_argument(
        "--loop-cpu",
        type=_integer,
        metavar="N",
        help="with --rt: the control loop's CPU (default: an isolated CPU, else the highest)",
    )
    rec.add_argument(
        "--sim-cpu",
        type=_integer,
        metavar="N",
        help="with --rt: the simulated hand's CPU (default: the lowest other one)",
    )
    rec.add_argument(
        "--accept-missed-deadlines",
        action="store_true",
        help="run on a real bus even if the host fails the timing check made "
        "before it (docs/timing.md): the hand may stop on LOOP_OVERRUN, or "
        "worse, get late commands",
    )
    rec.add_argument(
        "--summary-json",
        type=_output_path,
        metavar="FILE.json",
        help="write the run summary as JSON (units in its key names)",
    )
    rec.add_argument(
        "--seed", type=_seed, help="simulated hand seed (default: the hand config's sim.seed)"
    )
    rec.add_argument(
        "--sim-faults",
        type=Path,
        metavar="FAULTS.yaml",
        help="fault scenario for the simulated hand (config/sim/)",
    )
    rec.add_argument(
        "--reset-node-faults",
        action="store_true",
        help="clear faults latched in the nodes before starting (explicit reset)",
    )
    rec.add_argument(
        "--max-seconds",
        type=_amount,
        metavar="S",
        help="time budget [s], > 0: stop (controlled) after this long, outcome "
        "time_budget, exit 0 (default: no limit; lockstep counts simulated "
        "time)",
    )
    rec.add_argument(
        "--log",
        type=_output_path,
        metavar="RUN.mcap",
        help="record every tick, event and frame to an MCAP file "
        "(see docs/recording.md; read it with 'handctl replay')",
    )
    rec.add_argument(
        "--plot",
        type=_output_path,
        metavar="OUT.png",
        help="overview PNG: phases, torques, object heights, centre-line angle "
        "(simulated hand in lockstep)",
    )
    rec.add_argument(
        "--live",
        type=_port,
        nargs="?",
        const=DEFAULT_LIVE_PORT,
        metavar="PORT",
        help="serve the recorded channels to Foxglove over WebSocket on "
        f"127.0.0.1:PORT while the hand runs (default {DEFAULT_LIVE_PORT}; "
        "needs --log)",
    )
    rec.set_defaults(func=_cmd_run_recipe)


def _add_plan(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    plan = _command(
        sub,
        "plan",
        help="plan a recipe's torques from a template (analysis, then search)",
        description="Compute the torques of every phase of a recipe template: the analysis' "
        "torque with the largest robust margin at each phase's grasp, refined by a "
        "search on the simulated hand scored over perturbed models. Writes the "
        "compiled recipe with per-phase provenance.",
        examples=[
            "handctl plan config/recipes/swap_two_cylinders.template.yaml -o "
            "config/recipes/swap_two_cylinders.yaml --plot plan/",
            "handctl plan TEMPLATE.yaml --from PHASE --base RECIPE.yaml [--schedule-only] "
            "-o RECIPE.yaml",
            "handctl plan config/recipes/swap_two_cylinders.template.yaml "
            "--base config/recipes/swap_two_cylinders.yaml --keep-torques --models 48 "
            "-o config/recipes/swap_two_cylinders.yaml",
        ],
    )
    plan.add_argument(
        "template", type=Path, metavar="TEMPLATE.yaml", help="recipe template (config/recipes/)"
    )
    plan.add_argument(
        "--hand",
        type=Path,
        default=DEFAULT_HAND,
        metavar="HAND.yaml",
        help=f"hand config ({DEFAULT_HAND_HELP})",
    )
    plan.add_argument(
        "-o",
        "--output",
        type=_output_path,
        required=True,
        metavar="RECIPE.yaml",
        help="where to write the compiled recipe",
    )
    plan.add_argument(
        "--plot",
        type=_output_dir,
        metavar="DIR",
        help="write each phase's torque region (chosen torque marked) as PNGs",
    )
    plan.add_argument(
        "--models", type=_integer, metavar="N", help="perturbed models (default: the template's)"
    )
    plan.add_argument(
        "--quick",
        action="store_true",
        help="the smallest search (smoke tests): each phase's first candidates (the "
        "analysis', the template's, the previous phase's and the random flexion seeds) on "
        "every model, then 1 generation of 2 instead of 4 of 16",
    )
    plan.add_argument(
        "--from",
        dest="start",
        metavar="PHASE",
        help="plan only from this phase of the template on; the phases before it keep the "
        "torques of --base (every model still runs them)",
    )
    plan.add_argument(
        "--base",
        type=Path,
        metavar="RECIPE.yaml",
        help="with --from: a recipe compiled from the same template for the same hand",
    )
    plan.add_argument(
        "--schedule-only",
        action="store_true",
        help="with --from and --base: keep every phase's own torques from --base and search "
        "only the template's planned schedule entries (plan: {models: N}) of the phases from "
        "--from on",
    )
    plan.add_argument(
        "--keep-torques",
        action="store_true",
        help="with --base, without --from: keep every searched phase's torques and the "
        "torques of its planned schedule entries (plan: {models: N}) from --base and search "
        "nothing; the template's other keys (exits, feedback, guard, written schedule "
        "entries, a free phase edited there) are compiled onto them, and every model runs the "
        "recipe for the provenance",
    )
    plan.add_argument(
        "--workers",
        type=_integer,
        metavar="N",
        help="local worker processes (default: every core; 1 runs in this "
        "process); the recipe is the same for any N",
    )
    plan.add_argument(
        "--scheduler",
        metavar="tcp://HOST:PORT",
        help="run the work on this Dask distributed cluster instead "
        "(pip install 'handctl[cluster]'; see docs/scale.md)",
    )
    _add_dbc(
        plan,
        "the CAN protocol of the hand (a DBC file) instead of the one generated from its "
        "config, for a hand whose can_ids only it carries (the simulated hand the plan runs "
        "on speaks it)",
    )
    plan.set_defaults(func=_cmd_plan)


def _add_bringup_run_options(p: argparse.ArgumentParser) -> None:
    """The options of a bring-up command that runs the hand through the Runtime (calibrate
    tdt, jog): how it runs, as ``run recipe`` has them."""
    p.add_argument(
        "--realtime",
        action="store_true",
        help="on the simulated hand: free-running in its own process, not lockstep",
    )
    p.add_argument(
        "--rt",
        action="store_true",
        help="ask for SCHED_FIFO and locked memory (says so when refused); on the "
        "simulated hand with --realtime only",
    )
    p.add_argument(
        "--seed", type=_seed, help="simulated hand seed (default: the hand config's sim.seed)"
    )
    p.add_argument(
        "--sim-faults",
        type=Path,
        metavar="FAULTS.yaml",
        help="fault scenario for the simulated hand (config/sim/)",
    )
    p.add_argument(
        "--reset-node-faults",
        action="store_true",
        help="clear faults latched in the nodes before starting (explicit reset)",
    )
    p.add_argument(
        "--accept-missed-deadlines",
        action="store_true",
        help="run on a real bus even if the host fails the timing check made before it "
        "(docs/timing.md): the hand may stop on LOOP_OVERRUN",
    )


def _add_bringup(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    """Bring-up commands (docs/bringup.md): nodes, calibrate tdt, jog, monitor."""
    nodes = _command(
        sub,
        "nodes",
        examples=["handctl nodes", "handctl nodes --bus socketcan:can0 --json"],
        help="list the hand's nodes as the bus shows them (listens, never sends)",
        description="Listen for the nodes' Feedback, Status and Heartbeat and print one row "
        "per configured node: present or missing, state, fault bits, protocol and "
        "firmware versions, feedback rate, counters, rejects; frames of nodes not "
        "in the hand config are flagged. Sends nothing. On --bus sim (the default) "
        "a simulated hand is started in this process to listen to.",
        notes="Exit 0 when every configured node is there, in no fault, of the host's "
        "protocol version, and no other node is heard; 1 otherwise.",
    )
    nodes.add_argument(
        "--bus",
        default="sim",
        help="sim (default), hand (the config's bus), socketcan:can0, "
        "unix:DIR, virtual:NAME, INTERFACE:CHANNEL",
    )
    _add_dbc(nodes)
    nodes.add_argument(
        "--hand",
        type=Path,
        default=DEFAULT_HAND,
        metavar="HAND.yaml",
        help=f"hand config ({DEFAULT_HAND_HELP})",
    )
    nodes.add_argument(
        "--seconds", type=_amount, metavar="S", help="how long to listen [s] (default 1)"
    )
    nodes.add_argument("--json", action="store_true", help="print the result as JSON")
    nodes.set_defaults(func=_cmd_nodes)

    calibrate = _command(
        sub,
        "calibrate",
        help="calibrate the hand's sensors",
        description="Calibrate the hand's sensors through the Runtime and the safety supervisor.",
        examples=["handctl calibrate tdt -o calibrated.yaml"],
    )
    calibrations = calibrate.add_subparsers(dest="what", metavar="WHAT", required=True)
    tdt = _command(
        calibrations,
        "tdt",
        examples=[
            "handctl calibrate tdt -o calibrated.yaml",
            "handctl calibrate tdt --bus socketcan:can0 --rt --hand HAND.yaml --write",
        ],
        help="measure each TDT sensor's offset and noise at zero torque",
        description="Enable every node at zero torque (through the Runtime and the supervisor), "
        "let the fingers settle, measure each TDT sensor's offset and noise, and "
        "write a copy of the hand config with the new offsets (comments and layout "
        "kept). Refused, naming the joint, if a joint moves or a sensor's noise or "
        "offset is implausible. Default bus: the simulated hand, in lockstep.",
        notes="Exit 0 written, 1 refused (nothing written), 2 bad input, 3 safety stop, "
        "130 interrupted (Ctrl-C: a controlled stop).",
    )
    _add_dbc(tdt)
    tdt.add_argument(
        "--hand",
        type=Path,
        default=DEFAULT_HAND,
        metavar="HAND.yaml",
        help=f"hand config ({DEFAULT_HAND_HELP})",
    )
    tdt.add_argument(
        "-o",
        "--output",
        type=_output_path,
        metavar="HAND.yaml",
        help="where to write the calibrated copy of the hand config: a new file, or an "
        "earlier calibrated copy of the same hand, differing in TDT offsets alone "
        "(nothing else is replaced)",
    )
    tdt.add_argument("--write", action="store_true", help="overwrite the hand config itself")
    tdt.add_argument(
        "--bus",
        default="sim",
        help="sim (default), hand, socketcan:can0, unix:DIR, INTERFACE:CHANNEL",
    )
    tdt.add_argument(
        "--seconds", type=_amount, metavar="S", help="measurement time [s] (default 1)"
    )
    tdt.add_argument(
        "--settle",
        type=_amount,
        metavar="S",
        help="time at zero torque before measuring [s] (default 2)",
    )
    tdt.add_argument(
        "--max-span",
        type=_amount,
        metavar="RAD",
        help="a joint that moves more than this [rad] is refused (default 0.1, or half the "
        "widest joint range if less)",
    )
    tdt.add_argument(
        "--max-noise",
        type=_amount,
        metavar="NM",
        help="a noise (1 sigma) above this [N·m] is refused (default 0.02, or a tenth of the "
        "largest tau_max if less)",
    )
    tdt.add_argument(
        "--max-offset",
        type=_amount,
        metavar="NM",
        help="an offset above this [N·m] is refused (default 0.25, or the largest tau_max if less)",
    )
    _add_bringup_run_options(tdt)
    tdt.add_argument(
        "--json", type=_output_path, metavar="FILE.json", help="write the measurement as JSON"
    )
    tdt.set_defaults(func=_cmd_calibrate_tdt)

    jog = _command(
        sub,
        "jog",
        examples=[
            "handctl jog f1_j2 --torque 0.05",
            "handctl jog f3_j1 --torque -0.05 --seconds 3 --bus socketcan:can0",
            "handctl jog f1_j2 --torque -0.03 --recover --bus socketcan:can0",
        ],
        help="one joint under a small torque, every other at zero, through safety",
        description="Ramp one joint to a torque (N·m) within its rate limit, hold it, ramp "
        "back to zero; every other joint gets zero. A one-phase recipe run by the "
        "normal Runtime: every torque through the supervisor with the hand's "
        "limits, and the soft-limit guard. A table of the joint's angle and TDT "
        "torque is printed as it runs. Default bus: the simulated hand, in lockstep.",
        notes="Ctrl-C or SIGTERM: a controlled stop (torque to zero, nodes disabled), exit "
        "130. A torque over half of the joint's tau_max (all of it with --recover) is "
        "refused (exit 2) before anything is sent. --recover brings back a joint resting "
        "outside its soft limits (no other run can arm then): the supervisor lets that "
        "joint, and only it, be outside as long as it comes back in (never more than "
        "0.02 rad further out "
        "than the farthest in it came), and the jog ends once it is 0.15 rad inside; "
        "exit 1 if it is still outside when --seconds are up.",
    )
    jog.add_argument("joint", help="joint name, as the hand config names it")
    jog.add_argument(
        "--recover",
        action="store_true",
        help="bring the joint back from outside its soft limits: the torque's sign must "
        "push it back in (negative from above the upper limit)",
    )
    jog.add_argument(
        "--torque", type=_real, required=True, metavar="X", help="torque [N·m], signed"
    )
    jog.add_argument(
        "--seconds", type=_amount, metavar="S", help="how long to hold it [s] (default 2)"
    )
    _add_dbc(jog)
    jog.add_argument(
        "--hand",
        type=Path,
        default=DEFAULT_HAND,
        metavar="HAND.yaml",
        help=f"hand config ({DEFAULT_HAND_HELP})",
    )
    jog.add_argument(
        "--bus",
        default="sim",
        help="sim (default), hand, socketcan:can0, unix:DIR, INTERFACE:CHANNEL",
    )
    _add_bringup_run_options(jog)
    jog.set_defaults(func=_cmd_jog)

    mon = _command(
        sub,
        "monitor",
        examples=[
            "handctl monitor",
            "handctl monitor --bus socketcan:can0 | jq .",
            "handctl monitor --log RUN.mcap",
        ],
        help="a live decoded view of the bus (listens, never sends)",
        description="Decode every frame on the bus: per message its rate, last values in "
        "units, and the CRC, counter and length rejects a receiver would make; "
        "unknown ids are counted. A full-screen view on a terminal, JSON lines "
        "(one snapshot every --every seconds, and a last one) when piped. Sends "
        "nothing. On --bus sim (the default) a simulated hand is started in this "
        "process to listen to.",
        notes="Ends after --seconds, or with Ctrl-C (exit 0); a log is read to its end, "
        "or through its first --seconds of log time.",
    )
    mon.add_argument(
        "--bus",
        help="sim (default), hand, socketcan:can0, unix:DIR, virtual:NAME, INTERFACE:CHANNEL",
    )
    _add_dbc(mon)
    mon.add_argument(
        "--hand",
        type=Path,
        metavar="HAND.yaml",
        help=f"hand config ({DEFAULT_HAND_HELP}; with --log: the recorded one, and another "
        "is refused)",
    )
    mon.add_argument(
        "--log",
        type=Path,
        metavar="RUN.mcap",
        help="read the raw frames of a recording instead of a bus, decoded with the "
        "protocol the recording keeps",
    )
    mon.add_argument(
        "--seconds",
        type=_amount,
        metavar="S",
        help="stop after this long [s] (default: at Ctrl-C; of log time with --log, from its "
        "first frame, default: the whole log)",
    )
    mon.add_argument(
        "--every",
        type=_amount,
        metavar="S",
        help="time between JSON snapshots [s] (default 1; of log time with --log)",
    )
    mon.set_defaults(func=_cmd_monitor)


def _add_replay(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    rep = _command(
        sub,
        "replay",
        help="summarise, plot, re-run or replay a recording",
        description="Read a recording (handctl run recipe --log RUN.mcap), complete or "
        "truncated, and print its summary: phases, largest torques, faults, timing, "
        "drops. Exit 1 when --rerun finds a mismatch.",
        examples=[
            "handctl replay RUN.mcap --rerun --plot OUT.png",
            "handctl replay RUN.mcap --export candump frames.log",
        ],
    )
    rep.add_argument("log", type=Path, metavar="RUN.mcap", help="the recording")
    rep.add_argument(
        "--plot",
        type=_output_path,
        metavar="OUT.png",
        help="torques over time with phase bands (and object poses if simulated)",
    )
    rep.add_argument(
        "--rerun",
        action="store_true",
        help="feed the logged frames through a fresh driver, recipe runner and "
        "safety; compare the applied torques tick by tick, bit for bit",
    )
    rep.add_argument(
        "--to-bus",
        metavar="SPEC",
        help="send the logged frames onto a bus (virtual:NAME, socketcan:can0, ...) "
        "with their original timing",
    )
    rep.add_argument(
        "--hand",
        type=Path,
        metavar="HAND.yaml",
        help="with --to-bus: the config of the hand on that bus; every command sent is held "
        "to its limits as well as the recorded hand's (needed on any bus but virtual: and "
        "unix:, since a log's own limits can be rewritten with it)",
    )
    _add_dbc(
        rep,
        "with --hand: the CAN protocol of the hand on that bus (a DBC file) instead of the "
        "one generated from its config, as run's --dbc",
    )
    rep.add_argument(
        "--speed",
        type=_amount,
        metavar="X",
        help="with --to-bus or --live: time scale [× recorded speed] (2 = twice as fast)",
    )
    rep.add_argument(
        "--direction",
        choices=("both", "rx", "tx"),
        help="with --to-bus: which logged frames to send (default both on a virtual: or "
        "unix: bus, tx, the host's alone, on any other: a hand there sends its own)",
    )
    rep.add_argument(
        "--export",
        nargs=2,
        metavar=("FORMAT", "OUT"),
        help="write the frames as candump, asc or blf (python-can's log formats)",
    )
    rep.add_argument(
        "--json",
        type=_output_path,
        metavar="FILE.json",
        help="write the summary (and re-run report) as JSON",
    )
    rep.add_argument(
        "--live",
        type=_port,
        nargs="?",
        const=DEFAULT_LIVE_PORT,
        metavar="PORT",
        help="stream the recording to Foxglove over WebSocket on 127.0.0.1:PORT "
        f"at its recorded speed (or --speed X; default port "
        f"{DEFAULT_LIVE_PORT})",
    )
    rep.set_defaults(func=_cmd_replay)


def _run(func: Callable[[argparse.Namespace], int], args: argparse.Namespace) -> int:
    from handctl.stopsignals import finished, interruption, raised

    try:
        _refuse_empty_names(args)
        return func(args)
    except ConfigError as exc:
        print(f"handctl: error: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except BusError as exc:
        print(f"handctl: bus error: {exc}", file=sys.stderr)
        return EXIT_BUS
    except HandctlError as exc:
        from handctl.hostcheck import HostTimingError  # not before: it imports numpy

        if isinstance(exc, HostTimingError):
            print(f"handctl: refused: {exc}", file=sys.stderr)
            return EXIT_HOST
        print(f"handctl: error: {exc}", file=sys.stderr)
        return EXIT_FAILED
    except KeyboardInterrupt:
        print(f"handctl: {interruption()}", file=sys.stderr)
        return EXIT_INTERRUPTED
    except OSError as exc:
        # a file the command was told to read or write that the system refused (a full disk,
        # a file turned read-only since the options were checked): its name and the reason
        if exc.filename is not None:
            print(f"handctl: error: {exc.filename}: {exc.strerror or exc}", file=sys.stderr)
            return EXIT_BAD_INPUT
        if exc.errno is not None and exc.strerror and not raised():
            # the system's refusal of a write to a file already open, which carries no name
            # (a full disk under a file being written): its reason, not a bare traceback
            print(f"handctl: error: {_system_refusal(exc)}", file=sys.stderr)
            return EXIT_FAILED
        return _unexpected(exc)
    except Exception as exc:  # a bug: said as one, with what to report
        return _unexpected(exc)
    finally:
        finished()  # the command has its result (``stopsignals.finished``)


def _system_refusal(exc: OSError) -> str:
    """An ``OSError`` the system raised, without a file's name: its reason and its errno's
    name (``ENOSPC``), which is what to search for."""
    import errno

    name = errno.errorcode.get(exc.errno or 0)
    code = f", {name}" if name else ""
    return f"the system refused a read or a write ({exc.strerror}{code})"


def _unexpected(exc: Exception) -> int:
    """An exception no handctl error explains: the host out of memory, an interrupt come out
    as another error, or else a bug, said as one with its traceback."""
    from handctl.stopsignals import raised

    if _out_of_memory(exc):
        # the host's limit, not a bug in handctl (nor the input's): said as such, in
        # one line; a run stops its hand itself on any exception inside its loop, so a
        # run that had begun had its hand stopped before this (found by an outside
        # audit: an allocation after the stop said "internal error ... a bug")
        print(
            f"handctl: error: this host ran out of memory ({type(exc).__name__}: {exc}); "
            "a run that had begun stopped its hand first. Free memory, or raise the "
            "process's limit (ulimit -v), and try again",
            file=sys.stderr,
        )
        return EXIT_FAILED
    if raised():  # an interrupt that came out as another error (``stopsignals.raised``)
        print(
            f"handctl: interrupted ({raised()}: {type(exc).__name__}: {exc})",
            file=sys.stderr,
        )
        return EXIT_INTERRUPTED
    # not a bare traceback: the first line says what failed and that it is handctl's own
    # fault, not the input's; a run's stop does not pass through here (the loop stops
    # the hand itself on any exception inside it)
    import traceback

    print(
        f"handctl: internal error: {type(exc).__name__}: {exc} (a bug in handctl, not in "
        "the input; please report it with the traceback below)",
        file=sys.stderr,
    )
    traceback.print_exception(exc, file=sys.stderr)
    return EXIT_FAILED


def _out_of_memory(exc: BaseException) -> bool:
    """Whether ``exc`` is an allocation that failed: Python's, or MuJoCo's (a ``FatalError``
    saying so: MuJoCo's own allocator under a memory limit)."""
    return isinstance(exc, MemoryError) or (
        type(exc).__name__ == "FatalError" and "allocate memory" in str(exc)
    )


class _ReaderMayLeave(io.TextIOBase):
    """stdout or stderr for a reader that may stop reading (``handctl check | head -1``), or
    a file that can no longer be written (``> /dev/full``, a disk full, an I/O error).

    Once the reader is gone, what is still written goes to /dev/null (its descriptor too, so
    that the interpreter's last flush finds somewhere to go): the command finishes its work,
    a run stops the hand as it would anyway, and the exit code is the command's own rather
    than a ``BrokenPipeError`` (or ``OSError``) traceback. A reader leaving is normal and
    passes in silence; a stdout that fails otherwise is said once on stderr, since what it
    held is lost.
    """

    def __init__(self, stream: IO[str] | None, name: str) -> None:
        super().__init__()
        self.stream = stream
        self.name = name
        # None: started with the descriptor closed (``>&-``), so nothing can be written
        self.reader_gone = stream is None

    def write(self, text: str) -> int:
        stream = self.stream
        if stream is not None and not self.reader_gone:
            self._guard(lambda: _write_encodable(stream, text))
        return len(text)

    def flush(self) -> None:
        if self.stream is not None and not self.reader_gone:
            self._guard(self.stream.flush)

    def isatty(self) -> bool:
        return self.stream is not None and not self.reader_gone and self.stream.isatty()

    def fileno(self) -> int:
        if self.stream is None:
            raise io.UnsupportedOperation(f"{self.name} was closed when handctl started")
        return self.stream.fileno()

    @property
    def encoding(self) -> str:  # type: ignore[override]
        return str(getattr(self.stream, "encoding", "utf-8"))

    def _guard(self, op: Callable[[], object]) -> None:
        try:
            op()
        except BrokenPipeError:
            self._gone()
        except OSError as exc:
            self._gone()
            if self.name == "stdout":
                print(
                    f"handctl: warning: stdout cannot be written ({exc.strerror or exc}); "
                    "the rest of what it would show is dropped",
                    file=sys.stderr,
                )

    def _gone(self) -> None:
        self.reader_gone = True
        assert self.stream is not None  # a closed one is gone from the start
        try:
            devnull = os.open(os.devnull, os.O_WRONLY)
            os.dup2(devnull, self.stream.fileno())
            os.close(devnull)
        except (OSError, ValueError):  # no descriptor (a test's capture): nothing to flush
            pass


def _write_encodable(stream: IO[str], text: str) -> None:
    """Write ``text`` as far as the stream's encoding can say it: a character it has no code
    for (``N·m``, ``τ`` under ``LANG=C`` or ``PYTHONIOENCODING=latin-1``) is written as its
    escape, as Python's own stderr does. Output in a poorer encoding is still output; a
    ``UnicodeEncodeError`` ended a finished run before its ``--summary-json`` was written."""
    try:
        stream.write(text)
    except UnicodeEncodeError:
        encoding = getattr(stream, "encoding", None) or "ascii"
        stream.write(text.encode(encoding, "backslashreplace").decode(encoding))


@contextmanager
def _output_for_readers_that_leave() -> Iterator[None]:
    saved = sys.stdout, sys.stderr
    sys.stdout = _ReaderMayLeave(sys.stdout, "stdout")
    sys.stderr = _ReaderMayLeave(sys.stderr, "stderr")
    try:
        yield
    finally:
        for wrapped in (sys.stdout, sys.stderr):
            wrapped.flush()
        sys.stdout, sys.stderr = saved


def main(argv: Sequence[str] | None = None) -> int:
    # Before the first import of MuJoCo, and whatever the environment says, as for
    # matplotlib's backend below (importing handctl did it too; a caller's environment
    # changed since is set back here)
    mujoco_opengl_off()
    # handctl's plots are files drawn on an Agg canvas, never a window, so matplotlib's
    # backend is none of the user's business here; a value matplotlib does not know made its
    # import raise after a whole run, whose summary was then never printed
    os.environ.pop("MPLBACKEND", None)
    with _output_for_readers_that_leave():
        # SIGTERM is Ctrl-C for every command, from the start: while a hand config, a recipe
        # and their imports load (seconds on a busy machine) it too ends the command with exit
        # 130. ``handctl run`` turns both into its controlled stop once the run begins.
        if threading.current_thread() is not threading.main_thread():  # signals are not ours
            return _run_args(argv)
        from handctl.stopsignals import ENDING, interrupt, working

        working()

        before = signal.signal(signal.SIGTERM, interrupt)
        # a terminal that went away, Ctrl-\\ (SIGQUIT: it ended a jog or a replay onto a bus
        # by the signal, no stop sent) and the rest of stopsignals.ENDING; but a run started
        # under nohup (SIGHUP ignored) asked to outlive its terminal, and keeps ignoring it
        ending = {sig: signal.getsignal(sig) for sig in ENDING}
        for sig, inherited in ending.items():
            if inherited is not signal.SIG_IGN:
                signal.signal(sig, interrupt)
        # SIGINT too, explicitly: a process started with it ignored (a background job of a
        # non-interactive shell, a supervisor's child) inherits SIG_IGN, and Python then
        # leaves it so; a plan or a check would go on through every Ctrl-C and kill -INT.
        # ``interrupt``, not Python's own handler: once the command has its result
        # (``stopsignals.finished``) a Ctrl-C is said and changes no exit, as the others are;
        # Python's raised it all the same, and a jog's result became 130 (an outside audit).
        before_int = signal.signal(signal.SIGINT, interrupt)
        try:
            return _run_args(argv)
        finally:
            signal.signal(signal.SIGTERM, before)
            signal.signal(signal.SIGINT, before_int)
            for sig, inherited in ending.items():
                signal.signal(sig, inherited)


def leave(code: int) -> None:
    """What ``__main__.entry`` does once the command has its result (``code``, its exit):
    the stop signals are ignored for what is left, the interpreter's own shutdown. That
    shutdown puts back the default of every signal with a Python handler, and a SIGTERM in
    its last tens of milliseconds killed the process by the signal (exit -15, 143 in a shell)
    after a run that had finished and written its summary. One noted on the way
    (``stopsignals.LATE``) is said."""
    from handctl.stopsignals import LATE, ignore_stops

    ignore_stops()
    if LATE and sys.stderr is not None:
        names = ", ".join(dict.fromkeys(LATE))
        with contextlib.suppress(OSError, ValueError):  # a stderr that cannot be written
            print(
                f"handctl: {names} came after the command had finished; its exit ({code}) stands",
                file=sys.stderr,
            )


def _run_args(argv: Sequence[str] | None) -> int:
    args = build_parser().parse_args(argv)
    return _run(args.func, args)


if __name__ == "__main__":
    raise SystemExit(main())
