"""The joint names of a URDF file, read with the standard library.

The configuration is validated against the URDF before any port is opened and without importing Pinocchio;
:mod:`kinematics` builds the full model from the same file.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from pathlib import Path


def revolute_joints(path: Path) -> list[str]:
    """Names of the revolute joints of a URDF file, in document order (fixed joints are skipped).

    Raises:
        ValueError: the file is not readable XML with a ``<robot>`` root, a joint has no name, or a joint is
            neither revolute nor fixed (continuous, prismatic, floating and planar joints are not supported:
            Pinocchio gives continuous joints two coordinates, and the others are not driven by a rotary drive).
    """
    try:
        root = ET.parse(path).getroot()
    except ET.ParseError as exc:
        raise ValueError(f"{path} is not valid XML: {exc}") from None
    except OSError as exc:
        raise ValueError(f"cannot read {path}: {exc}") from None
    if root.tag != "robot":
        raise ValueError(f"{path}: the root element is <{root.tag}>, a URDF needs <robot>")
    names: list[str] = []
    for joint in root.findall("joint"):  # direct children only: <transmission> also holds <joint> elements
        name, kind = joint.get("name"), joint.get("type")
        if not name:
            raise ValueError(f"{path}: a <joint> has no name")
        if kind == "revolute":
            names.append(name)
        elif kind != "fixed":
            raise ValueError(f"{path}: joint {name!r} has type {kind!r}; supported types: revolute, fixed")
    return names
