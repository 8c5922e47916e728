"""Fault injection: the specification syntax and what each kind does to requests and replies."""

from __future__ import annotations

import pytest

from motion.emulator import Corruption, Emulator, Fault, InjectedFault, RunState, parse_fault
from motion.errors import DecodeError
from motion.protocol import (
    Bare,
    Command,
    ErrorFlags,
    MotorState,
    MultiMotorTorque,
    Rs485Parser,
    SpeedControl,
    Status1,
    WireProtocol,
    can_frame,
    rs485_frame,
)


@pytest.mark.parametrize(
    ("spec", "fault"),
    [
        ("over_temperature:2@5-20:95", Fault(InjectedFault.OVER_TEMPERATURE, 2, 5.0, 20.0, 95.0)),
        ("under_voltage:1@0", Fault(InjectedFault.UNDER_VOLTAGE, 1, 0.0)),
        ("silent:32@1.5", Fault(InjectedFault.SILENT, 32, 1.5)),
        ("delay:1@0:15", Fault(InjectedFault.DELAY, 1, 0.0, None, 15.0)),
        ("corrupt:3@2-3:length", Fault(InjectedFault.CORRUPT, 3, 2.0, 3.0, corruption=Corruption.LENGTH)),
        ("DROP:4@0.5:0.25", Fault(InjectedFault.DROP, 4, 0.5, None, 0.25)),
        ("blocked:2@1.5-2", Fault(InjectedFault.BLOCKED, 2, 1.5, 2.0)),
        ("power_cycle:2@3.5", Fault(InjectedFault.POWER_CYCLE, 2, 3.5)),
    ],
)
def test_fault_specs_parse_and_describe_themselves(spec: str, fault: Fault) -> None:
    assert parse_fault(spec) == fault
    assert parse_fault(fault.describe()) == fault


@pytest.mark.parametrize(
    ("spec", "message"),
    [
        ("overheat:1@0", "unknown kind 'overheat'"),
        ("silent:1", "missing '@START'"),
        ("silent:x@0", "motor 'x' is not an id"),
        ("silent:33@0", "outside 1..32"),
        ("silent:1@abc", "are not START"),
        ("delay:1@5-2:10", "must be after its start"),
        ("silent:1@0:3", "takes no parameter"),
        ("drop:1@0:1.5", "a probability in 0..1"),
        ("delay:1@0:-1", "a delay >= 0 ms"),
        ("corrupt:1@0:bits", "not one of payload, id, length"),
        ("nothing", "expected KIND:MOTOR@START"),
        ("power_cycle:1@1-2", "happens at one instant: give no END"),
        ("power_cycle:1@1:5", "takes no parameter"),
    ],
)
def test_bad_fault_specs_say_what_is_wrong(spec: str, message: str) -> None:
    with pytest.raises(ValueError, match=message.replace("(", r"\(").replace(")", r"\)").replace(".", r"\.")):
        parse_fault(spec)


def test_faults_are_active_in_their_window_only() -> None:
    fault = parse_fault("silent:1@1-2")
    assert [fault.active(t) for t in (0.99, 1.0, 1.5, 2.0)] == [False, True, True, False]
    assert parse_fault("silent:1@1").active(1e9)


def test_silent_drive_neither_hears_nor_answers_until_the_fault_ends() -> None:
    emulator = Emulator([1, 2], faults=[parse_fault("silent:1@0.1-0.2")])
    emulator.advance(0.1)
    assert emulator.request(1, SpeedControl(100.0)) == []
    assert emulator.drives[1].state is RunState.OFF  # not executed either
    assert len(emulator.request(2, Bare(Command.READ_STATUS_1))) == 1  # the others carry on
    emulator.advance(0.1)
    assert len(emulator.request(1, Bare(Command.READ_STATUS_1))) == 1


def test_silent_drive_keeps_running_its_last_command() -> None:
    emulator = Emulator([1], faults=[parse_fault("silent:1@0.1")])
    emulator.request(1, SpeedControl(200.0))
    emulator.advance(0.5)
    assert emulator.request(1, Bare(Command.MOTOR_OFF)) == []
    assert emulator.drives[1].speed_dps == pytest.approx(200.0, rel=0.05)


def test_blocked_joint_stays_where_it_was_until_the_fault_ends() -> None:
    emulator = Emulator([1, 2], faults=[parse_fault("blocked:1@0.3-0.6")])
    for motor_id in (1, 2):
        emulator.request(motor_id, SpeedControl(200.0))
    emulator.advance(0.31)
    held = emulator.drives[1].angle_deg
    emulator.advance(0.19)
    assert emulator.drives[1].angle_deg == held and emulator.drives[1].speed_dps == 0.0
    assert emulator.drives[2].speed_dps == pytest.approx(200.0, rel=0.05)  # the other joint is free
    assert abs(emulator.drives[1].iq_a) > 1.0  # its drive pushes against the block
    emulator.advance(0.4)
    assert emulator.drives[1].speed_dps == pytest.approx(200.0, rel=0.05)  # free again


