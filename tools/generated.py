"""What the generators share: repository-relative names, and ``--check`` against the files
on disk.

Generated files are committed (firmware authors and readers of the docs need them without
running Python), so each generator has a ``--check`` mode that tests run: it must agree with
what the generator would write, byte for byte but for line endings.
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any

from handctl.protocol import Protocol, load_protocol

ROOT = Path(__file__).resolve().parent.parent
DEFAULT_DBC = ROOT / "firmware_protocol" / "handctl.dbc"


def display_path(path: Path) -> str:
    """Repository-relative, so generated text never depends on where the checkout lives."""
    try:
        return path.resolve().relative_to(ROOT).as_posix()
    except ValueError:
        return path.name


def read_protocol(dbc: Path, hand: Path | None) -> tuple[Protocol, Any, str, str]:
    """What a generator generates from: the protocol of the hand config ``hand`` (``--hand``,
    the DBC generated for it) or of the DBC file ``dbc``; with its cantools database, its name
    in the generated text and the options that redo it (empty for the packaged DBC)."""
    import cantools

    if hand is not None:
        from handctl.config import load_hand
        from handctl.hand_protocol import generated_protocol

        protocol = generated_protocol(load_hand(hand))
        name = f"the DBC generated for {display_path(hand)}"
        option = f" --hand {display_path(hand)}"
    else:
        protocol = load_protocol(dbc)
        name = display_path(dbc)
        option = "" if dbc.resolve() == DEFAULT_DBC.resolve() else f" --dbc {name}"
    db = cantools.database.load_string(protocol.text, database_format="dbc", strict=True)
    return protocol, db, name, option


def write_or_check(
    tool: str, files: dict[Path, str], source: str, command: str, check: bool
) -> int:
    """Write ``files`` (path -> text), or with ``check`` write nothing and return 1 when one
    on disk differs from its text, naming it, what it is generated from and how to redo it."""
    if check:
        stale = [
            path
            for path, text in files.items()
            if not path.exists() or path.read_text(encoding="utf-8").replace("\r\n", "\n") != text
        ]
        for path in stale:
            print(
                f"{tool}: {display_path(path)} is not what {source} generates; run: {command}",
                file=sys.stderr,
            )
        return 1 if stale else 0
    from handctl.errors import ConfigError
    from handctl.outfile import check_writable

    for path, text in files.items():
        # a directory or a device given as --out was an IsADirectoryError traceback; a file
        # where its directory should be, a FileExistsError: each is said, exit 2
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            check_writable(path, "--out")
            path.write_text(text, encoding="utf-8", newline="\n")
        except ConfigError as exc:
            print(f"{tool}: {exc}", file=sys.stderr)
            return 2
        except OSError as exc:
            print(
                f"{tool}: --out: {display_path(path)} could not be written ({exc})", file=sys.stderr
            )
            return 2
    return 0
