"""Emulated drive behaviour, deterministic: manual simulation time, requests through the protocol codec."""

from __future__ import annotations

import math

import pytest

from motion.emulator import DriveLoop, DriveModel, Emulator, LoadModel, RunState, parse_fault
from motion.protocol import (
    COMMANDS,
    Acceleration,
    Bare,
    Command,
    Direction,
    EncoderOffset,
    EncoderReading,
    ErrorFlags,
    IncrementalPosition,
    IncrementalPositionSpeed,
    Message,
    MotorState,
    MultiMotorTorque,
    MultiTurnAngle,
    MultiTurnPosition,
    MultiTurnPositionSpeed,
    OpenLoopControl,
    OpenLoopState,
    PhaseCurrents,
    PidGains,
    SingleTurnAngle,
    SingleTurnPosition,
    SingleTurnPositionSpeed,
    SpeedControl,
    SpinDirection,
    Status1,
    TorqueControl,
    WireProtocol,
)
from motion.protocol.table import command_of

FRICTIONLESS = LoadModel(inertia_kgm2=1e-3, viscous_friction_nm_per_dps=0.0, coulomb_friction_nm=0.0)


def ask(emulator: Emulator, motor_id: int, message: Message, transport: WireProtocol = WireProtocol.CAN) -> Message:
    """One request, exactly one reply from the addressed drive."""
    replies = emulator.request(motor_id, message, transport)
    assert [r[0] for r in replies] == [motor_id]
    return replies[0][1]


def run(emulator: Emulator, seconds: float, motor_id: int = 1, every_s: float = 0.002) -> list[float]:
    """Advance and return the drive's speed (dps) sampled every ``every_s``."""
    speeds = []
    for _ in range(round(seconds / every_s)):
        emulator.advance(every_s)
        speeds.append(emulator.drives[motor_id].speed_dps)
    return speeds


def test_position_mode_converges_within_the_drive_max_speed() -> None:
    emulator = Emulator([1], model=DriveModel(max_speed_dps=400.0))
    drive = emulator.drives[1]
    reply = ask(emulator, 1, MultiTurnPosition(angle_deg=180.0))
    assert isinstance(reply, MotorState) and reply.command is Command.MULTI_TURN_POSITION
    speeds = run(emulator, 1.5)
    assert max(speeds) <= 400.0 * 1.05
    assert max(speeds) >= 400.0 * 0.95  # a 180 deg move reaches the cruise speed
    assert drive.angle_deg == pytest.approx(180.0, abs=0.05)
    angle = ask(emulator, 1, Bare(Command.READ_MULTI_TURN_ANGLE))
    assert isinstance(angle, MultiTurnAngle) and angle.angle_deg == pytest.approx(180.0, abs=0.05)


def test_position_with_max_speed_respects_the_request_and_zero_never_moves() -> None:
    emulator = Emulator([1])
    drive = emulator.drives[1]
    ask(emulator, 1, MultiTurnPositionSpeed(angle_deg=-90.0, max_speed_dps=150.0))
    speeds = run(emulator, 1.2)
    assert min(speeds) >= -150.0 * 1.05
    assert drive.angle_deg == pytest.approx(-90.0, abs=0.05)
    ask(emulator, 1, MultiTurnPositionSpeed(angle_deg=0.0, max_speed_dps=0.0))
    run(emulator, 0.3)
    assert drive.angle_deg == pytest.approx(-90.0, abs=0.05)


def test_stop_holds_position_and_run_resumes_the_mode() -> None:
    # An unbalanced load: holding needs torque, so a coasting motor would visibly move.
    emulator = Emulator([1], load=LoadModel(load_torque_nm=0.3))
    drive = emulator.drives[1]
    ask(emulator, 1, SpeedControl(speed_dps=360.0))
    run(emulator, 0.4)
    assert drive.speed_dps == pytest.approx(360.0, rel=0.05)
    assert ask(emulator, 1, Bare(Command.MOTOR_STOP)) == Bare(Command.MOTOR_STOP)
    run(emulator, 0.3)
    assert (drive.state, drive.setpoint is not None) == (RunState.STOPPED, True)  # holding, command kept
    held = drive.angle_deg
    run(emulator, 0.5)
    assert drive.angle_deg == pytest.approx(held, abs=0.1)
    assert abs(drive.speed_dps) < 1.0
    # 0.3 N·m of load at 0.1 N·m/A, give or take 0.05 N·m of static friction.
    assert -3.55 <= drive.iq_a <= -2.45
    ask(emulator, 1, Bare(Command.MOTOR_RUN))
    run(emulator, 0.4)
    assert drive.state is RunState.RUNNING
    assert drive.speed_dps == pytest.approx(360.0, rel=0.05)


