"""The slcan shim (motion.transport.slcan_shim) on a real pseudo-terminal with real python-can and pyserial."""

from __future__ import annotations

import errno
import os
import select
import sys
import time
from collections.abc import Iterator

import can
import pytest

from motion.errors import PortLost
from motion.protocol import CanFrame
from motion.transport import CanTransport
from motion.transport.base import port_gone
from motion.transport.can_endpoint import CanEndpoint
from motion.transport.slcan_shim import MAX_LINE_BYTES, SlcanShimBus, needs_shim
from tests.junk_flood import JunkFlood
from tests.test_transport_peers import status2

pytestmark = pytest.mark.skipif(sys.platform == "win32", reason="pseudo-terminals are POSIX")

FRAME_A = b"t1418A400680128230000\r"  # 0x141, a4 00 68 01 28 23 00 00
FRAME_B = b"t1428A400000000000000\r"


@pytest.fixture
def pty_bus() -> Iterator[tuple[int, SlcanShimBus]]:
    import tty

    master, slave = os.openpty()
    tty.setraw(slave)
    bus = SlcanShimBus(os.ttyname(slave), bitrate=1_000_000, sleep_after_open=0)
    os.read(master, 4096)  # the open sequence python-can wrote (close, bit rate, open)
    try:
        yield master, bus
    finally:
        bus.shutdown()
        os.close(master)
        os.close(slave)


def _frames(bus: SlcanShimBus, count: int, timeout_s: float = 1.0) -> list[tuple[int, bytes]]:
    got: list[tuple[int, bytes]] = []
    end = time.monotonic() + timeout_s
    while len(got) < count and time.monotonic() < end:
        message = bus.recv(0.05)
        if message is not None:
            got.append((message.arbitration_id, bytes(message.data)))
    return got


def test_joined_lines_come_out_one_by_one_from_one_read(pty_bus: tuple[int, SlcanShimBus]) -> None:
    master, bus = pty_bus
    os.write(master, b"z\r" + FRAME_A + b"z\r" + FRAME_B * 5)
    time.sleep(0.05)
    first = bus.recv(0.05)
    assert first is not None and (first.arbitration_id, bytes(first.data)) == (
        0x141,
        bytes.fromhex("a4 00 68 01 28 23 00 00"),
    )
    # The first frame's read took in every waiting byte: the rest is in the shim's buffer, none left in the port.
    assert bus.serialPortOrig.in_waiting == 0
    assert bytes(bus._buffer) == b"z\r" + FRAME_B * 5
    assert bus.pending_input()
    frames = _frames(bus, 5)
    assert frames == [(0x142, bytes.fromhex("a4") + bytes(7))] * 5
    assert not bus.pending_input()


def test_a_line_split_across_writes_is_reassembled(pty_bus: tuple[int, SlcanShimBus]) -> None:
    master, bus = pty_bus
    for cut in (1, 5, len(FRAME_A) - 1):
        os.write(master, FRAME_A[:cut])
        time.sleep(0.01)
        assert bus.recv(0.0) is None  # only part of a line so far
        os.write(master, FRAME_A[cut:])
        assert _frames(bus, 1) == [(0x141, bytes.fromhex("a4 00 68 01 28 23 00 00"))]


def test_garbage_lines_are_dropped_and_counted(pty_bus: tuple[int, SlcanShimBus]) -> None:
    master, bus = pty_bus
    os.write(master, b"tXYZ8\r" + FRAME_A + b"x12\r\a" + b"t14\r" + FRAME_B + b"\xff\xfe\r")
    assert _frames(bus, 2) == [(0x141, bytes.fromhex("a4 00 68 01 28 23 00 00")), (0x142, b"\xa4" + bytes(7))]
    assert bus.garbled_lines >= 3
    assert bus.recv(0.01) is None


def test_recv_waits_for_its_timeout_and_no_longer(pty_bus: tuple[int, SlcanShimBus]) -> None:
    _, bus = pty_bus
    start = time.monotonic()
    assert bus.recv(0.02) is None
    assert 0.015 <= time.monotonic() - start < 0.5


