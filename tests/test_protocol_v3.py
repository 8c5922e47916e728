"""The V3 family's codec (issue 17, first step): golden vectors from the V4.2 document's worked examples, round trips,
the fast path against the checked path, and the fuzz invariant (any bytes raise only DecodeError)."""

from __future__ import annotations

import contextlib
import math
import struct

import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from motion.errors import DecodeError, EncodeError
from motion.protocol import (
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
from motion.protocol.messages import Message
from motion.protocol.table import Direction, WireProtocol, unpack_fields
from motion.protocol.v3 import COMMANDS_V3, frames, motion_frame
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
    MotionCommand,
    MotionState,
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

C = CommandV3
REQ, REP = Direction.REQUEST, Direction.REPLY

#: (direction, arbitration id, DATA[0..7] as in the document's example, the message it carries).
GOLDEN: list[tuple[Direction, int, str, Message]] = [
    (REQ, 0x141, "30 01 00 00 00 00 00 00", PidRead(PidIndex.CURRENT_KP)),
    (REP, 0x241, "30 01 00 00 00 00 80 3F", PidParameter(C.READ_PID, PidIndex.CURRENT_KP, 1.0)),
    (REQ, 0x141, "31 01 00 00 00 00 C0 3F", PidParameter(C.WRITE_PID_RAM, PidIndex.CURRENT_KP, 1.5)),
    (REP, 0x241, "31 01 00 00 00 00 C0 3F", PidParameter(C.WRITE_PID_RAM, PidIndex.CURRENT_KP, 1.5)),
    (REQ, 0x141, "32 01 00 00 00 00 C0 3F", PidParameter(C.WRITE_PID_ROM, PidIndex.CURRENT_KP, 1.5)),
    (REQ, 0x141, "42 00 00 00 00 00 00 00", AccelerationRead(AccelerationIndex.POSITION_ACCELERATION)),
    (
        REP,
        0x241,
        "42 00 00 00 10 27 00 00",
        PlanningAcceleration(C.READ_ACCELERATION, AccelerationIndex.POSITION_ACCELERATION, 10000),
    ),
    (
        REP,
        0x241,
        "42 01 00 00 10 27 00 00",
        PlanningAcceleration(C.READ_ACCELERATION, AccelerationIndex.POSITION_DECELERATION, 10000),
    ),
    *[
        (d, base, f"43 0{i} 00 00 10 27 00 00", PlanningAcceleration(C.WRITE_ACCELERATION, AccelerationIndex(i), 10000))
        for i in range(4)
        for d, base in ((REQ, 0x141), (REP, 0x241))
    ],
    (REQ, 0x141, "60 00 00 00 00 00 00 00", BareV3(C.READ_MULTI_TURN_ENCODER)),
    (REP, 0x241, "60 00 00 00 10 27 00 00", MultiTurnEncoder(C.READ_MULTI_TURN_ENCODER, 10000)),
    (REP, 0x241, "61 00 00 00 10 27 00 00", MultiTurnEncoder(C.READ_MULTI_TURN_ENCODER_RAW, 10000)),
    (REP, 0x241, "62 00 00 00 10 27 00 00", MultiTurnEncoder(C.READ_MULTI_TURN_ENCODER_OFFSET, 10000)),
    (REQ, 0x141, "63 00 00 00 10 27 00 00", MultiTurnEncoder(C.WRITE_ENCODER_ZERO, 10000)),
    (REP, 0x241, "63 00 00 00 10 27 00 00", MultiTurnEncoder(C.WRITE_ENCODER_ZERO, 10000)),
    (REQ, 0x141, "64 00 00 00 00 00 00 00", BareV3(C.WRITE_CURRENT_AS_ZERO)),
    (REP, 0x241, "64 00 00 00 10 27 00 00", MultiTurnEncoder(C.WRITE_CURRENT_AS_ZERO, 10000)),
    (REP, 0x241, "90 00 33 08 BE 2C 8B 24", EncoderReading(2099, 11454, 9355)),
    (REP, 0x241, "92 00 00 00 A0 8C 00 00", MultiTurnAngle(360.0)),
    (REP, 0x241, "94 00 00 00 00 00 10 27", SingleTurnAngle(100.0)),
    (
        REP,
        0x241,
        "9A 32 00 01 E5 01 04 00",
        Status1V3(50, BrakeCommand.RELEASE, 48.5, SystemErrorFlags.LOW_VOLTAGE),
    ),
    (REP, 0x241, "9C 32 64 00 F4 01 2D 00", MotorStateV3(C.READ_STATUS_2, 50, 1.0, 500, 45)),
    (REP, 0x241, "9D 32 C2 0B 10 FA C0 F9", PhaseCurrents(30.1, -15.2, -16.0, 50)),
    (REQ, 0x141, "80 00 00 00 00 00 00 00", BareV3(C.MOTOR_OFF)),
    (REQ, 0x141, "A1 00 00 00 64 00 00 00", TorqueControl(1.0)),
    (REP, 0x241, "A1 32 64 00 F4 01 2D 00", MotorStateV3(C.TORQUE, 50, 1.0, 500, 45)),
    (REQ, 0x141, "A1 00 00 00 9C FF 00 00", TorqueControl(-1.0)),
    (REP, 0x241, "A1 32 9C FF 0C FE D3 FF", MotorStateV3(C.TORQUE, 50, -1.0, -500, -45)),
    (REQ, 0x141, "A2 00 00 00 10 27 00 00", SpeedControl(100.0)),
    (REQ, 0x141, "A2 00 00 00 F0 D8 FF FF", SpeedControl(-100.0)),
    (REP, 0x241, "A2 32 9C FF 0C FE D3 FF", MotorStateV3(C.SPEED, 50, -1.0, -500, -45)),
    (REQ, 0x141, "A4 00 F4 01 A0 8C 00 00", MultiTurnPositionSpeed(360.0, 500.0)),
    (REQ, 0x141, "A4 00 F4 01 60 73 FF FF", MultiTurnPositionSpeed(-360.0, 500.0)),
    (REP, 0x241, "A4 32 64 00 F4 01 2D 00", MotorStateV3(C.MULTI_TURN_POSITION_SPEED, 50, 1.0, 500, 45)),
    (REP, 0x241, "A6 32 64 00 F4 01 E8 03", SingleTurnStateV3(50, 1.0, 500, 1000)),
    (REQ, 0x141, "A8 00 F4 01 A0 8C 00 00", IncrementalPositionSpeed(360.0, 500.0)),
    (REQ, 0x141, "A8 00 F4 01 60 73 FF FF", IncrementalPositionSpeed(-360.0, 500.0)),
    (REP, 0x241, "A8 32 9C FF 0C FE D3 FF", MotorStateV3(C.INCREMENTAL_POSITION_SPEED, 50, -1.0, -500, -45)),
    (REP, 0x241, "70 00 00 00 00 00 00 03", RunModeReply(RunMode.POSITION_LOOP)),
    (REQ, 0x141, "76 00 00 00 00 00 00 00", BareV3(C.RESET)),
    (REQ, 0x141, "77 00 00 00 00 00 00 00", BareV3(C.RELEASE_BRAKE)),
    (REP, 0x241, "78 00 00 00 00 00 00 00", BareV3(C.LOCK_BRAKE)),
    (REP, 0x241, "B1 00 00 00 00 00 00 10", Runtime(268435456)),
    (REP, 0x241, "B2 00 00 00 2E 89 34 01", VersionDate(20220206)),
    (REQ, 0x141, "B3 00 00 00 00 00 00 00", CommunicationTimeout(0)),
    (REQ, 0x141, "B3 00 00 00 E8 03 00 00", CommunicationTimeout(1000)),
    (REQ, 0x141, "B4 00 00 00 00 00 00 01", BaudRate(1)),
    (REP, 0x241, "B5 58 38 53 32 56 31 30", MotorModel("X8S2V10")),
    (REQ, 0x141, "B6 60 01 01 00 00 00 00", ActiveReply(ActiveReplyCommand.READ_MULTI_TURN_ENCODER, 1, 10.0)),
    (REQ, 0x141, "20 01 00 00 00 00 00 00", FunctionControl(FunctionIndex.CLEAR_MULTI_TURN, 0)),
    (REQ, 0x141, "20 02 00 00 01 00 00 00", FunctionControl(FunctionIndex.CAN_ID_FILTER, 1)),
    (REP, 0x241, "20 02 00 00 01 00 00 00", FunctionControl(FunctionIndex.CAN_ID_FILTER, 1)),
    (REQ, 0x300, "79 00 00 00 00 00 00 02", CanIdCommand(ReadWrite.WRITE, 2)),
    (REQ, 0x300, "79 00 01 00 00 00 00 00", CanIdCommand(ReadWrite.READ, 0)),
    (REP, 0x300, "79 00 01 00 00 00 42 02", CanIdReply(ReadWrite.READ, 0x242)),
]


@pytest.mark.parametrize(("direction", "arbitration_id", "data", "message"), GOLDEN)
def test_the_documents_examples_encode_and_decode(
    direction: Direction, arbitration_id: int, data: str, message: Message
) -> None:
    payload = bytes.fromhex(data)
    if direction is REQ:
        frame = frames.encode_can_request(message, 1)
        decoded = frames.decode_can_request(arbitration_id, payload)
        assert decoded.message == message
        assert decoded.motor_id == (None if arbitration_id == frames.CAN_ID_SETTING_ID else 1)
    else:
        frame = frames.encode_can_reply(message, 1)
        motor_id, reply = frames.decode_can_reply(arbitration_id, payload)
        assert reply == message
        assert motor_id == (None if arbitration_id == frames.CAN_ID_SETTING_ID else 1)
    assert (frame.arbitration_id, frame.data) == (arbitration_id, payload)
    assert type(message) is type(frames.decode_payload(payload, direction))


def test_every_command_of_the_document_is_in_the_table() -> None:
    assert set(COMMANDS_V3) == set(CommandV3)
    for code, spec in COMMANDS_V3.items():
        assert spec.layout(WireProtocol.CAN, REQ) is not None, code
    no_reply = {C.RESET, C.BAUD_RATE, C.ACTIVE_REPLY}
    assert {c for c, s in COMMANDS_V3.items() if s.layout(WireProtocol.CAN, REP) is None} == no_reply


def test_a_broadcast_goes_on_0x280_and_each_drive_answers_on_its_own_id() -> None:
    frame = frames.encode_can_broadcast(BareV3(C.MOTOR_OFF))
    assert (frame.arbitration_id, frame.data.hex(" ")) == (0x280, "80 00 00 00 00 00 00 00")
    request = frames.decode_can_request(0x280, bytes.fromhex("60 00 00 00 00 00 00 00"))
    assert request == frames.CanRequestV3(None, BareV3(C.READ_MULTI_TURN_ENCODER))
    replies = {"241": "10 27", "242": "20 4E", "243": "30 75", "244": "40 9C"}
    for arbitration_id, value in replies.items():
        motor_id, reply = frames.decode_can_reply(int(arbitration_id, 16), bytes.fromhex(f"60 00 00 00 {value} 00 00"))
        assert motor_id == int(arbitration_id, 16) - 0x240
        assert isinstance(reply, MultiTurnEncoder) and reply.encoder == 10000 * motor_id
    with pytest.raises(EncodeError, match="one drive"):
        frames.encode_can_broadcast(MotionCommand(0.0, 0.0, 0.0, 0.0, 0.0))


def test_the_motion_frame_of_the_documents_example() -> None:
    command = frames.decode_can_request(0x401, bytes.fromhex("E6 66 82 E0 52 33 3B 55"))
    assert command.motor_id == 1 and isinstance(command.message, MotionCommand)
    m = command.message
    # 16-bit position over 65535 steps (the example divides by 65536 and gets 9.99: docs/protocol.md)
    assert m.position_rad == pytest.approx(0xE666 * 25 / 65535 - 12.5)
    assert (m.velocity_rad_s, m.kp, m.kd, m.torque_nm) == pytest.approx((1.0220, 10.012, 1.0, 10.004), abs=1e-3)
    assert frames.encode_can_request(m, 1).data.hex(" ") == "e6 66 82 e0 52 33 3b 55"
    motor_id, state = frames.decode_can_reply(0x501, bytes.fromhex("01 E6 65 82 EB 55 00 00"))
    assert motor_id == 1 and isinstance(state, MotionState)
    assert (state.velocity_rad_s, state.torque_nm) == pytest.approx((1.0220, 10.004), abs=1e-3)
    assert frames.encode_can_reply(state, 1).data.hex(" ") == "01 e6 65 82 eb 55 00 00"
    with pytest.raises(EncodeError, match=r"kp.*0\.\.500"):
        motion_frame.encode_motion(MotionCommand(0.0, 0.0, 500.5, 0.0, 0.0, motion_frame.V42_RANGES))
    with pytest.raises(DecodeError, match="names drive 2"):
        frames.decode_can_reply(0x501, bytes.fromhex("02 E6 65 82 EB 55 00 00"))


def test_out_of_range_values_are_refused_naming_the_range() -> None:
    with pytest.raises(EncodeError, match=r"acceleration_dps2.*0\.\.60000"):
        frames.encode_payload(
            PlanningAcceleration(C.WRITE_ACCELERATION, AccelerationIndex.SPEED_ACCELERATION, 60001), REQ
        )
    with pytest.raises(EncodeError, match="value"):
        frames.encode_payload(PidParameter(C.WRITE_PID_RAM, PidIndex.SPEED_KP, math.inf), REQ)
    with pytest.raises(EncodeError, match="value"):
        frames.encode_payload(PidParameter(C.WRITE_PID_RAM, PidIndex.SPEED_KP, 1e39), REQ)
    # the document's 0xA6 example sends 36000 in a field whose range it gives as 0..35999 (docs/protocol.md)
    with pytest.raises(EncodeError, match=r"angle_deg.*0\.\.359\.99"):
        frames.encode_payload(SingleTurnPositionSpeed(SpinDirection.CLOCKWISE, 360.0, 500.0), REQ)
    with pytest.raises(DecodeError, match="angle_deg"):
        frames.decode_payload(bytes.fromhex("A6 00 F4 01 A0 8C 00 00"), REQ)
    with pytest.raises(DecodeError, match="not a finite"):
        frames.decode_payload(bytes.fromhex("30 01 00 00 00 00 C0 7F"), REP)  # NaN
    with pytest.raises(EncodeError, match="V3 family"):
        frames.encode_payload(Runtime(5), REQ)
    with pytest.raises(EncodeError, match="motor_id"):
        frames.encode_can_request(BareV3(C.MOTOR_OFF), 33)


def test_rs485_frames_carry_the_can_bytes_under_a_crc16() -> None:
    assert frames.crc16(b"123456789") == 0x4B37  # CRC-16/MODBUS check value
    raw = frames.encode_rs485_request(MultiTurnPositionSpeed(360.0, 500.0), 1)
    assert raw[:11].hex(" ") == "3e 01 08 a4 00 f4 01 a0 8c 00 00"
    assert int.from_bytes(raw[11:], "little") == frames.crc16(raw[:11])
    assert frames.decode_rs485_request(raw) == (1, MultiTurnPositionSpeed(360.0, 500.0))
    broadcast = frames.encode_rs485_request(BareV3(C.MOTOR_OFF), None)
    assert broadcast[:3].hex(" ") == "3e cd 08" and frames.decode_rs485_request(broadcast)[0] is None
    reply = frames.encode_rs485_reply(MotorStateV3(C.READ_STATUS_2, 50, 1.0, 500, 45), 4)
    assert frames.decode_rs485_reply(reply) == (4, MotorStateV3(C.READ_STATUS_2, 50, 1.0, 500, 45))
    set_id = frames.encode_rs485_request(CanIdCommand(ReadWrite.WRITE, 2), 1)
    assert set_id[:11].hex(" ") == "3e cd 08 79 00 00 00 00 00 00 02"
    bad = bytearray(raw)
    bad[5] ^= 1
    with pytest.raises(DecodeError, match="CRC16"):
        frames.decode_rs485_request(bytes(bad))
    with pytest.raises(EncodeError, match="RS485"):
        frames.encode_rs485_request(ActiveReply(ActiveReplyCommand.READ_STATUS_2, 1, 10.0), 1)


_COMMAND_BYTES = st.sampled_from([*sorted(int(c) for c in CommandV3), 0, 51, 158, 255])


def _payloads() -> st.SearchStrategy[bytes]:
    return st.builds(lambda code, rest: bytes((code,)) + rest, _COMMAND_BYTES, st.binary(min_size=7, max_size=7))


@settings(max_examples=1500, deadline=None)
@given(_payloads(), st.sampled_from([REQ, REP]))
@example(bytes.fromhex("30 01 00 00 00 00 80 3F"), REP)
@example(bytes.fromhex("9A 32 00 01 E5 01 FF FF"), REP)
def test_whatever_decodes_encodes_back_and_the_fast_path_agrees(data: bytes, direction: Direction) -> None:
    try:
        message = frames.decode_payload(data, direction)
    except DecodeError:
        return
    again = frames.encode_payload(message, direction)
    assert frames.decode_payload(again, direction) == message
    if direction is REQ:  # reserved bytes are zero in a request that decodes: the bytes themselves come back
        assert again == data
    spec = COMMANDS_V3[CommandV3(data[0])]
    layout = spec.layout(WireProtocol.CAN, direction)
    assert layout is not None
    assert unpack_fields(layout, data, spec.code, first=1, check_reserved=direction is REQ) == message


@settings(max_examples=1500, deadline=None)
@given(st.integers(0, 0x7FF), st.binary(max_size=12))
def test_any_can_frame_raises_only_decode_error(arbitration_id: int, data: bytes) -> None:
    for decode in (frames.decode_can_request, frames.decode_can_reply):
        with contextlib.suppress(DecodeError):
            decode(arbitration_id, data)


@settings(max_examples=800, deadline=None)
@given(st.binary(max_size=16), st.integers(0, 255))
def test_any_rs485_bytes_raise_only_decode_error(data: bytes, address: int) -> None:
    framed = bytes((0x3E, address, 8)) + data[:8].ljust(8, b"\0")
    for raw in (data, framed + frames.crc16(framed).to_bytes(2, "little")):
        for decode in (frames.decode_rs485_request, frames.decode_rs485_reply):
            with contextlib.suppress(DecodeError):
                decode(raw)


@settings(max_examples=500, deadline=None)
@given(st.binary(min_size=8, max_size=8))
def test_the_motion_frame_round_trips_every_bit_pattern(data: bytes) -> None:
    assert motion_frame.encode_motion(motion_frame.decode_motion(data)) == data
    v44 = motion_frame.motion_ranges(motion_frame.V44_FIRST_FIRMWARE, "X6S2V20")
    assert motion_frame.encode_motion(motion_frame.decode_motion(data, v44)) == data


def test_the_motion_frame_ranges_follow_the_drives_firmware_and_model() -> None:
    # issue 31 §6: firmware dated 2026042402 or later (0xB2) packs the motion frame onto V4.4's wider ranges: position
    # ±12.566 rad, kd 0..50, torque ± the model's peak torque (X6 60, X8 129 N·m); kp and speed unchanged
    v42 = motion_frame.motion_ranges(20240528, "X8S2V10")
    assert v42 == motion_frame.V42_RANGES and v42.torque_nm == (-24.0, 24.0)
    x6 = motion_frame.motion_ranges(2026042402, "X6S2V20")
    x8 = motion_frame.motion_ranges(2026050101, "X8S2V10")
    assert x6.torque_nm == (-60.0, 60.0) and x8.torque_nm == (-129.0, 129.0)
    assert x6.position_rad == pytest.approx((-12.566, 12.566), abs=1e-3) and x6.kd == (0.0, 50.0)
    assert (x6.kp, x6.velocity_rad_s) == (v42.kp, v42.velocity_rad_s)
    # the dates as the drives report them (YYYYMMDD) or with a build number (YYYYMMDDNN)
    assert motion_frame.motion_ranges(20260501, "X6S2V20") == x6
    assert motion_frame.motion_ranges(2026042401, "X6S2V20") == v42 == motion_frame.motion_ranges(20260423, "X6")
    with pytest.raises(EncodeError, match="that day's builds differ"):
        motion_frame.motion_ranges(20260424, "X6S2V20")
    # the same 10 N·m asked: on V4.2's ranges the X6 would read the bits as 25 N·m, 2.5 times as much
    asked = MotionCommand(0.0, 0.0, 0.0, 0.0, 10.0, x6)
    as_v42 = motion_frame.decode_motion(motion_frame.encode_motion(asked))
    assert as_v42.torque_nm == pytest.approx(10.0 * 24.0 / 60.0, abs=0.02)
    assert motion_frame.decode_motion(motion_frame.encode_motion(asked), x6).torque_nm == pytest.approx(10.0, abs=0.02)
    with pytest.raises(EncodeError, match=r"torque_nm.*-60\.\.60 \(V4\.4 X6 \(60 N·m\)\)"):
        motion_frame.encode_motion(MotionCommand(0.0, 0.0, 0.0, 0.0, 61.0, x6))
    # unknown: refused, never guessed
    with pytest.raises(EncodeError, match="motor series whose V4.4 torque range is known"):
        motion_frame.motion_ranges(2026042402, "X12S2V10")
    with pytest.raises(EncodeError, match=r"firmware date \(0xB2\)"):
        motion_frame.motion_ranges(None, "X8S2V10")
    with pytest.raises(EncodeError, match="the drive's motion-frame ranges"):
        frames.encode_can_request(MotionCommand(0.0, 0.0, 0.0, 0.0, 1.0), 1)


@given(st.floats(width=32, allow_nan=False, allow_infinity=False))
def test_float32_parameters_round_trip(value: float) -> None:
    message = PidParameter(C.WRITE_PID_ROM, PidIndex.POSITION_KD, value)
    payload = frames.encode_payload(message, REQ)
    assert payload[4:] == struct.pack("<f", value)
    assert frames.decode_payload(payload, REQ) == message
