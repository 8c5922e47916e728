"""Emulated V3-family drives (issue 17): every command answered through the V3 codec on CAN and RS485, output-shaft
units through the drive's gear, the communication-loss protection (0xB3) that cuts the output, holding brakes, the
0x280 broadcast and the motion frame. Simulation time, in process."""

from __future__ import annotations

import contextlib
import json
import math
import signal
import subprocess
import sys
import time
import uuid
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
import pytest
import yaml

from motion.compose import negotiate_family
from motion.config import ArmConfig, parse_config
from motion.config.schema import ProtocolSetting
from motion.emulator import DriveModel, Emulator, Fault, InjectedFault, LoadModel, VirtualCanAttachment
from motion.emulator.drive_v3 import MODEL_NAME, VERSION_DATE
from motion.emulator.simulated import SimulatedBus, Simulation
from motion.errors import ConfigError, TransportError
from motion.protocol import CanFrame, MultiTurnAngle, MultiTurnPositionSpeed, SpeedControl, TorqueControl
from motion.protocol.messages import Message
from motion.protocol.table import Direction, ProtocolFamily, WireProtocol
from motion.protocol.v3 import COMMANDS_V3, frames
from motion.protocol.v3.frames import Rs485ParserV3
from motion.protocol.v3.messages import (
    AccelerationIndex,
    AccelerationRead,
    ActiveReply,
    ActiveReplyCommand,
    BareV3,
    BaudRate,
    BrakeCommand,
    CanIdCommand,
    CanIdReply,
    CommandV3,
    CommunicationTimeout,
    FunctionControl,
    FunctionIndex,
    MotionCommand,
    MotionState,
    MotorModel,
    MotorStateV3,
    MultiTurnEncoder,
    PidIndex,
    PidParameter,
    PidRead,
    PlanningAcceleration,
    ReadWrite,
    Status1V3,
    SystemErrorFlags,
    VersionDate,
)
from motion.protocol.v3.motion_frame import motion_ranges
from motion.transport.base import Request
from motion.transport.can_endpoint import CanEndpoint
from motion.transport.can_transport import CanTransport
from motion.transport.rs485_transport import Rs485Transport
from tests.test_emulator_bus import start_cli

C = CommandV3
ROOT = Path(__file__).resolve().parent.parent
GEAR = 6.0


@contextlib.contextmanager
def v3_drives(link: Path, ids: str = "1,2") -> Iterator[None]:
    """``rmd-motion emulate --protocol v3`` on an slcan pty at ``link`` for the duration."""
    process = start_cli("--ids", ids, "--protocol", "v3", "--slcan-link", str(link))
    try:
        assert process.stdout is not None
        assert process.stdout.readline().startswith(f"slcan: {link}")
        assert "emulating motors" in process.stdout.readline()
        yield
    finally:
        process.send_signal(signal.SIGTERM)
        process.communicate(timeout=10)


def _cli(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "motion.cli", *args], capture_output=True, text=True, timeout=30, check=False
    )


def _emulator(**kwargs: object) -> Emulator:
    model = DriveModel(gear_ratio=GEAR, encoder_bits=14)
    return Emulator([1, 2], model=model, load=LoadModel(), family=ProtocolFamily.V3, **kwargs)  # type: ignore[arg-type]


def _one(emulator: Emulator, message: Message, transport: WireProtocol = WireProtocol.CAN) -> Message:
    replies = emulator.request(1, message, transport)
    assert len(replies) == 1 and replies[0][0] == 1
    return replies[0][1]


def _requests() -> list[Message]:
    """One request of every command of the V4.2 document (harmless ones: nothing moves far)."""
    out: list[Message] = []
    for code, spec in COMMANDS_V3.items():
        layout = spec.layout(WireProtocol.CAN, Direction.REQUEST)
        assert layout is not None
        samples: dict[type[Message], Message] = {
            BareV3: BareV3(code),
            PidRead: PidRead(PidIndex.SPEED_KP),
            PidParameter: PidParameter(code, PidIndex.SPEED_KI, 2.5),
            AccelerationRead: AccelerationRead(AccelerationIndex.POSITION_ACCELERATION),
            PlanningAcceleration: PlanningAcceleration(code, AccelerationIndex.SPEED_ACCELERATION, 1000),
            MultiTurnEncoder: MultiTurnEncoder(code, 0),
            FunctionControl: FunctionControl(FunctionIndex.ERROR_BROADCAST, 1),
            CanIdCommand: CanIdCommand(ReadWrite.READ, 0),
            CommunicationTimeout: CommunicationTimeout(0),
            BaudRate: BaudRate(1),
            ActiveReply: ActiveReply(ActiveReplyCommand.READ_STATUS_2, 0, 10.0),
            TorqueControl: TorqueControl(0.0),
            SpeedControl: SpeedControl(0.0),
            MultiTurnPositionSpeed: MultiTurnPositionSpeed(0.0, 100.0),
        }
        if layout.cls in samples:
            out.append(samples[layout.cls])
    return out


