"""The files a command is told to write, asked about before the work begins: a name that does
not resolve to a place for a file is bad input naming the option, never an exception."""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import pytest

from handctl.errors import ConfigError
from handctl.outfile import check_log_target, check_writable, refuse_same_files
from handctl.recording.reader import MAGIC

from ..conftest import ROOT


def test_a_symlink_loop_is_bad_input_naming_the_option(tmp_path: Path) -> None:
    (tmp_path / "a").symlink_to(tmp_path / "b")
    (tmp_path / "b").symlink_to(tmp_path / "a")
    with pytest.raises(ConfigError, match=r"--json: expected a file name that resolves"):
        check_writable(tmp_path / "a", "--json")


def test_a_file_in_a_writable_directory_is_its_resolved_self(tmp_path: Path) -> None:
    (tmp_path / "link").symlink_to(tmp_path / "real.yaml")
    assert check_writable(tmp_path / "link", "-o") == tmp_path / "real.yaml"


def test_a_fifo_or_a_device_is_not_a_file_to_write(tmp_path: Path) -> None:
    """A FIFO blocked a run in open() for good (Ctrl-C unheard); a device lost the log."""
    fifo = tmp_path / "log.mcap"
    os.mkfifo(fifo)
    for path in (fifo, Path(os.devnull)):
        with pytest.raises(ConfigError, match=r"--log: expected a regular file"):
            check_writable(path, "--log")


def test_an_output_that_is_an_input_or_another_output_is_refused(tmp_path: Path) -> None:
    recipe = tmp_path / "recipe.yaml"
    recipe.write_text("name: x\n")
    (tmp_path / "alias.yaml").symlink_to(recipe)
    os.link(recipe, tmp_path / "hard.yaml")
    inputs = {"the recipe": recipe, "--dbc": None}
    for same in (recipe, tmp_path / "alias.yaml", tmp_path / "hard.yaml"):
        with pytest.raises(ConfigError, match=r"--log: expected another file than the recipe's"):
            refuse_same_files({"--log": same}, inputs)
    new = tmp_path / "sub" / ".." / "run.mcap"  # not there yet: compared by name
    with pytest.raises(ConfigError, match=r"--summary-json: expected another file than --log's"):
        refuse_same_files({"--log": tmp_path / "run.mcap", "--summary-json": new}, inputs)
    refuse_same_files({"--log": tmp_path / "run.mcap", "--plot": None}, inputs)


