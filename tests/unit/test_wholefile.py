"""Files written whole (``handctl.wholefile``): a plot as every output, through its link, with
the umask's mode, under a name as long as the file system allows, naming no other file."""

from __future__ import annotations

import os
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # after the backend is chosen
import pytest
from matplotlib.figure import Figure

from handctl.wholefile import PictureNotWrittenError, save_picture, write_whole


def _figure() -> Figure:
    fig, ax = plt.subplots()
    ax.plot([0, 1], [0, 1])
    return fig


def test_a_new_picture_gets_the_umask_s_mode_and_an_old_one_keeps_its_own(tmp_path: Path) -> None:
    """Written beside its name and renamed, a plot kept the temporary file's 0600: a shared
    plot no one else could read."""
    fig = _figure()
    before = os.umask(0o022)
    try:
        save_picture(fig, tmp_path / "new.png")
        old = tmp_path / "old.png"
        old.write_bytes(b"old")
        old.chmod(0o640)
        save_picture(fig, old)
    finally:
        os.umask(before)
    assert (tmp_path / "new.png").stat().st_mode & 0o777 == 0o644
    assert old.stat().st_mode & 0o777 == 0o640
    assert old.read_bytes().startswith(b"\x89PNG")


def test_a_link_is_written_through_not_replaced(tmp_path: Path) -> None:
    (tmp_path / "shared").mkdir()
    real = tmp_path / "shared" / "real.png"
    real.write_bytes(b"old")
    link = tmp_path / "link.png"
    link.symlink_to(Path("shared") / "real.png")
    save_picture(_figure(), link)
    assert link.is_symlink()
    assert real.read_bytes().startswith(b"\x89PNG")


def test_a_name_as_long_as_the_file_system_allows_is_written(tmp_path: Path) -> None:
    """The file beside it was named after it, 14 characters longer: past NAME_MAX."""
    longest = os.pathconf(tmp_path, "PC_NAME_MAX")
    name = "p" * (longest - len(".png")) + ".png"
    save_picture(_figure(), tmp_path / name)
    write_whole(tmp_path / ("j" * (longest - len(".json")) + ".json"), b"{}\n")
    assert sorted(len(p.name) for p in tmp_path.iterdir()) == [longest, longest]


def test_a_picture_names_no_temporary_file(tmp_path: Path) -> None:
    """Drawn to the file beside it, an .svgz recorded that file's name in its gzip header
    (``gunzip -N`` restored it under it) and an .eps its title."""
    fig = _figure()
    save_picture(fig, tmp_path / "fig.svgz")
    save_picture(fig, tmp_path / "fig.eps")
    header = (tmp_path / "fig.svgz").read_bytes()[:10]
    assert header[:2] == b"\x1f\x8b" and not header[3] & 0x08  # no FNAME field
    assert b".tmp" not in (tmp_path / "fig.eps").read_bytes()
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []


def test_a_picture_that_cannot_be_written_names_itself_and_leaves_nothing(tmp_path: Path) -> None:
    gone = tmp_path / "gone" / "p.png"
    with pytest.raises(PictureNotWrittenError) as caught:
        save_picture(_figure(), gone)
    assert caught.value.why == "No such file or directory"
    assert str(caught.value) == f"{gone}: no plot written (No such file or directory)"
