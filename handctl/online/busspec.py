"""Bus specs: what ``--bus`` names, and the python-can constructor arguments that open it.

- ``sim``: the simulated hand. Resolved by the caller (the CLI starts the simulated hand as a
  peer on a private virtual channel and opens ``virtual:<that channel>`` here), because the
  online plane never imports the simulation.
- ``hand``: the interface and channel written in the hand config's ``bus`` section.
- ``virtual:NAME``: python-can's in-process virtual bus (tests, lockstep runs).
- ``socketcan:can0``: a Linux SocketCAN interface. The kernel owns its bit rates; handctl checks
  that the interface exists and says how to configure it when it does not.
- ``unix:DIRECTORY``: handctl's own python-can interface over Unix datagram sockets, one per
  participant in DIRECTORY: a bus that crosses processes on one machine without a kernel CAN
  driver or any network traffic (the simulated hand in its own process, kill tests).
- ``INTERFACE:CHANNEL``: any other python-can interface, given the config's CAN-FD bit rates.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import can

from handctl.config import BusConfig
from handctl.errors import BusError, ConfigError


@dataclass(frozen=True)
class BusSpec:
    interface: str
    channel: str

    def __str__(self) -> str:
        return f"{self.interface}:{self.channel}" if self.channel else self.interface


def parse_spec(
    spec: str, bus_config: BusConfig | None = None, source: str = "the hand config"
) -> BusSpec:
    """Split ``INTERFACE:CHANNEL``; ``hand`` takes both from the hand config (``source``, its
    file, for an error)."""
    if spec == "sim":
        return BusSpec("sim", "")
    if spec == "hand":
        if bus_config is None:
            raise BusError("bus spec 'hand' needs a hand config")
        check_interface(bus_config, source)
        return BusSpec(bus_config.interface, bus_config.channel)
    interface, sep, channel = spec.partition(":")
    if not sep or not interface or not channel:
        raise ConfigError(
            "--bus", "", "sim, hand, or INTERFACE:CHANNEL (e.g. socketcan:can0, virtual:test)", spec
        )
    if interface not in can.VALID_INTERFACES:
        raise ConfigError(
            "--bus",
            "interface",
            "a python-can interface (" + ", ".join(sorted(can.VALID_INTERFACES)) + ")",
            interface,
        )
    return BusSpec(interface, channel)


def check_interface(bus_config: BusConfig, source: str) -> None:
    """Refuse a hand config whose ``bus.interface`` python-can does not know, where the
    config is read (``handctl check``, ``--bus hand``), not when a bring-up tool first opens
    the bus and python-can says "Unknown interface type". The hand config's own loader
    cannot: it is shared with code that never imports python-can."""
    if bus_config.interface not in can.VALID_INTERFACES:
        raise ConfigError(
            source,
            "bus.interface",
            "a python-can interface (" + ", ".join(sorted(can.VALID_INTERFACES)) + ")",
            bus_config.interface,
        )


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


def check_socketcan(
    channel: str,
    bus_config: BusConfig,
    sysfs: Path = Path("/sys/class/net"),
) -> None:
    """Refuse a SocketCAN channel that is missing or down, with the command that fixes it."""
    node = sysfs / channel
    hint = socketcan_setup_command(channel, bus_config)
    if not node.exists():
        raise BusError(
            f"socketcan:{channel}: no such network interface; load the driver and "
            f"configure it with: {hint}"
        )
    operstate = (node / "operstate").read_text().strip() if (node / "operstate").exists() else ""
    if operstate == "down":
        raise BusError(f"socketcan:{channel}: interface is down; bring it up with: {hint}")
