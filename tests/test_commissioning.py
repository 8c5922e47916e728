"""The holding check (issue 33 §2) on emulated arms in simulated time: what it judges, and what it refuses."""

from __future__ import annotations

import pytest

from motion.api import Arm
from motion.api.commissioning import check_holding
from motion.errors import MotionError, MotionFault
from tests.test_telemetry import CONFIGS


def test_an_arm_as_configured_holds_as_its_model_says() -> None:
    with Arm.from_config(CONFIGS / "arm6.yaml", emulate=True, initial_deg=[0, 30, -45, 0, 20, 0]) as arm:
        verdicts = check_holding(arm)
    judged = {v.name for v in verdicts if v.judged}
    assert {"shoulder_pitch", "elbow_pitch"} <= judged  # gravity loads them at this pose
    assert all(v.matches for v in verdicts), [v.text() for v in verdicts]


def test_a_halted_arm_raises_its_fault_and_a_moving_one_is_refused() -> None:
    with Arm.from_config(CONFIGS / "arm2.yaml", emulate=True) as arm:
        handle = arm.move_to({"shoulder": 30.0}, wait=False)
        arm.sleep(0.05)
        with pytest.raises(MotionError, match="needs the arm at rest and ready; it is moving"):
            check_holding(arm)
        handle.wait()
        arm.stop()
        with pytest.raises(MotionFault) as caught:
            check_holding(arm)
        assert caught.value.kind.value == "stop"
