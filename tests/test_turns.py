"""Turn offsets of geared joints (issue 16): the resolution rules at connect, one by one."""

from __future__ import annotations

import dataclasses
import re
from pathlib import Path

import numpy as np
import pytest

from kinematics.plant import ArmPlant
from motion import Arm
from motion.api import measure_modes
from motion.compose import build_controller, build_supervisor, feedforward_for, resolve_frames
from motion.config import ArmConfig, load_config
from motion.control.controller import Controller
from motion.control.turns import (
    CONTINUITY_MOTOR_DEG,
    POWER_UP_SAG_MOTOR_DEG,
    Source,
    TurnError,
    TurnRecord,
    ambiguous_after,
    drive_reading,
    edge_margin_deg,
    resolve_joint,
    resolve_output_joint,
    resolve_turns,
)
from motion.emulator import Emulator
from motion.emulator.arm import arm_emulator
from motion.emulator.drive import RunState
from motion.emulator.faults import parse_fault
from motion.emulator.simulated import SimulatedBus, SimulatedClock, Simulation
from motion.errors import ConfigError, FaultKind, MotionFault
from motion.keep import STATE_DIR_ENV, load_turn_records, save_turn_records, turns_store
from motion.protocol import WireProtocol
from motion.protocol.table import ProtocolFamily
from motion.transmission import ArmTransmission, Transmission
from tests.motion_rig import CONFIGS, arm_config

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


# ---------------------------------------------------------------------------------------------- on emulated drives


def _arm2_with_windows(shoulder: tuple[float, float], elbow: tuple[float, float]) -> ArmConfig:
    config = arm_config("arm2.yaml", rate_hz=200)
    windows = (shoulder, elbow)
    joints = tuple(dataclasses.replace(j, power_on_window_deg=w) for j, w in zip(config.joints, windows, strict=True))
    return dataclasses.replace(config, joints=joints)


def _powered_up_at(config: ArmConfig, pose_deg: list[float]) -> tuple[Emulator, ArmPlant, Controller]:
    """arm2's emulated drives powered up with the arm at ``pose_deg`` (their multi-turn angles restart from the
    single-turn reading), and a controller on them in simulated time."""
    emulator, plant = arm_emulator(config, initial_deg=pose_deg)
    for drive in emulator.drives.values():
        drive.power_cycle()
    simulation = Simulation(emulator, WireProtocol.CAN)
    controller = build_controller(
        config, SimulatedBus(simulation), feedforward=feedforward_for(config), clock=SimulatedClock(simulation)
    )
    return emulator, plant, controller


def _moves_where_commanded(config: ArmConfig, controller: Controller, plant: ArmPlant) -> None:
    """A supervised move of arm2 to (20, 10) deg lands there, as the plant and the controller see it."""
    supervisor = build_supervisor(config, controller)
    supervisor.start()
    try:
        supervisor.move_to([20.0, 10.0], 0.5)
        assert supervisor.wait(10.0)
        controller.pause(0.5)
        np.testing.assert_allclose(plant.joint_positions_deg(), [20.0, 10.0], atol=0.1)
        np.testing.assert_allclose(controller.snapshot.position_deg, [20.0, 10.0], atol=0.1)
    finally:
        supervisor.close()


def test_arm2_powered_up_away_from_zero_is_read_where_it_is_and_moves_where_commanded() -> None:
    config = _arm2_with_windows((55.0, 65.0), (-55.0, -45.0))
    emulator, plant, controller = _powered_up_at(config, [60.0, -50.0])
    readings = [drive.angle_deg for drive in emulator.drives.values()]
    assert all(0.0 <= r < 360.0 for r in readings)  # the drives know the joints only modulo 40 deg
    turns = resolve_frames(controller, config)
    assert [(t.source, t.turns) for t in turns] == [(Source.WINDOW, 1), (Source.WINDOW, 1)]
    np.testing.assert_allclose(controller.read_positions(), [60.0, -50.0], atol=0.01)
    _moves_where_commanded(config, controller, plant)


