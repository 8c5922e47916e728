"""Drawn drive models: emulated drives that differ from the configuration's model the way real ones do, for the
property tests and explorers that must hold on drives we did not tune for.

A :class:`DriveDraw` scales, per joint, what the emulator's drive and plant take from the configuration's
``emulation`` block: the drive's loop tuning (its position and speed loop gains, as a factor on the factory gains),
its true torque constant, the rotor inertia and the joint's friction (viscous and Coulomb together), plus the drives'
reply latency. The ranges are the model error the controller must bear (issue 30: inertia ±30 %, friction ±50 %,
torque constant ±20 %), loop tuning from half to twice the factory's, and a reply latency from the emulator's
0.2 ms up to 1 ms.
"""

from __future__ import annotations

import dataclasses
import math
import random
from dataclasses import dataclass

from motion.config import ArmConfig
from motion.config.schema import EmulatedPidConfig
from motion.emulator import DEFAULT_PID
from motion.emulator.timing import DEFAULT_LATENCY_S

#: Loop gains as a factor on the factory's (drawn log-uniformly).
GAIN_RANGE = (0.5, 2.0)
#: The true torque constant as a factor on the configured one.
TORQUE_CONSTANT_RANGE = (0.8, 1.2)
#: Rotor inertia as a factor on the configured one.
INERTIA_RANGE = (0.7, 1.3)
#: Viscous and Coulomb friction as a factor on the configured ones.
FRICTION_RANGE = (0.5, 1.5)
#: The drives' reply latency, s.
LATENCY_RANGE_S = (DEFAULT_LATENCY_S, 0.001)
#: The largest value of a gain in 0x30 units (one byte).
_GAIN_MAX = 255


@dataclass(frozen=True)
class JointDraw:
    """One joint's drive: factors on the configured figures (1.0: as configured)."""

    gain: float = 1.0
    torque_constant: float = 1.0
    inertia: float = 1.0
    friction: float = 1.0


@dataclass(frozen=True)
class DriveDraw:
    """Every joint's drive (in the configuration's joint order) and the drives' reply latency, s."""

    joints: tuple[JointDraw, ...]
    latency_s: float = DEFAULT_LATENCY_S

    def describe(self) -> str:
        """The draw as a Python literal."""
        rows = ", ".join(
            f"JointDraw({j.gain!r}, {j.torque_constant!r}, {j.inertia!r}, {j.friction!r})" for j in self.joints
        )
        return f"DriveDraw(({rows},), latency_s={self.latency_s!r})"


def draw_drives(rng: random.Random, joints: int) -> DriveDraw:
    """Drives for ``joints`` joints, each drawn on its own within the ranges above (3 significant figures)."""

    def uniform(bounds: tuple[float, float]) -> float:
        return float(f"{rng.uniform(*bounds):.3g}")

    low, high = (math.log(b) for b in GAIN_RANGE)
    drawn = tuple(
        JointDraw(
            gain=float(f"{math.exp(rng.uniform(low, high)):.3g}"),
            torque_constant=uniform(TORQUE_CONSTANT_RANGE),
            inertia=uniform(INERTIA_RANGE),
            friction=uniform(FRICTION_RANGE),
        )
        for _ in range(joints)
    )
    return DriveDraw(drawn, latency_s=uniform(LATENCY_RANGE_S))


def with_drives(config: ArmConfig, drives: DriveDraw) -> ArmConfig:
    """``config`` whose emulated drives are ``drives`` (the controller's model, the joints' own figures, unchanged)."""
    if len(drives.joints) != len(config.joints):
        raise ValueError(f"{len(drives.joints)} drawn drives for an arm of {len(config.joints)} joints")
    joints = []
    for joint, draw in zip(config.joints, drives.joints, strict=True):
        emulation = joint.emulation

        def scaled(name: str, draw: JointDraw = draw, emulation: object = emulation.pid) -> int:
            configured = getattr(emulation, name)
            base = int(getattr(DEFAULT_PID, name) if configured is None else configured)
            return max(1, min(_GAIN_MAX, round(base * draw.gain)))

        pid = EmulatedPidConfig(
            angle_kp=scaled("angle_kp"),
            angle_ki=scaled("angle_ki"),
            speed_kp=scaled("speed_kp"),
            speed_ki=scaled("speed_ki"),
            iq_kp=emulation.pid.iq_kp,
            iq_ki=emulation.pid.iq_ki,
        )
        true_kt = emulation.torque_constant_nm_per_a or joint.torque_constant_nm_per_a
        emulated = dataclasses.replace(
            emulation,
            pid=pid,
            torque_constant_nm_per_a=true_kt * draw.torque_constant,
            rotor_inertia_kgm2=emulation.rotor_inertia_kgm2 * draw.inertia,
            viscous_friction_nm_per_dps=emulation.viscous_friction_nm_per_dps * draw.friction,
            coulomb_friction_nm=emulation.coulomb_friction_nm * draw.friction,
        )
        joints.append(dataclasses.replace(joint, emulation=emulated))
    return dataclasses.replace(config, joints=tuple(joints))
