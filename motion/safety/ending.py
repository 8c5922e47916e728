"""The end of a session: after the loop, every axis halted, the braked joints locked at rest, every joint awaited at
rest (where its turn record is written: :func:`motion.keep.resting_angles`), the settings restored.

No path leaves a motor moving under our last command: :meth:`SessionEnd.run` runs from ``Supervisor.close`` and from
the bus's close hook; :func:`emergency_stop` from garbage collection and process exit, where nobody is left to raise
to.
"""

from __future__ import annotations

import logging

from motion.control.controller import Controller
from motion.control.drivesetup import DriveSetup
from motion.protocol import Command
from motion.safety.halted import HaltGuard
from motion.safety.states import ArmEvent, ArmState, StateMachine
from motion.safety.watchdog import Watchdog
from motion.transport import Request

logger = logging.getLogger("motion.safety")

# How long the drives' settings at start and end may take (a few exchanges), s.
SETUP_WINDOW_S = 0.2
#: The longest an exchange after the loop waits for its replies, s (see :func:`end_window_s`).
END_EXCHANGE_S = 0.02
#: How long a close waits for the braked joints to come to rest before it locks their brakes, and for every joint
#: to come to rest (a drive's own stop from full speed takes a few tenths of a second), s.
BRAKE_SETTLE_S = 1.0
#: The states whose halt has gone out: the end sends it again where it is owed (any other, HALT_PENDING too, whose halt
#: has not gone out yet: the drives' own stop now).
_HALT_SENT = (ArmState.HALTING, ArmState.HALTED)


def end_window_s(controller: Controller, drives: DriveSetup) -> float:
    """How long an exchange after the loop (the close's halt and brake reads, a failed release's lock) waits for its
    replies, s: at most a control period's share for them, and half a drive's link timeout: a silent drive's wait
    never starves the healthy ones into their link-loss stop before the close turns the protection off."""
    window = min(END_EXCHANGE_S, controller.period_s * controller.options.reply_budget)
    if drives.link_timeout_ms:
        window = min(window, drives.link_timeout_ms / 2000.0)
    return window


