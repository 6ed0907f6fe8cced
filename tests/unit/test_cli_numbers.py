"""Numbers on the command line: what every integer option takes, through the real parser."""

from __future__ import annotations

import argparse
from collections.abc import Iterator

import pytest

from handctl import cli
from handctl.errors import shown

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


def test_no_option_is_parsed_by_int_itself() -> None:
    """A new integer option uses the shared type (``cli._integer``), not ``int``, which takes
    what no user types as a number; and every one is in the table the tests below walk."""
    found = set()
    for words, action in _options(cli.build_parser()):
        assert action.type is not int, (words, action.option_strings)
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
