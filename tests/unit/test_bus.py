"""Bus specs, SocketCAN configuration paths (without the kernel) and never-raising I/O."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import can
import pytest

from handctl.config import HandConfig
from handctl.errors import BusError, ConfigError
from handctl.online.bus import EXTENDED_ID_FLAG, BusEventKind, Frame, HandBus, open_bus
from handctl.online.busspec import (
    BusSpec,
    bus_kwargs,
    check_socketcan,
    parse_spec,
    socketcan_setup_command,
)

from ..local_socketcan import LocalSocketcanBus


def test_parse_specs(hand: HandConfig) -> None:
    assert parse_spec("sim") == BusSpec("sim", "")
    assert parse_spec("virtual:abc") == BusSpec("virtual", "abc")
    assert parse_spec("socketcan:can0") == BusSpec("socketcan", "can0")
    assert parse_spec("hand", hand.bus) == BusSpec("socketcan", "can0")
    assert str(parse_spec("pcan:PCAN_USBBUS1")) == "pcan:PCAN_USBBUS1"


@pytest.mark.parametrize("spec", ["can0", "socketcan:", ":can0", "nosuchiface:0"])
def test_bad_specs_name_what_is_wrong(spec: str) -> None:
    with pytest.raises(ConfigError) as info:
        parse_spec(spec)
    assert "--bus" in str(info.value)


def test_a_hand_config_naming_an_interface_python_can_lacks_is_refused(hand: HandConfig) -> None:
    """Where the config is read (``--bus hand``; ``handctl check`` calls the same check), not
    when a bring-up tool opens the bus and python-can says "Unknown interface type"."""
    bogus = replace(hand.bus, interface="bogus")
    with pytest.raises(ConfigError) as info:
        parse_spec("hand", bogus, hand.source)
    assert (info.value.file, info.value.key, info.value.found) == (
        hand.source,
        "bus.interface",
        "bogus",
    )
    assert "socketcan" in info.value.expected and "unix" in info.value.expected


def test_socketcan_kwargs_leave_bitrates_to_the_kernel(hand: HandConfig) -> None:
    kwargs = bus_kwargs(BusSpec("socketcan", "can0"), hand.bus)
    assert kwargs == {
        "interface": "socketcan",
        "channel": "can0",
        "fd": True,
        "receive_own_messages": False,
    }


def test_other_adapters_get_both_bitrates(hand: HandConfig) -> None:
    kwargs = bus_kwargs(BusSpec("pcan", "PCAN_USBBUS1"), hand.bus)
    assert kwargs["fd"] is True
    assert kwargs["bitrate"] == 1_000_000
    assert kwargs["data_bitrate"] == 5_000_000
    classic = replace(hand.bus, fd=False, data_bitrate=None)
    kwargs = bus_kwargs(BusSpec("pcan", "PCAN_USBBUS1"), classic)
    assert kwargs["fd"] is False and "data_bitrate" not in kwargs


def test_socketcan_setup_command(hand: HandConfig) -> None:
    assert socketcan_setup_command("can1", hand.bus) == (
        "sudo ip link set can1 up type can bitrate 1000000 dbitrate 5000000 fd on restart-ms 100"
    )
    classic = replace(hand.bus, fd=False, data_bitrate=None)
    assert socketcan_setup_command("can1", classic).endswith("bitrate 1000000 restart-ms 100")


def _yes() -> bool:
    """A kernel with SocketCAN (AF_CAN), as a robot's has and this one has not."""
    return True


def test_socketcan_check_against_a_sysfs_tree(hand: HandConfig, tmp_path: Path) -> None:
    with pytest.raises(BusError, match=r"no such network interface.*ip link set can0 up"):
        check_socketcan("can0", hand.bus, sysfs=tmp_path, has_socketcan=_yes)
    (tmp_path / "can0").mkdir()
    (tmp_path / "can0" / "operstate").write_text("down\n")
    with pytest.raises(BusError, match=r"interface is down.*dbitrate 5000000 fd on"):
        check_socketcan("can0", hand.bus, sysfs=tmp_path, has_socketcan=_yes)
    (tmp_path / "can0" / "operstate").write_text("up\n")
    check_socketcan("can0", hand.bus, sysfs=tmp_path, has_socketcan=_yes)