class SessionEnd:
    """Once the loop has ended: the halt to every axis, the brakes of the joints at rest locked, every joint awaited at
    rest, and only then the drives' settings restored.

    Args:
        controller: the controller (its loop has ended).
        machine: the arm's state machine.
        guard: the halted state's bookkeeping.
        watchdog: the watchdog (limits; the joints' names).
        drives: the drives' settings of the session.
        window_s: the longest an exchange waits for its replies, s (:func:`end_window_s`).
    """

    def __init__(
        self,
        controller: Controller,
        *,
        machine: StateMachine,
        guard: HaltGuard,
        watchdog: Watchdog,
        drives: DriveSetup,
        window_s: float,
    ) -> None:
        self.controller = controller
        self.machine = machine
        self.guard = guard
        self.watchdog = watchdog
        self.drives = drives
        self._window_s = window_s
        #: The joints the end saw at rest after its halt, by name, and their angles then, degrees (a joint still
        #: coasting, or whose drive was not heard, is not among them): where their turn records are written.
        self.rest_deg: dict[str, float] = {}

    def run(self) -> bool:
        """The halt to every axis in one batch (the drives not known to be halted last, so that a silent one's
        timeouts delay nobody's halt), re-sent to the late until :data:`SETUP_WINDOW_S`; the brakes locked at rest;
        every joint awaited at rest until :data:`BRAKE_SETTLE_S` (:attr:`rest_deg`); the settings restored. Every
        exchange carries the 0x92 reads of the axes whose turns are not sure (a drive heard again after a silence:
        :meth:`~motion.control.controller.Controller.turn_reads`). Returns False when nothing could be sent (the bus
        closed or lost, the arm closed)."""
        controller, guard, machine = self.controller, self.guard, self.machine
        bus, clock = controller.bus, controller.clock
        state = machine.state
        if bus.closed or state in (ArmState.BUS_LOST, ArmState.CLOSED):
            return False
        if state not in _HALT_SENT:
            guard.begin(Command.MOTOR_STOP)  # the drives' own stop now, kept as in a halted cycle (brakes included)
        owed = guard.unacknowledged
        order = sorted(guard.ids, key=lambda i: (i in owed, i))
        until = clock.now() + SETUP_WINDOW_S
        ask = controller.bare_request
        try:
            batch = guard.locks_due()  # (a braked joint its drive cannot hold: its brake first, as in the loop)
            batch += [ask(i, guard.codes[i]) for i in order]
            self._exchange(batch, clock.now() + self._window_s)
            # Late acknowledgements (a loaded host, a slow drive): halted cycles, each a short exchange that reads
            # every drive (none starves into its link-loss stop), until every drive acknowledged or ``until``.
            while guard.unacknowledged and clock.now() < until:
                self._exchange(guard.requests(), min(until, clock.now() + self._window_s))
        except Exception as exc:  # the session ends anyway: leave a trace
            logger.error("the halt at the end of the session failed: %s: %s", type(exc).__name__, exc)
        if machine.state is ArmState.HALTING and not guard.unacknowledged:
            machine.fire(ArmEvent.ACKNOWLEDGED)
        settle_until = clock.now() + BRAKE_SETTLE_S
        if self.drives.braked_ids and not self.drives.brakes_locked:
            self._lock_brakes_at_rest(settle_until)
        self._await_rest(settle_until)
        self.drives.restore(clock.now() + SETUP_WINDOW_S, lock=())  # (the brakes: above, only where at rest)
        return True

    def _exchange(self, requests: list[Request], deadline_s: float) -> None:
        """One exchange after the loop, with the 0x92 reads of the axes whose turns are not sure, taken in by the
        axes and the halted state's bookkeeping."""
        controller, clock = self.controller, self.controller.clock
        requests += controller.turn_reads(clock.now(), deadline_s - clock.now())
        replies = controller.bus.transact(requests, deadline_s)
        controller.absorb(replies)
        self.guard.take(replies, controller.axes, self.watchdog.within, clock.now())

    def _await_rest(self, deadline_s: float) -> None:
        """Halted cycles, one a control period, until every joint has read at rest since its halt
        (:meth:`HaltGuard.at_rest`; a drive unheard meanwhile may answer again), or until ``deadline_s``;
        :attr:`rest_deg` then holds those at rest. A turn record written while a joint coasts would leave the next
        session a reading the joint does not stop at."""
        controller, guard = self.controller, self.guard
        clock, n = controller.clock, len(guard.ids)
        try:
            while clock.now() < deadline_s and not all(guard.at_rest(i) for i in range(n)):
                start_s = clock.now()
                self._exchange(guard.requests(), min(deadline_s, start_s + self._window_s))
                clock.sleep_until(min(deadline_s, start_s + controller.period_s))
        except Exception as exc:
            logger.error("the joints could not be read at rest at the end: %s: %s", type(exc).__name__, exc)
        q = controller.axes.q_deg
        self.rest_deg = {name: float(q[i]) for i, name in enumerate(self.watchdog.names) if guard.at_rest(i)}

    def _lock_brakes_at_rest(self, deadline_s: float) -> None:
        """After the final halt: halted cycles (:meth:`HaltGuard.requests`: every drive read, none starves into its
        link-loss stop, the halt re-sent where owed) until every brake has locked by the guard's rule (at rest for
        :data:`~motion.safety.halted.BRAKE_REST_S` with the whole arm calm, one at a time), or until ``deadline_s``
        (a brake is no stopping device: a joint still moving is left to its drive's hold, and logged)."""
        controller, guard = self.controller, self.guard
        clock = controller.clock
        try:
            while not guard.all_locked() and clock.now() < deadline_s:
                self._exchange(guard.requests(), min(deadline_s, clock.now() + self._window_s))
        except Exception as exc:
            logger.error("the braked joints could not be read at the end: %s: %s", type(exc).__name__, exc)
        pending = [i for i in guard.braked_ids if i not in guard.locked]
        if pending:
            names = ", ".join(self.watchdog.names[self.watchdog.index[i]] for i in pending)
            logger.error("brakes not locked (%s): not seen at rest after the halt; their drives hold them", names)


def emergency_stop(controller: Controller, ids: tuple[int, ...]) -> None:
    """Garbage collection / process exit: end the loop, then 0x81 to every axis (best effort, never raises)."""
    try:
        controller.shutdown(1.0)
        if not controller.bus.closed:
            requests = [controller.bare_request(i, Command.MOTOR_STOP) for i in ids]
            controller.bus.transact(requests, controller.clock.now() + 0.02)
    except Exception as exc:  # at exit there is nobody to raise to; leave a trace
        logger.error("emergency stop failed: %s: %s", type(exc).__name__, exc)