def _frame_lines(bus: SlcanShimBus, count: int) -> list[object]:
    got: list[object] = []
    end = time.monotonic() + 1.0
    while len(got) < count and time.monotonic() < end:
        item = bus.recv_frame(0.05)
        if item is not None:
            got.append(item if item.__class__ is tuple else ("message", item))
    return got


def test_recv_frame_gives_standard_data_frames_as_tuples_and_the_rest_as_python_can_does(
    pty_bus: tuple[int, SlcanShimBus],
) -> None:
    master, bus = pty_bus
    remote, extended, short = b"r1410\r", b"T000001418A400000000000000\r", b"t1413A40102\r"
    os.write(master, FRAME_A + b"z\r" + remote + extended + short + b"t14G8A400680128230000\r" + FRAME_B)
    got = _frame_lines(bus, 5)
    assert got[0] == (0x141, bytes.fromhex("a4 00 68 01 28 23 00 00"))
    kinds = [
        item[1] for item in got[1:3] if isinstance(item, tuple)
    ]  # python-can's own messages for the remote and the extended frame
    assert isinstance(kinds[0], can.Message) and kinds[0].is_remote_frame and kinds[0].arbitration_id == 0x141
    assert isinstance(kinds[1], can.Message) and kinds[1].is_extended_id and kinds[1].arbitration_id == 0x141
    assert got[3] == (0x141, bytes.fromhex("a4 01 02"))  # a 3-byte frame is a frame (the transport counts it bad)
    assert got[4] == (0x142, b"\xa4" + bytes(7))  # the garbled line between was dropped and counted
    assert bus.garbled_lines == 1
    assert bus.recv_frame(0.01) is None


@pytest.mark.parametrize("path", ["recv_frame", "recv"])
def test_a_frame_line_with_junk_or_two_lines_run_together_are_garbled_not_frames(
    pty_bus: tuple[int, SlcanShimBus], path: str
) -> None:
    # python-can's parser reads the id, the length and that many bytes, and ignores what follows: each of these was a
    # frame (0x141 a4 00 68 01 28 23 00 00) to it
    master, bus = pty_bus
    junk_after = FRAME_A[:-1] + b"XYZ\r"
    run_together = FRAME_A[:-1] + FRAME_B  # FRAME_A's \r lost
    too_many = FRAME_A[:-1] + b"00\r"  # a ninth byte (a length code of 8)
    stamped = FRAME_A[:-1] + b"1A2B\r"  # an adapter's time stamp: a frame
    fd_frame = b"d141F" + b"00" * 64 + b"\r"  # CAN FD, 64 bytes: a frame (python-can's message)
    os.write(master, junk_after + run_together + too_many + stamped + fd_frame + FRAME_B)
    got: list[tuple[int, bytes]] = []
    end = time.monotonic() + 2.0
    while len(got) < 3 and time.monotonic() < end:
        item = bus.recv_frame(0.05) if path == "recv_frame" else bus.recv(0.05)
        if isinstance(item, can.Message):
            got.append((item.arbitration_id, bytes(item.data)))
        elif item is not None:
            got.append(item)
    assert got == [(0x141, bytes.fromhex("a4 00 68 01 28 23 00 00")), (0x141, bytes(64)), (0x142, b"\xa4" + bytes(7))]
    assert bus.garbled_lines == 3


def _read_bytes(fd: int, count: int, timeout_s: float = 5.0) -> bytes:
    """``count`` bytes from ``fd`` (a pty delivers a write in pieces on a busy host), or what came by ``timeout_s``."""
    got = b""
    end = time.monotonic() + timeout_s
    while len(got) < count and time.monotonic() < end:
        if select.select([fd], [], [], max(0.0, end - time.monotonic()))[0]:
            got += os.read(fd, count - len(got))
    return got


