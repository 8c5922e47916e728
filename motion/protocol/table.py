"""The command table: ONE declaration per command, with its request and reply layout on each transport.

Encoders, decoders, the emulator's replies and ``docs/protocol.md``'s command table are all derived from
:data:`COMMANDS`. A layout lists the fields of a message class with their byte offset, width, signedness,
exact scale (physical = raw * num / den), unit and valid raw range.

Offsets are counted from DATA[0] of the 8-byte CAN payload (DATA[0] is the command byte) and from the first
data byte of an RS485 frame (DATA[5] of the frame). Reserved bytes ("NULL 0x00") are written as zero; a
request whose reserved bytes are not zero is rejected, a reply's reserved bytes are ignored (drives of other
series and firmware use some of them).
"""

from __future__ import annotations

import math
import struct
from collections.abc import Mapping
from dataclasses import dataclass, field, fields
from enum import Enum, IntEnum, IntFlag, StrEnum
from fractions import Fraction
from typing import Any, Final

from motion.errors import DecodeError, EncodeError
from motion.protocol import scales
from motion.protocol.messages import (
    Acceleration,
    Bare,
    Command,
    EncoderOffset,
    EncoderReading,
    ErrorFlags,
    IncrementalPosition,
    IncrementalPositionSpeed,
    Message,
    MotorState,
    MultiMotorTorque,
    MultiTurnAngle,
    MultiTurnPosition,
    MultiTurnPositionSpeed,
    OpenLoopControl,
    OpenLoopState,
    PhaseCurrents,
    PidGains,
    ProductInfo,
    SingleTurnAngle,
    SingleTurnPosition,
    SingleTurnPositionSpeed,
    SpeedControl,
    SpinDirection,
    Status1,
    TorqueControl,
)


class WireProtocol(StrEnum):
    """The two wire protocols (the configuration's ``bus.transport`` names one)."""

    CAN = "can"  #: CAN v2.3: 8-byte frames on ID 0x140 + motor id
    RS485 = "rs485"  #: RS485 v1.62: 0x3E-framed, checksummed


class ProtocolFamily(StrEnum):
    """The drives' protocol generation (the configuration's ``bus.protocol`` names one, or ``auto``)."""

    V2 = "v2"  #: the two documents of ../shared/protocol (CAN v2.3, RS485 v1.62): replies on 0x140 + id
    V3 = "v3"  #: driver V3 ("Servo Motor Control Protocol" V4.2): replies on 0x240 + id (motion.protocol.v3)


#: The RS485 baud rates of each generation, bit/s: v1.62 section 1 (115200 the factory default); V4.2 0xB4's codes
#: 0..4 (115200 the factory default).
RS485_BAUDRATES: Final[Mapping[ProtocolFamily, tuple[int, ...]]] = {
    ProtocolFamily.V2: (9600, 19200, 57600, 115_200),
    ProtocolFamily.V3: (115_200, 500_000, 1_000_000, 1_500_000, 2_500_000),
}


class Direction(Enum):
    """Which way a frame travels."""

    REQUEST = "request"  #: host -> drive
    REPLY = "reply"  #: drive -> host


class Kind(Enum):
    """How a field's raw integer maps to its Python value."""

    INT = "int"  #: an int with scale 1
    REAL = "real"  #: a float, raw * num / den
    ENUM = "enum"  #: an IntEnum member (only its members are valid)
    FLAGS = "flags"  #: an IntFlag (every bit pattern is kept)
    TEXT = "text"  #: NUL-padded ASCII of ``width`` bytes
    FLOAT32 = "float32"  #: an IEEE-754 single, little-endian (V3 family's PID parameters); finite values only


#: Largest finite IEEE-754 single.
FLOAT32_MAX: Final = 3.4028234663852886e38
_FLOAT32: Final = struct.Struct("<f")

MOTOR_ID_MIN: Final = 1
MOTOR_ID_MAX: Final = 32
#: An arm on several buses names each drive by its address, ``bus index × ADDRESS_STRIDE + motor id`` (the first bus:
#: the motor id itself), so that control and safety keep one key per drive; the buses' transport splits it again.
ADDRESS_STRIDE: Final = 100
CAN_PAYLOAD_BYTES: Final = 8
RS485_MAX_DATA_BYTES: Final = 60


