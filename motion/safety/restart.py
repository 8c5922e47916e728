"""A drive that restarted (a brown-out, a loose supply), by its family's documented sign: one monitor, a drive's 0x92
or 0xB1 reply in, a ``drive_restarted`` fault or nothing out. Its turn count is then lost: every target in the old
frame would be off by whole turns.

- The older family (v2.3 / v1.62) counts its turns from its power-up: the multi-turn angle (0x92) starts again in
  the drive's first turn. The controller's axes hold every 0x92 reading against the angle they track from the encoder
  (:mod:`motion.control.axes`) and tell a lost frame (:attr:`~motion.control.axes.AxisStates.frame_jump_deg`): a
  reading half a turn or more away where nothing was missed (no motion explains it), or in the first turn after a
  gap. A reading that motion explains (after a silence, outside the first turn) puts the missed turns back: no restart.
- V3: the runtime (0xB1, ms since power-up) going back; and, a round-robin sooner, the fine angle read in every cycle
  jumping between two consecutive cycles by half a motor turn or more beyond what its speed covers, into the first
  output turn, where a drive in single-turn mode restarts (V4.2 section 2.12). Readings further apart (a reply
  missing, a cycle skipped) are not compared: motion may explain them.
"""

from __future__ import annotations

import logging
import math
from typing import Final

from motion.control.axes import UNWRAP_BOUND_MOTOR_DEG
from motion.control.controller import Controller
from motion.control.turns import in_first_turn
from motion.errors import FaultKind, MotionFault
from motion.protocol import MultiTurnAngle
from motion.protocol.table import Direction, WireProtocol, field_range
from motion.protocol.v3.messages import CommandV3, Runtime

logger = logging.getLogger("motion.safety")

#: Where a V3 drive's runtime (0xB1, ms) wraps (one past its field's largest value, as the table declares it), and
#: the slack given to the host's clock against the drive's, ms.
RUNTIME_WRAP_MS: Final = field_range(CommandV3.READ_RUNTIME, Direction.REPLY, WireProtocol.CAN, "runtime_ms")[1] + 1
RUNTIME_SLACK_MS: Final = 1000.0
#: Two fine-angle readings (V3) are of consecutive cycles when at most this many periods apart (one skipped cycle or
#: a missing reply between them makes two).
CONSECUTIVE_PERIODS: Final = 1.5