def test_send_frame_writes_the_line_python_can_writes(pty_bus: tuple[int, SlcanShimBus]) -> None:
    master, bus = pty_bus
    frames = [(0x141, bytes.fromhex("a4 00 68 01 28 23 00 00")), (0x280, bytes.fromhex("ff 7f 00 80 01 00 fe ff"))]
    expected = b"t1418A400680128230000\rt2808FF7F00800100FEFF\r"
    _read_bytes(master, 1 << 16, timeout_s=0.3)  # the rest of the open sequence, on a busy host still on its way
    for arbitration_id, data in frames:
        bus.send_frame(arbitration_id, data, 0.1)
    fast = _read_bytes(master, len(expected))
    for arbitration_id, data in frames:
        bus.send(can.Message(arbitration_id=arbitration_id, data=data, is_extended_id=False), 0.1)
    assert fast == _read_bytes(master, len(expected)) == expected
    with pytest.raises(ValueError, match="0x800"):
        bus.send_frame(0x800, b"", 0.1)
    with pytest.raises(ValueError, match="9 bytes"):
        bus.send_frame(0x141, bytes(9), 0.1)
    # a batch: the same lines, in one write (a cycle's frames in one system call); a bad frame writes none of it
    bus.send_frames(frames, 0.1)
    assert _read_bytes(master, len(expected)) == expected
    with pytest.raises(ValueError, match="0x800"):
        bus.send_frames([frames[0], (0x800, b"")], 0.1)
    assert _read_bytes(master, 1, timeout_s=0.1) == b""


def test_endpoint_uses_the_shim_while_python_can_lacks_the_fix() -> None:
    import tty

    master, slave = os.openpty()
    tty.setraw(slave)
    try:
        with CanEndpoint("slcan", os.ttyname(slave), 1_000_000, sleep_after_open=0) as endpoint:
            assert isinstance(endpoint._bus, SlcanShimBus) is needs_shim()
            assert (endpoint._recv_frame is not None) is needs_shim()  # the loop's frames skip can.Message
            os.write(master, FRAME_A + FRAME_B)
            time.sleep(0.02)
            first, second = endpoint.recv(0.5), endpoint.recv(0.0)  # the second is buffered: no select wait
            assert first is not None and second is not None
            assert (first[0], second[0]) == (
                CanFrame(0x141, bytes.fromhex("a4 00 68 01 28 23 00 00")),
                CanFrame(0x142, b"\xa4" + bytes(7)),
            )
    finally:
        os.close(master)
        os.close(slave)


# ---------------------------------------------------------------------------------------------- issue 29


def test_a_terminal_error_of_a_dying_adapter_is_a_can_error_that_says_the_port_is_gone(
    pty_bus: tuple[int, SlcanShimBus], monkeypatch: pytest.MonkeyPatch
) -> None:
    # a busy host, an adapter dying mid-move: pyserial's flush() after the write ran tcdrain on the dead pty, whose
    # termios.error(EIO) is no OSError: it escaped the transport, and the arm halted for an "exception" instead of
    # a lost bus ("error: (5, 'Input/output error')")
    import termios

    _, bus = pty_bus

    def dead(*_: object) -> None:
        raise termios.error(errno.EIO, "Input/output error")

    monkeypatch.setattr(bus.serialPortOrig, "flush", dead)
    with pytest.raises(can.CanOperationError, match="Input/output error") as raised:
        bus.send_frame(0x141, bytes(8), 0.1)
    assert port_gone(raised.value)


