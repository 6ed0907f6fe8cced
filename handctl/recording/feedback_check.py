"""The re-run's check of the received frames: what its driver made of the logged frames,
against what the run's driver made of them.

The applied torques of a re-run can agree with the log while the frames it was fed do not: a
Feedback frame with one bit flipped fails its CRC, the driver rejects it, and an open-loop
phase goes on with the previous feedback to the same torques. So after each control tick's
poll the re-run's joint state (angles, TDT torques, feedback ages, node states and fault bits)
must be bit for bit the logged ``/hand/joint_state``, and the frames it rejected, by kind, the
logged ``rejected_frames`` events. A difference names the tick, the frame id and what differs.
"""

from __future__ import annotations

import math
import struct
from collections.abc import Sequence
from typing import Any

from handctl.config import HandConfig
from handctl.online.bus import Frame
from handctl.online.drivers.hand import HandDriver
from handctl.online.drivers.receiver import Reject
from handctl.protocol import Layout

#: Differences kept (the report lists the first few); a tampered log can differ every tick.
MAX_KEPT = 1000
#: Frames named per difference.
MAX_FRAMES_NAMED = 4


def _same_floats(logged: Sequence[float | None], rerun: Sequence[float]) -> list[int]:
    """Indices where two float vectors differ bit for bit (the log writes NaN as null)."""
    differ = []
    for i, (a, b) in enumerate(zip(logged, rerun, strict=False)):
        if a is None:
            if not math.isnan(b):
                differ.append(i)
        elif struct.pack("<d", a) != struct.pack("<d", b):
            differ.append(i)
    if len(logged) != len(rerun):
        differ += list(range(min(len(logged), len(rerun)), max(len(logged), len(rerun))))
    return differ


def _hex(frame: Frame) -> str:
    return f"0x{frame.arbitration_id:03X} {frame.data.hex()}"


