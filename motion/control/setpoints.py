"""The set-points of one control cycle: one builder per control mode behind one interface (:class:`SetpointBuilder`),
chosen by :data:`BUILDERS` (a new mode is a builder and its entry there).

Position mode streams 0xA4 (multi-turn angle + max speed) per joint. Torque mode computes, per joint,
``tau = feedforward(q, qd_ref, qdd_ref) + Kp (q_ref - q) + Kd (qd_ref - qd)``, converts it to torque current
(limited per joint; the limiting is recorded) and sends it in one 0x280 frame for motor ids 1..4 (CAN) and 0xA1
frames for the others (and for every joint on RS485).

The builders work in Python floats per joint: for a few joints a numpy call costs more than the arithmetic; the
operations and their order are those of the array formulas, so the results are the same float64s.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Final, Protocol

import numpy as np
from numpy.typing import NDArray

from motion.config.schema import ControlMode
from motion.control.axes import AxisSpec, AxisStates
from motion.control.family import DriveFamily
from motion.protocol import MultiMotorTorque, MultiTurnPositionSpeed, TorqueControl, WireProtocol
from motion.protocol.compiled import frozen_builder
from motion.protocol.scales import iq_amps
from motion.protocol.table import ADDRESS_STRIDE, MULTI_TORQUE_MOTOR_IDS, split_address
from motion.trajectory import State
from motion.transmission import ArmTransmission, FloatArray
from motion.transport.base import Request

#: ``feedforward(q_deg, qd_dps, qdd_dps2) -> tau_nm``, arrays in joint order (gravity, optionally inertia).
Feedforward = Callable[[FloatArray, FloatArray, FloatArray], FloatArray]

# Constructors of the messages built every cycle that set the slots directly (a frozen dataclass's own __init__ goes
# through object.__setattr__ for each field, several times slower); same objects, same equality.
NEW_REQUEST: Final = frozen_builder(Request)
_NEW_POSITION: Final = frozen_builder(MultiTurnPositionSpeed)
_NEW_TORQUE: Final = frozen_builder(TorqueControl)
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


@dataclass(frozen=True, slots=True)
class BuilderSettings:
    """What every builder is made from (the controller's, constant while it lives).

    Attributes:
        specs: the axes, in joint order.
        families: each axis' drive's capabilities (its family's), in joint order.
        wires: each bus's wire protocol, by the bus index of the drives' addresses.
        velocity_limit_dps: each joint's velocity limit, motor side, deg/s.
        speed_headroom: position mode: the 0xA4 cap is the planned motor speed times this, plus the floor.
        speed_floor_share: position mode: the floor, as a share of the velocity limit.
        kp_nm_per_deg: torque mode: the PD stiffness per joint.
        kd_nm_per_dps: torque mode: the PD damping per joint.
        feedforward: torque mode: the feed-forward (None: zero).
        multi_motor_frame: torque mode: use the 0x280 frame where it applies.
        record: the set-points record the builder fills in.
    """

    specs: tuple[AxisSpec, ...]
    families: tuple[DriveFamily, ...]
    wires: tuple[WireProtocol, ...]
    velocity_limit_dps: FloatArray
    speed_headroom: float
    speed_floor_share: float
    kp_nm_per_deg: FloatArray
    kd_nm_per_dps: FloatArray
    feedforward: Feedforward | None
    multi_motor_frame: bool
    record: Setpoints


class SetpointBuilder(Protocol):
    """The set-points of one control mode."""

    def set_frame(self, transmission: ArmTransmission, axes: AxisStates) -> None:
        """Use this mapping (with the turn offsets) and these axis states from now on."""

    def build(self, reference: State) -> list[Request]:
        """The cycle's set-point requests for ``reference``; records them in the settings' record."""

    def tracking_caps(self) -> FloatArray | None:
        """The latest 0xA4 speed caps, motor side (the tracking model's), or None where the mode sends none."""


class PositionSetpoints:
    """0xA4 per joint: the reference angle, and a speed cap of the planned speed times the headroom plus a floor (so
    that the drive's own position loop, which lags the stream, can catch up, and the last set-points of a move are
    reached), never above the joint's velocity limit nor the field's ceiling."""

    def __init__(self, settings: BuilderSettings) -> None:
        self._settings = settings
        self.speed_floor_dps = settings.velocity_limit_dps * settings.speed_floor_share
        self.speed_limit_dps = settings.velocity_limit_dps
        wires = settings.wires
        ceiling = np.array(
            [
                family.speed_ceiling_dps(wires[split_address(s.motor_id)[0]]) * s.drive_gear_ratio
                for s, family in zip(settings.specs, settings.families, strict=True)
            ]
        )  # (each by its family and its bus's wire)
        self._ceiling_dps = np.minimum(ceiling, self.speed_limit_dps).tolist()
        self._axes: tuple[tuple[int, float, float, float, float, float], ...] = ()

    def set_frame(self, transmission: ArmTransmission, axes: AxisStates) -> None:
        # Per axis: motor id, motor deg per joint deg (as ArmTransmission has them), zero offset, speed floor, the
        # drive's degrees per motor degree (1, or 1 / its reduction where it takes output-shaft angles) and the speed
        # cap's ceiling in motor deg/s.
        specs = self._settings.specs
        self._axes = tuple(
            zip(
                [s.motor_id for s in specs],
                [t.direction * t.gear_ratio for t in transmission.transmissions],
                [t.zero_offset_deg for t in transmission.transmissions],
                self.speed_floor_dps.tolist(),
                [1.0 / s.drive_gear_ratio for s in specs],
                self._ceiling_dps,
                strict=True,
            )
        )

    def build(self, reference: State) -> list[Request]:
        headroom = self._settings.speed_headroom
        new_request, new_position = NEW_REQUEST, _NEW_POSITION
        angles: list[float] = []
        caps: list[float] = []
        requests: list[Request] = []
        for (motor_id, motor_per_joint, offset_deg, floor_dps, to_drive, ceiling), q_deg, qd_dps in zip(
            self._axes, reference.position.tolist(), reference.velocity.tolist(), strict=True
        ):
            angle = (q_deg - offset_deg) * motor_per_joint
            cap = min(abs(qd_dps * motor_per_joint) * headroom + floor_dps, ceiling)
            angles.append(angle)
            caps.append(cap)
            requests.append(new_request(motor_id, new_position(angle * to_drive, cap * to_drive)))
        record = self._settings.record
        record.motor_angle_deg[:] = angles
        record.max_speed_dps[:] = caps
        return requests

    def tracking_caps(self) -> FloatArray | None:
        return self._settings.record.max_speed_dps


class TorqueSetpoints:
    """PD plus the feed-forward per joint, as torque currents limited per joint: 0xA1 each, and one 0x280 frame for
    motors 1..4 of a bus where it applies (CAN, all four joints of this arm: the frame commands them whether they
    belong to the arm or not, so a foreign drive on the bus is never switched into torque mode); on each bus of an arm
    on several."""

    def __init__(self, settings: BuilderSettings) -> None:
        self._settings = settings
        specs = settings.specs
        self._ids = ids = [s.motor_id for s in specs]  # (the drives' addresses: bus index × stride + motor id)
        usable = settings.multi_motor_frame
        # (a bus where 0x280 carries the four currents: CAN, and drives of a family whose 0x280 does)
        can = [wire is WireProtocol.CAN for wire in settings.wires]
        for a, family in zip(ids, settings.families, strict=True):
            can[split_address(a)[0]] &= family.multi_torque_frame
        #: One 0x280 frame per CAN bus whose motors 1..4 are all joints of the arm: (the address of that bus's motor
        #: 1, the joints of the frame's four currents in the frame's order).
        self._frames: list[tuple[int, list[int]]] = []
        for bus in sorted({split_address(a)[0] for a in ids if can[split_address(a)[0]]}) if usable else ():
            addresses = [bus * ADDRESS_STRIDE + m for m in MULTI_TORQUE_MOTOR_IDS]
            if all(a in ids for a in addresses):
                self._frames.append((addresses[0], [ids.index(a) for a in addresses]))
        framed = {i for _, joints in self._frames for i in joints}
        self._single = [i for i in range(len(specs)) if i not in framed]
        self._transmission: ArmTransmission | None = None
        self._state: AxisStates | None = None

    def set_frame(self, transmission: ArmTransmission, axes: AxisStates) -> None:
        self._transmission, self._state = transmission, axes

    def build(self, reference: State) -> list[Request]:
        settings, axes = self._settings, self._state
        assert axes is not None  # (set_frame first)
        torques = [
            kp * (q_ref - q) + kd * (qd_ref - qd)
            for kp, kd, q_ref, q, qd_ref, qd in zip(
                settings.kp_nm_per_deg.tolist(),
                settings.kd_nm_per_dps.tolist(),
                reference.position.tolist(),
                axes.q_deg.tolist(),
                reference.velocity.tolist(),
                axes.qd_dps.tolist(),
                strict=True,
            )
        ]
        if settings.feedforward is not None:
            feedforward = settings.feedforward(axes.q_deg, reference.velocity, reference.acceleration).tolist()
            torques = [tau + ff for tau, ff in zip(torques, feedforward, strict=True)]
        return self.torque_frames(torques)

    def torque_frames(self, torques: Sequence[float]) -> list[Request]:
        """The torque-current requests for joint torques (N·m, joint order), limited per joint; records the torque and
        the limiting."""
        assert self._transmission is not None  # (set_frame first)
        record = self._settings.record
        record.torque_nm[:] = torques
        raw, limited = self._transmission.iq_raw_limited_list(torques)
        record.limited[:] = limited
        currents = [iq_amps(r) for r in raw]
        ids, new_request, new_torque = self._ids, NEW_REQUEST, _NEW_TORQUE
        requests = [new_request(ids[i], new_torque(currents[i])) for i in self._single]
        for first, joints in self._frames:
            requests.append(new_request(first, _NEW_MULTI_TORQUE(*[currents[i] for i in joints])))
        return requests

    def tracking_caps(self) -> FloatArray | None:
        return None


#: The builder of each control mode.
BUILDERS: Final[dict[ControlMode, Callable[[BuilderSettings], SetpointBuilder]]] = {
    ControlMode.POSITION: PositionSetpoints,
    ControlMode.TORQUE: TorqueSetpoints,
}


def setpoint_builder(mode: ControlMode, settings: BuilderSettings) -> SetpointBuilder:
    """The builder of ``mode``.

    Raises:
        ValueError: a mode without one.
    """
    try:
        build = BUILDERS[mode]
    except KeyError:
        raise ValueError(f"unknown control mode {mode!r}") from None
    return build(settings)
