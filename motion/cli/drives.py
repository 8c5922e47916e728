"""Commands that talk to the drives one request at a time, without the control loop: ``scan``, ``status``,
``hold``, ``stop``, ``off``, ``clear``, ``pid``, ``accel`` and ``zero``.

None of them moves a joint except ``hold`` (which commands every drive to hold where it is) and ``off`` (which
releases the torque: an arm under gravity falls unless it has brakes).
"""

from __future__ import annotations

import argparse
import math
import sys
from collections.abc import Callable, Mapping, Sequence
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING, Any, Final

from motion.cli import offline
from motion.cli.common import (
    EVERY_GENERATION,
    EXIT_OK,
    EXIT_USAGE,
    Interrupts,
    Session,
    UsageError,
    exchange,
    flag_names,
    print_json,
    print_table,
    warn,
)
from motion.cli.program import load_program
from motion.compose import build_controller, drive_setup, resolve_frames, torque_stability
from motion.config import ArmConfig, JointConfig
from motion.control.axes import UNWRAP_BOUND_MOTOR_DEG
from motion.control.drive_record import DriveRecord
from motion.control.drivesetup import LINK_TIMEOUT
from motion.control.family import FAMILIES, DriveFamily
from motion.control.ratecheck import RateError
from motion.control.stability import REQUIRED_MARGIN, StabilityReport
from motion.control.tracking import PositionLoopFit
from motion.control.turns import CONTINUITY_MOTOR_DEG, joint_angle
from motion.control.unwrap import UnwrapHeadroom
from motion.errors import FaultKind, MotionFault
from motion.keep import drive_record_for, load_turn_records, save_turn_records
from motion.protocol import (
    Acceleration,
    Bare,
    Command,
    EncoderOffset,
    Message,
    MultiTurnAngle,
    MultiTurnPositionSpeed,
    PidGains,
    Status1,
)
from motion.protocol.table import (
    Direction,
    ProtocolFamily,
    WireProtocol,
    field_names,
    field_range,
)
from motion.protocol.v3.messages import (
    AccelerationIndex,
    AccelerationRead,
    PidIndex,
    PidParameter,
    PidRead,
    PlanningAcceleration,
    Status1V3,
)
from motion.transport import Request, Transport

if TYPE_CHECKING:
    from motion.api import Arm

#: ``hold``: the drive's speed cap while holding, as a share of the joint's velocity limit.
HOLD_SPEED_SHARE: Final = 0.1
#: The PI gains in the order ``pid set`` takes them (the frame's order).
PID_FIELDS: Final = field_names(Command.WRITE_PID_RAM, Direction.REQUEST, WireProtocol.CAN)
#: The largest acceleration limit the protocol carries, motor deg/s².
ACCELERATION_MAX_DPS2: Final = int(
    field_range(Command.WRITE_ACCELERATION_RAM, Direction.REQUEST, WireProtocol.CAN, "acceleration_dps2")[1]
)
#: How long the drives have to answer ``restore``'s writes, s.
RESTORE_WINDOW_S: Final = 0.5
#: Why ROM writes need ``--yes``.
FLASH_WARNING: Final = (
    "it writes the drive's flash (ROM), which wears with every write (a limited number of write cycles)"
)


def _requests(joints: Sequence[JointConfig], message: Message) -> list[Request]:
    return [Request(j.address, message) for j in joints]


def _ask(
    bus: Transport, session: Session, joints: Sequence[JointConfig], message: Message, expect: type[Message]
) -> dict[int, Any]:
    """``message`` to every joint of ``joints`` on an open bus; each must answer with an ``expect`` (by motor id)."""
    return exchange(bus, _requests(joints, message), session.names, expect)


def _ask_bare(
    bus: Transport,
    session: Session,
    joints: Sequence[JointConfig],
    code: int,
    expect: Callable[[DriveFamily], type[Message]] | None = None,
) -> dict[int, Any]:
    """The request without data for ``code`` to every joint of ``joints``, each in its drive's generation (its
    bus's); each must answer with its generation's ``expect`` (default: the request's echo), by motor id."""
    requests = [Request(j.address, FAMILIES[bus.family_of(j.address)].bare(code)) for j in joints]
    return exchange(bus, requests, session.names, _expected(bus, expect or (lambda f: type(f.bare(code)))))


