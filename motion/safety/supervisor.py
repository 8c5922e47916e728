"""The guarded control cycle: a fault anywhere halts every axis in the cycle it is detected.

Reaction (:class:`~motion.config.schema.HaltPolicy`): ``stop`` sends 0x81 and ``off`` 0x80 to every axis at once
(in the same cycle, before any other command), re-sent to the drives that did not acknowledge until they do or
``halt_retry_s`` passes; ``hold`` replaces the reference with a jerk-limited stop and keeps streaming (position or
torque) to hold where it ends — only while communication is healthy: faults of the bus, of a drive, or of our own
code fall back to 0x81. A collision has a reaction of its own (``safety.collision_reaction``, default the halt
policy; it is not holdable, so ``hold`` means 0x81 for it): ``comply`` streams gravity compensation with zero gains
(torque mode), so that the arm yields to what it hit, until any other fault (communication, a drive, a limit, an
E-stop) halts every axis with 0x81. Then the arm is FAULTED: motion commands raise the fault until
:meth:`Supervisor.clear` (0x9B to every drive) finds every drive answering with clean flags and no cause left.

The states (:class:`~motion.safety.states.ArmState`) are the whole story, and each has its cycle
(:attr:`Supervisor.state_cycles`, keyed by the state as h11 keys its readers): READY and MOVING run the guarded
cycle; HOLDING streams the stop ramp, COMPLYING gravity compensation, HALT_PENDING sends the halt that is owed
(:mod:`motion.safety.reaction`); HALTING and HALTED keep the halted state every cycle (:mod:`motion.safety.halted`,
:mod:`motion.safety.halted_cycle`: the halt to every drive not known to be halted, a read to every drive; HALTING
until every drive acknowledged or ``halt_retry_s`` passed); BUS_LOST and CLOSED have none: the loop ends. Every change
of state goes through the transition table, and a pair the table does not know leads to the state's safe state
(HALT_PENDING, or HALTING once a halt went out). The rest lives beside: the reaction to a fault
(:mod:`motion.safety.reaction`), the hold's check (:mod:`motion.safety.hold`), the clear
(:mod:`motion.safety.clearing`), the end of the session (:mod:`motion.safety.ending`) and the records
(:mod:`motion.safety.records`).

No path leaves a motor moving under our last command: exceptions in the cycle are faults; E-stop requests
(:meth:`Supervisor.estop`, the CLI's Ctrl-C / SIGTERM) are faults; :meth:`Supervisor.close`, garbage collection and
process exit send 0x81 to every axis before the bus is released.
"""

from __future__ import annotations

import atexit
import logging
import threading
import weakref
from collections.abc import Callable, Sequence

from motion.control.commands import MotionTicket
from motion.control.controller import Controller, Feedforward
from motion.control.drivesetup import DriveSetup, link_timeout_ms
from motion.control.ratecheck import StatusRounds
from motion.errors import FaultKind, MotionError, MotionFault, TransportError
from motion.safety.brakes import BrakeWatch, evaluate_cycle
from motion.safety.clearing import Clearing
from motion.safety.collision import CollisionObserver
from motion.safety.context import SafetyContext
from motion.safety.ending import SETUP_WINDOW_S, SessionEnd, emergency_stop, end_window_s
from motion.safety.halted import HaltGuard
from motion.safety.halted_cycle import HaltedCycle
from motion.safety.reaction import FaultReaction
from motion.safety.records import FaultLog, HaltRecord, Reaction, Records, exception_origin
from motion.safety.rest import RestCheck
from motion.safety.states import HALT_STATES, TRANSITIONS, ArmEvent, ArmState, InvalidTransition, StateMachine
from motion.safety.watchdog import SafetySettings, Watchdog
from motion.transmission import FloatArray
from motion.transport import Request

__all__ = ["HaltRecord", "Reaction", "Records", "StateCycle", "Supervisor"]

logger = logging.getLogger("motion.safety")

