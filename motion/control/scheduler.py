"""Fixed-rate control loop with absolute deadlines (no drift), overrun counting and timing statistics.

Cycle *k* is scheduled at ``t0 + k * period``; the loop never schedules relative to "now", so a late cycle does not
push the following ones. A cycle that ends after the next cycle's start is an overrun; the loop then skips the
missed grid points (it does not burst to catch up) and counts them.
"""

from __future__ import annotations

import contextlib
import math
import threading
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from motion.control.clock import Clock, MonotonicClock

#: One control cycle: ``cycle(k, start_s, deadline_s) -> keep_running``. ``deadline_s`` is the start of cycle k+1.
CycleFn = Callable[[int, float, float], bool]

MIN_RATE_HZ = 1.0
MAX_RATE_HZ = 5000.0


@dataclass(frozen=True, slots=True)
class LoopStatistics:
    """Timing of a loop run. Jitter is the wake-up time minus the scheduled start; periods are start to start."""

    cycles: int
    overruns: int
    skipped_cycles: int
    rate_hz: float
    achieved_rate_hz: float
    period_mean_s: float
    jitter_p50_s: float
    jitter_p99_s: float
    jitter_max_s: float
    busy_p99_s: float

    def summary(self) -> str:
        """One line for people."""
        return (
            f"{self.cycles} cycles at {self.achieved_rate_hz:.1f} Hz (target {self.rate_hz:g} Hz), "
            f"jitter p50 {self.jitter_p50_s * 1e6:.0f} us p99 {self.jitter_p99_s * 1e6:.0f} us "
            f"max {self.jitter_max_s * 1e6:.0f} us, cycle busy p99 {self.busy_p99_s * 1e6:.0f} us, "
            f"{self.overruns} overruns ({self.skipped_cycles} cycles skipped)"
        )


