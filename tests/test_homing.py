"""Homing against a hard stop (issue 16), on emulated drives in simulated time."""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

from motion.api import Arm
from motion.config import ArmConfig, load_config
from motion.control.turns import TurnError
from motion.homing import HomingError, homed_joints, homing_variant, turns_to_stop
from motion.transmission import Transmission
from tests.motion_rig import CONFIGS

ARM6 = CONFIGS / "arm6.yaml"
SHOULDER = 1  # arm6's shoulder_pitch, 1:36: one motor turn is 10 deg of the joint


def _arm6(**homing: float) -> ArmConfig:
    config = load_config(ARM6)
    joints = list(config.joints)
    stop = joints[SHOULDER].homing
    assert stop is not None
    joints[SHOULDER] = dataclasses.replace(joints[SHOULDER], homing=dataclasses.replace(stop, **homing))
    return dataclasses.replace(config, joints=tuple(joints))


def test_homing_from_an_unknown_start_finds_the_turns_and_the_arm_then_goes_where_commanded() -> None:
    # the drives power up with the shoulder at -47.3 deg, outside its window: it reads 2.7 deg (five 10 deg turns
    # lost); homed at connect, before the arm is handed over
    arm = Arm(_arm6(speed_dps=10.0), emulate=True, start_pose={"shoulder_pitch": -47.3}, home=["shoulder_pitch"])
    with arm:
        assert arm.plant is not None
        [result] = arm.homing
        assert result.turns_correction == -5
        assert abs(result.remainder_deg) < 0.05
        assert arm.turns[SHOULDER].source.value == "homed"
        true = arm.plant.joint_positions_deg()
        assert true[SHOULDER] == pytest.approx(-119.0, abs=0.05)  # off the stop (-125), inside the limit (-120)
        assert arm.positions()["shoulder_pitch"] == pytest.approx(true[SHOULDER], abs=0.1)
        for target in (-30.0, 40.0):
            arm.move_to({"shoulder_pitch": target})
            arm.sleep(0.3)
            true = arm.plant.joint_positions_deg()
            assert true[SHOULDER] == pytest.approx(target, abs=0.1)
            assert arm.positions()["shoulder_pitch"] == pytest.approx(true[SHOULDER], abs=0.1)


def test_without_homing_that_start_is_refused_at_connect() -> None:
    with pytest.raises(TurnError, match=r"joint shoulder_pitch: .*\[-3, 3\]"):
        Arm(load_config(ARM6), emulate=True, start_pose={"shoulder_pitch": -47.3}).connect()


def test_no_stop_within_the_travel_is_an_error_and_the_arm_stays_halted() -> None:
    with Arm(_arm6(speed_dps=10.0, max_travel_deg=20.0), emulate=True) as arm, pytest.raises(HomingError) as caught:
        arm.home(["shoulder_pitch"])
    assert "no stop within 20 deg" in str(caught.value)


def test_joints_that_cannot_be_homed_are_refused_by_name() -> None:
    config = load_config(ARM6)
    with pytest.raises(HomingError, match="unknown joint 'knee'"):
        homed_joints(config, ["knee"])
    with pytest.raises(HomingError, match="joint elbow_pitch has no hard stop configured.*shoulder_pitch"):
        homed_joints(config, ["elbow_pitch"])
    with pytest.raises(HomingError, match="named twice"):
        homed_joints(config, ["shoulder_pitch", "shoulder_pitch"])
    with pytest.raises(HomingError, match="joint elbow_pitch"):
        Arm(config, emulate=True, home=["elbow_pitch"])  # refused before anything opens


def test_the_homing_variant_frees_only_what_homing_needs() -> None:
    config = load_config(ARM6)
    variant = homing_variant(config, ["shoulder_pitch"])
    assert variant.control.mode.value == "position"
    shoulder, elbow = variant.joints[SHOULDER], variant.joints[2]
    assert shoulder.position_min_deg < -1e5 and shoulder.power_on_window_deg is None
    assert (elbow.position_min_deg, elbow.position_max_deg) == (-150.0, 150.0)  # the others keep their limits
    assert all(j.collision_threshold_nm is None for j in variant.joints)  # the observer needs the unknown angle
    assert variant.safety == config.safety


def test_a_stop_found_between_whole_turns_is_refused() -> None:
    gear36 = Transmission(gear_ratio=36, direction=1, zero_offset_deg=0.0, torque_constant_nm_per_a=0.1)
    turns, remainder = turns_to_stop("j", gear36, -75.2, -125.0)
    assert turns == -5
    assert remainder == pytest.approx(-0.2)
    with pytest.raises(HomingError, match=r"-3\.00 deg from stop_deg -125"):
        turns_to_stop("j", gear36, -78.0, -125.0)


def test_cli_home_prints_the_correction_and_lands_inside_the_limits(tmp_path: Path) -> None:
    data = yaml.safe_load(ARM6.read_text())
    data["joints"][SHOULDER]["homing"]["speed_dps"] = 20.0
    data["model"]["urdf"] = str(CONFIGS / data["model"]["urdf"])
    config = tmp_path / "arm6.yaml"
    config.write_text(yaml.safe_dump(data))
    command = [sys.executable, "-m", "motion.cli", "home", "--config", str(config), "shoulder_pitch", "--emulate"]
    result = subprocess.run([*command, "--json"], capture_output=True, text=True, check=False, timeout=120)
    assert result.returncode == 0, result.stderr
    report = json.loads(result.stdout)
    [joint] = report["joints"]
    assert joint["joint"] == "shoulder_pitch" and joint["turns_correction"] == 0  # emulated drives: powered at zero
    assert abs(joint["remainder_deg"]) < 0.05
    positions = {j["name"]: j["position_deg"] for j in report["status"]["joints"]}
    assert positions["shoulder_pitch"] == pytest.approx(-119.0, abs=0.1)
    refused = subprocess.run([*command[:-2], "elbow_pitch"], capture_output=True, text=True, check=False)
    assert refused.returncode == 2 and "no hard stop configured" in refused.stderr
    np.testing.assert_equal(refused.stdout, "")
