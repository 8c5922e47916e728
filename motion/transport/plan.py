"""A batch's plan (:class:`Plan`): the slots its replies fill, everything about them that does not change from cycle
to cycle (:meth:`motion.transport.Transport.transact` keeps one per batch shape)."""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Final

from motion.protocol import Command, Message
from motion.protocol.table import ADDRESS_STRIDE, MULTI_TORQUE_MOTOR_IDS

if TYPE_CHECKING:
    from motion.transport.base import MotorCounters, Request

#: Slot states.
NOT_SENT: Final = 0
OPEN: Final = 1
FILLED: Final = 2
EXPIRED: Final = 3
#: Signature entry of a 0x280 request (four slots, motors 1..4; it has no motor id or command byte of its own), less
#: its bus's index on an arm of several buses (its request's address names the bus).
MULTI_KEY: Final = -1


@dataclass(frozen=True, slots=True)
class Plan:
    """The slots of one batch shape: everything about them that does not change from cycle to cycle.

    Attributes:
        first_slot: per request, its first slot; a last entry, the number of slots.
        slot_request: per slot, the index of its request.
        slot_motor: per slot, the motor expected to answer.
        slot_key: per slot, ``motor id << 8 | command byte``.
        slot_next: per slot, the next slot with the same key (-1: none): replies fill them first-in, first-out.
        first_slot_of_key: the first slot of each key.
        slot_counters: per slot, its motor's counters.
        one_each: every request has exactly one slot (request i has slot i).
        not_sent, no_messages, no_times: a cycle's initial slot states, messages and reply times (copied).
        all_open: every slot open.
    """

    first_slot: tuple[int, ...]
    slot_request: tuple[int, ...]
    slot_motor: tuple[int, ...]
    slot_key: tuple[int, ...]
    slot_next: tuple[int, ...]
    first_slot_of_key: Mapping[int, int]
    slot_counters: tuple[MotorCounters, ...]
    one_each: bool
    not_sent: list[int]
    no_messages: list[Message | None]
    no_times: list[float | None]
    all_open: tuple[int, ...]

    @classmethod
    def empty(cls) -> Plan:
        """The plan of an empty batch."""
        return cls((0,), (), (), (), (), {}, (), True, [], [], [], ())

    @classmethod
    def build(
        cls, signature: tuple[int, ...], requests: Sequence[Request], counters: Callable[[int], MotorCounters]
    ) -> Plan:
        """The plan of the batch ``requests`` whose keys are ``signature`` (see :meth:`Transport._plan`)."""
        first_slot: list[int] = []
        slot_request: list[int] = []
        slot_motor: list[int] = []
        slot_key: list[int] = []
        slot_next: list[int] = []
        first_of_key: dict[int, int] = {}
        last_of_key: dict[int, int] = {}
        for index, (request, key) in enumerate(zip(requests, signature, strict=True)):
            first_slot.append(len(slot_motor))
            if key <= MULTI_KEY:  # motors 1..4 of the bus the request's address names
                base = (MULTI_KEY - key) * ADDRESS_STRIDE
                expected = [(base + m, (base + m) << 8 | Command.TORQUE) for m in MULTI_TORQUE_MOTOR_IDS]
            else:
                expected = [(request.motor_id, key)]
            for motor_id, slot_key_ in expected:
                slot = len(slot_motor)
                slot_request.append(index)
                slot_motor.append(motor_id)
                slot_key.append(slot_key_)
                slot_next.append(-1)
                last = last_of_key.get(slot_key_)
                if last is None:
                    first_of_key[slot_key_] = slot
                else:
                    slot_next[last] = slot
                last_of_key[slot_key_] = slot
        first_slot.append(len(slot_motor))
        n = len(slot_motor)
        return cls(
            first_slot=tuple(first_slot),
            slot_request=tuple(slot_request),
            slot_motor=tuple(slot_motor),
            slot_key=tuple(slot_key),
            slot_next=tuple(slot_next),
            first_slot_of_key=first_of_key,
            slot_counters=tuple(counters(motor_id) for motor_id in slot_motor),
            one_each=n == len(requests),
            not_sent=[NOT_SENT] * n,
            no_messages=[None] * n,
            no_times=[None] * n,
            all_open=(OPEN,) * n,
        )
