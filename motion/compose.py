"""Composition: the one place that builds the running parts of an arm from its configuration — bus, controller, rate
check, supervisor (the matching emulated drives, in simulated time or on a wire, are :mod:`motion.emulator.arm`'s).
The API, the CLI, the tests' rig and the bench all assemble an arm through these functions, so they agree on every
condition (which feed-forward, which wire protocol, which safety settings).
"""

from __future__ import annotations

import dataclasses
import logging
import math
from collections.abc import Callable, Collection, Mapping, Sequence
from typing import TYPE_CHECKING

import numpy as np

from motion.config.schema import (
    ArmConfig,
    BusConfig,
    CanBusConfig,
    JointConfig,
    ProtocolSetting,
    link_timeout_problem,
)
from motion.control import identify
from motion.control.axes import AxisSpec
from motion.control.clock import Clock
from motion.control.controller import Controller, ControllerOptions, Feedforward
from motion.control.drive_record import same_power_on
from motion.control.drivesetup import DriveSetup, link_timeout_ms
from motion.control.family import FAMILIES
from motion.control.ratecheck import DEFAULT_MARGIN, RateCheck, RateError, measure_rate
from motion.control.stability import (
    MASS_LOW,
    ROTOR_INERTIA_LOW,
    JointLoop,
    StabilityError,
    StabilityReport,
    gains_for_bandwidth,
    stability_report,
)
from motion.control.startup import read_angles, read_runtimes
from motion.control.tracking import PositionLoopFit
from motion.control.turns import (
    JointTurns,
    Source,
    TurnError,
    TurnRecord,
    assumed_span,
    resolve_turns,
    turn_joint_deg,
)
from motion.control.unwrap import check_unwrapping
from motion.errors import ConfigError, TransportError
from motion.keep import drive_record_for
from motion.protocol import WireProtocol
from motion.protocol.generation import GENERATIONS
from motion.protocol.table import ADDRESS_STRIDE, RS485_BAUDRATES, ProtocolFamily, split_address
from motion.safety import SafetySettings, Supervisor
from motion.safety.watchdog import CollisionObserver, Watchdog
from motion.trajectory import JointLimits
from motion.transmission import FloatArray
from motion.transport import Transport, open_transport
from motion.transport.buses import several
from motion.transport.identity import read_identities

if TYPE_CHECKING:
    from kinematics.figure import ArmFigure

logger = logging.getLogger("motion.config")


def joint_limits(config: ArmConfig) -> JointLimits:
    """Planning limits of every joint (joint side)."""
    j = config.joints
    return JointLimits(
        names=config.joint_names,
        position_min_deg=tuple(x.position_min_deg for x in j),
        position_max_deg=tuple(x.position_max_deg for x in j),
        velocity_dps=tuple(x.velocity_limit_dps for x in j),
        acceleration_dps2=tuple(x.acceleration_limit_dps2 for x in j),
        jerk_dps3=tuple(x.jerk_limit_dps3 for x in j),
    )


def axis_specs(
    config: ArmConfig, family: ProtocolFamily | Sequence[ProtocolFamily] = ProtocolFamily.V2
) -> tuple[AxisSpec, ...]:
    """The controller's view of every joint, for drives of ``family`` (a sequence: each bus's, in the order of
    ``buses:``): a drive that reports its output shaft (V3) has the joint's whole reduction inside (the actuator's
    output is the joint; :mod:`motion.control.family`)."""
    families = [family] * len(config.buses) if isinstance(family, str) else list(family)
    return tuple(
        AxisSpec(
            j.name,
            j.address,
            j.encoder_bits,
            j.kp_nm_per_deg,
            j.kd_nm_per_dps,
            drive_gear_ratio=j.gear_ratio if FAMILIES[families[j.bus_index]].output_shaft else 1.0,
            label=j.drive_label,
        )
        for j in config.joints
    )


def bus_wires(config: ArmConfig) -> tuple[WireProtocol, ...]:
    """The wire protocol of each bus of the arm, in the order of ``buses:`` (the bus index of the addresses)."""
    return tuple(bus.transport for bus in config.buses)


def controller_options(config: ArmConfig) -> ControllerOptions:
    """Loop settings from ``control:``."""
    return ControllerOptions(mode=config.control.mode, rate_hz=config.control.rate_hz, wires=bus_wires(config))


