"""Measured state of all axes, updated from drive replies (joint side, arrays in joint order).

The multi-turn position is read once with 0x92 at start; after that it is tracked by unwrapping the encoder of
every reply: its change between two replies is taken the way round nearest to the motion the speeds reported in the
two predict. This holds whatever that prediction while the rotor turns less than half a revolution
(:data:`UNWRAP_BOUND_MOTOR_DEG`) between two replies of the same motor: at the joint's velocity limit, for as long as
:attr:`AxisStates.unwrap_gap_s` (a configuration whose velocity limits do not unwrap at its rate is refused:
:mod:`motion.control.unwrap`); the prediction follows a joint beyond its velocity limit too (one falling with its
drive off, one pushed) while its speed changes by less than that between two replies.

The drive's own multi-turn angle (0x92) keeps the turns while it is powered; the encoder gives the fine angle between
its reads. An axis is *anchored* while its tracked turns are sure: since its 0x92 and state replies were last taken
in one exchange, none of its replies went missing and none came longer than ``unwrap_gap_s`` after the one before. An
axis that is not (a drive silent, a cycle skipped, a speed that turns its shaft half a turn a sample or fills the
speed field) is read with 0x92 in every exchange until it is
(:meth:`AxisStates.unanchored`), and that reading puts back the whole turns the encoder missed: after any silence the
controller's angle is the drive's. Each 0x92 reading is held against the tracked angle; a difference of half a turn or
more is (:meth:`AxisStates._take_reading`):

- after a gap, where motion explains it, the turns the encoder missed, unless the reading lies in the drive's first
  turn (:func:`motion.control.turns.in_first_turn`): that is where a drive reads after a power-up (a restart), and a
  restart cannot be told from motion there: the frame is taken as lost;
- on an anchored axis (nothing missed, motion within the unwrapping bound), no motion at all: the drive restarted.

A lost frame (:attr:`AxisStates.frame_jump_deg`) stays lost for the session: the tracked angle goes on from the
encoder in the old frame, and no reading changes it (the watchdog faults the arm, ``drive_restarted``).

Drives whose motion replies carry whole degrees and no encoder (the V3 family) are read with 0x92 in every cycle
instead (:mod:`motion.control.family`): their angle is the drive's reading at once.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, MutableSequence, Sequence
from dataclasses import dataclass
from typing import Any, Final, cast

import numpy as np
from numpy.typing import NDArray

from motion.control.family import FAMILIES, DriveFamily
from motion.control.turns import TURN_DEG, in_first_turn
from motion.protocol import Command, MotorState, MultiTurnAngle, WireProtocol
from motion.protocol.table import Direction, ProtocolFamily, field_range
from motion.transmission import ArmTransmission, FloatArray

#: Width of the encoder fields of the replies, bits.
ENCODER_FIELD_BITS = 16
#: The encoder's change between two replies is taken the shortest way round: the shaft must turn less than half a
#: turn between them for the turns to be counted, motor degrees. A 0x92 reading within it of the tracked angle (both
#: taken in one exchange) is on the same turn.
UNWRAP_BOUND_MOTOR_DEG: Final = 180.0
#: The largest speed the older family's state replies carry, motor deg/s: a reading there may be a faster motor's.
SPEED_FIELD_MAX_DPS: Final = field_range(Command.READ_STATUS_2, Direction.REPLY, WireProtocol.CAN, "speed_dps")[1]


@dataclass(frozen=True, slots=True)
class AxisSpec:
    """What the controller needs to know of one joint.

    Attributes:
        name: joint name.
        motor_id: the drive's address: its motor id 1..32 on an arm of one bus, else ``bus index × ADDRESS_STRIDE +
            motor id`` (:mod:`motion.transport.buses`).
        encoder_bits: encoder resolution (counts per rotor revolution = 2**bits).
        kp_nm_per_deg: torque-mode position gain, N·m per degree of joint error.
        kd_nm_per_dps: torque-mode velocity gain, N·m per deg/s of joint velocity error.
        drive_gear_ratio: motor-shaft degrees per degree the drive reports and takes (1 for a drive that reports its
            motor, as the older family's do; its own reduction for a drive that reports its output shaft, as V3-driver
            drives do: :mod:`motion.control.family`).
    """

    name: str
    motor_id: int
    encoder_bits: int = 14
    kp_nm_per_deg: float = 0.0
    kd_nm_per_dps: float = 0.0
    drive_gear_ratio: float = 1.0
    label: str = ""  #: how messages name the drive ("motor 3 on bus right"); "" gives "motor {motor_id}"

    @property
    def drive_label(self) -> str:
        """How messages name the drive."""
        return self.label or f"motor {self.motor_id}"


def _cells(array: NDArray[Any]) -> MutableSequence[Any]:
    """The elements of a 1-D array as a memoryview (Python numbers in and out)."""
    return cast("MutableSequence[Any]", array.data)


class AxisStates:
    """Measured joint positions, velocities, currents and temperatures, refreshed from replies.

    Args:
        specs: the axes, in joint order.
        transmission: the joint <-> motor mapping, same order.
        family: the drives' protocol family: whether the angle comes from the encoder of every motion reply (tracked
            across wraps) or from a 0x92 read in every cycle (motion replies in whole degrees); a sequence: each
            axis' (an arm whose buses have drives of both families).
        velocity_limit_motor_dps: per axis, the joint's velocity limit at the motor, deg/s: the encoder's turns are
            sure across a gap between two replies of at most :data:`UNWRAP_BOUND_MOTOR_DEG` over it
            (:attr:`unwrap_gap_s`); None: across any gap (only a missing reply unanchors an axis).
    """

    def __init__(
        self,
        specs: Sequence[AxisSpec],
        transmission: ArmTransmission,
        family: DriveFamily | Sequence[DriveFamily] = FAMILIES[ProtocolFamily.V2],
        velocity_limit_motor_dps: Sequence[float] | None = None,
    ) -> None:
        n = len(specs)
        families = [family] * n if isinstance(family, DriveFamily) else list(family)
        reads_angle = [f.angle_every_cycle for f in families]
        self.specs = tuple(specs)
        self.transmission = transmission
        self.index = {spec.motor_id: i for i, spec in enumerate(specs)}
        # Which absorb: the encoder's, the 0x92 read's, or both, each over its own axes (mixed families).
        self._angle_every_cycle = all(reads_angle)
        self._mixed = any(reads_angle) and not all(reads_angle)
        self._state_type = next((f.state_type for f in families if f.angle_every_cycle), families[0].state_type)
        self._encoder_index = {k: i for k, i in self.index.items() if not reads_angle[i]}
        self._angle_index = {k: i for k, i in self.index.items() if reads_angle[i]}
        #: The step of each joint's speed reading, joint deg/s: one step of its drive's speed field (of the motor for
        #: the older family, of the output shaft for V3: the family's ``speed_step_dps``) through the transmission.
        self.speed_step_dps = np.array(
            [
                abs(t.joint_rate(f.speed_step_dps * s.drive_gear_ratio))
                for s, t, f in zip(specs, transmission.transmissions, families, strict=True)
            ]
        )
        # The encoder fields are uint16: wider encoders report their top 16 bits (docs/protocol.md).
        self.counts_per_rev = np.array([float(1 << min(s.encoder_bits, ENCODER_FIELD_BITS)) for s in specs])
        # Per axis, for absorb: counts per revolution, and the joint's motor -> joint conversions.
        self._terms = tuple(
            (counts, t.joint_deg, t.joint_rate)
            for counts, t in zip(self.counts_per_rev.tolist(), transmission.transmissions, strict=True)
        )
        self.motor_deg = np.zeros(n)  # unwrapped multi-turn rotor angle
        self.motor_speed_dps = np.zeros(n)
        self.encoder = np.zeros(n, dtype=np.int64)
        self.q_deg = np.zeros(n)
        self.qd_dps = np.zeros(n)
        self.iq_a = np.zeros(n)
        self.temperature_c = np.zeros(n)
        self.last_reply_s = np.full(n, -np.inf)
        self.fresh = np.zeros(n, dtype=bool)  # got a state reply in the latest cycle
        limits = velocity_limit_motor_dps or [0.0] * n
        #: Per axis, the longest gap between two of its replies across which the encoder's turns are sure at the
        #: joint's velocity limit, s (inf: any; the axes whose angle is read in every cycle need none).
        self.unwrap_gap_s = np.array(
            [
                math.inf if reads or not abs(v) > 0.0 else UNWRAP_BOUND_MOTOR_DEG / abs(v)
                for reads, v in zip(reads_angle, limits, strict=True)
            ]
        )
        #: Per axis, whether its tracked turns are sure (the module docstring); those read in every cycle always are.
        self.anchored = np.array(reads_angle, dtype=bool)
        #: Per axis, the whole-turn difference between the drive's 0x92 reading and the tracked angle that showed its
        #: frame lost (a restart), motor degrees; NaN: none. Kept for the session: no later reading changes the axis.
        self.frame_jump_deg = np.full(n, np.nan)
        #: Per axis, the whole motor turns its 0x92 readings put back after gaps (the encoder missed them).
        self.turns_restored = np.zeros(n, dtype=np.int64)
        # The arrays' elements as memoryview cells, which absorb reads and writes at half the cost of numpy's indexing
        # (the arrays are only ever changed in place, so the views stay theirs).
        arrays: tuple[NDArray[Any], ...] = (self.encoder, self.motor_deg, self.motor_speed_dps, self.iq_a)
        arrays += (self.temperature_c, self.last_reply_s, self.q_deg, self.qd_dps, self.fresh)
        self._cells = tuple(_cells(array) for array in arrays)
        self._gap_cells = (_cells(self.unwrap_gap_s), _cells(self.anchored))
        self._stale = np.zeros(n, dtype=bool)  # work array of unanchored()
        self._since = np.zeros(n)
        self._reach = np.zeros(n)
        self._fast = np.zeros(n, dtype=bool)
        self._loose = np.zeros(n, dtype=bool)
        self._unwrapped = ~np.array(reads_angle, dtype=bool)
        self._none_fresh = np.zeros(n, dtype=bool).data
        # Output-shaft drives: motor degrees per degree the drive reports, and the per-axis conversions.
        self._drive_terms = tuple(
            (float(spec.drive_gear_ratio), t.joint_deg, t.joint_rate)
            for spec, t in zip(specs, transmission.transmissions, strict=True)
        )

    def initialise(self, i: int, multi_turn_deg: float, encoder: int) -> None:
        """Anchor axis ``i``: the 0x92 angle and an encoder reading taken at (nearly) the same moment."""
        self.motor_deg[i] = multi_turn_deg
        self.encoder[i] = encoder
        self.anchored[i] = True
        self.last_reply_s[i] = np.nan  # (the next reply unwraps from this reading, whenever it comes)
        self._refresh_joint(i)

    def unanchored(self, now_s: float) -> NDArray[np.intp]:
        """The axes whose exchange at ``now_s`` must read their drive's multi-turn angle (0x92): those not anchored,
        those whose replies would come longer than :attr:`unwrap_gap_s` after their last one, and those whose last
        reported speed turns the shaft half a turn by then or fills its field (a faster motor's, maybe) (indexes)."""
        since = np.subtract(now_s, self.last_reply_s, out=self._since)
        stale = np.greater(since, self.unwrap_gap_s, out=self._stale)
        stale |= np.logical_not(self.anchored, out=self._loose)
        speed = np.abs(self.motor_speed_dps, out=self._reach)
        saturated = np.greater_equal(speed, SPEED_FIELD_MAX_DPS, out=self._fast)  # (a faster motor's, maybe)
        saturated &= self._unwrapped
        stale |= saturated
        since *= speed
        fast = np.greater_equal(since, UNWRAP_BOUND_MOTOR_DEG, out=self._fast)
        fast &= self._unwrapped  # (an angle read in every cycle is never unwrapped)
        stale |= fast
        return np.flatnonzero(stale)

    def update(self, i: int, state: object, received_s: float) -> None:
        """Take one 0x9C / 0xA1..0xA8 reply of axis ``i`` (the family's motion reply)."""
        self.absorb(((self.specs[i].motor_id, None, state, received_s),), keep_fresh=True)

    def absorb(self, replies: Iterable[tuple[int, object, object, float | None]], *, keep_fresh: bool = False) -> None:
        """Take a cycle's replies (:class:`~motion.transport.Reply` tuples: motor id, request, message, time).

        Every motion reply (the family's, e.g. :class:`MotorState`) that arrived for an axis refreshes it; :attr:`fresh`
        then marks those axes (and only those, unless ``keep_fresh``). Where the family reads the angle in every
        cycle, a :class:`MultiTurnAngle` sets it. Anything else is ignored.
        """
        if self._mixed:  # (each of the two over its axes; a sequence of replies, read twice)
            replies = replies if isinstance(replies, Sequence) else list(replies)
            self._absorb_states(replies, keep_fresh, self._encoder_index)
            self._absorb_read_angles(replies, True, self._angle_index)
        elif self._angle_every_cycle:
            self._absorb_read_angles(replies, keep_fresh, self.index)
        else:
            self._absorb_states(replies, keep_fresh, self.index)

    def _absorb_states(
        self, replies: Iterable[tuple[int, object, object, float | None]], keep_fresh: bool, index: Mapping[int, int]
    ) -> None:
        """:meth:`absorb` for drives whose motion replies carry the encoder (the axes of ``index``), in Python."""
        # The control cycle's hot path: the arrays' cells and the per-axis terms are looked up once, and the
        # arithmetic is done in Python floats and ints (a numpy scalar costs several times as much per operation),
        # with the same operations in the same order as the arrays would do them, so the results are the same float64s.
        terms = self._terms
        encoders, motor_degs, speeds, iqs, temperatures, last_reply_s, q_deg, qd_dps, fresh = self._cells
        gaps, anchored = self._gap_cells
        if not keep_fresh:
            fresh[:] = self._none_fresh
        others: list[tuple[int, object, float | None]] | None = None  # missing replies and 0x92's, taken after
        for motor_id, _request, state, received_s in replies:
            i = index.get(motor_id)
            if i is None:
                continue
            if not isinstance(state, MotorState):
                if state is None or state.__class__ is MultiTurnAngle:
                    if others is None:
                        others = []
                    others.append((i, state, received_s))
                continue
            if received_s is None:
                continue
            counts, joint_deg, joint_rate = terms[i]
            speed_dps = float(state.speed_dps)
            since_s = received_s - last_reply_s[i]
            # The encoder's change is taken the way round nearest to what the speeds reported at both ends predict
            # (nothing is predicted across a gap longer than the velocity limit unwraps, nor at the first reply after
            # an anchor: NaN). Beyond the envelope the configuration was checked for (a gap, a speed that turns the
            # shaft half a turn per sample, or one the field cannot tell) the turns are confirmed by 0x92.
            expected = 0.0
            if since_s > gaps[i]:
                anchored[i] = False
            elif since_s <= gaps[i] and since_s < math.inf:
                before_dps = speeds[i]
                expected = (before_dps + speed_dps) * since_s * counts / 720.0
                fastest = max(abs(before_dps), abs(speed_dps))
                if fastest * since_s >= UNWRAP_BOUND_MOTOR_DEG or fastest >= SPEED_FIELD_MAX_DPS:
                    anchored[i] = False
            encoder = state.encoder
            delta = encoder - encoders[i]
            delta -= round((delta - expected) / counts) * int(counts)
            encoders[i] = encoder
            motor_deg = motor_degs[i] + delta * 360.0 / counts
            motor_degs[i] = motor_deg
            speeds[i] = speed_dps
            iqs[i] = state.iq_a
            temperatures[i] = state.temperature_c
            last_reply_s[i] = received_s
            fresh[i] = True
            q_deg[i] = joint_deg(motor_deg)
            qd_dps[i] = joint_rate(speed_dps)
        if others is not None:
            self._take_others(others)

    def _take_others(self, others: list[tuple[int, object, float | None]]) -> None:
        """An exchange's missing replies and 0x92 readings of encoder axes (:meth:`_absorb_states`), after its state
        replies."""
        fresh = self._cells[-1]
        for i, message, received_s in others:
            if message is None:
                if not fresh[i]:  # a drive unheard: its turns are sure again once a 0x92 reading confirms them
                    self.anchored[i] = False
            elif fresh[i] and received_s is not None:  # (with its state reply of the same exchange)
                self._take_reading(i, message.angle_deg, received_s - self.last_reply_s.item(i))  # type: ignore[attr-defined]

    def _take_reading(self, i: int, reading_deg: float, after_s: float) -> None:
        """A 0x92 reading of encoder axis ``i`` (motor degrees, the drive's frame) taken ``after_s`` after its state
        reply of the same exchange (the shaft turned on meanwhile at the speed that reply reported): held against
        the tracked angle (the module docstring). With the speed field full, how far it turned is unknown: the
        reading confirms nothing until the speed is told again."""
        speed_dps = self.motor_speed_dps.item(i)
        if abs(speed_dps) >= SPEED_FIELD_MAX_DPS:
            return
        jump = reading_deg - self.motor_deg.item(i) - speed_dps * after_s
        if abs(jump) < UNWRAP_BOUND_MOTOR_DEG:
            self.anchored[i] = True
            return
        if not math.isnan(self.frame_jump_deg.item(i)):
            return  # (lost for the session: the tracked angle goes on in the old frame)
        if self.anchored[i] or in_first_turn(reading_deg):
            self.frame_jump_deg[i] = jump
            self.anchored[i] = True  # (nothing more to confirm)
            return
        turns = round(jump / TURN_DEG)
        self.motor_deg[i] += turns * TURN_DEG
        self.turns_restored[i] += turns
        self.anchored[i] = True
        self._refresh_joint(i)

    def _absorb_read_angles(
        self, replies: Iterable[tuple[int, object, object, float | None]], keep_fresh: bool, index: Mapping[int, int]
    ) -> None:
        """:meth:`absorb` for drives whose motion replies carry whole degrees (the axes of ``index``): the angle from
        0x92, the rest from the motion reply, both in the drive's (output-shaft) units converted to the motor's."""
        terms, state_type = self._drive_terms, self._state_type
        _encoders, motor_degs, speeds, iqs, temperatures, last_reply_s, q_deg, qd_dps, fresh = self._cells
        if not keep_fresh:
            fresh[:] = self._none_fresh
        for motor_id, _request, message, received_s in replies:
            i = index.get(motor_id)
            if i is None or received_s is None:
                continue
            drive_gear, joint_deg, joint_rate = terms[i]
            if message.__class__ is MultiTurnAngle:
                motor_deg = message.angle_deg * drive_gear
                motor_degs[i] = motor_deg
                q_deg[i] = joint_deg(motor_deg)
            elif message.__class__ is state_type:
                speed_dps = message.speed_dps * drive_gear  # type: ignore[attr-defined]
                speeds[i] = speed_dps
                iqs[i] = message.iq_a  # type: ignore[attr-defined]
                temperatures[i] = message.temperature_c  # type: ignore[attr-defined]
                last_reply_s[i] = received_s
                fresh[i] = True
                qd_dps[i] = joint_rate(speed_dps)

    def _refresh_joint(self, i: int) -> None:
        t = self.transmission.transmissions[i]
        self.q_deg[i] = t.joint_deg(self.motor_deg.item(i))
        self.qd_dps[i] = t.joint_rate(self.motor_speed_dps.item(i))

    def positions(self) -> FloatArray:
        """A copy of the joint positions, degrees."""
        return self.q_deg.copy()
