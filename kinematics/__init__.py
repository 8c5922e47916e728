"""Arm kinematics and dynamics for rmd-motion (the only importer of Pinocchio)."""

from __future__ import annotations