def opening_families(config: ArmConfig) -> tuple[ProtocolFamily, ...]:
    """The generation each bus opens in (in the order of ``buses:``) before :func:`negotiate_family` asks the
    drives: the one its ``protocol`` names; with ``auto`` the one the other buses name (where they name one), else
    the older, unless its RS485 baud rate is one only V3 drives run at."""
    named = {ProtocolFamily(b.protocol.value) for b in config.buses if b.protocol is not ProtocolSetting.AUTO}
    return tuple(
        (named.copy().pop() if len(named) == 1 else _opening(bus))
        if bus.protocol is ProtocolSetting.AUTO
        else ProtocolFamily(bus.protocol.value)
        for bus in config.buses
    )


def _opening(bus: BusConfig) -> ProtocolFamily:
    """The generation a bus whose ``protocol`` is ``auto`` opens in."""
    if not isinstance(bus, CanBusConfig) and bus.baudrate not in RS485_BAUDRATES[ProtocolFamily.V2]:
        return ProtocolFamily.V3
    return ProtocolFamily.V2


def open_bus(config: ArmConfig, **overrides: object) -> Transport:
    """Open the configured bus (every bus of an arm on several, as one :class:`~motion.transport.buses.Buses`), each
    speaking its configured protocol generation (``auto``: :func:`opening_families`, until :func:`negotiate_family`);
    ``overrides`` replace configured values (e.g. ``channel=`` of an emulator): a value for every bus, or a mapping of
    bus names to each one's (``channel={"left": ..., "right": ...}``).

    Raises:
        TransportError: a bus or port could not be opened (those opened before are closed again).
    """
    opened: list[Transport] = []
    try:
        for bus, family in zip(config.buses, opening_families(config), strict=True):
            mine = {
                key: value[bus.name] if isinstance(value, Mapping) else value
                for key, value in overrides.items()
                if not isinstance(value, Mapping) or bus.name in value
            }
            opened.append(open_transport(bus.transport.value, **(bus.settings() | {"family": family} | mine)))
        return several(opened, [bus.name for bus in config.buses])
    except BaseException:
        for transport in opened:
            transport.close()
        raise


#: Connect: the window in which the configured drives answer the generation check on a CAN bus, s.
GENERATION_CHECK_WINDOW_S = 0.1
#: ... and how often the drives that have not answered are asked (one that answers later than the window on a busy
#: host would otherwise be taken for absent, and its generation for the older one).
GENERATION_CHECK_ATTEMPTS = 3


def negotiate_family(bus: Transport, config: ArmConfig) -> Transport:
    """The transport that speaks to the configured drives in their protocol generation (issue 17), each bus in its
    own drives' (an arm on several buses may have drives of one generation on one bus, of the other on another):
    ``bus`` itself, or one over the same links in the generations found (:meth:`Transport.with_families`, which takes
    the links over).

    The configured drives are asked for their status: on CAN (a real bus or a simulated one) once at the frame level,
    their reply ids telling the generation (:mod:`motion.transport.detect`); on RS485 in each generation's framing in
    turn (a drive stays silent to the other framing, whose checksums fail). Drives that do not answer are left to the
    connect's own reads (which name them). A bus's ``protocol: auto`` follows what answered on it (nothing: the
    generation it opened in, :func:`opening_families`); ``v2`` / ``v3`` are checked against it.

    Raises:
        TransportError: drives of both generations on one bus (each named), or drives that answer in the other
            generation than their bus's ``protocol`` says.
    """
    ids = [j.address for j in config.joints]
    found: dict[int, ProtocolFamily] = {}
    for _ in range(GENERATION_CHECK_ATTEMPTS):  # (a reply later than the window on a busy host: asked again)
        answers = bus.probe_families([i for i in ids if i not in found], GENERATION_CHECK_WINDOW_S)
        found.update(answers or {})
        if answers is None or len(found) == len(ids):  # (None: this transport cannot tell)
            break
    wanted: list[ProtocolFamily] = []
    for index, bus_config in enumerate(config.buses):
        here = {j.address: found[j.address] for j in config.joints_on(index) if j.address in found}
        on_bus = set(here.values())
        where = f"bus {bus_config.name}" if bus_config.name else "one bus"
        if len(on_bus) > 1:
            raise TransportError(
                f"drives of both protocol generations on {where} ({_families_text(here, config)}): refused"
            )
        setting = bus_config.protocol
        if setting is not ProtocolSetting.AUTO and on_bus and on_bus != {ProtocolFamily(setting.value)}:
            key = f"buses.{bus_config.name}.protocol" if bus_config.name else "bus.protocol"
            (told,) = on_bus
            raise TransportError(
                f"{key} is {setting.value}, but the drives answer in the {told.value} protocol "
                f"({_families_text(here, config)}): set {key} to {told.value} or auto"
            )
        wanted.append(on_bus.pop() if on_bus else bus.families[index])
    spoken = bus.with_families(wanted)
    if found:
        labels = {j.address: j.drive_label for j in config.joints}
        groups: dict[tuple[WireProtocol, ProtocolFamily], list[int]] = {}  # (identity reads per wire and generation)
        for address in sorted(found):
            index = split_address(address)[0]
            groups.setdefault((config.buses[index].transport, wanted[index]), []).append(address)
        for (wire, family), on in groups.items():
            if described := describe_drives(spoken, on, wire, labels):
                logger.info("drives of the %s: %s", GENERATIONS[family].title, described)
    return spoken


