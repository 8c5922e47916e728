"""Per-cycle fault monitors: every reply is watched, and the first violated limit becomes a :class:`MotionFault`.

Sources, in the order they are checked: drive error flags (0x9A, read round-robin with 0x92, on CAN enough per cycle
that every drive's flags are at most ``motion.control.ratecheck.FLAG_AGE_S`` old, on RS485 one per cycle: ``2 n_axes``
cycles; and every 0x9B reply), a drive that restarted (:class:`~motion.safety.restart.RestartCheck`: its documented
sign in the 0x92 and 0xB1 replies), motor temperature in every reply, supply voltage, missing
replies (consecutive misses and time since the last good reply), corrupt frames, measured position beyond the joint
limits, measured speed beyond the joint's velocity limit × its margin (:mod:`motion.safety.overspeed`), collisions
(the momentum observer's residual per joint against its threshold), following error, and scheduler overrun streaks.
The planned set-point is checked before it is sent.

The collision check (the injected momentum observer, its signal and the threshold in force) is
:mod:`motion.safety.collision`; the watchdog runs it in every evaluated cycle and gives its figures out under its own
names (``collision_signal_nm``, ``collision_limit_nm`` ...).
"""

from __future__ import annotations

import collections
import math
from dataclasses import dataclass

import numpy as np

from motion.config.schema import HaltPolicy
from motion.control.controller import Controller
from motion.control.family import STATE_TYPES, STATUS_TYPES
from motion.errors import FaultKind, MotionFault
from motion.protocol import MultiTurnAngle, Status1
from motion.protocol.v3.messages import Runtime, Status1V3
from motion.safety.collision import CollisionCheck, CollisionObserver
from motion.safety.collision_bound import MODEL_ERROR
from motion.safety.overspeed import OverspeedCheck
from motion.safety.restart import RestartCheck
from motion.trajectory import State
from motion.transmission import FloatArray
from motion.transport import Reply

__all__ = ["CollisionObserver", "SafetySettings", "Watchdog"]  # (the observer's type: where it was declared before)

# Measured positions may pass a joint limit by this much (encoder resolution, drive overshoot), deg.
POSITION_LIMIT_TOLERANCE_DEG = 0.1
_DEG_PER_RAD = 180.0 / math.pi
# Window of the corrupt-frame count, s.
CORRUPT_WINDOW_S = 1.0
#: The share of the tracking model's lag (behind the reference) that a drive within the stated bounds may add to the
#: following error, by whether the drives close the position loop (the mode's ``drive_position_loop``) and whether
#: their loop settings are read (0x30, 0x33): the host's loop (torque mode), the torque constant (±20 %) and rotor
#: inertia (±30 %) of the controller's own loop (and, through the PD's stiffness, the torque constant's share of the
#: torque asked for and the friction's of the Coulomb figure: :data:`motion.safety.collision_bound.MODEL_ERROR`); the
#: drive's loop with the settings read, none (the model runs the drive's own loop); without them (V3 drives), a
#: tuning from half to twice the model's prior: up to twice its lag.
FOLLOWING_LAG_ERROR: dict[tuple[bool, bool], float] = {
    (False, True): 0.5,
    (False, False): 0.5,
    (True, True): 0.0,
    (True, False): 1.0,
}
# Expected joint speed above which a joint counts as moving for the following-error check, deg/s.
_MOVING_DPS = 1.0
#: A joint's speed may trail the model's (and the reference's) by this many cycles of their change without slipping:
#: the phase of the exchange's sample and of the drive's loops against the model's (a blocked joint falls short by
#: its whole speed, far beyond that).
SLIP_PHASE_CYCLES = 2.0


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
        halt_retry_s: how long the arm stays HALTING for drives that have not acknowledged the halt, s (their halt
            is re-sent after that too, while the session is open).
        collision_threshold_nm: per joint, the observer residual that faults the arm (``collision``), N·m; inf for
            a joint that is not watched; empty: no joint is.
        collision_reaction: the reaction to a collision (None: ``halt_policy``; ``hold`` reacts with 0x81, a
            collision is not holdable; ``comply``: gravity compensation, torque mode).
        collision_window_s: the collision signal is the residual's change over this long, s (0: the residual).
        coulomb_friction_nm: per joint, its Coulomb friction, N·m: a halted joint whose drive's hold swings it is
            released (0x80) only where gravity loads it less (empty: never released).
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
    collision_threshold_nm: tuple[float, ...] = ()
    collision_reaction: HaltPolicy | None = None
    collision_window_s: float = 0.0
    coulomb_friction_nm: tuple[float, ...] = ()


