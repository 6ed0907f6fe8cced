"""The only module that imports python-can: open a bus from a spec, drain it, send on it.

Everything above this module sees ``Frame`` and ``BusEvent`` values, never python-can objects,
so the loop cannot be surprised by a python-can exception: a full transmit queue, an error frame
or a bus-off comes out as a typed event that safety can act on, and the tick goes on.

Bus specs:
- ``sim``: the simulated hand. Resolved by the caller (the CLI starts the simulated hand as a
  peer on a private virtual channel and opens ``virtual:<that channel>`` here), because the
  online plane never imports the simulation.
- ``hand``: the interface and channel written in the hand config's ``bus`` section.
- ``virtual:NAME``: python-can's in-process virtual bus (tests, lockstep runs).
- ``socketcan:can0``: a Linux SocketCAN interface. The kernel owns its bit rates; handctl checks
  that the interface exists and says how to configure it when it does not.
- ``INTERFACE:CHANNEL``: any other python-can interface, given the config's CAN-FD bit rates.
"""

from __future__ import annotations

import enum
import errno
import os
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import can

from handctl.config import BusConfig
from handctl.errors import BusError, ConfigError

#: Frames drained per call at most: a babbling node must not keep one tick busy forever.
DRAIN_LIMIT = 512

# Linux error-frame classes (linux/can/error.h), as python-can hands them over.
_CAN_ERR_CRTL = 0x004
_CAN_ERR_BUSOFF = 0x040
_CAN_ERR_RESTARTED = 0x100
_CAN_ERR_CRTL_PASSIVE = 0x30  # rx or tx error-passive bits in data[1]


@dataclass(frozen=True, slots=True)
class Frame:
    """One CAN frame as the rest of handctl sees it. ``timestamp_ns`` is the bus's time."""

    arbitration_id: int
    data: bytes
    timestamp_ns: int = 0
    is_fd: bool = True


class BusEventKind(enum.Enum):
    ERROR_FRAME = "error_frame"
    ERROR_PASSIVE = "error_passive"
    BUS_OFF = "bus_off"
    BUS_RESTARTED = "bus_restarted"
    TX_QUEUE_FULL = "tx_queue_full"
    TX_FAILED = "tx_failed"
    RX_FAILED = "rx_failed"
    FOREIGN_FRAME = "foreign_frame"  # counted by callers; kept here so one enum names them all


@dataclass(frozen=True, slots=True)
class BusEvent:
    kind: BusEventKind
    detail: str
    timestamp_ns: int


@dataclass(frozen=True)
class BusSpec:
    interface: str
    channel: str

    def __str__(self) -> str:
        return f"{self.interface}:{self.channel}" if self.channel else self.interface


def parse_spec(spec: str, bus_config: BusConfig | None = None) -> BusSpec:
    """Split ``INTERFACE:CHANNEL``; ``hand`` takes both from the hand config."""
    if spec == "sim":
        return BusSpec("sim", "")
    if spec == "hand":
        if bus_config is None:
            raise BusError("bus spec 'hand' needs a hand config")
        return BusSpec(bus_config.interface, bus_config.channel)
    interface, sep, channel = spec.partition(":")
    if not sep or not interface or not channel:
        raise ConfigError("--bus", "", "sim, hand, or INTERFACE:CHANNEL (e.g. socketcan:can0, "
                          "virtual:test)", spec)
    if interface not in can.VALID_INTERFACES:
        raise ConfigError("--bus", "interface",
                          "a python-can interface (" + ", ".join(sorted(can.VALID_INTERFACES))
                          + ")", interface)
    return BusSpec(interface, channel)


def bus_kwargs(spec: BusSpec, bus_config: BusConfig) -> dict[str, Any]:
    """The python-can constructor arguments for ``spec`` under the hand's bus settings."""
    kwargs: dict[str, Any] = {"interface": spec.interface, "channel": spec.channel}
    if spec.interface == "virtual":
        kwargs["receive_own_messages"] = False
        kwargs["protocol"] = can.CanProtocol.CAN_FD if bus_config.fd else can.CanProtocol.CAN_20
    elif spec.interface == "socketcan":
        # Bit rates of a SocketCAN interface are set with `ip link`, not by the process.
        kwargs["fd"] = bus_config.fd
    elif spec.interface == "udp_multicast":
        kwargs["fd"] = bus_config.fd
        kwargs["receive_own_messages"] = False
    else:
        kwargs["fd"] = bus_config.fd
        kwargs["bitrate"] = bus_config.bitrate
        if bus_config.fd and bus_config.data_bitrate:
            kwargs["data_bitrate"] = bus_config.data_bitrate
    return kwargs


def socketcan_setup_command(channel: str, bus_config: BusConfig) -> str:
    """The `ip link` command that brings a SocketCAN interface up with the hand's bit rates."""
    cmd = f"sudo ip link set {channel} up type can bitrate {bus_config.bitrate}"
    if bus_config.fd:
        cmd += f" dbitrate {bus_config.data_bitrate} fd on"
    return cmd


def check_socketcan(channel: str, bus_config: BusConfig, sysfs: Path = Path("/sys/class/net"),
                    ) -> None:
    """Refuse a SocketCAN channel that is missing or down, with the command that fixes it."""
    node = sysfs / channel
    hint = socketcan_setup_command(channel, bus_config)
    if not node.exists():
        raise BusError(f"socketcan:{channel}: no such network interface; load the driver and "
                       f"configure it with: {hint}")
    operstate = (node / "operstate").read_text().strip() if (node / "operstate").exists() else ""
    if operstate == "down":
        raise BusError(f"socketcan:{channel}: interface is down; bring it up with: {hint}")


