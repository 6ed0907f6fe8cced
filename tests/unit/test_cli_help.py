"""Every subcommand's help, new ones included: examples at the end, units on quantities,
placeholders that say what a file is."""

from __future__ import annotations

import argparse
import re
from collections.abc import Iterator
from pathlib import Path

import pytest

from handctl.cli import build_parser

#: A quantity's unit in brackets, e.g. ``[s]``, ``[N·m per N·m, dimensionless]``.
UNIT = re.compile(r"\[[^\]]+\]")
#: A file placeholder: NAME.ext (``RUN.mcap``, ``OUT.png``, ``HAND.yaml``) or DIR.
FILE_PLACEHOLDER = re.compile(r"^([A-Z]+\.[a-z]+|DIR)$")


def commands(
    parser: argparse.ArgumentParser, path: str = "handctl"
) -> Iterator[tuple[str, argparse.ArgumentParser]]:
    """Every parser below ``parser`` (itself excluded), with its command line."""
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, child in action.choices.items():
                yield f"{path} {name}", child
                yield from commands(child, f"{path} {name}")


ALL = list(commands(build_parser()))


def test_the_walk_finds_the_commands() -> None:
    names = {path for path, _ in ALL}
    assert {
        "handctl check",
        "handctl run recipe",
        "handctl analyze torque-set",
        "handctl replay",
        "handctl sim",
        "handctl plan",
    } <= names


@pytest.mark.parametrize(("path", "parser"), ALL, ids=[p for p, _ in ALL])
def test_help_ends_with_examples_of_this_command(
    path: str, parser: argparse.ArgumentParser
) -> None:
    text = parser.format_help()
    assert "\nexamples:\n" in text, path
    examples = text.rsplit("\nexamples:\n", 1)[1].strip().splitlines()
    assert 1 <= len(examples) <= 3, examples
    for line in examples:
        assert line.strip().startswith(path), (path, line)


@pytest.mark.parametrize(("path", "parser"), ALL, ids=[p for p, _ in ALL])
def test_every_quantity_has_a_unit(path: str, parser: argparse.ArgumentParser) -> None:
    for action in parser._actions:
        if action.type is float:
            assert action.help and UNIT.search(action.help), (path, action.option_strings)


@pytest.mark.parametrize(("path", "parser"), ALL, ids=[p for p, _ in ALL])
def test_file_arguments_have_placeholders_that_say_what_the_file_is(
    path: str, parser: argparse.ArgumentParser
) -> None:
    for action in parser._actions:
        if action.type is Path:
            assert isinstance(action.metavar, str), (path, action.dest)
            assert FILE_PLACEHOLDER.match(action.metavar), (path, action.dest, action.metavar)


def test_an_option_is_taken_only_in_full_and_a_slip_is_said_with_the_command_s_usage(
    capsys: pytest.CaptureFixture[str],
) -> None:
    """``--acc`` ran as ``--accept-missed-deadlines`` (a switch a controller of a real hand
    should take only spelled out), and a mistyped option was said with the top-level usage
    (``usage: handctl [-h] [--version] COMMAND ...``), no hint."""
    recipe = "config/recipes/swap_two_cylinders.yaml"
    for args, said in [
        (
            ["run", "recipe", recipe, "--acc"],
            "--acc (did you mean --accept-missed-deadlines? options are taken only in full)",
        ),
        (["jog", "f1_j1", "--torque", "0.1", "--rec"], "--rec (did you mean --recover?"),
        (
            ["run", "recipe", recipe, "--summay-json", "x.json"],
            "--summay-json (did you mean --summary-json?) x.json",
        ),
    ]:
        with pytest.raises(SystemExit) as info:
            build_parser().parse_args(args)
        assert info.value.code == 2
        err = capsys.readouterr().err
        assert f"unrecognized arguments: {said}" in err, err
        assert err.startswith(f"usage: handctl {args[0]}"), err


def test_a_success_that_asked_no_turn_does_not_say_it_turned_zero_degrees() -> None:
    """A one-object recipe asks no turn: 'at least 0 deg turned' said a criterion there was
    not."""
    from handctl.cli import _experiment_verdict

    held = {"success": True, "lifted": True, "dropped": False, "held_s": 2.0}
    assert _experiment_verdict({**held, "min_total_turn_deg": 0.0}) == (
        "success (lifted, held, nothing dropped)"
    )
    assert _experiment_verdict({**held, "min_total_turn_deg": 170.0}) == (
        "success (lifted, held, nothing dropped, at least 170 deg turned)"
    )


@pytest.mark.parametrize(
    ("outcome", "said"),
    [
        ("safety_stop", "the run ended in a safety stop, before its end"),
        ("interrupted", "the run was interrupted before its end"),
        ("startup_failed", "the run never started"),
    ],
)
def test_an_experiment_whose_run_was_stopped_says_how_in_words(outcome: str, said: str) -> None:
    """An interrupted run's experiment said "the run ended in interrupted, not at its end":
    the outcome's name pasted into one sentence for all. Every outcome but the two a run
    ends as asked in has words of its own."""
    from handctl.cli import _experiment_verdict
    from handctl.experiment.merit import ENDED_AS_ASKED
    from handctl.online.loop import Outcome

    assert {o.value for o in Outcome} - set(ENDED_AS_ASKED) == {
        "safety_stop",
        "interrupted",
        "startup_failed",
    }
    held = {"success": False, "lifted": True, "dropped": False, "held_s": 2.0}
    verdict = _experiment_verdict({**held, "min_total_turn_deg": 0.0, "stopped": outcome})
    assert verdict == f"FAILED: {said}"