class FixedRateLoop:
    """Runs ``cycle`` at ``rate_hz`` on absolute deadlines, in the calling thread or its own.

    Args:
        rate_hz: cycle rate, Hz.
        cycle: the cycle function; it returns False to end the loop. An exception ends the loop and is kept in
            :attr:`error` (and re-raised by :meth:`run`).
        clock: time source (inject a ManualClock in tests).
        history: number of most recent cycles kept for the statistics.
    """

    def __init__(self, rate_hz: float, cycle: CycleFn, clock: Clock | None = None, history: int = 100_000) -> None:
        if isinstance(rate_hz, bool) or not (
            isinstance(rate_hz, (int, float)) and MIN_RATE_HZ <= rate_hz <= MAX_RATE_HZ
        ):
            raise ValueError(f"rate_hz: {rate_hz!r} is outside the valid range {MIN_RATE_HZ:g}..{MAX_RATE_HZ:g}")
        self.rate_hz = float(rate_hz)
        self.period_s = 1.0 / self.rate_hz
        self._cycle = cycle
        self.clock: Clock = clock if clock is not None else MonotonicClock()
        self._jitter = np.zeros(history)
        self._busy = np.zeros(history)
        self._starts = np.zeros(history)
        self.cycles = 0
        self.overruns = 0
        self.skipped_cycles = 0
        self.error: BaseException | None = None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._stepping = False
        self._step_lock = threading.RLock()
        self._begun = False
        self._ended = False
        self._t0 = 0.0
        self._k = 0

    def run(self) -> None:
        """Run cycles until ``cycle`` returns False or :meth:`stop` is called; re-raises a cycle's exception."""
        self._begin()
        while not self._stop.is_set() and self._next_cycle():
            pass

    def _begin(self) -> None:
        self._t0 = self.clock.now()
        self._k = 0
        self._begun = True
        self._ended = False

    def _next_cycle(self) -> bool:
        """Run cycle k at its scheduled start; False once the loop has ended (re-raises a cycle's exception)."""
        clock, period = self.clock, self.period_s
        jitter, busy, starts, size = self._jitter, self._busy, self._starts, len(self._jitter)
        t0, k = self._t0, self._k
        try:
            scheduled = t0 + k * period
            clock.sleep_until(scheduled)
            woke = clock.now()
            slot = self.cycles % size
            jitter[slot] = woke - scheduled
            starts[slot] = woke
            keep = self._cycle(k, scheduled, scheduled + period)
            done = clock.now()
            busy[slot] = done - woke
            self.cycles += 1
        except BaseException as exc:
            self.error = exc
            self._ended = True
            raise
        if not keep:
            self._ended = True
            return False
        k += 1
        if done > t0 + k * period:
            self.overruns += 1
            # Skip the grid points already missed: start at the next one still in the future.
            next_k = math.floor((done - t0) / period) + 1
            self.skipped_cycles += next_k - k
            k = next_k
        self._k = k
        return True

    def begin_stepping(self) -> None:
        """Start the loop without a thread: the cycles run in whichever thread calls :meth:`step_until`.

        This is how a simulated clock is run: simulated time passes only while someone waits for it.
        """
        if self._thread is not None or self._begun:
            raise RuntimeError("the loop is already running")
        self._stepping = True
        self._begin()

    def step_until(self, done: Callable[[], bool], timeout_s: float | None = None) -> bool:
        """Run cycles in the calling thread until ``done()`` holds or ``timeout_s`` of the loop's clock passed.

        Returns:
            ``done()`` at the end (also when the loop ended).
        """
        clock = self.clock
        end = None if timeout_s is None else clock.now() + timeout_s
        while not done():
            # One cycle at a time, whichever thread waits: two waiting threads (a motion's wait() and an E-stop)
            # take turns instead of running cycles at once.
            with self._step_lock:
                if done():
                    break
                if self._ended or self._stop.is_set() or (end is not None and clock.now() >= end):
                    return done()
                if end is not None and self._t0 + self._k * self.period_s > end:
                    clock.sleep_until(end)  # the next cycle starts after the wait ends
                    return done()
                self._next_cycle()
        return True

    @property
    def next_cycle(self) -> int:
        """Index of the next cycle to run (cycle ``k`` is scheduled at ``t0 + k * period``)."""
        return self._k

    @property
    def stepping(self) -> bool:
        """True when the loop runs its cycles in the callers' threads (see :meth:`begin_stepping`)."""
        return self._stepping

    def start(self, name: str = "rmd-control") -> None:
        """Run the loop in a new thread."""
        if self._thread is not None or self._begun:
            raise RuntimeError("the loop is already running")
        self._thread = threading.Thread(target=self._run_quietly, name=name, daemon=True)
        self._thread.start()

    def _run_quietly(self) -> None:
        # The exception is kept in self.error for the owner; a thread has nobody else to raise it to.
        with contextlib.suppress(BaseException):
            self.run()

    def stop(self) -> None:
        """Ask the loop to end after the current cycle."""
        self._stop.set()

    def join(self, timeout_s: float | None = None) -> bool:
        """Wait for the loop thread; returns True when it has ended."""
        if self._thread is None:
            return True
        self._thread.join(timeout_s)
        return not self._thread.is_alive()

    @property
    def wake_jitter_s(self) -> float:
        """Wake-up jitter of the cycle in progress, s (read from inside the cycle function, e.g. a cycle hook)."""
        return float(self._jitter[self.cycles % len(self._jitter)])

    @property
    def last_busy_s(self) -> float:
        """Wake-up to return of the last completed cycle, s (0.0 before the first one)."""
        return float(self._busy[(self.cycles - 1) % len(self._busy)]) if self.cycles else 0.0

    @property
    def running(self) -> bool:
        """True while the loop thread is alive (stepping: from :meth:`begin_stepping` until it ended or stopped)."""
        if self._stepping:
            return not (self._ended or self._stop.is_set())
        return self._thread is not None and self._thread.is_alive()

    def statistics(self) -> LoopStatistics:
        """Statistics over the most recent cycles (up to ``history``)."""
        n = min(self.cycles, len(self._jitter))
        if n == 0:
            return LoopStatistics(0, 0, 0, self.rate_hz, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
        order = np.argsort(self._starts[:n]) if self.cycles > len(self._jitter) else slice(0, n)
        starts = self._starts[:n][order]
        jitter = self._jitter[:n]
        periods = np.diff(starts)
        mean = float(periods.mean()) if len(periods) else 0.0
        return LoopStatistics(
            cycles=self.cycles,
            overruns=self.overruns,
            skipped_cycles=self.skipped_cycles,
            rate_hz=self.rate_hz,
            achieved_rate_hz=1.0 / mean if mean > 0 else 0.0,
            period_mean_s=mean,
            jitter_p50_s=float(np.percentile(jitter, 50)),
            jitter_p99_s=float(np.percentile(jitter, 99)),
            jitter_max_s=float(jitter.max()),
            busy_p99_s=float(np.percentile(self._busy[:n], 99)),
        )