def _expected(bus: Transport, pick: Callable[[DriveFamily], type[Message]]) -> tuple[type[Message], ...]:
    """The reply types ``pick`` names for the generations ``bus`` speaks (one where it speaks one)."""
    return tuple(dict.fromkeys(pick(FAMILIES[f]) for f in bus.families))


def _ask_once(
    session: Session, joints: Sequence[JointConfig], message: Message, expect: type[Message]
) -> dict[int, Any]:
    """Open the bus (drives of the older generation), :func:`_ask`, release the bus."""
    with session.open_bus() as bus:
        return _ask(bus, session, joints, message, expect)


def _check_echo(joint: JointConfig, echo: Message, sent: Message) -> None:
    if echo != sent:
        raise MotionFault(FaultKind.WRITE_FAILED, joint=joint.name, detail=f"the drive echoed {echo}, not {sent}")


def _label(joint: JointConfig) -> str:
    return f"{joint.name} ({joint.drive_label})"


# ---------------------------------------------------------------------------------------------------- status


def status(args: argparse.Namespace, interrupts: Interrupts) -> int:
    """Every joint's position, speed, current, temperature, voltage and flags, read without moving anything."""
    session = Session.from_args(args)
    config = session.config
    with session.open_bus(speaks=EVERY_GENERATION) as bus:
        # The controller's start-up reads (0x92 + 0x9C) give the joint angles exactly as a motion command sees them;
        # its loop is never started.
        controller = build_controller(config, bus)
        records = None if args.forget_turns else load_turn_records(config, bus.describe())
        turns = resolve_frames(controller, config, records=records, stayed_powered=args.keep_turns)
        controller.read_positions()
        save_turn_records(config, bus.describe(), controller, (j.source for j in turns), [j.power_on for j in turns])
        status1: dict[int, Status1 | Status1V3] = _ask_bare(
            bus, session, config.joints, Command.READ_STATUS_1, lambda f: f.status_type
        )
        where = bus.describe()
        record, _ = drive_record_for(bus)
    axes = controller.axes
    several = len(config.buses) > 1  # (then each joint's bus is shown)
    joints: list[dict[str, object]] = []
    rows: list[tuple[object, ...]] = []
    for i, joint in enumerate(config.joints):
        s = status1[joint.address]
        q, qd, iq = float(axes.q_deg[i]), float(axes.qd_dps[i]), float(axes.iq_a[i])
        inside = joint.position_min_deg <= q <= joint.position_max_deg
        flags = flag_names(s.errors)
        joints.append(
            {
                "name": joint.name,
                "motor_id": joint.motor_id,
                **({"bus": joint.bus} if several else {}),
                "position_deg": round(q, 4),
                "velocity_dps": round(qd, 3),
                "iq_a": round(iq, 3),
                "temperature_c": s.temperature_c,
                "voltage_v": s.voltage_v,
                "errors": flags,
                "within_limits": inside,
                "turns": turns[i].turns,
                "turns_from": str(turns[i].source),
                "rom_writes": record.rom_writes(DriveRecord.key(where, joint.address)),
            }
        )
        rows.append(
            (
                joint.name,
                joint.motor_id,
                *((joint.bus,) if several else ()),
                f"{q:9.3f} deg" + ("" if inside else " (outside limits)"),
                f"{qd:8.2f} deg/s",
                f"{iq:6.2f} A",
                f"{s.temperature_c} °C",
                f"{s.voltage_v:.1f} V",
                ",".join(flags) or "ok",
                turns[i].describe(),
                record.rom_writes(DriveRecord.key(where, joint.address)),
            )
        )
    if args.json:
        print_json({"name": config.name, "bus": where, "joints": joints})
        return EXIT_OK
    print(f"{config.name} on {where}")
    header = ("position", "velocity", "iq", "temp", "voltage", "flags", "turns", "ROM writes")
    print_table(("joint", "motor", *(("bus",) if several else ()), *header), rows)
    return EXIT_OK


