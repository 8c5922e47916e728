"""One object per protocol generation: what a transport, a scan or a command needs of the drives' wire protocol,
so that none of them asks which generation it speaks (issue 32 §2).

A :class:`Generation` holds its family's codec (encode a request, decode a reply, the CAN reply ids, the RS485
framing and its parser), its documents' names, its RS485 baud rates and the status read every scan and probe sends.
The control layer's counterpart, what control does differently per family, is
:class:`motion.control.family.DriveFamily`; the two are looked up once, by the bus's family, where it is opened.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Final

from motion.protocol import can_frame, rs485_frame
from motion.protocol.can_frame import CanFrame
from motion.protocol.messages import Bare, Command, Message, MultiMotorTorque, TorqueControl
from motion.protocol.rs485_frame import Rs485Parser, StreamBuffer
from motion.protocol.table import (
    CAN_ID_BASE,
    MULTI_TORQUE_MOTOR_IDS,
    RS485_BAUDRATES,
    Direction,
    ProtocolFamily,
    WireProtocol,
)
from motion.protocol.v3 import frames as frames_v3
from motion.protocol.v3.messages import BareV3, CommandV3


@dataclass(frozen=True, slots=True)
class Generation:
    """The wire protocol of one generation of drives.

    Attributes:
        family: the protocol family.
        title: how messages name the generation ("the V3-driver protocol (V4.2)").
        can_document: the CAN document's version ("v2.3", "V4.2").
        rs485_document: the RS485 document's version ("v1.62", "V4.2").
        can_reply_base: the drives reply on this id + their motor id.
        rs485_baudrates: the baud rates its RS485 drives take, bit/s.
        status_read: the 0x9A request (what a scan and the generation probe send).
        encode_can_request: ``(message, motor_id) -> CanFrame``.
        decode_can_reply: ``(arbitration_id, data) -> (motor_id, message)`` (raises ``DecodeError``).
        encode_rs485_request: ``(message, motor_id) -> bytes``.
        rs485_parser: a new parser of the generation's RS485 byte stream.
        identity_reads: what tells a drive's model and firmware, by wire (the older family's CAN document has no such
            read; its RS485 one has 0x12; V3 has 0xB5 model and 0xB2 firmware date on both).
        decode_rs485_reply: ``raw frame -> (motor_id, message)`` (None: a frame naming no single drive).

    The drive's side (what an emulated drive needs):

    Attributes:
        decode_can_request: ``(arbitration_id, data) -> (motor_id, message)``; None: a frame for several drives.
        decode_rs485_request: ``raw frame -> (motor_id, message)``; None: a frame for every drive.
        encode_can_reply: ``(message, motor_id) -> CanFrame``.
        encode_rs485_reply: ``(message, motor_id) -> bytes``.
        spread: ``(message, ids) -> [(motor_id, message)]``: what each drive takes of a frame for several drives
            (the older family's 0x280: motors 1..4 each their torque current; V3's 0x280 / 0xCD: every drive the
            same command).
    """

    family: ProtocolFamily
    title: str
    can_document: str
    rs485_document: str
    can_reply_base: int
    rs485_baudrates: tuple[int, ...]
    status_read: Message
    encode_can_request: Callable[[Message, int], CanFrame]
    decode_can_reply: Callable[[int, bytes], tuple[int | None, Message]]
    encode_rs485_request: Callable[[Message, int], bytes]
    rs485_parser: Callable[[], StreamBuffer]
    identity_reads: Mapping[WireProtocol, tuple[Message, ...]]
    decode_rs485_reply: Callable[[bytes], tuple[int | None, Message]]
    decode_can_request: Callable[[int, bytes], tuple[int | None, Message]]
    decode_rs485_request: Callable[[bytes], tuple[int | None, Message]]
    encode_can_reply: Callable[[Message, int], CanFrame]
    encode_rs485_reply: Callable[[Message, int], bytes]
    spread: Callable[[Message, Sequence[int]], list[tuple[int, Message]]]
    _bare: Callable[[int], Message]

    def bare(self, code: int) -> Message:
        """The generation's request without data for ``code`` (0x80, 0x81, 0x92, 0x9A, 0x9C, ...)."""
        return self._bare(code)


