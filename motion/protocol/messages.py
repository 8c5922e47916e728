"""Typed RMD protocol messages: frozen, slotted dataclasses in physical units.

A message is transport-neutral: ``MultiTurnPositionSpeed(angle_deg=90.0, max_speed_dps=180.0)`` is the same
object whether it goes out on CAN (int32 angle, uint16 1 dps speed) or RS485 (int64 angle, uint32 0.01 dps
speed). The wire layout, scale and range of every field per transport live in :mod:`motion.protocol.table`;
:func:`motion.protocol.table.raw_values` gives the raw integers a message has on a given transport.

Angles are motor-shaft degrees (the drive's own reading, before any gear reduction), speeds motor-shaft deg/s.
Classes whose ``command`` is a field serve several commands with the same shape (``MotorState`` answers
0x9C and 0xA1..0xA8); the others serve exactly one command and carry it as a class variable.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import IntEnum, IntFlag
from typing import ClassVar


class Command(IntEnum):
    """Command bytes of both protocol documents (DATA[0] on CAN, the command byte on RS485)."""

    READ_PID = 0x30  #: read the PI gains of the three loops
    WRITE_PID_RAM = 0x31  #: write PI gains to RAM (lost at power-off)
    WRITE_PID_ROM = 0x32  #: write PI gains to ROM (flash wear; kept at power-off)
    READ_ACCELERATION = 0x33  #: read the acceleration limit, dps/s
    WRITE_ACCELERATION_RAM = 0x34  #: write the acceleration limit to RAM
    READ_ENCODER = 0x90  #: read encoder position, raw position and offset
    WRITE_ENCODER_OFFSET = 0x91  #: write the encoder offset (zero point) to ROM
    WRITE_ZERO_ROM = 0x19  #: write the current position to ROM as zero (needs a power cycle)
    READ_MULTI_TURN_ANGLE = 0x92  #: read the multi-turn angle
    READ_SINGLE_TURN_ANGLE = 0x94  #: read the single-turn angle
    SET_ZERO_RAM = 0x95  #: current position as zero until power-off (CAN only, "not available yet")
    READ_STATUS_1 = 0x9A  #: temperature, voltage, error flags
    CLEAR_ERRORS = 0x9B  #: clear error flags (only once the cause is gone); replies like 0x9A
    READ_STATUS_2 = 0x9C  #: temperature, torque current, speed, encoder
    READ_STATUS_3 = 0x9D  #: phase currents
    MOTOR_OFF = 0x80  #: motor off, clears the running state and the last command
    MOTOR_STOP = 0x81  #: motor stop, keeps the running state and the last command
    MOTOR_RUN = 0x88  #: resume the command that was running before 0x81
    OPEN_LOOP = 0xA0  #: open-loop output power (RMD-S)
    TORQUE = 0xA1  #: torque (iq) closed loop
    SPEED = 0xA2  #: speed closed loop
    MULTI_TURN_POSITION = 0xA3  #: multi-turn position with the drive's max speed
    MULTI_TURN_POSITION_SPEED = 0xA4  #: multi-turn position with a max speed
    SINGLE_TURN_POSITION = 0xA5  #: single-turn position with a spin direction
    SINGLE_TURN_POSITION_SPEED = 0xA6  #: single-turn position with a spin direction and a max speed
    INCREMENTAL_POSITION = 0xA7  #: incremental position
    INCREMENTAL_POSITION_SPEED = 0xA8  #: incremental position with a max speed
    READ_MODEL = 0x12  #: driver and motor model, hardware and firmware version (RS485 only)


class SpinDirection(IntEnum):
    """Spin direction of the single-turn position commands 0xA5 / 0xA6."""

    CLOCKWISE = 0x00  #: clockwise
    COUNTERCLOCKWISE = 0x01  #: counterclockwise


class ErrorFlags(IntFlag):
    """Error state byte of 0x9A / 0x9B. Bits the documents mark invalid are kept as read."""

    NONE = 0  #: no error
    LOW_VOLTAGE = 0x01  #: bit 0: low-voltage protection
    OVER_TEMPERATURE = 0x08  #: bit 3: over-temperature protection


@dataclass(frozen=True, slots=True)
class Message:
    """Base class of every protocol message."""


# --- shapes shared by several commands ----------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class Bare(Message):
    """A command without data, and the echo replies of such commands (0x80, 0x81, 0x88, reads...)."""

    command: Command


@dataclass(frozen=True, slots=True)
class PidGains(Message):
    """PI gains of the position, speed and torque loops (0x30 reply, 0x31 / 0x32 request and reply)."""

    command: Command
    angle_kp: int
    angle_ki: int
    speed_kp: int
    speed_ki: int
    iq_kp: int
    iq_ki: int


@dataclass(frozen=True, slots=True)
class Acceleration(Message):
    """Acceleration limit in dps/s (0x33 reply, 0x34 request and reply)."""

    command: Command
    acceleration_dps2: int


@dataclass(frozen=True, slots=True)
class EncoderOffset(Message):
    """Encoder offset in encoder counts (0x91 request and reply, 0x19 reply on CAN)."""

    command: Command
    encoder_offset: int


@dataclass(frozen=True, slots=True)
class Status1(Message):
    """Temperature, supply voltage and error flags (0x9A and 0x9B replies)."""

    command: Command
    temperature_c: int
    voltage_v: float
    errors: ErrorFlags


@dataclass(frozen=True, slots=True)
class MotorState(Message):
    """Temperature, torque current, speed and encoder (0x9C and 0xA1..0xA8 replies).

    ``iq_a`` is the torque current (RMD-L / RMD-X / MG). RMD-S drives put their output power (-1000..1000)
    in the same bytes; read it with :func:`motion.protocol.table.raw_values`.
    """

    command: Command
    temperature_c: int
    iq_a: float
    speed_dps: int
    encoder: int


# --- shapes of one command each ---------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class EncoderReading(Message):
    """Encoder position (raw minus offset), raw position and offset, in counts (0x90 reply)."""

    command: ClassVar[Command] = Command.READ_ENCODER
    encoder: int
    encoder_raw: int
    encoder_offset: int


@dataclass(frozen=True, slots=True)
class MultiTurnAngle(Message):
    """Multi-turn motor angle in degrees, positive clockwise (0x92 reply)."""

    command: ClassVar[Command] = Command.READ_MULTI_TURN_ANGLE
    angle_deg: float


@dataclass(frozen=True, slots=True)
class SingleTurnAngle(Message):
    """Single-turn motor angle 0..359.99 degrees from the encoder zero (0x94 reply)."""

    command: ClassVar[Command] = Command.READ_SINGLE_TURN_ANGLE
    angle_deg: float


@dataclass(frozen=True, slots=True)
class PhaseCurrents(Message):
    """Phase currents in amperes (0x9D reply); the temperature is carried on RS485 only (None on CAN)."""

    command: ClassVar[Command] = Command.READ_STATUS_3
    ia_a: float
    ib_a: float
    ic_a: float
    temperature_c: int | None = None


@dataclass(frozen=True, slots=True)
class OpenLoopState(Message):
    """Temperature, output power (-1000..1000), speed and encoder (0xA0 reply)."""

    command: ClassVar[Command] = Command.OPEN_LOOP
    temperature_c: int
    power: int
    speed_dps: int
    encoder: int


@dataclass(frozen=True, slots=True)
class ProductInfo(Message):
    """Driver and motor names, hardware and firmware versions (0x12 reply, RS485 only)."""

    command: ClassVar[Command] = Command.READ_MODEL
    driver_name: str
    motor_name: str
    hardware_version: float
    firmware_version: float


@dataclass(frozen=True, slots=True)
class OpenLoopControl(Message):
    """Open-loop output power -1000..1000 (0xA0, RMD-S)."""

    command: ClassVar[Command] = Command.OPEN_LOOP
    power: int


@dataclass(frozen=True, slots=True)
class TorqueControl(Message):
    """Torque current set-point in amperes, -32..32 A (0xA1)."""

    command: ClassVar[Command] = Command.TORQUE
    iq_a: float


@dataclass(frozen=True, slots=True)
class SpeedControl(Message):
    """Speed set-point in motor deg/s (0xA2)."""

    command: ClassVar[Command] = Command.SPEED
    speed_dps: float


@dataclass(frozen=True, slots=True)
class MultiTurnPosition(Message):
    """Multi-turn position set-point in motor degrees (0xA3)."""

    command: ClassVar[Command] = Command.MULTI_TURN_POSITION
    angle_deg: float


@dataclass(frozen=True, slots=True)
class MultiTurnPositionSpeed(Message):
    """Multi-turn position set-point with the drive's speed capped at ``max_speed_dps`` (0xA4)."""

    command: ClassVar[Command] = Command.MULTI_TURN_POSITION_SPEED
    angle_deg: float
    max_speed_dps: float