@pytest.mark.parametrize("transport", [WireProtocol.CAN, WireProtocol.RS485])
def test_every_command_gets_the_reply_the_table_gives(transport: WireProtocol) -> None:
    emulator = _emulator()
    sent = 0
    for request in _requests():
        code = CommandV3(request.command)  # type: ignore[attr-defined]
        if transport is WireProtocol.RS485 and code is C.ACTIVE_REPLY:
            continue
        replies = emulator.request(1, request, transport)
        layout = COMMANDS_V3[code].layout(WireProtocol.CAN, Direction.REPLY)
        if layout is None:
            assert replies == [], code
        else:
            every = code is C.CAN_ID  # 0x79 goes to every drive on the bus (0x300 / 0xCD), and each answers
            assert [type(m) for _, m in replies] == [layout.cls] * (len(emulator.ids) if every else 1), code
            if layout.echo:
                assert replies[0][1] == request
        sent += 1
    assert sent >= 30


def test_positions_and_speeds_are_the_output_shafts() -> None:
    emulator = _emulator()
    _one(emulator, MultiTurnPositionSpeed(90.0, 180.0))
    emulator.advance(2.0)
    angle = _one(emulator, BareV3(C.READ_MULTI_TURN_ANGLE))
    assert isinstance(angle, MultiTurnAngle) and angle.angle_deg == pytest.approx(90.0, abs=0.2)
    state = _one(emulator, BareV3(C.READ_STATUS_2))
    assert isinstance(state, MotorStateV3) and state.angle_deg in (89, 90)
    encoder = _one(emulator, BareV3(C.READ_MULTI_TURN_ENCODER))
    assert isinstance(encoder, MultiTurnEncoder)
    assert encoder.encoder == pytest.approx(90.0 * GEAR / 360.0 * (1 << 14), rel=0.01)  # motor encoder counts
    _one(emulator, SpeedControl(30.0))
    emulator.advance(1.0)
    state = _one(emulator, BareV3(C.READ_STATUS_2))
    assert isinstance(state, MotorStateV3) and state.speed_dps == pytest.approx(30, abs=2)


def test_the_communication_loss_protection_cuts_the_output_and_locks_the_brake() -> None:
    emulator = _emulator(brakes=[1])
    assert _one(emulator, BareV3(C.RELEASE_BRAKE)) == BareV3(C.RELEASE_BRAKE)
    assert _one(emulator, CommunicationTimeout(50)) == CommunicationTimeout(50)
    _one(emulator, SpeedControl(60.0))
    for _ in range(30):  # frames every 20 ms: within the protection time
        emulator.advance(0.02)
        _one(emulator, BareV3(C.READ_STATUS_2))
    drive = emulator.drives[1]
    assert drive.link_losses == 0  # type: ignore[attr-defined]
    assert abs(drive.speed_dps / GEAR - 60.0) < 3.0
    emulator.advance(0.049)  # the host goes quiet
    assert drive.link_losses == 0  # type: ignore[attr-defined]
    emulator.advance(0.1)
    assert drive.link_losses == 1  # type: ignore[attr-defined]
    status = _one(emulator, BareV3(C.READ_STATUS_1))
    assert isinstance(status, Status1V3) and status.brake is BrakeCommand.LOCK
    emulator.advance(0.5)
    assert abs(drive.speed_dps) < 1e-6  # held by the brake
    # without the protection (0 ms) a quiet host leaves the drive running
    other = _emulator()
    _one(other, SpeedControl(60.0))
    other.advance(1.0)
    assert abs(other.drives[1].speed_dps / GEAR - 60.0) < 3.0


