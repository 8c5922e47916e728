"""``rmd-motion check --offline``: a configuration checked without hardware (issue 33 §3).

It loads the configuration and its model (URDF or chain) and, per joint, sets what the model asks against what the
drive can give:

- **hold**: the largest gravity torque the joint carries anywhere in the limits of every joint (sampled: every
  combination of each joint's lower limit, middle and upper limit, and :data:`RANDOM_POSES` poses drawn in the
  limits; :func:`kinematics.envelope.sampled_poses`), against the torque the drive gives at its current limit
  (``current_limit_a × torque_constant_nm_per_a ×
  gear_ratio``, at the joint);
- **stability** (every mode: torque mode's PD gains, checked where the mode is torque): the gain margin of each
  joint's PD at the configured rate and the lowest rate that keeps it (:mod:`motion.control.stability`);
- **move**: that gravity torque plus the torque to accelerate every joint at its configured acceleration limit at
  once, each in the direction that adds to the joint's load (``Σ_k |M_jk(q)| a_k`` with the rotors' inertia on the
  diagonal), at the worst sampled pose.

A joint that cannot hold itself up (hold above the torque available) is an error (exit 2); one whose hold takes more
than :data:`HOLD_WARNING_SHARE` of it, or that cannot move as configured, is a warning. With a program, the program is
validated against the configuration too.

Per joint also the encoder's **unwrapping** headroom (:func:`unwrapping`): the motor degrees per sample at the
velocity limit against half a turn, and the rates that unwrap it; a joint beyond the bound is an error (connect refuses
it too: :mod:`motion.control.unwrap`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Final

import numpy as np

from motion.config import ArmConfig
from motion.control.stability import StabilityError, StabilityReport
from motion.control.unwrap import UnwrapHeadroom, unwrap_headroom, unwrap_problems

#: A hold that takes more than this share of the torque available leaves too little for moving and for model error.
HOLD_WARNING_SHARE: Final = 0.8
#: kg·m² per unit of :func:`kinematics.mass_matrix` (N·m per deg/s²).
_KGM2_PER_DEG_UNIT: Final = 180.0 / math.pi


@dataclass(frozen=True)
class JointBudget:
    """One joint's torques, N·m at the joint, and the pose (degrees, every joint) where each is largest."""

    name: str
    available_nm: float
    hold_nm: float
    hold_pose_deg: tuple[float, ...]
    move_nm: float
    move_pose_deg: tuple[float, ...]

    @property
    def hold_share(self) -> float:
        return self.hold_nm / self.available_nm

    @property
    def move_share(self) -> float:
        return self.move_nm / self.available_nm


def budgets(config: ArmConfig) -> list[JointBudget]:
    """Every joint's :class:`JointBudget` (the module docstring).

    Raises:
        ConfigError: the model cannot be built (a URDF that Pinocchio cannot read or that does not match the joints).
    """
    from kinematics import build_arm  # noqa: PLC0415 - Pinocchio only where a check needs it
    from kinematics.dynamics import gravity_torque, mass_matrix  # noqa: PLC0415
    from kinematics.envelope import sampled_poses  # noqa: PLC0415

    arm = build_arm(config)
    joints = config.joints
    gear = np.array([j.gear_ratio for j in joints])
    available = np.array([j.current_limit_a * j.torque_constant_nm_per_a * j.gear_ratio for j in joints])
    # the rotors' inertia at the joint: the joint's rotor_inertia_kgm2, else its emulation's (the same drive)
    rotor = np.array([j.rotor_inertia_kgm2 or j.emulation.rotor_inertia_kgm2 for j in joints]) * gear**2
    acceleration = np.radians([j.acceleration_limit_dps2 for j in joints])
    hold = np.zeros(len(joints))
    move = np.zeros(len(joints))
    hold_at = np.zeros((len(joints), len(joints)))
    move_at = np.zeros((len(joints), len(joints)))
    for q in sampled_poses(config):
        g = np.abs(gravity_torque(arm, q))
        inertia = np.abs(mass_matrix(arm, q)) * _KGM2_PER_DEG_UNIT + np.diag(rotor)  # kg·m², for rad/s²
        total = g + inertia @ acceleration
        for better, best, at, value in ((g > hold, hold, hold_at, g), (total > move, move, move_at, total)):
            best[better] = value[better]
            at[better] = q
    return [
        JointBudget(j.name, float(available[i]), float(hold[i]), tuple(hold_at[i]), float(move[i]), tuple(move_at[i]))
        for i, j in enumerate(joints)
    ]