def test_stop_brakes_at_the_acceleration_limit() -> None:
    emulator = Emulator([1], model=DriveModel(acceleration_dps2=2000), load=FRICTIONLESS)
    drive = emulator.drives[1]
    ask(emulator, 1, SpeedControl(speed_dps=600.0))
    run(emulator, 0.5)
    ask(emulator, 1, Bare(Command.MOTOR_STOP))
    run(emulator, 0.1)
    assert drive.speed_dps == pytest.approx(400.0, abs=30.0)  # 600 - 2000 * 0.1
    run(emulator, 0.5)
    assert abs(drive.speed_dps) < 1.0


def test_motor_off_coasts_with_zero_current_and_forgets_the_command() -> None:
    load = LoadModel(inertia_kgm2=1e-3, viscous_friction_nm_per_dps=0.0, coulomb_friction_nm=0.01)
    emulator = Emulator([1], load=load)
    drive = emulator.drives[1]
    ask(emulator, 1, SpeedControl(speed_dps=500.0))
    run(emulator, 0.5)
    ask(emulator, 1, Bare(Command.MOTOR_OFF))
    run(emulator, 0.1)
    reply = ask(emulator, 1, Bare(Command.READ_STATUS_2))
    assert isinstance(reply, MotorState) and reply.iq_a == 0.0
    # Only Coulomb friction decelerates: 0.01 N·m / (1e-3 + 3e-5) kg·m² = 9.7 rad/s² = 556 dps/s.
    expected = 500.0 - 0.01 / 1.03e-3 * 180 / math.pi * 0.1
    assert drive.speed_dps == pytest.approx(expected, rel=0.03)
    ask(emulator, 1, Bare(Command.MOTOR_RUN))  # nothing to resume after 0x80
    run(emulator, 0.1)
    assert drive.state is RunState.OFF and drive.setpoint is None and drive.iq_a == 0.0


def test_torque_mode_accelerates_the_load_per_torque_constant_and_inertia() -> None:
    model = DriveModel(torque_constant_nm_per_a=0.2, rotor_inertia_kgm2=1e-4)
    emulator = Emulator([1], model=model, load=FRICTIONLESS)
    reply = ask(emulator, 1, TorqueControl(iq_a=1.5))
    assert isinstance(reply, MotorState) and reply.command is Command.TORQUE
    run(emulator, 0.2)
    # 0.3 N·m on 1.1e-3 kg·m² for 0.2 s (the current lag of ~0.5 ms costs < 1 %).
    expected_dps = 0.2 * 1.5 / 1.1e-3 * 0.2 * 180 / math.pi
    assert emulator.drives[1].speed_dps == pytest.approx(expected_dps, rel=0.02)
    state = ask(emulator, 1, Bare(Command.READ_STATUS_2))
    assert isinstance(state, MotorState) and state.iq_a == pytest.approx(1.5, abs=0.02)


def test_torque_mode_is_not_limited_by_the_current_limit_but_speed_mode_is() -> None:
    model = DriveModel(current_limit_a=2.0)
    emulator = Emulator([1], model=model, load=LoadModel(coulomb_friction_nm=100.0))  # locked rotor
    ask(emulator, 1, TorqueControl(iq_a=5.0))
    run(emulator, 0.05)
    assert emulator.drives[1].iq_a == pytest.approx(5.0, abs=0.01)
    ask(emulator, 1, SpeedControl(speed_dps=300.0))
    run(emulator, 0.2)
    assert emulator.drives[1].iq_a == pytest.approx(2.0, abs=0.01)


