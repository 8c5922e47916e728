"""The arm's shape for drawing it (the live view, :mod:`motion.view`): joint placements and link segments.

Built from the arm's Pinocchio model (URDF or YAML chain): per model joint the segments of its link, from the joint's
origin to each child joint's origin (at a tip, toward the link's centre of mass), in the joint's own frame; and, for
joint angles in configuration order, every joint's placement in the base frame. An :class:`ArmFigure` owns its model
data: one per thread (the view's, never the control loop's).
"""

from __future__ import annotations

import numpy as np
import pinocchio as pin
from numpy.typing import NDArray

from kinematics.model import build_arm
from motion.config import ArmConfig

FloatArray = NDArray[np.float64]

#: A link reaching less far than this is drawn as a stub of this length along the joint's z axis, m.
MIN_LINK_M = 0.05


class ArmFigure:
    """Joint placements and link segments of one arm (see the module docstring).

    Attributes:
        links: per model joint (base to tip, Pinocchio's order), the end points of its link segments in its frame, m.
        reach: the farthest joint origin from the base at the zero pose (at least :data:`MIN_LINK_M`), m.
        up: the unit vector against gravity (z when gravity is zero).
    """

    def __init__(self, config: ArmConfig) -> None:
        self._arm = build_arm(config)
        model = self._arm.model
        children: list[list[FloatArray]] = [[] for _ in range(model.njoints)]
        for j in range(1, model.njoints):
            parent = int(model.parents[j])
            if parent > 0:
                children[parent].append(np.array(model.jointPlacements[j].translation, dtype=np.float64))
        self._q = np.zeros(model.nq)
        positions, _ = self.placements(np.zeros(len(config.joints)))
        self.reach = max(MIN_LINK_M, *(float(np.linalg.norm(p)) for p in positions))
        self.links = tuple(tuple(children[j] or [self._tip(model, j)]) for j in range(1, model.njoints))
        gravity = np.array(config.model.gravity_m_s2, dtype=np.float64)
        norm = float(np.linalg.norm(gravity))
        self.up: FloatArray = -gravity / norm if norm > 0 else np.array([0.0, 0.0, 1.0])

    @staticmethod
    def _tip(model: object, joint: int) -> FloatArray:
        lever = np.array(model.inertias[joint].lever, dtype=np.float64)  # type: ignore[attr-defined]
        return 2.0 * lever if np.linalg.norm(lever) > MIN_LINK_M / 10 else np.array([0.0, 0.0, MIN_LINK_M])

    def placements(self, q_deg: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Every joint's origin (J×3, m) and orientation (J×4 quaternions w, x, y, z) in the base frame at the joint
        angles ``q_deg`` (configuration order, deg)."""
        arm = self._arm
        self._q[arm.to_config] = np.radians(q_deg)
        pin.forwardKinematics(arm.model, arm.data, self._q)
        frames = arm.data.oMi[1:]
        positions = np.array([np.array(m.translation) for m in frames])
        quaternions = np.array([_wxyz(pin.Quaternion(m.rotation)) for m in frames])
        return positions, quaternions


def _wxyz(q: pin.Quaternion) -> FloatArray:
    return np.array([q.w, q.x, q.y, q.z])
