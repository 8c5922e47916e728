"""What the commands of ``rmd-motion`` share: exit codes, the session (configuration + bus overrides), signal
handling, joint targets and output."""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import os
import signal
import sys
import types
from collections.abc import Callable, Collection, Iterator, Mapping, Sequence
from dataclasses import dataclass
from enum import IntFlag
from typing import Any, Final

from motion.compose import negotiate_family, open_bus, with_bandwidth_gains
from motion.config import ArmConfig, CanBusConfig, JointConfig, Rs485BusConfig, load_config_or_example
from motion.config.schema import BusConfig
from motion.errors import DrivesSilent, MotionError, PortHeld, PortUnavailable, TransportError
from motion.protocol import Message
from motion.protocol.generation import GENERATIONS
from motion.protocol.table import ADDRESS_STRIDE, ProtocolFamily
from motion.transport import Request, Transport
from motion.view import DEFAULT_HOST, DEFAULT_PORT, PORTS, ViewOptions, host_warning

EXIT_OK: Final = 0
EXIT_FAULT: Final = 1
EXIT_USAGE: Final = 2
EXIT_COMMUNICATION: Final = 3
EXIT_INTERRUPTED: Final = 130

#: Time the drives get to answer a one-off batch of requests (not a control cycle), s.
REPLY_TIMEOUT_S: Final = 0.2
#: The bus override options and the bus kind each applies to.
#: Every kind of bus's command-line overrides (each bus configuration names its own: ``overridable``).
BUS_OVERRIDES: Final = tuple(dict.fromkeys((*CanBusConfig.overridable, *Rs485BusConfig.overridable)))
#: What :meth:`Session.open_bus` lets a command speak: the drives of either generation, or the older one alone.
EVERY_GENERATION: Final = tuple(ProtocolFamily)
OLDER_ONLY: Final = (ProtocolFamily.V2,)
#: Where pseudo-terminal devices live.
_PTY_PREFIX: Final = "/dev/pts/"


class UsageError(Exception):
    """The command line asks for something invalid (exit code 2); nothing was sent."""


# ---------------------------------------------------------------------------------------------------- signals


class Interrupts:
    """SIGINT and SIGTERM raise KeyboardInterrupt in the main thread, except inside :meth:`deferred` sections
    (a signal there is raised when the outermost section ends) or after :meth:`ignore`. Inside a :meth:`halting`
    section a signal first asks the control loop to halt every axis, at once, deferred or not."""

    def __init__(self) -> None:
        self._depth = 0
        self._pending = False
        self._ignored = False
        self._previous: dict[int, Any] = {}
        self._halt: Callable[[str], None] | None = None

    def install(self) -> None:
        """Take over SIGINT and SIGTERM (:meth:`restore` gives them back)."""
        for signum in (signal.SIGINT, signal.SIGTERM):
            self._previous[signum] = signal.signal(signum, self._handle)

    def restore(self) -> None:
        """Give SIGINT and SIGTERM back to their previous handlers."""
        for signum, handler in self._previous.items():
            signal.signal(signum, handler)
        self._previous.clear()

    def _handle(self, signum: int, frame: types.FrameType | None) -> None:
        if self._ignored:
            return
        if self._halt is not None and not self._pending:  # (a second Ctrl-C: the loop has the first request)
            # nothing to halt (not connected yet): the signal goes on as any other
            with contextlib.suppress(MotionError):
                self._halt(signal.Signals(signum).name)
        if self._depth:
            self._pending = True
            return
        raise KeyboardInterrupt

    @contextlib.contextmanager
    def deferred(self) -> Iterator[None]:
        """A section that a signal must not cut short (connecting, halting, releasing the bus). A signal there is
        raised when the outermost section ends, also in place of an exception that ends it (the halt a
        :meth:`halting` section asked for ends a homing in connect with its fault: the KeyboardInterrupt's cause)."""
        self._depth += 1
        try:
            yield
        except Exception as exc:
            if self._depth == 1 and self._take_pending():
                raise KeyboardInterrupt from exc
            raise
        finally:
            self._depth -= 1
        if not self._depth and self._take_pending():
            raise KeyboardInterrupt

    def _take_pending(self) -> bool:
        """Whether a deferred signal is to be raised now (once)."""
        if self._pending and not self._ignored:
            self._pending = False
            return True
        return False

    @contextlib.contextmanager
    def halting(self, halt: Callable[[str], None]) -> Iterator[None]:
        """A section in which the motors may move under a control loop (connecting with homing, a command's
        motion): a signal first calls ``halt`` with its name (``"SIGINT"``), deferred or not. It runs in the signal
        handler, between two bytecodes of the main thread (which may be in a control cycle itself, in simulated
        time): it must only ask the loop to halt every axis in its next cycle and return
        (:meth:`motion.api.Arm.request_stop`); a MotionError from it (nothing to halt yet) is ignored."""
        previous, self._halt = self._halt, halt
        try:
            yield
        finally:
            self._halt = previous

    def ignore(self) -> None:
        """Ignore further signals (the halt after the first one must run to its end)."""
        self._ignored = True


