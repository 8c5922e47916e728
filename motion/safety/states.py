"""The arm's state machine as a transition table; an unknown (state, event) goes to the safe state and raises."""

from __future__ import annotations

import threading
from enum import Enum
from typing import Final

from motion.errors import MotionError


class ArmState(Enum):
    """Where the arm is."""

    READY = "ready"  #: enabled, holding the reference, accepts motion
    MOVING = "moving"  #: playing a motion
    FAULTED = "faulted"  #: every axis halted; motion is refused until clear() succeeds
    CLOSED = "closed"  #: the loop has ended and the bus is released


class ArmEvent(Enum):
    """What happens to it."""

    MOVE = "move"  #: a motion command was accepted
    DONE = "done"  #: the motion ended
    FAULT = "fault"  #: a fault was detected (or an E-stop requested)
    CLEARED = "cleared"  #: clear() found every drive clean
    CLOSE = "close"  #: the arm is shut down


SAFE_STATE: Final = ArmState.FAULTED

TRANSITIONS: Final[dict[tuple[ArmState, ArmEvent], ArmState]] = {
    (ArmState.READY, ArmEvent.MOVE): ArmState.MOVING,
    (ArmState.READY, ArmEvent.DONE): ArmState.READY,
    (ArmState.READY, ArmEvent.FAULT): ArmState.FAULTED,
    (ArmState.READY, ArmEvent.CLOSE): ArmState.CLOSED,
    (ArmState.MOVING, ArmEvent.MOVE): ArmState.MOVING,
    (ArmState.MOVING, ArmEvent.DONE): ArmState.READY,
    (ArmState.MOVING, ArmEvent.FAULT): ArmState.FAULTED,
    (ArmState.MOVING, ArmEvent.CLOSE): ArmState.CLOSED,
    (ArmState.FAULTED, ArmEvent.FAULT): ArmState.FAULTED,
    (ArmState.FAULTED, ArmEvent.CLEARED): ArmState.READY,
    (ArmState.FAULTED, ArmEvent.CLOSE): ArmState.CLOSED,
    (ArmState.CLOSED, ArmEvent.CLOSE): ArmState.CLOSED,
    (ArmState.CLOSED, ArmEvent.FAULT): ArmState.CLOSED,
}


class InvalidTransition(MotionError):
    """An event that the current state does not accept; the machine is now in the safe state."""


class StateMachine:
    """Thread-safe holder of the arm state, driven only through :data:`TRANSITIONS`."""

    def __init__(self, initial: ArmState = ArmState.READY) -> None:
        self._state = initial
        self._lock = threading.Lock()

    @property
    def state(self) -> ArmState:
        """The current state."""
        return self._state

    def fire(self, event: ArmEvent) -> ArmState:
        """Apply ``event``.

        Raises:
            InvalidTransition: the pair is not in the table; the state becomes :data:`SAFE_STATE` (unless closed).
        """
        with self._lock:
            nxt = TRANSITIONS.get((self._state, event))
            if nxt is None:
                previous = self._state
                if previous is not ArmState.CLOSED:
                    self._state = SAFE_STATE
                raise InvalidTransition(f"event {event.value!r} is not allowed in state {previous.value!r}")
            self._state = nxt
            return nxt