def _families_text(found: Mapping[int, ProtocolFamily], config: ArmConfig) -> str:
    """``"motor 1: v2, motor 2: v3"`` (``"motor 2 on bus right: v3"`` on an arm of several buses): for an error that
    names each drive's generation."""
    labels = {j.address: j.drive_label for j in config.joints}
    return ", ".join(f"{labels.get(a, f'motor {a}')}: {f.value}" for a, f in sorted(found.items()))


def describe_drives(
    bus: Transport, ids: Sequence[int], wire: WireProtocol, labels: Mapping[int, str] | None = None
) -> str:
    """``"motor 1 X8S2V10 firmware 20240528, ..."``: what each drive tells of its model and firmware, as read now
    (a drive that does not answer is named so) and kept in ``bus.identities``; empty where their generation (of
    ``ids``, all of one: ``bus.family_of``) has no such read on ``wire``. ``labels`` name the drives by address
    (``"motor 1 on bus left"``).

    Raises:
        TransportError: the bus failed.
    """
    if not ids or not GENERATIONS[bus.family_of(ids[0])].identity_reads[wire]:
        return ""
    told = read_identities(bus, ids, wire, GENERATION_CHECK_WINDOW_S)
    bus.identities.update(told)
    named = labels or {}
    return ", ".join(f"{named.get(i, f'motor {i}')} {told[i].text if i in told else '(no answer)'}" for i in ids)


def feedforward_for(config: ArmConfig) -> Feedforward | None:
    """The feed-forward the configuration asks for: in torque mode, gravity and/or inertia from the Pinocchio model
    (``control.gravity_feedforward``, ``control.inertia_feedforward``); in position mode none (the drive closes the
    loop)."""
    control = config.control
    if not control.mode.traits.host_torque or not (control.gravity_feedforward or control.inertia_feedforward):
        return None
    from kinematics import build_arm, feedforward  # noqa: PLC0415 - Pinocchio only where an arm needs it

    return feedforward(build_arm(config), gravity=control.gravity_feedforward, inertia=control.inertia_feedforward)


def inertia_for(config: ArmConfig) -> Callable[[FloatArray], FloatArray] | None:
    """Torque mode: the arm's mass matrix as a function of the joint angles, kg·m², for the model of the PD loop's
    tracking (:mod:`motion.control.tracking`); None in position mode.

    The links' share comes from the arm's model; the rotors', ``gear_ratio² × rotor inertia`` on the diagonal, from
    the joints' ``rotor_inertia_kgm2`` (on a light wrist joint it is most of the inertia the PD loop
    moves).
    """
    if not config.control.mode.traits.host_torque:
        return None
    from kinematics import build_arm, mass_matrix  # noqa: PLC0415 - Pinocchio only where an arm needs it

    arm = build_arm(config)
    per_deg = math.pi / 180.0  # mass_matrix is in N·m per deg/s²
    rotors = np.diag([j.gear_ratio**2 * j.rotor_inertia_kgm2 for j in config.joints])

    def inertia(q_deg: FloatArray) -> FloatArray:
        mass: FloatArray = mass_matrix(arm, q_deg) / per_deg + rotors
        return mass

    return inertia


