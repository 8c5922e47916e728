"""Which braked joints' drives cannot hold them: a monitor of its own, one cycle's replies in, a fault or nothing out.

After a halt a joint with a holding brake (``joints[].brake``, V3 drives) is held by its drive's own stop (0x81)
until it has come to rest, and only then braked (:mod:`motion.safety.halted`): a holding brake is no stopping device.
That rule needs a drive that holds. One that has cut its own output does not execute the 0x81 sent every cycle, and a
joint gravity loads never comes to rest under it: it falls (arm6_v3's shoulder from 25 to 341 deg in 5 s, its limits
±120, no 0x78 sent). :class:`BrakeWatch` tells those drives from a cycle's replies, and such a joint is braked at once
(0x78), whatever its speed, in the cycle its drive is found:

- its 0x9A shows its family's **over-temperature** or **under-voltage** flag: level-2 errors (V4.3 / V4.4, section 8),
  under which the drive's power stage is off; it recovers by itself once the cause is gone, the output staying off
  until the next control command (0x81 is none);
- its replies have been missing for more than ``safety.max_missed_replies`` cycles in a row, or for longer than
  ``safety.reply_timeout_ms`` (the watchdog's ``no_reply``): a **silent** drive, or a **lost link**. A drive that
  hears nothing cuts its output and locks its brake by itself once its communication-loss time passes (0xB3); one
  that hears us but whose replies are lost is not seen to hold. The 0x78 reaches it if anything does.

Under ``halt_policy: off`` every braked joint's output goes off by the policy: the halt brakes it at once too
(:class:`~motion.safety.halted.HaltGuard`; no finding of this monitor). A brake that locks at speed wears, and stops
the joint within its dynamic torque: that is the cost of a drive that cannot hold, never of one that can.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

from motion.control.family import STATUS_TYPES, DriveFamily
from motion.errors import FaultKind, MotionFault
from motion.safety.watchdog import Watchdog
from motion.transport import Reply


class BrakeWatch:
    """The braked joints whose drives cannot hold them (see the module docstring); control thread only.

    Args:
        names: every joint's name, in joint order.
        ids: every joint's address (motor id), in joint order.
        braked_ids: the addresses of the joints with a holding brake.
        families: every joint's drive family, in joint order (its flags' bits).
        max_missed_replies: consecutive cycles with a missing reply a drive is allowed (``safety.max_missed_replies``).
        reply_timeout_s: the longest a drive may go without a good reply, s (``safety.reply_timeout_ms``).
    """

    def __init__(
        self,
        names: Sequence[str],
        ids: Sequence[int],
        braked_ids: Sequence[int],
        families: Sequence[DriveFamily],
        *,
        max_missed_replies: int,
        reply_timeout_s: float,
    ) -> None:
        index = {motor_id: i for i, motor_id in enumerate(ids)}
        self.braked_ids = tuple(braked_ids)
        self._names = {motor_id: names[index[motor_id]] for motor_id in self.braked_ids}
        self._bits = {
            motor_id: (families[index[motor_id]].over_temperature, families[index[motor_id]].low_voltage)
            for motor_id in self.braked_ids
        }
        self._max_missed = max_missed_replies
        self._timeout_s = reply_timeout_s
        #: The braked joints found unable to hold since the last :meth:`reset`, by address: the finding.
        self.unheld: dict[int, MotionFault] = {}
        self._misses = dict.fromkeys(self.braked_ids, 0)
        self._last_good_s = dict.fromkeys(self.braked_ids, math.nan)
        self._missing: set[int] = set()
        self._answered: set[int] = set()
        self._now_s = math.nan
        self._found: list[MotionFault] = []

    def reset(self) -> None:
        """Every drive holds again (a clear: the drives' outputs come back with their next control command)."""
        self.unheld.clear()
        self._misses = dict.fromkeys(self.braked_ids, 0)
        self._last_good_s = dict.fromkeys(self.braked_ids, math.nan)

    def take(self, replies: Sequence[Reply], now_s: float) -> MotionFault | None:
        """One cycle's replies, taken in at ``now_s``: the fault of the braked joints newly found unable to hold (each
        added to :attr:`unheld`), or None."""
        if not self.braked_ids:
            return None
        self._now_s = now_s
        bits, missing, answered = self._bits, self._missing, self._answered
        found = self._found
        missing.clear()
        answered.clear()
        found.clear()
        for reply in replies:
            motor_id, message = reply.motor_id, reply.message
            if motor_id not in bits:
                continue
            if message is None:
                missing.add(motor_id)
                continue
            answered.add(motor_id)
            if motor_id in self.unheld or not isinstance(message, STATUS_TYPES):
                continue
            hot, low = bits[motor_id]
            errors = int(message.errors)
            if errors & hot:
                why = "its own over-temperature protection turned its output off"
                found.append(self._unheld(motor_id, FaultKind.DRIVE_OVER_TEMPERATURE, message.temperature_c, why))
            elif errors & low:
                why = "its own under-voltage protection turned its output off"
                found.append(self._unheld(motor_id, FaultKind.DRIVE_LOW_VOLTAGE, message.voltage_v, why))
        for motor_id in self.braked_ids:
            if motor_id not in missing:
                if motor_id in answered:
                    self._misses[motor_id] = 0
                    self._last_good_s[motor_id] = now_s
                continue  # (answered, or not asked in this exchange)
            self._misses[motor_id] += 1
            last = self._last_good_s[motor_id]
            if math.isnan(last):  # (the first cycle seen: the reply clock starts here, as the watchdog's does)
                self._last_good_s[motor_id] = last = now_s
            misses = self._misses[motor_id]
            if motor_id not in self.unheld and (misses > self._max_missed or now_s - last > self._timeout_s):
                why = f"no reply in {misses} cycles, {now_s - last:.3f} s: it is not seen to hold"
                found.append(self._unheld(motor_id, FaultKind.NO_REPLY, float(misses), why))
        if not found:
            return None
        first = found[0]
        joints = [f.joint for f in found if f.joint is not None]
        return MotionFault(
            first.kind, joint=first.joint, value=first.value, time_s=now_s, detail=first.detail, joints=joints
        )

    def _unheld(self, motor_id: int, kind: FaultKind, value: float, why: str) -> MotionFault:
        """Joint ``motor_id``'s drive cannot hold it (``why``): recorded in :attr:`unheld`, its fault returned."""
        fault = MotionFault(
            kind,
            joint=self._names[motor_id],
            value=value,
            time_s=self._now_s,
            detail=f"its drive cannot hold it ({why}): its brake is locked at once, whatever its speed",
        )
        self.unheld[motor_id] = fault
        return fault


def evaluate_cycle(
    watchdog: Watchdog, brakes: BrakeWatch, replies: list[Reply], now_s: float, *, complying: bool = False
) -> None:
    """A guarded cycle's monitors on its replies: the watchdog's fault, and the brake watch's finding, which a fault
    the hold is for does not hide (a stop ramp would leave the braked joint falling).

    Raises:
        MotionFault: the watchdog's fault, or the brake watch's where the watchdog found none or a holdable one.
    """
    unheld = brakes.take(replies, now_s)
    try:
        watchdog.evaluate(replies, now_s, complying=complying)
    except MotionFault as fault:
        if unheld is None or not fault.kind.holdable:
            raise
    if unheld is not None:
        raise unheld


__all__ = ["BrakeWatch", "evaluate_cycle"]