class Watchdog:
    """Evaluates the monitors once per cycle (called from the control thread only)."""

    def __init__(
        self, controller: Controller, settings: SafetySettings, observer: CollisionObserver | None = None
    ) -> None:
        self.controller = controller
        self.settings = settings
        #: The collision observer (None: none runs, no residual is recorded).
        self.observer = observer
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
        self._good = np.zeros(n, dtype=bool)  # answered this cycle with nothing missing
        self._silent = np.zeros(n)  # time since the last good reply, s
        self._bad_seen = np.zeros(n, dtype=np.int64)
        self._corrupt: list[collections.deque[float]] = [collections.deque() for _ in range(n)]
        self._overruns_seen = 0
        self._overrun_streak = 0
        #: The restart check (:mod:`motion.safety.restart`), on every 0x92 and 0xB1 reply.
        self.restart = RestartCheck(controller)
        self._counters = [controller.bus.motor_counters(motor_id) for motor_id in self.ids]
        # Following error: work arrays, and whether a cycle has run since start() (the first has no expectation).
        self._following = False
        #: The following-error fault of the latest evaluation (None: none; evaluated also when another fault came
        #: first).
        self.following: MotionFault | None = None
        self._error = np.zeros(n)
        self._slip = np.zeros(n)
        self._following_limit = np.zeros(n)
        drive_loop = controller.options.mode.traits.drive_position_loop
        self._lag_error = np.array(
            [FOLLOWING_LAG_ERROR[drive_loop, f.reads_loop_settings] for f in controller.families]
        )
        # torque mode: what a drive within the stated model error adds (see _advance_sensitivity)
        self._torque_mode = controller.options.mode.traits.host_torque
        self._kp = np.array([s.kp_nm_per_deg for s in specs], dtype=np.float64)
        self._kd = np.array([s.kd_nm_per_dps for s in specs], dtype=np.float64)
        self._friction_allowance = np.zeros(n)
        friction = np.array(settings.coulomb_friction_nm or (0.0,) * n, dtype=np.float64)
        np.divide(MODEL_ERROR[2] * friction, self._kp, out=self._friction_allowance, where=self._kp > 0.0)
        self._minv = np.diagonal(controller.tracking.mass_inverse)  # a view: the model updates M⁻¹ in place
        self._sensitivity = np.zeros((3, n))  # d(angle)/d(torque constant): deg, deg/s, deg/s²
        self._sensitivity_s = math.nan
        # the model arm's inertia about each joint, as last evaluated, when, and its rate of change, kg·m²(/s)
        self._inertia_before = np.full(n, math.nan)
        self._inertia_s = math.nan
        self._inertia_seen = -1  # the model's evaluation the rate is from
        self._inertia_rate = np.zeros(n)
        self._damping = self._kd.copy()
        self._speed_slack = np.zeros(n)
        self._moving = np.zeros(n, dtype=bool)
        self._behind = np.zeros(n, dtype=bool)
        self._magnitude = np.zeros(n)
        self._change = np.zeros(n)
        self._expected_before = np.zeros(n)  # the model's and the reference's speeds at the previous check
        self._reference_before = np.zeros(n)
        self._share = np.zeros(n)
        #: The overspeed check (:mod:`motion.safety.overspeed`), run in every evaluated cycle.
        self.overspeed = OverspeedCheck(controller)
        #: Per joint, the fastest measured speed that is no ``overspeed`` fault, joint deg/s.
        self.overspeed_limit_dps = self.overspeed.limit_dps
        #: The collision check (:mod:`motion.safety.collision`), run in every evaluated cycle.
        self.collision = CollisionCheck(
            controller, observer, settings.collision_threshold_nm, settings.collision_window_s
        )
        # (its arrays, updated in place: the published snapshot holds them)
        #: The configured collision threshold per joint, N·m (inf: not watched).
        self.collision_threshold = self.collision.threshold
        #: The latest residual per joint, N·m (NaN before the first observer step).
        self.residual_nm = self.collision.residual_nm
        #: The latest collision signal per joint (the residual's change over the window), N·m.
        self.collision_signal_nm = self.collision.signal_nm
        #: The latest threshold in force per joint: the configured one, or the bound where that is higher, N·m.
        self.collision_limit_nm = self.collision.limit_nm
        #: How long after the observer (re)starts the collision check is armed, s.
        self.collision_arming_s = self.collision.arming_s

    def start(self, now_s: float) -> None:
        """Reset the reply clocks (at loop start or after a clear)."""
        self.last_good_s[:] = now_s
        self.misses[:] = 0
        self.restart.restart()
        # The counter objects live as long as the transport: look them up once, not every cycle.
        self._counters = [self.controller.bus.motor_counters(motor_id) for motor_id in self.ids]
        for i, counter in enumerate(self._counters):
            self._bad_seen[i] = counter.bad_frames
            self._corrupt[i].clear()
        self._overruns_seen = self.controller.loop.overruns
        self._overrun_streak = 0
        self.collision.restart()
        self.restart_following()

    def rehearse(self, replies: list[Reply], now_s: float) -> None:
        """A guarded cycle's host work at rest on a measuring exchange's ``replies``, nothing sent (the rate check
        times it, :func:`motion.control.ratecheck.measure_rate`): the controller's
        (:meth:`~motion.control.controller.Controller.rehearse`), the set-point check and every monitor, the collision
        observer included. A fault seen here is left to the loop's first cycle, whose watchdog starts afresh
        (:meth:`start`), as does the observer."""
        self.controller.rehearse(replies, now_s)
        try:
            self.check_setpoint(self.controller.reference)
            self.evaluate(replies, now_s)
        except MotionFault:
            pass

    def check_setpoint(self, reference: State) -> None:
        """Refuse to send a planned set-point outside the joint limits.

        Raises:
            MotionFault: kind ``setpoint_limit``.
        """
        self._check_limits(reference.position, FaultKind.SETPOINT_LIMIT, "planned set-point outside the limits")

    def within(self, i: int, q_deg: float) -> bool:
        """Joint ``i`` at ``q_deg`` is inside its limits (with the measurement's tolerance)."""
        return bool(self.lower[i] <= q_deg <= self.upper[i])

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

    def evaluate(self, replies: list[Reply], now_s: float, *, complying: bool = False) -> None:
        """Check one cycle's replies and the controller's state.

        Args:
            replies: the cycle's replies.
            now_s: the time they were taken in.
            complying: the arm yields to a collision (``comply``): the observer runs but does not fault, there
                is no reference to follow, and no loop to keep it to a speed (no overspeed check).

        Raises:
            MotionFault: the first violated limit that cannot be held (communication, a drive's flags, a limit, an
                overspeed, a collision), else the first one that can (temperature, voltage, following error, overrun).
                Every monitor runs in every cycle: a fault the hold is for must not hide one it is not for.
        """
        settings = self.settings
        held: MotionFault | None = None
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
        held = held or self._check_messages(replies, now_s)
        self._check_corrupt(now_s)
        q = self.controller.axes.q_deg
        self._check_limits(q, FaultKind.POSITION_LIMIT, "measured position beyond the limit")
        # (not while the arm yields to a collision: no loop holds it to a speed then, by design; its limits do)
        overspeed = None if complying else self.overspeed.check(self.controller.axes.qd_dps)
        if overspeed is not None:
            raise overspeed
        self.collision.run(check=not complying)
        if complying:  # no reference to follow, so no expectation either until the arm follows one again
            self.restart_following()
            self.following = None
        else:
            # evaluated whatever else this cycle found: a hold for a hot motor must still see a joint that does not
            # follow it (the supervisor escalates a persisting one)
            self.following = self._following_fault(q, now_s) if self._following else None
            held = held or self.following
            self._following = True
        overruns = self.controller.loop.overruns
        self._overrun_streak = self._overrun_streak + 1 if overruns > self._overruns_seen else 0
        self._overruns_seen = overruns
        if self._overrun_streak > settings.max_overrun_streak:
            held = held or self._fault(
                FaultKind.OVERRUN,
                None,
                float(self._overrun_streak),
                float(settings.max_overrun_streak),
                "consecutive overruns",
            )
        if held is not None:
            raise held

    @property
    def residual_cycle(self) -> int:
        """The loop cycle count of the cycle that computed :attr:`residual_nm` (-1: none yet)."""
        return self.collision.residual_cycle

    @property
    def collision_bound_nm(self) -> FloatArray:
        """The latest bound of the collision signal per joint, N·m (:mod:`motion.safety.collision_bound`; zeros
        without an observer): the check's array."""
        return self.collision.bound_nm

    @property
    def collision_guarding(self) -> bool:
        """Whether a collision check runs: an observer, and a threshold on at least one joint."""
        return self.collision.guarding

    @property
    def collision_armed(self) -> bool:
        """Whether the latest collision signal was (or would have been) held against the thresholds: the observer
        has settled since its (re)start (calibration looks only at these cycles)."""
        return self.collision.armed

    @property
    def following_error_deg(self) -> FloatArray:
        """The latest following error per joint, deg (|expected - q|, plus the lag lost by slipping; zeros until a
        cycle checked it since the expectation (re)started): the watchdog's array."""
        return self._error

    @property
    def following_limit_deg(self) -> FloatArray:
        """The following-error limit in force per joint at the latest check, deg (the configured one plus what a drive
        within the stated model error adds): the watchdog's array."""
        return self._following_limit

    def _check_messages(self, replies: list[Reply], now_s: float) -> MotionFault | None:
        """Each reply's own checks (flags, the restart sign, temperature): raises an unholdable fault, returns the
        first holdable one (None: none)."""
        held: MotionFault | None = None
        index = self.index
        for reply in replies:
            i = index.get(reply.motor_id)
            message = reply.message
            if i is None or message is None:
                continue
            if isinstance(message, STATUS_TYPES):
                try:
                    self._check_status(i, message)
                except MotionFault as fault:
                    if not fault.kind.holdable:
                        raise
                    held = held or fault
            elif isinstance(message, (MultiTurnAngle, Runtime)):
                restarted = self.restart.check(i, message, now_s)
                if restarted is not None:
                    raise restarted
            elif isinstance(message, STATE_TYPES) and message.temperature_c >= self.temperature_limit[i]:
                held = held or self._fault(
                    FaultKind.TEMPERATURE,
                    i,
                    message.temperature_c,
                    float(self.temperature_limit[i]),
                    "motor temperature",
                )
        return held

    def restart_following(self) -> None:
        """No following-error check in the next cycle; the expectation starts again from the measured state."""
        self._following = False
        self._error[:] = 0.0
        self._sensitivity[:] = 0.0
        self._sensitivity_s = math.nan
        controller = self.controller
        controller.tracking.reset(controller.axes.q_deg, controller.axes.qd_dps, controller.reference.position)
        np.copyto(self._expected_before, controller.axes.qd_dps)
        np.copyto(self._reference_before, controller.reference.velocity)

    def _following_fault(self, q: FloatArray, now_s: float) -> MotionFault | None:
        """|expected - measured| against the threshold; a joint slower than both the model and the reference also
        loses the lag it was expected to have (a joint that stops while it should move is as far from the reference
        as it is), so that a blocked joint is caught as soon as the raw reference-minus-measured error would catch
        it. Slower than both: in magnitude, by more than a joint within the model error may lag (:meth:`_slip_share`),
        with both moving the same way. Where the model swings past a stopping or turning reference and back (torque
        mode), a joint a little behind the model's swing is slower than one of them; a joint that turns back before
        the model does (a drive stronger than the model swings less far) moves against the model, and one that turns
        back after it (a weaker drive) is still at speed in the other direction or a few cycles behind: none is a
        slip."""
        controller = self.controller
        tracking, qd = controller.tracking, controller.axes.qd_dps
        slip, other = self._slip, self._error
        slack = None
        if self._torque_mode:
            self._advance_sensitivity(now_s)
            slack = np.abs(self._sensitivity[1], out=self._speed_slack)
            slack *= MODEL_ERROR[0]  # the speed a drive within the model error may lack: no slip
        self._slip_share(tracking.expected_dps, self._expected_before, qd, slip, slack)
        self._slip_share(controller.reference.velocity, self._reference_before, qd, other, None)
        np.minimum(slip, other, out=slip)
        np.multiply(tracking.expected_dps, controller.reference.velocity, out=other)
        slip *= np.greater(other, 0.0, out=self._behind)  # the model and the reference moving the same way
        np.multiply(tracking.lag_deg, controller.reference.velocity, out=other)
        slip *= np.greater(other, 0.0, out=self._behind)  # the model behind the reference, not past it
        slip *= tracking.lag_deg
        error = self._error
        np.subtract(tracking.expected_deg, q, out=error)
        error += slip
        np.abs(error, out=error)
        # the limit in force: the configured one, plus the share of the modelled lag a drive within the stated
        # bounds may add to it (FOLLOWING_LAG_ERROR), but not of the lag a slower joint lost (that is its error: a
        # blocked joint is still caught as soon as by the raw reference)
        limit = self._following_limit
        np.abs(tracking.lag_deg, out=limit)
        limit -= np.abs(slip, out=self._share)
        limit *= self._lag_error
        limit += self.settings.following_error_deg
        if self._torque_mode:
            np.abs(self._sensitivity[0], out=self._share)
            self._share *= MODEL_ERROR[0]
            limit += self._share
            limit += self._friction_allowance
        over = self._share
        np.divide(error, limit, out=over)
        worst = int(over.argmax())
        if over[worst] <= 1.0:
            return None
        return self._fault(
            FaultKind.FOLLOWING_ERROR,
            worst,
            float(error[worst]),
            float(limit[worst]),
            "|expected - q| (+ lag lost by slipping)",
        )

    def _advance_sensitivity(self, now_s: float) -> None:
        """Torque mode: what a drive within the stated model error adds to the following error.

        A drive whose torque constant is off by ε delivers ``(1 + ε) τ`` for every torque ``τ`` asked of it: the joint
        then moves by ``ε s`` from the model (and its speed by ``ε ṡ``), where ``s`` (the sensitivity to the torque
        constant) is the motion the torque asked for makes through the PD loop, ``M s̈ = τ − Kp s − (Kd + Ṁ) ṡ`` (M⁻¹'s
        diagonal at the model's pose, ``Ṁ`` the rate of change of M's diagonal: :meth:`_track_inertia_rate`; the
        torque held over each step, as the drives hold it). Static, that is the
        share of the gravity feed-forward the PD must hold up; moving, it rings as the loop does (a lightly damped
        loop, such as a base joint stretched out, swings by several times the static figure, and a weaker drive turns
        back cycles after the model). The friction's share of the Coulomb figure adds through the PD's stiffness."""
        position, speed, acceleration = self._sensitivity
        dt = now_s - self._sensitivity_s
        self._sensitivity_s = now_s
        if dt > 0.0:  # (NaN after a restart: the sensitivity starts from rest)
            np.multiply(speed, dt, out=self._share)
            position += self._share
            np.multiply(acceleration, 0.5 * dt * dt, out=self._share)
            position += self._share
            np.multiply(acceleration, dt, out=self._share)
            speed += self._share
        self._track_inertia_rate(now_s)
        np.multiply(self._kp, position, out=acceleration)
        np.multiply(self._damping, speed, out=self._share)
        acceleration += self._share
        np.subtract(self.controller.torque_nm, acceleration, out=acceleration)
        acceleration *= self._minv
        acceleration *= _DEG_PER_RAD

    def _track_inertia_rate(self, now_s: float) -> None:
        """The damping the deviation sees: the PD's, plus the rate of change of the arm's inertia about each joint
        (the velocity-product torques' share of a joint's own speed: ``∂(C q̇)ᵢ/∂q̇ᵢ = Ṁᵢᵢ``; an arm folding in
        while its base turns speeds the base up, an undamping of its deviation), from the model's evaluations."""
        tracking = self.controller.tracking
        if tracking.inertia_evaluations != self._inertia_seen and tracking.inertia_kgm2 is not None:
            self._inertia_seen = tracking.inertia_evaluations
            diagonal = np.diagonal(tracking.inertia_kgm2)
            if math.isfinite(self._inertia_s) and now_s > self._inertia_s:
                np.subtract(diagonal, self._inertia_before, out=self._inertia_rate)
                self._inertia_rate /= now_s - self._inertia_s
            np.copyto(self._inertia_before, diagonal)
            self._inertia_s = now_s
            np.multiply(self._inertia_rate, math.pi / 180.0, out=self._damping)
            self._damping += self._kd

    def _slip_share(
        self, speed_dps: FloatArray, previous_dps: FloatArray, qd: FloatArray, out: FloatArray, slack: FloatArray | None
    ) -> None:
        """The share of ``speed_dps`` the measured speed's magnitude falls short of, 0..1, into ``out``; 0 where the
        shortfall is within :data:`SLIP_PHASE_CYCLES` times the speed's change since the previous cycle
        (``previous_dps``; a joint a cycle or two behind a turning swing is no slip) plus ``slack`` (deg/s: what a
        drive within the model error may lack), and where the speed is below the moving threshold. ``previous_dps``
        then takes ``speed_dps``."""
        moving, magnitude, change = self._moving, self._magnitude, self._change
        np.subtract(speed_dps, previous_dps, out=change)
        np.abs(change, out=change)
        change *= SLIP_PHASE_CYCLES
        if slack is not None:
            change += slack
        np.copyto(previous_dps, speed_dps)
        np.abs(qd, out=magnitude)
        np.abs(speed_dps, out=out)
        out -= magnitude  # slower in magnitude: a joint swinging the other way at speed is moving, not stuck
        np.greater(out, change, out=moving)
        out *= moving
        np.abs(speed_dps, out=change)
        np.greater(change, _MOVING_DPS, out=moving)
        out *= moving
        np.divide(out, change, out=out, where=moving)
        np.minimum(out, 1.0, out=out)
        np.maximum(out, 0.0, out=out)
        out *= moving

    def restarts(self, replies: list[Reply], now_s: float) -> list[MotionFault]:
        """The drives that a cycle's replies show restarted, one ``drive_restarted`` fault each (while the arm is
        halted, when nothing else is evaluated: a drive that restarts then has lost its turn count all the same)."""
        found = []
        index, check = self.index, self.restart.check
        for reply in replies:
            i = index.get(reply.motor_id)
            message = reply.message
            if i is not None and isinstance(message, (MultiTurnAngle, Runtime)):
                fault = check(i, message, now_s)
                if fault is not None:
                    found.append(fault)
        return found

    def _check_status(self, i: int, status: Status1 | Status1V3) -> None:
        family = self.controller.families[i]
        errors = int(status.errors)
        if errors & family.over_temperature:
            raise self._fault(
                FaultKind.DRIVE_OVER_TEMPERATURE, i, status.temperature_c, None, f"drive error {status.errors!r}"
            )
        if errors & family.low_voltage:
            raise self._fault(FaultKind.DRIVE_LOW_VOLTAGE, i, status.voltage_v, None, f"drive error {status.errors!r}")
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
        missed, good, misses = self._missing, self._good, self.misses
        np.greater(self._answered, missed, out=good)  # answered and nothing missing
        np.add(misses, 1, out=misses, where=missed)
        np.copyto(misses, 0, where=good)
        np.copyto(self.last_good_s, now_s, where=good)
        worst = int(misses.argmax())
        if self.misses[worst] > settings.max_missed_replies:
            raise self._fault(
                FaultKind.NO_REPLY,
                worst,
                float(self.misses[worst]),
                float(settings.max_missed_replies),
                "consecutive misses",
            )
        silent = np.subtract(now_s, self.last_good_s, out=self._silent)
        worst = int(silent.argmax())
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
