"""Emulated drives that turn the arm's own Pinocchio model: gravity really loads the motors."""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence

import numpy as np

from kinematics.dynamics import FloatArray, mass_matrix
from kinematics.model import build_arm
from kinematics.plant import ArmPlant
from motion.config import ArmConfig
from motion.emulator import Emulator, Fault
from motion.emulator.arm import emulator_for
from motion.protocol.table import ProtocolFamily


def arm_emulator(
    config: ArmConfig,
    *,
    initial_deg: Sequence[float] | None = None,
    faults: Iterable[Fault] = (),
    family: ProtocolFamily = ProtocolFamily.V2,
) -> tuple[Emulator, ArmPlant]:
    """Emulated drives of ``config`` coupled through the arm's rigid-body dynamics (forward dynamics with gravity).

    Each drive's speed loop is tuned for its joint's inertia as a fixed-gain loop on a varying load is tuned on the
    real arm (:func:`tuning_inertia`): whatever the pose the emulator starts at.

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
    inertia = tuning_inertia(config)
    loads = {name: float(inertia[i]) for i, name in enumerate(config.joint_names)}
    return emulator_for(config, plant=plant, load_inertia_kgm2=loads, faults=faults, family=family), plant


#: Poses drawn within the joints' limits to find each joint's range of inertia (fixed seed: the same tuning every run).
TUNING_POSES = 256
_TUNING_SEED = 0


def tuning_inertia(config: ArmConfig) -> FloatArray:
    """The inertia each joint's speed loop is tuned for, kg·m², configuration order: the geometric mean of the
    smallest and largest diagonal of M(q) over :data:`TUNING_POSES` poses drawn within the limits (and the zero pose).

    A joint's inertia changes with the pose of the joints beyond it (the base yaw of arm6 carries 0.007 kg·m² with
    the arm upright and 0.87 with it stretched out); a loop with fixed gains is tuned for a compromise, and the
    geometric mean makes the largest mismatch, either way, the smallest: sqrt(largest / smallest). A drive tuned at
    the light end rings at the heavy one (arm6's base yaw, tuned upright, swung ±4° at 1 Hz stretched out), one
    tuned at the heavy end rings in its speed loop at the light one.
    """
    arm = build_arm(config)
    low = np.array([j.position_min_deg for j in config.joints])
    high = np.array([j.position_max_deg for j in config.joints])
    rng = np.random.default_rng(_TUNING_SEED)
    poses = [np.zeros(len(low)), *(rng.uniform(low, high) for _ in range(TUNING_POSES))]
    diagonals = np.array([np.diag(mass_matrix(arm, q)) for q in poses]) * (180.0 / math.pi)
    tuned: FloatArray = np.sqrt(diagonals.min(axis=0) * diagonals.max(axis=0))
    return tuned
