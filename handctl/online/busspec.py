"""Bus specs: what ``--bus`` names, and the python-can constructor arguments that open it.

- ``sim``: the simulated hand. Resolved by the caller (the CLI starts the simulated hand as a
  peer on a private virtual channel and opens ``virtual:<that channel>`` here), because the
  online plane never imports the simulation.
- ``hand``: the interface and channel written in the hand config's ``bus`` section.
- ``virtual:NAME``: python-can's in-process virtual bus (tests, lockstep runs).
- ``socketcan:can0``: a Linux SocketCAN interface. The kernel owns its bit rates; handctl checks
  that the interface exists and says how to configure it when it does not.
- ``unix:DIRECTORY``: handctl's own python-can interface over Unix datagram sockets, one per
  participant in DIRECTORY (absolute: ``unix_rule``): a bus that crosses processes on one
  machine without a kernel CAN driver or any network traffic (the simulated hand in its own
  process, kill tests).
- ``INTERFACE:CHANNEL``: any other python-can interface, given the config's CAN-FD bit rates.
"""

from __future__ import annotations

import shlex
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import can

from handctl.config import BusConfig
from handctl.errors import BusError, ConfigError, Description, escaped

#: bytes: the kernel's ``IFNAMSIZ``, the NUL included; a name has one byte fewer at most.
IFNAMSIZ = 16
#: The kernel's ``isspace`` (``lib/ctype.c``): tab to carriage return, space, and 0xA0,
#: applied by ``dev_valid_name`` byte by byte to the name's bytes.
_KERNEL_SPACE = frozenset(b"\t\n\v\f\r \xa0")
#: ``/sys/class/net/<name>/type`` of a CAN interface (``ARPHRD_CAN``, linux/if_arp.h).
ARPHRD_CAN = 280
#: ``/sys/class/net/<name>/mtu`` of a classic CAN interface and of a CAN FD one (bytes: the
#: kernel's ``CAN_MTU`` and ``CANFD_MTU``, sizeof struct can_frame and canfd_frame).
CAN_MTU = 16
CANFD_MTU = 72
#: ``IFF_UP`` in ``/sys/class/net/<name>/flags`` (linux/if.h): the interface was brought up.
IFF_UP = 0x1
#: What a SocketCAN channel must be, said in error messages.
IFNAME_RULE = (
    f"a Linux interface name (1 to {IFNAMSIZ - 1} bytes, no '/', ':', whitespace or NUL, "
    "not '.' or '..'), e.g. can0"
)


@dataclass(frozen=True)
class BusSpec:
    interface: str
    channel: str

    def __str__(self) -> str:
        """The spec as messages show it: a channel from argv or a hand config may hold
        control characters or bytes that are not UTF-8, which are shown ``escaped``."""
        text = f"{self.interface}:{self.channel}" if self.channel else self.interface
        return escaped(text)


def parse_spec(
    spec: str,
    bus_config: BusConfig | None = None,
    source: str = "the hand config",
    option: str = "--bus",
) -> BusSpec:
    """Split ``INTERFACE:CHANNEL``; ``hand`` takes both from the hand config (``source``, its
    file, for an error); ``option`` is the one that gave ``spec``, for an error."""
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
            option, "", "sim, hand, or INTERFACE:CHANNEL (e.g. socketcan:can0, virtual:test)", spec
        )
    if interface not in can.VALID_INTERFACES:
        raise ConfigError(
            option,
            "interface",
            "a python-can interface (" + ", ".join(sorted(can.VALID_INTERFACES)) + ")",
            interface,
        )
    check_channel(interface, channel, option, "channel")
    if interface == "unix":
        _check_unix_directory(channel, option)
    return BusSpec(interface, channel)


