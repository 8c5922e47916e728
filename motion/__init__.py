"""rmd-motion: trajectory-level multi-axis motion control for MyActuator RMD servo drives.

The curated API::

    from motion import Arm
    with Arm.from_config("configs/arm6.yaml", emulate=True) as arm:
        arm.move_to({"shoulder_pitch": 30.0}, speed_scale=0.5)
"""

from __future__ import annotations

__version__ = "0.1.0"

from motion.api import Arm, ArmStatus, JointStatus, MotionHandle
from motion.errors import (
    ConfigError,
    DecodeError,
    EncodeError,
    MotionError,
    MotionFault,
    PlanningError,
    ProtocolError,
    TransportError,
    TransportTimeout,
)

__all__ = [
    "Arm",
    "ArmStatus",
    "ConfigError",
    "DecodeError",
    "EncodeError",
    "JointStatus",
    "MotionError",
    "MotionFault",
    "MotionHandle",
    "PlanningError",
    "ProtocolError",
    "TransportError",
    "TransportTimeout",
    "__version__",
]