def test_a_classic_can_interface_is_refused_for_a_can_fd_hand(
    hand: HandConfig, tmp_path: Path
) -> None:
    """python-can opens a classic interface (mtu 16) for CAN FD all the same, and the kernel
    refuses every CAN FD frame sent on it: the run failed at start-up with the bus's errors,
    not saying why. Refused before the run, with the mtu expected and found and the command
    that fixes it; a classic hand on a CAN FD interface is fine (its frames are classic)."""
    for name in ("can0", "vcan0"):
        (tmp_path / name).mkdir()
        (tmp_path / name / "type").write_text("280\n")
        (tmp_path / name / "mtu").write_text("16\n")
        (tmp_path / name / "operstate").write_text("up\n")
    with pytest.raises(BusError) as info:
        check_socketcan("can0", hand.bus, sysfs=tmp_path, has_socketcan=_yes)
    said = str(info.value)
    assert said.startswith("socketcan:can0: a classic CAN interface (its mtu is 16)")
    assert "CAN FD (an mtu of 72)" in said
    assert (
        "sudo ip link set can0 down && sudo ip link set can0 up type can bitrate 1000000 "
        "dbitrate 5000000 fd on restart-ms 100" in said
    )
    with pytest.raises(BusError, match=r"sudo ip link set vcan0 down && sudo ip link set vcan0 "):
        check_socketcan("vcan0", hand.bus, sysfs=tmp_path, has_socketcan=_yes)
    classic = replace(hand.bus, fd=False, data_bitrate=None)
    check_socketcan("can0", classic, sysfs=tmp_path, has_socketcan=_yes)
    (tmp_path / "can0" / "mtu").write_text("72\n")
    check_socketcan("can0", hand.bus, sysfs=tmp_path, has_socketcan=_yes)
    check_socketcan("can0", classic, sysfs=tmp_path, has_socketcan=_yes)


def test_a_controller_in_bus_off_is_not_told_to_bring_an_up_interface_up(
    hand: HandConfig, tmp_path: Path
) -> None:
    """In bus-off the kernel turns the carrier off: ``operstate`` reads down while the
    interface is up (IFF_UP in ``flags``). It was told to run ``ip link set can0 up type
    can ...``, which a running device refuses ("Device or resource busy")."""
    node = tmp_path / "can0"
    node.mkdir()
    (node / "type").write_text("280\n")
    (node / "mtu").write_text("72\n")
    (node / "operstate").write_text("down\n")
    (node / "flags").write_text("0x40081\n")  # IFF_UP | IFF_NOARP | IFF_ECHO, as can0's
    with pytest.raises(BusError) as info:
        check_socketcan("can0", hand.bus, sysfs=tmp_path, has_socketcan=_yes)
    said = str(info.value)
    assert said.startswith("socketcan:can0: interface is up but has no carrier: its controller")
    assert "bus-off" in said and "sudo ip link set can0 type can restart" in said
    assert "up type can bitrate" not in said
    (node / "flags").write_text("0x40080\n")  # brought down: the command that brings it up
    with pytest.raises(BusError, match=r"interface is down; bring it up with: sudo ip link set"):
        check_socketcan("can0", hand.bus, sysfs=tmp_path, has_socketcan=_yes)


def test_opening_socketcan_here_fails_with_a_hint(hand: HandConfig) -> None:
    # This kernel has no SocketCAN; whatever the reason, the error says what to do.
    with pytest.raises(BusError, match="socketcan:handctl-none"):
        open_bus("socketcan:handctl-none", hand.bus)


