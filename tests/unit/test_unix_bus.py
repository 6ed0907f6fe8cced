"""handctl's unix datagram bus, between real sockets of one process.

Linux queues ``net.unix.max_dgram_qlen`` datagrams per receiving socket (often 10), however
small they are and whoever sent them. A receiver that falls behind must cost delay, not frames,
as a CAN controller keeps a frame it took until arbitration lets it go; a receiver that stopped
reading costs itself frames once the transmit queue is full, every one of them counted, and
never costs the sender a send (on CAN, a listener that does not read overflows its own queue).
"""

from __future__ import annotations

import socket
import struct
import time
from collections.abc import Callable, Iterator
from dataclasses import replace
from pathlib import Path
from typing import Any

import can
import pytest

from handctl.config import HandConfig
from handctl.errors import ConfigError
from handctl.online import unixcan
from handctl.online.bus import (
    EXTENDED_ID_FLAG,
    MAX_FRAME_DATA,
    BusEventKind,
    Frame,
    HandBus,
    open_bus,
)
from handctl.online.busspec import parse_spec
from handctl.online.taps import TAP_TX
from handctl.online.unixcan import TX_QUEUE_FRAMES, UnixDatagramBus

OpenUnix = Callable[[], HandBus]


@pytest.fixture
def open_unix(hand: HandConfig, tmp_path: Path) -> Iterator[OpenUnix]:
    """Participants of one unix bus in a private directory, closed afterwards."""
    opened: list[HandBus] = []

    def participant() -> HandBus:
        bus = open_bus(f"unix:{tmp_path / 'bus'}", hand.bus)
        opened.append(bus)
        return bus

    yield participant
    for bus in opened:
        bus.close()


def catch_up(rx: HandBus, tx: HandBus, got: list[Frame], want: int) -> None:
    """The receiver reads and the sender flushes (its next burst would) until ``want`` frames
    arrived or no more come."""
    for _ in range(20):
        got += rx.drain()
        if len(got) >= want:
            return
        tx.flush()


def test_a_receiver_that_falls_behind_gets_every_frame_in_order(open_unix: OpenUnix) -> None:
    rx, tx = open_unix(), open_unix()
    sent: list[bytes] = []
    got: list[Frame] = []
    for tick in range(5):
        # twenty single-frame bursts between two reads: twice the datagrams the queue holds
        for i in range(20):
            data = bytes((tick, i, 0, 0, 0, 0, 0, 0))
            assert tx.send(0x050, data)
            sent.append(data)
        got += rx.drain()
    catch_up(rx, tx, got, len(sent))
    assert [f.data for f in got] == sent
    assert tx.events() == []
    assert (tx.sent, tx.tx_failed) == (len(sent), 0)
    counts = tx.transport_counts()
    assert counts["queue_full"] > 0  # the queue was full, and nothing was lost for it
    assert (counts["frames_dropped"], counts["frames_held"]) == (0, 0)


def test_held_frames_go_first_merged_into_few_datagrams(open_unix: OpenUnix) -> None:
    rx, tx = open_unix(), open_unix()
    for i in range(40):
        assert tx.send(0x050, bytes((i,)))
    queued = tx.transport_counts()["datagrams_sent"]
    assert tx.transport_counts()["frames_held"] == 40 - queued
    assert len(rx.drain()) == queued
    assert tx.send(0x181, bytes(16))  # the next burst takes what was held along, in order
    assert tx.transport_counts()["datagrams_sent"] == queued + 1
    frames = rx.drain()
    assert [f.data[0] for f in frames[:-1]] == list(range(queued, 40))
    assert frames[-1].arbitration_id == 0x181


def _offer(tx: HandBus, frames: int) -> None:
    """``frames`` single-frame bursts, numbered, every one of them sent."""
    for i in range(frames):
        assert tx.send(0x101, i.to_bytes(2, "little"))


