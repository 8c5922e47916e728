"""The lag-aware following-error check (issue 18), in simulated time.

- Full-speed moves through every joint's whole range, on emulated drives whose position loops are softer (0.5x) and
  stiffer (2x) than the factory's, and with slower replies: no following-error fault at the configured thresholds,
  although the raw |reference - measured| error exceeds them by up to three times (asserted, so that the test keeps
  testing something).
- A joint blocked mid-move is caught in as few cycles as by the check against the raw reference (the model switched
  off), for position and torque mode.
- The model itself: its parameters from 0x30 / 0x33 through the gear, and cycles that keep no memory.
"""

from __future__ import annotations

import dataclasses
import json
import math
import tracemalloc
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import pytest

from motion.compose import identify_position_loops
from motion.config import ArmConfig
from motion.config.schema import ControlMode, EmulatedPidConfig
from motion.control.controller import Controller
from motion.control.tracking import ANGLE_GAIN_PER_S_PER_UNIT, PositionLoop
from motion.emulator import DEFAULT_PID, Fault, InjectedFault
from motion.errors import MotionFault
from motion.keep import STATE_DIR_ENV, offer_stored_tracking, store_tracking, tracking_store
from motion.protocol import Acceleration, Command, PidGains
from motion.transport import Reply
from tests.motion_rig import Rig, arm_config, emulated_arm


def _tuned(config: ArmConfig, gain_scale: float) -> ArmConfig:
    """Every emulated drive's position-loop gain times ``gain_scale`` (through the configuration's emulation).

    The collision observer is off: these tests are about the following-error check (arm6's collision thresholds,
    calibrated on the demo's path with the factory gains, trip on wrist_pitch, 0.073 against 0.067 N·m, in a
    full-range sweep on drives twice as stiff).
    """
    angle_kp = round(DEFAULT_PID.angle_kp * gain_scale)
    joints = tuple(
        dataclasses.replace(
            j.without_collision_threshold(),
            emulation=dataclasses.replace(j.emulation, pid=EmulatedPidConfig(angle_kp=angle_kp)),
        )
        for j in config.joints
    )
    return dataclasses.replace(config, joints=joints)


#: The sweeps stop this far inside the limits, deg: the position-limit monitor allows 0.1 deg, a drive's own loop
#: at full speed overshoots by a few tenths under gravity, and arm6's torque-mode PD, without inertia feed-forward,
#: by about inertia × acceleration / kp (2 deg on the shoulder: 0.9 kg·m² × 4.2 rad/s² / 2 N·m per deg).
MARGIN_DEG = {ControlMode.POSITION: 1.0, ControlMode.TORQUE: 3.0}


def _whole_range(config: ArmConfig) -> list[list[float]]:
    """Each joint alone to its upper limit, its lower limit and back to 0 at full speed (with a neighbour, the base
    turning while the shoulder reaches out saturates the base drive, tuned for the arm upright), then both arm2
    joints together end to end."""
    n = len(config.joints)
    margin = MARGIN_DEG[config.control.mode]
    upper = [j.position_max_deg - margin for j in config.joints]
    lower = [j.position_min_deg + margin for j in config.joints]
    targets = []
    for j in range(n):
        for end in (upper, lower):
            target = [0.0] * n
            target[j] = end[j]
            targets.append(target)
        targets.append([0.0] * n)
    if n == 2:
        targets += [upper, lower, [0.0] * n]
    return targets


class _Errors:
    """Per cycle: the raw |previous reference - measured| and the |expected - measured| the watchdog checks."""

    def __init__(self) -> None:
        self.raw: list[np.ndarray] = []
        self.residual: list[np.ndarray] = []
        self._previous: np.ndarray | None = None

    def __call__(self, controller: Controller, start_s: float, replies: list[Reply]) -> None:
        q = controller.axes.q_deg
        if self._previous is not None:
            self.raw.append(np.abs(self._previous - q))
        self.residual.append(np.abs(controller.tracking.expected_deg - q))
        self._previous = controller.reference.position.copy()


def _run_moves(rig: Rig, targets: Sequence[Sequence[float]]) -> _Errors:
    errors = _Errors()
    rig.controller.cycle_hooks.append(errors)
    supervisor = rig.supervisor
    assert supervisor is not None
    for target in targets:
        supervisor.move_to(target, speed_scale=1.0)
        assert supervisor.wait(30.0)  # a fault raises here
    return errors


#: (config, mode, rate or None for the configured one, gain scale, reply latency s, raw error it must exceed, as a
#: share of the following-error limit; position mode plans at 90 % of the velocity limits)
SWEEPS = [
    ("arm6.yaml", ControlMode.POSITION, None, 0.5, 0.002, 3.0),
    ("arm6.yaml", ControlMode.POSITION, None, 1.0, None, 2.7),
    ("arm6.yaml", ControlMode.POSITION, None, 2.0, None, 2.7),
    ("arm2.yaml", ControlMode.POSITION, 200.0, 0.5, None, 1.5),
    ("arm2.yaml", ControlMode.POSITION, 200.0, 1.0, None, 1.1),
    ("arm2.yaml", ControlMode.POSITION, 200.0, 2.0, 0.001, 1.1),
    ("arm2.yaml", ControlMode.TORQUE, None, 1.0, None, 0.0),
    ("arm2.yaml", ControlMode.TORQUE, 100.0, 1.0, 0.002, 1.0),
    ("arm6.yaml", ControlMode.TORQUE, None, 1.0, None, 0.0),
]


