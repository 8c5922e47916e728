"""The reaction to a fault, in the cycle it is detected, and the cycles of the states it leads to.

:meth:`FaultReaction.react` decides by the policy (:class:`~motion.config.schema.HaltPolicy`), the fault's kind and
the state (whether the table lets it HOLD or COMPLY) and starts the reaction at once: COMPLYING (a collision under
``comply``: gravity compensation with zero gains), HOLDING (``hold``, a holdable kind, the arm running: a jerk-limited
stop of the reference, then held) or HALTING (0x81, 0x80 under ``off``, to every axis in one batch). A reaction that
cannot start falls back to the halt; a send that fails leaves every drive owed its halt (HALTING, sent again every
cycle), and a bus that closed is lost (BUS_LOST).

The states' cycles: :meth:`~FaultReaction.holding_cycle` streams the stop ramp and escalates a fault the hold is not
for, or a hold that does not hold (:mod:`motion.safety.hold`), to the halt; :meth:`~FaultReaction.complying_cycle`
streams gravity compensation until any fault halts; :meth:`~FaultReaction.pending_cycle` (HALT_PENDING, the table's
safe state of a state that sent no halt) sends the halt owed. HALTING and HALTED: :mod:`motion.safety.halted_cycle`.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from typing import Final

import numpy as np

from motion.config.schema import HaltPolicy
from motion.control.controller import Feedforward
from motion.errors import FaultKind, MotionError, MotionFault, TransportError
from motion.protocol import Command
from motion.safety.brakes import evaluate_cycle
from motion.safety.context import SafetyContext, SafetyPart
from motion.safety.hold import HoldCheck
from motion.safety.records import REACTIONS, HaltRecord, Reaction, same_cause
from motion.safety.states import HALT_STATES, TRANSITIONS, ArmEvent, ArmState
from motion.trajectory import State
from motion.transport import Request

logger = logging.getLogger("motion.safety")

#: Shortest window given to a reaction's first frames in the detection cycle, s: a fault found late in its cycle still
#: gets its halt (on RS485 one frame after the other) out and answered.
HALT_WINDOW_S = 0.002

#: What the log says each reaction does.
_ACTIONS: Final = {
    Reaction.COMPLY: "comply",
    Reaction.HOLD: "stop ramp and hold",
    Reaction.MOTOR_OFF: "0x80 off",
    Reaction.MOTOR_STOP: "0x81 stop",
}
#: The streamed reactions, as the log names one that could not start.
_STREAMED: Final = {Reaction.COMPLY: "compliance", Reaction.HOLD: "the hold"}


class FaultReaction(SafetyPart):
    """Reacts to faults and runs the cycles of HOLDING, COMPLYING and HALT_PENDING (control thread only).

    Args:
        context: the supervisor's pieces (its settings: the halt policy, the collision reaction, ``halt_retry_s``;
            its watchdog is evaluated in the streamed reactions' cycles).
        gravity: gravity compensation for ``comply`` (None: a collision halts with 0x81).
        reads: the next cycle's status reads (the supervisor's round robin).
    """

    def __init__(
        self,
        context: SafetyContext,
        *,
        gravity: Feedforward | None,
        reads: Callable[[], tuple[Request, ...]],
    ) -> None:
        super().__init__(context)
        self.gravity = gravity
        self._reads = reads
        self.hold = HoldCheck(context.controller, context.watchdog)
        #: Until when HALTING waits for every drive's acknowledgement (set whenever HALTING is entered).
        self.halt_until_s = -math.inf
        #: A send of the halt failed, and none has gone through since (logged once per run of failures).
        self.send_failing = False
        self._starters: dict[Reaction, Callable[[MotionFault, float, float], float]] = {
            Reaction.COMPLY: self._start_comply,
            Reaction.HOLD: self._start_hold,
        }

    def react(self, fault: MotionFault, k: int, start_s: float, deadline_s: float) -> None:
        """React to ``fault`` (seen in cycle ``k``, -1 in a faulted state's cycle): the stop ramp where the policy,
        the kind and the state allow it, compliance for a collision under ``comply``, else the halt."""
        controller = self.controller
        detected = controller.clock.now()
        # a move queued during this cycle must not replace the halt, and the motion playing ends here, by this fault
        controller.abort_motion(fault)
        state = self.machine.state
        if self._repeated(fault, state):
            return
        self.log.record(fault)
        policy = self._policy(fault)
        code = Command.MOTOR_OFF if policy is HaltPolicy.OFF else Command.MOTOR_STOP
        chosen = self._choose(fault, policy, state, code)
        level = logging.INFO if fault.kind is FaultKind.CLOSE else logging.ERROR
        logger.log(level, "halting every axis (%s): %s", _ACTIONS[chosen], fault)
        sent = detected
        try:
            sent = self._start(chosen, fault, start_s, deadline_s, detected_s=detected, code=code)
        except TransportError as exc:
            # recorded before the state changes (HALTING, or BUS_LOST): a thread waiting on the state reads it at once
            self.log.halts.append(HaltRecord(fault, k, detected, sent, Reaction(code.name)))
            self._send_failed(exc, detected, code)
            return
        except Exception as exc:  # the state is HALTING: the next cycle sends the halt again
            logger.error("halt could not be sent: %s: %s", type(exc).__name__, exc)
        reaction = REACTIONS.get(self.machine.state) or Reaction(self.guard.code.name)
        self.log.halts.append(HaltRecord(fault, k, detected, sent, reaction))

    def _repeated(self, fault: MotionFault, state: ArmState) -> bool:
        """Whether ``fault`` is the cause the halt is for, again (a hook, a tap, a port that keeps failing, in every
        cycle): recorded once. The halted cycle goes on sending the halt to every drive not known to be halted (its
        bookkeeping was done before the hooks ran); a send that failed leaves every drive owed its halt again."""
        current = self.log.fault
        if state not in HALT_STATES or current is None or not same_cause(fault, current):
            return False
        if fault.kind is FaultKind.TRANSPORT:
            if self.controller.bus.closed:
                self.lose_bus(TransportError(fault.detail))
            else:
                self.guard.begin(self.guard.code)
        return True

    def _policy(self, fault: MotionFault) -> HaltPolicy:
        """The reaction configured for ``fault``: the collision reaction for a collision, else the halt policy."""
        settings = self.settings
        if self.machine.state is ArmState.COMPLYING:  # compliance ends in the drives' own stop, whatever the policy
            return HaltPolicy.STOP
        if fault.kind is FaultKind.COLLISION and settings.collision_reaction is not None:
            return settings.collision_reaction
        return settings.halt_policy

    def _choose(self, fault: MotionFault, policy: HaltPolicy, state: ArmState, code: Command) -> Reaction:
        """Compliance for a collision under ``comply`` where the state can yield (running, or holding: the ramp
        would go on into what the arm hit) and a gravity model is there; the stop ramp under ``hold`` for a holdable
        kind where the state can hold (running); else the halt ``code``."""
        if (
            policy is HaltPolicy.COMPLY
            and fault.kind is FaultKind.COLLISION
            and (state, ArmEvent.COMPLY) in TRANSITIONS
            and self.gravity is not None
        ):
            return Reaction.COMPLY
        if policy is HaltPolicy.HOLD and fault.kind.holdable and (state, ArmEvent.HOLD) in TRANSITIONS:
            return Reaction.HOLD
        return Reaction(code.name)

    def _start(
        self,
        chosen: Reaction,
        fault: MotionFault,
        start_s: float,
        deadline_s: float,
        *,
        detected_s: float,
        code: Command,
    ) -> float:
        """Start ``chosen``; returns when its first frames went out. A streamed reaction that cannot start must not
        leave the last command in force: every axis is halted with ``code`` (0x81) instead.

        Raises:
            TransportError: a send failed.
        """
        starter = self._starters.get(chosen)
        if starter is not None:
            try:
                return starter(fault, start_s, deadline_s)
            except TransportError:
                raise
            except Exception as exc:
                logger.error(
                    "%s could not start (%s: %s): halting every axis with 0x81 instead",
                    _STREAMED[chosen],
                    type(exc).__name__,
                    exc,
                )
        return self.start_halt(detected_s, deadline_s, code)

    def _start_comply(self, fault: MotionFault, start_s: float, deadline_s: float) -> float:
        """Enter COMPLYING: gravity compensation alone from this cycle on; returns when it was sent.

        Raises:
            Exception: whatever kept it from starting (the caller falls back to the drives' own halt).
        """
        controller = self.controller
        gravity = self.gravity
        if gravity is None:
            raise MotionError("no gravity model to comply with")
        self.machine.fire(ArmEvent.COMPLY)
        sent = controller.clock.now()
        controller.comply_step(sent, self.window_end(sent, deadline_s), gravity)
        return sent

    def _start_hold(self, fault: MotionFault, start_s: float, deadline_s: float) -> float:
        """Enter HOLDING: replace the reference with a jerk-limited stop and send its first set-point; returns when it
        was sent. After a following error the stop ramp starts from where the joints are, as they move (a ramp from
        the reference would carry a blocked joint's set-point on past what blocks it).

        Raises:
            Exception: whatever kept the hold from starting (the caller falls back to the drives' own halt).
        """
        controller = self.controller
        self.machine.fire(ArmEvent.HOLD)
        self.hold.restart()
        follower = controller.follower
        if follower is None:
            raise MotionError("no trajectory follower to plan the stop ramp")
        if fault.kind is FaultKind.FOLLOWING_ERROR:
            axes = controller.axes
            measured = State(axes.positions(), axes.qd_dps.copy(), np.zeros(len(axes.q_deg)))
            follower.stop_from(start_s, measured)
            controller.reference = measured
            self.watchdog.restart_following()  # the expectation starts again from there too
        else:
            follower.stop(start_s)
        sent = controller.clock.now()
        controller.step(sent, self.window_end(sent, deadline_s), apply_pending=False)
        return sent

    def start_halt(self, detected_s: float, deadline_s: float, code: Command) -> float:
        """Enter HALTING: 0x81 (0x80 under ``halt_policy: off``) to every axis now, in one batch; returns when it was
        sent."""
        self._enter_halting(code, detected_s)
        sent = self.controller.clock.now()
        try:
            self.send_halt(self.window_end(sent, deadline_s))
        finally:
            self._stop_reference()
        return sent

    def window_end(self, sent_s: float, deadline_s: float) -> float:
        """Until when a reaction's first exchange, sent at ``sent_s``, waits for its replies in a cycle that ends at
        ``deadline_s`` (the next one's start): :data:`HALT_WINDOW_S` at least, else not into the last part of the
        cycle (half of what the reply budget leaves). One that waited for a silent drive up to the next cycle's start
        ran over it, the loop skipped the next cycle, and the other drives heard nothing for two periods (the
        explorer: an E-stop at a cycle's start, a healthy V3 drive tripped its 20 ms link-loss protection at 100 Hz).
        What answers after the window is taken in the next cycles."""
        controller = self.controller
        leave_s = 0.5 * (1.0 - controller.options.reply_budget) * controller.period_s
        return max(sent_s + HALT_WINDOW_S, deadline_s - leave_s)

    def _enter_halting(self, code: Command, detected_s: float) -> None:
        """Every drive is owed the halt ``code``; HALTING, which waits for their acknowledgements until
        ``halt_retry_s`` after ``detected_s``."""
        self.guard.begin(code)
        self.halt_until_s = detected_s + self.settings.halt_retry_s
        if self.machine.state is not ArmState.HALTING:
            self.machine.fire(ArmEvent.HALT)

    def _stop_reference(self) -> None:
        """The reference stops where the arm is: an aborted path must not go on playing (in telemetry, the snapshot
        and progress) while the drives stand halted."""
        controller = self.controller
        if controller.follower is not None:
            q = controller.axes.positions()
            controller.follower.hold_at(q)
            controller.reference = State.at_rest(q)

    def _send_failed(self, exc: TransportError, detected_s: float, code: Command) -> None:
        """A send failed while reacting to a fault. A closed bus is lost (nothing more can be sent); an open one (a
        full transmit queue, a write refused once) stays HALTING, and every cycle sends the halt again (a hold or
        compliance whose first step failed: HALTING from now on)."""
        if self.controller.bus.closed:
            self.lose_bus(exc)
            return
        if not self.send_failing:  # once per run of failures, not every cycle
            logger.error("the halt could not be sent (%s): sent again every cycle", exc)
        self.send_failing = True
        self._enter_halting(code, detected_s)

    def lose_bus(self, exc: BaseException) -> None:
        """BUS_LOST: nothing more can be sent, the loop ends."""
        if self.machine.state is not ArmState.BUS_LOST:
            self.machine.fire(ArmEvent.BUS_GONE)
            logger.critical(
                "the bus is gone (%s): the halt could not be sent to the drives on it (an arm on several buses: it "
                "went to the others'); the control loop ends",
                exc,
            )

    def send_halt(self, deadline_s: float) -> None:
        """The halt to the drives not known to be halted (in the detection cycle: every drive, one batch)."""
        controller, guard = self.controller, self.guard
        replies = controller.bus.transact(guard.halt_requests(), deadline_s)
        self.send_failing = False
        guard.take(replies, controller.axes, self.watchdog.within, controller.clock.now())
        if not guard.unacknowledged and self.machine.state is ArmState.HALTING:
            self.machine.fire(ArmEvent.ACKNOWLEDGED)

    # ------------------------------------------------------------------------------------- the states' cycles

    def holding_cycle(self, state: ArmState, start_s: float, deadline_s: float) -> None:
        """HOLDING: the stop ramp, then the hold, streamed; a fault the hold is not for halts, and so does a hold that
        does not hold (:class:`~motion.safety.hold.HoldCheck`), whatever fault the hold is for or this cycle found
        besides."""
        controller = self.controller
        extra = self._reads()
        check = self.watchdog.check_setpoint  # the stop ramp must not pass a limit either
        try:
            replies = controller.step(start_s, deadline_s, extra=extra, check=check, apply_pending=False)
            evaluate_cycle(self.watchdog, self.brakes, replies, controller.clock.now())
        except MotionFault as fault:
            if not fault.kind.holdable:
                self.react(fault, -1, start_s, deadline_s)  # the drives' own halt
                return
            # the kind of fault the hold is for (a motor that stays hot while it cools): the hold goes on, unless...
        escalation = self.hold.escalation(controller.clock.now())
        if escalation is not None:
            self.react(escalation, -1, start_s, deadline_s)

    def complying_cycle(self, state: ArmState, start_s: float, deadline_s: float) -> None:
        """COMPLYING: gravity compensation with zero gains, streamed; any fault (communication, a drive, a limit)
        halts with the drives' own stop (the collision check is not held against the yielding arm).

        Raises:
            MotionError: no gravity model (COMPLYING is entered only with one): a fault like any other exception.
        """
        controller, gravity = self.controller, self.gravity
        if gravity is None:
            raise MotionError("complying without a gravity model")
        extra = self._reads()
        try:
            replies = controller.comply_step(start_s, deadline_s, gravity, extra=extra)
            evaluate_cycle(self.watchdog, self.brakes, replies, controller.clock.now(), complying=True)
        except MotionFault as fault:  # communication, a drive, a limit: the drives' own halt
            self.react(fault, -1, start_s, deadline_s)

    def pending_cycle(self, state: ArmState, start_s: float, deadline_s: float) -> None:
        """HALT_PENDING: the arm came here through an event its state did not accept, with no halt sent: the halt
        goes out to every axis now, for a fault of kind ``state``."""
        now = self.controller.clock.now()
        code = self.guard.code
        unsent = MotionFault(FaultKind.STATE, time_s=now, detail="halting without a halt sent")
        if self.log.fault is None:
            self.log.record(unsent)
        else:  # (the arm keeps the fault it is faulted for: a hold that a move raced into here)
            self.log.faults.append(unsent)
        logger.error("halting every axis: %s", unsent)
        sent = self.start_halt(now, deadline_s, code)
        self.log.halts.append(HaltRecord(unsent, -1, now, sent, Reaction(code.name)))