def test_run_refuses_a_log_over_its_own_recipe_before_any_work(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """It replaced the recipe with MCAP data and exited 0."""
    from handctl import cli

    recipe = tmp_path / "recipe.yaml"
    shutil.copy(ROOT / "config" / "recipes" / "swap_two_cylinders.yaml", recipe)
    before = recipe.read_bytes()
    args = ["run", "recipe", str(recipe), "--log", str(recipe)]
    assert cli.main(args) == cli.EXIT_BAD_INPUT
    assert "--log: expected another file than the recipe's" in capsys.readouterr().err
    assert recipe.read_bytes() == before


def test_a_long_path_is_named_whole(tmp_path: Path) -> None:
    """Values in messages are cut at 80 characters; a file's name is what the user must find
    again, so it is not."""
    deep = tmp_path.joinpath(*["a_directory_that_is_not_there"] * 6, "run.mcap")
    with pytest.raises(ConfigError) as info:
        check_writable(deep, "--log")
    assert f"found '{deep}'" in str(info.value) and len(str(deep)) > 160


@pytest.mark.parametrize(
    "command, victim, says",
    [
        (["replay", "{f}", "--export", "candump", "{f}"], "run.mcap", "--export"),
        (["replay", "{f}", "--json", "{f}"], "run.mcap", "--json"),
        (["calibrate", "tdt", "--dbc", "{f}", "-o", "{f}"], "hand.dbc", "-o"),
        (
            ["calibrate", "tdt", "--dbc", "{f}", "-o", "x.yaml", "--json", "{f}"],
            "hand.dbc",
            "--json",
        ),
        (["check", "--timing", "{f}", "--json", "{f}"], "hand.yaml", "--json"),
        (["analyze", "torque-set", "{f}", "--k", "1", "1", "--json", "{f}"], "s.yaml", "--json"),
    ],
    ids=[
        "replay-export",
        "replay-json",
        "calibrate-o-dbc",
        "calibrate-json-dbc",
        "check",
        "analyze",
    ],
)
def test_no_command_writes_over_what_it_reads(
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    command: list[str],
    victim: str,
    says: str,
) -> None:
    """Each replaced its input (a recording emptied by an export, a DBC or a hand config
    overwritten by a summary) and exited 0; refused before any work now, the file as it was."""
    from handctl import cli

    path = tmp_path / victim
    path.write_bytes(b"what the user keeps\n")
    args = [a.replace("{f}", str(path)) for a in command]
    assert cli.main([a if a != "x.yaml" else str(tmp_path / a) for a in args]) == 2
    assert f"{says}: expected another file than " in capsys.readouterr().err
    assert path.read_bytes() == b"what the user keeps\n"


@pytest.mark.parametrize("option", ["--log", "--summary-json", "--plot"])
def test_an_output_named_as_a_directory_is_bad_input(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], option: str
) -> None:
    """``Path`` drops a trailing separator: --log y.mcap/ wrote, or replaced, y.mcap."""
    from handctl import cli

    kept = tmp_path / "y.mcap"
    kept.write_bytes(b"an earlier run\n")
    recipe = str(ROOT / "config" / "recipes" / "swap_two_cylinders.yaml")
    with pytest.raises(SystemExit) as stop:
        cli.main(["run", "recipe", recipe, option, f"{kept}/"])
    assert stop.value.code == cli.EXIT_BAD_INPUT
    assert f"argument {option}: expected a file name, found '{kept}/' (a directory's)" in (
        capsys.readouterr().err
    )
    assert kept.read_bytes() == b"an earlier run\n"


@pytest.mark.parametrize(("name", "why"), [("-", "standard output is not"), ("", "an empty")])
def test_an_output_named_dash_or_nothing_is_bad_input(
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
    name: str,
    why: str,
) -> None:
    """``--json -`` wrote a file named '-' where standard output was meant, and ``--json ''``
    was said as '.'."""
    from handctl import cli

    monkeypatch.chdir(tmp_path)
    with pytest.raises(SystemExit) as stop:
        cli.main(["check", "--timing", "--seconds", "0.1", "--json", name])
    assert stop.value.code == cli.EXIT_BAD_INPUT
    err = capsys.readouterr().err
    assert f"argument --json: expected a file name, found {name!r} ({why}" in err
    assert list(tmp_path.iterdir()) == []


def test_a_recording_replaces_only_a_recording_or_nothing(tmp_path: Path) -> None:
    """A hand config given as --log, or reached through a symlink named like a log, was
    replaced by MCAP data; a log over a log (the same run again) is said, not refused."""
    assert check_log_target(tmp_path / "new.mcap", "--log") is False
    (tmp_path / "empty.mcap").touch()
    assert check_log_target(tmp_path / "empty.mcap", "--log") is False
    old = tmp_path / "old.mcap"
    old.write_bytes(MAGIC + b"rest of a recording")
    assert check_log_target(old, "--log") is True
    hand = tmp_path / "hand.yaml"
    shutil.copy(ROOT / "config" / "hands" / "hiroshima_hand.yaml", hand)
    link = tmp_path / "run.mcap"
    link.symlink_to(hand)
    for given in (hand, link):
        with pytest.raises(ConfigError) as info:
            check_log_target(given, "--log")
        assert str(info.value).startswith("--log: expected a new file, or a recording (MCAP)")
    assert hand.read_bytes() == (ROOT / "config" / "hands" / "hiroshima_hand.yaml").read_bytes()


