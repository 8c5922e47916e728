"""Whether every joint is at rest: what ``clear()`` requires before the loop takes the joints over again.

A halted joint coasts until its drive's own stop brings it to rest (0x81 brakes it at the drive's own deceleration;
under 0x80 friction and gravity have it). A clear hands every joint to the loop, which holds where it reads the
joint *then*: a joint still moving is pulled back by the loop's stiffness (the drive's position loop at up to the
velocity limit, or the controller's PD) from wherever its momentum carries it. Cleared 4 ms after an E-stop with the
shoulder at 118 deg/s, arm2's PD swung it through 7.6 deg, 3.5 times its drive's own stopping distance. So a clear
needs every joint at rest, and this check says which one is not.

At rest, per joint: every reading of its speed over the last :data:`REST_S` before its latest one (and at least two
readings) at most its rest speed, :attr:`RestCheck.rest_dps`: one step of the coarsest speed field, whole deg/s of a
V3 drive's output (:data:`motion.safety.halted.BRAKE_REST_DPS`), or one step of the joint's own field where that is
coarser (the older family's 1 deg/s of the motor, through the gear: a ninth of that on a 1:9 joint). A reading at or
below one step is as still as the field can tell, and a joint creeping slower than one step of the coarsest field
moves less than 0.05 deg in :data:`REST_S`. The time is the brake's (:data:`motion.safety.halted.BRAKE_REST_S`, the
time a braked joint reads at rest before its brake locks): a reading or two can catch a joint swinging through zero
speed as its drive's hold settles. A cycle without a reading of the joint (its reply missing) starts its time again:
it was not seen.

:class:`RestCheck` takes the readings of every cycle, in every state (:meth:`RestCheck.take`), and the clear's own
(:mod:`motion.safety.clearing`), and says which joint is not at rest (:meth:`RestCheck.moving`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Final

import numpy as np

from motion.control.controller import Controller
from motion.errors import FaultKind, MotionFault
from motion.safety.halted import BRAKE_REST_DPS, BRAKE_REST_S

#: How long every reading of a joint must show it at rest, s (the brake's rest time, :data:`BRAKE_REST_S`).
REST_S: Final = BRAKE_REST_S
#: Times closer than this are the same instant (simulated time's sums of periods), s.
_SAME_S: Final = 1e-9


class RestCheck:
    """Each joint's readings at rest, from the measured speeds of every cycle (control thread only).

    Args:
        controller: the controller whose measured joint states (speeds, which joints the latest replies refreshed
            and when) are read.
    """

    def __init__(self, controller: Controller) -> None:
        self.controller = controller
        n = len(controller.specs)
        self.names = tuple(s.name for s in controller.specs)
        #: Per joint, the fastest reading that counts as at rest, joint deg/s (module doc).
        self.rest_dps = np.maximum(BRAKE_REST_DPS, controller.axes.speed_step_dps)
        #: Per joint, when it was last read faster than that, or not read in a cycle (the reply's time, or the
        #: cycle's; -inf: neither yet), s.
        self.moved_s = np.full(n, -np.inf)
        #: Per joint, its readings at rest since then.
        self.readings_at_rest = np.zeros(n, dtype=np.int64)
        self._taken_s = np.full(n, -np.inf)  # the reply time of the latest reading taken
        self._speed = np.zeros(n)
        self._new = np.zeros(n, dtype=bool)
        self._still = np.zeros(n, dtype=bool)
        self._other = np.zeros(n, dtype=bool)

    def take(self) -> None:
        """Take the latest readings (those the controller's latest exchange refreshed and not taken yet; a joint
        without one in that exchange was not seen, and its time at rest starts again)."""
        axes = self.controller.axes
        new, still, other, count = self._new, self._still, self._other, self.readings_at_rest
        np.greater(axes.last_reply_s, self._taken_s, out=new)
        new &= axes.fresh
        np.copyto(self._taken_s, axes.last_reply_s, where=new)
        np.abs(axes.qd_dps, out=self._speed)
        np.less_equal(self._speed, self.rest_dps, out=still)
        np.logical_not(still, out=other)
        other &= new  # read moving
        np.copyto(self.moved_s, axes.last_reply_s, where=other)
        np.copyto(count, 0, where=other)
        np.logical_not(axes.fresh, out=other)  # not read
        np.copyto(self.moved_s, self.controller.clock.now(), where=other)
        np.copyto(count, 0, where=other)
        still &= new
        count += still

    def moving(self, also: Sequence[str] = ()) -> MotionFault | None:
        """The joint not at rest (module doc), as the fault of a clear it refuses (kind ``clear_failed``, naming the
        joint, its latest speed reading and the rest speed; the first such joint in joint order, every one in the
        detail, followed by ``also``: what else keeps the clear from succeeding); None when every joint is at rest."""
        axes = self.controller.axes
        rested = axes.last_reply_s - self.moved_s  # (once per clear: an allocation is no matter here)
        moving = [
            i for i in range(len(self.names)) if not (rested[i] >= REST_S - _SAME_S and self.readings_at_rest[i] >= 2)
        ]
        if not moving:
            return None
        parts = []
        for i in moving:
            speed, at_rest_s = float(axes.qd_dps[i]), float(rested[i])
            if abs(speed) > self.rest_dps[i] or not axes.fresh[i]:
                how = "moving" if axes.fresh[i] else "not read in the latest cycle"
            else:
                how = f"at rest for {max(at_rest_s, 0.0) * 1000:.1f} ms" if math.isfinite(at_rest_s) else "read once"
            parts.append(f"{self.names[i]} {speed:+.1f} deg/s ({how})")
        first = moving[0]
        return MotionFault(
            FaultKind.CLEAR_FAILED,
            joint=self.names[first],
            value=float(axes.qd_dps[first]),
            threshold=float(self.rest_dps[first]),
            time_s=self.controller.clock.now(),
            detail="; ".join(
                [
                    f"not every joint is at rest (every reading for {REST_S * 1000:g} ms at most {BRAKE_REST_DPS:g} "
                    f"deg/s or one step of its speed field): {', '.join(parts)}; clear() once they are",
                    *also,
                ]
            ),
            joints=tuple(self.names[i] for i in moving),
        )
