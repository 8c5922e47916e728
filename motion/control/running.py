"""Running a :class:`~motion.control.controller.Controller`'s loop: starting it (in its own thread, or stepped by the
waiting thread in simulated time), waiting on it, pausing with it, ending it."""

from __future__ import annotations

import time
from collections.abc import Callable

from motion.control.axes import AxisStates
from motion.control.clock import Clock, is_simulated
from motion.control.scheduler import CycleFn, FixedRateLoop, LoopStatistics
from motion.control.tracking import ExpectedTracking
from motion.trajectory import State

# How often a thread that waits on a running loop looks again, s.
_POLL_S = 0.002


def _never() -> bool:
    return False


class LoopRunning:
    """Start, wait on, pause with and end a controller's loop (the controller's cycle is its own)."""

    loop: FixedRateLoop
    clock: Clock
    rate_hz: float
    tracking: ExpectedTracking
    axes: AxisStates
    reference: State
    _stop_loop: bool

    def start(self, cycle: CycleFn | None = None) -> None:
        """Run the loop in its own thread (after :meth:`read_positions`).

        Args:
            cycle: the cycle function to run instead of :meth:`cycle` (a safety supervisor's guarded cycle).
        """
        self._stop_loop = False
        # what the rate check's rehearsals taught the model is not the loop's history
        self.tracking.reset(self.axes.q_deg, self.axes.qd_dps, self.reference.position)
        if cycle is not None:
            self.loop = FixedRateLoop(self.rate_hz, cycle, clock=self.clock)
        if is_simulated(self.clock):
            self.loop.begin_stepping()
        else:
            self.loop.start()

    def wait_for(self, done: Callable[[], bool], timeout_s: float | None = None) -> bool:
        """Wait until ``done()`` holds or ``timeout_s`` passes; returns ``done()``.

        With a simulated clock the waiting thread runs the control cycles itself (``timeout_s`` is simulated time);
        otherwise it polls while the loop thread runs.
        """
        if self.loop.stepping:
            return self.loop.step_until(done, timeout_s)
        end = None if timeout_s is None else time.monotonic() + timeout_s
        while not done():
            if end is not None and time.monotonic() >= end:
                return done()
            time.sleep(_POLL_S)
        return True

    def pause(self, duration_s: float) -> None:
        """Let ``duration_s`` pass with the loop running (simulated time advances; real time sleeps)."""
        if self.loop.stepping:
            end = self.clock.now() + duration_s
            self.loop.step_until(_never, duration_s)
            self.clock.sleep_until(end)  # time passes for the drives also after the loop has ended
        else:
            time.sleep(duration_s)

    @property
    def stopping(self) -> bool:
        """True once :meth:`shutdown` asked the loop to end."""
        return self._stop_loop

    def shutdown(self, timeout_s: float = 2.0) -> LoopStatistics:
        """End the loop after the current cycle and wait for it; returns the loop statistics."""
        self._stop_loop = True
        self.loop.stop()
        self.loop.join(timeout_s)
        return self.loop.statistics()

    @property
    def error(self) -> BaseException | None:
        """The exception that ended the loop, if any."""
        return self.loop.error