# ---------------------------------------------------------------------------------------------------- session


@dataclass(frozen=True, slots=True)
class Session:
    """The validated configuration of a command and the bus settings the command line overrides.

    Attributes:
        config: the arm.
        overrides: replacements for configured bus settings (``interface``/``channel`` or ``port``).
    """

    config: ArmConfig
    overrides: Mapping[str, object]

    @classmethod
    def from_args(cls, args: argparse.Namespace) -> Session:
        """Load ``--config`` and check the bus overrides against its bus (no port is opened).

        Raises:
            ConfigError: the file is missing or invalid.
            UsageError: an override for the other kind of bus.
        """
        config = with_bandwidth_gains(load_config_or_example(args.config))
        given: dict[str, list[str]] = {}
        for name in BUS_OVERRIDES:
            values = getattr(args, name, None) or []
            if values:
                given[name] = [values] if isinstance(values, str) else list(values)  # (a Namespace made by hand: str)
        if len(config.buses) == 1:
            allowed = config.bus.overridable
            wrong = [f"--{name}" for name in given if name not in allowed]
            if wrong:
                valid = " and ".join(f"--{n}" for n in allowed)
                raise UsageError(
                    f"{', '.join(wrong)}: {config.source} has a {config.bus.transport.value} bus; its overrides are "
                    f"{valid}"
                )
        overrides: dict[str, object] = {name: _override(config, name, values) for name, values in given.items()}
        sleeps = {
            bus.name: 0
            for bus in config.buses
            if isinstance(bus, CanBusConfig)
            and _given(overrides, "interface", bus, bus.interface) == "slcan"
            and _is_pty(str(_given(overrides, "channel", bus, bus.channel)))
        }
        # python-can waits 2 s for a real slcan adapter to boot; a pseudo-terminal (an emulator) has none.
        if sleeps:
            overrides["sleep_after_open"] = sleeps if len(config.buses) > 1 else 0
        return cls(config, overrides)

    def open_bus(self, *, check: bool = True, speaks: Collection[ProtocolFamily] = OLDER_ONLY) -> Transport:
        """Open the configured bus with the overrides and (``check``) speak the drives' generation
        (:func:`motion.compose.negotiate_family`; the returned transport owns the port), refusing V3 drives unless
        the command ``speaks`` theirs (:data:`EVERY_GENERATION`; ``scan`` reads any generation and does not ask).

        Raises:
            TransportError: the bus or port could not be opened, or its drives were refused.
        """
        bus = open_bus(self.config, **self.overrides)
        if not check:
            return bus
        try:
            spoken = negotiate_family(bus, self.config)
        except TransportError:
            bus.close()
            raise
        unspoken = [(k, f) for k, f in enumerate(spoken.families) if f not in speaks]
        if unspoken:
            spoken.close()
            index, family = unspoken[0]
            name = self.config.buses[index].name
            where = f"on bus {name} " if name and len(self.config.buses) > 1 else ""
            raise TransportError(
                f"the drives {where}answer in the {GENERATIONS[family].title}: this command speaks "
                f"the {' and '.join(GENERATIONS[f].title for f in speaks)} alone; status, stop, off, hold, clear, "
                "pid get, accel get, check, move, run, demo and scan speak theirs"
            )
        return spoken

    @property
    def names(self) -> dict[int, str]:
        """Joint name by drive address (the motor id on an arm of one bus)."""
        return {j.address: j.name for j in self.config.joints}

    def joint(self, name: str) -> JointConfig:
        """The configured joint ``name``.

        Raises:
            UsageError: no such joint (the message lists the joints).
        """
        for joint in self.config.joints:
            if joint.name == name:
                return joint
        raise UsageError(unknown_joint(self.config, name))

    def joints(self, names: Sequence[str]) -> tuple[JointConfig, ...]:
        """The joints named (every joint when ``names`` is empty), in the order given."""
        return tuple(self.joint(n) for n in names) if names else self.config.joints