def test_a_direct_drive_joint_without_a_window_powered_up_below_zero_is_refused_with_the_window_to_set() -> None:
    # issue 33 §7: a 1:1 elbow without a window powered up 20 deg off its zero reads 340 (arm2's elbow is mounted
    # mirrored: +20 at the joint is -20 at the motor): connect took it with a warning and the first move faulted on
    # its set-point; now it is refused (the CLI exits 2), naming the window that finds the turn
    config = _arm2_with_windows((-5.0, 5.0), (-5.0, 5.0))
    elbow = dataclasses.replace(config.joints[1], gear_ratio=1.0, power_on_window_deg=None)
    config = dataclasses.replace(config, joints=(config.joints[0], elbow))
    emulator, _, controller = _powered_up_at(config, [0.0, 20.0])
    assert emulator.drives[elbow.motor_id].angle_deg == pytest.approx(340.0, abs=0.01)
    with pytest.raises(TurnError) as caught:
        resolve_frames(controller, config)
    text = str(caught.value)
    assert re.search(r"joint elbow: the drive reads 3(39\.9\d|40\.0\d) motor deg", text), text
    assert re.search(r"puts the joint at -3(39\.9\d|40\.0\d) deg, outside its limits \[-135, 135\]", text), text
    assert "power_on_window_deg: [-135, 135]" in text
    # ... and with that window the same drive is read where the joint is
    windowed = dataclasses.replace(
        config, joints=(config.joints[0], dataclasses.replace(elbow, power_on_window_deg=(-135.0, 135.0)))
    )
    _, _, controller = _powered_up_at(windowed, [0.0, 20.0])
    turns = resolve_frames(controller, windowed)
    assert (turns[1].source, turns[1].turns) == (Source.WINDOW, -1)
    np.testing.assert_allclose(controller.read_positions(), [0.0, 20.0], atol=0.05)  # (the arm sags a little)


def test_a_window_that_misses_the_true_pose_is_refused_before_any_command() -> None:
    config = _arm2_with_windows((55.0, 65.0), (-25.0, -15.0))
    emulator, plant, controller = _powered_up_at(config, [60.0, -50.0])
    with pytest.raises(TurnError) as caught:
        resolve_frames(controller, config)
    assert "joint elbow" in str(caught.value) and "[-25, -15]" in str(caught.value)
    assert "shoulder" not in str(caught.value)
    assert all(drive.state is RunState.OFF for drive in emulator.drives.values())  # nothing was commanded
    np.testing.assert_allclose(plant.joint_positions_deg(), [60.0, -50.0], atol=0.05)


def test_records_are_kept_per_arm_and_bus_and_a_bad_file_is_left_aside(caplog: pytest.LogCaptureFixture) -> None:
    config = _arm2_with_windows((55.0, 65.0), (-55.0, -45.0))
    _, _, controller = _powered_up_at(config, [60.0, -50.0])
    turns = resolve_frames(controller, config)
    controller.read_positions()
    path = save_turn_records(config, "can slcan:/dev/ttyACM0", controller, (t.source for t in turns))
    assert path == turns_store(config)
    records = load_turn_records(config, "can slcan:/dev/ttyACM0")
    assert {name: (r.motor_id, r.turns) for name, r in records.items()} == {"shoulder": (1, 1), "elbow": (2, 1)}
    assert records["shoulder"].reading_deg == pytest.approx(180.0, abs=0.1)  # the drive's own frame
    assert load_turn_records(config, "can slcan:/dev/ttyACM1") == {}  # another bus: other drives
    path.write_text("{not json")
    assert load_turn_records(config, "can slcan:/dev/ttyACM0") == {}
    assert "recorded turn offsets ignored" in caplog.text


# ---------------------------------------------------------------------------------------------- V3: output-shaft angles


@pytest.mark.parametrize(
    ("reading_output_deg", "source", "turns", "joint_deg"),
    [
        (50.0, Source.ABSOLUTE, 0, 50.0),  # issue 31 §3: a V3 reading of 50.00 deg (0x241#9200000088130000)
        (-10.0, Source.ABSOLUTE, 0, -10.0),  # a drive that keeps its multi-turn value
        (350.0, Source.OUTPUT_TURN, -9, -10.0),  # single-turn mode, powered up at -10 deg: one output turn back
        (400.0, Source.OUTPUT_TURN, -9, 40.0),
    ],
)
def test_an_output_shaft_reading_is_the_joints_angle_or_one_output_turn_from_it(
    reading_output_deg: float, source: Source, turns: int, joint_deg: float
) -> None:
    joint = resolve_output_joint("shoulder", GEAR9, reading_output_deg * 9, (-90.0, 90.0), None, output_turn=9)
    assert (joint.source, joint.turns) == (source, turns)
    assert joint.joint_deg == pytest.approx(joint_deg)


