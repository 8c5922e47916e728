"""``rmd-motion scan``: which motor ids answer on the bus, in which protocol generation (on CAN told by the reply
id), with what they tell of themselves (the older family's RS485 0x12; V3: model 0xB5 and firmware date 0xB2)."""

from __future__ import annotations

import argparse
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Final

from motion.cli.common import (
    EXIT_COMMUNICATION,
    EXIT_OK,
    Interrupts,
    Session,
    flag_names,
    print_json,
    print_table,
    warn,
)
from motion.config import ArmConfig, JointConfig
from motion.config.schema import ProtocolSetting
from motion.control.family import STATUS_TYPES
from motion.protocol import Status1
from motion.protocol.generation import GENERATIONS
from motion.protocol.table import (
    ADDRESS_STRIDE,
    MOTOR_ID_MAX,
    MOTOR_ID_MIN,
    ProtocolFamily,
    WireProtocol,
    split_address,
)
from motion.protocol.v3.messages import Status1V3
from motion.transport import Request, Transport
from motion.transport.buses import Buses
from motion.transport.can_transport import CanTransport
from motion.transport.identity import Identity, read_identities

#: Scan: the reply window of a CAN batch (the drives answer in parallel), s, plus a share per request: an adapter
#: (and an emulator in its own process on a busy host) passes the frames one after the other.
SCAN_CAN_S: Final = 0.25
SCAN_CAN_PER_REQUEST_S: Final = 0.01
#: Scan: the reply window of each RS485 request (one drive after the other), s.
SCAN_RS485_PER_ID_S: Final = 0.03
#: Scan: a configured drive that did not answer is asked again with windows this many times longer.
SCAN_RETRY_STRETCH: Final = 4.0


def _label(joint: JointConfig) -> str:
    return f"{joint.name} ({joint.drive_label})"


def _drive(config: ArmConfig, address: int) -> str:
    """``"3"``, or ``"3 on bus right"`` on an arm of several buses."""
    index, motor_id = split_address(address)
    return f"{motor_id} on bus {config.buses[index].name}" if len(config.buses) > 1 else str(motor_id)


@dataclass(frozen=True)
class _Scanned:
    """A drive that answered the scan: its generation, its status, and what it told of itself (None: nothing)."""

    family: ProtocolFamily
    status: Status1 | Status1V3
    identity: Identity | None


@contextmanager
def _speaking(bus: Transport, family: ProtocolFamily) -> Iterator[Transport]:
    """``bus`` where it speaks ``family``, else a second transport on its CAN port that does (a scan meets drives of
    either generation on one CAN bus)."""
    if bus.family is family:
        yield bus
        return
    assert isinstance(bus, CanTransport)
    with CanTransport.over(bus.port, clock=bus.clock, family=family, owns_port=False) as other:
        yield other


def _scan_in(bus: Transport, ids: Sequence[int], wire: WireProtocol, stretch: float) -> dict[int, _Scanned]:
    """The status (0x9A) and identity of ``ids`` on a transport that speaks their generation (windows ``stretch``
    times the defaults)."""
    generation = bus.generation
    window_s = stretch * _window(wire, len(ids))
    replies = bus.transact([Request(i, generation.status_read) for i in ids], bus.clock() + window_s)
    status = {r.motor_id: r.message for r in replies if isinstance(r.message, STATUS_TYPES)}
    answered = sorted(status)
    reads = len(answered) * len(generation.identity_reads[wire])
    identities = read_identities(bus, answered, wire, stretch * _window(wire, reads))
    return {i: _Scanned(bus.family, status[i], identities.get(i)) for i in answered}


def _window(wire: WireProtocol, requests: int) -> float:
    """Scan's reply window for a batch of ``requests`` on ``wire``, s."""
    return SCAN_CAN_S + (SCAN_CAN_PER_REQUEST_S if wire is WireProtocol.CAN else SCAN_RS485_PER_ID_S) * requests