@pytest.mark.parametrize(("name", "mode", "rate_hz", "gain_scale", "latency_s", "raw_over"), SWEEPS)
def test_full_speed_through_the_whole_range_does_not_fault(
    name: str,
    mode: ControlMode,
    rate_hz: float | None,
    gain_scale: float,
    latency_s: float | None,
    raw_over: float,
    tmp_path: Path,
) -> None:
    config = _tuned(arm_config(name, mode=mode, rate_hz=rate_hz), gain_scale)
    targets = _whole_range(config)
    limit = config.safety.following_error_deg
    with emulated_arm(config, "sim", tmp_path, supervised=True, latency_s=latency_s) as rig:
        errors = _run_moves(rig, targets)
    raw, residual = np.max(errors.raw), np.max(errors.residual)
    assert raw > raw_over * limit or raw_over == 0.0, f"raw error {raw:.2f} deg: the case tests nothing"
    # the expectation stays well inside the threshold: a real deviation of half of it is still seen
    assert residual < 0.5 * limit, (residual, limit)


#: (config, mode, rate, speed scale, target, blocked motor id, block after s)
BLOCKS = [
    ("arm2.yaml", ControlMode.POSITION, 200.0, 0.4, [80.0, -100.0], 1, 0.4),
    ("arm2.yaml", ControlMode.POSITION, 200.0, 0.6, [60.0, -100.0], 2, 0.3),
    ("arm2.yaml", ControlMode.TORQUE, 500.0, 1.0, [80.0, -100.0], 2, 0.3),
    ("arm2.yaml", ControlMode.TORQUE, 200.0, 0.4, [80.0, -100.0], 1, 0.4),
    ("arm6.yaml", ControlMode.POSITION, 250.0, 0.6, [0.0, 0.0, 0.0, 0.0, 0.0, 150.0], 6, 0.4),
    ("arm6.yaml", ControlMode.POSITION, 250.0, 0.3, [0.0, 60.0, 0.0, 0.0, 0.0, 0.0], 2, 0.6),
]


def _cycles_to_detect(
    config: ArmConfig, speed: float, target: list[float], motor_id: int, after_s: float, tmp_path: Path, *, model: bool
) -> tuple[int, MotionFault]:
    with emulated_arm(config, "sim", tmp_path, supervised=True) as rig:
        rig.controller.tracking.enabled = model
        supervisor = rig.supervisor
        assert supervisor is not None
        supervisor.move_to(target, speed_scale=speed)
        rig.sleep(after_s)
        assert not supervisor.faults
        first = rig.controller.loop.next_cycle  # the first cycle that can see the block
        rig.emulator.add_fault(Fault(InjectedFault.BLOCKED, motor_id, start_s=rig.emulator.time_s))
        with pytest.raises(MotionFault) as info:
            supervisor.wait(5.0)
        return supervisor.halts[0].cycle - first + 1, info.value


@pytest.mark.parametrize(("name", "mode", "rate_hz", "speed", "target", "motor_id", "after_s"), BLOCKS)
def test_a_blocked_joint_is_caught_as_fast_as_by_the_raw_reference(
    name: str,
    mode: ControlMode,
    rate_hz: float,
    speed: float,
    target: list[float],
    motor_id: int,
    after_s: float,
    tmp_path: Path,
) -> None:
    config = _tuned(arm_config(name, mode=mode, rate_hz=rate_hz), 1.0)  # (the collision observer off: with it,
    # arm6's blocked joint is a collision first; here the following-error check is compared with what it was)
    before, _ = _cycles_to_detect(config, speed, target, motor_id, after_s, tmp_path, model=False)
    cycles, fault = _cycles_to_detect(config, speed, target, motor_id, after_s, tmp_path, model=True)
    assert fault.kind == "following_error"
    assert cycles <= before, (cycles, before)


def test_position_loop_prior_from_the_drive_through_the_gear() -> None:
    gains = dataclasses.replace(DEFAULT_PID, command=Command.READ_PID, angle_kp=80)
    loop = PositionLoop.from_drive(gains, Acceleration(Command.READ_ACCELERATION, 36_000), gear_ratio=9.0)
    assert loop.angle_gain_per_s == 80 * ANGLE_GAIN_PER_S_PER_UNIT
    assert loop.acceleration_dps2 == pytest.approx(4000.0)  # motor 36 000 deg/s² is 4 000 deg/s² at the joint
    none = PositionLoop.from_drive(gains, Acceleration(Command.READ_ACCELERATION, 0), gear_ratio=9.0)
    assert math.isinf(none.acceleration_dps2)  # 0 reads as "no limit"