def test_an_output_shaft_reading_no_whole_turn_brings_inside_the_limits_is_refused() -> None:
    with pytest.raises(
        TurnError,
        match=r"joint shoulder: the drive reads 200\.00 output deg, which puts the joint at "
        r"200\.00 deg, outside its limits \[-90, 90\], and no whole output turn \(360 deg",
    ):
        resolve_output_joint("shoulder", GEAR9, 200.0 * 9, (-90.0, 90.0), None, output_turn=9)
    # limits spanning more than a turn: a reading outside them cannot be told (two turns would do)
    with pytest.raises(TurnError, match="2 whole output turns would bring it inside"):
        resolve_output_joint("roll", GEAR9, 550.0 * 9, (-200.0, 200.0), None, output_turn=9)  # 190 or -170


def test_an_output_shaft_drive_that_ran_since_the_record_keeps_its_turns_wherever_the_joint_went() -> None:
    record = TurnRecord(1, turns=-9, reading_deg=300.0 * 9, source=Source.OUTPUT_TURN, power_on=(10.0, 1000.0))
    for powered_since, expected in ((True, (Source.KEPT, -9)), (False, (Source.OUTPUT_TURN, -9))):
        joint = resolve_output_joint(
            "shoulder", GEAR9, 350.0 * 9, (-90.0, 90.0), record, powered_since=powered_since, output_turn=9
        )
        assert (joint.source, joint.turns) == expected


@pytest.mark.parametrize(
    ("pose", "readings", "resolved"),
    [
        # a reading of 50.00 deg was refused before (§3); the elbow turns the other way: -10 deg reads 10
        ([50.0, -10.0], [50.0, 10.0], [(Source.ABSOLUTE, 0), (Source.ABSOLUTE, 0)]),
        # single-turn mode: -10 deg reads 350, the elbow at 50 reads 310 (-50): one output turn each
        ([-10.0, 50.0], [350.0, 310.0], [(Source.OUTPUT_TURN, -9), (Source.OUTPUT_TURN, -9)]),
    ],
)
def test_v3_arm2_powered_up_away_from_zero_is_read_where_it_is_without_a_window(
    pose: list[float], readings: list[float], resolved: list[tuple[Source, int]]
) -> None:
    # arm2's windows ([-5, 5]) are for the older drives: a V3 drive's reading is the output's, 0..360 deg after a
    # power-up in single-turn mode (the emulated drives' default)
    config = arm_config("arm2.yaml", rate_hz=200)
    emulator, plant = arm_emulator(config, initial_deg=pose, family=ProtocolFamily.V3)
    for drive in emulator.drives.values():
        drive.power_cycle()
    read = [drive.angle_deg / drive.model.gear_ratio for drive in emulator.drives.values()]
    assert read == pytest.approx(readings, abs=0.05)
    simulation = Simulation(emulator, WireProtocol.CAN)
    controller = build_controller(
        config,
        SimulatedBus(simulation, ProtocolFamily.V3),
        feedforward=feedforward_for(config),
        clock=SimulatedClock(simulation),
    )
    turns = resolve_frames(controller, config)
    assert [(t.source, t.turns) for t in turns] == resolved
    np.testing.assert_allclose(controller.read_positions(), pose, atol=0.05)
    _moves_where_commanded(config, controller, plant)


def test_an_output_shaft_reading_of_a_drive_without_a_whole_reduction_is_refused_saying_why() -> None:
    # (review: it divided by the zero output turn)
    odd = Transmission(gear_ratio=9.5, direction=1, zero_offset_deg=0.0, torque_constant_nm_per_a=0.1)
    with pytest.raises(TurnError, match=r"reads 200\.00 output deg.*no whole number of motor turns"):
        resolve_output_joint("j", odd, 200.0 * 9.5, (-90.0, 90.0), None, output_turn=0)
    assert resolve_output_joint("j", odd, 50.0 * 9.5, (-90.0, 90.0), None, output_turn=0).source is Source.ABSOLUTE


