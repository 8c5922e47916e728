"""The transport interface: one batched ``transact(requests, deadline_s)`` per control cycle.

:class:`Transport` follows python-can's ``BusABC`` shape: the public methods live here and call a few template
methods that a backend implements (``_prepare`` encodes a cycle's requests, ``_exchange`` puts them on the wire
and feeds the frames it receives to ``_offer``, ``_close`` releases the port). Backends are imported lazily by
name through :func:`motion.transport.open_transport`.

Matching rule (the same on every backend)
-----------------------------------------
Every request expects replies keyed by ``(motor id, command byte)``: one from its own motor, or four 0xA1-style
replies from motors 1..4 for the 0x280 :class:`~motion.protocol.MultiMotorTorque` frame. Each expected reply is a
*slot*; a slot is *open* from the moment its request went out until it is filled or expires (CAN: at the
cycle's deadline; RS485: at the end of the request's own reply window). A decoded reply fills the first open
slot with its key, in request order, so replies may arrive in any order and two requests with the same key in
one cycle are answered first-in, first-out (drives answer in the order they were asked).

A reply that finds no open slot is *stale*: it arrived before its request was sent (a previous cycle's reply
still in the receive queue, which is how anything that arrives before the cycle's sends is drained), or its
request was already answered (a duplicate), or nobody asked. An expired slot leaves an *outstanding* mark on
its key (at most one per key): the next reply with that key is presumed to be the late answer to the expired
request, counted stale and never matched, even if a slot with that key is open at the time.

The one-reply ambiguity: replies carry no sequence number, so the late answer to an expired request and the
prompt answer to a newer request with the same key cannot be told apart. If the expired request was lost (or
its reply was) rather than late, the mark wrongly discards the first reply after it, and that cycle reports
no reply for the key. So that a lost frame costs at most that one extra cycle (and does not re-arm itself for
ever), a mark consumed while a slot with its key was open is not re-armed when that slot then expires too;
the price is that a drive whose replies are late in two consecutive cycles can have the second late reply
matched to the third cycle's request, i.e. data one cycle old. Reply latency above a cycle shows up as
repeated ``timeouts`` and ``stale_frames`` in the counters either way. For the same reason a duplicated
reply is only recognised as stale while no newer request with its key is open: a copy that arrives after the
next request with that key went out is taken as its answer.

Counters
--------
:class:`MotorCounters` per motor id (created when a motor is first addressed or first heard from) and one
:class:`BusCounters` per transport. After every cycle ``sent == replied + timeouts`` for each motor, except that
a request the RS485 backend had no time left to send counts a timeout without a send (and one
``BusCounters.skipped_requests``).
"""

from __future__ import annotations

import time
import types
from abc import ABC, abstractmethod
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Final, NamedTuple, Self

from motion.errors import TransportError
from motion.protocol import Command, Message, MultiMotorTorque
from motion.protocol.compiled import frozen_builder
from motion.protocol.table import MULTI_TORQUE_MOTOR_IDS, command_of

#: ``tap(time_s, received, arbitration_id, data)``: called with every frame a backend sends (``received`` False) or
#: takes in (True), at the transport clock's time; ``arbitration_id`` is None on RS485, where ``data`` is the bytes as
#: written to or read from the port (a read may hold part of a frame, or several). It runs on the control path: it
#: must be quick and must not raise.
FrameTap = Callable[[float, bool, int | None, bytes], None]

#: Slot states.
_NOT_SENT: Final = 0
_OPEN: Final = 1
_FILLED: Final = 2
_EXPIRED: Final = 3


@dataclass(frozen=True, slots=True)
class Request:
    """One request of a control cycle.

    Attributes:
        motor_id: drive id 1..32; ignored for :class:`~motion.protocol.MultiMotorTorque` (motors 1..4).
        message: the request message.
    """

    motor_id: int
    message: Message


@dataclass(frozen=True, slots=True)
class Reply:
    """The outcome of one expected reply.

    Attributes:
        motor_id: the drive that was expected to answer.
        request: the request message this reply belongs to.
        message: the decoded reply, or None when none arrived by the deadline.
        received_s: time of the transport's clock when the reply was taken in, or None.
    """

    motor_id: int
    request: Message
    message: Message | None
    received_s: float | None

    @property
    def ok(self) -> bool:
        """True when a reply arrived in time."""
        return self.message is not None


