"""The drive-side settings a control session needs, applied before its loop starts.

What a family asks for (:mod:`motion.control.family`); for the older family there is nothing to set. For V3-driver
drives:

* **planning accelerations 0** (0x43, position acceleration and deceleration): the drive then tracks each 0xA4 target
  directly instead of running its own trapezoid on top of the planned stream. 0x43 writes RAM and ROM (the document
  offers no RAM-only write), so the session reads them (0x42) and writes only those that are not 0 yet;
* **communication-loss protection** (0xB3, ROM): a few control periods, so that a drive stops by itself (output cut,
  brake locked) when the host dies or the cable drops. The document has no read of it: the session writes it only
  when the host's record (:mod:`motion.control.drive_record`) does not show this value written to this drive since
  it was powered on (its runtime, 0xB1, tells: the record cannot tell a power-cycled drive from another one);
* **holding brakes** (0x77 / 0x78) of the joints configured with one: released when the loop starts, locked when the
  arm has halted (:mod:`motion.safety.supervisor`) and at the end.

The settings are left as they are when the session ends (a drive keeps tracking its stream directly, and stops when
its host goes silent): ``rmd-motion restore`` writes back what the drives held before rmd-motion first changed them
(:meth:`DriveSetup.restore_settings`). The ROM writes of a session are counted (:attr:`DriveSetup.rom_writes`, the
log) and added to the record's count per drive (``rmd-motion status``).
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable, Collection, Mapping, Sequence
from typing import Any, TypeAlias

from motion.control.drive_record import DriveRecord, same_power_on
from motion.control.family import DriveFamily
from motion.errors import ConfigError, DrivesSilent, TransportError
from motion.protocol.v3.messages import (
    AccelerationRead,
    BareV3,
    CommandV3,
    CommunicationTimeout,
    PlanningAcceleration,
    Runtime,
)
from motion.transport.base import Reply, Request, Transport

logger = logging.getLogger(__name__)

#: The communication-loss time in control periods when the configuration does not set it.
LINK_TIMEOUT_PERIODS = 5
#: ... and never below this, s (a drive's own timer has a millisecond step; a host's hiccup is a few ms).
LINK_TIMEOUT_MIN_S = 0.02


def link_timeout_ms(period_s: float, configured_s: float | None) -> int:
    """The 0xB3 time for a loop of ``period_s``: the configured one, else :data:`LINK_TIMEOUT_PERIODS` periods (at
    least :data:`LINK_TIMEOUT_MIN_S`), whole milliseconds rounded up (0: off)."""
    seconds = configured_s if configured_s is not None else max(LINK_TIMEOUT_PERIODS * period_s, LINK_TIMEOUT_MIN_S)
    return math.ceil(round(seconds * 1000.0, 6))


#: A ROM write and the record's changes it makes once a drive acknowledged it: (key, name, value; None removes).
_Write: TypeAlias = tuple[Request, list[tuple[str, str, Any]]]
#: The record's names of the settings (:mod:`motion.control.drive_record`).
LINK_TIMEOUT = "link_timeout"
MODEL = "model"
_ORIGINAL_ACCELERATION = "acceleration_before_{}"


class DriveSetup:
    """The settings of one session's drives (see the module docstring).

    Args:
        bus: the transport.
        family: the drives' family; a sequence: each one's (of ``ids``, an arm whose buses have drives of both).
        ids: every joint's motor id.
        braked_ids: the ids of joints with a holding brake.
        link_timeout_ms: the communication-loss time the drives need, ms (0: the protection off).
        record: the host's record of the drives' settings (default: one in memory).
        now: the clock the record's times are in, s (the host's wall clock for real drives, so that sessions in
            different processes compare; a simulation's clock for its drives).

    Raises:
        ConfigError: brakes or a link timeout on a family without them.
    """

    def __init__(
        self,
        bus: Transport,
        family: DriveFamily | Sequence[DriveFamily],
        ids: Sequence[int],
        braked_ids: Sequence[int],
        link_timeout_ms: int,
        *,
        record: DriveRecord | None = None,
        now: Callable[[], float] = time.time,
        labels: Mapping[int, str] | None = None,
    ) -> None:
        families = [family] * len(ids) if isinstance(family, DriveFamily) else list(family)
        #: Each drive's family, by motor id.
        self.families = dict(zip(ids, families, strict=True))
        unbraked = [i for i in braked_ids if not self.families[i].brakes]
        if unbraked:
            told = self.families[unbraked[0]].family.value
            raise ConfigError("<configuration>", "joints[].brake", f"the {told} drives have no brake commands")
        self.bus = bus
        self.ids = tuple(ids)
        self.braked_ids = tuple(braked_ids)
        # the drives with planning accelerations to zero, and those with the communication-loss protection
        self._planning = [i for i in self.ids if self.families[i].planning_accelerations]
        self._protected = [i for i in self.ids if self.families[i].link_protection]
        self.link_timeout_ms = link_timeout_ms if self._protected else 0
        self.record = record if record is not None else DriveRecord(None)
        self._now = now
        self._labels = dict(labels or {})
        #: ROM writes this session sent (0x43, 0xB3).
        self.rom_writes = 0
        self.brakes_locked = True

    def apply(self, deadline_s: float) -> None:
        """Zero the planning accelerations that are not 0, set the communication-loss time where the record does not
        show it set, release the brakes; record what was written.

        Raises:
            TransportError: a drive did not answer a read or a write.
        """
        self.recognise_drives()
        writes: list[_Write] = []
        if self._planning:
            writes += self._acceleration_writes(deadline_s)
        if self._protected:
            writes += self._link_timeout_writes(deadline_s)
        if writes:
            self._write_rom(writes, deadline_s, "session settings")
        if self.sets_drives:
            logger.info("drive settings: %d ROM write(s) this session (%s)", self.rom_writes, self.bus.describe())
        self.release_brakes(deadline_s)

    @property
    def sets_drives(self) -> bool:
        """Whether the session sets anything on its drives (planning accelerations, the communication-loss time)."""
        return bool(self._planning or self._protected)

    def _key(self, motor_id: int) -> str:
        return DriveRecord.key(self.bus.describe(), motor_id)

    def recognise_drives(self) -> None:
        """Keep each drive's model (0xB5, read at connect: ``bus.identities``) in its record; a drive whose model is
        not the one its record was made with is another drive at that id: its record starts anew (logged), so that
        nothing of the drive it replaced is written back to it (``restore``) or taken as set on it."""
        changed = False
        for motor_id in self.ids:
            identity = self.bus.identities.get(motor_id)
            model = identity.model if identity is not None else None
            if model is None:
                continue  # (the drive did not tell: its record stands as it is)
            key = self._key(motor_id)
            recorded = self.record.get(key, MODEL)
            if recorded == model:
                continue
            if recorded is not None:
                logger.warning(
                    "motor %d on %s is a %s, its record was made with a %s: the record starts anew for it",
                    motor_id,
                    self.bus.describe(),
                    model,
                    recorded,
                )
                self.record.forget(key)
            self.record.put(key, MODEL, model)
            changed = True
        if changed:
            self.record.save()

    def _acceleration_writes(self, deadline_s: float) -> list[_Write]:
        """0x43 of 0 for each planning acceleration that is not 0 (what it held first is recorded once written)."""
        reads = [
            Request(i, AccelerationRead(index))
            for i in self._planning
            for index in self.families[i].planning_accelerations
        ]
        writes = []
        for reply in self._ask(reads, deadline_s, "planning acceleration read (0x42)"):
            message = reply.message
            assert isinstance(message, PlanningAcceleration)
            if message.acceleration_dps2 == 0:
                continue
            key, name = self._key(reply.motor_id), _ORIGINAL_ACCELERATION.format(int(message.index))
            first = [(key, name, message.acceleration_dps2)] if self.record.get(key, name) is None else []
            request = Request(reply.motor_id, PlanningAcceleration(CommandV3.WRITE_ACCELERATION, message.index, 0))
            writes.append((request, first))
        return writes

    def _link_timeout_writes(
        self, deadline_s: float, needed_ms: int | None = None, *, silent: list[int] | None = None
    ) -> list[_Write]:
        """0xB3 to each drive the record does not show holding ``needed_ms`` (default the session's time) since its
        power-on. A drive that does not answer its runtime read raises, unless ``silent`` collects it (the others'
        writes are then still made).

        Raises:
            DrivesSilent: a drive did not answer (without ``silent``).
        """
        reads = [Request(i, BareV3(CommandV3.READ_RUNTIME)) for i in self._protected]
        now, writes = self._now(), []
        needed = self.link_timeout_ms if needed_ms is None else needed_ms
        if silent is None:
            replies = self._ask(reads, deadline_s, "runtime read (0xB1)")
        else:
            replies = self.bus.transact(reads, deadline_s)
            silent += sorted(r.motor_id for r in replies if r.message is None)
        for reply in replies:
            message = reply.message
            if message is None:
                continue
            assert isinstance(message, Runtime)
            key, runtime_s = self._key(reply.motor_id), message.runtime_ms / 1000.0
            if not _still_holds(self.record.get(key, LINK_TIMEOUT), needed, runtime_s, now):
                entry = {"ms": needed, "runtime_s": runtime_s, "at_s": now}
                writes.append((Request(reply.motor_id, CommunicationTimeout(needed)), [(key, LINK_TIMEOUT, entry)]))
        return writes

    def _write_rom(self, writes: list[_Write], deadline_s: float, what: str) -> None:
        """Send ROM writes; for each one a drive acknowledged, take its changes into the record and count it (the
        session's count and, in the record, the drive's); save the record.

        Raises:
            TransportError: a drive did not answer (what it did is not known: the record keeps what it had).
        """
        # by drive and message (a reply names the request message it answers)
        changes = {(request.motor_id, request.message): updates for request, updates in writes}
        replies = self.bus.transact([request for request, _ in writes], deadline_s)
        silent = set()
        for reply in replies:
            if reply.message is None:
                silent.add(reply.motor_id)
                continue
            for key, name, value in changes.get((reply.motor_id, reply.request), ()):
                self.record.put(key, name, value)
            self.rom_writes += 1
            self.record.count_rom_writes(self._key(reply.motor_id), 1)
        self.record.save()
        if silent:
            raise self._silent(what, sorted(silent))

    def suspend_protection(self, deadline_s: float) -> None:
        """The communication-loss protection off (0xB3 = 0) where the record does not show it off, before this session
        closes while another loop of the same program follows (homing, then the arm's): the bus is quiet between
        them, for longer than the protection's time. The next session sets it again.

        Raises:
            TransportError: a drive did not answer.
        """
        if self.link_timeout_ms:
            # (every drive that answers is suspended, also when another does not: a drive left out would stop in the
            # quiet time; the explorer found one drive's dropped reply leave four others protected, and tripping)
            # the reads wait for a silent drive until their deadline while the others' protection runs: half the
            # protection's time at most (the explorer found a 0.25 s wait for one silent drive trip four others)
            silent: list[int] = []
            now = self.bus.clock()
            read_by = min(now + (deadline_s - now) / 2, now + self.link_timeout_ms / 2000.0)
            writes = self._link_timeout_writes(read_by, 0, silent=silent)
            if writes:
                self._write_rom(writes, deadline_s, "communication-loss protection off (0xB3)")
            if silent:
                raise self._silent("runtime read (0xB1)", silent, ": their protection stays on")

    def restore_settings(self, deadline_s: float) -> list[str]:
        """Write back what the drives held before rmd-motion first changed them: the planning accelerations the
        record kept, the communication-loss protection off (its factory value); forget them in the record. Returns
        what was written, one line per drive.

        Raises:
            TransportError: a drive did not answer.
        """
        self.recognise_drives()
        writes: list[_Write] = []
        done = []
        for motor_id in self.ids:
            key, written = self._key(motor_id), []
            for index in self.families[motor_id].planning_accelerations:
                name = _ORIGINAL_ACCELERATION.format(int(index))
                value = self.record.get(key, name)
                if value is not None:
                    request = Request(motor_id, PlanningAcceleration(CommandV3.WRITE_ACCELERATION, index, int(value)))
                    writes.append((request, [(key, name, None)]))
                    written.append(f"{index.name.lower()} {value} deg/s²")
            if self.families[motor_id].link_protection:
                writes.append((Request(motor_id, CommunicationTimeout(0)), [(key, LINK_TIMEOUT, None)]))
                written.append("communication-loss protection off")
            if written:
                done.append(f"{self._labels.get(motor_id, f'motor {motor_id}')}: " + ", ".join(written))
        if writes:
            self._write_rom(writes, deadline_s, "restore")
        return done

    def brake_requests(self, code: int) -> list[Request]:
        """0x77 (release) or 0x78 (lock) to every braked joint."""
        return [Request(i, self.families[i].bare(code)) for i in self.braked_ids]

    def release_brakes(self, deadline_s: float) -> None:
        """0x77 to every braked joint (before the loop commands them)."""
        if self.braked_ids:
            self.brakes_locked = False  # (before: a drive that missed the reply may have released: the end locks all)
            self._ask(self.brake_requests(CommandV3.RELEASE_BRAKE), deadline_s, "brake release (0x77)")

    def restore(self, deadline_s: float, *, lock: Collection[int] | None = None) -> None:
        """The session's end: lock the brakes (the settings stay: module docstring); best effort (a drive that does
        not answer is logged: the bus is closing). Once: a second call (the supervisor's close, then the bus's) sends
        nothing.

        Args:
            deadline_s: when the drives' answers are due.
            lock: the braked joints whose brakes lock (those seen at rest after the halt); None: every one.
        """
        if self.brakes_locked:
            return
        requests = [r for r in self.brake_requests(CommandV3.LOCK_BRAKE) if lock is None or r.motor_id in lock]
        try:
            if requests:
                self._ask(requests, deadline_s, "brake lock (0x78)")
        except TransportError as exc:
            logger.error("the brakes were not all locked: %s", exc)
        finally:
            self.brakes_locked = True

    def _silent(self, what: str, silent: Sequence[int], more: str = "") -> DrivesSilent:
        """The error for drives (by address) that did not answer ``what``, each named as messages name it."""
        named = tuple(self._labels.get(i, f"motor {i}") for i in silent)
        return DrivesSilent(f"no reply to the {what} from {', '.join(named)}{more}", tuple(silent), named)

    def _ask(self, requests: list[Request], deadline_s: float, what: str) -> list[Reply]:
        replies = self.bus.transact(requests, deadline_s)
        silent = sorted({r.motor_id for r in replies if r.message is None})
        if silent:
            raise self._silent(what, silent)
        return replies


def _still_holds(written: object, needed_ms: int, runtime_s: float, now_s: float) -> bool:
    """Whether a drive whose runtime reads ``runtime_s`` still holds the time the record shows written: the same
    time, on a drive that has run since (:func:`~motion.control.drive_record.same_power_on`)."""
    if not isinstance(written, dict) or written.get("ms") != needed_ms:
        return False
    try:
        return same_power_on(float(written["runtime_s"]), float(written["at_s"]), runtime_s, now_s)
    except (KeyError, TypeError, ValueError):
        return False
