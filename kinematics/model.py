"""The arm's Pinocchio model, built once from a validated :class:`~motion.config.ArmConfig`."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any
from xml.etree import ElementTree

import numpy as np
import pinocchio as pin
from numpy.typing import NDArray

from motion.config import ArmConfig
from motion.errors import ConfigError

IndexArray = NDArray[np.intp]


@dataclass(frozen=True, slots=True, eq=False)
class ArmModel:
    """A Pinocchio model and its one ``data``, with the mapping between configuration and model joint order.

    The functions of :mod:`kinematics.dynamics` take and return arrays in configuration joint order; Pinocchio's
    order (the URDF tree order) may differ and is matched by joint name. ``data`` is scratch space reused by every
    call, so an ArmModel must not be shared between threads (build one per thread).

    Attributes:
        name: arm name.
        joint_names: joint names in configuration order.
        model: the ``pinocchio.Model`` (radians, SI units).
        data: the ``pinocchio.Data`` created once from ``model``.
        to_model: for each model coordinate, the index of its configuration joint.
        to_config: for each configuration joint, the index of its model coordinate.
        source: the configuration file, for error messages.
    """

    name: str
    joint_names: tuple[str, ...]
    model: Any
    data: Any
    to_model: IndexArray
    to_config: IndexArray
    source: str


def build_arm(config: ArmConfig) -> ArmModel:
    """Build the model from ``config.model`` (URDF or YAML chain) with the configured gravity vector.

    Raises:
        ConfigError: Pinocchio cannot read the URDF, or its joints do not match the configured joints.
    """
    model = _from_urdf(config) if config.model.urdf is not None else _from_chain(config)
    model.gravity = pin.Motion(np.array(config.model.gravity_m_s2, dtype=np.float64), np.zeros(3))
    to_config = []
    for i, name in enumerate(config.joint_names):
        joint_id = model.getJointId(name) if model.existJointName(name) else None
        if joint_id is None or model.joints[joint_id].nq != 1 or model.joints[joint_id].nv != 1:
            raise ConfigError(config.source, f"joints[{i}].name", f"{name!r} is not a revolute joint of the model")
        to_config.append(model.joints[joint_id].idx_q)
    if model.nq != len(to_config) or model.nv != len(to_config):
        raise ConfigError(
            config.source, "model", f"the model has {model.nv} degrees of freedom, {len(to_config)} joints configured"
        )
    to_config_array = np.array(to_config, dtype=np.intp)
    to_model_array = np.argsort(to_config_array)
    to_config_array.flags.writeable = to_model_array.flags.writeable = False
    return ArmModel(
        name=config.name,
        joint_names=config.joint_names,
        model=model,
        data=model.createData(),
        to_model=to_model_array,
        to_config=to_config_array,
        source=config.source,
    )


def _from_urdf(config: ArmConfig) -> Any:
    _check_urdf(config)
    try:
        return pin.buildModelFromUrdf(str(config.model.urdf))
    except (ValueError, RuntimeError) as exc:
        raise ConfigError(config.source, "model.urdf", f"Pinocchio cannot build a model from it: {exc}") from None


def _check_urdf(config: ArmConfig) -> None:
    """What Pinocchio builds a model from without a word but no arm has: a link of negative (or not finite) mass or
    inertia moment, a moving joint whose axis is the zero vector (the ``chain:`` form refuses both when it loads).

    Raises:
        ConfigError: naming ``model.urdf``, the link or joint and the value.
    """
    source, key = config.source, "model.urdf"
    try:
        root = ElementTree.parse(str(config.model.urdf)).getroot()
    except (OSError, ElementTree.ParseError) as exc:
        raise ConfigError(source, key, f"cannot read it as XML: {exc}") from None

    def numbers(element: ElementTree.Element, attribute: str, what: str) -> list[float]:
        text = element.get(attribute, "")
        try:
            return [float(v) for v in text.split()]
        except ValueError:
            raise ConfigError(source, key, f"{what}: {attribute}={text!r} is not a list of numbers") from None

    for link in root.iter("link"):
        name = link.get("name", "?")
        for mass in link.iterfind("inertial/mass"):
            value = numbers(mass, "value", f"link {name!r} mass")
            if len(value) != 1 or not (math.isfinite(value[0]) and value[0] >= 0):
                raise ConfigError(source, key, f"link {name!r}: mass {mass.get('value')!r} kg (valid: a number >= 0)")
        for inertia in link.iterfind("inertial/inertia"):
            for moment in ("ixx", "iyy", "izz"):
                value = numbers(inertia, moment, f"link {name!r} inertia")
                if len(value) != 1 or not (math.isfinite(value[0]) and value[0] >= 0):
                    raise ConfigError(
                        source, key, f"link {name!r}: inertia {moment}={inertia.get(moment)!r} kg·m² (valid: >= 0)"
                    )
    for joint in root.iter("joint"):
        if joint.get("type") not in ("revolute", "continuous", "prismatic"):
            continue
        name = joint.get("name", "?")
        for axis in joint.iterfind("axis"):
            xyz = numbers(axis, "xyz", f"joint {name!r} axis")
            if len(xyz) != 3 or not all(map(math.isfinite, xyz)) or not any(xyz):
                raise ConfigError(
                    source, key, f"joint {name!r}: axis {axis.get('xyz')!r} (valid: three numbers, not all zero)"
                )


def _from_chain(config: ArmConfig) -> Any:
    model = pin.Model()
    model.name = config.name
    parent_joint, frame = 0, 0
    for link in config.model.chain:
        placement = pin.SE3(pin.rpy.rpyToMatrix(np.array(link.origin_rpy_rad)), np.array(link.origin_xyz_m))
        joint_model = pin.JointModelRevoluteUnaligned(np.array(link.axis, dtype=np.float64))
        joint = model.addJoint(parent_joint, joint_model, placement, link.joint)
        inertia = pin.Inertia(link.mass_kg, np.array(link.com_xyz_m), np.array(link.inertia_kgm2.matrix()))
        model.appendBodyToJoint(joint, inertia, pin.SE3.Identity())
        frame = model.addJointFrame(joint, frame)
        frame = model.addBodyFrame(link.link_name, joint, pin.SE3.Identity(), frame)
        parent_joint = joint
    if config.model.tip_xyz_m is not None:
        tip = pin.SE3(np.eye(3), np.array(config.model.tip_xyz_m))
        model.addFrame(pin.Frame("tip", parent_joint, frame, tip, pin.FrameType.OP_FRAME))
    return model
