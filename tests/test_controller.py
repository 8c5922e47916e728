"""The controller's request builders, byte-level: 0xA4 max speed (headroom, floor, ceiling), torque FF + PD with
visible current limiting, and the 0x280 / 0xA1 split."""

from __future__ import annotations

import dataclasses
import uuid
from collections.abc import Iterator

import numpy as np
import pytest

from motion.compose import build_controller, open_bus
from motion.config import ArmConfig, load_config
from motion.config.schema import ControlMode
from motion.control.controller import Controller, Feedforward
from motion.protocol import MultiMotorTorque, MultiTurnPositionSpeed, TorqueControl
from motion.trajectory import State
from tests.motion_rig import CONFIGS


def _controller(name: str, mode: ControlMode, feedforward: Feedforward | None = None) -> Iterator[Controller]:
    config: ArmConfig = load_config(CONFIGS / name)
    config = dataclasses.replace(config, control=dataclasses.replace(config.control, mode=mode))
    with open_bus(config, interface="virtual", channel=uuid.uuid4().hex, bitrate=None) as bus:
        yield build_controller(config, bus, feedforward=feedforward)


@pytest.fixture
def arm2_position() -> Iterator[Controller]:
    yield from _controller("arm2.yaml", ControlMode.POSITION)


def test_position_requests_carry_motor_angle_and_speed_with_headroom_and_floor(arm2_position: Controller) -> None:
    # shoulder 1:9 direction +1, elbow 1:9 direction -1; velocity limits 180 and 240 deg/s
    ref = State(np.array([10.0, 20.0]), np.array([30.0, -40.0]), np.zeros(2))
    requests = arm2_position.build_requests(ref)
    assert [r.motor_id for r in requests] == [1, 2]
    shoulder, elbow = (r.message for r in requests)
    assert isinstance(shoulder, MultiTurnPositionSpeed) and isinstance(elbow, MultiTurnPositionSpeed)
    assert shoulder.angle_deg == pytest.approx(90.0) and elbow.angle_deg == pytest.approx(-180.0)
    # max speed = |planned motor speed| * 1.5 + 10 % of the motor-side velocity limit
    assert shoulder.max_speed_dps == pytest.approx(30 * 9 * 1.5 + 0.1 * 180 * 9)
    assert elbow.max_speed_dps == pytest.approx(40 * 9 * 1.5 + 0.1 * 240 * 9)
    # at rest (the last cycles of a move) the floor still lets the drive reach the set-point
    rest = arm2_position.build_requests(State.at_rest([10.0, 20.0]))
    assert [r.message.max_speed_dps for r in rest] == pytest.approx([162.0, 216.0])  # type: ignore[attr-defined]


def test_position_speed_is_capped_at_the_field_width(arm2_position: Controller) -> None:
    ref = State(np.array([0.0, 0.0]), np.array([1e5, 0.0]), np.zeros(2))
    shoulder = arm2_position.build_requests(ref)[0].message
    assert isinstance(shoulder, MultiTurnPositionSpeed) and shoulder.max_speed_dps == 65535.0  # CAN uint16 dps


def test_torque_requests_ff_plus_pd_and_visible_limiting() -> None:
    for controller in _controller("arm2.yaml", ControlMode.TORQUE, feedforward=lambda q, qd, qdd: np.array([1.0, 0.0])):
        # shoulder kp 0.5 N·m/deg, kd 0.02 N·m/(deg/s); measured at rest at 0
        ref = State(np.array([2.0, 0.0]), np.array([10.0, 0.0]), np.zeros(2))
        requests = controller.build_requests(ref)
        tau = 1.0 + 0.5 * 2.0 + 0.02 * 10.0
        assert controller.torque_nm[0] == pytest.approx(tau)
        shoulder = requests[0].message
        assert isinstance(shoulder, TorqueControl)
        # joint torque = direction * gear * kt * iq -> iq = 2.2 / (9 * 0.1) A, on the 0.016 A grid
        assert shoulder.iq_a == pytest.approx(round(tau / 0.9 / 0.016) * 0.016)
        assert not controller.limited.any()
        # far from the reference: the PD asks for more than the shoulder's 15 A limit; the command is limited and
        # the limiting is visible
        far = State(np.array([80.0, 0.0]), np.zeros(2), np.zeros(2))
        limited = controller.build_requests(far)[0].message
        assert isinstance(limited, TorqueControl) and limited.iq_a == pytest.approx(15.0, abs=0.016)
        assert controller.limited.tolist() == [True, False]
        # arm2 has motors 1 and 2 only: no 0x280 (it would command motors 3 and 4 too)
        assert all(isinstance(r.message, TorqueControl) for r in requests)


def test_arm6_torque_packs_motors_1_to_4_in_one_0x280_frame() -> None:
    for controller in _controller("arm6.yaml", ControlMode.TORQUE):
        requests = controller.build_requests(State(np.full(6, 1.0), np.zeros(6), np.zeros(6)))
        kinds = [type(r.message) for r in requests]
        assert kinds.count(MultiMotorTorque) == 1 and kinds.count(TorqueControl) == 2
        assert sorted(r.motor_id for r in requests if isinstance(r.message, TorqueControl)) == [5, 6]
        multi = next(r.message for r in requests if isinstance(r.message, MultiMotorTorque))
        assert all(getattr(multi, f"iq{i}_a") != 0.0 for i in range(1, 5))  # every joint of 1..4 got its current