# Batch shapes whose slot layout is kept (a control loop uses a handful: its batch plus each round-robin read).
_MAX_PLANS: Final = 64


class _Plan(NamedTuple):
    """The slot layout of one batch shape (shared by every cycle of that shape; never changed once made)."""

    request_first_slot: list[int]
    slot_motor: list[int]
    slot_key: list[int]
    slot_next: list[int]
    first_slot_of_key: dict[int, int]
    slot_counters: list[MotorCounters]


def _key_of(request: Request) -> int:
    """The reply key a request expects (motor id << 8 | command byte; -1 for the 0x280 frame, -2 for no command)."""
    message = request.message
    if isinstance(message, MultiMotorTorque):
        return -1
    command = command_of(message)
    return -2 if command is None else request.motor_id << 8 | command


# Replies are built for every expected reply of every cycle: the slot-setting constructor (see frozen_builder).
_NEW_REPLY: Final = frozen_builder(Reply)


@dataclass(slots=True)
class MotorCounters:
    """Per-motor frame counters (mutable, updated by every cycle).

    Attributes:
        sent: requests that went out to the motor (the 0x280 frame counts once for each of motors 1..4).
        replied: replies matched to a request.
        timeouts: expected replies that had not arrived by their deadline (including skipped requests).
        bad_frames: frames for this motor that failed to decode (bad length, unknown command, bad field; on
            RS485 also corrupt bytes seen while waiting for this motor's reply).
        stale_frames: valid replies that were not matched (late, duplicated, or unsolicited).
    """

    sent: int = 0
    replied: int = 0
    timeouts: int = 0
    bad_frames: int = 0
    stale_frames: int = 0


@dataclass(slots=True)
class BusCounters:
    """Counters of the bus as a whole.

    Attributes:
        cycles: calls of ``transact``.
        unknown_id_frames: CAN frames whose arbitration id is not a drive reply id (0x141..0x160).
        bad_frames: corrupt frames that cannot be attributed to a motor (RS485: seen before a request was sent).
        dropped_bytes: RS485 bytes the stream parser discarded (garbage, corrupt and truncated frames).
        skipped_requests: RS485 requests not sent because the cycle's deadline had passed.
    """

    cycles: int = 0
    unknown_id_frames: int = 0
    bad_frames: int = 0
    dropped_bytes: int = 0
    skipped_requests: int = 0


