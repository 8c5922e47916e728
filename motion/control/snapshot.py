"""What the control loop publishes after every cycle: an immutable picture of the arm that any thread may read.

The loop replaces :attr:`Controller.snapshot <motion.control.controller.Controller.snapshot>` with a new object at
the end of each cycle (one reference assignment, atomic in Python); nothing in a published snapshot ever changes, so
a reader (``Arm.status()``, the CLI's progress, a live view) needs no lock and never sees half a cycle, and the loop
never waits for a reader.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np
from numpy.typing import NDArray

from motion.errors import MotionFault

#: Rows of :attr:`CycleSnapshot.joints`, in this order (``fresh`` as 1.0 / 0.0).
JOINT_ROWS = (
    "position_deg",
    "velocity_dps",
    "reference_deg",
    "iq_a",
    "temperature_c",
    "fresh",
    "expected_deg",
    "collision_signal_nm",
    "collision_limit_nm",
)


class CycleSnapshot(NamedTuple):
    """The arm after one control cycle (controller clock; joint order; a read-only array).

    A named tuple rather than a frozen dataclass: it is built every cycle, and a tuple is built in a third of the time.

    Attributes:
        cycle: cycles run so far, this one included.
        time_s: the cycle's scheduled start, s.
        joints: one row per :data:`JOINT_ROWS` entry, one column per joint (read-only).
        commanded: set-points were sent in this cycle (False while halted: reads only).
        motion_start_s: start of the motion being played, s (NaN when none is).
        motion_end_s: its end, s (NaN when none is).
        state: the arm's state (``motion.safety.ArmState`` value: ``ready``, ``moving``, ``halting`` ...); a
            transition between cycles is published at once, in a copy of the cycle's snapshot.
        fault: the fault the arm is halted or holding for (None when it is not).
        overruns: cycles so far that ended after the next one's start.
        skipped_cycles: grid points skipped so far to catch up.
        jitter_s: this cycle's wake-up time minus its scheduled start, s.
    """

    cycle: int
    time_s: float
    joints: NDArray[np.float64]
    commanded: bool
    motion_start_s: float = math.nan
    motion_end_s: float = math.nan
    state: str = "ready"
    fault: MotionFault | None = None
    overruns: int = 0
    skipped_cycles: int = 0
    jitter_s: float = 0.0

    @property
    def fresh(self) -> NDArray[np.bool_]:
        """Per joint, whether this cycle brought a reply with its state."""
        fresh: NDArray[np.bool_] = self.joints[5] != 0.0
        return fresh

    @property
    def position_deg(self) -> NDArray[np.float64]:
        """Measured joint angles, deg."""
        return self._row(0)

    @property
    def velocity_dps(self) -> NDArray[np.float64]:
        """Measured joint speeds, deg/s."""
        return self._row(1)

    @property
    def reference_deg(self) -> NDArray[np.float64]:
        """The reference the cycle sent set-points for, deg."""
        return self._row(2)

    @property
    def iq_a(self) -> NDArray[np.float64]:
        """Measured torque currents, A."""
        return self._row(3)

    @property
    def expected_deg(self) -> NDArray[np.float64]:
        """Where each joint should be under its control loop (the following error is this minus the measured
        angle; :mod:`motion.control.tracking`), deg."""
        return self._row(6)

    @property
    def collision_signal_nm(self) -> NDArray[np.float64]:
        """The collision observer's signal per joint, N·m (what ``collision_threshold_nm`` applies to; NaN without
        an observer; the safety layer's evaluation of the cycle before)."""
        return self._row(7)

    @property
    def collision_limit_nm(self) -> NDArray[np.float64]:
        """The collision threshold in force per joint, N·m: the configured one, or the bound where that is higher
        (:mod:`motion.safety.collision_bound`; inf for a joint not watched, NaN without an observer)."""
        return self._row(8)

    @property
    def temperature_c(self) -> NDArray[np.float64]:
        """Motor temperatures, °C."""
        return self._row(4)

    def _row(self, index: int) -> NDArray[np.float64]:
        row: NDArray[np.float64] = self.joints[index]
        return row

    @property
    def moving(self) -> bool:
        """True while a motion is being played."""
        return not math.isnan(self.motion_end_s)


def frozen(rows: Sequence[NDArray[Any]]) -> NDArray[np.float64]:
    """A read-only copy of ``rows`` stacked (it belongs to a published snapshot)."""
    array = np.array(rows, dtype=np.float64)
    array.flags.writeable = False
    return array


@dataclass(frozen=True, slots=True)
class MotionProgress:
    """How far a motion has come (controller clock).

    Attributes:
        elapsed_s: time since it started, s (at most its duration).
        duration_s: its planned duration, s.
        done: it has ended (reached its end, was stopped, or a fault halted the arm).
    """

    elapsed_s: float
    duration_s: float
    done: bool

    @property
    def fraction(self) -> float:
        """Share of the motion done, 0..1 (1 once it has ended)."""
        if self.done or self.duration_s <= 0.0:
            return 1.0
        return min(1.0, max(0.0, self.elapsed_s / self.duration_s))
