"""rmd-motion: trajectory-level multi-axis motion control for MyActuator RMD servo drives.

The curated API::

    from motion import Arm
    with Arm.from_config("configs/arm6.yaml", emulate=True) as arm:
        arm.move_to({"shoulder_pitch": 30.0}, speed_scale=0.5)
"""

from __future__ import annotations

__version__ = "0.1.0"

from typing import TYPE_CHECKING, Any

from motion.errors import (
    ConfigError,
    DecodeError,
    EncodeError,
    FaultKind,
    MotionError,
    MotionFault,
    PlanningError,
    PortLost,
    ProtocolError,
    TransportError,
    TransportTimeout,
)

if TYPE_CHECKING:
    from motion.api import Arm, ArmStatus, JointStatus, MotionHandle
    from motion.view import ViewOptions

_API = {"Arm", "ArmStatus", "JointStatus", "MotionHandle", "ViewOptions"}


def __getattr__(name: str) -> Any:
    # The API pulls in python-can, pyserial, Ruckig and NumPy: load it on first use, so that `import motion.protocol`
    # stays light and backends are imported only when used.
    if name in _API:
        from motion import api  # noqa: PLC0415

        return getattr(api, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


__all__ = [
    "Arm",
    "ArmStatus",
    "ConfigError",
    "DecodeError",
    "EncodeError",
    "FaultKind",
    "JointStatus",
    "MotionError",
    "MotionFault",
    "MotionHandle",
    "PlanningError",
    "PortLost",
    "ProtocolError",
    "TransportError",
    "TransportTimeout",
    "ViewOptions",
    "__version__",
]
