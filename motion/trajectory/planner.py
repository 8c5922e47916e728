"""Time-synchronised, jerk-limited multi-joint trajectories with Ruckig (the only importer of ``ruckig``).

All quantities are joint-side: degrees, deg/s, deg/s², deg/s³. A :class:`Segment` is one Ruckig trajectory
(every joint starts and arrives together); a :class:`Path` chains segments end to end. Ruckig's community
version has no intermediate waypoints, so :meth:`Planner.path` computes a pass-through velocity at each waypoint
and plans one segment per waypoint pair with that velocity as target and start: the path passes each waypoint
exactly, without stopping where the joints keep their direction.

Ruckig's ``min_position``/``max_position`` are not enforced by the community version, so every plan is checked
against the joint limits through the trajectory's position extrema.
"""

from __future__ import annotations

import math
import numbers
import re
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Final

import numpy as np
import numpy.typing as npt
from ruckig import ControlInterface, InputParameter, Result, Ruckig, RuckigError, Trajectory

from motion.errors import PlanningError
from motion.protocol.compiled import frozen_builder

FloatArray = npt.NDArray[np.float64]

# Ruckig's offline calculate() reports success as Working (Finished is for online update()).
_OK = (Result.Working, Result.Finished)
# Position-limit checks tolerate round-off of the extrema computation.
_LIMIT_TOLERANCE_DEG = 1e-6
# Velocities and accelerations below this are round-off, deg/s or deg/s².
_RESIDUE = 1e-9
#: Ruckig's message when its profile search found no profile (see :meth:`Planner._calculate`).
_PROFILE_SEARCH_FAILED = "error in step"
#: The factor the limits are lowered by when it did.
_OFF_BORDER = 1.0 - 1e-9
# Pass-through speeds keep this share of the velocity limit as headroom for synchronisation.
_PASS_VELOCITY_SHARE = 0.9


@dataclass(frozen=True, slots=True)
class JointLimits:
    """Per-joint kinematic limits, joint side.

    Raises:
        PlanningError: a limit is not finite and positive, or a position range is empty.
    """

    names: tuple[str, ...]
    position_min_deg: tuple[float, ...]
    position_max_deg: tuple[float, ...]
    velocity_dps: tuple[float, ...]
    acceleration_dps2: tuple[float, ...]
    jerk_dps3: tuple[float, ...]

    def __post_init__(self) -> None:
        n = len(self.names)
        for label in ("position_min_deg", "position_max_deg", "velocity_dps", "acceleration_dps2", "jerk_dps3"):
            values = getattr(self, label)
            if len(values) != n:
                raise PlanningError(f"{label}: {len(values)} values for {n} joints")
            for name, value in zip(self.names, values, strict=True):
                if not math.isfinite(value) or (label not in {"position_min_deg", "position_max_deg"} and value <= 0):
                    raise PlanningError(
                        f"{name}.{label}: {value!r} must be finite" + ("" if "position" in label else " and > 0")
                    )
        for name, lo, hi in zip(self.names, self.position_min_deg, self.position_max_deg, strict=True):
            if lo >= hi:
                raise PlanningError(f"{name}: position_min_deg {lo} must be < position_max_deg {hi}")

    @property
    def dofs(self) -> int:
        """Number of joints."""
        return len(self.names)


@dataclass(frozen=True, slots=True)
class State:
    """Joint positions (deg), velocities (deg/s) and accelerations (deg/s²)."""

    position: FloatArray
    velocity: FloatArray
    acceleration: FloatArray

    @classmethod
    def at_rest(cls, position_deg: Sequence[float] | FloatArray) -> State:
        """A state with zero velocity and acceleration."""
        p = np.array(position_deg, dtype=np.float64)
        return cls(p, np.zeros_like(p), np.zeros_like(p))


# State's slot-setting constructor (see frozen_builder), for the state sampled every cycle.
_new_state: Final = frozen_builder(State)


