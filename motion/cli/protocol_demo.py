"""``rmd-motion demo --protocol``: one control cycle's frames encoded and decoded on both transports."""

from __future__ import annotations

from motion.protocol import (
    Bare,
    Command,
    ErrorFlags,
    Message,
    MotorState,
    MultiMotorTorque,
    MultiTurnPositionSpeed,
    Rs485Parser,
    Status1,
    can_frame,
    rs485_frame,
)


def _show(label: str, wire: str, motor_id: int | None, message: Message) -> None:
    target = f"motor {motor_id}" if motor_id is not None else "motors 1-4"
    print(f"  {label:<6} {wire:<58} -> {target}: {message}")


def protocol_demo() -> int:
    """Encode one control cycle's frames on both transports and print them decoded again."""
    requests: list[tuple[int, Message]] = [
        (1, MultiTurnPositionSpeed(angle_deg=90.0, max_speed_dps=360.0)),
        (2, MultiTurnPositionSpeed(angle_deg=-45.5, max_speed_dps=120.0)),
        (3, Bare(Command.READ_STATUS_1)),
    ]
    replies: list[tuple[int, Message]] = [
        (1, MotorState(Command.MULTI_TURN_POSITION_SPEED, 32, 1.6, 355, 4096)),
        (2, MotorState(Command.MULTI_TURN_POSITION_SPEED, 31, -0.8, -118, 12000)),
        (3, Status1(Command.READ_STATUS_1, 36, 24.1, ErrorFlags.NONE)),
    ]
    print("CAN v2.3 (ID: payload)")
    for motor_id, message in requests:
        frame = can_frame.encode_request(message, motor_id)
        decoded = can_frame.decode_request(frame.arbitration_id, frame.data)
        _show("host", f"{frame.arbitration_id:03X}: {frame.data.hex(' ')}", decoded.motor_id, decoded.message)
    for motor_id, message in replies:
        frame = can_frame.encode_reply(message, motor_id)
        rid, reply = can_frame.decode_reply(frame.arbitration_id, frame.data)
        _show("drive", f"{frame.arbitration_id:03X}: {frame.data.hex(' ')}", rid, reply)
    multi = can_frame.encode_request(MultiMotorTorque(1.6, -0.8, 0.0, 0.0))
    decoded = can_frame.decode_request(multi.arbitration_id, multi.data)
    _show("host", f"{multi.arbitration_id:03X}: {multi.data.hex(' ')}", decoded.motor_id, decoded.message)

    print("RS485 v1.62 (frames found in one byte stream with garbage between them)")
    parser = Rs485Parser()
    stream = b"\x00\xff".join(rs485_frame.encode_request(m, i) for i, m in requests)
    parser.feed(stream)
    while (frame485 := parser.next_frame()) is not None:
        raw = frame485.to_bytes()
        motor_id, message = rs485_frame.decode_request(raw)
        _show("host", raw.hex(" "), motor_id, message)
    for motor_id, message in replies:
        raw = rs485_frame.encode_reply(message, motor_id)
        rid, reply = rs485_frame.decode_reply(raw)
        _show("drive", raw.hex(" "), rid, reply)
    print(f"parser: {parser.frames} frames, {parser.dropped_bytes} garbage bytes dropped")
    return 0
