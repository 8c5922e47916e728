"""The checks of what a caller passes to the API: the arm's options, joint angles, waypoints and durations.

Each turns a value from the caller into the form the arm uses or refuses it before anything moves: an option with a
:class:`~motion.errors.ConfigError` (as a configuration key would be), a motion with a
:class:`~motion.errors.PlanningError`, a duration with a ``ValueError``.
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Mapping, Sequence

import numpy as np

from motion.config import ArmConfig
from motion.errors import ConfigError, PlanningError
from motion.transmission import FloatArray

_EMULATE_CHOICES: dict[bool | str, str | None] = {
    False: None,
    True: "simulated",
    "simulated": "simulated",
    "realtime": "realtime",
}


def emulation_of(config: ArmConfig, emulate: bool | str) -> str | None:
    """The emulation ``emulate`` asks for: ``None`` (hardware), ``"simulated"`` or ``"realtime"``.

    Raises:
        ConfigError: ``emulate`` is none of False, True, ``"simulated"``, ``"realtime"``.
    """
    if emulate not in _EMULATE_CHOICES:
        raise ConfigError(config.source, "<emulate>", f"{emulate!r} is not one of False, True, 'simulated', 'realtime'")
    return _EMULATE_CHOICES[emulate]


def start_pose_of(
    config: ArmConfig,
    pose: Mapping[str, float] | None,
    emulate: bool | str,
    initial_deg: Sequence[float] | None,
) -> tuple[float, ...] | None:
    """The emulated power-up pose in joint order (unnamed joints at 0), or None.

    Raises:
        ConfigError: not emulated, together with ``initial_deg``, an unknown joint or a non-finite angle.
    """
    if pose is None:
        return None
    if not emulate:
        raise ConfigError(config.source, "<start_pose>", "applies to emulated drives only (emulate=...)")
    if initial_deg is not None:
        raise ConfigError(config.source, "<start_pose>", "give start_pose or initial_deg, not both")
    names = config.joint_names
    for name, angle in pose.items():
        if name not in names:
            raise ConfigError(config.source, "<start_pose>", f"unknown joint {name!r}; joints: {', '.join(names)}")
        if not math.isfinite(angle):
            raise ConfigError(config.source, f"<start_pose>.{name}", f"expected a finite angle; found {angle!r}")
    return tuple(float(pose.get(name, 0.0)) for name in names)


def degrees(label: str, value: object) -> float:
    """A joint angle given to the API, as a float: a real number (not a bool, not a string), finite."""
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise PlanningError(f"{label}: {value!r} is not a number of degrees")
    angle = float(value)
    if not math.isfinite(angle):
        raise PlanningError(f"{label}: {angle!r} is not a finite number of degrees")
    return angle


def seconds(label: str, value: object) -> float:
    """A duration given to the API, s: a finite real number >= 0."""
    if isinstance(value, bool) or not isinstance(value, numbers.Real) or not (0.0 <= float(value) < math.inf):
        raise ValueError(f"{label}: {value!r} is not a duration (a finite number of seconds >= 0)")
    return float(value)


def joint_targets(
    targets: Mapping[str, float], base: FloatArray, index: Mapping[str, int], label: str = "targets"
) -> FloatArray:
    """``base`` (every joint's angle, deg) with the named joints of ``targets`` replaced; ``index`` gives each
    joint's place, in joint order.

    Raises:
        PlanningError: ``targets`` is not a mapping, names an unknown joint or gives a value that is no angle.
    """
    if not isinstance(targets, Mapping):
        raise PlanningError(
            f"{label}: a mapping of joint names to degrees is expected (joints: {', '.join(index)}), "
            f"got {type(targets).__name__} {targets!r}"
        )
    q = base.copy()
    for name, value in targets.items():
        if name not in index:
            raise PlanningError(f"{label}: unknown joint {name!r}; joints: {', '.join(index)}")
        q[index[name]] = degrees(f"{label}[{name!r}]", value)
    return q


def _row(point: Sequence[float], names: Sequence[str], label: str) -> FloatArray:
    """A waypoint given as a full list of angles in joint order."""
    if isinstance(point, str | bytes) or not isinstance(point, Sequence | np.ndarray) or len(point) != len(names):
        raise PlanningError(
            f"{label}: a mapping of joint names to degrees or {len(names)} angles in joint order "
            f"({', '.join(names)}) is expected, got {point!r}"
        )
    return np.array([degrees(f"{label}[{k}]", v) for k, v in enumerate(point)], dtype=np.float64)


def waypoint_rows(
    waypoints: Sequence[Mapping[str, float] | Sequence[float]], start: FloatArray, index: Mapping[str, int]
) -> FloatArray:
    """The waypoints of :meth:`~motion.api.Arm.follow` as rows of every joint's angle, deg: a mapping names some
    joints (the others keep the previous row's angle, the first row's ``start``'s), a list gives every angle in joint
    order (``index``'s).

    Raises:
        PlanningError: not a list of waypoints, none, or a waypoint that is neither form.
    """
    if isinstance(waypoints, Mapping | str | bytes) or not isinstance(waypoints, Sequence | np.ndarray):
        raise PlanningError(f"waypoints: a list of waypoints is expected, got {type(waypoints).__name__}")
    names = list(index)
    previous = start
    rows = []
    for k, point in enumerate(waypoints):
        label = f"waypoints[{k}]"
        row = joint_targets(point, previous, index, label) if isinstance(point, Mapping) else _row(point, names, label)
        rows.append(row)
        previous = row
    if not rows:
        raise PlanningError("waypoints: at least one waypoint is required")
    return np.array(rows, dtype=np.float64)
