"""What a caller of the API reads back: the handle of a queued motion (its end, its progress) and the arm's status,
the latter two from the snapshot the loop published last (read without waiting on the loop)."""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from motion.api.arguments import seconds
from motion.config.schema import ControlConfig
from motion.control.controller import Controller
from motion.control.scheduler import LoopStatistics
from motion.control.snapshot import MotionProgress
from motion.protocol.table import split_address
from motion.safety import Supervisor

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


@dataclass(frozen=True)
class Arrival:
    """How a motion's joints arrived at its end (``control.goal_tolerance_deg`` and friends).

    Attributes:
        arrived: every joint came within the goal tolerance of its target and stayed there for the settle time,
            within the goal time after the reference ended.
        after_s: from the end of the reference to that (or to the goal time, when they did not), s (the arm's clock).
        error_deg: each joint's distance from its target then, degrees.
    """

    arrived: bool
    after_s: float
    error_deg: dict[str, float]

    def text(self, tolerance_deg: float) -> str:
        """In words: where the joints arrived, or which did not and by how much."""
        if self.arrived:
            return f"arrived within {tolerance_deg:g} deg {self.after_s:.2f} s after the reference ended"
        missed = {n: e for n, e in self.error_deg.items() if e > tolerance_deg}
        far = ", ".join(f"{n} {e:.3f} deg" for n, e in missed.items()) or "every joint within it, but not settled"
        return (
            f"not arrived {self.after_s:.2f} s after the reference ended (goal_tolerance_deg {tolerance_deg:g}): {far} "
            "from the target"
        )


class MotionHandle:
    """A queued motion; :meth:`wait` blocks until it ends (its reference ended and, with a goal tolerance, the joints
    arrived or the goal time passed: :attr:`arrival`) and raises the fault that halted it."""

    def __init__(self, supervisor: Supervisor, goal: ControlConfig | None = None) -> None:
        self._supervisor = supervisor
        self._goal = goal if goal is not None and goal.goal_tolerance_deg > 0.0 else None
        #: How the joints arrived (None: no goal tolerance, the motion not ended yet, or another one took over).
        self.arrival: Arrival | None = None
        # the arrival under way: when it began (the arm's clock), its deadline, since when the joints are within
        self._arriving: tuple[float, float] | None = None
        self._within_since: list[float] = []
        self._settled = self._goal is None

    def wait(self, timeout_s: float | None = None) -> bool:
        """Wait for the end of the motion, and then for the joints to arrive (see :class:`Arrival`; a joint that
        does not arrive within the goal time is logged, not a fault); False on timeout (the arrival, if under way,
        goes on at the next call).

        Raises:
            MotionFault: a fault halted every axis.
            ValueError: ``timeout_s`` is neither None nor a finite number of seconds >= 0.
        """
        timeout = None if timeout_s is None else seconds("timeout_s", timeout_s)
        clock = self._supervisor.controller.clock
        begun = clock.now()
        if not self._supervisor.wait(timeout):
            return False
        if self._settled or self._goal is None:
            return True
        left = None if timeout is None else max(0.0, timeout - (clock.now() - begun))
        if not self._arrive(self._goal, left):
            return False
        self._supervisor.wait(0.0)  # (a fault while arriving is raised as during the motion)
        return True

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
        if supervisor.state.faulted or not controller.idle:
            return True
        names = [s.name for s in controller.specs]
        self.arrival = Arrival(
            bool(within_since) and controller.snapshot.time_s - within_since[0] >= goal.goal_settle_s,
            controller.snapshot.time_s - start_s,
            {n: round(float(e), 4) for n, e in zip(names, error, strict=True)},
        )
        if not self.arrival.arrived:
            logger.warning("%s", self.arrival.text(goal.goal_tolerance_deg))
        return True

    @property
    def done(self) -> bool:
        """True when the motion ended (or was halted)."""
        return self._supervisor.controller.wait_idle(0) or self._supervisor.state.faulted

    def progress(self) -> MotionProgress:
        """How far the arm's motion has come, from the snapshot the loop published last (never waits on the loop)."""
        snapshot = self._supervisor.controller.snapshot
        if not snapshot.moving:
            return MotionProgress(0.0, 0.0, done=self.done)
        duration = snapshot.motion_end_s - snapshot.motion_start_s
        elapsed = min(duration, max(0.0, snapshot.time_s - snapshot.motion_start_s))
        return MotionProgress(elapsed, duration, done=self.done)
