"""A recording's frames: back onto a bus with their timing, or out to python-can's log formats."""

from __future__ import annotations

import collections
import functools
import itertools
import math
import shutil
import tempfile
import time
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np

from handctl.config import FingerConfig, HandConfig
from handctl.errors import ConfigError, Description, HandctlError, escaped
from handctl.hand_protocol import node_message, protocol_for
from handctl.online.safety.limits import (
    GRID_SLACK,
    JointLimits,
    angle_violations,
    outside_text,
)
from handctl.protocol import COMMAND_WATCHDOG_S, NODE_COMMANDS, NODE_TIMING_MARGIN_S, Layout
from handctl.protocol import Protocol as WireProtocol
from handctl.recording import channels as ch
from handctl.recording.messages import EXTENDED_ID_FLAG
from handctl.recording.metadata import recorded_hand, recorded_protocol
from handctl.recording.reader import Recording, iter_decoded, open_recording, require_topics
from handctl.wholefile import left_as_it_was, whole_file

if TYPE_CHECKING:  # the bus only where frames are sent: reading a log needs none of it
    from handctl.online.bus import HandBus

#: buses where no real hand listens: a replay onto them may take the log's limits as its own
SIMULATED_BUSES = ("virtual", "unix")
#: the logged frames of each ``--direction``
DIRECTION_TOPICS = {"both": (ch.CAN_RX, ch.CAN_TX), "rx": (ch.CAN_RX,), "tx": (ch.CAN_TX,)}


def logged_frames(
    recording: Recording,
    direction: str = "both",
    bus_events: Callable[[str, str], None] | None = None,
    refused: Callable[[int, int], None] | None = None,
) -> Iterator[tuple[int, int, bytes, bool]]:
    """``(log_time_ns, arbitration_id, data, is_rx)`` in the order they were on the wire;
    ``bus_events(name, detail)`` is told of each bus event the run logged (``/events``, kind
    ``bus``) where it is among them, in the same pass (``monitor --log``), and
    ``refused(log_time_ns, arbitration_id)`` of each frame the bus refused, which never was
    on the wire (``check_commands``)."""
    if direction not in DIRECTION_TOPICS:
        raise ConfigError("--direction", "", "both, rx or tx", direction)
    topics = DIRECTION_TOPICS[direction] + ((ch.EVENTS,) if bus_events is not None else ())
    for topic, log_time, msg in iter_decoded(recording, topics):
        if topic == ch.EVENTS:
            if bus_events is not None and msg["kind"] == "bus":
                bus_events(str(msg["name"]), str(msg["detail"]))
            continue
        if topic == ch.CAN_TX and msg.get("ok") is False:
            if refused is not None:
                refused(log_time, msg["id"])
            continue  # the bus refused it: it never was on the wire
        yield log_time, msg["id"], bytes.fromhex(msg["data"]), topic == ch.CAN_RX


def to_bus(
    recording: Recording,
    spec: str,
    speed: float = 1.0,
    direction: str = "both",
    sleep: Callable[[float], None] = time.sleep,
    clock: Callable[[], float] = time.perf_counter,
    hand: HandConfig | None = None,
    stops: StopNotes | None = None,
) -> dict[str, Any]:
    """Send the logged frames onto the bus ``spec`` with their original spacing / ``speed``.

    ``stops`` are the stop signals the command notes rather than raises
    (``handctl.stopsignals.noted_stops``): looked at between two frames, the first ends the
    sending with the stop of the nodes left enabled, and no later one cuts that stop short.

    Frames are paced against their due times (not slept frame to frame), so the time spent
    sending does not add up into drift; a sender more than a period behind shifts the rest of
    the replay by as much (``shifted_ms``) rather than send a backlog at once.

    Checked and sent from one copy of the file, taken first: the checks read the log, and the
    sending read it again, so what was written into it in between (a copy still arriving, a
    file appended to) went onto the bus unchecked. The copy is a file without a name (in the
    temporary directory, read through ``/proc/self/fd``), which the system frees however
    the replay ends: a named one in a private directory stayed behind a replay killed
    (SIGKILL), 50 MB a minute of run (found by an outside audit)."""
    if not speed > 0 or not math.isfinite(speed):
        raise ConfigError("--speed", "", "a speed factor > 0 (1 = as recorded)", speed)
    with tempfile.TemporaryFile(prefix="handctl-to-bus-") as private:
        try:
            with recording.path.open("rb") as source:
                shutil.copyfileobj(source, private)
            private.flush()
        except OSError as exc:
            raise ConfigError(
                str(recording.path), "", "a log that can be read whole", exc.strerror or str(exc)
            ) from None
        copy = Path(f"/proc/self/fd/{private.fileno()}")
        snapshot = open_recording(copy)
        snapshot.path = recording.path  # every message names the log the user gave
        snapshot.read_from = copy
        return _to_bus(snapshot, spec, speed, direction, sleep, clock, hand, stops or _NoStops())


def _to_bus(
    recording: Recording,
    spec: str,
    speed: float,
    direction: str,
    sleep: Callable[[float], None],
    clock: Callable[[], float],
    hand: HandConfig | None,
    stops: StopNotes,
) -> dict[str, Any]:
    from handctl.online.bus import open_bus

    given = hand is not None
    hand = _checked_commands(recording, spec, direction, speed, hand)
    # The stop of the nodes left enabled speaks what the frames sent spoke: the recorded
    # DBC, unless the hand on the bus was given. From the hand config alone, the DBC the
    # log recorded was set aside: a node whose DataIDs differed refused the zero torque and
    # the disable by CRC and held its last torque until its watchdog (found by an outside
    # audit).
    protocol = protocol_for(hand) if given else recorded_protocol(recording) or protocol_for(hand)
    # A sender that fell behind (a stall, a slow machine) and sent its backlog back to back
    # broke on the wire the rate limit the commands were checked against on their logged
    # spacing. Behind by more than a period (the slack ``check_commands`` gives a late
    # tick), the rest of the replay is shifted instead, as late as this frame.
    tally = _Tally(hand.bus.period_s, speed)
    left = _LeftEnabled(hand, protocol)
    heard = _FaultsHeard(hand, left, clock)
    if stops.first:  # during the checks: nothing sent yet
        raise ReplayInterrupted("", stops.first, stops.later)
    # the stop signals looked at between two frames: raised, a second one cut the stop
    # short, and Ctrl-Z suspended the replay (``to_bus``)
    from handctl.online.buslock import take_bus
    from handctl.online.busspec import parse_spec

    # one handctl host per bus on this machine, as a run (``buslock``): held to the end
    bus_spec = parse_spec(spec, hand.bus, hand.source, "--to-bus")
    period_s = tally.period_s
    with open_bus(spec, hand.bus) as bus, take_bus(bus_spec, "this replay"):
        _nobody_else(bus, hand, spec, stops, heard)
        frames = logged_frames(recording, direction)

        def stop() -> tuple[str, str, str]:
            """The replay's stop of the nodes it left enabled, then the wait for every
            node's DISABLED: what was sent, what failed, what is only said."""
            stopped = left.stop(bus, period_s, sleep)
            return (stopped, *_confirm_disabled(bus, heard, hand.bus.period_s, sleep))

        try:
            _send_frames(frames, bus, tally, clock, sleep, stops, heard)
        except KeyboardInterrupt as exc:
            # a replay stopped midway (Ctrl-C, SIGTERM) left the hand under the last torques
            # sent, until the nodes' watchdog faulted them: stopped as a run stops
            raise ReplayInterrupted(_said(*stop(), heard), str(exc)) from None
        if stops.first:
            raise ReplayInterrupted(_said(*stop(), heard), stops.first, stops.later)
        # so did a log that ends with nodes enabled (a run killed, a log cut short), and a
        # replay a node went into FAULT under
        stopped, failed, warning = stop()
        counts = bus.transport_counts()
    report: dict[str, Any] = {
        "sent": tally.sent,
        "failed": tally.failed,
        "worst_late_ms": round(tally.worst_late * 1e3, 3),
        "shifted_ms": round(tally.shifted * 1e3, 3),
        "bus": spec,
        "speed": speed,
        "direction": direction,
    }
    if stopped:
        report["stopped"] = stopped
    failures = heard.told() + ([failed] if failed else [])
    if failures:
        report["node_fault"] = "; ".join(failures)
    warnings = [warning] if warning else []
    if tally.sent and counts.get("datagrams_sent") == 0:
        # The unix bus makes its directory if it is not there, and a send with nobody else
        # in it succeeds: "N frames sent, 0 failed" to a mistyped directory looked like a
        # replay somebody had heard. (A CAN bus without a listener has no ACK, and says so.)
        warnings.append(
            f"no other participant was on {spec}: nobody received the frames "
            "(is the listener's bus directory this one?)"
        )
    if warnings:
        report["warning"] = "; ".join(warnings)
    return report


def _said(stopped: str, failed: str, warning: str, heard: _FaultsHeard) -> str:
    """What a replay interrupted says of its stop: what it sent, what failed, in one."""
    return "; ".join(x for x in (stopped, *heard.told(), failed, warning) if x)


