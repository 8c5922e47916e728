"""Commissioning by the holding current (issue 33 §2): with the arm holding still, each joint's measured torque
(its drive's torque current through the configured gear, direction and torque constant) against the model's gravity
torque g(q) there. A swapped motor id, a wrong ``gear_ratio``, ``direction`` or ``torque_constant_nm_per_a`` shows as
a mismatch before anything moves.

The bound a joint's torque may differ by without a mismatch, from what the check cannot know (the stated bounds of
:mod:`motion.safety.collision_bound`): the torque constant ±20 % and the model's masses ±:data:`MASS_ERROR` (a share
of ``|g|``), friction at rest up to its breakaway (``(1 + 50 %) × coulomb_friction_nm``, either way: a joint held by
stiction takes any torque up to it) and :data:`CURRENT_STEPS` steps of the reply's current field. A joint whose
gravity torque is within that bound of zero cannot be judged this way (gravity does not load it): ``rmd-motion jog``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Final

import numpy as np

from motion.errors import MotionError
from motion.safety.collision_bound import MODEL_ERROR

if TYPE_CHECKING:
    from motion.api.arm import Arm

#: How long the arm holds before the currents are averaged, and over how long they are, s.
SETTLE_S: Final = 0.3
AVERAGE_S: Final = 0.2
#: The published snapshots read over that time.
SAMPLES: Final = 10
#: The share of ``|g|`` the model's masses may be off by.
MASS_ERROR: Final = 0.2
#: Steps of the current field in the bound.
CURRENT_STEPS: Final = 3.0


@dataclass(frozen=True)
class HoldingVerdict:
    """One joint's holding torque against the model's, N·m at the joint.

    Attributes:
        name: the joint.
        motor_id: its drive.
        measured_nm: the torque its drive holds with (averaged).
        model_nm: the model's gravity torque g(q) there.
        bound_nm: how far they may differ (the module docstring).
        judged: gravity loads the joint beyond the bound (else it is not judged: jog it).
        drive: how messages name its drive ("motor 2", "motor 2 on bus right").
    """

    name: str
    motor_id: int
    measured_nm: float
    model_nm: float
    bound_nm: float
    judged: bool
    drive: str = ""

    @property
    def matches(self) -> bool:
        return not self.judged or abs(self.measured_nm - self.model_nm) <= self.bound_nm

    def text(self) -> str:
        """In words, with what a mismatch may mean."""
        label = f"{self.name} ({self.drive or f'motor {self.motor_id}'})"
        figures = f"holds with {self.measured_nm:+.2f} N·m where the model's gravity takes {self.model_nm:+.2f} N·m"
        if not self.judged:
            return f"{label} {figures}: gravity does not load it enough to tell (rmd-motion jog {self.name})"
        if self.matches:
            return f"{label} {figures} (within {self.bound_nm:.2f}): as configured"
        ratio = self.measured_nm / self.model_nm
        if abs(ratio + 1.0) <= 0.3:
            why = "the sign is reversed: its direction"
        elif ratio > 0:
            why = f"{ratio:.2f} times the model's: its gear_ratio or torque_constant_nm_per_a, or the model's masses"
        else:
            why = "another joint's load, or a wrong direction: its motor_id (swapped with another joint's?)"
        return f"{label} {figures} (bound {self.bound_nm:.2f}): {why}"


def _hold(arm: Arm, duration_s: float) -> None:
    """Let ``duration_s`` pass with the arm holding; a fault meanwhile is raised (the arm halted)."""
    arm.sleep(duration_s)
    fault = arm.supervisor.fault if arm.supervisor is not None else None
    if fault is not None:
        raise fault


def check_holding(arm: Arm) -> list[HoldingVerdict]:
    """Hold the connected arm still for :data:`SETTLE_S`, average each joint's torque over :data:`AVERAGE_S` and set
    it against g(q) (the module docstring). Nothing moves: the arm holds where it is.

    Raises:
        MotionError: the arm is not connected, or not ready (moving).
        MotionFault: the arm is halted by a fault (that fault), or a fault halted it meanwhile.
    """
    from kinematics import build_arm  # noqa: PLC0415 - Pinocchio only where a check needs it
    from kinematics.dynamics import gravity_torque  # noqa: PLC0415

    if arm.fault is not None:
        raise arm.fault
    state = arm.status().state
    if state != "ready":
        raise MotionError(f"the holding check needs the arm at rest and ready; it is {state}")
    controller = arm.controller
    assert controller is not None
    _hold(arm, SETTLE_S)
    transmission = controller.transmission
    total = np.zeros(len(arm.names))
    for _ in range(SAMPLES):  # (the published snapshots: nothing is added to the control loop)
        _hold(arm, AVERAGE_S / SAMPLES)
        total += transmission.joint_torque_nm(controller.snapshot.iq_a)
    measured = total / SAMPLES
    model = gravity_torque(build_arm(arm.config), controller.snapshot.position_deg)
    step_nm = np.abs(transmission.joint_torque_nm(np.array([f.current_step_a for f in controller.families])))
    joints = arm.config.joints
    breakaway = np.array([(1.0 + MODEL_ERROR[2]) * j.coulomb_friction_nm for j in joints])
    floor = breakaway + CURRENT_STEPS * step_nm
    bound = (MODEL_ERROR[0] + MASS_ERROR) * np.abs(model) + floor
    return [
        HoldingVerdict(
            j.name,
            j.motor_id,
            float(measured[i]),
            float(model[i]),
            float(bound[i]),
            bool(abs(model[i]) > 2 * floor[i]),
            j.drive_label,
        )
        for i, j in enumerate(joints)
    ]