def test_a_joint_left_a_whole_turn_from_its_window_is_continued_with_keep_turns_and_never_put_elsewhere() -> None:
    # issue 33 §1: arm2's shoulder (1:9) left at 40 deg reads 360 motor deg, as a drive powered up there would: the
    # next session cannot tell. It is refused with both answers and the condition of each (never --forget-turns
    # alone, which put the joint at 0 while it stood at 40), and --keep-turns (the drives stayed powered) continues
    config = arm_config("arm2.yaml", rate_hz=200)
    emulator, _ = arm_emulator(config, initial_deg=[40.0, 0.0])  # (drives not power-cycled: they count on)
    simulation = Simulation(emulator, WireProtocol.CAN)
    controller = build_controller(config, SimulatedBus(simulation), clock=SimulatedClock(simulation))
    shoulder = controller.base_transmission.transmissions[0]
    window = config.joints[0].power_on_window_deg
    assert window is not None and ambiguous_after(shoulder, 40.0, 0, window) == -1  # the session's end warns
    assert ambiguous_after(shoulder, 35.0, 0, window) is None  # 315 motor deg: no window count lands there
    records = {
        "shoulder": TurnRecord(1, turns=0, reading_deg=360.0, source=Source.WINDOW),
        "elbow": TurnRecord(2, turns=0, reading_deg=0.0, source=Source.WINDOW),
    }
    with pytest.raises(TurnError) as caught:
        resolve_frames(controller, config, records=records)
    text = str(caught.value)
    assert "if the drives stayed powered since, the joint is at 40.00 deg (run again with --keep-turns" in text
    assert "if they were powered up with the joint inside its power_on_window_deg [-5, 5], it is at" in text
    assert "--forget-turns" in text and "if neither, home it" in text
    turns = resolve_frames(controller, config, records=records, stayed_powered=True)
    # the shoulder takes the record where its reading cannot tell; the elbow's reading tells (as it always did)
    assert [(t.source, t.turns) for t in turns] == [(Source.KEPT, 0), (Source.WINDOW, 0)]
    np.testing.assert_allclose(controller.read_positions(), [40.0, 0.0], atol=0.05)


# ------------------------------------------------------------------------------ the unwrapping envelope, restarts


def x10_bench(folder: Path, rate_hz: float = 10.0) -> ArmConfig:
    """bench1's lever on an X10-100 (1:35) at 60 deg/s: 210 motor degrees per sample at 10 Hz (written in
    ``folder``)."""
    text = (CONFIGS / "bench1.yaml").read_text()
    for old, new in (
        ("rate_hz: 200", f"rate_hz: {rate_hz:g}"),
        ("    gear_ratio: 9               # motor-shaft degrees per joint degree\n", "    actuator: X10-100\n"),
        ("    torque_constant_nm_per_a: 0.1\n", ""),
        ("velocity_limit_dps: 180.0", "velocity_limit_dps: 60.0"),
    ):
        assert old in text
        text = text.replace(old, new)
    path = folder / f"x10-{rate_hz:g}.yaml"
    path.write_text(text)
    return load_config(path)


def test_a_joint_whose_velocity_limit_the_encoder_cannot_unwrap_at_the_rate_is_refused_at_connect(
    tmp_path: Path,
) -> None:
    # issue: an X10-100 (1:35) at 60 deg/s at 10 Hz turns 210 motor deg per cycle; the encoder's unwrapping took it
    # the short way round, a 0x92 read then "jumped by 361 motor deg: it restarted", and every joint's record went
    config = x10_bench(tmp_path)
    assert config.joints[0].gear_ratio == 35.0
    arm = Arm(config, emulate=True)
    with pytest.raises(ConfigError) as refused:
        arm.connect()
    text = str(refused.value)
    assert "joints[0].velocity_limit_dps" in text and "joint lever" in text
    assert "velocity_limit_dps 60 × gear_ratio 35 / control.rate_hz 10" in text and "210.0 motor deg per sample" in text
    assert "180 motor deg (half a turn)" in text and "above 11.7 Hz" in text and "below 51.4 deg/s" in text
    assert arm.supervisor is None and arm.controller is None  # nothing started
    # the rate check's controllers (`rmd-motion check`) are refused the same way
    emulator, _ = arm_emulator(config)
    with pytest.raises(ConfigError, match="210.0 motor deg per sample"):
        measure_modes(config, SimulatedBus(Simulation(emulator, WireProtocol.CAN)))
    # at a rate that unwraps it, it connects and moves at its velocity limit
    with Arm(x10_bench(tmp_path, rate_hz=20.0), emulate=True) as arm:
        arm.move_to({"lever": 60.0})
        assert arm.positions()["lever"] == pytest.approx(60.0, abs=0.5)
        assert arm.supervisor is not None and not arm.supervisor.faults


