"""The emulated drives of a configured arm: the same :class:`~motion.config.ArmConfig` describes the real arm and its
emulation.

:func:`emulator_for` gives every configured joint an emulated drive with the joint's motor id, gear ratio, torque
constant, encoder, current limit and rotor inertia, so a program tested on the emulator talks to the same ids with the
same units.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Iterable, Mapping
from dataclasses import fields

from motion.config.schema import ArmConfig, JointConfig
from motion.emulator.core import Emulator
from motion.emulator.faults import Fault
from motion.emulator.model import DEFAULT_PID, DriveModel, LoadModel
from motion.emulator.plant import Plant
from motion.protocol.table import ProtocolFamily

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
    family: ProtocolFamily = ProtocolFamily.V2,
) -> Emulator:
    """Emulated drives matching ``config``, speaking ``family`` (V3: the joints with ``brake`` have one).

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
    models = {j.motor_id: drive_model(j, supply) for j in config.joints}
    loads = {
        j.motor_id: LoadModel(
            inertia_kgm2=inertia.get(j.name, DEFAULT_LOAD_INERTIA_KGM2),
            viscous_friction_nm_per_dps=j.emulation.viscous_friction_nm_per_dps,
            coulomb_friction_nm=j.emulation.coulomb_friction_nm,
        )
        for j in config.joints
    }
    stops = {j.motor_id: hard_stops(j) for j in config.joints if j.homing is not None}
    # The emulator's own rule (only its V3 drives have brakes), not control's FAMILIES[family].brakes, which says the
    # same from a layer above the emulator.
    braked = [j.motor_id for j in config.joints if j.brake] if family is ProtocolFamily.V3 else []
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
