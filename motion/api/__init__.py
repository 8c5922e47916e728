"""The Python API: one :class:`Arm` from one configuration file.

::

    from motion import Arm
    with Arm.from_config("configs/arm6.yaml", emulate=True) as arm:   # connect, read state, enable
        arm.move_to({"shoulder_pitch": 30.0, "elbow_pitch": -45.0}, speed_scale=0.5)  # degrees; blocks
        handle = arm.follow([{"base_yaw": 20.0}, {"base_yaw": -20.0}], wait=False)
        handle.wait()
        print(arm.status())
    # leaving the block halts every axis (0x81) and releases the bus

This package is the composition root: it is the one place in :mod:`motion` (with the CLI) that builds the
Pinocchio model (:mod:`kinematics`) and hands the controller its feed-forward callable and the emulator its plant.

Its modules: :mod:`~motion.api.arm` (:class:`Arm`), :mod:`~motion.api.arguments` (the checks of what a caller
passes), :mod:`~motion.api.status` (what a caller reads back: :class:`MotionHandle`, :class:`ArmStatus`) and
:mod:`~motion.api.emulation` (emulated drives: their generation, their real-time process and what this host holds
against them).
"""

from __future__ import annotations

from motion.api.arm import Arm
from motion.api.emulation import emulated_families, emulator_process, measure_modes, realtime_capacity
from motion.api.status import ArmStatus, Arrival, EndReason, JointStatus, MotionHandle
from motion.view import ViewOptions  # the options of Arm(view=...): `from motion import ViewOptions` comes here

__all__ = [
    "Arm",
    "ArmStatus",
    "Arrival",
    "EndReason",
    "JointStatus",
    "MotionHandle",
    "ViewOptions",
    "emulated_families",
    "emulator_process",
    "measure_modes",
    "realtime_capacity",
]
