"""handctl: grasp, lift and manipulate objects with a joint-torque-controlled hand over CAN."""

import os

__version__ = "0.1.0"


def mujoco_opengl_off() -> None:
    """MuJoCo's OpenGL off, whatever ``MUJOCO_GL`` says, for every ``import mujoco`` after.

    handctl draws nothing with it. Unless told otherwise, ``import mujoco`` loads GLFW, which
    starts a ``python -c`` child to probe its library (a Ctrl-C during that import left the
    child behind); and a renderer it cannot load (``MUJOCO_GL=osmesa`` without OSMesa, a
    value MuJoCo does not know) makes the import raise, a traceback in every command that
    builds the simulated hand."""
    os.environ["MUJOCO_GL"] = "disable"
