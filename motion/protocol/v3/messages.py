"""Messages of the V3-driver family ("Servo Motor Control Protocol" V4.2, applicable driver V3).

The command bytes are those of the V4.2 document (:class:`CommandV3`); where a command has the same byte, shape and
meaning as in the older family, the older message class is used as it is (``TorqueControl``, ``SpeedControl``,
``MultiTurnPositionSpeed``, ``SingleTurnPositionSpeed``, ``IncrementalPositionSpeed``, ``EncoderReading``,
``MultiTurnAngle``, ``SingleTurnAngle``, ``PhaseCurrents``): their layouts on the wire are this family's own
(:mod:`motion.protocol.v3.table`). The classes here are the shapes the older family lacks. Angles and speeds are
those of the output shaft, as the V4.2 document defines them.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import IntEnum, IntFlag
from typing import ClassVar

from motion.protocol.messages import Message


class CommandV3(IntEnum):
    """Command bytes of the V4.2 document (DATA[0] on CAN and in the RS485 data field)."""

    FUNCTION_CONTROL = 0x20  #: function control by index (0x20)
    READ_PID = 0x30  #: read one PID parameter by index (float32)
    WRITE_PID_RAM = 0x31  #: write one PID parameter to RAM by index
    WRITE_PID_ROM = 0x32  #: write one PID parameter to ROM by index
    READ_ACCELERATION = 0x42  #: read one planning acceleration by index
    WRITE_ACCELERATION = 0x43  #: write one planning acceleration to RAM and ROM by index
    READ_MULTI_TURN_ENCODER = 0x60  #: multi-turn encoder position (zero offset subtracted)
    READ_MULTI_TURN_ENCODER_RAW = 0x61  #: multi-turn encoder original position
    READ_MULTI_TURN_ENCODER_OFFSET = 0x62  #: multi-turn encoder zero offset
    WRITE_ENCODER_ZERO = 0x63  #: write a multi-turn encoder value to ROM as the zero
    WRITE_CURRENT_AS_ZERO = 0x64  #: write the current multi-turn position to ROM as the zero (0x76 to apply)
    READ_RUN_MODE = 0x70  #: the operating mode (current, speed, position loop)
    RESET = 0x76  #: restart the drive's program (no reply)
    RELEASE_BRAKE = 0x77  #: release the holding brake
    LOCK_BRAKE = 0x78  #: lock the holding brake
    CAN_ID = 0x79  #: read or write the CAN / RS485 id (CAN: on arbitration id 0x300)
    MOTOR_OFF = 0x80  #: output off, running state cleared
    MOTOR_STOP = 0x81  #: stop, the closed loop stays
    READ_ENCODER = 0x90  #: single-turn encoder: position, original position, zero offset
    READ_MULTI_TURN_ANGLE = 0x92  #: multi-turn angle of the output shaft, 0.01 deg
    READ_SINGLE_TURN_ANGLE = 0x94  #: single-turn angle, 0.01 deg
    READ_STATUS_1 = 0x9A  #: temperature, brake, voltage, 16-bit error word
    READ_STATUS_2 = 0x9C  #: temperature, torque current, speed, angle (whole degrees)
    READ_STATUS_3 = 0x9D  #: temperature and phase currents
    TORQUE = 0xA1  #: torque current closed loop
    SPEED = 0xA2  #: speed closed loop
    MULTI_TURN_POSITION_SPEED = 0xA4  #: absolute position with a max speed
    SINGLE_TURN_POSITION_SPEED = 0xA6  #: single-turn position with a direction and a max speed
    INCREMENTAL_POSITION_SPEED = 0xA8  #: incremental position with a max speed
    READ_RUNTIME = 0xB1  #: time since start, ms
    READ_VERSION_DATE = 0xB2  #: firmware date, YYYYMMDD
    COMMUNICATION_TIMEOUT = 0xB3  #: communication-loss protection time, ms (0: off)
    BAUD_RATE = 0xB4  #: bus baud rate code (no usable reply)
    READ_MODEL = 0xB5  #: motor model, 7 ASCII characters
    ACTIVE_REPLY = 0xB6  #: periodic replies of a read command without requests (CAN only)


class ActiveReplyCommand(IntEnum):
    """The read commands 0xB6 can make a drive send by itself (the document also lists 0x9E, which it never
    defines: not accepted)."""

    READ_MULTI_TURN_ENCODER = 0x60  #: multi-turn encoder position
    READ_MULTI_TURN_ENCODER_RAW = 0x61  #: multi-turn encoder original position
    READ_MULTI_TURN_ENCODER_OFFSET = 0x62  #: multi-turn encoder zero offset
    READ_MULTI_TURN_ANGLE = 0x92  #: multi-turn angle
    READ_STATUS_1 = 0x9A  #: status 1 and error word
    READ_STATUS_2 = 0x9C  #: status 2
    READ_STATUS_3 = 0x9D  #: status 3


class PidIndex(IntEnum):
    """Parameter index of 0x30..0x32."""

    CURRENT_KP = 0x01  #: current loop KP
    CURRENT_KI = 0x02  #: current loop KI
    SPEED_KP = 0x04  #: speed loop KP
    SPEED_KI = 0x05  #: speed loop KI
    POSITION_KP = 0x07  #: position loop KP
    POSITION_KI = 0x08  #: position loop KI
    POSITION_KD = 0x09  #: position loop KD


class AccelerationIndex(IntEnum):
    """Function index of 0x42 / 0x43."""

    POSITION_ACCELERATION = 0x00  #: position planning: initial to maximum speed
    POSITION_DECELERATION = 0x01  #: position planning: maximum speed to standstill
    SPEED_ACCELERATION = 0x02  #: speed planning: toward the target speed, both directions
    SPEED_DECELERATION = 0x03  #: speed planning: down to the target speed in the same direction


class FunctionIndex(IntEnum):
    """Function index of 0x20."""

    CLEAR_MULTI_TURN = 0x01  #: clear the multi-turn value, new zero (after a restart)
    CAN_ID_FILTER = 0x02  #: 1: CAN id filter on (0x280 / 0x300 then unusable); saved
    ERROR_BROADCAST = 0x03  #: 1: send 0x9A every 100 ms while an error lasts
    SAVE_MULTI_TURN = 0x04  #: 1: keep the multi-turn value over power-off (0: single-turn mode); after a restart
    SET_CAN_ID = 0x05  #: the new CAN id (ROM, after a restart)
    MAX_POSITIVE_ANGLE = 0x06  #: largest angle of the position modes (ROM, at once)
    MAX_NEGATIVE_ANGLE = 0x07  #: most negative angle of the position modes (ROM, at once)


class RunMode(IntEnum):
    """Operating mode of 0x70."""

    CURRENT_LOOP = 0x01  #: current (torque) loop
    SPEED_LOOP = 0x02  #: speed loop
    POSITION_LOOP = 0x03  #: position loop


class BrakeCommand(IntEnum):
    """The brake control command 0x9A reports (DATA[3])."""

    LOCK = 0  #: the last brake command was lock
    RELEASE = 1  #: the last brake command was release


class ReadWrite(IntEnum):
    """Read / write flag of 0x79."""

    WRITE = 0  #: write the id
    READ = 1  #: read the id


class SystemErrorFlags(IntFlag):
    """The 16-bit error word of 0x9A (``System_errorState``). Bits the document does not name are kept as read."""

    NONE = 0  #: no error
    STALL = 0x0002  #: motor stall (level 1)
    LOW_VOLTAGE = 0x0004  #: under-voltage (level 2)
    OVER_VOLTAGE = 0x0008  #: over-voltage (level 2)
    OVER_CURRENT = 0x0010  #: phase current over-current (level 1)
    POWER_OVERRUN = 0x0040  #: supply current over its limit (level 2)
    CALIBRATION_WRITE = 0x0080  #: calibration parameter write / read error (level 1)
    OVER_SPEED = 0x0100  #: speeding (level 2)
    OVER_TEMPERATURE = 0x1000  #: motor over-temperature (level 2)
    ENCODER_CALIBRATION = 0x2000  #: encoder calibration error (level 2)


@dataclass(frozen=True, slots=True)
class BareV3(Message):
    """A command without data, and the echo replies of such commands (0x77, 0x78, 0x80, 0x81, the reads)."""

    command: CommandV3


@dataclass(frozen=True, slots=True)
class PidRead(Message):
    """0x30 request: which parameter to read."""

    command: ClassVar[CommandV3] = CommandV3.READ_PID
    index: PidIndex


@dataclass(frozen=True, slots=True)
class PidParameter(Message):
    """One PID parameter (0x30 reply, 0x31 / 0x32 request and echo): a float32."""

    command: CommandV3
    index: PidIndex
    value: float


@dataclass(frozen=True, slots=True)
class AccelerationRead(Message):
    """0x42 request: which planning acceleration to read."""

    command: ClassVar[CommandV3] = CommandV3.READ_ACCELERATION
    index: AccelerationIndex


@dataclass(frozen=True, slots=True)
class PlanningAcceleration(Message):
    """One planning acceleration, deg/s² of the output shaft (0x42 reply, 0x43 request and echo)."""

    command: CommandV3
    index: AccelerationIndex
    acceleration_dps2: int


@dataclass(frozen=True, slots=True)
class MultiTurnEncoder(Message):
    """A multi-turn encoder value, counts (0x60 / 0x61 / 0x62 / 0x64 replies, 0x63 request and echo)."""

    command: CommandV3
    encoder: int


@dataclass(frozen=True, slots=True)
class Status1V3(Message):
    """0x9A reply: temperature, the last brake command, supply voltage and the error word."""

    command: ClassVar[CommandV3] = CommandV3.READ_STATUS_1
    temperature_c: int
    brake: BrakeCommand
    voltage_v: float
    errors: SystemErrorFlags


@dataclass(frozen=True, slots=True)
class MotorStateV3(Message):
    """0x9C and 0xA1 / 0xA2 / 0xA4 / 0xA8 replies: temperature, torque current, speed and the output angle in
    whole degrees (int16: ±32767 deg; the precise angle comes from 0x92 or 0x60)."""

    command: CommandV3
    temperature_c: int
    iq_a: float
    speed_dps: int
    angle_deg: int


@dataclass(frozen=True, slots=True)
class SingleTurnStateV3(Message):
    """0xA6 reply: temperature, torque current, speed and the single-turn encoder position."""

    command: ClassVar[CommandV3] = CommandV3.SINGLE_TURN_POSITION_SPEED
    temperature_c: int
    iq_a: float
    speed_dps: int
    encoder: int


@dataclass(frozen=True, slots=True)
class RunModeReply(Message):
    """0x70 reply."""

    command: ClassVar[CommandV3] = CommandV3.READ_RUN_MODE
    mode: RunMode


@dataclass(frozen=True, slots=True)
class Runtime(Message):
    """0xB1 reply: time since the drive started or was reset."""

    command: ClassVar[CommandV3] = CommandV3.READ_RUNTIME
    runtime_ms: int


@dataclass(frozen=True, slots=True)
class VersionDate(Message):
    """0xB2 reply: the firmware's date as the integer YYYYMMDD (20220206 = 6 February 2022)."""

    command: ClassVar[CommandV3] = CommandV3.READ_VERSION_DATE
    date: int