class _Tally:
    """What a replay sent: frames that went and that the bus refused, how late it was."""

    def __init__(self, period_s: float, speed: float) -> None:
        self.speed = speed
        self.period_s = period_s / speed  # s, a loop period as sent
        self.sent = self.failed = 0
        self.worst_late = self.shifted = 0.0  # s


def _send_frames(
    frames: Iterator[tuple[int, int, bytes, bool]],
    bus: HandBus,
    tally: _Tally,
    clock: Callable[[], float],
    sleep: Callable[[float], None],
    stops: StopNotes,
    heard: _FaultsHeard,
) -> None:
    """Send ``frames`` (``logged_frames``) at their times, listening to the nodes once a
    period, until the last, a stop signal, or what the nodes say stops the replay."""
    left, period_s = heard.left, tally.period_s
    start: float | None = None
    first = 0
    listened = -math.inf
    for log_time, frame_id, data, _ in frames:
        if start is None:
            start, first = clock(), log_time
        due = start + (log_time - first) * 1e-9 / tally.speed
        wait = due - clock()
        if wait > 0:
            _nap(wait, due, clock, sleep, stops)
        else:
            tally.worst_late = max(tally.worst_late, -wait)
            if -wait > period_s:
                start -= wait
                tally.shifted -= wait
        if stops.first:
            break
        if due - listened >= period_s:  # what the nodes say, once a period
            listened = due
            if heard.hear(bus.drain(), bus.events()):
                if heard.foreign:
                    left.estop(bus)  # at once, before the stop's zeros (row 45)
                break
        if bus.send(frame_id, data):
            tally.sent += 1
            left.sent(frame_id, data)
        else:
            tally.failed += 1


def _nobody_else(
    bus: HandBus, hand: HandConfig, spec: str, stops: StopNotes, heard: _FaultsHeard
) -> None:
    """Nobody else commands the nodes, before the first frame: a replay onto a hand a run
    drives fought it frame by frame, neither's limits holding for the nodes (``otherhost``).
    A stop signal while it listened ends the replay as one during the checks: nothing sent.
    Nor is a node in FAULT from before: a replay clears no fault (a run's
    ``--reset-node-faults`` does), and onto a hand a killed run had left faulted it sent its
    frames, then said a node "went into FAULT while the replay had it enabled" and left
    enabled by it, both untrue (found by an outside audit). Nor a node of another hand
    config (its Feedback stream of another length): the replay enabled it and sent torques
    before it noticed (an outside audit); nor more rejected Feedback frames than the hand's
    reject limit, as a run's start-up refuses them. Nor a joint resting outside its
    soft limits, which stops any run before any torque: a replay onto a hand whose fingers
    had sagged past a limit enabled every node and sent its torques (an outside audit)."""
    from handctl.online.otherhost import refuse_another_host

    faulted: list[str] = []
    refuse_another_host(bus, hand, spec, "this replay", lambda f: faulted.extend(heard.faulted(f)))
    if stops.first:
        raise ReplayInterrupted("", stops.first, stops.later)
    if heard.stranger:
        # first: the FAULT and the angles of a node of another config are not read
        raise HandctlError(
            f"{spec}: {heard.stranger}, heard before the replay sent anything: its frames are "
            "not that hand's (nothing was sent)"
        )
    if heard.rejected.said:
        raise HandctlError(
            f"{spec}: {heard.rejected.said}; heard before the replay sent anything (nothing "
            "was sent)"
        )
    if faulted:
        raise HandctlError(
            f"{spec}: {', '.join(dict.fromkeys(faulted))} in FAULT before the replay sent "
            "anything: a replay clears no fault (a run's --reset-node-faults does, once what "
            "faulted it is understood); nothing was sent"
        )
    outside = heard.outside_before()
    if outside:
        # as a run refuses to arm (safety.md #19): the hand at rest outside, nothing sent
        raise HandctlError(
            f"{spec}: a joint of the hand on the bus rests outside its soft limits: {outside}; "
            "no replay drives a hand from there, as no run does (nothing was sent)"
        )


def hand_needed(spec: str) -> ConfigError:
    """The refusal of a replay onto ``spec``, a bus a real hand may be on, without the hand
    config of that hand (``--hand``)."""
    where = "whose bus --to-bus hand names" if spec == "hand" else f"on {spec}"
    return ConfigError(
        "--hand",
        "",
        f"the config of the hand {where}, whose limits bound every command sent (the log's "
        "own hand config is part of what a tampered log can rewrite)",
        "nothing",
    )


class StopNotes(Protocol):
    """The stop signals noted while a replay sends (``handctl.stopsignals.Noted``): the
    first, and the ones after it."""

    first: str
    later: list[str]


class _NoStops:
    """No signal noted: a replay whose caller takes the signals as interrupts."""

    def __init__(self) -> None:
        self.first = ""
        self.later: list[str] = []


#: s, the longest sleep between two looks at a stop signal while a replay waits for a frame's
#: time: a log's silence (a start-up's seconds) held a Ctrl-C that long.
NAP_S = 0.05


def _nap(
    wait: float,
    due: float,
    clock: Callable[[], float],
    sleep: Callable[[float], None],
    stops: StopNotes,
) -> None:
    """Sleep ``wait`` s, until ``due`` on ``clock``, or until a stop signal is noted."""
    while wait > NAP_S and not stops.first:
        sleep(NAP_S)
        wait = due - clock()
    if wait > 0 and not stops.first:
        sleep(wait)


class ReplayInterrupted(KeyboardInterrupt):
    """A replay onto a bus interrupted; ``stopped`` says what was sent to stop the nodes it
    had left enabled ("" if none were), ``why`` the signal, ``ignored`` the ones that came
    while the stop was sent."""

    def __init__(self, stopped: str, why: str = "", ignored: Sequence[str] = ()) -> None:
        super().__init__(why or stopped)
        self.stopped = stopped
        self.why = why
        self.ignored = list(ignored)


def _checked_commands(
    recording: Recording, spec: str, direction: str, speed: float, hand: HandConfig | None
) -> HandConfig:
    """The hand whose limits bound the replay onto ``spec``, once the log's commands are
    within them (and within the recorded hand's); refused otherwise, before anything is
    sent."""
    from handctl.online.busspec import parse_spec

    require_topics(recording, (ch.CAN_RX, ch.CAN_TX), "--to-bus")
    recorded = recorded_hand(recording)
    assert recorded is not None
    if hand is None and parse_spec(spec, recorded.bus).interface not in SIMULATED_BUSES:
        # The recorded hand config is in the log, and its digest is no seal: a log whose
        # tau_max was raised and whose digest was computed again passed every check against
        # its own limits. On a bus where a real hand may listen, the limits are the
        # operator's.
        raise hand_needed(spec)
    if hand is not None:
        # first: a hand of another shape makes every later check's figures another hand's (a
        # rate limit refused, naming a joint of the log's, where the shapes differed: found
        # by an outside audit)
        check_shape(recorded, hand)
    check_pacing(recording, recorded, direction)
    check_commands(recording, recorded, direction, speed)
    check_command_gaps(recording, recorded, direction, speed)
    if hand is not None:
        check_commands(recording, hand, direction, speed, on_bus=True)
    return hand if hand is not None else recorded


