"""Reply timing: the drive's processing latency and an optional model of the time frames occupy the bus.

CAN: a frame's bits are counted exactly - SOF, 11-bit identifier, RTR, IDE, r0, DLC, data, the frame's own CRC-15
and the stuff bits that this particular bit pattern needs (a complementary bit after five equal bits, from SOF to the
end of the CRC), then CRC delimiter, ACK slot and delimiter, 7-bit EOF and 3-bit intermission. An 8-byte frame takes
111 bits without stuffing and at most 135 with the worst-case 24 stuff bits: 111..135 µs at 1 Mbit/s.

RS485: 10 bits per byte at the baud rate (start, 8 data, stop; 8N1): a 13-byte reply takes 1.13 ms at 115200 baud.

The bus is one shared medium (CAN) or half duplex (RS485): a frame starts when the bus is free, so a batch of
requests and replies is serialised as on the wire. Arbitration priority is not modelled (first ready, first sent).
A drive executes a request when it arrives; the model delays the replies (by the request's and their own bus time).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Final

#: Default reply latency of an emulated drive, s (the RS485 document says replies come "within 0.5 ms").
DEFAULT_LATENCY_S: Final = 0.0002
#: Bits of a classic frame outside the stuffed region: CRC delimiter 1, ACK slot 1, ACK delimiter 1, EOF 7, IFS 3.
_CAN_UNSTUFFED_TAIL_BITS: Final = 13
_CAN_CRC15_POLY: Final = 0x4599
_CAN_STUFF_RUN: Final = 5
#: Bits on the wire per RS485 byte (8N1: start + 8 data + stop).
RS485_BITS_PER_BYTE: Final = 10


@dataclass(frozen=True, slots=True)
class TimingModel:
    """How long a drive takes to answer.

    Attributes:
        latency_s: time from the end of a request to the start of the reply, s.
        bus_time: also model the time frames occupy the bus (CAN bits at the bit rate, RS485 bytes at the baud
            rate), serialising the frames of a batch as on the wire.

    Raises:
        ValueError: a negative or non-finite latency.
    """

    latency_s: float = DEFAULT_LATENCY_S
    bus_time: bool = False

    def __post_init__(self) -> None:
        if not (math.isfinite(self.latency_s) and self.latency_s >= 0):
            raise ValueError(f"latency must be a time >= 0 s, got {self.latency_s!r}")


def _crc15(bits: list[int]) -> int:
    crc = 0
    for bit in bits:
        feedback = bit ^ ((crc >> 14) & 1)
        crc = (crc << 1) & 0x7FFF
        if feedback:
            crc ^= _CAN_CRC15_POLY
    return crc


def _msb_bits(value: int, width: int) -> list[int]:
    return [(value >> (width - 1 - i)) & 1 for i in range(width)]


def can_frame_bits(arbitration_id: int, data: bytes) -> int:
    """Bits a classic CAN data frame with an 11-bit identifier occupies on the bus, stuff bits included.

    Args:
        arbitration_id: the 11-bit identifier.
        data: 0..8 data bytes.
    """
    bits = [0, *_msb_bits(arbitration_id & 0x7FF, 11), 0, 0, 0, *_msb_bits(len(data), 4)]
    for byte in data:
        bits += _msb_bits(byte, 8)
    bits += _msb_bits(_crc15(bits), 15)
    stuffed, run, previous = 0, 0, -1
    for bit in bits:
        run = run + 1 if bit == previous else 1
        previous = bit
        if run == _CAN_STUFF_RUN:
            # The inserted complementary bit starts the next run.
            stuffed += 1
            previous, run = 1 - bit, 1
    return len(bits) + stuffed + _CAN_UNSTUFFED_TAIL_BITS


def can_frame_time_s(arbitration_id: int, data: bytes, bitrate: int) -> float:
    """Time a classic CAN frame occupies the bus at ``bitrate`` bit/s, s."""
    return can_frame_bits(arbitration_id, data) / bitrate


def rs485_frame_time_s(n_bytes: int, baud: int) -> float:
    """Time ``n_bytes`` take on an RS485 line at ``baud`` bit/s (8N1), s."""
    return n_bytes * RS485_BITS_PER_BYTE / baud


class BusClock:
    """Serialises frames on one medium: a frame starts when both it is ready and the bus is free."""

    def __init__(self) -> None:
        self.busy_until_s = -math.inf

    def occupy(self, ready_s: float, duration_s: float) -> float:
        """Reserve the bus for a frame ready at ``ready_s`` lasting ``duration_s``; return when it ends, s."""
        self.busy_until_s = max(ready_s, self.busy_until_s) + duration_s
        return self.busy_until_s
