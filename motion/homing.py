"""Homing: find a geared joint's turn count against its hard stop (``rmd-motion home``, ``Arm(..., home=...)``).

The drive's single-turn encoder is absolute within a motor turn; what a power-up loses is the whole turns
(:mod:`motion.control.turns`). Homing finds them from a hard stop whose joint angle is configured
(``joints[].homing.stop_deg``, outside the joint's limits):

1. The arm runs under a guarded loop of its own, built from a *homing variant* of the configuration
   (:func:`homing_variant`): position mode (the drives' own loops; no feed-forward from angles not yet known), no
   collision observer (its model of the whole arm needs the angle homing looks for, and touching the stop is the
   point), and for the joints being homed no position limits and no power-on window. Every other fault rule stays
   active: drive flags, temperature, voltage, replies, following error, the other joints' limits, overruns.
2. After :data:`SETTLE_S` of holding, the joint moves toward its stop at ``homing.speed_dps`` for at most
   ``homing.max_travel_deg`` and ``homing.timeout_s``. The stop is reached when the joint has stalled, judged in
   time and distance, not by one cycle's reading (:class:`StallCriterion`): its torque current stays
   ``homing.current_limit_a`` away from what moving freely took (a slow average: gravity changes along the way)
   while it moves no more than the stop's give and two steps of its angle's measurement, for at least
   :data:`STALL_SAMPLES` samples and as long as the seek takes to cover twice that distance. A joint that follows
   the seek moves farther in that time at any rate, however late its measurement or sparse its set-points (a drive
   that reaches each before the next comes reads a low speed while it moves, and its reference leads it by a
   period's travel: a rule on either found a false stop at low rates). A rate at which the stall cannot be told
   before the seek's set-point has run past the stop by more than ``safety.following_error_deg`` (the
   following-error check would halt the joint first) is refused before the seek, with the figures
   (:func:`seek_criterion`). A cycle hook watches every cycle and holds the joint where it stalled in the cycle it
   finds the stop.
3. The joint backs off by ``homing.back_off_deg``, and at least to :data:`LIMIT_CLEARANCE_DEG` inside its limits.
   The angle measured at the stop, in the controller's provisional frame, differs from ``stop_deg`` by whole motor
   turns plus what the stop yields: the nearest whole number of turns is the correction, and a remainder of more
   than a quarter of a turn is refused (the configured ``stop_deg`` or ``zero_offset_deg`` is wrong, or something
   else stopped the joint).

Homing can be interrupted in every step: a stop (``Arm.stop()`` from another thread, Ctrl-C or SIGTERM in
``rmd-motion``) is an E-stop request to the homing loop, which halts every axis (0x81) in its next cycle; the homing
steps look for faults every control period and raise it (a MotionFault of kind ``stop``).
"""

from __future__ import annotations

import dataclasses
import logging
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Final

from motion.config.schema import ArmConfig, ControlMode, JointConfig
from motion.control.controller import Controller
from motion.control.tracking import PositionLoop
from motion.control.turns import TURN_DEG, turn_joint_deg
from motion.errors import MotionError, TransportError
from motion.protocol.table import Direction, WireProtocol, field_spec
from motion.protocol.v3.messages import CommandV3
from motion.safety import ArmState, Supervisor
from motion.safety.watchdog import FOLLOWING_LAG_ERROR
from motion.trajectory import State
from motion.transmission import Transmission
from motion.transport import Reply

logger = logging.getLogger("motion.homing")