def require_peers(spec: BusSpec, option: str = "--bus") -> None:
    """A unix bus a command only joins (to listen to the nodes, or to drive a hand that is
    on it) must be there: its directory is made by the first participant, and a mistyped
    one was made by the command, which then said every node was missing (``nodes``, a
    "listens only" command, left the directory behind)."""
    if spec.interface != "unix":
        return
    from handctl.online.unixcan import anyone_on

    directory = Path(spec.channel)
    if not directory.is_dir():
        found = "no such directory"
    elif not anyone_on(directory):
        found = "nobody is on it"  # its participants ended (a killed hand's socket in it)
    else:
        return
    raise ConfigError(
        option,
        "channel",
        "the directory of a unix bus a hand is on (start one with 'handctl sim --bus "
        "unix:DIRECTORY')",
        Description(f"{escaped(spec.channel)}: {found}"),
    )


def _check_unix_directory(channel: str, option: str) -> None:
    """A ``--bus unix:DIRECTORY`` whose directory cannot be the bus's, said as the bad input it
    is (it was a bus error, exit 4, from the bus's opening). Only for a spec given now: a hand
    config's or a recording's bus is checked where it is opened, on the machine it runs on."""
    path = Path(channel)
    if not path.parent.is_dir():
        raise ConfigError(
            option,
            "channel",
            f"a directory in an existing one (the bus makes its own directory, not those "
            f"above it: {path.parent} is not a directory)",
            channel,
        )
    if path.exists() and not path.is_dir():
        raise ConfigError(
            option,
            "channel",
            "a directory (each participant's socket is made in it)",
            f"{channel}: not a directory",
        )
    if path.is_symlink() and not path.exists():
        # a loop of links, or one to nothing: the bus's making of its directory failed on it
        # (FileExistsError, a bus error, exit 4)
        raise ConfigError(
            option,
            "channel",
            "a directory (each participant's socket is made in it)",
            Description(
                f"{escaped(channel)}: a symbolic link that leads to no directory (a loop, or "
                "a link to nothing)"
            ),
        )


def check_channel(interface: str, channel: str, source: str, key: str) -> None:
    """A ``ConfigError`` naming ``source`` and ``key`` for a channel no bus of ``interface``
    can have: a SocketCAN name the kernel never gives (``valid_ifname``), a relative unix bus
    directory (``unix_rule``). One rule for a ``--bus`` spec and a hand config's bus."""
    if interface == "socketcan" and not valid_ifname(channel):
        raise ConfigError(source, key, IFNAME_RULE, channel)
    if interface == "unix" and not Path(channel).is_absolute():
        raise ConfigError(source, key, unix_rule(channel), channel)


def unix_rule(channel: str) -> str:
    """What a unix bus directory must be, said for ``channel``.

    Absolute: the directory is what the participants share, and a relative one is taken
    from each process's working directory, so a simulated hand and a host started from two
    directories with the same spec were on two buses, each hearing nothing. Refused rather
    than resolved: the user's spec is what every participant must be given, and a resolved
    one would differ from it without saying so."""
    return f"an absolute directory (e.g. unix:{Path(channel).absolute()})"


def valid_ifname(name: str) -> bool:
    """Whether the kernel would take ``name`` for a network interface (``dev_valid_name``
    in net/core/dev.c). Checked where a spec or a hand config is read: a name the kernel
    never has would otherwise reach a sysfs path (``..``, ``a/b``), a message of any length,
    or, unquoted, the ``ip link`` command handctl suggests (``can0;reboot``)."""
    raw = name.encode("utf-8", "surrogateescape")
    return (
        0 < len(raw) < IFNAMSIZ
        and name not in (".", "..")
        and not any(b in _KERNEL_SPACE or b in b"/:\0" for b in raw)
    )


def check_interface(bus_config: BusConfig, source: str) -> None:
    """Refuse a hand config whose ``bus.interface`` python-can does not know, where the
    config is read (``handctl check``, ``--bus hand``), not when a bring-up tool first opens
    the bus and python-can says "Unknown interface type". The hand config's own loader
    cannot: it is shared with code that never imports python-can. A SocketCAN channel
    must be a name the kernel could have (``valid_ifname``)."""
    if bus_config.interface not in can.VALID_INTERFACES:
        raise ConfigError(
            source,
            "bus.interface",
            "a python-can interface (" + ", ".join(sorted(can.VALID_INTERFACES)) + ")",
            bus_config.interface,
        )
    check_channel(bus_config.interface, bus_config.channel, source, "bus.channel")