@pytest.mark.parametrize("family", ["v2", "v3"])
def test_after_a_drive_silent_mid_move_the_controller_reads_the_drive_and_sees_no_restart(family: str) -> None:
    # issue: arm2, drive 1 silent 0.5-0.75 s mid-move: an older drive keeps its last torque and turned 398 motor deg
    # unheard; its continuous 0x92 reading (864.7 motor deg) was taken for a restart and the controller then read the
    # shoulder at 56.07 deg where it stood at 96.08, beyond its 90 deg limit
    config = load_config(CONFIGS / "arm2.yaml")
    if family == "v3":  # (four frames per joint and cycle: the rate a simulated CAN bus holds for them)
        config = dataclasses.replace(config, control=dataclasses.replace(config.control, rate_hz=250.0))
    arm = Arm(config, emulate=True, emulated_protocol=family, faults=[parse_fault("silent:1@0.5-0.75")])
    with arm:
        with pytest.raises(MotionFault):
            arm.move_to({"shoulder": 80.0, "elbow": -60.0})
        arm.sleep(1.0)
        supervisor, plant = arm.supervisor, arm.plant
        assert supervisor is not None and plant is not None
        kinds = [(f.kind, f.joint) for f in supervisor.faults]
        assert (FaultKind.DRIVE_RESTARTED, "shoulder") not in kinds and not supervisor.lost_frames, kinds
        positions = arm.positions()
        np.testing.assert_allclose([positions["shoulder"], positions["elbow"]], plant.joint_positions_deg(), atol=0.02)
        if positions["shoulder"] > 90.0:  # the truth: it ran past its limit while unheard, a fault of its own
            assert (FaultKind.POSITION_LIMIT, "shoulder") in kinds


def _hardware_like(config: ArmConfig, simulation: Simulation) -> Arm:
    """An arm on emulated drives that it takes for hardware (a simulated bus of the caller's): its turns are resolved
    from the power-on windows and the records, and recorded at close, as on hardware."""
    return Arm(config, bus=SimulatedBus(simulation))


def _faulted_session(
    fault: str, state_dir: Path, monkeypatch: pytest.MonkeyPatch
) -> tuple[Simulation, ArmPlant, MotionFault]:
    """arm2 as hardware (its records in ``state_dir``) moving to (80, -100) deg with ``fault`` injected: the
    simulation, its plant and the fault that halted the move; the session is closed at once."""
    monkeypatch.setenv(STATE_DIR_ENV, str(state_dir))
    config = load_config(CONFIGS / "arm2.yaml")
    emulator, plant = arm_emulator(config, faults=[parse_fault(fault)])
    simulation = Simulation(emulator, WireProtocol.CAN)
    with _hardware_like(config, simulation) as arm, pytest.raises(MotionFault) as caught:
        arm.move_to({"shoulder": 80.0, "elbow": -100.0})
    return simulation, plant, caught.value


def test_a_drive_that_restarts_drops_its_joints_turn_record_alone(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    # issue: a restart deleted every joint's record, and the next session refused every joint
    simulation, _, fault = _faulted_session("power_cycle:2@0.6", tmp_path, monkeypatch)
    assert fault.kind is FaultKind.DRIVE_RESTARTED and fault.joint == "elbow"
    config = load_config(CONFIGS / "arm2.yaml")
    records = load_turn_records(config, "simulated can")
    assert set(records) == {"shoulder"}
    shoulder = simulation.emulator.drives[1]
    assert records["shoulder"].reading_deg == pytest.approx(shoulder.angle_deg, abs=0.1)
    # the next session keeps the shoulder's turns; the elbow is resolved afresh (from its window: refused here, its
    # drive's new frame puts it outside), and named alone
    with pytest.raises(TurnError) as refused:
        _hardware_like(config, simulation).connect()
    assert "joint elbow" in str(refused.value) and "shoulder" not in str(refused.value)


def test_a_turn_record_is_written_where_the_joint_came_to_rest_never_while_it_coasts(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    # issue: a drive silent mid-move, the session closed soon after: the elbow's record was written at -443.6 motor deg
    # while it came to rest at -306.6, and the next session refused it, --keep-turns too
    simulation, plant, fault = _faulted_session("silent:1@0.5-0.75", tmp_path, monkeypatch)
    assert fault.kind is FaultKind.NO_REPLY  # (closed at once, the joints still braking, the shoulder's drive unheard)
    config = load_config(CONFIGS / "arm2.yaml")
    emulator = simulation.emulator
    records = load_turn_records(config, "simulated can")
    at_rest = [drive.angle_deg for drive in emulator.drives.values()]
    assert set(records) == {"shoulder", "elbow"}
    assert [records[n].reading_deg for n in ("shoulder", "elbow")] == pytest.approx(at_rest, abs=0.1)
    simulation.sleep_until(simulation.now_s + 1.0)  # at rest: the drives' holds settle them by a fraction of a degree
    assert [drive.angle_deg for drive in emulator.drives.values()] == pytest.approx(at_rest, abs=1.0)
    with _hardware_like(config, simulation) as arm:
        assert [t.source for t in arm.turns] == [Source.KEPT, Source.KEPT]
        positions = arm.positions()
        np.testing.assert_allclose([positions["shoulder"], positions["elbow"]], plant.joint_positions_deg(), atol=0.02)
