"""The arm's links as a transform tree (what ROS tools call ``/tf``): each link's pose relative to its parent link at
given joint angles, from the arm's Pinocchio model (URDF or YAML chain), with the link names of the model.

A URDF's root link (the body fixed to the world, e.g. ``base_link``) is the tree's root and has no transform of its
own; a YAML chain has no root link, so its first link hangs from ``universe`` (Pinocchio's world frame). A
:class:`LinkFrames` owns its model data: one per thread.

Its :attr:`~LinkFrames.urdf` is what a viewer draws the arm from (``/robot_description``): the configuration's URDF,
with a sphere at each moving link's origin and a cylinder to each of its child joints (toward its centre of mass at a
tip) added to the links that have no ``<visual>`` of their own (the shapes the live view draws:
:mod:`kinematics.figure`); for a YAML chain, a URDF written from the chain, with those shapes.
"""

from __future__ import annotations

import math
from typing import Any, NamedTuple
from xml.etree import ElementTree

import numpy as np
import pinocchio as pin
from numpy.typing import NDArray

from kinematics.figure import ArmFigure
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
        urdf: the URDF a viewer draws the arm from (module docstring).
    """

    def __init__(self, config: ArmConfig) -> None:
        self._arm = build_arm(config)
        model = self._arm.model
        frames = model.frames
        body = pin.FrameType.BODY
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
        self.urdf = _described(config, model, ArmFigure(config).links)

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


#: The drawn shapes' radii, m.
JOINT_RADIUS_M = 0.025
LINK_RADIUS_M = 0.015


def _xyz(vector: Any) -> str:
    return " ".join(f"{float(v) + 0.0:.6g}" for v in vector)  # (+ 0.0: no "-0")


def _visuals(segments: tuple[FloatArray, ...]) -> list[ElementTree.Element]:
    """A sphere at the link's origin and a cylinder along each segment (URDF cylinders lie along their z axis)."""
    sphere = ElementTree.Element("visual")
    ElementTree.SubElement(ElementTree.SubElement(sphere, "geometry"), "sphere", radius=f"{JOINT_RADIUS_M:g}")
    out = [sphere]
    for end in segments:
        length = float(np.linalg.norm(end))
        if length < 1e-9:
            continue
        axis = np.asarray(end, dtype=np.float64) / length
        z = np.array([0.0, 0.0, 1.0])
        turn = np.cross(z, axis)
        sine, cosine = float(np.linalg.norm(turn)), float(axis @ z)
        if sine < 1e-12:
            rotation = np.eye(3) if cosine > 0 else np.diag([1.0, -1.0, -1.0])
        else:
            rotation = pin.AngleAxis(math.atan2(sine, cosine), turn / sine).matrix()
        visual = ElementTree.Element("visual")
        ElementTree.SubElement(visual, "origin", xyz=_xyz(axis * length / 2), rpy=_xyz(pin.rpy.matrixToRpy(rotation)))
        geometry = ElementTree.SubElement(visual, "geometry")
        ElementTree.SubElement(geometry, "cylinder", radius=f"{LINK_RADIUS_M:g}", length=f"{length:.6g}")
        out.append(visual)
    return out


def _described(config: ArmConfig, model: Any, links: tuple[tuple[FloatArray, ...], ...]) -> str:
    """The URDF a viewer draws (module docstring). ``links``: per model joint, its link's segments in its frame."""
    body = pin.FrameType.BODY
    link_of: dict[int, str] = {}  # model joint -> the name of the link it moves
    for frame in model.frames:
        if frame.type == body and int(frame.parentJoint) > 0:
            link_of.setdefault(int(frame.parentJoint), str(frame.name))
    if config.model.urdf is not None:
        robot = ElementTree.parse(str(config.model.urdf)).getroot()
        drawn = {name: j for j, name in link_of.items()}
        for link in robot.iter("link"):
            moved_by = drawn.get(link.get("name", ""))
            if moved_by is not None and link.find("visual") is None:
                link.extend(_visuals(links[moved_by - 1]))
        return ElementTree.tostring(robot, encoding="unicode")
    robot = ElementTree.Element("robot", name=config.name)
    ElementTree.SubElement(robot, "link", name=str(model.frames[0].name))
    joints = {joint.name: joint for joint in config.joints}
    for j in range(1, model.njoints):
        ElementTree.SubElement(robot, "link", name=link_of[j]).extend(_visuals(links[j - 1]))
        parent = int(model.parents[j])
        joint = ElementTree.SubElement(robot, "joint", name=str(model.names[j]), type="revolute")
        ElementTree.SubElement(joint, "parent", link=link_of[parent] if parent > 0 else str(model.frames[0].name))
        ElementTree.SubElement(joint, "child", link=link_of[j])
        placement = model.jointPlacements[j]
        ElementTree.SubElement(
            joint, "origin", xyz=_xyz(placement.translation), rpy=_xyz(pin.rpy.matrixToRpy(placement.rotation))
        )
        ElementTree.SubElement(joint, "axis", xyz=_xyz(model.joints[j].extract().axis))
        configured = joints[str(model.names[j])]  # (limits as configured: viewers offer sliders within them)
        low, high = math.radians(configured.position_min_deg), math.radians(configured.position_max_deg)
        speed = math.radians(configured.velocity_limit_dps)
        ElementTree.SubElement(
            joint, "limit", lower=f"{low:.6g}", upper=f"{high:.6g}", effort="0", velocity=f"{speed:.6g}"
        )
    return ElementTree.tostring(robot, encoding="unicode")
