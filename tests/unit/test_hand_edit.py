"""New TDT offsets written into a hand config's text: in place where the layout allows it
(flow or block mappings, offsets inherited from an anchor), as a dump where it does not; the
result always reads back as the same hand with exactly the new offsets."""

from __future__ import annotations

import re
from typing import Any

import pytest
import yaml

from handctl.bringup.hand_edit import with_tdt_offsets
from handctl.config import HandConfig, parse_hand
from handctl.schema import parse_yaml

from ..conftest import HAND_YAML


class _NoAliases(yaml.SafeDumper):
    def ignore_aliases(self, data: Any) -> bool:
        return True


def _offsets(hand: HandConfig) -> dict[str, float]:
    return {j.name: round(0.0011 * (k - 4), 4) for k, j in enumerate(hand.joints)}


def _reads_back(text: str, hand: HandConfig, offsets: dict[str, float]) -> None:
    back = parse_hand(parse_yaml(text, "edited"))
    assert {j.name: j.tdt.offset for j in back.joints} == offsets
    assert [j.tau_max for j in back.joints] == [j.tau_max for j in hand.joints]


def test_block_mappings_are_edited_in_place(hand: HandConfig) -> None:
    text = "# my hand\n" + yaml.dump(
        yaml.safe_load(HAND_YAML.read_text()), Dumper=_NoAliases, sort_keys=False
    )
    offsets = _offsets(hand)
    edited = with_tdt_offsets(text, hand, offsets)
    assert not edited.dumped and edited.text.startswith("# my hand\n")
    _reads_back(edited.text, hand, offsets)


def test_a_block_joint_that_inherits_its_tdt_gets_its_own(hand: HandConfig) -> None:
    text = yaml.dump(yaml.safe_load(HAND_YAML.read_text()), Dumper=_NoAliases, sort_keys=False)
    text = text.replace("  - name: f1_j1\n", "  - &j1\n    name: f1_j1\n")
    text = re.sub(r"  - name: f2_j1\n(    .*\n)+", "  - <<: *j1\n    name: f2_j1\n", text)
    assert parse_hand(parse_yaml(text, "t")).joints == hand.joints  # the same hand
    offsets = _offsets(hand)
    edited = with_tdt_offsets(text, hand, offsets)
    assert not edited.dumped
    assert "    name: f2_j1\n    tdt: {scale: 1.0, offset: " in edited.text
    _reads_back(edited.text, hand, offsets)


def test_a_tdt_shared_through_an_alias_is_dumped(hand: HandConfig) -> None:
    text = yaml.safe_dump(yaml.safe_load(HAND_YAML.read_text()), sort_keys=False)
    assert "tdt: *id001" in text  # the dumper shares the equal tdt mappings
    offsets = _offsets(hand)
    edited = with_tdt_offsets(text, hand, offsets)
    assert edited.dumped and "shares its tdt with another joint" in edited.why
    _reads_back(edited.text, hand, offsets)


def test_offsets_no_hand_config_can_carry_are_refused_not_written(hand: HandConfig) -> None:
    """-5 N·m on f2_j3 puts the readings of its device_tau_max beyond the Feedback signal's
    range: neither the edit nor the dump reads back, and that is said, not raised raw."""
    offsets = {j.name: 0.0 for j in hand.joints} | {"f2_j3": -5.0}
    with pytest.raises(ValueError, match="with the new offsets it does not read back"):
        with_tdt_offsets(HAND_YAML.read_text(), hand, offsets)
