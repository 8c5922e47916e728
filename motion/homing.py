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
   ``homing.max_travel_deg`` and ``homing.timeout_s``. The stop is reached when the measured torque current rises
   ``homing.current_limit_a`` above what moving freely took (a slow average: gravity changes along the way), or the
   joint falls :data:`STALL_DEG` behind its reference *and* has slowed below :data:`STALL_SPEED_SHARE` of the seek's
   speed (a joint late by the host's or the bus's delays still moves at that speed: no stop); a cycle hook watches
   every cycle.
3. The reference stops at the full limits, and the joint backs off by ``homing.back_off_deg``, and at least to
   :data:`LIMIT_CLEARANCE_DEG` inside its limits. The angle measured at the stop, in the controller's provisional
   frame, differs from ``stop_deg`` by whole motor turns plus what the stop yields: the nearest whole number of turns
   is the correction, and a remainder of more than a quarter of a turn is refused (the configured ``stop_deg`` or
   ``zero_offset_deg`` is wrong, or something else stopped the joint).

Homing can be interrupted in every step: a stop (``Arm.stop()`` from another thread, Ctrl-C or SIGTERM in
``rmd-motion``) is an E-stop request to the homing loop, which halts every axis (0x81) in its next cycle; the homing
steps look for faults every control period and raise it (a MotionFault of kind ``stop``).
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Final

from motion.config.schema import ArmConfig, ControlMode, JointConfig
from motion.control.controller import Controller
from motion.control.turns import TURN_DEG, turn_joint_deg
from motion.errors import MotionError, TransportError
from motion.safety import ArmState, Supervisor
from motion.transmission import Transmission
from motion.transport import Reply

logger = logging.getLogger("motion.homing")

#: A joint that falls this far behind its reference while seeking has reached its stop, degrees.
STALL_DEG: Final = 1.0
#: ... once it has slowed below this share of the seek's speed (a joint against its stop has stopped; one behind its
#: reference because the measurement is late, on a loaded host or a slow bus, still moves at the seek's speed).
STALL_SPEED_SHARE: Final = 0.5
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
    """A cycle hook: the first cycle in which joint ``index`` pressed against something — its torque current
    :attr:`current_limit_a` above the current it took to move freely (a slow average: gravity changes along the way),
    or :data:`STALL_DEG` behind its reference and slower than :data:`STALL_SPEED_SHARE` of ``seek_dps``."""

    def __init__(self, index: int, current_limit_a: float, period_s: float, seek_dps: float) -> None:
        self.index = index
        self.current_limit_a = current_limit_a
        self._stalled_dps = STALL_SPEED_SHARE * abs(seek_dps)
        self._alpha = min(1.0, period_s / FREE_CURRENT_TAU_S)
        self.free_a: float | None = None  # the average current while moving freely
        self.found: tuple[float, float, float] | None = None  # (time, angle, current)

    def __call__(self, controller: Controller, start_s: float, _replies: list[Reply]) -> None:
        if self.found is not None:
            return
        i, axes = self.index, controller.axes
        q, iq = float(axes.q_deg[i]), float(axes.iq_a[i])
        free = iq if self.free_a is None else self.free_a
        lag = abs(float(controller.reference.position[i]) - q)
        stalled = lag >= STALL_DEG and abs(float(axes.qd_dps[i])) < self._stalled_dps
        if abs(iq - free) >= self.current_limit_a or stalled:
            self.found = (start_s, q, iq - free)
        else:
            self.free_a = free + self._alpha * (iq - free)


def seek_stop(supervisor: Supervisor, index: int, joint: JointConfig, pause: Callable[[float], None]) -> HomingResult:
    """Move joint ``index`` to its stop, back off, and return where the stop was (the loop of ``supervisor`` runs
    the homing variant; ``pause`` lets time pass with it running).

    Raises:
        HomingError: no stop within the travel or the time, or a remainder no whole turn count explains.
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
    watch = _StopWatch(index, homing.current_limit_a, period, homing.speed_dps)
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
    supervisor.stop_motion()  # at the full limits: the seek's scaled ones would take seconds to stop
    _wait_idle(supervisor, pause)
    turns, remainder = turns_to_stop(joint.name, joint.transmission(), found_deg, homing.stop_deg)
    # back off the stop by back_off_deg, and at least into the joint's limits, where the arm's loop takes over
    near_limit = joint.position_min_deg if toward < 0 else joint.position_max_deg
    inside = -toward * max(homing.back_off_deg, abs(near_limit - homing.stop_deg) + LIMIT_CLEARANCE_DEG)
    back = controller.reference.position.copy()
    back[index] = found_deg - remainder + inside  # the stop's own angle in this frame, then off it
    supervisor.move_to(back, homing.speed_dps / joint.velocity_limit_dps)
    _wait_idle(supervisor, pause)
    return HomingResult(joint.name, found_deg, turns, remainder, found_s - began, current)


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
    "STALL_DEG",
    "STALL_SPEED_SHARE",
    "HomingError",
    "HomingResult",
    "corrected_turns",
    "finish_halt",
    "homed_joints",
    "homing_variant",
    "quiet_ahead",
    "seek_stop",
    "turns_to_stop",
]