@dataclass(frozen=True, slots=True)
class Field:
    """One field of a layout.

    Attributes:
        name: attribute of the message class.
        offset: byte offset in the payload (see the module docstring).
        width: bytes on the wire (1..8; 7 for the CAN 0x92 angle).
        signed: two's complement if true.
        kind: how the raw integer becomes a Python value.
        num: scale numerator (physical = raw * num / den).
        den: scale denominator.
        unit: physical unit, for messages and docs.
        lo: smallest valid raw value (defaults to the type's minimum).
        hi: largest valid raw value (defaults to the type's maximum).
        enum: the IntEnum / IntFlag class of ENUM / FLAGS fields.
    """

    name: str
    offset: int
    width: int
    signed: bool
    kind: Kind = Kind.INT
    num: int = 1
    den: int = 1
    unit: str = ""
    lo: int = 0
    hi: int = 0
    enum: type[IntEnum] | type[IntFlag] | None = None

    def __post_init__(self) -> None:
        if self.lo == 0 and self.hi == 0 and self.kind not in (Kind.TEXT, Kind.FLOAT32):
            bits = 8 * self.width
            lo, hi = (-(1 << (bits - 1)), (1 << (bits - 1)) - 1) if self.signed else (0, (1 << bits) - 1)
            object.__setattr__(self, "lo", lo)
            object.__setattr__(self, "hi", hi)

    @property
    def ctype(self) -> str:
        """C-like type name of the wire field (``int32``, ``uint16``, ``int56``, ``char[20]``)."""
        if self.kind is Kind.TEXT:
            return f"char[{self.width}]"
        if self.kind is Kind.FLOAT32:
            return "float32"
        return f"{'int' if self.signed else 'uint'}{8 * self.width}"

    def physical(self, raw: int) -> float:
        """Physical value of a raw integer (exactly rounded: ``raw * num / den``)."""
        return raw * self.num / self.den if self.kind is Kind.REAL else raw

    def valid_range(self) -> str:
        """Human-readable valid range in physical units, with the raw range."""
        unit = f" {self.unit}" if self.unit else ""
        if self.kind is Kind.ENUM and self.enum is not None:
            return "{" + ", ".join(f"{m.name}={m.value}" for m in self.enum) + "}"
        if self.kind is Kind.TEXT:
            return f"ASCII text of at most {self.width} bytes"
        if self.kind is Kind.FLOAT32:
            return f"a finite float32 (|x| <= {FLOAT32_MAX:.7g}){' ' + self.unit if self.unit else ''}"
        if self.kind is Kind.REAL:
            return f"{self.physical(self.lo):g}..{self.physical(self.hi):g}{unit} (raw {self.lo}..{self.hi})"
        return f"{self.lo}..{self.hi}{unit}"


@dataclass(frozen=True, slots=True)
class Layout:
    """Layout of one message on one transport in one direction.

    Attributes:
        cls: the message class.
        fields: the fields on the wire, in offset order.
        length: RS485 data length (bytes after the header); CAN payloads are always 8 bytes.
        echo: the reply repeats the request (documentation only; the layout says the same).
    """

    cls: type[Message]
    fields: tuple[Field, ...] = ()
    length: int = 0
    echo: bool = False
    used: frozenset[int] = field(init=False, default=frozenset())
    uncarried: tuple[str, ...] = field(init=False, default=())
    has_command_field: bool = field(init=False, default=False)

    def __post_init__(self) -> None:
        used: set[int] = set()
        for f in self.fields:
            used.update(range(f.offset, f.offset + f.width))
        names = {f.name for f in self.fields}
        attrs = [f.name for f in fields(self.cls)]
        object.__setattr__(self, "used", frozenset(used))
        object.__setattr__(self, "uncarried", tuple(a for a in attrs if a not in names and a != "command"))
        object.__setattr__(self, "has_command_field", "command" in attrs)


