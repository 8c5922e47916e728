"""Emulated RMD drives on a virtual slcan USB-CAN adapter, an RS485 pty or a python-can virtual bus.

Examples::

    rmd-motion emulate --ids 1-6 --slcan-link /tmp/rmd-can          # then: can.Bus('slcan', '/tmp/rmd-can', ...)
    rmd-motion emulate --ids 1,3,5 --rs485-link /tmp/rmd-485 --bus-time --log frames.log
    rmd-motion emulate --ids 1-4 --virtual-channel arm --fault over_temperature:2@5-20:95 --fault delay:1@0:15
    rmd-motion emulate --config configs/arm2.yaml --slcan-link /tmp/rmd-can    # the arm's own drives and dynamics

It prints the path of each attachment, then runs until SIGINT or SIGTERM (exit code 0). Exit codes: 2 for usage
errors, 3 when a pty, link or bus cannot be set up or an attachment fails. ``python -m motion.emulator`` runs the
same command without ``--config``: building drives from an arm configuration (and its dynamic model) is the job of
the composition root, ``rmd-motion emulate`` (:mod:`motion.cli`), which hands :func:`run_emulate` an
:data:`EmulatorFactory`.
"""

from __future__ import annotations

import argparse
import contextlib
import logging
import math
import signal
import sys
import threading
import types
from collections.abc import Callable, Iterator, Mapping, Sequence
from typing import Any, TypeVar

from motion.emulator.attach import (
    DEFAULT_CAN_BITRATE,
    DEFAULT_RS485_BAUD,
    Attachment,
    Rs485Attachment,
    SlcanAttachment,
    VirtualCanAttachment,
)
from motion.emulator.core import Emulator
from motion.emulator.drive_v3 import EmulatedDriveV3
from motion.emulator.faults import Fault, parse_fault
from motion.emulator.framelog import FrameLog
from motion.emulator.model import DriveModel
from motion.emulator.timing import DEFAULT_LATENCY_S, TimingModel
from motion.errors import TransportError
from motion.protocol.table import MOTOR_ID_MAX, MOTOR_ID_MIN, RS485_BAUDRATES, ProtocolFamily

EXIT_OK = 0
EXIT_USAGE = 2
EXIT_COMMUNICATION = 3
#: Baud rates of the RS485 documents (both generations; each family's own are checked with --protocol).
RS485_BAUDS = tuple(sorted({rate for rates in RS485_BAUDRATES.values() for rate in rates}))
N = TypeVar("N", int, float)
#: Builds the emulated drives from the faults to schedule (``rmd-motion emulate --config``: the arm's drives).
EmulatorFactory = Callable[[Sequence[Fault]], Emulator]
#: Options that describe the drives themselves; a configuration gives them per joint instead.
_DRIVE_OPTIONS = {"encoder_bits": "--encoder-bits", "gear_ratio": "--gear-ratio", "seed": "--seed"}
_DEFAULT_ENCODER_BITS = 14
_DEFAULT_GEAR_RATIO = 1.0
_DEFAULT_SEED = 0
#: How often the main thread checks the attachments while waiting for a signal, s.
_WATCH_S = 0.2


def parse_ids(text: str) -> tuple[int, ...]:
    """Parse motor ids such as ``1-6``, ``1,3,5`` or ``1-3,8`` into a sorted tuple.

    Raises:
        ValueError: a part is not an id or a range, an id is outside 1..32, a range is reversed, or an id repeats.
    """
    ids: list[int] = []
    for part in text.split(","):
        first, dash, last = part.strip().partition("-")
        try:
            lo = int(first)
            hi = int(last) if dash else lo
        except ValueError:
            raise ValueError(f"{part.strip()!r} is not an id or a range like 1-6") from None
        for value in (lo, hi):
            if not MOTOR_ID_MIN <= value <= MOTOR_ID_MAX:
                raise ValueError(f"motor id {value} is outside {MOTOR_ID_MIN}..{MOTOR_ID_MAX}")
        if hi < lo:
            raise ValueError(f"range {part.strip()!r} goes backwards")
        ids += range(lo, hi + 1)
    repeated = sorted({i for i in ids if ids.count(i) > 1})
    if repeated:
        raise ValueError(f"motor id {repeated[0]} is given twice")
    return tuple(sorted(ids))


