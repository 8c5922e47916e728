"""Read and validate an arm configuration file (the only importer of ``yaml`` in the package).

Keys, required keys and defaults come from the dataclasses of :mod:`motion.config.schema`; this module adds the
types and ranges. Every problem raises :class:`~motion.errors.ConfigError` naming the file, the key path
(``joints[1].gear_ratio``), what is allowed and what was found. Nothing is clipped or defaulted silently.
"""

from __future__ import annotations

import dataclasses
import difflib
import math
import os
import sys
from collections.abc import Callable, Hashable, Iterable, Mapping, Sequence
from dataclasses import MISSING, dataclass, fields
from enum import StrEnum
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypeVar, cast

import numpy as np
import yaml

from motion.config import schema
from motion.config.urdf import revolute_joints
from motion.errors import ConfigError
from motion.protocol import WireProtocol
from motion.protocol.messages import Command
from motion.protocol.table import (
    MOTOR_ID_MAX,
    MOTOR_ID_MIN,
    RS485_BAUDRATES,
    Direction,
    ProtocolFamily,
    field_range,
)
from motion.transmission import IQ_LIMIT_A

_T = TypeVar("_T")
_E = TypeVar("_E", bound=StrEnum)

_FLOAT_MAX = sys.float_info.max
#: Relative slack for the physical-consistency check of an inertia matrix.
_INERTIA_TOLERANCE = 1e-9

# An emulated drive's PI gains (0x30 / 0x31: uint8 units) and acceleration (0x34), as the table declares them.
_GAIN_LO, _GAIN_HI = field_range(Command.WRITE_PID_RAM, Direction.REQUEST, WireProtocol.CAN, "angle_kp")
_ACCELERATION_LO, _ACCELERATION_HI = field_range(
    Command.WRITE_ACCELERATION_RAM, Direction.REQUEST, WireProtocol.CAN, "acceleration_dps2"
)


@dataclass(frozen=True, slots=True)
class _Range:
    """Allowed interval of a number; ``None`` leaves that side unbounded."""

    lo: float | None = None
    hi: float | None = None
    lo_open: bool = False
    hi_open: bool = False

    def __contains__(self, value: float) -> bool:
        above = self.lo is None or value > self.lo or (not self.lo_open and value == self.lo)
        below = self.hi is None or value < self.hi or (not self.hi_open and value == self.hi)
        return above and below

    def __str__(self) -> str:
        low = "" if self.lo is None else f"{self.lo:g} {'<' if self.lo_open else '<='} "
        high = "" if self.hi is None else f" {'<' if self.hi_open else '<='} {self.hi:g}"
        return f"{low}x{high}" if low or high else "any finite number"


@dataclass(frozen=True, slots=True)
class _OneOf:
    """Allowed set of numbers."""

    values: tuple[int, ...]

    def __contains__(self, value: float) -> bool:
        return value in self.values

    def __str__(self) -> str:
        return "one of " + ", ".join(str(v) for v in self.values)


_Allowed = _Range | _OneOf
_ANY = _Range()
_POSITIVE = _Range(lo=0, lo_open=True)
_NON_NEGATIVE = _Range(lo=0)
#: The longest communication-loss time accepted, ms (a minute: beyond it the protection protects nothing).
LINK_TIMEOUT_MAX_MS = 60_000


class _Invalid(Exception):
    """A value is wrong; the reader adds file and key path (``suffix`` extends the path, e.g. ``[1]``)."""

    def __init__(self, message: str, suffix: str = "") -> None:
        super().__init__(message)
        self.message = message
        self.suffix = suffix


def _describe(value: object) -> str:
    if isinstance(value, bool):
        return f"the boolean {value}"
    if value is None:
        return "nothing (null)"
    if isinstance(value, str):
        try:
            float(value)
        except ValueError:
            return f"the string {value!r}"
        return f"the string {value!r} (write numbers unquoted; YAML 1.1 needs a dot in exponents: 1.0e-4)"
    if isinstance(value, Mapping):
        return "a mapping"
    if isinstance(value, list | tuple):
        return "a list"
    return repr(value)


