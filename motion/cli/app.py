"""The parser and the entry point of ``rmd-motion``, and the mapping of errors to exit codes."""

from __future__ import annotations

import argparse
import os
import sys
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Final

from motion import __version__
from motion.cli import collision, drives, examples, moves, program, scan
from motion.cli.common import (
    EXIT_COMMUNICATION,
    EXIT_FAULT,
    EXIT_INTERRUPTED,
    EXIT_OK,
    EXIT_USAGE,
    Command,
    Interrupts,
    Session,
    UsageError,
    add_bus_arguments,
    add_emulate_flag,
    add_holding_flag,
    add_turns_flag,
    add_view_arguments,
    communication_hint,
    parse_pose,
    speed_scale_arg,
    view_options,
)
from motion.cli.protocol_demo import protocol_demo
from motion.compose import opening_families
from motion.config import ArmConfig, load_config_or_example
from motion.config.schema import CanBusConfig
from motion.emulator import Emulator, Fault
from motion.emulator.cli import EmulatorFactory, add_emulate_arguments, parse_ids, protocols_of, run_emulate
from motion.errors import (
    ConfigError,
    DecodeError,
    EncodeError,
    MotionError,
    MotionFault,
    PlanningError,
    TransportError,
)
from motion.protocol.table import ProtocolFamily

DESCRIPTION: Final = "Multi-axis motion control of MyActuator RMD drives over CAN or RS485."
EPILOG: Final = """\
exit codes: 0 done, 1 motion fault (every axis halted), 2 usage or configuration error (nothing was sent),
3 communication error (bus or port failed, a drive did not answer), 130 interrupted by Ctrl-C or SIGTERM (after
every axis was halted).

Every command that talks to the bus takes --config FILE (validated before any port is opened) and the bus
overrides --interface/--channel (CAN) or --port (RS485), e.g. to use an emulator's pty:
  rmd-motion emulate --config configs/arm2.yaml --slcan-link /tmp/rmd-can &
  rmd-motion move --config configs/arm2.yaml --interface slcan --channel /tmp/rmd-can shoulder=20 elbow=-30"""
#: Share of each joint's velocity limit the drives of ``emulate --config`` hold their start pose with (motor side).
EMULATED_HOLD_SPEED_SHARE: Final = 0.1


# ---------------------------------------------------------------------------------------------------- emulate


def arm_emulator_factory(
    config: ArmConfig,
    start_pose: Mapping[str, float] | None = None,
    family: ProtocolFamily | Sequence[ProtocolFamily] = ProtocolFamily.V2,
) -> EmulatorFactory:
    """Drives of ``config`` speaking ``family`` (a sequence: each bus's), coupled through its Pinocchio model, holding
    the start pose (as if braked; V3 joints with a brake are held by it): each joint at 0 deg (or the limit nearest to
    it), or, with ``start_pose``, the joints named there, where the drives power up (their multi-turn angles restart
    from the single-turn readings).

    Without the hold, the emulated arm would fall under gravity from the moment the emulator starts until a host
    takes control; a real arm rests on its brakes or its stops instead.
    """

    def build(faults: Sequence[Fault]) -> Emulator:
        from motion.emulator.arm import arm_emulator  # noqa: PLC0415 - Pinocchio only when emulating an arm

        pose = start_pose or {}
        start = [pose.get(j.name, min(max(0.0, j.position_min_deg), j.position_max_deg)) for j in config.joints]
        emulator, _plant = arm_emulator(config, initial_deg=start, faults=faults, family=family)
        if start_pose:
            emulator.power_cycle()
        for joint in config.joints:
            drive = emulator.drives[joint.address]
            speed = joint.velocity_limit_dps * joint.gear_ratio * EMULATED_HOLD_SPEED_SHARE
            drive.hold_here(speed)
        return emulator

    return build


