"""How the suite's tests are shared between pytest-xdist's workers (``-n 2`` in pyproject.toml).

A work unit is a whole test module, as xdist's ``--dist loadscope`` makes it: many modules set
up one costly thing for all their tests (a run of a recipe, a fault campaign, a recording), and
a module split between two workers would set it up on both. Tests marked
``xdist_group(NAME)`` leave their modules and form one unit of their own, run on one worker one
after another: the real-time tests (``tests/integration/realtime.py``), so that no two of them
compete for the CPUs, and the readers of the session's run of the default recipe, so that it
runs once."""

from __future__ import annotations

from xdist.scheduler import LoadScopeScheduling


class ModuleOrGroupScheduling(LoadScopeScheduling):  # type: ignore[misc]  # xdist is untyped
    """``--dist loadscope`` with ``--dist loadgroup``'s groups: xdist appends ``@NAME`` to
    the node id of a test marked ``xdist_group(NAME)`` when it runs with ``--dist
    loadgroup``."""

    def _split_scope(self, nodeid: str) -> str:
        # "@" after the last "]": a parameter's id may itself hold an "@"
        if nodeid.rfind("@") > nodeid.rfind("]"):
            return nodeid.rsplit("@", 1)[1]
        return str(super()._split_scope(nodeid))
