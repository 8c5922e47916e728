"""Where each joint should be now: a model of how the drives follow the stream, for the following-error check.

The reference is where the planner wants the arm; no real joint is there. In position mode the drive's own position
loop trails the 0xA4 stream (by speed / loop gain at low speed, and by the braking distance of its acceleration limit,
``speed² / (2 a)``, at high speed); in torque mode the controller's PD loop trails a reference whose inertia is not fed
forward. :class:`ExpectedTracking` runs a small per-joint model of that loop alongside the real one, driven by the
same commands, and gives the *expected* joint angle; the watchdog compares the measured angle with it, so that a fault
threshold means "this far from where the arm should be now" whatever the speed and the drive's tuning.

Position mode (per joint, joint side, the drive's loop as the documents and the drives describe it): the speed the
drive asks for is ``min(angle_gain × |error|, sqrt(2 a |error|), max_speed)`` toward the 0xA4 target, slewed at the
acceleration limit ``a`` (0x33, 0 = none), where ``angle_gain`` comes from the angle-loop gain read with 0x30
(:data:`ANGLE_GAIN_PER_S_PER_UNIT` per unit: the documents give no scale, so it is a prior that identification
replaces, see :func:`identify_position_loop`) and ``max_speed`` is the cap the controller sent. The speed loop under
it is taken as ideal.

Torque mode: the controller's own law (PD on the reference for the set-point instant, plus the share of the
inertia the feed-forward covers) applied to a rigid joint of the given inertia, gravity cancelled by the feed-forward,
the torque held over the period as the drives hold it. Without an inertia the model expects the reference.

The model steps from one cycle's start to the next with the command that cycle sent (skipped cycles are integrated
over); it is reset to the measured state whenever no set-points are streamed (halted) and at every (re)start. All
arrays are preallocated: a cycle allocates nothing.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from motion.config.schema import ControlMode
from motion.protocol import Acceleration, Bare, Command, PidGains
from motion.transmission import ArmTransmission, FloatArray
from motion.transport.base import Reply, Request, Transport

#: Angle-loop gain per unit of the 0x30 ``angle_kp``: speed asked for (deg/s) per degree of angle error, 1/s. The
#: documents give no physical scale; this is the one the project's emulated drives use, a prior for real drives.
ANGLE_GAIN_PER_S_PER_UNIT = 0.5
#: Longest integration step of the position-loop model, s (2 ms would halve the cost and raise the model's error on
#: arm6 at full speed from 0.42 to 0.65 deg at most, and bias the identification).
MAX_STEP_S = 0.001
#: Times a drive is asked for its loop settings (0x30, 0x33) before the prior is kept.
READ_ATTEMPTS = 3
_READS = (Command.READ_PID, Command.READ_ACCELERATION)
#: Torque mode: the mass matrix is evaluated again once a joint has moved this far, deg.
INERTIA_STEP_DEG = 5.0
_RAD_PER_DEG = math.pi / 180.0
_DEG_PER_RAD = 180.0 / math.pi
#: A drive whose acceleration limit reads 0 has none; the model then uses this (deg/s², joint side).
_NO_LIMIT = 1e12


@dataclass(frozen=True, slots=True)
class PositionLoop:
    """The position loop of one drive, joint side.

    Attributes:
        angle_gain_per_s: speed asked for per degree of angle error, 1/s.
        acceleration_dps2: the drive's acceleration limit, joint side, deg/s² (``inf``: none).
    """

    angle_gain_per_s: float
    acceleration_dps2: float

    @classmethod
    def from_drive(cls, gains: PidGains, acceleration: Acceleration | None, gear_ratio: float) -> PositionLoop:
        """The prior from the drive's 0x30 gains and 0x33 acceleration (motor side; converted through the gear)."""
        accel = acceleration.acceleration_dps2 if acceleration is not None else 0
        return cls(
            angle_gain_per_s=max(gains.angle_kp, 1) * ANGLE_GAIN_PER_S_PER_UNIT,
            acceleration_dps2=accel / gear_ratio if accel > 0 else math.inf,
        )