def emulate(args: argparse.Namespace, interrupts: Interrupts) -> int:
    """``emulate``: drives of ``--ids`` or of the arm of ``--config``."""
    interrupts.restore()  # run_emulate handles SIGINT and SIGTERM itself (a clean shutdown, exit 0)
    if not args.config:
        if args.start_pose:
            raise UsageError("--start-pose needs --config (the joints it names)")
        return run_emulate(args, None)
    config = load_config_or_example(args.config)
    # each bus's generation: --protocol's, else the configuration's (auto: the one the bus opens in)
    try:
        names = [b.name for b in config.buses]
        families = protocols_of(args.protocol, names, opening_families(config))
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    args.protocol = None if len(set(families)) > 1 else [("", families[0])]  # (the drive options' checks: one)
    args.line_families = [f for f, b in zip(families, config.buses, strict=True) if not isinstance(b, CanBusConfig)]
    args.line_bauds = {k: b.baudrate for k, b in enumerate(config.buses) if not isinstance(b, CanBusConfig)}
    buses = [(b.name, b.transport.value.lower()) for b in config.buses] if len(config.buses) > 1 else []
    return run_emulate(args, arm_emulator_factory(config, parse_pose(config, args.start_pose), families), buses)


# ---------------------------------------------------------------------------------------------------- demo, plot


def demo(args: argparse.Namespace, interrupts: Interrupts) -> int:
    """``demo``: the example arm on emulated drives (:mod:`motion.demo`), or ``--protocol`` the frame demo."""
    if args.protocol:
        return protocol_demo()
    from motion.demo import run_demo  # noqa: PLC0415 - Pinocchio and matplotlib load only for the demo

    return run_demo(args.out, quiet=args.quiet, view=view_options(args), drives=ProtocolFamily(args.drives))


def view(args: argparse.Namespace, interrupts: Interrupts) -> int:
    """``view RUN.mcap``: replay a recorded run; ``view --config FILE``: the arm live (holding) until Ctrl-C."""
    if args.run_log is not None:
        return _replay(args)
    if args.config is None:
        raise UsageError("give a recorded run (RUN.mcap) to replay, or --config FILE to see the arm live")
    options = view_options(args, wanted=True)
    return moves.with_arm(
        args, Session.from_args(args), interrupts, lambda arm: EXIT_OK, emulate=args.emulate, view=options
    )


def _replay(args: argparse.Namespace) -> int:
    from motion.compose import arm_figure  # noqa: PLC0415 - Pinocchio loads only to view
    from motion.telemetry import load_log  # noqa: PLC0415 - as plot
    from motion.view import Replay  # noqa: PLC0415

    try:
        log = load_log(args.run_log)
    except (OSError, ValueError) as exc:
        raise UsageError(f"cannot replay {args.run_log}: {exc}") from exc
    source = args.config or log.meta.get("config_source")
    if not source:
        raise UsageError(f"{args.run_log} names no configuration: give --config FILE")
    config = load_config_or_example(source)
    options = view_options(args, wanted=True)
    assert options is not None
    replay = Replay(log, config, arm_figure(config), host=options.host, port=options.port)
    print(
        f"replaying {args.run_log} ({log.cycles} cycles, {log.duration_s:.2f} s) at {replay.url}: Ctrl-C ends",
        flush=True,
    )
    try:
        while True:
            time.sleep(0.2)
    except KeyboardInterrupt:
        pass
    finally:
        replay.close()
    return EXIT_OK


def plot(args: argparse.Namespace, interrupts: Interrupts) -> int:
    """``plot LOG -o OUT.png`` (:mod:`motion.plot`)."""
    from motion.plot import plot_log  # noqa: PLC0415 - matplotlib loads only for plotting

    if Path(args.output).suffix.lower() != ".png":
        raise UsageError(f"plot draws a PNG: name it OUT.png, found {args.output}")
    try:
        plot_log(args.log, args.output)
    except (OSError, ValueError) as exc:
        raise UsageError(f"cannot plot {args.log}: {exc}") from exc
    print(f"wrote {args.output}")
    return EXIT_OK


def export(args: argparse.Namespace, interrupts: Interrupts) -> int:
    """``export RUN.mcap OUT.npz``: the recording's columns and metadata for numpy (:mod:`motion.telemetry`)."""
    from motion.telemetry import load_log  # noqa: PLC0415 - as plot

    output = Path(args.output)
    if output.suffix != ".npz":
        raise UsageError(f"export writes a numpy archive: name it OUT.npz, found {args.output}")
    if output.exists() and output.resolve() == Path(args.log).resolve():
        raise UsageError(f"{args.output} is the recording itself: name another file")
    try:
        log = load_log(args.log)
    except (OSError, ValueError) as exc:
        raise UsageError(f"cannot read {args.log}: {exc}") from exc
    try:
        log.export_npz(output)
    except OSError as exc:
        raise UsageError(f"cannot write {args.output}: {exc}") from exc
    print(f"wrote {args.output}: {log.cycles} cycles of {', '.join(log.joint_names)}")
    return EXIT_OK


