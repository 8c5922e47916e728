"""What every part of the supervisor works with (the fault reaction, the halted cycle, the clearing, the session's
end): one :class:`SafetyContext`, taken by each part as :class:`SafetyPart`'s attributes."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from motion.control.controller import Controller
    from motion.safety.brakes import BrakeWatch
    from motion.safety.halted import HaltGuard
    from motion.safety.records import FaultLog
    from motion.safety.states import StateMachine
    from motion.safety.watchdog import SafetySettings, Watchdog


@dataclass(frozen=True, slots=True)
class SafetyContext:
    """The supervisor's shared pieces.

    Attributes:
        controller: the controller.
        settings: the safety settings (halt policy, collision reaction, ``halt_retry_s``, limits).
        machine: the arm's state machine.
        guard: the halted state's bookkeeping.
        watchdog: the watchdog.
        log: the session's faults.
        brakes: the braked joints whose drives cannot hold them (:mod:`motion.safety.brakes`).
    """

    controller: Controller
    settings: SafetySettings
    machine: StateMachine
    guard: HaltGuard
    watchdog: Watchdog
    log: FaultLog
    brakes: BrakeWatch


class SafetyPart:
    """A part of the supervisor: the context's pieces as its own attributes."""

    def __init__(self, context: SafetyContext) -> None:
        self.controller = context.controller
        self.settings = context.settings
        self.machine = context.machine
        self.guard = context.guard
        self.watchdog = context.watchdog
        self.log = context.log
        self.brakes = context.brakes
