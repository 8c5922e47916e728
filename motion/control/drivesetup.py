"""The drive-side settings a control session needs, applied before its loop starts and restored when it ends.

What a family asks for (:mod:`motion.control.family`); for the older family there is nothing to set. For V3-driver
drives:

* **planning accelerations 0** (0x43, position acceleration and deceleration): the drive then tracks each 0xA4 target
  directly instead of running its own trapezoid on top of the planned stream; the values read before (0x42) are
  written back at the end. 0x43 writes RAM and ROM (the document offers no RAM-only write), so a session that dies
  without its end leaves 0 in ROM: ``rmd-motion`` sets them again at its next start, and any other tool sees tracking
  mode until it sets its own;
* **communication-loss protection** (0xB3): a few control periods, so that a drive stops by itself (output cut, brake
  locked) when the host dies or the cable drops; the document has no read of it, so the end writes 0 (off, the
  factory value);
* **holding brakes** (0x77 / 0x78) of the joints configured with one: released when the loop starts, locked when the
  arm has halted (:mod:`motion.safety.supervisor`) and at the end.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Collection, Sequence

from motion.control.family import DriveFamily
from motion.errors import ConfigError, TransportError
from motion.protocol.v3.messages import (
    AccelerationIndex,
    AccelerationRead,
    CommandV3,
    CommunicationTimeout,
    PlanningAcceleration,
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


class DriveSetup:
    """The settings of one session's drives (see the module docstring).

    Args:
        bus: the transport.
        family: the drives' family.
        ids: every joint's motor id.
        braked_ids: the ids of joints with a holding brake.
        link_timeout_ms: the communication-loss time to set, ms (0: leave the protection off).

    Raises:
        ConfigError: brakes or a link timeout on a family without them.
    """

    def __init__(
        self, bus: Transport, family: DriveFamily, ids: Sequence[int], braked_ids: Sequence[int], link_timeout_ms: int
    ) -> None:
        if braked_ids and not family.brakes:
            raise ConfigError(
                "<configuration>", "joints[].brake", f"the {family.family.value} drives have no brake commands"
            )
        self.bus = bus
        self.family = family
        self.ids = tuple(ids)
        self.braked_ids = tuple(braked_ids)
        self.link_timeout_ms = link_timeout_ms if family.link_protection else 0
        #: The planning accelerations read before they were set to 0, by (motor id, index).
        self.saved_accelerations: dict[tuple[int, int], int] = {}
        self.applied = False
        self.brakes_locked = True

    def apply(self, deadline_s: float) -> None:
        """Read and zero the planning accelerations, set the communication-loss time, release the brakes.

        Raises:
            TransportError: a drive did not answer a read or a write.
        """
        indexes = self.family.planning_accelerations
        if indexes:
            reads = [Request(i, AccelerationRead(index)) for i in self.ids for index in indexes]
            for reply in self._ask(reads, deadline_s, "planning acceleration read (0x42)"):
                message = reply.message
                assert isinstance(message, PlanningAcceleration)
                self.saved_accelerations[reply.motor_id, int(message.index)] = message.acceleration_dps2
            self.applied = True
            zero = [
                Request(i, PlanningAcceleration(CommandV3.WRITE_ACCELERATION, index, 0))
                for i in self.ids
                for index in indexes
            ]
            self._ask(zero, deadline_s, "planning acceleration write (0x43)")
        if self.link_timeout_ms:
            self.applied = True
            timeout = CommunicationTimeout(self.link_timeout_ms)
            self._ask([Request(i, timeout) for i in self.ids], deadline_s, "communication-loss time (0xB3)")
        self.release_brakes(deadline_s)

    def brake_requests(self, code: int) -> list[Request]:
        """0x77 (release) or 0x78 (lock) to every braked joint."""
        return [Request(i, self.family.bare(code)) for i in self.braked_ids]

    def release_brakes(self, deadline_s: float) -> None:
        """0x77 to every braked joint (before the loop commands them)."""
        if self.braked_ids:
            self._ask(self.brake_requests(CommandV3.RELEASE_BRAKE), deadline_s, "brake release (0x77)")
            self.brakes_locked = False

    def restore(self, deadline_s: float, *, lock: Collection[int] | None = None) -> None:
        """Lock the brakes, write back the planning accelerations, turn the protection off; best effort (a drive
        that does not answer is logged: the bus is closing). Once: a second call (the supervisor's close, then the
        bus's) sends nothing, and a later :meth:`apply` reads what this one wrote back.

        Args:
            deadline_s: when the drives' answers are due.
            lock: the braked joints whose brakes lock (those seen at rest after the halt); None: every one.
        """
        if not self.applied and self.brakes_locked:
            return
        requests = [r for r in self.brake_requests(CommandV3.LOCK_BRAKE) if lock is None or r.motor_id in lock]
        requests += [
            Request(motor_id, PlanningAcceleration(CommandV3.WRITE_ACCELERATION, AccelerationIndex(index), value))
            for (motor_id, index), value in self.saved_accelerations.items()
        ]
        if self.link_timeout_ms:
            requests += [Request(i, CommunicationTimeout(0)) for i in self.ids]
        if not requests:
            return
        try:
            self._ask(requests, deadline_s, "restore")
        except TransportError as exc:
            logger.error("the drives' settings were not all restored: %s", exc)
        finally:
            self.applied, self.brakes_locked = False, True
            self.saved_accelerations.clear()

    def _ask(self, requests: list[Request], deadline_s: float, what: str) -> list[Reply]:
        replies = self.bus.transact(requests, deadline_s)
        silent = sorted({r.motor_id for r in replies if r.message is None})
        if silent:
            raise TransportError(f"no reply to the {what} from motor(s) {', '.join(map(str, silent))}")
        return replies