class RestartCheck:
    """The restart sign of each drive's 0x92 and 0xB1 replies (control thread only).

    Args:
        controller: the controller whose axes track the angles.
    """

    def __init__(self, controller: Controller) -> None:
        self.controller = controller
        specs = controller.specs
        n = len(specs)
        self.names = tuple(s.name for s in specs)
        self._tracks_encoder = [not f.angle_every_cycle for f in controller.families]
        self._drive_gear = [s.drive_gear_ratio for s in specs]
        self._consecutive_s = CONSECUTIVE_PERIODS * controller.period_s
        self._runtime_ms = [-1] * n
        self._runtime_s = [math.nan] * n  # when it was read
        # the fine angle read in every cycle (motor deg, and when: NaN before the first), two lists: no tuple per joint
        # and cycle
        self._last_angle_deg = [math.nan] * n
        self._last_angle_s = [math.nan] * n
        self._restored = [0] * n  # the turns the axes put back after gaps, as last told
        self._restored_told = [False] * n

    def restart(self) -> None:
        """The loop (re)starts: no fine angle to compare with yet."""
        self._last_angle_s[:] = [math.nan] * len(self._last_angle_s)

    def check(self, i: int, message: MultiTurnAngle | Runtime, now_s: float) -> MotionFault | None:
        """The restart sign in a 0x92 or 0xB1 reply of joint ``i`` (taken in at ``now_s``, after the axes took the
        cycle's replies): the ``drive_restarted`` fault (never held: a stop ramp would be in the old frame), or
        None."""
        if isinstance(message, Runtime):
            return self._runtime(i, message, now_s)
        if self._tracks_encoder[i]:
            return self._frame(i, message)
        return self._angle_jump(i, message, now_s)

    def _frame(self, i: int, reading: MultiTurnAngle) -> MotionFault | None:
        """The axes' verdict on an older drive's 0x92 reading: its frame lost. Turns put back after a gap are told
        (a restart while the drive was unheard, its joint moving on past its first turn, reads as that motion)."""
        axes = self.controller.axes
        restored = int(axes.turns_restored[i])
        if restored != self._restored[i]:
            (logger.debug if self._restored_told[i] else logger.warning)(  # (once a joint: a spinning one every cycle)
                "%s: its drive's multi-turn angle (0x92) puts back %+d motor turn(s) its encoder missed while it was "
                "unheard or beyond its unwrapping bound; had its drive lost power meanwhile, its turns would be lost "
                "(home it then)",
                self.names[i],
                restored - self._restored[i],
            )
            self._restored[i], self._restored_told[i] = restored, True
        jump = float(axes.frame_jump_deg[i])
        if math.isnan(jump):
            return None
        where = (
            "to its first turn, where a drive reads after a power-up"
            if in_first_turn(reading.angle_deg)
            else "while every reply of its encoder came (no motion explains it)"
        )
        return self._restarted(i, jump, f"({jump / 360.0:+.2f} turns) from the angle its encoder counted, {where}")

    def _angle_jump(self, i: int, reading: MultiTurnAngle, now_s: float) -> MotionFault | None:
        """A V3 drive's fine angle, read in every cycle, against the one of the cycle before."""
        motor_deg = reading.angle_deg * self._drive_gear[i]
        jump = motor_deg - self._last_angle_deg[i]
        elapsed_s = now_s - self._last_angle_s[i]  # NaN before the first reading: no comparison holds
        self._last_angle_deg[i], self._last_angle_s[i] = motor_deg, now_s
        if not elapsed_s <= self._consecutive_s or not in_first_turn(reading.angle_deg):
            return None
        reach = abs(float(self.controller.axes.motor_speed_dps[i])) * elapsed_s
        if abs(jump) < UNWRAP_BOUND_MOTOR_DEG + reach:
            return None
        return self._restarted(i, jump, "between two cycles, beyond what its speed covers, into its first output turn")

    def _restarted(self, i: int, jump_deg: float, how: str) -> MotionFault:
        """The ``drive_restarted`` fault of joint ``i`` whose 0x92 angle jumped by ``jump_deg`` motor degrees."""
        return MotionFault(
            FaultKind.DRIVE_RESTARTED,
            joint=self.names[i],
            value=round(jump_deg / 360.0, 2),
            time_s=self.controller.clock.now(),
            detail=f"the drive's multi-turn angle (0x92) jumped by {jump_deg:.1f} motor deg {how}: it restarted "
            "(power), and its turn offset is lost",
        )

    def _runtime(self, i: int, reading: Runtime, now_s: float) -> MotionFault | None:
        """A V3 drive's runtime (0xB1) counts from its power-up: less than the last reading means it restarted, its
        multi-turn count then lost unless it keeps it (and the brake locked, the output off)."""
        last, last_s = self._runtime_ms[i], self._runtime_s[i]
        self._runtime_ms[i], self._runtime_s[i] = reading.runtime_ms, now_s
        # the uint32 of milliseconds wraps after 49.7 days: a smaller reading the elapsed time carries past the wrap
        # is the count going on
        wrapped = last + (now_s - last_s) * 1000.0 + RUNTIME_SLACK_MS >= RUNTIME_WRAP_MS
        if reading.runtime_ms >= last or wrapped:
            return None
        return MotionFault(
            FaultKind.DRIVE_RESTARTED,
            joint=self.names[i],
            value=reading.runtime_ms / 1000.0,
            threshold=last / 1000.0,
            time_s=self.controller.clock.now(),
            detail=f"the drive's runtime (0xB1) went back from {last} ms to {reading.runtime_ms} ms: it restarted "
            "(power)",
        )