def collision_observer_for(config: ArmConfig, *, always: bool = False) -> CollisionObserver | None:
    """The momentum observer of the arm's Pinocchio model (friction, rotor inertia and gain from the configuration)
    when a joint has a ``collision_threshold_nm``, or ``always`` (to record residuals, e.g. to calibrate thresholds);
    else None."""
    if not (always or config.collision_watched):
        return None
    from kinematics.observer import momentum_observer  # noqa: PLC0415 - Pinocchio only where an arm needs it

    return momentum_observer(config)


def arm_figure(config: ArmConfig) -> ArmFigure:
    """The arm's shape for the live view (built in the view's process; see :mod:`motion.view`)."""
    from kinematics.figure import ArmFigure  # noqa: PLC0415 - Pinocchio only where an arm needs it

    return ArmFigure(config)


def velocity_torques_for(config: ArmConfig) -> Callable[[FloatArray, FloatArray], FloatArray]:
    """The arm's velocity-product torques C(q, q̇) q̇ (Coriolis and centripetal), N·m, as a function of the joint
    angles and speeds (deg, deg/s), for the model of the PD loop's tracking in torque mode."""
    from kinematics import build_arm, feedforward  # noqa: PLC0415 - as above

    dynamics = feedforward(build_arm(config), gravity=False, inertia=True)
    still = np.zeros(len(config.joints))
    return lambda q_deg, qd_dps: dynamics(q_deg, qd_dps, still)


def gravity_for(config: ArmConfig) -> Feedforward:
    """Gravity alone, g(q): the ``comply`` reaction to a collision streams it (torque mode), and a halted joint whose
    drive's hold swings it is released only where it cannot make the joint fall (:mod:`motion.safety.halted`)."""
    from kinematics import build_arm, feedforward  # noqa: PLC0415 - as above

    return feedforward(build_arm(config), gravity=True, inertia=False)


def build_controller(
    config: ArmConfig, bus: Transport, *, feedforward: Feedforward | None = None, clock: Clock | None = None
) -> Controller:
    """A controller for ``config`` on ``bus`` (call ``read_positions()`` before moving). In torque mode with a
    feed-forward, the tracking model learns the joints' inertia from the arm's model.

    Raises:
        ConfigError: a joint's velocity limit turns its motor half a turn or more per cycle on a drive whose encoder is
            unwrapped (:func:`motion.control.unwrap.check_unwrapping`: the figures and the rates that hold).
    """
    check_unwrapping(config, [FAMILIES[bus.family_of(j.address)].angle_every_cycle for j in config.joints])
    controller = Controller(
        axis_specs(config, [bus.family_of(k * ADDRESS_STRIDE) for k in range(len(config.buses))]),
        config.transmission(),
        joint_limits(config),
        bus,
        options=controller_options(config),
        feedforward=feedforward,
        clock=clock,
    )
    inertia = inertia_for(config) if feedforward is not None else None
    if inertia is not None:
        controller.tracking.set_inertia(
            inertia, fed_forward=config.control.inertia_feedforward, bias=velocity_torques_for(config)
        )
    return controller


def torque_loops(config: ArmConfig) -> tuple[JointLoop, ...]:
    """Every joint's torque-mode loop as :mod:`motion.control.stability` checks it: its gains and the inertia it sees
    across the joint limits (:func:`kinematics.envelope.inertia_envelope`, at the stated bounds' low end)."""
    from kinematics import build_arm  # noqa: PLC0415 - Pinocchio only where a check needs it
    from kinematics.envelope import inertia_envelope  # noqa: PLC0415

    envelope = inertia_envelope(build_arm(config), config, mass_low=MASS_LOW, rotor_low=ROTOR_INERTIA_LOW)
    return tuple(
        JointLoop(j.name, j.kp_nm_per_deg, j.kd_nm_per_dps, float(low), float(high))
        for j, low, high in zip(config.joints, envelope.low_kgm2, envelope.high_kgm2, strict=True)
    )


def with_bandwidth_gains(config: ArmConfig) -> ArmConfig:
    """``config`` with the gains of every joint that gives ``bandwidth_hz`` filled in
    (:func:`motion.control.stability.gains_for_bandwidth` at the largest inertia the joint sees in the limits, so that
    the bandwidth is at least the one given and the loop at least critically damped at every pose); ``config``
    itself where no joint gives one."""
    if all(j.bandwidth_hz is None for j in config.joints):
        return config
    loops = torque_loops(config)
    joints = []
    for joint, loop in zip(config.joints, loops, strict=True):
        if joint.bandwidth_hz is None:
            joints.append(joint)
            continue
        kp, kd = gains_for_bandwidth(joint.bandwidth_hz, loop.inertia_high_kgm2)
        joints.append(dataclasses.replace(joint, kp_nm_per_deg=kp, kd_nm_per_dps=kd))
    return dataclasses.replace(config, joints=tuple(joints))


