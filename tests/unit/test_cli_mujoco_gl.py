"""handctl leaves MuJoCo's OpenGL alone: ``import mujoco`` under the command loads no GLFW (whose
library probe is a child process that a Ctrl-C during the import would leave behind), unless
the user chose a renderer."""

from __future__ import annotations

import os
import subprocess
import sys

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


def test_a_renderer_the_user_chose_is_kept() -> None:
    assert _run({**os.environ, "MUJOCO_GL": "glfw"}) == ["glfw", "True"]