class _FaultsHeard:
    """What the nodes of the hand on the bus say of themselves in their Feedback (its state,
    its joints' angles), as far as it stops a replay.

    A node heard in FAULT while the replay had it enabled: the hand stopped following the log
    (the nodes' command watchdog timed out on a replay that fell behind, on a loaded host),
    and the replay went on sending to a faulted hand and exited 0, as if it had been
    replayed. A joint outside its soft limits (the hand's on the bus), before the first frame
    or while the replay had its node enabled: the replay watched no angle, and onto a hand
    whose fingers hung past a limit it enabled every node and sent its torques, exit 0, where
    a run stops before any torque (found by an outside audit).

    A Feedback that is not to be read (another length, a bad CRC) is a rejected frame, held
    to the hand's reject limit as a run holds them (REJECT_RATE, ``_Rejected``)."""

    def __init__(
        self,
        hand: HandConfig,
        left: _LeftEnabled,
        clock: Callable[[], float] = time.perf_counter,
    ) -> None:
        # once, not once a period as the replay listens
        from handctl.online.drivers.finger import fault_names, parse_feedback, rebooted
        from handctl.protocol import NodeState

        self._fault_names, self._parse, self._fault = fault_names, parse_feedback, NodeState.FAULT
        self._enabled, self._rebooted, self._clock = NodeState.ENABLED, rebooted, clock
        self.left = left
        layouts = [(finger, left.layouts[finger.node_id]) for finger in hand.fingers]
        self.feedback = {ls.feedback.frame_id: (finger, ls.feedback) for finger, ls in layouts}
        self.heartbeat = {ls.heartbeat.frame_id: (finger, ls.heartbeat) for finger, ls in layouts}
        #: each node's last Heartbeat uptime (ms) and when it was heard (s, on the clock)
        self._uptimes: dict[int, tuple[int, float]] = {}
        #: the bus hand's soft limits, and each node's first joint among them
        self.limits = JointLimits.from_hand(hand, left.protocol)
        starts = itertools.accumulate((len(f.joints) for f in hand.fingers), initial=0)
        self._first_joint = dict(zip((f.node_id for f in hand.fingers), starts, strict=False))
        #: rad, each joint's angle as its node's last good Feedback said (NaN: none heard yet)
        self.angles = np.full(len(self.limits.names), math.nan)
        #: what stopped the replay (a node in FAULT, a joint outside, ...) and what was
        #: heard after it (another sender during the wait for DISABLED), in order
        self.reasons: list[str] = []
        #: how many times the replay listened, and each node's last two good Feedback states
        #: with the listen that heard each (the wait for DISABLED reads them)
        self.listens = 0
        self.recent: dict[int, collections.deque[tuple[int, int]]] = {}
        #: a node heard answering with a Feedback of another length (another hand config),
        #: before the first frame ("": none)
        self.stranger = ""
        #: the hand's command identifiers: each one's message name and node
        self.commands = {
            frame_id: (("NodeCommand" if is_command else "TorqueCommand"), node)
            for frame_id, (node, is_command) in left.of_id.items()
        }
        #: what another sender on one of them was first heard sending ("": none), and the
        #: reason it is among ``reasons``
        self.foreign = self._foreign_said = ""
        self._rejects_told = False
        self.rejected = _Rejected(hand, clock)

    def faulted(self, frames: Sequence[Any]) -> list[str]:
        """The nodes of the hand ``frames`` (``Frame``s) say are in FAULT, enabled by the
        replay or not, each as "node N (name, its fault bits)"; the angles they say kept."""
        out = []
        for frame in frames:
            found = self.feedback.get(frame.arbitration_id)
            if found is None:
                continue
            # one of another length skipped, a node of another config was enabled and sent
            # torques before the replay noticed it, once it listened to the nodes it had
            # enabled; now ``stranger``, once its stream keeps that length
            if not self.rejected.accepted(*found, frame.data):
                self.stranger = self.rejected.stranger
                continue
            _, bits = self._read(found[0], found[1], frame.data)
            if bits is not None:
                out.append(f"node {found[0].node_id} ({found[0].name}, {'+'.join(bits)})")
        return out

    def outside_before(self) -> str:
        """The joints outside their soft limits by the Feedback heard so far, as a run says
        them before any torque (with the command that brings each back); "" if none."""
        outside = angle_violations(self.angles, self.limits)
        if not outside:
            return ""
        return outside_text(outside[0], self.angles, self.limits, True)

    def _read(
        self, finger: FingerConfig, layout: Layout, data: bytes
    ) -> tuple[int, list[str] | None]:
        """The angles a Feedback ``data`` of ``layout`` (its length and CRC checked) says
        kept; the node's state it says, and the names of the fault bits it says if it says
        FAULT ("no fault bits" for none), None if it does not."""
        feedback = self._parse(layout.decode(data)[1])
        first = self._first_joint[finger.node_id]
        joints = len(finger.joints)
        self.angles[first : first + joints] = feedback.angles[:joints]
        if feedback.state != self._fault:
            return feedback.state, None
        return feedback.state, self._fault_names(feedback.fault_bits) or ["no fault bits"]

    def hear(self, frames: Sequence[Any], events: Sequence[Any] = ()) -> bool:
        """Whether a node the replay had enabled said FAULT in ``frames`` (``Frame``s), or
        DISABLED after it had said ENABLED, or rebooted, or a joint of one outside its soft
        limits; or a node's Feedback frames were rejected past the reject limit; or another
        sender was heard on one of the hand's command identifiers (a frame, or a remote frame
        among the bus's ``events``). What it was is ``first``."""
        self.listens += 1
        if self._another_sender(frames, events):
            return True
        for frame in frames:
            found = self.feedback.get(frame.arbitration_id)
            if found is not None:
                said = self._feedback(*found, frame.data)
            elif frame.arbitration_id in self.heartbeat:
                said = self._heartbeat(*self.heartbeat[frame.arbitration_id], frame.data)
            else:
                continue
            if said:
                self.reasons.append(said)
                return True
        return False

    @property
    def first(self) -> str:
        """What stopped the replay ("": nothing the nodes said)."""
        return self.reasons[0] if self.reasons else ""

    def told(self) -> list[str]:
        """Every reason heard, another sender's with what became of the e-stop."""
        return [
            r + (self.left.estop_said() if r == self._foreign_said else "") for r in self.reasons
        ]

    def disabled_since(self, node: int, listen: int) -> bool:
        """Whether ``node``'s last good Feedback, heard after ``listen``, says it is not
        ENABLED."""
        recent = self.recent.get(node)
        if not recent:
            return False
        at, state = recent[-1]
        return at > listen and state != self._enabled

    def enabled_since(self, node: int, listen: int) -> bool:
        """Whether ``node``'s last two good Feedback, both heard after ``listen``, say it is
        ENABLED: the second was sent after the node had heard what came before the first."""
        recent = self.recent.get(node, ())
        return len(recent) == 2 and all(at > listen and s == self._enabled for at, s in recent)

    def names(self, nodes: Sequence[int]) -> str:
        return ", ".join(f"node {n} ({self.left.fingers[n].name})" for n in nodes)

    def _feedback(self, finger: FingerConfig, layout: Layout, data: bytes) -> str:
        """What stops the replay in a Feedback ``data`` of ``finger``'s ("": nothing)."""
        if not self.rejected.accepted(finger, layout, data):
            # a node of another hand config on the bus (fewer joints a node, another
            # protocol): the recorded hand's enable was taken, its Feedback never read,
            # so its FAULT went unheard and the replay sent on to the end, exit 0. Said
            # so of one frame of another length, any peer's on the id stopped the
            # replay, blaming another hand config (an outside audit): that is said once
            # the node's own stream keeps the length, the rest held to the reject limit
            if not self.rejected.said or self._rejects_told:
                return ""
            self._rejects_told = True
            return f"{self.rejected.said}, and the replay stopped there"
        node = finger.node_id
        state, bits = self._read(finger, layout, data)
        self.recent.setdefault(node, collections.deque(maxlen=2)).append((self.listens, state))
        if node not in self.left.enabled:
            return ""
        if bits is not None:
            return (
                f"node {node} ({finger.name}) went into FAULT ({', '.join(bits)}) "
                "while the replay had it enabled: the hand stopped following the log, and "
                "the replay stopped there"
            )
        if state == self._enabled:
            self.left.said_enabled.add(node)
        elif node in self.left.said_enabled:
            # A node that rebooted comes back DISABLED and takes none of the log's
            # torques: the replay sent the rest of the log to it and exited 0 (an outside
            # audit). Not a DISABLED from before the enable: the node has said ENABLED since
            # the replay's last node command to it (``_LeftEnabled.said_enabled``).
            return (
                f"node {node} ({finger.name}) said DISABLED while the replay had it enabled, "
                "after it had said ENABLED: it rebooted, or something else disabled it, and "
                "takes none of the log's torques; the replay stopped there"
            )
        return self._outside(finger)

    def _heartbeat(self, finger: FingerConfig, layout: Layout, data: bytes) -> str:
        """What stops the replay in a Heartbeat ``data`` of ``finger``'s: its uptime gone
        back while the replay had the node enabled, a reboot ("": nothing)."""
        if not layout.crc_ok(data):
            return ""
        node, now = finger.node_id, self._clock()
        uptime = int(layout.decode(data)[1][1])
        last = self._uptimes.get(node)
        self._uptimes[node] = (uptime, now)
        if last is None or node not in self.left.enabled:
            return ""
        if not self._rebooted(last[0], uptime, round((now - last[1]) * 1e9)):
            return ""
        return (
            f"node {node} ({finger.name}) rebooted while the replay had it enabled (its "
            f"uptime went back from {last[0]} ms to {uptime} ms): it comes back DISABLED and "
            "takes none of the log's torques; the replay stopped there"
        )

    def _outside(self, finger: FingerConfig) -> str:
        """A joint of ``finger`` outside its soft limits under the replay's torque pushing it
        further out, as the replay says it ("": none)."""
        first = self._first_joint[finger.node_id]
        lows, highs = self.limits.angle_min_list, self.limits.angle_max_list
        # A joint outside is the replay's to stop when the torque it last sent the joint
        # pushes it further out: a joint that sinks out under no torque, or one towards
        # its range, is not driven there by the replay, as a run's controlled stop does
        # not fault a joint that sinks out while its torques ramp out (row 64). Stopped on
        # any joint outside, the replay of a run's end ramp onto a hand that sags ended
        # in a stop, exit 1, where the run had ended well (found by an outside audit).
        torques = self.left.torques.get(finger.node_id, ())
        for k, j in enumerate(range(first, first + len(finger.joints))):
            torque = torques[k] if k < len(torques) else 0.0
            below, above = self.angles[j] < lows[j], self.angles[j] > highs[j]
            if (below and torque < 0.0) or (above and torque > 0.0):
                return (
                    f"{outside_text(j, self.angles, self.limits, False)}: a joint of "
                    f"node {finger.node_id} ({finger.name}) left its soft limits with the "
                    f"replay's torque ({torque:+.4g} N·m) pushing it further, as a run "
                    "stops on ANGLE_LIMIT, and the replay stopped there"
                )
        return ""

    def _another_sender(self, frames: Sequence[Any], events: Sequence[Any]) -> bool:
        """Whether a frame on one of the hand's command identifiers is among ``frames``, or
        a remote frame on one among ``events``: the replay does not hear its own, so another
        host (or a forged command) commands the nodes beside it, and the nodes take whichever
        comes at their next counter. Listened for only before the first frame, a second
        host that began during the replay had node 1 for some 235 ticks, the replay's own
        commands rejected, until the node's reject limit latched it (an outside audit)."""
        from handctl.online.bus import BusEventKind

        if self.foreign:
            return False  # said, and the e-stop sent, when it was first heard
        heard = [(f.arbitration_id, f.data) for f in frames if f.arbitration_id in self.commands]
        heard += [
            (e.frame_id, None)
            for e in events
            if e.kind is BusEventKind.REMOTE_FRAME and e.frame_id in self.commands
        ]
        if not heard:
            return False
        frame_id, data = heard[0]
        name, node = self.commands[frame_id]
        finger = self.left.fingers[node]
        what = "a remote frame (RTR)" if data is None else f"{len(data)} bytes: {data[:16].hex()}"
        self.foreign = (
            f"another sender on the hand's {name} id 0x{frame_id:03X} of node {node} "
            f"({finger.name}) while the replay sent ({what}): a second host or a forged "
            "command, which the nodes may obey instead of the replay's"
        )
        self._foreign_said = f"{self.foreign}, as a run stops on FOREIGN_COMMAND"
        self.reasons.append(self._foreign_said)
        return True