def test_a_receiver_that_stopped_reading_costs_itself_counted_frames(open_unix: OpenUnix) -> None:
    rx, tx = open_unix(), open_unix()
    offered = TX_QUEUE_FRAMES + 100
    _offer(tx, offered)
    # The queue and the transmit queue full, the receiver loses frames; the sender none.
    dropped = tx.transport_counts()["frames_dropped"]
    assert dropped > 0
    assert (tx.sent, tx.tx_failed, tx.events()) == (offered, 0, [])
    # What it was not refused arrives, all of it, in order, once the receiver reads again:
    # the first frames, which its queues held.
    got: list[Frame] = []
    catch_up(rx, tx, got, offered - dropped)
    assert [int.from_bytes(f.data, "little") for f in got] == list(range(offered - dropped))


def test_a_stopped_listener_costs_a_reading_receiver_nothing(open_unix: OpenUnix) -> None:
    """A monitor held by SIGSTOP on the hand's bus: the node that reads gets every command,
    and the host never fails a send for the listener's sake."""
    stopped, node, host = open_unix(), open_unix(), open_unix()
    offered = TX_QUEUE_FRAMES + 100
    got: list[Frame] = []
    for i in range(offered):
        assert host.send(0x101, i.to_bytes(2, "little"))
        got += node.drain()
    got += node.drain()
    assert [int.from_bytes(f.data, "little") for f in got] == list(range(offered))
    assert (host.tx_failed, host.events()) == (0, [])
    dropped = host.transport_counts()["frames_dropped"]
    assert dropped > 0
    late: list[Frame] = []
    catch_up(stopped, host, late, offered - dropped)
    assert len(late) == offered - dropped
    assert stopped.transport_counts()["rx_frames_lost"] == dropped


def test_a_path_in_the_directory_that_is_no_participant_costs_nobody_a_frame(
    open_unix: OpenUnix, tmp_path: Path
) -> None:
    """A stream socket bound among the participants (``connect`` fails with EPROTOTYPE) used
    to end the loop over the receivers with that error: every participant failed every send,
    the host's stop frames among them. It is passed over and left as it is, and so is a file
    that is no socket (a refused connection was taken for a dead participant's socket and
    the file unlinked)."""
    directory = tmp_path / "bus"
    directory.mkdir()
    strangers = []
    for name in ("0-stream.sock", "zz-stream.sock"):  # before and after the participants
        stream = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        stream.bind(str(directory / name))
        stream.listen(1)
        strangers.append(stream)
    (directory / "1-notes.sock").write_text("not a socket")
    try:
        node, host = open_unix(), open_unix()
        for i in range(5):
            assert host.send(0x101, bytes([i]))
        got = node.drain()
        assert [f.data for f in got] == [bytes([i]) for i in range(5)]
        assert host.tx_failed == 0 and host.events() == []
        assert node.send(0x181, b"\x01")
        assert [f.data for f in host.drain()] == [b"\x01"]
    finally:
        for stream in strangers:
            stream.close()
    assert {p.name for p in directory.iterdir()} >= {
        "0-stream.sock",
        "zz-stream.sock",
        "1-notes.sock",
    }


def test_a_frame_longer_than_can_fd_allows_is_dropped_as_a_bus_event(open_unix: OpenUnix) -> None:
    """The unix bus carries up to 255 bytes a frame; no CAN-FD frame has more than 64. Such a
    frame was acted on, then logged cut to 64 bytes (the log's re-run differed from the run):
    it is dropped where it is drained, said as an event, and the frames around it arrive."""
    rx, tx = open_unix(), open_unix()
    assert tx.send(0x281, bytes(8))
    assert tx.send(0x281, bytes(70))
    assert tx.send(0x281, bytes(64))
    got = rx.drain()
    assert [len(f.data) for f in got] == [8, 64]
    events = rx.events()
    assert [e.kind for e in events] == [BusEventKind.RX_FAILED]
    assert "a frame of 70 bytes (id 0x281), longer than CAN-FD's 64: dropped" in events[0].detail


