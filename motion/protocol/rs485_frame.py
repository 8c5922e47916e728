"""RS485 v1.62 framing: the 0x3E envelope, its two checksums, and an incremental stream parser.

A frame is ``3E cmd id len hsum`` followed, when ``len > 0``, by ``len`` data bytes and their checksum.
Both checksums are the sum of the covered bytes modulo 256. The parser is sans-I/O: feed it whatever the port
returned, take frames out; it resynchronises after garbage, truncated frames and bad checksums and counts what it
dropped.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import Enum
from typing import Final

from motion.errors import DecodeError
from motion.protocol.compiled import CODECS, FALLBACK_ERRORS
from motion.protocol.messages import Message
from motion.protocol.table import (
    COMMANDS,
    MOTOR_ID_MAX,
    MOTOR_ID_MIN,
    RS485_MAX_DATA_BYTES,
    Direction,
    WireProtocol,
    check_motor_id,
    command_of,
    layout_for,
    pack_fields,
    spec_and_layout,
    unpack_fields,
)

#: First byte of every RS485 frame.
HEAD: Final = 0x3E
#: Bytes of the header: head, command, id, data length, header checksum.
HEADER_BYTES: Final = 5
#: Bits on the wire per RS485 byte (8N1: start + 8 data + stop).
RS485_BITS_PER_BYTE: Final = 10


def rs485_frame_time_s(n_bytes: int, baud: int) -> float:
    """Time ``n_bytes`` take on an RS485 line at ``baud`` bit/s (8N1), s."""
    return n_bytes * RS485_BITS_PER_BYTE / baud


def checksum(data: bytes | bytearray | memoryview) -> int:
    """Sum of the bytes modulo 256 (both the header and the data checksum)."""
    return sum(data) & 0xFF


def frame_size(data_length: int) -> int:
    """Total bytes of a frame carrying ``data_length`` data bytes."""
    return HEADER_BYTES + (data_length + 1 if data_length else 0)


@dataclass(frozen=True, slots=True)
class Rs485Frame:
    """A checksum-valid RS485 frame, not yet interpreted: command byte, motor id and data section."""

    command: int
    motor_id: int
    data: bytes

    def to_bytes(self) -> bytes:
        """The frame on the wire, with both checksums."""
        header = bytes((HEAD, self.command, self.motor_id, len(self.data)))
        out = header + bytes((checksum(header),))
        return out + self.data + bytes((checksum(self.data),)) if self.data else out


def _encode(message: Message, motor_id: int, direction: Direction) -> bytes:
    # Fast path (motion.protocol.compiled); anything unusual takes the checked path below (same bytes or the error).
    encoder = CODECS[WireProtocol.RS485, direction].encoders.get(message.__class__)
    if encoder is not None and motor_id.__class__ is int and MOTOR_ID_MIN <= motor_id <= MOTOR_ID_MAX:
        try:
            payload = encoder(message)
        except FALLBACK_ERRORS:
            payload = None
        if payload is not None:
            command = message.command  # type: ignore[attr-defined]  # every RS485 message class has one
            return Rs485Frame(command, motor_id, payload).to_bytes()
    layout = layout_for(message, WireProtocol.RS485, direction)
    check_motor_id(motor_id)
    command = command_of(message)
    assert command is not None
    data = bytearray(layout.length)
    pack_fields(layout, message, data)
    return Rs485Frame(command, motor_id, bytes(data)).to_bytes()


def encode_request(message: Message, motor_id: int) -> bytes:
    """Build the RS485 frame of a host request.

    Raises:
        EncodeError: a bad motor id, a value out of range, or a message RS485 cannot carry as a request.
    """
    return _encode(message, motor_id, Direction.REQUEST)


def encode_reply(message: Message, motor_id: int) -> bytes:
    """Build the RS485 frame of a drive reply (what the emulator sends).

    Raises:
        EncodeError: a bad motor id, a value out of range, or a message RS485 cannot carry as a reply.
    """
    return _encode(message, motor_id, Direction.REPLY)


def split_frame(raw: bytes) -> Rs485Frame:
    """Check the envelope of one complete frame (head, length, both checksums, motor id).

    Raises:
        DecodeError: anything wrong with the envelope.
    """
    raw = bytes(raw)
    if len(raw) < HEADER_BYTES:
        raise DecodeError(f"RS485 frame shorter than its {HEADER_BYTES}-byte header", raw)
    if raw[0] != HEAD:
        raise DecodeError(f"RS485 frame must start with 0x{HEAD:02X}", raw)
    if raw[4] != checksum(raw[:4]):
        raise DecodeError(f"header checksum 0x{raw[4]:02X} != 0x{checksum(raw[:4]):02X}", raw)
    length = raw[3]
    if length > RS485_MAX_DATA_BYTES:
        raise DecodeError(f"data length {length} exceeds {RS485_MAX_DATA_BYTES}", raw)
    if len(raw) != frame_size(length):
        raise DecodeError(f"frame of data length {length} must be {frame_size(length)} bytes, got {len(raw)}", raw)
    data = raw[HEADER_BYTES : HEADER_BYTES + length]
    if length and raw[-1] != checksum(data):
        raise DecodeError(f"data checksum 0x{raw[-1]:02X} != 0x{checksum(data):02X}", raw)
    if not MOTOR_ID_MIN <= raw[2] <= MOTOR_ID_MAX:
        raise DecodeError(f"motor id {raw[2]} is outside {MOTOR_ID_MIN}..{MOTOR_ID_MAX}", raw)
    return Rs485Frame(raw[1], raw[2], data)


def decode_frame(frame: Rs485Frame, direction: Direction) -> Message:
    """Interpret a checksum-valid frame as a request or a reply.

    Raises:
        DecodeError: unknown command, wrong data length for the command, bad field, set reserved byte.
    """
    code = frame.command
    compiled = CODECS[WireProtocol.RS485, direction].layouts[code] if 0 <= code <= 0xFF else None
    if compiled is not None and len(frame.data) == compiled.size:
        message = compiled.decode(frame.data)
        if message is not None:
            return message
    found = spec_and_layout(COMMANDS, code, WireProtocol.RS485, direction)
    if found is None:
        raise DecodeError(f"0x{code:02X} is not an RS485 v1.62 {direction.value} command", frame.to_bytes())
    spec, layout = found
    if len(frame.data) != layout.length:
        raise DecodeError(
            f"0x{code:02X} {direction.value} carries {layout.length} data bytes, got {len(frame.data)}",
            frame.to_bytes(),
        )
    try:
        return unpack_fields(layout, frame.data, spec.code, first=0, check_reserved=direction is Direction.REQUEST)
    except DecodeError as exc:
        raise DecodeError(exc.reason, frame.to_bytes()) from None


def decode_request(raw: bytes) -> tuple[int, Message]:
    """Decode one complete host request frame into ``(motor_id, message)``.

    Raises:
        DecodeError: on any invalid byte string.
    """
    frame = split_frame(raw)
    return frame.motor_id, decode_frame(frame, Direction.REQUEST)


def decode_reply(raw: bytes) -> tuple[int, Message]:
    """Decode one complete drive reply frame into ``(motor_id, message)``.

    Raises:
        DecodeError: on any invalid byte string.
    """
    frame = split_frame(raw)
    return frame.motor_id, decode_frame(frame, Direction.REPLY)


class StreamBuffer:
    """The buffer and the counters of an incremental frame parser (this family's :class:`Rs485Parser` and the V3
    family's): what the parsers share; each finds its own frames in ``_buffer``.

    Attributes:
        dropped_bytes: bytes discarded while resynchronising.
        bad_header_checksums: candidate headers whose checksum failed.
        bad_data_checksums: candidate frames whose data checksum failed.
        bad_lengths: candidates with an impossible length or motor id.
        truncated: incomplete candidates given up on by ``next_frame(flush=True)``.
        frames: valid frames returned.
    """

    def __init__(self) -> None:
        self._buffer = bytearray()
        self.dropped_bytes = 0
        self.bad_header_checksums = 0
        self.bad_data_checksums = 0
        self.bad_lengths = 0
        self.truncated = 0
        self.frames = 0

    @property
    def pending(self) -> int:
        """Bytes buffered and not yet returned or dropped (a frame in progress)."""
        return len(self._buffer)

    def feed(self, chunk: bytes | bytearray) -> None:
        """Append received bytes."""
        self._buffer += chunk

    def discard(self) -> int:
        """Drop everything buffered (e.g. at the end of a half-duplex transaction); returns the count."""
        n = len(self._buffer)
        self.dropped_bytes += n
        self._buffer.clear()
        return n

    def _drop(self, n: int) -> None:
        del self._buffer[:n]
        self.dropped_bytes += n

    def _next_raw(self, head: int, flush: bool) -> bytes | None:
        """The next valid frame's bytes, or None when the buffer holds no complete one yet: the resynchronising loop
        both parsers share. Bytes before ``head`` are dropped; each candidate is judged by :meth:`_judge`, and a bad
        one (or, with ``flush``, an incomplete one) loses its first byte, so a frame behind it is still found."""
        buf = self._buffer
        while True:
            start = buf.find(head)
            if start < 0:
                self._drop(len(buf))
                return None
            if start:
                self._drop(start)
            verdict = self._judge(buf)
            if verdict is Verdict.WAIT:
                return None
            if verdict is Verdict.SHORT:
                if not flush:
                    return None
                self.truncated += 1
                self._drop(1)
                continue
            if isinstance(verdict, str):
                setattr(self, verdict, getattr(self, verdict) + 1)
                self._drop(1)
                continue
            assert isinstance(verdict, int)
            frame = bytes(buf[:verdict])
            del buf[:verdict]
            self.frames += 1
            return frame

    def _judge(self, buf: bytearray) -> int | str | Verdict:
        """A candidate at the buffer's start: its size when it is a valid frame, the counter a bad one counts in, or
        a :class:`Verdict`."""
        raise NotImplementedError

    def next_bytes(self, *, flush: bool = False) -> bytes | None:
        """The next valid frame's bytes, head to checksum, or None when the buffer holds no complete one yet
        (``flush``: see the parser's ``next_frame``)."""
        return self._next_raw(HEAD, flush)

    def next_reply(self, *, flush: bool = False) -> tuple[int | None, Message | None] | None:
        """The next valid frame of a drive's reply as ``(the drive it names, its message)``, or None when the buffer
        holds no complete frame yet (``flush``: see the parser's ``next_frame``). The drive is None for a frame that
        names no single drive; the message None for a frame whose checksums held but whose content did not decode."""
        raise NotImplementedError


class Verdict(Enum):
    """What :meth:`StreamBuffer._judge` says of a candidate that is neither a frame nor a bad one."""

    WAIT = "too short to judge"
    SHORT = "not complete yet: wait for the rest or, flushing, give it up"


class Rs485Parser(StreamBuffer):
    """Incremental frame parser for a byte stream; never raises on input.

    ``feed(chunk)`` appends bytes; ``next_frame()`` returns the next checksum-valid :class:`Rs485Frame` or None
    when more bytes are needed. Bytes that cannot start a valid frame are dropped one at a time, so a frame that
    follows garbage, a truncated frame or a corrupted frame is still found.

    Attributes:
        dropped_bytes: bytes discarded while resynchronising.
        bad_header_checksums: candidate headers whose checksum failed.
        bad_data_checksums: candidate frames whose data checksum failed.
        bad_lengths: candidate headers with a data length above 60 or a motor id outside 1..32.
        truncated: incomplete candidates given up on by ``next_frame(flush=True)``.
        frames: valid frames returned.
    """

    def next_frame(self, *, flush: bool = False) -> Rs485Frame | None:
        """Return the next valid frame, or None if the buffer holds no complete one yet.

        Args:
            flush: no more bytes are coming for now (a deadline or an inter-frame gap passed): treat an
                incomplete candidate as truncated, drop its first byte and look for a complete frame behind it.
        """
        raw = self._next_raw(HEAD, flush)
        if raw is None:
            return None
        return Rs485Frame(raw[1], raw[2], raw[HEADER_BYTES : HEADER_BYTES + raw[3]])

    def next_reply(self, *, flush: bool = False) -> tuple[int | None, Message | None] | None:
        """See :meth:`StreamBuffer.next_reply`."""
        frame = self.next_frame(flush=flush)
        if frame is None:
            return None
        try:
            return frame.motor_id, decode_frame(frame, Direction.REPLY)
        except DecodeError:
            return frame.motor_id, None

    def _judge(self, buf: bytearray) -> int | str | Verdict:
        if len(buf) < HEADER_BYTES:
            return Verdict.WAIT
        if buf[4] != checksum(buf[:4]):
            return "bad_header_checksums"
        length, motor_id = buf[3], buf[2]
        if length > RS485_MAX_DATA_BYTES or not MOTOR_ID_MIN <= motor_id <= MOTOR_ID_MAX:
            return "bad_lengths"
        size = frame_size(length)
        if len(buf) < size:
            return Verdict.SHORT
        if length and buf[size - 1] != checksum(buf[HEADER_BYTES : HEADER_BYTES + length]):
            return "bad_data_checksums"
        return size
