"""The simulated hand: the plant, its sensors and one emulated node per finger, as one bus peer.

The host cannot tell it from the real hand by its frames: it hears and speaks only through a
``HandBus``, with the ids, layouts, rates and rules of ``firmware_protocol/``. It runs in two
ways:

- **Lockstep**: the runtime calls ``step()`` after it has sent its commands; ``step`` drains
  them, runs the nodes, advances the plant one loop period and sends what the nodes send. Given
  the seed, two runs give the same frames, and a run goes as fast as the machine allows.
- **Free-running**: ``start()`` runs the same tick on its own 1 kHz timerfd in a thread, an
  independent peer as the real hand would be; ``standalone`` does so on any python-can bus for
  ``handctl sim --bus SPEC``.

One tick (1 ms, the protocol's node period): switch due faults; drain the bus and hand every
frame to every node (each node checks and counts what is not for it, as the spec says); the
nodes' watchdogs; the applied torques into the plant; one plant step; sensors; each node
publishes; the frames of the tick leave in identifier order, as CAN arbitration would send
frames queued together.

The emulated nodes do not hear one another's frames (python-can does not hand a bus what it
sent itself); a real node would only count them as unexpected ids. Frames an injector sends on
behalf of a foreign node (babbling) are heard, since they can matter (on id 0 they stop every
node). On an interface that echoes a sender's own frames (``udp_multicast``), the nodes hear
their own frames and count them as unexpected, as the spec says of "a frame sent by itself".
"""

from __future__ import annotations

import itertools
import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from operator import itemgetter
from pathlib import Path
from typing import Any

import numpy as np

from handctl.config import HandConfig
from handctl.errors import ConfigError, escaped
from handctl.hand_protocol import protocol_for
from handctl.online.bus import BusEventKind, HandBus, open_bus
from handctl.online.clock import collector_paused, request_realtime
from handctl.online.timerfd import PeriodicTimer
from handctl.protocol import NodeState
from handctl.sim.faults import FaultSchedule, Injector, load_scenario
from handctl.sim.firmware import EmulatedNode
from handctl.sim.params import NODE_TICK_NS, NODE_TICK_S, SimParams, parse_sim
from handctl.sim.plant import ObjectPose, Plant
from handctl.sim.sensors import EncoderModel, TdtModel

#: SCHED_FIFO priority of a free-running hand asked to run in real time: below the control
#: loop's (``request_realtime``'s 80), so the loop wins where the two share a core.
SIM_RT_PRIORITY = 70
#: A free-running hand that fell behind catches up by at most this many ticks at once; older
#: ones are counted as missed, so one long stall does not turn into a burst of frames.
MAX_CATCH_UP = 5
#: A standalone hand prints its status this often (s) ...
PROGRESS_PERIOD_S = 1.0
#: ... and asks whether it should go on this often (s): its host may have died.
WATCH_PERIOD_S = 0.1

_BY_ID = itemgetter(0)


@dataclass(frozen=True)
class GroundTruth:
    """What really happened, for logs and evaluation only; nothing on the bus carries it."""

    time: float  # s of simulated time
    objects: tuple[ObjectPose, ...]
    joint_angles: tuple[float, ...]  # rad, true (not quantised)
    joint_torques: tuple[float, ...]  # N·m, transmitted by the tendons