class Segment:
    """One time-synchronised Ruckig trajectory, sampled by time since its start."""

    __slots__ = ("_trajectory", "duration_s", "end")

    def __init__(self, trajectory: Trajectory) -> None:
        self._trajectory = trajectory
        self.duration_s: float = float(trajectory.duration)
        self.end = self.sample(self.duration_s)

    def sample(self, t_s: float) -> State:
        """Reference state ``t_s`` seconds after the start (clamped to the segment)."""
        # Sampled every control cycle: Ruckig's lists of Python floats become float64 arrays as they are.
        p, v, a = self._trajectory.at_time(min(max(t_s, 0.0), self.duration_s))
        return _new_state(np.array(p), np.array(v), np.array(a))

    def extrema(self) -> tuple[FloatArray, FloatArray]:
        """Smallest and largest position of every joint over the segment, in degrees."""
        ext = self._trajectory.position_extrema
        return np.array([e.min for e in ext]), np.array([e.max for e in ext])


class Path:
    """Segments played one after the other; time 0 is the start of the first."""

    __slots__ = ("_cursor", "_start_s", "_starts", "duration_s", "segments")

    def __init__(self, segments: Sequence[Segment]) -> None:
        if not segments:
            raise PlanningError("a path needs at least one segment")
        self.segments = tuple(segments)
        starts = np.cumsum([0.0] + [s.duration_s for s in self.segments])
        self._starts = starts
        self._start_s = tuple(starts.tolist())  # the same times as Python floats, for sample()
        self.duration_s = float(starts[-1])
        self._cursor = 0

    @property
    def end(self) -> State:
        """The final state."""
        return self.segments[-1].end

    @property
    def boundaries_s(self) -> FloatArray:
        """Start time of each segment and the end time of the last one, in seconds."""
        return self._starts.copy()

    def sample(self, t_s: float) -> State:
        """Reference state at time ``t_s`` (clamped to the path). Monotonic calls are O(1)."""
        starts, i = self._start_s, self._cursor
        if t_s < starts[i]:
            i = 0
        last = len(self.segments) - 1
        while i < last and t_s >= starts[i + 1]:
            i += 1
        self._cursor = i
        return self.segments[i].sample(t_s - starts[i])


#: Ruckig's results its Python module has no name for (ruckig 0.19.4's ``Result`` lacks them: converting one raises
#: ``ValueError: -101 is not a valid Result``), from its C++ ``Result`` enum.
_UNNAMED_RESULTS: Final = {
    -101: "the trajectory would last longer than Ruckig's numerical limits allow (a speed_scale this small?)",
    -104: "a velocity, acceleration or jerk limit is zero",
}
_UNNAMED_RESULT = re.compile(r"^(-?\d+) is not a valid Result")


def _calculate(otg: Ruckig, inp: InputParameter, trajectory: Trajectory) -> Result:
    """``otg.calculate``, whose results without a Python name raise RuckigError with their C++ meaning.

    Shim (exit: a ruckig release whose Python ``Result`` lists every C++ result, then ``otg.calculate`` directly).
    """
    try:
        return otg.calculate(inp, trajectory)
    except ValueError as exc:
        unnamed = _UNNAMED_RESULT.match(str(exc))
        if unnamed is None:
            raise
        code = int(unnamed.group(1))
        raise RuckigError(
            f"result {code}: {_UNNAMED_RESULTS.get(code, 'an error Ruckig has no name for here')}"
        ) from exc