def torque_stability(config: ArmConfig, rate_hz: float | None = None) -> StabilityReport:
    """Every joint's torque-mode margin at ``rate_hz`` (default: the configured rate), whatever the mode."""
    return stability_report(torque_loops(config), config.control.rate_hz if rate_hz is None else rate_hz)


def check_envelope(config: ArmConfig) -> StabilityReport | None:
    """At connect, before the bus opens: what the configuration's rate must hold that a file's own checks cannot see
    when the configuration was changed in code (the communication-loss time against the period), and the torque loop's
    stability (:func:`check_stability`, whose report is returned).

    Raises:
        ConfigError: ``safety.link_timeout_ms`` shorter than the loop leaves between a drive's frames.
        StabilityError: a joint's PD without margin at the rate.
    """
    problem = link_timeout_problem(config.safety.link_timeout_ms, config.control.rate_hz)
    if problem is not None:
        raise ConfigError(config.source, "safety.link_timeout_ms", problem)
    return check_stability(config)


def check_stability(config: ArmConfig) -> StabilityReport | None:
    """At connect, before the bus opens: in a mode where the host closes the loop, every joint's PD keeps its margin
    at the configured rate (None in other modes).

    Raises:
        StabilityError: a joint without margin (names it, its margin, the lowest rate and the highest gains that hold).
    """
    if not config.control.mode.traits.host_torque:
        return None
    report = torque_stability(config)
    if report.failing:
        raise StabilityError(config.source, report)
    return report


def stable_from_hz(config: ArmConfig) -> float:
    """The rate check's floor for ``config``'s mode (:attr:`RateCheck.stable_from_hz`): where the host closes the
    loop, the lowest rate at which every joint's PD keeps its margin; else 0."""
    if not config.control.mode.traits.host_torque:
        return 0.0
    lowest = torque_stability(config).lowest_rate_hz
    return math.inf if math.isnan(lowest) else lowest


def check_rate(controller: Controller, config: ArmConfig) -> RateCheck:
    """The rate check at connect (after ``read_positions``, before the loop starts): measure the round trip and a
    guarded cycle's host work (a watchdog of the configuration's, collision observer included, rehearsing on the
    measuring replies), warn about a thin margin, refuse a rate that does not hold.

    Raises:
        RateError: ``control.rate_hz`` cannot be held (names the measured figures and the highest rate that holds).
        TransportError: a drive did not answer the measuring reads.
    """
    margin = config.control.rate_margin
    if margin < DEFAULT_MARGIN:
        logger.warning(
            "control.rate_margin %g is below the default %g: the loop may miss deadlines when the host is busy",
            margin,
            DEFAULT_MARGIN,
        )
    check = measure_rate(
        controller,
        margin=margin,
        rehearse=rehearsal_watchdog(config, controller).rehearse,
        stable_from_hz=stable_from_hz(config),
    )
    logger.info("rate check: %s", check.summary())
    if not check.holds:
        raise RateError(config.source, check)
    return check


def safety_settings(config: ArmConfig) -> SafetySettings:
    """Fault thresholds and halt policy from ``safety:``, ``control.halt_policy`` and the joints (a joint without a
    ``collision_threshold_nm`` gets inf: not watched).

    A drive counts as lost when it misses more than ``max_missed_replies`` consecutive cycles, or when nothing good
    came from it for ``reply_timeout_ms`` plus ``max_missed_replies + 1`` control periods.
    """
    safety = config.safety
    period = config.control.period_s
    return SafetySettings(
        halt_policy=config.control.halt_policy,
        temperature_limit_c=tuple(j.temperature_limit_c for j in config.joints),
        min_voltage_v=safety.min_voltage_v,
        following_error_deg=safety.following_error_deg,
        reply_timeout_s=safety.reply_timeout_ms / 1000.0 + (safety.max_missed_replies + 1) * period,
        max_missed_replies=safety.max_missed_replies,
        collision_threshold_nm=tuple(math.inf if t is None else t for t in config.collision_thresholds_nm),
        collision_reaction=config.collision_reaction,
        collision_window_s=safety.collision_window_s,
        coulomb_friction_nm=tuple(j.coulomb_friction_nm for j in config.joints),
    )


