"""Emulated drives for the API: the protocol generation they speak, the process that runs them in real time
(``rmd-motion emulate``), and what this host holds in real time against them (the demo's figure)."""

from __future__ import annotations

import dataclasses
import os
import shutil
import subprocess
import sys
import tempfile
from collections.abc import Iterator, Mapping, Sequence
from contextlib import contextmanager
from pathlib import Path

from motion.compose import (
    build_controller,
    feedforward_for,
    negotiate_family,
    open_bus,
    opening_families,
    rehearsal_watchdog,
    stable_from_hz,
)
from motion.config import ArmConfig
from motion.config.schema import CanBusConfig, ControlMode, ProtocolSetting
from motion.control.ratecheck import RateCheck, measure_rate
from motion.emulator import Fault
from motion.emulator.simulated import DEFAULT_BITRATE
from motion.errors import ConfigError, MotionError, TransportError
from motion.protocol.table import ProtocolFamily, WireProtocol
from motion.transport import Transport

#: How long the emulator process gets to end after SIGTERM, s.
_EMULATOR_EXIT_S = 5.0


def _end_process(process: subprocess.Popen[str]) -> None:
    process.terminate()
    try:
        process.communicate(timeout=_EMULATOR_EXIT_S)
    except subprocess.TimeoutExpired:
        process.kill()
        process.communicate()


def emulated_families(
    config: ArmConfig, protocol: ProtocolFamily | str | Sequence[ProtocolFamily | str] | None
) -> tuple[ProtocolFamily, ...]:
    """The generation the emulated drives of each bus speak (in the order of ``buses:``): ``protocol`` on every bus
    (a sequence: each bus's), else the one each bus opens in (:func:`motion.compose.opening_families`: the configured
    one; with ``auto`` the one the other buses name, else the older, or V3 at a V3-only baud rate).

    Raises:
        ConfigError: an unknown generation, one per bus of another count than the buses', or one that contradicts a
            bus's ``protocol``.
    """
    if protocol is None:
        return opening_families(config)
    given = [protocol] * len(config.buses) if isinstance(protocol, str) else list(protocol)
    if len(given) != len(config.buses):
        raise ConfigError(
            config.source, "<emulated_protocol>", f"{len(given)} generations for {len(config.buses)} buses"
        )
    families = []
    for bus, value in zip(config.buses, given, strict=True):
        try:
            family = ProtocolFamily(value)
        except ValueError:
            raise ConfigError(config.source, "<emulated_protocol>", f"{value!r} is not one of v2, v3") from None
        setting = bus.protocol
        if setting is not ProtocolSetting.AUTO and setting.value != family.value:
            key = f"buses.{bus.name}.protocol" if bus.name else "bus.protocol"
            raise ConfigError(
                config.source,
                "<emulated_protocol>",
                f"{key} is {setting.value}: the emulated drives cannot speak {family.value} (use auto)",
            )
        families.append(family)
    return tuple(families)


def simulated_lines(config: ArmConfig) -> list[tuple[WireProtocol, int]]:
    """The lines of ``config``'s simulated time: one per bus, each at its own rate (their exchanges run at the same
    time: a CAN bus's frames go out together, an RS485 line's one exchange after the other)."""
    return [
        (WireProtocol.CAN, bus.bitrate or DEFAULT_BITRATE)
        if isinstance(bus, CanBusConfig)
        else (WireProtocol.RS485, bus.baudrate)
        for bus in config.buses
    ]


