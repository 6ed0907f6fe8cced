"""Numbers on the command line: what every integer option takes, and negative numbers in
exponent form as values, through the real parser."""

from __future__ import annotations

import argparse
from collections.abc import Iterator
from pathlib import Path

import pytest

from handctl import cli
from handctl.errors import shown

from ..conftest import ROOT

#: Every integer option of every command: the command, what else it requires, the option,
#: a value it takes.
INTEGER_OPTIONS = [
    (("check",), ("--timing",), "--loop-cpu", "1"),
    (("sim",), ("--bus", "virtual:x"), "--seed", "7"),
    (("sim",), ("--bus", "virtual:x"), "--parent-pid", "4321"),
    (("run", "recipe"), ("r.yaml",), "--loop-cpu", "1"),
    (("run", "recipe"), ("r.yaml",), "--sim-cpu", "0"),
    (("run", "recipe"), ("r.yaml",), "--seed", "7"),
    (("run", "recipe"), ("r.yaml",), "--live", "8765"),
    (("plan",), ("t.yaml", "-o", "out.yaml"), "--models", "4"),
    (("plan",), ("t.yaml", "-o", "out.yaml"), "--workers", "2"),
    (("replay",), ("run.mcap",), "--live", "8765"),
    (("calibrate", "tdt"), (), "--seed", "7"),
    (("jog",), ("f1_j2", "--torque", "0.05"), "--seed", "7"),
]
IDS = [f"{' '.join(command)} {option}" for command, _, option, _ in INTEGER_OPTIONS]


def _options(
    parser: argparse.ArgumentParser, words: tuple[str, ...] = ()
) -> Iterator[tuple[tuple[str, ...], argparse.Action]]:
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                yield from _options(sub, (*words, name))
        else:
            yield words, action


#: Every number option of every command: the command, what else it requires, the option,
#: whether it takes a negative number (a signed torque, a ratio) or is a time, a speed or a
#: limit, never below 0.
NUMBER_OPTIONS = [
    (("check",), ("--timing",), "--seconds", False),
    (("analyze", "torque-set"), ("s.yaml",), "--k", True),
    (("sim",), ("--bus", "virtual:x"), "--seconds", False),
    (("run", "recipe"), ("r.yaml",), "--max-seconds", False),
    (("nodes",), (), "--seconds", False),
    (("calibrate", "tdt"), (), "--seconds", False),
    (("calibrate", "tdt"), (), "--settle", False),
    (("calibrate", "tdt"), (), "--max-span", False),
    (("calibrate", "tdt"), (), "--max-noise", False),
    (("calibrate", "tdt"), (), "--max-offset", False),
    (("jog",), ("f1_j2",), "--torque", True),
    (("jog",), ("f1_j2", "--torque", "0.05"), "--seconds", False),
    (("monitor",), (), "--seconds", False),
    (("monitor",), (), "--every", False),
    (("replay",), ("run.mcap",), "--speed", False),
]


def test_every_number_option_is_listed_as_signed_or_not() -> None:
    found = {
        (words, action.option_strings[0])
        for words, action in _options(cli.build_parser())
        if action.type in (cli._real, cli._amount)
    }
    assert found == {(command, option) for command, _, option, _ in NUMBER_OPTIONS}


@pytest.mark.parametrize(
    ("command", "required", "option", "signed"),
    NUMBER_OPTIONS,
    ids=[f"{' '.join(command)} {option}" for command, _, option, _ in NUMBER_OPTIONS],
)
def test_a_number_option_s_examples_are_numbers_it_takes(
    command: tuple[str, ...],
    required: tuple[str, ...],
    option: str,
    signed: bool,
    capsys: pytest.CaptureFixture[str],
) -> None:
    """``--max-seconds 1s`` was told "expected a number (e.g. 0.5, -1e-3)", an example that
    option refuses (it must be > 0): a negative example only for an option that takes one."""
    values = ["1s", "1s"] if option == "--k" else ["1s"]
    with pytest.raises(SystemExit) as done:
        cli.build_parser().parse_args([*command, *required, option, *values])
    assert done.value.code == cli.EXIT_BAD_INPUT
    err = capsys.readouterr().err
    examples = "0.5, -1e-3" if signed else "0.5, 2"
    assert f"argument {option}: expected a number (e.g. {examples}), found '1s'" in err, err