def test_no_other_output_replaces_a_recording(tmp_path: Path) -> None:
    """calibrate -o, plan -o, a summary or an export given a run's log by a slip replaced it
    (a 2 MB log by a 7.8 kB hand config), exit 0; only a recording may replace a recording."""
    log = tmp_path / "run.mcap"
    log.write_bytes(MAGIC + b"a run's recording")
    with pytest.raises(ConfigError) as info:
        check_writable(log, "-o")
    assert str(info.value).startswith("-o: expected a file that is not a run's recording")
    assert check_writable(log, "--log", recording=True) == log.resolve()
    assert log.read_bytes() == MAGIC + b"a run's recording"


@pytest.mark.parametrize(
    "command",
    [
        ["check", "--timing", "--seconds", "0.1", "--json", "{f}"],
        ["run", "recipe", "config/recipes/swap_two_cylinders.yaml", "--summary-json", "{f}"],
        ["calibrate", "tdt", "-o", "{o}", "--json", "{f}"],
        [
            "analyze",
            "torque-set",
            "config/analysis/paper_fig3.yaml",
            "--k",
            "1",
            "1",
            "--json",
            "{f}",
        ],
    ],
)
def test_a_json_output_replaces_only_json(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], command: list[str]
) -> None:
    """A summary or a report written over another hand's config or a recipe replaced it,
    exit 0 (only recordings were kept from it). Refused before any work; an earlier JSON
    output, or an empty file, is written again."""
    from handctl import cli

    victim = tmp_path / "other_hand.yaml"
    shutil.copy(ROOT / "config" / "hands" / "planar_2f2j.yaml", victim)
    before = victim.read_text()
    args = [a.format(f=victim, o=tmp_path / "cal.yaml") for a in command]
    assert cli.main(args) == cli.EXIT_BAD_INPUT
    err = capsys.readouterr().err
    assert "expected a new file, or an earlier JSON output to write again" in err
    assert "an existing file that is not JSON" in err
    assert victim.read_text() == before and not (tmp_path / "cal.yaml").exists()
    earlier = tmp_path / "earlier.json"
    for text in ('{"outcome": "done"}\n', ""):
        earlier.write_text(text)
        check_writable(earlier, "--json", json_output=True)