# ---------------------------------------------------------------------------------------------------- halt & hold


def _halt(args: argparse.Namespace, code: Command) -> int:
    session = Session.from_args(args)
    joints = session.config.joints
    with session.open_bus(speaks=EVERY_GENERATION) as bus:  # the same byte in both generations
        _ask_bare(bus, session, joints, code)
    print(f"{code.name.lower().replace('_', ' ')} (0x{code:02X}) acknowledged by {', '.join(map(_label, joints))}")
    return EXIT_OK


def stop(args: argparse.Namespace, interrupts: Interrupts) -> int:
    """0x81 to every joint: the drives stop and hold where they stop."""
    return _halt(args, Command.MOTOR_STOP)


def off(args: argparse.Namespace, interrupts: Interrupts) -> int:
    """0x80 to every joint: torque released."""
    warn("motor off: the drives release their torque; an arm under gravity falls unless it has brakes")
    return _halt(args, Command.MOTOR_OFF)


def hold(args: argparse.Namespace, interrupts: Interrupts) -> int:
    """Every drive holds its present angle in its own position loop (0xA4), also after the command ends."""
    session = Session.from_args(args)
    joints = session.config.joints
    with session.open_bus(speaks=EVERY_GENERATION) as bus:
        families = {j.address: FAMILIES[bus.family_of(j.address)] for j in joints}
        protected = [j for j in joints if families[j.address].link_protection]
        if protected:
            _refuse_hold_under_protection(bus, protected)
        # (a V3 drive reads and takes output-shaft degrees: motor degrees / its reduction)
        gear = {j.address: j.gear_ratio if families[j.address].output_shaft else 1.0 for j in joints}
        angles: dict[int, MultiTurnAngle] = _ask_bare(
            bus, session, joints, Command.READ_MULTI_TURN_ANGLE, lambda _: MultiTurnAngle
        )
        requests = [
            Request(
                j.address,
                MultiTurnPositionSpeed(
                    angles[j.address].angle_deg,
                    j.velocity_limit_dps * j.gear_ratio * HOLD_SPEED_SHARE / gear[j.address],
                ),
            )
            for j in joints
        ]
        exchange(bus, requests, session.names, _expected(bus, lambda f: f.state_type))
        records = load_turn_records(session.config, bus.describe())

    def joint_deg(joint: JointConfig) -> str:
        """The joint angle with the turns the last session recorded, while the drive continues from it."""
        reading = angles[joint.address].angle_deg * gear[joint.address]
        record = records.get(joint.name)
        if record is None or abs(reading - record.reading_deg) > CONTINUITY_MOTOR_DEG:
            return f"{joint_angle(joint.transmission(), reading, 0):.2f} deg (turns not known)"
        return f"{joint_angle(joint.transmission(), reading, record.turns):.2f} deg"

    held = ", ".join(f"{j.name} at {joint_deg(j)}" for j in joints)
    print(f"holding (drive position loop, 0xA4): {held}")
    return EXIT_OK


def _refuse_hold_under_protection(bus: Transport, joints: Sequence[JointConfig]) -> None:
    """Raise UsageError where the host's record shows a drive's communication-loss protection on: it would stop the
    drive that long after ``hold`` ends (0xB3 has no read: a drive the record does not know is held)."""
    record, _ = drive_record_for(bus)
    on = {}
    for joint in joints:
        written = record.get(DriveRecord.key(bus.describe(), joint.address), LINK_TIMEOUT)
        if isinstance(written, dict) and written.get("ms"):
            on[joint.name] = written["ms"]
    if on:
        listed = ", ".join(f"{name} {ms} ms" for name, ms in on.items())
        raise UsageError(
            f"hold refused: rmd-motion's sessions left these drives' communication-loss protection on (0xB3: "
            f"{listed}), so they would stop by themselves that long after this command ends; turn it off with "
            "`rmd-motion restore --yes`, and set safety.link_timeout_ms: 0 for the sessions that should leave the "
            "drives holding"
        )


