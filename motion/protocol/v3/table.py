"""The V3 family's command table: ONE declaration per command of the V4.2 document.

The same design as :mod:`motion.protocol.table` (its :class:`~motion.protocol.table.Field`,
:class:`~motion.protocol.table.Layout` and :class:`~motion.protocol.table.CommandSpec`): each command's request and
reply layout, with byte offsets from DATA[0] (the command byte), widths, signedness, exact scales and valid ranges.
A V3 RS485 frame carries exactly the 8 bytes of the CAN frame (``3E id 08 DATA[0..7] crc16``), so one layout serves
both transports; the table's layouts are filed under :attr:`WireProtocol.CAN` and :data:`RS485_COMMANDS` says which
commands RS485 has. Errata of the document and the decisions taken are in ``docs/protocol.md``.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, Final

from motion.protocol.messages import (
    EncoderReading,
    IncrementalPositionSpeed,
    MultiTurnAngle,
    MultiTurnPositionSpeed,
    PhaseCurrents,
    SingleTurnAngle,
    SingleTurnPositionSpeed,
    SpeedControl,
    SpinDirection,
    TorqueControl,
)
from motion.protocol.table import (
    COMMAND_TABLES,
    CommandSpec,
    Field,
    Kind,
    Layout,
    WireProtocol,
    _i8,
    _i16,
    _i32,
    _u8,
    _u16,
    _u32,
)
from motion.protocol.v3.messages import (
    AccelerationIndex,
    AccelerationRead,
    ActiveReply,
    ActiveReplyCommand,
    BareV3,
    BaudRate,
    BrakeCommand,
    CanIdCommand,
    CanIdReply,
    CommandV3,
    CommunicationTimeout,
    FunctionControl,
    FunctionIndex,
    MotorModel,
    MotorStateV3,
    MultiTurnEncoder,
    PidIndex,
    PidParameter,
    PidRead,
    PlanningAcceleration,
    ReadWrite,
    RunMode,
    RunModeReply,
    Runtime,
    SingleTurnStateV3,
    Status1V3,
    SystemErrorFlags,
    VersionDate,
)

_DEG: dict[str, Any] = dict(kind=Kind.REAL, num=1, den=100, unit="deg")
_CDPS: dict[str, Any] = dict(kind=Kind.REAL, num=1, den=100, unit="dps")
_DPS: dict[str, Any] = dict(kind=Kind.REAL, num=1, den=1, unit="dps")
_AMPS: dict[str, Any] = dict(kind=Kind.REAL, num=1, den=100, unit="A")
_SINGLE: dict[str, Any] = dict(_DEG, lo=0, hi=35999)
_TEMPERATURE: dict[str, Any] = dict(unit="degC")
#: Planning acceleration: 100..60000 deg/s² per the document, and 0 (the position loop then tracks the target
#: directly, 0xA4's text): see docs/protocol.md.
_ACCELERATION: dict[str, Any] = dict(unit="dps/s", lo=0, hi=60000)


def _can(layout: Layout) -> dict[WireProtocol, Layout]:
    return {WireProtocol.CAN: layout}


def _bare(echo: bool = False) -> dict[WireProtocol, Layout]:
    return _can(Layout(BareV3, echo=echo))


def _state() -> dict[WireProtocol, Layout]:
    """temperature int8, iq int16 0.01 A, speed int16 1 dps, angle int16 1 deg: the motion commands' reply."""
    return _can(
        Layout(
            MotorStateV3,
            (
                _i8("temperature_c", 1, **_TEMPERATURE),
                _i16("iq_a", 2, **_AMPS),
                _i16("speed_dps", 4, unit="dps"),
                _i16("angle_deg", 6, unit="deg"),
            ),
        )
    )


def _pid(echo: bool) -> dict[WireProtocol, Layout]:
    return _can(
        Layout(
            PidParameter,
            (_u8("index", 1, kind=Kind.ENUM, enum=PidIndex), Field("value", 4, 4, False, kind=Kind.FLOAT32)),
            echo=echo,
        )
    )


def _acceleration(echo: bool) -> dict[WireProtocol, Layout]:
    return _can(
        Layout(
            PlanningAcceleration,
            (
                _u8("index", 1, kind=Kind.ENUM, enum=AccelerationIndex),
                _u32("acceleration_dps2", 4, **_ACCELERATION),
            ),
            echo=echo,
        )
    )


def _encoder(echo: bool = False) -> dict[WireProtocol, Layout]:
    return _can(Layout(MultiTurnEncoder, (_i32("encoder", 4, unit="counts"),), echo=echo))