def test_speed_mode_tracks_and_is_capped_at_the_max_speed() -> None:
    emulator = Emulator([1], model=DriveModel(max_speed_dps=500.0))
    drive = emulator.drives[1]
    ask(emulator, 1, SpeedControl(speed_dps=-250.0))
    run(emulator, 0.5)
    assert drive.speed_dps == pytest.approx(-250.0, rel=0.02)
    reply = ask(emulator, 1, SpeedControl(speed_dps=2000.0))
    assert isinstance(reply, MotorState) and reply.speed_dps == pytest.approx(-250, abs=5)
    run(emulator, 0.5)
    assert drive.speed_dps == pytest.approx(500.0, rel=0.02)


def test_acceleration_limit_written_with_0x34_shapes_speed_ramps() -> None:
    emulator = Emulator([1], load=FRICTIONLESS)
    assert ask(emulator, 1, Acceleration(Command.WRITE_ACCELERATION_RAM, 1000)) == Acceleration(
        Command.WRITE_ACCELERATION_RAM, 1000
    )
    assert ask(emulator, 1, Bare(Command.READ_ACCELERATION)) == Acceleration(Command.READ_ACCELERATION, 1000)
    ask(emulator, 1, SpeedControl(speed_dps=500.0))
    run(emulator, 0.25)
    assert emulator.drives[1].speed_dps == pytest.approx(250.0, abs=15.0)
    run(emulator, 0.4)
    assert emulator.drives[1].speed_dps == pytest.approx(500.0, rel=0.02)
    emulator.power_cycle()  # 0x34 writes RAM only
    assert ask(emulator, 1, Bare(Command.READ_ACCELERATION)) == Acceleration(
        Command.READ_ACCELERATION, DriveModel().acceleration_dps2
    )


@pytest.mark.parametrize(
    ("direction", "target", "expected"),
    [
        (SpinDirection.CLOCKWISE, 350.0, 350.0),
        (SpinDirection.COUNTERCLOCKWISE, 350.0, -10.0),
        (SpinDirection.CLOCKWISE, 5.0, 365.0),
        (SpinDirection.COUNTERCLOCKWISE, 5.0, 5.0),
    ],
)
def test_single_turn_position_goes_the_commanded_way(direction: SpinDirection, target: float, expected: float) -> None:
    emulator = Emulator([1])
    drive = emulator.drives[1]
    ask(emulator, 1, MultiTurnPosition(angle_deg=10.0))
    run(emulator, 0.5)
    ask(emulator, 1, SingleTurnPosition(direction=direction, angle_deg=target))
    speeds = run(emulator, 1.5)
    assert drive.angle_deg == pytest.approx(expected, abs=0.05)
    wrong_way = min(speeds) if expected > 10.0 else -max(speeds)
    assert wrong_way > -5.0  # never turned the other way round
    single = ask(emulator, 1, Bare(Command.READ_SINGLE_TURN_ANGLE))
    assert isinstance(single, SingleTurnAngle) and single.angle_deg == pytest.approx(expected % 360, abs=0.05)


def test_single_turn_position_with_max_speed() -> None:
    emulator = Emulator([1])
    ask(
        emulator,
        1,
        SingleTurnPositionSpeed(direction=SpinDirection.COUNTERCLOCKWISE, angle_deg=270.0, max_speed_dps=200.0),
    )
    speeds = run(emulator, 1.2)
    assert min(speeds) >= -200.0 * 1.05
    assert emulator.drives[1].angle_deg == pytest.approx(-90.0, abs=0.05)


def test_incremental_moves_are_relative_to_the_current_position() -> None:
    emulator = Emulator([1])
    drive = emulator.drives[1]
    ask(emulator, 1, MultiTurnPosition(angle_deg=30.0))
    run(emulator, 0.5)
    ask(emulator, 1, IncrementalPosition(angle_deg=100.0))
    run(emulator, 0.8)
    assert drive.angle_deg == pytest.approx(130.0, abs=0.05)
    ask(emulator, 1, IncrementalPositionSpeed(angle_deg=-50.0, max_speed_dps=100.0))
    speeds = run(emulator, 1.0)
    assert min(speeds) >= -105.0
    assert drive.angle_deg == pytest.approx(80.0, abs=0.05)