#: wrong-length Feedback frames of one node in a row, each at the counter after the one
#: before and no frame of the right length between, that are taken for its own stream: a
#: node of another config (a peer's frame, or a few, on the id are rejects)
ANOTHER_CONFIG_RUN = 5


class _Rejected:
    """The Feedback frames a replay does not read (another length, a bad CRC), counted per
    node against the hand's reject limit as a run counts them (more than
    ``safety.max_rejects_in_window`` within ``safety.reject_window_s`` is REJECT_RATE, row
    44), and a node whose own stream keeps another length, which is another hand config's.
    Once said (``said``), a replay stops there."""

    def __init__(self, hand: HandConfig, clock: Callable[[], float]) -> None:
        self._clock = clock
        self.limit = hand.safety.max_rejects_in_window
        self.window_s = hand.safety.reject_window_s
        self._times: dict[int, collections.deque[tuple[float, str]]] = {}
        #: per node, its run of frames of one wrong length: the length, how many, the
        #: last one's counter (None: too short to carry one)
        self._runs: dict[int, tuple[int, int, int | None]] = {}
        #: the first node heard keeping another length in its stream ("": none)
        self.stranger = ""
        #: what stops a replay: the stranger, or the first node over the reject limit
        self.said = ""

    def accepted(self, finger: FingerConfig, layout: Layout, data: bytes) -> bool:
        """Whether ``data``, a Feedback of ``finger``'s on ``layout``, is one to read; one
        that is not is counted."""
        node = finger.node_id
        if len(data) == layout.length and layout.crc_ok(data):
            self._runs.pop(node, None)
            return True
        kind = "crc"
        if len(data) != layout.length:
            kind = "length"
            counter = data[1] if len(data) > 1 else None
            length, count, last = self._runs.get(node, (-1, 0, None))
            own = (
                length == len(data)
                and counter is not None
                and last is not None
                and counter == (last + 1) & 0xFF
            )
            count = count + 1 if own else 1
            self._runs[node] = (len(data), count, counter)
            if count >= ANOTHER_CONFIG_RUN and not self.said:
                self.stranger = self.said = _another_config(finger, layout, len(data))
        now = self._clock()
        times = self._times.setdefault(node, collections.deque())
        times.append((now, kind))
        while now - times[0][0] > self.window_s:
            times.popleft()
        if len(times) > self.limit and not self.said:
            kinds = collections.Counter(k for _, k in times)
            self.said = (
                f"node {node} ({finger.name}): {len(times)} of its {layout.name} frames "
                f"rejected within {self.window_s:g} s ("
                + ", ".join(f"{k} {v}" for k, v in sorted(kinds.items()))
                + f"; at most {self.limit}, the hand's safety.max_rejects_in_window): frames "
                "on its identifier that are not its own, or its own corrupted, hide what it "
                "says, as a run stops on REJECT_RATE"
            )
        return False


def _another_config(finger: FingerConfig, layout: Layout, length: int) -> str:
    """A node that answers with a Feedback of ``length`` bytes, not its ``layout``'s, as the
    replay says it: a hand of another config is on the bus."""
    return (
        f"node {finger.node_id} ({finger.name}) answers with a {layout.name} of {length} "
        f"bytes where the recorded hand's is {layout.length}: a hand of another config is on "
        "the bus"
    )


class _LeftEnabled:
    """The nodes a replay's frames may have left enabled, and how to stop them: each node's
    last ``TorqueCommand`` and ``NodeCommand`` counters, and whether an enable or a torque
    was sent after its last disable."""

    def __init__(self, hand: HandConfig, protocol: WireProtocol) -> None:
        # what the stop needs, imported before the first frame goes: imported when the stop
        # began (``handctl.online.loop``, some 25 ms), the zero torque came 25-100 ms after
        # the last command, and the nodes' 10 ms watchdog had faulted them first
        from handctl.online.drivers.finger import FingerLayouts, make_command, make_node_command
        from handctl.online.loop import (
            DEFIANT_AFTER_PERIODS,
            DISABLE_CONFIRM_S,
            ZERO_TICKS_BEFORE_DISABLE,
        )
        from handctl.online.safety.watchdog import ticks_lasting
        from handctl.protocol import ESTOP_REASONS

        self._command = make_command
        self._node_command = make_node_command
        self._zero_ticks = ZERO_TICKS_BEFORE_DISABLE
        self.defiant_after = DEFIANT_AFTER_PERIODS
        self.confirm_polls = functools.partial(ticks_lasting, DISABLE_CONFIRM_S)
        #: the nodes the frames sent enabled at any time: whose DISABLED the end waits for
        self.ever: set[int] = set()
        #: the nodes whose disable the bus refused, owed until it or an e-stop goes
        self.disable_owed: set[int] = set()
        self.disable_refusals = 0
        #: the e-stop, which every node latches whatever it is told next (PROTOCOL.md)
        self._estop_layout = protocol.layout("EStop")
        self._estop_frames = tuple(
            self._estop_layout.encode(c, (ESTOP_REASONS["host_safety"],)) for c in range(256)
        )
        self._estop_counter = 0
        #: e-stops that went, and whether one the bus refused is owed
        self.estops = 0
        self.estop_owed = False
        self.fingers = {f.node_id: f for f in hand.fingers}
        #: the protocol the nodes speak (the recorded DBC's, or the one of ``--hand``)
        self.protocol = protocol
        self.layouts = {
            f.node_id: FingerLayouts.for_node(protocol, f.node_id) for f in hand.fingers
        }
        #: each command identifier: its node, and whether it is the node's NodeCommand
        self.of_id = {
            frame_id: (node, frame_id == layouts.node_command.frame_id)
            for node, layouts in self.layouts.items()
            for frame_id in (layouts.command.frame_id, layouts.node_command.frame_id)
        }
        self.counters: dict[int, int] = {}
        self.enabled: set[int] = set()
        #: each node's torques (N·m) as its last TorqueCommand sent carried them
        self.torques: dict[int, tuple[float, ...]] = {}
        #: the nodes whose Feedback said ENABLED since the replay's last node command to
        #: them: a DISABLED after that is not one sent before the enable (``_FaultsHeard``)
        self.said_enabled: set[int] = set()

    def sent(self, frame_id: int, data: bytes) -> None:
        found = self.of_id.get(frame_id)
        if found is None:
            return
        node, is_command = found
        layouts = self.layouts[node]
        counter, values = (layouts.node_command if is_command else layouts.command).decode(data)
        self.counters[frame_id] = counter
        if not is_command:
            self.torques[node] = values  # N·m, per joint slot, as last sent
        else:
            self.said_enabled.discard(node)
        if is_command and int(values[0]) == NODE_COMMANDS["disable"]:
            self.enabled.discard(node)
        elif not is_command or int(values[0]) == NODE_COMMANDS["enable"]:
            self.enabled.add(node)
            self.ever.add(node)

    def estop(self, bus: Any, owed: bool = True) -> bool:
        """Send the e-stop (host safety), prepared: whether it went. One the bus refused is
        ``owed``, and the stop's ticks send it again until one goes; the one after a stop
        frame the bus refused is not: that frame is sent again, and the e-stop after it."""
        frame = self._estop_frames[self._estop_counter]
        went = _went(bus, self._estop_layout.frame_id, frame)
        if went:
            self._estop_counter = (self._estop_counter + 1) & 0xFF
            self.estops += 1
        self.estop_owed = owed and not went and not self.estops
        return went

    def estop_said(self) -> str:
        """What became of the e-stop, as the replay's failure says it."""
        if self.estops:
            return (
                "; the e-stop was sent: every node latches FAULT (ESTOP), which no enable "
                "lifts (a run's --reset-node-faults clears it)"
            )
        return "; the e-stop could not be sent (the bus refused it)"

    def stop(self, bus: Any, period_s: float, sleep: Callable[[float], None]) -> str:
        """Zero torque for as many periods as a run's stop, then disable, to every node left
        enabled; what was done, or "" when no node was. An e-stop owed goes on each tick.

        Each frame the bus refuses keeps its counter for the next (the node would take the
        next for a skip), and the e-stop follows it, as a run's stop frames do; a disable
        refused is owed until it or an e-stop goes (``resend``). Sent blind, a refused
        disable left the node ENABLED and the replay said it had stopped it."""
        if self.estop_owed:
            self.estop(bus)
        nodes = sorted(self.enabled)
        if not nodes:
            return ""
        zero_refused = 0
        for tick in range(self._zero_ticks + 1):
            for node in nodes:
                layout = self.layouts[node].command
                zero = (0.0,) * len(layout.signals)
                if not self._send(bus, layout, zero):
                    zero_refused += 1
                    self._estop_after_a_refusal(bus)
            if tick < self._zero_ticks:
                sleep(period_s)
            if self.estop_owed:
                self.estop(bus)
        self.disable_owed = set(nodes)
        self.resend(bus)
        self.enabled.clear()
        said = (
            f"node(s) {', '.join(map(str, nodes))} left enabled by the frames sent: zero "
            "torque and a disable sent after them, as a run's stop does"
        )
        if zero_refused:
            said += f" (the bus refused {zero_refused} of the zero-torque frames)"
        return said

    def resend(self, bus: Any) -> None:
        """The disable to the nodes still owed it, each on its next counter, and the e-stop
        after any the bus refuses, until one or the other goes."""
        for node in sorted(self.disable_owed):
            layout = self.layouts[node].node_command
            if self._send(bus, layout, "disable"):
                self.disable_owed.discard(node)
        if self.disable_owed:
            self.disable_refusals += 1
            self._estop_after_a_refusal(bus)
        if self.estops:
            self.disable_owed.clear()  # the e-stop went in its place: every node latches it

    def _send(self, bus: Any, layout: Layout, what: tuple[float, ...] | str) -> bool:
        """A zero torque (``what`` the torques) or a node command (its name) on ``layout``,
        at the next counter, which only a frame that went uses up."""
        frame_id = layout.frame_id
        counter = (self.counters.get(frame_id, -1) + 1) & 0xFF
        if isinstance(what, str):
            frame = self._node_command(layout, counter, what)
        else:
            frame = self._command(layout, counter, what)
        went = _went(bus, *frame)
        if went:
            self.counters[frame_id] = counter
        return went

    def _estop_after_a_refusal(self, bus: Any) -> None:
        """The e-stop after a stop frame the bus refused, unless one has gone already."""
        if not self.estops:
            self.estop(bus, owed=False)