class ExpectedTracking:
    """The expected joint angles of one arm under its control loop (see the module docstring).

    Args:
        mode: the control mode (position: the drives' loops; torque: the controller's PD).
        transmission: the joints' transmissions (gear ratios and torque limits).
        kp_nm_per_deg: torque mode: the PD stiffness per joint.
        kd_nm_per_dps: torque mode: the PD damping per joint.
        ids: the motor ids, in joint order.
        read_drives: read each drive's loop settings (0x30, 0x33) in the first cycles; False keeps the prior until an
            identification is offered (drives of a family without those shapes); a sequence: per joint.

    Attributes:
        expected_deg: where each joint should be at the latest cycle's measurement, deg (read-only between cycles).
        expected_dps: its expected speed, deg/s.
        lag_deg: the model's lag behind the reference of the previous cycle at that instant, deg.
        enabled: False expects the reference itself (no lag: the check as it was before the model).
    """

    def __init__(
        self,
        mode: ControlMode,
        transmission: ArmTransmission,
        kp_nm_per_deg: FloatArray,
        kd_nm_per_dps: FloatArray,
        ids: Sequence[int],
        *,
        read_drives: bool | Sequence[bool] = True,
    ) -> None:
        n = len(transmission)
        if mode.traits.drive_position_loop == mode.traits.host_torque:
            raise ValueError(
                f"the tracking models know the drive's position loop and the host's torque loop, not {mode}"
            )
        self.mode = mode
        self._host_torque, self._drive_loop = mode.traits.host_torque, mode.traits.drive_position_loop  # (per cycle)
        self.n = n
        self.gear_ratio = np.array([abs(t.gear_ratio) for t in transmission.transmissions])
        self.kp = np.asarray(kp_nm_per_deg, dtype=np.float64).copy()
        self.kd = np.asarray(kd_nm_per_dps, dtype=np.float64).copy()
        self.torque_limit_nm = np.array(
            [abs(t.nm_per_a) * t.current_limit_a for t in transmission.transmissions], dtype=np.float64
        )
        self._negative_limit_nm = -self.torque_limit_nm
        self.expected_deg = np.zeros(n)
        self.expected_dps = np.zeros(n)
        self.lag_deg = np.zeros(n)
        self.enabled = True
        # Position loop parameters (prior: the emulated drives' factory gains until read or identified).
        self.angle_gain_per_s = np.full(n, 100 * ANGLE_GAIN_PER_S_PER_UNIT)
        self.acceleration_dps2 = np.full(n, math.inf)
        self._accel = np.full(n, _NO_LIMIT)
        #: Per joint: the drive's 0x30 angle_kp and 0x33 acceleration as read (None: not read yet).
        self.drive_settings: list[tuple[int, int | None] | None] = [None] * n
        #: Per joint: whether the position loop in use is an identified one (see :meth:`offer_identified`).
        self.identified = [False] * n
        self._joint_of = {motor_id: j for j, motor_id in enumerate(ids)}
        self._reads = [[Request(i, Bare(c)) for c in _READS] for i in ids]
        reading = [read_drives] * n if isinstance(read_drives, bool) else list(read_drives)
        self._unread = [j for j in range(n) if reading[j]]
        self._read_turn = 0
        self._attempts = [0] * n
        self._gains: list[PidGains | None] = [None] * n
        self._accels: list[Acceleration | None] = [None] * n
        self._offered: list[tuple[tuple[int, int | None], PositionLoop] | None] = [None] * n
        # Torque mode: joint inertia (None until given: the model then expects the reference) and fed-forward share.
        self.inertia_kgm2: FloatArray | None = None
        #: How many times :attr:`inertia_kgm2` was evaluated (a reader tells a new evaluation by it).
        self.inertia_evaluations = 0
        self.inertia_feedforward = False
        self._inertia_of: Callable[[FloatArray], FloatArray] | None = None
        self._bias_of: Callable[[FloatArray, FloatArray], FloatArray] | None = None
        self._inertia_at = np.zeros(n)  # the joint angles the mass matrix was evaluated at, deg
        self._mass_inv = np.zeros((n, n))
        # State and the command in force since the last step.
        self._x = np.zeros(n)
        self._v = np.zeros(n)
        self._target = np.zeros(n)  # position: the 0xA4 target; torque: the reference position
        self._cap = np.full(n, np.inf)  # position: the 0xA4 max speed, joint side
        self._ref_v = np.zeros(n)
        self._ref_a = np.zeros(n)
        self._tau = np.zeros(n)
        self._accel_dps2 = np.zeros(n)
        self._x_law = np.zeros(n)  # torque mode: the state the controller's law sees (one cycle old)
        self._v_law = np.zeros(n)
        self._commanded = False
        self._t_s = math.nan
        # Work buffers.
        self._e = np.zeros(n)
        self._w = np.zeros(n)
        self._work = chase_work(n)

    # ------------------------------------------------------------------------------------------------ parameters

    def set_position_loops(self, loops: Sequence[PositionLoop]) -> None:
        """Use these position-loop parameters (joint order)."""
        self.angle_gain_per_s[:] = [loop.angle_gain_per_s for loop in loops]
        self.acceleration_dps2[:] = [loop.acceleration_dps2 for loop in loops]
        np.copyto(self._accel, np.where(np.isfinite(self.acceleration_dps2), self.acceleration_dps2, _NO_LIMIT))

    def position_loops(self) -> tuple[PositionLoop, ...]:
        """The position-loop parameters in use (joint order)."""
        return tuple(
            PositionLoop(float(g), float(a)) for g, a in zip(self.angle_gain_per_s, self.acceleration_dps2, strict=True)
        )

    def set_inertia(
        self,
        inertia_kgm2: Sequence[float] | FloatArray | Callable[[FloatArray], FloatArray],
        *,
        fed_forward: bool,
        bias: Callable[[FloatArray, FloatArray], FloatArray] | None = None,
    ) -> None:
        """Torque mode: the arm's inertia, kg·m² (joint side, rotors included): per joint (independent joints), an
        N×N mass matrix, or a function of the joint angles (deg, evaluated at each cycle's reference) giving either;
        whether the feed-forward covers it (then only the sampling and the torque limit make the joints trail
        the reference); and, where it does not, the arm's velocity-product torques C(q, q̇) q̇ as a function of the
        joint angles and speeds (deg, deg/s; N·m), evaluated at the model's state each cycle: a joint whose inertia
        grows as the arm stretches out is slowed by them, and the PD loop lets it trail by as much."""
        self._bias_of = None if fed_forward else bias
        if callable(inertia_kgm2):
            self._inertia_of = inertia_kgm2
            self._set_mass(inertia_kgm2(self._x))
            np.copyto(self._inertia_at, self._x)
        else:
            self._inertia_of = None
            self._set_mass(np.asarray(inertia_kgm2, dtype=np.float64))
        self.inertia_feedforward = fed_forward

    @property
    def mass_inverse(self) -> FloatArray:
        """Torque mode: M⁻¹ of the model arm, 1/(kg·m²) (zeros without an inertia; updated in place)."""
        return self._mass_inv

    def _set_mass(self, inertia: FloatArray) -> None:
        if self.inertia_kgm2 is None:
            self.inertia_kgm2 = np.zeros((self.n, self.n))
        if inertia.ndim == 1:
            self.inertia_kgm2[:] = 0.0
            np.fill_diagonal(self.inertia_kgm2, inertia)
        else:
            np.copyto(self.inertia_kgm2, inertia)
        np.copyto(self._mass_inv, np.linalg.inv(self.inertia_kgm2))  # once per evaluation, not per cycle
        self.inertia_evaluations += 1

    # ------------------------------------------------------------------------------------------------ drive reads

    @property
    def unread(self) -> bool:
        """Whether a drive's angle-loop gain (0x30) and acceleration limit (0x33) are still to be read."""
        return bool(self._unread)

    def next_reads(self) -> list[Request]:
        """The reads of the next drive in turn (0x30 and 0x33), to append to a cycle's batch: one drive per cycle,
        so that the first cycles after connect carry them at the end of their batches (the set-points and their
        replies keep their timing), each drive asked at most :data:`READ_ATTEMPTS` times (then the prior stays)."""
        j = self._unread[self._read_turn % len(self._unread)]
        self._read_turn += 1
        self._attempts[j] += 1
        return self._reads[j]

    def take_replies(self, replies: list[Reply]) -> list[Reply]:
        """Take the replies to :meth:`next_reads` out of a cycle's replies (answered or not: a drive that does not
        know 0x30 is no lost drive) and use what they carry; returns the others (the same list when none was
        there)."""
        keep: list[Reply] = []
        for reply in replies:
            request = reply.request
            if not (isinstance(request, Bare) and request.command in _READS):
                keep.append(reply)
                continue
            j = self._joint_of.get(reply.motor_id)
            if j is None:
                continue
            if isinstance(reply.message, PidGains):
                self._gains[j] = reply.message
            elif isinstance(reply.message, Acceleration):
                self._accels[j] = reply.message
        if len(keep) == len(replies):
            return replies
        for j in list(self._unread):
            gains = self._gains[j]
            if gains is not None:
                self._use_drive(j, gains, self._accels[j])
                self._unread.remove(j)
            elif self._attempts[j] >= READ_ATTEMPTS:
                self._unread.remove(j)  # the prior stays
        return keep

    def read_now(self, bus: Transport, deadline_s: float) -> None:
        """Read every unread drive's loop settings in one exchange (at connect, where a cycle's batch has no room
        for them: RS485, where an exchange takes as long as a set-point's)."""
        requests = [request for j in self._unread for request in self._reads[j]]
        for j in self._unread:
            self._attempts[j] = READ_ATTEMPTS
        self.take_replies(bus.transact(requests, deadline_s))

    def offer_identified(self, j: int, settings: tuple[int, int | None], loop: PositionLoop) -> None:
        """An identified position loop for joint ``j``, to use once the drive is read with these settings
        (``(angle_kp, acceleration)``, as :attr:`drive_settings` holds them) instead of the prior."""
        self._offered[j] = (settings, loop)
        if self.drive_settings[j] == settings:
            self._set_loop(j, loop)
            self.identified[j] = True

    def _use_drive(self, j: int, gains: PidGains, accel: Acceleration | None) -> None:
        settings = (gains.angle_kp, accel.acceleration_dps2 if accel is not None else None)
        self.drive_settings[j] = settings
        offered = self._offered[j]
        if offered is not None and offered[0] == settings:
            self._set_loop(j, offered[1])
            self.identified[j] = True
        else:
            self._set_loop(j, PositionLoop.from_drive(gains, accel, float(self.gear_ratio[j])))
            self.identified[j] = False

    def _set_loop(self, j: int, loop: PositionLoop) -> None:
        loops = list(self.position_loops())
        loops[j] = loop
        self.set_position_loops(loops)

    # ------------------------------------------------------------------------------------------------ the cycle

    def reset(self, q_deg: FloatArray, qd_dps: FloatArray, reference_deg: FloatArray | None = None) -> None:
        """Start again from the measured state (at start, after a halt or a clear): the expected angle is the
        measured one and nothing is commanded until :meth:`command`."""
        np.copyto(self._x, q_deg)
        np.copyto(self._v, qd_dps)
        np.copyto(self.expected_deg, q_deg)
        np.copyto(self.expected_dps, qd_dps)
        np.copyto(self._target, q_deg if reference_deg is None else reference_deg)
        self.lag_deg[:] = 0.0
        self._commanded = False
        self._t_s = math.nan

    def advance(self, t_s: float, q_deg: FloatArray, qd_dps: FloatArray) -> None:
        """Bring the model to ``t_s`` (this cycle's start: its measurement instant) under the command in force,
        and publish :attr:`expected_deg`. Without a command in force the model follows the measurement."""
        if not self._commanded or math.isnan(self._t_s):
            np.copyto(self._x, q_deg)
            np.copyto(self._v, qd_dps)
            np.copyto(self._x_law, q_deg)
            np.copyto(self._v_law, qd_dps)
        elif not self.enabled:
            np.copyto(self._x, self._target)  # the reference itself: no lag expected
            np.copyto(self._v, self._ref_v)
        else:
            dt = t_s - self._t_s
            if self._host_torque:
                # The controller's next torque is computed from the measurement before this cycle's replies.
                np.copyto(self._x_law, self._x)
                np.copyto(self._v_law, self._v)
            if dt > 0:
                if self._drive_loop:
                    self._position_step(dt)
                else:
                    self._torque_step(dt)
        self._t_s = t_s
        np.copyto(self.expected_deg, self._x)
        np.copyto(self.expected_dps, self._v)
        np.subtract(self._target, self._x, out=self.lag_deg)  # the target in force is the previous reference

    def command(
        self,
        t_s: float,
        reference_deg: FloatArray,
        reference_dps: FloatArray,
        reference_dps2: FloatArray,
        max_speed_motor_dps: FloatArray | None,
    ) -> None:
        """The set-points this cycle sent (at ``t_s``, after :meth:`advance`): the reference for the next instant
        and, in position mode, the 0xA4 speed caps (motor side)."""
        if self._host_torque and self.inertia_kgm2 is not None:
            # The mass matrix changes slowly with the pose: evaluated again once a joint moved by INERTIA_STEP_DEG
            # (the arm model's work is most of this method's cost).
            if self._inertia_of is not None and self._moved_beyond(reference_deg):
                self._set_mass(self._inertia_of(reference_deg))
                np.copyto(self._inertia_at, reference_deg)
            self._torque_law(reference_deg, reference_dps, reference_dps2)
        else:
            np.copyto(self._target, reference_deg)
            np.copyto(self._ref_v, reference_dps)
            if max_speed_motor_dps is not None:
                np.divide(max_speed_motor_dps, self.gear_ratio, out=self._cap)
        self._commanded = True
        self._t_s = t_s

    def _moved_beyond(self, reference_deg: FloatArray) -> bool:
        """Whether a joint of ``reference_deg`` is more than INERTIA_STEP_DEG from where the mass was evaluated."""
        distance = self._e
        np.subtract(reference_deg, self._inertia_at, out=distance)
        np.abs(distance, out=distance)
        return bool(distance.max() > INERTIA_STEP_DEG)

    def stop_commanding(self) -> None:
        """No set-points go out (halted): the model follows the measurement until the next command."""
        self._commanded = False

    # ------------------------------------------------------------------------------------------------ models

    def _position_step(self, dt: float) -> None:
        chase(
            self._x,
            self._v,
            dt,
            target=self._target,
            cap=self._cap,
            gain=self.angle_gain_per_s,
            accel=self._accel,
            work=self._work,
        )

    def _torque_law(self, reference_deg: FloatArray, reference_dps: FloatArray, reference_dps2: FloatArray) -> None:
        """Take the reference, then the controller's torque on the model arm (PD, plus M·qdd_ref where the
        feed-forward covers the inertia; gravity is cancelled by the feed-forward), limited, and the acceleration it
        gives, held until the next cycle (as the drives hold the torque)."""
        mass = self.inertia_kgm2
        assert mass is not None
        np.copyto(self._target, reference_deg)
        np.copyto(self._ref_v, reference_dps)
        np.copyto(self._ref_a, reference_dps2)
        tau, e = self._tau, self._e
        np.subtract(self._target, self._x_law, out=e)
        np.multiply(self.kp, e, out=tau)
        np.subtract(self._ref_v, self._v_law, out=e)
        e *= self.kd
        tau += e
        if self.inertia_feedforward:
            np.multiply(self._ref_a, _RAD_PER_DEG, out=e)
            np.dot(mass, e, out=self._w)
            tau += self._w
        np.minimum(tau, self.torque_limit_nm, out=tau)
        np.maximum(tau, self._negative_limit_nm, out=tau)
        np.dot(self._mass_inv, tau, out=self._accel_dps2)
        self._accel_dps2 *= _DEG_PER_RAD
        self._bias_step()

    def _bias_step(self) -> None:
        """Take the velocity-product torques at the model's state out of its acceleration (where they are given)."""
        if self._bias_of is None:
            return
        w = self._w
        np.dot(self._mass_inv, self._bias_of(self._x, self._v), out=w)
        w *= _DEG_PER_RAD
        self._accel_dps2 -= w

    def _torque_step(self, dt: float) -> None:
        x, v = self._x, self._v
        if self.inertia_kgm2 is None:
            np.copyto(x, self._target)  # no inertia known: the reference is the expectation
            np.copyto(v, self._ref_v)
            return
        a, step = self._accel_dps2, self._e
        np.multiply(v, dt, out=step)
        x += step
        np.multiply(a, 0.5 * dt * dt, out=step)
        x += step
        np.multiply(a, dt, out=step)
        v += step


