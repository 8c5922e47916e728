"""The arm drawn on the page: from its Pinocchio model (a sphere per joint, a cylinder per link segment) or from its
URDF's visual meshes (see :mod:`motion.view`)."""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from pathlib import Path
from typing import Any, Protocol

import numpy as np
from numpy.typing import NDArray

from motion.config import ArmConfig

FloatArray = NDArray[np.float64]


def _z_to(direction: FloatArray) -> FloatArray:
    """The rotation (w, x, y, z) that turns +z into ``direction`` (a unit vector)."""
    z = np.array([0.0, 0.0, 1.0])
    axis = np.cross(z, direction)
    s, c = float(np.linalg.norm(axis)), float(np.dot(z, direction))
    if s < 1e-9:
        return np.array([1.0, 0.0, 0.0, 0.0]) if c > 0 else np.array([0.0, 1.0, 0.0, 0.0])
    angle = math.atan2(s, c)
    return np.array([math.cos(angle / 2), *(axis / s * math.sin(angle / 2))])


def _has_visuals(config: ArmConfig) -> bool:
    urdf = config.model.urdf
    if urdf is None:
        return False
    try:
        return ET.parse(urdf).getroot().find(".//visual") is not None
    except (OSError, ET.ParseError):
        return False


class ArmGeometry(Protocol):
    """The arm's shape for drawing (:class:`kinematics.figure.ArmFigure`, built by :func:`motion.compose.arm_figure`;
    this module never builds the model itself)."""

    links: tuple[tuple[FloatArray, ...], ...]
    reach: float
    up: FloatArray

    def placements(self, q_deg: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Every joint's origin (J×3) and orientation (J×4, w x y z) at ``q_deg``."""
        ...


class _StickFigure:
    """The arm from its model: a sphere per joint, a cylinder per link segment (see the module docstring)."""

    def __init__(
        self, server: Any, geometry: ArmGeometry, name: str, rgb: tuple[int, int, int], opacity: float | None
    ) -> None:
        self._geometry = geometry
        radius = min(max(0.04 * geometry.reach, 0.005), 0.05)
        looks = {"color": rgb, "opacity": opacity, "cast_shadow": False, "receive_shadow": False}
        self._nodes = []
        for j, ends in enumerate(geometry.links):
            node = server.scene.add_frame(f"/{name}/joint{j}", show_axes=False)
            self._nodes.append(node)
            server.scene.add_icosphere(f"/{name}/joint{j}/hub", radius=1.4 * radius, subdivisions=1, **looks)
            for k, end in enumerate(ends):
                length = float(np.linalg.norm(end))
                server.scene.add_cylinder(
                    f"/{name}/joint{j}/link{k}",
                    radius=radius,
                    height=length,
                    radial_segments=12,
                    wxyz=_z_to(end / length),
                    position=end / 2,
                    **looks,
                )

    def pose(self, q_deg: FloatArray) -> None:
        """Place the figure at the joint angles ``q_deg`` (configuration order, deg)."""
        if not np.isfinite(q_deg).all():
            return
        positions, quaternions = self._geometry.placements(q_deg)
        for node, position, wxyz in zip(self._nodes, positions, quaternions, strict=True):
            node.position = position
            node.wxyz = wxyz


class _UrdfFigure:
    """The arm from its URDF's visual meshes (yourdfpy, through viser's URDF helper)."""

    def __init__(self, server: Any, config: ArmConfig, name: str, rgb: tuple[int, int, int], opacity: float | None):
        from viser.extras import ViserUrdf  # noqa: PLC0415 - as viser

        assert config.model.urdf is not None
        red, green, blue = (c / 255 for c in rgb)
        color = None if opacity is None else (red, green, blue, opacity)
        self._urdf = ViserUrdf(server, Path(config.model.urdf), root_node_name=f"/{name}", mesh_color_override=color)
        actuated = list(self._urdf.get_actuated_joint_names())
        index = {joint: i for i, joint in enumerate(config.joint_names)}
        self._order = np.array([index[joint] for joint in actuated], dtype=np.intp)

    def pose(self, q_deg: FloatArray) -> None:
        """Place the figure at the joint angles ``q_deg`` (configuration order, deg)."""
        if np.isfinite(q_deg).all():
            self._urdf.update_cfg(np.radians(q_deg[self._order]))


def frame_the_arm(server: Any, geometry: ArmGeometry) -> None:
    """Up against gravity, a floor grid and a camera that sees the whole arm (its reach at the zero pose)."""
    reach, up = 1.3 * geometry.reach, geometry.up
    server.scene.set_up_direction(tuple(up))
    side = np.cross(up, [1.0, 0.0, 0.0] if abs(up[0]) < 0.9 else [0.0, 1.0, 0.0])
    side /= np.linalg.norm(side)
    server.initial_camera.position = tuple(2.2 * reach * side + 1.2 * reach * up + 0.8 * reach * np.cross(side, up))
    server.initial_camera.look_at = tuple(0.3 * reach * up)
    plane = {0: "yz", 1: "xz", 2: "xy"}[int(np.argmax(np.abs(up)))]
    server.scene.add_grid("/grid", width=2 * reach, height=2 * reach, cell_size=reach / 10, plane=plane)


def new_figure(
    server: Any,
    *,
    config: ArmConfig,
    geometry: ArmGeometry,
    name: str,
    rgb: tuple[int, int, int],
    opacity: float | None,
) -> Any:
    """The arm's figure ``name``: from its URDF's meshes where it has visuals, else from its model."""
    if _has_visuals(config):
        return _UrdfFigure(server, config, name, rgb, opacity)
    return _StickFigure(server, geometry, name, rgb, opacity)