def test_open_loop_power_drives_the_motor_and_is_reported() -> None:
    emulator = Emulator([1], load=FRICTIONLESS)
    reply = ask(emulator, 1, OpenLoopControl(power=200))
    assert isinstance(reply, OpenLoopState) and reply.power == 200
    run(emulator, 0.3)  # time constant J R / kt² = 31 ms
    # No-load speed: 20 % of 24 V against 0.1 V·s/rad of back-EMF = 48 rad/s.
    assert emulator.drives[1].speed_dps == pytest.approx(48.0 * 180 / math.pi, rel=0.01)
    status = ask(emulator, 1, Bare(Command.READ_STATUS_2))
    assert isinstance(status, MotorState) and abs(status.iq_a) < 0.1


def test_pid_gains_ram_are_lost_at_power_cycle_and_rom_survives() -> None:
    emulator = Emulator([1])
    factory = ask(emulator, 1, Bare(Command.READ_PID))
    assert isinstance(factory, PidGains)
    ram = PidGains(Command.WRITE_PID_RAM, 10, 20, 30, 40, 50, 60)
    assert ask(emulator, 1, ram) == ram
    assert ask(emulator, 1, Bare(Command.READ_PID)) == PidGains(Command.READ_PID, 10, 20, 30, 40, 50, 60)
    emulator.power_cycle(1)
    assert ask(emulator, 1, Bare(Command.READ_PID)) == factory
    rom = PidGains(Command.WRITE_PID_ROM, 90, 5, 60, 30, 70, 70)
    assert ask(emulator, 1, rom, WireProtocol.RS485) == rom
    assert ask(emulator, 1, Bare(Command.READ_PID)) == PidGains(Command.READ_PID, 90, 5, 60, 30, 70, 70)
    emulator.power_cycle()
    assert ask(emulator, 1, Bare(Command.READ_PID)) == PidGains(Command.READ_PID, 90, 5, 60, 30, 70, 70)


def test_pid_gains_change_the_response() -> None:
    fast, slow = Emulator([1]), Emulator([1])
    ask(slow, 1, PidGains(Command.WRITE_PID_RAM, 100, 0, 5, 40, 50, 50))
    for emulator in (fast, slow):
        ask(emulator, 1, SpeedControl(speed_dps=300.0))
        run(emulator, 0.03)
    assert fast.drives[1].speed_dps > slow.drives[1].speed_dps + 50.0
    ask(slow, 1, PidGains(Command.WRITE_PID_RAM, 0, 0, 0, 0, 0, 0))
    ask(slow, 1, Bare(Command.MOTOR_OFF))
    ask(slow, 1, SpeedControl(speed_dps=300.0))
    run(slow, 0.1)
    assert slow.drives[1].iq_a == 0.0  # zero gains: the drive does nothing


def test_under_voltage_flag_clears_only_when_the_cause_is_gone() -> None:
    emulator = Emulator([1])
    emulator.add_fault(parse_fault("under_voltage:1@0.1-0.5:12"))
    ask(emulator, 1, SpeedControl(speed_dps=200.0))
    run(emulator, 0.2)
    status = ask(emulator, 1, Bare(Command.READ_STATUS_1))
    assert status == Status1(Command.READ_STATUS_1, 25, 12.0, ErrorFlags.LOW_VOLTAGE)
    drive = emulator.drives[1]
    assert drive.state is RunState.OFF and drive.iq_a == 0.0  # protection: like 0x80
    cleared = ask(emulator, 1, Bare(Command.CLEAR_ERRORS))
    assert isinstance(cleared, Status1) and cleared.errors == ErrorFlags.LOW_VOLTAGE
    ask(emulator, 1, SpeedControl(speed_dps=200.0))  # ignored while flagged
    run(emulator, 0.1)
    assert drive.state is RunState.OFF
    run(emulator, 0.3)  # voltage back at 0.5 s; the flag stays latched
    status = ask(emulator, 1, Bare(Command.READ_STATUS_1))
    assert isinstance(status, Status1) and status.voltage_v == 24.0 and status.errors == ErrorFlags.LOW_VOLTAGE
    cleared = ask(emulator, 1, Bare(Command.CLEAR_ERRORS), WireProtocol.RS485)
    assert cleared == Status1(Command.CLEAR_ERRORS, 25, 24.0, ErrorFlags.NONE)
    ask(emulator, 1, SpeedControl(speed_dps=200.0))
    run(emulator, 0.3)
    assert drive.speed_dps == pytest.approx(200.0, rel=0.05)


