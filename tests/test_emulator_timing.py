"""Bus-time model: CAN bit counting with stuffing, RS485 byte times, serialisation on one medium."""

from __future__ import annotations

import random

import pytest

from motion.emulator.timing import BusClock, TimingModel, can_frame_bits, can_frame_time_s
from motion.protocol import Bare, Command, MotorState, can_frame
from motion.protocol.rs485_frame import rs485_frame_time_s


def test_an_all_zero_frame_has_one_stuff_bit_per_five_zeros() -> None:
    # SOF + id + RTR + IDE + r0 + DLC = 19 zero bits, CRC-15 of zeros is zero: 34 zeros, 6 stuff bits,
    # plus the 13 fixed tail bits.
    assert can_frame_bits(0x000, b"") == 34 + 6 + 13


def test_eight_byte_frames_take_111_to_135_bits() -> None:
    rng = random.Random(1)
    counts = {can_frame_bits(rng.randrange(0x800), rng.randbytes(8)) for _ in range(500)}
    assert min(counts) >= 111 and max(counts) <= 135
    assert len(counts) > 5  # stuffing depends on the content
    assert can_frame_bits(0x141, bytes(8)) > can_frame_bits(0x155, b"\x55" * 8)


def test_frame_and_byte_times() -> None:
    frame = can_frame.encode_reply(MotorState(Command.READ_STATUS_2, 30, 1.0, 10, 100), 1)
    assert 111e-6 <= can_frame_time_s(frame.arbitration_id, frame.data, 1_000_000) <= 135e-6
    assert can_frame_time_s(frame.arbitration_id, frame.data, 500_000) == pytest.approx(
        2 * can_frame_time_s(frame.arbitration_id, frame.data, 1_000_000)
    )
    assert rs485_frame_time_s(13, 115_200) == pytest.approx(13 * 10 / 115_200)
    assert can_frame_bits(0x141, can_frame.encode_request(Bare(Command.READ_STATUS_2), 1).data) >= 111


def test_bus_clock_serialises_frames() -> None:
    bus = BusClock()
    assert bus.occupy(1.0, 0.1) == pytest.approx(1.1)
    assert bus.occupy(1.0, 0.1) == pytest.approx(1.2)  # waits for the first
    assert bus.occupy(2.0, 0.1) == pytest.approx(2.1)  # bus idle meanwhile


def test_timing_model_refuses_negative_latency() -> None:
    with pytest.raises(ValueError, match="latency"):
        TimingModel(latency_s=-0.001)


def _bit_by_bit(arbitration_id: int, data: bytes) -> int:
    """The frame's bits counted the slow, obvious way: a list of bits, a bit-serial CRC-15, a bit-serial stuffer."""
    bits = [0] + [(arbitration_id >> (10 - i)) & 1 for i in range(11)] + [0, 0, 0]
    bits += [(len(data) >> (3 - i)) & 1 for i in range(4)]
    for byte in data:
        bits += [(byte >> (7 - i)) & 1 for i in range(8)]
    crc = 0
    for bit in bits:
        feedback = bit ^ ((crc >> 14) & 1)
        crc = (crc << 1) & 0x7FFF
        if feedback:
            crc ^= 0x4599
    bits += [(crc >> (14 - i)) & 1 for i in range(15)]
    stuffed, run, previous = 0, 0, -1
    for bit in bits:
        run = run + 1 if bit == previous else 1
        previous = bit
        if run == 5:
            stuffed += 1
            previous, run = 1 - bit, 1
    return len(bits) + stuffed + 13


def test_the_fast_bit_count_is_the_bit_serial_one() -> None:
    rng = random.Random(7)
    frames = [(rng.randrange(0x800), rng.randbytes(rng.randrange(9))) for _ in range(3000)]
    # runs that end exactly on a stuff bit, long runs, and runs that a stuff bit joins
    frames += [(0x000, bytes(n)) for n in range(9)] + [(0x7FF, b"\xff" * n) for n in range(9)]
    frames += [(0x0F8, b"\x07\xc1\xf0\x7c\x1f\x07\xc1\xf0"), (0x1E0, b"\xf0\x0f\xf0\x0f\xe0\x1f\x80\x7f")]
    for arbitration_id, data in frames:
        assert can_frame_bits(arbitration_id, data) == _bit_by_bit(arbitration_id, data), (hex(arbitration_id), data)
