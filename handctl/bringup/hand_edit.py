"""A hand config with new TDT offsets, written by editing the numbers in its text.

An engineer's hand config carries comments, anchors, flow mappings and a ``sim`` section laid
out by hand; a YAML dump would throw all of that away. So the offsets are edited where they
stand: the YAML is composed (not constructed) to find, for each joint, the text span of its own
``tdt.offset``, and the number there is replaced. A joint that has no ``tdt`` of its own (it
takes it from an anchor through ``<<``) gets one added to its mapping, so that no two joints
share an offset through the anchor any more.

The edited text is parsed again and must give the same hand with exactly the new offsets. When
it does not (a layout this editor does not know: an alias for a whole joint, a tag, a multi-line
flow mapping it cannot place a key in), the config is dumped instead, which is correct but loses
the comments and the layout; ``EditedHand.dumped`` says so, and the command warns.
"""

from __future__ import annotations

import dataclasses
import difflib
import re
from collections.abc import Mapping
from dataclasses import dataclass

from handctl.config import HandConfig, parse_hand
from handctl.errors import ConfigError
from handctl.schema import (
    MappingNode,
    Node,
    ScalarNode,
    SequenceNode,
    compose_yaml,
    dump_yaml,
    parse_yaml,
)

#: Decimals of an offset written to the file: the wire's TDT resolution is 0.0001 N·m.
DECIMALS = 4


@dataclass(frozen=True)
class EditedHand:
    text: str
    dumped: bool  # True when the text could not be edited in place and was dumped instead
    why: str = ""


def format_offset(value: float) -> str:
    text = f"{round(value, DECIMALS):.{DECIMALS}f}"
    return "0.0000" if text == "-0.0000" else text


def with_tdt_offsets(text: str, hand: HandConfig, offsets: Mapping[str, float]) -> EditedHand:
    """``text`` (the file ``hand`` was loaded from) with ``offsets`` (joint name -> N·m);
    ``ValueError`` when no text with them reads back as the same hand."""
    wanted = {name: float(format_offset(v)) for name, v in offsets.items()}
    try:
        edited = _edit(text, hand, wanted)
        _verify(edited, hand, wanted)
        return EditedHand(edited, dumped=False)
    except _CannotEditError as exc:
        why = str(exc)
    dumped = _dump(text, hand, wanted)
    try:
        _verify(dumped, hand, wanted)
    except _CannotEditError as exc:
        # not a layout: the hand with these offsets is not a hand config (an offset that puts
        # a limit out of the wire's range, say), so there is nothing right to write
        raise ValueError(f"with the new offsets it does not read back ({exc})") from None
    return EditedHand(dumped, dumped=True, why=why)


class _CannotEditError(Exception):
    pass


def _scalar_value(node: MappingNode, key: str) -> Node | None:
    for k, v in node.value:
        if isinstance(k, ScalarNode) and k.value == key:
            return v  # type: ignore[no-any-return]
    return None


def _edit(text: str, hand: HandConfig, offsets: Mapping[str, float]) -> str:
    try:
        root = compose_yaml(text)
    except ValueError as exc:  # it was read before, so this is not expected
        raise _CannotEditError(f"the YAML cannot be composed: {exc}") from None
    if not isinstance(root, MappingNode):
        raise _CannotEditError("the top level is not a mapping")
    fingers = _scalar_value(root, "fingers")
    if not isinstance(fingers, SequenceNode):
        raise _CannotEditError("fingers is not a plain sequence")
    edits: list[tuple[int, int, str]] = []  # (start, end, replacement) in the text
    seen: set[int] = set()  # joint and tdt nodes met: an alias is the very node again
    for finger in fingers.value:
        joints = _scalar_value(finger, "joints") if isinstance(finger, MappingNode) else None
        if not isinstance(joints, SequenceNode):
            raise _CannotEditError("a finger's joints are not a plain sequence")
        for joint in joints.value:
            if not isinstance(joint, MappingNode) or id(joint) in seen:
                raise _CannotEditError("a joint is an alias of another one")
            seen.add(id(joint))
            name_node = _scalar_value(joint, "name")
            name = name_node.value if isinstance(name_node, ScalarNode) else None
            if not isinstance(name, str) or name not in offsets:
                raise _CannotEditError(f"joint {name!r} has no name of its own")
            tdt = _scalar_value(joint, "tdt")
            if tdt is not None:
                if id(tdt) in seen:
                    raise _CannotEditError(f"{name} shares its tdt with another joint (an alias)")
                seen.add(id(tdt))
            edits.append(_joint_edit(text, joint, name, offsets[name], hand))
    edits.sort(reverse=True)
    out = text
    for start, end, replacement in edits:
        out = out[:start] + replacement + out[end:]
    return out


