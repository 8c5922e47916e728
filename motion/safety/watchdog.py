"""Per-cycle fault monitors: every reply is watched, and the first violated limit becomes a :class:`MotionFault`.

Sources, in the order they are checked: drive error flags (0x9A, read round-robin so every drive's flags are at
most ``n_axes`` cycles old, and every 0x9B reply), motor temperature in every reply, supply voltage, missing replies
(consecutive misses and time since the last good reply), corrupt frames, measured position beyond the joint limits,
following error, and scheduler overrun streaks. The planned set-point is checked before it is sent.
"""

from __future__ import annotations

import collections
from dataclasses import dataclass

import numpy as np

from motion.config.schema import HaltPolicy
from motion.control.controller import Controller
from motion.errors import FaultKind, MotionFault
from motion.protocol import ErrorFlags, MotorState, Status1
from motion.trajectory import State
from motion.transmission import FloatArray
from motion.transport import Reply

# Measured positions may pass a joint limit by this much (encoder resolution, drive overshoot), deg.
POSITION_LIMIT_TOLERANCE_DEG = 0.1
# Window of the corrupt-frame count, s.
CORRUPT_WINDOW_S = 1.0
# Expected joint speed above which a joint counts as moving for the following-error check, deg/s.
_MOVING_DPS = 1.0


@dataclass(frozen=True, slots=True)
class SafetySettings:
    """Thresholds of the monitors and the reaction.

    Attributes:
        halt_policy: the reaction to a fault.
        temperature_limit_c: per joint, °C.
        min_voltage_v: supply voltage below which the arm faults, V.
        following_error_deg: largest |expected - measured| joint angle, deg (expected: where the joint should be
            now under its control loop, :mod:`motion.control.tracking`).
        reply_timeout_s: longest time without a good reply from a drive, s (on top of the missed-reply count).
        max_missed_replies: consecutive cycles with a missing reply tolerated per drive.
        max_corrupt_frames: corrupt frames per drive tolerated within one second.
        max_overrun_streak: consecutive overrunning cycles tolerated.
        halt_retry_s: how long unacknowledged halt frames are re-sent, s.
    """

    halt_policy: HaltPolicy
    temperature_limit_c: tuple[float, ...]
    min_voltage_v: float
    following_error_deg: float
    reply_timeout_s: float
    max_missed_replies: int
    max_corrupt_frames: int = 3
    max_overrun_streak: int = 3
    halt_retry_s: float = 0.2


