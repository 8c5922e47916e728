"""The halted state as an invariant kept every cycle (HALTING and HALTED), not an event.

Once a halt went out, every cycle until ``clear()`` or close:

* **every drive gets a frame** — a state read (0x9C), after its halt while it is not known to be halted: the
  controller's own silence never trips a V3 drive's communication-loss protection (``safety.link_timeout_ms``);
* **the halt is re-sent to any drive not known to be halted**: one that never acknowledged it (it is re-sent every
  cycle for as long as the session is open, not only for ``halt_retry_s``), one that missed a reply (silent, dropped,
  corrupt: whatever it did meanwhile, it may have come back under its last command), one whose reading shows it
  driving (:meth:`HaltGuard.take`), and, in turn, one drive per cycle whatever it shows;
* **a joint beyond its limits** while halted is a fault of its own (recorded once per excursion), its halt re-sent;
* **a braked joint is stopped, not released**: under 0x80 it gets 0x81 until its brake locks (which turns its output
  off), so that it does not fall meanwhile;
* **a brake locks on a joint at rest where its drive holds**: after its drive acknowledged the halt, once every
  reading taken since for :data:`BRAKE_REST_S` showed at most :data:`BRAKE_REST_DPS`, and while no joint of the arm
  reads faster than :data:`SWING_DPS` (a joint swinging elsewhere jolts it through the arm): a holding brake is no
  stopping device;
* **a brake locks at once where its drive cannot hold**: a braked joint whose drive has cut its output (its own
  over-temperature or under-voltage protection, silent or out of reach: :class:`~motion.safety.brakes.BrakeWatch`)
  and, under ``halt_policy: off``, every braked joint get 0x78 in the halt's batch or the cycle the drive is found,
  first in it, and again every cycle until it is acknowledged, whatever the joint's speed (a joint gravity loads
  never comes to rest under a drive that does not hold it: it falls).

"Driving", from a state reply of a drive that acknowledged its halt: under 0x81 (the drive brakes to a standstill and
holds), once it has stood at rest for :data:`BRAKE_REST_S` (an overshoot of its own stop passes through zero speed:
no anchor there), its angle leaving :data:`STILL_BAND_DEG` around where it did; under 0x80 (the drive's output is
off), a torque current above :data:`OFF_CURRENT_A` (an unbraked joint under 0x80 may fall or coast: its motion is no
sign). A drive that keeps moving without ever coming to rest is caught by the halt re-asserted in turn (a running
drive stops) and, where it swings back and forth, by :data:`SWINGS_TO_RELEASE`.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Container, Iterable, Sequence
from typing import Final

from motion.control.axes import AxisStates
from motion.control.family import BARE_TYPES, STATE_TYPES
from motion.protocol import Command
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
#: A halted joint that swings this many times (faster than :data:`SWING_DPS`, each the other way than the one before)
#: without standing at rest for :data:`BRAKE_REST_S` in between: its drive's own hold oscillates (a position loop
#: tuned for another load, its speed uncapped), which 0x81 sent again does not change (:meth:`HaltGuard.take` reports
#: it once; the supervisor releases it with 0x80 where gravity cannot move it). A drive's own stop overshoots and
#: settles in a swing or two; three back-and-forth periods are no stop.
SWINGS_TO_RELEASE: Final = 6
#: A swing is counted beyond this speed, joint deg/s: ten steps of the coarsest speed field (V3: whole deg/s of the
#: output).
SWING_DPS: Final = 10.0
#: A halted joint that keeps moving faster than :data:`SWING_DPS` for this long without coming to rest is not held by
#: its drive's hold either (its hold point is elsewhere: a joint pushed past what its drive resists runs back to it at
#: the drive's top speed, turns away), s: a drive's own stop from full speed takes a few tenths of a second. (Not
#: slower motion: at 3 deg/s the explorer found drawn drives whose hold settles a loaded joint that slowly, released
#: without need.)
RESTLESS_S: Final = 1.0
#: A drive turned off with 0x80 that reads more torque current than this is driving again, A: some twenty steps of
#: the coarsest current field (0.01 A V3, 33/2048 A older drives); an off drive reads its noise, a few steps.
OFF_CURRENT_A: Final = 0.3


#: A joint that left its limits while halted counts as back inside once this far inside, joint deg: one resting on
#: its limit, its reading dithering by a count across it, is one excursion, not one per crossing.
LIMIT_REARM_DEG: Final = 0.5


class HaltGuard:
    """Per-drive bookkeeping of the halted state (see the module docstring); called from the control thread only.

    Args:
        ids: every joint's motor id, in joint order.
        braked_ids: the ids of joints with a holding brake.
        ask: the request without data for a command to a drive, in its family's protocol (motor id, command ->
            request: ``Controller.bare_request``).
        unheld: the braked joints whose drives cannot hold them, as it grows (the brake watch's
            :attr:`~motion.safety.brakes.BrakeWatch.unheld`): braked at once.
        clock: the time of the brake commands (:attr:`lock_sent_s`; None: the latest :meth:`take`'s).
    """

    def __init__(
        self,
        ids: Sequence[int],
        braked_ids: Sequence[int],
        ask: Callable[[int, int], Request],
        *,
        unheld: Container[int] = frozenset(),
        clock: Callable[[], float] | None = None,
    ) -> None:
        self.ids = tuple(ids)
        self.index = {motor_id: i for i, motor_id in enumerate(self.ids)}
        self.braked_ids = tuple(braked_ids)
        self._ask = ask
        #: The braked joints whose drives cannot hold them (their addresses; the brake watch's finding, kept live).
        self.unheld = unheld
        self._clock = clock
        #: When the first 0x78 went out to each braked joint since the arm was last cleared, by address, s (the
        #: clock's): for a joint braked at once (:meth:`braked_at_once`), the brake command it stops by.
        self.lock_sent_s: dict[int, float] = {}
        n = len(self.ids)
        #: The halt command in force (0x81, or 0x80 under ``halt_policy: off``).
        self.code = Command.MOTOR_STOP
        #: The halt each drive gets, by motor id: :attr:`code`, but 0x81 for a braked joint under 0x80 (its output
        #: goes off when its brake locks, at rest: a joint must not fall until then).
        self.codes = dict.fromkeys(self.ids, Command.MOTOR_STOP)
        #: Drives not known to be halted: their halt goes out every cycle until they acknowledge it.
        self.unacknowledged: set[int] = set()
        #: Drives that have not answered the halt since it went out, or since a reading of theirs showed them driving
        #: again: the ones the halt may not have reached. A subset of :attr:`unacknowledged`, which also holds drives
        #: that answered it and then missed a reply (a missed reply says nothing of what a drive runs; its halt is sent
        #: again all the same).
        self.unanswered: set[int] = set()
        #: Braked joints whose brake this session locked since the halt (released again by a clear).
        self.locked: set[int] = set()
        self._acknowledged = [False] * n
        self._rest_deg = [math.nan] * n
        self._rest_since = [math.nan] * n
        self._outside = [False] * n
        self._swings = [0] * n
        self._swing_sign = [0.0] * n
        self._moving_since = [math.nan] * n
        self._fast: set[int] = set()  # joints whose latest reading is faster than SWING_DPS
        self._turn = 0
        self._now = math.nan
        self._silent: set[int] = set()  # drives whose latest reply is missing
        self._reads = {motor_id: ask(motor_id, Command.READ_STATUS_2) for motor_id in self.ids}
        # (the halted cycle's requests, built once: the reads of every drive, each drive's halt as its code says,
        # each braked joint's lock)
        self._read_batch = [self._reads[motor_id] for motor_id in self.ids]
        self._halts = {motor_id: ask(motor_id, self.codes[motor_id]) for motor_id in self.ids}
        self._locks = {motor_id: ask(motor_id, CommandV3.LOCK_BRAKE) for motor_id in self.braked_ids}

    def begin(self, code: Command) -> None:
        """A halt with ``code`` goes out to every drive now: none is known to be halted."""
        self.code = code
        braked = self.braked_ids
        self.codes = {i: Command.MOTOR_STOP if i in braked else code for i in self.ids}
        self._halts = {i: self._ask(i, c) for i, c in self.codes.items()}
        self.unacknowledged = set(self.ids)
        self.unanswered = set(self.ids)
        for i in range(len(self.ids)):
            self._forget(i)
            self._swings[i], self._swing_sign[i] = 0, 0.0

    def reset(self) -> None:
        """The arm was cleared: nothing is halted, nothing is owed."""
        self.unacknowledged.clear()
        self.unanswered.clear()
        self.locked.clear()
        self.lock_sent_s.clear()
        self._silent.clear()
        for i in range(len(self.ids)):
            self._forget(i)
            self._moving_since[i] = math.nan
            self._outside[i] = False
            self._swings[i], self._swing_sign[i] = 0, 0.0

    def at_rest(self, i: int) -> bool:
        """Whether joint ``i`` has read at rest (at most :data:`BRAKE_REST_DPS`) in every reading for
        :data:`BRAKE_REST_S` since its drive acknowledged the halt (as a brake waits for)."""
        return self._acknowledged[i] and self._now - self._rest_since[i] >= BRAKE_REST_S

    def all_locked(self) -> bool:
        """Whether every braked joint's brake has locked since the halt."""
        return len(self.locked) == len(self.braked_ids)

    def braked_at_once(self) -> list[int]:
        """The braked joints (addresses) whose brake locks at once, whatever their speed: their drives cannot hold
        them (:attr:`unheld`), or the halt turns every output off (``halt_policy: off``)."""
        every = self.code == Command.MOTOR_OFF
        return [i for i in self.braked_ids if every or i in self.unheld]

    def locks_due(self) -> list[Request]:
        """0x78 to every joint braked at once whose lock has not been acknowledged (first in a batch), the time of
        each one's first recorded in :attr:`lock_sent_s`."""
        if not self._locks:
            return []
        due = [i for i in self.braked_at_once() if i not in self.locked]
        for i in due:
            self._sent_lock(i)
        return [self._locks[i] for i in due]

    def _sent_lock(self, motor_id: int) -> None:
        if motor_id not in self.lock_sent_s:
            self.lock_sent_s[motor_id] = self._clock() if self._clock is not None else self._now

    def halt_requests(self) -> list[Request]:
        """The locks due at once (:meth:`locks_due`), then the halt to every drive not known to be halted, in id
        order."""
        halts, silent = self._halts, self._silent
        batch = self.locks_due()
        batch += [halts[motor_id] for motor_id in sorted(self.unacknowledged, key=lambda i: (i in silent, i))]
        return batch

    def requests(self) -> list[Request]:
        """The halted cycle's batch: the halt to every drive not known to be halted and, in turn, to one drive
        whatever it shows; a state read to every drive (its readings never have gaps that its encoder's turns could
        slip through while it moves); then 0x78 to the braked joints found at rest. The locks due at once go first
        (:meth:`locks_due`)."""
        ids, owed, halts, silent = self.ids, self.unacknowledged, self._halts, self._silent
        self._turn = (self._turn + 1) % len(ids)
        reassert = ids[self._turn]
        if silent:  # the drives that missed their last reply last: on RS485 their timeouts delay nobody's frames
            ids = tuple(sorted(ids, key=lambda i: i in silent))
        batch = self.locks_due()
        batch += [halts[i] for i in ids if i in owed or i == reassert] if owed else [halts[reassert]]
        batch += [self._reads[i] for i in ids] if silent else self._read_batch
        if self._locks and not self._fast and len(self.locked) < len(self._locks):
            due = self._brakes_due()
            if due is not None:
                self._sent_lock(due)
                batch.append(self._locks[due])
        return batch

    def _brakes_due(self) -> int | None:
        """The braked joint whose brake may lock now, if any: one per cycle (a brake that locks jolts the arm; the
        next one waits for readings at rest after that), and only while the whole arm is calm (a joint swinging
        elsewhere jolts this one through the arm: the caller checks that)."""
        index, now, rest_since = self.index, self._now, self._rest_since
        every = self.code == Command.MOTOR_OFF  # (then each is braked at once)
        for motor_id in self.braked_ids:
            if (
                not every
                and motor_id not in self.unheld
                and motor_id not in self.locked
                and motor_id not in self.unacknowledged
                and now - rest_since[index[motor_id]] >= BRAKE_REST_S
            ):
                return motor_id
        return None

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
            their limits; the joints its drive's hold does not hold (swinging: :data:`SWINGS_TO_RELEASE`, or restless:
            :data:`RESTLESS_S`), each reported once per halt.
        """
        index, codes = self.index, self.codes
        q_deg, qd_dps, iq_a = axes.q_deg, axes.qd_dps, axes.iq_a
        self._now = now_s
        driving: list[int] = []
        outside: list[int] = []
        swinging: list[int] = []
        answered: set[int] = set()
        unanswered: set[int] = set()
        for reply in replies:
            i = index.get(reply.motor_id)
            if i is None:
                continue
            message = reply.message
            motor_id = reply.motor_id
            if message is None:  # silent, dropped or corrupt: whatever it did meanwhile, halt it again
                self._owe(i)
                self._moving_since[i] = math.nan  # (restless counts motion seen: none was, meanwhile)
                unanswered.add(motor_id)
                continue
            answered.add(motor_id)
            if isinstance(message, BARE_TYPES):
                self._take_bare(i, motor_id, message.command)
            elif isinstance(message, STATE_TYPES):
                q, qd = float(q_deg[i]), float(qd_dps[i])
                self._take_angle(i, q, qd, within, outside)
                if not self._acknowledged[i]:
                    continue
                if codes[motor_id] == Command.MOTOR_STOP and (self._swung(i, qd) or self._restless(i, qd)):
                    swinging.append(i)
                if self._driving(i, q, qd, float(iq_a[i])):
                    driving.append(i)
                    self._owe(i)
                    self.unanswered.add(motor_id)  # its own reading casts doubt on the halt it answered
        if unanswered or self._silent:  # silent: not one of its replies came (one that answered some is alive)
            self._silent -= answered
            self._silent |= unanswered - answered
        return driving, outside, swinging

    def _take_bare(self, i: int, motor_id: int, command: int) -> None:
        """A reply without data from joint ``i``'s drive: its halt acknowledged, or its brake locked."""
        if command == self.codes[motor_id]:
            if not self._acknowledged[i]:
                self._acknowledged[i] = True
            self.unacknowledged.discard(motor_id)
            self.unanswered.discard(motor_id)
        elif command == CommandV3.LOCK_BRAKE:
            self.locked.add(motor_id)
            self._set_code(motor_id, self.code)  # (under 0x80: its output off now, as the policy says)
            self._rest_since = [math.nan] * len(self.ids)  # the lock jolted the arm: at rest again first

    def _take_angle(
        self, i: int, q: float, qd: float, within: Callable[[int, float], bool], outside: list[int]
    ) -> None:
        """Joint ``i`` read at ``q`` moving at ``qd``: whether it moves fast, and whether it has just left its limits
        (appended to ``outside``, its halt owed again) or come back inside clear of them."""
        if abs(qd) > SWING_DPS:
            self._fast.add(i)
        else:
            self._fast.discard(i)
        if not within(i, q):
            if not self._outside[i]:
                outside.append(i)
                self._owe(i)
                self._outside[i] = True
        elif self._outside[i] and within(i, q - LIMIT_REARM_DEG) and within(i, q + LIMIT_REARM_DEG):
            self._outside[i] = False  # back inside, clear of the limit: a next excursion is one again

    def release(self, i: int) -> None:
        """Joint ``i``'s drive gets 0x80 from now on (until the next halt): its own hold does not hold it."""
        self._set_code(self.ids[i], Command.MOTOR_OFF)
        self._owe(i)

    def _others_unsettled(self) -> bool:
        """Whether a joint other than the one being read may be moving fast: one read faster than :data:`SWING_DPS`
        besides it, or one whose drive did not answer (its joint unseen: a silent drive in torque mode keeps its last
        torque command)."""
        return len(self._fast) > 1 or bool(self._silent)

    def _set_code(self, motor_id: int, code: Command) -> None:
        """The drive's halt from now on is ``code``."""
        self.codes[motor_id] = code
        self._halts[motor_id] = self._ask(motor_id, code)

    def _restless(self, i: int, qd: float) -> bool:
        """Whether joint ``i`` has just moved faster than :data:`SWING_DPS` for :data:`RESTLESS_S` (once a run), by
        itself: not reported while another joint moves that fast too (one falling, its drive off or unreachable: a
        joint its hold resists with is dragged through the arm, and released it would only coast further)."""
        if abs(qd) <= SWING_DPS:
            self._moving_since[i] = math.nan
            return False
        if math.isnan(self._moving_since[i]):
            self._moving_since[i] = self._now
            return False
        # (another joint fast now: not reported at this reading, but its time still counts: a joint whose hold runs
        # it back at top speed jolts the others through the arm itself, now and then, all the way; the explorer found
        # one whose count restarted at each jolt and was never released)
        if self._now - self._moving_since[i] < RESTLESS_S or self._others_unsettled():
            return False
        self._moving_since[i] = math.inf  # reported: not again until it slows down
        return True

    def _swung(self, i: int, qd: float) -> bool:
        """Count the swings of joint ``i`` (its speed beyond :data:`SWING_DPS`, the other way than the last one) since
        it last stood at rest for :data:`BRAKE_REST_S`: True when they reach :data:`SWINGS_TO_RELEASE`. Swings while
        another joint moves that fast too are not its own (see :meth:`_restless`): they are not counted."""
        if abs(qd) <= SWING_DPS or self._others_unsettled():
            return False
        sign = math.copysign(1.0, qd)
        if sign == self._swing_sign[i]:
            return False
        self._swings[i] += 1
        self._swing_sign[i] = sign
        return self._swings[i] == SWINGS_TO_RELEASE

    def _driving(self, i: int, q: float, qd: float, iq: float) -> bool:
        """Whether a drive that acknowledged its halt reads as driving again (see the module docstring); keeps the
        rest bookkeeping."""
        now = self._now
        if abs(qd) <= BRAKE_REST_DPS:
            if math.isnan(self._rest_since[i]):
                self._rest_since[i] = now
            elif now - self._rest_since[i] >= BRAKE_REST_S:
                self._swings[i], self._swing_sign[i] = 0, 0.0  # at rest a while: no oscillation
                if math.isnan(self._rest_deg[i]):
                    self._rest_deg[i] = q  # where the halt left it
        else:
            self._rest_since[i] = math.nan
        if self.codes[self.ids[i]] == Command.MOTOR_OFF:
            return abs(iq) > OFF_CURRENT_A
        rest = self._rest_deg[i]
        return not math.isnan(rest) and abs(q - rest) > STILL_BAND_DEG

    def _owe(self, i: int) -> None:
        """Drive ``i`` is not known to be halted: its halt goes out again until it acknowledges."""
        self.unacknowledged.add(self.ids[i])
        self._forget(i)

    def _forget(self, i: int) -> None:
        # (not when joint i began moving fast: a halt sent again does not move a hold point, and a joint its hold runs
        # back turns away at top speed is restless however often its halt is owed meanwhile: leaving its limits on
        # the way, an E-stop; the explorer found one whose timer was restarted by each until its run ended)
        self._acknowledged[i] = False
        self._rest_deg[i] = math.nan
        self._rest_since[i] = math.nan
