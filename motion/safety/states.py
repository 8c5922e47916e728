"""The arm's state machine as a transition table; an unknown (state, event) goes to the safe state and raises."""

from __future__ import annotations

import threading
from collections.abc import Callable
from enum import Enum
from typing import Final

from motion.errors import MotionError


class ArmState(Enum):
    """Where the arm is. Six of the states are faulted (:attr:`faulted`): motion is refused in them."""

    READY = "ready"  #: enabled, holding the reference, accepts motion
    MOVING = "moving"  #: playing a motion
    HOLDING = "holding"  #: faulted: a jerk-limited stop of the reference is streamed, then held (policy ``hold``)
    #: faulted: a collision; gravity compensation with zero gains is streamed so that the arm yields (``comply``)
    COMPLYING = "complying"
    #: faulted: the drives' own halt is owed to every axis and has not gone out yet (where an event the state does
    #: not accept leads from a state that sent none, :data:`SAFE_STATES`): the next cycle sends it
    HALT_PENDING = "halt_pending"
    HALTING = "halting"  #: faulted: 0x81 / 0x80 went to every axis; re-sent to those that have not acknowledged
    HALTED = "halted"  #: faulted: every drive acknowledged its halt (or the retry bound passed); reads only
    BUS_LOST = "bus_lost"  #: faulted: the bus failed, nothing can be sent; the loop has ended
    CLOSED = "closed"  #: the loop has ended and the bus is released

    @property
    def faulted(self) -> bool:
        """True in the states that refuse motion until ``clear()`` (HOLDING, COMPLYING, HALT_PENDING, HALTING,
        HALTED, BUS_LOST)."""
        return self in _FAULTED


_FAULTED: Final = frozenset(
    {
        ArmState.HOLDING,
        ArmState.COMPLYING,
        ArmState.HALT_PENDING,
        ArmState.HALTING,
        ArmState.HALTED,
        ArmState.BUS_LOST,
    }
)
#: The states of the drives' own halt, owed or sent (a fault whose cause repeats there is recorded once).
HALT_STATES: Final = frozenset({ArmState.HALT_PENDING, ArmState.HALTING, ArmState.HALTED})


class ArmEvent(Enum):
    """What happens to it."""

    MOVE = "move"  #: a motion command was accepted
    DONE = "done"  #: the motion ended
    HOLD = "hold"  #: a fault whose reaction is the stop ramp (policy ``hold``, a holdable kind, healthy bus)
    COMPLY = "comply"  #: a collision whose reaction is to yield (``safety.collision_reaction: comply``, healthy bus)
    HALT = "halt"  #: a fault whose reaction is the drives' own halt (0x81 / 0x80 to every axis)
    ACKNOWLEDGED = "acknowledged"  #: every drive acknowledged the halt, or the retry bound passed
    BUS_GONE = "bus_gone"  #: the bus failed: nothing more can be sent
    CLEARED = "cleared"  #: clear() found every drive clean
    CLOSE = "close"  #: the arm is shut down


_NO_HALT_SENT: Final = (ArmState.READY, ArmState.MOVING, ArmState.HOLDING, ArmState.COMPLYING, ArmState.HALT_PENDING)
#: Where an event that the current state does not accept leads, by state: every axis is halted (again). From a state
#: that sent no halt, HALT_PENDING, whose cycle sends it; from one that did, HALTING, which goes on sending it to every
#: drive not known to be halted (the fault it was sent for stays the arm's fault). BUS_LOST and CLOSED have none: they
#: stay as they are, nothing can be sent from them.
SAFE_STATES: Final[dict[ArmState, ArmState]] = {
    **dict.fromkeys(_NO_HALT_SENT, ArmState.HALT_PENDING),
    ArmState.HALTING: ArmState.HALTING,
    ArmState.HALTED: ArmState.HALTING,
}


def _from_each(
    states: tuple[ArmState, ...], event: ArmEvent, target: ArmState
) -> dict[tuple[ArmState, ArmEvent], ArmState]:
    return {(state, event): target for state in states}


_RUNNING: Final = (ArmState.READY, ArmState.MOVING)
_SENDING: Final = (*_NO_HALT_SENT, ArmState.HALTING, ArmState.HALTED)

TRANSITIONS: Final[dict[tuple[ArmState, ArmEvent], ArmState]] = {
    **_from_each(_RUNNING, ArmEvent.MOVE, ArmState.MOVING),
    **_from_each(_RUNNING, ArmEvent.DONE, ArmState.READY),
    **_from_each(_RUNNING, ArmEvent.HOLD, ArmState.HOLDING),
    # a collision while running or during a stop ramp: yield (the ramp would go on into what the arm hit)
    **_from_each((*_RUNNING, ArmState.HOLDING), ArmEvent.COMPLY, ArmState.COMPLYING),
    # a fault in any state that can still send halts every axis: also an escalation of a hold or of compliance (a
    # fault of the bus, of a drive, a limit, an E-stop), a new fault or E-stop while halting or halted (the halt
    # is sent again), and the halt going out from HALT_PENDING
    **_from_each(_SENDING, ArmEvent.HALT, ArmState.HALTING),
    (ArmState.HALTING, ArmEvent.ACKNOWLEDGED): ArmState.HALTED,
    **_from_each(_SENDING, ArmEvent.BUS_GONE, ArmState.BUS_LOST),
    (ArmState.HOLDING, ArmEvent.CLEARED): ArmState.READY,
    (ArmState.COMPLYING, ArmEvent.CLEARED): ArmState.READY,
    (ArmState.HALTED, ArmEvent.CLEARED): ArmState.READY,
    **_from_each(tuple(ArmState), ArmEvent.CLOSE, ArmState.CLOSED),
}


class InvalidTransition(MotionError):
    """An event that the current state does not accept; the machine is now in its safe state (:data:`SAFE_STATES`)."""


class StateMachine:
    """Thread-safe holder of the arm state, driven only through :data:`TRANSITIONS`."""

    def __init__(self, initial: ArmState = ArmState.READY, on_change: Callable[[ArmState], None] | None = None) -> None:
        self._state = initial
        self._lock = threading.Lock()
        #: Called with the new state after every transition (the safe state too), under the machine's lock.
        self.on_change = on_change

    @property
    def state(self) -> ArmState:
        """The current state."""
        return self._state

    def fire(self, event: ArmEvent) -> ArmState:
        """Apply ``event``.

        Raises:
            InvalidTransition: the pair is not in the table; the state becomes the state's safe state
                (:data:`SAFE_STATES`; none when the bus is lost or the arm closed: nothing can be sent from there).
        """
        with self._lock:
            nxt = TRANSITIONS.get((self._state, event))
            if nxt is None:
                previous = self._state
                safe = SAFE_STATES.get(previous)
                if safe is not None:
                    self._set(safe)
                raise InvalidTransition(f"event {event.value!r} is not allowed in state {previous.value!r}")
            self._set(nxt)
            return nxt

    def _set(self, state: ArmState) -> None:
        self._state = state
        if self.on_change is not None:
            self.on_change(state)