def test_a_locked_brake_holds_the_joint_and_refuses_motion() -> None:
    load = LoadModel(load_torque_nm=0.2)  # a constant pull (above the friction) that would turn the joint
    emulator = Emulator([1], model=DriveModel(gear_ratio=GEAR), load=load, family=ProtocolFamily.V3, brakes=[1])
    start = _one(emulator, BareV3(C.READ_MULTI_TURN_ANGLE))
    _one(emulator, MultiTurnPositionSpeed(45.0, 100.0))
    emulator.advance(1.0)
    assert _one(emulator, BareV3(C.READ_MULTI_TURN_ANGLE)) == start  # locked: held, the command did nothing
    _one(emulator, BareV3(C.RELEASE_BRAKE))
    emulator.advance(0.2)
    moved = _one(emulator, BareV3(C.READ_MULTI_TURN_ANGLE))
    assert isinstance(moved, MultiTurnAngle) and isinstance(start, MultiTurnAngle)
    assert abs(moved.angle_deg - start.angle_deg) > 1.0  # released and unpowered: the load turns it
    goal = round(moved.angle_deg) + 20.0
    _one(emulator, MultiTurnPositionSpeed(goal, 100.0))
    emulator.advance(1.5)
    there = _one(emulator, BareV3(C.READ_MULTI_TURN_ANGLE))
    assert isinstance(there, MultiTurnAngle) and there.angle_deg == pytest.approx(goal, abs=0.5)
    _one(emulator, BareV3(C.LOCK_BRAKE))
    emulator.advance(0.5)
    assert _one(emulator, BareV3(C.READ_MULTI_TURN_ANGLE)) == there


def test_a_broadcast_reaches_every_drive_and_each_answers_on_its_own_id() -> None:
    emulator = _emulator()
    exchange = emulator.handle_can(frames.encode_can_broadcast(BareV3(C.READ_STATUS_2)))
    assert [o.wire.arbitration_id for o in exchange.replies] == [0x241, 0x242]
    ids = emulator.handle_can(frames.encode_can_broadcast(CanIdCommand(ReadWrite.READ, 0)))
    assert [(o.wire.arbitration_id, o.message) for o in ids.replies] == [
        (0x300, CanIdReply(ReadWrite.READ, 0x241)),
        (0x300, CanIdReply(ReadWrite.READ, 0x242)),
    ]


def test_an_rs485_id_read_answers_with_the_id_itself() -> None:
    # issue 31, item 2: V4.2 section 7.4 example 2 shows the id in DATA[7] of an RS485 0x79 read reply; the emulator
    # answered with the CAN reply id (0x0241) there
    exchange = _emulator().handle_rs485(bytes.fromhex("3ECD0879000100000000 00F895".replace(" ", "")))
    assert [bytes(o.wire)[:11].hex(" ").upper() for o in exchange.replies] == [
        "3E CD 08 79 00 01 00 00 00 00 01",
        "3E CD 08 79 00 01 00 00 00 00 02",
    ]
    assert [o.message for o in exchange.replies] == [
        CanIdReply(ReadWrite.READ, 1 << 8),
        CanIdReply(ReadWrite.READ, 2 << 8),
    ]


def test_parameters_live_in_ram_and_rom_and_reset_restores_rom() -> None:
    emulator = _emulator()
    _one(emulator, PidParameter(C.WRITE_PID_RAM, PidIndex.SPEED_KP, 7.5))
    _one(emulator, PidParameter(C.WRITE_PID_ROM, PidIndex.POSITION_KP, 3.25))
    assert _one(emulator, PidRead(PidIndex.SPEED_KP)) == PidParameter(C.READ_PID, PidIndex.SPEED_KP, 7.5)
    _one(emulator, PlanningAcceleration(C.WRITE_ACCELERATION, AccelerationIndex.POSITION_ACCELERATION, 0))
    assert emulator.drives[1].acceleration_dps2 == 0  # 0: the position loop tracks the target directly
    assert emulator.request(1, BareV3(C.RESET)) == []  # no reply
    assert _one(emulator, PidRead(PidIndex.SPEED_KP)) != PidParameter(C.READ_PID, PidIndex.SPEED_KP, 7.5)
    assert _one(emulator, PidRead(PidIndex.POSITION_KP)) == PidParameter(C.READ_PID, PidIndex.POSITION_KP, 3.25)


def test_the_motion_frame_runs_the_drives_own_pd() -> None:
    emulator = _emulator()
    target = math.radians(30.0)
    ranges = motion_ranges(VERSION_DATE, MODEL_NAME)  # (what the drive says of itself at 0xB2 / 0xB5)
    reply = emulator.request(1, MotionCommand(target, 0.0, 20.0, 1.0, 0.0, ranges))
    assert isinstance(reply[0][1], MotionState) and reply[0][1].motor_id == 1
    for _ in range(100):
        emulator.advance(0.01)
        state = emulator.request(1, MotionCommand(target, 0.0, 20.0, 1.0, 0.0, ranges))[0][1]
    assert isinstance(state, MotionState) and state.position_rad == pytest.approx(target, abs=0.02)


