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
import random
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Final

#: Default reply latency of an emulated drive, s (the RS485 document says replies come "within 0.5 ms").
DEFAULT_LATENCY_S: Final = 0.0002
#: Bits of a classic frame outside the stuffed region: CRC delimiter 1, ACK slot 1, ACK delimiter 1, EOF 7, IFS 3.
_CAN_UNSTUFFED_TAIL_BITS: Final = 13
_CAN_CRC15_POLY: Final = 0x4599
_CAN_STUFF_RUN: Final = 5


@dataclass(frozen=True, slots=True)
class TimingModel:
    """How long a drive takes to answer.

    Attributes:
        latency_s: time from the end of a request to the start of the reply, s.
        bus_time: also model the time frames occupy the bus (CAN bits at the bit rate, RS485 bytes at the baud
            rate), serialising the frames of a batch as on the wire.
        jitter_s: each reply comes up to this much later again, drawn uniformly per reply, s.
        seed: the seed of the jitter's draws (the same seed, the same replies).

    Raises:
        ValueError: a negative or non-finite latency or jitter.
    """

    latency_s: float = DEFAULT_LATENCY_S
    bus_time: bool = False
    jitter_s: float = 0.0
    seed: int = 0
    _draw: Callable[[], float] = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        for name in ("latency_s", "jitter_s"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise ValueError(f"{name.removesuffix('_s')} must be a time >= 0 s, got {value!r}")
        object.__setattr__(self, "_draw", random.Random(self.seed).random)

    def reply_delay_s(self) -> float:
        """The time from a request's end to its reply's start, s: the latency, plus this reply's jitter."""
        if self.jitter_s:
            return self.latency_s + self.jitter_s * self._draw()
        return self.latency_s


def _crc15_table() -> tuple[int, ...]:
    """CRC-15/CAN of each byte value from a zero register, bit by bit (the byte-wise step below uses it)."""
    table = []
    for byte in range(256):
        crc = byte << 7
        for _ in range(8):
            crc = ((crc << 1) ^ _CAN_CRC15_POLY) if crc & 0x4000 else crc << 1
        table.append(crc & 0x7FFF)
    return tuple(table)


_CRC15_TABLE: Final = _crc15_table()
#: SOF, identifier, RTR, IDE, r0 and DLC: the bits before the data.
_CAN_HEADER_BITS: Final = 19


def _stuff_step(state: int, bit: int) -> tuple[int, int]:
    """One bit through the stuffing: ``state`` is ``last bit × 8 + run length`` (run 1..4); returns the next state
    and the stuff bits inserted after this bit (a fifth equal bit takes a complementary one, which starts the next
    run)."""
    last, run = divmod(state, 8)
    run = run + 1 if bit == last else 1
    if run == _CAN_STUFF_RUN:
        return (1 - bit) * 8 + 1, 1
    return bit * 8 + run, 0


def _stuff_table() -> tuple[tuple[int, ...], ...]:
    """Per stuffing state and byte value (most significant bit first): ``next state × 4 + stuff bits``."""
    table: list[tuple[int, ...]] = [(0,) * 256] * 16
    for state in [last * 8 + run for last in (0, 1) for run in range(1, _CAN_STUFF_RUN)]:
        row = []
        for byte in range(256):
            current, stuffed = state, 0
            for shift in range(7, -1, -1):
                current, more = _stuff_step(current, (byte >> shift) & 1)
                stuffed += more
            row.append(current * 4 + stuffed)
        table[state] = tuple(row)
    return tuple(table)


_STUFF_TABLE: Final = _stuff_table()


def can_frame_bits(arbitration_id: int, data: bytes) -> int:
    """Bits a classic CAN data frame with an 11-bit identifier occupies on the bus, stuff bits included.

    The frame from SOF to the end of the data is one integer; the CRC is computed a byte at a time from a table (with
    a zero register leading zero bits change nothing, so the 19 header bits are padded to 24), and the stuff bits a
    byte at a time through a table of the stuffing states (the emulated bus times every frame of every cycle).

    Args:
        arbitration_id: the 11-bit identifier.
        data: 0..8 data bytes.
    """
    n = len(data)
    # SOF, RTR, IDE and r0 are dominant (0): identifier at bits 4.., DLC in the low 4 bits of the header
    header = ((arbitration_id & 0x7FF) << 7) | n
    message = (header << (8 * n)) | int.from_bytes(data, "big")
    crc = 0
    for byte in message.to_bytes(3 + n, "big"):
        crc = ((crc << 8) & 0x7FFF) ^ _CRC15_TABLE[((crc >> 7) ^ byte) & 0xFF]
    width = _CAN_HEADER_BITS + 8 * n + 15
    frame = (message << 15) | crc
    # Stuffing, a byte at a time through a table of the stuffing states (last bit, run length): after five equal
    # bits a complementary bit is inserted, which starts the next run. SOF (0) opens the first run; the bits after
    # it that do not fill a byte go one by one.
    state, stuffed = 1, 0
    rest = width - 1
    for shift in range(rest - 1, rest - 1 - rest % 8, -1):
        state, more = _stuff_step(state, (frame >> shift) & 1)
        stuffed += more
    table = _STUFF_TABLE
    for byte in (frame & ((1 << (rest - rest % 8)) - 1)).to_bytes((rest - rest % 8) // 8, "big"):
        code = table[state][byte]
        state, stuffed = code >> 2, stuffed + (code & 3)
    return width + stuffed + _CAN_UNSTUFFED_TAIL_BITS


def can_frame_time_s(arbitration_id: int, data: bytes, bitrate: int) -> float:
    """Time a classic CAN frame occupies the bus at ``bitrate`` bit/s, s."""
    return can_frame_bits(arbitration_id, data) / bitrate


class BusClock:
    """Serialises frames on one medium: a frame starts when both it is ready and the bus is free."""

    def __init__(self) -> None:
        self.busy_until_s = -math.inf

    def occupy(self, ready_s: float, duration_s: float) -> float:
        """Reserve the bus for a frame ready at ``ready_s`` lasting ``duration_s``; return when it ends, s."""
        self.busy_until_s = max(ready_s, self.busy_until_s) + duration_s
        return self.busy_until_s