def clear(args: argparse.Namespace, interrupts: Interrupts) -> int:
    """0x9B to every joint; a flag whose cause persists stays set (exit 1). V3 drives have no 0x9B (their level-2
    errors clear by themselves once the cause is gone): their error words are read and reported the same way."""
    session = Session.from_args(args)
    joints = session.config.joints
    with session.open_bus(speaks=EVERY_GENERATION) as bus:
        requests = [
            Request(j.address, f.bare(Command.CLEAR_ERRORS if f.clears_errors else Command.READ_STATUS_1))
            for j in joints
            for f in (FAMILIES[bus.family_of(j.address)],)
        ]
        replies: dict[int, Status1 | Status1V3] = exchange(
            bus, requests, session.names, _expected(bus, lambda f: f.status_type)
        )
    left = {j.name: flag_names(replies[j.address].errors) for j in joints if replies[j.address].errors}
    for joint in joints:
        print(f"{_label(joint)}: {', '.join(left.get(joint.name, [])) or 'clear'}")
    if left:
        detail = "; ".join(f"{name}: {', '.join(flags)} still set (its cause persists)" for name, flags in left.items())
        raise MotionFault(FaultKind.CLEAR_FAILED, joint=next(iter(left)), detail=detail)
    return EXIT_OK


# ---------------------------------------------------------------------------------------------------- settings


def pid_value_arg(text: str) -> int | None:
    """argparse type of a PI gain (0x31 / 0x32: 0..255), or ``-`` to keep the drive's value."""
    if text == "-":
        return None
    lo, hi = (int(x) for x in field_range(Command.WRITE_PID_RAM, Direction.REQUEST, WireProtocol.CAN, "angle_kp"))
    if not text.isdigit() or not lo <= int(text) <= hi:
        raise argparse.ArgumentTypeError(f"{text!r} is not a gain {lo}..{hi} (or - to keep the present one)")
    return int(text)


def _gains_row(joint: JointConfig, gains: PidGains) -> tuple[object, ...]:
    return (joint.name, joint.motor_id, *(getattr(gains, f) for f in PID_FIELDS))


def pid(args: argparse.Namespace, interrupts: Interrupts) -> int:
    """``pid get [JOINT...]`` / ``pid set [--ram|--rom] JOINT ANGLE_KP ANGLE_KI SPEED_KP SPEED_KI IQ_KP IQ_KI``."""
    session = Session.from_args(args)
    if args.action == "get":
        return _print_parameters(session, args, _PID_READS)
    joint = session.joint(args.joint)
    if args.rom and not args.yes:
        raise UsageError(
            f"pid set --rom refused without --yes: {FLASH_WARNING}, and the drive loads the gains at every power-on "
            "(undoing them takes another ROM write). Try them with --ram first (lost at the next power cycle), "
            "then write them once with --rom --yes"
        )
    code = Command.WRITE_PID_ROM if args.rom else Command.WRITE_PID_RAM
    with session.open_bus() as bus:
        old: PidGains = _ask(bus, session, [joint], Bare(Command.READ_PID), PidGains)[joint.address]
        values = {f: v for f, v in zip(PID_FIELDS, args.gains, strict=True) if v is not None}
        new = replace(old, command=code, **values)
        _check_echo(joint, _ask(bus, session, [joint], new, PidGains)[joint.address], new)
    target = "ROM (kept at power-off)" if args.rom else "RAM (lost at the next power cycle)"
    print(f"{_label(joint)}: PI gains written to {target}")
    print_table(("", *PID_FIELDS), [("before", *_gains_row(joint, old)[2:]), ("after", *_gains_row(joint, new)[2:])])
    return EXIT_OK


#: A read of `pid get` / `accel get`: its request, the reply it expects, and the columns a reply fills for a joint.
_Read = tuple[Message, type[Message], Callable[[Any, JointConfig], dict[str, float]]]


def _v3_parameter_reads(
    requests: Sequence[PidRead | AccelerationRead], expect: type[Message], field: str
) -> tuple[_Read, ...]:
    """The V3 drives' parameters, read one index at a time: a column per index, named after it."""

    def column(name: str) -> Callable[[Any, JointConfig], dict[str, float]]:
        return lambda reply, _: {name: getattr(reply, field)}

    return tuple((request, expect, column(request.index.name.lower())) for request in requests)


