"""Emulated RMD drives: the behaviour of every command, plant physics, bus attachments and fault injection.

Quick start (deterministic, no bus)::

    from motion.emulator import Emulator
    from motion.protocol import MultiTurnPositionSpeed

    emulator = Emulator([1, 2])
    emulator.request(1, MultiTurnPositionSpeed(angle_deg=90.0, max_speed_dps=360.0))
    emulator.advance(0.5)  # simulation seconds

On a bus (simulation time follows the monotonic clock)::

    with VirtualCanAttachment(Emulator(range(1, 7)), "arm"):
        ...  # CanEndpoint("virtual", "arm") talks to drives 1..6
"""

from __future__ import annotations

from motion.emulator.attach import (
    Attachment,
    AttachmentStats,
    Rs485Attachment,
    SlcanAttachment,
    VirtualCanAttachment,
)
from motion.emulator.core import DEFAULT_STEP_S, Emulator, Exchange, Outgoing
from motion.emulator.drive import DriveLoop, EmulatedDrive, RunState, Setpoint
from motion.emulator.faults import Corruption, Fault, InjectedFault, parse_fault
from motion.emulator.framelog import FrameLog
from motion.emulator.model import DEFAULT_PID, DriveModel, LoadModel
from motion.emulator.plant import IndependentLoads, Plant
from motion.emulator.slcan import SlcanDevice
from motion.emulator.timing import TimingModel, can_frame_bits

__all__ = [
    "DEFAULT_PID",
    "DEFAULT_STEP_S",
    "Attachment",
    "AttachmentStats",
    "Corruption",
    "DriveLoop",
    "DriveModel",
    "EmulatedDrive",
    "Emulator",
    "Exchange",
    "Fault",
    "FrameLog",
    "IndependentLoads",
    "InjectedFault",
    "LoadModel",
    "Outgoing",
    "Plant",
    "Rs485Attachment",
    "RunState",
    "Setpoint",
    "SlcanAttachment",
    "SlcanDevice",
    "TimingModel",
    "VirtualCanAttachment",
    "can_frame_bits",
    "parse_fault",
]
