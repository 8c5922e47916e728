"""The arm's links as a transform tree (what ROS tools call ``/tf``): each link's pose relative to its parent link at
given joint angles, from the arm's Pinocchio model (URDF or YAML chain), with the link names of the model.

A URDF's root link (the body fixed to the world, e.g. ``base_link``) is the tree's root and has no transform of its
own; a YAML chain has no root link, so its first link hangs from ``universe`` (Pinocchio's world frame). A
:class:`LinkFrames` owns its model data: one per thread.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import pinocchio as pin
from numpy.typing import NDArray

from kinematics.model import build_arm
from motion.config import ArmConfig

FloatArray = NDArray[np.float64]


class LinkTransform(NamedTuple):
    """One link's pose in its parent link's frame."""

    parent: str
    child: str
    translation_m: tuple[float, float, float]
    rotation_xyzw: tuple[float, float, float, float]


class LinkFrames:
    """Link transforms of one arm (see the module docstring).

    Attributes:
        root: the name of the tree's root frame.
        urdf: the URDF's text, or None for a YAML chain.
    """

    def __init__(self, config: ArmConfig) -> None:
        self._arm = build_arm(config)
        model = self._arm.model
        frames = model.frames
        body = pin.FrameType.BODY
        self.urdf = None if config.model.urdf is None else config.model.urdf.read_text()
        self.root = str(frames[0].name)
        links: list[tuple[int, int]] = []  # (frame, its parent link's frame; 0: the world)
        for f in range(1, len(frames)):
            if frames[f].type != body:
                continue
            parent = int(frames[f].parentFrame)
            while parent != 0 and frames[parent].type != body:
                parent = int(frames[parent].parentFrame)
            if parent == 0 and int(frames[f].parentJoint) == 0 and self.root == str(frames[0].name):
                self.root = str(frames[f].name)  # the URDF's root link: fixed to the world
                continue
            links.append((f, parent))
        root_frame = int(model.getFrameId(self.root)) if self.root != str(frames[0].name) else 0
        self._links = [(f, root_frame if p == 0 else p) for f, p in links]
        self._names = [str(frame.name) for frame in frames]
        self._q = np.zeros(model.nq)

    @property
    def names(self) -> list[str]:
        """The child link of each transform, in the order :meth:`transforms` gives them."""
        return [self._names[f] for f, _ in self._links]

    def transforms(self, q_deg: FloatArray) -> list[LinkTransform]:
        """Every link's pose in its parent's frame at the joint angles ``q_deg`` (configuration order, deg)."""
        arm = self._arm
        self._q[arm.to_config] = np.radians(q_deg)
        pin.framesForwardKinematics(arm.model, arm.data, self._q)
        placements = arm.data.oMf
        out = []
        for f, parent in self._links:
            local = placements[parent].actInv(placements[f])
            quaternion = pin.Quaternion(local.rotation)
            t = local.translation
            out.append(
                LinkTransform(
                    self._names[parent],
                    self._names[f],
                    (float(t[0]), float(t[1]), float(t[2])),
                    (float(quaternion.x), float(quaternion.y), float(quaternion.z), float(quaternion.w)),
                )
            )
        return out
