"""The emulator on real buses: python-can's virtual bus, a slcan pty opened by python-can, an RS485 pty opened by
pyserial, and the command line. Replies are decoded with the protocol codec; timing checks are lower bounds only.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
import uuid
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest
import serial

from motion.emulator import (
    Emulator,
    FrameLog,
    Rs485Attachment,
    SlcanAttachment,
    TimingModel,
    VirtualCanAttachment,
    parse_fault,
)
from motion.emulator.cli import parse_ids
from motion.emulator.pty import PseudoTerminal
from motion.errors import DecodeError
from motion.protocol import (
    Bare,
    CanFrame,
    Command,
    Message,
    MotorState,
    MultiMotorTorque,
    Rs485Parser,
    WireProtocol,
    can_frame,
    rs485_frame,
)
from motion.transport.can_endpoint import CanEndpoint
from tests.test_emulator_drive import check_reply, requests_for

ROOT = Path(__file__).resolve().parent.parent
REPLY_TIMEOUT_S = 2.0
QUIET_S = 0.15


def wait_for(condition: Callable[[], bool], timeout_s: float = REPLY_TIMEOUT_S) -> bool:
    deadline = time.monotonic() + timeout_s
    while not condition():
        if time.monotonic() > deadline:
            return False
        time.sleep(0.005)
    return True


def can_exchange(host: CanEndpoint, frame: CanFrame, count: int = 1) -> list[tuple[int, Message]]:
    """Send a request and collect ``count`` decoded replies (a stray extra reply would fail the next exchange's
    checks; with ``count`` 0 the bus must stay quiet for a while).
    """
    host.send(frame)
    replies: list[tuple[int, Message]] = []
    deadline = time.monotonic() + REPLY_TIMEOUT_S
    while len(replies) < count and time.monotonic() < deadline:
        received = host.recv(deadline - time.monotonic())
        if received is not None:
            replies.append(can_frame.decode_reply(received[0].arbitration_id, received[0].data))
    if not count:
        assert host.recv(QUIET_S) is None, "a reply where none was expected"
    return replies


def rs485_exchange(port: serial.Serial, raw: bytes, timeout_s: float = REPLY_TIMEOUT_S) -> bytes | None:
    """Send a request frame and return the reply frame, or None if the line stays silent."""
    port.write(raw)
    parser = Rs485Parser()
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        parser.feed(port.read(port.in_waiting or 1))
        frame = parser.next_frame()
        if frame is not None:
            return frame.to_bytes()
    return None


@pytest.fixture
def frame_log(tmp_path: Path) -> Iterator[FrameLog]:
    with FrameLog(tmp_path / "frames.log") as log:
        yield log


def log_lines(tmp_path: Path, direction: str) -> list[str]:
    return [line for line in (tmp_path / "frames.log").read_text().splitlines() if line.split()[1] == direction]


BROKEN_CAN = [
    CanFrame(0x141, bytes(8)),  # command 0x00
    CanFrame(0x141, bytes.fromhex("9a000000000000")),  # 7 bytes
    CanFrame(0x13F, bytes.fromhex("9a00000000000000")),  # id below 0x141
    CanFrame(0x142, bytes.fromhex("9a00000000000001")),  # reserved byte set
]


def check_can_bus(host: CanEndpoint, attachment: VirtualCanAttachment | SlcanAttachment, tmp_path: Path) -> None:
    """Every CAN command answered as the table says; 0x280 answered by 1..4 in order; broken frames counted."""
    requests = requests_for(WireProtocol.CAN)
    for message in requests:
        replies = can_exchange(host, can_frame.encode_request(message, 2))
        assert len(replies) == 1 and replies[0][0] == 2, message
        check_reply(message, replies[0][1], WireProtocol.CAN)
    replies = can_exchange(host, can_frame.encode_request(MultiMotorTorque(0.1, 0.2, 0.3, 0.4)), 4)
    assert [motor_id for motor_id, _ in replies] == [1, 2, 3, 4]
    assert all(isinstance(m, MotorState) and m.command is Command.TORQUE for _, m in replies)
    assert can_exchange(host, can_frame.encode_request(Bare(Command.READ_STATUS_1), 9), 0) == []  # nobody there
    for frame in BROKEN_CAN:
        assert can_exchange(host, frame, 0) == []
    assert wait_for(lambda: attachment.stats.decode_errors == len(BROKEN_CAN))
    stats = attachment.stats
    sent = len(requests) + 2 + len(BROKEN_CAN)
    assert (stats.requests, stats.replies, stats.unanswered) == (sent, len(requests) + 4, 1)
    assert len(log_lines(tmp_path, "BAD")) == len(BROKEN_CAN)
    assert len(log_lines(tmp_path, "OUT")) == stats.replies
    assert "motor 2: MotorState(command=<Command.READ_STATUS_2" in "\n".join(log_lines(tmp_path, "OUT"))


def test_virtual_can_bus(tmp_path: Path, frame_log: FrameLog) -> None:
    channel = f"emu-{uuid.uuid4().hex}"
    emulator = Emulator([1, 2, 3, 4])
    with (
        VirtualCanAttachment(emulator, channel, frame_log=frame_log) as attachment,
        CanEndpoint("virtual", channel) as host,
    ):
        check_can_bus(host, attachment, tmp_path)


def test_slcan_pty_opened_by_python_can(tmp_path: Path, frame_log: FrameLog) -> None:
    link = tmp_path / "rmd-can"
    emulator = Emulator([1, 2, 3, 4])
    with SlcanAttachment(emulator, link, frame_log=frame_log) as attachment:
        assert attachment.path == str(link) and os.readlink(link).startswith("/dev/pts/")
        with CanEndpoint("slcan", str(link), bitrate=500_000, sleep_after_open=0) as host:
            check_can_bus(host, attachment, tmp_path)
            assert attachment.device.is_open and attachment.bitrate == 500_000
        assert wait_for(lambda: not attachment.device.is_open)  # python-can closed the channel with C
        assert attachment.stats.adapter_errors == 2  # its C before O, and its second O: BELL on a real adapter too
    assert not os.path.lexists(link)


def test_slcan_receive_honours_short_timeouts(tmp_path: Path) -> None:
    # python-can's slcan blocks for its serial read timeout (1 ms) whatever timeout recv() gets; the endpoint waits
    # on the port itself, so a poll of an idle bus returns at once and a short wait ends on time. The fastest of
    # several tries is compared (noise only makes a try slower); before the fix every try took >= 1 ms.
    link = tmp_path / "rmd-can"
    with (
        SlcanAttachment(Emulator([1]), link),
        CanEndpoint("slcan", str(link), bitrate=1_000_000, sleep_after_open=0) as host,
    ):
        polls, waits = [], []
        for _ in range(10):
            start = time.perf_counter()
            assert host.recv(0.0) is None
            polls.append(time.perf_counter() - start)
            start = time.perf_counter()
            assert host.recv(0.0002) is None
            waits.append(time.perf_counter() - start)
        assert min(polls) < 0.0005 and min(waits) < 0.0008, (min(polls), min(waits))
        replies = can_exchange(host, can_frame.encode_request(Bare(Command.READ_STATUS_1), 1))
        assert replies[0][0] == 1  # frames still come through the descriptor wait


def test_full_pty_drops_whole_writes_never_the_end_of_one() -> None:
    # A client that falls behind must see whole frames or none: a cut line garbles slcan (python-can then raises).
    line = b"t1418A41F2A000000E803\r"
    with PseudoTerminal() as pty:
        client = os.open(pty.slave_path, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
        try:
            delivered = 0
            while pty.write(line) == 0:  # nobody reads: fill the pty
                delivered += 1
                assert delivered < 1_000_000, "the pty never filled"
            assert pty.write(line) == len(line)  # dropped whole while the rest of the last one waits
            received = b""
            for _ in range(1000):
                pty.read(0.0)  # sends what is left of the last accepted write
                try:
                    chunk = os.read(client, 65536)
                except BlockingIOError:
                    chunk = b""
                received += chunk
                if len(received) >= len(line) * delivered and not chunk:
                    break
        finally:
            os.close(client)
    assert received == line * delivered


def test_rs485_pty_opened_by_pyserial(tmp_path: Path, frame_log: FrameLog) -> None:
    link = tmp_path / "rmd-485"
    emulator = Emulator([1, 5])
    with (
        Rs485Attachment(emulator, link, frame_log=frame_log) as attachment,
        serial.Serial(str(link), 115200, timeout=0.01) as port,
    ):
        requests = requests_for(WireProtocol.RS485)
        for message in requests:
            reply = rs485_exchange(port, rs485_frame.encode_request(message, 5))
            assert reply is not None, message
            motor_id, decoded = rs485_frame.decode_reply(reply)
            assert motor_id == 5
            check_reply(message, decoded, WireProtocol.RS485)
        good = rs485_frame.encode_request(Bare(Command.READ_STATUS_1), 1)
        broken = [
            good[:-1] + bytes([good[-1] ^ 1]),  # header checksum
            rs485_frame.encode_request(Bare(Command.READ_STATUS_1), 1)[:4] + b"\x00",
            bytes.fromhex("3e 12 01 00 45"),  # the document's 0x12 example (erratum R1)
            rs485_frame.Rs485Frame(0x00, 1, b"").to_bytes(),  # no such command
            rs485_frame.Rs485Frame(0x9A, 1, b"\x00").to_bytes(),  # 0x9A carries no data
            rs485_frame.Rs485Frame(0x95, 1, b"").to_bytes(),  # CAN only
        ]
        for raw in broken:
            assert rs485_exchange(port, raw, QUIET_S) is None, raw.hex(" ")
        assert wait_for(lambda: attachment.stats.decode_errors >= len(broken))
        assert rs485_exchange(port, good) is not None  # the line still works
        # the emulator thread counts a reply after writing it: the reader may have it first on a slow host
        assert wait_for(lambda: attachment.stats.replies == len(requests) + 1), attachment.stats
    assert len(log_lines(tmp_path, "BAD")) == attachment.stats.decode_errors


def test_simulation_time_follows_the_wall_clock_on_a_bus() -> None:
    emulator = Emulator([1])
    with VirtualCanAttachment(emulator, f"emu-{uuid.uuid4().hex}"):
        time.sleep(0.3)
        assert emulator.time_s >= 0.25
    assert emulator.time_s < 5.0


def test_latency_delay_fault_and_bus_time_are_lower_bounds_on_reply_time() -> None:
    channel = f"emu-{uuid.uuid4().hex}"
    emulator = Emulator(range(1, 7), faults=[parse_fault("delay:6@0:40")])
    timing = TimingModel(latency_s=0.005, bus_time=True)
    with (
        VirtualCanAttachment(emulator, channel, bitrate=10_000, timing=timing),
        CanEndpoint("virtual", channel) as host,
    ):
        start = time.monotonic()
        replies = can_exchange(host, can_frame.encode_request(Bare(Command.READ_STATUS_2), 1))
        assert replies and time.monotonic() - start >= 0.005 + 2 * 111 / 10_000
        start = time.monotonic()
        for motor_id in range(1, 6):
            host.send(can_frame.encode_request(Bare(Command.READ_STATUS_2), motor_id))
        for _ in range(5):
            assert host.recv(REPLY_TIMEOUT_S) is not None
        assert time.monotonic() - start >= 10 * 111 / 10_000  # ten frames, one after the other
        start = time.monotonic()
        assert can_exchange(host, can_frame.encode_request(Bare(Command.READ_STATUS_2), 6))
        assert time.monotonic() - start >= 0.040


def test_rs485_bus_time_counts_bytes_at_the_baud_rate(tmp_path: Path) -> None:
    emulator = Emulator([1])
    timing = TimingModel(latency_s=0.0, bus_time=True)
    with (
        Rs485Attachment(emulator, tmp_path / "line", baud=9600, timing=timing) as attachment,
        serial.Serial(attachment.path, 9600, timeout=0.01) as port,
    ):
        start = time.monotonic()
        assert rs485_exchange(port, rs485_frame.encode_request(Bare(Command.READ_STATUS_2), 1)) is not None
        assert time.monotonic() - start >= (5 + 13) * 10 / 9600


def test_link_faults_on_the_bus(tmp_path: Path) -> None:
    emulator = Emulator([1, 2], faults=[parse_fault("corrupt:1@0"), parse_fault("silent:2@0")])
    with (
        Rs485Attachment(emulator, tmp_path / "line") as attachment,
        serial.Serial(attachment.path, 115200, timeout=0.01) as port,
    ):
        port.write(rs485_frame.encode_request(Bare(Command.READ_STATUS_1), 1))
        assert wait_for(lambda: port.in_waiting >= 13)
        with pytest.raises(DecodeError, match="checksum"):
            rs485_frame.decode_reply(port.read(13))
        assert rs485_exchange(port, rs485_frame.encode_request(Bare(Command.READ_STATUS_1), 2), QUIET_S) is None
        assert wait_for(lambda: attachment.stats.corrupted == 1 and attachment.stats.unanswered == 1)


def test_a_pty_link_never_replaces_a_regular_file(tmp_path: Path) -> None:
    path = tmp_path / "precious"
    path.write_text("keep")
    with pytest.raises(Exception, match="not a symlink"):
        Rs485Attachment(Emulator([1]), path)
    assert path.read_text() == "keep"


def test_parse_ids() -> None:
    assert parse_ids("1-6") == (1, 2, 3, 4, 5, 6)
    assert parse_ids("5,1,3") == (1, 3, 5)
    assert parse_ids(" 1-2 , 32") == (1, 2, 32)
    for text, message in [
        ("0-3", "outside 1..32"),
        ("1,33", "outside 1..32"),
        ("6-1", "goes backwards"),
        ("1-3,2", "given twice"),
        ("a", "not an id"),
        ("", "not an id"),
    ]:
        with pytest.raises(ValueError, match=message):
            parse_ids(text)


def start_cli(*args: str) -> subprocess.Popen[str]:
    return subprocess.Popen(
        [sys.executable, "-m", "motion.emulator", *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        cwd=ROOT,
    )


def test_cli_runs_until_sigterm_and_logs_every_frame(tmp_path: Path) -> None:
    rs485_link, slcan_link, log = tmp_path / "r485", tmp_path / "slcan", tmp_path / "cli.log"
    process = start_cli(
        "--ids", "1-3", "--rs485-link", str(rs485_link), "--slcan-link", str(slcan_link),
        "--log", str(log), "--latency-ms", "0.5", "--bus-time", "--fault", "under_voltage:2@0",
    )  # fmt: skip
    try:
        assert process.stdout is not None
        lines = [process.stdout.readline() for _ in range(3)]
        assert lines[0].startswith(f"slcan: {slcan_link} (pty /dev/pts/")
        assert lines[1].startswith(f"rs485: {rs485_link} (pty /dev/pts/")
        assert "emulating motors 1,2,3" in lines[2] and "under_voltage:2@0" in lines[2]
        with serial.Serial(str(rs485_link), 115200, timeout=0.01) as port:
            reply = rs485_exchange(port, rs485_frame.encode_request(Bare(Command.READ_STATUS_1), 2))
            assert reply is not None
            assert rs485_frame.decode_reply(reply)[1] == rs485_frame.decode_reply(reply)[1]
            port.write(b"\x3e\x00\x01\x00\x3f")  # checksum-valid frame of an unknown command
        with CanEndpoint("slcan", str(slcan_link), bitrate=1_000_000, sleep_after_open=0) as host:
            assert can_exchange(host, can_frame.encode_request(Bare(Command.READ_STATUS_2), 3))
        time.sleep(0.1)
    finally:
        process.send_signal(signal.SIGTERM)
        _, stderr = process.communicate(timeout=10)
    assert process.returncode == 0, stderr
    assert "rs485: 2 requests, 1 replies, 1 protocol errors" in stderr
    text = log.read_text()
    assert " IN   rs485" in text and " OUT  rs485" in text and " BAD  rs485" in text and " OUT  slcan" in text
    assert "Status1(command=<Command.READ_STATUS_1: 154>, temperature_c=25, voltage_v=12.0" in text
    assert not rs485_link.exists() and not slcan_link.exists()


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--ids", "1-40", "--rs485-link", "x"], "motor id 40 is outside 1..32"),
        (["--ids", "1-3"], "at least one of --slcan-link"),
        (["--ids", "1", "--virtual-channel", "c", "--fault", "silent:2@0"], "motor 2 is not emulated"),
        (["--ids", "1", "--virtual-channel", "c", "--fault", "hot:1@0"], "unknown kind 'hot'"),
    ],
)
def test_cli_usage_errors_exit_2(args: list[str], message: str) -> None:
    process = start_cli(*args)
    _, stderr = process.communicate(timeout=20)
    assert process.returncode == 2
    assert message in stderr
