"""The one table of faults: what each means and how the hand is stopped when it happens.

Two stop categories, as in the usual stop categories of machine safety:

- ``IMMEDIATE``: zero torque in the very frames of the tick that detected the fault. For faults
  where the host can no longer trust what it commands or measures (non-finite torques, lost
  feedback, a node or bus in trouble, e-stop): holding any torque on bad information is worse
  than letting the fingers go limp.
- ``RAMP``: a ramp from the last applied torque to zero at the rate limit, and within
  ``RAMP_BOUND_S`` whatever the rate limit (never slower than a controlled stop). For
  faults where the information is still good but the situation is not (a joint past its soft
  limit, a torque sensor disagreeing with the command, late ticks): a ramp lets the grasped
  objects settle instead of being dropped by a step.

Every fault latches until an explicit reset; ``docs/faults.md`` is generated from this table.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass


class StopCategory(enum.Enum):
    IMMEDIATE = "immediate zero torque"
    RAMP = "ramp to zero"


#: The ramp of a RAMP stop reaches zero within this time (s), whatever the torque was.
RAMP_BOUND_S = 0.05

#: A controlled stop (Ctrl-C, SIGTERM, SIGHUP, the time budget) takes the torque out at the
#: joint's rate limit, and reaches zero within this time (s) whatever the rate limit: a hand
#: configured with a slow rate limit (0.03 N·m/s takes 15 s from 0.45 N·m) must not keep its
#: torque on for as long after the operator asked for it off. Where the rate limit is the
#: faster (every shipped hand: 30 ms from tau_max), the stop is as the rate limit makes it.
STOP_BOUND_S = 0.5


class FaultCode(enum.IntEnum):
    NON_FINITE_TORQUE = 1
    WRONG_SHAPE = 2
    ANGLE_LIMIT = 3
    FEEDBACK_TIMEOUT = 4
    HEARTBEAT_LOST = 5
    NODE_FAULT = 6
    NODE_STATE = 7
    NODE_REBOOT = 8
    LOOP_OVERRUN = 9
    TDT_MISMATCH = 10
    TDT_STUCK = 11
    BUS_ERROR = 12
    ESTOP = 13
    RECIPE_ABORT = 14
    STARTUP = 15
    # An exception inside the run, one code per stage of the tick it came from (the loop reads
    # the stage from the traceback). The stop does not use the stage that raised: zero-torque
    # and disable frames encoded at start-up, sent without the codec (``handctl/online/loop.py``).
    POLL_EXCEPTION = 16
    DECODE_EXCEPTION = 17
    ESTIMATOR_EXCEPTION = 18
    RUNNER_EXCEPTION = 19
    SUPERVISOR_EXCEPTION = 20
    ENCODE_EXCEPTION = 21
    SEND_EXCEPTION = 22
    RECORD_EXCEPTION = 23
    HOOK_EXCEPTION = 24
    CLOCK_EXCEPTION = 25
    STATUS_EXCEPTION = 26
    RUN_EXCEPTION = 27
    RX_BACKLOG = 30
    NODE_CONTRADICTION = 31
    REJECT_RATE = 32
    FOREIGN_COMMAND = 33
    RECORDING_LOST = 34


@dataclass(frozen=True)
class FaultSpec:
    code: FaultCode
    category: StopCategory
    meaning: str


FAULTS: dict[FaultCode, FaultSpec] = {
    spec.code: spec
    for spec in (
        FaultSpec(
            FaultCode.NON_FINITE_TORQUE,
            StopCategory.IMMEDIATE,
            "a desired torque is NaN or infinite (never clamped)",
        ),
        FaultSpec(
            FaultCode.WRONG_SHAPE,
            StopCategory.IMMEDIATE,
            "the desired torque vector does not have one value per joint",
        ),
        FaultSpec(
            FaultCode.ANGLE_LIMIT, StopCategory.RAMP, "a joint angle is outside its soft limits"
        ),
        FaultSpec(
            FaultCode.FEEDBACK_TIMEOUT,
            StopCategory.IMMEDIATE,
            "no valid feedback from a node for longer than the feedback age limit",
        ),
        FaultSpec(
            FaultCode.HEARTBEAT_LOST,
            StopCategory.IMMEDIATE,
            "no valid heartbeat from a node for longer than the heartbeat limit",
        ),
        FaultSpec(
            FaultCode.NODE_FAULT,
            StopCategory.IMMEDIATE,
            "a node reports FAULT (its own fault bits say why)",
        ),
        FaultSpec(
            FaultCode.NODE_STATE,
            StopCategory.IMMEDIATE,
            "a node left ENABLED while the host was commanding torque",
        ),
        FaultSpec(
            FaultCode.NODE_REBOOT,
            StopCategory.IMMEDIATE,
            "a node's uptime went backwards: it rebooted",
        ),
        FaultSpec(
            FaultCode.LOOP_OVERRUN,
            StopCategory.RAMP,
            "three consecutive ticks missed their deadline",
        ),
        FaultSpec(
            FaultCode.TDT_MISMATCH,
            StopCategory.RAMP,
            "a TDT torque disagrees with the applied command beyond the tolerance, "
            "throughout the window",
        ),
        FaultSpec(
            FaultCode.TDT_STUCK,
            StopCategory.RAMP,
            "a TDT reading did not change at all over the window while the command did (given "
            "three of the sensor's lags to answer once the command has moved)",
        ),
        FaultSpec(
            FaultCode.BUS_ERROR,
            StopCategory.IMMEDIATE,
            "bus-off, or command frames that could not be sent",
        ),
        FaultSpec(
            FaultCode.ESTOP,
            StopCategory.IMMEDIATE,
            "an e-stop was requested (operator, signal, or a node)",
        ),
        FaultSpec(
            FaultCode.RECIPE_ABORT,
            StopCategory.RAMP,
            "a recipe abort condition held, or a phase ran past its time limit",
        ),
        FaultSpec(
            FaultCode.STARTUP,
            StopCategory.IMMEDIATE,
            "a node did not answer, or was not in the expected state, while starting",
        ),
        FaultSpec(
            FaultCode.POLL_EXCEPTION,
            StopCategory.IMMEDIATE,
            "the tick's poll (draining the bus, taking its events) raised an exception",
        ),
        FaultSpec(
            FaultCode.DECODE_EXCEPTION,
            StopCategory.IMMEDIATE,
            "checking or decoding a received frame raised an exception",
        ),
        FaultSpec(
            FaultCode.ESTIMATOR_EXCEPTION,
            StopCategory.IMMEDIATE,
            "the object estimator raised an exception",
        ),
        FaultSpec(
            FaultCode.RUNNER_EXCEPTION,
            StopCategory.IMMEDIATE,
            "the recipe runner raised an exception",
        ),
        FaultSpec(
            FaultCode.SUPERVISOR_EXCEPTION,
            StopCategory.IMMEDIATE,
            "the safety supervisor (checks, limiter, state machine) raised an exception",
        ),
        FaultSpec(
            FaultCode.ENCODE_EXCEPTION,
            StopCategory.IMMEDIATE,
            "encoding a command frame raised an exception (e.g. a torque the wire cannot carry)",
        ),
        FaultSpec(
            FaultCode.SEND_EXCEPTION,
            StopCategory.IMMEDIATE,
            "sending the command frames raised an exception",
        ),
        FaultSpec(
            FaultCode.RECORD_EXCEPTION,
            StopCategory.IMMEDIATE,
            "the record sink raised an exception",
        ),
        FaultSpec(
            FaultCode.HOOK_EXCEPTION, StopCategory.IMMEDIATE, "a tick hook raised an exception"
        ),
        FaultSpec(
            FaultCode.CLOCK_EXCEPTION,
            StopCategory.IMMEDIATE,
            "waiting for the tick raised an exception (in lockstep: stepping the peer)",
        ),
        FaultSpec(
            FaultCode.STATUS_EXCEPTION,
            StopCategory.IMMEDIATE,
            "the tick's accounting or the status-line callback raised an exception",
        ),
        FaultSpec(
            FaultCode.RUN_EXCEPTION,
            StopCategory.IMMEDIATE,
            "the run raised an exception outside a tick's stages (start-up, enabling, "
            "the final disable)",
        ),
        FaultSpec(
            FaultCode.RX_BACKLOG,
            StopCategory.IMMEDIATE,
            "a drain left frames waiting: more arrived than the bus can carry between two "
            "ticks (a flood), so what the host reads next is already old",
        ),
        FaultSpec(
            FaultCode.NODE_CONTRADICTION,
            StopCategory.IMMEDIATE,
            "a node's reports contradict each other or the protocol: latched or reserved "
            "fault bits outside FAULT, ENABLED after FAULT without a fault reset, a state the "
            "protocol does not define, one counter with two contents (a second sender), or a "
            "Status of another protocol version than the host's",
        ),
        FaultSpec(
            FaultCode.REJECT_RATE,
            StopCategory.IMMEDIATE,
            "more frames of one node rejected within the window than the safety section "
            "allows (a replayed or corrupted stream may be hiding what the node says)",
        ),
        FaultSpec(
            FaultCode.RECORDING_LOST,
            StopCategory.RAMP,
            "the recording writer of a run with a log ended while the run went on, or did "
            "not take the run's records in time (its rings overflowed): the rest of the run "
            "would drive the hand unrecorded",
        ),
        FaultSpec(
            FaultCode.FOREIGN_COMMAND,
            StopCategory.IMMEDIATE,
            "a frame on one of the host's own command identifiers (TorqueCommand, "
            "NodeCommand) was heard: another host, or a forged command, that the nodes may "
            "obey instead of this one",
        ),
    )
}


@dataclass(frozen=True)
class Fault:
    """One detected fault: the code, where (joint or node), and what was seen."""

    code: FaultCode
    detail: str
    tick: int

    @property
    def category(self) -> StopCategory:
        return FAULTS[self.code].category

    def __str__(self) -> str:
        return f"{self.code.name} at tick {self.tick}: {self.detail}"
