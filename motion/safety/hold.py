"""Whether a hold holds: the check that escalates HOLDING to the drives' own halt (``hold_failed``).

A hold (HOLDING) streams a jerk-limited stop of the reference and then holds where it ended. A joint that does not
follow it, or a drive pushing at its current limit to hold it, is blocked or pushed against: never pushed for ever,
whatever fault the hold is for.
"""

from __future__ import annotations

import math

import numpy as np

from motion.control.controller import Controller
from motion.errors import FaultKind, MotionFault
from motion.safety.watchdog import Watchdog

#: A following error seen in this many consecutive cycles of a hold (whose ramp starts from the measured state, so
#: that a joint that follows has none) escalates to the drives' own halt: a blocked joint is never pushed for ever.
HOLD_ESCALATION_CYCLES = 3
#: ... and so does a torque current at the joint's ``current_limit_a`` for this long, s: a drive's loop saturated by
#: the jump of its set-point to where the joint stands unwinds within a few of its time constants (tens of ms; 20 ms
#: seen on the emulator at 200 Hz), a drive pushing against an obstacle does not. (In position mode the drive's own
#: current limit may differ from the configured one: above it this never fires, and the persisting following error is
#: left to escalate; below it, a hold that needs more current escalates to 0x81, the safe side.)
HOLD_AT_LIMIT_S = 0.1


class HoldCheck:
    """A hold's strikes (cycles with a following error) and how long a current has stood at its limit (control
    thread only).

    Args:
        controller: the controller (its measured currents and the torque builder's limiting).
        watchdog: the watchdog (the latest following-error fault, the joints' names).
    """

    def __init__(self, controller: Controller, watchdog: Watchdog) -> None:
        self.controller = controller
        self.watchdog = watchdog
        self._strikes = 0
        self._at_limit_since = math.nan
        #: Each joint's current limit, A: a hold that keeps a drive at it pushes against something.
        self._current_limit_a = np.array([t.current_limit_a for t in controller.transmission.transmissions])
        self._iq_magnitude = np.zeros_like(self._current_limit_a)
        self._at_limit = np.zeros(len(self._current_limit_a), dtype=bool)
        self._torque_mode = controller.options.mode.traits.host_torque

    def restart(self) -> None:
        """A hold starts: no strikes, no current at its limit yet."""
        self._strikes, self._at_limit_since = 0, math.nan

    def escalation(self, now_s: float) -> MotionFault | None:
        """A hold that does not hold: a joint that does not follow even the hold (whose ramp starts from the measured
        state, so that a joint that follows has no error) for :data:`HOLD_ESCALATION_CYCLES`, or a torque current at
        its limit for :data:`HOLD_AT_LIMIT_S` — a blocked joint, or one pushed: never pushed against for ever.

        Returns:
            The ``hold_failed`` fault, or None while the hold holds.
        """
        controller, following = self.controller, self.watchdog.following
        if following is None:
            self._strikes = 0
        else:
            self._strikes += 1
            if self._strikes >= HOLD_ESCALATION_CYCLES:
                return MotionFault(
                    FaultKind.HOLD_FAILED,
                    joint=following.joint,
                    value=following.value,
                    threshold=following.threshold,
                    time_s=following.time_s,
                    detail=f"{following.kind.value} persisted for {self._strikes} cycles of the hold",
                )
        at_limit, magnitude = self._at_limit, self._iq_magnitude  # (kept between cycles: no array per cycle)
        np.greater_equal(np.abs(controller.axes.iq_a, out=magnitude), self._current_limit_a, out=at_limit)
        if self._torque_mode:
            np.logical_or(at_limit, controller.limited, out=at_limit)
        if not at_limit.any():
            self._at_limit_since = math.nan
        elif math.isnan(self._at_limit_since):
            self._at_limit_since = now_s
        elif now_s - self._at_limit_since >= HOLD_AT_LIMIT_S:
            i = int(np.argmax(at_limit))
            return MotionFault(
                FaultKind.HOLD_FAILED,
                joint=self.watchdog.names[i],
                value=float(controller.axes.iq_a[i]),
                threshold=float(self._current_limit_a[i]),
                time_s=now_s,
                detail=f"torque current at its limit for {now_s - self._at_limit_since:.3f} s of the hold (blocked?)",
            )
        return None