_SPECS: tuple[CommandSpec, ...] = (
    CommandSpec(
        CommandV3.FUNCTION_CONTROL,
        "Function control",
        _can(Layout(FunctionControl, (_u8("index", 1, kind=Kind.ENUM, enum=FunctionIndex), _i32("value", 4)))),
        _can(
            Layout(FunctionControl, (_u8("index", 1, kind=Kind.ENUM, enum=FunctionIndex), _i32("value", 4)), echo=True)
        ),
    ),
    CommandSpec(
        CommandV3.READ_PID,
        "Read PID parameter",
        _can(Layout(PidRead, (_u8("index", 1, kind=Kind.ENUM, enum=PidIndex),))),
        _pid(False),
    ),
    CommandSpec(CommandV3.WRITE_PID_RAM, "Write PID parameter to RAM", _pid(False), _pid(True)),
    CommandSpec(CommandV3.WRITE_PID_ROM, "Write PID parameter to ROM", _pid(False), _pid(True)),
    CommandSpec(
        CommandV3.READ_ACCELERATION,
        "Read acceleration",
        _can(Layout(AccelerationRead, (_u8("index", 1, kind=Kind.ENUM, enum=AccelerationIndex),))),
        _acceleration(False),
    ),
    CommandSpec(
        CommandV3.WRITE_ACCELERATION, "Write acceleration to RAM and ROM", _acceleration(False), _acceleration(True)
    ),
    CommandSpec(CommandV3.READ_MULTI_TURN_ENCODER, "Read multi-turn encoder position", _bare(), _encoder()),
    CommandSpec(
        CommandV3.READ_MULTI_TURN_ENCODER_RAW, "Read multi-turn encoder original position", _bare(), _encoder()
    ),
    CommandSpec(CommandV3.READ_MULTI_TURN_ENCODER_OFFSET, "Read multi-turn encoder zero offset", _bare(), _encoder()),
    CommandSpec(CommandV3.WRITE_ENCODER_ZERO, "Write encoder value to ROM as zero", _encoder(), _encoder(echo=True)),
    CommandSpec(CommandV3.WRITE_CURRENT_AS_ZERO, "Write current position to ROM as zero", _bare(), _encoder()),
    CommandSpec(
        CommandV3.READ_RUN_MODE,
        "Read operating mode",
        _bare(),
        _can(Layout(RunModeReply, (_u8("mode", 7, kind=Kind.ENUM, enum=RunMode),))),
    ),
    CommandSpec(CommandV3.RESET, "System reset (no reply)", _bare(), {}),
    CommandSpec(CommandV3.RELEASE_BRAKE, "Release brake", _bare(), _bare(echo=True)),
    CommandSpec(CommandV3.LOCK_BRAKE, "Lock brake", _bare(), _bare(echo=True)),
    CommandSpec(
        CommandV3.CAN_ID,
        "Read or write the id",
        _can(Layout(CanIdCommand, (_u8("access", 2, kind=Kind.ENUM, enum=ReadWrite), _u8("can_id", 7, lo=0, hi=32)))),
        _can(Layout(CanIdReply, (_u8("access", 2, kind=Kind.ENUM, enum=ReadWrite), _u16("value", 6)))),
    ),
    CommandSpec(CommandV3.MOTOR_OFF, "Motor off", _bare(), _bare(echo=True)),
    CommandSpec(CommandV3.MOTOR_STOP, "Motor stop", _bare(), _bare(echo=True)),
    CommandSpec(
        CommandV3.READ_ENCODER,
        "Read single-turn encoder",
        _bare(),
        _can(Layout(EncoderReading, (_u16("encoder", 2), _u16("encoder_raw", 4), _u16("encoder_offset", 6)))),
    ),
    CommandSpec(
        CommandV3.READ_MULTI_TURN_ANGLE,
        "Read multi-turn angle",
        _bare(),
        _can(Layout(MultiTurnAngle, (_i32("angle_deg", 4, **_DEG),))),
    ),
    CommandSpec(
        CommandV3.READ_SINGLE_TURN_ANGLE,
        "Read single-turn angle",
        _bare(),
        _can(Layout(SingleTurnAngle, (_u16("angle_deg", 6, **_SINGLE),))),
    ),
    CommandSpec(
        CommandV3.READ_STATUS_1,
        "Read status 1 and error word",
        _bare(),
        _can(
            Layout(
                Status1V3,
                (
                    _i8("temperature_c", 1, **_TEMPERATURE),
                    _u8("brake", 3, kind=Kind.ENUM, enum=BrakeCommand),
                    _u16("voltage_v", 4, kind=Kind.REAL, num=1, den=10, unit="V"),
                    _u16("errors", 6, kind=Kind.FLAGS, enum=SystemErrorFlags),
                ),
            )
        ),
    ),
    CommandSpec(CommandV3.READ_STATUS_2, "Read status 2", _bare(), _state()),
    CommandSpec(
        CommandV3.READ_STATUS_3,
        "Read status 3 (phase currents)",
        _bare(),
        _can(
            Layout(
                PhaseCurrents,
                (
                    _i8("temperature_c", 1, **_TEMPERATURE),
                    _i16("ia_a", 2, **_AMPS),
                    _i16("ib_a", 4, **_AMPS),
                    _i16("ic_a", 6, **_AMPS),
                ),
            )
        ),
    ),
    CommandSpec(
        CommandV3.TORQUE, "Torque closed loop", _can(Layout(TorqueControl, (_i16("iq_a", 4, **_AMPS),))), _state()
    ),
    CommandSpec(
        CommandV3.SPEED, "Speed closed loop", _can(Layout(SpeedControl, (_i32("speed_dps", 4, **_CDPS),))), _state()
    ),
    CommandSpec(
        CommandV3.MULTI_TURN_POSITION_SPEED,
        "Absolute position with max speed",
        _can(Layout(MultiTurnPositionSpeed, (_u16("max_speed_dps", 2, **_DPS), _i32("angle_deg", 4, **_DEG)))),
        _state(),
    ),
    CommandSpec(
        CommandV3.SINGLE_TURN_POSITION_SPEED,
        "Single-turn position with max speed",
        _can(
            Layout(
                SingleTurnPositionSpeed,
                (
                    _u8("direction", 1, kind=Kind.ENUM, enum=SpinDirection),
                    _u16("max_speed_dps", 2, **_DPS),
                    _u16("angle_deg", 4, **_SINGLE),
                ),
            )
        ),
        _can(
            Layout(
                SingleTurnStateV3,
                (
                    _i8("temperature_c", 1, **_TEMPERATURE),
                    _i16("iq_a", 2, **_AMPS),
                    _i16("speed_dps", 4, unit="dps"),
                    _u16("encoder", 6, unit="counts"),
                ),
            )
        ),
    ),
    CommandSpec(
        CommandV3.INCREMENTAL_POSITION_SPEED,
        "Incremental position with max speed",
        _can(Layout(IncrementalPositionSpeed, (_u16("max_speed_dps", 2, **_DPS), _i32("angle_deg", 4, **_DEG)))),
        _state(),
    ),
    CommandSpec(CommandV3.READ_RUNTIME, "Read runtime", _bare(), _can(Layout(Runtime, (_u32("runtime_ms", 4),)))),
    CommandSpec(
        CommandV3.READ_VERSION_DATE, "Read firmware date", _bare(), _can(Layout(VersionDate, (_u32("date", 4),)))
    ),
    CommandSpec(
        CommandV3.COMMUNICATION_TIMEOUT,
        "Communication-loss protection time",
        _can(Layout(CommunicationTimeout, (_u32("timeout_ms", 4, unit="ms"),))),
        _can(Layout(CommunicationTimeout, (_u32("timeout_ms", 4, unit="ms"),), echo=True)),
    ),
    CommandSpec(
        CommandV3.BAUD_RATE, "Baud rate (no usable reply)", _can(Layout(BaudRate, (_u8("code", 7, hi=4),))), {}
    ),
    CommandSpec(
        CommandV3.READ_MODEL,
        "Read motor model",
        _bare(),
        _can(Layout(MotorModel, (Field("model", 1, 7, False, kind=Kind.TEXT),))),
    ),
    CommandSpec(
        CommandV3.ACTIVE_REPLY,
        "Active reply (CAN only, no reply)",
        _can(
            Layout(
                ActiveReply,
                (
                    _u8("reply_command", 1, kind=Kind.ENUM, enum=ActiveReplyCommand),
                    _u8("enabled", 2, hi=1),
                    _u16("interval_ms", 3, kind=Kind.REAL, num=10, den=1, unit="ms"),
                ),
            )
        ),
        {},
    ),
)

#: Every command of the V4.2 document, by command byte.
COMMANDS_V3: Final[Mapping[CommandV3, CommandSpec]] = {CommandV3(spec.code): spec for spec in _SPECS}
COMMAND_TABLES[CommandV3] = COMMANDS_V3  # (field_spec / field_range serve this family too)
#: The commands an RS485 V3 drive has (0xB6 active replies are CAN only).
RS485_COMMANDS: Final = frozenset(COMMANDS_V3) - {CommandV3.ACTIVE_REPLY}