def test_a_line_longer_than_any_slcan_line_is_junk_dropped_to_its_end(pty_bus: tuple[int, SlcanShimBus]) -> None:
    master, bus = pty_bus
    os.write(master, b"x" * 1000 + b"\r" + FRAME_A)  # a whole over-long line, then a frame
    assert _frames(bus, 1) == [(0x141, bytes.fromhex("a4 00 68 01 28 23 00 00"))]
    assert (bus.junk_bytes, bus.garbled_lines) == (1001, 1)
    os.write(master, b"y" * 300)  # an over-long line still coming: dropped as it comes, the buffer stays empty
    end = time.monotonic() + 2.0  # (a pty delivers a write in pieces on a busy host)
    while bus.junk_bytes < 1301 and time.monotonic() < end:
        assert bus.recv(0.05) is None
    assert (bus.junk_bytes, bus.garbled_lines, len(bus._buffer)) == (1301, 2, 0)
    os.write(master, b"y12\r" + FRAME_B)  # its end (short as it is, still junk), then a frame: in sync again
    assert _frames(bus, 1) == [(0x142, b"\xa4" + bytes(7))]
    assert (bus.junk_bytes, bus.garbled_lines) == (1305, 2)


#: The flood goes on this long: a read that ignored its timeout would last as long.
FLOOD_S = 6.0
#: A generous bound of a call with a timeout of a fraction of a second, on a loaded host (far below FLOOD_S).
SLACK_S = 2.0


def test_an_adapter_flooding_junk_holds_the_timeout_with_a_bounded_buffer() -> None:
    with JunkFlood(FLOOD_S) as flood:
        bus = SlcanShimBus(flood.path, bitrate=1_000_000, sleep_after_open=0)
        try:
            start = time.monotonic()
            assert bus.recv(0.2) is None
            assert bus.recv_frame(0.2) is None
            assert time.monotonic() - start < 0.4 + SLACK_S
            assert len(bus._buffer) <= MAX_LINE_BYTES
            assert bus.junk_bytes > MAX_LINE_BYTES and bus.garbled_lines >= 1
        finally:
            bus.shutdown()


def test_a_transport_on_a_flooding_adapter_keeps_its_deadline_and_counts_the_junk() -> None:
    with JunkFlood(FLOOD_S) as flood, CanTransport("slcan", flood.path, 1_000_000, sleep_after_open=0) as transport:
        start = transport.clock()
        replies = transport.transact([status2(1), status2(2)], start + 0.2)
        assert transport.clock() - start < 0.2 + SLACK_S
        assert [r.ok for r in replies] == [False, False]
        assert transport.bus_counters.dropped_bytes > MAX_LINE_BYTES
        assert "bytes of junk" in transport.junk_note()


def test_an_adapter_that_dies_is_lost_and_its_transport_closes_clean() -> None:
    import tty

    master, slave = os.openpty()
    tty.setraw(slave)
    try:
        transport = CanTransport("slcan", os.ttyname(slave), 1_000_000, sleep_after_open=0)
        assert transport.transact([status2(1)], transport.clock() + 0.02)[0].message is None  # nobody answers yet
        assert (transport.lost, transport.closed) == (None, False)
        os.close(master)  # the adapter's end dies: the port hangs up, a write fails with EIO
        master = -1
        with pytest.raises(PortLost, match="the port is gone"):
            transport.transact([status2(1)], transport.clock() + 0.1)
        assert transport.lost is not None and transport.closed  # nothing more can be sent: a loop on it ends
        start = time.monotonic()
        with pytest.raises(PortLost, match="the port is gone"):  # at once, without trying the port again
            transport.transact([status2(1)], transport.clock() + 1.0)
        assert time.monotonic() - start < 0.5
        endpoint = transport.port
        assert isinstance(endpoint, CanEndpoint)
        bus = endpoint._bus
        transport.close()  # python-can's close command cannot be written: logged, not raised
        if isinstance(bus, SlcanShimBus):
            assert not bus.serialPortOrig.is_open  # and the descriptor was released all the same
        assert transport.lost is not None
    finally:
        if master >= 0:
            os.close(master)
        os.close(slave)


@pytest.mark.parametrize(
    ("installed", "expected"),
    [
        ("4.6.1", True),
        ("4.5.0", True),
        ("4.6.1rc1", True),
        ("3.3.4", True),
        ("4.6.2", False),
        ("5.0.0", False),
        ("4.7", False),
        ("garbage", True),
    ],
)
def test_needs_shim_by_release(installed: str, expected: bool) -> None:
    assert needs_shim(installed) is expected
