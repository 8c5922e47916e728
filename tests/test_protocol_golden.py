"""Golden vectors: one table drives both encode and decode, on both transports.

Rows marked ``doc`` are the worked examples of the RS485 document; every other row was computed by hand from
the byte tables (checksums are sums mod 256). The document's 0x12 example carries a wrong header checksum
(erratum R1 in docs/protocol.md) and is checked separately below.
"""

from __future__ import annotations

from dataclasses import dataclass

import pytest

from motion.errors import DecodeError
from motion.protocol import (
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
    can_frame,
    rs485_frame,
)

C = Command
CW, CCW = SpinDirection.CLOCKWISE, SpinDirection.COUNTERCLOCKWISE
REQ, REP = "request", "reply"


@dataclass(frozen=True)
class Vector:
    transport: str  # "can" | "rs485"
    direction: str  # REQ | REP
    motor_id: int
    message: Message
    wire: str  # CAN: "ID: 8 bytes"; RS485: the frame
    source: str = "hand"

    def __str__(self) -> str:
        return f"{self.transport}-{self.direction}-{type(self.message).__name__}-{self.wire}"


PID = PidGains(C.READ_PID, 100, 50, 40, 30, 20, 10)

VECTORS = [
    # ---------------------------------------------------------------- CAN v2.3 (ID 0x140 + id)
    Vector("can", REQ, 1, Bare(C.READ_PID), "141: 30 00 00 00 00 00 00 00"),
    Vector("can", REP, 1, PID, "141: 30 00 64 32 28 1E 14 0A"),
    Vector("can", REQ, 2, PidGains(C.WRITE_PID_RAM, 100, 50, 40, 30, 20, 10), "142: 31 00 64 32 28 1E 14 0A"),
    Vector("can", REP, 3, PidGains(C.WRITE_PID_ROM, 1, 2, 3, 4, 5, 6), "143: 32 00 01 02 03 04 05 06"),
    Vector("can", REQ, 1, Bare(C.READ_ACCELERATION), "141: 33 00 00 00 00 00 00 00"),
    Vector("can", REP, 1, Acceleration(C.READ_ACCELERATION, 10000), "141: 33 00 00 00 10 27 00 00"),
    Vector("can", REQ, 1, Acceleration(C.WRITE_ACCELERATION_RAM, 36000), "141: 34 00 00 00 A0 8C 00 00"),
    Vector("can", REQ, 1, Bare(C.READ_ENCODER), "141: 90 00 00 00 00 00 00 00"),
    Vector("can", REP, 1, EncoderReading(1000, 1500, 500), "141: 90 00 E8 03 DC 05 F4 01"),
    Vector("can", REQ, 1, EncoderOffset(C.WRITE_ENCODER_OFFSET, 0x1234), "141: 91 00 00 00 00 00 34 12"),
    Vector("can", REP, 1, EncoderOffset(C.WRITE_ENCODER_OFFSET, 0x1234), "141: 91 00 00 00 00 00 34 12"),
    Vector("can", REQ, 1, Bare(C.WRITE_ZERO_ROM), "141: 19 00 00 00 00 00 00 00"),
    Vector("can", REP, 1, EncoderOffset(C.WRITE_ZERO_ROM, 0x2000), "141: 19 00 00 00 00 00 00 20"),
    Vector("can", REQ, 1, Bare(C.READ_MULTI_TURN_ANGLE), "141: 92 00 00 00 00 00 00 00"),
    Vector("can", REP, 1, MultiTurnAngle(1000.0), "141: 92 A0 86 01 00 00 00 00"),
    Vector("can", REP, 1, MultiTurnAngle(-1.0), "141: 92 9C FF FF FF FF FF FF"),
    Vector("can", REP, 1, SingleTurnAngle(359.99), "141: 94 00 00 00 00 00 9F 8C"),
    Vector("can", REQ, 1, Bare(C.SET_ZERO_RAM), "141: 95 00 00 00 00 00 00 00"),
    Vector("can", REP, 1, Bare(C.SET_ZERO_RAM), "141: 95 00 00 00 00 00 00 00"),
    Vector("can", REQ, 32, Bare(C.READ_STATUS_1), "160: 9A 00 00 00 00 00 00 00"),
    Vector(
        "can",
        REP,
        1,
        Status1(C.READ_STATUS_1, 45, 24.0, ErrorFlags.LOW_VOLTAGE | ErrorFlags.OVER_TEMPERATURE),
        "141: 9A 2D 00 F0 00 00 00 09",
    ),
    Vector("can", REP, 1, Status1(C.CLEAR_ERRORS, -5, 12.5, ErrorFlags.NONE), "141: 9B FB 00 7D 00 00 00 00"),
    Vector("can", REP, 1, MotorState(C.READ_STATUS_2, 30, 1.6, -360, 16383), "141: 9C 1E 64 00 98 FE FF 3F"),
    Vector("can", REP, 1, PhaseCurrents(1.0, -0.5, -0.5), "141: 9D 00 40 00 E0 FF E0 FF"),
    Vector("can", REQ, 1, Bare(C.MOTOR_OFF), "141: 80 00 00 00 00 00 00 00"),
    Vector("can", REP, 1, Bare(C.MOTOR_STOP), "141: 81 00 00 00 00 00 00 00"),
    Vector("can", REQ, 1, Bare(C.MOTOR_RUN), "141: 88 00 00 00 00 00 00 00"),
    Vector("can", REQ, 1, OpenLoopControl(-1000), "141: A0 00 00 00 18 FC 00 00"),
    Vector("can", REP, 1, OpenLoopState(25, 500, 100, 0), "141: A0 19 F4 01 64 00 00 00"),
    Vector("can", REQ, 1, TorqueControl(-32.0), "141: A1 00 00 00 30 F8 00 00"),
    Vector("can", REP, 1, MotorState(C.TORQUE, 40, -1.6, 0, 8192), "141: A1 28 9C FF 00 00 00 20"),
    Vector("can", REQ, 1, SpeedControl(100.5), "141: A2 00 00 00 42 27 00 00"),
    Vector("can", REQ, 1, MultiTurnPosition(360.0), "141: A3 00 00 00 A0 8C 00 00"),
    Vector("can", REQ, 1, MultiTurnPosition(-90.0), "141: A3 00 00 00 D8 DC FF FF"),
    Vector("can", REQ, 1, MultiTurnPositionSpeed(360.0, 500.0), "141: A4 00 F4 01 A0 8C 00 00"),
    Vector("can", REQ, 1, SingleTurnPosition(CCW, 180.0), "141: A5 01 00 00 50 46 00 00"),
    Vector("can", REQ, 1, SingleTurnPositionSpeed(CW, 90.0, 720.0), "141: A6 00 D0 02 28 23 00 00"),
    Vector("can", REQ, 1, IncrementalPosition(-45.5), "141: A7 00 00 00 3A EE FF FF"),
    Vector("can", REQ, 1, IncrementalPositionSpeed(10.0, 60.0), "141: A8 00 3C 00 E8 03 00 00"),
    Vector("can", REQ, 0, MultiMotorTorque(1.6, -1.6, 0.0, 32.0), "280: 64 00 9C FF 00 00 D0 07"),
    # ---------------------------------------------------------------- RS485 v1.62
    Vector("rs485", REQ, 1, Bare(C.READ_PID), "3E 30 01 00 6F"),
    Vector("rs485", REP, 1, PID, "3E 30 01 06 75 64 32 28 1E 14 0A FA"),
    Vector("rs485", REQ, 2, PidGains(C.WRITE_PID_RAM, 100, 50, 40, 30, 20, 10), "3E 31 02 06 77 64 32 28 1E 14 0A FA"),
    Vector("rs485", REP, 3, PidGains(C.WRITE_PID_ROM, 1, 2, 3, 4, 5, 6), "3E 32 03 06 79 01 02 03 04 05 06 15"),
    Vector("rs485", REQ, 1, Bare(C.READ_ACCELERATION), "3E 33 01 00 72"),
    Vector("rs485", REP, 1, Acceleration(C.READ_ACCELERATION, 10000), "3E 33 01 04 76 10 27 00 00 37"),
    Vector("rs485", REQ, 1, Acceleration(C.WRITE_ACCELERATION_RAM, 36000), "3E 34 01 04 77 A0 8C 00 00 2C"),
    Vector("rs485", REQ, 1, Bare(C.READ_ENCODER), "3E 90 01 00 CF"),
    Vector("rs485", REP, 1, EncoderReading(1000, 1500, 500), "3E 90 01 06 D5 E8 03 DC 05 F4 01 C1"),
    Vector("rs485", REQ, 1, EncoderOffset(C.WRITE_ENCODER_OFFSET, 0x1234), "3E 91 01 02 D2 34 12 46"),
    Vector("rs485", REQ, 1, Bare(C.WRITE_ZERO_ROM), "3E 19 01 00 58", "doc"),
    Vector("rs485", REP, 1, Bare(C.WRITE_ZERO_ROM), "3E 19 01 00 58", "doc"),
    Vector("rs485", REQ, 1, Bare(C.READ_MULTI_TURN_ANGLE), "3E 92 01 00 D1"),
    Vector("rs485", REP, 1, MultiTurnAngle(1000.0), "3E 92 01 08 D9 A0 86 01 00 00 00 00 00 27"),
    Vector("rs485", REP, 1, MultiTurnAngle(-1.0), "3E 92 01 08 D9 9C FF FF FF FF FF FF FF 95"),
    Vector("rs485", REQ, 1, Bare(C.READ_SINGLE_TURN_ANGLE), "3E 94 01 00 D3"),
    Vector("rs485", REP, 1, SingleTurnAngle(359.99), "3E 94 01 02 D5 9F 8C 2B"),
    Vector("rs485", REQ, 1, Bare(C.READ_STATUS_1), "3E 9A 01 00 D9"),
    Vector(
        "rs485",
        REP,
        1,
        Status1(C.READ_STATUS_1, 45, 24.0, ErrorFlags.LOW_VOLTAGE | ErrorFlags.OVER_TEMPERATURE),
        "3E 9A 01 07 E0 2D 00 F0 00 00 00 09 26",
    ),
    Vector(
        "rs485", REP, 1, Status1(C.CLEAR_ERRORS, -5, 12.5, ErrorFlags.NONE), "3E 9B 01 07 E1 FB 00 7D 00 00 00 00 78"
    ),
    Vector(
        "rs485", REP, 1, MotorState(C.READ_STATUS_2, 30, 1.6, -360, 16383), "3E 9C 01 07 E2 1E 64 00 98 FE FF 3F 56"
    ),
    Vector("rs485", REQ, 1, Bare(C.READ_STATUS_3), "3E 9D 01 00 DC"),
    Vector("rs485", REP, 1, PhaseCurrents(1.0, -0.5, -0.5, 33), "3E 9D 01 07 E3 21 40 00 E0 FF E0 FF 1F"),
    Vector("rs485", REQ, 1, Bare(C.MOTOR_OFF), "3E 80 01 00 BF", "doc"),
    Vector("rs485", REP, 1, Bare(C.MOTOR_OFF), "3E 80 01 00 BF", "doc"),
    Vector("rs485", REQ, 1, Bare(C.MOTOR_STOP), "3E 81 01 00 C0", "doc"),
    Vector("rs485", REQ, 1, Bare(C.MOTOR_RUN), "3E 88 01 00 C7", "doc"),
    Vector("rs485", REQ, 1, OpenLoopControl(-1000), "3E A0 01 02 E1 18 FC 14"),
    Vector("rs485", REP, 1, OpenLoopState(25, 500, 100, 0), "3E A0 01 07 E6 19 F4 01 64 00 00 00 72"),
    Vector("rs485", REQ, 1, TorqueControl(-32.0), "3E A1 01 02 E2 30 F8 28"),
    Vector("rs485", REP, 1, MotorState(C.TORQUE, 40, -1.6, 0, 8192), "3E A1 01 07 E7 28 9C FF 00 00 00 20 E3"),
    Vector("rs485", REQ, 1, SpeedControl(100.5), "3E A2 01 04 E5 42 27 00 00 69"),
    Vector("rs485", REQ, 1, MultiTurnPosition(360.0), "3E A3 01 08 EA A0 8C 00 00 00 00 00 00 2C"),
    Vector("rs485", REQ, 1, MultiTurnPosition(-90.0), "3E A3 01 08 EA D8 DC FF FF FF FF FF FF AE"),
    Vector(
        "rs485",
        REQ,
        1,
        MultiTurnPositionSpeed(360.0, 500.0),
        "3E A4 01 0C EF A0 8C 00 00 00 00 00 00 50 C3 00 00 3F",
    ),
    Vector(
        "rs485",
        REQ,
        32,
        MultiTurnPositionSpeed(0.01, 0.01),
        "3E A4 20 0C 0E 01 00 00 00 00 00 00 00 01 00 00 00 02",
    ),
    Vector("rs485", REQ, 1, SingleTurnPosition(CCW, 180.0), "3E A5 01 04 E8 01 50 46 00 97"),
    Vector("rs485", REQ, 1, SingleTurnPositionSpeed(CW, 90.0, 720.0), "3E A6 01 08 ED 00 28 23 00 40 19 01 00 A5"),
    Vector("rs485", REQ, 1, IncrementalPosition(-45.5), "3E A7 01 04 EA 3A EE FF FF 26"),
    Vector("rs485", REQ, 1, IncrementalPositionSpeed(10.0, 60.0), "3E A8 01 08 EF E8 03 00 00 70 17 00 00 72"),
    Vector("rs485", REQ, 1, Bare(C.READ_MODEL), "3E 12 01 00 51"),
    Vector(
        "rs485",
        REP,
        1,
        ProductInfo("RMD-X8", "X8-PRO-1:6", 1.2, 3.5),
        "3E 12 01 2A 7B 52 4D 44 2D 58 38 00 00 00 00 00 00 00 00 00 00 00 00 00 00 "
        "58 38 2D 50 52 4F 2D 31 3A 36 00 00 00 00 00 00 00 00 00 00 0C 23 4B",
    ),
]


