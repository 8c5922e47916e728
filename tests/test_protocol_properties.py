"""Hypothesis round trips for every command on both transports, the fuzz invariant, and bad-input errors."""

from __future__ import annotations

import contextlib
from typing import Any

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from motion.errors import DecodeError, EncodeError
from motion.protocol import (
    COMMANDS,
    Acceleration,
    Bare,
    Command,
    Direction,
    MultiMotorTorque,
    MultiTurnPosition,
    MultiTurnPositionSpeed,
    Rs485Parser,
    SingleTurnPosition,
    SingleTurnPositionSpeed,
    SpinDirection,
    TorqueControl,
    WireProtocol,
    can_frame,
    raw_values,
    rs485_frame,
)
from motion.protocol.table import MULTI_TORQUE_LAYOUT, Field, Kind, Layout

# Angles of 7- and 8-byte fields beyond 2**50 centidegrees (1.1e13 degrees) are not exact in a float.
EXACT_FLOAT_RAW = 1 << 50

CASES = [
    (code, transport, direction, layout)
    for code, spec in COMMANDS.items()
    for transport in WireProtocol
    for direction in Direction
    if (layout := spec.layout(transport, direction)) is not None
]


def _field_strategy(f: Field) -> st.SearchStrategy[tuple[object, int | None]]:
    if f.kind is Kind.TEXT:
        text = st.text(st.characters(min_codepoint=1, max_codepoint=127), max_size=f.width)
        return text.map(lambda s: (s, None))
    lo, hi = max(f.lo, -EXACT_FLOAT_RAW), min(f.hi, EXACT_FLOAT_RAW)
    if f.kind is Kind.ENUM:
        assert f.enum is not None
        return st.sampled_from(list(f.enum)).map(lambda m: (m, m.value))
    if f.kind is Kind.FLAGS:
        assert f.enum is not None
        enum = f.enum
        return st.integers(lo, hi).map(lambda r: (enum(r), r))
    return st.integers(lo, hi).map(lambda r: (f.physical(r), r))


def _message_strategy(layout: Layout, code: Command | None) -> st.SearchStrategy[tuple[Any, dict[str, int]]]:
    parts = {f.name: _field_strategy(f) for f in layout.fields}

    def build(values: dict[str, tuple[object, int | None]]) -> tuple[Any, dict[str, int]]:
        kwargs = {name: v for name, (v, _) in values.items()}
        if layout.has_command_field:
            kwargs["command"] = code
        raws = {name: r for name, (_, r) in values.items() if r is not None}
        return layout.cls(**kwargs), raws

    return st.fixed_dictionaries(parts).map(build)


def _encode(transport: WireProtocol, direction: Direction, message: Any, motor_id: int) -> bytes:
    if transport is WireProtocol.CAN:
        enc = can_frame.encode_request if direction is Direction.REQUEST else can_frame.encode_reply
        frame = enc(message, motor_id)
        return frame.arbitration_id.to_bytes(2, "big") + frame.data
    enc485 = rs485_frame.encode_request if direction is Direction.REQUEST else rs485_frame.encode_reply
    return enc485(message, motor_id)


def _decode(transport: WireProtocol, direction: Direction, wire: bytes) -> tuple[int | None, Any]:
    if transport is WireProtocol.CAN:
        ident, data = int.from_bytes(wire[:2], "big"), wire[2:]
        if direction is Direction.REQUEST:
            req = can_frame.decode_request(ident, data)
            return req.motor_id, req.message
        return can_frame.decode_reply(ident, data)
    dec = rs485_frame.decode_request if direction is Direction.REQUEST else rs485_frame.decode_reply
    return dec(wire)


