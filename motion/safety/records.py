"""What the supervisor reports: the fault the arm is faulted for, and the session's bounded fault and halt records.

:class:`FaultLog` holds them for the supervisor and the modules that share its work: the fault goes out with the
state in every snapshot, a record is kept of every fault and of every halt (when it was detected, when its reaction
went out, what that was), and a cause that repeats while halted is recorded once.
"""

from __future__ import annotations

import collections
import logging
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from enum import StrEnum
from typing import Final, TypeVar, overload

from motion.control.clock import Clock
from motion.control.snapshot import SnapshotPublisher
from motion.errors import FaultKind, MotionFault
from motion.protocol import Command
from motion.safety.states import ArmState, StateMachine

logger = logging.getLogger("motion.safety")

_T = TypeVar("_T")
#: The most fault and halt records kept (a cause that repeats is recorded once; this bounds what a long session keeps).
RECORDS_KEPT = 1000


class Records(Sequence[_T]):
    """A session's fault or halt records, bounded: the first ``kept // 2`` (the cause is among them) and the latest
    ``kept - kept // 2``; :attr:`dropped` counts those left out between."""

    def __init__(self, kept: int) -> None:
        self._first: list[_T] = []
        self._first_kept = kept // 2
        self._latest: collections.deque[_T] = collections.deque(maxlen=kept - kept // 2)
        #: Records left out between the first and the latest.
        self.dropped = 0

    def append(self, record: _T) -> None:
        """Keep ``record`` (and leave out the oldest of the latest, once full)."""
        if len(self._first) < self._first_kept:
            self._first.append(record)
            return
        if len(self._latest) == self._latest.maxlen:
            self.dropped += 1
        self._latest.append(record)

    def __len__(self) -> int:
        return len(self._first) + len(self._latest)

    @overload
    def __getitem__(self, index: int) -> _T: ...
    @overload
    def __getitem__(self, index: slice) -> list[_T]: ...
    def __getitem__(self, index: int | slice) -> _T | list[_T]:
        return [*self._first, *self._latest][index]

    def __iter__(self) -> Iterator[_T]:
        yield from self._first
        yield from self._latest


class Reaction(StrEnum):
    """What the supervisor did about a fault (telemetry's ``fault_action``)."""

    HOLD = "hold"  #: a jerk-limited stop ramp of the reference, then held (``halt_policy: hold``)
    COMPLY = "comply"  #: gravity compensation with zero gains (``collision_reaction: comply``)
    MOTOR_STOP = Command.MOTOR_STOP.name  #: 0x81 to every axis: the drives stop themselves
    MOTOR_OFF = Command.MOTOR_OFF.name  #: 0x80 to every axis: the drives release their torque (``halt_policy: off``)


#: The reactions that a state stands for (any other: the halt command that went out).
REACTIONS: Final = {ArmState.HOLDING: Reaction.HOLD, ArmState.COMPLYING: Reaction.COMPLY}


@dataclass(frozen=True, slots=True)
class HaltRecord:
    """When a fault was detected and when its halt went out (controller clock, seconds; cycle index), and how."""

    fault: MotionFault
    cycle: int
    detected_s: float
    halt_sent_s: float
    reaction: Reaction


def same_cause(a: MotionFault, b: MotionFault) -> bool:
    """Whether two faults report the same cause (kind, joint and detail; values and times aside)."""
    return a.kind is b.kind and a.joint == b.joint and a.detail == b.detail


def exception_origin(exc: BaseException) -> tuple[str, str, int]:
    """Where ``exc`` was raised: its type, and the file and line of its innermost frame."""
    tb = exc.__traceback__
    if tb is None:
        return type(exc).__qualname__, "", 0
    while tb.tb_next is not None:
        tb = tb.tb_next
    return type(exc).__qualname__, tb.tb_frame.f_code.co_filename, tb.tb_lineno


class FaultLog:
    """The session's faults: written by the control thread, read by any.

    Args:
        machine: the arm's state machine (its state is published with the fault).
        publisher: the controller's snapshot publisher.
        clock: the controller's clock.
    """

    def __init__(self, machine: StateMachine, publisher: SnapshotPublisher, clock: Clock) -> None:
        self._machine = machine
        self._publisher = publisher
        self._clock = clock
        self._fault: MotionFault | None = None
        self.faults: Records[MotionFault] = Records(RECORDS_KEPT)
        self.halts: Records[HaltRecord] = Records(RECORDS_KEPT)
        #: Joints whose drive restarted in this session: their turn count is lost, clear() refuses until a new
        #: session resolves it.
        self.lost_frames: set[str] = set()
        #: Where the exception behind the latest ``exception`` fault was raised (its type, file and line).
        self.exception_origin: tuple[str, str, int] | None = None

    @property
    def fault(self) -> MotionFault | None:
        """The fault the arm is faulted for (None when it is not)."""
        return self._fault

    @fault.setter
    def fault(self, fault: MotionFault | None) -> None:
        self._fault = fault
        self.publish(self._machine.state)

    def publish(self, state: ArmState) -> None:
        """State and fault into the published snapshot (:meth:`SnapshotPublisher.set_condition`); the state
        machine's ``on_change``."""
        self._publisher.set_condition(state.value, self._fault)

    def record(self, fault: MotionFault) -> None:
        """The arm is faulted for ``fault`` from now on (published); recorded, and a drive that restarted loses its
        joint's frame."""
        self.fault = fault
        self.faults.append(fault)
        if fault.kind is FaultKind.DRIVE_RESTARTED and fault.joint is not None:
            self.lost_frames.add(fault.joint)

    def record_halted(self, fault: MotionFault, code: Command) -> None:
        """A fault seen while the halt ``code`` is in force: recorded and logged; the halt stays (the drive concerned
        gets it again)."""
        logger.error("while %s: %s", self._machine.state.value, fault)
        self.faults.append(fault)
        now = self._clock.now()
        self.halts.append(HaltRecord(fault, -1, now, now, Reaction(code.name)))
