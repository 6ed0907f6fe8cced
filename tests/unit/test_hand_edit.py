"""New TDT offsets written into a hand config's text: in place where the layout allows it
(flow or block mappings, offsets inherited from an anchor), as a dump where it does not; the
result always reads back as the same hand with exactly the new offsets."""

from __future__ import annotations

import re
from typing import Any

import pytest
import yaml

from handctl.bringup.hand_edit import with_line_ends, with_tdt_offsets
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


def test_a_block_joint_whose_merge_key_is_its_last_gets_its_tdt_in_place(
    hand: HandConfig,
) -> None:
    """The new tdt went after the line where the anchor ``<<: *flexor`` names is defined,
    lines above (the alias's node is the anchored one): the edit did not read back, the file
    was dumped without its comments, and the warning blamed a line of the user's file that
    reads well (found by an outside audit). It goes after the merge key's own line."""
    text = HAND_YAML.read_text()
    flow = (
        "      - {<<: *flexor, name: f1_j2, link_length: 0.050, half_thickness: 0.0075, "
        "tau_max: 0.45, device_tau_max: 0.60, angle_min: -0.90, angle_max: 2.30}\n"
    )
    block = (
        "      - name: f1_j2        # middle joint\n"
        "        link_length: 0.050\n"
        "        half_thickness: 0.0075\n"
        "        tau_max: 0.45\n"
        "        device_tau_max: 0.60\n"
        "        angle_min: -0.90\n"
        "        angle_max: 2.30\n"
        "        <<: *flexor          # the rest as f1_j1\n"
    )
    assert flow in text
    text = text.replace(flow, block)
    assert parse_hand(parse_yaml(text, "t")).joints == hand.joints  # the same hand
    offsets = _offsets(hand)
    edited = with_tdt_offsets(text, hand, offsets)
    assert not edited.dumped, edited.why
    added = f"tdt: {{scale: 1.0, offset: {offsets['f1_j2']:.4f}}}\n"
    assert "        <<: *flexor          # the rest as f1_j1\n        " + added in edited.text
    _reads_back(edited.text, hand, offsets)


def test_an_edit_that_does_not_read_back_blames_the_edit_not_the_file(
    hand: HandConfig, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The warning said the user's hand config was not valid YAML at a line of it that
    reads well (found by an outside audit): the text that does not read back is the edit's."""
    from handctl.bringup import hand_edit

    monkeypatch.setattr(hand_edit, "_edit", lambda text, hand, offsets: text + "x: [\n")
    edited = with_tdt_offsets(HAND_YAML.read_text(), hand, _offsets(hand))
    assert edited.dumped
    assert edited.why.startswith("handctl's edit of it does not read back: the edited text: ")
    assert hand.source not in edited.why


def test_each_line_keeps_its_own_ending_and_a_new_one_takes_its_neighbour_s() -> None:
    raw = "a: 1\r\nb: 2\r\nc: 3\nd: 4\n"
    edited = "a: 1\nb: 5\nc: 3\n  x: 9\nd: 4\n"
    assert with_line_ends(raw, edited) == "a: 1\r\nb: 5\r\nc: 3\n  x: 9\nd: 4\n"
    assert with_line_ends("a: 1\nb: 2", "a: 1\nb: 3") == "a: 1\nb: 3"
