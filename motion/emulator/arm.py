"""The emulated drives of a configured arm: the same :class:`~motion.config.ArmConfig` describes the real arm and its
emulation.

:func:`emulator_for` gives every configured joint an emulated drive with the joint's motor id, gear ratio, torque
constant, encoder, current limit and rotor inertia, so a program tested on the emulator talks to the same ids with the
same units. :func:`arm_emulator` couples those drives through the arm's own Pinocchio model (forward dynamics with
gravity, :class:`kinematics.plant.ArmPlant`): gravity really loads the motors.

Like the composition roots, this module imports :mod:`kinematics` only inside the functions that build the arm's
model, so Pinocchio is loaded only where an arm is emulated (:func:`emulator_for` alone does not load it).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import fields
from typing import TYPE_CHECKING

import numpy as np

from motion.config.schema import ArmConfig, JointConfig
from motion.emulator.core import Emulator
from motion.emulator.faults import Fault
from motion.emulator.model import DEFAULT_PID, DriveModel, LoadModel
from motion.emulator.plant import Plant
from motion.protocol.table import ProtocolFamily
from motion.transmission import FloatArray

if TYPE_CHECKING:
    from kinematics.plant import ArmPlant

# The emulated drive's own speed cap (0xA3/0xA5/0xA7 and holding) is this many times the joint limit, motor side.
_DRIVE_SPEED_MARGIN = 2.0
# Emulated supply voltage, V, at least this share above the configured minimum.
_EMULATED_SUPPLY_V = 24.0
_SUPPLY_MARGIN = 1.2
# Joint-side load inertia assumed for emulated independent loads when no plant is given, kg·m².
DEFAULT_LOAD_INERTIA_KGM2 = 0.01


def drive_model(joint: JointConfig, supply_voltage_v: float = 24.0) -> DriveModel:
    """The emulated drive of one joint, on a supply of ``supply_voltage_v``, tuned as its ``emulation`` says."""
    emulation = joint.emulation
    gains = {f.name: getattr(emulation.pid, f.name) for f in fields(emulation.pid)}
    pid = dataclasses.replace(DEFAULT_PID, **{k: v for k, v in gains.items() if v is not None})
    factory = DriveModel()
    return DriveModel(
        pid=pid,
        acceleration_dps2=factory.acceleration_dps2
        if emulation.acceleration_dps2 is None
        else emulation.acceleration_dps2,
        supply_voltage_v=supply_voltage_v,
        gear_ratio=joint.gear_ratio,
        torque_constant_nm_per_a=joint.emulation.torque_constant_nm_per_a or joint.torque_constant_nm_per_a,
        rotor_inertia_kgm2=joint.emulation.rotor_inertia_kgm2,
        encoder_bits=joint.encoder_bits,
        current_limit_a=joint.current_limit_a,
        max_speed_dps=joint.velocity_limit_dps * joint.gear_ratio * _DRIVE_SPEED_MARGIN,
        motor_name=f"EMU-{joint.name}"[:20],
    )


def emulator_for(
    config: ArmConfig,
    *,
    plant: Plant | None = None,
    load_inertia_kgm2: Mapping[str, float] | None = None,
    faults: Iterable[Fault] = (),
    family: ProtocolFamily | Sequence[ProtocolFamily] = ProtocolFamily.V2,
) -> Emulator:
    """Emulated drives matching ``config``, speaking ``family`` (a sequence: each bus's, in the order of ``buses:``;
    V3: the joints with ``brake`` have one).

    Args:
        config: the arm.
        plant: the mechanics (e.g. ``kinematics.plant.ArmPlant`` for gravity-coupled joints); default independent
            loads with the configured friction.
        load_inertia_kgm2: joint-side load inertia per joint name, used to tune each drive's speed loop (and as the
            independent loads' inertia); default :data:`DEFAULT_LOAD_INERTIA_KGM2`.
        faults: faults to schedule.
    """
    inertia = dict(load_inertia_kgm2 or {})
    # The emulated supply sits comfortably above the configured minimum (a 48 V arm gets 48 V, not 24 V).
    supply = max(_EMULATED_SUPPLY_V, config.safety.min_voltage_v * _SUPPLY_MARGIN)
    models = {j.address: drive_model(j, supply) for j in config.joints}
    loads = {
        j.address: LoadModel(
            inertia_kgm2=inertia.get(j.name, DEFAULT_LOAD_INERTIA_KGM2),
            viscous_friction_nm_per_dps=j.emulation.viscous_friction_nm_per_dps,
            coulomb_friction_nm=j.emulation.coulomb_friction_nm,
        )
        for j in config.joints
    }
    stops = {j.address: hard_stops(j) for j in config.joints if j.homing is not None}
    # The emulator's own rule (only its V3 drives have brakes), not control's FAMILIES[family].brakes, which says the
    # same from a layer above the emulator.
    families = [family] * len(config.buses) if isinstance(family, str) else list(family)
    braked = [j.address for j in config.joints if j.brake and families[j.bus_index] is ProtocolFamily.V3]
    return Emulator(
        models.keys(), model=models, load=loads, plant=plant, faults=faults, stops=stops, family=family, brakes=braked
    )


def hard_stops(joint: JointConfig) -> tuple[float, float]:
    """The emulated plant's bounds of a joint with a hard stop (``homing.stop_deg``), in the emulator's coordinate
    (motor angle / gear ratio, rad): the joint angle is ``direction × p + zero_offset_deg``."""
    assert joint.homing is not None
    p = math.radians((joint.homing.stop_deg - joint.zero_offset_deg) / joint.direction)
    below = joint.homing.stop_deg <= joint.position_min_deg  # the stop bounds the joint angle from below
    return (p, math.inf) if below == (joint.direction > 0) else (-math.inf, p)


def arm_emulator(
    config: ArmConfig,
    *,
    initial_deg: Sequence[float] | None = None,
    faults: Iterable[Fault] = (),
    family: ProtocolFamily | Sequence[ProtocolFamily] = ProtocolFamily.V2,
) -> tuple[Emulator, ArmPlant]:
    """Emulated drives of ``config`` coupled through the arm's rigid-body dynamics (forward dynamics with gravity).

    Each drive's speed loop is tuned for its joint's inertia as a fixed-gain loop on a varying load is tuned on the
    real arm (:func:`tuning_inertia`): whatever the pose the emulator starts at.

    Args:
        config: the arm.
        initial_deg: joint angles at start, degrees, configuration order (default all zero).
        faults: faults to schedule on the emulated drives.
        family: the drives' protocol generation (a sequence: each bus's).

    Returns:
        The emulator (attach it to a bus) and its plant (to read the true joint angles).
    """
    from kinematics.model import build_arm  # noqa: PLC0415 - Pinocchio only where an arm is emulated
    from kinematics.plant import ArmPlant  # noqa: PLC0415 - as above

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
    from kinematics.dynamics import mass_matrix  # noqa: PLC0415 - Pinocchio only where an arm is emulated
    from kinematics.model import build_arm  # noqa: PLC0415 - as above

    arm = build_arm(config)
    low = np.array([j.position_min_deg for j in config.joints])
    high = np.array([j.position_max_deg for j in config.joints])
    rng = np.random.default_rng(_TUNING_SEED)
    poses = [np.zeros(len(low)), *(rng.uniform(low, high) for _ in range(TUNING_POSES))]
    diagonals = np.array([np.diag(mass_matrix(arm, q)) for q in poses]) * (180.0 / math.pi)
    tuned: FloatArray = np.sqrt(diagonals.min(axis=0) * diagonals.max(axis=0))
    return tuned