def _to_number(value: object, allowed: _Allowed = _ANY) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise _Invalid(f"expected a number ({allowed}); found {_describe(value)}")
    number = float(value) if abs(value) < _FLOAT_MAX else math.inf  # a huge YAML int would overflow float()
    if not math.isfinite(number) or number not in allowed:
        raise _Invalid(f"out of range (allowed: {allowed}); found {value!r}")
    return number


def _to_integer(value: object, allowed: _Allowed) -> int:
    if isinstance(value, bool) or not isinstance(value, int):
        raise _Invalid(f"expected an integer ({allowed}); found {_describe(value)}")
    if value not in allowed:
        raise _Invalid(f"out of range (allowed: {allowed}); found {value!r}")
    return value


def _to_flag(value: object) -> bool:
    if not isinstance(value, bool):
        raise _Invalid(f"expected true or false; found {_describe(value)}")
    return value


def _to_text(value: object) -> str:
    if not isinstance(value, str) or not value.strip():
        raise _Invalid(f"expected a non-empty string; found {_describe(value)}")
    return value


def _to_choice(value: object, choices: type[_E], false_alias: _E | None, refused: Mapping[_E, str]) -> _E:
    if value is False and false_alias is not None:
        return false_alias  # YAML 1.1 reads an unquoted `off` as False
    for member, why in refused.items():
        if value == member.value:
            raise _Invalid(why)
    if isinstance(value, str) and value in {c.value for c in choices}:
        return choices(value)
    hint = " (YAML 1.1 reads unquoted on/off/yes/no as booleans; quote the value)" if isinstance(value, bool) else ""
    allowed = ", ".join(c.value for c in choices if c not in refused)
    raise _Invalid(f"expected one of {allowed}; found {_describe(value)}{hint}")


def _to_numbers(value: object, count: int, form: str) -> list[float]:
    """A list of ``count`` finite numbers (``form`` names them in the message, e.g. ``[x, y, z]``)."""
    if not isinstance(value, list | tuple) or len(value) != count:
        raise _Invalid(f"expected a list of {count} numbers {form}; found {_describe(value)}")
    items: list[float] = []
    for i, item in enumerate(value):
        try:
            items.append(_to_number(item))
        except _Invalid as exc:
            raise _Invalid(exc.message, f"[{i}]") from None
    return items


#: The keys of a per-mode ``collision_threshold_nm``, in the order of its two numbers.
_THRESHOLD_MODES = ("position", "torque")


def _to_vector3(value: object) -> schema.Vec3:
    x, y, z = _to_numbers(value, 3, "[x, y, z]")
    return (x, y, z)


def _to_interval(value: object) -> tuple[float, float]:
    low, high = _to_numbers(value, 2, "[min, max]")
    if low >= high:
        raise _Invalid(f"expected [min, max] with min < max; found [{low:g}, {high:g}]")
    return (low, high)


#: Keys of earlier versions, and what replaced them (a key in control cycles changed its meaning with the rate).
_REPLACED = {
    "collision_window_cycles": "replaced by collision_window_s, in seconds (the cycles times the control period: "
    "8 cycles at 250 Hz is 0.032)",
    "collision_gain_per_cycle": "replaced by collision_observer_gain_per_s, the observer gain K_O in 1/s (the gain "
    "per cycle times control.rate_hz: 0.5 at 250 Hz is 125)",
}