def test_a_power_cycle_restarts_the_drives_turn_count_and_leaves_it_off() -> None:
    emulator = Emulator([1, 2], faults=[parse_fault("power_cycle:1@2")])
    for motor_id in (1, 2):
        emulator.request(motor_id, SpeedControl(2000.0))
    emulator.advance(1.999)
    before = emulator.drives[1].angle_deg
    assert before > 720.0  # past its first turns
    emulator.advance(0.0015)  # the power cycle's step
    drive = emulator.drives[1]
    assert drive.state is RunState.OFF  # it forgot its command
    assert 0.0 <= drive.angle_deg < 360.0  # counting from its single-turn reading again
    turns = (before - drive.angle_deg) / 360.0
    assert abs(turns - round(turns)) < 0.02 and round(turns) >= 2  # by whole turns: the shaft did not jump
    assert emulator.drives[2].state is RunState.RUNNING  # the other drive carries on
    restarted = drive.angle_deg
    emulator.advance(1.0)
    assert drive.angle_deg > restarted + 10.0  # once only: it coasts on from the restart, counting continuously


def test_dropped_requests_are_not_executed_and_a_probability_drops_some() -> None:
    def answers(seed: int) -> list[int]:
        emulator = Emulator([1, 2], faults=[parse_fault("drop:1@0"), parse_fault("drop:2@0:0.5")], seed=seed)
        assert emulator.request(1, SpeedControl(100.0)) == []
        assert emulator.drives[1].setpoint is None
        return [len(emulator.request(2, Bare(Command.READ_STATUS_2))) for _ in range(200)]

    answered = answers(7)
    assert 60 < sum(answered) < 140
    assert answers(7) == answered  # seeded: a test can replay a lossy link
    assert answers(8) != answered


def test_delay_fault_delays_replies_of_that_drive_only() -> None:
    emulator = Emulator([1, 2], faults=[parse_fault("delay:2@0:15"), parse_fault("delay:2@0:5")])
    exchange = emulator.handle_can(can_frame.encode_request(MultiMotorTorque(0.0, 0.0, 0.0, 0.0)))
    assert [(o.motor_id, o.delay_s) for o in exchange.replies] == [(1, 0.0), (2, pytest.approx(0.020))]
    default = Emulator([1], faults=[parse_fault("delay:1@0")])
    assert default.handle_can(can_frame.encode_request(Bare(Command.READ_PID), 1)).replies[0].delay_s == 0.010


@pytest.mark.parametrize("how", list(Corruption))
def test_corrupted_can_replies_do_not_decode(how: Corruption) -> None:
    emulator = Emulator([5], faults=[Fault(InjectedFault.CORRUPT, 5, 0.0, corruption=how)])
    exchange = emulator.handle_can(can_frame.encode_request(Bare(Command.READ_STATUS_2), 5))
    (outgoing,) = exchange.replies
    assert outgoing.corruption is how and isinstance(outgoing.message, MotorState)
    with pytest.raises(DecodeError):
        can_frame.decode_reply(outgoing.wire.arbitration_id, outgoing.wire.data)


@pytest.mark.parametrize("how", list(Corruption))
@pytest.mark.parametrize("command", [Command.READ_STATUS_2, Command.MOTOR_STOP])  # with and without data
def test_corrupted_rs485_replies_are_rejected_by_the_parser(how: Corruption, command: Command) -> None:
    emulator = Emulator([5], faults=[Fault(InjectedFault.CORRUPT, 5, 0.0, corruption=how)])
    (outgoing,) = emulator.handle_rs485(rs485_frame.encode_request(Bare(command), 5)).replies
    with pytest.raises(DecodeError):
        rs485_frame.decode_reply(outgoing.wire)
    parser = Rs485Parser()
    parser.feed(outgoing.wire)
    assert parser.next_frame(flush=True) is None


def test_physical_fault_defaults_follow_the_drive_thresholds() -> None:
    emulator = Emulator([1, 2], faults=[parse_fault("under_voltage:1@0"), parse_fault("over_temperature:2@0-0.01")])
    assert emulator.request(1, Bare(Command.READ_STATUS_1)) == [
        (1, Status1(Command.READ_STATUS_1, 25, 12.0, ErrorFlags.LOW_VOLTAGE))
    ]
    assert emulator.request(2, Bare(Command.READ_STATUS_1), WireProtocol.RS485) == [
        (2, Status1(Command.READ_STATUS_1, 90, 24.0, ErrorFlags.OVER_TEMPERATURE))
    ]


def test_faulted_drive_stops_driving_until_cleared_and_commanded_again() -> None:
    emulator = Emulator([1], faults=[parse_fault("over_temperature:1@0.2-0.3:85")])
    emulator.request(1, SpeedControl(300.0))
    emulator.advance(0.2)
    assert emulator.drives[1].speed_dps == pytest.approx(300.0, rel=0.05)
    emulator.advance(0.01)
    drive = emulator.drives[1]
    assert drive.state is RunState.OFF and drive.iq_a == 0.0 and drive.errors == ErrorFlags.OVER_TEMPERATURE
