"""Clocks for the control loop: the real monotonic clock with a hybrid sleep/spin wait, and a manual clock.

Every time in the controller is seconds of one clock; tests inject :class:`ManualClock` so that a control run is
deterministic and as fast as the CPU allows.
"""

from __future__ import annotations

import time
from typing import Protocol

# Sleep until this long before the deadline, then spin: Linux sleeps overshoot by ~50-100 µs, more under load.
DEFAULT_SPIN_S = 0.0005


class Clock(Protocol):
    """What the scheduler needs of a clock."""

    def now(self) -> float:
        """Current time, seconds."""

    def sleep_until(self, deadline_s: float) -> None:
        """Return at (or just after) ``deadline_s``."""


class MonotonicClock:
    """``time.monotonic`` with a hybrid wait: ``time.sleep`` for the bulk, a short spin for the last bit.

    Args:
        spin_s: how long before the deadline to stop sleeping and spin (0 = never spin).
    """

    def __init__(self, spin_s: float = DEFAULT_SPIN_S) -> None:
        if spin_s < 0:
            raise ValueError(f"spin_s: {spin_s!r} must be >= 0")
        self.spin_s = spin_s

    def now(self) -> float:
        """Current monotonic time, seconds."""
        return time.monotonic()

    def sleep_until(self, deadline_s: float) -> None:
        """Sleep, then spin, until ``deadline_s``."""
        remaining = deadline_s - time.monotonic() - self.spin_s
        if remaining > 0:
            time.sleep(remaining)
        while time.monotonic() < deadline_s:
            pass


class ManualClock:
    """A clock that only moves when told to; ``sleep_until`` jumps to the deadline at once.

    Args:
        start_s: initial time, seconds.
    """

    def __init__(self, start_s: float = 0.0) -> None:
        self._t = start_s

    def now(self) -> float:
        """Current manual time, seconds."""
        return self._t

    def sleep_until(self, deadline_s: float) -> None:
        """Jump to ``deadline_s`` (never backwards)."""
        self._t = max(self._t, deadline_s)

    def advance(self, dt_s: float) -> None:
        """Move time forward by ``dt_s`` (e.g. to simulate a slow cycle)."""
        if dt_s < 0:
            raise ValueError(f"dt_s: {dt_s!r} must be >= 0")
        self._t += dt_s


def is_simulated(clock: object) -> bool:
    """True for a clock whose time passes only when the program waits (a simulation's): a loop on it runs its cycles
    in the waiting thread, never in a thread of its own."""
    return getattr(clock, "simulated", False) is True