def test_no_option_is_parsed_by_int_or_float_themselves() -> None:
    """A new number option uses a shared type (``cli._integer``, ``cli._amount``), not ``int``
    or ``float``, which take what no user types as a number (digits of other scripts); and
    every integer option is in the table the tests below walk."""
    found = set()
    for words, action in _options(cli.build_parser()):
        assert action.type not in (int, float), (words, action.option_strings)
        if action.type in (cli._integer, cli._seed, cli._port):
            found.add((words, action.option_strings[0]))
    listed = {(command, option) for command, _, option, _ in INTEGER_OPTIONS}
    assert found == listed


@pytest.mark.parametrize(("command", "required", "option", "value"), INTEGER_OPTIONS, ids=IDS)
def test_an_integer_option_takes_ascii_digits(
    command: tuple[str, ...], required: tuple[str, ...], option: str, value: str
) -> None:
    args = cli.build_parser().parse_args([*command, *required, option, value])
    assert getattr(args, option.lstrip("-").replace("-", "_")) == int(value)


@pytest.mark.parametrize(
    "digits",
    [
        "８７６５",  # full width: int() took it
        "٣",  # ARABIC-INDIC DIGIT THREE
        "१",  # DEVANAGARI DIGIT ONE
        "1_0",
        " 5",
        "5\n",
        "0x10",
        "",
        "9" * 5000,  # more digits than int() converts: argparse said "invalid _integer value"
    ],
    ids=[
        "full-width",
        "arabic-indic",
        "devanagari",
        "underscore",
        "space",
        "newline",
        "hex",
        "empty",
        "huge",
    ],
)
@pytest.mark.parametrize(("command", "required", "option", "value"), INTEGER_OPTIONS, ids=IDS)
def test_an_integer_option_refuses_other_digits_as_a_usage_error(
    command: tuple[str, ...],
    required: tuple[str, ...],
    option: str,
    value: str,
    digits: str,
    capsys: pytest.CaptureFixture[str],
) -> None:
    with pytest.raises(SystemExit) as done:
        cli.build_parser().parse_args([*command, *required, option, digits])
    assert done.value.code == cli.EXIT_BAD_INPUT
    err = capsys.readouterr().err
    assert f"argument {option}: expected " in err and f"found {shown(digits)}" in err, err
    assert "invalid" not in err
    if not digits.isascii():
        assert "ASCII digits 0-9" in err


def test_every_parser_takes_a_negative_number_in_exponent_form_as_a_value() -> None:
    """The top parser's and every subcommand's, new ones too: each is handctl's own."""
    parsers = [cli.build_parser()]
    while parsers:
        parser = parsers.pop()
        assert parser._negative_number_matcher is cli.NEGATIVE_NUMBER, parser.prog
        for action in parser._actions:
            if isinstance(action, argparse._SubParsersAction):
                parsers.extend(action.choices.values())


@pytest.mark.parametrize(
    ("text", "value"),
    [("-1e-3", -1e-3), ("-2.5E+2", -250.0), ("-.5e1", -5.0), ("-3.e0", -3.0), ("-7", -7.0)],
)
def test_a_negative_number_in_exponent_form_is_a_value(text: str, value: float) -> None:
    parser = cli.build_parser()
    assert parser.parse_args(["jog", "f1_j2", "--torque", text]).torque == value
    assert parser.parse_args(["analyze", "torque-set", "s.yaml", "--k", text, text]).k == [
        value,
        value,
    ]


@pytest.mark.parametrize("text", ["-e3", "-1e", "-1e-", "-x1", "--1e3"])
def test_what_is_no_number_is_still_an_option(text: str) -> None:
    with pytest.raises(SystemExit) as done:
        cli.build_parser().parse_args(["jog", "f1_j2", "--torque", text])
    assert done.value.code == cli.EXIT_BAD_INPUT


def test_a_negative_time_budget_in_exponent_form_is_refused_as_a_duration(
    capsys: pytest.CaptureFixture[str],
) -> None:
    """Through the command itself: the value reaches the check that says what is wrong with
    it, rather than argparse's "expected one argument"."""
    code = cli.main(["run", "recipe", "r.yaml", "--max-seconds", "-1e-3"])
    assert code == cli.EXIT_BAD_INPUT
    err = capsys.readouterr().err
    assert "--max-seconds" in err and "-0.001" in err and "expected one argument" not in err