def _scan_ids(bus: Transport, ids: Sequence[int], wire: WireProtocol, stretch: float) -> dict[int, _Scanned]:
    """Ask ``ids`` who they are (windows ``stretch`` times the defaults), each in its generation: on a real CAN bus
    the reply ids tell the generations apart (an id that did not answer is asked in the bus's own); elsewhere the
    bus's generation alone answers."""
    if not isinstance(bus, CanTransport):
        return _scan_in(bus, ids, wire, stretch)
    generations = bus.probe_families(ids, stretch * _window(WireProtocol.CAN, len(ids))) or {}
    groups: dict[ProtocolFamily, list[int]] = {}
    for motor_id in ids:
        groups.setdefault(generations.get(motor_id, bus.family), []).append(motor_id)
    scanned: dict[int, _Scanned] = {}
    for family, group in groups.items():
        with _speaking(bus, family) as speaker:
            scanned.update(_scan_in(speaker, group, wire, stretch))
    return scanned


def scan(args: argparse.Namespace, interrupts: Interrupts) -> int:
    """Which motor ids answer 0x9A, in which protocol generation (CAN: told by the reply id), and their model (RS485:
    0x12; V3 drives: 0xB5 and the firmware date 0xB2)."""
    session = Session.from_args(args)
    config = session.config
    ids: tuple[int, ...] = args.ids or tuple(range(MOTOR_ID_MIN, MOTOR_ID_MAX + 1))
    several = len(config.buses) > 1
    answered: dict[int, _Scanned] = {}  # by address (an arm on several buses: each bus scanned on its own)
    with session.open_bus(check=False) as bus:
        parts = bus.buses if isinstance(bus, Buses) else (bus,)
        for index, (part, bus_config) in enumerate(zip(parts, config.buses, strict=True)):
            wire, base = bus_config.transport, index * ADDRESS_STRIDE
            found = _scan_ids(part, ids, wire, 1.0)
            # a configured drive that did not answer is asked once more with a longer window (a busy host or
            # adapter can hold replies back longer than the first window): it is reported missing only then
            configured = {j.motor_id for j in config.joints_on(index)}
            again = [i for i in ids if i in configured and i not in found]
            if again:
                found.update(_scan_ids(part, again, wire, SCAN_RETRY_STRETCH))
            answered.update({base + i: scanned for i, scanned in found.items()})
        where = bus.describe()
    names = session.names
    drives: list[dict[str, object]] = []
    rows: list[tuple[object, ...]] = []
    for address, scanned in sorted(answered.items()):
        status, identity = scanned.status, scanned.identity
        flags = flag_names(status.errors)
        index, motor_id = split_address(address)
        bus_name = config.buses[index].name
        drives.append(
            {
                "motor_id": motor_id,
                **({"bus": bus_name} if several else {}),
                "joint": names.get(address),
                "protocol": scanned.family.value,
                "voltage_v": status.voltage_v,
                "temperature_c": status.temperature_c,
                "errors": flags,
                "model": None if identity is None else identity.record,
            }
        )
        rows.append(
            (motor_id, *((bus_name,) if several else ()), names.get(address, "-"), scanned.family.value,
             f"{status.voltage_v:.1f} V", f"{status.temperature_c} °C", ",".join(flags) or "ok",
             "-" if identity is None else identity.text)
        )  # fmt: skip
    missing = [_label(j) for j in config.joints if j.address not in answered]
    if args.json:
        print_json({"bus": where, "drives": drives, "missing": missing})
    else:
        print(f"{where}: {len(drives)} of {len(ids) * len(config.buses)} ids answered")
        print_table(
            ("id", *(("bus",) if several else ()), "joint", "protocol", "voltage", "temp", "flags", "model"), rows
        )
    for index, bus_config in enumerate(config.buses):
        here = {a: s.family for a, s in sorted(answered.items()) if split_address(a)[0] == index}
        key = f"buses.{bus_config.name}.protocol" if several else "bus.protocol"
        if len(set(here.values())) > 1:
            told = ", ".join(f"{_drive(config, a)}: {f.value}" for a, f in here.items())
            warn(f"drives of both protocol generations on {f'bus {bus_config.name}' if several else 'the bus'} "
                 f"({told}): a bus's drives speak one (connecting refuses it)")  # fmt: skip
            continue
        setting = bus_config.protocol
        other = [a for a, f in here.items() if setting is not ProtocolSetting.AUTO and f.value != setting.value]
        if other:
            speaks = GENERATIONS[here[other[0]]].title
            warn(
                f"motor(s) {', '.join(_drive(config, a) for a in other)} speak the {speaks}, not the configuration's "
                f"({key}: {setting.value}): set it to {here[other[0]].value} or auto"
            )
    if missing:
        warn(f"communication error: configured joint(s) not answering: {', '.join(missing)}")
        return EXIT_COMMUNICATION
    return EXIT_OK