#: Work arrays of :func:`chase`: six of the state's shape.
ChaseWork = tuple[FloatArray, FloatArray, FloatArray, FloatArray, FloatArray, FloatArray]


def chase_work(shape: int) -> ChaseWork:
    """Work arrays for :func:`chase` on ``shape`` entries."""
    return (np.zeros(shape), np.zeros(shape), np.zeros(shape), np.zeros(shape), np.zeros(shape), np.zeros(shape))


def chase(
    x: FloatArray,
    v: FloatArray,
    dt: float,
    *,
    target: FloatArray,
    cap: FloatArray,
    gain: FloatArray,
    accel: FloatArray,
    work: ChaseWork,
) -> None:
    """The position-loop model over ``dt`` seconds, in place: angles ``x`` (deg) and speeds ``v`` (deg/s) chase
    ``target`` at ``min(gain |e|, sqrt(2 accel |e|), cap)``, the speed slewed at ``accel`` (arrays of one shape, one
    entry per joint or per candidate of :func:`fit_position_loop`; ``work`` from :func:`chase_work`)."""
    steps = max(1, math.ceil(dt / MAX_STEP_S - 1e-9))
    h = dt / steps
    e, s, w, two_accel, slew, no_slew = work
    np.multiply(accel, 2.0, out=two_accel)
    np.multiply(accel, h, out=slew)
    np.negative(slew, out=no_slew)
    for _ in range(steps):
        np.subtract(target, x, out=e)
        np.abs(e, out=s)
        np.multiply(s, two_accel, out=w)
        np.sqrt(w, out=w)  # braking curve: sqrt(2 a |e|)
        s *= gain
        np.minimum(s, w, out=s)
        np.minimum(s, cap, out=s)
        np.copysign(s, e, out=s)  # the speed the drive asks for
        np.subtract(s, v, out=w)
        np.minimum(w, slew, out=w)  # slewed at the acceleration limit (np.clip's wrapper costs more than both)
        np.maximum(w, no_slew, out=w)
        v += w
        np.multiply(v, h, out=w)
        x += w


