"""Parameters of an emulated drive (motor, power stage, firmware settings) and of the load it turns.

Sides: a *motor-side* quantity is measured at the motor shaft (what the drive reports: angles, speeds, iq); a
*joint-side* quantity is measured after the gear (what the plant integrates). ``gear_ratio`` is motor-shaft degrees per
joint degree, as in the project's transmission convention (docs/architecture.md), with direction +1: a drive's emulated
joint turns the same way as its motor. Friction is joint side, in the units of the arm configuration's ``emulation``
block.

The three PI loops of the drive map their uint8 gains (0x30..0x32) to physical gains through the scales below. The
speed loop is scaled by the inertia the drive was tuned for, so that a gain means a bandwidth whatever the load: a
real installation tunes its gains to its load; the emulator starts "tuned" to the load it is attached to.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Final

from motion.errors import ConfigError
from motion.protocol.messages import Command, PidGains
from motion.protocol.table import Direction, WireProtocol, field_range

#: What the drive's registers hold is what the protocol carries (the table's ranges).
_ACCELERATION_MAX: Final = field_range(
    Command.WRITE_ACCELERATION_RAM, Direction.REQUEST, WireProtocol.CAN, "acceleration_dps2"
)[1]
_ENCODER_OFFSET_MAX: Final = field_range(
    Command.WRITE_ENCODER_OFFSET, Direction.REQUEST, WireProtocol.CAN, "encoder_offset"
)[1]

#: Position loop: proportional gain in 1/s per unit of ``angle_kp`` (speed reference = gain × angle error).
ANGLE_KP_PER_S: Final = 0.5
#: Position loop: integral gain in 1/s² per unit of ``angle_ki``.
ANGLE_KI_PER_S2: Final = 0.02
#: Speed loop: closed-loop bandwidth in rad/s per unit of ``speed_kp`` (at the tuned inertia).
SPEED_KP_RAD_S: Final = 4.0
#: Speed loop: PI zero (integral gain / proportional gain) in rad/s per unit of ``speed_ki``.
SPEED_KI_RAD_S: Final = 0.5
#: Current loop: closed-loop bandwidth in rad/s per unit of ``iq_kp`` (the loop is modelled as its first-order
#: closed-loop response because the winding's electrical time constant is below the integration step).
IQ_KP_RAD_S: Final = 40.0
#: Largest torque current the power stage can drive, in A (the documents' reply range, ±33 A).
HARDWARE_CURRENT_LIMIT_A: Final = 33.0
#: Firmware gains of a drive fresh from the factory (ROM at first power-on).
DEFAULT_PID: Final = PidGains(Command.READ_PID, 100, 50, 50, 40, 50, 50)


def _check(owner: str, checks: tuple[tuple[str, str, bool], ...], values: object) -> None:
    """Raise ConfigError naming the first failed check (``(field, allowed, ok)``)."""
    for name, allowed, ok in checks:
        if not ok:
            raise ConfigError(f"<{owner}>", name, f"allowed: {allowed}; found: {getattr(values, name)!r}")


def _positive(x: float) -> bool:
    return math.isfinite(x) and x > 0


def _non_negative(x: float) -> bool:
    return math.isfinite(x) and x >= 0


@dataclass(frozen=True, slots=True)
class DriveModel:
    """One drive and its motor: electrical, thermal, encoder and firmware (ROM) parameters.

    Attributes:
        gear_ratio: motor-shaft degrees per joint degree (1 for direct drive).
        torque_constant_nm_per_a: motor-side torque per ampere of torque current, N·m/A (also the back-EMF
            constant in V·s/rad).
        rotor_inertia_kgm2: rotor inertia, motor side, kg·m² (the plant sees ``gear_ratio² ×`` this).
        winding_resistance_ohm: phase resistance, Ω (copper losses, open-loop current, voltage limit).
        pole_pairs: motor pole pairs (electrical angle of the phase currents of 0x9D).
        encoder_bits: single-turn encoder resolution, 12..18 bits. Above 16 bits the uint16 encoder fields carry
            the top 16 bits (counts >> (bits - 16)), and 0x91 offsets are in those units.
        current_limit_a: "Max Torque Current" setting, A: caps iq in the speed and position modes (not 0xA1).
        max_speed_dps: "Max Speed" setting, motor deg/s: speed cap of 0xA2, 0xA3, 0xA5, 0xA7 and of 0x81 holding.
        acceleration_dps2: acceleration limit at power-on (0x34 writes RAM only), motor deg/s²; 0 means no limit.
        pid: PI gains in ROM at first power-on.
        tuned_inertia_kgm2: motor-side inertia the speed-loop gains are scaled for, kg·m²; None: the inertia of
            the load the emulator attaches the drive to (rotor + joint-side load / gear_ratio²).
        supply_voltage_v: supply voltage, V.
        low_voltage_v: under-voltage protection threshold (error bit 0 below it), V.
        over_temperature_c: over-temperature protection threshold (error bit 3 above it), °C.
        ambient_c: ambient temperature, °C (also the motor temperature at start).
        thermal_resistance_k_per_w: winding-to-ambient thermal resistance, K/W.
        thermal_time_constant_s: winding thermal time constant, s.
        shaft_zero_deg: mechanical shaft angle (the raw encoder angle) when the plant's joint is at 0, degrees.
        encoder_offset: encoder offset in ROM at first power-on, in encoder-field units.
        driver_name: 0x12 driver model text (ASCII, at most 20 bytes).
        motor_name: 0x12 motor model text (ASCII, at most 20 bytes).
        hardware_version: 0x12 hardware version (0.0..25.5, one decimal).
        firmware_version: 0x12 firmware version (0.0..25.5, one decimal).
    """

    gear_ratio: float = 1.0
    torque_constant_nm_per_a: float = 0.1
    rotor_inertia_kgm2: float = 3.0e-5
    winding_resistance_ohm: float = 0.3
    pole_pairs: int = 14
    encoder_bits: int = 14
    current_limit_a: float = 16.0
    max_speed_dps: float = 720.0
    acceleration_dps2: int = 36_000
    pid: PidGains = field(default=DEFAULT_PID)
    tuned_inertia_kgm2: float | None = None
    supply_voltage_v: float = 24.0
    low_voltage_v: float = 18.0
    over_temperature_c: float = 80.0
    ambient_c: float = 25.0
    thermal_resistance_k_per_w: float = 2.0
    thermal_time_constant_s: float = 120.0
    shaft_zero_deg: float = 0.0
    encoder_offset: int = 0
    driver_name: str = "RMD-EMU"
    motor_name: str = "EMULATED"
    hardware_version: float = 1.0
    firmware_version: float = 1.0

    def __post_init__(self) -> None:
        _check(
            "DriveModel",
            (
                ("gear_ratio", "> 0", _positive(self.gear_ratio)),
                ("torque_constant_nm_per_a", "> 0", _positive(self.torque_constant_nm_per_a)),
                ("rotor_inertia_kgm2", ">= 0", _non_negative(self.rotor_inertia_kgm2)),
                ("winding_resistance_ohm", "> 0", _positive(self.winding_resistance_ohm)),
                ("pole_pairs", ">= 1", self.pole_pairs >= 1),
                ("encoder_bits", "12..18", 12 <= self.encoder_bits <= 18),
                (
                    "current_limit_a",
                    f"0 < x <= {HARDWARE_CURRENT_LIMIT_A:g}",
                    0 < self.current_limit_a <= HARDWARE_CURRENT_LIMIT_A,
                ),
                ("max_speed_dps", "> 0", _positive(self.max_speed_dps)),
                ("acceleration_dps2", f"0..{_ACCELERATION_MAX:g}", 0 <= self.acceleration_dps2 <= _ACCELERATION_MAX),
                ("tuned_inertia_kgm2", "None or > 0", self.tuned_inertia_kgm2 is None or self.tuned_inertia_kgm2 > 0),
                ("supply_voltage_v", ">= 0", _non_negative(self.supply_voltage_v)),
                ("thermal_resistance_k_per_w", "> 0", _positive(self.thermal_resistance_k_per_w)),
                ("thermal_time_constant_s", "> 0", _positive(self.thermal_time_constant_s)),
                ("shaft_zero_deg", "a finite number", math.isfinite(self.shaft_zero_deg)),
                ("encoder_offset", f"0..{_ENCODER_OFFSET_MAX:g}", 0 <= self.encoder_offset <= _ENCODER_OFFSET_MAX),
            ),
            self,
        )


@dataclass(frozen=True, slots=True)
class LoadModel:
    """The load one drive turns when the loads are independent (joint side).

    Attributes:
        inertia_kgm2: load inertia about the joint axis, kg·m², without the rotor.
        viscous_friction_nm_per_dps: viscous friction, N·m per joint deg/s.
        coulomb_friction_nm: Coulomb (dry) friction, N·m; also the breakaway torque.
        load_torque_nm: constant external torque on the joint (an unbalanced load), N·m.
        initial_deg: joint angle at start, degrees.
    """

    inertia_kgm2: float = 1.0e-3
    viscous_friction_nm_per_dps: float = 2.0e-4
    coulomb_friction_nm: float = 0.05
    load_torque_nm: float = 0.0
    initial_deg: float = 0.0

    def __post_init__(self) -> None:
        _check(
            "LoadModel",
            (
                ("inertia_kgm2", ">= 0", _non_negative(self.inertia_kgm2)),
                ("viscous_friction_nm_per_dps", ">= 0", _non_negative(self.viscous_friction_nm_per_dps)),
                ("coulomb_friction_nm", ">= 0", _non_negative(self.coulomb_friction_nm)),
                ("load_torque_nm", "a finite number", math.isfinite(self.load_torque_nm)),
                ("initial_deg", "a finite number", math.isfinite(self.initial_deg)),
            ),
            self,
        )