@dataclass(frozen=True, slots=True)
class SingleTurnPosition(Message):
    """Single-turn position set-point 0..359.99 degrees with a spin direction (0xA5)."""

    command: ClassVar[Command] = Command.SINGLE_TURN_POSITION
    direction: SpinDirection
    angle_deg: float


@dataclass(frozen=True, slots=True)
class SingleTurnPositionSpeed(Message):
    """Single-turn position set-point with a spin direction and a max speed (0xA6)."""

    command: ClassVar[Command] = Command.SINGLE_TURN_POSITION_SPEED
    direction: SpinDirection
    angle_deg: float
    max_speed_dps: float


@dataclass(frozen=True, slots=True)
class IncrementalPosition(Message):
    """Move by ``angle_deg`` motor degrees from the current position (0xA7)."""

    command: ClassVar[Command] = Command.INCREMENTAL_POSITION
    angle_deg: float


@dataclass(frozen=True, slots=True)
class IncrementalPositionSpeed(Message):
    """Move by ``angle_deg`` motor degrees with a max speed (0xA8)."""

    command: ClassVar[Command] = Command.INCREMENTAL_POSITION_SPEED
    angle_deg: float
    max_speed_dps: float


@dataclass(frozen=True, slots=True)
class MultiMotorTorque(Message):
    """Torque currents of motors 1..4 in one CAN frame on ID 0x280; each motor replies like 0xA1."""

    iq1_a: float
    iq2_a: float
    iq3_a: float
    iq4_a: float
