"""Motion commands between threads and the control loop.

A command (:class:`MoveCommand`, :class:`PathCommand`, :class:`PlayCommand`, :class:`StopCommand`) may come from any
thread: it is queued (:meth:`CommandQueue.put`) and planned in the control thread at the start of the next cycle
(:meth:`CommandQueue.apply`), from the reference at that instant, so a new target never steps the reference's velocity
or acceleration. One command waits at a time: a newer one replaces it.

Each queued command has a :class:`MotionTicket`, which the control thread ends once with how the motion ended
(:class:`MotionEnd`): its reference ran to its end, another motion took its place (one queued while it waited or
played: the newer one supersedes it, from whichever thread it came), a stop ramp ended it, it could not be planned
when its turn came, or a fault ended it. A caller waits on its own motion's ticket, never on whichever motion the
arm plays by then.
"""

from __future__ import annotations

import dataclasses
import threading
from collections.abc import Sequence
from dataclasses import dataclass
from enum import Enum
from typing import TypeAlias

import numpy as np

from motion.config.schema import ControlMode
from motion.control.scheduler import FixedRateLoop
from motion.errors import MotionError, PlanningError
from motion.trajectory import Follower, JointLimits, Path, Planner, State
from motion.transmission import FloatArray


@dataclass(frozen=True, slots=True)
class MoveCommand:
    """Queued: a coordinated move to ``target_deg`` (joint order)."""

    target_deg: FloatArray
    speed_scale: float


@dataclass(frozen=True, slots=True)
class PathCommand:
    """Queued: a path through ``waypoints_deg`` (one row per waypoint)."""

    waypoints_deg: FloatArray
    speed_scale: float


@dataclass(frozen=True, slots=True)
class PlayCommand:
    """Queued: a path planned elsewhere, played as it is."""

    path: Path


@dataclass(frozen=True, slots=True)
class StopCommand:
    """Queued: a jerk-limited stop of the current motion (not a fault)."""


#: A motion command waiting for the next cycle (a tagged union: each kind is its own class).
Pending: TypeAlias = MoveCommand | PathCommand | PlayCommand | StopCommand


class MotionEnd(Enum):
    """How a queued motion ended (:attr:`MotionTicket.end`)."""

    COMPLETED = "completed"  #: its reference ran to its end
    SUPERSEDED = "superseded"  #: a motion queued after it took its place, while it waited or played
    HELD = "held"  #: a stop (:meth:`MotionCommands.stop_motion`) ramped it to rest; the ramp has ended
    REJECTED = "rejected"  #: it could not be planned from the live reference when its turn came; it never played
    ABORTED = "aborted"  #: a fault, an E-stop or the close ended it (:attr:`MotionTicket.cause`)


class MotionTicket:
    """One queued motion command: how it ended, once it has (set once, by the control thread; read by any)."""

    __slots__ = ("cause", "end")

    def __init__(self) -> None:
        #: How the motion ended; None while it waits or plays.
        self.end: MotionEnd | None = None
        #: What ended it, where something did: the PlanningError of a rejected one, the fault of an aborted one.
        self.cause: BaseException | None = None

    def finish(self, end: MotionEnd, cause: BaseException | None = None) -> None:
        """The motion ended as ``end`` (the first end stands: a motion ends once)."""
        if self.end is None:
            self.cause = cause
            self.end = end  # (last: a reader that sees the end sees its cause)


def planning_limits(limits: JointLimits, mode: ControlMode, catch_up_share: float) -> JointLimits:
    """The limits the planner plans within: the joints' own, but for position mode's velocities, which keep
    ``catch_up_share`` of each limit free (the 0xA4 speed cap is the limit itself: a drive lagging the stream still has
    room below it to catch up)."""
    if not mode.traits.drive_position_loop or not catch_up_share:
        return limits
    share = 1.0 - catch_up_share
    return dataclasses.replace(limits, velocity_dps=tuple(v * share for v in limits.velocity_dps))


