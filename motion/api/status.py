"""What a caller of the API reads back: the handle of a queued motion (its end, its progress) and the arm's status,
the latter two from the snapshot the loop published last (read without waiting on the loop)."""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass
from enum import StrEnum
from typing import Any, Final

import numpy as np

from motion.api.arguments import seconds
from motion.config.schema import ControlConfig
from motion.control.commands import MotionEnd, MotionTicket
from motion.control.controller import Controller
from motion.control.scheduler import LoopStatistics
from motion.control.snapshot import MotionProgress
from motion.errors import FaultKind, MotionFault, PlanningError
from motion.protocol.table import split_address
from motion.safety import Supervisor
from motion.transmission import FloatArray

logger = logging.getLogger("motion.api")


@dataclass(frozen=True, slots=True)
class JointStatus:
    """One joint's measured and reference state (joint side)."""

    name: str
    motor_id: int
    position_deg: float
    velocity_dps: float
    reference_deg: float
    iq_a: float
    temperature_c: float
    bus: str = ""  #: the bus the drive is on, on an arm of several ("" on an arm of one)


@dataclass(frozen=True, slots=True)
class ArmStatus:
    """The arm at one instant."""

    name: str
    state: str
    fault: str | None
    joints: tuple[JointStatus, ...]
    loop: LoopStatistics

    def as_dict(self) -> dict[str, Any]:
        """Plain data for ``--json``."""
        return {
            "name": self.name,
            "state": self.state,
            "fault": self.fault,
            "joints": [
                {
                    "name": j.name,
                    "motor_id": j.motor_id,
                    **({"bus": j.bus} if j.bus else {}),
                    "position_deg": round(j.position_deg, 4),
                    "velocity_dps": round(j.velocity_dps, 3),
                    "reference_deg": round(j.reference_deg, 4),
                    "iq_a": round(j.iq_a, 3),
                    "temperature_c": j.temperature_c,
                }
                for j in self.joints
            ],
            "loop": {
                "cycles": self.loop.cycles,
                "rate_hz": round(self.loop.achieved_rate_hz, 2),
                "jitter_p99_us": round(self.loop.jitter_p99_s * 1e6, 1),
                "overruns": self.loop.overruns,
            },
        }


def arm_status(name: str, controller: Controller, buses: Sequence[str] = ()) -> ArmStatus:
    """Measured and reference state of every joint of arm ``name`` (on ``buses``, by index, where it has several),
    its state and the loop statistics."""
    snapshot = controller.snapshot  # published by the loop: one consistent cycle, read without a lock
    joints = tuple(
        JointStatus(
            name=spec.name,
            motor_id=split_address(spec.motor_id)[1],
            bus=buses[split_address(spec.motor_id)[0]] if len(buses) > 1 else "",
            position_deg=float(snapshot.position_deg[i]),
            velocity_dps=float(snapshot.velocity_dps[i]),
            reference_deg=float(snapshot.reference_deg[i]),
            iq_a=float(snapshot.iq_a[i]),
            temperature_c=float(snapshot.temperature_c[i]),
        )
        for i, spec in enumerate(controller.specs)
    )
    fault = str(snapshot.fault) if snapshot.fault is not None else None
    return ArmStatus(name, snapshot.state, fault, joints, controller.loop.statistics())


class EndReason(StrEnum):
    """Why a motion ended as it did (:attr:`Arrival.reason`)."""

    COMPLETED = "completed"  #: its reference ran to its end (the joints then arrived, or not: ``arrived``)
    SUPERSEDED = "superseded"  #: a motion given after it (from any thread) took its place, while it waited or ran
    HELD = "held"  #: :meth:`Arm.hold` ramped it to rest short of its target
    STOPPED = "stopped"  #: an E-stop (:meth:`Arm.stop`, the view's STOP, Ctrl-C) or the arm's close halted it
    FAULTED = "faulted"  #: a fault halted the arm (or held it: ``halt_policy: hold``)
    REJECTED = "rejected"  #: it could not be planned from the live reference when its turn came; it never ran


#: The fault kinds of a stop someone asked for (the rest are faults the arm found).
_STOPS: Final = frozenset({FaultKind.ESTOP, FaultKind.STOP, FaultKind.CLOSE, FaultKind.BUS_CLOSING})
#: The supervisor's end of a motion -> the reason a caller reads (an aborted one: by its cause, :func:`_aborted`).
_REASONS: Final = {
    MotionEnd.COMPLETED: EndReason.COMPLETED,
    MotionEnd.SUPERSEDED: EndReason.SUPERSEDED,
    MotionEnd.HELD: EndReason.HELD,
    MotionEnd.REJECTED: EndReason.REJECTED,
}