# ---------------------------------------------------------------------------------------------------- parser


def _ids_arg(text: str) -> tuple[int, ...]:
    try:
        return parse_ids(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def _command(
    sub: argparse._SubParsersAction[argparse.ArgumentParser], name: str, run: Command, text: str, *, bus: bool = True
) -> argparse.ArgumentParser:
    parser = sub.add_parser(name, help=text, description=text)
    if bus:
        add_bus_arguments(parser)
    parser.set_defaults(run=run)
    return parser


def _json(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--json", action="store_true", help="print one JSON document on stdout (for scripts)")


def _motion_options(parser: argparse.ArgumentParser, speed_scale: str) -> None:
    parser.add_argument("--speed-scale", type=speed_scale_arg, default=1.0, metavar="S", help=speed_scale)
    add_emulate_flag(parser)
    add_turns_flag(parser)
    add_view_arguments(parser)
    parser.add_argument(
        "--log", metavar="FILE.mcap", help="record every control cycle as MCAP (Foxglove, rosbags; `rmd-motion plot`)"
    )
    parser.add_argument("--trace", metavar="FILE", help="record every frame on the bus (CAN: candump log)")
    add_holding_flag(parser)
    _json(parser)


def _actions(
    sub: argparse._SubParsersAction[argparse.ArgumentParser], name: str, run: Command, text: str
) -> tuple[argparse.ArgumentParser, argparse.ArgumentParser]:
    """A ``get`` / ``set`` pair of actions; ``get`` takes joint names (default all) and ``--json``."""
    parser = _command(sub, name, run, text, bus=False)
    actions = parser.add_subparsers(dest="action", required=True, metavar="ACTION")
    get = actions.add_parser("get", help="read the values of the joints (default: all)")
    add_bus_arguments(get)
    get.add_argument("joints", nargs="*", metavar="JOINT")
    _json(get)
    put = actions.add_parser("set", help="write one joint's value")
    add_bus_arguments(put)
    put.add_argument("joint", metavar="JOINT")
    return get, put


def _settings_commands(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    _, put = _actions(sub, "pid", drives.pid, "read or write the drives' PI gains (0x30, 0x31 RAM, 0x32 ROM)")
    names = tuple(f.upper() for f in drives.PID_FIELDS)
    put.description = (
        f"write the six PI gains of one joint, in this order: {' '.join(names)} (- keeps the present gain)"
    )
    where = put.add_mutually_exclusive_group()
    where.add_argument("--ram", action="store_true", help="RAM: lost at the next power cycle (default)")
    where.add_argument("--rom", action="store_true", help="ROM: kept at power-off; wears the flash (needs --yes)")
    put.add_argument("--yes", action="store_true", help="confirm a ROM write")
    # (one metavar for the six: argparse's help cannot format a tuple metavar of a positional argument)
    put.add_argument("gains", nargs=len(names), type=drives.pid_value_arg, metavar="GAIN", help=" ".join(names))

    _, put = _actions(sub, "accel", drives.accel, "read or write the drives' acceleration limit (0x33, 0x34 RAM)")
    put.description = "write one joint's acceleration limit to RAM, motor-shaft deg/s² (0: no limit)"
    put.add_argument("dps2", type=drives.accel_value_arg, metavar="DPS2")

    zero = _command(sub, "zero", drives.zero, "write a joint's present position to ROM as its zero (0x19)")
    zero.add_argument("joint", metavar="JOINT")
    zero.add_argument("--yes", action="store_true", help="confirm the ROM write (flash wear; needs a power cycle)")

    restore = _command(
        sub,
        "restore",
        drives.restore,
        "write back the drive settings rmd-motion's sessions changed, as they were before the first change (V3: "
        "planning accelerations 0x43, communication-loss protection off 0xB3)",
    )
    restore.add_argument("--yes", action="store_true", help="confirm the ROM writes (flash wear)")


def version_text() -> str:
    """``rmd-motion VERSION``."""
    return f"rmd-motion {__version__}"


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of ``rmd-motion``."""
    parser = argparse.ArgumentParser(
        prog="rmd-motion", description=DESCRIPTION, epilog=EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--version", action="version", version=version_text())
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    scanning = _command(sub, "scan", scan.scan, "list the motor ids that answer on the bus (0x9A; RS485 also 0x12)")
    scanning.add_argument("--ids", type=_ids_arg, metavar="IDS", help="ids to try: 1-6, 1,3,5 (default 1-32)")
    _json(scanning)
    status = _command(sub, "status", drives.status, "read every joint's state without moving anything")
    add_turns_flag(status)
    _json(status)
    check = _command(
        sub,
        "check",
        drives.check,
        "measure what this host and bus hold in real time (reads only): the highest control rate per mode; "
        "exit 0 when control.rate_hz holds, 2 when it does not",
    )
    check.add_argument(
        "--identify",
        action="store_true",
        help="then MOVE each joint alone out and back at full speed (position mode) to identify its position loop "
        "for the following-error check, and store it",
    )
    check.add_argument(
        "--offline",
        action="store_true",
        help="no bus: per joint, the gravity torque at the worst pose in its limits and the torque to move at the "
        "configured accelerations, against what its drive gives; exit 2 when a joint cannot hold the arm up",
    )
    check.add_argument("--program", metavar="PROGRAM.yaml", help="with --offline: validate this program as well")
    check.add_argument(
        "--holding",
        action="store_true",
        help="connect and hold still: each joint's holding torque against the model's gravity torque (a swapped motor "
        "id, a wrong gear_ratio, direction or torque constant); exit 2 on a mismatch; nothing moves",
    )
    add_emulate_flag(check)
    add_turns_flag(check)
    _json(check)

    move = _command(sub, "move", moves.move, "move joints to targets (degrees); the others keep their position")
    move.add_argument("targets", nargs="+", metavar="JOINT=DEG")
    _motion_options(move, "scale of the velocity limits, (0, 1] (default 1)")
    run = _command(sub, "run", moves.run, "run a program of move / path / wait steps (validated before moving)")
    run.formatter_class = argparse.RawDescriptionHelpFormatter
    run.epilog = program.FORMAT
    run.add_argument("program", metavar="PROGRAM.yaml", help="the program (its format below)")
    _motion_options(run, "multiplies every step's speed scale, (0, 1] (default 1)")

    jog = _command(
        sub,
        "jog",
        moves.jog,
        "MOVE one joint slowly by a few degrees and back; report which drive turned and which way (commissioning)",
    )
    jog.add_argument("joint", metavar="JOINT")
    jog.add_argument("--deg", type=float, default=moves.JOG_DEG, help=f"joint degrees out (default {moves.JOG_DEG:g})")
    add_emulate_flag(jog)
    add_turns_flag(jog)
    jog.add_argument(
        "--log", metavar="FILE.mcap", help="record every control cycle as MCAP (Foxglove, rosbags; `rmd-motion plot`)"
    )
    jog.add_argument("--trace", metavar="FILE", help="record every frame on the bus (CAN: candump log)")
    _json(jog)

    home = _command(
        sub,
        "home",
        moves.home,
        "MOVE joints slowly to their configured hard stops (joints[].homing) to find their turn offsets",
    )
    home.add_argument("joints", nargs="+", metavar="JOINT")
    add_emulate_flag(home)
    add_turns_flag(home)
    add_holding_flag(home)
    home.add_argument(
        "--log", metavar="FILE.mcap", help="record every control cycle as MCAP (Foxglove, rosbags; `rmd-motion plot`)"
    )
    home.add_argument("--trace", metavar="FILE", help="record every frame on the bus (CAN: candump log)")
    _json(home)
    collision.add_arguments(_command(sub, "collision-calibrate", collision.calibrate, collision.HELP))
    _command(sub, "hold", drives.hold, "make every drive hold its present position (0xA4 in the drive's loop)")
    _command(
        sub,
        "stop",
        drives.stop,
        "stop every drive (0x81): it stops and holds (a V3 drive with its link-loss protection on only until that "
        "time passes without a frame)",
    )
    _command(sub, "off", drives.off, "turn every drive off (0x80): torque released, the arm may fall")
    _command(sub, "clear", drives.clear, "clear the drives' error flags (0x9B); exit 1 while a cause persists")
    _settings_commands(sub)

    emulator = _command(
        sub, "emulate", emulate, "run emulated RMD drives on an slcan or RS485 pseudo-terminal", bus=False
    )
    add_emulate_arguments(emulator, config=True)
    demo_parser = _command(
        sub, "demo", demo, "the 6-DOF example arm on emulated drives: logs, traces and plots", bus=False
    )
    demo_parser.add_argument(
        "--out", type=Path, metavar="DIR", help="where the logs, traces and plots go (default ./rmd-motion-demo)"
    )
    demo_parser.add_argument("--quiet", action="store_true", help="print nothing but errors")
    demo_parser.add_argument(
        "--drives",
        choices=[f.value for f in ProtocolFamily],
        default=ProtocolFamily.V2.value,
        help="the emulated drives' protocol generation: v2 (default) or v3 (driver V3, as `emulate --protocol v3`; "
        "the controller tells it at connect)",
    )
    demo_parser.add_argument(
        "--protocol", action="store_true", help="instead: one control cycle encoded and decoded on both transports"
    )
    add_view_arguments(demo_parser)
    examples.add_init_arguments(_command(sub, "init", examples.init, examples.HELP, bus=False))
    view_parser = _command(
        sub,
        "view",
        view,
        "see the arm in the browser: live (--config FILE; holding until Ctrl-C, STOP halts it) or a recorded run "
        "replayed (RUN.mcap; --config when its configuration file has moved)",
        bus=False,
    )
    view_parser.add_argument("run_log", nargs="?", metavar="RUN.mcap", help="a recorded run to replay")
    add_bus_arguments(view_parser, required=False)
    add_emulate_flag(view_parser)
    add_turns_flag(view_parser)
    add_view_arguments(view_parser, flag=False)
    view_parser.set_defaults(log=None, trace=None)
    plot_parser = _command(sub, "plot", plot, "plot a recorded run (.mcap, or an exported .npz) into a PNG", bus=False)
    plot_parser.add_argument("log", metavar="RUN.mcap")
    plot_parser.add_argument("-o", "--output", required=True, metavar="OUT.png")
    export_parser = _command(
        sub, "export", export, "write a recorded run's columns as a numpy .npz archive (numpy.load reads it)", bus=False
    )
    export_parser.add_argument("log", metavar="RUN.mcap")
    export_parser.add_argument("output", metavar="OUT.npz")
    return parser


# ---------------------------------------------------------------------------------------------------- main


def main(argv: Sequence[str] | None = None) -> int:
    """Run ``rmd-motion``; returns the exit code (argparse exits with 2 on a usage error)."""
    args = build_parser().parse_args(argv)
    interrupts = Interrupts()
    interrupts.install()
    try:
        code: int = args.run(args, interrupts)
        return code
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    except BrokenPipeError:
        # The reader of stdout went away (`| head`); the command itself is done (an arm is closed by then).
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return EXIT_OK
    except MotionFault as exc:
        print(f"motion fault, every axis halted: {exc}", file=sys.stderr)
        if exc.cause is not None:
            print(f"likely cause: {exc.cause}", file=sys.stderr)
        return EXIT_FAULT
    except (UsageError, ConfigError, PlanningError, EncodeError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return EXIT_USAGE
    except (TransportError, DecodeError) as exc:
        print(f"communication error: {exc}", file=sys.stderr)
        hint = communication_hint(exc, getattr(args, "config", None))
        if hint is not None:
            print(f"hint: {hint}", file=sys.stderr)
        return EXIT_COMMUNICATION
    except OSError as exc:  # a file of ours, such as --log (the transports raise TransportError for the bus)
        print(f"error: {exc}", file=sys.stderr)
        return EXIT_USAGE
    except MotionError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return EXIT_USAGE
    finally:
        interrupts.restore()
