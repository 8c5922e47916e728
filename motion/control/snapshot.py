"""What the control loop publishes after every cycle: an immutable picture of the arm that any thread may read.

The loop replaces :attr:`Controller.snapshot <motion.control.controller.Controller.snapshot>` with a new object at
the end of each cycle (one reference assignment, atomic in Python); nothing in a published snapshot ever changes, so
a reader (``Arm.status()``, the CLI's progress, a live view) needs no lock and never sees half a cycle, and the loop
never waits for a reader.
"""

from __future__ import annotations

import functools
import math
import threading
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, Final, NamedTuple, TypeAlias

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


# The snapshot from its fields in one tuple (what the named tuple's own constructor does, minus a call).
_SnapshotFields: TypeAlias = tuple[
    int, float, NDArray[np.float64], bool, float, float, str, MotionFault | None, int, int, float
]
_new_snapshot: Final[Callable[[_SnapshotFields], CycleSnapshot]] = functools.partial(tuple.__new__, CycleSnapshot)


class SnapshotPublisher:
    """The loop's publication (the module docstring): the latest :class:`CycleSnapshot`, the arm's state and fault as
    the safety layer last set them, and a tap called with each snapshot.

    Args:
        n_joints: joints of the arm.

    Attributes:
        snapshot: the arm after the latest cycle (replaced, never changed: any thread may read it without a lock).
        tap: called by the loop with each published snapshot, in its thread (a live view's feed: must never wait).
        signal: a per-joint array the safety layer keeps up to date (its collision signal, N·m), published in every
            snapshot as it stands (NaN: none); ``limit``: the same for the threshold in force.
    """

    def __init__(self, n_joints: int) -> None:
        self.snapshot = CycleSnapshot(0, math.nan, frozen([np.zeros(n_joints)] * len(JOINT_ROWS)), False)
        self.tap: Callable[[CycleSnapshot], None] | None = None
        self.signal: NDArray[np.float64] = np.full(n_joints, np.nan)
        self.limit: NDArray[np.float64] = np.full(n_joints, np.nan)
        # the state and fault, and the lock that keeps a transition from another thread and the loop's next snapshot
        # from overwriting each other
        self._condition: tuple[str, MotionFault | None] = ("ready", None)
        self._lock = threading.Lock()

    def publish(  # noqa: PLR0917 - the snapshot's fields, as the loop has them
        self,
        cycle: int,
        start_s: float,
        rows: tuple[NDArray[Any], ...],
        commanded: bool,
        motion: tuple[float, float],
        loop: tuple[int, int, float],
    ) -> None:
        """Replace :attr:`snapshot` with a cycle's (one stacked copy: the loop never waits on a reader): its
        ``rows`` (the first seven of :data:`JOINT_ROWS`; the collision rows are :attr:`signal` and :attr:`limit`),
        the motion's start and end and the loop's overruns, skipped cycles and wake-up jitter."""
        joints = frozen((*rows, self.signal, self.limit))
        with self._lock:
            state, fault = self._condition
            self.snapshot = _new_snapshot((cycle, start_s, joints, commanded, *motion, state, fault, *loop))
        tap = self.tap
        if tap is not None:
            tap(self.snapshot)

    def set_condition(self, state: str, fault: MotionFault | None) -> None:
        """The arm's state and fault changed (the safety layer's transition, in any thread): publish them at once in
        a copy of the latest snapshot, and in every snapshot from now on."""
        with self._lock:
            self._condition = (state, fault)
            self.snapshot = self.snapshot._replace(state=state, fault=fault)


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