@pytest.mark.parametrize(
    ("code", "transport", "direction", "layout"),
    CASES,
    ids=[f"{c:02X}-{t.value}-{d.value}" for c, t, d, _ in CASES],
)
@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(data=st.data(), motor_id=st.integers(1, 32))
def test_round_trip_every_command(
    code: Command, transport: WireProtocol, direction: Direction, layout: Layout, data: st.DataObject, motor_id: int
) -> None:
    message, raws = data.draw(_message_strategy(layout, code))
    wire = _encode(transport, direction, message, motor_id)
    decoded_id, decoded = _decode(transport, direction, wire)
    assert decoded == message
    assert decoded_id == motor_id
    assert _encode(transport, direction, decoded, motor_id) == wire
    assert raw_values(message, transport, direction) == raws


@settings(max_examples=200, deadline=None)
@given(data=st.data())
def test_round_trip_multi_motor_torque(data: st.DataObject) -> None:
    message, raws = data.draw(_message_strategy(MULTI_TORQUE_LAYOUT, None))
    frame = can_frame.encode_request(message)
    assert frame.arbitration_id == 0x280
    decoded = can_frame.decode_request(frame.arbitration_id, frame.data)
    assert decoded.motor_id is None
    assert decoded.message == message
    assert raw_values(message, WireProtocol.CAN, Direction.REQUEST) == raws


# ------------------------------------------------------------------------------------------------ fuzz invariant


@settings(max_examples=3000, deadline=None)
@given(
    ident=st.one_of(st.integers(0, 0x7FF), st.integers(0x141, 0x160), st.just(0x280)),
    data=st.one_of(
        st.binary(max_size=9),
        # mostly-valid frames (drive ids, 8 bytes, known command bytes) so the decoders reach the field checks
        st.tuples(st.sampled_from([int(c) for c in Command]), st.binary(min_size=7, max_size=7)).map(
            lambda t: bytes((t[0],)) + t[1]
        ),
    ),
)
def test_can_decoders_raise_only_decode_error(ident: int, data: bytes) -> None:
    for decode in (can_frame.decode_request, can_frame.decode_reply):
        with contextlib.suppress(DecodeError):
            decode(ident, data)


@settings(max_examples=3000, deadline=None)
@given(
    body=st.one_of(
        st.binary(max_size=70),
        # mostly-valid frames so the decoders get past the envelope checks
        st.tuples(
            st.sampled_from([int(c) for c in Command] + [0x00, 0xFF]), st.integers(0, 33), st.binary(max_size=61)
        ).map(lambda t: rs485_frame.Rs485Frame(t[0], t[1], t[2]).to_bytes()),
    )
)
def test_rs485_decoders_raise_only_decode_error(body: bytes) -> None:
    for decode in (rs485_frame.decode_request, rs485_frame.decode_reply):
        with contextlib.suppress(DecodeError):
            decode(body)


@settings(max_examples=1000, deadline=None)
@given(chunks=st.lists(st.binary(max_size=40), max_size=10))
def test_rs485_parser_never_raises_and_returns_only_valid_frames(chunks: list[bytes]) -> None:
    parser = Rs485Parser()
    fed = 0
    for chunk in chunks:
        parser.feed(chunk)
        fed += len(chunk)
        while (frame := parser.next_frame()) is not None:
            rs485_frame.split_frame(frame.to_bytes())  # raises if the checksums were not right
    while (frame := parser.next_frame(flush=True)) is not None:
        rs485_frame.split_frame(frame.to_bytes())
    assert parser.pending < rs485_frame.HEADER_BYTES
    assert parser.dropped_bytes <= fed


# ------------------------------------------------------------------------------------------------ parser resync

A4 = rs485_frame.encode_request(MultiTurnPositionSpeed(90.0, 100.0), 3)
STOP = rs485_frame.encode_request(Bare(Command.MOTOR_STOP), 7)


def _frames(parser: Rs485Parser, *, flush: bool = False) -> list[bytes]:
    out = []
    while (frame := parser.next_frame(flush=flush)) is not None:
        out.append(frame.to_bytes())
    return out


def test_parser_skips_garbage_between_frames_and_counts_it() -> None:
    parser = Rs485Parser()
    parser.feed(b"\x00\x3e\x3e\xff" + A4 + b"garbage" + STOP)
    assert _frames(parser) == [A4, STOP]
    assert parser.dropped_bytes == 4 + len(b"garbage")
    assert parser.bad_header_checksums >= 1