def test_a_bus_that_carries_classic_can_only_is_refused_for_a_can_fd_hand(
    hand: HandConfig, channel: str
) -> None:
    """A backend that opens a classic CAN 2.0 bus (python-can's ``protocol``: gs_usb always,
    an adapter without CAN FD) for a CAN FD hand failed every send, and the run failed at
    start-up with the bus's errors. Here python-can's virtual bus, told it is classic."""
    classic_bus = {"protocol": can.CanProtocol.CAN_20}
    with pytest.raises(BusError) as info:
        open_bus(f"virtual:{channel}", hand.bus, classic_bus)
    assert str(info.value).startswith(f"virtual:{channel}: the hand config's bus is CAN FD")
    assert "classic CAN 2.0 frames only" in str(info.value)
    classic = replace(hand.bus, fd=False, data_bitrate=None)
    with open_bus(f"virtual:{channel}", classic, classic_bus) as bus:
        assert bus.send(0x101, bytes(8))


def test_sim_spec_is_not_opened_here(hand: HandConfig) -> None:
    with pytest.raises(BusError, match="resolved by the caller"):
        open_bus("sim", hand.bus)


def test_frames_cross_the_virtual_bus(bus_pair: tuple[HandBus, HandBus]) -> None:
    host, peer = bus_pair
    assert host.send(0x101, bytes(range(8)))
    assert host.send(0x181, bytes(range(16)))
    frames = peer.drain()
    assert [(f.arbitration_id, f.data) for f in frames] == [
        (0x101, bytes(range(8))),
        (0x181, bytes(range(16))),
    ]
    assert all(f.is_fd for f in frames)
    assert host.drain() == []  # own frames are not echoed
    assert peer.drain() == []  # drained means empty, without waiting


class _TapError(RuntimeError):
    """What the test's taps raise."""


@pytest.mark.parametrize("raised", [_TapError, SystemExit, KeyboardInterrupt])
@pytest.mark.parametrize("kind", ["virtual", "unix"])
def test_a_tap_that_raises_leaves_the_frames_their_fate_and_is_held(
    hand: HandConfig, channel: str, tmp_path: Path, kind: str, raised: type[BaseException]
) -> None:
    """A tap's exception came out of ``send`` after the bus took the frame, and the sender
    took the frame for refused (found by an outside audit): the frames went, are counted as
    sent, and the first exception is held for the tap's owner. Whatever it is: a SystemExit
    or a KeyboardInterrupt out of a tap still gave a counter back that the frame had used
    (found by an outside audit of the first fix)."""
    spec = f"virtual:{channel}" if kind == "virtual" else f"unix:{tmp_path / 'bus'}"
    with open_bus(spec, hand.bus) as peer, open_bus(spec, hand.bus) as host:
        host.prepare_send()
        first, second = raised("tx"), raised("rx")

        def tap(frames: list[tuple[int, bytes]], direction: int) -> None:
            raise first

        def rx_tap(frames: list[Frame]) -> None:
            raise second

        host.tap, host.rx_tap = tap, rx_tap
        assert host.send(0x101, b"\x01", more=True)
        assert host.send(0x102, b"\x02")
        assert (host.sent, host.tx_failed) == (2, 0)
        assert host.tap_error is first
        assert [f.arbitration_id for f in peer.drain()] == [0x101, 0x102]
        peer.send(0x181, b"\x03")
        assert [f.arbitration_id for f in host.drain()] == [0x181]  # drained all the same
        assert host.tap_error is first  # the first is kept


def test_drain_is_bounded(bus_pair: tuple[HandBus, HandBus]) -> None:
    host, peer = bus_pair
    for i in range(30):
        host.send(0x100 + i, b"\x00")
    assert len(peer.drain(limit=10)) == 10
    assert len(peer.drain()) == 20


def test_error_frames_become_events(bus_pair: tuple[HandBus, HandBus]) -> None:
    host, peer = bus_pair
    assert host.send_error_frame()
    host.send(0x101, bytes(8))
    frames = peer.drain()
    assert len(frames) == 1
    events = peer.events()
    assert [e.kind for e in events] == [BusEventKind.ERROR_FRAME]
    assert peer.events() == []


def test_full_receiver_queue_is_an_event_not_an_exception(hand: HandConfig, channel: str) -> None:
    with (
        open_bus(f"virtual:{channel}", hand.bus) as host,
        open_bus(f"virtual:{channel}", hand.bus, {"rx_queue_size": 2}),
    ):
        results = [host.send(0x101, bytes(8)) for _ in range(4)]
        assert results == [True, True, False, False]
        kinds = [e.kind for e in host.events()]
        assert kinds == [BusEventKind.TX_FAILED, BusEventKind.TX_FAILED]
        assert host.sent == 2