def test_over_temperature_flag_clears_only_after_cooling() -> None:
    model = DriveModel(thermal_time_constant_s=1.0)
    emulator = Emulator([1], model=model)
    emulator.add_fault(parse_fault("over_temperature:1@0.1-0.3"))  # held at 80 + 10 degC
    run(emulator, 0.35)
    status = ask(emulator, 1, Bare(Command.CLEAR_ERRORS))
    assert isinstance(status, Status1) and status.errors == ErrorFlags.OVER_TEMPERATURE
    assert status.temperature_c > 80
    run(emulator, 1.0)  # 25 + 65 e^-1 = 49 degC
    status = ask(emulator, 1, Bare(Command.READ_STATUS_1))
    assert isinstance(status, Status1) and status.temperature_c < 55
    assert status.errors == ErrorFlags.OVER_TEMPERATURE  # latched until cleared
    assert ask(emulator, 1, Bare(Command.CLEAR_ERRORS)) == Status1(
        Command.CLEAR_ERRORS, status.temperature_c, 24.0, ErrorFlags.NONE
    )


def test_temperature_rises_with_current_squared_and_cools_toward_ambient() -> None:
    locked = LoadModel(coulomb_friction_nm=100.0)

    def heat(iq_a: float) -> float:
        emulator = Emulator([1], load=locked)
        ask(emulator, 1, TorqueControl(iq_a=iq_a))
        emulator.advance(5.0)
        return emulator.drives[1].temperature_c - 25.0

    # 1.5 × 0.3 Ω × i² into 60 J/K (120 s / 2 K/W): about 3.7 K for 10 A in 5 s, four times less for 5 A.
    rise_10, rise_5 = heat(10.0), heat(5.0)
    assert rise_10 == pytest.approx(1.5 * 0.3 * 100 * 5 / 60, rel=0.05)
    assert rise_10 / rise_5 == pytest.approx(4.0, rel=0.02)
    emulator = Emulator([1], model=DriveModel(thermal_time_constant_s=2.0), load=locked)
    ask(emulator, 1, TorqueControl(iq_a=20.0))
    emulator.advance(2.0)
    hot = emulator.drives[1].temperature_c
    ask(emulator, 1, Bare(Command.MOTOR_OFF))
    emulator.advance(2.0)
    assert 25.0 < emulator.drives[1].temperature_c < 25.0 + (hot - 25.0) * 0.4


@pytest.mark.parametrize("bits", [12, 14, 18])
def test_encoder_wraps_once_per_turn(bits: int) -> None:
    emulator = Emulator([1], model=DriveModel(encoder_bits=bits, shaft_zero_deg=123.4), load=FRICTIONLESS)
    field_max = 1 << min(bits, 16)
    ask(emulator, 1, SpeedControl(speed_dps=360.0))
    emulator.advance(0.3)
    wraps, previous = 0, None
    for _ in range(400):  # 2 s at 360 dps: two turns
        emulator.advance(0.005)
        reading = ask(emulator, 1, Bare(Command.READ_ENCODER))
        assert isinstance(reading, EncoderReading)
        assert 0 <= reading.encoder < field_max and 0 <= reading.encoder_raw < field_max
        assert reading.encoder == (reading.encoder_raw - reading.encoder_offset) % field_max
        if previous is not None and reading.encoder < previous:
            wraps += 1
            assert previous > field_max * 0.9 and reading.encoder < field_max * 0.1
        previous = reading.encoder
    assert wraps == 2
    single = ask(emulator, 1, Bare(Command.READ_SINGLE_TURN_ANGLE))
    state = ask(emulator, 1, Bare(Command.READ_STATUS_2))
    assert isinstance(single, SingleTurnAngle) and isinstance(state, MotorState)
    assert single.angle_deg == pytest.approx(state.encoder * 360 / field_max, abs=360 / field_max + 0.01)


