"""Measured state of all axes, updated from drive replies (joint side, arrays in joint order).

The multi-turn position is read once with 0x92 at start; after that it is tracked by unwrapping the encoder of
every reply: a change of the encoder by more than half a revolution between two replies is taken as a wrap. This
holds while the rotor turns less than half a revolution between two replies of the same motor (at 200 Hz and one
missed reply: 18 000 deg/s rotor speed, above any RMD drive's rated speed). Drives whose motion replies carry whole
degrees and no encoder (the V3 family) are read with 0x92 in every cycle instead (:mod:`motion.control.family`).
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, MutableSequence, Sequence
from dataclasses import dataclass
from typing import Any, cast

import numpy as np
from numpy.typing import NDArray

from motion.control.family import FAMILIES, DriveFamily
from motion.protocol import MotorState, MultiTurnAngle
from motion.protocol.table import ProtocolFamily
from motion.transmission import ArmTransmission, FloatArray

#: Width of the encoder fields of the replies, bits.
ENCODER_FIELD_BITS = 16


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
    """

    def __init__(
        self,
        specs: Sequence[AxisSpec],
        transmission: ArmTransmission,
        family: DriveFamily | Sequence[DriveFamily] = FAMILIES[ProtocolFamily.V2],
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
        # The arrays' elements as memoryview cells, which absorb reads and writes at half the cost of numpy's indexing
        # (the arrays are only ever changed in place, so the views stay theirs).
        arrays: tuple[NDArray[Any], ...] = (self.encoder, self.motor_deg, self.motor_speed_dps, self.iq_a)
        arrays += (self.temperature_c, self.last_reply_s, self.q_deg, self.qd_dps, self.fresh)
        self._cells = tuple(_cells(array) for array in arrays)
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
        self._refresh_joint(i)

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
        if not keep_fresh:
            fresh[:] = self._none_fresh
        for motor_id, _request, state, received_s in replies:
            i = index.get(motor_id)
            if i is None or received_s is None or not isinstance(state, MotorState):
                continue
            counts, joint_deg, joint_rate = terms[i]
            encoder = state.encoder
            delta = encoder - encoders[i]
            if delta > counts / 2:
                delta -= int(counts)
            elif delta < -counts / 2:
                delta += int(counts)
            encoders[i] = encoder
            motor_deg = motor_degs[i] + delta * 360.0 / counts
            motor_degs[i] = motor_deg
            speed_dps = float(state.speed_dps)
            speeds[i] = speed_dps
            iqs[i] = state.iq_a
            temperatures[i] = state.temperature_c
            last_reply_s[i] = received_s
            fresh[i] = True
            q_deg[i] = joint_deg(motor_deg)
            qd_dps[i] = joint_rate(speed_dps)

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
