"""Online trajectory playback: the reference the controller samples every cycle.

A :class:`Follower` holds the current :class:`~motion.trajectory.planner.Path` and its start time. A new target
while moving is planned from the reference state at that instant (position, velocity and acceleration), so
re-targeting never steps the velocity or the acceleration; a stop is a jerk-limited ramp to zero velocity.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from motion.trajectory.planner import FloatArray, Path, Planner, State


class Follower:
    """Plays paths against controller time (seconds, any monotonic clock).

    Args:
        planner: the planner of the arm.
        position_deg: where the arm is at rest now.
    """

    def __init__(self, planner: Planner, position_deg: Sequence[float] | FloatArray) -> None:
        self.planner = planner
        self._hold = State.at_rest(position_deg)
        self._path: Path | None = None
        self._t0 = 0.0

    @property
    def moving(self) -> bool:
        """True while a path is being played."""
        return self._path is not None

    @property
    def path(self) -> Path | None:
        """The path being played, if any."""
        return self._path

    def end_time(self) -> float:
        """Controller time at which the current path ends (the start time when idle)."""
        return self._t0 + (self._path.duration_s if self._path is not None else 0.0)

    def sample(self, t_s: float) -> State:
        """Reference at controller time ``t_s``; when the path has ended the follower holds its end state."""
        path = self._path
        if path is None:
            return self._hold
        if t_s >= self._t0 + path.duration_s:
            end = path.end
            self._hold = State.at_rest(end.position)
            self._path = None
            return self._hold
        return path.sample(t_s - self._t0)

    def play(self, path: Path, t_s: float) -> None:
        """Start ``path`` at controller time ``t_s`` (its first state must be the current reference)."""
        self._path = path
        self._t0 = t_s

    def move_to(self, t_s: float, target_deg: Sequence[float] | FloatArray, *, speed_scale: float = 1.0) -> Path:
        """Plan from the reference at ``t_s`` to ``target_deg`` and play it (re-targets a running move)."""
        path = Path([self.planner.move(self.sample(t_s), target_deg, speed_scale=speed_scale)])
        self.play(path, t_s)
        return path

    def follow(
        self, t_s: float, waypoints_deg: Sequence[Sequence[float]] | FloatArray, *, speed_scale: float = 1.0
    ) -> Path:
        """Plan a waypoint path from the reference at ``t_s`` and play it."""
        path = self.planner.path(self.sample(t_s), waypoints_deg, speed_scale=speed_scale)
        self.play(path, t_s)
        return path

    def stop(self, t_s: float) -> Path:
        """Ramp from the reference at ``t_s`` to zero velocity (jerk-limited) and hold where it ends."""
        state = self.sample(t_s)
        if not np.any(state.velocity) and not np.any(state.acceleration):
            self._path = None
            self._hold = State.at_rest(state.position)
            return Path([self.planner.stop(self._hold)])
        path = Path([self.planner.stop(state)])
        self.play(path, t_s)
        return path

    def stop_from(self, t_s: float, state: State) -> Path:
        """Ramp from ``state`` (e.g. the measured one) at ``t_s`` to zero velocity (jerk-limited) and hold where it
        ends: the reference jumps to ``state`` first."""
        self._path = None
        self._hold = State.at_rest(state.position)
        path = Path([self.planner.stop(state)])
        self.play(path, t_s)
        return path

    def hold_at(self, position_deg: Sequence[float] | FloatArray) -> None:
        """Drop any path and hold ``position_deg`` (e.g. after a halt, at the measured position)."""
        self._path = None
        self._hold = State.at_rest(position_deg)
