"""handctl leaves MuJoCo's OpenGL alone: ``import mujoco`` under the command loads no GLFW (whose
library probe is a child process that a Ctrl-C during the import would leave behind), whatever
the environment asks for: handctl renders nothing with it, and a renderer it cannot load broke
the import."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

from ..conftest import ROOT

#: Runs the command (its help), then imports MuJoCo as the simulated hand does, and says
#: what it found.
SCRIPT = """
import os, sys
from handctl.cli import main
try:
    main(["--help"])
except SystemExit:
    pass
import mujoco
print(os.environ.get("MUJOCO_GL"), "glfw" in sys.modules)
"""


def _run(env: dict[str, str]) -> list[str]:
    done = subprocess.run(
        [sys.executable, "-c", SCRIPT],
        check=False,
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.returncode == 0, done.stderr
    return done.stdout.splitlines()[-1].split()


def test_the_command_imports_mujoco_without_its_opengl() -> None:
    env = {k: v for k, v in os.environ.items() if k != "MUJOCO_GL"}
    assert _run(env) == ["disable", "False"]


@pytest.mark.parametrize("chosen", ["glfw", "osmesa", "bogus"])
def test_a_renderer_in_the_environment_is_not_loaded(chosen: str) -> None:
    """``MUJOCO_GL=osmesa`` without its library was an AttributeError, and a value MuJoCo
    does not know a RuntimeError, a traceback in every command that builds the simulated
    hand."""
    assert _run({**os.environ, "MUJOCO_GL": chosen}) == ["disable", "False"]


def test_importing_handctl_leaves_a_programs_mujoco_rendering_alone() -> None:
    """A program that imports handctl as a library and renders with MuJoCo itself: the
    import turned MuJoCo's OpenGL off for its whole process, and its renderer failed (found
    by an outside audit). The command line and the Dask workers turn it off; the import
    does not."""
    done = subprocess.run(
        [sys.executable, "-c", "import os, handctl.cli; print(os.environ['MUJOCO_GL'])"],
        env={**os.environ, "MUJOCO_GL": "egl"},
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == "egl"
