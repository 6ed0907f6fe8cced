"""The lock a run holds on its log's file, one place for the recorder that holds it and for
the option check that asks, before the run, whether another run holds it; and the name of
the recording a run writes beside its log until it begins, for the recorder that writes
and clears them and the reader that points at one."""

from __future__ import annotations

import fcntl
import glob
from pathlib import Path

from handctl.errors import ConfigError


def lock_log(fd: int, path: Path) -> None:
    """A run's lock on its log's file (``fd``, at ``path``): another run's is bad input. The
    recorder holds it for the run; ``check_log_target`` takes it a moment to ask."""
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        raise ConfigError(
            str(path),
            "",
            "a log no other run is writing (give this run another --log)",
            "another process writing it now (it holds the file's lock)",
        ) from None
    except OSError:
        pass  # no locks on this file system: recorded unlocked


#: The end of the name of the recording a run writes beside its log's path until it begins
#: (``.NAME.PID.handctl-partial``).
PARTIAL_SUFFIX = ".handctl-partial"


def partials_beside(path: Path) -> list[Path]:
    """The recordings runs on the log ``path`` wrote beside it (``PARTIAL_SUFFIX``)."""
    return list(path.parent.glob(f".{glob.escape(path.name)}.*{PARTIAL_SUFFIX}"))