@dataclass(frozen=True, slots=True)
class PositionLoopFit:
    """What :func:`fit_position_loop` found for one joint.

    Attributes:
        loop: the identified parameters.
        rms_prior_deg: RMS of expected - measured with the prior, deg.
        rms_deg: the same with the identified parameters, deg.
        max_deg: largest |expected - measured| with the identified parameters, deg.
    """

    loop: PositionLoop
    rms_prior_deg: float
    rms_deg: float
    max_deg: float


#: The fit's search: factors of the prior, 2^-SPAN .. 2^SPAN, in POINTS steps, then a finer pass around the best.
_FIT_SPAN = 2.0
_FIT_POINTS = 17
#: Where the acceleration search is centred for a drive that reports no acceleration limit, deg/s² (joint side).
_FIT_ACCEL_FALLBACK_DPS2 = 3600.0


@dataclass(frozen=True, slots=True)
class MoveRecord:
    """One joint's recorded move, per cycle: what was sent and what was measured.

    Attributes:
        t_s: each cycle's start (its measurement instant), s.
        target_deg: the 0xA4 target the cycle sent, joint side, deg.
        cap_dps: the 0xA4 max speed the cycle sent, joint side, deg/s.
        q_deg: the position measured in the cycle, deg.
        qd_dps: the speed measured in the cycle, deg/s.
    """

    t_s: FloatArray
    target_deg: FloatArray
    cap_dps: FloatArray
    q_deg: FloatArray
    qd_dps: FloatArray