def _joint_edit(
    text: str, joint: MappingNode, name: str, offset: float, hand: HandConfig
) -> tuple[int, int, str]:
    tdt = _scalar_value(joint, "tdt")
    number = format_offset(offset)
    if isinstance(tdt, MappingNode):
        value = _scalar_value(tdt, "offset")
        if isinstance(value, ScalarNode) and value.style is None:
            return value.start_mark.index, value.end_mark.index, number
        raise _CannotEditError(f"{name}: tdt.offset is not a plain number")
    if tdt is not None:
        raise _CannotEditError(f"{name}: tdt is not a mapping")
    # The joint takes its tdt from an anchor: give it one of its own.
    scale = next(j.tdt.scale for j in hand.joints if j.name == name)
    entry = f"tdt: {{scale: {scale!r}, offset: {number}}}"
    if joint.flow_style:
        close = joint.end_mark.index - 1
        if text[close] != "}":
            raise _CannotEditError(f"{name}: its flow mapping does not end where expected")
        before = close
        while before > 0 and text[before - 1] in " \t":
            before -= 1
        if "\n" in text[before - 1 : close]:
            raise _CannotEditError(f"{name}: its flow mapping ends on a line of its own")
        return before, before, f", {entry}"
    first_key = joint.value[0][0]
    last_key, last_value = joint.value[-1]
    if last_value.start_mark.index < last_key.end_mark.index:
        # an alias (``<<: *flexor``): its node is the anchored one, whose marks are where
        # the anchor is defined, lines above; the key's own line is this mapping's last.
        # Placed after the anchor's line, the new tdt broke the file (found by an outside
        # audit). The alias after the key on its line is the whole value.
        line_end = text.find("\n", last_key.end_mark.index)
    else:
        line_end = text.find("\n", last_value.end_mark.index)
        if "\n" in text[last_value.start_mark.index : last_value.end_mark.index]:
            line_end = -1
    if line_end < 0:
        raise _CannotEditError(f"{name}: its last key does not end its line")
    indent = " " * first_key.start_mark.column
    return line_end + 1, line_end + 1, f"{indent}{entry}\n"


#: a line and its own ending (none on a last line without one)
_LINE = re.compile(r"([^\r\n]*)(\r\n|\r|\n|$)")


def _lines(text: str) -> list[tuple[str, str]]:
    found = [(m.group(1), m.group(2)) for m in _LINE.finditer(text)]
    return found[:-1] if found and found[-1] == ("", "") else found


def with_line_ends(raw: str, edited: str) -> str:
    """``edited`` (made from ``raw`` read with its line ends made \\n) with each line's own
    ending of ``raw`` put back: a line the edit kept keeps its ending, and a line it added
    or changed takes the ending of the line before it in ``raw`` (the one after, at the
    top). Every line was given \\r\\n when any line had one, and a file of mixed endings
    came back rewritten on every line but those (found by an outside audit)."""
    if "\r" not in raw:
        return edited
    old, new = _lines(raw), _lines(edited)
    matcher = difflib.SequenceMatcher(None, [b for b, _ in old], [b for b, _ in new], False)
    out: list[str] = []
    for tag, i1, i2, j1, j2 in matcher.get_opcodes():
        for k in range(j1, j2):
            body, end = new[k]
            i = i1 + k - j1
            if end and tag in ("equal", "replace") and i < i2 and old[i][1]:
                end = old[i][1]
            elif end:
                near = old[i1 - 1] if i1 > 0 else old[i1] if i1 < len(old) else ("", "\n")
                end = near[1] or end
            out.append(body + end)
    return "".join(out)


def _dump(text: str, hand: HandConfig, offsets: Mapping[str, float]) -> str:
    data = parse_yaml(text, "the hand config").data
    for finger in data["fingers"]:
        finger["joints"] = [dict(joint) for joint in finger["joints"]]
        for joint in finger["joints"]:
            joint["tdt"] = {**joint["tdt"], "offset": offsets[joint["name"]]}
    header = (
        f"# {hand.name}: written by handctl calibrate tdt as a plain dump (the original's "
        "layout could not be edited in place)\n"
    )
    return header + dump_yaml(data)


def _verify(text: str, hand: HandConfig, offsets: Mapping[str, float]) -> None:
    """The edited text must be the same hand but for exactly the new offsets."""
    try:
        # against the DBC the hand was loaded with (--dbc): one that numbers its frames
        # otherwise refused every calibration of such a hand after it had measured
        got = parse_hand(parse_yaml(text, hand.source), dbc=hand.dbc)
    except ConfigError as exc:
        # the edited text's fault, not the file's: named as the hand config, the message sent
        # the user to a line of their own file that reads well (found by an outside audit)
        where = "the edited text" if exc.file == hand.source else exc.file
        said = ConfigError(where, exc.key, exc.expected, exc.found)
        raise _CannotEditError(f"handctl's edit of it does not read back: {said}") from None
    for old, new in zip(hand.joints, got.joints, strict=True):
        want = dataclasses.replace(old, tdt=dataclasses.replace(old.tdt, offset=offsets[old.name]))
        if new != want:
            raise _CannotEditError(f"{old.name} reads back as {new}, not {want}")
    if (got.bus, got.safety, got.name, len(got.fingers)) != (
        hand.bus,
        hand.safety,
        hand.name,
        len(hand.fingers),
    ):
        raise _CannotEditError("the edited text reads back as another hand")
