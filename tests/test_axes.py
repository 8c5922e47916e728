"""Measured axis state: the multi-turn position tracked by unwrapping the encoder of every reply, its turns confirmed by
the drive's multi-turn angle (0x92) after any gap, and a lost frame told by a restart's sign alone."""

from __future__ import annotations

import numpy as np
import pytest

from motion.control.axes import AxisSpec, AxisStates
from motion.protocol import Bare, Command, Message, MotorState, MultiTurnAngle
from motion.transmission import ArmTransmission, Transmission
from motion.transport import Reply


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


# ------------------------------------------------------------------------------------- turns confirmed by 0x92

GEAR9 = Transmission(9.0, 1, 0.0, 0.1)
COUNTS = 1 << 14
VELOCITY_LIMIT_MOTOR_DPS = 1620.0  # arm2's shoulder: 180 deg/s behind 1:9


def _axis() -> AxisStates:
    axes = AxisStates([AxisSpec("j", 1, 14)], ArmTransmission([GEAR9]), velocity_limit_motor_dps=[1620.0])
    axes.initialise(0, multi_turn_deg=720.0, encoder=0)
    return axes


def _state(motor_deg: float, speed_dps: float = 0.0) -> MotorState:
    """A state reply of a drive whose multi-turn angle is ``motor_deg`` (its frame starting at encoder 0)."""
    return MotorState(Command.READ_STATUS_2, 30, 0.0, round(speed_dps), round(motor_deg / 360.0 * COUNTS) % COUNTS)


def _exchange(axes: AxisStates, t: float, *messages: Message | None) -> None:
    axes.absorb([Reply(1, Bare(Command.READ_STATUS_2), m, None if m is None else t) for m in messages])


def test_a_gap_in_the_replies_is_confirmed_by_0x92_which_puts_back_the_turns_the_encoder_missed() -> None:
    # issue: arm2's shoulder silent 0.5-0.75 s mid-move turned 398 motor deg unheard; its 0x92 reading of 864.7 motor
    # deg was taken for a restart. Now the axis is read with 0x92 until its turns are confirmed, and motion explains
    # the difference: whole turns put back, no frame lost
    axes = _axis()
    _exchange(axes, 0.002, _state(730.0))
    assert axes.anchored[0] and axes.unanchored(0.004).size == 0
    _exchange(axes, 0.004, None)  # its drive went silent
    assert not axes.anchored[0] and list(axes.unanchored(0.006)) == [0]  # 0x92 with every exchange from now on
    _exchange(axes, 0.254, _state(730.0 + 398.0), MultiTurnAngle(730.0 + 398.0))
    assert axes.motor_deg[0] == pytest.approx(1128.0, abs=360.0 / COUNTS)
    assert axes.q_deg[0] == pytest.approx(1128.0 / 9.0, abs=0.01)
    assert axes.anchored[0] and np.isnan(axes.frame_jump_deg[0]) and axes.turns_restored[0] == 1


@pytest.mark.parametrize("since_s", [0.12, 0.5])
def test_a_reply_longer_after_the_last_than_the_velocity_limit_unwraps_unanchors_the_axis(since_s: float) -> None:
    axes = _axis()
    _exchange(axes, 0.002, _state(730.0))
    assert axes.unwrap_gap_s[0] == pytest.approx(180.0 / VELOCITY_LIMIT_MOTOR_DPS)  # 0.11 s
    assert list(axes.unanchored(0.002 + since_s)) == [0]  # (asked before the exchange goes out)
    _exchange(axes, 0.002 + since_s, _state(730.0 + 190.0 + 360.0))  # the encoder alone sees 190 deg
    assert not axes.anchored[0]
    _exchange(axes, 0.004 + since_s, _state(730.0 + 190.0 + 360.0), MultiTurnAngle(730.0 + 190.0 + 360.0))
    assert axes.motor_deg[0] == pytest.approx(1280.0, abs=360.0 / COUNTS) and axes.anchored[0]


def test_the_encoder_is_unwrapped_the_way_its_reported_speed_predicts() -> None:
    # a joint beyond its velocity limit (falling with its drive off): 250 motor deg per sample, which the shortest way
    # round takes for -110; the speeds the replies report carry it, and its turns are confirmed by 0x92 meanwhile
    axes = _axis()
    angle = 720.0
    _exchange(axes, 0.0, _state(angle, speed_dps=25000.0))  # (the first reply after the anchor: no prediction yet)
    for k in range(1, 20):
        angle += 250.0
        _exchange(axes, 0.01 * k, _state(angle, speed_dps=25000.0))
        assert axes.motor_deg[0] == pytest.approx(angle, abs=360.0 / COUNTS)
    assert list(axes.unanchored(0.2)) == [0]  # 250 deg a sample: beyond half a turn, confirmed by 0x92


def test_a_reading_a_turn_away_that_no_gap_explains_or_in_the_first_turn_after_one_is_a_lost_frame() -> None:
    axes = _axis()
    _exchange(axes, 0.002, _state(730.0))
    _exchange(axes, 0.004, _state(731.0), MultiTurnAngle(11.0))  # restarted: its first turn, 720 deg short
    assert axes.frame_jump_deg[0] == pytest.approx(-720.0, abs=0.1)
    _exchange(axes, 0.006, _state(1200.0, 0), MultiTurnAngle(480.0))  # and it stays lost, the old frame kept
    assert axes.frame_jump_deg[0] == pytest.approx(-720.0, abs=0.1) and axes.turns_restored[0] == 0
    # after a silence, a first-turn reading a turn away is a restart too: the two cannot be told apart there
    axes = _axis()
    _exchange(axes, 0.002, _state(370.0 + 360.0))
    _exchange(axes, 0.004, None)
    _exchange(axes, 0.5, _state(370.0 + 360.0), MultiTurnAngle(10.0))
    assert axes.frame_jump_deg[0] == pytest.approx(-720.0, abs=0.1)


def test_a_motor_beyond_what_its_speed_field_carries_is_confirmed_only_once_its_speed_is_told_again() -> None:
    # a reading taken a moment after the state reply: at a full field (32767 deg/s: maybe a faster motor's) how far
    # the shaft turned between the two is unknown, so the reading neither puts turns back nor loses the frame
    axes = _axis()
    _exchange(axes, 0.0, _state(720.0, speed_dps=32767.0))
    assert list(axes.unanchored(0.001)) == [0]
    _exchange(axes, 0.004, _state(900.0, speed_dps=32767.0), MultiTurnAngle(900.0 + 720.0))
    assert not axes.anchored[0] and axes.turns_restored[0] == 0 and np.isnan(axes.frame_jump_deg[0])
    _exchange(axes, 0.008, _state(1620.0, speed_dps=0.0), MultiTurnAngle(1620.0))  # slowed down: told again
    assert axes.anchored[0] and axes.motor_deg[0] == pytest.approx(1620.0, abs=360.0 / COUNTS)