def test_the_first_cycles_read_the_drives_loops(tmp_path: Path) -> None:
    config = _tuned(arm_config("arm6.yaml"), 0.5)
    with emulated_arm(config, "sim", tmp_path) as rig:
        tracking = rig.controller.tracking
        assert tracking.drive_settings == [None] * 6
        before = tracking.unread
        rig.sleep(6 * rig.controller.period_s)  # one drive per cycle, at the end of the batch
        assert before and not tracking.unread
        loops = tracking.position_loops()
    for joint, loop, settings in zip(config.joints, loops, tracking.drive_settings, strict=True):
        assert settings == (50, 36_000)
        assert loop.angle_gain_per_s == 50 * ANGLE_GAIN_PER_S_PER_UNIT
        assert loop.acceleration_dps2 == pytest.approx(36_000 / joint.gear_ratio)
    assert isinstance(DEFAULT_PID, PidGains)


@pytest.mark.parametrize("mode", [ControlMode.POSITION, ControlMode.TORQUE])
def test_the_model_keeps_no_memory_per_cycle(mode: ControlMode, tmp_path: Path) -> None:
    config = arm_config("arm6.yaml", mode=mode, rate_hz=250)
    with emulated_arm(config, "sim", tmp_path) as rig:
        controller = rig.controller
        controller.move_to([30.0, 20.0, -40.0, 45.0, 30.0, -60.0])
        rig.sleep(0.3)
        tracking = controller.tracking
        tracking._inertia_of = None  # the arm model's mass matrix is Pinocchio's work, not the model's
        ref = controller.reference
        q, qd, caps = controller.axes.q_deg, controller.axes.qd_dps, controller.setpoints.max_speed_dps
        t = rig.now()
        tracking.advance(t, q, qd)  # warm up
        tracking.command(t, ref.position, ref.velocity, ref.acceleration, caps)
        tracemalloc.start()
        for k in range(1, 50):
            tracking.advance(t + k * 0.004, q, qd)
            tracking.command(t + k * 0.004, ref.position, ref.velocity, ref.acceleration, caps)
        current, peak = tracemalloc.get_traced_memory()
        tracemalloc.stop()
    # no buffer per cycle: 49 cycles leave nothing behind and never hold more than a few small temporaries (torque
    # mode: the solve of the mass matrix)
    assert current < 1024 and peak < 2048, (current, peak)


def test_identification_finds_a_drive_whose_gain_scale_is_not_the_prior(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # a drive from another maker: the same 0x30 reading, but a loop 2.5x softer and a 3x lower acceleration than
    # the prior makes of it (the documents give no scale): the prior's expectation is off, identification finds it
    config = arm_config("arm2.yaml", mode=ControlMode.POSITION, rate_hz=200)
    with emulated_arm(config, "sim", tmp_path, supervised=True) as rig:
        supervisor = rig.supervisor
        assert supervisor is not None
        tracking = rig.controller.tracking
        rig.sleep(0.05)  # the drives' loop settings are read
        true = tracking.position_loops()
        tracking.set_position_loops(
            [PositionLoop(loop.angle_gain_per_s * 2.5, loop.acceleration_dps2 * 3) for loop in true]
        )
        fits = identify_position_loops(supervisor, config)
        for (name, fit), loop in zip(fits.items(), true, strict=True):
            assert fit.loop.angle_gain_per_s == pytest.approx(loop.angle_gain_per_s, rel=0.2), name
            assert fit.loop.acceleration_dps2 == pytest.approx(loop.acceleration_dps2, rel=0.3), name
            assert fit.rms_deg < 0.2 * fit.rms_prior_deg and fit.max_deg < 0.5, (name, fit)
        assert tracking.position_loops() == tuple(fit.loop for fit in fits.values())  # in use from now on

        # stored with the drive settings read at connect; offered to the next connection, where it is used for the
        # drives that still have those settings (not the retuned elbow)
        monkeypatch.setenv(STATE_DIR_ENV, str(tmp_path / "state"))
        path = store_tracking(config, rig.controller, fits)
        assert path == tracking_store(config) and path.parent == tmp_path / "state"
    stored = {j["name"]: j for j in json.loads(path.read_text())["joints"]}
    stored["elbow"]["drive_angle_kp"] = 80  # as if the elbow's gain had been changed with 0x31 since
    path.write_text(json.dumps({**json.loads(path.read_text()), "joints": list(stored.values())}))
    with emulated_arm(config, "sim", tmp_path) as rig:
        tracking = rig.controller.tracking
        assert offer_stored_tracking(config, rig.controller) == ["shoulder", "elbow"]
        rig.sleep(0.05)
        assert tracking.identified == [True, False]
        assert tracking.position_loops() == (fits["shoulder"].loop, true[1])
        path.write_text("{")
        assert offer_stored_tracking(config, rig.controller) == []
