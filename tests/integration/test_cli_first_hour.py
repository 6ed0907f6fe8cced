"""The command line as a newcomer meets it: from any directory, with exit codes that mean
what the README says, output that may be cut short, and a summary that names its units."""

from __future__ import annotations

import json
import math
import re
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

from handctl.cli import DEFAULT_HAND, status_text
from handctl.config import load_hand
from handctl.online.loop import Outcome, StatusLine
from handctl.online.recipes.loader import load_recipe
from handctl.session import RunRequest, run_recipe

from ..conftest import HAND_YAML, ROOT, handctl
from .rig import TWO_PHASES, write_recipe

RECIPE = ROOT / "config" / "recipes" / "swap_two_cylinders.yaml"
#: A unit (or "this is a fraction") in a key: ``held_s``, ``lateness_us``, ``stage_cpu_us_p99``.
UNIT_IN_KEY = re.compile(r"_(s|ms|us|ns|m|mm|rad|deg|nm|n|hz|mb|fraction|ratio)(_|$)", re.I)


def test_the_packaged_default_hand_is_the_repository_copy() -> None:
    assert DEFAULT_HAND.read_bytes() == HAND_YAML.read_bytes()


def test_defaults_do_not_depend_on_the_current_directory(tmp_path: Path) -> None:
    done = handctl("check", cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    assert done.stdout.splitlines()[-1] == "ok"


def test_a_missing_hand_is_reported_against_the_option_that_named_it(tmp_path: Path) -> None:
    done = handctl("run", "recipe", str(RECIPE), "--hand", "nothere.yaml", cwd=tmp_path)
    assert done.returncode == 2
    assert "handctl: error: --hand: expected an existing hand config file" in done.stderr
    assert "nothere.yaml: no such file" in done.stderr
    done = handctl("check", "nothere.yaml", cwd=tmp_path)
    assert done.returncode == 2
    assert "HAND.yaml: expected an existing hand config file" in done.stderr


def test_check_refuses_an_interface_python_can_lacks(tmp_path: Path) -> None:
    """A typo in bus.interface is found by ``handctl check``, not by the first bring-up tool
    that opens the bus."""
    hand = tmp_path / "hand.yaml"
    hand.write_text(HAND_YAML.read_text().replace("interface: socketcan", "interface: sockectan"))
    done = handctl("check", str(hand), cwd=tmp_path)
    assert done.returncode == 2, done.stdout + done.stderr
    assert f"{hand}: bus.interface: expected a python-can interface (" in done.stderr
    assert "found 'sockectan'" in done.stderr


@pytest.mark.parametrize("seconds", ["-1", "0", "nan", "inf", "1e308"])
def test_a_time_budget_that_is_not_a_duration_is_bad_input(tmp_path: Path, seconds: str) -> None:
    out = tmp_path / "out.json"
    done = handctl(
        "run",
        "recipe",
        str(RECIPE),
        "--max-seconds",
        seconds,
        "--summary-json",
        str(out),
        cwd=tmp_path,
    )
    assert done.returncode == 2, done.stderr
    assert "--max-seconds: expected a number of seconds > 0" in done.stderr
    assert not out.exists()  # refused before the run: nothing was sent


@pytest.mark.parametrize(
    ("command", "said"),
    [
        (("analyze", "torque-set", "config/analysis/paper_fig3.yaml", "--k", "nan", "0.1"), "--k"),
        (("analyze", "torque-set", "config/analysis/paper_fig3.yaml", "--k", "1e308", "1"), "--k"),
        (("replay", "run.mcap", "--to-bus", "virtual:never", "--speed", "1e-300"), "--speed"),
        (("replay", "run.mcap", "--to-bus", "virtual:never", "--speed", "1e9"), "--speed"),
    ],
    ids=["k nan", "k huge", "speed tiny", "speed huge"],
)
def test_a_number_out_of_an_options_range_is_bad_input(command: tuple[str, ...], said: str) -> None:
    """Before, these exited 1 (``--k nan``), overflowed into numpy's warnings and exit 0
    (``--k 1e308``), or stopped in a traceback (``--speed 1e-300``: a time stamp out of range)."""
    done = handctl(*command, cwd=ROOT)
    assert done.returncode == 2, done.stdout + done.stderr
    assert "Traceback" not in done.stderr and "Warning" not in done.stderr
    assert f"handctl: error: {said}: expected " in done.stderr


def test_a_run_that_ends_on_its_time_budget_has_its_own_outcome(tmp_path: Path) -> None:
    out = tmp_path / "out.json"
    done = handctl(
        "run",
        "recipe",
        str(RECIPE),
        "--max-seconds",
        "0.5",
        "--summary-json",
        str(out),
        cwd=tmp_path,
    )
    assert done.returncode == 0, done.stderr
    summary = json.loads(out.read_text())
    assert summary["outcome"] == "time_budget"
    assert summary["completed"] is False
    assert summary["faults"] == []
    assert "time budget of 0.5 s reached" in summary["message"]
    assert all(n["state"] == "DISABLED" for n in summary["sim"]["nodes"].values())


def test_a_reader_that_leaves_early_ends_no_command_with_a_traceback(tmp_path: Path) -> None:
    proc = subprocess.Popen(
        [sys.executable, "-m", "handctl", "check"],
        cwd=tmp_path,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
    )
    assert proc.stdout is not None and proc.stderr is not None
    proc.stdout.close()  # as `| head -0` would: every line the command writes has no reader
    stderr = proc.stderr.read().decode()
    proc.stderr.close()
    assert proc.wait(timeout=300) == 0, stderr
    assert "Traceback" not in stderr and "BrokenPipeError" not in stderr, stderr


def _floats_without_units(value: Any, path: tuple[str, ...] = ()) -> list[str]:
    if isinstance(value, dict):
        return [p for k, v in value.items() for p in _floats_without_units(v, (*path, str(k)))]
    if isinstance(value, list):
        return [p for v in value for p in _floats_without_units(v, path)]
    if (
        isinstance(value, float)
        and math.isfinite(value)
        and not any(UNIT_IN_KEY.search(key) for key in path)
    ):
        return [".".join(path)]
    return []


def test_the_summary_names_its_units_and_the_other_nodes_frames_are_no_rejects(
    hand_config: Any,
) -> None:
    hand, recipe = hand_config
    lines: list[StatusLine] = []
    report = run_recipe(RunRequest(hand=hand, recipe=recipe, max_seconds=1.2), status=lines.append)
    assert report.result.outcome is Outcome.TIME_BUDGET
    summary = json.loads(json.dumps(report.summary))
    assert _floats_without_units(summary) == []
    for node in summary["sim"]["nodes"].values():
        assert not [k for k, v in node.items() if k.startswith("reject") and v], node
        assert node["other_ids_ignored"] > 0  # the other nodes' command frames, seen and left
    # The status line: phase k of n, time in it, and that lockstep time is simulated.
    assert all(line.simulated for line in lines)
    numbers = [line.phase_number for line in lines]
    assert numbers == sorted(numbers) and {1, 2} <= set(numbers)
    assert all(line.phase_count == 2 for line in lines)
    second = [line for line in lines if line.phase_number == 2]
    assert second[0].phase_s < second[-1].phase_s < second[-1].t_s
    assert "sim " in status_text(second[-1]) and "phase 2/2 second" in status_text(second[-1])
    # the first phase ran out its 0.4 s: the line says so from then on, and not before
    assert status_text(second[-1]).endswith("timed out: first")
    assert "timed out" not in status_text(lines[0])


@pytest.fixture
def hand_config(tmp_path: Path) -> tuple[Any, Any]:
    hand = load_hand(HAND_YAML)
    return hand, load_recipe(write_recipe(tmp_path, TWO_PHASES), hand)


OUTPUTS = [
    ("run", "recipe", str(RECIPE), "--summary-json", "{out}", "--max-seconds", "0.1"),
    ("run", "recipe", str(RECIPE), "--plot", "{out}", "--max-seconds", "0.1"),
    (
        "analyze",
        "torque-set",
        "config/analysis/paper_fig3.yaml",
        "--k",
        "0.9",
        "0.1",
        "--json",
        "{out}",
    ),
    ("check", "--timing", "--seconds", "0.05", "--json", "{out}"),
]


@pytest.mark.parametrize(
    "command", OUTPUTS, ids=lambda c: f"{c[0]} {c[-3] if c[0] == 'run' else c[-2]}"
)
@pytest.mark.parametrize("where", ["missing directory", "a directory"])
def test_an_output_file_that_cannot_be_written_is_refused_before_the_work(
    tmp_path: Path, command: tuple[str, ...], where: str
) -> None:
    """Before, a run ran to its end and then stopped in a traceback (FileNotFoundError), and
    a directory given to --plot was written beside it as DIR.png."""
    out = tmp_path / "nowhere" / "out.json" if where == "missing directory" else tmp_path
    option = next(
        a for a in command if a.startswith("-") and command[command.index(a) + 1] == "{out}"
    )
    done = handctl(*(str(out) if a == "{out}" else a for a in command), cwd=ROOT)
    assert done.returncode == 2, done.stdout + done.stderr
    assert "Traceback" not in done.stderr
    expected = (
        "a file in an existing directory" if where == "missing directory" else "not a directory"
    )
    assert f"handctl: error: {option}: expected " in done.stderr and expected in done.stderr
    assert "ticks" not in done.stdout  # nothing ran
    assert not (tmp_path.parent / f"{tmp_path.name}.png").exists()


PLOTS = [
    ("run", "recipe", str(RECIPE), "--max-seconds", "0.1", "--plot"),
    ("analyze", "torque-set", "config/analysis/paper_fig3.yaml", "--k", "0.9", "0.1", "--plot"),
]


@pytest.mark.parametrize("command", PLOTS, ids=lambda c: c[0])
@pytest.mark.parametrize("name", ["out.txt", "out"])
def test_a_plot_in_no_picture_format_is_refused_before_the_work(
    tmp_path: Path, command: tuple[str, ...], name: str
) -> None:
    """Before, the run (or the analysis) ran to its end and then stopped in matplotlib's
    traceback (``Format 'txt' is not supported``); a name without a suffix was written as
    ``out.png``, not the file the user named."""
    done = handctl(*command, str(tmp_path / name), cwd=ROOT)
    assert done.returncode == 2, done.stdout + done.stderr
    assert "Traceback" not in done.stderr
    assert "handctl: error: --plot: expected a picture file name ending in .png" in done.stderr
    assert "ticks" not in done.stdout
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize(
    "command",
    [
        ("run", "recipe", str(RECIPE)),
        ("jog", "f1_j2", "--torque", "0.05", "--seconds", "0.3"),
    ],
    ids=["run", "jog"],
)
def test_a_bus_that_is_not_there_is_a_bus_error_before_the_timing_check(
    command: tuple[str, ...],
) -> None:
    """Before, a run on a real bus made the host's timing check first (2 s) and a loaded host
    failed it: exit 5, "pass --accept-missed-deadlines", and the missing interface was said
    only once that was passed; on a quiet host the same command gave exit 4."""
    done = handctl(*command, "--bus", "socketcan:hctlnone9", cwd=ROOT)
    assert done.returncode == 4, done.stdout + done.stderr
    assert "handctl: bus error: socketcan:hctlnone9:" in done.stderr
    assert "timing check" not in done.stdout + done.stderr
    assert "Traceback" not in done.stderr


#: Interface names the kernel takes that hold what a terminal acts on or cannot show: an
#: escape sequence, DEL, a C1 control (U+0085), a byte that is not UTF-8 (0xFF, which Python
#: holds as the lone surrogate U+DCFF); each with how a message shows it.
ODD_NAMES = [
    ("ca\x1b[31mn", "ca\\x1b[31mn"),
    ("c\x7fn", "c\\x7fn"),
    ("c\x85n", "c\\x85n"),
    ("c\udcffn", "c\\xffn"),
]


@pytest.mark.parametrize(("name", "shown"), ODD_NAMES, ids=["escape", "del", "c1", "not-utf-8"])
def test_an_interface_name_with_control_characters_or_bytes_is_shown_escaped(
    tmp_path: Path, name: str, shown: str
) -> None:
    """Such a name, from ``--bus`` or a hand config's ``bus.channel``, was echoed raw: the
    escape sequence recoloured the terminal that showed the error, the byte 0xFF became
    ``\\udcff``. Now every message that names it shows it escaped, and the command it
    suggests is one a shell decodes back to the name (``$'...'``)."""
    done = handctl("nodes", "--bus", f"socketcan:{name}", "--seconds", "0.2", cwd=ROOT)
    assert done.returncode == 4, done.stdout + done.stderr
    # no such interface, or (as here) no SocketCAN in the kernel: either way named escaped
    assert f"handctl: bus error: socketcan:{shown}: " in done.stderr
    hint = done.stderr.split("configure it with: ")[1].split(" up type can")[0]
    assert hint.startswith("sudo ip link set $'")
    said = subprocess.run(
        ["bash", "-c", f"printf %s {hint.removeprefix('sudo ip link set ')}"],
        capture_output=True,
        check=True,
    )
    assert said.stdout == name.encode("utf-8", "surrogateescape")
    _nothing_raw(done.stdout + done.stderr)
    if shown.endswith("\\xffn"):  # a hand config is UTF-8 text: it cannot hold such a byte
        return
    hand = tmp_path / "hand.yaml"
    hand.write_text(
        HAND_YAML.read_text().replace("channel: can0", f'channel: "{shown}"'), encoding="utf-8"
    )
    checked = handctl("check", str(hand), cwd=tmp_path)
    assert checked.returncode == 0, checked.stdout + checked.stderr
    assert f"bus socketcan:{shown}, CAN-FD" in checked.stdout
    _nothing_raw(checked.stdout + checked.stderr)


def _nothing_raw(output: str) -> None:
    assert not any(c in output for c in "\x1b\x7f\x85\udcff"), output
    assert "\\udcff" not in output, output


def test_a_refused_interface_name_is_shown_escaped_in_the_error(tmp_path: Path) -> None:
    """The bad-input message (a name the kernel never gives) shows a byte that is not UTF-8
    as ``\\xff``, not as the surrogate Python holds it as."""
    done = handctl("nodes", "--bus", "socketcan:a/\udcff\x1b", cwd=ROOT)
    assert done.returncode == 2, done.stdout + done.stderr
    assert "--bus: channel: expected a Linux interface name" in done.stderr
    assert "found 'a/\\xff\\x1b'" in done.stderr


@pytest.mark.parametrize(
    ("command", "said"),
    [
        (("replay", "run.mcap", "--direction", "rx"), "--direction: expected --to-bus SPEC"),
        (("monitor", "--bus", "", "--seconds", "0.2"), "--bus: expected sim, hand, or"),
        (("calibrate", "tdt", "--write", "-o", "{tmp}/copy.yaml"), "--write: expected either"),
    ],
    ids=["replay direction alone", "monitor empty bus", "calibrate write and copy"],
)
def test_an_option_that_would_be_ignored_is_bad_input(
    tmp_path: Path, command: tuple[str, ...], said: str
) -> None:
    """Before, each exited 0 doing something else than asked: the direction dropped, the
    empty bus taken for the simulated hand, ``--write`` dropped for the copy."""
    done = handctl(*(a.replace("{tmp}", str(tmp_path)) for a in command), cwd=ROOT)
    assert done.returncode == 2, done.stdout + done.stderr
    assert f"handctl: error: {said}" in done.stderr
    assert list(tmp_path.iterdir()) == []


def test_options_that_cannot_work_are_refused_before_anything_is_said_or_measured(
    tmp_path: Path,
) -> None:
    """``check --timing --loop-cpu 7`` said 'timing check: a bare timer loop ...' before
    its refusal; ``replay --to-bus`` onto a bus a real hand may be on, without ``--hand``,
    printed the whole summary first; ``--to-bus bogus`` was said of ``--bus``."""
    done = handctl("check", "--timing", "--seconds", "1", "--loop-cpu", "4096")
    assert done.returncode == 2, done.stderr
    assert "--loop-cpu: expected one of the CPUs this process may use" in done.stderr
    assert "timing check" not in done.stdout + done.stderr
    log = tmp_path / "no.mcap"  # never read: each is refused before the recording is opened
    for spec, said in [
        ("bogus", "handctl: error: --to-bus: expected sim, hand, or INTERFACE:CHANNEL"),
        ("unix:relative/dir", "handctl: error: --to-bus: channel: expected an absolute"),
        ("udp_multicast:239.1.1.3", "handctl: error: --hand: expected the config of the hand"),
        ("hand", "handctl: error: --hand: expected the config of the hand whose bus"),
        ("sim", "handctl: error: --to-bus: expected a bus other processes are on"),
    ]:
        done = handctl("replay", str(log), "--to-bus", spec)
        assert done.returncode == 2, done.stderr
        assert done.stderr.startswith(said), done.stderr
        assert done.stdout == ""


def test_a_bus_inside_the_process_is_said_to_be_one() -> None:
    """``nodes --bus virtual:x`` listed every node missing, ``run`` stopped on 'no feedback'
    after its start-up, and neither said that nothing outside the process is on such a bus
    (``sim`` said it; the others now say it too)."""
    said = "--bus virtual:first-hour lives inside this process: nothing in another process"
    for args in (["nodes", "--seconds", "0.2"], ["monitor", "--seconds", "0.1"]):
        done = handctl(*args, "--bus", "virtual:first-hour")
        assert f"handctl: warning: {said}" in done.stderr, done.stderr


@pytest.mark.parametrize("command", PLOTS, ids=lambda c: c[0])
def test_a_plot_never_replaces_a_file_of_another_kind(
    tmp_path: Path, command: tuple[str, ...]
) -> None:
    """A hand config copied to a name ending in .png was replaced by the plot, exit 0, where
    every other output refuses to replace a file of another kind (an outside audit); an
    earlier picture is drawn again."""
    victim = tmp_path / "hand.png"
    text = (ROOT / "config" / "hands" / "hiroshima_hand.yaml").read_text()
    victim.write_text(text)
    done = handctl(*command, str(victim), cwd=ROOT)
    assert done.returncode == 2, done.stdout + done.stderr
    assert "handctl: error: --plot: expected a new file, or an earlier picture to draw again" in (
        done.stderr
    )
    assert f"found {victim}: an existing file that is not a picture" in done.stderr
    assert victim.read_text() == text
    victim.write_bytes(b"\x89PNG\r\n\x1a\n an earlier plot")
    done = handctl(*command, str(victim), cwd=ROOT)
    assert done.returncode == 0, done.stderr
    assert victim.stat().st_size > 1000


@pytest.mark.parametrize(
    "command",
    [
        ("run", "recipe", "config/recipes/swap_two_cylinders.yaml"),
        ("jog", "f1_j1", "--torque", "0.01"),
        ("calibrate", "tdt", "-o", "{out}"),
        ("nodes",),
        ("monitor", "--seconds", "0.1"),
    ],
    ids=["run", "jog", "calibrate", "nodes", "monitor"],
)
def test_a_real_hand_s_config_on_the_default_bus_is_told_to_give_its_bus(
    tmp_path: Path, command: tuple[str, ...]
) -> None:
    """A hand config without a ``sim:`` section (a real hand's) with ``--bus`` forgotten was
    "sim: expected this key (required)", which sent the user to write a simulation (found by
    an outside audit)."""
    real = tmp_path / "real_hand.yaml"
    text = HAND_YAML.read_text()
    real.write_text(text[: text.index("\nsim:") + 1])
    args = [a.replace("{out}", str(tmp_path / "cal.yaml")) for a in command]
    done = handctl(*args, "--hand", str(real))
    assert done.returncode == 2, done.stderr
    assert f"{real}: sim: expected a sim: section for --bus sim, the simulated hand" in (
        done.stderr
    )
    assert "--bus hand (the interface in its config)" in done.stderr
