"""What a run did (issue 33 §5), gathered cycle by cycle while it runs: per joint the largest following error and the
cycles its current was at its limit, and how long that lasted before the latest cycle; with the loop's timing, the
summary ``move``, ``run`` and the demo print, and the physical cause a fault is likely to have had.

A joint's current counts as at its limit when its command was clipped there (torque mode: the set-point builder
limits it) or, in position mode (the drive limits it), when the measured current reaches :data:`AT_LIMIT_SHARE` of
the joint's ``current_limit_a``, or comes within :data:`AT_LIMIT_STEPS` steps of the reply's current field of it
(a small limit is a few steps of that field: 0.2 A reads 0.193 A in 33/2048 A steps).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING, Any, Final

import numpy as np

from motion.config import ArmConfig
from motion.errors import FaultKind, MotionFault

if TYPE_CHECKING:
    from motion.safety import Supervisor

#: Position mode: a measured current within this share of the joint's limit counts as at the limit.
AT_LIMIT_SHARE: Final = 0.97
#: ... or within this many steps of the current field.
AT_LIMIT_STEPS: Final = 1.5
#: A fault after this many cycles at the current limit in a row names the limit as its likely cause.
CAUSE_CYCLES: Final = 5
#: The faults a joint starved of current can cause.
_STARVED: Final = frozenset({FaultKind.FOLLOWING_ERROR, FaultKind.HOLD_FAILED})


class RunSummary:
    """A hook on the controller's cycles (:attr:`Controller.cycle_hooks`) that keeps the module's figures.

    Args:
        config: the arm's configuration (joint names, current limits, control mode).
        supervisor: the arm's supervisor (its watchdog's following error, its controller's currents).
    """

    def __init__(self, config: ArmConfig, supervisor: Supervisor) -> None:
        n = len(config.joints)
        self.names = config.joint_names
        self._limit_a = np.array([j.current_limit_a for j in config.joints])
        step_a = np.array([f.current_step_a for f in supervisor.controller.families])
        margin = np.maximum((1.0 - AT_LIMIT_SHARE) * self._limit_a, AT_LIMIT_STEPS * step_a)
        self._at_limit_a = self._limit_a - margin  # position mode: a measured current at the limit
        self._torque = config.control.mode.traits.host_torque
        self._supervisor = supervisor
        #: Cycles seen.
        self.cycles = 0
        #: Per joint: the largest following error, deg; the cycles at the current limit; the latest run of them.
        self.max_error_deg = np.zeros(n)
        self.limited_cycles = np.zeros(n, dtype=np.int64)
        self.limited_streak = np.zeros(n, dtype=np.int64)
        self._at = np.zeros(n, dtype=bool)
        self._abs_a = np.zeros(n)
        self._explained: MotionFault | None = None

    def __call__(self, controller: Any, start_s: float, replies: Sequence[Any]) -> None:
        """One cycle (the controller calls it after each exchange); the first cycle that sees a fault gives it its
        cause (:attr:`MotionFault.cause`), from the cycles before it."""
        fault = self._supervisor.fault
        if fault is not None and fault is not self._explained:
            self._explained = fault
            fault.cause = self.cause(fault)
        self.cycles += 1
        np.fmax(self.max_error_deg, self._supervisor.watchdog.following_error_deg, out=self.max_error_deg)
        at = self._at
        if self._torque:  # (the set-points' flags of a cycle that sent none are the last sent cycle's)
            np.logical_and(controller.setpoints.limited, controller.setpoints.commanded, out=at)
        else:
            np.greater_equal(np.abs(controller.axes.iq_a, out=self._abs_a), self._at_limit_a, out=at)
        self.limited_cycles += at
        streak = self.limited_streak
        np.add(streak, at, out=streak)
        np.multiply(streak, at, out=streak)  # (no allocation per cycle: this runs in the control loop)

    def cause(self, fault: MotionFault) -> str | None:
        """The likely physical cause of ``fault``, where the evidence is there (a joint of the fault at its current
        limit for :data:`CAUSE_CYCLES` cycles or more just before it), else None."""
        if fault.kind not in _STARVED:
            return None
        for name in fault.joints or self.names:
            j = self.names.index(name) if name in self.names else None
            if j is None or self.limited_streak[j] < CAUSE_CYCLES:
                continue
            cycles = int(self.limited_streak[j])
            return (
                f"{name} at its {self._limit_a[j]:g} A current limit for {cycles} cycles before the fault: the torque "
                "constant or the current limit is too low for this load or speed (or the joint is blocked); check "
                "torque_constant_nm_per_a and current_limit_a, or move slower (--speed-scale)"
            )
        return None

    def as_dict(self, controller: Any) -> dict[str, Any]:
        """The summary: cycles, the loop's timing, and per joint the largest following error and the cycles at the
        current limit (the demo's table)."""
        stats = controller.loop.statistics()
        worst = int(np.argmax(self.max_error_deg)) if self.cycles else 0
        return {
            "cycles": self.cycles,
            "rate_hz": round(stats.achieved_rate_hz, 3),
            "jitter_us": {
                "p50": round(stats.jitter_p50_s * 1e6),
                "p99": round(stats.jitter_p99_s * 1e6),
                "max": round(stats.jitter_max_s * 1e6),
            },
            "overruns": stats.overruns,
            "max_following_error": {"joint": self.names[worst], "deg": round(float(self.max_error_deg[worst]), 4)},
            "joints": {
                name: {
                    "max_following_error_deg": round(float(self.max_error_deg[j]), 4),
                    "current_limited_cycles": int(self.limited_cycles[j]),
                }
                for j, name in enumerate(self.names)
            },
        }

    def text(self, controller: Any) -> str:
        """The summary in a line for people."""
        d = self.as_dict(controller)
        jitter = d["jitter_us"]
        limited = ", ".join(
            f"{n} {j['current_limited_cycles']}" for n, j in d["joints"].items() if j["current_limited_cycles"]
        )
        worst = d["max_following_error"]
        return (
            f"{d['cycles']} cycles at {d['rate_hz']:.1f} Hz, jitter p50/p99/max {jitter['p50']}/{jitter['p99']}/"
            f"{jitter['max']} us, {d['overruns']} overruns, max following error {worst['deg']:.3f} deg "
            f"({worst['joint']}), current-limited cycles: {limited or 'none'}"
        )
