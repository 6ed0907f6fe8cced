"""The metadata records of a recording: what a later reader needs to trust and re-run it, and
the hand config and recipe read back out of them.

MCAP metadata maps strings to strings, so structured values are JSON text. The hand config and
the recipe go in as the YAML text that was loaded (a re-run parses exactly that), with the
hand's hash beside it so a reader can tell which hand a log belongs to.
"""

from __future__ import annotations

import hashlib
import platform
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import replace
from functools import lru_cache
from importlib import metadata as importlib_metadata
from pathlib import Path
from typing import Any

import orjson

from handctl import __version__
from handctl.config import HandConfig, parse_hand
from handctl.errors import ConfigError, Description
from handctl.hand_protocol import protocol_for
from handctl.online.recipes.loader import check_against_hand, parse_recipe
from handctl.online.recipes.schema import Recipe
from handctl.protocol import Protocol, parse_protocol
from handctl.recording import channels as ch
from handctl.recording.reader import Recording
from handctl.schema import parse_yaml

#: The packages whose versions a recording names.
PACKAGES = ("numpy", "mujoco", "python-can", "mcap", "orjson", "cantools", "pyyaml")


def valid_text(text: str) -> str:
    """``text`` as valid UTF-8: a byte that is not (a file name or an argument in another
    encoding, which Python holds as a lone surrogate) shown as ``\\xNN``, the rest as it is.
    MCAP strings and JSON must be UTF-8; such a byte in ``--log``'s path failed the run's
    start with a TypeError from the encoder, and no log."""
    try:
        text.encode("utf-8")
    except UnicodeEncodeError:
        try:
            raw = text.encode("utf-8", "surrogateescape")
        except UnicodeEncodeError:  # a surrogate no file name or argument decodes to
            return text.encode("utf-8", "backslashreplace").decode("utf-8")
        return raw.decode("utf-8", "backslashreplace")
    return text


def valid_strings(value: Any) -> Any:
    """``value`` with every string in it made ``valid_text``: what goes into a recording's
    metadata or the writer's set-up."""
    return map_strings(value, valid_text)