@dataclass(frozen=True, slots=True)
class CommandSpec:
    """One command of the documents: its name and its layouts per transport and direction (``code`` is a member of
    the family's command enum: :class:`Command`, or the V3 family's ``CommandV3``)."""

    code: IntEnum
    title: str
    request: Mapping[WireProtocol, Layout]
    reply: Mapping[WireProtocol, Layout]

    def layout(self, transport: WireProtocol, direction: Direction) -> Layout | None:
        """The layout on ``transport`` in ``direction``, or None when the transport lacks the command."""
        return (self.request if direction is Direction.REQUEST else self.reply).get(transport)


# --- field helpers: one line per field in the table below ---------------------------------------------------

_DEG: dict[str, Any] = dict(kind=Kind.REAL, num=scales.CENTIDEGREE[0], den=scales.CENTIDEGREE[1], unit="deg")
_CDPS: dict[str, Any] = dict(kind=Kind.REAL, num=1, den=100, unit="dps")
_DPS: dict[str, Any] = dict(kind=Kind.REAL, num=1, den=1, unit="dps")
_IQ_CMD: dict[str, Any] = dict(
    kind=Kind.REAL,
    num=scales.IQ_SCALE[0],
    den=scales.IQ_SCALE[1],
    unit="A",
    lo=-scales.IQ_RAW_LIMIT,
    hi=scales.IQ_RAW_LIMIT,
)
_IQ_REPLY: dict[str, Any] = dict(kind=Kind.REAL, num=scales.IQ_SCALE[0], den=scales.IQ_SCALE[1], unit="A")


def _u8(name: str, offset: int, **kw: Any) -> Field:
    return Field(name, offset, 1, False, **kw)


def _i8(name: str, offset: int, **kw: Any) -> Field:
    return Field(name, offset, 1, True, **kw)


def _u16(name: str, offset: int, **kw: Any) -> Field:
    return Field(name, offset, 2, False, **kw)


def _i16(name: str, offset: int, **kw: Any) -> Field:
    return Field(name, offset, 2, True, **kw)


def _i32(name: str, offset: int, **kw: Any) -> Field:
    return Field(name, offset, 4, True, **kw)


def _u32(name: str, offset: int, **kw: Any) -> Field:
    return Field(name, offset, 4, False, **kw)


def _i64(name: str, offset: int, **kw: Any) -> Field:
    return Field(name, offset, 8, True, **kw)


def _pid(first: int) -> tuple[Field, ...]:
    names = ("angle_kp", "angle_ki", "speed_kp", "speed_ki", "iq_kp", "iq_ki")
    return tuple(_u8(n, first + i) for i, n in enumerate(names))


def _state(first: int, cls: type[Message] = MotorState) -> tuple[Field, ...]:
    """temperature int8, iq (or power) int16, speed int16 1 dps, encoder uint16 — the common reply block."""
    second = (
        _i16("power", first + 1, lo=-1000, hi=1000) if cls is OpenLoopState else _i16("iq_a", first + 1, **_IQ_REPLY)
    )
    return (
        _i8("temperature_c", first, unit="degC"),
        second,
        _i16("speed_dps", first + 3, unit="dps"),
        _u16("encoder", first + 5, unit="counts"),
    )


def _status1(first: int) -> tuple[Field, ...]:
    """temperature int8, NULL, voltage uint16 0.1 V, NULL, NULL, error byte."""
    return (
        _i8("temperature_c", first, unit="degC"),
        _u16("voltage_v", first + 2, kind=Kind.REAL, num=1, den=10, unit="V"),
        _u8("errors", first + 6, kind=Kind.FLAGS, enum=ErrorFlags),
    )


_ACCEL: dict[str, Any] = dict(unit="dps/s", lo=0, hi=(1 << 31) - 1)
_DIRECTION: dict[str, Any] = dict(kind=Kind.ENUM, enum=SpinDirection)
_SINGLE: dict[str, Any] = dict(_DEG, lo=0, hi=35999)
_OFFSET: dict[str, Any] = dict(unit="counts")

_PHASES = ("ia_a", "ib_a", "ic_a")
_PHASE: dict[str, Any] = dict(kind=Kind.REAL, num=1, den=64, unit="A")

_BARE = Layout(Bare)


def _both(layout: Layout) -> dict[WireProtocol, Layout]:
    return {WireProtocol.CAN: layout, WireProtocol.RS485: layout}