#: A joint pressed against its stop may still read this much motion, joint degrees, beyond two steps of its angle's
#: measurement: the give of the stop and of the gear as the press rises from the homing current to the drive's limit
#: (the motor's encoder reads the joint through the gear, whose backlash alone is about 10 arcmin, 0.17 deg, on an
#: RMD-X planetary).
STOP_GIVE_DEG: Final = 0.25
#: A stall is seen in at least this many samples, two intervals: one interval without motion is no stop (a drive that
#: reached a sparse set-point before the next one came waits there; a joint in stick-slip sticks for a moment).
STALL_SAMPLES: Final = 3
#: Cycle starts lie on the loop's grid; their differences are compared with the time criterion within this, s.
_TIME_SLACK_S: Final = 1e-9
#: Time constant of the average current while moving freely toward the stop, s.
FREE_CURRENT_TAU_S: Final = 0.25
#: The arm holds this long under the homing loop before a seek starts (the drives take up their loads), s.
SETTLE_S: Final = 0.5
#: The largest remainder (share of one motor turn, joint side) between the angle found at the stop and the configured
#: ``stop_deg`` once whole turns are taken out.
REMAINDER_SHARE_MAX: Final = 0.25
#: Homing leaves a joint at least this far inside its limits, degrees.
LIMIT_CLEARANCE_DEG: Final = 1.0
#: Position limits of a joint being homed in the homing variant, degrees: none in effect (the frame is not known).
_UNLIMITED_DEG: Final = 1.0e6


class HomingError(MotionError):
    """Homing could not find the stop, or found it where no whole number of turns explains (the CLI exits 2)."""


@dataclass(frozen=True, slots=True)
class HomingResult:
    """One joint's homing.

    Attributes:
        name: the joint.
        stop_found_deg: the angle measured at the stop, in the provisional frame, degrees.
        turns_correction: whole motor turns added to the joint's turn offset.
        remainder_deg: what the stop yielded (or its configured angle misses), degrees: found + correction - stop.
        seek_s: how long the seek took, seconds (the arm's clock).
        current_a: the torque current above the free-moving one when the stop was reached, A.
    """

    name: str
    stop_found_deg: float
    turns_correction: int
    remainder_deg: float
    seek_s: float
    current_a: float


@dataclass(frozen=True, slots=True)
class StallCriterion:
    """When a seeking joint has stalled against its stop: its torque current at ``homing.current_limit_a`` from the
    free-moving one in every sample of a run of :data:`STALL_SAMPLES` samples or more, over at least :attr:`time_s`,
    in which it moved no more than :attr:`distance_deg`.

    Attributes:
        step_deg: the step of the joint's angle measurement, joint degrees (the older drives' encoder field, V3
            drives' 0x92 angle, through the gear).
        distance_deg: :data:`STOP_GIVE_DEG` plus two steps (two readings of a still joint differ by one).
        time_s: the longer of the time the seek's speed takes over twice :attr:`distance_deg` and
            ``STALL_SAMPLES - 1`` control periods: a joint that follows the seek moves at least ``speed × (time_s -
            period)`` in it (it may wait up to a period for its next set-point), which is more than the distance.
    """

    step_deg: float
    distance_deg: float
    time_s: float


def stall_criterion(speed_dps: float, period_s: float, step_deg: float) -> StallCriterion:
    """The stall criterion of a seek at ``speed_dps`` under a loop of ``period_s`` with an angle measured in steps of
    ``step_deg`` (joint side)."""
    distance = STOP_GIVE_DEG + 2.0 * step_deg
    time_s = max(2.0 * distance / abs(speed_dps), (STALL_SAMPLES - 1) * period_s)
    return StallCriterion(step_deg, distance, time_s)


def angle_step_deg(controller: Controller, index: int) -> float:
    """The step of joint ``index``'s angle measurement, joint degrees: a V3 drive's 0x92 angle (its output shaft's)
    or the older drive's encoder field (a motor turn over its counts), through the gear."""
    spec = controller.specs[index]
    if controller.families[index].angle_every_cycle:
        field = field_spec(CommandV3.READ_MULTI_TURN_ANGLE, Direction.REPLY, WireProtocol.CAN, "angle_deg")
        motor_deg = field.physical(1) * spec.drive_gear_ratio
    else:
        motor_deg = TURN_DEG / float(controller.axes.counts_per_rev[index])
    return abs(controller.transmission.transmissions[index].joint_rate(motor_deg))


