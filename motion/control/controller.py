"""The controller: one cycle = take the replies -> update state -> plan the next set-point -> build the batch ->
one ``transact`` by the deadline.

The set-points of each control mode are built by its builder (:mod:`motion.control.setpoints`); the motion commands
other threads give are :class:`~motion.control.commands.MotionCommands`, starting and waiting on the loop
:class:`~motion.control.running.LoopRunning`.

Motion commands (:meth:`Controller.move_to`, :meth:`Controller.follow`, :meth:`Controller.stop_motion`) may come from
any thread: they are queued and planned in the control thread at the start of the next cycle, from the reference at
that instant, so a new target never steps the reference's velocity or acceleration.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from motion.config.schema import ControlMode
from motion.control.axes import AxisSpec, AxisStates
from motion.control.clock import Clock, MonotonicClock
from motion.control.commands import CommandQueue, MotionCommands, planning_limits
from motion.control.family import FAMILIES, STATE_TYPES, DriveFamily
from motion.control.running import LoopRunning
from motion.control.scheduler import FixedRateLoop
from motion.control.setpoints import BuilderSettings, Feedforward, Setpoints, TorqueSetpoints, setpoint_builder
from motion.control.snapshot import CycleSnapshot, SnapshotPublisher
from motion.control.startup import read_every_drive, silent_drives
from motion.control.tracking import ExpectedTracking
from motion.errors import MotionError
from motion.protocol import (
    Command,
    Message,
    MotorState,
    MultiTurnAngle,
    WireProtocol,
)
from motion.protocol.table import split_address
from motion.trajectory import Follower, JointLimits, Path, Planner, State
from motion.transmission import ArmTransmission, FloatArray
from motion.transport.base import Reply, Request, Transport

__all__ = ["Controller", "ControllerOptions", "Feedforward", "Setpoints"]


@dataclass(frozen=True, slots=True)
class ControllerOptions:
    """Settings of the control loop.

    Attributes:
        mode: position or torque streaming.
        rate_hz: control rate, Hz.
        wires: the wire protocol of each bus, by the bus index of the drives' addresses (each bus's decides the 0xA4
            speed cap's ceiling, the use of 0x280 and how many status reads its cycle carries).
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
    wires: tuple[WireProtocol, ...] = (WireProtocol.CAN,)
    speed_headroom: float = 1.5
    speed_floor_share: float = 0.1
    catch_up_share: float = 0.1
    reply_budget: float = 0.8
    multi_motor_frame: bool = True