def _went(bus: Any, frame_id: int, data: bytes) -> bool:
    """Whether the bus took a frame of the replay's stop: the stop goes on whatever the bus
    does, a send that raised included."""
    try:
        return bool(bus.send(frame_id, data))
    except Exception:
        return False


#: frames a drain of the wait for DISABLED may take: all there are
_EVERY_FRAME = 1 << 30


def _confirm_disabled(
    bus: HandBus, heard: _FaultsHeard, period_s: float, sleep: Callable[[float], None]
) -> tuple[str, str]:
    """Listen after the replay's last frame or its stop, as a run does after its disable
    (``Runtime._confirm_disabled``), until every node the replay enabled and heard from says
    it is no longer ENABLED, for ``DISABLE_CONFIRM_S`` (and a few periods past
    ``DEFIANT_AFTER_PERIODS``) at most; a disable the bus refused is sent again meanwhile.
    What failed (a node that goes on saying ENABLED, which gets the e-stop; a disable that
    never went; another sender heard) and what is only said (a node not heard disabled in
    time, which its watchdog stops), "" each when none.

    A node that ignored the log's disable was left ENABLED, the replay saying nothing and
    exiting 0, until its watchdog latched FAULT (TIMEOUT) (an outside audit)."""
    left = heard.left
    nodes = [n for n in sorted(left.ever) if n in heard.recent]
    if not nodes and not left.disable_owed:
        return "", ""  # no node of the hand heard: nobody to confirm (a listener, a tool)
    polls = max(left.confirm_polls(period_s), left.defiant_after + 3)

    # Every frame waiting heard first, and every one in each poll: a replay that fell behind
    # has a backlog of the nodes' frames from before the disable, which a drain of a
    # bounded number left for the polls after, the nodes taken for defiant on their old
    # ENABLED (found running it against a simulated hand on a loaded host)
    def listen() -> None:
        heard.hear(bus.drain(limit=_EVERY_FRAME), bus.events())
        if heard.foreign and not left.estops:  # heard now, or its e-stop refused before
            left.estop(bus)

    listen()
    start = heard.listens
    failed: list[str] = []
    # A node heard ENABLED past the threshold has disobeyed, whatever it says after: its
    # command watchdog latches FAULT (TIMEOUT) 10 ms after the last command, which a wait
    # that ran late (a loaded host) heard, and took for the node stopped (exit 0)
    defiant: set[int] = set()
    for _ in range(polls):
        sleep(period_s)
        if left.estop_owed:
            left.estop(bus)
        if left.disable_owed:
            left.resend(bus)
        listen()
        defiant.update(n for n in nodes if heard.enabled_since(n, start + left.defiant_after))
        if not left.disable_owed and all(
            n in defiant or heard.disabled_since(n, start) for n in nodes
        ):
            break
    if left.disable_owed:
        failed.append(
            f"the bus refused the disable of node(s) {', '.join(map(str, left.disable_owed))} "
            f"{left.disable_refusals} time(s), and the e-stop after it: a node still ENABLED "
            "stops only when its command watchdog latches FAULT (TIMEOUT)"
        )
    if defiant:
        for _ in range(polls):  # the last word the replay has: until the bus takes it
            if left.estop(bus):
                break
            sleep(period_s)
        failed.append(
            f"{heard.names(sorted(defiant))} went on saying ENABLED after the disable"
            + left.estop_said()
        )
    quiet = [n for n in nodes if n not in defiant and not heard.disabled_since(n, start)]
    warnings = []
    if left.disable_refusals and not left.disable_owed:
        warnings.append(
            f"the bus refused the stop's disable {left.disable_refusals} time(s) before it "
            "went" + (" or the e-stop in its place" if left.estops else "")
        )
    if quiet:
        warnings.append(
            f"{heard.names(quiet)} not heard disabled within {polls * period_s * 1e3:g} ms of "
            "the disable (last heard ENABLED, or silent since); a node that hears no command "
            f"for {COMMAND_WATCHDOG_S * 1e3:g} ms sets its torque to zero and latches FAULT "
            "(TIMEOUT), which the next run clears with --reset-node-faults"
        )
    return "; ".join(failed), "; ".join(warnings)


def check_pacing(recording: Recording, hand: HandConfig, direction: str = "both") -> None:
    """Refuse, before anything is sent, a log whose frame is logged at another time than its
    tick: the recorder stamps each frame with its tick's time, and a replay sends it then.
    One frame moved an hour on held the replay (every earlier frame sent, the nodes enabled)
    silent for that hour; nothing else read the frame's time."""
    ticks: dict[int, int] = {}
    for _, log_time, msg in iter_decoded(recording, (ch.TIMING,)):
        ticks[int(msg["tick"])] = log_time
    if not ticks:
        _check_no_commands(recording, hand, direction)
        return
    order = sorted(ticks)
    _check_no_hole(recording, order)
    _check_no_gap(recording, ticks, order, _first_command_ns(recording, hand, direction))
    slack = round(hand.bus.period_s * 1e9)
    # a frame of no logged tick is one of the start-up's, before the first tick: one dated
    # among the ticks was put in (a run logs none there; frames of tick -1 set at 3 s went out)
    first, before = min(ticks.values()) - SILENT_START_NS, min(ticks.values()) + slack
    for topic, log_time, msg in iter_decoded(recording, DIRECTION_TOPICS.get(direction, ())):
        due = ticks.get(int(msg.get("tick", -1)))
        late = abs(log_time - due) > slack if due is not None else not first <= log_time <= before
        if late:
            raise ConfigError(
                str(recording.path),
                f"{topic} frame 0x{msg['id']:03X} of tick {msg.get('tick')}",
                "a frame logged at its tick's time"
                + ("" if due is None else f" ({due} ns, within {slack} ns)")
                + ", as the recorder stamps it (nothing was sent)",
                Description(f"log time {log_time} ns"),
            )


def _command_ids(hand: HandConfig) -> set[int]:
    """The identifiers a host commands ``hand``'s nodes on (TorqueCommand, NodeCommand)."""
    return {f.can_ids.torque_command for f in hand.fingers} | {
        f.can_ids.node_command for f in hand.fingers
    }


