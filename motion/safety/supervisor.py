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

The states (:class:`~motion.safety.states.ArmState`) are the whole story: READY and MOVING run the guarded cycle;
HOLDING streams the stop ramp; COMPLYING streams gravity compensation; HALTING and HALTED keep the halted state every
cycle (:mod:`motion.safety.halted`: the halt to every drive not known to be halted, a read to every drive; HALTING
until every drive acknowledged or ``halt_retry_s`` passed); BUS_LOST ends the loop. Every change of state goes through
the transition table, and a pair the table does not know leads to HALTING, whose cycle sends the halt if none went out.

No path leaves a motor moving under our last command: exceptions in the cycle are faults; E-stop requests
(:meth:`Supervisor.estop`, the CLI's Ctrl-C / SIGTERM) are faults; :meth:`Supervisor.close`, garbage collection and
process exit send 0x81 to every axis before the bus is released.
"""

from __future__ import annotations

import atexit
import logging
import math
import threading
import weakref
from collections.abc import Sequence
from typing import Final

import numpy as np

from motion.config.schema import HaltPolicy
from motion.control.controller import Controller, Feedforward
from motion.control.drivesetup import DriveSetup, link_timeout_ms
from motion.control.ratecheck import status_reads_per_cycle
from motion.errors import FaultKind, MotionError, MotionFault, TransportError
from motion.protocol import Command
from motion.safety.clearing import Clearing
from motion.safety.collision import CollisionObserver
from motion.safety.ending import SETUP_WINDOW_S, SessionEnd, emergency_stop, end_window_s
from motion.safety.halted import HaltGuard
from motion.safety.hold import HoldCheck
from motion.safety.records import REACTIONS, FaultLog, HaltRecord, Reaction, Records, exception_origin, same_cause
from motion.safety.states import ArmEvent, ArmState, InvalidTransition, StateMachine
from motion.safety.watchdog import SafetySettings, Watchdog
from motion.trajectory import State
from motion.transmission import FloatArray
from motion.transport import Reply, Request

__all__ = ["HaltRecord", "Reaction", "Records", "Supervisor"]

logger = logging.getLogger("motion.safety")

# Shortest window given to the halt frames' acknowledgements in the detection cycle, s.
_HALT_WINDOW_S = 0.002
#: Real time allowed on top of the collision check's arming cycles before motion is let go anyway (with a warning).
_ARMING_SLACK_S = 0.25
# Shortest window given to the halt frames' acknowledgements in the detection cycle, s.
HALT_WINDOW_S = 0.002
#: A halted cycle's replies before its exchange (one that fails before it has none: its frames go out all the same).
_NO_REPLIES: Final[list[Reply]] = []


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
        family = controller.family
        self.ids = ids = tuple(s.motor_id for s in controller.specs)
        self.drives = drives = drives or DriveSetup(
            controller.bus, family, list(ids), (), link_timeout_ms(controller.period_s, None)
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
        #: The halted state's bookkeeping (:mod:`motion.safety.halted`).
        self.guard = guard = HaltGuard(ids, drives.braked_ids, family.bare)
        #: Whether a hold holds.
        self.hold = HoldCheck(controller, watchdog)
        window_s = end_window_s(controller, drives)
        #: clear(), carried out in the loop.
        self.clearing = Clearing(
            controller,
            settings=settings,
            machine=machine,
            guard=guard,
            watchdog=watchdog,
            log=log,
            drives=drives,
            end_window_s=window_s,
        )
        #: The end of the session, once the loop has ended.
        self.ending = SessionEnd(
            controller, machine=machine, guard=guard, watchdog=watchdog, drives=drives, window_s=window_s
        )
        self._send_failing = False
        self._halt_until_s: float | None = None  # until when the halt is re-sent; None: no halt went out yet
        # Requests from other threads, taken by the next cycle:
        self._estop_request: FaultKind | None = None
        self._estop_detail = "E-stop requested"
        self._clear_request = threading.Event()
        self._clear_done = threading.Event()
        self._clear_result: MotionFault | None = None
        # 0x9A (flags, voltage, temperature) and 0x92 (the multi-turn angle: a drive that restarted) in turn
        # (the V3 family: 0x9A and 0xB1, its runtime, which starts again when the drive restarted)
        reads_of = (Command.READ_STATUS_1, family.restart_read)
        self._status_reads = [Request(i, family.bare(command)) for i in ids for command in reads_of]
        self._round_robin = 0  # a counter of its own: the cycle index k jumps over skipped cycles
        #: How many of them each cycle carries (CAN: every drive's flags at most FLAG_AGE_S old).
        self.status_reads_per_cycle = status_reads_per_cycle(len(ids), controller.period_s, controller.options.protocol)
        self._finalizer = weakref.finalize(self, emergency_stop, controller, ids, family.bare)
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

    def move_to(self, target_deg: Sequence[float] | FloatArray, speed_scale: float = 1.0) -> None:
        """Queue a coordinated move (see :meth:`Controller.move_to`).

        Raises:
            MotionFault: the arm is faulted.
            PlanningError: an invalid target (nothing moves).
        """
        self._refuse_if_faulted()
        self.controller.move_to(target_deg, speed_scale)
        self._accept_motion()

    def follow(self, waypoints_deg: Sequence[Sequence[float]] | FloatArray, speed_scale: float = 1.0) -> None:
        """Queue a waypoint path (see :meth:`Controller.follow`)."""
        self._refuse_if_faulted()
        self.controller.follow(waypoints_deg, speed_scale)
        self._accept_motion()

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

    def estop(self, reason: FaultKind = FaultKind.ESTOP, timeout_s: float = 1.0) -> bool:
        """Halt every axis now (in the next cycle); returns True once the halt went out."""
        self.request_estop(reason)
        machine = self.machine
        return self.controller.wait_for(lambda: machine.state.faulted, timeout_s)

    def clear(self, timeout_s: float = 1.0) -> None:
        """Send 0x9B to every drive; succeed only if every drive answers with clean flags and no cause remains.

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
            self.estop(FaultKind.CLOSE, timeout_s)
        self.controller.shutdown(timeout_s)
        self._end_session()  # (if the bus has closed, its close hook did it)
        self._finalizer()
        self.machine.fire(ArmEvent.CLOSE)

    # ------------------------------------------------------------------------------------------------ the cycle

    def cycle(self, k: int, start_s: float, deadline_s: float) -> bool:
        """The guarded cycle: run by the scheduler; never raises (every failure is a fault that halts)."""
        controller = self.controller
        state = self.machine.state
        if state is ArmState.BUS_LOST or state is ArmState.CLOSED:
            return False
        try:
            if state.faulted:
                self._faulted_cycle(state, start_s, deadline_s)
            else:
                if self._estop_request is not None:
                    reason, self._estop_request = self._estop_request, None
                    raise MotionFault(reason, time_s=controller.clock.now(), detail=self._estop_detail)
                extra = self._next_status_reads()
                replies = controller.step(start_s, deadline_s, extra=extra, check=self.watchdog.check_setpoint)
                self.watchdog.evaluate(replies, controller.clock.now())
                if self.machine.state is ArmState.MOVING and controller.idle:
                    self.machine.fire(ArmEvent.DONE)
        except MotionFault as fault:
            self._halt(fault, k, start_s, deadline_s)
        except TransportError as exc:
            self._halt(
                MotionFault(FaultKind.TRANSPORT, time_s=controller.clock.now(), detail=str(exc)), k, start_s, deadline_s
            )
        except Exception as exc:
            detail = f"{type(exc).__name__}: {exc}"
            origin = exception_origin(exc)
            # the same exception from the same place again while halted (its message may change every time: a
            # count, a time) is the same cause: recorded once, the halted cycle goes on
            if not (origin == self.log.exception_origin and self.machine.state in (ArmState.HALTING, ArmState.HALTED)):
                self.log.exception_origin = origin
                error = MotionFault(FaultKind.EXCEPTION, time_s=controller.clock.now(), detail=detail)
                self._halt(error, k, start_s, deadline_s)
        return not controller.stopping and self.machine.state is not ArmState.BUS_LOST

    def _next_status_reads(self) -> tuple[Request, ...]:
        """0x9A or 0x92 for the next drives in turn, :attr:`status_reads_per_cycle` of them: every drive's flags and
        multi-turn angle are at most ``2 n_axes / status_reads_per_cycle`` cycles old."""
        reads, count = self._status_reads, len(self._status_reads)
        if self.status_reads_per_cycle == 1:
            self._round_robin = (self._round_robin + 1) % count
            return (reads[self._round_robin],)
        first = self._round_robin + 1
        self._round_robin = (self._round_robin + self.status_reads_per_cycle) % count
        return tuple(reads[(first + j) % count] for j in range(self.status_reads_per_cycle))

    def _halt(self, fault: MotionFault, k: int, start_s: float, deadline_s: float) -> None:
        """React to ``fault``: the stop ramp where the policy, the kind and the state allow it, else the halt."""
        controller = self.controller
        detected = controller.clock.now()
        controller.discard_pending()  # a move queued during this cycle must not replace the halt
        state = self.machine.state
        repeated = state.faulted and self.log.fault is not None and same_cause(fault, self.log.fault)
        if repeated and state in (ArmState.HALTING, ArmState.HALTED):
            # the same cause again in every cycle (a hook, a tap, a port that keeps failing), recorded once: the
            # halted cycle goes on sending the halt to every drive not known to be halted (its bookkeeping was done
            # before the hooks ran); a send that failed leaves every drive owed its halt again
            if fault.kind is FaultKind.TRANSPORT:
                if controller.bus.closed:
                    self._lose_bus(TransportError(fault.detail))
                else:
                    self.guard.begin(self.guard.code)
            return
        self.log.record(fault)
        policy = self._policy(fault)
        code = Command.MOTOR_OFF if policy is HaltPolicy.OFF else Command.MOTOR_STOP
        running = state in (ArmState.READY, ArmState.MOVING)
        holdable = running and policy is HaltPolicy.HOLD and fault.kind.holdable
        comply = (
            policy is HaltPolicy.COMPLY
            and fault.kind is FaultKind.COLLISION
            and (running or state is ArmState.HOLDING)
            and self.gravity is not None
        )
        action = (
            "comply"
            if comply
            else "stop ramp and hold"
            if holdable
            else ("0x80 off" if policy is HaltPolicy.OFF else "0x81 stop")
        )
        level = logging.INFO if fault.kind is FaultKind.CLOSE else logging.ERROR
        logger.log(level, "halting every axis (%s): %s", action, fault)
        sent = detected
        try:
            if comply:
                try:
                    sent = self._start_comply(start_s, deadline_s)
                except TransportError:
                    raise
                except Exception as exc:  # compliance that cannot start must not leave the last command in force
                    logger.error(
                        "compliance could not start (%s: %s): halting every axis with 0x81 instead",
                        type(exc).__name__,
                        exc,
                    )
                    comply = False
            if holdable:
                try:
                    sent = self._start_hold(fault, start_s, deadline_s)
                except TransportError:
                    raise
                except Exception as exc:  # a hold that cannot start must not leave the last command in force
                    logger.error(
                        "the hold could not start (%s: %s): halting every axis with 0x81 instead",
                        type(exc).__name__,
                        exc,
                    )
                    holdable = False
            if not holdable and not comply:
                sent = self._start_halt(detected, deadline_s, code)
        except TransportError as exc:
            self._send_failed(exc, detected, deadline_s, code)
        except Exception as exc:  # the state is HALTING: the next cycle sends the halt again
            logger.error("halt could not be sent: %s: %s", type(exc).__name__, exc)
        reaction = REACTIONS.get(self.machine.state) or Reaction(self.guard.code.name)
        self.halts.append(HaltRecord(fault, k, detected, sent, reaction))

    def _policy(self, fault: MotionFault) -> HaltPolicy:
        """The reaction configured for ``fault``: the collision reaction for a collision, else the halt policy."""
        settings = self.settings
        if self.machine.state is ArmState.COMPLYING:  # compliance ends in the drives' own stop, whatever the policy
            return HaltPolicy.STOP
        if fault.kind is FaultKind.COLLISION and settings.collision_reaction is not None:
            return settings.collision_reaction
        return settings.halt_policy

    def _start_comply(self, start_s: float, deadline_s: float) -> float:
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
        controller.comply_step(sent, max(deadline_s, sent + HALT_WINDOW_S), gravity)
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
            measured = State(axes.positions(), axes.qd_dps.copy(), np.zeros(len(self.ids)))
            follower.stop_from(start_s, measured)
            controller.reference = measured
            self.watchdog.restart_following()  # the expectation starts again from there too
        else:
            follower.stop(start_s)
        sent = controller.clock.now()
        controller.step(sent, max(deadline_s, sent + HALT_WINDOW_S), apply_pending=False)
        return sent

    def _start_halt(self, detected_s: float, deadline_s: float, code: Command) -> float:
        """Enter HALTING: 0x81 (0x80 under ``halt_policy: off``) to every axis now, in one batch; returns when it was
        sent."""
        self.guard.begin(code)
        self._halt_until_s = detected_s + self.settings.halt_retry_s
        if self.machine.state is not ArmState.HALTING:
            self.machine.fire(ArmEvent.HALT)
        sent = self.controller.clock.now()
        try:
            self._send_halt(max(deadline_s, sent + HALT_WINDOW_S))
        finally:
            self._stop_reference()
        return sent

    def _stop_reference(self) -> None:
        """The reference stops where the arm is: an aborted path must not go on playing (in telemetry, the snapshot
        and progress) while the drives stand halted."""
        controller = self.controller
        if controller.follower is not None:
            q = controller.axes.positions()
            controller.follower.hold_at(q)
            controller.reference = State.at_rest(q)

    def _send_failed(self, exc: TransportError, detected_s: float, deadline_s: float, code: Command) -> None:
        """A send failed while reacting to a fault. A closed bus is lost (nothing more can be sent); an open one (a
        full transmit queue, a write refused once) stays HALTING, and every cycle sends the halt again."""
        if self.controller.bus.closed:
            self._lose_bus(exc)
            return
        if not self._send_failing:  # once per run of failures, not every cycle
            logger.error("the halt could not be sent (%s): sent again every cycle", exc)
        self._send_failing = True
        if self.machine.state is not ArmState.HALTING:  # a hold or compliance whose first step failed
            self.machine.fire(ArmEvent.HALT)
        self.guard.begin(code)
        self._halt_until_s = detected_s + self.settings.halt_retry_s

    def _lose_bus(self, exc: BaseException) -> None:
        if self.machine.state is not ArmState.BUS_LOST:
            self.machine.fire(ArmEvent.BUS_GONE)
            logger.critical("the bus is gone (%s): the halt could not be sent; the control loop ends", exc)

    def _send_halt(self, deadline_s: float) -> None:
        """The halt to the drives not known to be halted (in the detection cycle: every drive, one batch)."""
        replies = self.controller.bus.transact(self.guard.halt_requests(), deadline_s)
        self._send_failing = False
        self.guard.take(replies, self.controller.axes, self.watchdog.within, self.controller.clock.now())
        if not self.guard.unacknowledged and self.machine.state is ArmState.HALTING:
            self.machine.fire(ArmEvent.ACKNOWLEDGED)

    def _faulted_cycle(self, state: ArmState, start_s: float, deadline_s: float) -> None:
        controller = self.controller
        now = controller.clock.now()
        if self._clear_request.is_set() and state in (ArmState.HOLDING, ArmState.COMPLYING, ArmState.HALTED):
            self._clear_request.clear()
            try:
                self._clear_result = self.clearing.run(state, deadline_s)
                if self._clear_result is None:  # READY: no halt went out since
                    self._halt_until_s = None
            finally:
                self._clear_done.set()
            return
        if self._estop_request is not None:  # while holding: escalates to the drives' own halt; else sent again
            reason, self._estop_request = self._estop_request, None
            raise MotionFault(reason, time_s=now, detail=f"E-stop requested while {state.value}")
        if state is ArmState.COMPLYING and self.gravity is not None:
            extra = self._next_status_reads()
            try:
                replies = controller.comply_step(start_s, deadline_s, self.gravity, extra=extra)
                self.watchdog.evaluate(replies, controller.clock.now(), complying=True)
            except MotionFault as fault:  # communication, a drive, a limit: the drives' own halt
                self._halt(fault, -1, start_s, deadline_s)
            return
        if state is ArmState.HOLDING:
            self._holding_cycle(start_s, deadline_s)
            return
        if state is ArmState.HALTING and self._halt_until_s is None:
            # reached through the safe state of the table: no halt went out yet
            unsent = MotionFault(FaultKind.STATE, time_s=now, detail="halting without a halt sent")
            self.fault = unsent
            self.faults.append(unsent)
            logger.error("halting every axis: %s", unsent)
            sent = self._start_halt(now, deadline_s, self.guard.code)
            self.halts.append(HaltRecord(unsent, -1, now, sent, Reaction(self.guard.code.name)))
            return
        self._halted_cycle(state, start_s, deadline_s)

    def _holding_cycle(self, start_s: float, deadline_s: float) -> None:
        """The stop ramp, then the hold, streamed; a fault the hold is not for halts, and so does a hold that does not
        hold (:class:`~motion.safety.hold.HoldCheck`), whatever fault the hold is for or this cycle found besides."""
        controller = self.controller
        extra = self._next_status_reads()
        check = self.watchdog.check_setpoint  # the stop ramp must not pass a limit either
        try:
            replies = controller.step(start_s, deadline_s, extra=extra, check=check, apply_pending=False)
            self.watchdog.evaluate(replies, controller.clock.now())
        except MotionFault as fault:
            if not fault.kind.holdable:
                self._halt(fault, -1, start_s, deadline_s)  # the drives' own halt
                return
            # the kind of fault the hold is for (a motor that stays hot while it cools): the hold goes on, unless...
        escalation = self.hold.escalation(controller.clock.now())
        if escalation is not None:
            self._halt(escalation, -1, start_s, deadline_s)

    def _halted_cycle(self, state: ArmState, start_s: float, deadline_s: float) -> None:
        """HALTING and HALTED: every drive gets a frame (its halt while it is not known to be halted, else a state
        read; see :mod:`motion.safety.halted`), joints that leave their limits and drives that restarted are faults
        of their own, and braked joints lock once at rest."""
        controller = self.controller
        requests = self.guard.requests()
        requests.extend(self._next_status_reads())
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
            self._take_halted(state, replies)
            raise
        self._take_halted(state, replies)

    def _take_halted(self, state: ArmState, replies: list[Reply]) -> None:
        """The halted cycle's replies: acknowledgements, drives driving or swinging, limits, restarts, and the end of
        HALTING."""
        controller, guard = self.controller, self.guard
        self._send_failing = False
        now = controller.clock.now()
        axes = controller.axes
        driving, outside, swinging = guard.take(replies, axes, self.watchdog.within, now)
        names = self.watchdog.names
        for i in driving:
            logger.warning("%s reads as driving while halted: its halt is sent again", names[i])
        for i in outside:
            detail = "beyond its limits while halted (its halt is sent again)"
            self.log.record_halted(
                MotionFault(
                    FaultKind.POSITION_LIMIT, joint=names[i], value=float(axes.q_deg[i]), time_s=now, detail=detail
                ),
                guard.code,
            )
        for i in swinging:
            self.log.record_halted(self._swinging(i, now), guard.code)
        for fault in self.watchdog.restarts(replies, now):
            if fault.joint not in self.lost_frames:
                self.lost_frames.add(str(fault.joint))
                self.log.record_halted(fault, guard.code)
        if state is ArmState.HALTING and self._halt_until_s is not None:
            if guard.unacknowledged and now < self._halt_until_s:
                return
            if guard.unacknowledged:
                logger.error(
                    "drives %s did not acknowledge the halt within %g s: it is sent to them every cycle while the "
                    "session is open",
                    sorted(guard.unacknowledged),
                    self.settings.halt_retry_s,
                )
            self.machine.fire(ArmEvent.ACKNOWLEDGED)

    def _swinging(self, i: int, now_s: float) -> MotionFault:
        """Joint ``i`` swings back and forth, or runs on, although halted (its drive's own 0x81 hold does not hold it):
        released with 0x80 where gravity cannot move it (its gravity torque here within its Coulomb friction), else kept
        at 0x81."""
        controller = self.controller
        gravity = self.gravity
        friction = self.settings.coulomb_friction_nm
        load_nm = math.inf
        if gravity is not None and friction:
            zero = np.zeros(len(self.ids))
            load_nm = abs(float(gravity(controller.axes.q_deg, zero, zero)[i]))
        braked = self.ids[i] in self.drives.braked_ids  # its brake locks once at rest: never released
        released = not braked and load_nm <= (friction[i] if friction else -math.inf)
        if released:
            self.guard.release(i)
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