def map_strings(value: Any, text: Callable[[str], str]) -> Any:
    """``value`` with ``text`` applied to every string in it, keys too, in dicts, lists and
    tuples (a tuple comes back a list, as JSON has it)."""
    if isinstance(value, str):
        return text(value)
    if isinstance(value, dict):
        return {map_strings(k, text): map_strings(v, text) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [map_strings(v, text) for v in value]
    return value


def _read(path: str) -> str:
    try:
        return Path(path).read_text(encoding="utf-8")
    except OSError:
        return ""


def package_version(package: str) -> str:
    try:
        return importlib_metadata.version(package)
    except importlib_metadata.PackageNotFoundError:
        return "not installed"


def versions() -> dict[str, str]:
    found = {
        "handctl": __version__,
        "python": platform.python_version(),
        "platform": platform.platform(),
    }
    found |= {name: package_version(name) for name in PACKAGES}
    return found


def start_metadata(
    hand: HandConfig, recipe: Recipe | None, command_line: Sequence[str] = ()
) -> dict[str, dict[str, str]]:
    """The records known before the run: hand, recipe, versions, the command line."""
    hand_text = _read(hand.source)
    # The protocol the run speaks goes with the hand, as text: a re-run decodes and encodes
    # with it, whatever DBC (given or generated) the handctl of the re-run would choose.
    dbc = protocol_for(hand).text
    records = {
        ch.META_HAND: {
            "name": hand.name,
            "source": hand.source,
            "config_hash": hand.config_hash,
            "sha256": hashlib.sha256(hand_text.encode()).hexdigest(),
            "yaml": hand_text,
            "dbc": dbc,
            "dbc_sha256": hashlib.sha256(dbc.encode()).hexdigest(),
        },
        ch.META_VERSIONS: versions(),
    }
    if recipe is not None:
        records[ch.META_RECIPE] = {
            "name": recipe.name,
            "source": recipe.source,
            "yaml": _read(recipe.source),
        }
    records["handctl.command"] = {
        "command_line": orjson.dumps(valid_strings(list(command_line or sys.argv))).decode(),
        "started_unix_ns": str(time.time_ns()),
        "format_version": str(ch.FORMAT_VERSION),
    }
    # The sources are paths as given: any of them may hold a byte that is not UTF-8.
    result: dict[str, dict[str, str]] = valid_strings(records)
    return result


def run_metadata(
    *,
    mode: str,
    bus: str,
    seed: int,
    period_ns: int,
    startup_ticks: int,
    reset_node_faults: bool,
    answer_ticks: int | None = None,
    estimator: bool,
    sim_faults: str = "",
) -> dict[str, str]:
    """How the runtime was set up: what a re-run must set up the same way."""
    return {
        "mode": mode,
        "bus": bus,
        "seed": str(seed),
        "period_ns": str(period_ns),
        "startup_ticks": str(startup_ticks),
        # the nodes' time to answer once one is heard (``Runtime.answer_ticks``)
        "answer_ticks": str(startup_ticks if answer_ticks is None else answer_ticks),
        "reset_node_faults": str(reset_node_faults),
        "estimator": str(estimator),
        "sim_faults": sim_faults,
    }


def check_run_metadata(recording: Recording, hand: HandConfig | None) -> None:
    """Refuse a ``handctl.run`` record that is not what a run writes (``run_metadata``): a
    log whose mode, seed or period was rewritten was summarised and re-run "bit-exact" as
    it was, its period read into the phases' times. None is fine (a run stopped before its
    runtime was set up writes none)."""
    run = recording.metadata.get(ch.META_RUN)
    if not run:
        return

    def refuse(key: str, expected: str) -> ConfigError:
        return ConfigError(
            str(recording.path), f"metadata {ch.META_RUN}.{key}", expected, run.get(key, "nothing")
        )

    if run.get("mode") not in ("lockstep", "realtime"):
        raise refuse("mode", "lockstep or realtime")
    for key in ("seed", "startup_ticks"):
        if not run.get(key):
            raise refuse(key, "a whole number >= 0")
        recording.meta_int(ch.META_RUN, key, 0)  # said as every whole number is
    recording.meta_int(ch.META_RUN, "answer_ticks", 0)  # a log from before it has none
    period_ns = recording.meta_int(ch.META_RUN, "period_ns", -1, minimum=1)
    if hand is not None and period_ns != round(hand.bus.period_s * 1e9):
        raise refuse(
            "period_ns",
            f"{round(hand.bus.period_s * 1e9)} (the period of the recorded hand's "
            f"{hand.bus.loop_rate_hz:g} Hz loop)",
        )
    for key in ("reset_node_faults", "estimator"):
        if run.get(key) not in ("True", "False"):
            raise refuse(key, "True or False")


def missing_record(recording: Recording, name: str) -> str | Description:
    """What a metadata record the log lacks is, for a refusal's "found": a damaged record
    (its bytes fail to read: the header of ``handctl replay`` names where), or nothing.
    A byte flipped in the hand's record was said as "found nothing", as if the log had
    been recorded without a hand (found by an outside audit)."""
    if name in recording.bad_metadata:
        return Description(
            f"a damaged record {name!r} (it does not read: handctl replay's header says where)"
        )
    return "nothing"


def recorded_hand(recording: Recording, required: bool = True) -> HandConfig | None:
    """The hand config a recording's run used, as it was loaded then."""
    text = recording.meta(ch.META_HAND, "yaml")
    digest = recording.meta(ch.META_HAND, "sha256")
    if not text and digest:
        # the record is there, its digest with it, and the text it is the digest of is not:
        # a record damaged in place (zeros over it read as other keys). Read as a log of no
        # hand, its summary came out whole and "complete", its phase and torque tables empty.
        keys = ", ".join(repr(k) for k in recording.metadata.get(ch.META_HAND, {}))
        raise ConfigError(
            str(recording.path),
            f"metadata {ch.META_HAND}.yaml",
            f"the hand config whose sha256 the run recorded ({digest[:16]}...)",
            Description(f"none: the record is damaged or edited (its keys: {keys})"),
        )
    if not text:
        if required:
            raise ConfigError(
                str(recording.path),
                f"metadata {ch.META_HAND}.yaml",
                "the hand config the run used (recorded by handctl)",
                missing_record(recording, ch.META_HAND),
            )
        return None
    _check_digest(recording, "yaml", "sha256", text)
    protocol = recorded_protocol(recording)
    return _parsed_hand(text, protocol, str(recording.path))


@lru_cache(maxsize=8)
def _parsed_hand(text: str, protocol: Protocol | None, path: str) -> HandConfig:
    """The recorded hand config parsed once per log: a replay asked for it five times (its
    summary, series, plot, frames and re-run), each a parse of the YAML and the DBC's
    checks, a fifth of a short log's replay."""
    return _as_recorded(
        parse_hand(parse_yaml(text, f"{path} (its recorded hand config)"), protocol)
    )


def _as_recorded(hand: HandConfig) -> HandConfig:
    """``hand`` read by the rules of the handctl that recorded it, where a later rule would
    refuse what that one ran: a written ``half_thickness: 0`` beside a ``sim.links`` radius
    was taken for "not given" until the rule that holds it to the radius came, and a log of
    such a hand lost its simulated hand with it (no turn, no torque panels in its plot, and
    ``monitor --log`` refused it; found by an outside audit of that rule). The run was what
    it was: its log reads as it did."""
    if not any(j.half_thickness_given and j.half_thickness == 0 for j in hand.joints):
        return hand
    fingers = tuple(
        replace(
            finger,
            joints=tuple(
                replace(j, half_thickness_given=False) if j.half_thickness == 0 else j
                for j in finger.joints
            ),
        )
        for finger in hand.fingers
    )
    return replace(hand, fingers=fingers)


def _check_digest(recording: Recording, key: str, digest_key: str, text: str) -> None:
    """Refuse a recorded text that is not the one the run recorded the digest of: a hand or
    DBC edited in the log would re-run, replay onto a bus and decode with limits and ids the
    run never had. A text without its digest is refused too: every handctl log records the
    digest beside the text (the hand's since format version 1 began, the DBC's since the
    DBC was recorded), and a log whose digest was deleted was taken for one from before the
    digest, its hand's tau_max edited and accepted (an outside audit)."""
    recorded = recording.meta(ch.META_HAND, digest_key)
    if not recorded:
        raise ConfigError(
            str(recording.path),
            f"metadata {ch.META_HAND}.{digest_key}",
            f"the sha256 of {key} the run recorded beside it (every handctl log has it)",
            Description("none: the record was edited after the run"),
        )
    actual = hashlib.sha256(text.encode()).hexdigest()
    if actual != recorded:
        raise ConfigError(
            str(recording.path),
            f"metadata {ch.META_HAND}.{key}",
            f"the text whose sha256 the run recorded ({digest_key} {recorded[:16]}...)",
            f"a text whose sha256 is {actual[:16]}... (edited after the run)",
        )


def recorded_protocol(recording: Recording) -> Protocol | None:
    """The protocol the run spoke, as it recorded it (None in a recording from before the
    protocol was recorded: then it was the packaged DBC, which the hand generates)."""
    text = recording.meta(ch.META_HAND, "dbc")
    if not text:
        return None
    _check_digest(recording, "dbc", "dbc_sha256", text)
    return parse_protocol(text, f"{recording.path} (its recorded DBC)")


def recorded_recipe(recording: Recording, hand: HandConfig) -> Recipe:
    """The recipe a recording's run used, checked against its hand as it was then."""
    recipe = parse_recorded_recipe(recording, hand)
    check_against_hand(recipe, hand)
    return recipe


def parse_recorded_recipe(recording: Recording, hand: HandConfig) -> Recipe:
    """The recipe a recording's run used, read for its hand but not yet held to its hand
    config's digest (``check_against_hand``): a reader that can do without a recipe tells a
    recipe of older rules from one compiled for another hand."""
    text = recording.meta(ch.META_RECIPE, "yaml")
    if not text:
        raise ConfigError(
            str(recording.path),
            f"metadata {ch.META_RECIPE}.yaml",
            "the recipe the run used (recorded by handctl)",
            missing_record(recording, ch.META_RECIPE),
        )
    return parse_recipe(
        parse_yaml(text, f"{recording.path} (its recorded recipe)"), hand, as_recorded=True
    )