def test_encoder_offset_writes_take_effect_at_the_next_power_cycle() -> None:
    emulator = Emulator([1], model=DriveModel(shaft_zero_deg=90.0))  # raw 4096 of 16384 at the start
    before = ask(emulator, 1, Bare(Command.READ_ENCODER))
    assert before == EncoderReading(encoder=4096, encoder_raw=4096, encoder_offset=0)
    assert ask(emulator, 1, EncoderOffset(Command.WRITE_ENCODER_OFFSET, 1000)) == EncoderOffset(
        Command.WRITE_ENCODER_OFFSET, 1000
    )
    assert ask(emulator, 1, Bare(Command.READ_ENCODER)) == before  # ROM only
    emulator.power_cycle()
    assert ask(emulator, 1, Bare(Command.READ_ENCODER)) == EncoderReading(3096, 4096, 1000)
    angle = ask(emulator, 1, Bare(Command.READ_MULTI_TURN_ANGLE))
    assert isinstance(angle, MultiTurnAngle) and angle.angle_deg == pytest.approx(3096 * 360 / 16384, abs=0.01)
    # 0x19: the current raw position becomes the ROM zero; CAN replies with it, RS485 echoes.
    assert ask(emulator, 1, Bare(Command.WRITE_ZERO_ROM)) == EncoderOffset(Command.WRITE_ZERO_ROM, 4096)
    assert ask(emulator, 1, Bare(Command.WRITE_ZERO_ROM), WireProtocol.RS485) == Bare(Command.WRITE_ZERO_ROM)
    assert ask(emulator, 1, Bare(Command.READ_ENCODER)) == EncoderReading(3096, 4096, 1000)
    emulator.power_cycle()
    assert ask(emulator, 1, Bare(Command.READ_ENCODER)) == EncoderReading(0, 4096, 4096)


def test_set_zero_ram_zeroes_the_angles_at_once_until_power_off_without_moving() -> None:
    emulator = Emulator([1])
    ask(emulator, 1, MultiTurnPosition(angle_deg=500.0))
    emulator.advance(1.5)
    assert ask(emulator, 1, Bare(Command.SET_ZERO_RAM)) == Bare(Command.SET_ZERO_RAM)
    angle = ask(emulator, 1, Bare(Command.READ_MULTI_TURN_ANGLE))
    assert isinstance(angle, MultiTurnAngle) and angle.angle_deg == pytest.approx(0.0, abs=0.03)
    emulator.advance(0.3)  # the held target is a shaft position: zeroing does not move the motor
    assert emulator.drives[1].angle_deg == pytest.approx(0.0, abs=0.05)
    emulator.power_cycle()
    reading = ask(emulator, 1, Bare(Command.READ_ENCODER))
    assert isinstance(reading, EncoderReading) and reading.encoder_offset == 0
    angle = ask(emulator, 1, Bare(Command.READ_MULTI_TURN_ANGLE))
    assert isinstance(angle, MultiTurnAngle) and angle.angle_deg == pytest.approx(500.0 - 360.0, abs=0.05)


def test_multi_motor_torque_frame_answers_in_ascending_id_order() -> None:
    emulator = Emulator([4, 2, 1, 7])
    replies = emulator.request(0, MultiMotorTorque(0.5, 1.0, 1.5, -2.0))
    assert [motor_id for motor_id, _ in replies] == [1, 2, 4]  # 3 is absent, 7 is not addressed
    assert all(isinstance(m, MotorState) and m.command is Command.TORQUE for _, m in replies)
    emulator.advance(0.05)
    assert [emulator.drives[i].iq_a for i in (1, 2, 4)] == pytest.approx([0.5, 1.0, -2.0], abs=0.01)
    assert emulator.drives[7].state is RunState.OFF
    setpoint = emulator.drives[4].setpoint
    assert setpoint is not None and setpoint.mode is DriveLoop.TORQUE