class _Node:
    """A YAML mapping being read into one of the schema dataclasses.

    It knows its file and key path, rejects unknown keys up front (so that a misspelt key is reported as such,
    not as a missing one) and takes each key's default from the dataclass field.
    """

    def __init__(
        self,
        data: object,
        source: str,
        path: str,
        *schemas: type[Any],
        extra: Iterable[str] = (),
        hidden: Iterable[str] = (),
    ) -> None:
        self.source = source
        self.path = path
        if not isinstance(data, Mapping):
            raise ConfigError(source, path or "<root>", f"expected a mapping of keys; found {_describe(data)}")
        self._data: Mapping[Hashable, object] = data
        self._defaults: dict[str, object] = {}
        allowed = set(extra)
        for kind in schemas:
            for f in fields(kind):
                if f.metadata.get("derived"):
                    continue  # set from another key (e.g. the torque-mode half of collision_threshold_nm)
                allowed.add(f.name)
                if f.default is not MISSING:
                    self._defaults[f.name] = f.default
                elif f.default_factory is not MISSING:
                    self._defaults[f.name] = f.default_factory()
        allowed -= set(hidden)
        for key in data:
            if key in _REPLACED and key not in allowed:
                raise self.error(str(key), _REPLACED[str(key)])
            if key not in allowed:
                close = difflib.get_close_matches(str(key), allowed, n=1)
                hint = f" (did you mean {close[0]!r}?)" if close else ""
                known = ", ".join(sorted(allowed))
                raise self.error(str(key), f"unknown key{hint}; allowed keys: {known}")

    def key_path(self, key: str) -> str:
        """Full key path of ``key`` in this mapping (the mapping's own path for ``""``)."""
        if not key:
            return self.path
        return f"{self.path}.{key}" if self.path else key

    def error(self, key: str, message: str) -> ConfigError:
        """A ConfigError for ``key`` of this mapping."""
        return ConfigError(self.source, self.key_path(key), message)

    def has(self, key: str) -> bool:
        """Whether the file gives ``key``."""
        return key in self._data

    def defaults(self, **values: object) -> _Node:
        """Replace the schema's defaults of some keys (defaults that depend on another section); returns self."""
        self._defaults.update(values)
        return self

    def _read(self, key: str, expected: str, convert: Callable[[object], _T], required: bool | None) -> _T:
        if key in self._data:
            try:
                return convert(self._data[key])
            except _Invalid as exc:
                raise ConfigError(self.source, self.key_path(key) + exc.suffix, exc.message) from None
        if required or key not in self._defaults:
            raise self.error(key, f"required key is missing (expected {expected})")
        return cast(_T, self._defaults[key])

    def number(self, key: str, allowed: _Allowed = _ANY, *, required: bool | None = None) -> float:
        """A finite number (int or float, not bool) within ``allowed``; ``required`` overrides the schema."""
        return self._read(key, f"a number, {allowed}", lambda v: _to_number(v, allowed), required)

    def integer(self, key: str, allowed: _Allowed) -> int:
        """An integer (not bool, not float) within ``allowed``."""
        return self._read(key, f"an integer, {allowed}", lambda v: _to_integer(v, allowed), None)

    def flag(self, key: str) -> bool:
        """A boolean."""
        return self._read(key, "true or false", _to_flag, None)

    def text(self, key: str) -> str:
        """A non-empty string."""
        return self._read(key, "a non-empty string", _to_text, None)

    def choice(
        self, key: str, choices: type[_E], *, false_alias: _E | None = None, refused: Mapping[_E, str] | None = None
    ) -> _E:
        """One of the values of a StrEnum; ``false_alias`` is what a YAML 1.1 boolean False stands for; ``refused``
        members are not valid here (each with the reason given)."""
        no = refused or {}
        expected = "one of " + ", ".join(c.value for c in choices if c not in no)
        return self._read(key, expected, lambda v: _to_choice(v, choices, false_alias, no), None)

    def vector3(self, key: str) -> schema.Vec3:
        """A list of three finite numbers."""
        return self._read(key, "a list of 3 numbers", _to_vector3, None)

    def interval(self, key: str) -> tuple[float, float]:
        """A list of two finite numbers, the first smaller."""
        return self._read(key, "a list of 2 numbers [min, max]", _to_interval, None)

    def child(self, key: str, *schemas: type[Any], extra: Iterable[str] = ()) -> _Node:
        """The sub-mapping ``key`` (an empty one when absent and the schema gives it a default)."""
        if key not in self._data and key not in self._defaults:
            raise self.error(key, "required section is missing")
        return _Node(self._data.get(key, {}), self.source, self.key_path(key), *schemas, extra=extra)

    def children(self, key: str, kind: type[Any]) -> list[_Node]:
        """The non-empty list of mappings ``key``."""
        items = self._data.get(key)
        if not isinstance(items, list) or not items:
            found = "nothing (missing)" if key not in self._data else _describe(items)
            raise self.error(key, f"expected a non-empty list of mappings; found {found}")
        return [_Node(item, self.source, f"{self.key_path(key)}[{i}]", kind) for i, item in enumerate(items)]


