"""V3 family framing: messages <-> CAN frames and RS485 frames, and the MIT-style motion frame.

CAN (V4.2 document, section 1.1): requests on ``0x140 + id``, replies on ``0x240 + id``; ``0x280`` carries one
single-motor request to every drive at once (each answers on its own reply id); 0x79 (the id setting) travels on
``0x300`` both ways; the motion frame goes on ``0x400 + id`` and is answered on ``0x500 + id``.

RS485 (section 1.2): ``3E id 08 DATA[0..7] crc16``: the data field is the CAN frame's 8 bytes; id ``0xCD`` addresses
every drive. The CRC is CRC-16/MODBUS (reflected polynomial 0xA001, initial 0xFFFF) over every byte from the 0x3E
head to the last data byte, low byte first (docs/protocol.md says how that was decided).

Encoding takes the compiled fast path of :mod:`motion.protocol.compiled` built from the V3 table, else the checked
path of :mod:`motion.protocol.table`, which gives the same bytes or the error. Decoding raises only
:class:`~motion.errors.DecodeError`, whatever the bytes.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Final

from motion.errors import DecodeError, EncodeError
from motion.protocol.can_frame import CanFrame
from motion.protocol.compiled import FALLBACK_ERRORS, build_codec
from motion.protocol.messages import Message
from motion.protocol.rs485_frame import StreamBuffer, Verdict
from motion.protocol.table import (
    CAN_PAYLOAD_BYTES,
    MOTOR_ID_MAX,
    MOTOR_ID_MIN,
    Direction,
    Layout,
    WireProtocol,
    check_motor_id,
    pack_fields,
    spec_and_layout,
    unpack_fields,
)
from motion.protocol.v3.messages import CanIdCommand, CanIdReply, MotionCommand, MotionState
from motion.protocol.v3.motion_frame import decode_motion, decode_motion_state, encode_motion, encode_motion_state
from motion.protocol.v3.table import COMMANDS_V3, RS485_COMMANDS

#: Single-motor requests go on ``CAN_REQUEST_BASE + id``.
CAN_REQUEST_BASE: Final = 0x140
#: Drives reply on ``CAN_REPLY_BASE + id``.
CAN_REPLY_BASE: Final = 0x240
#: One single-motor request to every drive on the bus.
CAN_BROADCAST_ID: Final = 0x280
#: The 0x79 id setting, both ways.
CAN_ID_SETTING_ID: Final = 0x300
#: The motion frame goes on ``MOTION_REQUEST_BASE + id`` ...
MOTION_REQUEST_BASE: Final = 0x400
#: ... and is answered on ``MOTION_REPLY_BASE + id``.
MOTION_REPLY_BASE: Final = 0x500
#: RS485: the id that addresses every drive.
RS485_BROADCAST_ID: Final = 0xCD
RS485_HEAD: Final = 0x3E
#: head, id, length, 8 data bytes, CRC low, CRC high.
RS485_FRAME_BYTES: Final = 13

_CODECS = {d: build_codec(WireProtocol.CAN, d, COMMANDS_V3) for d in Direction}


# ------------------------------------------------------------------------------------------------ payloads


def _layout(message: Message, direction: Direction) -> Layout:
    code: object = getattr(message, "command", None)
    found = spec_and_layout(COMMANDS_V3, code, WireProtocol.CAN, direction) if isinstance(code, int) else None
    layout = found[1] if found is not None else None
    if layout is None or type(message) is not layout.cls:
        what = f"0x{int(code):02X}" if isinstance(code, int) else type(message).__name__
        raise EncodeError("message", f"a {direction.value} of the V3 family's commands", what)
    return layout


def encode_payload(message: Message, direction: Direction) -> bytes:
    """The 8 bytes (DATA[0..7]) of a message of the V3 family, the same on CAN and RS485.

    Raises:
        EncodeError: a value out of range or of the wrong type, or a message the family has no such frame for.
    """
    encoder = _CODECS[direction].encoders.get(message.__class__)
    if encoder is not None:
        try:
            data = encoder(message)
        except FALLBACK_ERRORS:
            data = None
        if data is not None:
            return data
    layout = _layout(message, direction)
    data_out = bytearray(CAN_PAYLOAD_BYTES)
    data_out[0] = int(message.command)  # type: ignore[attr-defined]  # every V3 payload message has one
    pack_fields(layout, message, data_out)
    return bytes(data_out)


def decode_payload(data: bytes, direction: Direction) -> Message:
    """The message of 8 payload bytes.

    Raises:
        DecodeError: not 8 bytes, an unknown command, a field out of range, a set reserved byte (requests).
    """
    data = bytes(data)
    if len(data) != CAN_PAYLOAD_BYTES:
        raise DecodeError(f"a V3 payload is {CAN_PAYLOAD_BYTES} bytes, got {len(data)}", data)
    decoder = _CODECS[direction].decoders[data[0]]
    message = decoder(data) if decoder is not None else None
    if message is not None:
        return message
    found = spec_and_layout(COMMANDS_V3, data[0], WireProtocol.CAN, direction)
    if found is None:
        raise DecodeError(f"0x{data[0]:02X} is not a V3 {direction.value} command", data)
    spec, layout = found
    return unpack_fields(layout, data, spec.code, first=1, check_reserved=direction is Direction.REQUEST)


# ------------------------------------------------------------------------------------------------ CAN


@dataclass(frozen=True, slots=True)
class CanRequestV3:
    """A decoded V3 request: ``motor_id`` is None for one sent to every drive (0x280, 0x300)."""

    motor_id: int | None
    message: Message


def encode_can_request(message: Message, motor_id: int) -> CanFrame:
    """The CAN frame of a request to drive ``motor_id`` (0x79 goes on 0x300 to every drive, whatever the id).

    Raises:
        EncodeError: a bad motor id, a value out of range, a message the family has no request for.
    """
    check_motor_id(motor_id)
    if isinstance(message, MotionCommand):
        return CanFrame(MOTION_REQUEST_BASE + motor_id, encode_motion(message))
    data = encode_payload(message, Direction.REQUEST)
    return CanFrame(CAN_ID_SETTING_ID if isinstance(message, CanIdCommand) else CAN_REQUEST_BASE + motor_id, data)


def encode_can_broadcast(message: Message) -> CanFrame:
    """One request to every drive on the bus (0x280; 0x79 on 0x300).

    Raises:
        EncodeError: as :func:`encode_can_request`; the motion frame has no broadcast.
    """
    if isinstance(message, MotionCommand):
        raise EncodeError("message", "a single-motor request (the motion frame is addressed to one drive)", "0x400")
    data = encode_payload(message, Direction.REQUEST)
    return CanFrame(CAN_ID_SETTING_ID if isinstance(message, CanIdCommand) else CAN_BROADCAST_ID, data)


def encode_can_reply(message: Message, motor_id: int) -> CanFrame:
    """The CAN frame a drive sends (what the emulator sends).

    Raises:
        EncodeError: a bad motor id, a value out of range, a message the family has no reply for.
    """
    check_motor_id(motor_id)
    if isinstance(message, MotionState):
        if message.motor_id != motor_id:
            raise EncodeError("motor_id", f"{motor_id} (the drive that replies)", message.motor_id)
        return CanFrame(MOTION_REPLY_BASE + motor_id, encode_motion_state(message))
    data = encode_payload(message, Direction.REPLY)
    return CanFrame(CAN_ID_SETTING_ID if isinstance(message, CanIdReply) else CAN_REPLY_BASE + motor_id, data)


def _single_id(arbitration_id: int, base: int) -> int | None:
    motor_id = arbitration_id - base
    return motor_id if MOTOR_ID_MIN <= motor_id <= MOTOR_ID_MAX else None


def decode_can_request(arbitration_id: int, data: bytes) -> CanRequestV3:
    """Decode a host's frame (what the emulator receives).

    Raises:
        DecodeError: an id that carries no V3 request, wrong length, unknown command, bad field, set reserved byte.
    """
    if arbitration_id in (CAN_BROADCAST_ID, CAN_ID_SETTING_ID):
        message = decode_payload(data, Direction.REQUEST)
        if (arbitration_id == CAN_ID_SETTING_ID) is not isinstance(message, CanIdCommand):
            raise DecodeError(f"0x{arbitration_id:X} does not carry 0x{bytes(data)[0]:02X}", bytes(data))
        return CanRequestV3(None, message)
    motor_id = _single_id(arbitration_id, CAN_REQUEST_BASE)
    if motor_id is not None:
        message = decode_payload(data, Direction.REQUEST)
        if isinstance(message, CanIdCommand):
            raise DecodeError("0x79 goes on 0x300, not on a drive's id", bytes(data))
        return CanRequestV3(motor_id, message)
    motor_id = _single_id(arbitration_id, MOTION_REQUEST_BASE)
    if motor_id is not None:
        return CanRequestV3(motor_id, decode_motion(data))
    raise DecodeError(f"arbitration id 0x{arbitration_id:X} carries no V3 request", bytes(data))


def decode_can_reply(arbitration_id: int, data: bytes) -> tuple[int | None, Message]:
    """Decode a drive's frame into ``(motor_id, message)`` (motor id None for a 0x79 reply on 0x300).

    Raises:
        DecodeError: an id that carries no V3 reply, wrong length, unknown command or bad field.
    """
    motor_id = _single_id(arbitration_id, CAN_REPLY_BASE)
    if motor_id is not None:
        return motor_id, decode_payload(data, Direction.REPLY)
    if arbitration_id == CAN_ID_SETTING_ID:
        message = decode_payload(data, Direction.REPLY)
        if not isinstance(message, CanIdReply):
            raise DecodeError(f"0x300 carries 0x79 only, got 0x{bytes(data)[0]:02X}", bytes(data))
        return None, message
    motor_id = _single_id(arbitration_id, MOTION_REPLY_BASE)
    if motor_id is not None:
        state = decode_motion_state(data)
        if state.motor_id != motor_id:
            raise DecodeError(f"motion reply on 0x{arbitration_id:X} names drive {state.motor_id}", bytes(data))
        return motor_id, state
    raise DecodeError(f"arbitration id 0x{arbitration_id:X} carries no V3 reply", bytes(data))


# ------------------------------------------------------------------------------------------------ RS485


def crc16(data: bytes | bytearray | memoryview) -> int:
    """CRC-16/MODBUS: reflected polynomial 0xA001, initial value 0xFFFF, no final XOR."""
    crc = 0xFFFF
    for byte in data:
        crc ^= byte
        for _ in range(8):
            crc = (crc >> 1) ^ 0xA001 if crc & 1 else crc >> 1
    return crc


def _rs485_frame(address: int, payload: bytes) -> bytes:
    body = bytes((RS485_HEAD, address, CAN_PAYLOAD_BYTES)) + payload
    return body + crc16(body).to_bytes(2, "little")


def _rs485_payload(message: Message, direction: Direction) -> bytes:
    if isinstance(message, (MotionCommand, MotionState)) or getattr(message, "command", None) not in RS485_COMMANDS:
        raise EncodeError("message", "a command of the V3 RS485 protocol (not 0xB6, not the motion frame)", message)
    return encode_payload(message, direction)


def encode_rs485_request(message: Message, motor_id: int | None) -> bytes:
    """The RS485 frame of a request to drive ``motor_id`` (None: every drive, id 0xCD; 0x79 always goes to 0xCD).

    Raises:
        EncodeError: a bad motor id, a value out of range, a command RS485 lacks.
    """
    payload = _rs485_payload(message, Direction.REQUEST)
    broadcast = motor_id is None or isinstance(message, CanIdCommand)
    return _rs485_frame(RS485_BROADCAST_ID if broadcast else check_motor_id(motor_id), payload)  # type: ignore[arg-type]


def encode_rs485_reply(message: Message, motor_id: int) -> bytes:
    """The RS485 frame a drive sends (0x79 replies carry 0xCD, as the document's example shows).

    Raises:
        EncodeError: a bad motor id, a value out of range, a command RS485 lacks.
    """
    payload = _rs485_payload(message, Direction.REPLY)
    return _rs485_frame(RS485_BROADCAST_ID if isinstance(message, CanIdReply) else check_motor_id(motor_id), payload)


def _header_ok(head: bytes | bytearray) -> bool:
    """Whether the first 3 bytes are ``3E id 08`` with an id 1..32 or 0xCD."""
    address = head[1]
    return (
        head[0] == RS485_HEAD
        and head[2] == CAN_PAYLOAD_BYTES
        and (address == RS485_BROADCAST_ID or MOTOR_ID_MIN <= address <= MOTOR_ID_MAX)
    )


def _crc_ok(frame: bytes | bytearray) -> bool:
    """Whether a 13-byte frame's CRC (low byte first) matches its other bytes."""
    return crc16(frame[:-2]) == int.from_bytes(frame[-2:], "little")


def _rs485_split(raw: bytes) -> tuple[int, bytes]:
    raw = bytes(raw)
    if len(raw) != RS485_FRAME_BYTES:
        raise DecodeError(f"a V3 RS485 frame is {RS485_FRAME_BYTES} bytes, got {len(raw)}", raw)
    if not _header_ok(raw):
        raise DecodeError(f"expected 3E <id 1..32 or CD> 08 at the start, got {raw[:3].hex(' ')}", raw)
    if not _crc_ok(raw):
        raise DecodeError(f"CRC16 0x{int.from_bytes(raw[-2:], 'little'):04X} != 0x{crc16(raw[:-2]):04X}", raw)
    return raw[1], raw[3:-2]


def decode_rs485_request(raw: bytes) -> tuple[int | None, Message]:
    """``(motor id or None for 0xCD, message)`` of a host's frame.

    Raises:
        DecodeError: wrong length, head or CRC, a bad id, an unknown command, a bad field, a set reserved byte.
    """
    address, payload = _rs485_split(raw)
    message = decode_payload(payload, Direction.REQUEST)
    if getattr(message, "command", None) not in RS485_COMMANDS:
        raise DecodeError("0xB6 active replies are CAN only", bytes(raw))
    return (None if address == RS485_BROADCAST_ID else address), message


def decode_rs485_reply(raw: bytes) -> tuple[int | None, Message]:
    """``(motor id, message)`` of a drive's frame (id None for a 0x79 reply on 0xCD).

    Raises:
        DecodeError: wrong length, head or CRC, a bad id, an unknown command or a bad field.
    """
    address, payload = _rs485_split(raw)
    return (None if address == RS485_BROADCAST_ID else address), decode_payload(payload, Direction.REPLY)


class Rs485ParserV3(StreamBuffer):
    """Finds V3 RS485 frames (``3E id 08 DATA[0..7] crc16``, 13 bytes) in a byte stream: feed it whatever the port
    returned, take frames out (as their 13 bytes, head to CRC, checked). Resynchronises after garbage, truncated frames
    and bad CRCs one byte at a time, and counts what it dropped, under the names of the older family's parser
    (:class:`motion.protocol.Rs485Parser`) so that a transport reads either alike.

    Attributes:
        dropped_bytes: bytes discarded while resynchronising.
        bad_header_checksums: always 0 (a V3 frame has no header checksum; its CRC covers the header).
        bad_data_checksums: candidates whose CRC failed.
        bad_lengths: candidates whose length byte is not 8 or whose id is neither 1..32 nor 0xCD.
        truncated: incomplete candidates given up on by ``next_frame(flush=True)``.
        frames: valid frames returned.
    """

    def next_frame(self, *, flush: bool = False) -> bytes | None:
        """The next valid frame's bytes, or None if the buffer holds no complete one yet.

        Args:
            flush: no more bytes are coming for now: an incomplete candidate is truncated, its first byte dropped.
        """
        return self._next_raw(RS485_HEAD, flush)

    def next_reply(self, *, flush: bool = False) -> tuple[int | None, Message | None] | None:
        """See :meth:`motion.protocol.rs485_frame.StreamBuffer.next_reply` (a 0x79 reply on 0xCD names no drive)."""
        raw = self.next_frame(flush=flush)
        if raw is None:
            return None
        try:
            return decode_rs485_reply(raw)
        except DecodeError:
            return (None if raw[1] == RS485_BROADCAST_ID else raw[1]), None  # (the parser checked the id: 1..32)

    def _judge(self, buf: bytearray) -> int | str | Verdict:
        if len(buf) >= 3 and not _header_ok(buf):
            return "bad_lengths"
        if len(buf) < RS485_FRAME_BYTES:
            return Verdict.SHORT
        if not _crc_ok(buf[:RS485_FRAME_BYTES]):
            return "bad_data_checksums"
        return RS485_FRAME_BYTES
