"""Read and validate an arm configuration file (the only importer of ``yaml`` in the package).

Keys, required keys and defaults come from the dataclasses of :mod:`motion.config.schema`; the section parsers
(:mod:`motion.config.sections`, :mod:`motion.config.joints`, reading through :mod:`motion.config.nodes`) add the
types and ranges. Every problem raises :class:`~motion.errors.ConfigError` naming the file, the key path
(``joints[1].gear_ratio``), what is allowed and what was found. Nothing is clipped or defaulted silently.
"""

from __future__ import annotations

import os
from collections.abc import Hashable, Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

import yaml

from motion.config import schema
from motion.config.joints import joints_section
from motion.config.nodes import Node
from motion.config.sections import LINK_TIMEOUT_MAX_MS, buses_section, control_section, model_section, safety_section
from motion.errors import ConfigError

__all__ = ["LINK_TIMEOUT_MAX_MS", "load_config", "parse_config", "read_yaml", "write_joint_values"]


def parse_config(
    data: object, source: str = "<string>", base_dir: str | os.PathLike[str] | None = None
) -> schema.ArmConfig:
    """Validate a configuration mapping (as read from YAML) into an :class:`~motion.config.schema.ArmConfig`.

    Args:
        data: the mapping.
        source: where it came from, for error messages.
        base_dir: directory a relative ``model.urdf`` is resolved against (default: the working directory).

    Raises:
        ConfigError: naming ``source``, the key path, what is allowed and what was found.
    """
    root = Node(data, source, "", schema.ArmConfig, hidden=["source"], extra=["bus"])
    control = control_section(root.child("control", schema.ControlConfig))
    buses = buses_section(root)
    joints = joints_section(root, control.mode, buses)
    return schema.ArmConfig(
        name=root.text("name"),
        buses=buses,
        control=control,
        model=model_section(root, joints, Path(base_dir) if base_dir is not None else Path.cwd()),
        safety=safety_section(root.child("safety", schema.SafetyConfig), control),
        joints=joints,
        source=source,
    )


# libyaml's parser where PyYAML was built with it (its wheels are): ten times faster than the pure-Python one.
if TYPE_CHECKING or not getattr(yaml, "__with_libyaml__", False):  # noqa: SIM108 (mypy needs a plain class here)
    _SafeLoader = yaml.SafeLoader
else:
    _SafeLoader = yaml.CSafeLoader


class _Loader(_SafeLoader):
    """SafeLoader that rejects a key given twice in one mapping (PyYAML silently keeps the last)."""

    def construct_mapping(self, node: yaml.MappingNode, deep: bool = False) -> dict[Hashable, Any]:
        seen: set[str] = set()
        for key_node, _ in node.value:
            key = self.construct_object(key_node, deep=deep)
            if isinstance(key, str):
                if key in seen:
                    raise yaml.constructor.ConstructorError(None, None, f"duplicate key {key!r}", key_node.start_mark)
                seen.add(key)
        return super().construct_mapping(node, deep)


def read_yaml(path: str | os.PathLike[str]) -> Any:
    """Read a YAML file as plain data (mappings, lists, scalars); a key given twice in a mapping is an error.

    Raises:
        ConfigError: the file is missing or unreadable, or is not valid YAML (the key path gives line and column).
    """
    file = Path(path)
    source = str(file)
    try:
        text = file.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise ConfigError(source, "<file>", "file not found") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(source, "<file>", f"cannot read the file: {exc}") from None
    try:
        return yaml.load(text, Loader=_Loader)  # a SafeLoader subclass: plain data only
    except yaml.MarkedYAMLError as exc:
        mark = exc.problem_mark or exc.context_mark
        where = f"line {mark.line + 1}, column {mark.column + 1}" if mark is not None else "<file>"
        raise ConfigError(source, where, f"invalid YAML: {exc.problem or exc}") from None
    except yaml.YAMLError as exc:
        raise ConfigError(source, "<file>", f"invalid YAML: {exc}") from None


def load_config(path: str | os.PathLike[str]) -> schema.ArmConfig:
    """Read, parse and validate an arm configuration file; a relative URDF path is relative to the file.

    Raises:
        ConfigError: the file is missing or unreadable, is not valid YAML (the key path gives line and column),
            or does not validate.
    """
    file = Path(path)
    return parse_config(read_yaml(file), source=str(file), base_dir=file.parent)


def _yaml_value(value: float | str) -> float | str:
    """A number as a float, a word (e.g. ``bound``) as it is."""
    return value if isinstance(value, str) else float(value)


def write_joint_values(
    source: str | os.PathLike[str],
    target: str | os.PathLike[str],
    key: str,
    values: Mapping[str, float | str | Mapping[str, float | str]],
) -> schema.ArmConfig:
    """Write a copy of the configuration ``source`` to ``target`` with ``key`` set on the named joints (e.g. the
    proposed ``collision_threshold_nm``), and return the copy validated. The copy is written by the YAML library:
    the values are kept, the comments are not; a relative ``model.urdf`` is rewritten to stay valid from the
    copy's directory.

    Raises:
        ConfigError: the source is invalid, a joint is not in it, or the copy does not validate.
        OSError: the copy cannot be written.
    """
    source_path, target_path = Path(source), Path(target)
    load_config(source_path)  # the source itself is valid
    data = read_yaml(source_path)
    joints = {str(j.get("name")): j for j in data["joints"]}
    for name, value in values.items():
        if name not in joints:
            raise ConfigError(str(source_path), "joints", f"no joint {name!r}")
        joints[name][key] = (
            _yaml_value(value) if not isinstance(value, Mapping) else {k: _yaml_value(v) for k, v in value.items()}
        )
    model = data.get("model", {})
    if isinstance(model, dict) and "urdf" in model:
        urdf = (source_path.parent / str(model["urdf"])).resolve()
        model["urdf"] = os.path.relpath(urdf, target_path.resolve().parent)
    text = yaml.safe_dump(data, sort_keys=False, allow_unicode=True)
    parse_config(yaml.safe_load(text), str(target_path), target_path.resolve().parent)
    target_path.write_text(text, encoding="utf-8")
    return load_config(target_path)