class Transport(ABC):
    """A bus that exchanges one batch of requests and replies per control cycle.

    Not thread-safe: one control loop owns a transport. Use it as a context manager, or call :meth:`close`.

    Args:
        clock: time source in seconds; ``deadline_s`` of :meth:`transact` is an absolute time of this clock.
            It must advance at the rate of real time (the backends wait on the port for ``deadline_s - clock()``
            real seconds), so it may be offset from :func:`time.monotonic` but not frozen.
    """

    def __init__(self, *, clock: Callable[[], float] = time.monotonic) -> None:
        self.clock = clock
        self.bus_counters = BusCounters()
        #: Optional observer of every frame (a bus trace); see :data:`FrameTap`.
        self.frame_tap: FrameTap | None = None
        #: Called (in order, from the closing thread) before the port is released: a control loop that owns the bus
        #: halts its axes and ends there, so that closing the port never leaves a motor running.
        self.close_hooks: list[Callable[[], None]] = []
        self._counters: dict[int, MotorCounters] = {}
        self._counters_view: Mapping[int, MotorCounters] = types.MappingProxyType(self._counters)
        self._closed = False
        # Outstanding marks survive between cycles; everything below is per-cycle state in reused containers.
        self._outstanding: set[int] = set()
        self._ambiguous: set[int] = set()
        self._request_first_slot: list[int] = []
        self._slot_motor: list[int] = []
        self._slot_key: list[int] = []
        self._slot_request: list[Message] = []
        self._slot_state: list[int] = []
        self._slot_message: list[Message | None] = []
        self._slot_time: list[float | None] = []
        self._slot_next: list[int] = []
        self._slot_counters: list[MotorCounters] = []
        self._first_slot_of_key: dict[int, int] = {}
        # Plans of the batch shapes seen (a control loop sends the same few shapes every cycle): the slot layout,
        # keyed by the requests' (motor id, command) sequence, is laid out once per shape.
        self._plans: dict[tuple[int, ...], _Plan] = {}
        self._last_slot_of_key: dict[int, int] = {}
        self._open_slots = 0

    # --- public API ---------------------------------------------------------------------------------------

    @property
    def counters(self) -> Mapping[int, MotorCounters]:
        """Per-motor counters by motor id (a live read-only view)."""
        return self._counters_view

    @property
    def closed(self) -> bool:
        """True once :meth:`close` was called."""
        return self._closed

    def transact(self, requests: Sequence[Request], deadline_s: float) -> list[Reply]:
        """Send one cycle's requests and collect their replies until ``deadline_s``.

        Args:
            requests: the cycle's requests, sent in this order.
            deadline_s: absolute time of :attr:`clock` by which the call returns.

        Returns:
            One :class:`Reply` per expected reply, in request order (a 0x280 request yields four, for motors
            1..4, in its place); ``message`` is None for a reply that did not arrive by the deadline.

        Raises:
            EncodeError: a request cannot be encoded on this transport (nothing was sent).
            TransportError: the transport is closed, or the bus failed (bus off, port gone, write refused).
        """
        if self._closed:
            raise TransportError(f"{self.describe()} is closed")
        self._prepare(requests)
        self._plan(requests)
        self.bus_counters.cycles += 1
        self._exchange(deadline_s)
        return self._finish()

    def close(self) -> None:
        """Run the close hooks, then release the bus or port; safe to call more than once."""
        if not self._closed:
            try:
                for hook in list(self.close_hooks):
                    hook()
            finally:
                self._closed = True
                self._close()

    def __enter__(self) -> Self:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: types.TracebackType | None
    ) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"<{type(self).__name__} {self.describe()}{' closed' if self._closed else ''}>"

    # --- template methods ---------------------------------------------------------------------------------

    @abstractmethod
    def describe(self) -> str:
        """A short name of the bus or port for messages (``"can virtual:bus0"``, ``"rs485 /dev/ttyUSB0"``)."""

    @abstractmethod
    def _prepare(self, requests: Sequence[Request]) -> None:
        """Encode the cycle's requests, before anything is sent.

        Raises:
            EncodeError: a request cannot be carried by this transport.
        """

    @abstractmethod
    def _exchange(self, deadline_s: float) -> None:
        """Send the prepared requests and feed received replies to :meth:`_offer` until all slots are closed or
        ``deadline_s`` passes. Call :meth:`_sent` after each request went out.

        Raises:
            TransportError: the bus failed.
        """

    @abstractmethod
    def _close(self) -> None:
        """Release the bus or port (called once)."""

    # --- helpers for the backends ---------------------------------------------------------------------------

    def motor_counters(self, motor_id: int) -> MotorCounters:
        """The counters of ``motor_id``, created on first use."""
        counters = self._counters.get(motor_id)
        if counters is None:
            counters = self._counters[motor_id] = MotorCounters()
        return counters

    def _plan(self, requests: Sequence[Request]) -> None:
        """Lay out the cycle's expected replies (slots): from the plan of this batch shape, made on its first use."""
        shape = tuple([_key_of(request) for request in requests])
        plan = self._plans.get(shape)
        if plan is None:
            plan = self._make_plan(requests, shape)
        (
            self._request_first_slot,
            self._slot_motor,
            self._slot_key,
            self._slot_next,
            self._first_slot_of_key,
            self._slot_counters,
        ) = plan
        n = len(plan.slot_motor)
        self._slot_request = [r.message for r in requests] if n == len(requests) else self._expand(requests)
        self._slot_state = [_NOT_SENT] * n
        self._slot_message = [None] * n
        self._slot_time = [None] * n
        self._ambiguous.clear()
        self._open_slots = 0

    @staticmethod
    def _expand(requests: Sequence[Request]) -> list[Message]:
        """The request of every slot (a 0x280 request has four)."""
        slots: list[Message] = []
        for request in requests:
            message = request.message
            slots.extend(
                [message] * len(MULTI_TORQUE_MOTOR_IDS) if isinstance(message, MultiMotorTorque) else [message]
            )
        return slots

    def _make_plan(self, requests: Sequence[Request], shape: tuple[int, ...]) -> _Plan:
        # New containers: the current ones may belong to the plan of another shape.
        first_slot: list[int] = []
        self._request_first_slot = first_slot
        self._slot_motor, self._slot_key, self._slot_next, self._slot_counters = [], [], [], []
        self._first_slot_of_key = {}
        self._last_slot_of_key.clear()
        for request in requests:
            first_slot.append(len(self._slot_motor))
            message = request.message
            if isinstance(message, MultiMotorTorque):
                for motor_id in MULTI_TORQUE_MOTOR_IDS:
                    self._add_slot(motor_id, Command.TORQUE)
            else:
                command = command_of(message)
                # _prepare already rejected messages without a command byte.
                assert command is not None
                self._add_slot(request.motor_id, command)
        first_slot.append(len(self._slot_motor))
        plan = _Plan(
            first_slot,
            self._slot_motor,
            self._slot_key,
            self._slot_next,
            self._first_slot_of_key,
            self._slot_counters,
        )
        if len(self._plans) >= _MAX_PLANS:  # a program sending ever new shapes: keep memory bounded
            self._plans.clear()
        self._plans[shape] = plan
        return plan

    def _add_slot(self, motor_id: int, command: int) -> None:
        slot, key = len(self._slot_motor), motor_id << 8 | command
        self._slot_motor.append(motor_id)
        self._slot_key.append(key)
        self._slot_next.append(-1)
        self._slot_counters.append(self.motor_counters(motor_id))
        # Chain the slots of each key in request order, so that replies fill them first-in, first-out.
        last = self._last_slot_of_key.get(key)
        if last is None:
            self._first_slot_of_key[key] = slot
        else:
            self._slot_next[last] = slot
        self._last_slot_of_key[key] = slot

    def _sent(self, index: int) -> None:
        """Request ``index`` went out: open its slots."""
        state, counters = self._slot_state, self._slot_counters
        for slot in range(self._request_first_slot[index], self._request_first_slot[index + 1]):
            state[slot] = _OPEN
            self._open_slots += 1
            counters[slot].sent += 1

    def _answered(self, index: int) -> bool:
        """True when no slot of request ``index`` is still open."""
        state, first = self._slot_state, self._request_first_slot
        return all(state[slot] != _OPEN for slot in range(first[index], first[index + 1]))

    def _offer(self, motor_id: int, message: Message) -> None:
        """Take in one decoded reply: fill the first open slot with its key, or count it stale."""
        counters = self._counters.get(motor_id) or self.motor_counters(motor_id)
        command = command_of(message)
        if command is None:
            counters.bad_frames += 1
            return
        key = motor_id << 8 | command
        slot = self._first_slot_of_key.get(key, -1)
        while slot >= 0 and self._slot_state[slot] != _OPEN:
            slot = self._slot_next[slot]
        if key in self._outstanding:
            # Presumed the late answer to an expired request; see the module docstring for the ambiguity.
            self._outstanding.discard(key)
            if slot >= 0:
                self._ambiguous.add(key)
            counters.stale_frames += 1
            return
        if slot < 0:
            counters.stale_frames += 1
            return
        self._slot_state[slot] = _FILLED
        self._slot_message[slot] = message
        self._slot_time[slot] = self.clock()
        self._open_slots -= 1
        counters.replied += 1

    def _expire(self, index: int) -> None:
        """Close the still open slots of request ``index`` as timed out and mark their keys outstanding."""
        for slot in range(self._request_first_slot[index], self._request_first_slot[index + 1]):
            if self._slot_state[slot] == _OPEN:
                self._expire_slot(slot)

    def _expire_slot(self, slot: int) -> None:
        self._slot_state[slot] = _EXPIRED
        self._open_slots -= 1
        self._slot_counters[slot].timeouts += 1
        key = self._slot_key[slot]
        if key not in self._ambiguous:
            self._outstanding.add(key)

    def _finish(self) -> list[Reply]:
        state = self._slot_state
        for slot in range(len(state)):
            if state[slot] == _OPEN:
                self._expire_slot(slot)
            elif state[slot] == _NOT_SENT:
                state[slot] = _EXPIRED
                self._slot_counters[slot].timeouts += 1
                self.bus_counters.skipped_requests += 1
        new_reply = _NEW_REPLY
        return [
            new_reply(motor_id, request, message, received_s)
            for motor_id, request, message, received_s in zip(
                self._slot_motor, self._slot_request, self._slot_message, self._slot_time, strict=True
            )
        ]