def seek_overrun_deg(speed_dps: float, period_s: float, stall: StallCriterion, lag_deg: float) -> float:
    """How far past its stop a seek's set-point may run before the press ends, joint degrees: the joint's lag behind
    it at the seek's speed (``lag_deg``), plus the seek's travel over the stall's run in whole periods and two more
    (the first sample of the press comes up to a period after the contact, and the batch of the cycle that finds the
    stop still carries the seek's next set-point: the hold goes out in the next one)."""
    periods = max(STALL_SAMPLES - 1, math.ceil(stall.time_s / period_s - _TIME_SLACK_S))
    return abs(speed_dps) * (periods + 2) * period_s + lag_deg


def _contact_lag_deg(loop: PositionLoop, speed_dps: float, lag_share: float) -> float:
    """A joint's lag behind its target at ``speed_dps`` under its drive's position loop (the tracking model's: speed
    over the angle gain, or the braking distance of its acceleration limit where longer), plus the share a drive
    within the stated bounds may add (:data:`~motion.safety.watchdog.FOLLOWING_LAG_ERROR`)."""
    v = abs(speed_dps)
    return max(v / loop.angle_gain_per_s, v * v / (2.0 * loop.acceleration_dps2)) * (1.0 + lag_share)


def seek_criterion(supervisor: Supervisor, index: int, joint: JointConfig) -> StallCriterion:
    """The stall criterion of joint ``index``'s seek under ``supervisor``'s loop, once the seek is known to end its
    press before the following-error check halts the joint (:func:`seek_overrun_deg` within
    ``safety.following_error_deg``).

    Raises:
        HomingError: the rate or the seek's speed does not let the stop be told in time (the figures, the highest
            speed at this rate and the lowest rate at this speed).
    """
    homing = joint.homing
    if homing is None:  # homed_joints() refuses these
        raise HomingError(f"joint {joint.name} has no hard stop configured")
    controller = supervisor.controller
    period, step = controller.period_s, angle_step_deg(controller, index)
    loop = controller.tracking.position_loops()[index]
    share = FOLLOWING_LAG_ERROR[(True, controller.families[index].reads_loop_settings)]
    limit = supervisor.settings.following_error_deg

    def overrun(speed_dps: float, period_s: float) -> float:
        stall = stall_criterion(speed_dps, period_s, step)
        return seek_overrun_deg(speed_dps, period_s, stall, _contact_lag_deg(loop, speed_dps, share))

    speed = homing.speed_dps
    stall = stall_criterion(speed, period, step)
    reach = overrun(speed, period)
    if reach <= limit:
        return stall
    # (the stall's run is whole periods: the figures are stepped to ones that hold)
    fastest = math.floor(_bisect(lambda v: overrun(v, period) <= limit, 0.0, speed) * 10.0) / 10.0
    while fastest > 0.0 and overrun(fastest, period) > limit:
        fastest = round(fastest - 0.1, 1)
    rate = "no rate at this speed"
    if overrun(speed, 1.0 / _RATE_SEARCH_HZ) <= limit:
        slowest_hz = math.ceil(_bisect(lambda hz: overrun(speed, 1.0 / hz) > limit, 1.0 / period, _RATE_SEARCH_HZ))
        while overrun(speed, 1.0 / slowest_hz) > limit:
            slowest_hz += 1
        rate = f"control.rate_hz >= {slowest_hz:g} at this speed"
    raise HomingError(
        f"joint {joint.name}: homing at {speed:g} deg/s under {1.0 / period:g} Hz cannot tell its stop in time: the "
        f"stall is told by at most {stall.distance_deg:.2f} deg of motion over {stall.time_s:.3f} s "
        f"({STALL_SAMPLES} samples at least) with the current at homing.current_limit_a, by when the seek's set-point "
        f"has run up to {reach:.2f} deg past the stop, more than safety.following_error_deg = {limit:g} (the "
        f"following-error check would halt the joint first); use homing.speed_dps <= {fastest:g} at this rate, or "
        f"{rate}"
    )


#: The highest rate the refusal of a seek looks for, Hz.
_RATE_SEARCH_HZ: Final = 10_000.0


