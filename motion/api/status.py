"""What a caller of the API reads back: the handle of a queued motion (its end, its progress) and the arm's status,
the latter two from the snapshot the loop published last (read without waiting on the loop)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from motion.api.arguments import seconds
from motion.control.controller import Controller
from motion.control.scheduler import LoopStatistics
from motion.control.snapshot import MotionProgress
from motion.safety import Supervisor


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


def arm_status(name: str, controller: Controller) -> ArmStatus:
    """Measured and reference state of every joint of arm ``name``, its state and the loop statistics."""
    snapshot = controller.snapshot  # published by the loop: one consistent cycle, read without a lock
    joints = tuple(
        JointStatus(
            name=spec.name,
            motor_id=spec.motor_id,
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


class MotionHandle:
    """A queued motion; :meth:`wait` blocks until it ends and raises the fault that halted it."""

    def __init__(self, supervisor: Supervisor) -> None:
        self._supervisor = supervisor

    def wait(self, timeout_s: float | None = None) -> bool:
        """Wait for the end of the motion; False on timeout.

        Raises:
            MotionFault: a fault halted every axis.
            ValueError: ``timeout_s`` is neither None nor a finite number of seconds >= 0.
        """
        return self._supervisor.wait(None if timeout_s is None else seconds("timeout_s", timeout_s))

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
