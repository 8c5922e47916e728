"""Turn offsets of geared joints (issue 16): the resolution rules at connect, one by one."""

from __future__ import annotations

import numpy as np
import pytest

from motion.control.turns import (
    CONTINUITY_MOTOR_DEG,
    POWER_UP_SAG_MOTOR_DEG,
    Source,
    TurnError,
    TurnRecord,
    drive_reading,
    edge_margin_deg,
    resolve_joint,
    resolve_turns,
)
from motion.transmission import ArmTransmission, Transmission

GEAR9 = Transmission(gear_ratio=9, direction=1, zero_offset_deg=0.0, torque_constant_nm_per_a=0.1)
MIRRORED36 = Transmission(gear_ratio=36, direction=-1, zero_offset_deg=2.5, torque_constant_nm_per_a=0.1)


def power_up_reading(t: Transmission, joint_deg: float) -> float:
    """What a drive without a multi-turn battery reads when it powers up with its joint at ``joint_deg``."""
    return float(np.mod(t.motor_deg(joint_deg), 360.0))


@pytest.mark.parametrize(
    ("transmission", "joint_deg", "window"),
    [
        (GEAR9, 60.0, (55.0, 65.0)),
        (GEAR9, -50.0, (-55.0, -45.0)),
        (GEAR9, 0.3, (-5.0, 5.0)),
        (MIRRORED36, -30.0, (-32.0, -27.0)),
        (MIRRORED36, 87.1, (85.0, 90.0)),
    ],
)
def test_a_joint_powered_up_inside_its_window_is_found_there(
    transmission: Transmission, joint_deg: float, window: tuple[float, float]
) -> None:
    reading = power_up_reading(transmission, joint_deg)
    found = resolve_joint("j", transmission, reading, window, None)
    assert found.source is Source.WINDOW
    assert found.joint_deg == pytest.approx(joint_deg, abs=1e-9)
    assert transmission.joint_deg(reading + 360.0 * found.turns) == pytest.approx(joint_deg, abs=1e-9)


def test_a_reading_that_settled_a_little_below_the_first_turn_still_counts_as_a_power_up() -> None:
    found = resolve_joint("j", GEAR9, -0.4 * POWER_UP_SAG_MOTOR_DEG, (-5.0, 5.0), None)
    assert found.source is Source.WINDOW
    assert found.joint_deg == pytest.approx(-0.4 * POWER_UP_SAG_MOTOR_DEG / 9)


def test_a_joint_outside_its_window_is_refused_naming_joint_reading_and_window() -> None:
    reading = power_up_reading(GEAR9, 20.0)  # 180 motor deg: the joint at 20 or -20 or 60 ...
    with pytest.raises(TurnError) as caught:
        resolve_joint("shoulder", GEAR9, reading, (-5.0, 5.0), None)
    text = str(caught.value)
    assert "joint shoulder" in text
    assert "180.00 motor deg" in text
    assert "[-5, 5]" in text
    assert "-20.00 or 20.00 deg" in text
    assert "home" in text


def test_a_landing_near_a_window_edge_is_refused() -> None:
    window = (-5.0, 5.0)
    margin = edge_margin_deg(GEAR9, window)
    assert margin == 1.0  # a quarter of the 30 deg gap, capped at 1 deg
    with pytest.raises(TurnError, match="within 1 deg of an edge"):
        resolve_joint("j", GEAR9, power_up_reading(GEAR9, 4.5), window, None)
    assert resolve_joint("j", GEAR9, power_up_reading(GEAR9, 3.9), window, None).source is Source.WINDOW


def test_the_edge_margin_shrinks_with_the_gap_between_windows() -> None:
    # 1:36 -> one turn is 10 deg; a 9 deg window leaves 1 deg of gap, a quarter of it is the margin
    assert edge_margin_deg(MIRRORED36, (0.0, 9.0)) == pytest.approx(0.25)


def test_a_drive_that_turned_since_power_up_without_a_record_is_refused() -> None:
    with pytest.raises(TurnError, match="turned since it powered up"):
        resolve_joint("j", GEAR9, 900.0, (-5.0, 5.0), None)


def test_a_record_that_continues_into_the_reading_keeps_its_turns() -> None:
    record = TurnRecord(1, turns=2, reading_deg=905.0, source=Source.WINDOW)
    found = resolve_joint("j", GEAR9, 900.0, (-5.0, 5.0), record)
    assert (found.source, found.turns) == (Source.KEPT, 2)
    assert found.joint_deg == pytest.approx((900.0 + 720.0) / 9)


def test_a_record_that_does_not_continue_is_left_aside() -> None:
    record = TurnRecord(1, turns=2, reading_deg=900.0 + 2 * CONTINUITY_MOTOR_DEG, source=Source.WINDOW)
    with pytest.raises(TurnError, match="turned since it powered up"):
        resolve_joint("j", GEAR9, 900.0, (-5.0, 5.0), record)


def test_a_first_turn_reading_outside_the_window_keeps_a_continuing_record() -> None:
    # the last session left the joint at 30 deg (270 motor deg, the first turn): not a power-up in the window
    record = TurnRecord(1, turns=0, reading_deg=270.0, source=Source.WINDOW)
    found = resolve_joint("j", GEAR9, 270.5, (-5.0, 5.0), record)
    assert (found.source, found.turns) == (Source.KEPT, 0)


def test_a_first_turn_reading_that_window_and_record_explain_differently_is_refused() -> None:
    # parked at 38 deg (342 motor deg); powered up at -2 deg, the drive would read 342 too
    record = TurnRecord(1, turns=0, reading_deg=342.0, source=Source.WINDOW)
    with pytest.raises(TurnError, match="--forget-turns") as caught:
        resolve_joint("j", GEAR9, 342.0, (-5.0, 5.0), record)
    assert "-2.00 deg" in str(caught.value)
    assert "38.00 deg" in str(caught.value)
    assert resolve_joint("j", GEAR9, 342.0, (-5.0, 5.0), None).joint_deg == pytest.approx(-2.0)


def test_a_joint_without_a_window_assumes_the_drives_count_or_keeps_a_record() -> None:
    assert resolve_joint("j", GEAR9, 900.0, None, None).source is Source.ASSUMED
    assert resolve_joint("j", GEAR9, 900.0, None, None).turns == 0
    record = TurnRecord(1, turns=-1, reading_deg=880.0, source=Source.HOMED)
    assert resolve_joint("j", GEAR9, 900.0, None, record).turns == -1


def test_every_refusal_is_reported_at_once() -> None:
    with pytest.raises(TurnError) as caught:
        resolve_turns(
            ["a", "b", "c"],
            [GEAR9, GEAR9, GEAR9],
            [180.0, 0.0, 180.0],
            [(-5.0, 5.0), (-5.0, 5.0), (-5.0, 5.0)],
            [None, None, None],
        )
    lines = str(caught.value).splitlines()
    assert [line.split(":")[0] for line in lines] == ["joint a", "joint c"]


def test_turns_fold_into_the_transmission_exactly() -> None:
    arm = ArmTransmission([GEAR9, MIRRORED36], ["a", "b"])
    shifted = arm.with_turns([3, -2])
    readings = np.array([123.4, -50.0])
    expected = arm.joint_deg(readings + 360.0 * np.array([3, -2]))
    np.testing.assert_allclose(shifted.joint_deg(readings), expected, atol=1e-9)
    np.testing.assert_allclose(shifted.motor_deg(expected), readings, atol=1e-9)
    assert drive_reading(MIRRORED36, float(expected[1]), -2) == pytest.approx(-50.0)