class CommandQueue:
    """The command waiting for the next cycle, the motion playing, the latest command that could not be planned, and
    whether the arm is idle (nothing queued or playing)."""

    def __init__(self) -> None:
        self._pending: Pending | None = None
        self._ticket: MotionTicket | None = None  # the waiting command's
        self._playing: MotionTicket | None = None  # the motion the follower plays (or its stop ramp)
        self._held = False  # a stop ramp has replaced the playing motion's path
        self._rejected: PlanningError | None = None
        self._lock = threading.Lock()
        #: Set while nothing is queued or playing.
        self.idle = threading.Event()
        self.idle.set()

    @property
    def waiting(self) -> bool:
        """Whether a command waits for the next cycle."""
        return self._pending is not None

    def put(self, pending: Pending) -> MotionTicket:
        """Queue ``pending`` (any thread), replacing a command that still waits (it never plays: superseded, or held
        by a stop); returns its ticket."""
        ticket = MotionTicket()
        with self._lock:
            if self._ticket is not None:
                self._ticket.finish(MotionEnd.HELD if isinstance(pending, StopCommand) else MotionEnd.SUPERSEDED)
            self._pending, self._ticket = pending, ticket
            self.idle.clear()
        return ticket

    def discard(self, cause: BaseException | None = None) -> None:
        """Drop a queued command (a halt must not be overridden by a move queued in the same cycle): it never plays,
        ended by ``cause``."""
        with self._lock:
            if self._ticket is not None:
                self._ticket.finish(MotionEnd.ABORTED, cause)
            self._pending = self._ticket = None

    def abort(self, cause: BaseException | None) -> None:
        """A fault (or a stop, or the close) ends the motion: the queued command is dropped and the one playing ends,
        both by ``cause`` (the control thread, before the reaction replaces the reference)."""
        self.discard(cause)
        with self._lock:
            if self._playing is not None:
                self._playing.finish(MotionEnd.ABORTED, cause)
                self._playing = None

    def take_rejection(self, of: MotionTicket | None = None) -> PlanningError | None:
        """The PlanningError of the last queued command that could not be planned from the live reference, once
        (with ``of``: only if it is that ticket's)."""
        with self._lock:
            error = self._rejected
            if of is not None and (error is None or error is not of.cause):
                return None
            self._rejected = None
        return error

    def apply(self, follower: Follower, t_s: float) -> None:
        """Plan the queued command on ``follower`` at ``t_s`` (the control thread, at a cycle's start). A command that
        cannot be planned from the live reference (a re-target whose stop would overshoot a limit) leaves the current
        motion going; the caller hears of it through :meth:`take_rejection`."""
        with self._lock:
            pending, self._pending = self._pending, None
            ticket, self._ticket = self._ticket, None
        if pending is None or ticket is None:
            return
        try:
            match pending:
                case MoveCommand(target, speed_scale):
                    follower.move_to(t_s, target, speed_scale=speed_scale)
                case PathCommand(waypoints, speed_scale):
                    follower.follow(t_s, waypoints, speed_scale=speed_scale)
                case PlayCommand(path):
                    follower.play(path, t_s)
                case StopCommand():
                    follower.stop(t_s)
                case other:  # never a default: an unknown command is an error
                    raise TypeError(f"unknown motion command {other!r}")
        except PlanningError as exc:
            ticket.finish(MotionEnd.REJECTED, exc)
            with self._lock:
                self._rejected = exc
                if not follower.moving and self._pending is None:
                    self._end_playing()
                    self.idle.set()
            return
        with self._lock:
            if isinstance(pending, StopCommand):
                ticket.finish(MotionEnd.COMPLETED)  # (the stop's own ticket: its ramp is the held motion's end)
                self._held = True
                return
            if self._playing is not None:
                self._playing.finish(MotionEnd.HELD if self._held else MotionEnd.SUPERSEDED)
            self._playing, self._held = ticket, False

    def _end_playing(self) -> None:
        """The follower stopped playing (under the lock): the motion it played ran to its end, or its stop ramp did."""
        playing = self._playing
        if playing is not None:
            playing.finish(MotionEnd.HELD if self._held else MotionEnd.COMPLETED)
            self._playing = None

    def settle(self, follower: Follower) -> None:
        """The cycle's end: the motion playing ended once the follower stopped playing it, and the queue is idle once
        nothing is queued or playing (set once, not again every cycle of a hold: an Event's set takes a lock and
        notifies). Under the lock a ``put`` takes, so that a command queued meanwhile keeps the queue busy."""
        if follower.moving or self.idle.is_set():
            return
        with self._lock:
            self._end_playing()
            if self._pending is None:
                self.idle.set()


