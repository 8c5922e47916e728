"""Safety: per-cycle fault monitors, the arm state machine and the guarded cycle that halts every axis on a fault."""

from __future__ import annotations

from motion.safety.collision import CollisionObserver
from motion.safety.records import HaltRecord, Reaction
from motion.safety.states import ArmEvent, ArmState, InvalidTransition, StateMachine
from motion.safety.supervisor import Supervisor
from motion.safety.watchdog import SafetySettings, Watchdog

__all__ = [
    "ArmEvent",
    "ArmState",
    "CollisionObserver",
    "HaltRecord",
    "InvalidTransition",
    "Reaction",
    "SafetySettings",
    "StateMachine",
    "Supervisor",
    "Watchdog",
]