def test_level_two_errors_show_in_the_error_word_and_clear_by_themselves() -> None:
    fault = Fault(InjectedFault.UNDER_VOLTAGE, 1, start_s=0.1, end_s=0.3)
    emulator = _emulator(faults=[fault])
    emulator.advance(0.2)
    status = _one(emulator, BareV3(C.READ_STATUS_1))
    assert isinstance(status, Status1V3) and status.errors == SystemErrorFlags.LOW_VOLTAGE
    emulator.advance(0.2)
    status = _one(emulator, BareV3(C.READ_STATUS_1))
    assert isinstance(status, Status1V3) and status.errors == SystemErrorFlags.NONE


def test_emulate_serves_v3_drives_on_an_slcan_link_in_its_own_process(tmp_path: Path) -> None:
    link = tmp_path / "slcan"
    process = start_cli("--ids", "1,2", "--protocol", "v3", "--brakes", "2", "--slcan-link", str(link))
    try:
        assert process.stdout is not None
        assert process.stdout.readline().startswith(f"slcan: {link}")
        assert "emulating motors 1,2" in process.stdout.readline()
        with CanEndpoint("slcan", str(link), bitrate=1_000_000, sleep_after_open=0) as host:
            host.send(frames.encode_can_request(BareV3(C.READ_STATUS_1), 2), 0.5)
            received = host.recv(2.0)
            assert received is not None and received[0].arbitration_id == 0x242  # V3 replies on 0x240 + id
            motor_id, status = frames.decode_can_reply(received[0].arbitration_id, received[0].data)
            assert motor_id == 2 and isinstance(status, Status1V3) and status.brake is BrakeCommand.LOCK
            host.send(frames.encode_can_broadcast(BareV3(C.READ_VERSION_DATE)), 0.5)
            answers = [host.recv(2.0) for _ in range(2)]
            assert sorted(a[0].arbitration_id for a in answers if a is not None) == [0x241, 0x242]
    finally:
        process.send_signal(signal.SIGTERM)
        _, stderr = process.communicate(timeout=10)
    assert process.returncode == 0, stderr
    assert "slcan: 2 requests, 3 replies, 0 protocol errors" in stderr


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--ids", "1", "--virtual-channel", "c", "--brakes", "1"], "--brakes needs --protocol v3"),
        (["--ids", "1", "--virtual-channel", "c", "--protocol", "v3", "--brakes", "2"], "brakes [2]"),
        (["--ids", "1", "--virtual-channel", "c", "--protocol", "v4"], "'v4': expected v2, v3, or BUS=v2|v3"),
    ],
)
def test_emulate_refuses_what_v3_emulation_lacks(args: list[str], message: str) -> None:
    process = start_cli(*args)
    _, stderr = process.communicate(timeout=20)
    assert process.returncode == 2
    assert message in stderr


@pytest.mark.parametrize("wire", [WireProtocol.CAN, WireProtocol.RS485])
def test_the_transport_exchanges_v3_batches_with_the_same_matching(wire: WireProtocol) -> None:
    simulation = Simulation(_emulator(), wire)
    bus = SimulatedBus(simulation)
    assert bus.family is ProtocolFamily.V3
    batch = [
        Request(1, MultiTurnPositionSpeed(20.0, 200.0)),
        Request(2, BareV3(C.READ_MULTI_TURN_ANGLE)),
        Request(1, BareV3(C.READ_MULTI_TURN_ENCODER)),
    ]
    period_s = 0.005 if wire is WireProtocol.CAN else 0.02  # 115200 baud: 13-byte frames take 1.1 ms each way
    cycles = round(1.0 / period_s)
    for k in range(cycles):  # 1 s of cycles
        replies = bus.transact(batch, (k + 0.8) * period_s)
        simulation.sleep_until((k + 1) * period_s)
    assert [type(r.message) for r in replies] == [MotorStateV3, MultiTurnAngle, MultiTurnEncoder]
    state = replies[0].message
    assert isinstance(state, MotorStateV3) and state.angle_deg == 20
    counters = bus.counters[1]
    assert counters.sent == counters.replied == 2 * cycles and counters.timeouts == 0


