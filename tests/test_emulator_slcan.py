"""The virtual slcan adapter's command set, without a pty."""

from __future__ import annotations

from motion.emulator.slcan import BELL, OK, SlcanDevice, SlcanFrame
from motion.protocol import CanFrame


def feed(device: SlcanDevice, text: str) -> tuple[bytes, list[SlcanFrame]]:
    return device.feed(text.encode())


def test_python_can_open_sequence() -> None:
    device = SlcanDevice()
    # slcanBus(bitrate=1000000): close, set bit rate, empty data bit rate, open, then open again.
    answer, frames = feed(device, "C\rS8\r\rO\rO\r")
    assert answer == BELL + OK + OK + OK + BELL and frames == []
    assert device.is_open and device.bitrate == 1_000_000 and device.errors == 2
    assert feed(device, "C\r")[0] == OK and not device.is_open


def test_bit_rates_only_while_closed() -> None:
    device = SlcanDevice()
    assert feed(device, "S6\r")[0] == OK and device.bitrate == 500_000
    assert feed(device, "S9\r")[0] == BELL and device.bitrate == 500_000
    assert feed(device, "s0014\r")[0] == OK and device.bitrate == 500_000  # BTR 00 14 at 8 MHz
    assert feed(device, "s011C\r")[0] == OK and device.bitrate == 125_000
    assert feed(device, "sXYZW\r")[0] == BELL
    feed(device, "O\r")
    assert feed(device, "S8\r")[0] == BELL and device.bitrate == 125_000


def test_versions_serial_and_status() -> None:
    device = SlcanDevice(serial_number="AB12")
    assert feed(device, "V\rN\r")[0] == b"V1013\rNAB12\r"
    assert feed(device, "F\r")[0] == BELL  # status needs an open channel
    feed(device, "O\r")
    assert feed(device, "F\r")[0] == b"F00\r"


def test_frames_from_the_host() -> None:
    device = SlcanDevice()
    assert feed(device, "t14180102030405060708\r") == (BELL, [])  # channel closed
    feed(device, "O\r")
    answer, frames = feed(device, "t14180102030405060708\rT1234567820A0B\rr1410\rR000000010\r")
    assert answer == b"z\rZ\rz\rZ\r"
    assert frames == [
        SlcanFrame(0x141, bytes(range(1, 9))),
        SlcanFrame(0x12345678, b"\x0a\x0b", extended=True),
        SlcanFrame(0x141, b"", remote=True),
        SlcanFrame(0x1, b"", extended=True, remote=True),
    ]
    for bad in ("t1418010203\r", "t800100\r", "t14190000000000000000000000\r", "t14G100\r", "t1\r"):
        assert feed(device, bad) == (BELL, []), bad


def test_listen_only_refuses_to_send() -> None:
    device = SlcanDevice()
    assert feed(device, "L\r")[0] == OK
    assert feed(device, "t1410\r") == (BELL, [])
    assert device.to_host(CanFrame(0x141, b"\x9a" + bytes(7)), 0.0).startswith(b"t1418")


def test_frames_to_the_host_with_time_stamps_and_polling() -> None:
    device = SlcanDevice()
    frame = CanFrame(0x141, bytes.fromhex("9c1a6400140000a0"))
    assert device.to_host(frame, 1.0) == b""  # closed: nothing goes out
    assert feed(device, "Z1\rX0\rO\r")[0] == OK * 3
    assert device.to_host(frame, 61.5) == b""  # auto-poll off: queued
    device.to_host(frame, 61.6)
    assert feed(device, "P\r")[0] == b"t14189C1A6400140000A005DC\r"  # 61.5 s -> 1500 ms mod 60000
    assert feed(device, "A\r")[0] == b"t14189C1A6400140000A00640\rA\r"
    assert feed(device, "P\r")[0] == OK


def test_settings_and_garbage() -> None:
    device = SlcanDevice()
    assert feed(device, "M00000000\rm000007FF\rU2\rQ0\rX1\rZ0\r")[0] == OK * 6
    assert feed(device, "W2\r")[0] == BELL
    assert feed(device, "x" * 100)[0] == BELL  # an overlong line is dropped up to its CR
    assert feed(device, "x" * 100 + "\r")[0] == b""
    assert feed(device, "\r")[0] == OK
    assert feed(device, "V\r\n")[0] == b"V1013\r"  # CR LF tolerated