def test_parser_byte_by_byte() -> None:
    parser = Rs485Parser()
    out: list[bytes] = []
    for b in A4 + STOP:
        parser.feed(bytes((b,)))
        out += _frames(parser)
    assert out == [A4, STOP]
    assert parser.dropped_bytes == 0


def test_parser_drops_bad_data_checksum_and_finds_next_frame() -> None:
    corrupt = bytearray(A4)
    corrupt[8] ^= 0x40
    parser = Rs485Parser()
    parser.feed(bytes(corrupt) + STOP)
    assert _frames(parser) == [STOP]
    assert parser.bad_data_checksums == 1
    assert parser.dropped_bytes == len(A4)


def test_parser_recovers_after_truncated_frame() -> None:
    parser = Rs485Parser()
    parser.feed(A4[:9] + STOP)  # the A4 frame lost its tail; its length swallows STOP for now
    assert _frames(parser) == []
    assert _frames(parser, flush=True) == [STOP]
    assert parser.truncated >= 1
    parser.feed(A4)
    assert _frames(parser) == [A4]


def test_parser_rejects_oversized_length_without_waiting() -> None:
    parser = Rs485Parser()
    header = bytes((0x3E, 0xA4, 0x01, 61))
    parser.feed(header + bytes((rs485_frame.checksum(header),)) + STOP)
    assert _frames(parser) == [STOP]
    assert parser.bad_lengths == 1


# ------------------------------------------------------------------------------------------------ bad input


@pytest.mark.parametrize(
    ("message", "motor_id", "field", "valid"),
    [
        (Bare(Command.MOTOR_OFF), 0, "motor_id", "1..32"),
        (Bare(Command.MOTOR_OFF), 33, "motor_id", "1..32"),
        (TorqueControl(32.1), 1, "iq_a", "-32..32 A"),
        (TorqueControl(-40.0), 1, "iq_a", "-32..32 A"),
        (SingleTurnPosition(SpinDirection.CLOCKWISE, 360.0), 1, "angle_deg", "0..359.99 deg"),
        (SingleTurnPosition(SpinDirection.CLOCKWISE, -0.01), 1, "angle_deg", "0..359.99 deg"),
        (MultiTurnPosition(21474836.48), 1, "angle_deg", "-2.14748e+07..2.14748e+07 deg"),
        (MultiTurnPositionSpeed(10.0, -1.0), 1, "max_speed_dps", "0..65535 dps"),
        (MultiTurnPositionSpeed(10.0, 65536.0), 1, "max_speed_dps", "0..65535 dps"),
        (SingleTurnPositionSpeed(2, 10.0, 5.0), 1, "direction", "CLOCKWISE=0, COUNTERCLOCKWISE=1"),  # type: ignore[arg-type]
        (MultiTurnPosition(float("nan")), 1, "angle_deg", "deg"),
        (MultiTurnPosition(True), 1, "angle_deg", "deg"),
        (Acceleration(Command.WRITE_ACCELERATION_RAM, -1), 1, "acceleration_dps2", "0..2147483647"),
        (MultiMotorTorque(0.0, 0.0, 33.0, 0.0), 1, "iq3_a", "-32..32 A"),
    ],
)
def test_can_encode_errors_name_field_range_and_value(message: Any, motor_id: int, field: str, valid: str) -> None:
    with pytest.raises(EncodeError) as info:
        can_frame.encode_request(message, motor_id)
    assert info.value.field == field
    assert valid in info.value.valid
    assert field in str(info.value) and repr(getattr(message, field, motor_id)) in str(info.value)