def test_a_can_transport_talks_to_v3_drives_in_another_process(tmp_path: Path) -> None:
    link = tmp_path / "slcan"
    with v3_drives(link, "1-3"):
        bus = CanTransport("slcan", str(link), 1_000_000, family=ProtocolFamily.V3, sleep_after_open=0)
        with bus:
            batch = [Request(i, BareV3(C.READ_STATUS_2)) for i in (1, 2, 3)] + [Request(2, BareV3(C.READ_MODEL))]
            replies = bus.transact(batch, time.monotonic() + 0.5)
            assert [type(r.message) for r in replies] == [MotorStateV3] * 3 + [MotorModel]
            assert [r.motor_id for r in replies] == [1, 2, 3, 2]


def _active_reply_times(port: CanEndpoint, clock: Callable[[], float], seconds: float) -> list[tuple[int, float]]:
    """(motor id, time) of every 0x92 reply received within ``seconds``."""
    seen: list[tuple[int, float]] = []
    end = clock() + seconds
    while (left := end - clock()) > 0:
        received = port.recv(left)
        if received is not None and received[0].data[:1] == bytes((C.READ_MULTI_TURN_ANGLE,)):
            seen.append((received[0].arbitration_id - frames.CAN_REPLY_BASE, received[1]))
    return seen


def test_active_replies_come_every_interval_without_requests_in_simulated_time() -> None:
    emulator = _emulator()
    simulation = Simulation(emulator, WireProtocol.CAN)
    bus = SimulatedBus(simulation)
    on = ActiveReply(ActiveReplyCommand.READ_MULTI_TURN_ANGLE, 1, 10.0)
    bus.transact([Request(1, on)], simulation.now_s + 0.002)  # (0xB6 has no reply: the slot times out)
    start, times = simulation.now_s, []
    while (arrival := simulation.next_arrival(start + 0.1)) is not None:
        simulation.now_s = arrival.time_s
        assert isinstance(arrival.wire, CanFrame) and arrival.wire.arbitration_id == frames.CAN_REPLY_BASE + 1
        times.append(arrival.time_s)
    assert len(times) == 10 and np.allclose(np.diff(times), 0.010)
    # a request for the read it sends by itself gets no answer; the other drive answers as before
    replies = bus.transact([Request(i, BareV3(C.READ_MULTI_TURN_ANGLE)) for i in (1, 2)], simulation.now_s + 0.002)
    assert replies[0].message is None and isinstance(replies[1].message, MultiTurnAngle)  # (the next comes in 8 ms)
    bus.transact([Request(1, ActiveReply(ActiveReplyCommand.READ_MULTI_TURN_ANGLE, 0, 10.0))], simulation.now_s + 0.002)
    simulation.sleep_until(simulation.now_s + 0.05)
    assert simulation.arrived_by(simulation.now_s) == []  # stopped


def test_active_replies_come_from_v3_drives_in_another_process(tmp_path: Path) -> None:
    link = tmp_path / "slcan"
    with v3_drives(link), CanEndpoint("slcan", str(link), 1_000_000, sleep_after_open=0) as port:
        on = ActiveReply(ActiveReplyCommand.READ_MULTI_TURN_ANGLE, 1, 20.0)
        port.send(frames.encode_can_request(on, 2), 0.1)
        seen = _active_reply_times(port, time.monotonic, 0.5)
        port.send(frames.encode_can_request(ActiveReply(ActiveReplyCommand.READ_MULTI_TURN_ANGLE, 0, 20.0), 2), 0.1)
        off_s = time.monotonic()
        after = [time.monotonic() - off_s for _ in _active_reply_times(port, time.monotonic, 0.6)]
    assert {motor for motor, _ in seen} == {2}
    assert 15 <= len(seen) <= 26, len(seen)  # every 20 ms for half a second (a busy host delays some)
    # stopped: at most the replies already under way when the request went out (a busy host delays the emulator's
    # reading it), none after; the replies would have gone on every 20 ms for the 0.6 s
    assert len(after) <= 3 and all(t < 0.3 for t in after), after