class MotionCommands:
    """The motion commands of a :class:`~motion.control.controller.Controller`: what any thread may call. Each is
    checked (planned once from the reference at rest) before it is queued for the control thread."""

    follower: Follower | None
    planner: Planner
    reference: State
    commands: CommandQueue
    loop: FixedRateLoop

    def _queue(self, pending: Pending) -> MotionTicket:
        if self.follower is None:
            raise MotionError("read_positions() must run before motion commands")
        return self.commands.put(pending)

    def move_to(self, target_deg: Sequence[float] | FloatArray, speed_scale: float = 1.0) -> MotionTicket:
        """Queue a coordinated move to ``target_deg`` (re-targets a running move, which ends superseded). Checked
        before it is queued; returns its ticket.

        Raises:
            PlanningError: the target or the scale is invalid (nothing is queued).
        """
        target = np.asarray(target_deg, dtype=np.float64)
        # planned once from the reference at rest (the loop plans from the live state when it applies it): the
        # vector, the limits, the scale and whatever Ruckig refuses (a duration beyond its limits) are refused here
        scale = self.planner.check_scale(speed_scale)
        self.planner.move(State.at_rest(self.reference.position), target, speed_scale=scale)
        return self._queue(MoveCommand(target, scale))

    def follow(self, waypoints_deg: Sequence[Sequence[float]] | FloatArray, speed_scale: float = 1.0) -> MotionTicket:
        """Queue a waypoint path from the current reference, planned once from it at rest first (as :meth:`move_to`);
        returns its ticket.

        Raises:
            PlanningError: a waypoint or the scale is invalid (nothing is queued).
        """
        scale = self.planner.check_scale(speed_scale)
        self.planner.path(State.at_rest(self.reference.position), waypoints_deg, speed_scale=scale)
        return self._queue(PathCommand(np.asarray(waypoints_deg, dtype=np.float64), scale))

    def play(self, path: Path) -> MotionTicket:
        """Queue a path planned elsewhere; it must start at the reference of the cycle that applies it."""
        return self._queue(PlayCommand(path))

    def stop_motion(self) -> None:
        """Queue a jerk-limited stop; the arm then holds where the stop ends (the motion playing ends held)."""
        self._queue(StopCommand())

    def wait_idle(self, timeout_s: float | None = None) -> bool:
        """Wait until the queued motion has ended; returns False on timeout."""
        if self.loop.stepping:
            return self.loop.step_until(self.commands.idle.is_set, timeout_s)
        return self.commands.idle.wait(timeout_s)

    @property
    def idle(self) -> bool:
        """True when no motion is queued or playing (never waits)."""
        return self.commands.idle.is_set()

    def discard_pending(self) -> None:
        """Drop a queued motion command (a halt must not be overridden by a move queued in the same cycle)."""
        self.commands.discard()

    def abort_motion(self, cause: BaseException | None) -> None:
        """End the motion: drop a queued command and end the one playing, both by ``cause`` (a fault's reaction)."""
        self.commands.abort(cause)

    def take_rejection(self) -> PlanningError | None:
        """The PlanningError of the last queued command that could not be planned from the live reference, once."""
        return self.commands.take_rejection()