class SimulatedHand:
    """A MuJoCo hand behind emulated CAN nodes. ``seed=None`` takes the config's ``sim.seed``."""

    def __init__(
        self,
        hand: HandConfig,
        bus: HandBus,
        seed: int | None = None,
        faults: FaultSchedule | None = None,
        params: SimParams | None = None,
    ) -> None:
        self.hand = hand
        self.params = params if params is not None else parse_sim(hand)
        self.seed = self.params.seed if seed is None else seed
        self.protocol = protocol_for(hand)
        self.plant = Plant(hand, self.params)
        rng = np.random.default_rng(self.seed)
        self.tdt = TdtModel(hand, self.params.tdt, rng)
        self.encoders = EncoderModel(hand, self.params.encoder)
        self.nodes: tuple[EmulatedNode, ...] = tuple(
            EmulatedNode(
                f,
                self.protocol,
                tdt_range=self.params.tdt.range,
                encoder_max_step=self.params.encoder.max_step,
            )
            for f in hand.fingers
        )
        starts = itertools.accumulate((len(f.joints) for f in hand.fingers), initial=0)
        self._slices: list[tuple[int, int]] = list(itertools.pairwise(starts))
        self._node_slices = [
            (node, a, b) for node, (a, b) in zip(self.nodes, self._slices, strict=True)
        ]
        self.faults = faults if faults is not None else FaultSchedule()
        self.active: list[Injector] = []
        self._rx_filters: list[Injector] = []
        self._tx_filters: list[Injector] = []
        self._periodic: list[Injector] = []
        self._bus = bus
        # A python-can bus does not hand a sender its own frames, but a babbling node is heard
        # by the emulated nodes as well as by the host: such frames come back through here.
        self._loopback: list[tuple[int, bytes]] = []
        self.ticks = 0
        # Lockstep follows the host's loop period in whole node ticks; a period that is not a
        # whole number of milliseconds (a 400 Hz classic-CAN hand) alternates 2 and 3 ticks,
        # so simulated time never drifts from the host's.
        self._period_ns = round(hand.bus.period_s * 1e9)
        self._target_ns = 0
        self.frames_in = 0
        self.frames_out = 0  # frames handed to the bus; those it could not send: tx_failed
        self._in_burst = False
        self.bus_events = 0
        self.missed_ticks = 0
        self._lock = threading.Lock()
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._error: BaseException | None = None

    @property
    def tx_failed(self) -> int:
        """Frames of this hand (and its injectors) that did not go: the bus's count."""
        return self._bus.tx_failed

    # -- lockstep ---------------------------------------------------------------------------
    @property
    def time(self) -> float:
        """Simulated time (s): ticks run so far times 1 ms."""
        return self.ticks * NODE_TICK_S

    def step(self) -> None:
        """Advance one loop period of the hand config, in whole 1 ms node ticks (lockstep)."""
        if self._thread is not None:
            raise RuntimeError("the simulated hand is free-running: step() is for lockstep")
        with self._lock:
            self._target_ns += self._period_ns
            while self.ticks * NODE_TICK_NS < self._target_ns:
                self._tick()

    def _tick(self) -> None:  # noqa: C901 - the simulated nodes' whole tick; to split
        now = self.ticks * NODE_TICK_NS
        if self.faults.pending:
            for on, injector in self.faults.due(self.ticks):
                (self._activate if on else self._deactivate)(injector, now)
        bus = self._bus
        nodes = self.nodes
        if self._loopback:
            self._receive_loopback(now)
        frames = bus.drain()
        if frames:
            self.frames_in += len(frames)
            rx_filters = self._rx_filters
            for frame in frames:
                fid = frame.arbitration_id
                data = frame.data
                if rx_filters and not all(f.rx(fid, data) for f in rx_filters):
                    continue
                for node in nodes:
                    node.receive(fid, data, now)
        events = bus.events()
        if events:
            self.bus_events += len(events)
            for event in events:
                if event.kind is BusEventKind.REMOTE_FRAME and event.frame_id is not None:
                    for node in nodes:
                        node.remote(event.frame_id)
        applied: list[float] = []
        for node, a, b in self._node_slices:
            node.update(now)
            applied += node.applied[: b - a]
        plant = self.plant
        plant.set_torque_commands(applied)
        plant.step()
        tdt = self.tdt.sample(plant.transmitted_torques.tolist())
        angles = self.encoders.sample(plant.joint_angles.tolist())
        out: list[tuple[int, bytes]] = []
        for node, a, b in self._node_slices:
            node.publish(now, tdt[a:b], angles[a:b], out)
        out.sort(key=_BY_ID)
        for injector in self._tx_filters:
            filtered: list[tuple[int, bytes]] = []
            for fid, data in out:
                injector.tx(fid, data, now, filtered)
            out = filtered
        # Everything the tick puts on the bus, the nodes' frames and an injector's (a babbling
        # node's), leaves as one burst: on the unix bus one datagram, not one per frame, so a
        # flood cannot fill the host's queue of datagrams by itself.
        send = bus.send
        for fid, data in out:
            send(fid, data, more=True)
        self.frames_out += len(out)
        periodic = self._periodic
        if periodic:
            self._in_burst = True
            try:
                for injector in periodic:
                    injector.tick(self, now)
            finally:
                self._in_burst = False
        bus.flush()
        self.ticks += 1

    # -- faults -----------------------------------------------------------------------------
    def load_faults(self, path: str | Path) -> None:
        """Add the injectors of a scenario file to this hand's schedule."""
        for entry in load_scenario(path, self.hand):
            self.faults.add(entry.injector, entry.start, entry.stop)

    def activate(self, injector: Injector) -> None:
        """Switch an injector on now (from the next tick's point of view)."""
        with self._lock:
            self._activate(injector, self.ticks * NODE_TICK_NS)

    def deactivate(self, injector: Injector) -> None:
        """Switch an injector off now; a no-op if it is not on."""
        with self._lock:
            self._deactivate(injector, self.ticks * NODE_TICK_NS)

    def _activate(self, injector: Injector, now: int) -> None:
        if injector in self.active:
            return
        injector.start(self, now)
        self.active.append(injector)
        self._sort_hooks()

    def _deactivate(self, injector: Injector, now: int) -> None:
        if injector not in self.active:
            return
        self.active.remove(injector)
        self._sort_hooks()
        injector.stop(self, now)

    def _sort_hooks(self) -> None:
        self._rx_filters = [i for i in self.active if i.filters_rx]
        self._tx_filters = [i for i in self.active if i.filters_tx]
        self._periodic = [i for i in self.active if i.periodic]

    def joint_indices(self, node: int | None, joint: int | None) -> list[int]:
        """Indices into the joint vectors (config order) of ``joint`` (1-based) of node
        ``node`` (None: all)."""
        out: list[int] = []
        for finger, (a, b) in zip(self.hand.fingers, self._slices, strict=True):
            if node is not None and finger.node_id != node:
                continue
            if joint is None:
                out += range(a, b)
            elif 1 <= joint <= b - a:
                out.append(a + joint - 1)
        return out

    def node_list(self, node: int | None) -> list[EmulatedNode]:
        return [n for n in self.nodes if node is None or n.node_id == node]

    def send_frame(self, frame_id: int, data: bytes) -> bool:
        """Put a frame on the bus outside the nodes' schedule (injectors); during a tick it
        joins the tick's burst."""
        self.frames_out += 1
        return self._bus.send(frame_id, data, more=self._in_burst)

    def send_foreign_frame(self, frame_id: int, data: bytes) -> bool:
        """Put a frame on the bus as another node would (injectors): the emulated nodes hear
        it too, at the next tick, before what the host sent since."""
        self._loopback.append((frame_id, data))
        return self.send_frame(frame_id, data)

    def _receive_loopback(self, now: int) -> None:
        frames, self._loopback = self._loopback, []
        for fid, data in frames:
            for node in self.nodes:
                node.receive(fid, data, now)

    def send_error_frame(self, error_class: int = 0x004) -> bool:
        return self._bus.send_error_frame(error_class)

    # -- observation ------------------------------------------------------------------------
    def ground_truth(self) -> GroundTruth:
        """Object poses and true joint state now: for logs and evaluation, never for control."""
        with self._lock:
            plant = self.plant
            return GroundTruth(
                time=self.time,
                objects=plant.object_poses(),
                joint_angles=tuple(plant.joint_angles.tolist()),
                joint_torques=tuple(plant.transmitted_torques.tolist()),
            )

    def ground_truth_summary(self) -> dict[str, Any]:
        """A JSON-ready account of the run for a summary: where the objects ended up (and how
        far they moved), the nodes' states and counts, the faults that were injected."""
        truth = self.ground_truth()
        objects = {}
        for pose, start in zip(truth.objects, self.params.objects, strict=True):
            objects[pose.name] = {
                "x_m": round(pose.x, 6),
                "y_m": round(pose.y, 6),
                "angle_rad": round(pose.angle, 6),
                "moved_m": round(math.hypot(pose.x - start.x, pose.y - start.y), 6),
                "turned_rad": round(pose.angle - start.angle, 6),
            }
        return {
            "seed": self.seed,
            "time_s": round(truth.time, 6),
            "objects": objects,
            "nodes": {
                n.finger.name: {
                    "state": NodeState(n.state).name,
                    "fault_bits": n.fault_bits,
                    "accepted": n.accepted,
                    "reject_crc": n.reject_crc,
                    "reject_counter": n.reject_counter,
                    "reject_length": n.reject_length,
                    # Not a rejection: the other nodes' frames (and any foreign ones), which a
                    # node sees on the shared bus and leaves alone, about 2 per tick per node.
                    "other_ids_ignored": n.reject_unexpected,
                    "reboots": n.reboots,
                }
                for n in self.nodes
            },
            "frames_in": self.frames_in,
            "frames_out": self.frames_out,
            "tx_failed": self.tx_failed,
            "transport": self._bus.transport_counts(),
            "faults": [
                {"fault": e.injector.describe(), "start_s": e.start, "stop_s": e.stop}
                for e in self.faults
            ],
        }

    def sagged_idle(self) -> list[str]:
        """The joints past their soft limits while no node is enabled: no host drives the
        hand, and the fingers hang where gravity and their contacts take them. The shipped
        hand's distal joints pass their limits after about 45 s so (they rest on the table
        and creep outward), and every run then refuses to start (ANGLE_LIMIT before any
        torque): a standalone hand left waiting for a minute said nothing of it (found by an
        outside audit). Empty while a node is enabled, when a limit is the host's to watch."""
        if any(n.state == int(NodeState.ENABLED) for n in self.nodes):
            return []
        angles = self.plant.joint_angles
        return [
            f"{joint.name} at {angles[i]:+.3f} rad, limits [{joint.angle_min:+.2f}, "
            f"{joint.angle_max:+.2f}]"
            for i, joint in enumerate(self.hand.joints)
            if not joint.angle_min <= angles[i] <= joint.angle_max
        ]

    def status_line(self) -> str:
        states = " ".join(
            f"{n.finger.name}={NodeState(n.state).name}"
            + (f"(0x{n.fault_bits:02X})" if n.fault_bits else "")
            for n in self.nodes
        )
        return (
            f"t={self.time:.3f} s  {states}  rx={self.frames_in} tx={self.frames_out} "
            f"missed={self.missed_ticks}"
        )

    # -- free-running -----------------------------------------------------------------------
    @property
    def running(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    def start(self) -> None:
        """Run on a 1 kHz timer in a thread until ``stop``: an independent peer on the bus."""
        if self._thread is not None:
            raise RuntimeError("the simulated hand is already running")
        self._stop.clear()
        self._error = None
        self._thread = threading.Thread(target=self._run, name="simulated-hand", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        """Stop the timer thread (within a tick); re-raises what made it fail, if anything."""
        thread, self._thread = self._thread, None
        if thread is not None:
            self._stop.set()
            thread.join()
        if self._error is not None:
            error, self._error = self._error, None
            raise error

    def wait_stopped(self, timeout: float) -> bool:
        """Wait up to ``timeout`` s for the timer thread to be told to stop; True if it was."""
        return self._stop.wait(timeout)

    def _run(self) -> None:
        try:
            with PeriodicTimer(NODE_TICK_NS) as timer:
                while not self._stop.is_set():
                    expirations = timer.read()
                    if expirations > MAX_CATCH_UP:
                        self.missed_ticks += expirations - MAX_CATCH_UP
                        expirations = MAX_CATCH_UP
                    with self._lock:
                        for _ in range(expirations):
                            self._tick()
        except BaseException as exc:  # handed to the thread that calls stop()
            self._error = exc


def standalone(
    hand: HandConfig,
    bus_spec: str,
    seconds: float | None = None,
    progress: Callable[[str], None] | None = None,
    *,
    seed: int | None = None,
    faults: FaultSchedule | None = None,
    ground_truth: Callable[[dict[str, Any]], None] | None = None,
    realtime: bool = False,
    keep_running: Callable[[], bool] | None = None,
) -> str:
    """Run the simulated hand free on ``bus_spec`` for ``seconds`` (None: until Ctrl-C).

    ``progress`` gets a status line about once a second. Returns a summary for the CLI;
    ``ground_truth`` also receives the ground truth at the end (``--summary-json``, for a host
    that started this process and wants to report where the objects ended up).

    ``realtime`` asks for SCHED_FIFO (``SIM_RT_PRIORITY``) and locked memory for the node
    timer, as the hand's node controllers have a core each: at normal priority any other load
    on the machine can hold the node ticks back for milliseconds, and the host, rightly, stops
    on the feedback that did not come (what the system refuses goes to ``progress``).

    ``keep_running``, asked every ``WATCH_PERIOD_S``, ends the run when it turns False (the
    host that started this hand is gone), as Ctrl-C would.
    """
    if bus_spec == "sim":  # the one spelling ``parse_spec`` takes for it
        # ``sim`` names this very hand to the commands that listen to it: as the bus it is
        # to join, it is a user's mix-up (bad input), not a bus that failed to open
        raise ConfigError(
            "--bus",
            "",
            "the bus this simulated hand joins: unix:DIRECTORY (a host in another process), "
            "virtual:NAME, hand, or INTERFACE:CHANNEL; 'sim' is the simulated hand itself",
            bus_spec,
        )
    bus = open_bus(bus_spec, hand.bus)
    interrupted = False
    try:
        sim = SimulatedHand(hand, bus, seed=seed, faults=faults)
        started = time.monotonic()
        # the node timer must not wait for a full garbage collection
        with collector_paused():
            if realtime:
                # Asked here, by the thread that starts the timer thread, which inherits it;
                # after the collector's full collection (tens of ms of CPU): at SCHED_FIFO it
                # held the CPU that long without blocking, and a soft RLIMIT_RTTIME of 20 ms
                # ended the hand with SIGXCPU before its first tick.
                for refused in request_realtime(SIM_RT_PRIORITY):
                    if progress is not None:
                        progress(f"warning: {refused}")
            sim.start()
            try:
                deadline = None if seconds is None else started + seconds
                next_progress = started + PROGRESS_PERIOD_S
                sagged_said = False
                while sim.running:
                    now = time.monotonic()
                    wait = (
                        WATCH_PERIOD_S if deadline is None else min(WATCH_PERIOD_S, deadline - now)
                    )
                    if wait <= 0 or sim.wait_stopped(wait):
                        break
                    if keep_running is not None and not keep_running():
                        interrupted = True
                        break
                    if progress is not None and time.monotonic() >= next_progress:
                        next_progress += PROGRESS_PERIOD_S
                        progress(sim.status_line())
                    if progress is not None and not sagged_said and (sagged := sim.sagged_idle()):
                        sagged_said = True
                        progress(
                            "warning: with no torque on it the hand has hung past its soft "
                            f"limits ({'; '.join(sagged)}): a run on this hand now stops "
                            "before any torque (ANGLE_LIMIT). Start the simulated hand again "
                            "just before the run, or bring each joint back with handctl jog "
                            "JOINT --torque X --recover (docs/bringup.md)"
                        )
            except KeyboardInterrupt:
                interrupted = True
            finally:
                sim.stop()
    finally:
        bus.close()
    wall = time.monotonic() - started
    if ground_truth is not None:
        ground_truth(sim.ground_truth_summary())
    rtf = sim.time / wall if wall > 0 else 0.0
    return (
        f"simulated hand on {escaped(bus_spec)}: {sim.time:.3f} s simulated in {wall:.3f} s "
        f"(real-time factor {rtf:.3f}){', interrupted' if interrupted else ''}; "
        f"{sim.frames_in} frames in, {sim.frames_out} out, {sim.tx_failed} failed sends, "
        f"{sim.bus_events} bus events, {sim.missed_ticks} missed ticks; at the end: "
        + sim.status_line()
    )
