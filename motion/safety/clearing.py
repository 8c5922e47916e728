"""``clear()`` carried out in the control loop: the way out of a faulted state, only with every cause gone.

0x9B to every drive where the family has it (its reply is the status; else the drives clear level-2 errors
themselves and the status is read) and a state read; the clear succeeds only if every drive answers with clean flags,
its supply and temperature within their limits, no joint lost its frame (a drive that restarted), every joint is
inside its limits and every joint is at rest (:mod:`motion.safety.rest`: a joint still coasting from its halt would
be pulled back by the loop from wherever it has got to). Then the brakes locked since the halt are released (all of
them, or none: a release that fails halfway locks them again), the reference holds where the arm is, the halt's
bookkeeping starts afresh and the state fires CLEARED (READY).
"""

from __future__ import annotations

import logging

from motion.control.drivesetup import DriveSetup
from motion.control.family import STATE_TYPES, STATUS_TYPES
from motion.errors import FaultKind, MotionFault, TransportError
from motion.protocol import Command
from motion.protocol.v3.messages import CommandV3
from motion.safety.context import SafetyContext, SafetyPart
from motion.safety.rest import RestCheck
from motion.safety.states import ArmEvent, ArmState
from motion.trajectory import State
from motion.transport import Reply

logger = logging.getLogger("motion.safety")

#: The shortest wait for the clear's replies, s (a cycle whose deadline has passed still gives them this long).
_CLEAR_WINDOW_S = 0.005


class Clearing(SafetyPart):
    """Carries out a clear request in a faulted state that accepts CLEARED (control thread only).

    Args:
        context: the supervisor's pieces (its settings: the limits a drive must be within; its guard: the brakes
            locked since the halt; its watchdog, started afresh; its log: the fault cleared, the joints whose frame is
            lost).
        drives: the drives' settings of the session (the brakes' release).
        rest: each joint's time at rest (fed every cycle by the supervisor; the clear's own readings are its latest).
        end_window_s: the longest wait for the replies of the brakes' lock after a failed release, s.
    """

    def __init__(
        self,
        context: SafetyContext,
        *,
        drives: DriveSetup,
        rest: RestCheck,
        end_window_s: float,
    ) -> None:
        super().__init__(context)
        self.drives = drives
        self.rest = rest
        self._end_window_s = end_window_s
        controller = context.controller
        ids, ask = context.guard.ids, controller.bare_request
        self._state_reads = [ask(i, Command.READ_STATUS_2) for i in ids]
        self._clear_requests = [
            ask(i, Command.CLEAR_ERRORS if controller.family_of(i).clears_errors else Command.READ_STATUS_1)
            for i in ids
        ]

    def run(self, state: ArmState, deadline_s: float) -> MotionFault | None:
        """Clear the arm faulted in ``state``; returns None when it is READY, else the ``clear_failed`` fault naming
        what is still wrong (the arm stays faulted).

        Raises:
            TransportError: an exchange failed (the brakes were locked again, as far as the drives answered).
        """
        controller = self.controller
        follower = controller.follower
        if state is ArmState.HOLDING and follower is not None and follower.moving:
            detail = "the stop ramp is still running: clear() once ended"
            return MotionFault(FaultKind.CLEAR_FAILED, time_s=controller.clock.now(), detail=detail)
        requests = self._clear_requests + self._state_reads
        window = max(deadline_s, controller.clock.now() + _CLEAR_WINDOW_S)
        replies: list[Reply] = controller.bus.transact(requests, window)
        controller.absorb(replies)
        self.rest.take()
        problems = self._problems(replies)
        moving = self.rest.moving(problems)  # (naming the joint and its speed, and whatever else is wrong)
        if moving is not None:
            return moving
        if problems:
            return MotionFault(FaultKind.CLEAR_FAILED, time_s=controller.clock.now(), detail="; ".join(problems))
        q = controller.axes.positions()
        if follower is None:
            return MotionFault(FaultKind.CLEAR_FAILED, time_s=controller.clock.now(), detail="no follower")
        if self.guard.locked:
            self._release_brakes(max(deadline_s, controller.clock.now() + _CLEAR_WINDOW_S))
        controller.discard_pending()  # nothing queued while faulted may start after the clear
        follower.hold_at(q)
        controller.reference = State.at_rest(q)
        self.log.fault = None
        self.guard.reset()
        self.brakes.reset()
        self.log.exception_origin = None
        self.watchdog.start(controller.clock.now())
        self.machine.fire(ArmEvent.CLEARED)
        return None

    def _release_brakes(self, deadline_s: float) -> None:
        """0x77 to the braked joints, locked since the halt with their drives off. A release that fails halfway
        (a drive did not answer) locks every brake again at once: a released brake on a drive that is off lets its
        joint fall (0x81 leaves an off drive off), and the joints stood at rest until now.

        Raises:
            TransportError: the release failed (the brakes were locked again, as far as the drives answered).
        """
        guard = self.guard
        try:
            self.drives.release_brakes(deadline_s)
        except TransportError:
            controller = self.controller
            guard.locked.clear()  # each counts as locked again once its drive acknowledges the lock
            try:
                replies = controller.bus.transact(
                    [controller.bare_request(i, CommandV3.LOCK_BRAKE) for i in guard.braked_ids],
                    controller.clock.now() + self._end_window_s,
                )
                guard.take(replies, controller.axes, self.watchdog.within, controller.clock.now())
            except TransportError as exc:
                logger.error("the brakes could not be locked again after a failed release: %s", exc)
            raise

    def _problems(self, replies: list[Reply]) -> list[str]:
        """What keeps the arm from being cleared, in words (none: it may be)."""
        specs = self.controller.specs
        names = {s.motor_id: s.name for s in specs}
        settings = self.settings
        ids = self.guard.ids
        limits = dict(zip(ids, settings.temperature_limit_c, strict=True))
        problems = []
        status = {r.motor_id: r.message for r in replies if isinstance(r.message, STATUS_TYPES)}
        state = {r.motor_id: r.message for r in replies if isinstance(r.message, STATE_TYPES)}
        for motor_id in ids:
            s, m = status.get(motor_id), state.get(motor_id)
            name = names[motor_id]
            if s is None or m is None:
                problems.append(f"{name}: no reply")
                continue
            if s.errors:
                problems.append(f"{name}: error flags {s.errors!r} still set")
            if s.voltage_v < settings.min_voltage_v:
                problems.append(f"{name}: supply {s.voltage_v:.1f} V below {settings.min_voltage_v:g} V")
            if max(s.temperature_c, m.temperature_c) >= limits[motor_id]:
                problems.append(f"{name}: temperature {s.temperature_c} °C at or above {limits[motor_id]:g} °C")
        for name in sorted(self.log.lost_frames):
            problems.append(
                f"{name}: its drive restarted (power) and the joint's position is no longer known (its turn count is "
                "lost): close the arm and connect again, where its power-on window or homing (Arm(..., home=[...]), "
                "rmd-motion home) establishes it"
            )
        q = self.controller.axes.q_deg
        lower, upper = self.watchdog.lower, self.watchdog.upper
        for i, spec in enumerate(specs):
            if not lower[i] <= q[i] <= upper[i]:
                problems.append(
                    f"{spec.name}: at {q[i]:.2f} deg, outside its limits {lower[i]:g}..{upper[i]:g} deg "
                    "(move it back by hand with the drives off: rmd-motion off)"
                )
        return problems