#: `pid get` per generation: the older drives' six PI gains in one reply (0x30); the V3 drives' float32 parameters
#: by index (0x30).
_PID_READS: Final[Mapping[ProtocolFamily, tuple[_Read, ...]]] = {
    ProtocolFamily.V2: ((Bare(Command.READ_PID), PidGains, lambda g, _: {f: getattr(g, f) for f in PID_FIELDS}),),
    ProtocolFamily.V3: _v3_parameter_reads([PidRead(i) for i in PidIndex], PidParameter, "value"),
}
#: `accel get` per generation: the older drives' one limit (0x33, motor deg/s², also shown at the joint); the V3
#: drives' planning accelerations by index (0x42, output shaft deg/s²).
_ACCELERATION_READS: Final[Mapping[ProtocolFamily, tuple[_Read, ...]]] = {
    ProtocolFamily.V2: (
        (
            Bare(Command.READ_ACCELERATION),
            Acceleration,
            lambda a, j: {"motor_dps2": a.acceleration_dps2, "joint_dps2": a.acceleration_dps2 / j.gear_ratio},
        ),
    ),
    ProtocolFamily.V3: _v3_parameter_reads(
        [AccelerationRead(i) for i in AccelerationIndex], PlanningAcceleration, "acceleration_dps2"
    ),
}


def _print_parameters(
    session: Session, args: argparse.Namespace, reads: Mapping[ProtocolFamily, tuple[_Read, ...]]
) -> int:
    """The joints' parameters that ``reads`` names for the drives' generation, printed as a table or JSON."""
    joints = session.joints(args.joints)
    values: dict[int, dict[str, float]] = {j.address: {} for j in joints}
    by_id = {j.address: j for j in joints}
    with session.open_bus(speaks=EVERY_GENERATION) as bus:
        by_family: dict[ProtocolFamily, list[JointConfig]] = {}  # (an arm's buses may have drives of both)
        for joint in joints:
            by_family.setdefault(bus.family_of(joint.address), []).append(joint)
        for family, group in by_family.items():
            for request, expect, columns in reads[family]:
                for motor_id, reply in _ask(bus, session, group, request, expect).items():
                    values[motor_id].update(columns(reply, by_id[motor_id]))
    if args.json:
        print_json({j.name: values[j.address] for j in joints})
    else:
        names = list(dict.fromkeys(c for j in joints for c in values[j.address]))  # (each generation's columns)
        print_table(
            ("joint", "motor", *names),
            [
                (j.name, j.motor_id, *(f"{values[j.address][c]:g}" if c in values[j.address] else "-" for c in names))
                for j in joints
            ],
        )
    return EXIT_OK


def accel_value_arg(text: str) -> int:
    """argparse type of an acceleration limit: a whole number of motor deg/s² >= 0 (0: no limit)."""
    if not text.isdigit() or int(text) > ACCELERATION_MAX_DPS2:
        raise argparse.ArgumentTypeError(f"{text!r} is not an acceleration 0..{ACCELERATION_MAX_DPS2} deg/s²")
    return int(text)


def accel(args: argparse.Namespace, interrupts: Interrupts) -> int:
    """``accel get [JOINT...]`` / ``accel set JOINT DPS2`` (motor shaft, RAM: lost at the next power cycle)."""
    session = Session.from_args(args)
    if args.action == "get":
        return _print_parameters(session, args, _ACCELERATION_READS)
    joint = session.joint(args.joint)
    request = Acceleration(Command.WRITE_ACCELERATION_RAM, args.dps2)
    _check_echo(joint, _ask_once(session, [joint], request, Acceleration)[joint.address], request)
    print(
        f"{_label(joint)}: acceleration limit {args.dps2} motor deg/s² ({args.dps2 / joint.gear_ratio:g} joint "
        "deg/s²) in RAM (lost at the next power cycle)"
    )
    return EXIT_OK