def _bus(root: _Node) -> schema.BusConfig:
    kinds: dict[WireProtocol, type[schema.BusConfig]] = {
        kind.transport: kind for kind in (schema.CanBusConfig, schema.Rs485BusConfig)
    }
    # Read `transport` with the keys of every bus kind allowed, then re-read strictly with the chosen kind's keys.
    transport = root.child("bus", *kinds.values(), extra=["transport"]).choice("transport", WireProtocol)
    node = root.child("bus", kinds[transport], extra=["transport"])
    if transport is WireProtocol.CAN:
        return schema.CanBusConfig(
            interface=node.text("interface"),
            channel=node.text("channel"),
            bitrate=node.integer("bitrate", _OneOf((500_000, 1_000_000))),
            protocol=node.choice("protocol", schema.ProtocolSetting),
        )
    protocol = node.choice("protocol", schema.ProtocolSetting)
    # the baud rates of the generation named, or of either with auto
    families = list(ProtocolFamily) if protocol is schema.ProtocolSetting.AUTO else [ProtocolFamily(protocol.value)]
    baudrates = sorted({rate for family in families for rate in RS485_BAUDRATES[family]})
    return schema.Rs485BusConfig(
        port=node.text("port"), baudrate=node.integer("baudrate", _OneOf(tuple(baudrates))), protocol=protocol
    )


def _control(node: _Node) -> schema.ControlConfig:
    policy = node.choice(
        "halt_policy",
        schema.HaltPolicy,
        false_alias=schema.HaltPolicy.OFF,
        refused={
            schema.HaltPolicy.COMPLY: "comply is a reaction to collisions only: set safety.collision_reaction instead"
        },
    )
    return schema.ControlConfig(
        halt_policy=policy,
        mode=node.choice("mode", schema.ControlMode),
        rate_hz=node.number("rate_hz", _Range(1, 1000)),
        gravity_feedforward=node.flag("gravity_feedforward"),
        inertia_feedforward=node.flag("inertia_feedforward"),
        rate_margin=node.number("rate_margin", _Range(1, 10)),
    )


def _safety(node: _Node, control: schema.ControlConfig) -> schema.SafetyConfig:
    reaction = (
        node.choice("collision_reaction", schema.HaltPolicy, false_alias=schema.HaltPolicy.OFF)
        if node.has("collision_reaction")
        else None
    )
    if reaction is schema.HaltPolicy.COMPLY and control.mode is not schema.ControlMode.TORQUE:
        raise node.error(
            "collision_reaction",
            f"comply needs control.mode torque (it streams gravity compensation); found mode {control.mode.value}",
        )
    return schema.SafetyConfig(
        following_error_deg=node.number("following_error_deg", _POSITIVE),
        min_voltage_v=node.number("min_voltage_v", _Range(0, 60, lo_open=True)),
        reply_timeout_ms=node.number("reply_timeout_ms", _Range(0, 1000, lo_open=True)),
        max_missed_replies=node.integer("max_missed_replies", _Range(0, 100)),
        collision_reaction=reaction,
        collision_observer_gain_per_s=node.number("collision_observer_gain_per_s", _Range(0, 10000, lo_open=True)),
        collision_window_s=node.number("collision_window_s", _Range(0, 1)),
        link_timeout_ms=(
            node.number("link_timeout_ms", _Range(0, LINK_TIMEOUT_MAX_MS)) if node.has("link_timeout_ms") else None
        ),
    )


def _emulation(node: _Node, rotor_inertia: float, viscous: float, coulomb: float) -> schema.EmulationConfig:
    node.defaults(rotor_inertia_kgm2=rotor_inertia, viscous_friction_nm_per_dps=viscous, coulomb_friction_nm=coulomb)
    pid = node.child("pid", schema.EmulatedPidConfig)
    gain = _Range(_GAIN_LO, _GAIN_HI)
    return schema.EmulationConfig(
        rotor_inertia_kgm2=node.number("rotor_inertia_kgm2", _NON_NEGATIVE),
        viscous_friction_nm_per_dps=node.number("viscous_friction_nm_per_dps", _NON_NEGATIVE),
        coulomb_friction_nm=node.number("coulomb_friction_nm", _NON_NEGATIVE),
        torque_constant_nm_per_a=(
            node.number("torque_constant_nm_per_a", _POSITIVE) if node.has("torque_constant_nm_per_a") else None
        ),
        pid=schema.EmulatedPidConfig(**{f.name: pid.integer(f.name, gain) for f in fields(schema.EmulatedPidConfig)}),
        acceleration_dps2=node.integer("acceleration_dps2", _Range(_ACCELERATION_LO, _ACCELERATION_HI)),
    )


