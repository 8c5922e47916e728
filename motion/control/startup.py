"""The reads before a control loop starts: every drive asked, a drive that missed a reply asked again.

The controller anchors its position tracking on them (:meth:`~motion.control.controller.Controller.read_positions`);
the turn resolution at connect reads the drives' angles and runtimes through them
(:func:`motion.compose.resolve_frames`).
"""

from __future__ import annotations

from collections.abc import Collection, Sequence
from typing import TYPE_CHECKING, Final

from motion.errors import DrivesSilent
from motion.protocol import Command, MultiTurnAngle
from motion.protocol.v3.messages import CommandV3, Runtime
from motion.transport.base import Reply

if TYPE_CHECKING:
    from motion.control.controller import Controller

#: How often a read before the loop is asked of a drive that did not answer.
READ_ATTEMPTS: Final = 3


def read_every_drive(
    controller: Controller, reads: Sequence[int], timeout_s: float, ids: Sequence[int] | None = None
) -> list[Reply]:
    """The reads of commands ``reads`` (each drive's family's request without data) to every drive of ``controller``
    (or those of ``ids``; before its loop runs), asked again of a drive that missed any of them, up to
    :data:`READ_ATTEMPTS` times in all (a frame lost, a host that stalled longer than ``timeout_s``: a drive that
    answers the next time is no communication error); the replies, the latest of each drive that answered every
    read."""
    pending: list[int] = list(controller.ids if ids is None else ids)
    taken: dict[int, list[Reply]] = {}
    for _ in range(READ_ATTEMPTS):
        requests = [controller.bare_request(motor_id, code) for motor_id in pending for code in reads]
        replies = controller.bus.transact(requests, controller.clock.now() + timeout_s)
        answered: dict[int, list[Reply]] = {}
        for reply in replies:
            answered.setdefault(reply.motor_id, []).append(reply)
        pending = []
        for motor_id, group in answered.items():
            if all(r.message is not None for r in group):
                taken[motor_id] = group
            else:
                pending.append(motor_id)
        if not pending:
            break
    return [reply for group in taken.values() for reply in group]


def silent_drives(controller: Controller, what: str, answered: Collection[int], note: str = "") -> DrivesSilent:
    """The error for the joints whose drives did not answer ``what``, each named with its motor id."""
    silent = [s for s in controller.specs if s.motor_id not in answered]
    named = ", ".join(f"{s.name} ({s.drive_label})" for s in silent)
    return DrivesSilent(
        f"no reply to the {what} from joint(s) {named}{note}",
        tuple(s.motor_id for s in silent),
        tuple(s.drive_label for s in silent),
    )


def read_angles(controller: Controller, timeout_s: float = 0.2) -> dict[int, float]:
    """Every drive's multi-turn reading (0x92), motor degrees in the drive's own frame, by motor id (an output-shaft
    reading times the drive's reduction).

    Raises:
        TransportError: a drive did not answer by ``timeout_s``.
    """
    replies = read_every_drive(controller, (Command.READ_MULTI_TURN_ANGLE,), timeout_s)
    gear = {s.motor_id: s.drive_gear_ratio for s in controller.specs}
    angles = {
        r.motor_id: r.message.angle_deg * gear[r.motor_id]
        for r in replies
        if isinstance(r.message, MultiTurnAngle) and r.motor_id in gear
    }
    if len(angles) < len(controller.specs):
        raise silent_drives(controller, "multi-turn angle read (0x92)", angles, controller.bus.junk_note())
    return angles


def read_runtimes(controller: Controller, timeout_s: float = 0.2) -> dict[int, float]:
    """Every drive's runtime (time since its power-on, 0xB1), s, by motor id, of the drives whose family tells it
    (none of the older drives).

    Raises:
        TransportError: a drive did not answer by ``timeout_s``.
    """
    telling = [i for i, f in zip(controller.ids, controller.families, strict=True) if f.tells_runtime]
    if not telling:
        return {}
    replies = read_every_drive(controller, (CommandV3.READ_RUNTIME,), timeout_s, telling)
    runtimes = {r.motor_id: r.message.runtime_ms / 1000.0 for r in replies if isinstance(r.message, Runtime)}
    if len(runtimes) < len(telling):
        raise silent_drives(controller, "runtime read (0xB1)", runtimes.keys() | (set(controller.ids) - set(telling)))
    return runtimes