def zero(args: argparse.Namespace, interrupts: Interrupts) -> int:
    """0x19: the joint's present motor position becomes its encoder zero, in ROM, after the next power cycle."""
    session = Session.from_args(args)
    joint = session.joint(args.joint)
    consequence = (
        "and the new zero takes effect only after the drive is power cycled, when every angle this joint reports "
        "shifts by its present motor angle (review the joint's zero_offset_deg in the configuration)"
    )
    if not args.yes:
        raise UsageError(f"zero refused without --yes: {FLASH_WARNING}, {consequence}")
    message = _ask_once(session, [joint], Bare(Command.WRITE_ZERO_ROM), Message)[joint.address]
    offset = f" (encoder offset {message.encoder_offset})" if isinstance(message, EncoderOffset) else ""
    print(f"{_label(joint)}: present position written to ROM as zero{offset}; power-cycle the drive to apply it")
    return EXIT_OK


def restore(args: argparse.Namespace, interrupts: Interrupts) -> int:
    """Write back the drive settings rmd-motion's sessions changed, as they were before the first change (V3: the
    planning accelerations, 0x43; the communication-loss protection off, 0xB3): ROM writes, so ``--yes``."""
    if not args.yes:
        raise UsageError(f"restore refused without --yes: {FLASH_WARNING}")
    session = Session.from_args(args)
    with session.open_bus(speaks=EVERY_GENERATION) as bus:
        setup = drive_setup(session.config, build_controller(session.config, bus))
        if not setup.sets_drives:
            print(
                f"the drives on {bus.describe()} speak the older protocol: rmd-motion's sessions change none of "
                "their settings"
            )
            return EXIT_OK
        done = setup.restore_settings(bus.clock() + RESTORE_WINDOW_S)
    for line in done:
        print(line)
    print(f"{setup.rom_writes} ROM write(s); the next session sets the drives for tracking again")
    return EXIT_OK