def _override(config: ArmConfig, name: str, values: Sequence[str]) -> object:
    """The override ``--NAME`` of ``values``: one value for the arm's one bus (or for every bus: ``--interface``), or
    ``BUS=VALUE`` per bus of an arm on several (``{bus: value}``).

    Raises:
        UsageError: an override for the other kind of bus, given twice for one bus, a plain ``--channel`` or ``--port``
            for several buses, or an unknown bus name.
    """
    buses = {bus.name: bus for bus in config.buses}
    several = len(buses) > 1
    per_bus: dict[str, str] = {}
    for value in values:
        bus_name, equals, rest = value.partition("=")
        if several and equals and bus_name in buses:
            target = [buses[bus_name]]
            if bus_name in per_bus:
                raise UsageError(f"--{name} is given twice for bus {bus_name}")
            per_bus[bus_name] = rest
        elif several and name != "interface":
            raise UsageError(
                f"--{name} {value!r}: {config.source} has several buses ({', '.join(buses)}): give --{name} BUS=VALUE "
                "for each bus it overrides"
            )
        else:
            if len(values) > 1:
                if several:
                    raise UsageError(f"--{name}: give BUS=VALUE for every bus it overrides, or one value for them all")
                raise UsageError(f"--{name} is given {len(values)} times: the arm has one bus")
            target = list(buses.values())
        for bus in target:
            if name not in bus.overridable:
                valid = " and ".join(f"--{n}" for n in bus.overridable)
                where = f"bus {bus.name}" if bus.name else "bus"
                raise UsageError(
                    f"--{name}: {config.source}'s {where} is a {bus.transport.value} bus; its overrides are {valid}"
                )
    if per_bus:
        if len(per_bus) != len(values):
            raise UsageError(f"--{name}: give BUS=VALUE for every bus it overrides, or one value for them all")
        return per_bus
    return values[0]


def _given(overrides: Mapping[str, object], name: str, bus: BusConfig, configured: str) -> object:
    """The value of ``name`` that ``bus`` opens with: the override (its own, or every bus's), else ``configured``."""
    value = overrides.get(name, configured)
    if isinstance(value, Mapping):
        return value.get(bus.name, configured)
    return value


def _is_pty(path: str) -> bool:
    """Whether ``path`` leads to a pseudo-terminal (such as the emulator's)."""
    return os.path.realpath(path).startswith(_PTY_PREFIX)


def add_bus_arguments(parser: argparse.ArgumentParser, *, required: bool = True) -> None:
    """``--config`` and the bus overrides."""
    parser.add_argument(
        "--config",
        required=required,
        metavar="FILE",
        help="arm configuration (YAML); when no such file exists, an example's name (arm2.yaml, configs/arm2.yaml)",
    )
    bus = parser.add_argument_group(
        "bus overrides (replace the configured bus settings; an arm on several buses: BUS=VALUE, once per bus)"
    )
    bus.add_argument(
        "--interface",
        action="append",
        metavar="[BUS=]NAME",
        help="CAN: python-can interface (socketcan, slcan, pcan, ...)",
    )
    bus.add_argument(
        "--channel",
        action="append",
        metavar="[BUS=]CHANNEL",
        help="CAN: interface channel (can0, /dev/ttyACM0, a pty, ...)",
    )
    bus.add_argument("--port", action="append", metavar="[BUS=]DEVICE", help="RS485: serial device (/dev/ttyUSB0, ...)")


def add_holding_flag(parser: argparse.ArgumentParser) -> None:
    """``--no-holding-check`` of the commands that move the arm through a program or to targets, or home it."""
    parser.add_argument(
        "--no-holding-check",
        action="store_true",
        help="skip the holding check (each joint's holding torque against the model's gravity torque, as `check "
        "--holding`; run on real buses before the first move, after the seek for `home`; exit 2 on a mismatch)",
    )


def add_emulate_flag(parser: argparse.ArgumentParser) -> None:
    """``--emulate``: the command runs on the configuration's emulated drives in simulated time (no port opened)."""
    parser.add_argument(
        "--emulate",
        action="store_true",
        help="run on the configuration's emulated drives, in simulated time: a dry run that opens no port and gives "
        "the same result on every host",
    )
    parser.add_argument(
        "--start-pose",
        action="append",
        default=[],
        metavar="JOINT=DEG",
        help="with --emulate: the emulated drives power up with the joint there (joints not named at 0 deg), so "
        "they know it only modulo 360/gear_ratio, as real drives do; repeatable",
    )


