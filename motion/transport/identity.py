"""What the drives tell of themselves (model, firmware): read at connect and by ``scan`` in each generation's own reads
(:attr:`~motion.protocol.generation.Generation.identity_reads`), kept on the transport (``Transport.identities``)."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass

from motion.protocol import Message, ProductInfo
from motion.protocol.generation import GENERATIONS
from motion.protocol.table import WireProtocol
from motion.protocol.v3.messages import MotionRanges, MotorModel, VersionDate
from motion.protocol.v3.motion_frame import motion_ranges
from motion.transport.base import Request, Transport


@dataclass(frozen=True)
class Identity:
    """What a drive told of itself: as text (``"X8S2V10 firmware 20240528"``, ``"MC400 / RMD-L-7015 hw 1.0 fw 3.2"``),
    as a record for JSON (the older family's 0x12 fields; else the text), and a V3 drive's model (0xB5) and firmware
    date (0xB2), None where it did not tell them."""

    text: str
    record: object
    model: str | None = None
    firmware_date: int | None = None

    @staticmethod
    def of(told: Mapping[type[Message], Message]) -> Identity:
        info = told.get(ProductInfo)
        if isinstance(info, ProductInfo):
            text = f"{info.driver_name} / {info.motor_name} hw {info.hardware_version:g} fw {info.firmware_version:g}"
            return Identity(text, asdict(info))
        model_reply, date_reply = told.get(MotorModel), told.get(VersionDate)
        model = model_reply.model if isinstance(model_reply, MotorModel) else None
        date = date_reply.date if isinstance(date_reply, VersionDate) else None
        text = f"{model or '(no model)'} firmware {date or '(no date)'}"
        return Identity(text, text, model, date)

    def motion_ranges(self) -> MotionRanges:
        """The V3 motion frame's ranges of this drive (:func:`motion.protocol.v3.motion_frame.motion_ranges`).

        Raises:
            EncodeError: the drive did not tell its firmware date, or its model's V4.4 ranges are not known.
        """
        return motion_ranges(self.firmware_date, self.model)


def read_identities(bus: Transport, ids: Sequence[int], wire: WireProtocol, window_s: float) -> dict[int, Identity]:
    """Each of ``ids`` that answered its generation's identity reads (``Generation.identity_reads`` on ``wire``, of
    its bus's generation: ``bus.family_of``) within ``window_s``, with what they told (none where the generation has
    no such read on ``wire``).

    Raises:
        TransportError: the bus failed.
    """
    requests = [Request(i, m) for i in ids for m in GENERATIONS[bus.family_of(i)].identity_reads[wire]]
    if not requests:
        return {}
    replies = bus.transact(requests, bus.clock() + window_s)
    told: dict[int, dict[type[Message], Message]] = {}
    for reply in replies:
        if reply.message is not None:
            told.setdefault(reply.motor_id, {})[type(reply.message)] = reply.message
    return {i: Identity.of(told[i]) for i in ids if i in told}
