"""The V3 drives' motion frame (MIT-style impedance control: request on CAN id 0x400 + id, reply on 0x500 + id): its
bit packing, and the ranges its fields map onto, which depend on the drive.

The V4.2 document gives one set of ranges (position ±12.5 rad, speed ±45 rad/s, kp 0..500, kd 0..5, torque ±24 N·m).
Drives whose firmware is dated 2026042402 or later (0xB2) use the later protocol's wider ones (V4.4: position
±12.566 rad, kd 0..50, feed-forward and feedback torque ± the motor model's peak torque; kp and speed unchanged), so
the same bits mean a torque 2.5 times larger on an X6. :func:`motion_ranges` chooses them from the firmware date and
the model (0xB5) and refuses where they are unknown; a :class:`~motion.protocol.v3.messages.MotionCommand` without
ranges is not encoded. Decisions and sources: ``docs/protocol.md`` ("V3 motion frame ranges").
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Final

from motion.errors import DecodeError, EncodeError
from motion.protocol.table import CAN_PAYLOAD_BYTES, MOTOR_ID_MAX, MOTOR_ID_MIN, check_motor_id
from motion.protocol.v3.messages import MotionCommand, MotionRanges, MotionState

#: The V4.2 document's ranges (every drive with firmware dated before :data:`V44_FIRST_FIRMWARE`).
V42_RANGES: Final = MotionRanges(
    position_rad=(-12.5, 12.5),
    velocity_rad_s=(-45.0, 45.0),
    kp=(0.0, 500.0),
    kd=(0.0, 5.0),
    torque_nm=(-24.0, 24.0),
    source="V4.2",
)
#: The first firmware date (0xB2, YYYYMMDDNN as the drives report it) with the V4.4 motion frame.
V44_FIRST_FIRMWARE: Final = 2026042402
#: V4.4: the torque range of each motor series, its peak torque, N·m (the series the later protocol names).
V44_PEAK_TORQUE_NM: Final[Mapping[str, float]] = {"X6": 60.0, "X8": 129.0}
#: V4.4's position range: ±4π rad.
V44_POSITION_RAD: Final = 4.0 * math.pi
#: V4.4's damping range.
V44_KD_MAX: Final = 50.0
#: Bits per field: position 16, the others 12.
BITS: Final = {"position_rad": 16, "velocity_rad_s": 12, "kp": 12, "kd": 12, "torque_nm": 12}


def motion_ranges(firmware_date: int | None, model: str | None) -> MotionRanges:
    """The motion frame's ranges of a drive with this firmware date (0xB2) and model (0xB5).

    Raises:
        EncodeError: the firmware date is unknown, or the firmware is V4.4 and the model's peak torque is not known
            (the torque range would be a guess: a torque off by a factor).
    """
    if firmware_date is None:
        raise EncodeError("firmware_date", "the drive's firmware date (0xB2)", None, "V3 motion frame ranges")
    if not _is_v44(firmware_date):
        return V42_RANGES
    series = _series(model or "")
    if series not in V44_PEAK_TORQUE_NM:
        raise EncodeError(
            "model",
            f"a motor series whose V4.4 torque range is known ({', '.join(V44_PEAK_TORQUE_NM)})",
            model,
            f"V3 motion frame ranges of firmware {firmware_date} (V4.4: torque ± the model's peak torque)",
        )
    peak = V44_PEAK_TORQUE_NM[series]
    return MotionRanges(
        position_rad=(-V44_POSITION_RAD, V44_POSITION_RAD),
        velocity_rad_s=V42_RANGES.velocity_rad_s,
        kp=V42_RANGES.kp,
        kd=(0.0, V44_KD_MAX),
        torque_nm=(-peak, peak),
        source=f"V4.4 {series} ({peak:g} N·m)",
    )


def _series(model: str) -> str:
    """A model's series: its leading letters and the digits after them (``X8S2V10`` -> ``X8``)."""
    letters = len(model) - len(model.lstrip("ABCDEFGHIJKLMNOPQRSTUVWXYZ"))
    digits = len(model[letters:]) - len(model[letters:].lstrip("0123456789"))
    return model[: letters + digits] if letters and digits else ""


def _is_v44(firmware_date: int) -> bool:
    """Whether firmware of this date has V4.4's motion frame. The drives report YYYYMMDD (the V4.2 document's
    example: 20220206) or, as the later protocol names the first V4.4 firmware, YYYYMMDDNN with a build number: a
    plain date of the day itself cannot tell build 01 from 02.

    Raises:
        EncodeError: a date in neither form, or the first V4.4 day without its build number.
    """
    first_day = V44_FIRST_FIRMWARE // 100
    if 10_000_000 <= firmware_date < 100_000_000:  # YYYYMMDD
        if firmware_date == first_day:
            raise EncodeError(
                "firmware_date",
                f"a date other than {first_day} (that day's builds differ: 01 has V4.2's motion frame, 02 V4.4's)",
                firmware_date,
                "V3 motion frame ranges",
            )
        return firmware_date > first_day
    if 1_000_000_000 <= firmware_date < 10_000_000_000:  # YYYYMMDDNN
        return firmware_date >= V44_FIRST_FIRMWARE
    raise EncodeError("firmware_date", "YYYYMMDD or YYYYMMDDNN (0xB2)", firmware_date, "V3 motion frame ranges")