def test_a_plan_replaces_only_a_recipe(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """``plan -o`` over a copy of a hand config, another template or notes replaced it with
    the recipe, exit 0. Refused before any work; a recipe there is planned again."""
    from handctl import cli

    template = ROOT / "config" / "recipes" / "swap_two_cylinders.template.yaml"
    hand = tmp_path / "hand.yaml"
    shutil.copy(ROOT / "config" / "hands" / "planar_2f2j.yaml", hand)
    other = tmp_path / "other.template.yaml"
    shutil.copy(template, other)
    notes = tmp_path / "notes.txt"
    notes.write_text("what I keep\n")
    for victim in (hand, other, notes):
        before = victim.read_bytes()
        assert cli.main(["plan", str(template), "-o", str(victim)]) == cli.EXIT_BAD_INPUT
        assert "-o: expected a new file, or a recipe to write again" in capsys.readouterr().err
        assert victim.read_bytes() == before
    from handctl.cli import _refuse_other_than_a_recipe

    _refuse_other_than_a_recipe(ROOT / "config" / "recipes" / "swap_two_cylinders.yaml")
    _refuse_other_than_a_recipe(tmp_path / "new.yaml")
    # a recipe written by hand (a bring-up hold recipe) is the user's, not a plan's to write
    # again: it was replaced, warned of as "for another hand (None)"
    hold = tmp_path / "hold.yaml"
    hold.write_text(
        "recipe: hold\nphases:\n  - {name: hold, torques: [0, 0, 0, 0, 0, 0, 0, 0, 0], "
        "ramp_s: 0.2, max_s: 1.0}\n"
    )
    before = hold.read_bytes()
    assert cli.main(["plan", str(template), "-o", str(hold)]) == cli.EXIT_BAD_INPUT
    err = capsys.readouterr().err
    assert "(a recipe written by hand, without compiled: true, is not replaced: give " in err
    assert f"found recipe hold, written by hand, in {hold}" in err
    assert hold.read_bytes() == before


def test_a_plan_s_refused_output_or_base_is_named_whole(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """``-o`` over a file that is no recipe, or one written by hand, and a ``--base`` that is
    no file were said with the path cut to 80 characters: in a project's tree the file's
    name, the part that tells which, was the part left out (found by an outside audit)."""
    from handctl import cli

    template = str(ROOT / "config" / "recipes" / "planar_lift_turn.template.yaml")
    planar = str(ROOT / "config" / "hands" / "planar_2f2j.yaml")
    deep = tmp_path / ("a_rather_long_directory_name_for_recipes" * 2) / "and_another_level"
    deep.mkdir(parents=True)
    notes = deep / "notes_kept_by_the_team.yaml"
    notes.write_text("what: I keep\n")
    hold = deep / "hold_written_by_hand.yaml"
    hold.write_text(
        "recipe: hold\nphases:\n  - {name: hold, torques: [0, 0, 0, 0], ramp_s: 0.2, max_s: 1.0}\n"
    )
    for victim, found in (
        (notes, f"found {notes}, an existing file that is not a recipe"),
        (hold, f"found recipe hold, written by hand, in {hold}"),
    ):
        assert len(str(victim)) > 80
        code = cli.main(["plan", template, "--hand", planar, "-o", str(victim)])
        assert code == cli.EXIT_BAD_INPUT
        assert found in capsys.readouterr().err
    missing = deep / "the_base_recipe_planned_last_week.yaml"
    out = str(tmp_path / "r.yaml")
    args = ["--hand", planar, "-o", out, "--from", "manipulate", "--base", str(missing)]
    assert cli.main(["plan", template, *args]) == cli.EXIT_BAD_INPUT
    assert f"--base: expected a compiled recipe file, found '{missing}'" in (
        capsys.readouterr().err
    )


def test_a_file_name_too_long_names_the_option(tmp_path: Path) -> None:
    """Said with the file's name alone ("File name too long"), no option, once the work had
    been set up."""
    with pytest.raises(ConfigError) as err:
        check_writable(tmp_path / ("a" * 300 + ".mcap"), "--log", recording=True)
    assert err.value.file == "--log"
    assert "a file name the system takes (File name too long)" in str(err.value)


def test_an_existing_json_output_too_deep_or_too_large_is_bad_input(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """JSON nested 200000 deep at a JSON output was a RecursionError from the check (a
    traceback, exit 1), and a file there was read whole however large (found by an outside
    audit). Neither is an output handctl writes: refused, and left as it was."""
    from handctl import cli
    from handctl.outfile import EXISTING_JSON_BYTES

    deep = tmp_path / "deep.json"
    deep.write_text("[" * 200_000 + "]" * 200_000)
    large = tmp_path / "large.json"
    large.write_text("[" + "0," * (EXISTING_JSON_BYTES // 2) + "0]")
    for victim, says in ((deep, "nested deeper"), (large, f"more than {EXISTING_JSON_BYTES}")):
        before = victim.read_bytes()
        with pytest.raises(ConfigError) as info:
            check_writable(victim, "--json", json_output=True)
        assert f"{victim}: an existing file that is not JSON handctl writes ({says}" in str(
            info.value
        )
        hand = str(ROOT / "config" / "hands" / "planar_2f2j.yaml")
        assert cli.main(["layout", hand, "-o", str(victim)]) == cli.EXIT_BAD_INPUT
        assert "-o: expected a new file, or an earlier JSON output" in capsys.readouterr().err
        assert victim.read_bytes() == before