def test_scan_names_each_drives_generation_firmware_and_model(tmp_path: Path) -> None:
    link = tmp_path / "slcan"
    arm2 = str(ROOT / "configs" / "arm2.yaml")  # (bus.protocol: auto)
    set_v2 = tmp_path / "arm2_v2.yaml"
    text = (ROOT / "configs" / "arm2.yaml").read_text()
    set_v2.write_text(text.replace("  bitrate: 1000000\n", "  bitrate: 1000000\n  protocol: v2\n", 1))
    scan = ("scan", "--interface", "slcan", "--channel", str(link), "--ids", "1-3", "--json")
    with v3_drives(link):
        result = _cli(*scan, "--config", arm2)
        told = _cli(*scan, "--config", str(set_v2))
    assert result.returncode == 0, result.stderr
    drives = json.loads(result.stdout)["drives"]
    assert [(d["motor_id"], d["protocol"], d["model"]) for d in drives] == [
        (1, "v3", "EMUX8V3 firmware 20240528"),
        (2, "v3", "EMUX8V3 firmware 20240528"),
    ]
    assert "not the configuration's" not in result.stderr  # (auto: whichever the drives speak)
    assert told.returncode == 0, told.stderr
    assert "speak the V3-driver protocol (V4.2), not the configuration's (bus.protocol: v2): set it to v3 or auto" in (
        told.stderr
    )


def _scan_arm6_v3_emulated(tmp_path: Path, *emulate_args: str) -> subprocess.CompletedProcess[str]:
    """``rmd-motion scan --json`` of arm6_v3 over ``rmd-motion emulate --config`` of it (extra ``emulate_args``) on an
    slcan pty."""
    link = tmp_path / "slcan"
    arm6_v3 = str(ROOT / "configs" / "arm6_v3.yaml")
    command = [sys.executable, "-m", "motion.cli", "emulate", "--config", arm6_v3, "--slcan-link", str(link)]
    process = subprocess.Popen(
        [*command, *emulate_args], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=ROOT
    )
    try:
        assert process.stdout is not None
        assert process.stdout.readline().startswith(f"slcan: {link}")
        assert "emulating motors" in process.stdout.readline()
        return _cli("scan", "--config", arm6_v3, "--interface", "slcan", "--channel", str(link), "--json")
    finally:
        process.send_signal(signal.SIGTERM)
        process.communicate(timeout=10)


def test_scan_of_a_v3_arm_over_its_own_emulator_with_the_default_ids_exits_0(tmp_path: Path) -> None:
    # issue 31: with a V3 configuration, the ids that did not answer as V3 drives were sent the older family's 0x9A
    # through the V3 codec (exit 2, "'0x9A' is outside the valid range"); and `emulate --config` of a V3
    # configuration emulated drives of the older generation unless told --protocol v3
    result = _scan_arm6_v3_emulated(tmp_path)
    assert result.returncode == 0, result.stderr
    report = json.loads(result.stdout)
    assert [(d["motor_id"], d["protocol"]) for d in report["drives"]] == [(i, "v3") for i in range(1, 7)]
    assert report["missing"] == []
    assert "protocol" not in result.stderr  # one generation, the configuration's: nothing to warn of


def test_scan_asks_a_configured_drive_that_answered_late_once_more_with_a_longer_window(tmp_path: Path) -> None:
    # under a busy host (slow-host --hogs 3) the emulator's replies came after scan's window and every configured
    # joint was reported missing (exit 3): motor 2 here answers 0.8 s late, after the first window (0.57 s for 32
    # ids) and within the second (four times as long, for the missing ids alone)
    result = _scan_arm6_v3_emulated(tmp_path, "--fault", "delay:2@0:800")
    assert result.returncode == 0, result.stderr
    report = json.loads(result.stdout)
    assert [d["motor_id"] for d in report["drives"]] == [1, 2, 3, 4, 5, 6] and report["missing"] == []


def test_the_emulated_model_is_seven_ascii_characters() -> None:
    # the document's 0xB5 reply carries 7 ASCII characters (X8S2V10); the emulated one was NUL-padded (EMU-V3\0)
    reply = _one(_emulator(), BareV3(CommandV3.READ_MODEL))
    assert isinstance(reply, MotorModel) and len(reply.model) == 7 and reply.model.isprintable()
    frame = frames.encode_can_reply(reply, 1)
    assert b"\0" not in bytes(frame.data[1:]) and frame.data[1:].decode("ascii") == reply.model


def _arm2(protocol: str | None = None) -> ArmConfig:
    text = (ROOT / "configs" / "arm2.yaml").read_text()
    if protocol is not None:
        text = text.replace("  bitrate: 1000000\n", f"  bitrate: 1000000\n  protocol: {protocol}\n", 1)
        assert f"protocol: {protocol}" in text
    return parse_config(yaml.safe_load(text), source="arm2.yaml", base_dir=ROOT / "configs")


