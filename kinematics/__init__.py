"""Arm kinematics and dynamics for rmd-motion (the only importer of Pinocchio).

Build the model once with :func:`build_arm`, then call the free functions every cycle. The API works in joint
degrees (deg, deg/s, deg/s²) and N·m, in configuration joint order. :func:`feedforward` gives the controller a
plain callable, so that :mod:`motion` never imports this package.
"""

from __future__ import annotations

from kinematics.dynamics import (
    FeedForward,
    FramePose,
    aba,
    feedforward,
    frame_names,
    frame_pose,
    gravity_torque,
    mass_matrix,
    rnea,
)
from kinematics.model import ArmModel, build_arm

__all__ = [
    "ArmModel",
    "FeedForward",
    "FramePose",
    "aba",
    "build_arm",
    "feedforward",
    "frame_names",
    "frame_pose",
    "gravity_torque",
    "mass_matrix",
    "rnea",
]