def test_an_adapter_echoing_the_hosts_own_frames_hands_back_only_the_others(
    channel: str,
) -> None:
    """Some adapters echo what the process sent (python-can marks the echo ``is_rx`` False;
    its virtual bus does so with ``receive_own_messages``): the host's own commands coming back
    would read as another sender on its command ids (``FOREIGN_COMMAND``)."""
    echoing = can.Bus(interface="virtual", channel=channel, receive_own_messages=True)
    other = can.Bus(interface="virtual", channel=channel)
    host = HandBus(echoing, BusSpec("virtual", channel), fd=False)
    try:
        assert host.send(0x101, bytes(8))
        assert host.drain() == []  # the echo of the host's own command is not received
        other.send(can.Message(arbitration_id=0x181, data=bytes(8), is_extended_id=False))
        assert [f.arbitration_id for f in host.drain()] == [0x181]
    finally:
        host.close()
        other.shutdown()


@pytest.mark.parametrize(("interface", "heard"), [("socketcan", True), ("gs_usb", False)])
def test_a_frame_another_program_on_this_computer_sent_is_heard_on_socketcan(
    channel: str, interface: str, heard: bool
) -> None:
    """SocketCAN marks every frame another socket of this computer sent ``is_rx`` False
    (the kernel's MSG_DONTROUTE), not only this process's own, which it does not hand back:
    taken for the host's echo, a second master, an e-stop sent with ``cansend`` and a
    ``handctl sim`` on the same vcan were never heard. An adapter that marks only the echo
    of its own frames so (gs_usb) still has it skipped. The SocketCAN bus is a double of its
    marking only (``tests/local_socketcan.py``): this machine has no SocketCAN."""
    local = LocalSocketcanBus(channel)
    other = can.Bus(interface="virtual", channel=channel)
    host = HandBus(local, BusSpec(interface, "vcan0"), fd=False)
    try:
        other.send(can.Message(arbitration_id=0x000, data=bytes(2), is_extended_id=False))
        other.send(can.Message(arbitration_id=0x101, data=bytes(8), is_extended_id=False))
        expected = [0x000, 0x101] if heard else []
        assert [f.arbitration_id for f in host.drain()] == expected
    finally:
        host.close()
        other.shutdown()


@pytest.mark.parametrize(
    ("frame_id", "extended", "said"),
    [(0x901, False, "0x901, beyond the 11 bits"), (0xFFFFFFFF, True, "0xFFFFFFFF, beyond the 29")],
)
def test_a_frame_whose_id_its_format_cannot_carry_is_dropped_and_said(
    hand: HandConfig, channel: str, frame_id: int, extended: bool, said: str
) -> None:
    """A peer on an emulated bus (virtual, unix) can send what no CAN controller would: a
    standard frame with a 12-bit id, an extended one past 29 bits. Passed on, it went into
    the run's log as it came, and ``replay`` refused the log the run itself wrote; masked to
    fit, it would read as another id's frame. Dropped, and said as ``RX_FAILED``; the frame
    after it is received."""
    with (
        open_bus(f"virtual:{channel}", hand.bus) as host,
        can.Bus(interface="virtual", channel=channel) as peer,
    ):
        peer.send(
            can.Message(arbitration_id=frame_id, is_extended_id=extended, data=b"\x01", check=False)
        )
        peer.send(can.Message(arbitration_id=0x181, data=b"\x07", is_extended_id=False))
        assert [f.arbitration_id for f in host.drain()] == [0x181]
        events = host.events()
        assert [e.kind for e in events] == [BusEventKind.RX_FAILED]
        assert said in events[0].detail


def test_send_after_close_is_an_event(hand: HandConfig, channel: str) -> None:
    bus = open_bus(f"virtual:{channel}", hand.bus)
    bus.close()
    assert bus.send(0x101, bytes(8)) is False
    assert bus.events()[0].kind == BusEventKind.TX_FAILED
    assert bus.drain() == []
    assert bus.events()[0].kind == BusEventKind.RX_FAILED