def bus_kwargs(spec: BusSpec, bus_config: BusConfig) -> dict[str, Any]:
    """The python-can constructor arguments for ``spec`` under the hand's bus settings."""
    kwargs: dict[str, Any] = {"interface": spec.interface, "channel": spec.channel}
    if spec.interface == "virtual":
        kwargs["receive_own_messages"] = False
        kwargs["protocol"] = can.CanProtocol.CAN_FD if bus_config.fd else can.CanProtocol.CAN_20
    elif spec.interface == "socketcan":
        # Bit rates of a SocketCAN interface are set with `ip link`, not by the process.
        kwargs["fd"] = bus_config.fd
        # its own frames would come back marked as any other local program's (``is_rx``
        # False), which HandBus hears (``LOCAL_SENDER_INTERFACES``)
        kwargs["receive_own_messages"] = False
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
    """The `ip link` command that brings a SocketCAN interface up with the hand's bit rates,
    the channel quoted for a shell (it is pasted into one, ``shell_word``); with the
    controller's own restart 100 ms after a bus-off, as docs/bringup.md sets it up (the
    host's supervisor stops the run on the bus-off either way)."""
    cmd = f"sudo ip link set {shell_word(channel)} up type can bitrate {bus_config.bitrate}"
    if bus_config.fd:
        cmd += f" dbitrate {bus_config.data_bitrate} fd on"
    return cmd + " restart-ms 100"


def shell_word(name: str) -> str:
    """``name`` as one word for a shell, in a command a message suggests. A name with a
    control character or a byte that is not UTF-8 (the kernel takes both) is written
    ``$'...'`` with its bytes as ``\\xNN`` (bash and POSIX shells decode it back), so that
    the message shows no raw control character and the pasted command names the interface;
    any other name is quoted as ``shlex`` quotes it."""
    if name.isprintable():
        return shlex.quote(name)
    raw = name.encode("utf-8", "surrogateescape")
    body = "".join(
        chr(b) if 0x20 <= b < 0x7F and chr(b) not in "\\'" else f"\\x{b:02x}" for b in raw
    )
    return f"$'{body}'"


#: what a kernel without SocketCAN is told, where the check finds it and where a socket does
NO_SOCKETCAN = (
    "this kernel has no SocketCAN (AF_CAN); load its modules (sudo modprobe can can_raw) or "
    "run on a kernel built with them"
)


def kernel_has_socketcan() -> bool:
    """Whether this kernel takes a SocketCAN socket (AF_CAN): False only when it says the
    address family is not supported; any other refusal is left to the socket's own error."""
    import errno
    import socket

    family = getattr(socket, "AF_CAN", None)
    if family is None:
        return False
    try:
        socket.socket(family, socket.SOCK_RAW, socket.CAN_RAW).close()
    except OSError as exc:
        return exc.errno != errno.EAFNOSUPPORT
    return True


def vcan_setup_command(channel: str, bus_config: BusConfig) -> str:
    """The commands that make a virtual SocketCAN interface (``vcan``): ``ip link set ... up
    type can`` cannot make an interface, and a vcan has no bit rate (CAN-FD needs its MTU)."""
    name = shell_word(channel)
    mtu = f" && sudo ip link set {name} mtu 72" if bus_config.fd else ""
    return (
        f"sudo modprobe vcan && sudo ip link add dev {name} type vcan{mtu} && "
        f"sudo ip link set {name} up"
    )