def _bare_both(echo: bool = False) -> dict[WireProtocol, Layout]:
    return _both(Layout(Bare, echo=echo))


def _can_rs(can: Layout, rs485: Layout) -> dict[WireProtocol, Layout]:
    return {WireProtocol.CAN: can, WireProtocol.RS485: rs485}


def _state_reply() -> dict[WireProtocol, Layout]:
    return _can_rs(Layout(MotorState, _state(1)), Layout(MotorState, _state(0), 7))


def _pid_both(echo: bool) -> dict[WireProtocol, Layout]:
    return _can_rs(Layout(PidGains, _pid(2), echo=echo), Layout(PidGains, _pid(0), 6, echo=echo))


def _accel_both(echo: bool) -> dict[WireProtocol, Layout]:
    return _can_rs(
        Layout(Acceleration, (_i32("acceleration_dps2", 4, **_ACCEL),), echo=echo),
        Layout(Acceleration, (_i32("acceleration_dps2", 0, **_ACCEL),), 4, echo=echo),
    )


def _status1_reply() -> dict[WireProtocol, Layout]:
    return _can_rs(Layout(Status1, _status1(1)), Layout(Status1, _status1(0), 7))


_SPECS: tuple[CommandSpec, ...] = (
    CommandSpec(Command.READ_PID, "Read PID", _bare_both(), _pid_both(False)),
    CommandSpec(Command.WRITE_PID_RAM, "Write PID to RAM", _pid_both(False), _pid_both(True)),
    CommandSpec(Command.WRITE_PID_ROM, "Write PID to ROM", _pid_both(False), _pid_both(True)),
    CommandSpec(Command.READ_ACCELERATION, "Read acceleration", _bare_both(), _accel_both(False)),
    CommandSpec(Command.WRITE_ACCELERATION_RAM, "Write acceleration to RAM", _accel_both(False), _accel_both(True)),
    CommandSpec(
        Command.READ_ENCODER,
        "Read encoder",
        _bare_both(),
        _can_rs(
            Layout(EncoderReading, (_u16("encoder", 2), _u16("encoder_raw", 4), _u16("encoder_offset", 6))),
            Layout(EncoderReading, (_u16("encoder", 0), _u16("encoder_raw", 2), _u16("encoder_offset", 4)), 6),
        ),
    ),
    CommandSpec(
        Command.WRITE_ENCODER_OFFSET,
        "Write encoder offset (ROM)",
        _can_rs(
            Layout(EncoderOffset, (_u16("encoder_offset", 6, **_OFFSET),)),
            Layout(EncoderOffset, (_u16("encoder_offset", 0, **_OFFSET),), 2),
        ),
        _can_rs(
            Layout(EncoderOffset, (_u16("encoder_offset", 6, **_OFFSET),), echo=True),
            Layout(EncoderOffset, (_u16("encoder_offset", 0, **_OFFSET),), 2, echo=True),
        ),
    ),
    CommandSpec(
        Command.WRITE_ZERO_ROM,
        "Write current position to ROM as zero",
        _bare_both(),
        _can_rs(Layout(EncoderOffset, (_u16("encoder_offset", 6, **_OFFSET),)), Layout(Bare, echo=True)),
    ),
    CommandSpec(
        Command.READ_MULTI_TURN_ANGLE,
        "Read multi-turn angle",
        _bare_both(),
        _can_rs(
            Layout(MultiTurnAngle, (Field("angle_deg", 1, 7, True, **_DEG),)),
            Layout(MultiTurnAngle, (_i64("angle_deg", 0, **_DEG),), 8),
        ),
    ),
    CommandSpec(
        Command.READ_SINGLE_TURN_ANGLE,
        "Read single-turn angle",
        _bare_both(),
        _can_rs(
            Layout(SingleTurnAngle, (_u16("angle_deg", 6, **_SINGLE),)),
            Layout(SingleTurnAngle, (_u16("angle_deg", 0, **_SINGLE),), 2),
        ),
    ),
    CommandSpec(
        Command.SET_ZERO_RAM,
        "Set current position as zero (RAM)",
        {WireProtocol.CAN: _BARE},
        {WireProtocol.CAN: Layout(Bare, echo=True)},
    ),
    CommandSpec(Command.READ_STATUS_1, "Read status 1 and error flags", _bare_both(), _status1_reply()),
    CommandSpec(Command.CLEAR_ERRORS, "Clear error flags", _bare_both(), _status1_reply()),
    CommandSpec(Command.READ_STATUS_2, "Read status 2", _bare_both(), _state_reply()),
    CommandSpec(
        Command.READ_STATUS_3,
        "Read status 3 (phase currents)",
        _bare_both(),
        _can_rs(
            Layout(PhaseCurrents, tuple(_i16(n, 2 + 2 * i, **_PHASE) for i, n in enumerate(_PHASES))),
            Layout(
                PhaseCurrents,
                (
                    _i8("temperature_c", 0, unit="degC"),
                    *tuple(_i16(n, 1 + 2 * i, **_PHASE) for i, n in enumerate(_PHASES)),
                ),
                7,
            ),
        ),
    ),
    CommandSpec(Command.MOTOR_OFF, "Motor off", _bare_both(), _bare_both(echo=True)),
    CommandSpec(Command.MOTOR_STOP, "Motor stop", _bare_both(), _bare_both(echo=True)),
    CommandSpec(Command.MOTOR_RUN, "Motor run", _bare_both(), _bare_both(echo=True)),
    CommandSpec(
        Command.OPEN_LOOP,
        "Open-loop power (RMD-S)",
        _can_rs(
            Layout(OpenLoopControl, (_i16("power", 4, lo=-1000, hi=1000),)),
            Layout(OpenLoopControl, (_i16("power", 0, lo=-1000, hi=1000),), 2),
        ),
        _can_rs(
            Layout(OpenLoopState, _state(1, OpenLoopState)),
            Layout(OpenLoopState, _state(0, OpenLoopState), 7),
        ),
    ),
    CommandSpec(
        Command.TORQUE,
        "Torque closed loop",
        _can_rs(
            Layout(TorqueControl, (_i16("iq_a", 4, **_IQ_CMD),)),
            Layout(TorqueControl, (_i16("iq_a", 0, **_IQ_CMD),), 2),
        ),
        _state_reply(),
    ),
    CommandSpec(
        Command.SPEED,
        "Speed closed loop",
        _can_rs(
            Layout(SpeedControl, (_i32("speed_dps", 4, **_CDPS),)),
            Layout(SpeedControl, (_i32("speed_dps", 0, **_CDPS),), 4),
        ),
        _state_reply(),
    ),
    CommandSpec(
        Command.MULTI_TURN_POSITION,
        "Multi-turn position",
        _can_rs(
            Layout(MultiTurnPosition, (_i32("angle_deg", 4, **_DEG),)),
            Layout(MultiTurnPosition, (_i64("angle_deg", 0, **_DEG),), 8),
        ),
        _state_reply(),
    ),
    CommandSpec(
        Command.MULTI_TURN_POSITION_SPEED,
        "Multi-turn position with max speed",
        _can_rs(
            Layout(MultiTurnPositionSpeed, (_u16("max_speed_dps", 2, **_DPS), _i32("angle_deg", 4, **_DEG))),
            Layout(MultiTurnPositionSpeed, (_i64("angle_deg", 0, **_DEG), _u32("max_speed_dps", 8, **_CDPS)), 12),
        ),
        _state_reply(),
    ),
    CommandSpec(
        Command.SINGLE_TURN_POSITION,
        "Single-turn position",
        _can_rs(
            Layout(SingleTurnPosition, (_u8("direction", 1, **_DIRECTION), _u16("angle_deg", 4, **_SINGLE))),
            Layout(SingleTurnPosition, (_u8("direction", 0, **_DIRECTION), _u16("angle_deg", 1, **_SINGLE)), 4),
        ),
        _state_reply(),
    ),
    CommandSpec(
        Command.SINGLE_TURN_POSITION_SPEED,
        "Single-turn position with max speed",
        _can_rs(
            Layout(
                SingleTurnPositionSpeed,
                (
                    _u8("direction", 1, **_DIRECTION),
                    _u16("max_speed_dps", 2, **_DPS),
                    _u16("angle_deg", 4, **_SINGLE),
                ),
            ),
            Layout(
                SingleTurnPositionSpeed,
                (
                    _u8("direction", 0, **_DIRECTION),
                    _u16("angle_deg", 1, **_SINGLE),
                    _u32("max_speed_dps", 4, **_CDPS),
                ),
                8,
            ),
        ),
        _state_reply(),
    ),
    CommandSpec(
        Command.INCREMENTAL_POSITION,
        "Incremental position",
        _can_rs(
            Layout(IncrementalPosition, (_i32("angle_deg", 4, **_DEG),)),
            Layout(IncrementalPosition, (_i32("angle_deg", 0, **_DEG),), 4),
        ),
        _state_reply(),
    ),
    CommandSpec(
        Command.INCREMENTAL_POSITION_SPEED,
        "Incremental position with max speed",
        _can_rs(
            Layout(IncrementalPositionSpeed, (_u16("max_speed_dps", 2, **_DPS), _i32("angle_deg", 4, **_DEG))),
            Layout(IncrementalPositionSpeed, (_i32("angle_deg", 0, **_DEG), _u32("max_speed_dps", 4, **_CDPS)), 8),
        ),
        _state_reply(),
    ),
    CommandSpec(
        Command.READ_MODEL,
        "Read driver and motor model",
        {WireProtocol.RS485: _BARE},
        {
            WireProtocol.RS485: Layout(
                ProductInfo,
                (
                    Field("driver_name", 0, 20, False, kind=Kind.TEXT),
                    Field("motor_name", 20, 20, False, kind=Kind.TEXT),
                    _u8("hardware_version", 40, kind=Kind.REAL, num=1, den=10),
                    _u8("firmware_version", 41, kind=Kind.REAL, num=1, den=10),
                ),
                42,
            )
        },
    ),
)