def test_a_receiver_is_told_how_many_frames_it_lost(open_unix: OpenUnix) -> None:
    """As a SocketCAN socket is told of its receive queue's overflow: a listener kept from
    reading can tell the gap it caused itself from a node that skipped a counter."""
    rx, tx = open_unix(), open_unix()
    offered = TX_QUEUE_FRAMES + 100
    _offer(tx, offered)
    refused = tx.transport_counts()["frames_dropped"]
    accepted = list(range(offered - refused))
    got: list[Frame] = []
    catch_up(rx, tx, got, len(accepted))  # told after what was held for it, where it was lost
    assert rx.transport_counts()["rx_frames_lost"] == refused > 0
    assert tx.transport_counts()["rx_frames_lost"] == 0  # the sender lost nothing itself
    assert tx.send(0x101, offered.to_bytes(2, "little"))  # said once
    got += rx.drain()
    assert rx.transport_counts()["rx_frames_lost"] == refused
    assert [int.from_bytes(f.data, "little") for f in got] == [*accepted, offered]


def test_a_burst_is_one_datagram_and_its_frames_share_its_fate(open_unix: OpenUnix) -> None:
    rx, tx = open_unix(), open_unix()
    taps: list[tuple[int, int]] = []
    tx.tap = lambda frames, direction: taps.extend((frame_id, direction) for frame_id, _ in frames)
    assert tx.send(0x181, bytes(16), more=True)
    assert tx.send(0x182, bytes(16), more=True)
    assert taps == [] and tx.sent == 0  # held until the burst ends
    assert tx.send(0x183, bytes(16))
    assert tx.transport_counts()["datagrams_sent"] == 1
    assert taps == [(0x181, TAP_TX), (0x182, TAP_TX), (0x183, TAP_TX)] and tx.sent == 3
    assert [f.arbitration_id for f in rx.drain()] == [0x181, 0x182, 0x183]


def test_python_can_opens_the_unix_bus_by_its_interface_name(tmp_path: Path) -> None:
    """The unix bus is a python-can interface (the ``can.interface`` entry point of the
    installed package), so any python-can program opens it by name, and its ``send`` sends
    at once, as python-can promises: no handctl code in between."""
    channel = str(tmp_path / "bus")
    sent = [
        can.Message(
            arbitration_id=0x123,
            data=bytes(range(12)),
            is_fd=True,
            bitrate_switch=True,
            is_extended_id=False,
        ),
        can.Message(arbitration_id=0x1ABCDEF, data=b"\x01\x02", is_fd=False, is_extended_id=True),
    ]
    with (
        can.Bus(interface="unix", channel=channel) as rx,
        can.Bus(interface="unix", channel=channel) as tx,
    ):
        for msg in sent:
            tx.send(msg)
        got = [rx.recv(timeout=5.0) for _ in sent]
        assert rx.recv(timeout=0) is None  # its own frames do not come back to the sender
    assert [
        (m.arbitration_id, bytes(m.data), m.is_fd, m.bitrate_switch, m.is_extended_id)
        for m in got
        if m is not None
    ] == [
        (m.arbitration_id, bytes(m.data), m.is_fd, m.bitrate_switch, m.is_extended_id) for m in sent
    ]