def _check_no_commands(recording: Recording, hand: HandConfig, direction: str) -> None:
    """Refuse a log of no tick row that holds a command frame: a run sends its commands on
    its ticks and logs a row for each (a start-up sends at most its enable before the first),
    so only a log whose rows were taken out has them, and with no row no frame's time was
    held to anything: a log whose ``/loop/timing`` channel was dropped (and its end record's
    tick count with it) and whose frames were moved 30 s on went out, enabled the nodes and
    then sent nothing for 30 s (an outside audit)."""
    commands = _command_ids(hand)
    for log_time, frame_id, data, is_rx in logged_frames(recording, direction):
        if frame_id in commands:
            raise ConfigError(
                str(recording.path),
                f"channel {ch.TIMING}",
                "a tick row for every tick a run sent its commands on (nothing was sent: "
                "without them no frame's time is held to its tick's)",
                Description(f"none, and the {_frame_at(log_time, frame_id, data, is_rx)}"),
            )


def _check_no_hole(recording: Recording, ticks: Sequence[int]) -> None:
    """Refuse a log whose ticks are not one after the other: a run records every tick, so a
    tick missing is a hole in the file (a chunk taken out of a log without its summary, or
    records the writer dropped), and the frames on either side of it would go out as if
    one period apart. Such a log read as cut short, not damaged, and went onto the bus whole
    (exit 0), commands on both sides of a 60 ms gap."""
    for before, after in itertools.pairwise(ticks):
        if after != before + 1:
            raise ConfigError(
                str(recording.path),
                f"{ch.TIMING} tick {before + 1}",
                "every tick between the first and the last, as a run records them (nothing "
                "was sent: the frames on either side of a hole are not the run's)",
                Description(f"ticks {before + 1}..{after - 1} missing, the log goes on at {after}"),
            )


def _first_command_ns(recording: Recording, hand: HandConfig, direction: str) -> int | None:
    """The log time of the first command frame (an enable, a torque) the log holds, or None."""
    commands = _command_ids(hand)
    for log_time, frame_id, _, _ in logged_frames(recording, direction):
        if frame_id in commands:
            return log_time
    return None


def _check_no_gap(
    recording: Recording,
    ticks: dict[int, int],
    order: Sequence[int],
    first_command_ns: int | None,
) -> None:
    """Refuse a log in which one tick comes longer after the one before than the nodes'
    command watchdog (``COMMAND_WATCHDOG_S``), once a command has been sent
    (``first_command_ns``). A run stops on LOOP_OVERRUN before its nodes'
    watchdog would (``most_misses_before_watchdog``), so a run that went on never logs such
    a gap; one whose times were edited does. Sent, the nodes held the last torque through
    the gap: a log whose times jumped three years 0.8 s in went out for 0.8 s, enabled the
    nodes, and then sent nothing until killed. (A run that did stall that long stopped
    there on LOOP_OVERRUN, and its nodes timed out: its log's gap is the same refusal.)
    A gap before the first command holds no torque and no enabled node: a real-time run's
    start-up, listening to its nodes on a loaded host, stalls so, and its log was refused
    (an outside audit). ``order``: the ticks of ``ticks`` (tick -> log time), sorted."""
    most_ns = round(COMMAND_WATCHDOG_S * 1e9)
    for before, after in itertools.pairwise(order):
        if first_command_ns is None or ticks[after] <= first_command_ns:
            continue  # nothing sent yet: nothing held through the gap
        gap = ticks[after] - ticks[before]
        if not 0 <= gap <= most_ns:
            raise ConfigError(
                str(recording.path),
                f"{ch.TIMING} tick {after}",
                f"a tick logged within the nodes' {COMMAND_WATCHDOG_S * 1e3:g} ms command "
                "watchdog after the one before, as a run that went on logs them (nothing was "
                "sent: through the gap the nodes would hold the last torque until their "
                "watchdog faulted them)",
                Description(f"{gap * 1e-9:.9g} s after tick {before}"),
            )


#: the most commands of one id a replay may send at once (with none for a loop period before):
#: a run's stop after an exception sends its zeros and its disable back to back without a
#: clock, six at the most
COMMAND_BURST = 8
#: ns: how long before the first timed tick a frame may be logged (a start-up that waits for
#: its nodes, at most its enable timeout, before its first timed tick)
SILENT_START_NS = 60_000_000_000


def shape_text(hand: HandConfig) -> str:
    """A hand's nodes and their joint counts, as a refusal names them: ``node N (NAME) 3
    joints, ...``."""
    return ", ".join(f"node {f.node_id} ({f.name}) {len(f.joints)} joints" for f in hand.fingers)


def check_shape(recorded: HandConfig, hand: HandConfig) -> None:
    """Refuse a ``--hand`` whose nodes are not the recorded hand's, node by node with as many
    joints each: the frames' checks go by ids and lengths, and a node of 5 joints recorded
    and one of 4 on the bus share a TorqueCommand's 12 bytes, so the fifth joint's torque went
    out in what the node on the bus reads as padding, and the log's Feedback frames, of
    another length than that node's, went out beside them (an outside audit)."""
    mine = [(f.node_id, len(f.joints)) for f in recorded.fingers]
    theirs = [(f.node_id, len(f.joints)) for f in hand.fingers]
    if mine != theirs:
        raise ConfigError(
            "--hand",
            "",
            f"a hand of the recorded shape ({shape_text(recorded)}), since the log's frames "
            "are that hand's (nothing was sent)",
            Description(f"{hand.source}: {shape_text(hand)}"),
        )


def check_commands(
    recording: Recording,
    hand: HandConfig,
    direction: str = "both",
    speed: float = 1.0,
    on_bus: bool = False,
) -> int:
    """Refuse, before anything is sent, a log whose frames hold a command the run's safety
    supervisor would never have let through; returns how many commands were checked.

    A log's command frames are what the supervisor let through, so a replay onto a bus (where
    a hand may listen) sends nothing it would refuse, unless the log was altered. So every
    frame with a command's id is checked, whichever channel holds it: a ``TorqueCommand`` or
    ``NodeCommand`` must be of the recorded protocol's length with a good CRC, and address a
    node of the recorded hand; each joint's torque must lie within ±``tau_max`` (and the
    torques a command carries beyond a finger's joints be zero), and it may change from the
    node's previous command by at most the rate limit over the time between the two as they
    are sent, the logged time over ``speed`` (one loop period of the log at least), unless it
    moves towards zero, as a stop does. Judged on the logged time, a replay at ``--speed 4``
    put four times the rate limit on the wire.

    ``on_bus``: ``hand`` is the one on the bus (``--hand``), not the recorded one: its own
    protocol's frame ids and its limits, each refusal naming it."""
    protocol = protocol_for(hand) if on_bus else recorded_protocol(recording) or protocol_for(hand)
    whose = "--hand's" if on_bus else "the recorded hand's"
    torque: dict[int, tuple[Layout, FingerConfig]] = {}
    other: dict[int, Layout] = {}
    stream: dict[int, int] = {}  # each node's NodeCommand id: its TorqueCommand id
    for finger in hand.fingers:
        torque[finger.can_ids.torque_command] = (
            protocol.layout("TorqueCommand", finger.node_id),
            finger,
        )
        other[finger.can_ids.node_command] = protocol.layout("NodeCommand", finger.node_id)
        stream[finger.can_ids.node_command] = finger.can_ids.torque_command
    # the log's own ticks (their spacing and lateness are what the slack is for), or the
    # hand's on the bus if its loop is faster: a log re-sealed to say 250 Hz was given four
    # times the slack of the 1 kHz hand it went to
    logged_period_s = (recorded_hand(recording) or hand).bus.period_s
    period_ns = round(min(logged_period_s, hand.bus.period_s) * 1e9)
    # what each joint may still change by (N·m), per command id: a bucket filled at the rate
    # limit over the time between a node's commands as they are sent, up to two periods'
    # worth. The supervisor allows one period's step a tick; the second period is the slack
    # a real-time log needs for a tick that ran late (the next one comes sooner). Judged on
    # the time since the previous command alone, with one period at least, any number of
    # commands stacked at one log time each got a whole step: 40 of them put 0.6 N·m on the
    # wire within a millisecond.
    period_s = period_ns * 1e-9 / speed
    last: dict[int, tuple[int, tuple[float, ...], list[float]]] = {}
    nodes = _NodeStates(stream)
    rate = _CommandRate(period_ns)
    checked = 0
    # the commands the bus refused since each id's last that went: the supervisor took each
    # for applied and stepped on from it, so the node, which kept its last torque, takes
    # their steps with the next that goes. A run whose bus refused two commands in a row
    # was refused here for a frame the supervisor had let through (an outside audit)
    refused: collections.Counter[int] = collections.Counter()
    for log_time, frame_id, data, is_rx in logged_frames(
        recording, direction, refused=lambda _, frame_id: refused.update((frame_id,))
    ):
        refuse = functools.partial(_refused, recording, log_time, frame_id, data, is_rx)
        entry = torque.get(frame_id)
        layout = entry[0] if entry is not None else other.get(frame_id)
        if layout is None and _aliases(frame_id, (*torque, *other)):
            raise refuse(
                "",
                f"no 29-bit frame whose low 11 bits are a command id of {whose} nodes (a "
                f"controller that keeps 11 bits takes it for 0x{frame_id & 0x7FF:03X})",
                f"29-bit id 0x{frame_id & 0x1FFFFFFF:X}",
            )
        if layout is None:
            named = node_message(frame_id)
            if named is not None and named[0] in ("TorqueCommand", "NodeCommand"):
                raise refuse(
                    "",
                    f"a command to one of {whose} nodes "
                    f"({', '.join(str(f.node_id) for f in hand.fingers)})",
                    f"{named[0]} to node {named[1]}",
                )
            continue
        checked += 1
        if not rate.take(frame_id, log_time):
            raise refuse(
                "",
                f"at most one {layout.name} to its node a loop period as sent "
                f"({period_s * 1e3:.3g} ms at --speed {speed:g}), {COMMAND_BURST} at once at "
                "most, as a run sends them",
                f"more, {COMMAND_BURST + 1} within {COMMAND_BURST * period_s * 1e3:.3g} ms "
                "or faster",
            )
        if not layout.crc_ok(data):
            raise refuse(
                "",
                f"a {layout.name} frame of {layout.length} bytes with a good CRC",
                f"{len(data)} bytes, "
                + ("a bad CRC" if len(data) == layout.length else "a wrong length"),
            )
        where = functools.partial(_frame_at, log_time, frame_id, data, is_rx)  # when refused
        counter, values = layout.decode(data)
        if entry is None:
            command = _node_command(recording, where, values[0])
            nodes.in_sequence(recording, where, layout.name, frame_id, counter)
            stream_id = nodes.command(frame_id, command)
            if stream_id is not None:
                last.pop(stream_id, None)  # zero applied from here: the next a first command
            continue
        finger = entry[1]
        # each joint's rate limit in counts of its signal's resolution a second: the budget
        # is kept in counts, the supervisor keeping every torque on that grid (``_torque_problem``)
        rates = [
            j.rate_limit / s.scale for j, s in zip(finger.joints, layout.signals, strict=False)
        ]
        # a node's first command (since its last disable or enable too): from zero, the
        # bucket full
        first = (log_time, (0.0,) * len(values), [2 * r * period_s for r in rates])
        before_ns, before, budget = last.get(frame_id, first)
        dt = max(0, log_time - before_ns) * 1e-9 / speed
        periods = 2 + refused.pop(frame_id, 0)
        budget = [
            min(periods * r * period_s, b + r * dt) for r, b in zip(rates, budget, strict=True)
        ]
        problem = _torque_problem(layout, finger, values, before, budget, speed, period_s)
        if problem is not None and on_bus:
            problem = (problem[0], f"{problem[1]} in --hand {hand.source}", problem[2])
        if problem is not None:
            raise refuse(*problem)
        nodes.in_sequence(recording, where, layout.name, frame_id, counter)
        if nodes.baseline(frame_id):
            # not applied: the node stays at zero, and the command after it is judged from
            # there (from this one, the node stepped from zero by that command's change and
            # this one's together)
            values = (0.0,) * len(values)
        for i, (tau, was) in enumerate(zip(values, before, strict=False)):
            if i < len(budget) and not _towards_zero(tau, was):
                budget[i] = max(0.0, budget[i] - _counts(tau - was, layout.signals[i].scale))
        # the budget's clock never runs back: a command dated before the one it follows
        # gets nothing, and the next is measured from the later of the two (from the earlier,
        # commands dated 0.7 ms back put 1.75 times the rate limit on the wire)
        last[frame_id] = (max(log_time, before_ns), values, budget)
    return checked