#: Every command of both documents, by command byte.
COMMANDS: Final[Mapping[Command, CommandSpec]] = {Command(spec.code): spec for spec in _SPECS}
#: Each family's table by the type of its command codes (the V3 family's adds itself: :mod:`motion.protocol.v3.table`),
#: so that :func:`field_spec` and :func:`field_range` serve both.
COMMAND_TABLES: Final[dict[type[IntEnum], Mapping[Any, CommandSpec]]] = {Command: COMMANDS}

#: CAN arbitration id of single-motor frames is ``CAN_ID_BASE + motor id`` (requests and replies).
CAN_ID_BASE: Final = 0x140
#: CAN arbitration id of the multi-motor torque frame (motors 1..4).
CAN_MULTI_TORQUE_ID: Final = 0x280
#: Motor ids the multi-motor torque frame addresses, in the order of its four iq fields.
MULTI_TORQUE_MOTOR_IDS: Final = (1, 2, 3, 4)
#: The 0x280 frame: four int16 torque currents, no command byte; each motor replies like 0xA1.
MULTI_TORQUE_LAYOUT: Final = Layout(
    MultiMotorTorque,
    tuple(_i16(f"iq{i + 1}_a", 2 * i, **_IQ_CMD) for i in range(len(MULTI_TORQUE_MOTOR_IDS))),
)