def _replay(record: MoveRecord, gains: FloatArray, accels: FloatArray) -> FloatArray:
    """expected - measured at every recorded cycle (rows) for every candidate (columns)."""
    m = len(gains)
    x, v = np.full(m, record.q_deg[0]), np.full(m, record.qd_dps[0])
    target, cap = np.zeros(m), np.zeros(m)
    work = chase_work(m)
    t = record.t_s
    errors = np.zeros((len(t), m))
    for k in range(1, len(t)):
        target[:] = record.target_deg[k - 1]
        cap[:] = record.cap_dps[k - 1]
        chase(x, v, float(t[k] - t[k - 1]), target=target, cap=cap, gain=gains, accel=accels, work=work)
        errors[k] = x - record.q_deg[k]
    return errors


def fit_position_loop(record: MoveRecord, prior: PositionLoop) -> PositionLoopFit:
    """Identify one joint's position loop from a recorded move: the angle gain and acceleration limit whose model,
    replayed against the commands sent, stays closest (least squares) to what was measured. The search is centred
    on ``prior`` (the parameters from 0x30 / 0x33) and spans a factor of 4 either way."""
    base_accel = prior.acceleration_dps2 if math.isfinite(prior.acceleration_dps2) else _FIT_ACCEL_FALLBACK_DPS2
    best_gain, best_accel, span = prior.angle_gain_per_s, base_accel, _FIT_SPAN
    for _ in range(2):  # coarse, then fine around the best
        factors = 2.0 ** np.linspace(-span, span, _FIT_POINTS)
        grid_gain, grid_accel = np.meshgrid(best_gain * factors, best_accel * factors)
        gains, accels = grid_gain.ravel(), grid_accel.ravel()
        cost = np.mean(_replay(record, gains, accels) ** 2, axis=0)
        k = int(np.argmin(cost))
        best_gain, best_accel = float(gains[k]), float(accels[k])
        span = 2.0 * span / (_FIT_POINTS - 1)
    accel_prior = prior.acceleration_dps2 if math.isfinite(prior.acceleration_dps2) else _NO_LIMIT
    replayed = _replay(record, np.array([prior.angle_gain_per_s, best_gain]), np.array([accel_prior, best_accel]))
    return PositionLoopFit(
        PositionLoop(best_gain, best_accel),
        float(np.sqrt(np.mean(replayed[:, 0] ** 2))),
        float(np.sqrt(np.mean(replayed[:, 1] ** 2))),
        float(np.abs(replayed[:, 1]).max()),
    )
