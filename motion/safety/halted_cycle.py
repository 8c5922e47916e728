"""The cycle of HALTING and HALTED: the halted state kept every cycle (:mod:`motion.safety.halted`), and its faults.

Every drive gets a frame (its halt while it is not known to be halted, else a state read), joints that leave their
limits and drives that restarted are faults of their own (recorded; the halt in force stays), a joint its drive's own
hold does not hold is released with 0x80 where gravity cannot move it, and braked joints lock once at rest. HALTING
ends (HALTED) once every drive acknowledged its halt, or ``halt_retry_s`` after the halt went out; the halt goes on
being sent to a drive that did not, in HALTED too.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from typing import Final

import numpy as np

from motion.control.controller import Feedforward
from motion.errors import FaultKind, MotionFault, TransportError
from motion.safety.context import SafetyContext, SafetyPart
from motion.safety.reaction import FaultReaction
from motion.safety.states import ArmEvent, ArmState
from motion.transport import Reply, Request

logger = logging.getLogger("motion.safety")

#: A halted cycle's replies before its exchange (one that fails before it has none: its frames go out all the same).
_NO_REPLIES: Final[list[Reply]] = []


class HaltedCycle(SafetyPart):
    """Runs HALTING's and HALTED's cycle (control thread only).

    Args:
        context: the supervisor's pieces (its settings: ``halt_retry_s`` and the joints' Coulomb friction, for a
            release with 0x80; its watchdog: limits, restarts, the joints' names).
        reaction: the fault reaction (when HALTING ends; whether a send is failing).
        gravity: gravity compensation (None: a joint whose hold does not hold is never released).
        reads: the next cycle's status reads (the supervisor's round robin).
    """

    def __init__(
        self,
        context: SafetyContext,
        *,
        reaction: FaultReaction,
        gravity: Feedforward | None,
        reads: Callable[[], tuple[Request, ...]],
    ) -> None:
        super().__init__(context)
        self.reaction = reaction
        self.gravity = gravity
        self._reads = reads

    def run(self, state: ArmState, start_s: float, deadline_s: float) -> None:
        """HALTING and HALTED: every drive gets a frame (its halt while it is not known to be halted, else a state
        read; see :mod:`motion.safety.halted`), joints that leave their limits and drives that restarted are faults
        of their own, and braked joints lock once at rest."""
        controller = self.controller
        requests = self.guard.requests()
        requests.extend(self._reads())
        controller.last_replies = _NO_REPLIES
        try:
            replies = controller.step(start_s, deadline_s, extra=requests, command=False, apply_pending=False)
        except TransportError:
            raise
        except Exception:
            replies = controller.last_replies  # a cycle hook failed after the exchange: its replies are taken in
            if replies is _NO_REPLIES:  # the cycle failed before its exchange: the frames go out all the same
                budget = controller.options.reply_budget
                replies = controller.bus.transact(requests, start_s + budget * (deadline_s - start_s))
                controller.absorb(replies)
            self._take(state, replies, deadline_s)
            raise
        self._take(state, replies, deadline_s)

    def _take(self, state: ArmState, replies: list[Reply], deadline_s: float) -> None:
        """The halted cycle's replies: acknowledgements, drives driving or swinging, limits, restarts, braked joints
        whose drives cannot hold (braked now, in this cycle), and the end of HALTING."""
        controller, guard, log = self.controller, self.guard, self.log
        self.reaction.send_failing = False
        now = controller.clock.now()
        axes = controller.axes
        driving, outside, swinging = guard.take(replies, axes, self.watchdog.within, now)
        names = self.watchdog.names
        for i in driving:
            logger.warning("%s reads as driving while halted: its halt is sent again", names[i])
        for i in outside:
            detail = "beyond its limits while halted (its halt is sent again)"
            log.record_halted(
                MotionFault(
                    FaultKind.POSITION_LIMIT, joint=names[i], value=float(axes.q_deg[i]), time_s=now, detail=detail
                ),
                guard.code,
            )
        for i in swinging:
            log.record_halted(self._swinging(i, now), guard.code)
        for fault in self.watchdog.restarts(replies, now):
            if fault.joint not in log.lost_frames:
                log.lost_frames.add(str(fault.joint))
                log.record_halted(fault, guard.code)
        if state is ArmState.HALTING:
            self._end_halting(now)
        unheld = self.brakes.take(replies, now)
        if unheld is not None:
            log.record_halted(unheld, guard.code)
            # (its 0x78 at once, not with the next cycle's batch: a joint its drive does not hold is falling)
            self.reaction.send_halt(self.reaction.window_end(controller.clock.now(), deadline_s))

    def _end_halting(self, now_s: float) -> None:
        """HALTED once every drive acknowledged its halt, or once ``halt_retry_s`` passed (the halt goes on being
        sent to the drives that did not)."""
        unacknowledged = self.guard.unacknowledged
        if unacknowledged and now_s < self.reaction.halt_until_s:
            return
        unanswered = self.guard.unanswered  # (not those that answered it and missed a read since)
        if unanswered:
            logger.error(
                "drives %s did not acknowledge the halt within %g s: it is sent to them every cycle while the "
                "session is open",
                sorted(unanswered),
                self.settings.halt_retry_s,
            )
        self.machine.fire(ArmEvent.ACKNOWLEDGED)

    def _swinging(self, i: int, now_s: float) -> MotionFault:
        """Joint ``i`` swings back and forth, or runs on, although halted (its drive's own 0x81 hold does not hold it):
        released with 0x80 where gravity cannot move it (its gravity torque here within its Coulomb friction), else kept
        at 0x81."""
        controller, guard = self.controller, self.guard
        gravity = self.gravity
        friction = self.settings.coulomb_friction_nm
        load_nm = math.inf
        if gravity is not None and friction:
            zero = np.zeros(len(guard.ids))
            load_nm = abs(float(gravity(controller.axes.q_deg, zero, zero)[i]))
        braked = guard.ids[i] in guard.braked_ids  # its brake locks once at rest: never released
        released = not braked and load_nm <= (friction[i] if friction else -math.inf)
        if released:
            guard.release(i)
        what = (
            f"released with 0x80 (gravity there {load_nm:.3f} N·m, within its friction)"
            if released
            else "kept at 0x81: gravity may load it beyond its friction; check the drive's position-loop tuning"
        )
        return MotionFault(
            FaultKind.HOLD_FAILED,
            joint=self.watchdog.names[i],
            value=float(controller.axes.q_deg[i]),
            time_s=now_s,
            detail=f"its drive's own hold (0x81) does not hold it (it swings, or runs on): {what}",
        )
