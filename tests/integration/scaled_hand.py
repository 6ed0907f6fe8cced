"""The shipped hand config with its simulated hand scaled, for the experiment's corners: the
sim section is not part of the config hash, so the compiled recipe still loads for it."""

from __future__ import annotations

from pathlib import Path

import yaml

from ..conftest import HAND_YAML


def scaled_hand(directory: Path, factors: dict[str, float]) -> Path:
    """``hand.yaml`` in ``directory``: each factor scales the simulated joints' key of its
    name (``damping``, ``frictionloss``, ``armature``), the drive's ``lag``, every object's
    ``mass``, or a contact's Coulomb coefficient (``friction.finger_table``)."""
    data = yaml.safe_load(HAND_YAML.read_text())
    sim = data["sim"]
    for key, factor in factors.items():
        if key == "mass":
            for obj in sim["objects"]:
                obj["mass"] = obj["mass"] * factor
        elif key.startswith("friction."):
            pair = key.removeprefix("friction.")
            sim["friction"][pair] = sim["friction"][pair] * factor
        else:
            section = sim["actuator"] if key == "lag" else sim["joints"]
            section[key] = section[key] * factor
    path = directory / "hand.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path