def _aborted(cause: BaseException | None) -> EndReason:
    """The reason of a motion a fault ended: STOPPED for a stop someone asked for, else FAULTED."""
    return EndReason.STOPPED if isinstance(cause, MotionFault) and cause.kind in _STOPS else EndReason.FAULTED


@dataclass(frozen=True)
class Arrival:
    """How a motion's joints arrived at its end (``control.goal_tolerance_deg`` and friends), or why they did not.

    Attributes:
        arrived: every joint came within the goal tolerance of its target and stayed there for the settle time,
            within the goal time after the reference ended. Never for a motion that did not run to its end.
        after_s: from the end of the reference to that (or to the goal time, when they did not), s (the arm's clock);
            0 for a motion that did not run to its end.
        error_deg: each joint's distance from its target then (for a motion cut short: from this motion's target,
            where it was cut), degrees.
        reason: how the motion ended: :attr:`EndReason.COMPLETED` (its reference ran to its end), or what cut it short.
    """

    arrived: bool
    after_s: float
    error_deg: dict[str, float]
    reason: EndReason = EndReason.COMPLETED

    def text(self, tolerance_deg: float) -> str:
        """In words: where the joints arrived, or which did not and by how much, or what cut the motion short."""
        if self.arrived:
            return f"arrived within {tolerance_deg:g} deg {self.after_s:.2f} s after the reference ended"
        if self.reason is not EndReason.COMPLETED:
            far = ", ".join(f"{n} {e:.3f} deg" for n, e in self.error_deg.items())
            return f"not arrived: {self.reason.value} ({far} from its target then)"
        missed = {n: e for n, e in self.error_deg.items() if e > tolerance_deg}
        far = ", ".join(f"{n} {e:.3f} deg" for n, e in missed.items()) or "every joint within it, but not settled"
        return (
            f"not arrived {self.after_s:.2f} s after the reference ended (goal_tolerance_deg {tolerance_deg:g}): {far} "
            "from the target"
        )


