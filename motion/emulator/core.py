"""The emulator: drives on one bus, the plant they turn, simulation time and the fault schedule.

Simulation time advances in fixed steps (:data:`DEFAULT_STEP_S`), either by hand (:meth:`Emulator.advance`, for
deterministic tests) or following the monotonic clock (:meth:`Emulator.sync`, which the bus attachments call). Each
step applies the faults that begin or end, lets every drive turn the plant's state into a torque, and integrates the
plant. Requests are decoded with the protocol codec, executed by the addressed drive and answered with replies
encoded by the same codec, after the link faults (silent, drop, delay, corrupt) had their say.

Thread safety: every public method takes the emulator's lock, so attachments on several threads can share it.
"""

from __future__ import annotations

import heapq
import logging
import math
import random
import threading
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Final, Generic, TypeVar

import numpy as np

from motion.emulator.drive import EmulatedDrive
from motion.emulator.drive_v3 import EmulatedDriveV3
from motion.emulator.faults import Corruption, Fault, InjectedFault, corrupt_can, corrupt_rs485, corrupt_rs485_v3
from motion.emulator.model import DriveModel, LoadModel
from motion.emulator.plant import IndependentLoads, Plant
from motion.errors import ConfigError
from motion.protocol import CanFrame, Message
from motion.protocol.generation import GENERATIONS
from motion.protocol.table import ADDRESS_STRIDE, ProtocolFamily, WireProtocol, check_motor_id, split_address

logger = logging.getLogger("motion.emulator")

#: Integration step, s (2 kHz: well above the drives' speed-loop bandwidth and any host control rate).
DEFAULT_STEP_S: Final = 0.0005
#: Largest stretch of simulation :meth:`Emulator.sync` catches up in one call, s; beyond it simulation time slips
#: behind the wall clock (counted in ``overruns``) rather than stalling the replies.
MAX_CATCH_UP_S: Final = 0.25
#: Default fault parameters relative to the drive's thresholds, and of the link faults.
_OVER_TEMPERATURE_MARGIN_C: Final = 10.0
_UNDER_VOLTAGE_MARGIN_V: Final = 6.0
_DEFAULT_DELAY_MS: Final = 10.0
_LINK_KINDS: Final = (InjectedFault.SILENT, InjectedFault.DROP, InjectedFault.DELAY, InjectedFault.CORRUPT)

W = TypeVar("W")


@dataclass(frozen=True, slots=True)
class Outgoing(Generic[W]):
    """One reply on its way to the host.

    Attributes:
        motor_id: the drive that answers.
        wire: the encoded reply (a :class:`CanFrame` or RS485 bytes), damaged if ``corruption`` is set.
        message: the reply as the drive built it.
        delay_s: extra delay from a ``delay`` fault, s.
        corruption: how a ``corrupt`` fault damaged ``wire``, or None.
    """

    motor_id: int
    wire: W
    message: Message
    delay_s: float = 0.0
    corruption: Corruption | None = None


@dataclass(frozen=True, slots=True)
class Exchange(Generic[W]):
    """What one request did.

    Attributes:
        motor_id: the addressed drive (None for the CAN 0x280 multi-motor frame).
        request: the decoded request.
        replies: replies in the order the drives send them (ascending id for 0x280).
        notes: why an addressed drive did not answer (absent, silent, dropped).
    """

    motor_id: int | None
    request: Message
    replies: tuple[Outgoing[W], ...]
    notes: tuple[str, ...]


