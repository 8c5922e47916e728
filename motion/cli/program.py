"""Motion programs for ``rmd-motion run``: a YAML list of steps, validated as a whole before anything moves (the
format: :data:`FORMAT`, shown by ``rmd-motion run --help``; examples: ``configs/programs/``).

Every error is a :class:`~motion.errors.ConfigError` naming the file, the step (``steps[2]``, counted from 0) and the
key (``steps[2].move.shoulder``).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Final

from motion.cli.common import target_problem

# The CLI may not import yaml (motion.config owns it): programs are read with the configuration's YAML reader
# (which also rejects duplicate keys).
from motion.config import ArmConfig, read_yaml
from motion.config.examples import resolve_program
from motion.errors import ConfigError

#: The format of a program, as ``run --help`` shows it.
FORMAT: Final = """\
a program is a YAML file:

  name: pick and place                     # optional
  steps:                                   # or the list of steps itself at the top level
    - move: {shoulder: 20, elbow: -30}     # joint targets, degrees; the joints not named keep their targets
      speed_scale: 0.5                     # optional, (0, 1] of the velocity, acceleration and jerk limits
    - wait: 0.5                            # seconds, holding where the arm is
    - path: [{shoulder: 0}, {shoulder: 30, elbow: 10}]   # waypoints, passed through without stopping
      speed_scale: 0.8                     # optional, as for move

every step and value is checked (joint names, limits, scales) before anything moves; an error names the file, the
step (steps[2], counted from 0) and the key. --speed-scale multiplies every step's scale. Examples, one per example
arm: configs/programs/ (rmd-motion init copies them); try one in simulated time first with --emulate."""
#: The step kinds and the keys each allows besides its own.
_KINDS: Final = {"move": ("speed_scale",), "path": ("speed_scale",), "wait": ()}
#: Keys of the top-level mapping form.
_TOP_KEYS: Final = ("name", "steps")


@dataclass(frozen=True, slots=True)
class MoveStep:
    """Move the named joints to their targets (degrees) and stop there."""

    targets: Mapping[str, float]
    speed_scale: float = 1.0


@dataclass(frozen=True, slots=True)
class PathStep:
    """Pass through every waypoint (joint name -> degrees; unnamed joints keep the previous value), stop at the last."""

    waypoints: tuple[Mapping[str, float], ...]
    speed_scale: float = 1.0


@dataclass(frozen=True, slots=True)
class WaitStep:
    """Hold for ``seconds``."""

    seconds: float


Step = MoveStep | PathStep | WaitStep


@dataclass(frozen=True, slots=True)
class Program:
    """A validated program."""

    source: str
    steps: tuple[Step, ...]


class _Reader:
    """Validates one program's data, raising ConfigError with the file and key path."""

    def __init__(self, source: str, config: ArmConfig) -> None:
        self.source = source
        self.config = config

    def error(self, key_path: str, message: str) -> ConfigError:
        return ConfigError(self.source, key_path, message)

    def number(self, key_path: str, value: object) -> float:
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise self.error(key_path, f"expected a number; found {value!r}")
        try:
            number = float(value)
        except OverflowError:  # an integer of hundreds of digits
            raise self.error(key_path, f"expected a number; found an integer of {len(str(value))} digits") from None
        if not math.isfinite(number):
            raise self.error(key_path, f"expected a finite number; found {value!r}")
        return number

    def speed_scale(self, key_path: str, step: Mapping[object, object]) -> float:
        if "speed_scale" not in step:
            return 1.0
        value = self.number(key_path + ".speed_scale", step["speed_scale"])
        if not 0.0 < value <= 1.0:
            raise self.error(key_path + ".speed_scale", f"{value:g} is outside (0, 1]")
        return value

    def targets(self, key_path: str, value: object) -> dict[str, float]:
        if not isinstance(value, Mapping) or not value:
            example = f"{{{self.config.joint_names[0]}: 30}}"
            raise self.error(key_path, f"expected a mapping of joint: degrees, e.g. {example}")
        targets = {}
        for name, angle in value.items():
            where = f"{key_path}.{name}"
            deg = self.number(where, angle)
            problem = target_problem(self.config, str(name), deg)
            if problem is not None:
                raise self.error(where, problem)
            targets[str(name)] = deg
        return targets

    def step(self, key_path: str, step: object) -> Step:
        if not isinstance(step, Mapping):
            raise self.error(key_path, f"expected a step mapping with one of {', '.join(_KINDS)}; found {step!r}")
        kinds = [k for k in _KINDS if k in step]
        if len(kinds) != 1:
            found = ", ".join(kinds) if kinds else "none"
            raise self.error(key_path, f"a step has exactly one of {', '.join(_KINDS)}; found {found}")
        kind = kinds[0]
        allowed = (kind, *_KINDS[kind])
        for key in step:
            if key not in allowed:
                raise self.error(f"{key_path}.{key}", f"unknown key for a {kind} step; allowed: {', '.join(allowed)}")
        where = f"{key_path}.{kind}"
        value = step[kind]
        if kind == "wait":
            seconds = self.number(where, value)
            if seconds < 0:
                raise self.error(where, f"{seconds:g} s: a wait cannot be negative")
            return WaitStep(seconds)
        scale = self.speed_scale(key_path, step)
        if kind == "move":
            return MoveStep(self.targets(where, value), scale)
        if not isinstance(value, Sequence) or isinstance(value, str) or not value:
            raise self.error(where, "expected a non-empty list of waypoints (mappings of joint: degrees)")
        return PathStep(tuple(self.targets(f"{where}[{i}]", w) for i, w in enumerate(value)), scale)


def parse_program(data: object, source: str, config: ArmConfig) -> Program:
    """Validate a program's data for ``config`` (joints and their ranges).

    Raises:
        ConfigError: naming ``source``, the step and the key.
    """
    reader = _Reader(source, config)
    steps = data
    if isinstance(data, Mapping):
        for key in data:
            if key not in _TOP_KEYS:
                raise reader.error(str(key), f"unknown key; allowed: {', '.join(_TOP_KEYS)}")
        steps = data.get("steps")
    if not isinstance(steps, list) or not steps:
        raise reader.error("steps", "expected a non-empty list of steps (move, path, wait)")
    return Program(source, tuple(reader.step(f"steps[{i}]", step) for i, step in enumerate(steps)))


def load_program(path: str | Path, config: ArmConfig) -> Program:
    """Read and validate a program file (see the module docstring); an example program stands in for
    ``configs/programs/NAME`` where no such file exists (:func:`~motion.config.examples.resolve_program`).

    Raises:
        ConfigError: the file is missing, not YAML, or not a valid program for ``config``.
    """
    file = resolve_program(path)
    return parse_program(read_yaml(file), str(file), config)