def _joint(node: _Node, mode: schema.ControlMode) -> schema.JointConfig:
    torque_mode = mode is schema.ControlMode.TORQUE
    rotor_inertia = node.number("rotor_inertia_kgm2", _NON_NEGATIVE)
    viscous = node.number("viscous_friction_nm_per_dps", _NON_NEGATIVE)
    coulomb = node.number("coulomb_friction_nm", _NON_NEGATIVE)
    thresholds = _collision_thresholds(node)
    joint = schema.JointConfig(
        name=node.text("name"),
        motor_id=node.integer("motor_id", _Range(MOTOR_ID_MIN, MOTOR_ID_MAX)),
        gear_ratio=node.number("gear_ratio", _POSITIVE),
        direction=node.integer("direction", _OneOf((1, -1))),
        zero_offset_deg=node.number("zero_offset_deg"),
        torque_constant_nm_per_a=node.number("torque_constant_nm_per_a", _POSITIVE),
        current_limit_a=node.number("current_limit_a", _Range(0, IQ_LIMIT_A, lo_open=True)),
        position_min_deg=node.number("position_min_deg"),
        position_max_deg=node.number("position_max_deg"),
        velocity_limit_dps=node.number("velocity_limit_dps", _POSITIVE),
        acceleration_limit_dps2=node.number("acceleration_limit_dps2", _POSITIVE),
        jerk_limit_dps3=node.number("jerk_limit_dps3", _POSITIVE),
        encoder_bits=node.integer("encoder_bits", _Range(12, 18)),
        kp_nm_per_deg=node.number("kp_nm_per_deg", _NON_NEGATIVE, required=torque_mode),
        kd_nm_per_dps=node.number("kd_nm_per_dps", _NON_NEGATIVE, required=torque_mode),
        temperature_limit_c=node.number("temperature_limit_c", _Range(0, 100, lo_open=True)),
        rotor_inertia_kgm2=rotor_inertia,
        viscous_friction_nm_per_dps=viscous,
        coulomb_friction_nm=coulomb,
        collision_threshold_nm=thresholds[0],
        collision_threshold_torque_nm=thresholds[1],
        power_on_window_deg=node.interval("power_on_window_deg") if node.has("power_on_window_deg") else None,
        brake=node.flag("brake"),
        emulation=_emulation(node.child("emulation", schema.EmulationConfig), rotor_inertia, viscous, coulomb),
    )
    if joint.position_min_deg >= joint.position_max_deg:
        raise node.error(
            "position_max_deg",
            f"must be greater than position_min_deg ({joint.position_min_deg:g}); found {joint.position_max_deg:g}",
        )
    window = joint.power_on_window_deg
    turn_deg = 360.0 / joint.gear_ratio
    if window is not None and window[1] - window[0] >= turn_deg:
        raise node.error(
            "power_on_window_deg",
            f"a window {window[1] - window[0]:g} deg wide cannot tell the motor's turns apart: one motor turn is "
            f"360 / gear_ratio = {turn_deg:g} deg of this joint, and the window must be narrower; found "
            f"[{window[0]:g}, {window[1]:g}]",
        )
    if node.has("homing"):
        joint = dataclasses.replace(joint, homing=_homing(node.child("homing", schema.HomingConfig), joint))
    return joint