def _bisect(ok: Callable[[float], bool], good: float, bad: float) -> float:
    """The edge between ``good`` (where ``ok`` holds) and ``bad`` (where it does not), to 1e-12 of their distance
    (``ok`` changing once between them)."""
    for _ in range(40):
        middle = 0.5 * (good + bad)
        if ok(middle):
            good = middle
        else:
            bad = middle
    return good


def homed_joints(config: ArmConfig, names: Sequence[str]) -> tuple[JointConfig, ...]:
    """The joints to home, by name.

    Raises:
        HomingError: an unknown joint, a repeated one, or one without ``homing`` in the configuration.
    """
    by_name = {j.name: j for j in config.joints}
    chosen: list[JointConfig] = []
    for name in names:
        joint = by_name.get(name)
        if joint is None:
            raise HomingError(f"unknown joint {name!r}; the joints of {config.name} are {', '.join(by_name)}")
        if joint.homing is None:
            with_stops = [j.name for j in config.joints if j.homing is not None]
            raise HomingError(
                f"joint {name} has no hard stop configured (joints[].homing.stop_deg); joints that can be homed: "
                f"{', '.join(with_stops) or 'none'}"
            )
        if joint in chosen:
            raise HomingError(f"joint {name} is named twice")
        chosen.append(joint)
    if not chosen:
        raise HomingError("name at least one joint to home")
    return tuple(chosen)


def homing_variant(config: ArmConfig, names: Sequence[str]) -> ArmConfig:
    """The configuration homing runs under (see the module docstring, step 1)."""
    homed = set(names)

    def relaxed(joint: JointConfig) -> JointConfig:
        if joint.name not in homed:
            return joint.without_collision_threshold()
        return dataclasses.replace(
            joint.without_collision_threshold(),
            position_min_deg=-_UNLIMITED_DEG,
            position_max_deg=_UNLIMITED_DEG,
            power_on_window_deg=None,
        )

    control = dataclasses.replace(
        config.control, mode=ControlMode.POSITION, gravity_feedforward=False, inertia_feedforward=False
    )
    return dataclasses.replace(config, control=control, joints=tuple(relaxed(j) for j in config.joints))


def turns_to_stop(name: str, transmission: Transmission, found_deg: float, stop_deg: float) -> tuple[int, float]:
    """The whole motor turns that carry the angle found at the stop onto the configured one, and the remainder.

    Raises:
        HomingError: the remainder is more than :data:`REMAINDER_SHARE_MAX` of a turn.
    """
    step = transmission.direction * turn_joint_deg(transmission)  # joint degrees per added motor turn
    turns = round((stop_deg - found_deg) / step)
    remainder = found_deg + turns * step - stop_deg
    if abs(remainder) > REMAINDER_SHARE_MAX * abs(step):
        raise HomingError(
            f"joint {name}: the stop was found at {found_deg:.2f} deg, {remainder:+.2f} deg from stop_deg "
            f"{stop_deg:g} once whole motor turns ({abs(step):g} deg each) are taken out: more than a quarter turn, so "
            "no turn count explains it; check homing.stop_deg and zero_offset_deg, and that nothing else blocked the "
            "joint"
        )
    return turns, remainder