def test_a_remote_frame_stays_one_on_the_unix_bus_and_is_no_data_frame_to_handbus(
    hand: HandConfig, tmp_path: Path
) -> None:
    """A remote frame (RTR) lost its flag on the unix bus's wire and reached every receiver as
    a data frame of 0 bytes: on id 0x000 an EStop of no data, logged as one (found by an
    outside audit). It stays a remote frame, and ``HandBus`` says it as an event, never as a
    ``Frame``."""
    channel = tmp_path / "bus"
    with (
        can.Bus(interface="unix", channel=str(channel)) as theirs,
        can.Bus(interface="unix", channel=str(channel)) as listener,
        open_bus(f"unix:{channel}", hand.bus) as ours,
    ):
        for frame_id, extended in ((0x000, False), (0x181, False), (0x12345, True)):
            theirs.send(
                can.Message(
                    arbitration_id=frame_id,
                    is_remote_frame=True,
                    is_extended_id=extended,
                    is_fd=False,
                )
            )
        heard = [listener.recv(timeout=5.0) for _ in range(3)]
        frames: list[Frame] = []
        events = []
        for _ in range(50):
            frames += ours.drain()
            events += ours.events()
            if len(events) == 3:
                break
            time.sleep(0.01)
    assert [(m.arbitration_id, m.is_remote_frame) for m in heard if m is not None] == [
        (0x000, True),
        (0x181, True),
        (0x12345, True),
    ]
    assert frames == []
    assert [(e.kind, e.frame_id) for e in events] == [
        (BusEventKind.REMOTE_FRAME, 0x000),
        (BusEventKind.REMOTE_FRAME, 0x181),
        (BusEventKind.REMOTE_FRAME, 0x12345 | EXTENDED_ID_FLAG),
    ]
    # on the e-stop's id the nodes act on any frame: said so, not as harmless (found by an
    # outside audit)
    assert events[0].detail.startswith("a remote frame (RTR) on id 0x000, the e-stop's: ")
    assert "every node acts on any frame on that id" in events[0].detail
    assert events[1].detail.startswith("a remote frame (RTR) on id 0x181: a request for data")
    assert "on id 0x00012345 (29-bit)" in events[2].detail


