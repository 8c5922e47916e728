"""Emulated drives that turn the arm's own Pinocchio model: gravity really loads the motors."""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence

import numpy as np

from kinematics.dynamics import mass_matrix
from kinematics.model import build_arm
from kinematics.plant import ArmPlant
from motion.compose import emulator_for
from motion.config import ArmConfig
from motion.emulator import Emulator, Fault
from motion.protocol.table import ProtocolFamily


def arm_emulator(
    config: ArmConfig,
    *,
    initial_deg: Sequence[float] | None = None,
    faults: Iterable[Fault] = (),
    family: ProtocolFamily = ProtocolFamily.V2,
) -> tuple[Emulator, ArmPlant]:
    """Emulated drives of ``config`` coupled through the arm's rigid-body dynamics (forward dynamics with gravity).

    Each drive's speed loop is tuned for the joint's inertia (the mass matrix diagonal at ``initial_deg``), as a
    drive tuned on the real arm would be.

    Args:
        config: the arm.
        initial_deg: joint angles at start, degrees, configuration order (default all zero).
        faults: faults to schedule on the emulated drives.
        family: the drives' protocol generation.

    Returns:
        The emulator (attach it to a bus) and its plant (to read the true joint angles).
    """
    start = np.zeros(len(config.joints)) if initial_deg is None else np.asarray(initial_deg, dtype=np.float64)
    plant = ArmPlant(build_arm(config), config, start)
    inertia = np.diag(mass_matrix(build_arm(config), start)) * (180.0 / math.pi)  # kg·m² per joint
    loads = {name: float(inertia[i]) for i, name in enumerate(config.joint_names)}
    return emulator_for(config, plant=plant, load_inertia_kgm2=loads, faults=faults, family=family), plant