def _to_thresholds(value: object) -> tuple[float, float]:
    """``collision_threshold_nm``: a number (both control modes) or ``{position: N, torque: N}``."""
    if not isinstance(value, Mapping):
        number = _to_number(value, _POSITIVE)
        return number, number
    unknown = sorted(str(k) for k in value if k not in _THRESHOLD_MODES)
    if unknown:
        raise _Invalid(f"unknown key {unknown[0]!r}; allowed keys: position, torque", f".{unknown[0]}")
    numbers = []
    for mode in _THRESHOLD_MODES:
        if mode not in value:
            raise _Invalid("required key is missing (a number, > 0; or give one number for both modes)", f".{mode}")
        try:
            numbers.append(_to_number(value[mode], _POSITIVE))
        except _Invalid as exc:
            raise _Invalid(exc.message, f".{mode}") from None
    return numbers[0], numbers[1]


def _collision_thresholds(node: _Node) -> tuple[float | None, float | None]:
    """The joint's collision thresholds in position and torque mode (None: not watched)."""
    if not node.has("collision_threshold_nm"):
        return None, None
    expected = "a number, > 0, or {position: N, torque: N}"
    return node._read("collision_threshold_nm", expected, _to_thresholds, None)


def _homing(node: _Node, joint: schema.JointConfig) -> schema.HomingConfig:
    stop = node.number("stop_deg", required=True)
    if joint.position_min_deg < stop < joint.position_max_deg:
        raise node.error(
            "stop_deg",
            f"a hard stop lies outside the joint's limits (<= position_min_deg {joint.position_min_deg:g} or >= "
            f"position_max_deg {joint.position_max_deg:g}); found {stop:g}",
        )
    back_off = node.number("back_off_deg", _POSITIVE)
    far = joint.position_max_deg if stop <= joint.position_min_deg else joint.position_min_deg
    homing = schema.HomingConfig(
        stop_deg=stop,
        speed_dps=node.number("speed_dps", _Range(0, joint.velocity_limit_dps, lo_open=True)),
        current_limit_a=node.number("current_limit_a", _Range(0, joint.current_limit_a, lo_open=True)),
        back_off_deg=back_off,
        max_travel_deg=node.number("max_travel_deg", _POSITIVE)
        if node.has("max_travel_deg")
        else abs(far - stop) + back_off,
        timeout_s=node.number("timeout_s", _POSITIVE),
    )
    return homing


def _joints(root: _Node, mode: schema.ControlMode) -> tuple[schema.JointConfig, ...]:
    nodes = root.children("joints", schema.JointConfig)
    joints = tuple(_joint(node, mode) for node in nodes)
    for i, joint in enumerate(joints):
        for earlier_index, earlier in enumerate(joints[:i]):
            for key, value in (("name", joint.name), ("motor_id", joint.motor_id)):
                if getattr(earlier, key) == value:
                    raise nodes[i].error(key, f"{value!r} is already used by joints[{earlier_index}]")
    return joints


def _inertia(node: _Node) -> schema.InertiaConfig:
    inertia = schema.InertiaConfig(
        ixx=node.number("ixx", _NON_NEGATIVE),
        ixy=node.number("ixy"),
        ixz=node.number("ixz"),
        iyy=node.number("iyy", _NON_NEGATIVE),
        iyz=node.number("iyz"),
        izz=node.number("izz", _NON_NEGATIVE),
    )
    moments = np.linalg.eigvalsh(np.array(inertia.matrix()))
    slack = _INERTIA_TOLERANCE * max(1.0, float(moments.max()))
    if moments.min() < -slack or 2 * moments.max() > moments.sum() + slack:
        raise node.error(
            "",
            f"not a physical inertia: principal moments {', '.join(f'{m:.6g}' for m in moments)} kg·m² must be "
            "non-negative and none larger than the sum of the other two",
        )
    return inertia


def _chain_joint(node: _Node) -> schema.ChainJointConfig:
    axis = node.vector3("axis")
    norm = math.hypot(*axis)
    if norm == 0:
        raise node.error("axis", "expected a non-zero vector; found [0, 0, 0]")
    return schema.ChainJointConfig(
        joint=node.text("joint"),
        axis=(axis[0] / norm, axis[1] / norm, axis[2] / norm),
        mass_kg=node.number("mass_kg", _NON_NEGATIVE),
        com_xyz_m=node.vector3("com_xyz_m"),
        inertia_kgm2=_inertia(node.child("inertia_kgm2", schema.InertiaConfig)),
        origin_xyz_m=node.vector3("origin_xyz_m"),
        origin_rpy_rad=node.vector3("origin_rpy_rad"),
        link=node.text("link") if node.has("link") else "",
    )