def _range(ranges: MotionRanges, name: str) -> tuple[float, float]:
    lo, hi = getattr(ranges, name)
    return float(lo), float(hi)


def _quantise(ranges: MotionRanges, name: str, value: object) -> int:
    lo, hi = _range(ranges, name)
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not lo <= value <= hi:
        raise EncodeError(name, f"{lo:g}..{hi:g} ({ranges.source})", value)
    return round((value - lo) / (hi - lo) * ((1 << BITS[name]) - 1))


def _physical(ranges: MotionRanges, name: str, raw: int) -> float:
    lo, hi = _range(ranges, name)
    return raw * (hi - lo) / ((1 << BITS[name]) - 1) + lo


def _ranges_of(message: MotionCommand | MotionState) -> MotionRanges:
    if message.ranges is None:
        raise EncodeError(
            "ranges",
            "the drive's motion-frame ranges (motion_ranges(firmware date 0xB2, model 0xB5): they differ by firmware "
            "and model)",
            None,
        )
    return message.ranges


def encode_motion(command: MotionCommand) -> bytes:
    """The 8 bytes of a motion frame: position 16 bits, then speed, kp, kd and torque 12 bits each, big-endian bit
    order as the document packs them, on the command's ranges.

    Raises:
        EncodeError: no ranges, or a value outside its range.
    """
    ranges = _ranges_of(command)
    p, v, kp, kd, t = (_quantise(ranges, name, getattr(command, name)) for name in BITS)
    word = (p << 48) | (v << 36) | (kp << 24) | (kd << 12) | t
    return word.to_bytes(8, "big")


def decode_motion(data: bytes, ranges: MotionRanges = V42_RANGES) -> MotionCommand:
    """A motion frame's request on ``ranges`` (the receiving drive's; every bit pattern is a valid command).

    Raises:
        DecodeError: not 8 bytes.
    """
    if len(data) != CAN_PAYLOAD_BYTES:
        raise DecodeError(f"a motion frame is {CAN_PAYLOAD_BYTES} bytes, got {len(data)}", bytes(data))
    word = int.from_bytes(data, "big")
    raws = (word >> 48, (word >> 36) & 0xFFF, (word >> 24) & 0xFFF, (word >> 12) & 0xFFF, word & 0xFFF)
    p, v, kp, kd, t = (_physical(ranges, name, raw) for name, raw in zip(BITS, raws, strict=True))
    return MotionCommand(p, v, kp, kd, t, ranges=ranges)


def encode_motion_state(state: MotionState) -> bytes:
    """The 8 bytes of a motion frame's reply: the drive's id, position 16 bits, speed and torque 12 bits, 2 zeros.

    Raises:
        EncodeError: an id outside 1..32, no ranges, or a value outside its range.
    """
    check_motor_id(state.motor_id)
    ranges = _ranges_of(state)
    p = _quantise(ranges, "position_rad", state.position_rad)
    v = _quantise(ranges, "velocity_rad_s", state.velocity_rad_s)
    t = _quantise(ranges, "torque_nm", state.torque_nm)
    return bytes((state.motor_id,)) + ((p << 24) | (v << 12) | t).to_bytes(5, "big") + bytes(2)


def decode_motion_state(data: bytes, ranges: MotionRanges = V42_RANGES) -> MotionState:
    """A motion frame's reply on ``ranges`` (the sending drive's; DATA[6..7] are reserved and ignored, as for every
    reply). The default is V4.2's, which the generic decoders (``decode_can_reply``) assume: the reply's ``ranges``
    say which were used, and a V4.4 drive's reply is decoded right only with its own.

    Raises:
        DecodeError: not 8 bytes, or an id outside 1..32.
    """
    data = bytes(data)
    if len(data) != CAN_PAYLOAD_BYTES:
        raise DecodeError(f"a motion reply is {CAN_PAYLOAD_BYTES} bytes, got {len(data)}", data)
    if not MOTOR_ID_MIN <= data[0] <= MOTOR_ID_MAX:
        raise DecodeError(f"motor id {data[0]} is outside {MOTOR_ID_MIN}..{MOTOR_ID_MAX}", data)
    word = int.from_bytes(data[1:6], "big")
    return MotionState(
        data[0],
        _physical(ranges, "position_rad", word >> 24),
        _physical(ranges, "velocity_rad_s", (word >> 12) & 0xFFF),
        _physical(ranges, "torque_nm", word & 0xFFF),
        ranges=ranges,
    )