def problems(found: list[JointBudget]) -> tuple[list[str], list[str]]:
    """(errors, warnings) in words, naming the joint, the figures and what to change."""
    errors, warnings = [], []
    for b in found:
        pose = ", ".join(f"{q:.0f}" for q in b.hold_pose_deg)
        if b.hold_share > 1.0:
            errors.append(
                f"{b.name} cannot hold the arm up: gravity takes {b.hold_nm:.2f} N·m at the pose ({pose}) deg, the "
                f"drive gives {b.available_nm:.2f} N·m at its current limit (current_limit_a × "
                "torque_constant_nm_per_a × gear_ratio): check those keys and the model's masses"
            )
        elif b.hold_share > HOLD_WARNING_SHARE:
            warnings.append(
                f"{b.name} holds the arm with {b.hold_share:.0%} of what it gives ({b.hold_nm:.2f} of "
                f"{b.available_nm:.2f} N·m at ({pose}) deg): little is left for moving and for model error"
            )
        if b.hold_share <= 1.0 and b.move_share > 1.0:
            warnings.append(
                f"{b.name} cannot move the arm as configured: gravity and every joint at its acceleration limit take "
                f"{b.move_nm:.2f} N·m, the drive gives {b.available_nm:.2f} N·m: lower acceleration_limit_dps2 "
                "(of it or its neighbours) or move slower (speed_scale)"
            )
    return errors, warnings


def stability_rows(report: StabilityReport) -> list[tuple[str, ...]]:
    """The stability table's rows: joint, margin at the rate, the lowest rate that holds, the highest gains there."""
    rows: list[tuple[str, ...]] = []
    for m in report.joints:
        lowest = "none ≤ 1000 Hz" if math.isnan(m.lowest_rate_hz) else f"{m.lowest_rate_hz:.0f} Hz"
        margin = "∞" if math.isinf(m.margin) else f"{m.margin:.2f}"
        scale = m.gain_scale
        rows.append(
            (
                m.joint.name,
                margin,
                lowest,
                f"{m.joint.kp_nm_per_deg * scale:.3g}",
                f"{m.joint.kd_nm_per_dps * scale:.3g}",
            )
        )
    return rows


def stability_problems(config: ArmConfig, report: StabilityReport) -> list[str]:
    """Errors where the configured mode closes the loop on the host and a joint has no margin at its rate."""
    if not config.control.mode.traits.host_torque or not report.failing:
        return []
    return [str(StabilityError(config.source, report))]


def unwrapping(config: ArmConfig) -> tuple[list[UnwrapHeadroom], list[str]]:
    """Every joint's encoder unwrapping headroom at ``control.rate_hz`` (a bus whose ``protocol`` is ``auto`` counts
    as the older family's, whose encoders are unwrapped), and an error per joint beyond the bound."""
    found = unwrap_headroom(config)
    return found, unwrap_problems(found, config.control.rate_hz)


def unwrapping_rows(found: list[UnwrapHeadroom]) -> list[tuple[str, str, str, str]]:
    """The unwrapping table's rows: joint, motor degrees per sample at the velocity limit, its share of the bound, and
    the rates that unwrap it."""
    return [
        (h.name, "-", "-", "any (0x92 every cycle)")
        if h.reads_angle
        else (h.name, f"{h.motor_deg_per_sample:.1f}", f"{h.share:.0%}", f"above {h.lowest_rate_hz:.3g} Hz")
        for h in found
    ]
