"""Trajectory planning (Ruckig) and online playback, joint side in degrees."""

from __future__ import annotations

from motion.trajectory.follower import Follower
from motion.trajectory.planner import JointLimits, Path, Planner, Segment, State

__all__ = ["Follower", "JointLimits", "Path", "Planner", "Segment", "State"]