def test_connect_tells_the_generation_and_refuses_a_mixed_bus_or_a_wrong_setting_naming_each_drive() -> None:
    channel = uuid.uuid4().hex
    older = Emulator([1], model=DriveModel(), load=LoadModel())
    newer = Emulator([2], model=DriveModel(), load=LoadModel(), family=ProtocolFamily.V3)
    with (
        VirtualCanAttachment(older, channel),
        VirtualCanAttachment(newer, channel),
        CanTransport("virtual", channel, None) as bus,
    ):
        for setting in (None, "v2", "v3"):
            with pytest.raises(TransportError, match=r"both protocol generations .*motor 1: v2, motor 2: v3"):
                negotiate_family(bus, _arm2(setting))
    with VirtualCanAttachment(_emulator(), channel), CanTransport("virtual", channel, None) as bus:
        spoken = negotiate_family(bus, _arm2())
        with spoken:  # (it took the channel over: it closes it)
            assert spoken is not bus and spoken.family is ProtocolFamily.V3
            assert negotiate_family(spoken, _arm2("v3")) is spoken
            with pytest.raises(TransportError, match=r"bus.protocol is v2, but the drives answer in the v3 protocol"):
                negotiate_family(spoken, _arm2("v2"))
    with VirtualCanAttachment(older, channel), CanTransport("virtual", channel, None) as bus:
        assert negotiate_family(bus, _arm2()) is bus
        with pytest.raises(TransportError, match=r"bus.protocol is v3, but the drives answer in the v2 protocol"):
            negotiate_family(bus, _arm2("v3"))


def test_bus_protocol_is_validated() -> None:
    with pytest.raises(ConfigError, match=r"bus\.protocol.*one of auto, v2, v3"):
        _arm2("v4")
    assert _arm2().bus.protocol is ProtocolSetting.AUTO


def test_the_drive_commands_on_a_bus_of_v3_drives_read_and_halt_them_or_say_why_they_cannot(tmp_path: Path) -> None:
    link = tmp_path / "slcan"
    config = str(ROOT / "configs" / "arm2.yaml")
    bus = ("--config", config, "--interface", "slcan", "--channel", str(link))
    with v3_drives(link):
        status = _cli("status", *bus, "--json")
        stop = _cli("stop", *bus)
        held = _cli("hold", *bus)
        gains = _cli("pid", "get", *bus, "--json")
        accelerations = _cli("accel", "get", *bus, "elbow", "--json")
        refused = _cli("pid", "set", *bus, "shoulder", "1", "2", "3", "4", "5", "6")
    assert status.returncode == 0, status.stderr
    joints = json.loads(status.stdout)["joints"]
    assert [(j["name"], j["errors"], j["voltage_v"] > 20) for j in joints] == [
        ("shoulder", [], True),
        ("elbow", [], True),
    ]
    assert stop.returncode == 0, stop.stderr
    assert "motor stop (0x81) acknowledged by shoulder (motor 1), elbow (motor 2)" in stop.stdout
    assert held.returncode == 0, held.stderr
    assert "holding (drive position loop, 0xA4): shoulder at 0.00 deg" in held.stdout
    assert gains.returncode == 0, gains.stderr
    shoulder = json.loads(gains.stdout)["shoulder"]
    assert list(shoulder) == [i.name.lower() for i in PidIndex] and shoulder["position_kd"] == 0.0
    assert accelerations.returncode == 0, accelerations.stderr
    assert list(json.loads(accelerations.stdout)) == ["elbow"]
    assert json.loads(accelerations.stdout)["elbow"]["position_acceleration"] > 0
    assert refused.returncode == 3, refused.stderr
    assert (
        "the drives answer in the V3-driver protocol (V4.2): this command speaks the older protocol "
        "(CAN v2.3 / RS485 v1.62) alone" in refused.stderr
    )