@contextmanager
def emulator_process(
    config: ArmConfig,
    *,
    log: str | os.PathLike[str] | None = None,
    latency_ms: float | None = None,
    faults: Sequence[Fault] = (),
    start_pose: Mapping[str, float] | None = None,
    protocol: ProtocolFamily | Sequence[ProtocolFamily] | None = None,
) -> Iterator[dict[str, object]]:
    """The drives of ``config``'s file, emulated in real time in a process of their own (``rmd-motion emulate``) on
    a slcan (CAN) or RS485 pseudo-terminal per bus, speaking ``protocol`` (a sequence: each bus's; None: each bus's
    configured one, :func:`emulated_families`); yields the bus overrides that reach them. Ended on exit.

    Raises:
        MotionError: the configuration was not read from a file.
        TransportError: the emulator process did not start.
    """
    source = Path(config.source)
    if not source.is_file():
        raise MotionError("real-time emulation builds the drives from the configuration file; this one has none")
    folder = Path(tempfile.mkdtemp(prefix="rmd-emulated-"))
    several = len(config.buses) > 1
    links = {bus.name: folder / (f"link-{bus.name}" if several else "link") for bus in config.buses}
    command = [sys.executable, "-m", "motion.cli", "emulate", "--config", str(source)]
    if protocol is not None:  # (the process speaks each bus's configured one unless told one for all, or each bus's)
        families = [protocol] * len(config.buses) if isinstance(protocol, str) else list(protocol)
        if len(set(families)) == 1:
            command += ["--protocol", ProtocolFamily(families[0]).value]
        else:
            command += [
                f"--protocol={bus.name}={ProtocolFamily(f).value}"
                for bus, f in zip(config.buses, families, strict=True)
            ]
    for bus, (name, link) in zip(config.buses, links.items(), strict=True):
        flag = "--slcan-link" if bus.transport is WireProtocol.CAN else "--rs485-link"
        command += [flag, f"{name}={link}" if several else str(link)]
    if log is not None:
        command += ["--log", os.fspath(log)]
    if latency_ms is not None:
        command += ["--latency-ms", f"{latency_ms:g}"]
    for fault in faults:  # the emulator's own clock: seconds since it started
        command += ["--fault", fault.describe()]
    for name, angle in (start_pose or {}).items():
        command += ["--start-pose", f"{name}={angle!r}"]
    process = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        if process.stdout is None:
            raise TransportError("the emulator process has no output pipe")
        lines: list[str] = []
        while not lines or not lines[-1].startswith("emulating motors"):
            line = process.stdout.readline()
            if not line:
                error = process.stderr.read() if process.stderr is not None else ""
                raise TransportError(f"the emulator process did not start: {' '.join(lines)} {error}".strip())
            lines.append(line.strip())
        yield _link_overrides(config, links)
    finally:
        _end_process(process)
        shutil.rmtree(folder, ignore_errors=True)


def _link_overrides(config: ArmConfig, links: Mapping[str, Path]) -> dict[str, object]:
    """The bus overrides that reach the emulator's pseudo-terminals: each value for the one bus, or a mapping of the
    buses' names to each one's (a key only for the buses of its transport)."""
    per_bus = {
        bus.name: {
            "interface": "slcan",
            "channel": str(links[bus.name]),
            "bitrate": DEFAULT_BITRATE,
            "sleep_after_open": 0,
        }
        if bus.transport is WireProtocol.CAN
        else {"port": str(links[bus.name])}
        for bus in config.buses
    }
    if len(per_bus) == 1:
        return dict(*per_bus.values())
    overrides: dict[str, dict[str, object]] = {}
    for name, mine in per_bus.items():
        for key, value in mine.items():
            overrides.setdefault(key, {})[name] = value
    return dict(overrides)


def measure_modes(config: ArmConfig, bus: Transport) -> dict[str, RateCheck]:
    """The rate check of ``config``'s joints on ``bus`` for each control mode (reads only: nothing moves).

    Raises:
        TransportError: a drive did not answer.
    """
    checks: dict[str, RateCheck] = {}
    for mode in ControlMode:
        variant = dataclasses.replace(config, control=dataclasses.replace(config.control, mode=mode))
        controller = build_controller(variant, bus, feedforward=feedforward_for(variant))
        controller.read_positions()
        rehearse = rehearsal_watchdog(variant, controller).rehearse
        checks[mode.value] = measure_rate(
            controller, margin=config.control.rate_margin, rehearse=rehearse, stable_from_hz=stable_from_hz(variant)
        )
    return checks


def realtime_capacity(
    config: ArmConfig, drives: ProtocolFamily | Sequence[ProtocolFamily] = ProtocolFamily.V2
) -> dict[str, RateCheck]:
    """What this host holds in real time for ``config``'s joints, per mode, against its drives emulated in a process
    of their own speaking ``drives`` (the demo's honest real-time figure).

    Raises:
        MotionError: the configuration was not read from a file.
        TransportError: the emulator process did not start or did not answer.
    """
    with (
        emulator_process(config, protocol=drives) as overrides,
        open_bus(config, **overrides) as opened,
        negotiate_family(opened, config) as bus,
    ):
        return measure_modes(config, bus)