@dataclass(frozen=True, slots=True)
class CommunicationTimeout(Message):
    """0xB3 request and echo: the communication-loss protection time (0: off). Longer without a frame, the drive
    cuts its output and locks the brake; it is kept in ROM."""

    command: ClassVar[CommandV3] = CommandV3.COMMUNICATION_TIMEOUT
    timeout_ms: int


@dataclass(frozen=True, slots=True)
class BaudRate(Message):
    """0xB4 request: the bus baud rate code (RS485 0..4: 115200, 500 k, 1 M, 1.5 M, 2.5 M; CAN 0..1: 500 k, 1 M).
    Kept in ROM; the reply comes at the new rate and is not used."""

    command: ClassVar[CommandV3] = CommandV3.BAUD_RATE
    code: int


@dataclass(frozen=True, slots=True)
class MotorModel(Message):
    """0xB5 reply: the motor model, 7 ASCII characters (``X8S2V10`` for an RMD-X8 S2 V10)."""

    command: ClassVar[CommandV3] = CommandV3.READ_MODEL
    model: str


@dataclass(frozen=True, slots=True)
class ActiveReply(Message):
    """0xB6 request (CAN only; no reply): the drive sends the replies of ``reply_command`` every ``interval_ms``
    without requests (several commands take turns), and stops answering requests for it."""

    command: ClassVar[CommandV3] = CommandV3.ACTIVE_REPLY
    reply_command: ActiveReplyCommand
    enabled: int
    interval_ms: float


