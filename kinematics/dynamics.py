"""Gravity, inverse and forward dynamics, mass matrix and forward kinematics of an :class:`ArmModel`.

Free functions over a model built once (Pinocchio's shape). The public API works in joint **degrees**: angles in
deg, speeds in deg/s, accelerations in deg/s², torques in N·m, arrays of one value per joint in configuration joint
order. Conversion to Pinocchio's radians and joint order happens inside.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import pinocchio as pin
from numpy.typing import ArrayLike, NDArray

from kinematics.model import ArmModel
from motion.errors import ConfigError

FloatArray = NDArray[np.float64]
#: Joint torques in N·m from joint angles (deg), speeds (deg/s) and accelerations (deg/s²).
FeedForward = Callable[[FloatArray, FloatArray, FloatArray], FloatArray]


@dataclass(frozen=True, slots=True, eq=False)
class FramePose:
    """Placement of a frame in the base (world) frame.

    Attributes:
        position_m: origin of the frame, in metres (shape (3,)).
        rotation: rotation matrix from the frame to the base frame (shape (3, 3)).
    """

    position_m: FloatArray
    rotation: FloatArray


def _model_order(arm: ArmModel, values: ArrayLike, name: str, to_radians: bool = True) -> FloatArray:
    """One value per configured joint -> a new array in model order, in radians if asked."""
    array = np.asarray(values, dtype=np.float64)
    if array.shape != arm.to_model.shape:
        raise ValueError(f"{name}: expected shape {arm.to_model.shape} (one value per joint), got {array.shape}")
    ordered = array[arm.to_model]
    return np.deg2rad(ordered, out=ordered) if to_radians else ordered


def gravity_torque(arm: ArmModel, q_deg: ArrayLike) -> FloatArray:
    """Joint torques in N·m that hold the arm still against gravity at ``q_deg``: g(q)."""
    q = _model_order(arm, q_deg, "q_deg")
    tau: FloatArray = pin.computeGeneralizedGravity(arm.model, arm.data, q)[arm.to_config]
    return tau


def rnea(arm: ArmModel, q_deg: ArrayLike, qd_dps: ArrayLike, qdd_dps2: ArrayLike) -> FloatArray:
    """Inverse dynamics: joint torques in N·m for angles (deg), speeds (deg/s) and accelerations (deg/s²).

    ``rnea(q, qd, qdd) = M(q)·qdd + C(q, qd)·qd + g(q)``.
    """
    q = _model_order(arm, q_deg, "q_deg")
    v = _model_order(arm, qd_dps, "qd_dps")
    a = _model_order(arm, qdd_dps2, "qdd_dps2")
    tau: FloatArray = pin.rnea(arm.model, arm.data, q, v, a)[arm.to_config]
    return tau


def aba(arm: ArmModel, q_deg: ArrayLike, qd_dps: ArrayLike, tau_nm: ArrayLike) -> FloatArray:
    """Forward dynamics: joint accelerations in deg/s² under joint torques ``tau_nm`` (N·m) at angles (deg) and
    speeds (deg/s). The inverse of :func:`rnea` for the same q and qd."""
    q = _model_order(arm, q_deg, "q_deg")
    v = _model_order(arm, qd_dps, "qd_dps")
    tau = _model_order(arm, tau_nm, "tau_nm", to_radians=False)
    qdd: FloatArray = pin.aba(arm.model, arm.data, q, v, tau)[arm.to_config]
    return np.rad2deg(qdd, out=qdd)


def _crba_fills_lower_triangle() -> bool:
    """Whether this Pinocchio's ``crba`` returns all of M (4.1 does) or only its upper triangle (older releases; pin
    2.7 and later is what pyproject allows). Asked once, of Pinocchio's sample manipulator. Exit plan: once pyproject
    requires a release that fills M, drop this and :func:`crba_full`'s symmetrising branch."""
    model = pin.buildSampleModelManipulator()
    mass = pin.crba(model, model.createData(), pin.neutral(model) + 0.5)
    return bool(np.abs(np.tril(mass, -1)).max() > 0.0)