class Emulator:
    """Emulated RMD drives on one bus, turning a plant.

    Args:
        ids: motor ids of the drives, 1..32.
        model: the drives' parameters, one for all or one per id.
        load: each drive's load, one for all or one per id. Always used to scale the drives' speed loops (unless
            the model says ``tuned_inertia_kgm2``), and to build the default plant.
        plant: the mechanics (joint side, drives in ascending id order); default :class:`IndependentLoads` of
            ``load`` with each rotor as armature.
        faults: faults to schedule (see :mod:`motion.emulator.faults`).
        step_s: integration step, s.
        seed: seed of the random draws of ``drop`` faults.
        stops: hard stops per motor id: the lowest and highest position of its joint in the plant's coordinate
            (motor angle / gear ratio, rad; ``-inf`` / ``inf`` where there is none). The joint cannot pass them.
        family: the protocol generation the drives speak: ``v2`` (:class:`EmulatedDrive`) or ``v3``
            (:class:`~motion.emulator.drive_v3.EmulatedDriveV3`, with its brakes and communication-loss protection);
            a sequence: each line's (bus index -> generation), one for every line a drive is on.
        brakes: V3 family: the ids of the drives whose joint has a holding brake.

    Raises:
        ValueError: an id outside 1..32 or given twice, a fault on a drive that is not emulated, a bad step, a plant
            of the wrong size, or no generation for a line.
    """

    def __init__(
        self,
        ids: Iterable[int],
        *,
        model: DriveModel | Mapping[int, DriveModel] | None = None,
        load: LoadModel | Mapping[int, LoadModel] | None = None,
        plant: Plant | None = None,
        faults: Iterable[Fault] = (),
        step_s: float = DEFAULT_STEP_S,
        seed: int = 0,
        stops: Mapping[int, tuple[float, float]] | None = None,
        family: ProtocolFamily | Sequence[ProtocolFamily] = ProtocolFamily.V2,
        brakes: Iterable[int] = (),
    ) -> None:
        id_list = [_check_address(i) for i in ids]
        if len(set(id_list)) != len(id_list) or not id_list:
            raise ValueError(f"motor ids must be distinct and at least one, got {id_list}")
        if not (math.isfinite(step_s) and step_s > 0):
            raise ValueError(f"integration step must be > 0 s, got {step_s!r}")
        self.ids: tuple[int, ...] = tuple(sorted(id_list))
        #: The drives' motor ids on each line (bus) they are on, by line index (their addresses split).
        self.line_ids: dict[int, tuple[int, ...]] = {}
        for address in self.ids:
            line, motor_id = split_address(address)
            self.line_ids[line] = (*self.line_ids.get(line, ()), motor_id)
        self.step_s = step_s
        models = [_pick(model, i, DriveModel) for i in self.ids]
        loads = [_pick(load, i, LoadModel) for i in self.ids]
        self.plant: Plant = plant or IndependentLoads(loads, [m.rotor_inertia_kgm2 * m.gear_ratio**2 for m in models])
        if self.plant.size != len(self.ids):
            raise ValueError(f"plant has {self.plant.size} joints for {len(self.ids)} drives")
        per_line = [family] if isinstance(family, str) else list(family)
        if isinstance(family, str):
            per_line *= max(self.line_ids) + 1
        if len(per_line) <= max(self.line_ids):
            raise ValueError(f"protocol generations {per_line}: one for each line 0..{max(self.line_ids)} expected")
        #: The protocol generation of each line's drives (by line index).
        self.families: tuple[ProtocolFamily, ...] = tuple(ProtocolFamily(f) for f in per_line)
        #: The first line's generation (the only one of a single bus).
        self.family = self.families[min(self.line_ids)]
        #: Each line's wire protocol (the drives' side of it: requests decoded, replies encoded).
        self.generations = tuple(GENERATIONS[f] for f in self.families)
        #: The first line's (see :attr:`family`).
        self.generation = GENERATIONS[self.family]
        self._encode_can = [_can_encoder(g.encode_can_reply) for g in self.generations]
        self._encode_rs485 = [
            _rs485_encoder(g.encode_rs485_reply, _CORRUPT_RS485[f])
            for g, f in zip(self.generations, self.families, strict=True)
        ]
        braked = set(brakes)
        v3 = {a for a in self.ids if self.families[split_address(a)[0]] is ProtocolFamily.V3}
        if braked - v3:
            raise ValueError(f"brakes {sorted(braked)}: expected ids of emulated V3 drives {sorted(v3)}")
        self.drives: dict[int, EmulatedDrive] = {}
        for i, m, ld in zip(self.ids, models, loads, strict=True):
            tuned = m.rotor_inertia_kgm2 + ld.inertia_kgm2 / m.gear_ratio**2
            wire_id = split_address(i)[1]  # (a drive knows its id on its own bus only)
            if i in v3:
                self.drives[i] = EmulatedDriveV3(wire_id, m, tuned, brake=i in braked)
            else:
                self.drives[i] = EmulatedDrive(wire_id, m, tuned)
        self._v3 = [(n, d) for n, d in enumerate(self.drives[i] for i in self.ids) if isinstance(d, EmulatedDriveV3)]
        self._order = [self.drives[i] for i in self.ids]
        self._index = {i: n for n, i in enumerate(self.ids)}
        self._torques = np.zeros(len(self.ids))
        #: External joint torque per drive (``collision`` faults), N·m, emulator order.
        self.external_torque_nm = np.zeros(len(self.ids))
        self._positions, self._velocities = self.plant.state()
        self._observe_all()
        self._lock = threading.RLock()
        self._rng = random.Random(seed)
        self._steps = 0
        self._target_s = 0.0
        self._epoch_s: float | None = None
        #: Times sync() gave up catching up and let simulation time slip behind the wall clock.
        self.overruns = 0
        self._faults: list[Fault] = []
        #: Blocked joints (emulator index -> where they are held, rad).
        self._blocked: dict[int, float] = {}
        #: Hard stops (emulator index -> (lowest, highest) joint position, rad, emulator coordinate).
        self._stops: dict[int, tuple[float, float]] = {}
        for motor_id, (low, high) in (stops or {}).items():
            if motor_id not in self._index or not low < high:
                raise ValueError(f"hard stops of motor {motor_id}: expected an emulated id and low < high")
            self._stops[self._index[motor_id]] = (low, high)
        self._done: list[Fault] = []  # one-shot faults that have happened
        self._events: list[tuple[float, int]] = []  # (sim time, motor id) where a physical fault begins or ends
        for fault in faults:
            self.add_fault(fault)

    # --- time -----------------------------------------------------------------------------------------------------

    @property
    def time_s(self) -> float:
        """Simulation time, s (a whole number of steps)."""
        return self._steps * self.step_s

    def advance(self, dt_s: float) -> None:
        """Advance simulation time by ``dt_s`` seconds (whole steps; the remainder carries over).

        Raises:
            ValueError: a negative or non-finite ``dt_s``.
        """
        if not (math.isfinite(dt_s) and dt_s >= 0):
            raise ValueError(f"cannot advance by {dt_s!r} s")
        with self._lock:
            self._target_s += dt_s
            # The epsilon keeps float noise from dropping a step that is due (0.1 / 0.0005 = 199.99999...).
            due = math.floor(self._target_s / self.step_s + 1e-9)
            for _ in range(due - self._steps):
                self._step()

    def advance_to(self, t_s: float) -> None:
        """Advance simulation time to ``t_s`` (no-op when it is already there or past it).

        Raises:
            ValueError: a non-finite ``t_s``.
        """
        if not math.isfinite(t_s):
            raise ValueError(f"cannot advance to {t_s!r} s")
        with self._lock:
            if t_s > self._target_s:
                self.advance(t_s - self._target_s)

    def sync(self, now_s: float | None = None) -> None:
        """Advance simulation time to the monotonic clock (``now_s``, default ``time.monotonic()``).

        The first call ties the current simulation time to ``now_s``; calls from several threads are harmless.
        """
        now = time.monotonic() if now_s is None else now_s
        with self._lock:
            if self._epoch_s is None:
                self._epoch_s = now - self._target_s
            behind = now - self._epoch_s - self._target_s
            if behind > MAX_CATCH_UP_S:
                self._epoch_s += behind - MAX_CATCH_UP_S
                behind = MAX_CATCH_UP_S
                self.overruns += 1
                logger.warning("emulator fell behind real time; simulation time slips (overrun %d)", self.overruns)
            if behind > 0:
                self.advance(behind)

    def _apply_fault_events(self) -> None:
        """Let the physical faults that began or ended by now take effect."""
        now = self.time_s
        while self._events and self._events[0][0] <= now:
            _, motor_id = heapq.heappop(self._events)
            self._refresh_physical_faults(motor_id)

    def _step(self) -> None:
        self._apply_fault_events()
        positions, velocities, torques, dt = self._positions, self._velocities, self._torques, self.step_s
        for n, drive in enumerate(self._order):
            torques[n] = drive.control(dt, float(positions[n]), float(velocities[n]))
        torques += self.external_torque_nm
        held = self._held_by_brakes() if self._v3 else {}
        self._positions, self._velocities = self.plant.step(dt, torques)
        if self._blocked or held:
            for n, position in (self._blocked | held).items():
                self.plant.hold(n, position)
            self._positions, self._velocities = self.plant.state()
        if self._stops:
            self._at_stops()
        self._steps += 1

    def _held_by_brakes(self) -> dict[int, float]:
        """V3 drives: trip the communication-loss protection where it is due; the joints whose brake is locked, at
        their position (emulator index -> rad)."""
        now = self.time_s
        held: dict[int, float] = {}
        for n, drive in self._v3:
            if drive.check_link(now):
                logger.info(
                    "motor %d: no frame for %d ms: output cut, brake locked",
                    drive.motor_id,
                    drive.communication_timeout_ms,
                )
            if drive.held:
                held[n] = float(self._positions[n])
        return held

    def _at_stops(self) -> None:
        """A joint that passed one of its hard stops is put back on it, at rest (the stop takes the momentum; the
        drive's torque keeps pressing it there); away from the stop it moves freely."""
        pressed = False
        for n, (low, high) in self._stops.items():
            position = float(self._positions[n])
            if position <= low or position >= high:
                self.plant.hold(n, low if position <= low else high, 1 if position <= low else -1)
                pressed = True
        if pressed:
            self._positions, self._velocities = self.plant.state()

    def _observe_all(self) -> None:
        for n, drive in enumerate(self._order):
            drive.observe(float(self._positions[n]), float(self._velocities[n]))

    def power_cycle(self, motor_id: int | None = None) -> None:
        """Switch one drive (or all) off and on: RAM settings are lost, ROM settings take effect."""
        with self._lock:
            self._observe_all()
            for drive in self._order if motor_id is None else [self.drives[motor_id]]:
                drive.power_cycle()

    # --- faults ---------------------------------------------------------------------------------------------------

    def add_fault(self, fault: Fault) -> None:
        """Schedule a fault.

        Raises:
            ValueError: the fault's drive is not emulated.
        """
        if fault.motor_id not in self.drives:
            raise ValueError(f"fault {fault.describe()}: motor {fault.motor_id} is not emulated (ids {self.ids})")
        with self._lock:
            self._faults.append(fault)
            if fault.kind not in _LINK_KINDS:
                heapq.heappush(self._events, (fault.start_s, fault.motor_id))
                if fault.end_s is not None:
                    heapq.heappush(self._events, (fault.end_s, fault.motor_id))

    @property
    def faults(self) -> tuple[Fault, ...]:
        """Every scheduled fault."""
        return tuple(self._faults)

    def _refresh_physical_faults(self, motor_id: int) -> None:
        drive, now = self.drives[motor_id], self.time_s
        volts, floors, external = [], [], 0.0
        active = [f for f in self._faults if f.motor_id == motor_id and f.active(now)]
        for f in active:  # one-shot faults whose instant has come, each once
            if f.kind is InjectedFault.POWER_CYCLE and not any(f is done for done in self._done):
                self._done.append(f)
                self._observe_all()
                drive.power_cycle()
        for f in active:
            if f.kind is InjectedFault.COLLISION and f.value is not None:
                external += f.value
            elif f.kind is InjectedFault.UNDER_VOLTAGE:
                volts.append(f.value if f.value is not None else drive.model.low_voltage_v - _UNDER_VOLTAGE_MARGIN_V)
            elif f.kind is InjectedFault.OVER_TEMPERATURE:
                default_c = drive.model.over_temperature_c + _OVER_TEMPERATURE_MARGIN_C
                floors.append(f.value if f.value is not None else default_c)
        self.external_torque_nm[self._index[motor_id]] = external
        drive.voltage_override_v = max(0.0, min(volts)) if volts else None
        n = self._index[motor_id]
        if any(f.kind is InjectedFault.BLOCKED for f in active):
            self._blocked.setdefault(n, float(self._positions[n]))
        else:
            self._blocked.pop(n, None)
        drive.temperature_floor_c = max(floors) if floors else None
        if floors:
            drive.temperature_c = max(drive.temperature_c, *floors)

    def _link(self, motor_id: int) -> tuple[str | None, float, Corruption | None]:
        """``(why the request is lost or None, extra reply delay in s, corruption)`` for a request now."""
        lost, delay_s, corruption, now = None, 0.0, None, self.time_s
        for f in self._faults:
            if f.motor_id != motor_id or f.kind not in _LINK_KINDS or not f.active(now):
                continue
            if f.kind is InjectedFault.SILENT:
                lost = f"silent ({f.describe()})"
            elif f.kind is InjectedFault.DROP:
                if self._rng.random() < (1.0 if f.value is None else f.value):
                    lost = f"request dropped ({f.describe()})"
            elif f.kind is InjectedFault.DELAY:
                delay_s += (_DEFAULT_DELAY_MS if f.value is None else f.value) / 1000.0
            else:
                corruption = f.corruption
        return lost, delay_s, corruption

    # --- replies without requests (0xB6) --------------------------------------------------------------------------

    def next_active_reply_s(self) -> float | None:
        """When the next reply a V3 drive sends by itself (0xB6) is due, simulation time; None: none is set up."""
        with self._lock:
            return min(
                (t for _, d in self._v3 if (t := d.next_active_reply_s()) is not None),
                default=None,
            )

    def active_replies(self, at_s: float | None = None, line: int | None = None) -> list[Outgoing[CanFrame]]:
        """The CAN frames the V3 drives (of bus ``line``, or of every bus) send by themselves (0xB6) that are due by
        the present simulation time (or ``at_s``, where the emulator was advanced to: its whole steps may stop short
        of it), in ascending drive address."""
        with self._lock:
            now = self.time_s if at_s is None else max(self.time_s, at_s)
            due: list[Outgoing[CanFrame]] = []
            for n, drive in self._v3:
                address = self.ids[n]
                if line is None or address // ADDRESS_STRIDE == line:
                    encode = self._encode_can[address // ADDRESS_STRIDE]
                    due.extend(
                        Outgoing(address, encode(m, drive.motor_id, None), m) for m in drive.active_replies_due(now)
                    )
            return due

    # --- requests -------------------------------------------------------------------------------------------------

    def handle_can(self, frame: CanFrame, line: int = 0) -> Exchange[CanFrame]:
        """Execute a CAN request frame that came on bus ``line`` (a frame for several drives, 0x280 / 0x300: each
        of that bus takes its share).

        Raises:
            DecodeError: the frame breaks the family's CAN protocol (id, length, command, field, reserved byte).
        """
        motor_id, message = self.generations[line].decode_can_request(frame.arbitration_id, frame.data)
        return self._dispatch(line, motor_id, message, WireProtocol.CAN, self._encode_can[line])

    def handle_rs485(self, raw: bytes, line: int = 0) -> Exchange[bytes]:
        """Execute an RS485 request frame that came on line ``line`` (V3: id 0xCD reaches every drive of it).

        Raises:
            DecodeError: the frame breaks the family's RS485 protocol (length, head, checksum, id, command, field).
        """
        motor_id, message = self.generations[line].decode_rs485_request(raw)
        return self._dispatch(line, motor_id, message, WireProtocol.RS485, self._encode_rs485[line])

    def _dispatch(
        self,
        line: int,
        motor_id: int | None,
        request: Message,
        transport: WireProtocol,
        encode: Callable[[Message, int, Corruption | None], W],
    ) -> Exchange[W]:
        """Each drive of bus ``line`` the request reaches (``motor_id``, or its share of a frame for several
        drives) executes it and answers; the exchange names drives by their addresses."""
        targets = (
            self.generations[line].spread(request, self.line_ids.get(line, ()))
            if motor_id is None
            else [(motor_id, request)]
        )
        base = line * ADDRESS_STRIDE
        replies: list[Outgoing[W]] = []
        notes: list[str] = []
        with self._lock:
            self._apply_fault_events()  # a request may come before the first step after a fault's start
            for target_id, message in targets:
                address = base + target_id
                drive = self.drives.get(address)
                if drive is None:
                    notes.append(f"motor {target_id} is not on the bus")
                    continue
                lost, delay_s, corruption = self._link(address)
                if lost is not None:
                    notes.append(f"motor {target_id}: {lost}")
                    continue
                n = self._index[address]
                drive.observe(float(self._positions[n]), float(self._velocities[n]))
                reply = drive.respond(message, self.time_s, transport)
                if reply is None:  # (V3: 0x76, 0xB4, 0xB6 have no reply)
                    continue
                replies.append(Outgoing(address, encode(reply, target_id, corruption), reply, delay_s, corruption))
        return Exchange(None if motor_id is None else base + motor_id, request, tuple(replies), tuple(notes))

    def request(
        self, motor_id: int, message: Message, transport: WireProtocol = WireProtocol.CAN
    ) -> list[tuple[int, Message]]:
        """Send one request through the codec and return the decoded replies as ``(motor_id, message)``.

        A convenience for tests and scripts: no bus, no latency. A :class:`MultiMotorTorque` ignores ``motor_id``.

        Raises:
            EncodeError: the request cannot be encoded.
            DecodeError: a reply was corrupted by a fault.
        """
        line, wire_id = split_address(motor_id)
        generation = self.generations[line]
        replies: list[tuple[tuple[int | None, Message], Outgoing[CanFrame] | Outgoing[bytes]]]
        if transport is WireProtocol.CAN:
            sent = self.handle_can(generation.encode_can_request(message, wire_id), line)
            replies = [(generation.decode_can_reply(o.wire.arbitration_id, o.wire.data), o) for o in sent.replies]
        else:
            done = self.handle_rs485(generation.encode_rs485_request(message, wire_id), line)
            replies = [(generation.decode_rs485_reply(o.wire), o) for o in done.replies]
        # (the id the reply carries, a corrupted one too; V3's 0x79 replies name no drive: the sender's)
        return [(o.motor_id if d[0] is None else line * ADDRESS_STRIDE + d[0], d[1]) for d, o in replies]


def _pick(value: W | Mapping[int, W] | None, motor_id: int, default: Callable[[], W]) -> W:
    if value is None:
        return default()
    if isinstance(value, Mapping):
        if motor_id not in value:
            raise ConfigError("<Emulator>", f"[{motor_id}]", "no parameters for this motor id")
        return value[motor_id]
    return value


def _can_encoder(encode: Callable[[Message, int], CanFrame]) -> Callable[[Message, int, Corruption | None], CanFrame]:
    """A family's CAN reply encoder, with a ``corrupt`` fault's damage applied."""

    def encode_reply(reply: Message, motor_id: int, corruption: Corruption | None) -> CanFrame:
        frame = encode(reply, motor_id)
        return frame if corruption is None else corrupt_can(frame, corruption, motor_id)

    return encode_reply


def _rs485_encoder(
    encode: Callable[[Message, int], bytes], corrupt: Callable[[bytes, Corruption], bytes]
) -> Callable[[Message, int, Corruption | None], bytes]:
    """A family's RS485 reply encoder, with a ``corrupt`` fault's damage applied."""

    def encode_reply(reply: Message, motor_id: int, corruption: Corruption | None) -> bytes:
        raw = encode(reply, motor_id)
        return raw if corruption is None else corrupt(raw, corruption)

    return encode_reply


#: How a ``corrupt`` fault damages each family's RS485 frame.
_CORRUPT_RS485: Final[Mapping[ProtocolFamily, Callable[[bytes, Corruption], bytes]]] = {
    ProtocolFamily.V2: corrupt_rs485,
    ProtocolFamily.V3: corrupt_rs485_v3,
}


def _check_address(address: int) -> int:
    """``address`` if it names a drive: a motor id 1..32 on the first bus, ``bus × ADDRESS_STRIDE + id`` beyond."""
    check_motor_id(split_address(address)[1] if isinstance(address, int) and address > 0 else address)
    return address