def _model(root: _Node, joints: Sequence[schema.JointConfig], base_dir: Path) -> schema.ModelConfig:
    node = root.child("model", schema.ModelConfig)
    if node.has("urdf") == node.has("chain"):
        raise node.error("", "give exactly one of urdf (a file) or chain (a list of joints)")
    gravity = node.vector3("gravity_m_s2")
    if node.has("urdf"):
        if node.has("tip_xyz_m"):
            raise node.error("tip_xyz_m", "allowed only with chain (a URDF names its own frames)")
        urdf = (base_dir / node.text("urdf")).resolve()
        if not urdf.is_file():
            raise node.error("urdf", f"file not found: {urdf}")
        try:
            names = revolute_joints(urdf)
        except ValueError as exc:
            raise node.error("urdf", str(exc)) from None
        _match_joints(root.source, [(name, node.key_path("urdf")) for name in names], joints, str(urdf))
        return schema.ModelConfig(urdf=urdf, gravity_m_s2=gravity)

    nodes = node.children("chain", schema.ChainJointConfig)
    chain = tuple(_chain_joint(n) for n in nodes)
    named = [(c.joint, n.key_path("joint")) for c, n in zip(chain, nodes, strict=True)]
    _match_joints(root.source, named, joints, "model.chain")
    frames = {c.joint for c in chain} | {"tip"}
    for c, n in zip(chain, nodes, strict=True):
        if c.link_name in frames:
            raise n.error("link", f"frame name {c.link_name!r} is already used (joint names, link names and 'tip')")
        frames.add(c.link_name)
    tip = node.vector3("tip_xyz_m") if node.has("tip_xyz_m") else None
    return schema.ModelConfig(chain=chain, gravity_m_s2=gravity, tip_xyz_m=tip)


def _match_joints(
    source: str, model_joints: Sequence[tuple[str, str]], joints: Sequence[schema.JointConfig], model_name: str
) -> None:
    """Check that the model's joints (name, key path) and the configured joints are the same set of names."""
    configured = [j.name for j in joints]
    seen: set[str] = set()
    for name, key_path in model_joints:
        if name in seen:
            raise ConfigError(source, key_path, f"joint {name!r} appears twice in {model_name}")
        if name not in configured:
            raise ConfigError(
                source, key_path, f"{model_name} joint {name!r} is not configured (joints: {', '.join(configured)})"
            )
        seen.add(name)
    for i, name in enumerate(configured):
        if name not in seen:
            found = ", ".join(n for n, _ in model_joints) or "none"
            raise ConfigError(
                source, f"joints[{i}].name", f"joint {name!r} is not a revolute joint of {model_name} (found: {found})"
            )


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
    root = _Node(data, source, "", schema.ArmConfig, hidden=["source"])
    control = _control(root.child("control", schema.ControlConfig))
    joints = _joints(root, control.mode)
    return schema.ArmConfig(
        name=root.text("name"),
        bus=_bus(root),
        control=control,
        model=_model(root, joints, Path(base_dir) if base_dir is not None else Path.cwd()),
        safety=_safety(root.child("safety", schema.SafetyConfig), control),
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


def write_joint_values(
    source: str | os.PathLike[str],
    target: str | os.PathLike[str],
    key: str,
    values: Mapping[str, float | Mapping[str, float]],
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
        joints[name][key] = float(value) if isinstance(value, int | float) else {k: float(v) for k, v in value.items()}
    model = data.get("model", {})
    if isinstance(model, dict) and "urdf" in model:
        urdf = (source_path.parent / str(model["urdf"])).resolve()
        model["urdf"] = os.path.relpath(urdf, target_path.resolve().parent)
    text = yaml.safe_dump(data, sort_keys=False, allow_unicode=True)
    parse_config(yaml.safe_load(text), str(target_path), target_path.resolve().parent)
    target_path.write_text(text, encoding="utf-8")
    return load_config(target_path)