class Controller(MotionCommands, LoopRunning):
    """Coordinated motion of several RMD joints on one bus.

    Args:
        specs: the axes, in joint order.
        transmission: joint <-> motor mapping, same order.
        limits: joint limits for planning.
        bus: the transport (its ``transact`` is called once per cycle).
        options: loop settings.
        feedforward: torque feed-forward for torque mode (None = zero).
        clock: time source (a ManualClock makes runs deterministic).

    Raises:
        ValueError: ``options.wires`` names no wire for a bus the axes' addresses are on.
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
        buses = max(split_address(s.motor_id)[0] for s in self.specs) + 1 if self.specs else 1
        if len(options.wires) < buses:
            raise ValueError(
                f"ControllerOptions.wires: {len(options.wires)} wire(s) for axes on {buses} buses (one per bus, by the "
                "bus index of their addresses)"
            )
        #: The joint <-> motor mapping of the configuration; :attr:`transmission` adds the turn offsets to it.
        self.base_transmission = transmission
        #: Whole motor turns per joint between this controller's frame and the drive's (:meth:`set_turns`).
        self.turns: tuple[int, ...] = (0,) * len(self.specs)
        self.options = options
        self.rate_hz = options.rate_hz
        self.bus = bus
        #: The joints' limits as configured (the planner's leave position mode's catch-up room free).
        self.limits = limits
        self.planner = Planner(planning_limits(limits, options.mode, options.catch_up_share))
        self.feedforward = feedforward
        self.clock: Clock = clock if clock is not None else MonotonicClock()
        self.loop = FixedRateLoop(options.rate_hz, self.cycle, clock=self.clock)
        self.period_s = self.loop.period_s
        self.follower: Follower | None = None
        self.reference = State.at_rest(np.zeros(len(self.specs)))
        self.kp = np.array([s.kp_nm_per_deg for s in self.specs])
        self.kd = np.array([s.kd_nm_per_dps for s in self.specs])
        self.ids = tuple(s.motor_id for s in self.specs)
        #: What each axis' drive's protocol family changes in control (:mod:`motion.control.family`), joint order
        #: (the drives of an arm's buses may be of both families, one per bus).
        self.families = families = tuple(FAMILIES[bus.family_of(i)] for i in self.ids)
        self._family_of = dict(zip(self.ids, families, strict=True))
        #: Where each joint should be at the latest measurement (the drives' or the PD loop's lag modelled).
        self.tracking = ExpectedTracking(
            options.mode,
            transmission,
            self.kp,
            self.kd,
            self.ids,
            read_drives=[f.reads_loop_settings for f in families],
        )
        # The fine angle read in every cycle's batch, for the axes whose motion replies lack it (empty: none).
        self._angle_reads = [
            self.bare_request(i, Command.READ_MULTI_TURN_ANGLE)
            for i, f in zip(self.ids, families, strict=True)
            if f.angle_every_cycle
        ]
        self.commands = CommandQueue()
        self._stop_loop = False
        #: The set-points of the latest cycle (updated in place).
        self.setpoints = Setpoints.zeros(len(self.specs))
        self._zero = np.zeros(len(self.specs))
        n = len(self.specs)
        #: What the loop publishes after every cycle (:mod:`motion.control.snapshot`).
        self.publisher = SnapshotPublisher(n)
        self.cycle_hooks: list[Callable[[Controller, float, list[Reply]], None]] = []
        #: The latest exchange's replies.
        self.last_replies: list[Reply] = []
        #: When the latest cycle's exchange went out, s: the drives sampled what they answered then (the collision
        #: observer steps between these instants, the tracking model runs from them: a late cycle is a longer step).
        self.exchanged_s = 0.0
        velocity_limit = np.abs(transmission.motor_rate(np.array(limits.velocity_dps)))
        self._velocity_limit_motor_dps = velocity_limit.tolist()
        # 0x92 to an axis whose tracked turns are not sure (AxisStates.unanchored), by joint
        self._turn_reads = [self.bare_request(i, Command.READ_MULTI_TURN_ANGLE) for i in self.ids]
        #: The set-points of the mode (:mod:`motion.control.setpoints`).
        self.builder = setpoint_builder(
            options.mode,
            BuilderSettings(
                self.specs,
                families,
                options.wires,
                velocity_limit,
                options.speed_headroom,
                options.speed_floor_share,
                self.kp,
                self.kd,
                feedforward,
                options.multi_motor_frame,
                self.setpoints,
            ),
        )
        self._set_frame(transmission)
        self._reply_budget = options.reply_budget

    # ------------------------------------------------------------------------------------------------ start-up

    def _set_frame(self, transmission: ArmTransmission) -> None:
        """Use ``transmission`` for every angle read and every target sent (before :meth:`read_positions`)."""
        self.transmission = transmission
        self.axes = AxisStates(self.specs, transmission, self.families, self._velocity_limit_motor_dps)
        self.builder.set_frame(transmission, self.axes)

    def family_of(self, address: int) -> DriveFamily:
        """The family of the drive at ``address`` (one of :attr:`ids`)."""
        return self._family_of[address]

    def bare_request(self, address: int, code: int) -> Request:
        """The request without data for ``code`` (0x80, 0x81, 0x92, 0x9A, 0x9C, ...) to the drive at ``address``,
        in its family's protocol."""
        return Request(address, self._family_of[address].bare(code))

    def turn_reads(self, now_s: float, window_s: float) -> list[Request]:
        """The 0x92 reads an exchange sent at ``now_s`` whose replies come within ``window_s`` must carry: one to each
        axis whose tracked turns are not sure then (:meth:`AxisStates.unanchored`: a drive that went unheard, a
        gap in its replies longer than its velocity limit unwraps); usually none."""
        return [self._turn_reads[i] for i in self.axes.unanchored(now_s + window_s)]

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

    def read_positions(self, timeout_s: float = 0.2) -> FloatArray:
        """Read every axis' multi-turn angle (0x92) and encoder (0x9C) and anchor the position tracking.

        Returns:
            The joint positions, degrees.

        Raises:
            TransportError: a drive did not answer both requests by ``timeout_s``.
        """
        replies = read_every_drive(self, (Command.READ_MULTI_TURN_ANGLE, Command.READ_STATUS_2), timeout_s)
        angles: dict[int, float] = {}
        states: dict[int, Message] = {}
        for reply in replies:
            if isinstance(reply.message, MultiTurnAngle):
                angles[reply.motor_id] = reply.message.angle_deg
            elif isinstance(reply.message, STATE_TYPES):
                states[reply.motor_id] = reply.message
        if len(angles.keys() & states.keys()) < len(self.specs):
            raise silent_drives(self, "start-up reads", angles.keys() & states.keys(), self.bus.junk_note())
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
        if WireProtocol.RS485 in self.options.wires:
            # An RS485 exchange takes as long as a set-point's: no room in a cycle's batch (on CAN the reads ride at
            # the end of the first cycles' batches, a quarter of a millisecond each, and connecting takes no longer;
            # an arm with an RS485 line among its buses reads them all now).
            self.tracking.read_now(self.bus, self.clock.now() + timeout_s)
        self.tracking.reset(q, self.axes.qd_dps)
        self._publish(0, now, False)  # what was read, before the first cycle
        return q

    # ------------------------------------------------------------------------------------------------ the cycle

    def build_requests(self, reference: State) -> list[Request]:
        """The cycle's batch for a reference state (pure apart from recording the set-points)."""
        return self.builder.build(reference)

    @property
    def torque_nm(self) -> FloatArray:
        """Torque mode: the joint torque the latest cycle asked for, N·m (see :class:`Setpoints`)."""
        return self.setpoints.torque_nm

    @property
    def limited(self) -> NDArray[np.bool_]:
        """Torque mode: the joints whose current the latest cycle limited."""
        return self.setpoints.limited

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
        if apply_pending and self.commands.waiting:
            self.commands.apply(follower, start_s)
        self.reference = ref = follower.sample(deadline_s)
        if check is not None:
            check(ref)
        requests = self.builder.build(ref) if command else []
        self.setpoints.commanded = command
        if extra:
            requests.extend(extra)
        if self.tracking.unread:  # the drives' loop settings, last in the first cycles' batches
            requests.extend(self.tracking.next_reads())
        replies = self._exchange(requests, start_s, deadline_s, command)
        self.commands.settle(follower)
        return replies

    def _exchange(self, requests: list[Request], start_s: float, deadline_s: float, commanded: bool) -> list[Reply]:
        if self._angle_reads:
            requests.extend(self._angle_reads)
        self.exchanged_s = sent_s = self.clock.now()
        reply_by_s = start_s + self._reply_budget * (deadline_s - start_s)
        requests.extend(self.turn_reads(sent_s, reply_by_s - sent_s))
        replies = self.bus.transact(requests, reply_by_s)
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
        tracking.command(start_s, ref.position, ref.velocity, ref.acceleration, self.builder.tracking_caps())

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
        builder = self.builder
        if not isinstance(builder, TorqueSetpoints):
            raise MotionError("comply needs torque mode")
        axes = self.axes
        self.reference = State.at_rest(axes.q_deg.copy())
        if self.follower is not None:
            self.follower.hold_at(self.reference.position)
        requests = builder.torque_frames(gravity(axes.q_deg, self._zero, self._zero).tolist())
        self.setpoints.commanded = True
        requests.extend(extra)
        return self._exchange(requests, start_s, deadline_s, True)

    def _publish(self, cycle: int, start_s: float, commanded: bool) -> None:
        axes, follower, loop = self.axes, self.follower, self.loop
        path = follower.path if follower is not None else None
        end = follower.end_time() if follower is not None and path is not None else math.nan
        start = end - path.duration_s if path is not None else math.nan
        rows = (axes.q_deg, axes.qd_dps, self.reference.position, axes.iq_a, axes.temperature_c, axes.fresh)
        self.publisher.publish(
            cycle,
            start_s,
            (*rows, self.tracking.expected_deg),
            commanded,
            (start, end),
            (loop.overruns, loop.skipped_cycles, loop.wake_jitter_s),
        )

    @property
    def snapshot(self) -> CycleSnapshot:
        """The arm after the latest cycle (:attr:`SnapshotPublisher.snapshot`)."""
        return self.publisher.snapshot

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
        self.builder.build(ref)
        self.exchanged_s = now_s
        self.absorb(replies)
        self._track(now_s, ref, True)
        self._publish(self.loop.cycles, now_s, False)

    def reference_path(self) -> Path | None:
        """The path being played, if any."""
        return self.follower.path if self.follower is not None else None