#: Real time allowed on top of the collision check's arming cycles before motion is let go anyway (with a warning).
_ARMING_SLACK_S = 0.25
#: A state's cycle: called with the state it runs for, the cycle's start and its deadline (s); raises a fault.
StateCycle = Callable[[ArmState, float, float], None]


class Supervisor:
    """Runs a :class:`Controller`'s loop with every fault source watched and halts on any.

    Args:
        controller: the controller (after ``read_positions()``).
        settings: thresholds and halt policy.
        observer: the collision observer (:func:`motion.compose.collision_observer_for`), or None.
        gravity: gravity compensation ``(q_deg, qd_dps, qdd_dps2) -> tau_nm`` for the ``comply`` reaction
            (:func:`motion.compose.gravity_for`); without it a collision halts every axis with 0x81.
        drives: the drive-side settings of the session (:mod:`motion.control.drivesetup`: V3 drives' planning
            accelerations, communication-loss time and brakes), applied at :meth:`start` and restored before the bus
            closes; None: the family's defaults, without brakes.
    """

    def __init__(
        self,
        controller: Controller,
        settings: SafetySettings,
        *,
        observer: CollisionObserver | None = None,
        gravity: Feedforward | None = None,
        drives: DriveSetup | None = None,
    ) -> None:
        self.controller = controller
        self.ids = ids = tuple(s.motor_id for s in controller.specs)
        self.drives = drives = drives or DriveSetup(
            controller.bus, controller.families, list(ids), (), link_timeout_ms(controller.period_s, None)
        )
        self.settings = settings
        self.watchdog = watchdog = Watchdog(controller, settings, observer)
        if observer is not None:  # the collision signal and the threshold in force go out in every snapshot
            controller.publisher.signal = watchdog.collision_signal_nm
            controller.publisher.limit = watchdog.collision_limit_nm
        self.gravity = gravity
        self.machine = machine = StateMachine(ArmState.READY)
        #: The session's faults: the one the arm is faulted for, every fault and halt record.
        self.log = log = FaultLog(machine, controller.publisher, controller.clock)
        machine.on_change = log.publish
        self.faults, self.halts, self.lost_frames = log.faults, log.halts, log.lost_frames
        #: The braked joints whose drives cannot hold them, braked at once (:mod:`motion.safety.brakes`).
        self.brakes = brakes = BrakeWatch(
            [s.name for s in controller.specs],
            ids,
            drives.braked_ids,
            controller.families,
            max_missed_replies=settings.max_missed_replies,
            reply_timeout_s=settings.reply_timeout_s,
        )
        #: The halted state's bookkeeping (:mod:`motion.safety.halted`).
        self.guard = guard = HaltGuard(
            ids, drives.braked_ids, controller.bare_request, unheld=brakes.unheld, clock=controller.clock.now
        )
        reads = self._next_status_reads
        context = SafetyContext(controller, settings, machine, guard, watchdog, log, brakes)
        #: The reaction to a fault, and the cycles of HOLDING, COMPLYING and HALT_PENDING.
        self.reaction = reaction = FaultReaction(context, gravity=gravity, reads=reads)
        halted = HaltedCycle(context, reaction=reaction, gravity=gravity, reads=reads)
        window_s = end_window_s(controller, drives)
        #: Each joint's time at rest, from every cycle's readings: a clear needs every joint at rest.
        self.rest = rest = RestCheck(controller)
        #: clear(), carried out in the loop.
        self.clearing = Clearing(context, drives=drives, rest=rest, end_window_s=window_s)
        #: The end of the session, once the loop has ended.
        self.ending = SessionEnd(
            controller, machine=machine, guard=guard, watchdog=watchdog, drives=drives, window_s=window_s
        )
        #: Each state's cycle (None: the loop has ended).
        self.state_cycles: dict[ArmState, StateCycle | None] = {
            ArmState.READY: self._running_cycle,
            ArmState.MOVING: self._running_cycle,
            ArmState.HOLDING: reaction.holding_cycle,
            ArmState.COMPLYING: reaction.complying_cycle,
            ArmState.HALT_PENDING: reaction.pending_cycle,
            ArmState.HALTING: halted.run,
            ArmState.HALTED: halted.run,
            ArmState.BUS_LOST: None,
            ArmState.CLOSED: None,
        }
        # Requests from other threads, taken by the next cycle:
        self._estop_request: FaultKind | None = None
        self._estop_detail = "E-stop requested"
        self._clear_request = threading.Event()
        self._clear_done = threading.Event()
        self._clear_result: MotionFault | None = None
        #: The round-robin status reads (0x9A and the restart read), each bus's in turn on its own (each cycle's
        #: reads spread over the buses: one bus carrying them all would make its cycle the longer one; an RS485
        #: line carries one a cycle).
        self.status_rounds = StatusRounds.of(controller)
        #: How many of them each cycle carries, over every bus (CAN: every drive's flags at most FLAG_AGE_S old).
        self.status_reads_per_cycle = self.status_rounds.per_cycle
        self._finalizer = weakref.finalize(self, emergency_stop, controller, ids)
        atexit.register(self._finalizer)

    # ------------------------------------------------------------------------------------------------ API

    @property
    def state(self) -> ArmState:
        """The arm's state."""
        return self.machine.state

    @property
    def unacknowledged(self) -> set[int]:
        """Drives not known to be halted (their halt goes out every cycle while the arm is halting or halted)."""
        return self.guard.unacknowledged

    @property
    def unanswered(self) -> set[int]:
        """Drives that never answered the halt in force (since it went out, or since a reading of theirs showed them
        driving again): the ones it may not have reached. Of :attr:`unacknowledged`, a drive that answered it and then
        missed a reply is not one."""
        return self.guard.unanswered

    @property
    def fault(self) -> MotionFault | None:
        """The fault the arm is halted or holding for (None when it is not)."""
        return self.log.fault

    @fault.setter
    def fault(self, fault: MotionFault | None) -> None:
        self.log.fault = fault

    def start(self) -> None:
        """Start the guarded loop (closing the bus first halts every axis and ends the loop)."""
        clock = self.controller.clock
        # (the hook first: a setup that fails half-way is restored when the bus closes)
        self.controller.bus.close_hooks.append(self._before_bus_close)
        self.drives.apply(clock.now() + SETUP_WINDOW_S)
        self.watchdog.start(clock.now())
        self.controller.start(self.cycle)
        self._await_collision_check()

    def _await_collision_check(self) -> None:
        """Hold still until the collision check is armed (it is blind for its first observer steps after a
        (re)start: :attr:`~motion.safety.watchdog.Watchdog.collision_arming_s`), so that no motion starts
        unguarded: called at loop start and after a clear; a fault meanwhile ends the wait (motion is refused)."""
        watchdog, machine = self.watchdog, self.machine
        if not watchdog.collision_guarding:
            return
        # twice the time, two cycles, and a host's stall, before giving up
        timeout_s = 2 * (watchdog.collision_arming_s + self.controller.period_s) + _ARMING_SLACK_S
        if not self.controller.wait_for(lambda: watchdog.collision_armed or machine.state.faulted, timeout_s):
            logger.warning(
                "the collision check is not armed %.3f s after the loop (re)started: collisions go unseen until it is",
                timeout_s,
            )

    def _before_bus_close(self) -> None:
        if self.controller.loop.running:
            if not self.machine.state.faulted:
                self.estop(FaultKind.BUS_CLOSING)
            self.controller.shutdown()
        self._end_session()

    def _end_session(self) -> None:
        """Once the loop has ended: every axis halted, the braked joints locked at rest, the drives' settings
        restored (:class:`~motion.safety.ending.SessionEnd`); then process exit has nothing left to do."""
        if self.ending.run():
            self._finalizer.detach()

    def _refuse_if_faulted(self) -> None:
        if self.machine.state.faulted:
            fault = self.fault or MotionFault(FaultKind.STATE, detail="faulted without a recorded fault")
            raise MotionFault(
                fault.kind,
                joint=fault.joint,
                value=fault.value,
                threshold=fault.threshold,
                time_s=fault.time_s,
                detail="motion refused until clear()",
            )
        if self.machine.state is ArmState.CLOSED:
            raise MotionError("the arm is closed")

    def move_to(self, target_deg: Sequence[float] | FloatArray, speed_scale: float = 1.0) -> MotionTicket:
        """Queue a coordinated move (see :meth:`Controller.move_to`); returns its ticket (how it ended, once it has).

        Raises:
            MotionFault: the arm is faulted.
            PlanningError: an invalid target (nothing moves).
        """
        self._refuse_if_faulted()
        ticket = self.controller.move_to(target_deg, speed_scale)
        self._accept_motion()
        return ticket

    def follow(self, waypoints_deg: Sequence[Sequence[float]] | FloatArray, speed_scale: float = 1.0) -> MotionTicket:
        """Queue a waypoint path (see :meth:`Controller.follow`); returns its ticket."""
        self._refuse_if_faulted()
        ticket = self.controller.follow(waypoints_deg, speed_scale)
        self._accept_motion()
        return ticket

    def _accept_motion(self) -> None:
        """MOVING, or — when a fault came in between the check and the queueing — withdraw the queued command (it
        must not play after a later clear()) and raise the fault."""
        try:
            self.machine.fire(ArmEvent.MOVE)
        except InvalidTransition:
            self.controller.discard_pending()
            self._refuse_if_faulted()
            raise

    def stop_motion(self) -> None:
        """Queue a jerk-limited stop (not a fault)."""
        self._refuse_if_faulted()
        self.controller.stop_motion()

    def wait(self, timeout_s: float | None = None) -> bool:
        """Wait for the motion to end; returns False on timeout.

        Raises:
            MotionFault: a fault halted the arm (before or during the wait).
        """
        controller = self.controller
        machine = self.machine
        if not controller.wait_for(lambda: controller.idle or machine.state.faulted, timeout_s):
            return False
        if machine.state.faulted and self.fault is not None:
            raise self.fault
        rejected = self.controller.take_rejection()
        if rejected is not None:
            raise rejected
        return True

    def request_estop(self, reason: FaultKind = FaultKind.ESTOP, detail: str = "E-stop requested") -> None:
        """Ask the loop to halt every axis in its next cycle, and return at once (any thread: a view's STOP button
        never waits for the loop, nor runs a simulated one)."""
        self._estop_detail = detail
        self._estop_request = reason

    def estop(
        self, reason: FaultKind = FaultKind.ESTOP, timeout_s: float = 1.0, detail: str = "E-stop requested"
    ) -> bool:
        """Halt every axis now (in the next cycle); returns True once the halt went out."""
        self.request_estop(reason, detail)
        machine = self.machine
        return self.controller.wait_for(lambda: machine.state.faulted, timeout_s)

    def clear(self, timeout_s: float = 1.0) -> None:
        """Send 0x9B to every drive; succeed only if every drive answers with clean flags and no cause remains
        (carried out by the loop in a state that accepts CLEARED: :class:`~motion.safety.clearing.Clearing`).

        Raises:
            MotionFault: kind ``clear_failed`` naming what is still wrong (the arm stays FAULTED).
            MotionError: the arm is not faulted, or the loop did not answer in time.
        """
        state = self.machine.state
        if not state.faulted or state is ArmState.BUS_LOST:
            raise MotionError(f"clear() needs a faulted arm with its bus; it is {state.value}")
        self._estop_request = None
        self._clear_result = MotionFault(FaultKind.CLEAR_FAILED, detail="the clear did not complete")
        self._clear_done.clear()
        self._clear_request.set()
        if not self.controller.wait_for(self._clear_done.is_set, timeout_s):
            raise MotionError("the control loop did not process clear() in time")
        result = self._clear_outcome()
        if result is not None:
            raise result
        if self.machine.state is not ArmState.READY:
            raise MotionFault(FaultKind.CLEAR_FAILED, detail=f"the arm is {self.machine.state.value} after clear()")
        self._await_collision_check()

    def _clear_outcome(self) -> MotionFault | None:
        """What the loop made of the clear request (None: success)."""
        return self._clear_result

    def close(self, timeout_s: float = 2.0) -> None:
        """Halt every axis with 0x81, end the loop, restore the drives' settings (:mod:`motion.control.drivesetup`);
        the bus stays open for its owner to close."""
        if self.machine.state is ArmState.CLOSED:
            return
        if self.controller.loop.running and not self.machine.state.faulted:
            self.estop(FaultKind.CLOSE, timeout_s, "the arm closed: every axis halted at the run's end")
        self.controller.shutdown(timeout_s)
        self._end_session()  # (if the bus has closed, its close hook did it)
        self._finalizer()
        self.machine.fire(ArmEvent.CLOSE)

    # ------------------------------------------------------------------------------------------------ the cycle

    def cycle(self, k: int, start_s: float, deadline_s: float) -> bool:
        """The guarded cycle: run by the scheduler; never raises (every failure is a fault that halts). The other
        threads' requests first, then the state's own cycle (:attr:`state_cycles`)."""
        controller = self.controller
        state = self.machine.state
        state_cycle = self.state_cycles[state]
        if state_cycle is None:
            return False
        self.rest.take()  # (the previous cycle's readings, in every state: a clear may come in any faulted one)
        try:
            if not self._take_requests(state, deadline_s):
                state_cycle(state, start_s, deadline_s)
        except MotionFault as fault:
            self.reaction.react(fault, k, start_s, deadline_s)
        except TransportError as exc:
            lost = MotionFault(FaultKind.TRANSPORT, time_s=controller.clock.now(), detail=str(exc))
            self.reaction.react(lost, k, start_s, deadline_s)
        except Exception as exc:
            detail = f"{type(exc).__name__}: {exc}"
            origin = exception_origin(exc)
            # the same exception from the same place again while halted (its message may change every time: a
            # count, a time) is the same cause: recorded once, the halted cycle goes on
            if not (origin == self.log.exception_origin and self.machine.state in HALT_STATES):
                self.log.exception_origin = origin
                error = MotionFault(FaultKind.EXCEPTION, time_s=controller.clock.now(), detail=detail)
                self.reaction.react(error, k, start_s, deadline_s)
        return not controller.stopping and self.machine.state is not ArmState.BUS_LOST

    def _take_requests(self, state: ArmState, deadline_s: float) -> bool:
        """The other threads' requests, in ``state``: a clear where the state accepts CLEARED (True: it was this
        cycle's work; elsewhere it waits for such a state), else an E-stop.

        Raises:
            MotionFault: the E-stop asked for (while holding: it escalates to the drives' own halt; while halted:
                the halt is sent again).
        """
        if self._clear_request.is_set() and (state, ArmEvent.CLEARED) in TRANSITIONS:
            self._clear_request.clear()
            try:
                self._clear_result = self.clearing.run(state, deadline_s)
            finally:
                self._clear_done.set()
            return True
        if self._estop_request is not None:
            reason, self._estop_request = self._estop_request, None
            detail = f"E-stop requested while {state.value}" if state.faulted else self._estop_detail
            raise MotionFault(reason, time_s=self.controller.clock.now(), detail=detail)
        return False

    def _running_cycle(self, state: ArmState, start_s: float, deadline_s: float) -> None:
        """READY and MOVING: this cycle's status reads with the step, its set-point checked before it is sent, every
        monitor on the replies; MOVING ends (DONE) when the motion has."""
        controller = self.controller
        extra = self._next_status_reads()
        replies = controller.step(start_s, deadline_s, extra=extra, check=self.watchdog.check_setpoint)
        evaluate_cycle(self.watchdog, self.brakes, replies, controller.clock.now())
        if self.machine.state is ArmState.MOVING and controller.idle:
            self.machine.fire(ArmEvent.DONE)

    def _next_status_reads(self) -> tuple[Request, ...]:
        """0x9A or 0x92 for the next drives in turn, :attr:`status_reads_per_cycle` of them over the buses: every
        drive's flags and multi-turn angle are at most ``2 × its bus's drives / its bus's reads per cycle`` cycles
        old."""
        return self.status_rounds.next()