def test_an_option_of_one_value_given_twice_with_two_values_is_refused(
    capsys: pytest.CaptureFixture[str],
) -> None:
    """argparse kept the last without a word: ``--bus sim ... --bus socketcan:can0`` drove
    the last one named, ``--max-seconds 5 ... --max-seconds 50`` ran ten times the first."""
    recipe = "config/recipes/swap_two_cylinders.yaml"
    for args, said in [
        (
            ["run", "recipe", recipe, "--bus", "sim", "--bus", "socketcan:can0"],
            "argument --bus: given twice, as 'sim' and then 'socketcan:can0': give it once",
        ),
        (
            ["run", "recipe", recipe, "--max-seconds", "5", "--max-seconds=50"],
            "argument --max-seconds: given twice, as '5.0' and then '50.0': give it once",
        ),
        (
            ["jog", "f1_j1", "--torque", "0.1", "--torque", "-0.1"],
            "argument --torque: given twice, as '0.1' and then '-0.1'",
        ),
        (
            ["analyze", "torque-set", "s.yaml", "--k", "1", "2", "--k", "1", "3"],
            "argument --k: given twice, as '1.0' '2.0' and then '1.0' '3.0'",
        ),
    ]:
        with pytest.raises(SystemExit) as info:
            build_parser().parse_args(args)
        assert info.value.code == 2
        err = capsys.readouterr().err
        assert said in err, err
        assert err.startswith(f"usage: handctl {args[0]}"), err
    # the same value twice is one option; every command's options, each twice
    parsed = build_parser().parse_args(
        ["run", "recipe", recipe, "--bus", "sim", "--max-seconds", "5", "--bus", "sim"]
    )
    assert (parsed.bus, parsed.max_seconds) == ("sim", 5.0)
    for path, parser in ALL:
        for action in parser._actions:
            if action.option_strings and isinstance(action, argparse._StoreAction):
                assert type(action).__name__ == "_StoreOnce", (path, action.option_strings)


def test_an_optional_value_left_out_is_said_as_left_out_when_given_twice(
    capsys: pytest.CaptureFixture[str],
) -> None:
    """``--live --live 8788`` was "given twice, as '8765' and then '8788'", a value the user
    never typed (found by an outside audit): the first is ``--live`` alone, its default."""
    for args, said in [
        (
            ["replay", "run.mcap", "--live", "--live", "8788"],
            "given twice, as --live alone (its default, 8765) and then '8788': give it once",
        ),
        (
            ["replay", "run.mcap", "--live", "8788", "--live"],
            "given twice, as '8788' and then --live alone (its default, 8765): give it once",
        ),
    ]:
        with pytest.raises(SystemExit) as info:
            build_parser().parse_args(args)
        assert info.value.code == 2
        assert said in capsys.readouterr().err
    # the port typed as the default is the default: one option, and a later parse says what
    # it was given, not what an earlier one was
    parsed = build_parser().parse_args(["replay", "run.mcap", "--live", "8765", "--live"])
    assert parsed.live == 8765
    with pytest.raises(SystemExit):
        build_parser().parse_args(["replay", "run.mcap", "--live", "8765", "--live", "8788"])
    assert "given twice, as '8765' and then '8788'" in capsys.readouterr().err


@pytest.mark.parametrize("command", [["replay"], ["run", "recipe"]])
def test_a_file_taken_as_the_live_port_says_to_put_live_after_it(
    command: list[str], capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    """``handctl replay --live base.mcap``: the optional port took the file, and the error
    said to reach the view through an SSH tunnel, for the dot in the name (found by an
    outside audit). A name that ends as a log or a config does, or names a file, is said as
    a file taken as the port."""
    existing = tmp_path / "recipe.txt"
    existing.write_text("")
    for name in ("base.mcap", "swap.yaml", "hand.yml", str(existing)):
        with pytest.raises(SystemExit) as info:
            build_parser().parse_args([*command, "--live", name])
        assert info.value.code == 2
        err = capsys.readouterr().err
        assert "put --live after the file, or give the port as --live=PORT" in err, err
        assert "SSH tunnel" not in err
    with pytest.raises(SystemExit):  # an address is still said as one
        build_parser().parse_args([*command, "--live", "0.0.0.0:8765"])
    err = capsys.readouterr().err
    assert "SSH tunnel" in err and "after the file" not in err


def test_to_bus_sends_the_node_frames_by_default_only_on_a_bus_of_this_machine(
    capsys: pytest.CaptureFixture[str],
) -> None:
    """On a real bus the nodes send their own Feedback, Status and Heartbeat: the logged
    copies went out beside them under the same identifiers by default (both directions),
    bit errors on CAN (found by an outside audit)."""
    from handctl.cli import _to_bus_direction

    assert _to_bus_direction("virtual:x") == "both"
    assert _to_bus_direction("unix:/tmp/hand") == "both"
    assert capsys.readouterr().err == ""
    for spec in ("socketcan:can0", "hand", "pcan:PCAN_USBBUS1"):
        assert _to_bus_direction(spec) == "tx"
        assert "to-bus: the host's frames only (--direction tx" in capsys.readouterr().err