class Watchdog:
    """Evaluates the monitors once per cycle (called from the control thread only)."""

    def __init__(self, controller: Controller, settings: SafetySettings) -> None:
        self.controller = controller
        self.settings = settings
        specs = controller.specs
        n = len(specs)
        self.names = tuple(s.name for s in specs)
        self.ids = tuple(s.motor_id for s in specs)
        self.index = {s.motor_id: i for i, s in enumerate(specs)}
        limits = controller.planner.limits
        self.lower = np.array(limits.position_min_deg) - POSITION_LIMIT_TOLERANCE_DEG
        self.upper = np.array(limits.position_max_deg) + POSITION_LIMIT_TOLERANCE_DEG
        self.temperature_limit = np.array(settings.temperature_limit_c)
        self.misses = np.zeros(n, dtype=np.int64)
        self.last_good_s = np.full(n, np.nan)
        self._missing = np.zeros(n, dtype=bool)
        self._answered = np.zeros(n, dtype=bool)
        self._bad_seen = np.zeros(n, dtype=np.int64)
        self._corrupt: list[collections.deque[float]] = [collections.deque() for _ in range(n)]
        self._overruns_seen = 0
        self._overrun_streak = 0
        self._counters = [controller.bus.motor_counters(motor_id) for motor_id in self.ids]
        # Following error: work arrays, and whether a cycle has run since start() (the first has no expectation).
        self._following = False
        self._error = np.zeros(n)
        self._slip = np.zeros(n)
        self._moving = np.zeros(n, dtype=bool)

    def start(self, now_s: float) -> None:
        """Reset the reply clocks (at loop start or after a clear)."""
        self.last_good_s[:] = now_s
        self.misses[:] = 0
        # The counter objects live as long as the transport: look them up once, not every cycle.
        self._counters = [self.controller.bus.motor_counters(motor_id) for motor_id in self.ids]
        for i, counter in enumerate(self._counters):
            self._bad_seen[i] = counter.bad_frames
            self._corrupt[i].clear()
        self._overruns_seen = self.controller.loop.overruns
        self._overrun_streak = 0
        self._following = False
        controller = self.controller
        controller.tracking.reset(controller.axes.q_deg, controller.axes.qd_dps, controller.reference.position)

    def check_setpoint(self, reference: State) -> None:
        """Refuse to send a planned set-point outside the joint limits.

        Raises:
            MotionFault: kind ``setpoint_limit``.
        """
        self._check_limits(reference.position, FaultKind.SETPOINT_LIMIT, "planned set-point outside the limits")

    def _check_limits(self, q: FloatArray, kind: FaultKind, detail: str) -> None:
        outside = (q < self.lower) | (q > self.upper)
        if outside.any():
            i = int(np.argmax(outside))
            bound = self.lower[i] if q[i] < self.lower[i] else self.upper[i]
            raise self._fault(kind, i, float(q[i]), float(bound), detail)

    def _fault(
        self, kind: FaultKind, i: int | None, value: float | None, threshold: float | None, detail: str
    ) -> MotionFault:
        return MotionFault(
            kind,
            joint=self.names[i] if i is not None else None,
            value=value,
            threshold=threshold,
            time_s=self.controller.clock.now(),
            detail=detail,
        )

    def evaluate(self, replies: list[Reply], now_s: float) -> None:
        """Check one cycle's replies and the controller's state.

        Raises:
            MotionFault: the first violated limit.
        """
        settings = self.settings
        self._missing[:] = False
        self._answered[:] = False
        index = self.index
        for reply in replies:  # first the reply bookkeeping, so that a drive fault never hides a lost drive
            i = index.get(reply.motor_id)
            if i is not None:
                if reply.message is None:
                    self._missing[i] = True
                else:
                    self._answered[i] = True
        self._check_replies(now_s)
        for reply in replies:
            i = index.get(reply.motor_id)
            message = reply.message
            if i is None or message is None:
                continue
            if isinstance(message, Status1):
                self._check_status(i, message)
            elif isinstance(message, MotorState) and message.temperature_c >= self.temperature_limit[i]:
                raise self._fault(
                    FaultKind.TEMPERATURE,
                    i,
                    message.temperature_c,
                    float(self.temperature_limit[i]),
                    "motor temperature",
                )
        self._check_corrupt(now_s)
        q = self.controller.axes.q_deg
        self._check_limits(q, FaultKind.POSITION_LIMIT, "measured position beyond the limit")
        if self._following:
            self._check_following(q)
        self._following = True
        overruns = self.controller.loop.overruns
        self._overrun_streak = self._overrun_streak + 1 if overruns > self._overruns_seen else 0
        self._overruns_seen = overruns
        if self._overrun_streak > settings.max_overrun_streak:
            raise self._fault(
                FaultKind.OVERRUN,
                None,
                float(self._overrun_streak),
                float(settings.max_overrun_streak),
                "consecutive overruns",
            )

    def _check_following(self, q: FloatArray) -> None:
        """|expected - measured| against the threshold; a joint slower than expected also loses the lag it was
        expected to have (a joint that stops while it should move is as far from the reference as it is), so that a
        blocked joint is caught as soon as the raw reference-minus-measured error would catch it."""
        tracking, qd = self.controller.tracking, self.controller.axes.qd_dps
        error, slip = self._error, self._slip
        expected_dps = tracking.expected_dps
        moving = self._moving
        np.abs(expected_dps, out=error)
        np.greater(error, _MOVING_DPS, out=moving)
        np.subtract(expected_dps, qd, out=slip)
        np.divide(slip, expected_dps, out=slip, where=moving)
        np.clip(slip, 0.0, 1.0, out=slip)
        slip *= moving
        slip *= tracking.lag_deg
        np.subtract(tracking.expected_deg, q, out=error)
        error += slip
        np.abs(error, out=error)
        worst = int(np.argmax(error))
        limit = self.settings.following_error_deg
        if error[worst] > limit:
            raise self._fault(
                FaultKind.FOLLOWING_ERROR, worst, float(error[worst]), limit, "|expected - q| (+ lag lost by slipping)"
            )

    def _check_status(self, i: int, status: Status1) -> None:
        if status.errors & ErrorFlags.OVER_TEMPERATURE:
            raise self._fault(FaultKind.DRIVE_OVER_TEMPERATURE, i, status.temperature_c, None, "drive error flag bit 3")
        if status.errors & ErrorFlags.LOW_VOLTAGE:
            raise self._fault(FaultKind.DRIVE_LOW_VOLTAGE, i, status.voltage_v, None, "drive error flag bit 0")
        if status.errors:
            raise self._fault(
                FaultKind.DRIVE_ERROR, i, float(status.errors), None, f"drive error flags {status.errors!r}"
            )
        if status.voltage_v < self.settings.min_voltage_v:
            raise self._fault(FaultKind.LOW_VOLTAGE, i, status.voltage_v, self.settings.min_voltage_v, "supply voltage")
        if status.temperature_c >= self.temperature_limit[i]:
            raise self._fault(
                FaultKind.TEMPERATURE, i, status.temperature_c, float(self.temperature_limit[i]), "motor temperature"
            )

    def _check_replies(self, now_s: float) -> None:
        settings = self.settings
        missed = self._missing
        self.misses[missed] += 1
        self.misses[~missed & self._answered] = 0
        self.last_good_s[self._answered & ~missed] = now_s
        worst = int(np.argmax(self.misses))
        if self.misses[worst] > settings.max_missed_replies:
            raise self._fault(
                FaultKind.NO_REPLY,
                worst,
                float(self.misses[worst]),
                float(settings.max_missed_replies),
                "consecutive misses",
            )
        silent = now_s - self.last_good_s
        worst = int(np.argmax(silent))
        if silent[worst] > settings.reply_timeout_s:
            raise self._fault(
                FaultKind.NO_REPLY,
                worst,
                float(silent[worst]),
                settings.reply_timeout_s,
                "seconds since the last good reply",
            )

    def _check_corrupt(self, now_s: float) -> None:
        for i, counter in enumerate(self._counters):
            if counter.bad_frames == self._bad_seen[i]:
                continue
            window = self._corrupt[i]
            window.extend([now_s] * (counter.bad_frames - int(self._bad_seen[i])))
            self._bad_seen[i] = counter.bad_frames
            while window and window[0] < now_s - CORRUPT_WINDOW_S:
                window.popleft()
            if len(window) > self.settings.max_corrupt_frames:
                raise self._fault(
                    FaultKind.CORRUPT_FRAMES,
                    i,
                    float(len(window)),
                    float(self.settings.max_corrupt_frames),
                    f"corrupt frames within {CORRUPT_WINDOW_S:g} s",
                )
