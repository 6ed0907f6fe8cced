"""A drawing of the scene in the hand plane, from MuJoCo's geom positions.

A picture is the quickest check that a configuration makes sense (fingers clear of the
cylinders, tips able to reach beneath them, room for the pair to turn), and it draws what
MuJoCo will simulate rather than what the config meant. matplotlib is imported only here and
only when a drawing is asked for.
"""

from __future__ import annotations

import math
from pathlib import Path

import mujoco
import numpy as np

from handctl.sim.plant import Plant


def _stadium(x0: float, y0: float, x1: float, y1: float, r: float) -> list[tuple[float, float]]:
    """Outline of a capsule's cross-section in the plane: a segment widened by ``r``."""
    heading = math.atan2(y1 - y0, x1 - x0)
    points = []
    for centre, start in (((x1, y1), heading - math.pi / 2), ((x0, y0), heading + math.pi / 2)):
        for a in np.linspace(start, start + math.pi, 12):
            points.append((centre[0] + r * math.cos(a), centre[1] + r * math.sin(a)))
    return points


def scene_half_width(plant: Plant) -> float:
    """Half the width (m) that shows every finger stretched out and every object."""
    reach = [abs(f.base_x) + sum(j.link_length for j in f.joints) for f in plant.hand.fingers]
    objects = [abs(o.x) + o.radius for o in plant.params.objects]
    return max(reach + objects + [plant.params.palm_half_width]) + 0.02


def draw_scene(plant: Plant, path: str | Path, title: str = "") -> Path:
    """Draw the current state of ``plant`` to a PNG at ``path``; returns the path."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Circle, Polygon, Rectangle

    model, data = plant.model, plant.data
    fig, ax = plt.subplots(figsize=(7.5, 4.6), dpi=120)
    params = plant.params
    ax.axhline(params.table_height, color="saddlebrown", lw=2)
    width = 2 * scene_half_width(plant)
    ax.add_patch(
        Rectangle((-width / 2, params.table_height - 0.01), width, 0.01, color="burlywood")
    )
    ax.add_patch(
        Rectangle(
            (-params.palm_half_width, 0.0),
            2 * params.palm_half_width,
            params.palm_thickness,
            color="grey",
            alpha=0.7,
        )
    )
    colours = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    for f_index, finger in enumerate(plant.hand.fingers):
        for joint in finger.joints:
            bid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, joint.name)
            gid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, joint.name)
            x0, y0 = data.xpos[bid][:2]
            axis = data.xmat[bid].reshape(3, 3)[:, 0]
            x1 = x0 + axis[0] * joint.link_length
            y1 = y0 + axis[1] * joint.link_length
            r = float(model.geom_size[gid][0])
            ax.add_patch(
                Polygon(
                    _stadium(x0, y0, x1, y1, r),
                    closed=True,
                    color=colours[f_index % len(colours)],
                    alpha=0.45,
                )
            )
            ax.plot([x0], [y0], "k.", ms=3)
    for pose, obj in zip(plant.object_poses(), params.objects, strict=True):
        ax.add_patch(Circle((pose.x, pose.y), obj.radius, color="orange", alpha=0.6))
        ax.plot(
            [pose.x, pose.x + obj.radius * math.cos(pose.angle)],
            [pose.y, pose.y + obj.radius * math.sin(pose.angle)],
            "k-",
            lw=1,
        )
    ax.set_aspect("equal")
    half_width = scene_half_width(plant)
    ax.set_xlim(-half_width, half_width)
    ax.set_ylim(params.table_height - 0.03, max(0.05, params.palm_thickness + 0.02))
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.grid(True, lw=0.3)
    ax.set_title(title or f"t = {plant.time:.3f} s")
    out = Path(path)
    fig.tight_layout()
    fig.savefig(out)
    plt.close(fig)
    return out
