"""Hand configs of other shapes, built from the default hand's YAML for the test at hand."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import yaml

DEFAULT_HAND = Path(__file__).resolve().parent.parent / "handctl" / "hands" / "hiroshima_hand.yaml"


def shaped_hand(
    tmp_path: Path,
    joints: list[int],
    node_ids: list[int] | None = None,
    edit: Callable[[dict[str, Any]], None] | None = None,
) -> Path:
    """A hand config file of the default hand's joints, reshaped and without its sim section:
    finger i gets ``joints[i]`` joints (copies of the default first finger's) and node id
    ``node_ids[i]``; ``edit`` may change the document before it is written."""
    doc = yaml.safe_load(DEFAULT_HAND.read_text(encoding="utf-8"))
    doc.pop("sim")
    template = doc["fingers"][0]
    nodes = node_ids or list(range(1, len(joints) + 1))
    fingers = []
    for i, (k, node) in enumerate(zip(joints, nodes, strict=True)):
        finger = dict(template, name=f"finger{i}", node_id=node)
        finger.pop("can_ids")
        finger["joints"] = [
            dict(template["joints"][min(j, 2)], name=f"finger{i}_joint{j}") for j in range(k)
        ]
        fingers.append(finger)
    doc["fingers"] = fingers
    if edit is not None:
        edit(doc)
    path = tmp_path / f"hand_{'x'.join(map(str, joints))}.yaml"
    path.write_text(yaml.safe_dump(doc), encoding="utf-8")
    return path