@pytest.mark.parametrize("text", ["０.５", "٣", "1e\uff13", "half", ""])
def test_a_number_option_refuses_digits_of_other_scripts(
    text: str, capsys: pytest.CaptureFixture[str]
) -> None:
    """``float`` took '０.５' as 0.5, as ``int`` took '８７６５'."""
    with pytest.raises(SystemExit) as done:
        cli.build_parser().parse_args(["jog", "f1_j2", "--torque", text])
    assert done.value.code == cli.EXIT_BAD_INPUT
    err = capsys.readouterr().err
    assert f"argument --torque: expected a number (e.g. 0.5, -1e-3), found {shown(text)}" in err


def test_a_negative_infinity_reaches_the_options_own_check(
    capsys: pytest.CaptureFixture[str],
) -> None:
    """``--k -inf 0.1`` was argparse's "expected 2 arguments": the value is the option's to
    refuse, as a finite number is its to take."""
    scenario = str(ROOT / "config" / "analysis" / "planar_2f2j.yaml")
    args = ["analyze", "torque-set", scenario, "--k", "-inf", "0.1"]
    assert cli.main(args) == cli.EXIT_BAD_INPUT
    assert "--k: expected two finite ratios" in capsys.readouterr().err


@pytest.mark.parametrize(
    ("argv", "option"),
    [
        (["check", "--json", "{tmp}/t.json"], "--json"),
        (["check", "--seconds", "5"], "--seconds"),
        (["check", "--no-rt"], "--no-rt"),
        (["check", "--loop-cpu", "0"], "--loop-cpu"),
        (["check", "--timing", "--dbc", "nosuch.dbc", "--seconds", "0.1"], "--dbc"),
    ],
)
def test_an_option_of_the_other_check_is_refused(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], argv: list[str], option: str
) -> None:
    """`check --json t.json` wrote no file and `check --timing --dbc nosuch.dbc` never looked
    at it, both exit 0: an option of the check not asked for did nothing, without a word."""
    words = [w.replace("{tmp}", str(tmp_path)) for w in argv]
    assert cli.main(words) == cli.EXIT_BAD_INPUT
    assert f"{option}: expected the check it belongs to" in capsys.readouterr().err
    assert not (tmp_path / "t.json").exists()


def test_the_timing_check_refuses_a_loop_cpu_it_would_not_use(
    capsys: pytest.CaptureFixture[str],
) -> None:
    """``check --timing --loop-cpu 0 --no-rt`` ran where the scheduler put it, as if on CPU 0
    (a run refuses --loop-cpu without --rt)."""
    args = ["check", "--timing", "--seconds", "0.1", "--loop-cpu", "0", "--no-rt"]
    assert cli.main(args) == cli.EXIT_BAD_INPUT
    assert "--loop-cpu: expected no --no-rt" in capsys.readouterr().err


@pytest.mark.parametrize("settle", ["-1", "3601", "1e6"])
def test_calibrate_says_the_settle_it_takes(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], settle: str
) -> None:
    """It said 'a time in seconds >= 0' of 1e6: the bound it kept was not the one it said."""
    args = ["calibrate", "tdt", "-o", str(tmp_path / "c.yaml"), "--settle", settle]
    assert cli.main(args) == cli.EXIT_BAD_INPUT
    assert "--settle: expected a time in seconds from 0 to 3600" in capsys.readouterr().err


def test_an_object_a_few_micrometres_below_rest_reads_as_zero_not_minus_zero() -> None:
    """A one-object hand whose cylinder never left the table read "height above rest -0.0 ->
    -0.0 mm" in its replay (an outside probe): a few µm of contact sink, shown as if the
    object had sunk into the table. Rounded to zero it is "+0.0"; a tenth of a mm is kept."""
    pose = {
        "start": {"height_above_rest_m": -4e-6, "x_m": -1e-6},
        "end": {"height_above_rest_m": -1e-4, "x_m": 0.0205},
    }
    line = cli._object_line("cyl", pose)
    assert line == "  cyl: height above rest +0.0 -> -0.1 mm, x +0.0 -> +20.5 mm"
    assert "-0.0" not in cli._object_line("cyl", {"start": pose["start"], "end": pose["start"]})
