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

A port that is gone
-------------------
A backend whose port fails in a way that lasts (:func:`port_gone`: a device unplugged, a dead adapter, the far end of
a pseudo-terminal closed) raises :class:`~motion.errors.PortLost`; from then on the transport is :attr:`~Transport.lost`
and counts as :attr:`~Transport.closed` (nothing more can be sent: a control loop on it ends, BUS_LOST), and
:meth:`~Transport.close` releases what is left without raising. Any other failure (a full transmit queue, a write that
timed out) raises a plain :class:`~motion.errors.TransportError` and leaves the transport open for the next try.
"""

from __future__ import annotations

import errno
import functools
import logging
import select
import time
import types
from abc import ABC, abstractmethod
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Final, NamedTuple

from motion.errors import PortLost, TransportError

try:
    import termios
except ImportError:  # (not a POSIX system: pyserial's ports raise OSError alone there)
    termios = None  # type: ignore[assignment]
from motion.closing import Closing
from motion.protocol import Message, MultiMotorTorque
from motion.protocol.generation import GENERATIONS
from motion.protocol.table import ADDRESS_STRIDE, ProtocolFamily
from motion.transport.plan import EXPIRED, FILLED, MULTI_KEY, NOT_SENT, OPEN, Plan

if TYPE_CHECKING:
    from motion.transport.identity import Identity
    from motion.transport.portlock import PortLock

#: ``tap(time_s, received, arbitration_id, data)``: called with every frame a backend sends (``received`` False) or
#: takes in (True), at the transport clock's time; ``arbitration_id`` is None on RS485, where ``data`` is the bytes as
#: written to or read from the port (a read may hold part of a frame, or several). It runs on the control path: it
#: must be quick and must not raise.
FrameTap = Callable[[float, bool, int | None, bytes], None]

logger = logging.getLogger("motion.transport")

#: Error numbers of a device that is gone for good (EIO: a terminal hung up, the far end of a pseudo-terminal closed;
#: ENXIO, ENODEV: a device unplugged; EBADF: its descriptor closed), as against a refusal that may pass (a full
#: transmit queue, a write timeout).
GONE_ERRNOS: Final = frozenset({errno.EIO, errno.ENXIO, errno.ENODEV, errno.EBADF})
#: What a port's terminal calls raise where pyserial does not wrap them: ``termios.error`` (not an OSError; its
#: arguments are the errno and its text), e.g. from ``flush()``'s tcdrain on a pty whose far end closed.
TERMINAL_ERRORS: Final[tuple[type[Exception], ...]] = (termios.error,) if termios is not None else ()
#: Everything a serial port's read, write or flush raises when it fails (pyserial's SerialException is an OSError).
PORT_ERRORS: Final[tuple[type[Exception], ...]] = (OSError, ValueError, *TERMINAL_ERRORS)
#: What ``poll`` reports on a descriptor whose device is gone: hung up, or no longer open.
_GONE_EVENTS: Final = getattr(select, "POLLHUP", 0) | getattr(select, "POLLNVAL", 0)


def port_gone(exc: BaseException, fd: int | None = None) -> bool:
    """True when the failure ``exc`` of a read or write on a port says the port is gone for good: an OSError of
    :data:`GONE_ERRNOS` anywhere in its chain (python-can and pyserial wrap the system's error in their own), or the
    port's descriptor ``fd`` hung up."""
    seen: set[int] = set()
    cause: BaseException | None = exc
    while cause is not None and id(cause) not in seen:
        if isinstance(cause, OSError) and cause.errno in GONE_ERRNOS:
            return True
        if isinstance(cause, TERMINAL_ERRORS) and cause.args and cause.args[0] in GONE_ERRNOS:
            return True
        seen.add(id(cause))
        cause = cause.__cause__ or cause.__context__
    if fd is None or not hasattr(select, "poll"):
        return False
    poller = select.poll()
    poller.register(fd, select.POLLIN)
    try:
        return any(events & _GONE_EVENTS for _, events in poller.poll(0))
    except OSError:
        return True


def port_lost(text: str) -> PortLost:
    """The :class:`PortLost` of a failure that ``text`` describes."""
    return PortLost(f"{text} (the port is gone: adapter unplugged or dead?)")


def port_failure(text: str, exc: BaseException, fd: int | None = None) -> TransportError:
    """The error to raise for ``exc``, a failed read or write on a port that ``text`` describes: :class:`PortLost`
    when the port is gone (:func:`port_gone`), else a :class:`TransportError`."""
    return port_lost(text) if port_gone(exc, fd) else TransportError(text)


#: Plans a transport keeps (a supervisor's status read rotates over the motors: one shape per motor).
_PLANS_KEPT: Final = 64


@dataclass(frozen=True, slots=True)
class Request:
    """One request of a control cycle.

    Attributes:
        motor_id: drive id 1..32; ignored for :class:`~motion.protocol.MultiMotorTorque` (motors 1..4).
        message: the request message.
    """

    motor_id: int
    message: Message


class Reply(NamedTuple):
    """The outcome of one expected reply.

    A named tuple rather than a frozen dataclass: one is built for every expected reply of every cycle, and a tuple
    is built in a third of the time. Immutable all the same.

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


# Builds a Reply from its four fields in one tuple (what the named tuple's own constructor does, minus a call).
_new_reply: Final[Callable[[tuple[int, Message, Message | None, float | None]], Reply]] = functools.partial(
    tuple.__new__, Reply
)


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
        dropped_bytes: bytes discarded as junk: on RS485 by the stream parser (garbage, corrupt and truncated
            frames), on slcan by the shim (lines longer than any slcan line; updated after a cycle with a reply
            missing).
        skipped_requests: RS485 requests not sent because the cycle's deadline had passed.
    """

    cycles: int = 0
    unknown_id_frames: int = 0
    bad_frames: int = 0
    dropped_bytes: int = 0
    skipped_requests: int = 0


def probe_in_turn(
    bus: Transport, ids: Sequence[int], window_s: float, sibling: Callable[[ProtocolFamily], Transport]
) -> dict[int, ProtocolFamily]:
    """The generation of each of ``ids`` that answers a status read (0x9A) in ``bus``'s framing, then of those
    silent to it in the other's (``sibling(family)``: a transport of that family on the same link, not owning it),
    each within ``window_s`` (a line where the framings differ: RS485).

    Raises:
        TransportError: the bus failed.
    """
    found: dict[int, ProtocolFamily] = {}
    silent = list(ids)
    for family in (bus.family, *(f for f in ProtocolFamily if f is not bus.family)):
        if not silent:
            break
        # (a transport of lines in different generations asks in each through a sibling speaking it on every line)
        speaker = bus if bus.families == (family,) * len(bus.families) else sibling(family)
        request = speaker.generation.status_read
        replies = speaker.transact([Request(i, request) for i in silent], speaker.clock() + window_s)
        found.update((r.motor_id, family) for r in replies if r.message is not None)
        silent = [i for i in silent if i not in found]
    return dict(sorted(found.items()))


class Transport(ABC, Closing):
    """A bus that exchanges one batch of requests and replies per control cycle.

    Not thread-safe: one control loop owns a transport. Use it as a context manager, or call :meth:`close`.

    Args:
        clock: time source in seconds; ``deadline_s`` of :meth:`transact` is an absolute time of this clock.
            It must advance at the rate of real time (the backends wait on the port for ``deadline_s - clock()``
            real seconds), so it may be offset from :func:`time.monotonic` but not frozen.
    """

    def __init__(
        self, *, clock: Callable[[], float] = time.monotonic, family: ProtocolFamily = ProtocolFamily.V2
    ) -> None:
        self.clock = clock
        #: The protocol generation the drives on this bus speak (their frames are encoded and decoded with it); of
        #: an arm's several buses, the first one's (:attr:`families`: each one's).
        self.family = ProtocolFamily(family)
        #: Its wire protocol: the codec the backends encode and decode with.
        self.generation = GENERATIONS[self.family]
        #: The generation of each bus, by bus index (the address's, ``motion.protocol.table.split_address``): one
        #: bus, its :attr:`family`.
        self.families: tuple[ProtocolFamily, ...] = (self.family,)
        #: What the drives told of themselves at connect, by motor id (:mod:`motion.transport.identity`).
        self.identities: dict[int, Identity] = {}
        self.bus_counters = BusCounters()
        #: Optional observer of every frame (a bus trace); see :data:`FrameTap`.
        self.frame_tap: FrameTap | None = None
        #: Called (in order, from the closing thread) before the port is released: a control loop that owns the bus
        #: halts its axes and ends there, so that closing the port never leaves a motor running.
        self.close_hooks: list[Callable[[], None]] = []
        self._counters: dict[int, MotorCounters] = {}
        self._counters_view: Mapping[int, MotorCounters] = types.MappingProxyType(self._counters)
        self._closed = False
        self._lost: PortLost | None = None
        # The session lock on the port this transport opened (motion.transport.portlock), released when it closes; None
        # where it opened none (a simulated bus, a port given to it) or handed its port on (_hand_over_lock).
        self._port_lock: PortLock | None = None
        # Outstanding marks survive between cycles. The slots' layout comes from a plan reused for every batch of the
        # same shape (see _plan); the rest is the cycle's own state.
        self._outstanding: set[int] = set()
        self._ambiguous: set[int] = set()
        self._plans: dict[tuple[int, ...], Plan] = {}
        self._slots = Plan.empty()
        self._slot_request: list[Message] = []
        self._slot_state: list[int] = []
        self._slot_message: list[Message | None] = []
        self._slot_time: list[float | None] = []
        self._open_slots = 0

    # --- public API ---------------------------------------------------------------------------------------

    @property
    def counters(self) -> Mapping[int, MotorCounters]:
        """Per-motor counters by motor id (a live read-only view)."""
        return self._counters_view

    @property
    def closed(self) -> bool:
        """True once :meth:`close` was called, or once the port was :attr:`lost` (nothing can be sent any more)."""
        return self._closed or self._lost is not None

    @property
    def lost(self) -> PortLost | None:
        """The error that found the port gone for good (see the module docstring), or None; kept after :meth:`close`."""
        return self._lost

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
            PortLost: the port is gone (now or before): the transport counts as closed from now on.
            TransportError: the transport is closed, or the bus failed (bus off, write refused).
        """
        if self._lost is not None:
            raise PortLost(str(self._lost))
        if self._closed:
            raise TransportError(f"{self.describe()} is closed")
        self._prepare(requests)
        self._plan(requests)
        self.bus_counters.cycles += 1
        try:
            self._exchange(deadline_s)
        except PortLost as exc:
            self._lost = exc
            raise
        return self._finish()

    def junk_note(self) -> str:
        """For an error about missing replies: the junk the line carried (``BusCounters.dropped_bytes``), as a clause
        to append (``"; rs485 /dev/ttyUSB0 dropped 4096 bytes of junk ..."``), or "" when none was dropped."""
        dropped = self.bus_counters.dropped_bytes
        if not dropped:
            return ""
        return f"; {self.describe()} dropped {dropped} bytes of junk (is the port's far end a drive bus adapter?)"

    def probe_families(self, ids: Sequence[int], window_s: float) -> dict[int, ProtocolFamily] | None:
        """Each of ``ids`` that answers a status read within ``window_s``, with the protocol generation its answer
        shows (:mod:`motion.transport.detect`; on RS485 in each framing in turn, :func:`probe_in_turn`); None where
        this transport cannot tell.

        Raises:
            TransportError: the bus failed.
        """
        return None

    def bus_times_s(self) -> Mapping[str, float] | None:
        """An arm on several buses: how long each bus's share of the last :meth:`transact` took, s, by bus name (the
        rate check names the bus that limits); None on one bus."""
        return None

    def _read_behind_the_slots(self) -> None:
        """The port was read past the slots (a generation probe drains and reads it at the frame level): the late
        answers that outstanding marks wait for were taken there, so no mark may swallow the next real answer (scan's
        second try lost every drive that had answered the first one late)."""
        self._outstanding.clear()
        self._ambiguous.clear()

    def request_wire_s(self, requests: Sequence[Request]) -> float | None:
        """The time the frames of ``requests`` occupy the wire, s (each encoded as :meth:`transact` would), or None
        where this transport does not know its wire's speed. The rate check adds what a cycle's set-points take on
        the wire beyond its measuring reads (an RS485 0xA4 frame is three times a read's).

        Raises:
            EncodeError: a request cannot be encoded on this transport.
        """
        return None

    def family_of(self, address: int) -> ProtocolFamily:
        """The generation the drive at ``address`` speaks (its bus's)."""
        families = self.families
        return families[address // ADDRESS_STRIDE] if len(families) > 1 else families[0]

    def with_family(self, family: ProtocolFamily) -> Transport:
        """A transport over the same link speaking ``family``, which takes the link over (closing it closes the
        link; this one then no longer does).

        Raises:
            TransportError: this transport cannot hand its link over.
        """
        raise TransportError(f"{self.describe()} cannot switch to the {ProtocolFamily(family).value} protocol family")

    def with_families(self, families: Sequence[ProtocolFamily]) -> Transport:
        """A transport over the same links speaking ``families[k]`` on bus ``k`` (itself where they are what it
        speaks; else it takes the links over, as :meth:`with_family`).

        Raises:
            TransportError: this transport cannot hand its link over, or speaks one generation on all its buses.
        """
        wanted = tuple(ProtocolFamily(f) for f in families)
        if wanted == self.families:
            return self
        if len(set(wanted)) == 1 and len(wanted) == len(self.families):
            return self.with_family(wanted[0])
        told = ", ".join(f.value for f in wanted)
        raise TransportError(f"{self.describe()} speaks one protocol generation on all its buses, not {told}")

    def close(self) -> None:
        """Run the close hooks, then release the bus or port; safe to call more than once. A port that cannot be
        released cleanly (a dead adapter refuses its closing command) is logged, never raised: the error that ended
        the session is the one to see."""
        if not self._closed:
            try:
                for hook in list(self.close_hooks):
                    hook()
            finally:
                self._closed = True
                try:
                    self._close()
                except TransportError as exc:  # expected of a port that is gone
                    logger.log(logging.WARNING if self._lost is None else logging.DEBUG, "%s", exc)
                finally:
                    if self._port_lock is not None:  # (after the port: no other session may open it before)
                        self._port_lock.release()

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
        ``deadline_s`` passes. Call :meth:`_sent` after each request went out (or :meth:`_sent_first` once for a batch
        sent back to back).

        Raises:
            TransportError: the bus failed.
        """

    @abstractmethod
    def _close(self) -> None:
        """Release the bus or port (called once).

        Raises:
            TransportError: it could not be released cleanly (logged by :meth:`close`).
        """

    # --- helpers for the backends ---------------------------------------------------------------------------

    def _hand_over_lock(self, successor: Transport) -> None:
        """``successor`` takes this transport's port over (it closes the port from now on): the port's session lock
        goes with it."""
        successor._port_lock, self._port_lock = self._port_lock, None

    def motor_counters(self, motor_id: int) -> MotorCounters:
        """The counters of ``motor_id``, created on first use."""
        counters = self._counters.get(motor_id)
        if counters is None:
            counters = self._counters[motor_id] = MotorCounters()
        return counters

    def _plan(self, requests: Sequence[Request]) -> None:
        """Lay out the cycle's expected replies (slots).

        A control loop sends batches of a few shapes (the same set-points every cycle, a rotating status read): the
        layout of a shape (keys, motors, counters, the first-in first-out chains) is built once and reused, so a
        cycle only computes the batch's keys and starts its own state.
        """
        signature = tuple(
            [
                MULTI_KEY - request.motor_id // ADDRESS_STRIDE  # (one per bus of an arm on several)
                if isinstance(request.message, MultiMotorTorque)
                # _prepare already rejected the messages without a command byte.
                else request.motor_id << 8 | request.message.command  # type: ignore[attr-defined]
                for request in requests
            ]
        )
        plan = self._plans.get(signature)
        if plan is None:
            if len(self._plans) >= _PLANS_KEPT:
                self._plans.clear()
            plan = self._plans[signature] = Plan.build(signature, requests, self.motor_counters)
        self._slots = plan
        self._slot_state = plan.not_sent.copy()
        self._slot_message = plan.no_messages.copy()
        self._slot_time = plan.no_times.copy()
        if plan.one_each:
            self._slot_request = [request.message for request in requests]
        else:
            self._slot_request = [requests[index].message for index in plan.slot_request]
        self._ambiguous.clear()
        self._open_slots = 0

    def _sent(self, index: int) -> None:
        """Request ``index`` went out: open its slots."""
        plan, state = self._slots, self._slot_state
        if plan.one_each:
            state[index] = OPEN
            plan.slot_counters[index].sent += 1
            self._open_slots += 1
            return
        first = plan.first_slot
        for slot in range(first[index], first[index + 1]):
            state[slot] = OPEN
            plan.slot_counters[slot].sent += 1
            self._open_slots += 1

    def _sent_first(self, count: int) -> None:
        """Requests ``0 .. count - 1`` went out, none of them before: open their slots (once for a batch sent back
        to back, instead of :meth:`_sent` for each)."""
        plan = self._slots
        end = plan.first_slot[count]
        self._slot_state[:end] = plan.all_open[:end]
        for counters in plan.slot_counters[:end]:
            counters.sent += 1
        self._open_slots += end

    def _answered(self, index: int) -> bool:
        """True when no slot of request ``index`` is still open."""
        plan, state = self._slots, self._slot_state
        if plan.one_each:
            return state[index] != OPEN
        first = plan.first_slot
        return all(state[slot] != OPEN for slot in range(first[index], first[index + 1]))

    def _offer(self, motor_id: int, message: Message) -> None:
        """Take in one decoded reply: fill the first open slot with its key, or count it stale."""
        counters = self._counters.get(motor_id)
        if counters is None:
            counters = self.motor_counters(motor_id)
        try:
            key: int = motor_id << 8 | message.command  # type: ignore[attr-defined]  # every reply class has one
        except AttributeError:  # (only the 0x280 request has none)
            counters.bad_frames += 1
            return
        plan, state = self._slots, self._slot_state
        slot = plan.first_slot_of_key.get(key, -1)
        while slot >= 0 and state[slot] != OPEN:
            slot = plan.slot_next[slot]
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
        state[slot] = FILLED
        self._slot_message[slot] = message
        self._slot_time[slot] = self.clock()
        self._open_slots -= 1
        counters.replied += 1

    def _expire(self, index: int) -> None:
        """Close the still open slots of request ``index`` as timed out and mark their keys outstanding."""
        first = self._slots.first_slot
        for slot in range(first[index], first[index + 1]):
            if self._slot_state[slot] == OPEN:
                self._expire_slot(slot)

    def _expire_slot(self, slot: int) -> None:
        plan = self._slots
        self._slot_state[slot] = EXPIRED
        self._open_slots -= 1
        plan.slot_counters[slot].timeouts += 1
        key = plan.slot_key[slot]
        if key not in self._ambiguous:
            self._outstanding.add(key)

    def _finish(self) -> list[Reply]:
        state, plan = self._slot_state, self._slots
        if OPEN in state or NOT_SENT in state:
            for slot in range(len(state)):
                if state[slot] == OPEN:
                    self._expire_slot(slot)
                elif state[slot] == NOT_SENT:
                    state[slot] = EXPIRED
                    plan.slot_counters[slot].timeouts += 1
                    self.bus_counters.skipped_requests += 1
        return list(
            map(_new_reply, zip(plan.slot_motor, self._slot_request, self._slot_message, self._slot_time, strict=True))
        )