def _v2_bare(code: int) -> Message:
    return Bare(Command(code))


def _v2_can_request(arbitration_id: int, data: bytes) -> tuple[int | None, Message]:
    request = can_frame.decode_request(arbitration_id, data)
    return request.motor_id, request.message


def _v2_rs485_request(raw: bytes) -> tuple[int | None, Message]:
    frame = rs485_frame.split_frame(raw)
    return frame.motor_id, rs485_frame.decode_frame(frame, Direction.REQUEST)


def _v2_spread(message: Message, ids: Sequence[int]) -> list[tuple[int, Message]]:
    """0x280 (the one frame for several drives): motors 1..4 each take their torque current as a 0xA1."""
    assert isinstance(message, MultiMotorTorque)
    currents = (message.iq1_a, message.iq2_a, message.iq3_a, message.iq4_a)
    return [(i, TorqueControl(iq)) for i, iq in zip(MULTI_TORQUE_MOTOR_IDS, currents, strict=True)]


def _v3_can_request(arbitration_id: int, data: bytes) -> tuple[int | None, Message]:
    request = frames_v3.decode_can_request(arbitration_id, data)
    return request.motor_id, request.message


def _v3_spread(message: Message, ids: Sequence[int]) -> list[tuple[int, Message]]:
    """0x280 and 0x300 (CAN), 0xCD (RS485): every drive takes the command (each answers on its own id)."""
    return [(i, message) for i in ids]


def _v3_bare(code: int) -> Message:
    return BareV3(CommandV3(code))


_V3_IDENTITY: Final = (BareV3(CommandV3.READ_MODEL), BareV3(CommandV3.READ_VERSION_DATE))

#: Each family's generation.
GENERATIONS: Final[Mapping[ProtocolFamily, Generation]] = {
    ProtocolFamily.V2: Generation(
        family=ProtocolFamily.V2,
        title="older protocol (CAN v2.3 / RS485 v1.62)",
        can_document="v2.3",
        rs485_document="v1.62",
        can_reply_base=CAN_ID_BASE,
        rs485_baudrates=RS485_BAUDRATES[ProtocolFamily.V2],
        status_read=Bare(Command.READ_STATUS_1),
        encode_can_request=can_frame.encode_request,
        decode_can_reply=can_frame.decode_reply,
        encode_rs485_request=rs485_frame.encode_request,
        rs485_parser=Rs485Parser,
        identity_reads={WireProtocol.CAN: (), WireProtocol.RS485: (Bare(Command.READ_MODEL),)},
        decode_rs485_reply=rs485_frame.decode_reply,
        decode_can_request=_v2_can_request,
        decode_rs485_request=_v2_rs485_request,
        encode_can_reply=can_frame.encode_reply,
        encode_rs485_reply=rs485_frame.encode_reply,
        spread=_v2_spread,
        _bare=_v2_bare,
    ),
    ProtocolFamily.V3: Generation(
        family=ProtocolFamily.V3,
        title="V3-driver protocol (V4.2)",
        can_document="V4.2",
        rs485_document="V4.2",
        can_reply_base=frames_v3.CAN_REPLY_BASE,
        rs485_baudrates=RS485_BAUDRATES[ProtocolFamily.V3],
        status_read=BareV3(CommandV3.READ_STATUS_1),
        encode_can_request=frames_v3.encode_can_request,
        decode_can_reply=frames_v3.decode_can_reply,
        encode_rs485_request=frames_v3.encode_rs485_request,
        rs485_parser=frames_v3.Rs485ParserV3,
        identity_reads=dict.fromkeys(WireProtocol, _V3_IDENTITY),
        decode_rs485_reply=frames_v3.decode_rs485_reply,
        decode_can_request=_v3_can_request,
        decode_rs485_request=frames_v3.decode_rs485_request,
        encode_can_reply=frames_v3.encode_can_reply,
        encode_rs485_reply=frames_v3.encode_rs485_reply,
        spread=_v3_spread,
        _bare=_v3_bare,
    ),
}