def _encode(v: Vector) -> str:
    if v.transport == "can":
        enc = can_frame.encode_request if v.direction == REQ else can_frame.encode_reply
        frame = enc(v.message, v.motor_id or 1)
        return f"{frame.arbitration_id:03X}: {frame.data.hex(' ').upper()}"
    enc485 = rs485_frame.encode_request if v.direction == REQ else rs485_frame.encode_reply
    return enc485(v.message, v.motor_id).hex(" ").upper()


def _decode(v: Vector) -> tuple[int | None, Message]:
    if v.transport == "can":
        ident, data = v.wire.split(":")
        if v.direction == REQ:
            req = can_frame.decode_request(int(ident, 16), bytes.fromhex(data))
            return req.motor_id, req.message
        return can_frame.decode_reply(int(ident, 16), bytes.fromhex(data))
    dec = rs485_frame.decode_request if v.direction == REQ else rs485_frame.decode_reply
    return dec(bytes.fromhex(v.wire))


@pytest.mark.parametrize("vector", VECTORS, ids=str)
def test_encode_matches_golden(vector: Vector) -> None:
    assert _encode(vector) == vector.wire


@pytest.mark.parametrize("vector", VECTORS, ids=str)
def test_decode_matches_golden(vector: Vector) -> None:
    motor_id, message = _decode(vector)
    assert message == vector.message
    assert type(message) is type(vector.message)
    assert motor_id == (vector.motor_id or None)


