"""The controller: one cycle = take the replies -> update state -> plan the next set-point -> build the batch ->
one ``transact`` by the deadline.

Position mode streams 0xA4 (multi-turn angle + max speed) per joint. Torque mode computes, per joint,
``tau = feedforward(q, qd_ref, qdd_ref) + Kp (q_ref - q) + Kd (qd_ref - qd)``, converts it to torque current
(limited per joint; the limiting is recorded) and sends it in one 0x280 frame for motor ids 1..4 (CAN) and 0xA1
frames for the others (and for every joint on RS485).

Motion commands (:meth:`Controller.move_to`, :meth:`Controller.follow`, :meth:`Controller.stop_motion`) may come from
any thread: they are queued and planned in the control thread at the start of the next cycle, from the reference at
that instant, so a new target never steps the reference's velocity or acceleration.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Final, TypeAlias

import numpy as np
from numpy.typing import NDArray

from motion.config.schema import ControlMode
from motion.control.axes import AxisSpec, AxisStates
from motion.control.clock import Clock, MonotonicClock, is_simulated
from motion.control.family import FAMILIES
from motion.control.scheduler import CycleFn, FixedRateLoop, LoopStatistics
from motion.control.snapshot import JOINT_ROWS, CycleSnapshot, frozen
from motion.control.tracking import ExpectedTracking
from motion.errors import MotionError, MotionFault, PlanningError, TransportError
from motion.protocol import (
    Command,
    Message,
    MotorState,
    MultiMotorTorque,
    MultiTurnAngle,
    MultiTurnPositionSpeed,
    TorqueControl,
    WireProtocol,
)
from motion.protocol.compiled import frozen_builder
from motion.protocol.scales import iq_amps
from motion.protocol.table import MULTI_TORQUE_MOTOR_IDS
from motion.protocol.v3.messages import CommandV3, Runtime
from motion.trajectory import Follower, JointLimits, Path, Planner, State
from motion.transmission import ArmTransmission, FloatArray
from motion.transport.base import Reply, Request, Transport

#: ``feedforward(q_deg, qd_dps, qdd_dps2) -> tau_nm``, arrays in joint order (gravity, optionally inertia).
Feedforward = Callable[[FloatArray, FloatArray, FloatArray], FloatArray]

# How often a thread that waits on a running loop looks again, s.
_POLL_S = 0.002


def _never() -> bool:
    return False


@dataclass(frozen=True, slots=True)
class ControllerOptions:
    """Settings of the control loop.

    Attributes:
        mode: position or torque streaming.
        rate_hz: control rate, Hz.
        protocol: the wire protocol of the bus (decides 0xA4 layout and the use of 0x280).
        speed_headroom: 0xA4 max speed = planned motor speed × headroom + floor, so that the drive's own position
            loop (which lags the stream by speed / its gain) can catch up during the move; never above the joint's
            velocity limit (a stale or jumping set-point cannot drive a joint past it).
        catch_up_share: position mode: the share of each joint's velocity limit the planner leaves free, so that a
            drive lagging the stream still has room below its cap (the limit) to catch up at the planned top speed.
        speed_floor_share: the floor as a share of the joint's velocity limit (motor side), so that the last
            set-points of a move, where the planned speed goes to zero, are still reached promptly.
        reply_budget: share of the period given to ``transact`` (the rest is for computing the next cycle).
        multi_motor_frame: use the 0x280 frame for motor ids 1..4 in torque mode on CAN (only when all four are
            joints of the arm).
    """

    mode: ControlMode = ControlMode.POSITION
    rate_hz: float = 200.0
    protocol: WireProtocol = WireProtocol.CAN
    speed_headroom: float = 1.5
    speed_floor_share: float = 0.1
    catch_up_share: float = 0.1
    reply_budget: float = 0.8
    multi_motor_frame: bool = True


def planning_limits(limits: JointLimits, options: ControllerOptions) -> JointLimits:
    """The limits the planner plans within: the joints' own, but for position mode's velocities, which keep
    ``options.catch_up_share`` of each limit free (the 0xA4 cap is the limit itself)."""
    if options.mode is not ControlMode.POSITION or not options.catch_up_share:
        return limits
    share = 1.0 - options.catch_up_share
    return dataclasses.replace(limits, velocity_dps=tuple(v * share for v in limits.velocity_dps))


#: How often a read before the loop is asked of a drive that did not answer (see ``Controller._read_every_drive``).
_READ_ATTEMPTS: Final = 3


@dataclass(frozen=True, slots=True)
class MoveCommand:
    """Queued: a coordinated move to ``target_deg`` (joint order)."""

    target_deg: FloatArray
    speed_scale: float


@dataclass(frozen=True, slots=True)
class PathCommand:
    """Queued: a path through ``waypoints_deg`` (one row per waypoint)."""

    waypoints_deg: FloatArray
    speed_scale: float


@dataclass(frozen=True, slots=True)
class PlayCommand:
    """Queued: a path planned elsewhere, played as it is."""

    path: Path


@dataclass(frozen=True, slots=True)
class StopCommand:
    """Queued: a jerk-limited stop of the current motion (not a fault)."""


# Constructors of the messages built every cycle that set the slots directly (a frozen dataclass's own __init__ goes
# through object.__setattr__ for each field, several times slower); same objects, same equality.
_NEW_REQUEST: Final = frozen_builder(Request)
_NEW_POSITION: Final = frozen_builder(MultiTurnPositionSpeed)
_NEW_TORQUE: Final = frozen_builder(TorqueControl)
# The snapshot from its six fields in one tuple (what the named tuple's own constructor does, minus a call).
_SnapshotFields: TypeAlias = tuple[
    int, float, NDArray[np.float64], bool, float, float, str, MotionFault | None, int, int, float
]
_new_snapshot: Final[Callable[[_SnapshotFields], CycleSnapshot]] = functools.partial(tuple.__new__, CycleSnapshot)
_NEW_MULTI_TORQUE: Final = frozen_builder(MultiMotorTorque)


@dataclass(slots=True)
class Setpoints:
    """What the latest cycle commanded, per joint in joint order (a typed record of the batch's set-points).

    The builders update the arrays in place (no allocation per cycle); they are read in the loop's thread (cycle
    hooks, telemetry). Other threads read the published snapshot instead.

    Attributes:
        commanded: the latest cycle sent set-points (False while halted: reads only).
        motor_angle_deg: position mode: the 0xA4 targets, motor side, deg.
        max_speed_dps: position mode: their speed caps, motor side, deg/s.
        torque_nm: torque mode: the joint torque asked for (feed-forward + PD), before the current limit, N·m.
        limited: torque mode: the joints whose current was limited.
    """

    commanded: bool
    motor_angle_deg: FloatArray
    max_speed_dps: FloatArray
    torque_nm: FloatArray
    limited: NDArray[np.bool_]

    @classmethod
    def zeros(cls, n_joints: int) -> Setpoints:
        """Nothing commanded yet."""
        nan = np.full(n_joints, np.nan)
        return cls(False, nan.copy(), nan.copy(), np.zeros(n_joints), np.zeros(n_joints, dtype=bool))


#: A motion command waiting for the next cycle (a tagged union: each kind is its own class).
Pending: TypeAlias = MoveCommand | PathCommand | PlayCommand | StopCommand


class Controller:
    """Coordinated motion of several RMD joints on one bus.

    Args:
        specs: the axes, in joint order.
        transmission: joint <-> motor mapping, same order.
        limits: joint limits for planning.
        bus: the transport (its ``transact`` is called once per cycle).
        options: loop settings.
        feedforward: torque feed-forward for torque mode (None = zero).
        clock: time source (a ManualClock makes runs deterministic).
    """

    def __init__(
        self,
        specs: Sequence[AxisSpec],
        transmission: ArmTransmission,
        limits: JointLimits,
        bus: Transport,
        *,
        options: ControllerOptions,
        feedforward: Feedforward | None = None,
        clock: Clock | None = None,
    ) -> None:
        self.specs = tuple(specs)
        #: The joint <-> motor mapping of the configuration; :attr:`transmission` adds the turn offsets to it.
        self.base_transmission = transmission
        #: Whole motor turns per joint between this controller's frame and the drive's (:meth:`set_turns`).
        self.turns: tuple[int, ...] = (0,) * len(self.specs)
        self.options = options
        self.bus = bus
        self.planner = Planner(planning_limits(limits, options))
        self.feedforward = feedforward
        self.clock: Clock = clock if clock is not None else MonotonicClock()
        self.loop = FixedRateLoop(options.rate_hz, self.cycle, clock=self.clock)
        self.period_s = self.loop.period_s
        self.follower: Follower | None = None
        self.reference = State.at_rest(np.zeros(len(self.specs)))
        self.kp = np.array([s.kp_nm_per_deg for s in self.specs])
        self.kd = np.array([s.kd_nm_per_dps for s in self.specs])
        self.ids = tuple(s.motor_id for s in self.specs)
        #: What the drives' protocol family changes in control (:mod:`motion.control.family`).
        self.family = family = FAMILIES[bus.family]
        #: Where each joint should be at the latest measurement (the drives' or the PD loop's lag modelled).
        self.tracking = ExpectedTracking(
            options.mode, transmission, self.kp, self.kd, self.ids, read_drives=family.reads_loop_settings
        )
        # The fine angle read in every cycle's batch, for families whose motion replies lack it (empty: none).
        self._angle_reads = (
            [Request(i, family.bare(Command.READ_MULTI_TURN_ANGLE)) for i in self.ids]
            if family.angle_every_cycle
            else []
        )
        self._pending: Pending | None = None
        self.rejected: PlanningError | None = None
        self._lock = threading.Lock()
        self._idle = threading.Event()
        self._idle.set()
        self._stop_loop = False
        #: The set-points of the latest cycle (updated in place).
        self.setpoints = Setpoints.zeros(len(self.specs))
        self._zero = np.zeros(len(self.specs))
        n = len(self.specs)
        #: The arm after the latest cycle (replaced, never changed: any thread may read it without a lock).
        self.snapshot = CycleSnapshot(0, math.nan, frozen([np.zeros(n)] * len(JOINT_ROWS)), False)
        #: Called by the loop with each published snapshot, in its thread (a live view's feed: must never wait).
        self.publish_tap: Callable[[CycleSnapshot], None] | None = None
        # the arm's state and fault as the safety layer last set them (:meth:`set_condition`), and the lock that
        # keeps a transition from another thread and the loop's next snapshot from overwriting each other
        self._condition: tuple[str, MotionFault | None] = ("ready", None)
        self._publish_lock = threading.Lock()
        self.cycle_hooks: list[Callable[[Controller, float, list[Reply]], None]] = []
        #: The latest exchange's replies.
        self.last_replies: list[Reply] = []
        #: When the latest cycle's exchange went out, s: the drives sampled what they answered then (the collision
        #: observer steps between these instants, the tracking model runs from them: a late cycle is a longer step).
        self.exchanged_s = 0.0
        #: A per-joint array the safety layer keeps up to date (its collision signal, N·m), published in every
        #: snapshot as it stands (NaN: none).
        self.published_signal: NDArray[np.float64] = np.full(n, np.nan)
        self.published_limit: NDArray[np.float64] = np.full(n, np.nan)
        # The 0x280 frame commands motors 1..4 whether they belong to the arm or not, so it is used only when all
        # four are joints of this arm: a foreign drive on the bus is never switched into torque mode.
        in_multi = [i for i, s in enumerate(self.specs) if s.motor_id in MULTI_TORQUE_MOTOR_IDS]
        self._multi = (
            in_multi
            if options.mode is ControlMode.TORQUE
            and options.protocol is WireProtocol.CAN
            and options.multi_motor_frame
            and family.multi_torque_frame
            and len(in_multi) == len(MULTI_TORQUE_MOTOR_IDS)
            else []
        )
        self._single = [i for i in range(len(self.specs)) if i not in self._multi]
        # the joints of the 0x280 frame's four currents, in the frame's order (motors 1..4)
        self._multi_joints = sorted(self._multi, key=lambda i: MULTI_TORQUE_MOTOR_IDS.index(self.ids[i]))
        # Constant per cycle, looked up once: the 0xA4 speed cap's terms, per joint (motor id, motor deg per joint
        # deg, zero offset, floor), and the builder of the mode's batch.
        velocity_limit = np.abs(transmission.motor_rate(np.array(limits.velocity_dps)))
        self._speed_floor_dps = velocity_limit * options.speed_floor_share
        self._speed_limit_dps = velocity_limit
        self._drive_gear = np.array([s.drive_gear_ratio for s in self.specs], dtype=np.float64)
        self._speed_ceiling_dps = family.speed_ceiling_dps(options.protocol)
        self._speed_headroom = options.speed_headroom
        self._set_frame(transmission)
        self._reply_budget = options.reply_budget
        self._build: Callable[[State], list[Request]]
        match options.mode:
            case ControlMode.POSITION:
                self._build = self._position_requests
            case ControlMode.TORQUE:
                self._build = self._torque_requests
            case mode:  # never a default: an unknown mode is an error
                raise ValueError(f"unknown control mode {mode!r}")

    # ------------------------------------------------------------------------------------------------ start-up

    def _set_frame(self, transmission: ArmTransmission) -> None:
        """Use ``transmission`` for every angle read and every target sent (before :meth:`read_positions`)."""
        self.transmission = transmission
        self.axes = AxisStates(self.specs, transmission, self.family)
        # Per axis: motor id, motor deg per joint deg (as ArmTransmission has them), zero offset, speed floor, the
        # drive's degrees per motor degree (1, or 1 / its reduction where it takes output-shaft angles) and the speed
        # cap's ceiling in motor deg/s.
        self._position_axes = tuple(
            zip(
                self.ids,
                [t.direction * t.gear_ratio for t in transmission.transmissions],
                [t.zero_offset_deg for t in transmission.transmissions],
                self._speed_floor_dps.tolist(),
                [1.0 / s.drive_gear_ratio for s in self.specs],
                np.minimum(self._speed_ceiling_dps * self._drive_gear, self._speed_limit_dps).tolist(),
                strict=True,
            )
        )

    @property
    def angle_reads(self) -> list[Request]:
        """The reads every cycle's batch carries besides the set-points (0x92 per joint for the V3 family; else
        none): a copy."""
        return list(self._angle_reads)

    def set_turns(self, turns: Sequence[int]) -> None:
        """Keep ``turns`` whole motor turns per joint between this controller's frame and the drives' (see
        :mod:`motion.control.turns`); before :meth:`read_positions`, or again after a re-resolution (homing), then
        followed by it.

        Raises:
            MotionError: the loop is running (the frame of a running loop never changes).
        """
        if self.loop.running:
            raise MotionError("the turn offsets cannot change while the loop runs")
        self.turns = tuple(int(k) for k in turns)
        self._set_frame(self.base_transmission.with_turns(self.turns))

    def _read_every_drive(self, reads: Sequence[Message], timeout_s: float) -> list[Reply]:
        """``reads`` to every drive (before the loop runs), asked again of a drive that missed any of them, up to
        :data:`_READ_ATTEMPTS` times in all (a frame lost, a host that stalled longer than ``timeout_s``: a drive
        that answers the next time is no communication error); the replies, the latest of each drive that answered
        every read."""
        pending: list[int] = list(self.ids)
        taken: dict[int, list[Reply]] = {}
        for _ in range(_READ_ATTEMPTS):
            requests = [Request(motor_id, message) for motor_id in pending for message in reads]
            replies = self.bus.transact(requests, self.clock.now() + timeout_s)
            answered: dict[int, list[Reply]] = {}
            for reply in replies:
                answered.setdefault(reply.motor_id, []).append(reply)
            pending = []
            for motor_id, group in answered.items():
                if all(r.message is not None for r in group):
                    taken[motor_id] = group
                else:
                    pending.append(motor_id)
            if not pending:
                break
        return [reply for group in taken.values() for reply in group]

    def read_angles(self, timeout_s: float = 0.2) -> dict[int, float]:
        """Every drive's multi-turn reading (0x92), motor degrees in the drive's own frame, by motor id (an
        output-shaft reading times the drive's reduction).

        Raises:
            TransportError: a drive did not answer by ``timeout_s``.
        """
        replies = self._read_every_drive((self.family.bare(Command.READ_MULTI_TURN_ANGLE),), timeout_s)
        gear = {s.motor_id: s.drive_gear_ratio for s in self.specs}
        angles = {
            r.motor_id: r.message.angle_deg * gear[r.motor_id]
            for r in replies
            if isinstance(r.message, MultiTurnAngle) and r.motor_id in gear
        }
        missing = [s.name for s in self.specs if s.motor_id not in angles]
        if missing:
            raise TransportError(
                f"no reply to the multi-turn angle read (0x92) from joint(s) {', '.join(missing)}{self.bus.junk_note()}"
            )
        return angles

    def read_runtimes(self, timeout_s: float = 0.2) -> dict[int, float]:
        """Every drive's runtime (time since its power-on, 0xB1), s, by motor id, where the family tells it (empty
        where not: the older drives).

        Raises:
            TransportError: a drive did not answer by ``timeout_s``.
        """
        if not self.family.tells_runtime:
            return {}
        replies = self._read_every_drive((self.family.bare(CommandV3.READ_RUNTIME),), timeout_s)
        runtimes = {r.motor_id: r.message.runtime_ms / 1000.0 for r in replies if isinstance(r.message, Runtime)}
        missing = [s.name for s in self.specs if s.motor_id not in runtimes]
        if missing:
            raise TransportError(f"no reply to the runtime read (0xB1) from joint(s) {', '.join(missing)}")
        return runtimes

    def read_positions(self, timeout_s: float = 0.2) -> FloatArray:
        """Read every axis' multi-turn angle (0x92) and encoder (0x9C) and anchor the position tracking.

        Returns:
            The joint positions, degrees.

        Raises:
            TransportError: a drive did not answer both requests by ``timeout_s``.
        """
        family = self.family
        reads = (family.bare(Command.READ_MULTI_TURN_ANGLE), family.bare(Command.READ_STATUS_2))
        replies = self._read_every_drive(reads, timeout_s)
        angles: dict[int, float] = {}
        states: dict[int, Message] = {}
        for reply in replies:
            if isinstance(reply.message, MultiTurnAngle):
                angles[reply.motor_id] = reply.message.angle_deg
            elif isinstance(reply.message, family.state_type):
                states[reply.motor_id] = reply.message
        missing = [s.name for s in self.specs if s.motor_id not in angles or s.motor_id not in states]
        if missing:
            raise TransportError(
                f"no reply to the start-up reads from joint(s) {', '.join(missing)}{self.bus.junk_note()}"
            )
        now = self.clock.now()
        for i, spec in enumerate(self.specs):
            state = states[spec.motor_id]
            # (a motion reply without an encoder: the V3 family's angle comes from 0x92 in every cycle)
            encoder = state.encoder if isinstance(state, MotorState) else 0
            self.axes.initialise(i, angles[spec.motor_id] * spec.drive_gear_ratio, encoder)
            self.axes.update(i, state, now)
        q = self.axes.positions()
        self.follower = Follower(self.planner, q)
        self.reference = State.at_rest(q)
        if self.options.protocol is WireProtocol.RS485:
            # An RS485 exchange takes as long as a set-point's: no room in a cycle's batch (on CAN the reads ride at
            # the end of the first cycles' batches, a quarter of a millisecond each, and connecting takes no longer).
            self.tracking.read_now(self.bus, self.clock.now() + timeout_s)
        self.tracking.reset(q, self.axes.qd_dps)
        self._publish(0, now, False)  # what was read, before the first cycle
        return q

    # ------------------------------------------------------------------------------------------------ commands

    def _queue(self, pending: Pending) -> None:
        if self.follower is None:
            raise MotionError("read_positions() must run before motion commands")
        with self._lock:
            self._pending = pending
            self._idle.clear()

    def move_to(self, target_deg: Sequence[float] | FloatArray, speed_scale: float = 1.0) -> None:
        """Queue a coordinated move to ``target_deg`` (re-targets a running move). Checked before it is queued.

        Raises:
            PlanningError: the target or the scale is invalid (nothing is queued).
        """
        target = np.asarray(target_deg, dtype=np.float64)
        # planned once from the reference at rest (the loop plans from the live state when it applies it): the
        # vector, the limits, the scale and whatever Ruckig refuses (a duration beyond its limits) are refused here
        scale = self.planner.check_scale(speed_scale)
        self.planner.move(State.at_rest(self.reference.position), target, speed_scale=scale)
        self._queue(MoveCommand(target, scale))

    def follow(self, waypoints_deg: Sequence[Sequence[float]] | FloatArray, speed_scale: float = 1.0) -> None:
        """Queue a waypoint path from the current reference, planned once from it at rest first (as :meth:`move_to`).

        Raises:
            PlanningError: a waypoint or the scale is invalid (nothing is queued).
        """
        scale = self.planner.check_scale(speed_scale)
        self.planner.path(State.at_rest(self.reference.position), waypoints_deg, speed_scale=scale)
        self._queue(PathCommand(np.asarray(waypoints_deg, dtype=np.float64), scale))

    def play(self, path: Path) -> None:
        """Queue a path planned elsewhere; it must start at the reference of the cycle that applies it."""
        self._queue(PlayCommand(path))

    def stop_motion(self) -> None:
        """Queue a jerk-limited stop; the arm then holds where the stop ends."""
        self._queue(StopCommand())

    def wait_idle(self, timeout_s: float | None = None) -> bool:
        """Wait until the queued motion has ended; returns False on timeout."""
        if self.loop.stepping:
            return self.loop.step_until(self._idle.is_set, timeout_s)
        return self._idle.wait(timeout_s)

    @property
    def idle(self) -> bool:
        """True when no motion is queued or playing (never waits)."""
        return self._idle.is_set()

    # ------------------------------------------------------------------------------------------------ the cycle

    def discard_pending(self) -> None:
        """Drop a queued motion command (a halt must not be overridden by a move queued in the same cycle)."""
        with self._lock:
            self._pending = None

    def take_rejection(self) -> PlanningError | None:
        """The PlanningError of the last queued command that could not be planned from the live reference, once."""
        with self._lock:
            error, self.rejected = self.rejected, None
        return error

    def _apply_pending(self, t_s: float) -> None:
        with self._lock:
            pending, self._pending = self._pending, None
        if pending is None or self.follower is None:
            return
        try:
            self._plan_pending(pending, t_s)
        except PlanningError as exc:
            # Not plannable from the live reference (e.g. a re-target whose stop would overshoot a limit): the
            # current motion goes on and the caller hears of it through take_rejection().
            with self._lock:
                self.rejected = exc
            if not self.follower.moving:
                self._idle.set()

    def _plan_pending(self, pending: Pending, t_s: float) -> None:
        follower = self.follower
        if follower is None:
            raise MotionError("read_positions() must run before the loop starts")
        match pending:
            case MoveCommand(target, speed_scale):
                follower.move_to(t_s, target, speed_scale=speed_scale)
            case PathCommand(waypoints, speed_scale):
                follower.follow(t_s, waypoints, speed_scale=speed_scale)
            case PlayCommand(path):
                follower.play(path, t_s)
            case StopCommand():
                follower.stop(t_s)
            case other:  # never a default: an unknown command is an error
                raise TypeError(f"unknown motion command {other!r}")

    def build_requests(self, reference: State) -> list[Request]:
        """The cycle's batch for a reference state (pure apart from recording the set-points)."""
        return self._build(reference)

    @property
    def torque_nm(self) -> FloatArray:
        """Torque mode: the joint torque the latest cycle asked for, N·m (see :class:`Setpoints`)."""
        return self.setpoints.torque_nm

    @property
    def limited(self) -> NDArray[np.bool_]:
        """Torque mode: the joints whose current the latest cycle limited."""
        return self.setpoints.limited

    def _position_requests(self, ref: State) -> list[Request]:
        # Python floats per joint: for a few joints a numpy call costs more than the arithmetic. The operations and
        # their order are those of ArmTransmission.motor_deg / motor_rate, so the results are the same float64s.
        # An output-shaft drive takes the motor-side values divided by its reduction (the factor is 1.0 otherwise:
        # the same float64s).
        headroom = self._speed_headroom
        new_request, new_position = _NEW_REQUEST, _NEW_POSITION
        angles: list[float] = []
        caps: list[float] = []
        requests: list[Request] = []
        for (motor_id, motor_per_joint, offset_deg, floor_dps, to_drive, ceiling), q_deg, qd_dps in zip(
            self._position_axes, ref.position.tolist(), ref.velocity.tolist(), strict=True
        ):
            angle = (q_deg - offset_deg) * motor_per_joint
            cap = min(abs(qd_dps * motor_per_joint) * headroom + floor_dps, ceiling)
            angles.append(angle)
            caps.append(cap)
            requests.append(new_request(motor_id, new_position(angle * to_drive, cap * to_drive)))
        record = self.setpoints
        record.motor_angle_deg[:] = angles
        record.max_speed_dps[:] = caps
        return requests

    def _torque_requests(self, ref: State) -> list[Request]:
        # PD plus the feed-forward, per joint, in Python floats (for a few joints a numpy call costs more than the
        # arithmetic).
        axes = self.axes
        torques = self._pd_torques(ref)
        if self.feedforward is not None:
            feedforward_list = self.feedforward(axes.q_deg, ref.velocity, ref.acceleration).tolist()
            torques = [tau + ff for tau, ff in zip(torques, feedforward_list, strict=True)]
        return self.torque_frames(torques)

    def _pd_torques(self, ref: State) -> list[float]:
        axes = self.axes
        return [
            kp * (q_ref - q) + kd * (qd_ref - qd)
            for kp, kd, q_ref, q, qd_ref, qd in zip(
                self.kp.tolist(),
                self.kd.tolist(),
                ref.position.tolist(),
                axes.q_deg.tolist(),
                ref.velocity.tolist(),
                axes.qd_dps.tolist(),
                strict=True,
            )
        ]

    def torque_frames(self, torques: Sequence[float]) -> list[Request]:
        """The torque-current requests (0xA1, and 0x280 where it applies) for joint torques (N·m, joint order),
        limited per joint; records the torque and the limiting."""
        record = self.setpoints
        record.torque_nm[:] = torques
        raw, limited = self.transmission.iq_raw_limited_list(torques)
        record.limited[:] = limited
        return self._current_requests([iq_amps(r) for r in raw])

    def _current_requests(self, currents: list[float]) -> list[Request]:
        """0xA1 requests of the joints on their own, and the 0x280 frame of motors 1..4 where it applies."""
        ids, new_request, new_torque = self.ids, _NEW_REQUEST, _NEW_TORQUE
        requests = [new_request(ids[i], new_torque(currents[i])) for i in self._single]
        if self._multi:
            frame = _NEW_MULTI_TORQUE(*[currents[i] for i in self._multi_joints])
            requests.append(new_request(MULTI_TORQUE_MOTOR_IDS[0], frame))
        return requests

    def absorb(self, replies: Sequence[Reply]) -> None:
        """Update the axis states from a cycle's replies."""
        self.axes.absorb(replies)

    def step(
        self,
        start_s: float,
        deadline_s: float,
        *,
        extra: Sequence[Request] = (),
        check: Callable[[State], None] | None = None,
        command: bool = True,
        apply_pending: bool = True,
    ) -> list[Reply]:
        """The work of one cycle: apply a queued command, sample the reference for ``deadline_s``, build the batch
        (plus ``extra`` requests), exchange it, absorb the replies.

        Args:
            start_s: the cycle's scheduled start.
            deadline_s: the next cycle's start (the set-point is for this instant).
            extra: requests appended to the batch (status reads).
            check: called with the reference before anything is sent; raising stops the cycle before the send.
            command: False sends only ``extra`` (no motion set-points), e.g. while halted.
            apply_pending: False leaves a queued motion command queued (while halted nothing new may start).

        Returns:
            The cycle's replies.
        """
        follower = self.follower
        if follower is None:
            raise MotionError("read_positions() must run before the loop starts")
        if apply_pending and self._pending is not None:
            self._apply_pending(start_s)
        self.reference = ref = follower.sample(deadline_s)
        if check is not None:
            check(ref)
        requests = self._build(ref) if command else []
        self.setpoints.commanded = command
        if extra:
            requests.extend(extra)
        if self.tracking.unread:  # the drives' loop settings, last in the first cycles' batches
            requests.extend(self.tracking.next_reads())
        replies = self._exchange(requests, start_s, deadline_s, command)
        if not follower.moving and self._pending is None and not self._idle.is_set():
            self._idle.set()  # (Event.set takes a lock and notifies: not again every cycle of a hold)
        return replies

    def _exchange(self, requests: list[Request], start_s: float, deadline_s: float, commanded: bool) -> list[Reply]:
        if self._angle_reads:
            requests.extend(self._angle_reads)
        self.exchanged_s = sent_s = self.clock.now()
        replies = self.bus.transact(requests, start_s + self._reply_budget * (deadline_s - start_s))
        if self.tracking.unread:
            replies = self.tracking.take_replies(replies)
        self.last_replies = replies  # (for a caller whose cycle a hook below ends with an exception)
        self.absorb(replies)
        self._track(max(start_s, sent_s), self.reference, commanded)
        self._publish(self.loop.cycles + 1, start_s, commanded)  # (the loop counts the cycle once it has ended)
        for hook in self.cycle_hooks:
            hook(self, start_s, replies)
        return replies

    def _track(self, start_s: float, ref: State, commanded: bool) -> None:
        """The expected angles at this cycle's measurement, then the model takes this cycle's set-points."""
        tracking, axes = self.tracking, self.axes
        tracking.advance(start_s, axes.q_deg, axes.qd_dps)
        if not commanded:
            tracking.stop_commanding()
            return
        caps = self.setpoints.max_speed_dps if self.options.mode is ControlMode.POSITION else None
        tracking.command(start_s, ref.position, ref.velocity, ref.acceleration, caps)

    def comply_step(
        self, start_s: float, deadline_s: float, gravity: Feedforward, *, extra: Sequence[Request] = ()
    ) -> list[Reply]:
        """A cycle that yields (torque mode, the ``comply`` reaction to a collision): gravity compensation alone,
        ``g(q)`` at the measured angles with zero gains, so that the arm holds itself up and a push moves it. The
        reference is the measured position at rest (the stop path is dropped), where a ``clear()`` holds the arm.

        Args:
            start_s: the cycle's scheduled start.
            deadline_s: the next cycle's start.
            gravity: ``(q_deg, qd_dps, qdd_dps2) -> tau_nm``, gravity alone.
            extra: requests appended to the batch (status reads).

        Raises:
            MotionError: the controller is not in torque mode (a position stream cannot yield).
        """
        if self.options.mode is not ControlMode.TORQUE:
            raise MotionError("comply needs torque mode")
        axes = self.axes
        self.reference = State.at_rest(axes.q_deg.copy())
        if self.follower is not None:
            self.follower.hold_at(self.reference.position)
        requests = self.torque_frames(gravity(axes.q_deg, self._zero, self._zero).tolist())
        self.setpoints.commanded = True
        requests.extend(extra)
        return self._exchange(requests, start_s, deadline_s, True)

    def _publish(self, cycle: int, start_s: float, commanded: bool) -> None:
        """Replace :attr:`snapshot` with this cycle's (one stacked copy: the loop never waits on a reader)."""
        axes, follower, loop = self.axes, self.follower, self.loop
        path = follower.path if follower is not None else None
        end = follower.end_time() if follower is not None and path is not None else math.nan
        joints = frozen(
            (
                axes.q_deg,
                axes.qd_dps,
                self.reference.position,
                axes.iq_a,
                axes.temperature_c,
                axes.fresh,
                self.tracking.expected_deg,
                self.published_signal,
                self.published_limit,
            )
        )
        start = end - path.duration_s if path is not None else math.nan
        with self._publish_lock:
            state, fault = self._condition
            self.snapshot = _new_snapshot(
                (
                    cycle,
                    start_s,
                    joints,
                    commanded,
                    start,
                    end,
                    state,
                    fault,
                    loop.overruns,
                    loop.skipped_cycles,
                    loop.wake_jitter_s,
                )
            )
        tap = self.publish_tap
        if tap is not None:
            tap(self.snapshot)

    def set_condition(self, state: str, fault: MotionFault | None) -> None:
        """The arm's state and fault changed (the safety layer's transition, in any thread): publish them at once in
        a copy of the latest snapshot, and in every snapshot from now on."""
        with self._publish_lock:
            self._condition = (state, fault)
            self.snapshot = self.snapshot._replace(state=state, fault=fault)

    def cycle(self, k: int, start_s: float, deadline_s: float) -> bool:
        """One unguarded control cycle (the scheduler calls it at ``start_s``); see :mod:`motion.safety` for the
        guarded one."""
        self.step(start_s, deadline_s)
        return not self._stop_loop

    def rehearse(self, replies: list[Reply], now_s: float) -> None:
        """The host's work of one cycle at rest on ``replies`` (a measuring exchange's), with nothing sent: the
        reference sampled where the arm holds, the set-points built (in torque mode with the feed-forward), the replies
        absorbed, the tracking model stepped and the snapshot published. The rate check times it; :meth:`start`
        restarts the tracking model from where the arm is.

        Raises:
            MotionError: :meth:`read_positions` has not run.
        """
        follower = self.follower
        if follower is None:
            raise MotionError("read_positions() must run before the rate check")
        self.reference = ref = follower.sample(now_s)
        self._build(ref)
        self.exchanged_s = now_s
        self.absorb(replies)
        self._track(now_s, ref, True)
        self._publish(self.loop.cycles, now_s, False)

    # ------------------------------------------------------------------------------------------------ loop

    def start(self, cycle: CycleFn | None = None) -> None:
        """Run the loop in its own thread (after :meth:`read_positions`).

        Args:
            cycle: the cycle function to run instead of :meth:`cycle` (a safety supervisor's guarded cycle).
        """
        self._stop_loop = False
        # what the rate check's rehearsals taught the model is not the loop's history
        self.tracking.reset(self.axes.q_deg, self.axes.qd_dps, self.reference.position)
        if cycle is not None:
            self.loop = FixedRateLoop(self.options.rate_hz, cycle, clock=self.clock)
        if is_simulated(self.clock):
            self.loop.begin_stepping()
        else:
            self.loop.start()

    def wait_for(self, done: Callable[[], bool], timeout_s: float | None = None) -> bool:
        """Wait until ``done()`` holds or ``timeout_s`` passes; returns ``done()``.

        With a simulated clock the waiting thread runs the control cycles itself (``timeout_s`` is simulated time);
        otherwise it polls while the loop thread runs.
        """
        if self.loop.stepping:
            return self.loop.step_until(done, timeout_s)
        end = None if timeout_s is None else time.monotonic() + timeout_s
        while not done():
            if end is not None and time.monotonic() >= end:
                return done()
            time.sleep(_POLL_S)
        return True

    def pause(self, duration_s: float) -> None:
        """Let ``duration_s`` pass with the loop running (simulated time advances; real time sleeps)."""
        if self.loop.stepping:
            end = self.clock.now() + duration_s
            self.loop.step_until(_never, duration_s)
            self.clock.sleep_until(end)  # time passes for the drives also after the loop has ended
        else:
            time.sleep(duration_s)

    @property
    def stopping(self) -> bool:
        """True once :meth:`shutdown` asked the loop to end."""
        return self._stop_loop

    def shutdown(self, timeout_s: float = 2.0) -> LoopStatistics:
        """End the loop after the current cycle and wait for it; returns the loop statistics."""
        self._stop_loop = True
        self.loop.stop()
        self.loop.join(timeout_s)
        return self.loop.statistics()

    @property
    def error(self) -> BaseException | None:
        """The exception that ended the loop, if any."""
        return self.loop.error

    def reference_path(self) -> Path | None:
        """The path being played, if any."""
        return self.follower.path if self.follower is not None else None