def test_the_v3_rs485_parser_finds_frames_in_split_joined_and_garbage_laden_input() -> None:
    frame_a = frames.encode_rs485_reply(MotorStateV3(C.READ_STATUS_2, 40, 1.5, 10, 3), 1)
    frame_b = frames.encode_rs485_reply(BareV3(C.MOTOR_OFF), 2)
    corrupt = bytearray(frame_a)
    corrupt[6] ^= 0x10
    parser = Rs485ParserV3()
    parser.feed(b"\x00\x3e\x3e\x05" + frame_a[:5])
    assert parser.next_frame() is None  # a frame in progress
    parser.feed(frame_a[5:] + bytes(corrupt) + b"\x3e\x01\x09" + frame_b)
    assert [parser.next_frame(), parser.next_frame(), parser.next_frame()] == [frame_a, frame_b, None]
    assert parser.bad_data_checksums >= 1 and parser.bad_lengths >= 2 and parser.frames == 2
    parser.feed(frame_b[:7])
    assert parser.next_frame(flush=True) is None and parser.truncated >= 1 and parser.pending == 0


def test_an_rs485_transport_talks_to_v3_drives_in_another_process(tmp_path: Path) -> None:
    link = tmp_path / "rs485"
    process = start_cli("--ids", "1,2", "--protocol", "v3", "--rs485-link", str(link))
    try:
        assert process.stdout is not None
        assert process.stdout.readline().startswith(f"rs485: {link}")
        process.stdout.readline()
        with Rs485Transport(str(link), family=ProtocolFamily.V3) as bus:
            batch = [Request(1, BareV3(C.READ_STATUS_2)), Request(2, MultiTurnPositionSpeed(5.0, 100.0))]
            batch.append(Request(2, BareV3(C.READ_VERSION_DATE)))
            replies = bus.transact(batch, time.monotonic() + 0.5)
            assert [type(r.message) for r in replies] == [MotorStateV3, MotorStateV3, VersionDate]
            assert bus.counters[2].replied == 2 and bus.bus_counters.bad_frames == 0
    finally:
        process.send_signal(signal.SIGTERM)
        _, stderr = process.communicate(timeout=10)
    assert "rs485: 3 requests, 3 replies, 0 protocol errors" in stderr


def test_the_multi_turn_angle_restarts_within_one_output_turn_unless_the_drive_keeps_it() -> None:
    # Issue 31 §3, section 2.12: 0x92 is the output shaft's multi-turn angle; function 0x20 index 4 = 1 keeps it over
    # power-off, 0 (single-turn mode, the emulated drives' default) restarts it within 0..360 output degrees
    emulator = _emulator()

    def angle_after_reset(target_deg: float) -> tuple[float, float]:
        _one(emulator, MultiTurnPositionSpeed(target_deg, 360.0))
        emulator.advance(2.0)
        before = _one(emulator, BareV3(C.READ_MULTI_TURN_ANGLE))
        assert emulator.request(1, BareV3(C.RESET)) == []
        after = _one(emulator, BareV3(C.READ_MULTI_TURN_ANGLE))
        assert isinstance(before, MultiTurnAngle) and isinstance(after, MultiTurnAngle)
        return before.angle_deg, after.angle_deg

    before, after = angle_after_reset(370.0)
    assert before == pytest.approx(370.0, abs=0.5) and after == pytest.approx(10.0, abs=0.5)
    _one(emulator, FunctionControl(FunctionIndex.SAVE_MULTI_TURN, 1))
    before, after = angle_after_reset(-370.0)  # (in the frame of the restart: a turn and a bit the other way)
    assert before == pytest.approx(-370.0, abs=0.5) and after == before


def test_scan_of_a_v3_rs485_line_with_the_default_ids_exits_0(tmp_path: Path) -> None:
    # issue 31 §1 on the other transport: the ids that do not answer are asked in the line's own generation (each
    # silent id costs RS485 a whole exchange's timeout: 32 ids at 115200 baud)
    config = tmp_path / "arm2_rs485_v3.yaml"
    config.write_text(
        (ROOT / "configs" / "arm2_rs485.yaml")
        .read_text()
        .replace("  transport: rs485\n", "  transport: rs485\n  protocol: v3\n", 1)
    )
    link = tmp_path / "rs485"
    command = [sys.executable, "-m", "motion.cli", "emulate", "--config", str(config), "--rs485-link", str(link)]
    process = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=ROOT)
    try:
        assert process.stdout is not None
        assert process.stdout.readline().startswith(f"rs485: {link}")
        assert "emulating motors" in process.stdout.readline()
        result = _cli("scan", "--config", str(config), "--port", str(link), "--json")
    finally:
        process.send_signal(signal.SIGTERM)
        process.communicate(timeout=10)
    assert result.returncode == 0, result.stderr
    report = json.loads(result.stdout)
    assert [(d["motor_id"], d["protocol"]) for d in report["drives"]] == [(1, "v3"), (2, "v3")]
    assert report["missing"] == []
