"""Which protocol generation the drives on a CAN bus speak, told apart by their reply ids (issue 17).

Both generations take a request on ``0x140 + id``; a drive of the older family answers on the same id, a V3 drive on
``0x240 + id``. :func:`detect_can` sends a status read (0x9A, the same 8 bytes in both families) to each id at the
frame level and sorts the answers by their ids. Works on any :class:`~motion.transport.can_transport.CanPort` (a
transport's ``port``); the transport then speaks to each drive in its generation (``Transport.family``).
"""

from __future__ import annotations

import time
from collections.abc import Iterable, Mapping

from motion.protocol import Bare, CanFrame, Command, can_frame
from motion.protocol.table import CAN_ID_BASE, ProtocolFamily
from motion.protocol.v3 import frames as frames_v3
from motion.protocol.v3.messages import CommandV3
from motion.transport.can_transport import SEND_TIMEOUT_MIN_S, CanPort


def _collect(port: CanPort, window_s: float, wanted: Mapping[int, int]) -> dict[int, bytes]:
    """Frames received within ``window_s`` whose arbitration id is a key of ``wanted`` and whose DATA[0] is its
    value, by arbitration id (the first of each)."""
    found: dict[int, bytes] = {}
    end = time.monotonic() + window_s
    while len(found) < len(wanted):
        remaining = end - time.monotonic()
        if remaining <= 0:
            break
        received = port.recv(remaining)
        if received is None:
            break
        frame = received[0]
        code = wanted.get(frame.arbitration_id)
        if code is not None and frame.data[:1] == bytes((code,)) and frame.arbitration_id not in found:
            found[frame.arbitration_id] = frame.data
    return found


def probe_frames(ids: Iterable[int]) -> list[CanFrame]:
    """The status read (0x9A, the same 8 bytes in both families) to each id, as CAN frames."""
    return [can_frame.encode_request(Bare(Command.READ_STATUS_1), motor_id) for motor_id in sorted(set(ids))]


def expected_answers(ids: Iterable[int]) -> dict[int, int]:
    """The arbitration ids an answer to :func:`probe_frames` may come on (either generation's), each with the command
    byte it must carry."""
    id_list = sorted(set(ids))
    older = {CAN_ID_BASE + i: int(Command.READ_STATUS_1) for i in id_list}
    newer = {frames_v3.CAN_REPLY_BASE + i: int(CommandV3.READ_STATUS_1) for i in id_list}
    return older | newer


def generations(arbitration_ids: Iterable[int]) -> dict[int, ProtocolFamily]:
    """The motor id and generation of each answer's arbitration id (one of :func:`expected_answers`)."""
    found: dict[int, ProtocolFamily] = {}
    for arbitration_id in sorted(arbitration_ids):
        if arbitration_id >= frames_v3.CAN_REPLY_BASE:
            found[arbitration_id - frames_v3.CAN_REPLY_BASE] = ProtocolFamily.V3
        else:
            found[arbitration_id - CAN_ID_BASE] = ProtocolFamily.V2
    return found


def detect_can(port: CanPort, ids: Iterable[int], window_s: float) -> dict[int, ProtocolFamily]:
    """Each id that answers a status read within ``window_s``, with the generation its reply id shows.

    Raises:
        TransportError: the interface failed.
    """
    id_list = sorted(set(ids))
    while port.recv(0.0) is not None:  # what was queued before is nobody's answer
        pass
    for frame in probe_frames(id_list):
        port.send(frame, SEND_TIMEOUT_MIN_S)
    return generations(_collect(port, window_s, expected_answers(id_list)))
