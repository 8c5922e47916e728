"""Measured axis state: the multi-turn position tracked by unwrapping the encoder of every reply."""

from __future__ import annotations

import numpy as np
import pytest

from motion.control.axes import AxisSpec, AxisStates
from motion.protocol import Command, MotorState
from motion.transmission import ArmTransmission, Transmission


@pytest.mark.parametrize("bits", [12, 14, 16, 18])
@pytest.mark.parametrize("step_deg", [100.0, -170.0])
def test_encoder_unwrapping_tracks_multi_turn_position(bits: int, step_deg: float) -> None:
    axes = AxisStates([AxisSpec("j", 1, bits)], ArmTransmission([Transmission(9.0, -1, 5.0, 0.1)]))
    counts = 1 << min(bits, 16)  # the uint16 fields carry the top 16 bits of wider encoders
    axes.initialise(0, multi_turn_deg=720.0, encoder=0)
    angle = 720.0
    for _ in range(300):  # 300 rotor steps of less than half a turn: dozens of encoder wraps
        angle += step_deg
        encoder = round((angle - 720.0) / 360.0 * counts) % counts
        axes.update(0, MotorState(Command.READ_STATUS_2, 30, 0.0, 0, encoder), 0.0)
    assert abs(axes.motor_deg[0] - angle) <= 360.0 / counts
    assert np.isclose(axes.q_deg[0], -angle / 9.0 + 5.0, atol=0.01)  # direction -1, gear 9, offset 5 deg