def test_every_command_has_a_golden_vector_on_each_transport_that_has_it() -> None:
    from motion.protocol import COMMANDS, WireProtocol

    covered = {(v.transport, getattr(v.message, "command", None)) for v in VECTORS}
    for code, spec in COMMANDS.items():
        for transport in WireProtocol:
            if transport in spec.request:
                assert (transport.value, code) in covered, f"no golden vector for 0x{code:02X} on {transport.value}"


def test_document_example_0x12_has_a_wrong_header_checksum() -> None:
    """RS485 doc, command (27): '3E 12 01 00 45' — 0x3E+0x12+0x01+0x00 = 0x51 (erratum R1)."""
    with pytest.raises(DecodeError, match="header checksum 0x45 != 0x51"):
        rs485_frame.decode_request(bytes.fromhex("3E 12 01 00 45"))
    assert rs485_frame.encode_request(Bare(C.READ_MODEL), 1) == bytes.fromhex("3E 12 01 00 51")


@pytest.mark.parametrize(
    ("example", "checksum"),
    [("3E 19 01 00", 0x58), ("3E 80 01 00", 0xBF), ("3E 81 01 00", 0xC0), ("3E 88 01 00", 0xC7)],
)
def test_document_header_checksums(example: str, checksum: int) -> None:
    assert rs485_frame.checksum(bytes.fromhex(example)) == checksum
