"""The benchmarks' hold recipe: the hand closed gently and held, the same work every tick.

A module of its own, importing of handctl only what every tree since the stage accounting has
(``handctl.handshape.flexion_sign``): ``tick_cost.py`` runs it with an older tree's handctl
first on the path (``bench.py loop --baseline REV``), and ``bench_loop``'s own imports
(``hostcheck.work_figures``, ``session`` and the rest) are newer than that baseline. While the
recipe lived in ``bench_loop``, importing it failed in every baseline tree before them.
"""

from __future__ import annotations

import json
from typing import TYPE_CHECKING

from handctl.handshape import flexion_sign

if TYPE_CHECKING:
    from handctl.config import HandConfig

#: N·m per N·m of tau_max and rad: how hard and how far the benchmarks' hold closes each
#: joint (its flexion's way), gently, well inside every limit
HOLD_TORQUE_FRACTION = 0.1
HOLD_POSE_RAD = 0.3


def hold_recipe(hand: HandConfig, name: str, seconds: float, pose: bool = True) -> str:
    """A one-phase recipe for ``hand`` that closes it gently and holds for ``seconds``: each
    joint flexed at ``HOLD_TORQUE_FRACTION`` of its tau_max and, with ``pose``, sprung towards
    ``HOLD_POSE_RAD`` of flexion (for the loop and soak benchmarks: the hand busy, nothing
    grasped); with ``pose`` the soft-limit guard is on too (the loop's whole feedback)."""
    torques: dict[str, float] = {}
    angles: dict[str, float] = {}
    for finger in hand.fingers:
        sign = flexion_sign(hand, finger)
        for joint in finger.joints:
            torques[joint.name] = round(sign * HOLD_TORQUE_FRACTION * joint.tau_max, 4)
            angles[joint.name] = sign * HOLD_POSE_RAD
    phase: dict[str, object] = {
        "name": "close",
        "torques": torques,
        "ramp_s": 0.3,
        "max_s": seconds,
        "on_timeout": "next",
    }
    doc: dict[str, object] = {
        "recipe": name,
        "description": "close the hand gently and hold, for a benchmark",
    }
    if pose:
        phase["pose"] = {"angles": angles, "stiffness": 0.05, "damping": 0.002}
        phase["joint_damping"] = 0.03  # the damping injection a braked phase adds
        doc["limit_guard_band"] = 0.15
    doc["phases"] = [phase]
    return json.dumps(doc)  # JSON is YAML
