"""The arm's inertia across its joint limits: what each joint sees at its lightest and at its heaviest.

A torque-mode PD is least stable where the joint is lightest, and least damped where it is heaviest
(:mod:`motion.control.stability`). Both come from the mass matrix M(q) sampled over the limits (:func:`sampled_poses`:
every combination of each joint's lower limit, middle and upper limit up to :data:`GRID_JOINTS` joints, and
:data:`RANDOM_POSES` poses drawn in the limits, the same on every run):

- the lightest is ``1 / (M⁻¹)ᵢᵢ``: the inertia the joint sees with every other joint free to move (the coupling: a
  torque on the joint also moves the others, so it sees less than its diagonal), the model's masses and the rotors'
  reflected inertia (``gear_ratio² × rotor_inertia_kgm2``) each at a share of its figure (their stated bounds);
- the heaviest is the diagonal ``Mᵢᵢ``, the rotor's at its figure.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass
from typing import Final

import numpy as np

from kinematics.dynamics import mass_matrix
from kinematics.model import ArmModel
from motion.config import ArmConfig

#: Random poses sampled besides the grid.
RANDOM_POSES: Final = 2000
#: A grid of every joint's lower limit, middle and upper limit is sampled up to this many joints (3^n poses).
GRID_JOINTS: Final = 7
#: The seed of the sampled poses (the same figures on every run).
SEED: Final = 33
#: kg·m² per (N·m per deg/s²): :func:`kinematics.mass_matrix` is per degree.
_SI_PER_DEG_UNITS: Final = 180.0 / math.pi


def sampled_poses(config: ArmConfig, random_poses: int = RANDOM_POSES) -> np.ndarray:
    """The sampled poses, degrees: one row per pose, one column per joint."""
    lo = np.array([j.position_min_deg for j in config.joints])
    hi = np.array([j.position_max_deg for j in config.joints])
    rows = [np.random.default_rng(SEED).uniform(lo, hi, size=(random_poses, len(lo)))]
    if len(lo) <= GRID_JOINTS:
        levels = np.stack([lo, (lo + hi) / 2.0, hi])  # (3, n)
        rows.append(
            np.array([levels[list(pick), range(len(lo))] for pick in itertools.product(range(3), repeat=len(lo))])
        )
    return np.vstack(rows)


@dataclass(frozen=True)
class InertiaEnvelope:
    """Per joint (configuration order), kg·m² at the joint.

    Attributes:
        low_kgm2: the smallest inertia the joint sees (``1 / (M⁻¹)ᵢᵢ``, the rotor's at its low bound).
        high_kgm2: the largest (``Mᵢᵢ``, the rotor's at its figure).
        low_pose_deg: where each low is found, degrees (every joint), one row per joint.
    """

    low_kgm2: np.ndarray
    high_kgm2: np.ndarray
    low_pose_deg: np.ndarray


def inertia_envelope(
    arm: ArmModel, config: ArmConfig, *, mass_low: float, rotor_low: float, random_poses: int = RANDOM_POSES
) -> InertiaEnvelope:
    """The :class:`InertiaEnvelope` of ``config`` over :func:`sampled_poses` (``mass_low``, ``rotor_low``: the
    model's rigid-body inertia and the rotors' at their low bounds, as factors on their figures)."""
    gear = np.array([j.gear_ratio for j in config.joints])
    rotor = np.array([j.rotor_inertia_kgm2 for j in config.joints]) * gear**2
    n = len(config.joints)
    low = np.full(n, np.inf)
    high = np.zeros(n)
    low_at = np.zeros((n, n))
    for q in sampled_poses(config, random_poses):
        rigid = mass_matrix(arm, q) * _SI_PER_DEG_UNITS
        seen = 1.0 / np.diag(np.linalg.inv(mass_low * rigid + np.diag(rotor_low * rotor)))
        lighter = seen < low
        low[lighter] = seen[lighter]
        low_at[lighter] = q
        high = np.maximum(high, np.diag(rigid) + rotor)
    return InertiaEnvelope(low, high, low_at)
