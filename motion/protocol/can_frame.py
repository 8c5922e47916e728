"""CAN v2.3 framing: messages <-> (arbitration id, 8-byte payload).

Single-motor frames use ID ``0x140 + motor id`` in both directions with the command byte in DATA[0]; the
multi-motor torque frame uses ID 0x280 and carries four int16 currents, each of motors 1..4 answering on its own
ID with a 0xA1-style reply. The direction of a frame cannot be told from its bytes, so there is one decoder per
direction.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Final

from motion.errors import DecodeError
from motion.protocol.compiled import CODECS, FALLBACK_ERRORS, MULTI_TORQUE_DECODE, Encoder, frozen_builder
from motion.protocol.messages import Message, MultiMotorTorque
from motion.protocol.table import (
    CAN_ID_BASE,
    CAN_MULTI_TORQUE_ID,
    CAN_PAYLOAD_BYTES,
    COMMANDS,
    MOTOR_ID_MAX,
    MOTOR_ID_MIN,
    MULTI_TORQUE_LAYOUT,
    Direction,
    WireProtocol,
    check_motor_id,
    command_of,
    layout_for,
    pack_fields,
    spec_and_layout,
    unpack_fields,
)


@dataclass(frozen=True, slots=True)
class CanFrame:
    """A classic CAN data frame with a standard (11-bit) identifier."""

    arbitration_id: int
    data: bytes


@dataclass(frozen=True, slots=True)
class CanRequest:
    """A decoded host request: ``motor_id`` is None for the 0x280 multi-motor frame."""

    motor_id: int | None
    message: Message


_new_frame = frozen_builder(CanFrame)
_new_request = frozen_builder(CanRequest)
_REQUEST_CODEC = CODECS[WireProtocol.CAN, Direction.REQUEST]
_REPLY_CODEC = CODECS[WireProtocol.CAN, Direction.REPLY]
_REQUEST_ENCODER = _REQUEST_CODEC.encoders.get
_REPLY_ENCODER = _REPLY_CODEC.encoders.get
_FIRST_ID: Final = CAN_ID_BASE + MOTOR_ID_MIN
_LAST_ID: Final = CAN_ID_BASE + MOTOR_ID_MAX


def _encode(message: Message, motor_id: int, encoders: Callable[[type[Message]], Encoder | None]) -> CanFrame | None:
    """The fast path (:mod:`motion.protocol.compiled`): the frame, or None to take the checked path, which gives the
    same frame or raises the error."""
    encoder = encoders(message.__class__)
    if encoder is None or motor_id.__class__ is not int or not MOTOR_ID_MIN <= motor_id <= MOTOR_ID_MAX:
        return None
    try:
        data = encoder(message)
    except FALLBACK_ERRORS:
        return None
    if data is None:
        return None
    return _new_frame(CAN_MULTI_TORQUE_ID if message.__class__ is MultiMotorTorque else CAN_ID_BASE + motor_id, data)


def _encode_checked(message: Message, motor_id: int, direction: Direction) -> CanFrame:
    layout = layout_for(message, WireProtocol.CAN, direction)
    data = bytearray(CAN_PAYLOAD_BYTES)
    if isinstance(message, MultiMotorTorque):
        pack_fields(layout, message, data)
        return CanFrame(CAN_MULTI_TORQUE_ID, bytes(data))
    check_motor_id(motor_id)
    command = command_of(message)
    assert command is not None
    data[0] = command
    pack_fields(layout, message, data)
    return CanFrame(CAN_ID_BASE + motor_id, bytes(data))


def encode_request(message: Message, motor_id: int = MOTOR_ID_MIN) -> CanFrame:
    """Build the CAN frame of a host request.

    Args:
        message: the request; a :class:`MultiMotorTorque` goes out on ID 0x280 and ignores ``motor_id``.
        motor_id: drive id 1..32.

    Raises:
        EncodeError: a bad motor id, a value out of range, or a message CAN cannot carry as a request.
    """
    return _encode(message, motor_id, _REQUEST_ENCODER) or _encode_checked(message, motor_id, Direction.REQUEST)


def encode_reply(message: Message, motor_id: int) -> CanFrame:
    """Build the CAN frame of a drive reply (what the emulator sends).

    Raises:
        EncodeError: a bad motor id, a value out of range, or a message CAN cannot carry as a reply.
    """
    return _encode(message, motor_id, _REPLY_ENCODER) or _encode_checked(message, motor_id, Direction.REPLY)


def _check_frame(arbitration_id: int, data: bytes) -> None:
    if len(data) != CAN_PAYLOAD_BYTES:
        raise DecodeError(f"CAN payload must be {CAN_PAYLOAD_BYTES} bytes, got {len(data)}", data)
    if arbitration_id != CAN_MULTI_TORQUE_ID and not (
        CAN_ID_BASE + MOTOR_ID_MIN <= arbitration_id <= CAN_ID_BASE + MOTOR_ID_MAX
    ):
        raise DecodeError(
            f"arbitration id 0x{arbitration_id:X} is neither 0x{CAN_ID_BASE + MOTOR_ID_MIN:X}.."
            f"0x{CAN_ID_BASE + MOTOR_ID_MAX:X} nor 0x{CAN_MULTI_TORQUE_ID:X}",
            data,
        )


def _decode(data: bytes, direction: Direction) -> Message:
    decoder = (_REQUEST_CODEC if direction is Direction.REQUEST else _REPLY_CODEC).decoders[data[0]]
    message = decoder(data) if decoder is not None else None
    return message if message is not None else _decode_checked(data, direction)


def _decode_checked(data: bytes, direction: Direction) -> Message:
    found = spec_and_layout(COMMANDS, data[0], WireProtocol.CAN, direction)
    if found is None:
        raise DecodeError(f"0x{data[0]:02X} is not a CAN v2.3 {direction.value} command", data)
    spec, layout = found
    return unpack_fields(layout, data, spec.code, first=1, check_reserved=direction is Direction.REQUEST)


def decode_request(arbitration_id: int, data: bytes) -> CanRequest:
    """Decode a host request (what the emulator receives).

    Raises:
        DecodeError: wrong length, id outside 0x141..0x160 / 0x280, unknown command, bad field, set reserved byte.
    """
    data = bytes(data)
    _check_frame(arbitration_id, data)
    if arbitration_id == CAN_MULTI_TORQUE_ID:
        multi = MULTI_TORQUE_DECODE.decode(data) if MULTI_TORQUE_DECODE is not None else None
        if multi is None:
            multi = unpack_fields(MULTI_TORQUE_LAYOUT, data, None, first=0, check_reserved=True)
        return _new_request(None, multi)
    return CanRequest(arbitration_id - CAN_ID_BASE, _decode(data, Direction.REQUEST))


def decode_reply(arbitration_id: int, data: bytes) -> tuple[int, Message]:
    """Decode a drive reply into ``(motor_id, message)``.

    Raises:
        DecodeError: wrong length, id outside 0x141..0x160, unknown command or bad field.
    """
    if data.__class__ is not bytes:
        data = bytes(data)
    if len(data) == CAN_PAYLOAD_BYTES and arbitration_id.__class__ is int and _FIRST_ID <= arbitration_id <= _LAST_ID:
        decoder = _REPLY_CODEC.decoders[data[0]]
        if decoder is not None and (message := decoder(data)) is not None:
            return arbitration_id - CAN_ID_BASE, message
    _check_frame(arbitration_id, data)
    if arbitration_id == CAN_MULTI_TORQUE_ID:
        raise DecodeError("ID 0x280 carries requests only; drives reply on 0x140 + id", data)
    return arbitration_id - CAN_ID_BASE, _decode_checked(data, Direction.REPLY)