def test_handbus_frames_cross_to_and_from_python_can_unchanged(
    hand: HandConfig, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """HandBus speaks to the unix bus in plain tuples (``FrameTransport``), building no
    python-can ``Message`` per frame; a python-can program on the same bus sees the same
    frames as from any python-can sender, and HandBus reads what such a program sends."""
    channel = tmp_path / "bus"
    built = [0]
    init = can.Message.__init__

    def counting(self: can.Message, *args: object, **kwargs: object) -> None:
        built[0] += 1
        init(self, *args, **kwargs)  # type: ignore[arg-type]

    with (
        open_bus(f"unix:{channel}", hand.bus) as ours,
        can.Bus(interface="unix", channel=str(channel)) as theirs,
    ):
        monkeypatch.setattr(can.Message, "__init__", counting)
        assert ours.send(0x101, bytes(range(16)), more=True)
        assert ours.send(0x1ABCDEF | EXTENDED_ID_FLAG, b"\x05\x06", more=True)
        assert ours.send(0x103, b"\x07")
        drained_nothing = ours.drain()
        assert built[0] == 0
        monkeypatch.setattr(can.Message, "__init__", init)
        got = [theirs.recv(timeout=5.0) for _ in range(3)]
        theirs.send(
            can.Message(arbitration_id=0x181, data=bytes(8), is_fd=False, is_extended_id=False)
        )
        theirs.send(
            can.Message(arbitration_id=0x12345, data=b"\x01", is_extended_id=True, is_fd=True)
        )
        theirs.send(can.Message(arbitration_id=0x040, is_error_frame=True, data=bytes(8)))
        monkeypatch.setattr(can.Message, "__init__", counting)
        frames: list[Frame] = []
        for _ in range(50):
            frames += ours.drain()
            if len(frames) == 2:
                break
        events = ours.events()
        assert built[0] == 0
    assert drained_nothing == []
    assert [
        (m.arbitration_id, bytes(m.data), m.is_fd, m.bitrate_switch, m.is_extended_id)
        for m in got
        if m is not None
    ] == [
        (0x101, bytes(range(16)), True, True, False),
        (0x1ABCDEF, b"\x05\x06", True, True, True),
        (0x103, b"\x07", True, True, False),
    ]
    assert [(f.arbitration_id, f.data, f.is_fd) for f in frames] == [
        (0x181, bytes(8), False),
        (0x12345 | EXTENDED_ID_FLAG, b"\x01", True),
    ]
    assert [e.kind for e in events] == [BusEventKind.BUS_OFF]


def test_the_participants_are_listed_again_only_when_the_directory_changed(
    hand: HandConfig, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A listing of the bus directory costs tens of µs: a sender lists it again only when
    the directory changed, and a participant that joins or leaves is still seen."""
    from handctl.online import unixcan

    monkeypatch.setattr(unixcan, "_SETTLED_NS", 0)  # any unchanged directory is settled
    listings = [0]
    glob = Path.glob

    def counting(self: Path, pattern: str) -> Any:
        listings[0] += 1
        return glob(self, pattern)

    monkeypatch.setattr(Path, "glob", counting)
    channel = f"unix:{tmp_path / 'bus'}"

    def send_after_refresh(tx: HandBus, frame_id: int) -> None:
        tx._bus._peers_at = 0.0  # type: ignore[attr-defined]  # the 50 ms are up
        assert tx.send(frame_id, b"\x01")

    with open_bus(channel, hand.bus) as tx, open_bus(channel, hand.bus) as first:
        send_after_refresh(tx, 0x101)
        assert [f.arbitration_id for f in first.drain()] == [0x101]
        before = listings[0]
        send_after_refresh(tx, 0x102)
        assert listings[0] == before  # nothing changed: no listing
        assert [f.arbitration_id for f in first.drain()] == [0x102]
        with open_bus(channel, hand.bus) as second:
            send_after_refresh(tx, 0x103)
            assert listings[0] == before + 1
            assert [f.arbitration_id for f in second.drain()] == [0x103]
            assert [f.arbitration_id for f in first.drain()] == [0x103]
        send_after_refresh(tx, 0x104)  # the second one left
        assert listings[0] == before + 2
        assert [f.arbitration_id for f in first.drain()] == [0x104]


def test_a_bus_readied_before_its_first_send_is_connected_to_each_receiver(
    open_unix: OpenUnix, hand: HandConfig
) -> None:
    """``prepare_send`` (a run's start-up ticks) looks the receivers up and connects to each,
    which the first send did otherwise (0.5 ms of CPU in the nodes' enable: docs/timing.md);
    a receiver that joins later is connected at a later call, and frames go as before."""
    tx, first = open_unix(), open_unix()
    unix = tx._bus
    assert isinstance(unix, UnixDatagramBus)
    tx.prepare_send()
    assert sorted(unix._links) == sorted(unix._peers) and len(unix._peers) == 1
    second = open_unix()
    # at once, not 50 ms later as a send would look: a run sends the nodes' enable at the
    # tick it first hears them, and a hand that joined since the last look missed it
    tx.prepare_send()
    assert len(unix._links) == 2
    assert tx.send(0x101, b"\x01") and tx.flush()
    for rx in (first, second):
        got: list[Frame] = []
        catch_up(rx, tx, got, 1)
        assert [f.data for f in got] == [b"\x01"]
    with open_bus(f"virtual:ready-{id(tx)}", hand.bus) as virtual:
        virtual.prepare_send()  # nothing to ready: no error


def _hostile_datagram(directory: Path, payload: bytes) -> None:
    """One datagram of ``payload`` to every participant in ``directory``, from a socket that
    is none: a peer that writes the wire by hand."""
    with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as peer:
        for path in directory.glob("*.sock"):
            peer.sendto(payload, str(path))


def _wire(frame_id: int, flags: int, data: bytes) -> bytes:
    return struct.pack("<dIBB", 0.0, frame_id, flags, len(data)) + data


@pytest.mark.parametrize(
    "payload, why",
    [
        # 40 frames of 64 bytes: more than the receive buffer holds, so the datagram comes cut
        (b"".join(_wire(0x181, 1, bytes(64)) for _ in range(40)), "longer than the"),
        (_wire(0x181, 1, bytes(16))[:-3], "a frame of 16 bytes with 13 left"),
        (_wire(0x181, 1, bytes(16)) + b"\x00\x01", "2 bytes after its last frame"),
        (_wire(0x181, 0x40, bytes(8)), "flags 0x40"),  # the transport's own word, forged
        # a lost count of 2**32 - 1: no sender loses that many frames for anyone in a second
        (_wire(0, 0x80, (2**32 - 1).to_bytes(4, "little")), "4294967295 frames were lost"),
    ],
    ids=["cut-by-the-buffer", "frame-cut-short", "bytes-after", "foreign-flag", "forged-lost"],
)
def test_a_malformed_datagram_is_dropped_whole_as_a_receive_failure(
    open_unix: OpenUnix, tmp_path: Path, payload: bytes, why: str
) -> None:
    """A datagram cut by the receive buffer used to be handed on with its last frame cut
    short, and a forged lost count was added as it came (a monitor's ``frames_lost`` went to
    trillions). Neither is passed on: the datagram is dropped, said as an ``RX_FAILED``
    event (as a frame over 64 bytes is, guarantee 55), and counted."""
    rx, tx = open_unix(), open_unix()
    _hostile_datagram(tmp_path / "bus", payload)
    assert tx.send(0x181, b"\x07")
    got: list[Frame] = []
    for _ in range(20):  # the drain that meets the failure ends there; the next goes on
        got += rx.drain()
        if got:
            break
    assert [(f.arbitration_id, f.data) for f in got] == [(0x181, b"\x07")]
    events = rx.events()
    assert [e.kind for e in events] == [BusEventKind.RX_FAILED]
    assert "unix bus: a malformed datagram" in events[0].detail and why in events[0].detail
    counts = rx.transport_counts()
    assert counts["rx_malformed"] == 1 and counts["rx_frames_lost"] == 0


def test_the_longest_datagram_a_sender_sends_arrives_whole(
    open_unix: OpenUnix, tmp_path: Path
) -> None:
    """The receive buffer holds a full batch of the longest CAN-FD frames, and no more: its
    size is derived from ``MAX_FRAME_DATA``, not written beside it."""
    rx = open_unix()
    full = [_wire(0x181 + i, 1, bytes([i]) * MAX_FRAME_DATA) for i in range(unixcan._BATCH)]
    _hostile_datagram(tmp_path / "bus", b"".join(full))
    got: list[Frame] = []
    for _ in range(20):
        got += rx.drain()
        if got:
            break
    assert [(f.arbitration_id, f.data) for f in got] == [
        (0x181 + i, bytes([i]) * MAX_FRAME_DATA) for i in range(unixcan._BATCH)
    ]
    assert rx.events() == []
    _hostile_datagram(tmp_path / "bus", b"".join(full) + _wire(0x181, 1, b"\x00"))
    for _ in range(20):
        if rx.drain() or rx.events():
            break
    assert rx.transport_counts()["rx_malformed"] == 1  # one byte more is cut by the buffer


def test_a_python_can_reader_is_told_of_a_malformed_datagram_as_python_can_says_it(
    tmp_path: Path,
) -> None:
    channel = tmp_path / "bus"
    with can.Bus(interface="unix", channel=str(channel)) as rx:
        _hostile_datagram(channel, _wire(0x181, 1, bytes(16))[:-1])
        with pytest.raises(can.CanOperationError, match="malformed datagram"):
            rx.recv(timeout=1.0)


def test_a_relative_unix_bus_directory_is_refused_not_made(
    hand: HandConfig, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Each process would take it from its own working directory: a hand and a host started
    from two directories with one spec were on two buses, each hearing nothing."""
    monkeypatch.chdir(tmp_path)
    with pytest.raises(ConfigError) as info:
        parse_spec("unix:relative_dir")
    assert (info.value.file, info.value.key) == ("--bus", "channel")
    assert f"unix:{tmp_path / 'relative_dir'}" in info.value.expected
    unix_hand = replace(hand.bus, interface="unix", channel="bus")
    with pytest.raises(ConfigError) as info:
        parse_spec("hand", unix_hand, hand.source)
    assert (info.value.file, info.value.key) == (hand.source, "bus.channel")
    with pytest.raises(ValueError, match="expected an absolute directory"):
        can.Bus(interface="unix", channel="relative_dir")
    assert list(tmp_path.iterdir()) == []
    parse_spec(f"unix:{tmp_path / 'bus'}")  # the documented form


def test_a_bus_directory_removed_in_use_fails_the_sends_and_says_why(
    open_unix: OpenUnix, tmp_path: Path
) -> None:
    """Sending to nobody looked like a bus that works: a run whose bus directory was removed
    stopped on the nodes' silence (FEEDBACK_TIMEOUT) with "0 bus events". The sends fail now,
    so the supervisor stops on its bus (BUS_ERROR) and the event names the directory."""
    import shutil
    import time

    rx, tx = open_unix(), open_unix()
    assert tx.send(0x181, bytes(8))
    assert len(rx.drain()) == 1
    shutil.rmtree(tmp_path / "bus")
    time.sleep(0.06)  # the directory is listed again at most every 50 ms
    assert not tx.send(0x181, bytes(8))
    events = tx.events()
    assert [e.kind for e in events] == [BusEventKind.TX_FAILED]
    assert f"the unix bus directory {tmp_path / 'bus'} is gone (removed" in events[0].detail


def test_a_bus_directory_made_anew_in_use_fails_the_sends_too(
    open_unix: OpenUnix, tmp_path: Path
) -> None:
    """Removed and made again (rm -rf; mkdir), the directory is another bus, and the sends
    went to nobody with no bus event, as a removed one's did."""
    import shutil
    import time

    rx, tx = open_unix(), open_unix()
    assert tx.send(0x181, bytes(8))
    assert len(rx.drain()) == 1
    shutil.rmtree(tmp_path / "bus")
    (tmp_path / "bus").mkdir()
    time.sleep(0.06)  # the directory is listed again at most every 50 ms
    assert not tx.send(0x181, bytes(8))
    assert [e.kind for e in tx.events()] == [BusEventKind.TX_FAILED]


def test_a_bus_directory_in_a_missing_one_is_refused_and_nothing_is_made(
    tmp_path: Path, hand: HandConfig
) -> None:
    """The bus makes its own directory, not the ones above it: a mistyped path made a whole
    tree, and the run then waited out its start-up for nodes no one would put there."""
    from handctl.errors import ConfigError
    from handctl.online.unixcan import UnixDatagramBus

    missing = tmp_path / "typo" / "bus"
    with pytest.raises(ConfigError, match="expected a directory in an existing one"):
        open_bus(f"unix:{missing}", hand.bus)
    with pytest.raises(ValueError, match="expected a directory in an existing one"):
        UnixDatagramBus(str(missing))  # as python-can opens it
    assert not (tmp_path / "typo").exists()
    with open_bus(f"unix:{tmp_path / 'bus'}", hand.bus):
        assert (tmp_path / "bus").is_dir()


def test_a_bus_spec_whose_directory_cannot_be_the_bus_s_is_bad_input(
    tmp_path: Path, hand: HandConfig
) -> None:
    """--bus unix:/nonexistent/dir and --bus unix:A_FILE were bus errors (exit 4, the second a
    bare FileExistsError): bad input, said against --bus before anything opens."""
    from handctl.errors import ConfigError
    from handctl.online.busspec import parse_spec
    from handctl.online.unixcan import UnixDatagramBus

    afile = tmp_path / "afile"
    afile.write_text("")
    for channel, said in (
        (tmp_path / "typo" / "bus", f"{tmp_path / 'typo'} is not a directory"),
        (afile, "not a directory"),
    ):
        with pytest.raises(ConfigError) as err:
            parse_spec(f"unix:{channel}", hand.bus, "test")
        assert (err.value.file, err.value.key) == ("--bus", "channel")
        assert said in str(err.value)
    with pytest.raises(ValueError, match=r"expected a directory .* found another kind of file"):
        UnixDatagramBus(str(afile))  # as python-can opens it
    assert parse_spec(f"unix:{tmp_path / 'bus'}", hand.bus, "test").channel == str(tmp_path / "bus")


def test_an_endpoint_name_left_behind_is_passed_over_and_too_many_are_said(
    tmp_path: Path, hand: HandConfig, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A participant killed with SIGKILL leaves its socket, and a process id comes round
    again: the bind failed with "Address already in use", naming neither the file nor why.
    Now the next name is taken; with every name tried taken, the bus says which."""
    import itertools
    import os

    from handctl.errors import BusError

    bus_dir = tmp_path / "bus"
    bus_dir.mkdir()
    pid = os.getpid()
    for n in range(1000, 1003):
        (bus_dir / f"{pid}-{n}.sock").write_text("left behind")
    monkeypatch.setattr(unixcan, "_unix_ids", itertools.count(1000))
    with open_bus(f"unix:{bus_dir}", hand.bus):
        assert (bus_dir / f"{pid}-1003.sock").is_socket()
    for n in range(1004, 1004 + unixcan._BIND_ATTEMPTS):
        (bus_dir / f"{pid}-{n}.sock").write_text("left behind")
    with pytest.raises(BusError, match=f"found {pid}-1004.sock, .* taken"):
        open_bus(f"unix:{bus_dir}", hand.bus)


def test_only_sockets_in_the_directory_are_sent_to_not_links(
    tmp_path: Path, hand: HandConfig
) -> None:
    """A symlink named like a participant sent every participant's traffic to the datagram
    socket it named (any on the machine); one to a participant doubled its frames."""
    bus_dir, outside = tmp_path / "bus", tmp_path / "outside.sock"
    victim = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    victim.bind(str(outside))
    victim.setblocking(False)
    try:
        with (
            open_bus(f"unix:{bus_dir}", hand.bus) as tx,
            open_bus(f"unix:{bus_dir}", hand.bus) as rx,
        ):
            for k, participant in enumerate(sorted(bus_dir.glob("*.sock"))):
                (bus_dir / f"twin{k}.sock").symlink_to(participant)
            (bus_dir / "link.sock").symlink_to(outside)
            time.sleep(0.1)  # past the participants' 50 ms between listings
            tx.send(0x123, b"\x01\x02")
            time.sleep(0.05)
            got = rx.drain(limit=100)
        with pytest.raises(BlockingIOError):
            victim.recv(100)
        assert [f.arbitration_id for f in got] == [0x123]
    finally:
        victim.close()


def test_a_bus_directory_that_is_a_loop_of_links_is_bad_input(
    tmp_path: Path, hand: HandConfig
) -> None:
    """Two symbolic links to each other: the bus's making of its directory failed on them,
    a bus error (exit 4) saying only FileExistsError."""
    from handctl.errors import ConfigError
    from handctl.online.busspec import parse_spec
    from handctl.online.unixcan import UnixDatagramBus

    (tmp_path / "a").symlink_to(tmp_path / "b")
    (tmp_path / "b").symlink_to(tmp_path / "a")
    with pytest.raises(ConfigError, match="a symbolic link that leads to no directory"):
        parse_spec(f"unix:{tmp_path / 'a'}", hand.bus, "test")
    with pytest.raises(ValueError, match="a symbolic link that leads to no directory"):
        UnixDatagramBus(str(tmp_path / "a"))


def test_the_participant_that_made_the_directory_takes_it_away_when_it_is_left_empty(
    tmp_path: Path,
) -> None:
    """``handctl sim --bus unix:/tmp/hand`` made the directory and left it behind, empty,
    after every session (found by an outside audit). One made beforehand is the user's and
    stays, and so does one another participant is still on (the maker cannot know whether
    one that joins after it leaves would find it)."""
    made = tmp_path / "made"
    maker = UnixDatagramBus(str(made))
    joined = UnixDatagramBus(str(made))
    joined.shutdown()
    assert made.is_dir()  # not the leaver's to take
    maker.shutdown()
    assert not made.exists()
    maker, joined = UnixDatagramBus(str(made)), UnixDatagramBus(str(made))
    maker.shutdown()
    assert made.is_dir()  # another is still on it
    joined.shutdown()
    given = tmp_path / "given"
    given.mkdir()
    UnixDatagramBus(str(given)).shutdown()
    assert given.is_dir() and not list(given.iterdir())
