"""The ``joints`` section of a configuration: each joint, with its emulated drive and its homing.

The keys a joint needs depend on the control mode (torque mode needs the PD gains), and some checks span keys
(the power-on window must be narrower than one motor turn; a hard stop lies outside the joint's limits).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence
from dataclasses import fields

from motion.config import schema
from motion.config.actuators import ACTUATORS
from motion.config.nodes import NON_NEGATIVE, POSITIVE, Invalid, Node, OneOf, Range, to_number
from motion.protocol import WireProtocol
from motion.protocol.messages import Command
from motion.protocol.table import MOTOR_ID_MAX, MOTOR_ID_MIN, Direction, field_range
from motion.transmission import IQ_LIMIT_A

# An emulated drive's PI gains (0x30 / 0x31: uint8 units) and acceleration (0x34), as the table declares them.
_GAIN_LO, _GAIN_HI = field_range(Command.WRITE_PID_RAM, Direction.REQUEST, WireProtocol.CAN, "angle_kp")
_ACCELERATION_LO, _ACCELERATION_HI = field_range(
    Command.WRITE_ACCELERATION_RAM, Direction.REQUEST, WireProtocol.CAN, "acceleration_dps2"
)

#: The keys of a per-mode ``collision_threshold_nm``, in the order of its two numbers.
_THRESHOLD_MODES = ("position", "torque")
#: A ``collision_threshold_nm`` of this word: the joint is watched with the collision bound alone in force (kept as 0).
BOUND_ALONE = "bound"


def _emulation(node: Node, rotor_inertia: float, viscous: float, coulomb: float) -> schema.EmulationConfig:
    node.defaults(rotor_inertia_kgm2=rotor_inertia, viscous_friction_nm_per_dps=viscous, coulomb_friction_nm=coulomb)
    pid = node.child("pid", schema.EmulatedPidConfig)
    gain = Range(_GAIN_LO, _GAIN_HI)
    return schema.EmulationConfig(
        rotor_inertia_kgm2=node.number("rotor_inertia_kgm2", NON_NEGATIVE),
        viscous_friction_nm_per_dps=node.number("viscous_friction_nm_per_dps", NON_NEGATIVE),
        coulomb_friction_nm=node.number("coulomb_friction_nm", NON_NEGATIVE),
        torque_constant_nm_per_a=(
            node.number("torque_constant_nm_per_a", POSITIVE) if node.has("torque_constant_nm_per_a") else None
        ),
        pid=schema.EmulatedPidConfig(**{f.name: pid.integer(f.name, gain) for f in fields(schema.EmulatedPidConfig)}),
        acceleration_dps2=node.integer("acceleration_dps2", Range(_ACCELERATION_LO, _ACCELERATION_HI)),
    )


def _actuator(node: Node) -> str | None:
    """The joint's ``actuator:`` model, whose published figures become the defaults of ``gear_ratio``,
    ``torque_constant_nm_per_a`` and ``current_limit_a`` (:mod:`motion.config.actuators`); None without the key."""
    if not node.has("actuator"):
        return None
    model = node.text("actuator")
    actuator = ACTUATORS.get(model)
    if actuator is None:
        raise node.error("actuator", f"one of the models of the table ({', '.join(ACTUATORS)}); found {model!r}")
    node.defaults(gear_ratio=actuator.gear_ratio, torque_constant_nm_per_a=actuator.torque_constant_nm_per_a)
    peak = actuator.peak_current_a
    if peak is not None and peak <= IQ_LIMIT_A:
        node.defaults(current_limit_a=peak)
    elif not node.has("current_limit_a"):
        why = (
            "its peak current is not in the table"
            if peak is None
            else f"its peak {peak:g} A exceeds the {IQ_LIMIT_A:g} A the torque command carries"
        )
        raise node.error(
            "current_limit_a", f"a current limit for the {model} (required: {why}), 0 < x <= {IQ_LIMIT_A:g} A"
        )
    return model


def _joint(node: Node, mode: schema.ControlMode) -> schema.JointConfig:
    bandwidth = node.number("bandwidth_hz", POSITIVE) if node.has("bandwidth_hz") else None
    if bandwidth is not None and (node.has("kp_nm_per_deg") or node.has("kd_nm_per_dps")):
        raise node.error(
            "bandwidth_hz",
            "gives the torque-mode gains (kp_nm_per_deg and kd_nm_per_dps from the arm's inertia): give either "
            "bandwidth_hz or both gains, not both",
        )
    torque_mode = mode.traits.host_torque and bandwidth is None  # (per-joint gains, unless from a bandwidth)
    actuator = _actuator(node)
    rotor_inertia = node.number("rotor_inertia_kgm2", NON_NEGATIVE)
    viscous = node.number("viscous_friction_nm_per_dps", NON_NEGATIVE)
    coulomb = node.number("coulomb_friction_nm", NON_NEGATIVE)
    thresholds = _collision_thresholds(node)
    joint = schema.JointConfig(
        name=node.text("name"),
        motor_id=node.integer("motor_id", Range(MOTOR_ID_MIN, MOTOR_ID_MAX)),
        gear_ratio=node.number("gear_ratio", POSITIVE),
        direction=node.integer("direction", OneOf((1, -1))),
        zero_offset_deg=node.number("zero_offset_deg"),
        torque_constant_nm_per_a=node.number("torque_constant_nm_per_a", POSITIVE),
        current_limit_a=node.number("current_limit_a", Range(0, IQ_LIMIT_A, lo_open=True)),
        position_min_deg=node.number("position_min_deg"),
        position_max_deg=node.number("position_max_deg"),
        velocity_limit_dps=node.number("velocity_limit_dps", POSITIVE),
        acceleration_limit_dps2=node.number("acceleration_limit_dps2", POSITIVE),
        jerk_limit_dps3=node.number("jerk_limit_dps3", POSITIVE),
        encoder_bits=node.integer("encoder_bits", Range(12, 18)),
        kp_nm_per_deg=node.number("kp_nm_per_deg", NON_NEGATIVE, required=torque_mode),
        kd_nm_per_dps=node.number("kd_nm_per_dps", NON_NEGATIVE, required=torque_mode),
        bandwidth_hz=bandwidth,
        temperature_limit_c=node.number("temperature_limit_c", Range(0, 100, lo_open=True)),
        rotor_inertia_kgm2=rotor_inertia,
        viscous_friction_nm_per_dps=viscous,
        coulomb_friction_nm=coulomb,
        collision_threshold_nm=thresholds[0],
        collision_threshold_torque_nm=thresholds[1],
        power_on_window_deg=node.interval("power_on_window_deg") if node.has("power_on_window_deg") else None,
        brake=node.flag("brake"),
        actuator=actuator,
        emulation=_emulation(node.child("emulation", schema.EmulationConfig), rotor_inertia, viscous, coulomb),
        bus=node.text("bus"),
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


def _to_threshold(value: object) -> float:
    """One mode's threshold: a number > 0, or ``bound`` (0: the bound alone in force)."""
    if value == BOUND_ALONE:
        return 0.0
    if isinstance(value, str):
        raise Invalid(f"expected a number (> 0) or {BOUND_ALONE}; found {value!r}")
    return to_number(value, POSITIVE)