def check_command_gaps(
    recording: Recording, hand: HandConfig, direction: str = "both", speed: float = 1.0
) -> None:
    """Refuse, before anything is sent, a ``--speed`` that spaces the commands to a node the
    log has enabled further apart on the wire than the nodes' command watchdog
    (``COMMAND_WATCHDOG_S``): each node would time out and latch a fault. Commands a run sent
    1 ms apart went out more than 10 ms apart below ``--speed 0.1``, and every node faulted
    at once; the gap between ticks was held to the watchdog (``_check_no_gap``) only as
    logged, never as sent. The commands' own times are read (from a node's enable or first
    command to its disable), ``hand`` being the recorded one whose frames they are (its
    ``NodeCommand`` values checked by ``check_commands`` first). A gap past the watchdog as
    logged is the log's own, refused as such whatever its tick rows say."""
    protocol = recorded_protocol(recording) or protocol_for(hand)
    node_commands = {
        f.can_ids.node_command: (f.node_id, protocol.layout("NodeCommand", f.node_id))
        for f in hand.fingers
    }
    torques = {f.can_ids.torque_command: f.node_id for f in hand.fingers}
    since: dict[int, int] = {}  # ns, each enabled node's last command
    widest = 0  # ns, the longest a node the log had enabled went without a command
    most_ns = round(COMMAND_WATCHDOG_S * 1e9)
    for log_time, frame_id, data, is_rx in logged_frames(recording, direction):
        node = torques.get(frame_id)
        disable = False
        if node is None and frame_id in node_commands:
            node, layout = node_commands[frame_id]
            disable = layout.decode(data)[1][0] == NODE_COMMANDS["disable"]
        if node is None:
            continue
        gap = log_time - since[node] if node in since else 0
        if gap > most_ns:
            # as logged: the ticks' rows hold each frame to its tick, but not a frame that
            # is missing (a node's commands taken out for 20 ms, every other check passed)
            raise ConfigError(
                str(recording.path),
                _frame_at(log_time, frame_id, data, is_rx),
                f"a command to node {node} within the nodes' {COMMAND_WATCHDOG_S * 1e3:g} ms "
                "command watchdog after its previous one while the log has it enabled, as a "
                "run sends them (nothing was sent: through the gap the node would hold its "
                "last torque until its watchdog faulted it)",
                Description(f"{gap * 1e-9:.9g} s after the one before"),
            )
        widest = max(widest, gap)
        if disable:
            del since[node]  # a node disabled has no watchdog to feed
        else:
            since[node] = log_time
    # Slowed, the commands may come as far apart as the watchdog less what the nodes' own
    # 1 ms tick and the bus take of it (``NODE_TIMING_MARGIN_S``, as a run's missed ticks are
    # bounded), or as the log has them if it has them further: at exactly the watchdog, the
    # speed the refusal named, every node faulted after a few frames (found by an outside
    # audit). A replay at its speed or faster spaces them as the run did, which the nodes took.
    allowed = max(widest, most_ns - round(NODE_TIMING_MARGIN_S * 1e9))
    if widest > allowed * speed:
        slowest = -(-widest * 1000 // allowed) / 1000  # rounded up to a thousandth
        raise ConfigError(
            "--speed",
            "",
            f"{slowest:g} or faster (nothing was sent): the log's commands to a node it has "
            f"enabled come up to {widest * 1e-6:g} ms apart, and slowed further they reach "
            f"the nodes more than {allowed * 1e-6:g} ms apart, within "
            f"{NODE_TIMING_MARGIN_S * 1e3:g} ms of their {COMMAND_WATCHDOG_S * 1e3:g} ms "
            "command watchdog (their own tick and the bus take that much of it), which "
            "faults every node",
            speed,
        )


def _node_command(recording: Recording, where: Callable[[], str], command: float) -> float:
    """A NodeCommand's ``command``, enable or disable, as the run sent them; never a fault
    reset, which clears what a node latched for a reason and is a person's decision for the
    run in front of them (``run --reset-node-faults``), not a replay's: one recorded so, or
    written into a log, went onto the bus unasked. Nor a command value the protocol does not
    define. ``where``: the frame, as ``_frame_at``."""
    if command not in (NODE_COMMANDS["enable"], NODE_COMMANDS["disable"]):
        raise ConfigError(
            str(recording.path),
            f"{where()}: Command",
            f"enable ({NODE_COMMANDS['enable']}) or disable ({NODE_COMMANDS['disable']}) "
            f"(nothing was sent): a replay never resets the faults a node latched, nor "
            f"sends a command the protocol does not define; a run does, asked "
            f"(`handctl run recipe ... --reset-node-faults`)",
            Description(
                "a fault reset" if command == NODE_COMMANDS["fault_reset"] else f"{command:g}"
            ),
        )
    return command


class _NodeStates:
    """What each node does with the log's commands as far as its applied torque goes: whether
    the frames so far leave it ENABLED (a replay finds its nodes DISABLED, ``_nobody_else``),
    and whether its next TorqueCommand is the one an enable makes its stream's baseline,
    never applied (PROTOCOL.md, "A new host"). A node disabled, or enabled again, applies
    zero whatever it was last sent, so its next commands are judged from zero: judged from
    the last command before, a disable and an enable in place of two commands took a node
    from 0 to 0.31 N·m in one frame (found by an outside audit)."""

    def __init__(self, streams: dict[int, int]) -> None:
        self._stream = streams  # each node's NodeCommand id: its TorqueCommand id
        self._enabled: set[int] = set()  # TorqueCommand ids
        self._opening: set[int] = set()
        self._counters: dict[int, int] = {}  # each command id: its last frame's counter

    def in_sequence(
        self, recording: Recording, where: Callable[[], str], name: str, frame_id: int, counter: int
    ) -> None:
        """Refuse a command whose counter is not the one after the previous frame's of its id
        (the first of each id any): a node takes a command only at its next counter and keeps
        what it applies through any other, so the commands after one out of sequence would
        be judged from a torque it never applied. Commands 101-109 of a ramp two counters
        apart, each within the rate limit, then one at the next counter: the node held zero
        through them and took the tenth's 0.2 N·m in one step (found by an outside audit).
        A run never logs one: a frame the bus refused is logged as not sent, and gives its
        counter back (``HandDriver.send``)."""
        previous = self._counters.get(frame_id)
        self._counters[frame_id] = counter
        if previous is not None and counter != (previous + 1) & 0xFF:  # 8 bits, PROTOCOL.md
            raise ConfigError(
                str(recording.path),
                f"{where()}: Counter",
                f"{(previous + 1) & 0xFF}, the one after the previous {name}'s, as a run sends "
                "them (nothing was sent): a node takes no command at another counter and "
                "keeps the torque it applies, so the commands after it would be judged from a "
                "torque the node never applied",
                counter,
            )

    def command(self, frame_id: int, command: float) -> int | None:
        """The TorqueCommand id of the node the ``command`` on NodeCommand id ``frame_id``
        disables or enables, its applied torque zero from here; None if it changes nothing
        (an enable of an enabled node keeps its torque and its stream)."""
        stream_id = self._stream[frame_id]
        enable = command == NODE_COMMANDS["enable"]
        if enable == (stream_id in self._enabled):
            return None
        for states in (self._enabled, self._opening):
            (states.add if enable else states.discard)(stream_id)
        return stream_id

    def baseline(self, frame_id: int) -> bool:
        """Whether the TorqueCommand on ``frame_id`` is its stream's baseline, not applied."""
        opening = frame_id in self._opening
        self._opening.discard(frame_id)
        return opening


def _aliases(frame_id: int, commands: Sequence[int]) -> bool:
    """A 29-bit frame whose low 11 bits are a command's id: a controller or a filter that
    keeps 11 bits takes it for that command, which no check of the command has seen."""
    return bool(frame_id & EXTENDED_ID_FLAG) and (frame_id & 0x7FF) in commands


class _CommandRate:
    """As many commands as a run sends: one a loop period of the log per node and message
    (at ``--speed`` s, one a period over s as sent), ``COMMAND_BURST`` at once at most (a stop
    after an exception sends its zeros and its disable without a clock). The same torque
    twenty times a tick, or fifty enables, were sent 1 µs apart."""

    def __init__(self, period_ns: int) -> None:
        self._per_ns = 1.0 / period_ns  # commands earned a logged ns
        self._left: dict[int, tuple[float, int]] = {}  # per id: may still send, counted when

    def take(self, frame_id: int, log_time: int) -> bool:
        """Whether one more command of ``frame_id`` at ``log_time`` is within the rate."""
        tokens, at = self._left.get(frame_id, (float(COMMAND_BURST), log_time))
        tokens = min(float(COMMAND_BURST), tokens + max(0, log_time - at) * self._per_ns)
        if tokens < 1.0:
            return False
        self._left[frame_id] = (tokens - 1.0, max(log_time, at))
        return True


def _counts(change: float, scale: float) -> int:
    """A change between two values of a signal of resolution ``scale``, in whole counts of
    it: both are on its grid (a frame carries nothing else), so the count is exact."""
    return abs(round(change / scale))


def _towards_zero(tau: float, was: float) -> bool:
    """A change a stop makes, which no rate limit holds back."""
    return 0 <= tau <= was or was <= tau <= 0


def _torque_problem(
    layout: Layout,
    finger: FingerConfig,
    values: tuple[float, ...],
    before: tuple[float, ...],
    budget: list[float],
    speed: float = 1.0,
    period_s: float = 0.0,
) -> tuple[str, str, float] | None:
    """What the supervisor would not have let through in one TorqueCommand (the signal, what
    it expects, the value), or None: a torque beyond a joint's ``tau_max``, a change beyond
    what its rate limit has left it (``budget``, in counts of the signal's resolution,
    ``check_commands``) unless towards zero, a torque for a joint the finger lacks.

    Judged on the signal's grid, with no slack a frame: the supervisor keeps every torque it
    applies on that grid within both limits (safety.md, row 63), so a run's frames need none.
    The resolution a frame spared (for logs of an encoder that rounded to the nearest) let a
    joint of rate limit 0.1 N·m/s at 1 kHz, whose step a tick is one resolution, ramp at
    twice that, and the half a resolution spared over ``tau_max`` let 0.05 N·m go out where
    ``tau_max`` was 0.04996 (found by an outside audit). ``GRID_SLACK`` of a count is
    floating-point rest, not a torque: a rate limit of 0.3 N·m/s gives 2.9999999999999996
    counts a millisecond, and the supervisor's 3."""
    for i, (signal, tau, was) in enumerate(zip(layout.signals, values, before, strict=True)):
        if i >= len(finger.joints):
            if tau != 0:
                joints = len(finger.joints)
                return signal.name, f"0 (the finger {finger.name} has {joints} joints)", tau
            continue
        joint = finger.joints[i]
        label = f"{signal.name} ({joint.name})"
        if not abs(tau) / signal.scale <= joint.tau_max / signal.scale + GRID_SLACK:
            return label, f"a torque within ±{joint.tau_max:g} N·m (its tau_max)", tau
        if (
            not _towards_zero(tau, was)
            and _counts(tau - was, signal.scale) > budget[i] + GRID_SLACK
        ):
            step = math.floor(budget[i] + GRID_SLACK) * signal.scale  # N·m, the largest on its grid
            return (
                label,
                f"a change of at most {step:.6g} N·m from the node's {was:g} N·m, its last "
                "command's or zero after a disable or an enable "
                f"(what its rate limit {joint.rate_limit:g} N·m/s has left since the "
                f"commands before, at most two periods' worth, {2 * period_s * 1e3:g} ms"
                + (
                    f" as sent, {2 * period_s * speed * 1e3:g} ms of the logged time at "
                    f"--speed {speed:g}"
                    if speed != 1.0
                    else ""
                )
                + f", in whole {signal.scale:g} N·m steps of its signal)",
                tau,
            )
    return None


def _frame_at(log_time: int, frame_id: int, data: bytes, is_rx: bool) -> str:
    """A logged frame as a refusal names it: its channel, id, bytes and log time."""
    return (
        f"{ch.CAN_RX if is_rx else ch.CAN_TX} frame 0x{frame_id:03X} {data.hex()} at log time "
        f"{log_time} ns"
    )


def _refused(
    recording: Recording,
    log_time: int,
    frame_id: int,
    data: bytes,
    is_rx: bool,
    signal: str,
    expected: str,
    found: object,
) -> ConfigError:
    where = _frame_at(log_time, frame_id, data, is_rx)
    return ConfigError(
        str(recording.path),
        f"{where}: {signal}" if signal else where,
        f"{expected}, as the supervisor lets a command through (nothing was sent)",
        found,
    )


def export(recording: Recording, fmt: str, out: str) -> dict[str, Any]:
    """Write the logged frames in a python-can log format (candump, asc, blf); what was
    written (``frames``, ``format``, ``path``, and a ``warning`` when the times are not the
    run's own)."""
    from handctl.recording.canlog import LOG_FORMATS, write_frames

    if fmt not in LOG_FORMATS:
        raise ConfigError("--export", "", "one of " + ", ".join(LOG_FORMATS), fmt)
    require_topics(recording, (ch.CAN_RX, ch.CAN_TX), "--export")
    hand = recorded_hand(recording, required=False)
    fd = hand.bus.fd if hand is not None else True
    started = recording.meta_int("handctl.command", "started_unix_ns", 0)
    frames = logged_frames(recording)
    first: list[int] = []

    def stamped() -> Iterator[tuple[float, int, bytes, bool, bool]]:
        for log_time, frame_id, data, is_rx in frames:
            if not first:
                first.append(log_time)
            yield ((started + log_time - first[0]) * 1e-9, frame_id, data, is_rx, fd)

    existed = Path(out).exists()
    try:
        # whole or not at all: written in place, a full disk left half a log under the name
        # and the earlier export, which the command may replace, gone
        with whole_file(Path(out)) as beside:
            count = write_frames(beside, fmt, stamped())
    except OSError as exc:
        raise HandctlError(
            f"--export: {escaped(out)} could not be written ({exc.strerror or exc}); "
            + left_as_it_was(existed)
        ) from None
    report: dict[str, Any] = {"frames": count, "format": fmt, "path": out}
    warnings = []
    if not started:
        # stamped from 1970 without a word: the times are the log's own, from its first frame
        warnings.append(
            "the log does not say when its run started (handctl.command.started_unix_ns): "
            "the frames are stamped from 0, the first frame's time"
        )
    if recording.damaged:
        # the frames either side of the hole follow one another in the file, as if the run
        # had sent nothing between them (the export said only how many it wrote)
        warnings.append(
            f"the log is DAMAGED ({recording.problem}): the exported frames have a hole "
            "there, the frames either side of it one after the other"
        )
    if warnings:
        report["warning"] = "; ".join(warnings)
    return report
