"""Scripted drive peers and shared helpers for the transport tests (this module holds no tests).

A peer is a thread on the other end of a real bus or port. It decodes the host's requests with the protocol codec
and answers each with a reply whose ``encoder`` field is a *tag*: how many requests with that (motor, command) the
drive has received, so a test can tell which request a matched reply answers. Like a real drive it answers in
order: a delayed reply also delays the replies after it.
"""

from __future__ import annotations

import heapq
import itertools
import threading
import time
from abc import ABC, abstractmethod
from collections import Counter
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import Generic, TypeVar

from motion.protocol import Bare, Command, ErrorFlags, Message, MotorState, MultiMotorTorque, Status1
from motion.protocol.table import MULTI_TORQUE_MOTOR_IDS, command_of
from motion.transport import Request, Transport

PayloadT = TypeVar("PayloadT")

#: Slack on top of a deadline that a loaded host meets: a CPU shared with busy loops (../shared/tools/slow-host) can
#: keep a thread waiting a tenth of a second. What the asserts tell apart is "returned at its deadline" from "waited
#: for the reply that never comes" (the scripted silent drive never answers).
MARGIN_S = 0.25


class LateHost:
    """A host that is descheduled right after each request goes out (``slow-host``'s busy loops do it at random): the
    transport's ``clock`` and ``frame_tap``. Each outgoing frame is followed by a pause in which the drives answer,
    after which the clock is past any deadline of the cycle."""

    def __init__(self, pause_s: float = 0.05) -> None:
        self.pause_s = pause_s
        self.offset_s = 0.0

    def clock(self) -> float:
        return time.monotonic() + self.offset_s

    def tap(self, _time_s: float, incoming: bool, _ident: int | None, _data: bytes) -> None:
        if not incoming:
            time.sleep(self.pause_s)
            self.offset_s += 3600.0


def status2(motor_id: int) -> Request:
    """A 0x9C read request (replied with a tagged MotorState)."""
    return Request(motor_id, Bare(Command.READ_STATUS_2))


def assert_balanced(transport: Transport) -> None:
    """Every expected reply was either matched or timed out, per motor (and skipped requests on the bus)."""
    counters = list(transport.counters.values())
    skipped = transport.bus_counters.skipped_requests
    if not skipped:
        assert all(c.sent == c.replied + c.timeouts for c in counters), transport.counters
    assert sum(c.sent for c in counters) + skipped == sum(c.replied + c.timeouts for c in counters)


@dataclass
class Script(Generic[PayloadT]):
    """How one drive answers.

    Attributes:
        delays_s: delay of the 1st, 2nd, ... reply; replies beyond the list are immediate.
        silent: never answer.
        edit: turns the encoded reply into what is actually sent (nothing, twice, corrupted, on another id...).
    """

    delays_s: list[float] = field(default_factory=list)
    silent: bool = False
    edit: Callable[[PayloadT], list[PayloadT]] | None = None


def reply_for(command: Command, motor_id: int, tag: int) -> Message:
    """The reply a drive gives to ``command``, tagged (``encoder`` or ``voltage_v``)."""
    if command in (Command.READ_STATUS_1, Command.CLEAR_ERRORS):
        return Status1(command, temperature_c=motor_id, voltage_v=float(tag), errors=ErrorFlags.NONE)
    return MotorState(command, temperature_c=motor_id, iq_a=0.0, speed_dps=0, encoder=tag)


def tag_of(message: Message | None) -> int:
    """The tag :func:`reply_for` put in a reply."""
    if isinstance(message, MotorState):
        return message.encoder
    assert isinstance(message, Status1), message
    return round(message.voltage_v)


class ScriptedDrives(threading.Thread, ABC, Generic[PayloadT]):
    """Emulated drives answering on a bus or port, following one :class:`Script` per motor id.

    Attributes:
        requests: every decoded request, as ``(motor id or None for 0x280, message)``.
    """

    def __init__(self, scripts: dict[int, Script[PayloadT]] | None = None) -> None:
        super().__init__(daemon=True)
        self.scripts: dict[int, Script[PayloadT]] = scripts or {}
        self.requests: list[tuple[int | None, Message]] = []
        self._tags: Counter[tuple[int, int]] = Counter()
        self._free_at_s: dict[int, float] = {}
        self._due: list[tuple[float, int, PayloadT]] = []
        self._order = itertools.count()
        self._stop_event = threading.Event()
        self.error: BaseException | None = None

    @abstractmethod
    def poll(self, timeout_s: float) -> Iterable[tuple[int | None, Message]]:
        """Wait up to ``timeout_s`` for requests and return the decoded ones."""

    @abstractmethod
    def encode(self, message: Message, motor_id: int) -> PayloadT:
        """Encode a reply."""

    @abstractmethod
    def send(self, payload: PayloadT) -> None:
        """Put a payload on the wire."""

    def run(self) -> None:
        try:
            while not self._stop_event.is_set():
                now = time.monotonic()
                wait_s = min(0.002, self._due[0][0] - now) if self._due else 0.002
                for motor_id, message in self.poll(max(wait_s, 0.0)):
                    self.requests.append((motor_id, message))
                    self._schedule(motor_id, message)
                now = time.monotonic()
                while self._due and self._due[0][0] <= now:
                    self.send(heapq.heappop(self._due)[2])
        except BaseException as exc:  # reported by stop(), so a broken peer fails the test instead of hanging it
            self.error = exc

    def stop(self) -> None:
        """Stop the thread and re-raise what broke it, if anything."""
        self._stop_event.set()
        self.join(timeout=5.0)
        if self.error is not None:
            raise self.error

    def _schedule(self, motor_id: int | None, message: Message) -> None:
        if isinstance(message, MultiMotorTorque):
            targets: tuple[int, ...] = MULTI_TORQUE_MOTOR_IDS
            command = Command.TORQUE
        else:
            assert motor_id is not None
            targets = (motor_id,)
            found = command_of(message)
            assert found is not None
            command = found
        now = time.monotonic()
        for target in targets:
            self._tags[target, command] += 1
            tag = self._tags[target, command]
            script = self.scripts.get(target, Script())
            if script.silent:
                continue
            delay_s = script.delays_s[tag - 1] if tag <= len(script.delays_s) else 0.0
            due_s = max(now + delay_s, self._free_at_s.get(target, 0.0))
            self._free_at_s[target] = due_s
            payload = self.encode(reply_for(command, target, tag), target)
            for edited in script.edit(payload) if script.edit else [payload]:
                heapq.heappush(self._due, (due_s, next(self._order), edited))