def command_of(message: Message) -> Command | None:
    """The command byte of a message (None for the 0x280 multi-motor frame)."""
    command: Command | None = getattr(message, "command", None)
    return command


def spec_and_layout(
    commands: Mapping[Any, CommandSpec], code: int, transport: WireProtocol, direction: Direction
) -> tuple[CommandSpec, Layout] | None:
    """What a command byte is in a family's table (:data:`COMMANDS`, or the V3 family's) on ``transport`` in
    ``direction``: its spec and layout, or None when the family has no such frame. (The tables are keyed by IntEnum
    members, which a plain int finds.)"""
    spec = commands.get(code)
    layout = spec.layout(transport, direction) if spec is not None else None
    return None if spec is None or layout is None else (spec, layout)


def split_address(address: int) -> tuple[int, int]:
    """``(bus index, motor id)`` of a drive's address (see :data:`ADDRESS_STRIDE`)."""
    return divmod(address, ADDRESS_STRIDE)


def check_motor_id(motor_id: int) -> int:
    """Return ``motor_id`` if it is a valid drive id (1..32).

    Raises:
        EncodeError: naming the valid range and the value.
    """
    if isinstance(motor_id, bool) or not isinstance(motor_id, int) or not MOTOR_ID_MIN <= motor_id <= MOTOR_ID_MAX:
        raise EncodeError("motor_id", f"{MOTOR_ID_MIN}..{MOTOR_ID_MAX}", motor_id)
    return motor_id