def _to_thresholds(value: object) -> tuple[float, float]:
    """``collision_threshold_nm``: a number or ``bound`` (both control modes), or ``{position: N, torque: N}``."""
    if not isinstance(value, Mapping):
        number = _to_threshold(value)
        return number, number
    unknown = sorted(str(k) for k in value if k not in _THRESHOLD_MODES)
    if unknown:
        raise Invalid(f"unknown key {unknown[0]!r}; allowed keys: position, torque", f".{unknown[0]}")
    numbers = []
    for mode in _THRESHOLD_MODES:
        if mode not in value:
            raise Invalid(
                f"required key is missing (a number, > 0, or {BOUND_ALONE}; or give one for both modes)", f".{mode}"
            )
        try:
            numbers.append(_to_threshold(value[mode]))
        except Invalid as exc:
            raise Invalid(exc.message, f".{mode}") from None
    return numbers[0], numbers[1]


def _collision_thresholds(node: Node) -> tuple[float | None, float | None]:
    """The joint's collision thresholds in position and torque mode (None: not watched)."""
    if not node.has("collision_threshold_nm"):
        return None, None
    expected = f"a number, > 0, {BOUND_ALONE}, or {{position: N, torque: N}}"
    return node.read("collision_threshold_nm", expected, _to_thresholds, None)


