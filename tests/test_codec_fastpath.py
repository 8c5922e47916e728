"""The codec's fast path (motion.protocol.compiled) agrees with the checked path of the table on every layout.

The fast path may only ever say "same as the checked path" or "take the checked path" (None); these tests feed both
the same messages and the same bytes, valid and not.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from motion.errors import DecodeError, EncodeError
from motion.protocol import (
    COMMANDS,
    Command,
    Direction,
    MotorState,
    MultiMotorTorque,
    MultiTurnPositionSpeed,
    TorqueControl,
    WireProtocol,
    can_frame,
    rs485_frame,
)
from motion.protocol.compiled import CODECS, FALLBACK_ERRORS, CompiledLayout, compile_layout, frozen_builder
from motion.protocol.table import MULTI_TORQUE_LAYOUT, Kind, Layout, pack_fields, unpack_fields

CASES: list[tuple[Command | None, WireProtocol, Direction, Layout]] = [
    (code, transport, direction, layout)
    for code, spec in COMMANDS.items()
    for transport in WireProtocol
    for direction in Direction
    if (layout := spec.layout(transport, direction)) is not None
]
CASES.append((None, WireProtocol.CAN, Direction.REQUEST, MULTI_TORQUE_LAYOUT))
IDS = [f"{'280' if c is None else f'{c:02X}'}-{t.value}-{d.value}" for c, t, d, _ in CASES]

#: Values a field may be given: in range, out of range, of another type, not finite.
ODD_VALUES = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True),
    st.integers(-(1 << 70), 1 << 70),
    st.booleans(),
    st.none(),
    st.sampled_from(["1", 1.5, -0.005, 0.005, 327.675, 2.5]),
)


def _compiled(code: Command | None, transport: WireProtocol, direction: Direction, layout: Layout) -> CompiledLayout:
    compiled = compile_layout(layout, code, transport, direction)
    if compiled is None:
        pytest.skip("struct cannot express this layout: the checked path handles it alone")
    return compiled


def _checked_encode(compiled: CompiledLayout, message: Any, transport: WireProtocol) -> bytes | Exception:
    data = bytearray(compiled.size)
    try:
        pack_fields(compiled.layout, message, data)
    except (EncodeError, OverflowError) as exc:  # a finite value whose scaled value is not (1e306 * 100)
        return exc
    if compiled.command is not None and transport is WireProtocol.CAN:
        data[0] = compiled.command
    return bytes(data)


def _fast_encode(compiled: CompiledLayout, message: Any) -> bytes | None:
    try:
        return compiled.encode(message)
    except FALLBACK_ERRORS:
        return None


def draw_message(compiled: CompiledLayout, data: st.DataObject, *, edges: bool = False) -> Any:
    """A message of the layout with drawn values: valid ones (as the table's type and as floats), odd ones, and with
    ``edges`` the range's ends and the values just beyond them."""
    values: dict[str, Any] = {}
    for f in compiled.layout.fields:
        if f.kind in (Kind.ENUM, Kind.FLAGS):
            assert f.enum is not None
            values[f.name] = data.draw(st.one_of(st.sampled_from(list(f.enum)), ODD_VALUES))
            continue
        valid = st.integers(f.lo, f.hi).map(f.physical)
        choices = [valid, valid.map(float), ODD_VALUES]
        if edges:
            ends = st.sampled_from([f.lo, f.hi, f.lo - 1, f.hi + 1]).map(f.physical)
            choices += [ends, ends.map(float)]
        values[f.name] = data.draw(st.one_of(*choices))
    return _message(compiled, values)


def _message(compiled: CompiledLayout, values: dict[str, Any]) -> Any:
    kwargs = dict(values)
    if compiled.layout.has_command_field:
        kwargs["command"] = compiled.command
    return compiled.layout.cls(**kwargs)


@pytest.mark.parametrize(("code", "transport", "direction", "layout"), CASES, ids=IDS)
@settings(max_examples=40, deadline=None)
@given(data=st.data())
def test_fast_encode_equals_checked_encode_or_defers(
    code: Command | None, transport: WireProtocol, direction: Direction, layout: Layout, data: st.DataObject
) -> None:
    compiled = _compiled(code, transport, direction, layout)
    message = draw_message(compiled, data)
    fast, checked = _fast_encode(compiled, message), _checked_encode(compiled, message, transport)
    if fast is not None:
        assert fast == checked, message


@pytest.mark.parametrize(("code", "transport", "direction", "layout"), CASES, ids=IDS)
@settings(max_examples=40, deadline=None)
@given(data=st.data())
def test_fast_decode_equals_checked_decode_or_defers(
    code: Command | None, transport: WireProtocol, direction: Direction, layout: Layout, data: st.DataObject
) -> None:
    compiled = _compiled(code, transport, direction, layout)
    payload = bytearray(data.draw(st.binary(min_size=compiled.size, max_size=compiled.size)))
    if data.draw(st.booleans()):  # mostly-zero payloads reach the reserved-byte and range checks
        payload = bytearray(b if data.draw(st.booleans()) else 0 for b in payload)
    if compiled.command is not None and transport is WireProtocol.CAN:
        payload[0] = compiled.command
    first = 1 if compiled.command is not None and transport is WireProtocol.CAN else 0
    fast = compiled.decode(bytes(payload))
    try:
        checked: Any = unpack_fields(
            layout, bytes(payload), compiled.command, first=first, check_reserved=direction is Direction.REQUEST
        )
    except DecodeError as exc:
        checked = exc
    if fast is not None:
        assert type(fast) is type(checked)
        assert fast == checked
        assert [getattr(fast, f.name) for f in dataclasses.fields(fast)] == [
            getattr(checked, f.name) for f in dataclasses.fields(checked)
        ]


def test_every_hot_path_layout_is_compiled() -> None:
    can_request, can_reply = CODECS[WireProtocol.CAN, Direction.REQUEST], CODECS[WireProtocol.CAN, Direction.REPLY]
    for cls in (MultiTurnPositionSpeed, TorqueControl, MultiMotorTorque):
        assert cls in can_request.encoders
    for code in (Command.MULTI_TURN_POSITION_SPEED, Command.TORQUE, Command.READ_STATUS_2, Command.READ_STATUS_1):
        assert can_reply.decoders[code] is not None
        assert CODECS[WireProtocol.RS485, Direction.REPLY].decoders[code] is not None


def test_fast_path_builds_equal_frames_and_messages() -> None:
    frame = can_frame.encode_request(MultiTurnPositionSpeed(90.0, 360.0), 1)
    assert (frame.arbitration_id, frame.data.hex(" ")) == (0x141, "a4 00 68 01 28 23 00 00")
    reply = MotorState(Command.MULTI_TURN_POSITION_SPEED, 31, 0.416, -5, 1000)
    motor_id, decoded = can_frame.decode_reply(0x143, can_frame.encode_reply(reply, 3).data)
    assert (motor_id, decoded) == (3, reply)
    assert hash(decoded) == hash(reply)
    with pytest.raises(dataclasses.FrozenInstanceError):
        decoded.encoder = 3  # type: ignore[attr-defined]
    wire = rs485_frame.encode_request(MultiTurnPositionSpeed(90.0, 360.0), 1)
    assert rs485_frame.decode_request(wire) == (1, MultiTurnPositionSpeed(90.0, 360.0))


@pytest.mark.parametrize(
    ("message", "field"),
    [
        (MultiTurnPositionSpeed(math.nan, 10.0), "angle_deg"),
        (MultiTurnPositionSpeed(1.0, math.inf), "max_speed_dps"),
        (MultiTurnPositionSpeed(1.0, 65535.6), "max_speed_dps"),
        (MultiTurnPositionSpeed(True, 1.0), "angle_deg"),
        (TorqueControl(32.01), "iq_a"),
        (MultiMotorTorque(0.0, 0.0, -40.0, 0.0), "iq3_a"),
    ],
)
def test_unusual_values_keep_the_checked_path_errors(message: Any, field: str) -> None:
    with pytest.raises(EncodeError) as caught:
        can_frame.encode_request(message, 1)
    assert caught.value.field == field
    with pytest.raises(EncodeError):
        can_frame.encode_request(MultiTurnPositionSpeed(1.0, 1.0), 33)


def test_frozen_builder_sets_every_field() -> None:
    build = frozen_builder(can_frame.CanFrame)
    assert build(0x141, b"\0" * 8) == can_frame.CanFrame(0x141, b"\0" * 8)