class Planner:
    """Plans jerk-limited, time-synchronised joint trajectories within :class:`JointLimits`.

    Args:
        limits: per-joint limits (joint side).
    """

    def __init__(self, limits: JointLimits) -> None:
        self.limits = limits
        n = limits.dofs
        self._otg = Ruckig(n)
        self._lo = np.array(limits.position_min_deg)
        self._hi = np.array(limits.position_max_deg)
        self._v = np.array(limits.velocity_dps)
        self._a = np.array(limits.acceleration_dps2)
        self._j = np.array(limits.jerk_dps3)

    # ------------------------------------------------------------------------------------------------ checks

    def check_scale(self, speed_scale: object) -> float:
        """``speed_scale`` as a float, or PlanningError naming it and the valid range (any real number type)."""
        if isinstance(speed_scale, bool) or not isinstance(speed_scale, numbers.Real):
            raise PlanningError(f"speed_scale: {speed_scale!r} is not a number (valid: (0, 1])")
        scale = float(speed_scale)
        if not 0.0 < scale <= 1.0:
            raise PlanningError(f"speed_scale: {scale!r} is outside the valid range (0, 1]")
        return scale

    def _vector(self, label: str, values: Sequence[float] | FloatArray) -> FloatArray:
        arr = np.asarray(values, dtype=np.float64)
        if arr.shape != (self.limits.dofs,):
            raise PlanningError(
                f"{label}: expected {self.limits.dofs} values ({', '.join(self.limits.names)}), got {arr.shape}"
            )
        bad = ~np.isfinite(arr)
        if bad.any():
            raise PlanningError(f"{label}: {self.limits.names[int(np.argmax(bad))]} is not finite")
        return arr

    def check_positions(self, label: str, position_deg: FloatArray) -> None:
        """Raise PlanningError naming the joint if a position is outside its limits."""
        outside = (position_deg < self._lo - _LIMIT_TOLERANCE_DEG) | (position_deg > self._hi + _LIMIT_TOLERANCE_DEG)
        if outside.any():
            i = int(np.argmax(outside))
            raise PlanningError(
                f"{label}: {self.limits.names[i]} = {position_deg[i]:.4f} deg is outside "
                f"[{self._lo[i]:g}, {self._hi[i]:g}] deg"
            )

    # ------------------------------------------------------------------------------------------------ planning

    def _calculate(self, inp: InputParameter, what: str) -> Segment:
        trajectory = Trajectory(self.limits.dofs)
        try:
            try:
                result = _calculate(self._otg, inp, trajectory)
            except RuckigError as exc:
                if _PROFILE_SEARCH_FAILED not in str(exc):
                    raise
                # Shim (exit: a Ruckig release in which tests/test_trajectory.py's boundary case plans without it):
                # Ruckig's profile search misses inputs that sit exactly on the border between two profile shapes
                # (0 -> 6 deg from rest at 18 deg/s, 12 deg/s², 24 deg/s³ fails in ruckig 0.19.4; pantor/ruckig
                # issue 90, open). Limits lowered by a relative 1e-9 step off the border; the plan keeps within
                # the real ones.
                inp.max_velocity = [v * _OFF_BORDER for v in inp.max_velocity]
                inp.max_acceleration = [a * _OFF_BORDER for a in inp.max_acceleration]
                inp.max_jerk = [j * _OFF_BORDER for j in inp.max_jerk]
                result = _calculate(self._otg, inp, trajectory)
        except RuckigError as exc:
            raise PlanningError(f"{what}: Ruckig rejected the input: {str(exc).splitlines()[0] or exc}") from exc
        if result not in _OK:
            raise PlanningError(f"{what}: Ruckig returned {result.name}")
        return Segment(trajectory)

    def _input(self, start: State, speed_scale: float) -> InputParameter:
        inp = InputParameter(self.limits.dofs)
        inp.current_position = start.position.tolist()
        # Round-off residues (1e-15 deg/s after a segment that ends at rest) make Ruckig's profile search fail.
        inp.current_velocity = np.where(np.abs(start.velocity) < _RESIDUE, 0.0, start.velocity).tolist()
        inp.current_acceleration = np.where(np.abs(start.acceleration) < _RESIDUE, 0.0, start.acceleration).tolist()
        inp.max_velocity = (self._v * speed_scale).tolist()
        inp.max_acceleration = (self._a * speed_scale**2).tolist()
        inp.max_jerk = (self._j * speed_scale**3).tolist()
        return inp

    def move(
        self,
        start: State,
        target_deg: Sequence[float] | FloatArray,
        *,
        speed_scale: float = 1.0,
        target_velocity_dps: Sequence[float] | FloatArray | None = None,
    ) -> Segment:
        """Plan from ``start`` (moving or not) to ``target_deg``; every joint arrives at the same time.

        ``speed_scale`` s in (0, 1] scales the trajectory in time: velocity limits × s, acceleration × s²,
        jerk × s³.

        Raises:
            PlanningError: a bad scale or vector, a target outside the position limits, a trajectory that would
                leave them (e.g. overshoot from a fast start), or a Ruckig error.
        """
        scale = self.check_scale(speed_scale)
        target = self._vector("target_deg", target_deg)
        self.check_positions("target", target)
        inp = self._input(start, scale)
        inp.target_position = target.tolist()
        if target_velocity_dps is not None:
            tv = self._vector("target_velocity_dps", target_velocity_dps)
            if (np.abs(tv) > self._v * scale + 1e-9).any():
                raise PlanningError("target_velocity_dps exceeds the (scaled) velocity limits")
            inp.target_velocity = tv.tolist()
        segment = self._calculate(inp, "move")
        low, high = segment.extrema()
        self.check_positions("trajectory minimum", low)
        self.check_positions("trajectory maximum", high)
        return segment

    def stop(self, start: State) -> Segment:
        """Plan the jerk-limited stop to zero velocity and acceleration at the full limits.

        The stop is never refused for position limits (stopping is always the right thing); callers that
        must know can check :meth:`Segment.extrema`.

        Raises:
            PlanningError: only for a Ruckig error (e.g. a start state far beyond the limits).
        """
        inp = self._input(start, 1.0)
        inp.control_interface = ControlInterface.Velocity
        inp.target_velocity = [0.0] * self.limits.dofs
        inp.target_acceleration = [0.0] * self.limits.dofs
        # A start beyond the limits (e.g. after an external push) must still be stoppable.
        inp.max_velocity = np.maximum(self._v, np.abs(start.velocity)).tolist()
        inp.max_acceleration = np.maximum(self._a, np.abs(start.acceleration)).tolist()
        return self._calculate(inp, "stop")

    def pass_velocities(self, points: FloatArray, scale: float) -> FloatArray:
        """Pass-through velocity at every point of a waypoint list (zero at both ends), deg/s.

        At an interior waypoint a joint keeps moving only if it moves the same way before and after; its speed is
        the central difference over the two rest-to-rest segment durations (so all joints pass along the
        path's direction), bounded by 90 % of the velocity limit and by the speed the acceleration limit can
        build up or shed over the shorter neighbouring stretch.
        """
        n_points = len(points)
        velocities = np.zeros_like(points)
        if n_points < 3:
            return velocities
        durations = [
            self.move(State.at_rest(points[k]), points[k + 1], speed_scale=scale).duration_s
            for k in range(n_points - 1)
        ]
        vmax = self._v * scale * _PASS_VELOCITY_SHARE
        amax = self._a * scale**2
        for i in range(1, n_points - 1):
            d_in = points[i] - points[i - 1]
            d_out = points[i + 1] - points[i]
            span = durations[i - 1] + durations[i]
            v = (points[i + 1] - points[i - 1]) / span if span > 0 else np.zeros_like(d_in)
            reach = np.sqrt(amax * np.minimum(np.abs(d_in), np.abs(d_out)))
            v = np.clip(v, -np.minimum(vmax, reach), np.minimum(vmax, reach))
            v[d_in * d_out <= 0] = 0.0
            velocities[i] = v
        return velocities

    def path(
        self, start: State, waypoints_deg: Sequence[Sequence[float]] | FloatArray, *, speed_scale: float = 1.0
    ) -> Path:
        """Plan through every waypoint without stopping where the motion continues; stops at the last one.

        A segment that Ruckig cannot reach with the chosen pass-through velocity is retried with half of it and
        finally with a stop at that waypoint, so planning always succeeds for valid waypoints.

        Raises:
            PlanningError: a bad scale, an empty list, a waypoint outside the limits.
        """
        scale = self.check_scale(speed_scale)
        rows = [self._vector(f"waypoints[{i}]", w) for i, w in enumerate(waypoints_deg)]
        if not rows:
            raise PlanningError("waypoints: at least one waypoint is required")
        for i, row in enumerate(rows):
            self.check_positions(f"waypoints[{i}]", row)
        points = np.vstack([start.position, *rows])
        velocities = self.pass_velocities(points, scale)
        segments: list[Segment] = []
        state = start
        for k in range(1, len(points)):
            segment, velocity = self._segment_with_fallback(state, points[k], velocities[k], scale)
            segments.append(segment)
            # Ruckig ends exactly on its target state: start the next segment there, not on a sampled copy.
            state = State(points[k], velocity, np.zeros_like(velocity))
        return Path(segments)

    def _segment_with_fallback(
        self, start: State, target: FloatArray, velocity: FloatArray, scale: float
    ) -> tuple[Segment, FloatArray]:
        error: PlanningError | None = None
        for factor in (1.0, 0.5, 0.0):
            try:
                used = velocity * factor
                return self.move(start, target, speed_scale=scale, target_velocity_dps=used), used
            except PlanningError as exc:
                error = exc
        assert error is not None
        raise error
