"""The arm-wide sections of a configuration: ``bus`` (or ``buses``), ``control``, ``safety`` and ``model`` (the
joints' own section is :mod:`motion.config.joints`).

Each parser reads one :class:`~motion.config.nodes.Node` into its schema dataclass, adding the ranges and the checks
that span keys (``comply`` needs torque mode; the model names exactly the configured joints).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

from motion.config import schema
from motion.config.nodes import NON_NEGATIVE, POSITIVE, Node, OneOf, Range
from motion.config.urdf import revolute_joints
from motion.errors import ConfigError
from motion.protocol import WireProtocol
from motion.protocol.table import RS485_BAUDRATES, ProtocolFamily

#: Relative slack for the physical-consistency check of an inertia matrix.
_INERTIA_TOLERANCE = 1e-9
#: The longest communication-loss time accepted, ms (a minute: beyond it the protection protects nothing).
LINK_TIMEOUT_MAX_MS = 60_000


def buses_section(root: Node) -> tuple[schema.BusConfig, ...]:
    """``bus`` (the arm's one bus) or ``buses`` (named buses, each a bus section of its own)."""
    if root.has("bus") == root.has("buses"):
        found = "both" if root.has("bus") else "neither"
        raise root.error("bus", f"give bus (one bus) or buses (named buses, each a bus section); found {found}")
    if root.has("bus"):
        return (_bus(lambda *kinds, extra: root.child("bus", *kinds, extra=extra), ""),)
    return tuple(
        _bus(lambda *kinds, extra, name=name: root.entry("buses", name, *kinds, extra=extra), name)
        for name in root.names("buses")
    )


def _bus(section: Callable[..., Node], name: str) -> schema.BusConfig:
    """One bus section (``section(*kinds, extra=...)`` reads it): the keys of the CAN or the RS485 bus, as its
    ``transport`` chooses."""
    kinds: dict[WireProtocol, type[schema.BusConfig]] = {
        kind.transport: kind for kind in (schema.CanBusConfig, schema.Rs485BusConfig)
    }
    # Read `transport` with the keys of every bus kind allowed, then re-read strictly with the chosen kind's keys.
    transport = section(*kinds.values(), extra=["transport"]).choice("transport", WireProtocol)
    node = section(kinds[transport], extra=["transport"])
    if transport is WireProtocol.CAN:
        return schema.CanBusConfig(
            interface=node.text("interface"),
            channel=node.text("channel"),
            bitrate=node.integer("bitrate", OneOf((500_000, 1_000_000))),
            protocol=node.choice("protocol", schema.ProtocolSetting),
            name=name,
        )
    protocol = node.choice("protocol", schema.ProtocolSetting)
    # the baud rates of the generation named, or of either with auto
    families = list(ProtocolFamily) if protocol is schema.ProtocolSetting.AUTO else [ProtocolFamily(protocol.value)]
    baudrates = sorted({rate for family in families for rate in RS485_BAUDRATES[family]})
    return schema.Rs485BusConfig(
        port=node.text("port"),
        baudrate=node.integer("baudrate", OneOf(tuple(baudrates))),
        protocol=protocol,
        name=name,
    )


def control_section(node: Node) -> schema.ControlConfig:
    """The ``control`` section (an unquoted ``halt_policy: off`` arrives as YAML 1.1's False)."""
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
        rate_hz=node.number("rate_hz", Range(1, 1000)),
        gravity_feedforward=node.flag("gravity_feedforward"),
        inertia_feedforward=node.flag("inertia_feedforward"),
        rate_margin=node.number("rate_margin", Range(1, 10)),
        goal_tolerance_deg=node.number("goal_tolerance_deg", Range(0, 10)),
        goal_settle_s=node.number("goal_settle_s", Range(0, 10)),
        goal_time_s=node.number("goal_time_s", Range(0, 60)),
    )


def safety_section(node: Node, control: schema.ControlConfig) -> schema.SafetyConfig:
    """The ``safety`` section; ``control`` for what depends on the mode (``comply`` needs torque mode)."""
    reaction = (
        node.choice("collision_reaction", schema.HaltPolicy, false_alias=schema.HaltPolicy.OFF)
        if node.has("collision_reaction")
        else None
    )
    if reaction is schema.HaltPolicy.COMPLY and not control.mode.traits.host_torque:
        raise node.error(
            "collision_reaction",
            f"comply needs control.mode torque (it streams gravity compensation); found mode {control.mode.value}",
        )
    link_timeout = (
        node.number("link_timeout_ms", Range(0, LINK_TIMEOUT_MAX_MS)) if node.has("link_timeout_ms") else None
    )
    problem = schema.link_timeout_problem(link_timeout, control.rate_hz)
    if problem is not None:
        raise node.error("link_timeout_ms", problem)
    return schema.SafetyConfig(
        following_error_deg=node.number("following_error_deg", POSITIVE),
        min_voltage_v=node.number("min_voltage_v", Range(0, 60, lo_open=True)),
        reply_timeout_ms=node.number("reply_timeout_ms", Range(0, 1000, lo_open=True)),
        max_missed_replies=node.integer("max_missed_replies", Range(0, 100)),
        collision_reaction=reaction,
        collision_observer_gain_per_s=node.number("collision_observer_gain_per_s", Range(0, 10000, lo_open=True)),
        collision_window_s=node.number("collision_window_s", Range(0, 1)),
        link_timeout_ms=link_timeout,
    )


def _inertia(node: Node) -> schema.InertiaConfig:
    inertia = schema.InertiaConfig(
        ixx=node.number("ixx", NON_NEGATIVE),
        ixy=node.number("ixy"),
        ixz=node.number("ixz"),
        iyy=node.number("iyy", NON_NEGATIVE),
        iyz=node.number("iyz"),
        izz=node.number("izz", NON_NEGATIVE),
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


def _chain_joint(node: Node) -> schema.ChainJointConfig:
    axis = node.vector3("axis")
    norm = math.hypot(*axis)
    if norm == 0:
        raise node.error("axis", "expected a non-zero vector; found [0, 0, 0]")
    return schema.ChainJointConfig(
        joint=node.text("joint"),
        axis=(axis[0] / norm, axis[1] / norm, axis[2] / norm),
        mass_kg=node.number("mass_kg", NON_NEGATIVE),
        com_xyz_m=node.vector3("com_xyz_m"),
        inertia_kgm2=_inertia(node.child("inertia_kgm2", schema.InertiaConfig)),
        origin_xyz_m=node.vector3("origin_xyz_m"),
        origin_rpy_rad=node.vector3("origin_rpy_rad"),
        link=node.text("link") if node.has("link") else "",
    )


def model_section(root: Node, joints: Sequence[schema.JointConfig], base_dir: Path) -> schema.ModelConfig:
    """The ``model`` section: a URDF (relative to ``base_dir``) or a chain, whose joints are exactly ``joints``."""
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