class MotionHandle:
    """A queued motion; :meth:`wait` blocks until it ends (its reference ended and, with a goal tolerance, the joints
    arrived or the goal time passed; or another motion, a hold, a stop or a fault cut it short: :attr:`arrival`) and
    raises the fault that halted it.

    Args:
        supervisor: the arm's supervisor.
        goal: the arm's control settings (its goal tolerance; None or a tolerance of 0: the motion ends with its
            reference).
        ticket: the motion's ticket from the supervisor (how it ended, once it has).
        target_deg: where the motion ends, joint order, degrees (a cut-short motion's error is measured from it).
    """

    def __init__(
        self,
        supervisor: Supervisor,
        goal: ControlConfig | None = None,
        *,
        ticket: MotionTicket,
        target_deg: Sequence[float] | FloatArray,
    ) -> None:
        self._supervisor = supervisor
        self._goal = goal if goal is not None and goal.goal_tolerance_deg > 0.0 else None
        self._ticket = ticket
        self._target = np.array(target_deg, dtype=np.float64)
        #: How the joints arrived, or why they did not: set once the motion ended, whenever it was cut short (None:
        #: not ended yet, or it ran to its end without a goal tolerance to arrive within).
        self.arrival: Arrival | None = None
        # the arrival under way: when it began (the arm's clock), its deadline, since when the joints are within
        self._arriving: tuple[float, float] | None = None
        self._within_since: list[float] = []
        self._settled = False

    def wait(self, timeout_s: float | None = None) -> bool:
        """Wait for the end of the motion, and then for the joints to arrive (see :class:`Arrival`; a joint that
        does not arrive within the goal time is logged, not a fault); False on timeout (the arrival, if under way,
        goes on at the next call). A motion that another one or a hold cut short ends as soon as it was cut (True,
        :attr:`arrival` says so).

        Raises:
            MotionFault: a fault (or a stop) halted every axis: the one that ended this motion, or one since.
            PlanningError: the motion could not be planned from the live reference when its turn came.
            ValueError: ``timeout_s`` is neither None nor a finite number of seconds >= 0.
        """
        timeout = None if timeout_s is None else seconds("timeout_s", timeout_s)
        supervisor, ticket = self._supervisor, self._ticket
        controller, machine = supervisor.controller, supervisor.machine
        begun = controller.clock.now()
        if not controller.wait_for(lambda: ticket.end is not None or machine.state.faulted, timeout):
            return False
        if not self._settled:
            if ticket.end is MotionEnd.COMPLETED and self._goal is not None and not machine.state.faulted:
                left = None if timeout is None else max(0.0, timeout - (controller.clock.now() - begun))
                if not self._arrive(self._goal, left):
                    return False
            else:
                self._settle_cut()
        self._raise_end()
        return True

    def _settle_cut(self) -> None:
        """The motion ended without an arrival to wait for: :attr:`arrival` says why, where it was cut short (one that
        ran to its end without a goal tolerance has none)."""
        self._settled = True
        ticket, supervisor = self._ticket, self._supervisor
        end = ticket.end
        if end is MotionEnd.ABORTED:
            self._record(False, 0.0, _aborted(ticket.cause))
        elif end is not None and end is not MotionEnd.COMPLETED:
            self._record(False, 0.0, _REASONS[end])
        elif supervisor.state.faulted and (end is None or self._goal is not None):
            self._record(False, 0.0, _aborted(supervisor.fault))  # (halted before it ended, or before it arrived)

    def _raise_end(self) -> None:
        """Raise what ended the motion or halted the arm since, if anything did.

        Raises:
            PlanningError: the motion could not be planned when its turn came.
            MotionFault: the arm is halted, or a fault (cleared since) ended this motion.
        """
        supervisor, ticket = self._supervisor, self._ticket
        cause = ticket.cause
        if ticket.end is MotionEnd.REJECTED and isinstance(cause, PlanningError):
            supervisor.controller.commands.take_rejection(ticket)  # (its own: not raised again by another wait)
            raise cause
        if supervisor.state.faulted and supervisor.fault is not None:
            raise supervisor.fault
        if ticket.end is MotionEnd.ABORTED and isinstance(cause, MotionFault):
            raise cause

    def _record(self, arrived: bool, after_s: float, reason: EndReason, error: FloatArray | None = None) -> None:
        """Set :attr:`arrival` (``error``: each joint's distance, by default from this motion's target now)."""
        controller = self._supervisor.controller
        if error is None:
            error = np.abs(controller.snapshot.position_deg - self._target)
        names = [s.name for s in controller.specs]
        rounded = {n: round(float(e), 4) for n, e in zip(names, error, strict=True)}
        self.arrival = Arrival(arrived, after_s, rounded, reason)

    def _arrive(self, goal: ControlConfig, left_s: float | None) -> bool:
        """Wait (at most ``left_s``) for the joints to arrive; True once that is settled (:attr:`arrival` set, or
        None where a fault or another motion ended it)."""
        controller, supervisor = self._supervisor.controller, self._supervisor
        error = np.zeros(len(controller.specs))
        within_since = self._within_since
        if self._arriving is None:
            start_s = controller.snapshot.time_s
            self._arriving = (start_s, start_s + goal.goal_time_s + goal.goal_settle_s)
        start_s, deadline_s = self._arriving

        def arrived() -> bool:
            if supervisor.state.faulted or not controller.idle:
                return True  # a fault, or another motion took over
            snapshot = controller.snapshot
            np.abs(np.subtract(snapshot.position_deg, snapshot.reference_deg, out=error), out=error)
            if error.max() > goal.goal_tolerance_deg:
                within_since.clear()
                return False
            if not within_since:
                within_since.append(snapshot.time_s)
            return snapshot.time_s - within_since[0] >= goal.goal_settle_s

        budget = max(0.0, deadline_s - controller.snapshot.time_s)
        if left_s is not None and left_s < budget:
            if not controller.wait_for(arrived, left_s):
                return False  # (the caller's timeout: the arrival goes on at the next wait)
        else:
            controller.wait_for(arrived, budget)
        self._settled = True
        if supervisor.state.faulted:
            self._record(False, 0.0, _aborted(supervisor.fault))
            return True
        if not controller.idle:
            self._record(False, 0.0, EndReason.SUPERSEDED)  # (given while its joints were arriving)
            return True
        snapshot = controller.snapshot
        settled = bool(within_since) and snapshot.time_s - within_since[0] >= goal.goal_settle_s
        self._record(settled, snapshot.time_s - start_s, EndReason.COMPLETED, error)
        if not settled:
            logger.warning("%s", self.arrival.text(goal.goal_tolerance_deg))  # type: ignore[union-attr]
        return True

    @property
    def done(self) -> bool:
        """True when the motion ended (ran to its end, or was cut short) or the arm was halted."""
        return self._ticket.end is not None or self._supervisor.state.faulted

    def progress(self) -> MotionProgress:
        """How far the arm's motion has come, from the snapshot the loop published last (never waits on the loop); a
        motion that ended (or was cut short) reads done."""
        snapshot = self._supervisor.controller.snapshot
        if not snapshot.moving or self._ticket.end is not None:
            return MotionProgress(0.0, 0.0, done=self.done)
        duration = snapshot.motion_end_s - snapshot.motion_start_s
        elapsed = min(duration, max(0.0, snapshot.time_s - snapshot.motion_start_s))
        return MotionProgress(elapsed, duration, done=self.done)