def test_rs485_widths_differ_from_can() -> None:
    # 0xA3/0xA4 angles are int64 on RS485: far beyond the CAN int32 range is fine there
    rs485_frame.encode_request(MultiTurnPosition(1e9), 1)
    with pytest.raises(EncodeError, match="angle_deg"):
        can_frame.encode_request(MultiTurnPosition(1e9), 1)
    # RS485 max speed is uint32 0.01 dps: 0.5 dps is representable there, rounds to 0 or 1 dps on CAN
    assert raw_values(MultiTurnPositionSpeed(0.0, 0.5), WireProtocol.RS485, Direction.REQUEST)["max_speed_dps"] == 50
    with pytest.raises(EncodeError, match="max_speed_dps"):
        rs485_frame.encode_request(MultiTurnPositionSpeed(0.0, 42949672.96), 1)


def test_commands_missing_on_a_transport_are_refused() -> None:
    with pytest.raises(EncodeError, match="0x95"):
        rs485_frame.encode_request(Bare(Command.SET_ZERO_RAM), 1)
    with pytest.raises(EncodeError, match="0x12"):
        can_frame.encode_request(Bare(Command.READ_MODEL), 1)
    with pytest.raises(EncodeError, match="MultiTurnPosition"):
        can_frame.encode_request(Bare(Command.MULTI_TURN_POSITION), 1)
    with pytest.raises(EncodeError, match="0x280"):
        rs485_frame.encode_request(MultiMotorTorque(0, 0, 0, 0), 1)


def test_field_not_carried_by_can_must_be_none() -> None:
    from motion.protocol import PhaseCurrents

    with pytest.raises(EncodeError, match="temperature_c"):
        can_frame.encode_reply(PhaseCurrents(1.0, 1.0, 1.0, temperature_c=30), 1)


@pytest.mark.parametrize(
    ("ident", "data", "match"),
    [
        (0x141, bytes.fromhex("A4 00 F4 01 A0 8C 00"), "8 bytes"),
        (0x140, bytes(8), "arbitration id 0x140"),
        (0x161, bytes(8), "arbitration id 0x161"),
        (0x141, bytes.fromhex("77 00 00 00 00 00 00 00"), "0x77"),
        (0x141, bytes.fromhex("A5 02 00 00 00 00 00 00"), "direction"),
        (0x141, bytes.fromhex("A5 00 00 00 A0 8C 00 00"), "angle_deg"),
        (0x141, bytes.fromhex("80 00 00 01 00 00 00 00"), "reserved byte DATA\\[3\\]"),
        (0x141, bytes.fromhex("12 00 00 00 00 00 00 00"), "0x12"),
    ],
)
def test_can_request_decode_errors(ident: int, data: bytes, match: str) -> None:
    with pytest.raises(DecodeError, match=match) as info:
        can_frame.decode_request(ident, data)
    assert info.value.raw == data


def test_reply_reserved_bytes_are_ignored_but_request_reserved_bytes_are_not() -> None:
    data = bytes.fromhex("9A 2D 55 F0 00 66 77 00")
    _, status = can_frame.decode_reply(0x141, data)
    assert status.voltage_v == 24.0  # type: ignore[attr-defined]
    with pytest.raises(DecodeError, match="reserved"):
        rs485_frame.decode_request(rs485_frame.Rs485Frame(0xA5, 1, bytes.fromhex("00 50 46 01")).to_bytes())


@pytest.mark.parametrize(
    ("wire", "match"),
    [
        ("3E A4 01", "shorter"),
        ("3F 80 01 00 C0", "start with 0x3E"),
        ("3E 80 01 00 BE", "header checksum"),
        ("3E 80 00 00 BE", "motor id 0"),
        ("3E A1 01 02 E2 30 F8 29", "data checksum"),
        ("3E A1 01 02 E2 30 F8", "must be 8 bytes"),
        ("3E A1 01 03 E3 30 F8 00 28", "carries 2 data bytes, got 3"),
        ("3E 95 01 00 D4", "0x95 is not an RS485"),
    ],
)
def test_rs485_decode_errors(wire: str, match: str) -> None:
    with pytest.raises(DecodeError, match=match) as info:
        rs485_frame.decode_request(bytes.fromhex(wire))
    assert info.value.raw == bytes.fromhex(wire)