class _StopWatch:
    """A cycle hook: where joint ``index`` stalled against something — its torque current
    :attr:`current_limit_a` away from the current it took to move freely (a slow average: gravity changes along the
    way) in every sample of a run of at least :data:`STALL_SAMPLES` samples over at least ``stall.time_s``, in which
    it moved no more than ``stall.distance_deg`` (see :class:`StallCriterion`)."""

    def __init__(self, index: int, current_limit_a: float, period_s: float, stall: StallCriterion) -> None:
        self.index = index
        self.current_limit_a = current_limit_a
        self.stall = stall
        self._alpha = min(1.0, period_s / FREE_CURRENT_TAU_S)
        self.free_a: float | None = None  # the average current while moving freely
        self._run: tuple[float, float, int] | None = None  # the run of pressing samples: (since, angle there, count)
        self.found: tuple[float, float, float] | None = None  # (time, angle, current)

    def __call__(self, controller: Controller, start_s: float, _replies: list[Reply]) -> None:
        if self.found is not None:
            return
        i, axes = self.index, controller.axes
        q, iq = float(axes.q_deg[i]), float(axes.iq_a[i])
        free = iq if self.free_a is None else self.free_a
        if abs(iq - free) < self.current_limit_a:
            self._run = None
            self.free_a = free + self._alpha * (iq - free)
            return
        run = self._run
        if run is None or abs(q - run[1]) > self.stall.distance_deg:
            self._run = (start_s, q, 1)  # pressing, and (again) not moving from here
            return
        since, anchor, count = run[0], run[1], run[2] + 1
        self._run = (since, anchor, count)
        if count >= STALL_SAMPLES and start_s - since >= self.stall.time_s - _TIME_SLACK_S:
            self.found = (start_s, anchor, iq - free)
            # The press ends in this cycle: the joint is held where it stands against its stop (a stop ramp would carry
            # its set-point on past the stop by the seek's braking distance, into a following error).
            held = controller.reference.position.copy()
            held[i] = q
            if controller.follower is not None:
                controller.follower.hold_at(held)
            controller.reference = State.at_rest(held)


def seek_stop(supervisor: Supervisor, index: int, joint: JointConfig, pause: Callable[[float], None]) -> HomingResult:
    """Move joint ``index`` to its stop, back off, and return where the stop was (the loop of ``supervisor`` runs
    the homing variant; ``pause`` lets time pass with it running).

    Raises:
        HomingError: a rate or speed at which the stop cannot be told in time (before the seek:
            :func:`seek_criterion`), no stop within the travel or the time, or a remainder no whole turn count explains.
        MotionFault: a fault halted the arm, or a stop (``Arm.stop()``, Ctrl-C: ``request_estop`` of ``supervisor``,
            taken in the loop's next cycle); raised within a control period of the halt.
    """
    homing = joint.homing
    if homing is None:  # homed_joints() refuses these
        raise HomingError(f"joint {joint.name} has no hard stop configured")
    controller = supervisor.controller
    clock, period = controller.clock, controller.period_s
    toward = -1.0 if homing.stop_deg <= joint.position_min_deg else 1.0
    start = controller.reference.position.copy()
    travel = homing.max_travel_deg if homing.max_travel_deg is not None else TURN_DEG
    target = start.copy()
    target[index] += toward * travel
    settled = clock.now() + SETTLE_S
    _run_until(supervisor, pause, lambda: clock.now() >= settled)
    stall = seek_criterion(supervisor, index, joint)
    watch = _StopWatch(index, homing.current_limit_a, period, stall)
    controller.cycle_hooks.append(watch)
    began = clock.now()
    try:
        supervisor.move_to(target, homing.speed_dps / joint.velocity_limit_dps)
        while watch.found is None:
            _raise_if_faulted(supervisor)
            if controller.idle:
                raise HomingError(
                    f"joint {joint.name}: no stop within {travel:g} deg of travel toward {homing.stop_deg:g} deg "
                    "(homing.max_travel_deg); the arm stopped there"
                )
            if clock.now() - began > homing.timeout_s:
                supervisor.stop_motion()
                raise HomingError(f"joint {joint.name}: no stop within homing.timeout_s = {homing.timeout_s:g} s")
            pause(period)
    finally:
        controller.cycle_hooks.remove(watch)
    found_s, found_deg, current = watch.found
    _wait_idle(supervisor, pause)  # (the watch held the joint where it found the stop)
    turns, remainder = turns_to_stop(joint.name, joint.transmission(), found_deg, homing.stop_deg)
    # back off the stop by back_off_deg, and at least into the joint's limits, where the arm's loop takes over
    near_limit = joint.position_min_deg if toward < 0 else joint.position_max_deg
    inside = -toward * max(homing.back_off_deg, abs(near_limit - homing.stop_deg) + LIMIT_CLEARANCE_DEG)
    back = controller.reference.position.copy()
    back[index] = found_deg - remainder + inside  # the stop's own angle in this frame, then off it
    supervisor.move_to(back, homing.speed_dps / joint.velocity_limit_dps)
    _wait_idle(supervisor, pause)
    return HomingResult(joint.name, found_deg, turns, remainder, found_s - began, current)