def check(args: argparse.Namespace, interrupts: Interrupts) -> int:
    """``check``: what this host and bus hold in real time, per control mode, for the configured joints; with
    ``--identify`` (position mode, when the configured rate holds) also each joint's position loop, identified from a
    full-speed move out and back (:meth:`motion.api.Arm.identify_tracking`) and stored for later connections.

    Without ``--identify`` it sends reads only. Exit 0 when the configured rate holds in the configured mode, 2 when it
    does not; with ``--identify``: 1 when a fault halted the identification.
    """
    from motion.api import measure_modes  # noqa: PLC0415 - Pinocchio only when checking

    session = Session.from_args(args)
    config = session.config
    chosen = [flag for flag in ("offline", "holding", "identify") if getattr(args, flag)]
    if len(chosen) > 1:
        raise UsageError(f"{' and '.join('--' + f for f in chosen)}: one check at a time")
    if args.offline or args.program:
        return _check_offline(args, session)
    if args.holding:
        from motion.cli.moves import holding  # noqa: PLC0415 - (moves builds arms; drives talks to drives)

        return holding(args, interrupts)
    if args.emulate:
        raise UsageError("--emulate: the rate check measures this host and bus; --holding and --offline run emulated")
    if args.identify and not config.control.mode.traits.drive_position_loop:
        mode = config.control.mode.value
        raise UsageError(f"--identify: {config.source} runs in {mode} mode; identification needs position mode")
    with session.open_bus(speaks=EVERY_GENERATION) as bus:
        checks = measure_modes(config, bus)
        where = bus.describe()
    configured = checks[config.control.mode.value]
    fits: dict[str, PositionLoopFit] = {}
    stored: Path | None = None
    if args.identify and configured.holds:
        from motion.cli.moves import with_arm  # noqa: PLC0415 - the moving commands' arm handling

        def identify(arm: Arm) -> int:
            nonlocal stored
            fits.update(arm.identify_tracking())
            stored = arm.tracking_file
            return EXIT_OK

        args.log = args.trace = None
        with_arm(args, session, interrupts, identify)
    rows = [
        (
            mode,
            f"{c.round_trip_p99_s * 1e3:.2f} ms",
            f"{c.host_p99_s * 1e3:.2f} ms",
            f"{c.highest_rate_hz:g} Hz",
            "-" if c.spread_hz is None else f"{c.spread_hz[0]:.0f}-{c.spread_hz[1]:.0f} Hz",
            f"{c.recommended_rate_hz:g} Hz",
            "holds" if c.holds else "does not hold",
        )
        for mode, c in checks.items()
    ]
    if args.json:
        document: dict[str, object] = {
            "bus": where,
            "rate_hz": config.control.rate_hz,
            "mode": config.control.mode.value,
            "margin": config.control.rate_margin,
            "holds": configured.holds,
            "modes": {
                mode: {
                    "round_trip_p99_s": c.round_trip_p99_s,
                    "host_p99_s": c.host_p99_s,
                    "highest_rate_hz": c.highest_rate_hz,
                    "spread_hz": None if c.spread_hz is None else list(c.spread_hz),
                    "samples": c.samples,
                    "recommended_rate_hz": c.recommended_rate_hz,
                    "stable_from_hz": c.stable_from_hz if math.isfinite(c.stable_from_hz) else None,
                    "holds": c.holds,
                }
                for mode, c in checks.items()
            },
        }
        if args.identify:
            document["identified"] = {name: _fit_dict(fit) for name, fit in fits.items()}
            document["stored"] = str(stored) if stored is not None else None
        print_json(document)
    else:
        print(
            f"{len(config.joints)} joints on {where}; configured control.rate_hz {config.control.rate_hz:g} Hz "
            f"({config.control.mode.value} mode), margin {config.control.rate_margin:g}"
        )
        header = (
            "mode",
            "round trip p99",
            "host work p99",
            "highest rate",
            "by quarter",
            "recommended",
            f"{config.control.rate_hz:g} Hz",
        )
        print_table(header, rows)
        if fits:
            print("position loops (expected tracking of the following-error check), identified from a move:")
            print_table(
                ("joint", "angle gain", "acceleration", "rms error: prior", "identified"),
                [
                    (
                        name,
                        f"{fit.loop.angle_gain_per_s:.1f} /s",
                        f"{fit.loop.acceleration_dps2:.0f} deg/s²",
                        f"{fit.rms_prior_deg:.3f} deg",
                        f"{fit.rms_deg:.3f} deg",
                    )
                    for name, fit in fits.items()
                ],
            )
            if stored is not None:
                print(f"stored in {stored}: used at every connection while the drives keep their gains")
    if configured.holds:
        return EXIT_OK
    warn(str(RateError(config.source, configured)))
    if args.identify:
        warn("--identify: nothing moved (the configured rate does not hold)")
    return EXIT_USAGE


def _check_offline(args: argparse.Namespace, session: Session) -> int:
    """``check --offline [--program FILE]``: :mod:`motion.cli.offline`; exit 2 when a joint cannot hold the arm up
    (or the program is invalid), else 0 (warnings on stderr)."""
    if not args.offline:
        raise UsageError("--program checks a program offline: give --offline as well")
    config = session.config
    steps = len(load_program(args.program, config).steps) if args.program else None  # (a bad one: exit 2 here)
    found = offline.budgets(config)
    errors, warnings = offline.problems(found)
    stability = torque_stability(config)
    errors += offline.stability_problems(config, stability)
    unwrap, unwrap_errors = offline.unwrapping(config)
    errors += unwrap_errors
    if args.json:
        print_json(
            {
                "config": config.source,
                "unwrapping": _unwrapping_json(unwrap),
                "program": {"file": args.program, "steps": steps} if args.program else None,
                "joints": {
                    b.name: {
                        "available_nm": round(b.available_nm, 4),
                        "hold_nm": round(b.hold_nm, 4),
                        "hold_pose_deg": [round(q, 2) for q in b.hold_pose_deg],
                        "move_nm": round(b.move_nm, 4),
                        "move_pose_deg": [round(q, 2) for q in b.move_pose_deg],
                    }
                    for b in found
                },
                "stability": _stability_dict(config, stability),
                "errors": errors,
                "warnings": warnings,
            }
        )
    else:
        print(f"{config.source}: offline (no bus); torques at the joints, the worst of the poses sampled in the limits")
        rows = [
            (b.name, f"{b.hold_nm:.2f}", f"{b.move_nm:.2f}", f"{b.available_nm:.2f}", f"{b.hold_share:.0%}",
             f"{b.move_share:.0%}")
            for b in found
        ]  # fmt: skip
        print_table(("joint", "hold N·m", "move N·m", "available N·m", "hold", "move"), rows)
        _print_stability(config, stability)
        _print_unwrapping(config, unwrap)
        if args.program:
            print(f"program {args.program}: {steps} steps, valid for this arm")
    for text in warnings:
        warn(text)
    for text in errors:
        print(f"error: {text}", file=sys.stderr)
    return EXIT_USAGE if errors else EXIT_OK