def field_spec(command: IntEnum, direction: Direction, transport: WireProtocol, field: str) -> Field:
    """The declaration of one field of a command's frame (the one place its type, scale and range are written), of
    either family (``command``: a :class:`Command` or a V3 ``CommandV3``).

    Raises:
        KeyError: the transport lacks the command in that direction, or its frame has no such field.
    """
    layout = COMMAND_TABLES[type(command)][command].layout(transport, direction)
    if layout is None:
        raise KeyError(f"0x{command:02X} has no {direction.value} on {transport.value}")
    for spec in layout.fields:
        if spec.name == field:
            return spec
    raise KeyError(f"the {direction.value} of 0x{command:02X} on {transport.value} has no field {field!r}")


def field_range(command: IntEnum, direction: Direction, transport: WireProtocol, field: str) -> tuple[float, float]:
    """Smallest and largest value of a field in physical units (deg, dps, A, ...), as the table declares them.

    Limits that the controller, the CLI, the configuration loader and the emulator need come from here, never from a
    copy of the number.

    Raises:
        KeyError: see :func:`field_spec`.
    """
    spec = field_spec(command, direction, transport, field)
    return spec.physical(spec.lo), spec.physical(spec.hi)


def field_names(command: Command, direction: Direction, transport: WireProtocol) -> tuple[str, ...]:
    """The names of a frame's fields in wire order (a message class's physical fields).

    Raises:
        KeyError: the transport lacks the command in that direction.
    """
    layout = COMMANDS[command].layout(transport, direction)
    if layout is None:
        raise KeyError(f"0x{command:02X} has no {direction.value} on {transport.value}")
    return tuple(spec.name for spec in layout.fields)


def layout_for(message: Message, transport: WireProtocol, direction: Direction) -> Layout:
    """The layout that carries ``message`` on ``transport`` in ``direction``.

    Raises:
        EncodeError: the transport lacks the command, or the message class does not belong to it.
    """
    if isinstance(message, MultiMotorTorque):
        if transport is WireProtocol.CAN and direction is Direction.REQUEST:
            return MULTI_TORQUE_LAYOUT
        raise EncodeError("message", "a CAN request (0x280 exists on CAN only)", type(message).__name__)
    command = command_of(message)
    spec = COMMANDS.get(command) if isinstance(command, Command) else None
    if spec is None:
        raise EncodeError("command", "the commands of the documents", command)
    layout = spec.layout(transport, direction)
    if layout is None:
        raise EncodeError("command", f"commands of the {transport.value} protocol", f"0x{command:02X} {spec.title}")
    if type(message) is not layout.cls:
        raise EncodeError(
            "message",
            f"{layout.cls.__name__} for a {direction.value} of 0x{command:02X} on {transport.value}",
            type(message).__name__,
        )
    return layout