def test_virtual_frames_between_handctl_buses_are_no_messages_and_others_still_hear_them(
    hand: HandConfig, channel: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Between handctl's own ends of a virtual channel a frame travels as a plain tuple, no
    python-can Message built; a plain python-can bus on the channel hears it as from any
    python-can sender, and what such a bus sends is drained as before."""
    built = [0]
    init = can.Message.__init__

    def counting(self: can.Message, *args: object, **kwargs: object) -> None:
        built[0] += 1
        init(self, *args, **kwargs)  # type: ignore[arg-type]

    with (
        open_bus(f"virtual:{channel}", hand.bus) as host,
        open_bus(f"virtual:{channel}", hand.bus) as peer,
        can.Bus(interface="virtual", channel=channel) as plain,
    ):
        monkeypatch.setattr(can.Message, "__init__", counting)
        assert host.send(0x101, bytes(range(16)))
        assert host.send(0x1ABCDEF | EXTENDED_ID_FLAG, b"\x05")
        got = peer.drain()
        assert built[0] == 2  # the two the plain bus was given, none for the peer
        monkeypatch.setattr(can.Message, "__init__", init)
        heard = [plain.recv(timeout=1.0) for _ in range(2)]
        plain.send(can.Message(arbitration_id=0x181, data=b"\x07", is_extended_id=False))
        from_plain = peer.drain()
    assert [(f.arbitration_id, f.data, f.is_fd) for f in got] == [
        (0x101, bytes(range(16)), True),
        (0x1ABCDEF | EXTENDED_ID_FLAG, b"\x05", True),
    ]
    assert [
        (m.arbitration_id, bytes(m.data), m.is_fd, m.bitrate_switch, m.is_extended_id, m.is_rx)
        for m in heard
        if m is not None
    ] == [
        (0x101, bytes(range(16)), True, True, False, True),
        (0x1ABCDEF, b"\x05", True, True, True, True),
    ]
    assert [(f.arbitration_id, f.data, f.is_fd) for f in from_plain] == [(0x181, b"\x07", False)]


@pytest.mark.parametrize(
    "spec, raised",
    [
        # python-can's socketcand backend takes host and port, not a channel: a TypeError
        ("socketcand:localhost", "TypeError"),
        # its kvaser backend without Kvaser's library: a NameError (or, with the library and
        # no adapter, a CanError): either way, this bus does not open
        ("kvaser:0", ""),
    ],
)
def test_a_backend_failing_in_its_own_way_is_a_bus_error_naming_the_spec(
    hand: HandConfig, spec: str, raised: str
) -> None:
    with pytest.raises(BusError, match=f"{spec}: cannot open the bus: {raised}"):
        open_bus(spec, hand.bus)


@pytest.mark.parametrize(
    "channel",
    [
        "abcdefghijklmnop",  # 16 bytes: IFNAMSIZ with no room for the NUL
        "a/b",
        "../../../proc",
        ".",
        "..",
        "can0 ",
        "can\n0",
        "can0:1",
        "x" * 5000,
        "ca\u00e0",  # its UTF-8 ends in byte 0xA0, a space to the kernel's isspace
    ],
)
def test_a_socketcan_channel_the_kernel_could_never_name_is_bad_input(
    hand: HandConfig, channel: str
) -> None:
    with pytest.raises(ConfigError) as info:
        parse_spec(f"socketcan:{channel}")
    assert (info.value.file, info.value.key, info.value.found) == ("--bus", "channel", channel)
    assert "1 to 15 bytes" in info.value.expected
    assert len(str(info.value)) < 300, "the name is shortened in the message"
    # the same channel in a hand config: refused by file and key, by `handctl check` too
    with pytest.raises(ConfigError) as info:
        parse_spec("hand", replace(hand.bus, channel=channel), hand.source)
    assert (info.value.file, info.value.key) == (hand.source, "bus.channel")
    # and by the open itself, before any sysfs path is made of it
    with pytest.raises(ConfigError):
        check_socketcan(channel, hand.bus, sysfs=Path("/nonexistent"))


def test_the_longest_interface_name_and_odd_legal_ones_are_taken() -> None:
    for channel in ("abcdefghijklmno", "can0;reboot", "vcan-1.2", "lo"):
        assert parse_spec(f"socketcan:{channel}") == BusSpec("socketcan", channel)


def test_the_suggested_command_quotes_the_channel_for_the_shell(
    hand: HandConfig, tmp_path: Path
) -> None:
    assert socketcan_setup_command("can0;reboot", hand.bus).startswith(
        "sudo ip link set 'can0;reboot' up type can"
    )
    with pytest.raises(BusError, match=r"ip link set 'can0;fd=1' up"):
        check_socketcan("can0;fd=1", hand.bus, sysfs=tmp_path, has_socketcan=_yes)


def test_an_interface_that_is_not_can_is_named_as_such(hand: HandConfig, tmp_path: Path) -> None:
    (tmp_path / "lo").mkdir()
    (tmp_path / "lo" / "type").write_text("772\n")  # ARPHRD_LOOPBACK
    (tmp_path / "lo" / "operstate").write_text("unknown\n")
    for kernel in (_yes, lambda: False):  # on a kernel without SocketCAN too: not told to
        # make lo a CAN interface with `ip link set lo up type can` (found by an outside audit)
        with pytest.raises(BusError, match=r"socketcan:lo: not a CAN interface \(its link type"):
            check_socketcan("lo", hand.bus, sysfs=tmp_path, has_socketcan=kernel)
    (tmp_path / "lo" / "type").write_text("280\n")
    check_socketcan("lo", hand.bus, sysfs=tmp_path, has_socketcan=_yes)


def test_a_kernel_without_socketcan_is_said_with_what_to_do(
    hand: HandConfig, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Past the interface checks (sysfs), the socket itself failed with a bare 'Address
    family not supported by protocol'. Run where the kernel has no AF_CAN (as here); on a
    kernel with it the failure cannot be made."""
    import errno
    import socket

    from handctl.online import bus as bus_module

    try:
        socket.socket(socket.AF_CAN, socket.SOCK_RAW, socket.CAN_RAW).close()
    except OSError as exc:
        if exc.errno != errno.EAFNOSUPPORT:
            raise
    else:
        pytest.skip("this kernel has SocketCAN")
    monkeypatch.setattr(bus_module, "check_socketcan", lambda *args, **kwargs: None)
    with pytest.raises(BusError, match=r"this kernel has no SocketCAN \(AF_CAN\); load its"):
        open_bus("socketcan:can0", hand.bus)


def test_a_vcan_and_a_kernel_without_socketcan_get_the_commands_that_fix_them(
    hand: HandConfig, tmp_path: Path
) -> None:
    """A missing vcan was told ``ip link set vcan0 up type can bitrate ...``, which cannot
    make an interface (nor does a vcan have a bit rate), and a kernel without AF_CAN was
    told the interface was missing, as if loading a driver would do."""
    with pytest.raises(BusError) as info:
        check_socketcan("vcan0", hand.bus, sysfs=tmp_path, has_socketcan=_yes)
    assert str(info.value) == (
        "socketcan:vcan0: no such network interface; a virtual CAN interface is made with: "
        "sudo modprobe vcan && sudo ip link add dev vcan0 type vcan && "
        "sudo ip link set vcan0 mtu 72 && sudo ip link set vcan0 up"
    )
    (tmp_path / "vcan0").mkdir()
    (tmp_path / "vcan0" / "operstate").write_text("down\n")
    with pytest.raises(
        BusError, match=r"interface is down; bring it up with: sudo ip link set vcan0 up$"
    ):
        check_socketcan("vcan0", hand.bus, sysfs=tmp_path, has_socketcan=_yes)
    (tmp_path / "can0").mkdir()
    (tmp_path / "can0" / "operstate").write_text("up\n")
    with pytest.raises(
        BusError, match=r"^socketcan:can0: this kernel has no SocketCAN \(AF_CAN\);"
    ):
        check_socketcan("can0", hand.bus, sysfs=tmp_path, has_socketcan=lambda: False)