def rehearsal_watchdog(config: ArmConfig, controller: Controller) -> Watchdog:
    """A watchdog like the supervisor's (thresholds, collision observer) for the rate check's rehearsals: its state
    is its own, so the loop's watchdog starts untouched."""
    return Watchdog(controller, safety_settings(config), collision_observer_for(config))


def build_supervisor(config: ArmConfig, controller: Controller, *, observe: bool = False) -> Supervisor:
    """The safety supervisor of ``controller`` (after ``read_positions()``): the thresholds of ``config``, the
    collision observer when a joint has a threshold (or ``observe``: residuals recorded, e.g. to calibrate), and
    gravity compensation for the ``comply`` reaction.

    Raises:
        ConfigError: a joint has ``brake: true`` but its drive's generation has no brake commands.
    """
    for i, joint in enumerate(config.joints):
        family = controller.family_of(joint.address)
        if joint.brake and not family.brakes:
            raise ConfigError(
                config.source,
                f"joints[{i}].brake",
                f"{joint.name} has a brake, but its drive answers in the {family.family.value} protocol, which has no "
                "brake commands (0x77 / 0x78 are the V3 driver's)",
            )
    return Supervisor(
        controller,
        safety_settings(config),
        observer=collision_observer_for(config, always=observe),
        gravity=gravity_for(config),
        drives=drive_setup(config, controller),
    )


def drive_setup(config: ArmConfig, controller: Controller) -> DriveSetup:
    """The drive-side settings of a session of ``config`` on ``controller``'s bus, with the host's record of them
    (:mod:`motion.control.drive_record`)."""
    ids = [j.address for j in config.joints]
    braked = [j.address for j in config.joints if j.brake]
    record, now = drive_record_for(controller.bus)
    return DriveSetup(
        controller.bus,
        controller.families,
        ids,
        braked,
        session_link_timeout_ms(config),
        record=record,
        now=now,
        labels={j.address: j.drive_label for j in config.joints},
    )


def session_link_timeout_ms(config: ArmConfig) -> int:
    """The communication-loss time a session sets on V3 drives (0xB3), ms: ``safety.link_timeout_ms``, else a few
    control periods (:func:`motion.control.drivesetup.link_timeout_ms`)."""
    configured_ms = config.safety.link_timeout_ms
    return link_timeout_ms(config.control.period_s, None if configured_ms is None else configured_ms / 1e3)


# ------------------------------------------------------------------------------------------ turns and position loops


def resolve_frames(
    controller: Controller,
    config: ArmConfig,
    *,
    records: Mapping[str, TurnRecord] | None = None,
    provisional: Collection[str] = (),
    stayed_powered: bool = False,
) -> tuple[JointTurns, ...]:
    """Read every drive's multi-turn angle and resolve each joint's turn offset (:mod:`motion.control.turns`) from
    its power-on window and ``records`` (what the last session left, :func:`load_turn_records`); the controller
    uses them from then on (call ``read_positions()`` next). ``stayed_powered``: the user says the drives have stayed
    powered since the records were made (``--keep-turns``): where a reading cannot tell, the record's turns hold. A
    joint without a window warns once that its turns are assumed. The ``provisional`` joints (about to be homed) take
    the record's turns or the drive's count, window aside and without a warning.

    Raises:
        TurnError: a joint with a window whose turns cannot be told (nothing has moved).
        TransportError: a drive did not answer.
    """
    readings = read_angles(controller)
    runtimes, now = (
        read_runtimes(controller),
        drive_record_for(controller.bus)[1](),
    )  # (the clock runtimes compare with)
    base = controller.base_transmission.transmissions
    known = records or {}
    found = [known.get(j.name) for j in config.joints]
    resolved = resolve_turns(
        config.joint_names,
        base,
        [readings[j.address] for j in config.joints],
        [None if j.name in provisional else j.power_on_window_deg for j in config.joints],
        found,
        powered_since=[
            _powered_since(r, runtimes.get(j.address), now) for j, r in zip(config.joints, found, strict=True)
        ],
        stayed_powered=stayed_powered,
        # drives that report their output shaft (V3): the reading is the joint's (the joints about to be homed aside)
        output_turns=[
            _output_turn(s.drive_gear_ratio) if f.output_shaft and s.name not in provisional else None
            for s, f in zip(controller.specs, controller.families, strict=True)
        ],
        limits=[(j.position_min_deg, j.position_max_deg) for j in config.joints],
    )
    resolved = tuple(
        dataclasses.replace(t, power_on=None if j.address not in runtimes else (runtimes[j.address], now))
        for j, t in zip(config.joints, resolved, strict=True)
    )
    controller.set_turns([j.turns for j in resolved])
    for joint, t, spec, axis in zip(resolved, base, config.joints, controller.specs, strict=True):
        output_turn_deg = 360.0 * axis.drive_gear_ratio / abs(t.gear_ratio)  # (joint degrees)
        if joint.source is Source.ABSOLUTE and spec.position_max_deg - spec.position_min_deg >= output_turn_deg:
            logger.warning(
                "joint %s: its limits span a whole output turn or more, so its V3 drive's reading is taken as it is: "
                "the drive must keep its multi-turn value (function 0x20 index 4 = 1), or the joint reads a turn off "
                "after a power-up elsewhere than in its first output turn",
                joint.name,
            )
        if joint.source is Source.ASSUMED and joint.name not in provisional:
            lo, hi = assumed_span(t, joint)
            outside_limits(joint, spec, turn_joint_deg(t))
            logger.warning(
                "joint %s has no power_on_window_deg: its turn count is assumed from the drive (right if it powered "
                "up between %.2f and %.2f deg; elsewhere the joint reads off by a multiple of %g deg)",
                joint.name,
                lo,
                hi,
                turn_joint_deg(t),
            )
    return resolved