def _to_raw(f: Field, value: object) -> int:
    """Raw integer of one field value, range-checked."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise EncodeError(f.name, f.valid_range(), value, "a number is required")
    if f.kind is Kind.REAL:
        if isinstance(value, float):
            if not math.isfinite(value):
                raise EncodeError(f.name, f.valid_range(), value, "a finite number is required")
            scaled = value * f.den / f.num
            if not math.isfinite(scaled):  # (1e308 A: finite, but no integer field holds it)
                raise EncodeError(f.name, f.valid_range(), value)
            raw = round(scaled)
        else:  # exact for integers of any size
            raw = round(Fraction(value * f.den, f.num))
    elif isinstance(value, int):
        raw = int(value)
        if f.kind is Kind.ENUM and f.enum is not None and raw not in f.enum._value2member_map_:
            raise EncodeError(f.name, f.valid_range(), value)
    else:
        raise EncodeError(f.name, f.valid_range(), value, "an integer is required")
    if not f.lo <= raw <= f.hi:
        raise EncodeError(f.name, f.valid_range(), value)
    return raw


def _text_bytes(f: Field, value: object) -> bytes:
    if not isinstance(value, str) or not value.isascii() or "\0" in value or len(value) > f.width:
        raise EncodeError(f.name, f.valid_range(), value)
    return value.encode("ascii").ljust(f.width, b"\0")


def _float32_bytes(f: Field, value: object) -> bytes:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise EncodeError(f.name, f.valid_range(), value, "a number is required")
    if not math.isfinite(value) or abs(value) > FLOAT32_MAX:
        raise EncodeError(f.name, f.valid_range(), value)
    return _FLOAT32.pack(value)


def pack_fields(layout: Layout, message: Message, data: bytearray) -> None:
    """Write the fields of ``message`` into ``data`` (CAN payload or RS485 data section).

    Raises:
        EncodeError: a value is out of range, of the wrong type, or not carried by this layout.
    """
    for name in layout.uncarried:
        if getattr(message, name) is not None:
            raise EncodeError(name, "None (this transport does not carry the field)", getattr(message, name))
    for f in layout.fields:
        value = getattr(message, f.name)
        end = f.offset + f.width
        if f.kind is Kind.TEXT:
            data[f.offset : end] = _text_bytes(f, value)
        elif f.kind is Kind.FLOAT32:
            data[f.offset : end] = _float32_bytes(f, value)
        else:
            data[f.offset : end] = _to_raw(f, value).to_bytes(f.width, "little", signed=f.signed)


def unpack_fields(layout: Layout, data: bytes, command: IntEnum | None, *, first: int, check_reserved: bool) -> Message:
    """Build the message of ``layout`` from ``data`` (CAN payload or RS485 data section).

    Args:
        layout: the layout to read.
        data: the payload; field offsets count from its first byte.
        command: the command byte, for message classes that carry it as a field.
        first: the first byte that belongs to the layout (1 on CAN, after the command byte; 0 on RS485).
        check_reserved: reject non-zero reserved bytes (requests) instead of ignoring them (replies).

    Raises:
        DecodeError: a field is out of range, a reserved byte is set, or text is not ASCII.
    """
    values: dict[str, object] = {}
    for f in layout.fields:
        chunk = data[f.offset : f.offset + f.width]
        if f.kind is Kind.TEXT:
            text = chunk.split(b"\0", 1)[0]
            if not text.isascii():
                raise DecodeError(f"{f.name}: text is not ASCII", data)
            values[f.name] = text.decode("ascii")
            continue
        if f.kind is Kind.FLOAT32:
            (number,) = _FLOAT32.unpack_from(chunk)
            if not math.isfinite(number):
                raise DecodeError(f"{f.name}: {number} is not {f.valid_range()}", data)
            values[f.name] = number
            continue
        raw = int.from_bytes(chunk, "little", signed=f.signed)
        if not f.lo <= raw <= f.hi:
            raise DecodeError(f"{f.name}: raw value {raw} is outside {f.valid_range()}", data)
        if f.kind is Kind.ENUM and f.enum is not None:
            if raw not in f.enum._value2member_map_:
                raise DecodeError(f"{f.name}: {raw} is not one of {f.valid_range()}", data)
            values[f.name] = f.enum(raw)
        elif f.kind is Kind.FLAGS and f.enum is not None:
            values[f.name] = f.enum(raw)
        else:
            values[f.name] = f.physical(raw)
    if check_reserved:
        for i in range(first, len(data)):
            if data[i] and i not in layout.used:
                raise DecodeError(f"reserved byte DATA[{i}] is 0x{data[i]:02X}, must be 0x00", data)
    if layout.has_command_field:
        values["command"] = command
    return layout.cls(**values)


def raw_values(message: Message, transport: WireProtocol, direction: Direction) -> dict[str, int]:
    """The raw integers of a message's numeric fields as they go on the wire of ``transport``.

    Raises:
        EncodeError: as for encoding.
    """
    layout = layout_for(message, transport, direction)
    return {
        f.name: _to_raw(f, getattr(message, f.name)) for f in layout.fields if f.kind not in (Kind.TEXT, Kind.FLOAT32)
    }