def _ids_arg(text: str) -> tuple[int, ...]:
    try:
        return parse_ids(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def _fault_arg(text: str) -> Fault:
    try:
        return parse_fault(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def _number_arg(convert: Callable[[str], N], valid: Callable[[N], bool], what: str) -> Callable[[str], N]:
    """An argparse ``type`` that converts a number and checks it, naming ``what`` it must be."""

    def parse(text: str) -> N:
        try:
            value = convert(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not {what}") from None
        if not valid(value):
            raise argparse.ArgumentTypeError(f"{text!r} is not {what}")
        return value

    return parse


_latency_arg = _number_arg(float, lambda v: 0 <= v < math.inf, "a latency >= 0 ms")
_bitrate_arg = _number_arg(int, lambda v: v > 0, "a bit rate > 0 bit/s")
_gear_arg = _number_arg(float, lambda v: 0 < v < math.inf, "a gear ratio > 0")


def add_emulate_arguments(parser: argparse.ArgumentParser, *, config: bool = False) -> None:
    """Add the options of ``rmd-motion emulate`` to ``parser``.

    Args:
        parser: the parser of the command.
        config: also offer ``--config FILE`` as the alternative to ``--ids`` (only where the caller passes
            :func:`run_emulate` a factory that builds the drives from the configuration).
    """
    drives = parser.add_mutually_exclusive_group(required=True)
    drives.add_argument(
        "--ids",
        type=_ids_arg,
        metavar="IDS",
        help="motor ids of the emulated drives: 1-6, 1,3,5 or 1-3,8 (each 1..32)",
    )
    if config:
        drives.add_argument(
            "--config",
            metavar="FILE",
            help="arm configuration: one drive per joint with its motor id, gear ratio, encoder and current limit, "
            "coupled through the arm's rigid-body dynamics (gravity loads the motors); the drives start holding "
            "the start pose (every joint at 0 deg, or at the limit nearest to it) as if braked",
        )
        parser.add_argument(
            "--start-pose",
            action="append",
            default=[],
            metavar="JOINT=DEG",
            help="with --config: the drives power up with the joint there (others at 0 deg, or the nearest limit), "
            "so they know it only modulo 360/gear_ratio, as real drives do; repeatable",
        )
    where = parser.add_argument_group("attachments (at least one)")
    where.add_argument(
        "--slcan-link",
        action="append",
        default=[],
        metavar="[BUS=]PATH",
        help="virtual slcan USB-CAN adapter on a pty, with a symlink at PATH; with --config of an arm on several "
        "buses, BUS=PATH for each of its CAN buses (repeat the option)",
    )
    where.add_argument(
        "--rs485-link",
        action="append",
        default=[],
        metavar="[BUS=]PATH",
        help="RS485 line on a pty, with a symlink at PATH; BUS=PATH for each RS485 bus of an arm on several",
    )
    where.add_argument(
        "--virtual-channel",
        metavar="NAME",
        help="python-can virtual bus channel (in-process: for a host running in this process)",
    )
    timing = parser.add_argument_group("timing")
    timing.add_argument(
        "--latency-ms",
        type=_latency_arg,
        default=DEFAULT_LATENCY_S * 1000,
        metavar="MS",
        help="drive reply latency in ms (default %(default)g)",
    )
    timing.add_argument(
        "--bus-time",
        action="store_true",
        help="also model bus occupation: CAN bits at the bit rate, RS485 10 bits/byte at the baud",
    )
    timing.add_argument(
        "--bitrate",
        type=_bitrate_arg,
        default=DEFAULT_CAN_BITRATE,
        metavar="BIT_S",
        help="bit rate of the virtual CAN bus for --bus-time (slcan uses the host's Sn command)",
    )
    timing.add_argument(
        "--baud",
        type=int,
        choices=RS485_BAUDS,
        help=f"RS485 baud rate for --bus-time, of every line (default: with --config each RS485 bus's baudrate; else "
        f"{DEFAULT_RS485_BAUD})",
    )
    parser.add_argument(
        "--fault",
        action="append",
        default=[],
        type=_fault_arg,
        metavar="KIND:MOTOR@START[-END][:PARAM]",
        help="inject a fault at simulation time START s (until END s): over_temperature[:degC], "
        "under_voltage[:V], silent, delay[:ms], corrupt[:payload|id|length], drop[:probability], blocked, "
        "collision:NM, power_cycle; repeatable (MOTOR of an arm on several buses: bus index x 100 + motor id, "
        "103 for motor 3 of the second)",
    )
    parser.add_argument(
        "--encoder-bits",
        type=int,
        choices=range(12, 19),
        metavar="12..18",
        help=f"encoder resolution of every drive (with --ids; default {_DEFAULT_ENCODER_BITS})",
    )
    parser.add_argument(
        "--gear-ratio",
        type=_gear_arg,
        metavar="RATIO",
        help=f"motor degrees per joint degree of every drive (with --ids; default {_DEFAULT_GEAR_RATIO:g})",
    )
    parser.add_argument(
        "--seed", type=int, help=f"seed of the drop faults' random draws (with --ids; default {_DEFAULT_SEED})"
    )
    parser.add_argument(
        "--protocol",
        action="append",
        type=_protocol_arg,
        metavar="[BUS=]v2|v3",
        help="the drives' protocol generation: v2 (the CAN v2.3 / RS485 v1.62 documents) or v3 (driver V3, "
        "V4.2 document: replies on 0x240+id, RS485 frames with a CRC16); BUS=v2|v3 for one bus of an arm on several "
        "(repeatable) (default: with --config, each bus's protocol where that names one, auto the older; else v2)",
    )
    parser.add_argument(
        "--brakes",
        type=_ids_arg,
        default=(),
        metavar="IDS",
        help="with --protocol v3: the drives whose joint has a holding brake (locked at power-on; 0x77 releases)",
    )
    parser.add_argument(
        "--log",
        metavar="FILE",
        help="write every frame in and out to FILE, one line each, timed by the emulator's clock (that of --fault)",
    )


def _build_emulator(args: argparse.Namespace, factory: EmulatorFactory | None) -> Emulator:
    """The drives of ``--ids`` (with the drive options), or of ``--config`` through ``factory``.

    Raises:
        ValueError: conflicting options, or drives or faults the emulator rejects (ConfigError is one).
    """
    family = protocol_of(args.protocol)
    # (--config: each RS485 line's generation; --baud applies to every line)
    given: Sequence[ProtocolFamily] | None = getattr(args, "line_families", None)
    families = (family,) if given is None else given
    for each in dict.fromkeys(families):
        if args.baud is not None and args.baud not in RS485_BAUDRATES[each]:
            allowed = ", ".join(map(str, RS485_BAUDRATES[each]))
            raise ValueError(f"--baud {args.baud}: {each.value} drives run at {allowed} baud")
    if args.brakes and getattr(args, "config", None) is not None:
        raise ValueError("--brakes applies to --ids only: with --config each joint's brake is configured (brake: true)")
    if args.brakes and family is not ProtocolFamily.V3:
        raise ValueError("--brakes needs --protocol v3 (the older drives have no brake commands)")
    if getattr(args, "config", None) is None:
        model = DriveModel(
            encoder_bits=_DEFAULT_ENCODER_BITS if args.encoder_bits is None else args.encoder_bits,
            gear_ratio=_DEFAULT_GEAR_RATIO if args.gear_ratio is None else args.gear_ratio,
        )
        seed = _DEFAULT_SEED if args.seed is None else args.seed
        return Emulator(args.ids, model=model, faults=args.fault, seed=seed, family=family, brakes=args.brakes)
    options = [option for name, option in _DRIVE_OPTIONS.items() if getattr(args, name) is not None]
    if options:
        raise ValueError(f"{', '.join(options)} apply to --ids only: with --config each joint's drive is configured")
    if factory is None:
        raise ValueError("--config needs the arm's model: run it as `rmd-motion emulate --config FILE`")
    return factory(tuple(args.fault))


def _protocol_arg(text: str) -> tuple[str, ProtocolFamily]:
    """``v3`` -> ``("", v3)``; ``right=v3`` -> ``("right", v3)``."""
    name, _, value = text.rpartition("=")
    try:
        return name, ProtocolFamily(value)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: expected v2, v3, or BUS=v2|v3") from None


def protocol_of(given: Sequence[tuple[str, ProtocolFamily]] | None) -> ProtocolFamily:
    """The one generation of ``--protocol`` (v2 where it is not given).

    Raises:
        ValueError: given more than once, or for a bus (``BUS=``: with ``--config`` of an arm on several buses).
    """
    if not given:
        return ProtocolFamily.V2
    if len(given) > 1 or given[0][0]:
        raise ValueError(
            "--protocol BUS=v2|v3 (or given more than once) applies to --config of an arm on several buses"
        )
    return given[0][1]


def protocols_of(
    given: Sequence[tuple[str, ProtocolFamily]] | None, buses: Sequence[str], configured: Sequence[ProtocolFamily]
) -> tuple[ProtocolFamily, ...]:
    """Each bus's generation (``buses`` by name; ``configured``: each one's own, where ``--protocol`` names none):
    one ``--protocol`` for every bus, or ``BUS=`` for each it names.

    Raises:
        ValueError: a bus unknown or named twice, or a plain value besides named ones.
    """
    families = list(configured)
    named: set[str] = set()
    for name, family in given or ():
        if not name:
            if len(given or ()) > 1:
                raise ValueError("--protocol: one value for every bus, or BUS=v2|v3 for each bus it names; not both")
            return (family,) * len(buses)
        if name not in buses:
            raise ValueError(f"--protocol {name}={family.value}: no bus {name!r}; the buses are {', '.join(buses)}")
        if name in named:
            raise ValueError(f"--protocol: bus {name} is named twice")
        named.add(name)
        families[buses.index(name)] = family
    return tuple(families)


def emulator_clock(emulator: Emulator) -> Callable[[], float]:
    """The emulator's simulation time as a clock (seconds since it started)."""
    return lambda: emulator.time_s


#: The kinds of link and the bus transport each carries.
_LINKS = {"slcan_link": ("--slcan-link", "can"), "rs485_link": ("--rs485-link", "rs485")}


def _links(args: argparse.Namespace, buses: Sequence[tuple[str, str]]) -> list[tuple[str, int, str, str]]:
    """``(option, line, bus name, path)`` of each ``--slcan-link`` / ``--rs485-link``: a plain PATH where the drives are
    on one bus (``buses`` empty or of one), ``BUS=PATH`` for each of an arm's several ``buses`` (name, transport).

    Raises:
        ValueError: a link given twice, a BUS=PATH without several buses, a bus unknown, of the other transport, or
            without a link.
    """
    links: list[tuple[str, int, str, str]] = []
    several = len(buses) > 1
    names = [name for name, _ in buses]
    for key, (option, transport) in _LINKS.items():
        given: list[str] = getattr(args, key)
        if not several:
            if len(given) > 1:
                raise ValueError(f"{option} is given {len(given)} times: the drives are on one bus")
            if given and "=" in given[0] and given[0].split("=", 1)[0] in names:
                given = [given[0].split("=", 1)[1]]
            links += [(option, 0, "", path) for path in given]
            continue
        for text in given:
            name, equals, path = text.partition("=")
            if not equals or not path:
                raise ValueError(
                    f"{option} {text!r}: the arm is on several buses: give BUS=PATH, BUS one of {', '.join(names)}"
                )
            if name not in names:
                raise ValueError(f"{option} {text!r}: no bus {name!r}; the buses are {', '.join(names)}")
            if buses[names.index(name)][1] != transport:
                raise ValueError(f"{option} {text!r}: bus {name} is a {buses[names.index(name)][1]} bus")
            if any(line == names.index(name) for _, line, _, _ in links):
                raise ValueError(f"{option} {text!r}: bus {name} has a link already")
            links.append((option, names.index(name), name, path))
    missing = [name for k, name in enumerate(names) if several and all(line != k for _, line, _, _ in links)]
    if missing:
        raise ValueError(
            f"no link for bus(es) {', '.join(missing)}: give one --slcan-link or --rs485-link BUS=PATH each"
        )
    return links


def _attachments(
    args: argparse.Namespace,
    emulator: Emulator,
    timing: TimingModel,
    frame_log: FrameLog | None,
    links: Sequence[tuple[str, int, str, str]],
) -> Iterator[Attachment[Any, Any]]:
    """The attachments the options ask for, made one at a time (the caller enters each before the next is made)."""
    if args.virtual_channel:
        yield VirtualCanAttachment(
            emulator, args.virtual_channel, bitrate=args.bitrate, timing=timing, frame_log=frame_log
        )
    bauds: Mapping[int, int] = getattr(args, "line_bauds", {})  # (each RS485 bus's of --config, by line)
    for option, line, _name, path in links:
        if option == "--slcan-link":
            yield SlcanAttachment(emulator, path, timing=timing, frame_log=frame_log, line=line)
        else:
            baud = args.baud or bauds.get(line, DEFAULT_RS485_BAUD)
            yield Rs485Attachment(emulator, path, baud=baud, timing=timing, frame_log=frame_log, line=line)


def run_emulate(
    args: argparse.Namespace, factory: EmulatorFactory | None = None, buses: Sequence[tuple[str, str]] = ()
) -> int:
    """Run the emulator until SIGINT or SIGTERM; returns the exit code.

    Args:
        args: the parsed options of :func:`add_emulate_arguments`.
        factory: builds the drives when ``args.config`` is given (see :data:`EmulatorFactory`).
        buses: the configuration's buses, ``(name, transport)`` each, when it has several (a link each).
    """
    if not (args.slcan_link or args.rs485_link or args.virtual_channel):
        print("error: give at least one of --slcan-link, --rs485-link, --virtual-channel", file=sys.stderr)
        return EXIT_USAGE
    if not logging.getLogger().handlers:
        logging.basicConfig(level=logging.WARNING, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    try:
        links = _links(args, buses)
        if args.virtual_channel and len(buses) > 1:
            raise ValueError("--virtual-channel carries one bus: the arm is on several (give a link per bus)")
        emulator = _build_emulator(args, factory)
        timing = TimingModel(args.latency_ms / 1000.0, args.bus_time)
    except ValueError as exc:  # ConfigError is a ValueError
        print(f"error: {exc}", file=sys.stderr)
        return EXIT_USAGE
    stop = threading.Event()

    def on_signal(signum: int, frame: types.FrameType | None) -> None:
        stop.set()

    previous = {s: signal.signal(s, on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
    attachments: list[Attachment[Any, Any]] = []
    failed = False
    try:
        with contextlib.ExitStack() as stack:
            try:
                # the log's clock is the emulator's (real time once the first frame syncs it): the times of --fault
                # and of the frames are then on one clock
                clock = emulator_clock(emulator)
                frame_log = stack.enter_context(FrameLog(args.log, clock=clock)) if args.log else None
                made = _attachments(args, emulator, timing, frame_log, links)
                attachments += [stack.enter_context(a) for a in made]
            except (TransportError, OSError) as exc:
                print(f"communication error: {exc}", file=sys.stderr)
                return EXIT_COMMUNICATION
            names = {line: name for _, line, name, _ in links}
            for attachment in attachments:
                device = getattr(attachment, "device_path", None)
                bus = f" (bus {names[attachment.line]})" if names.get(attachment.line) else ""
                pty = f" (pty {device})" if device else ""
                print(f"{attachment.channel}: {attachment.path}{pty}{bus}", flush=True)
            faults = ", ".join(f.describe() for f in emulator.faults) or "none"
            if len(buses) > 1:  # (each bus's drives by their own ids; a fault names a drive by its address)
                motors = ", ".join(
                    f"{','.join(map(str, emulator.line_ids.get(line, ())))} on bus {name}"
                    for line, (name, _) in enumerate(buses)
                )
            else:
                motors = ",".join(map(str, emulator.ids))
            print(f"emulating motors {motors}; faults: {faults}; stop with Ctrl-C or SIGTERM", flush=True)
            while not stop.wait(_WATCH_S):
                if any(a.failure is not None for a in attachments):
                    break
    except RuntimeError as exc:  # an attachment's thread failed; close() re-raised it
        print(f"communication error: {exc}", file=sys.stderr)
        failed = True
    finally:
        for signum, handler in previous.items():
            signal.signal(signum, handler)
    for attachment in attachments:
        s = attachment.stats
        print(
            f"{attachment.channel}: {s.requests} requests, {s.replies} replies, {s.decode_errors} protocol errors, "
            f"{s.unanswered} unanswered, {s.corrupted} corrupted, {s.undelivered} undelivered",
            file=sys.stderr,
        )
    stops = [drive.link_losses for drive in emulator.drives.values() if isinstance(drive, EmulatedDriveV3)]
    if stops:  # the drives' own stops when no frame came for their communication-loss time (0xB3)
        print(f"{sum(stops)} communication-loss stops", flush=True)
    return EXIT_COMMUNICATION if failed else EXIT_OK


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m motion.emulator``: the emulate command on its own."""
    parser = argparse.ArgumentParser(prog="python -m motion.emulator", description=(__doc__ or "").splitlines()[0])
    add_emulate_arguments(parser)
    return run_emulate(parser.parse_args(argv))