def add_view_arguments(parser: argparse.ArgumentParser, *, flag: bool = True) -> None:
    """``--view`` (with ``flag``) and where the page listens: ``--view-host`` / ``--view-port`` (see
    :mod:`motion.view`); without ``flag`` (``rmd-motion view``) ``--host`` as well."""
    if flag:
        parser.add_argument(
            "--view",
            action="store_true",
            help="show the arm live in the browser while the command runs (and after it, until Ctrl-C); with "
            "--emulate paced to the wall clock",
        )
    parser.add_argument(
        *(("--view-host",) if flag else ("--view-host", "--host")),  # rmd-motion view: --host too (--port is taken)
        dest="view_host",
        default=DEFAULT_HOST,
        metavar="HOST",
        help=f"address the view listens on (default {DEFAULT_HOST}: this computer only; anyone who can reach "
        "another one sees the arm and can press STOP)",
    )
    parser.add_argument(
        "--view-port",
        type=_port_arg,
        default=DEFAULT_PORT,
        metavar="PORT",
        help=f"the view's port (default {DEFAULT_PORT}; 0: any free one)",
    )


def _port_arg(text: str) -> int:
    valid = f"{PORTS[0]}..{PORTS[-1]}"
    try:
        port = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a port number ({valid})") from None
    if port not in PORTS:
        raise argparse.ArgumentTypeError(f"{port} is outside {valid}")
    return port


def view_options(args: argparse.Namespace, *, wanted: bool | None = None) -> ViewOptions | None:
    """The view the command asked for (``--view``, or ``wanted``), warning about an address beyond this computer."""
    if not (getattr(args, "view", False) if wanted is None else wanted):
        return None
    warning = host_warning(args.view_host)
    if warning is not None:
        warn(warning)
    return ViewOptions(args.view_host, args.view_port)


def add_turns_flag(parser: argparse.ArgumentParser) -> None:
    """``--forget-turns`` / ``--keep-turns``: the drives were powered up since the last session, or stayed powered
    (see :mod:`motion.control.turns`)."""
    turns = parser.add_mutually_exclusive_group()
    turns.add_argument(
        "--forget-turns",
        action="store_true",
        help="the drives have been powered up since the last session, with every joint inside its "
        "power_on_window_deg: leave the recorded turn offsets aside and resolve every joint from its window",
    )
    turns.add_argument(
        "--keep-turns",
        action="store_true",
        help="the drives have stayed powered since the last session: its recorded turn offsets hold (where a "
        "reading alone cannot tell)",
    )


# ---------------------------------------------------------------------------------------------------- joints


def unknown_joint(config: ArmConfig, name: str) -> str:
    """The message for a joint name that the configuration does not have."""
    return f"unknown joint {name!r}; the joints of {config.name} are {', '.join(config.joint_names)}"


def target_problem(config: ArmConfig, name: str, angle_deg: float) -> str | None:
    """Why ``name = angle_deg`` is not a valid target (unknown joint, outside its range), or None."""
    joint = next((j for j in config.joints if j.name == name), None)
    if joint is None:
        return unknown_joint(config, name)
    if not math.isfinite(angle_deg):
        return f"{name}: {angle_deg} is not a finite angle"
    if not joint.position_min_deg <= angle_deg <= joint.position_max_deg:
        return (
            f"{name} = {angle_deg:g} deg is outside its range "
            f"[{joint.position_min_deg:g}, {joint.position_max_deg:g}] deg"
        )
    return None


def parse_targets(config: ArmConfig, items: Sequence[str]) -> dict[str, float]:
    """``JOINT=DEG`` arguments -> ``{joint: deg}``, every one checked against the configuration.

    Raises:
        UsageError: a malformed item, a joint given twice, an unknown joint or a target outside the joint's range.
    """
    targets = parse_pose(config, items)
    for name, angle in targets.items():
        problem = target_problem(config, name, angle)
        if problem is not None:
            raise UsageError(problem)
    return targets


def parse_pose(config: ArmConfig, items: Sequence[str]) -> dict[str, float]:
    """``JOINT=DEG`` arguments -> ``{joint: deg}`` (joints of the configuration, finite angles, any value).

    Raises:
        UsageError: a malformed item, a joint given twice or an unknown joint.
    """
    pose: dict[str, float] = {}
    for item in items:
        name, equals, value = item.partition("=")
        name = name.strip()
        try:
            angle = float(value) if equals and name else math.nan
        except ValueError:
            angle = math.nan
        if not math.isfinite(angle):
            raise UsageError(f"{item!r}: expected JOINT=DEG, e.g. {config.joint_names[0]}=30")
        if name in pose:
            raise UsageError(f"{name} is given twice")
        if name not in config.joint_names:
            raise UsageError(unknown_joint(config, name))
        pose[name] = angle
    return pose