def check_seeks(
    supervisor: Supervisor, seeks: Sequence[tuple[int, JointConfig]], pause: Callable[[float], None]
) -> None:
    """Before the first seek: every joint of ``seeks`` (index, joint) can have its stop told in time
    (:func:`seek_criterion`), judged once the loop knows the drives' position loops (read in its first cycles).

    Raises:
        HomingError: a joint's seek cannot (nothing has moved).
        MotionFault: a fault halted the arm meanwhile.
    """
    tracking = supervisor.controller.tracking
    _run_until(supervisor, pause, lambda: not tracking.unread)
    for index, joint in seeks:
        seek_criterion(supervisor, index, joint)


def _wait_idle(supervisor: Supervisor, pause: Callable[[float], None]) -> None:
    """Let the loop run until the motion has ended; a fault on the way is raised."""
    controller = supervisor.controller
    _run_until(supervisor, pause, lambda: controller.idle)


def _run_until(supervisor: Supervisor, pause: Callable[[float], None], done: Callable[[], bool]) -> None:
    """Let the loop run, a control period at a time, until ``done()``; a fault (or a stop) on the way is raised
    within a period."""
    period = supervisor.controller.period_s
    while not done():
        _raise_if_faulted(supervisor)
        pause(period)
    _raise_if_faulted(supervisor)


def _raise_if_faulted(supervisor: Supervisor) -> None:
    fault = supervisor.fault
    if fault is not None and supervisor.state is not ArmState.READY:
        raise fault


def finish_halt(supervisor: Supervisor) -> None:
    """Before a halted homing loop is closed: let it re-send the halt to the drives that have not acknowledged it yet
    (until they do, or ``safety.halt_retry_s`` passes), as the arm's loop would."""
    controller = supervisor.controller
    halting = (ArmState.HALT_PENDING, ArmState.HALTING)  # (a halt owed goes out in the next cycle)
    if supervisor.state in halting and controller.loop.running:
        controller.wait_for(lambda: supervisor.state not in halting, supervisor.settings.halt_retry_s)


def quiet_ahead(supervisor: Supervisor) -> None:
    """Before a loop closes with another of this program to follow (homing, then the arm's): the drives' link-loss
    protection off, so that the quiet time between the loops (the next controller built, positions read) does not stop
    them (:meth:`~motion.control.drivesetup.DriveSetup.suspend_protection`; the next loop sets it again). A drive that
    does not answer is logged: the close goes on."""
    try:
        supervisor.drives.suspend_protection(supervisor.controller.clock.now() + SUSPEND_WINDOW_S)
    except TransportError as exc:
        logger.warning("the drives' link-loss protection was not turned off between loops: %s", exc)


#: How long the drives have to acknowledge the protection's suspension (:func:`quiet_ahead`), s.
SUSPEND_WINDOW_S = 0.5


def corrected_turns(turns: Sequence[int], index_of: Callable[[str], int], results: Sequence[HomingResult]) -> list[int]:
    """The turn offsets after homing: each homed joint's plus its correction."""
    corrected = list(turns)
    for result in results:
        corrected[index_of(result.name)] += result.turns_correction
    return corrected


__all__ = [
    "REMAINDER_SHARE_MAX",
    "STALL_SAMPLES",
    "STOP_GIVE_DEG",
    "HomingError",
    "HomingResult",
    "StallCriterion",
    "check_seeks",
    "corrected_turns",
    "finish_halt",
    "homed_joints",
    "homing_variant",
    "quiet_ahead",
    "seek_criterion",
    "seek_stop",
    "stall_criterion",
    "turns_to_stop",
]