@dataclass(frozen=True, slots=True)
class FunctionControl(Message):
    """0x20 request and echo: one function by index and its value."""

    command: ClassVar[CommandV3] = CommandV3.FUNCTION_CONTROL
    index: FunctionIndex
    value: int


@dataclass(frozen=True, slots=True)
class CanIdCommand(Message):
    """0x79 request (CAN: arbitration id 0x300, every drive listens): read the id, or write ``can_id``."""

    command: ClassVar[CommandV3] = CommandV3.CAN_ID
    access: ReadWrite
    can_id: int


@dataclass(frozen=True, slots=True)
class CanIdReply(Message):
    """0x79 reply: DATA[6..7] as a little-endian uint16. A read answers the drive's reply id on CAN (``value`` is
    0x240 + id) and the id itself in DATA[7] on RS485 (section 7.4: ``value`` is ``id << 8``); a write echoes the
    request, whose id sits in DATA[7] (``value`` is ``id << 8`` too)."""

    command: ClassVar[CommandV3] = CommandV3.CAN_ID
    access: ReadWrite
    value: int


@dataclass(frozen=True, slots=True)
class MotionRanges:
    """The ranges the motion frame (0x400 / 0x500) maps its 16- and 12-bit fields onto, (lowest, highest) each:
    they differ by firmware (V4.4 widened position, kd and torque) and, from V4.4 on, by motor model (the torque
    range is the model's peak torque). :func:`motion.protocol.v3.motion_frame.motion_ranges` chooses them from the
    drive's firmware date (0xB2) and model (0xB5).

    Attributes:
        position_rad: the position range, rad.
        velocity_rad_s: the speed range, rad/s.
        kp: the stiffness range.
        kd: the damping range.
        torque_nm: the feed-forward (request) and feedback (reply) torque range, N·m.
        source: which document and model the ranges come from (for messages).
    """

    position_rad: tuple[float, float]
    velocity_rad_s: tuple[float, float]
    kp: tuple[float, float]
    kd: tuple[float, float]
    torque_nm: tuple[float, float]
    source: str


@dataclass(frozen=True, slots=True)
class MotionCommand(Message):
    """The MIT-style motion frame (CAN arbitration id 0x400 + id): the drive's own PD,
    ``iq = (kp (p_des - p) + kd (v_des - v) + t_ff) / kt``. Quantised to 16 bits (position) and 12 bits onto
    ``ranges``, which depend on the drive (its firmware and model): a command without them is not encoded."""

    position_rad: float
    velocity_rad_s: float
    kp: float
    kd: float
    torque_nm: float
    ranges: MotionRanges | None = None


@dataclass(frozen=True, slots=True)
class MotionState(Message):
    """The reply to :class:`MotionCommand` (CAN arbitration id 0x500 + id): position, speed and torque, decoded
    onto ``ranges`` (the drive's)."""

    motor_id: int
    position_rad: float
    velocity_rad_s: float
    torque_nm: float
    ranges: MotionRanges | None = None
