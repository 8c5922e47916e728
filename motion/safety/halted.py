"""The halted state as an invariant kept every cycle (HALTING and HALTED), not an event.

Once a halt went out, every cycle until ``clear()`` or close:

* **every drive gets a frame** — its halt while it has not acknowledged it, else a state read (0x9C): the
  controller's own silence never trips a V3 drive's communication-loss protection (``safety.link_timeout_ms``);
* **the halt is re-sent to any drive not known to be halted**: one that never acknowledged it (it is re-sent every
  cycle for as long as the session is open, not only for ``halt_retry_s``), one that missed a reply (silent, dropped,
  corrupt: whatever it did meanwhile, it may have come back under its last command), one whose reading shows it
  driving (:meth:`HaltGuard.take`), and, in turn, one drive per cycle whatever it shows (a halt re-asserted costs a
  frame the read would have cost);
* **a joint beyond its limits** while halted is a fault of its own (recorded once per excursion), its halt re-sent;
* **a braked joint is stopped, not released**: under 0x80 it gets 0x81 until its brake locks (which turns its output
  off), so that it does not fall meanwhile;
* **a brake locks only on a joint at rest**: after its drive acknowledged the halt, once every reading taken since
  for :data:`BRAKE_REST_S` showed at most :data:`BRAKE_REST_DPS`.

"Driving", from a state reply of a drive that acknowledged its halt: under 0x81 (the drive brakes to a standstill and
holds), its speed rising :data:`SPEED_UP_DPS` above the slowest it read since the acknowledgement, or, once it came to
rest, its angle leaving :data:`STILL_BAND_DEG` around where it did; under 0x80 (the drive's output is off), a torque
current above :data:`OFF_CURRENT_A` (an unbraked joint under 0x80 may fall or coast: its motion is no sign).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Sequence
from typing import Final

from motion.control.axes import AxisStates
from motion.control.family import BARE_TYPES, STATE_TYPES
from motion.protocol import Command, Message
from motion.protocol.v3.messages import CommandV3
from motion.transport import Reply, Request

#: A braked joint at rest after a halt (its brake then locks), joint deg/s: the speed fields' step is 1 deg/s of
#: the motor (older drives) or of the output shaft (V3), so one step of the output's reading.
BRAKE_REST_DPS: Final = 1.0
#: How long a joint reads at rest, in every reading taken since its drive acknowledged the halt, before its brake
#: locks, s: a reading or two can catch a joint that swings through zero speed as its drive's hold settles (seen at
#: 8 deg/s a few ms after two readings at rest); several periods of the swing of a holding loop.
BRAKE_REST_S: Final = 0.05
#: A joint halted with 0x81 that came to rest and then moves this far is driven again, joint deg. Far above what a
#: drive's holding loop lets a loaded joint sag and what the angle fields resolve (0.01 deg of the motor or output).
STILL_BAND_DEG: Final = 2.0
#: A joint halted with 0x81 whose speed rises this far above the slowest it read since the acknowledgement is driven
#: again, joint deg/s: ten steps of the coarsest speed field (V3: whole deg/s of the output).
SPEED_UP_DPS: Final = 10.0
#: A joint halted with 0x81 found driving this many times in a row, each time the other way (its drive's own hold
#: oscillates: a position loop tuned for another load), is released with 0x80 instead: re-sending 0x81 to a stopped
#: drive changes nothing, and an oscillation at the current limit only grows. One way each time is a push (a person,
#: an obstacle): the drive's hold is what resists it, and it keeps 0x81.
SWINGS_TO_RELEASE: Final = 3
#: A drive turned off with 0x80 that reads more torque current than this is driving again, A: some twenty steps of
#: the coarsest current field (0.01 A V3, 33/2048 A older drives); an off drive reads its noise, a few steps.
OFF_CURRENT_A: Final = 0.3


class HaltGuard:
    """Per-drive bookkeeping of the halted state (see the module docstring); called from the control thread only.

    Args:
        ids: every joint's motor id, in joint order.
        braked_ids: the ids of joints with a holding brake.
        bare: the family's request without data for a command (``DriveFamily.bare``).
    """

    def __init__(self, ids: Sequence[int], braked_ids: Sequence[int], bare: Callable[[int], Message]) -> None:
        self.ids = tuple(ids)
        self.index = {motor_id: i for i, motor_id in enumerate(self.ids)}
        self.braked_ids = tuple(braked_ids)
        self._bare = bare
        n = len(self.ids)
        #: The halt command in force (0x81, or 0x80 under ``halt_policy: off``).
        self.code = Command.MOTOR_STOP
        #: The halt each drive gets, by motor id: :attr:`code`, but 0x81 for a braked joint under 0x80 (its output
        #: goes off when its brake locks, at rest: a joint must not fall until then).
        self.codes = dict.fromkeys(self.ids, Command.MOTOR_STOP)
        #: Drives not known to be halted: their halt goes out every cycle until they acknowledge it.
        self.unacknowledged: set[int] = set()
        #: Braked joints whose brake this session locked since the halt (released again by a clear).
        self.locked: set[int] = set()
        self._acknowledged = [False] * n
        self._slowest_dps = [math.inf] * n
        self._rest_deg = [math.nan] * n
        self._rest_since = [math.nan] * n
        self._outside = [False] * n
        self._swings = [0] * n
        self._swing_sign = [0.0] * n
        self._turn = 0
        self._now = math.nan
        self._reads = {motor_id: Request(motor_id, bare(Command.READ_STATUS_2)) for motor_id in self.ids}

    def begin(self, code: Command) -> None:
        """A halt with ``code`` goes out to every drive now: none is known to be halted."""
        self.code = code
        braked = self.braked_ids
        self.codes = {i: Command.MOTOR_STOP if i in braked else code for i in self.ids}
        self.unacknowledged = set(self.ids)
        for i in range(len(self.ids)):
            self._forget(i)
            self._swings[i], self._swing_sign[i] = 0, 0.0

    def reset(self) -> None:
        """The arm was cleared: nothing is halted, nothing is owed."""
        self.unacknowledged.clear()
        self.locked.clear()
        for i in range(len(self.ids)):
            self._forget(i)
            self._outside[i] = False
            self._swings[i], self._swing_sign[i] = 0, 0.0

    def halt_requests(self) -> list[Request]:
        """The halt to every drive not known to be halted, in id order."""
        bare, codes = self._bare, self.codes
        return [Request(motor_id, bare(codes[motor_id])) for motor_id in sorted(self.unacknowledged)]

    def requests(self) -> list[Request]:
        """The halted cycle's batch: one frame per drive (its halt, or a state read; the halt re-asserted to one drive
        in turn), then 0x78 to the braked joints found at rest."""
        ids = self.ids
        self._turn = (self._turn + 1) % len(ids)
        reassert = ids[self._turn]
        bare, codes = self._bare, self.codes
        batch = [
            Request(motor_id, bare(codes[motor_id]))
            if motor_id in self.unacknowledged or motor_id == reassert
            else self._reads[motor_id]
            for motor_id in ids
        ]
        if self.braked_ids:
            lock = self._bare(CommandV3.LOCK_BRAKE)
            batch += [Request(motor_id, lock) for motor_id in self._brakes_due()]
        return batch

    def _brakes_due(self) -> list[int]:
        index = self.index
        return [
            motor_id
            for motor_id in self.braked_ids
            if motor_id not in self.locked
            and motor_id not in self.unacknowledged
            and self._now - self._rest_since[index[motor_id]] >= BRAKE_REST_S
        ]

    def take(
        self,
        replies: Iterable[Reply],
        axes: AxisStates,
        within: Callable[[int, float], bool],
        now_s: float,
    ) -> tuple[list[int], list[int], list[int]]:
        """Take in a halted cycle's replies (the axes already absorbed them).

        Args:
            replies: the cycle's replies.
            axes: the measured joint states (angles, speeds, torque currents).
            within: ``(i, q_deg) -> bool``: joint ``i`` is inside its limits at ``q_deg``.
            now_s: when the replies were taken in.

        Returns:
            The joints (indexes) found driving, whose halt goes out again next cycle; the joints that have just left
            their limits; the joints whose hold oscillates, released with 0x80 from now on
            (:data:`SWINGS_TO_RELEASE`).
        """
        index, codes = self.index, self.codes
        q_deg, qd_dps, iq_a = axes.q_deg, axes.qd_dps, axes.iq_a
        self._now = now_s
        driving: list[int] = []
        outside: list[int] = []
        released: list[int] = []
        for reply in replies:
            i = index.get(reply.motor_id)
            if i is None:
                continue
            message = reply.message
            motor_id = reply.motor_id
            if message is None:  # silent, dropped or corrupt: whatever it did meanwhile, halt it again
                self._owe(i)
            elif isinstance(message, BARE_TYPES):
                if message.command == codes[motor_id]:
                    if not self._acknowledged[i]:
                        self._acknowledged[i] = True
                    self.unacknowledged.discard(motor_id)
                elif message.command == CommandV3.LOCK_BRAKE:
                    self.locked.add(motor_id)
            elif isinstance(message, STATE_TYPES):
                q, qd = float(q_deg[i]), float(qd_dps[i])
                out = not within(i, q)
                if out and not self._outside[i]:
                    outside.append(i)
                    self._owe(i)
                self._outside[i] = out
                if self._acknowledged[i] and self._driving(i, q, qd, float(iq_a[i])):
                    driving.append(i)
                    self._owe(i)
                    if self._swung(i, qd) and codes[motor_id] == Command.MOTOR_STOP:
                        codes[motor_id] = Command.MOTOR_OFF
                        released.append(i)
        return driving, outside, released

    def _swung(self, i: int, qd: float) -> bool:
        """Count a driving reading of joint ``i`` moving at ``qd``: True once it has been found driving one way, then
        the other, :data:`SWINGS_TO_RELEASE` times without coming to rest in between."""
        sign = math.copysign(1.0, qd)
        if sign != self._swing_sign[i]:
            self._swings[i] += 1
            self._swing_sign[i] = sign
        return self._swings[i] >= SWINGS_TO_RELEASE

    def _driving(self, i: int, q: float, qd: float, iq: float) -> bool:
        """Whether a drive that acknowledged its halt reads as driving again (see the module docstring); keeps the
        rest bookkeeping."""
        speed = abs(qd)
        if speed <= BRAKE_REST_DPS:
            if math.isnan(self._rest_since[i]):
                self._rest_since[i] = self._now
            elif self._now - self._rest_since[i] >= BRAKE_REST_S:
                self._swings[i], self._swing_sign[i] = 0, 0.0  # at rest a while: no oscillation
            if math.isnan(self._rest_deg[i]):
                self._rest_deg[i] = q
        else:
            self._rest_since[i] = math.nan
        if self.codes[self.ids[i]] == Command.MOTOR_OFF:
            return abs(iq) > OFF_CURRENT_A
        if speed > self._slowest_dps[i] + SPEED_UP_DPS:
            return True
        self._slowest_dps[i] = min(self._slowest_dps[i], speed)
        rest = self._rest_deg[i]
        return not math.isnan(rest) and abs(q - rest) > STILL_BAND_DEG

    def _owe(self, i: int) -> None:
        """Drive ``i`` is not known to be halted: its halt goes out again until it acknowledges."""
        self.unacknowledged.add(self.ids[i])
        self._forget(i)

    def _forget(self, i: int) -> None:
        self._acknowledged[i] = False
        self._slowest_dps[i] = math.inf
        self._rest_deg[i] = math.nan
        self._rest_since[i] = math.nan
