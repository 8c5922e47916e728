"""Sans-I/O RMD protocol core (CAN v2.3 and RS485 v1.62): bytes <-> typed messages.

Everything is derived from one table (:mod:`motion.protocol.table`): :mod:`~motion.protocol.can_frame` turns
messages into CAN frames and back, :mod:`~motion.protocol.rs485_frame` does the same for RS485 frames and parses
byte streams. No I/O, no sleeps, no logging here.
"""

from __future__ import annotations

from motion.protocol import can_frame, rs485_frame
from motion.protocol.can_frame import CanFrame, CanRequest
from motion.protocol.messages import (
    Acceleration,
    Bare,
    Command,
    EncoderOffset,
    EncoderReading,
    ErrorFlags,
    IncrementalPosition,
    IncrementalPositionSpeed,
    Message,
    MotorState,
    MultiMotorTorque,
    MultiTurnAngle,
    MultiTurnPosition,
    MultiTurnPositionSpeed,
    OpenLoopControl,
    OpenLoopState,
    PhaseCurrents,
    PidGains,
    ProductInfo,
    SingleTurnAngle,
    SingleTurnPosition,
    SingleTurnPositionSpeed,
    SpeedControl,
    SpinDirection,
    Status1,
    TorqueControl,
)
from motion.protocol.rs485_frame import Rs485Frame, Rs485Parser
from motion.protocol.table import (
    COMMANDS,
    CommandSpec,
    Direction,
    WireProtocol,
    field_names,
    field_range,
    raw_values,
)

__all__ = [
    "COMMANDS",
    "Acceleration",
    "Bare",
    "CanFrame",
    "CanRequest",
    "Command",
    "CommandSpec",
    "Direction",
    "EncoderOffset",
    "EncoderReading",
    "ErrorFlags",
    "IncrementalPosition",
    "IncrementalPositionSpeed",
    "Message",
    "MotorState",
    "MultiMotorTorque",
    "MultiTurnAngle",
    "MultiTurnPosition",
    "MultiTurnPositionSpeed",
    "OpenLoopControl",
    "OpenLoopState",
    "PhaseCurrents",
    "PidGains",
    "ProductInfo",
    "Rs485Frame",
    "Rs485Parser",
    "SingleTurnAngle",
    "SingleTurnPosition",
    "SingleTurnPositionSpeed",
    "SpeedControl",
    "SpinDirection",
    "Status1",
    "TorqueControl",
    "WireProtocol",
    "can_frame",
    "field_names",
    "field_range",
    "raw_values",
    "rs485_frame",
]
