"""Arm configuration: YAML file -> validated frozen dataclasses (the only importer of ``yaml``)."""

from __future__ import annotations

from motion.config.examples import example_config, example_names, load_config_or_example, resolve_config
from motion.config.loader import load_config, parse_config, read_yaml, write_joint_values
from motion.config.schema import (
    ArmConfig,
    BusConfig,
    CanBusConfig,
    ChainJointConfig,
    ControlConfig,
    ControlMode,
    EmulationConfig,
    HaltPolicy,
    HomingConfig,
    InertiaConfig,
    JointConfig,
    ModelConfig,
    Rs485BusConfig,
    SafetyConfig,
    Vec3,
)

__all__ = [
    "ArmConfig",
    "BusConfig",
    "CanBusConfig",
    "ChainJointConfig",
    "ControlConfig",
    "ControlMode",
    "EmulationConfig",
    "HaltPolicy",
    "HomingConfig",
    "InertiaConfig",
    "JointConfig",
    "ModelConfig",
    "Rs485BusConfig",
    "SafetyConfig",
    "Vec3",
    "example_config",
    "example_names",
    "load_config",
    "load_config_or_example",
    "parse_config",
    "read_yaml",
    "resolve_config",
    "write_joint_values",
]