def check_socketcan(
    channel: str,
    bus_config: BusConfig,
    sysfs: Path = Path("/sys/class/net"),
    has_socketcan: Callable[[], bool] = kernel_has_socketcan,
) -> None:
    """Refuse a SocketCAN channel that is no interface name (bad input), on a kernel without
    SocketCAN, missing, not a CAN interface, classic CAN for a CAN FD hand, down, or up with
    its controller off the bus, with the command that fixes it. ``sysfs`` is
    ``/sys/class/net``, a directory of a test's making in tests."""
    if not valid_ifname(channel):
        raise ConfigError("--bus", "channel", IFNAME_RULE, channel)
    node = sysfs / channel
    hint = socketcan_setup_command(channel, bus_config)
    shown = escaped(channel)
    virtual = channel.startswith("vcan")
    link_type = _read(node / "type")
    if link_type and link_type != str(ARPHRD_CAN):
        # first, on any kernel: `ip link set lo ... type can` was the advice for lo on one
        # without SocketCAN
        raise BusError(
            f"socketcan:{shown}: not a CAN interface (its link type is {link_type[:16]}, "
            f"a CAN interface's is {ARPHRD_CAN}, ARPHRD_CAN): name the CAN interface "
            "(`ip -details link show type can` lists them)"
        )
    if not has_socketcan():
        # no interface can be a CAN one on such a kernel: whatever is done to it, no socket
        # opens; what to do about the interface comes after the modules
        then = vcan_setup_command(channel, bus_config) if virtual else hint
        raise BusError(f"socketcan:{shown}: {NO_SOCKETCAN}, then configure it with: {then}")
    if not node.exists():
        if virtual:
            raise BusError(
                f"socketcan:{shown}: no such network interface; a virtual CAN interface is "
                f"made with: {vcan_setup_command(channel, bus_config)}"
            )
        raise BusError(
            f"socketcan:{shown}: no such network interface (`ip -details link show type can` "
            "lists the CAN interfaces; an adapter shows one once its driver is loaded); "
            f"then configure it with: {hint}"
        )
    name = shell_word(channel)
    mtu = _read(node / "mtu")
    if bus_config.fd and mtu == str(CAN_MTU):
        # python-can opens it all the same, and every CAN FD frame sent is refused (EINVAL):
        # the run failed at start-up with the bus's errors, not saying why. A classic hand on
        # a CAN FD interface is fine: its frames are classic ones
        if virtual:
            fix = f"sudo ip link set {name} down && sudo ip link set {name} mtu {CANFD_MTU}"
            fix += f" && sudo ip link set {name} up"
        else:
            fix = f"sudo ip link set {name} down && {hint}"
        raise BusError(
            f"socketcan:{shown}: a classic CAN interface (its mtu is {mtu}), and the hand "
            f"config's bus is CAN FD (an mtu of {CANFD_MTU}); set it up for CAN FD with: {fix} "
            "(a controller without CAN FD cannot be: the hand needs one with it)"
        )
    if _read(node / "operstate") in ("down", "lowerlayerdown"):
        if _flags(node) & IFF_UP:
            # up, but the kernel turned its carrier off: a controller in bus-off (restart-ms
            # 0, or not restarted yet). `ip link set ... up type can ...` fails on it, busy
            raise BusError(
                f"socketcan:{shown}: interface is up but has no carrier: its controller is "
                f"bus-off (or otherwise off the bus); restart it with: sudo ip link set {name} "
                f"type can restart (or take it down and up: sudo ip link set {name} down && "
                f"sudo ip link set {name} up); a controller that goes bus-off again points at "
                "the wiring, the termination, or a bit rate other than the nodes'"
            )
        if virtual:  # no bit rates to set on a virtual interface
            hint = f"sudo ip link set {name} up"
        raise BusError(f"socketcan:{shown}: interface is down; bring it up with: {hint}")


def _flags(node: Path) -> int:
    """The interface's ``flags`` (sysfs writes them in hex, ``0x1003``); 0 if unreadable."""
    try:
        return int(_read(node / "flags"), 16)
    except ValueError:
        return 0


def _read(path: Path) -> str:
    """A sysfs attribute, stripped; empty if it is not there or cannot be read (a kernel
    without it: the check it serves is then left to the socket's own error)."""
    try:
        return path.read_text().strip()
    except (OSError, UnicodeDecodeError):
        return ""