def speed_scale_arg(text: str) -> float:
    """argparse type of ``--speed-scale``: a number in (0, 1]."""
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not 0.0 < value <= 1.0:
        raise argparse.ArgumentTypeError(f"{text!r} is not a speed scale in (0, 1]")
    return value


# ---------------------------------------------------------------------------------------------------- bus


def exchange(
    bus: Transport,
    requests: Sequence[Request],
    names: Mapping[int, str],
    expect: type[Message] | tuple[type[Message], ...],
) -> dict[int, Any]:
    """One batch of one-off requests (one per motor); every motor must answer with an ``expect`` message (one of them:
    each generation's).

    Returns:
        The replies by motor id.

    Raises:
        TransportError: a drive did not answer in time, or answered with something else.
    """
    replies = bus.transact(requests, bus.clock() + REPLY_TIMEOUT_S)
    got = {r.motor_id: r.message for r in replies if isinstance(r.message, expect)}
    # (the joint's name tells the bus of an arm on several; the motor id is the drive's own on it)
    missing = [
        f"{names.get(r.motor_id, '?')} (motor {r.motor_id % ADDRESS_STRIDE})" for r in replies if r.motor_id not in got
    ]
    if missing:
        raise TransportError(
            f"no {expect.__name__ if isinstance(expect, type) else ' or '.join(e.__name__ for e in expect)} reply from "
            f"{', '.join(missing)} "
            f"on {bus.describe()} "
            f"within {REPLY_TIMEOUT_S * 1000:g} ms: is the drive powered, on this bus and at this id?"
        )
    return got


def flag_names(flags: IntFlag) -> list[str]:
    """The names of the set error bits (unknown bits as hex), of either family's error flags."""
    kind = type(flags)
    names = [f.name.lower() for f in kind if f and f in flags and f.name]
    known = 0
    for f in kind:
        known |= f.value
    if flags.value & ~known:
        names.append(f"0x{flags.value & ~known:02x}")
    return names


# ---------------------------------------------------------------------------------------------------- output


def print_json(data: object) -> None:
    """One JSON document on stdout."""
    print(json.dumps(data, indent=2))


def print_table(headers: Sequence[str], rows: Sequence[Sequence[object]]) -> None:
    """Left-aligned columns on stdout."""
    text = [[str(c) for c in headers], *([str(c) for c in row] for row in rows)]
    widths = [max(len(row[i]) for row in text) for i in range(len(headers))]
    for row in text:
        print("  ".join(cell.ljust(width) for cell, width in zip(row, widths, strict=True)).rstrip())


def warn(message: str) -> None:
    """A note on stderr."""
    print(message, file=sys.stderr)


#: A command: the parsed arguments and the signal handling -> exit code.
Command = Callable[[argparse.Namespace, Interrupts], int]


def communication_hint(exc: BaseException, config_path: object) -> str | None:
    """What to try next after a communication error, for the errors that have a usual cause (None: no hint)."""
    config = config_path or "FILE"
    if isinstance(exc, PortHeld):
        return (
            "another rmd-motion command or program is connected to this bus (the process named above): let it end, or "
            "end it (Ctrl-C there halts its arm first), then run this command again"
        )
    if isinstance(exc, PortUnavailable):
        rs485 = exc.link == "rs485"
        adapter, link, override = (
            ("a USB-RS485 adapter is --port /dev/ttyUSB0", "--rs485-link /tmp/rmd-rs485", "--port /tmp/rmd-rs485")
            if rs485
            else (
                "a SocketCAN interface must be up, `sudo ip link set can0 up type can bitrate 1000000`; a USB-CAN "
                "stick is --interface slcan --channel /dev/ttyACM0",
                "--slcan-link /tmp/rmd-slcan",
                "--interface slcan --channel /tmp/rmd-slcan",
            )
        )
        return (
            f'check the adapter (README, "Connecting hardware": {adapter}; a serial port needs read/write '
            f"permission, e.g. the dialout group). To try without hardware: `rmd-motion emulate --config {config} "
            f"{link}` in another terminal, then this command with {override} (move and run also take --emulate)"
        )
    if isinstance(exc, DrivesSilent):
        asked = ", ".join(exc.labels) or "the configured ones"
        return (
            f"the drive(s) asked: {asked}. `rmd-motion scan --config {config}` lists the ids that answer and their "
            "protocol generation. Check each drive's id (MyActuator's setup tool), its power, the wiring and, on CAN, "
            'the bus bit rate and the 120 Ohm termination at both ends (README, "Connecting hardware"). A dry run '
            f"without the drives: move and run take --emulate, or `rmd-motion emulate --config {config}` in another "
            "terminal serves the configured drives on a virtual adapter"
        )
    return None