def test_phase_currents_are_balanced_and_match_iq() -> None:
    emulator = Emulator([1], load=LoadModel(coulomb_friction_nm=100.0))
    ask(emulator, 1, TorqueControl(iq_a=4.0))
    emulator.advance(0.05)
    for transport in (WireProtocol.CAN, WireProtocol.RS485):
        phases = ask(emulator, 1, Bare(Command.READ_STATUS_3), transport)
        assert isinstance(phases, PhaseCurrents)
        assert phases.ia_a + phases.ib_a + phases.ic_a == pytest.approx(0.0, abs=0.05)
        amplitude = math.sqrt(2 / 3 * (phases.ia_a**2 + phases.ib_a**2 + phases.ic_a**2))
        assert amplitude == pytest.approx(4.0, abs=0.05)
        assert (phases.temperature_c is None) == (transport is WireProtocol.CAN)


SAMPLE_REQUESTS: list[Message] = [
    Bare(Command.READ_PID),
    PidGains(Command.WRITE_PID_RAM, 100, 50, 50, 40, 50, 50),
    PidGains(Command.WRITE_PID_ROM, 100, 50, 50, 40, 50, 50),
    Bare(Command.READ_ACCELERATION),
    Acceleration(Command.WRITE_ACCELERATION_RAM, 20000),
    Bare(Command.READ_ENCODER),
    EncoderOffset(Command.WRITE_ENCODER_OFFSET, 100),
    Bare(Command.WRITE_ZERO_ROM),
    Bare(Command.READ_MULTI_TURN_ANGLE),
    Bare(Command.READ_SINGLE_TURN_ANGLE),
    Bare(Command.SET_ZERO_RAM),
    Bare(Command.READ_STATUS_1),
    Bare(Command.CLEAR_ERRORS),
    Bare(Command.READ_STATUS_2),
    Bare(Command.READ_STATUS_3),
    Bare(Command.MOTOR_OFF),
    Bare(Command.MOTOR_STOP),
    Bare(Command.MOTOR_RUN),
    OpenLoopControl(100),
    TorqueControl(0.5),
    SpeedControl(90.0),
    MultiTurnPosition(10.0),
    MultiTurnPositionSpeed(20.0, 100.0),
    SingleTurnPosition(SpinDirection.CLOCKWISE, 30.0),
    SingleTurnPositionSpeed(SpinDirection.COUNTERCLOCKWISE, 40.0, 100.0),
    IncrementalPosition(5.0),
    IncrementalPositionSpeed(-5.0, 50.0),
    Bare(Command.READ_MODEL),
]


def code(message: Message) -> Command:
    command = command_of(message)
    assert command is not None
    return command


def requests_for(transport: WireProtocol) -> list[Message]:
    """The sample request of every command the transport has (the table decides which)."""
    out = [m for m in SAMPLE_REQUESTS if COMMANDS[code(m)].layout(transport, Direction.REQUEST)]
    assert {code(m) for m in out} == {
        code for code, spec in COMMANDS.items() if spec.layout(transport, Direction.REQUEST) is not None
    }
    return out


def check_reply(request: Message, reply: Message, transport: WireProtocol) -> None:
    """The reply has the command and the class the table declares for it."""
    command = code(request)
    layout = COMMANDS[command].layout(transport, Direction.REPLY)
    assert layout is not None and type(reply) is layout.cls
    assert command_of(reply) is command
    if layout.echo:
        assert reply == request


@pytest.mark.parametrize("transport", [WireProtocol.CAN, WireProtocol.RS485])
def test_every_command_is_answered_with_the_table_reply(transport: WireProtocol) -> None:
    emulator = Emulator([3])
    for message in requests_for(transport):
        emulator.advance(0.01)
        check_reply(message, ask(emulator, 3, message, transport), transport)


def test_absent_drive_does_not_answer() -> None:
    emulator = Emulator([1, 2])
    assert emulator.request(5, Bare(Command.READ_STATUS_1)) == []


def test_bad_construction_is_refused() -> None:
    with pytest.raises(ValueError, match="distinct"):
        Emulator([1, 1])
    with pytest.raises(ValueError, match="motor_id"):
        Emulator([33])
    with pytest.raises(ValueError, match="not emulated"):
        Emulator([1], faults=[parse_fault("silent:2@0")])