def _homing(node: Node, joint: schema.JointConfig) -> schema.HomingConfig:
    stop = node.number("stop_deg", required=True)
    if joint.position_min_deg < stop < joint.position_max_deg:
        raise node.error(
            "stop_deg",
            f"a hard stop lies outside the joint's limits (<= position_min_deg {joint.position_min_deg:g} or >= "
            f"position_max_deg {joint.position_max_deg:g}); found {stop:g}",
        )
    back_off = node.number("back_off_deg", POSITIVE)
    far = joint.position_max_deg if stop <= joint.position_min_deg else joint.position_min_deg
    homing = schema.HomingConfig(
        stop_deg=stop,
        speed_dps=node.number("speed_dps", Range(0, joint.velocity_limit_dps, lo_open=True)),
        current_limit_a=node.number("current_limit_a", Range(0, joint.current_limit_a, lo_open=True)),
        back_off_deg=back_off,
        max_travel_deg=node.number("max_travel_deg", POSITIVE)
        if node.has("max_travel_deg")
        else abs(far - stop) + back_off,
        timeout_s=node.number("timeout_s", POSITIVE),
    )
    return homing


def joints_section(
    root: Node, mode: schema.ControlMode, buses: Sequence[schema.BusConfig]
) -> tuple[schema.JointConfig, ...]:
    """The ``joints`` list, each joint read for control mode ``mode`` and placed on one of ``buses``; no two share a
    name, nor a motor id on one bus."""
    nodes = root.children("joints", schema.JointConfig)
    joints = tuple(_on_bus(node, _joint(node, mode), buses) for node in nodes)
    for i, joint in enumerate(joints):
        for earlier_index, earlier in enumerate(joints[:i]):
            if earlier.name == joint.name:
                raise nodes[i].error("name", f"{joint.name!r} is already used by joints[{earlier_index}]")
            if earlier.address == joint.address:
                on = f" on bus {joint.bus}" if joint.bus else ""
                raise nodes[i].error(
                    "motor_id", f"{joint.motor_id!r} is already used by joints[{earlier_index}]{on} (ids are per bus)"
                )
    return joints


def _on_bus(node: Node, joint: schema.JointConfig, buses: Sequence[schema.BusConfig]) -> schema.JointConfig:
    """``joint`` placed on the bus its ``bus`` key names: required with several buses, refused with the one ``bus``
    section, optional with one entry under ``buses``."""
    names = [b.name for b in buses]
    if not names[0]:  # the one `bus:` section
        if joint.bus:
            raise node.error(
                "bus", f"names a bus of `buses:`, but this arm has the one `bus:` section; found {joint.bus!r}"
            )
        return joint
    if not joint.bus:
        if len(names) > 1:
            raise node.error("bus", f"required key is missing (the bus the drive is on, one of {', '.join(names)})")
        return dataclasses.replace(joint, bus=names[0])
    if joint.bus not in names:
        raise node.error("bus", f"unknown bus {joint.bus!r}; the buses are {', '.join(names)}")
    return dataclasses.replace(joint, bus_index=names.index(joint.bus))