class _Message(can.Message):
    """A python-can message whose deep copy costs a constructor call, not the copy machinery.

    python-can's virtual bus deep-copies every frame for every receiver; the generic path
    (memo dict, a deep copy of the data bytearray) costs about 9 µs a frame, which is most of
    the bus time of a lockstep tick. The fields are plain values, so this copy is as deep.
    """

    __slots__ = ()

    def __deepcopy__(self, memo: dict[int, Any] | None) -> _Message:
        return _Message(
            timestamp=self.timestamp, arbitration_id=self.arbitration_id,
            is_extended_id=self.is_extended_id, is_remote_frame=self.is_remote_frame,
            is_error_frame=self.is_error_frame, channel=self.channel, dlc=self.dlc,
            data=bytearray(self.data), is_fd=self.is_fd, is_rx=self.is_rx,
            bitrate_switch=self.bitrate_switch,
            error_state_indicator=self.error_state_indicator)


class HandBus:
    """A python-can bus behind a small, never-raising interface for the loop."""

    def __init__(self, bus: can.BusABC, spec: BusSpec, fd: bool,
                 clock_ns: Callable[[], int] = time.monotonic_ns) -> None:
        self._bus = bus
        self.spec = spec
        self.fd = fd
        self._clock_ns = clock_ns
        self._events: list[BusEvent] = []
        self.sent = 0
        self.received = 0
        self.closed = False

    def drain(self, limit: int = DRAIN_LIMIT) -> list[Frame]:
        """Every frame that has arrived, without waiting; error frames become events."""
        frames: list[Frame] = []
        recv = self._bus.recv
        for _ in range(limit):
            try:
                msg = recv(timeout=0)
            except (can.CanError, OSError, ValueError) as exc:
                self._event(BusEventKind.RX_FAILED, str(exc))
                break
            if msg is None:
                break
            if msg.is_error_frame:
                self._error_frame(msg)
                continue
            self.received += 1
            frames.append(Frame(msg.arbitration_id, bytes(msg.data),
                                int(msg.timestamp * 1e9), msg.is_fd))
        return frames

    def send(self, arbitration_id: int, data: bytes) -> bool:
        """Send one frame without blocking; on failure record an event and return False."""
        msg = _Message(arbitration_id=arbitration_id, data=data, is_extended_id=False,
                       is_fd=self.fd, bitrate_switch=self.fd, check=False)
        try:
            self._bus.send(msg, timeout=0)
        except can.CanOperationError as exc:
            full = exc.error_code == errno.ENOBUFS or "No buffer space" in str(exc)
            self._event(BusEventKind.TX_QUEUE_FULL if full else BusEventKind.TX_FAILED, str(exc))
            return False
        except (can.CanError, OSError, ValueError) as exc:
            self._event(BusEventKind.TX_FAILED, f"{type(exc).__name__}: {exc}")
            return False
        self.sent += 1
        return True

    def send_error_frame(self, error_class: int = _CAN_ERR_CRTL, data: bytes = bytes(8)) -> bool:
        """Put an error frame on the bus (fault injection on virtual buses only).

        ``error_class`` is the Linux error class (0x004 controller, 0x040 bus-off,
        0x100 restarted), as a SocketCAN adapter would report it.
        """
        msg = _Message(arbitration_id=error_class, is_error_frame=True, is_extended_id=False,
                       data=data, check=False)
        try:
            self._bus.send(msg, timeout=0)
        except (can.CanError, OSError, ValueError):
            return False
        return True

    def events(self) -> list[BusEvent]:
        """Take the events since the last call."""
        events, self._events = self._events, []
        return events

    def close(self) -> None:
        if not self.closed:
            self.closed = True
            self._bus.shutdown()

    def __enter__(self) -> HandBus:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _event(self, kind: BusEventKind, detail: str) -> None:
        self._events.append(BusEvent(kind, detail, self._clock_ns()))

    def _error_frame(self, msg: can.Message) -> None:
        cls = msg.arbitration_id
        if cls & _CAN_ERR_BUSOFF:
            self._event(BusEventKind.BUS_OFF, f"error class 0x{cls:X}")
        elif cls & _CAN_ERR_RESTARTED:
            self._event(BusEventKind.BUS_RESTARTED, f"error class 0x{cls:X}")
        elif cls & _CAN_ERR_CRTL and len(msg.data) > 1 and msg.data[1] & _CAN_ERR_CRTL_PASSIVE:
            self._event(BusEventKind.ERROR_PASSIVE, f"controller 0x{msg.data[1]:02X}")
        else:
            self._event(BusEventKind.ERROR_FRAME, f"error class 0x{cls:X}")


def open_bus(spec: str | BusSpec, bus_config: BusConfig,
             options: dict[str, Any] | None = None) -> HandBus:
    """Open the bus named by ``spec``; every failure is a ``BusError`` that says what to do.

    ``options`` go to the python-can constructor unchanged (e.g. ``rx_queue_size`` of the
    virtual bus, or an adapter's own timing arguments).
    """
    parsed = spec if isinstance(spec, BusSpec) else parse_spec(spec, bus_config)
    if parsed.interface == "sim":
        raise BusError("bus spec 'sim' is resolved by the caller: start the simulated hand and "
                       "open its virtual channel")
    if parsed.interface == "socketcan" and os.name == "posix":
        check_socketcan(parsed.channel, bus_config)
    kwargs = bus_kwargs(parsed, bus_config)
    kwargs.update(options or {})
    try:
        bus = can.Bus(**kwargs)
    except (can.CanError, OSError, ValueError, ImportError, NotImplementedError) as exc:
        raise BusError(f"{parsed}: cannot open the bus: {type(exc).__name__}: {exc}") from None
    return HandBus(bus, parsed, bus_config.fd)