_CRBA_FULL = _crba_fills_lower_triangle()


def crba_full(model: pin.Model, data: pin.Data, q: FloatArray) -> FloatArray:
    """M(q) in model order and SI units, every entry filled (Pinocchio's own array when it fills them)."""
    mass: FloatArray = pin.crba(model, data, q)
    if not _CRBA_FULL:
        mass = np.triu(mass) + np.triu(mass, 1).T
    return mass


def mass_matrix(arm: ArmModel, q_deg: ArrayLike) -> FloatArray:
    """Joint-space inertia matrix M(q) in N·m per deg/s² (kg·m² × π/180), so that ``M @ qdd_dps2`` is N·m."""
    q = _model_order(arm, q_deg, "q_deg")
    full = crba_full(arm.model, arm.data, q)
    result: FloatArray = full[np.ix_(arm.to_config, arm.to_config)] * (math.pi / 180.0)
    return result


def frame_names(arm: ArmModel) -> tuple[str, ...]:
    """Names of the model's frames (links, joints, ``tip`` or URDF frames), without the world frame."""
    return tuple(f.name for f in arm.model.frames if f.name != "universe")


def frame_pose(arm: ArmModel, frame: str, q_deg: ArrayLike) -> FramePose:
    """Forward kinematics: placement of the named frame in the base frame at joint angles ``q_deg``.

    Raises:
        ConfigError: the model has no frame of that name.
    """
    if not arm.model.existFrame(frame):
        raise ConfigError(arm.source, "frame", f"no frame {frame!r}; frames: {', '.join(frame_names(arm))}")
    frame_id = arm.model.getFrameId(frame)
    pin.framesForwardKinematics(arm.model, arm.data, _model_order(arm, q_deg, "q_deg"))
    placement = arm.data.oMf[frame_id]
    return FramePose(position_m=placement.translation.copy(), rotation=placement.rotation.copy())


class _ArmFeedForward:
    """The callable :func:`feedforward` returns for gravity and / or inertia (the arguments in model order and
    radians: a fancy index and one multiply each, cheaper on a few joints than filling arrays of its own)."""

    __slots__ = ("_arm", "_gravity", "_inertia")

    def __init__(self, arm: ArmModel, *, gravity: bool, inertia: bool) -> None:
        self._arm, self._gravity, self._inertia = arm, gravity, inertia

    def __call__(self, q_deg: FloatArray, qd_dps: FloatArray, qdd_dps2: FloatArray) -> FloatArray:
        arm = self._arm
        q = _model_order(arm, q_deg, "q_deg")
        if not self._inertia:
            gravity: FloatArray = pin.computeGeneralizedGravity(arm.model, arm.data, q)[arm.to_config]
            return gravity
        v = _model_order(arm, qd_dps, "qd_dps")
        a = _model_order(arm, qdd_dps2, "qdd_dps2")
        tau: FloatArray = pin.rnea(arm.model, arm.data, q, v, a)[arm.to_config]
        if not self._gravity:
            tau -= pin.computeGeneralizedGravity(arm.model, arm.data, q)[arm.to_config]
        return tau


def feedforward(arm: ArmModel, *, gravity: bool = True, inertia: bool = False) -> FeedForward:
    """A feed-forward callable ``(q_deg, qd_dps, qdd_dps2) -> tau_nm`` for the controller.

    Args:
        arm: the model (the callable keeps it; use it from one thread).
        gravity: include the gravity torque g(q).
        inertia: include the inertial and Coriolis torques M(q)·qdd + C(q, qd)·qd.

    With neither, the callable returns zeros; speeds and accelerations are ignored unless ``inertia``.
    """
    if inertia or gravity:
        return _ArmFeedForward(arm, gravity=gravity, inertia=inertia)
    return lambda q, qd, qdd: np.zeros(len(arm.joint_names))
