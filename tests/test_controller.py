"""The controller's request builders, byte-level: 0xA4 max speed (headroom, floor, ceiling), torque FF + PD with
visible current limiting, and the 0x280 / 0xA1 split."""

from __future__ import annotations

import dataclasses
import uuid
from collections.abc import Iterator

import numpy as np
import pytest

from motion.api import Arm
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


def test_position_speed_is_capped_at_the_joints_velocity_limit(arm2_position: Controller) -> None:
    # Issue 31 §5: a reference near the limit (1.5 x would ask for more) or a jumping one never asks a drive for more
    # than its joint's limit (shoulder 180, elbow 240 deg/s; 1:9); below, the headroom and the floor as before.
    for velocity in ([170.0, -235.0], [1e5, -1e5]):
        ref = State(np.array([0.0, 0.0]), np.array(velocity), np.zeros(2))
        caps = [r.message.max_speed_dps for r in arm2_position.build_requests(ref)]  # type: ignore[attr-defined]
        assert caps == [180.0 * 9, 240.0 * 9]
    ref = State(np.array([0.0, 0.0]), np.array([100.0, 0.0]), np.zeros(2))
    caps = [r.message.max_speed_dps for r in arm2_position.build_requests(ref)]  # type: ignore[attr-defined]
    assert caps == pytest.approx([(100 * 1.5 + 18) * 9, 0.1 * 240 * 9])  # (168 deg/s: below 180)


def test_position_mode_plans_below_the_velocity_limit_torque_mode_at_it() -> None:
    # Position mode keeps catch_up_share (10 %) of each limit free for a lagging drive to catch up under its cap.
    for mode, share in ((ControlMode.POSITION, 0.9), (ControlMode.TORQUE, 1.0)):
        for controller in _controller("arm2.yaml", mode):
            motion = controller.planner.move(State.at_rest([-85.0, 130.0]), np.array([85.0, -130.0]))
            speeds = np.abs([motion.sample(t).velocity for t in np.linspace(0.0, motion.duration_s, 400)])
            top = speeds.max(axis=0)  # (time-synchronised: the elbow's move is the longest, the shoulder slower)
            assert top[1] == pytest.approx(240.0 * share, rel=1e-3) and top[0] <= 180.0 * share * (1 + 1e-9)


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


def test_a_v3_drives_speed_cap_is_its_joints_velocity_limit_in_output_degrees() -> None:
    # issue 31 §5 on the later generation: the V3 drive takes 0xA4's angle and speed cap at its output shaft, so the
    # cap of a jumping reference is the joint's own limit, not 1.5 x the planned speed + 10 % (elbow: 192 of 120)
    config = load_config(CONFIGS / "arm6_v3.yaml")
    with Arm(config, emulate=True) as arm:
        controller = arm.controller
        assert controller is not None and all(f.output_shaft for f in controller.families)
        limits = [j.velocity_limit_dps for j in config.joints]
        for scale in (1.0, 1e3):
            ref = State(np.zeros(len(limits)), scale * np.array(limits), np.zeros(len(limits)))
            caps = [r.message.max_speed_dps for r in controller.build_requests(ref)]  # type: ignore[attr-defined]
            assert caps == pytest.approx(limits)