class FeedbackCheck:
    """Compares the re-run driver's view of each tick's received frames with the log's."""

    def __init__(self, hand: HandConfig, driver: HandDriver) -> None:
        self.driver = driver
        self.joints = list(hand.joint_names)
        self.compared = 0
        self.mismatched_ticks = 0
        self.mismatches: list[str] = []
        self._slices: list[tuple[int, int]] = []
        start = 0
        for finger in hand.fingers:
            self._slices.append((start, start + len(finger.joints)))
            start += len(finger.joints)
        self._layouts: dict[int, Layout] = {
            fid: layout for node in driver.nodes for fid, (layout, _) in node.streams.items()
        }
        self._node_of: dict[int, int] = {
            fid: i for i, node in enumerate(driver.nodes) for fid in node.streams
        }
        self._logged: dict[str, int] = {}  # rejects the log reports, over the ticks handed out
        self._offset: dict[str, int] = {}  # differences already reported
        # The driver's own count lists (updated in place), and copies as of the last comparison.
        self._counts = [node.rejects.counts for node in driver.nodes]
        self._counts.append(driver.unexpected.counts)
        self._counts_seen = [list(c) for c in self._counts]
        self._node_seen = self._counts_seen[:-1]
        self._logged_more = False  # the log reported rejects since the last comparison
        self._pack: dict[int, struct.Struct] = {}

    # -- inputs --------------------------------------------------------------------------------
    def take(self, rejects: dict[str, int] | None) -> None:
        """The logged rejects of a tick the re-run is about to run (every tick, idle ones too:
        the recorder reports the rejects of idle ticks at the next control tick or at the
        end)."""
        if rejects:
            logged = self._logged
            for kind, count in rejects.items():
                logged[kind] = logged.get(kind, 0) + count
            self._logged_more = True

    # -- checks --------------------------------------------------------------------------------
    def tick(
        self, k: int, now_ns: int, joint_state: dict[str, Any] | None, rx: Sequence[Frame]
    ) -> None:
        """After control tick ``k``'s poll: the joint state and the rejects so far."""
        self.compared += 1
        problems = self._joint_state(k, now_ns, joint_state, rx)
        problems += self._rejects(k, rx)
        if problems:
            self.mismatched_ticks += 1
            room = MAX_KEPT - len(self.mismatches)
            self.mismatches += problems[: max(room, 0)]

    def end(self, k: int, rx: Sequence[Frame]) -> None:
        """After the run's last tick: the rejects of the ticks that only polled."""
        problems = self._rejects(k, rx)
        if problems:
            self.mismatched_ticks += 1
            self.mismatches += problems[: max(MAX_KEPT - len(self.mismatches), 0)]

    def _joint_state(  # noqa: C901 - compares every field of the state; to split
        self,
        k: int,
        now_ns: int,
        logged: dict[str, Any] | None,
        rx: Sequence[Frame],
    ) -> list[str]:
        if logged is None:
            return [f"tick {k}: the re-run polled feedback where the log has no joint state"]
        state = self.driver.state
        n = len(self.joints)
        pack = self._pack.get(n)
        if pack is None:
            pack = self._pack[n] = struct.Struct(f"<{n}d")
        angle, tdt = logged.get("angle_rad") or [], logged.get("tdt_torque_nm") or []
        ages = [now_ns - x if x >= 0 else -1 for x in state.feedback_ns.tolist()]
        node_state, node_faults = logged.get("node_state"), logged.get("node_fault_bits")
        try:
            same = state.angle.tobytes() == pack.pack(*angle) and state.tdt.tobytes() == pack.pack(
                *tdt
            )
        except (struct.error, TypeError):  # a wrong length, or null for NaN
            same = False
        if (
            same
            and ages == logged.get("feedback_age_ns")
            and (node_state is None or node_state == state.node_state)
            and (node_faults is None or node_faults == state.node_faults)
        ):
            return []
        # Something differs: say what, node by node, with the node's feedback frames.
        differ: dict[int, list[str]] = {}

        def add(node: int, text: str) -> None:
            differ.setdefault(node, []).append(text)

        for field, values, rerun in (
            ("angle_rad", angle, state.angle.tolist()),
            ("tdt_torque_nm", tdt, state.tdt.tolist()),
        ):
            for j in _same_floats(values, rerun):
                add(
                    self._node_of_joint(j),
                    f"{self._joint(j)} {field}: logged "
                    f"{values[j] if j < len(values) else 'nothing'}, re-run "
                    f"{rerun[j] if j < len(rerun) else 'nothing'}",
                )
        logged_ages = logged.get("feedback_age_ns") or []
        for j in range(max(len(ages), len(logged_ages))):
            a = logged_ages[j] if j < len(logged_ages) else None
            b = ages[j] if j < len(ages) else None
            if a != b:
                add(
                    self._node_of_joint(j),
                    f"{self._joint(j)} feedback_age_ns: logged {a}, re-run {b}",
                )
        for field, values, rerun_ints in (
            ("node_state", node_state, state.node_state),
            ("node_fault_bits", node_faults, state.node_faults),
        ):
            if values is not None and values != rerun_ints:
                for i in range(max(len(values), len(rerun_ints))):
                    a = values[i] if i < len(values) else None
                    b = rerun_ints[i] if i < len(rerun_ints) else None
                    if a != b:
                        add(i, f"{field}: logged {a}, re-run {b}")
        nodes = self.driver.nodes
        problems = []
        for i, texts in differ.items():
            if 0 <= i < len(nodes):
                layout = nodes[i].layouts.feedback
                frames = [f for f in rx if f.arbitration_id == layout.frame_id]
                what = f"{layout.name} 0x{layout.frame_id:03X}"
                heard = "; ".join(_hex(f) for f in frames[:MAX_FRAMES_NAMED]) or "none"
                problems.append(
                    f"tick {k}: {what} (frames in this tick: {heard}): the "
                    f"re-run's joint state from it is not the log's: "
                    f"{'; '.join(texts)}"
                )
            else:
                problems.append(
                    f"tick {k}: the joint state differs from the log: {'; '.join(texts)}"
                )
        return problems

    def _rejects(self, k: int, rx: Sequence[Frame]) -> list[str]:
        if not self._logged_more and self._counts == self._counts_seen:
            # Nothing new on either side (the counts ``reject_counts`` adds up), so as equal
            # as after the last comparison; ``reject_counts`` itself costs tens of µs.
            return []
        self._logged_more = False
        self._counts_seen = [list(c) for c in self._counts]
        rerun = self.driver.reject_counts()
        logged, offset = self._logged, self._offset
        problems = []
        node_counts = self._counts_seen[:-1]
        for kind in sorted(set(rerun) | set(logged)):
            have = rerun.get(kind, 0) - offset.get(kind, 0)
            want = logged.get(kind, 0)
            if have != want:
                offset[kind] = offset.get(kind, 0) + have - want  # reported once, not again
                frames = self._suspects(kind, node_counts, rx)
                named = "; ".join(_hex(f) for f in frames[:MAX_FRAMES_NAMED]) or "none"
                problems.append(
                    f"tick {k}: {kind} rejects: logged {want}, re-run {have} "
                    f"(frames in this tick: {named})"
                )
        self._node_seen = node_counts
        return problems

    def _suspects(
        self, kind: str, node_counts: list[list[int]], rx: Sequence[Frame]
    ) -> list[Frame]:
        """The tick's frames that can account for a difference in ``kind`` rejects."""
        layouts = self._layouts
        if kind == Reject.UNEXPECTED_ID.name.lower():
            return [f for f in rx if f.arbitration_id not in layouts]
        if kind == Reject.LENGTH.name.lower():
            return [
                f
                for f in rx
                if f.arbitration_id in layouts and len(f.data) != layouts[f.arbitration_id].length
            ]
        if kind == Reject.CRC.name.lower():
            return [
                f
                for f in rx
                if f.arbitration_id in layouts
                and len(f.data) == layouts[f.arbitration_id].length
                and not layouts[f.arbitration_id].crc_ok(f.data)
            ]
        changed = {
            i
            for i, (now, seen) in enumerate(zip(node_counts, self._node_seen, strict=True))
            if now != seen
        }
        ours = [f for f in rx if self._node_of.get(f.arbitration_id) in changed]
        return ours or list(rx)

    # -- helpers -------------------------------------------------------------------------------
    def _node_of_joint(self, j: int) -> int:
        for i, (start, stop) in enumerate(self._slices):
            if start <= j < stop:
                return i
        return -1

    def _joint(self, j: int) -> str:
        return self.joints[j] if 0 <= j < len(self.joints) else f"joint {j}"