def _print_stability(config: ArmConfig, report: StabilityReport) -> None:
    """``check --offline``'s stability table (:func:`motion.cli.offline.stability_rows`)."""
    used = "" if config.control.mode.traits.host_torque else f" (not in use: {config.control.mode.value} mode)"
    lowest = report.lowest_rate_hz
    allowed = "none up to 1000 Hz" if math.isnan(lowest) else f"{lowest:.0f} Hz and up"
    print(
        f"torque mode's PD loop{used} at {report.rate_hz:g} Hz: gain margin on drives within the stated bounds "
        f"(needed {REQUIRED_MARGIN:g}); rates its gains allow: {allowed}"
    )
    print_table(("joint", "margin", "lowest rate", "kp at most", "kd at most"), offline.stability_rows(report))


def _stability_dict(config: ArmConfig, report: StabilityReport) -> dict[str, object]:
    """The stability figures for ``--json`` (``null`` for no finite figure)."""

    def finite(x: float) -> float | None:
        return round(x, 4) if math.isfinite(x) else None

    return {
        "in_use": config.control.mode.traits.host_torque,
        "rate_hz": report.rate_hz,
        "required_margin": REQUIRED_MARGIN,
        "lowest_rate_hz": finite(report.lowest_rate_hz),
        "joints": {
            m.joint.name: {
                "margin": finite(m.margin),
                "lowest_rate_hz": finite(m.lowest_rate_hz),
                "kp_max_nm_per_deg": finite(m.joint.kp_nm_per_deg * m.gain_scale),
                "kd_max_nm_per_dps": finite(m.joint.kd_nm_per_dps * m.gain_scale),
            }
            for m in report.joints
        },
    }


def _print_unwrapping(config: ArmConfig, found: list[UnwrapHeadroom]) -> None:
    """``check --offline``'s table of the encoder's unwrapping headroom (:func:`motion.cli.offline.unwrapping`)."""
    print(
        f"encoder unwrapping at control.rate_hz {config.control.rate_hz:g} Hz: the motor's turn per sample at the "
        f"velocity limit, against half a turn ({UNWRAP_BOUND_MOTOR_DEG:g} motor deg)"
    )
    print_table(("joint", "motor deg/sample", "of the bound", "rates that unwrap"), offline.unwrapping_rows(found))


def _unwrapping_json(found: list[UnwrapHeadroom]) -> dict[str, dict[str, object]]:
    """``check --offline --json``'s unwrapping figures per joint."""
    return {
        h.name: {
            "reads_angle_every_cycle": h.reads_angle,
            "motor_deg_per_sample": None if h.reads_angle else round(h.motor_deg_per_sample, 3),
            "bound_motor_deg": h.bound_motor_deg,
            "lowest_rate_hz": None if h.reads_angle else round(h.lowest_rate_hz, 3),
            "holds": h.holds,
        }
        for h in found
    }


def _fit_dict(fit: PositionLoopFit) -> dict[str, float]:
    return {
        "angle_gain_per_s": fit.loop.angle_gain_per_s,
        "acceleration_dps2": fit.loop.acceleration_dps2,
        "rms_prior_deg": fit.rms_prior_deg,
        "rms_deg": fit.rms_deg,
        "max_deg": fit.max_deg,
    }