def outside_limits(joint: JointTurns, spec: JointConfig, turn_deg: float) -> None:
    """Refuse a joint whose assumed turn count (no ``power_on_window_deg``) puts it outside its limits: the drive
    powered up elsewhere than its first turn (a direct-drive joint at -20 deg reads 340), and the first move would
    fault on its set-point; a window finds the turn instead.

    Raises:
        TurnError: the joint is outside its limits (the message says what to configure).
    """
    lo, hi = spec.position_min_deg, spec.position_max_deg
    if lo <= joint.joint_deg <= hi:
        return
    if hi - lo < turn_deg:
        window = (
            f"power_on_window_deg: [{lo:g}, {hi:g}] (its limits: they span less than one motor turn, {turn_deg:g} deg)"
        )
    else:
        window = f"a power_on_window_deg narrower than one motor turn of this joint ({turn_deg:g} deg)"
    raise TurnError(
        f"joint {joint.name}: the drive reads {joint.reading_deg:.2f} motor deg, which without a power_on_window_deg "
        f"puts the joint at {joint.joint_deg:.2f} deg, outside its limits [{lo:g}, {hi:g}]: the drive powered up "
        f"elsewhere than in its first turn. Configure {window}, so that the turn is found from the window, or home it "
        "(`rmd-motion home`)"
    )


def _output_turn(drive_gear_ratio: float) -> int:
    """Motor turns per output turn of a drive with this reduction (0: not a whole number)."""
    turns = round(drive_gear_ratio)
    return turns if turns >= 1 and abs(drive_gear_ratio - turns) < 1e-9 else 0


def _powered_since(record: TurnRecord | None, runtime_s: float | None, now_s: float) -> bool | None:
    """Whether the drive has run since ``record``'s session, by its runtime (None: the drive does not tell)."""
    if record is None or record.power_on is None or runtime_s is None:
        return None
    return same_power_on(record.power_on[0], record.power_on[1], runtime_s, now_s)


def emulated_frames(controller: Controller, config: ArmConfig) -> tuple[JointTurns, ...]:
    """The frames of emulated drives powered up at the zero pose (turn offset 0 for every joint, nothing read)."""
    return tuple(
        JointTurns(j.name, 0, Source.EMULATED, math.nan, math.nan, j.power_on_window_deg) for j in config.joints
    )


def identify_position_loops(supervisor: Supervisor, config: ArmConfig) -> dict[str, PositionLoopFit]:
    """Identify every joint's position loop (:func:`motion.control.identify.identify_position_loops`) with the
    supervisor's moves: each at full speed and guarded like any other, waited for to its end; the controller's
    tracking model uses the result from then on.

    Raises:
        MotionError: the arm is not in position mode.
        MotionFault: a fault halted the arm during a move.
    """

    def move_to(target_deg: FloatArray) -> None:
        supervisor.move_to(target_deg, 1.0)
        supervisor.wait()

    return identify.identify_position_loops(supervisor.controller, config, move_to)
