"""Settings the schema accepts meet the loop's rate: what a configuration changed to a low rate must still hold."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest

from motion import Arm
from motion.config import load_config, load_config_or_example
from motion.errors import ConfigError
from tests.motion_rig import CONFIGS

ARM6_V3 = load_config_or_example("arm6_v3.yaml")


def test_a_link_timeout_shorter_than_the_gap_between_frames_is_refused(tmp_path: Path) -> None:
    # arm6_v3 sets 40 ms; at 20 Hz every drive cut its output between two frames and a plain move faulted
    # following_error (the joints never moved)
    slow = tmp_path / "arm6_v3.yaml"
    slow.write_text((CONFIGS / "arm6_v3.yaml").read_text().replace("rate_hz: 125", "rate_hz: 20"))
    (tmp_path / "arm6.urdf").write_text((CONFIGS / "arm6.urdf").read_text())
    with pytest.raises(ConfigError, match=r"safety\.link_timeout_ms.*40 ms is shorter than a loop at 20 Hz") as e:
        load_config(slow)
    assert "at least 2 periods, 100 ms" in str(e.value)
    changed = dataclasses.replace(ARM6_V3, control=dataclasses.replace(ARM6_V3.control, rate_hz=20.0))
    with pytest.raises(ConfigError, match="link_timeout_ms"):
        Arm(changed, emulate=True).connect()
    # at 20 Hz with the default (five periods) the same move arrives
    default = dataclasses.replace(changed, safety=dataclasses.replace(changed.safety, link_timeout_ms=None))
    with Arm(default, emulate=True) as arm:
        arrival = arm.move_to({"shoulder_pitch": 30.0, "elbow_pitch": -45.0}).arrival
        assert arrival is not None and arrival.arrived
        assert arm.status().state == "ready"


ARM6 = load_config_or_example("arm6.yaml")


@pytest.mark.parametrize("rate_hz", [17.0, 20.0])  # (arm6 unwraps its flange above 16 Hz)
def test_plain_moves_at_a_low_rate_raise_no_collision(rate_hz: float) -> None:
    # arm6 in position mode at 20 Hz, drives as modelled: the shoulder's collision signal reached 1.63 N·m against a
    # bound of 1.16 two cycles after the stream stopped, while its drive still closed the lag of the last step (the
    # bound took the position-mode steps' torque from the reference's speed, zero by then)
    config = dataclasses.replace(ARM6, control=dataclasses.replace(ARM6.control, rate_hz=rate_hz))
    targets = [
        {"shoulder_pitch": 30.0, "elbow_pitch": -45.0},
        {"base_yaw": 40.0, "wrist_pitch": 20.0},
        {"shoulder_pitch": -20.0, "elbow_pitch": 30.0, "base_yaw": -30.0},
        {j.name: 0.0 for j in ARM6.joints},
    ]
    with Arm(config, emulate=True) as arm:
        for target in targets:
            arm.move_to(target)
        assert arm.status().state == "ready"
