"""An empty file name on the command line is refused naming its option: argparse made it the
directory '.', said as "found .: not a file" under another name, or taken for no option."""

from __future__ import annotations

import argparse
from collections.abc import Iterator
from pathlib import Path

import pytest

from handctl import cli

from ..conftest import ROOT

RECIPE = str(ROOT / "config" / "recipes" / "swap_two_cylinders.yaml")
LOG = "run.mcap"


def _actions(parser: argparse.ArgumentParser) -> Iterator[argparse.Action]:
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for command in dict.fromkeys(action.choices.values()):
                yield from _actions(command)
        else:
            yield action


def test_every_file_name_argument_takes_an_empty_name_as_its_option_s() -> None:
    """Every argument of every command that is a file name: none is left a bare Path, which
    would make '' the directory '.'."""
    parser = cli.build_parser()
    assert not [a.dest for a in _actions(parser) if a.type is Path]
    named = [a for a in _actions(parser) if getattr(a.type, "__name__", "") == "convert"]
    assert len(named) >= 19


@pytest.mark.parametrize(
    ("argv", "option"),
    [
        (["check", ""], "HAND.yaml"),
        (["run", "recipe", ""], "RECIPE.yaml"),
        (["run", "recipe", RECIPE, "--hand", ""], "--hand"),
        (["run", "recipe", RECIPE, "--sim-faults", ""], "--sim-faults"),
        (["replay", ""], "RUN.mcap"),
        (["replay", LOG, "--to-bus", ""], "--to-bus"),
        (["replay", LOG, "--export", "candump", ""], "--export"),
    ],
)
def test_an_empty_file_name_is_refused_naming_its_option(
    argv: list[str], option: str, capsys: pytest.CaptureFixture[str]
) -> None:
    assert cli.main(argv) == cli.EXIT_BAD_INPUT
    err = capsys.readouterr().err
    assert err.startswith(f"handctl: error: {option}: ") and ": expected a " in err
    assert err.rstrip().endswith("found ''")


def test_plots_interrupted_leave_no_directory_they_made(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Ctrl-C while a plan's plots were drawn left an empty ``--plot`` tree (``a/b/plots``)
    behind (an outside probe). The directories made for them go with the interrupt; one that
    was there before stays."""
    from handctl.experiment import plot

    def interrupted(result: object, directory: Path) -> list[Path]:
        (directory / "01_lift.png").write_bytes(b"half drawn")
        raise KeyboardInterrupt

    monkeypatch.setattr(plot, "plot_plan", interrupted)
    there = tmp_path / "there"
    there.mkdir()
    with pytest.raises(KeyboardInterrupt):
        cli._plan_plots(object(), there / "a" / "b" / "plots")
    assert list(there.iterdir()) == []  # a, b and plots gone; there kept
