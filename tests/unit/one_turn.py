"""A template of one turn phase, as ``handctl plan`` reads it: what the tests of the keys a
template carries into its compiled recipe start from."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path

import yaml

from handctl.config import HandConfig
from handctl.planning.template import TemplatePhase, load_template


def one_turn_template(
    tmp_path: Path, hand: HandConfig, seed: Sequence[float], keys: Mapping[str, object]
) -> TemplatePhase:
    """The one turn phase (−45°, seeded with ``seed`` in the hand's joint order) of a template
    of two cylinders, with ``keys`` besides."""
    template = {
        "template": "one_turn",
        "recipe": "one_turn",
        "objects": [{"name": "cyl1", "radius": 0.02}, {"name": "cyl2", "radius": 0.02}],
        "phases": [
            {
                "name": "turn",
                "kind": "turn",
                "turn_deg": -45,
                "max_s": 1.0,
                "seed": dict(zip(hand.joint_names, seed, strict=True)),
                **keys,
            }
        ],
    }
    path = tmp_path / "t.template.yaml"
    path.write_text(yaml.safe_dump(template, sort_keys=False))
    return load_template(path, hand).phases[0]
